"""Static solver and models: verified against closed-form elasticity, Timoshenko, and finite differences."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import errors
from difftissue.boundary import BoundaryConditions
from difftissue.materials import Material, lattice_spring_constants
from difftissue.mesh import TetMesh, block
from difftissue.models import CheckedMaterial, make_model
from difftissue.solvers import StaticResult, solve_static
from difftissue.solvers import static as static_solver

E0 = 1.0e3


@pytest.fixture(scope="module")
def column():
    """A 1 x 1 x 2 block of 2 x 2 x 4 cubes (unit cells)."""
    return block((1.0, 1.0, 2.0), (2, 2, 4))


def _symmetric_bc(mesh):
    """Roller symmetry planes x=0, y=0, z=0: lateral faces x=Lx, y=Ly are traction-free."""
    return (
        BoundaryConditions.free(mesh)
        .fix(mesh, {"face": "x-min"}, "x")
        .fix(mesh, {"face": "y-min"}, "y")
        .fix(mesh, {"face": "z-min"}, "z")
    )


@pytest.mark.parametrize("kind", ["springs_volume", "fem_linear"])
def test_uniaxial_tension_and_compression_recover_E_and_nu(column, kind):
    model = make_model(column, kind)
    top = column.points[:, 2] == 2.0
    side = column.points[:, 0] == 1.0
    for nu in (0.3, 0.45, 0.49):
        for strain in (1e-4, -1e-4):
            bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0.0, 0.0, 2.0 * strain))
            sol = solve_static(model, Material(E0, nu), bc)
            stress = float(jnp.sum(sol.reaction[:, 2] * top)) / 1.0
            lateral = float(jnp.mean(sol.displacement[side, 0])) / 1.0
            assert stress / strain == pytest.approx(E0, rel=0.01), (kind, nu, strain)
            assert -lateral / strain == pytest.approx(nu, abs=0.01), (kind, nu, strain)
            if kind == "fem_linear":  # exact for linear tets
                assert stress / strain == pytest.approx(E0, rel=1e-8)
                assert -lateral / strain == pytest.approx(nu, rel=1e-8)


@pytest.mark.parametrize("kind", ["springs_volume", "fem_linear", "stable_neo_hookean"])
def test_confined_compression_gives_p_wave_modulus(column, kind):
    strain = -1e-5
    bc = (
        BoundaryConditions.free(column)
        .fix(column, {"any_of": [{"face": "x-min"}, {"face": "x-max"}]}, "x")
        .fix(column, {"any_of": [{"face": "y-min"}, {"face": "y-max"}]}, "y")
        .fix(column, {"face": "z-min"}, "z")
        .fix(column, {"face": "z-max"}, "z", (0, 0, 2.0 * strain))
    )
    top = column.points[:, 2] == 2.0
    for nu in (0.3, 0.45):
        mat = Material(E0, nu)
        lam, mu = mat.lame
        sol = solve_static(make_model(column, kind), mat, bc)
        stress = float(jnp.sum(sol.reaction[:, 2] * top))
        assert stress / strain == pytest.approx(lam + 2 * mu, rel=2e-4)


@pytest.mark.parametrize("kind", ["springs_volume", "fem_linear", "stable_neo_hookean", "fem_neo_hookean"])
def test_patch_test_affine_boundary_reproduced_in_interior(kind):
    mesh = block(1.0, 3)
    X = mesh.points
    A = np.array([[0.05, 0.02, -0.01], [0.00, -0.03, 0.04], [0.01, 0.02, 0.06]])
    affine = X @ A.T + np.array([0.1, -0.2, 0.05])
    boundary = np.unique(mesh.boundary_faces)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), boundary)
    assert interior.size == 8
    bc = BoundaryConditions.free(mesh).fix(mesh, boundary, "xyz", affine[boundary])
    sol = solve_static(make_model(mesh, kind), Material(E0, 0.45, cubic_coefficient=3.0), bc, load_steps=4)
    err = np.abs(np.asarray(sol.displacement)[interior] - affine[interior]).max()
    assert err <= 1e-9 * np.abs(affine).max(), err


def test_cantilever_matches_timoshenko():
    """Springs + volume model, 40 x 5 x 5 unit-aspect cells, L/h = 8, nu = 0.3, tip shear load."""
    E, nu, L, h, P = 1e4, 0.3, 8.0, 1.0, -1e-2
    mesh = block((L, h, h), (40, 5, 5))
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "x-min"}).add_force(mesh, {"face": "x-max"}, (0, 0, P), distribute="area")
    sol = solve_static(make_model(mesh, "springs_volume"), Material(E, nu), bc, linear_solver="dense")
    tip = float(jnp.mean(sol.displacement[mesh.points[:, 0] == L, 2]))
    G, I, A = E / (2 * (1 + nu)), h**4 / 12, h * h
    kappa = 10 * (1 + nu) / (12 + 11 * nu)  # Cowper's shear coefficient, rectangle
    timoshenko = P * L**3 / (3 * E * I) + P * L / (kappa * G * A)
    assert tip / timoshenko == pytest.approx(1.0, abs=0.05)


def test_incompressible_neo_hookean_uniaxial_closed_form(column):
    """Nominal stress of an incompressible neo-Hookean bar: P = mu (l - 1/l^2)."""
    model = make_model(column, "fem_neo_hookean")
    mat = Material(E0, 0.499)
    top = column.points[:, 2] == 2.0
    for stretch in (1.3, 0.8):
        bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, 2.0 * (stretch - 1)))
        sol = solve_static(model, mat, bc, load_steps=5)
        nominal = float(jnp.sum(sol.reaction[:, 2] * top))
        assert nominal == pytest.approx(mat.shear_modulus * (stretch - stretch**-2), rel=0.01)


def test_spring_constants_assemble_per_cube(column):
    model = make_model(column, "springs_volume")
    mat = Material(E0, 0.45, cubic_coefficient=2.0)
    k, a = model.spring_constants(mat)
    per_cube = lattice_spring_constants(mat, 0.5)
    mult = column.lattice.multiplicity
    edge = column.lattice.spring_kind == 0
    np.testing.assert_allclose(np.asarray(k)[edge], mult[edge] * float(per_cube.k_edge), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(k)[~edge], mult[~edge] * float(per_cube.k_diag), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(a)[edge], mult[edge] * float(per_cube.a_edge), rtol=1e-12)


# --------------------------------------------------------------------- gradients
@pytest.mark.parametrize("kind", ["springs_volume", "fem_neo_hookean"])
def test_implicit_gradient_matches_finite_differences(kind):
    mesh = block(1.0, 2)
    model = make_model(mesh, kind)
    top = mesh.points[:, 2] == 1.0
    base_bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "xy", (0.03, 0.0, 0.0))

    def output(p):
        E, nu, b, depth = p
        bc = base_bc.fix(mesh, {"face": "z-max"}, "z", (0.0, 0.0, depth))
        sol = solve_static(model, Material(E, nu, cubic_coefficient=b), bc)
        return jnp.sum(sol.reaction[:, 2] * top) + 1e3 * jnp.sum(sol.displacement[:, 0] ** 2)

    # One compiled program gives the value (reverse mode's primal), the reverse-mode gradient
    # and the forward-mode Jacobian; the eight difference evaluations reuse it (three separate
    # programs compiled ~1.5x as long; the executions are milliseconds on this 27-node mesh).
    @jax.jit
    def value_reverse_forward(p):
        value, vjp = jax.vjp(output, p)
        return value, vjp(jnp.ones_like(value))[0], jax.jacfwd(output)(p)

    def value(p):
        return value_reverse_forward(p)[0]

    p0 = jnp.array([1.0e3, 0.45, 4.0, -0.08])
    _, reverse, forward = (np.asarray(a) for a in value_reverse_forward(p0))
    for i in range(4):
        h = 1e-6 * abs(float(p0[i]))
        e = jnp.zeros(4).at[i].set(h)
        fd = float((value(p0 + e) - value(p0 - e)) / (2 * h))
        if kind == "fem_neo_hookean" and i == 2:
            # The FEM has no cubic coefficient: the gradient is exactly 0 and the difference
            # quotient is round-off (exactly 0 on a CPU; a GPU's scatter-adds sum in varying
            # order, ~1e-13 of the output).
            assert reverse[i] == 0.0 and abs(fd) * h <= 1e-12 * abs(float(value(p0))), (fd, float(value(p0)))
            continue
        assert reverse[i] == pytest.approx(fd, rel=1e-5), (i, reverse[i], fd)
        assert forward[i] == pytest.approx(reverse[i], rel=1e-9)


def test_gradient_with_respect_to_nodal_force():
    mesh = block(1.0, 2)
    model = make_model(mesh, "fem_linear")
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"})

    def tip(fz):
        sol = solve_static(model, Material(E0, 0.3), bc.add_force(mesh, {"face": "z-max"}, (0.0, 0.0, fz)))
        return jnp.mean(sol.displacement[:, 2])

    # the value and the gradient from one compiled program (not the gradient's operations
    # dispatched one by one and a second program for the value)
    value, g = (float(a) for a in jax.jit(jax.value_and_grad(tip))(-1.0))
    # Linear: the output is proportional to the force.
    assert g == pytest.approx(value / -1.0, rel=1e-9)


def test_no_recompile_on_second_call_with_new_values(column, caplog):
    model = make_model(column, "springs_volume")
    bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, 1e-3))
    solve_static(model, Material(E0, 0.3), bc)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        bc2 = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, -2e-3))
        solve_static(model, Material(2 * E0, 0.41, cubic_coefficient=1.0), bc2)
    compiled = [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()]
    assert compiled == [], compiled


def test_a_concrete_material_is_range_checked_on_the_host_not_in_the_compiled_solve(monkeypatch):
    """A concrete material reaches the compiled solve already checked (``CheckedMaterial``), so
    the program holds no ``equinox.error_if`` host callback for it: JAX never writes a program
    with a host callback to its persistent compilation cache (docs/dev/test-suite.md)."""
    traced_with = []
    solve_program = static_solver._solve_program

    def spy(model, material, *args):
        traced_with.append(type(material))
        return solve_program(model, material, *args)

    monkeypatch.setattr(static_solver, "_solve_program", spy)
    mesh = block((1.0, 1.0, 3.0), (1, 1, 3))  # a structure no other test compiles: traced here
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}, "xyz").fix(mesh, {"face": "z-max"}, "z", (0.0, 0.0, 1e-3))
    sol = solve_static(make_model(mesh, "fem_linear"), Material(E0, 0.3), bc)
    assert int(sol.result) == 0
    assert traced_with == [CheckedMaterial]


# ------------------------------------------------------------------- bad input
def test_bad_inputs_are_refused_with_named_errors(column):
    springs = make_model(column, "springs_volume")
    bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, 1e-3))
    with pytest.raises(errors.ModelRangeError, match="1/4"):
        solve_static(springs, Material(E0, 0.2), bc)
    with pytest.raises(errors.MaterialError, match="youngs_modulus"):
        solve_static(springs, Material(-1.0, 0.3), bc)
    with pytest.raises(errors.MaterialError, match="not finite"):
        Material(float("nan"), 0.3)
    two = make_model(column, "fem_linear")
    with pytest.raises(errors.MaterialError, match="one value per region"):
        solve_static(two, Material(jnp.array([1e3, 2e3]), 0.3), bc)
    # NaN parameters inside jit: a runtime error, not a silent NaN. On a GPU the program runs
    # asynchronously and the error is raised when the result is read: block on it.
    with pytest.raises(Exception, match="NaN"):
        jax.block_until_ready(jax.jit(lambda E: solve_static(two, Material(E, 0.3), bc).displacement)(jnp.nan))
    # Rigid modes.
    only_z = BoundaryConditions.free(column).fix(column, {"face": "z-min"}, "z")
    with pytest.raises(errors.RigidModeError, match="leave 3 rigid-body mode") as info:
        solve_static(two, Material(E0, 0.3), only_z)
    for mode in ("translation x", "translation y", "rotation about z"):
        assert mode in str(info.value)
    with pytest.raises(errors.RigidModeError, match="no displacement is prescribed"):
        solve_static(two, Material(E0, 0.3), BoundaryConditions.free(column))
    with pytest.raises(errors.BoundaryConditionError, match="NaN"):
        solve_static(two, Material(E0, 0.3), bc.fix(column, [0], "x", (jnp.nan, 0, 0)))
    with pytest.raises(errors.BoundaryConditionError, match="components"):
        bc.fix(column, [0], "w")


def test_models_refuse_what_they_cannot_represent():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    inverted = TetMesh(p, np.array([[0, 2, 1, 3]]), validate=False)
    with pytest.raises(errors.InvertedElementError, match="non-positive rest volume"):
        make_model(inverted, "fem_linear")
    with pytest.raises(errors.ModelError, match="cube lattice"):
        make_model(TetMesh(p, np.array([[0, 1, 2, 3]])), "springs_volume")
    with pytest.raises(errors.ModelError, match="too elongated"):
        make_model(block((1.0, 1.0, 1.0), (1, 1, 3)), "springs_volume")
    with pytest.raises(errors.ModelError, match="unknown model"):
        make_model(block(1.0, 1), "mass_spring")


def test_non_convergence_and_inversion_are_reported(column):
    model = make_model(column, "fem_neo_hookean")
    bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, 1.0))
    with pytest.raises(errors.ConvergenceError, match="max_steps"):
        solve_static(model, Material(E0, 0.45), bc, max_steps=1)
    sol = solve_static(model, Material(E0, 0.45), bc, max_steps=1, throw=False)
    assert int(sol.result) == StaticResult.max_steps_reached and not bool(sol.converged)
    # Pushing the top below the base: no admissible (non-inverted) equilibrium exists.
    linear = make_model(column, "fem_linear")
    crush = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, -2.5))
    with pytest.raises(errors.ConvergenceError, match="invert"):
        solve_static(linear, Material(E0, 0.3), crush)


def test_gradient_of_an_unconverged_solve_is_nan_in_both_modes(column):
    """throw=False and a solve stopped at max_steps: NaN derivatives (forward and reverse), never
    the implicit-function tangent of the unconverged state (which was finite and wrong)."""
    model = make_model(column, "fem_neo_hookean")
    bc = _symmetric_bc(column).fix(column, {"face": "z-max"}, "z", (0, 0, 0.5))
    top = np.asarray(column.points)[:, 2] == 2.0

    def force(E, max_steps):
        sol = solve_static(model, Material(E, 0.45), bc, max_steps=max_steps, throw=False, linear_solver="dense")
        return jnp.sum(sol.reaction[:, 2] * top), sol.result

    # value, gradient and tangent of the stopped solve from one jitted program (the value is
    # the forward pass the gradient runs), the converged solve's value and gradient from another
    (value, code), grad, tangent = jax.jit(
        lambda E: (*jax.value_and_grad(lambda e: force(e, 1), has_aux=True)(E), jax.jvp(lambda e: force(e, 1)[0], (E,), (1.0,))[1])
    )(E0)
    assert int(code) == StaticResult.max_steps_reached and np.isfinite(float(value))
    assert np.isnan(float(grad))
    assert np.isnan(float(tangent))
    # the same solve converged: finite and consistent (the force is proportional to E)
    (value, code), g = jax.jit(jax.value_and_grad(lambda E: force(E, 50), has_aux=True))(E0)
    assert int(code) == StaticResult.successful and np.isfinite(float(g))
    assert float(g) == pytest.approx(float(value) / E0, rel=1e-8)


def test_a_round_off_newton_step_is_convergence_only_at_a_positive_definite_matrix():
    """The xtol exit ("a full Newton correction below xtol |u|") counts only when that step's
    matrix was positive definite. A top node under a sharp cone's apex, not held on the axis,
    sparse solver: the curvature of the regularised distance to the axis is ~1e77 /m, so the
    first Newton correction (an LU solve through the indefinite Hessian) was 1e-78 m, below
    xtol, while the lateral residual was 3e-5 of the force scale; that state was reported
    converged with a force 28 % above the equilibrium's. Now the sparse solve reaches the
    stable equilibrium the dense Cholesky reaches (the apex node moved off the axis)."""
    from difftissue.scenarios import Indentation, indentation_block
    from difftissue.solvers.static import _full_gradient

    mesh = indentation_block((3e-3, 3e-3, 1.5e-3), (6, 6, 4), symmetry="none")  # a node on the axis x = y = 0
    full = Indentation(mesh, np.array([1e-4]), solver="full", model="fem_linear", indenter="cone", half_angle=np.deg2rad(70.0))
    p = np.asarray(mesh.points)
    apex = np.flatnonzero((np.hypot(p[:, 0], p[:, 1]) <= 1e-12) & (p[:, 2] == p[:, 2].max()))
    assert apex.size == 1
    fixed = np.asarray(full.bc.fixed).copy()
    fixed[apex, :2] = False
    bc = BoundaryConditions(fixed, full.bc.displacement, full.bc.force)
    model, material = full.model.with_depth(1e-4), Material(8e3, 0.3)
    rtol, xtol = 1e-10, 1e-8
    sols = {ls: solve_static(model, material, bc, linear_solver=ls, rtol=rtol, xtol=xtol) for ls in ("sparse", "dense")}
    free = jnp.asarray(bc.free_mask)
    checked = model.checked(material)
    # the norm of the free residual compiled once (not its operations one by one, three times)
    residual_norm = jax.jit(lambda u: jnp.linalg.norm(free * _full_gradient(model, u, checked, bc.force)))
    scale = float(residual_norm((1.0 - free) * bc.displacement))
    assert scale > 0
    for ls, sol in sols.items():
        residual = float(residual_norm(sol.displacement))
        assert bool(sol.converged) and residual <= max(rtol, xtol) * scale, ls
        # a stable equilibrium: the apex node slid off the axis (by ~34 um in x and y)
        assert np.hypot(*np.asarray(sol.displacement[apex[0], :2])) > 1e-5, ls
    force = {ls: float(jnp.sum(sol.reaction[:, 2])) for ls, sol in sols.items()}
    assert force["sparse"] == pytest.approx(force["dense"], rel=1e-9)


def test_line_search_evaluates_its_start_in_its_loop_and_reports_the_full_step():
    """``armijo_backtracking(e0_in_loop=True)`` evaluates ``potential(u)`` in a pass of its own
    loop (the predictor pass of ``solve_static``): the same step, acceptance and energy as with
    ``e0`` given, for the Armijo rule (a step that needs halving, one that fails) and the
    predictor's compare-only rule; ``return_full_step`` gives ``potential(u + d)``."""
    from difftissue.solvers.static import armijo_backtracking

    def potential(u):  # inf where inadmissible, as solve_static's
        e = jnp.sum((u - 1.0) ** 4) + 0.5 * jnp.sum(u**2)
        return jnp.where(jnp.all(u < 5.0), e, jnp.inf)

    u = jnp.array([0.2, -0.3])
    g = jax.grad(potential)(u)
    for d, compare in ((-0.1 * g, False), (-3.0 * g, False), (-100.0 * g, False), (-3.0 * g, True), (+0.5 * g, True), (jnp.array([jnp.nan, 0.0]), True)):
        gd = jnp.vdot(g, d)
        kw = dict(return_energy=True, compare_only=compare, max_tries=6)
        given = armijo_backtracking(potential, u, d, gd, e0=potential(u), return_full_step=True, **kw)
        in_loop = armijo_backtracking(potential, u, d, gd, e0=jnp.asarray(123.0), e0_in_loop=jnp.asarray(True), return_full_step=True, **kw)
        traced_off = armijo_backtracking(potential, u, d, gd, e0=potential(u), e0_in_loop=jnp.asarray(False), return_full_step=True, **kw)
        for a, b, c in zip(given, in_loop, traced_off):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
        np.testing.assert_array_equal(np.asarray(given[3]), np.asarray(potential(u + d)))
    alpha, accepted, e = armijo_backtracking(potential, u, -3.0 * g, jnp.vdot(g, -3.0 * g), return_energy=True)
    assert bool(accepted) and 0 < float(alpha) < 1 and float(e) < float(potential(u))


def test_setup_reads_the_element_node_arrays_without_evaluating_the_terms(column):
    """``solver_setup`` takes the node arrays of ``model.terms`` from an abstract trace (no
    eager, op-by-op evaluation of the element parameters): the arrays of the terms as
    evaluated, for the lattice, a FEM model and a contact model; where a node array is
    computed inside ``terms`` from a JAX array (it is then a tracer of that trace) or ``terms``
    reads the material's values, the terms are evaluated as called, with the same arrays."""
    import equinox as eqx

    from difftissue.contact import ContactModel, SphereIndenter
    from difftissue.solvers.static import _term_nodes

    material = Material(E0, 0.4)
    fem = make_model(column, "fem_linear")
    contact = ContactModel(fem, SphereIndenter(0.5, axis_xy=(0.5, 0.5), surface_z=2.0), column)
    traced_nodes = eqx.tree_at(lambda m: m.contact_nodes, contact, jnp.asarray(contact.contact_nodes))

    class NeedsValues(type(fem)):  # terms that read the material's values in Python
        def terms(self, material):
            assert float(jnp.max(self.region_values(material)["youngs_modulus"])) > 0
            return super().terms(material)

    for model in (make_model(column, "springs_volume"), fem, contact, traced_nodes, NeedsValues(column)):
        nodes = _term_nodes(model, material)
        expected = [t.nodes for t in model.terms(material)]
        assert len(nodes) == len(expected) >= 1
        for a, b in zip(nodes, expected):
            assert not isinstance(a, jax.core.Tracer)
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
