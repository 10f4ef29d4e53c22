"""The multigrid-preconditioned CG linear solver of the static solve: same answers and
implicit gradients as the dense solve, vmap, no recompilation, a named error when it fails."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sps

from difftissue.boundary import BoundaryConditions
from difftissue.errors import LinearSolverError
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.models import MODELS, make_model
from difftissue.solvers import solve_static
from difftissue.solvers.multigrid import EllMatrix, JacobiPreconditioner, ell_from_csr, pcg, rigid_body_modes, sparse_layout
from difftissue.solvers.static import _assemble_ell, _dense_hessian, _element_data, auto_linear_solver

DEPTH = 2e-4  # punch displacement [m]


def _punch(kind, cells=(6, 6, 4)):
    """A bonded block 12 x 12 x 8 mm under a bonded flat punch of radius 3 mm: enough nodes
    (245) for a two-level hierarchy."""
    mesh = block((0.012, 0.012, 0.008), cells)
    model = make_model(mesh, kind)
    X = np.asarray(mesh.points)
    top = (np.isclose(X[:, 2], 0.008)) & (np.hypot(X[:, 0] - 0.006, X[:, 1] - 0.006) <= 0.003 + 1e-12)
    fixed = np.zeros(X.shape, bool)
    fixed[np.isclose(X[:, 2], 0.0)] = True
    fixed[top] = True
    disp = np.zeros(X.shape)
    disp[top, 2] = -DEPTH
    return model, BoundaryConditions(fixed, jnp.asarray(disp), jnp.zeros(X.shape)), np.flatnonzero(top)


@pytest.fixture(scope="module")
def springs():
    return _punch("springs_volume")


def _force(model, bc, top, material, solver="multigrid", **kw):
    sol = solve_static(model, material, bc, linear_solver=solver, **kw)
    return jnp.sum(sol.reaction[top, 2])


def test_ell_layout_assembles_the_projected_hessian(springs):
    model, bc, _ = springs
    material = Material(1e4, 0.45, 2.0)
    terms = model.terms(material)
    layout = sparse_layout([t.nodes for t in terms], model.n_nodes)
    x = jnp.asarray(model.rest_points) + 1e-4 * jnp.sin(jnp.arange(3 * model.n_nodes).reshape(-1, 3))
    P = 1.0 - jnp.asarray(bc.fixed, float).reshape(-1)
    ell = layout.assemble(_element_data(model, x, material), P)
    H = _dense_hessian(model, x, material)
    expected = H * P[:, None] * P[None, :] + jnp.diag(1.0 - P)
    v = jnp.cos(jnp.arange(3 * model.n_nodes) * 0.3)
    np.testing.assert_allclose(ell.mv(v), expected @ v, rtol=1e-12, atol=1e-12 * float(jnp.abs(expected).max()))
    np.testing.assert_allclose(ell.diagonal(), jnp.diagonal(expected), rtol=1e-13)
    # Chunked assembly (large meshes: a fori_loop over element chunks, the last one padded)
    # gives the same matrix.
    for chunk in (7, 100):
        chunked = jax.jit(lambda x, P, c=chunk: _assemble_ell(layout, model, x, material, P, chunk=c))(x, P)
        np.testing.assert_allclose(chunked.data, ell.data, rtol=1e-13, atol=1e-13 * float(jnp.abs(ell.data).max()))


def test_ell_from_csr_and_pcg_on_a_known_system():
    rng = np.random.default_rng(0)
    M = sps.random(60, 60, density=0.1, random_state=1)
    A = (M @ M.T + 60 * sps.eye(60)).tocsr()
    ell = ell_from_csr(A)
    b = rng.standard_normal(60)
    np.testing.assert_allclose(ell.mv(jnp.asarray(b)), A @ b, rtol=1e-13)
    x, steps, res, neg = pcg(ell.mv, JacobiPreconditioner(1.0 / jnp.asarray(A.diagonal())), jnp.asarray(b), jnp.zeros(60), rtol=1e-12, max_steps=200)
    np.testing.assert_allclose(x, np.linalg.solve(A.toarray(), b), rtol=1e-10)
    assert float(res) <= 1e-12 and not bool(neg) and 0 < int(steps) < 60
    # an indefinite matrix is detected (negative curvature), not silently solved
    _, _, _, neg = pcg(EllMatrix(-ell.data, ell.cols).mv, lambda r: r, jnp.asarray(b), jnp.zeros(60), rtol=1e-12, max_steps=200)
    assert bool(neg)


def _textbook_pcg(A, M, b, steps, stop_below=None):
    """Textbook PCG (Saad, Alg. 9.1) in NumPy: the preconditioner applied to the starting
    residual and at the end of every iteration; ``stop_below``: r.z undefined (NaN) when
    |r| < stop_below, where the iteration stops with the iterate before."""
    x = np.zeros_like(b)
    r = b.copy()
    z = M(r)
    p, gamma, k = z.copy(), r @ z, 0
    while k < steps and np.isfinite(gamma):
        Ap = A @ p
        alpha = gamma / (p @ Ap)
        x, r = x + alpha * p, r - alpha * Ap
        k += 1
        z = M(r) if stop_below is None or np.linalg.norm(r) >= stop_below else np.full_like(r, np.nan)
        gamma_new = r @ z
        p, gamma = z + gamma_new / gamma * p, gamma_new
    return x, k


def test_pcg_iterates_are_the_textbook_ones():
    # pcg applies the preconditioner once per iteration (at the top of its loop): one copy of
    # a V-cycle in the compiled program. Its iterates must be the textbook algorithm's, also
    # where the preconditioner's output stops being finite (the iterate before is kept).
    rng = np.random.default_rng(3)
    M = sps.random(40, 40, density=0.15, random_state=4)
    A = (M @ M.T + 2 * sps.eye(40)).toarray()
    b = rng.standard_normal(40)
    d = 1.0 / np.diag(A)
    ell = ell_from_csr(sps.csr_matrix(A))
    for steps in (0, 1, 2, 5, 9):
        x, k, _, neg = pcg(ell.mv, JacobiPreconditioner(jnp.asarray(d)), jnp.asarray(b), jnp.zeros(40), rtol=0.0, max_steps=steps)
        x_ref, k_ref = _textbook_pcg(A, lambda r: d * r, b, steps)
        assert int(k) == k_ref == steps and not bool(neg)
        np.testing.assert_allclose(x, x_ref, rtol=1e-12, atol=1e-14)
    # A preconditioner that returns NaN once the residual is small: stop with the last finite iterate.
    x_ref, k_ref = _textbook_pcg(A, lambda r: d * r, b, 100, stop_below=1e-1 * np.linalg.norm(b))
    nan_below = jnp.asarray(1e-1 * np.linalg.norm(b))
    pre = lambda r: jnp.where(jnp.linalg.norm(r) >= nan_below, jnp.asarray(d) * r, jnp.nan)
    x, k, _, neg = pcg(ell.mv, pre, jnp.asarray(b), jnp.zeros(40), rtol=0.0, max_steps=100)
    assert 0 < k_ref < 100 and int(k) == k_ref and not bool(neg)
    assert np.all(np.isfinite(np.asarray(x)))
    np.testing.assert_allclose(x, x_ref, rtol=1e-12, atol=1e-14)


def test_rigid_body_modes_are_in_the_null_space_of_the_free_stiffness(springs):
    model, _, _ = springs
    material = Material(1e4, 0.45)
    H = _dense_hessian(model, jnp.asarray(model.rest_points), material)
    B = rigid_body_modes(model.rest_points)
    assert float(jnp.abs(H @ B).max()) <= 1e-9 * float(jnp.abs(H).max())


@pytest.mark.parametrize("kind", MODELS)
def test_multigrid_equals_dense_for_every_model(kind):
    model, bc, top = _punch(kind)
    material = Material(1e4, 0.45, 1.0 if kind == "springs_volume" else 0.0)
    dense = solve_static(model, material, bc, linear_solver="dense", rtol=1e-12)
    mg = solve_static(model, material, bc, linear_solver="multigrid", rtol=1e-12, cg_rtol=1e-12)
    assert bool(mg.converged)
    assert 0 < int(mg.linear_steps) < 60  # preconditioned: far fewer than the 735 unknowns
    scale = float(jnp.abs(dense.displacement).max())
    np.testing.assert_allclose(mg.displacement, dense.displacement, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(float(jnp.sum(mg.reaction[top, 2])), float(jnp.sum(dense.reaction[top, 2])), rtol=1e-8)


GRAD_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "pre_stretch", "depth")
GRAD_BASE = jnp.array([1e4, 0.45, 2.0, 1.02, 1.0])


@pytest.fixture(scope="module")
def multigrid_outputs(springs):
    """The punch force and one displacement as a function of all five inputs at once
    ``(E, nu, cubic coefficient, pre-stretch, depth scale)``, with its reverse-mode Jacobian and
    forward-mode JVP at the base point, each compiled once for the module (one program per
    mode instead of one per parametrised field)."""
    model, bc, top = springs
    node = int(np.flatnonzero(~np.asarray(bc.fixed)[:, 2])[len(top) + 40])

    @jax.jit
    def outputs(p):
        material = Material(p[0], p[1], p[2], 1000.0, p[3])
        b = BoundaryConditions(bc.fixed, bc.displacement * p[4], bc.force)
        sol = solve_static(model, material, b, linear_solver="multigrid", rtol=1e-12, cg_rtol=1e-12, preconditioner_material=Material(1e4, 0.45))
        return jnp.stack([jnp.sum(sol.reaction[top, 2]), sol.displacement[node, 2]])

    jac = np.asarray(jax.jit(jax.jacrev(outputs))(GRAD_BASE))  # (2 outputs, 5 inputs)
    tangent = jax.jit(lambda t: jax.jvp(outputs, (GRAD_BASE,), (t,))[1])
    return outputs, jac, tangent


@pytest.mark.parametrize("field", GRAD_FIELDS)
def test_implicit_gradients_through_multigrid_match_central_differences(multigrid_outputs, field):
    outputs, jacobian, tangent_along = multigrid_outputs
    i = GRAD_FIELDS.index(field)
    e = jnp.zeros(5).at[i].set(1.0)
    v = float(GRAD_BASE[i])
    h = 1e-4 * abs(v)
    jac = jacobian[:, i]
    fd = (outputs(GRAD_BASE + h * e) - outputs(GRAD_BASE - h * e)) / (2 * h)
    # rtol 1e-5, and an absolute floor of 1e-9 of each output per unit relative change for a
    # derivative that vanishes (the displacement under a displacement control does not depend on E)
    floor = 1e-9 * np.abs(np.asarray(outputs(GRAD_BASE))) / abs(v)
    assert np.all(np.abs(np.asarray(jac) - np.asarray(fd)) <= 1e-5 * np.abs(np.asarray(fd)) + floor), (jac, fd)
    assert np.all(np.abs(np.asarray(fd)) > 1e3 * floor) or field == "youngs_modulus"  # the derivatives checked are not zero
    tangent = tangent_along(e)  # forward mode agrees with reverse mode
    assert np.all(np.abs(np.asarray(tangent) - np.asarray(jac)) <= 1e-8 * np.abs(np.asarray(jac)) + 1e-3 * floor)


def test_vmap_over_specimens_equals_single_solves_without_recompiling(springs, caplog):
    model, bc, top = springs
    E = jnp.array([5e3, 1e4, 4e4])
    nu = jnp.array([0.3, 0.45, 0.4])

    @jax.jit
    def batch(E, nu):
        return jax.vmap(lambda e, n: _force(model, bc, top, Material(e, n), preconditioner_material=Material(1e4, 0.45)))(E, nu)

    forces = batch(E, nu)
    single = [float(_force(model, bc, top, Material(float(e), float(n)))) for e, n in zip(E, nu)]
    np.testing.assert_allclose(forces, single, rtol=1e-9)
    E2, nu2 = E * 1.5, nu * 0.9
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        batch(E2, nu2).block_until_ready()
    assert [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()] == []


def test_preconditioner_that_stops_converging_raises_a_named_error(springs):
    model, bc, _ = springs
    # A hierarchy built for nu = 0.3 applied at nu = 0.4999, with a small CG budget.
    with pytest.raises(LinearSolverError, match=r"CG iterations, relative residual"):
        solve_static(model, Material(1e4, 0.4999), bc, linear_solver="multigrid", cg_max_steps=5, preconditioner_material=Material(1e4, 0.3))


def test_tangent_of_an_unconverged_iterative_solve_is_nan_not_wrong(springs):
    model, bc, top = springs
    f = lambda E: _force(model, bc, top, Material(E, 0.45), cg_max_steps=3, throw=False)  # noqa: E731
    assert not np.isfinite(float(jax.jit(jax.grad(f))(1e4)))


def test_auto_rule():
    assert auto_linear_solver(24) == "dense"  # one lattice cube
    assert auto_linear_solver(2_187) == "dense"
    assert auto_linear_solver(3_267) == "multigrid"
    assert auto_linear_solver(200_000) == "multigrid"
    assert auto_linear_solver(2_187, concrete=False) == "dense"
    assert auto_linear_solver(200_000, concrete=False) == "cg"


def test_a_new_youngs_modulus_reuses_the_hierarchy(springs):
    import difftissue.solvers.multigrid as mg

    model, bc, top = springs
    _force(model, bc, top, Material(1e4, 0.42))
    n = len(mg._CACHE)
    f2 = _force(model, bc, top, Material(3e4, 0.42))
    assert len(mg._CACHE) == n  # E is normalised out of the reference: no new PyAMG setup
    np.testing.assert_allclose(float(f2), 3 * float(_force(model, bc, top, Material(1e4, 0.42), solver="dense")), rtol=1e-8)


def test_chunked_assembly_gives_the_same_solve(springs, monkeypatch):
    """A large mesh assembles its Hessian (and the hierarchy's reference matrix, built from a
    traced model) in element chunks: the same solve as the one-shot assembly."""
    from difftissue.solvers import multigrid, static

    model, bc, top = springs
    material = Material(1e4, 0.45, 1.0)
    ref = _force(model, bc, top, material)
    monkeypatch.setattr(static, "ASSEMBLY_CHUNK", 50)
    monkeypatch.setattr(multigrid, "_CACHE", {})
    monkeypatch.setattr(multigrid, "_LAYOUTS", {})
    np.testing.assert_allclose(_force(model, bc, top, material), ref, rtol=1e-10)


def test_gradient_of_a_solve_stopped_at_max_steps_is_nan_in_both_modes(springs):
    """throw=False, Newton stopped at max_steps (the CG solves themselves converge): NaN
    tangents and cotangents, never the implicit tangent of the unconverged state."""
    model, bc, top = springs
    deep = BoundaryConditions(bc.fixed, 20 * bc.displacement, bc.force)  # 4 mm on an 8 mm block: nonlinear

    def force(E, max_steps):
        sol = solve_static(model, Material(E, 0.45, 2.0), deep, linear_solver="multigrid", max_steps=max_steps, throw=False, preconditioner_material=Material(1e4, 0.45))
        return jnp.sum(sol.reaction[top, 2]), sol.result

    # the value, the gradient and the tangent from one jitted program (not the surrounding code
    # op by op, nor one program each)
    (value, code), grad, tangent = jax.jit(
        lambda E: (*jax.value_and_grad(lambda e: force(e, 1), has_aux=True)(E), jax.jvp(lambda e: force(e, 1)[0], (E,), (1.0,))[1])
    )(1e4)
    assert int(code) != 0 and np.isfinite(float(value))  # the premise: a failed solve with a finite state
    assert np.isnan(float(grad))
    assert np.isnan(float(tangent))


def _const_bytes(closed_jaxpr):
    return sum(int(getattr(c, "nbytes", 0)) for c in closed_jaxpr.consts)


def test_solve_static_with_a_setup_takes_the_mesh_as_traced_arguments(springs):
    """A setup built beforehand (solver_setup) lets solve_static run inside jit with the model
    and the boundary conditions as arguments: the same force as the direct call, and the
    program holds no mesh-sized constant (the closed-over version holds the hierarchy)."""
    from difftissue.errors import ModelError
    from difftissue.solvers import solver_setup

    model, bc, top = springs
    material = Material(1e4, 0.45, 2.0)
    ref = Material(1e4, 0.45)
    direct = float(_force(model, bc, top, material, rtol=1e-12, cg_rtol=1e-12, preconditioner_material=ref))
    setup = solver_setup(model, material, bc, linear_solver="multigrid", preconditioner_material=ref, material_is_traced=True)
    assert setup.linear_solver == "multigrid" and setup.hierarchy is not None

    def force(model, bc, setup, material):
        sol = solve_static(model, material, bc, rtol=1e-12, cg_rtol=1e-12, setup=setup)
        return jnp.sum(sol.reaction[top, 2])

    np.testing.assert_allclose(float(jax.jit(force)(model, bc, setup, material)), direct, rtol=1e-12)
    mesh_bytes = sum(int(a.nbytes) for a in jax.tree_util.tree_leaves(model) if hasattr(a, "nbytes"))
    as_arguments = jax.make_jaxpr(force)(model, bc, setup, material)
    closed = jax.make_jaxpr(lambda m: _force(model, bc, top, m, rtol=1e-12, cg_rtol=1e-12, preconditioner_material=ref))(material)
    assert _const_bytes(as_arguments) < 0.05 * mesh_bytes < _const_bytes(closed)
    with pytest.raises(ModelError, match="setup was built for"):
        solve_static(make_model(block((0.01, 0.01, 0.01), (2, 2, 2)), "springs_volume"), material, bc, setup=setup)
    with pytest.raises(ModelError, match="built for 'multigrid'"):
        solve_static(model, material, bc, linear_solver="cg", setup=setup)


def test_scenario_protocol_takes_its_mesh_and_setup_as_arguments():
    """Indentation with the multigrid solver: predict (the protocol compiled with the arrays
    and the solver setup as arguments) equals the protocol compiled with the scenario closed
    over, to 1e-11 (the same iterations; XLA orders the sums of a program with constants
    differently: 1e-12 relative measured on a 1,215-unknown punch, CG tolerance 1e-10); the shared program holds no mesh-sized constant; another mesh of the same
    shape (twice as thick) shares the program and gets its own answer."""
    import equinox as eqx

    from difftissue import scenarios
    from difftissue.scenarios import Indentation, SolverOptions

    def punch(height):
        mesh = block((0.012, 0.012, height), (6, 6, 4))
        return Indentation(mesh, [1e-4, 2e-4], indenter="flat_punch", radius=0.003, bonded_punch=True, base="bonded",
                           model="fem_linear", options=SolverOptions(rtol=1e-12, linear_solver="multigrid"))

    material = Material(1e4, 0.45)
    sc = punch(0.008)
    closed = np.asarray(jax.jit(lambda m: sc._solve_protocol(m)[0])(material))
    np.testing.assert_allclose(np.asarray(sc.predict(material)), closed, rtol=1e-11)
    solve = scenarios._jitted_solve(sc)
    dynamic, _ = eqx.partition(sc, eqx.is_array)
    jaxpr = jax.make_jaxpr(solve.program.fn)(dynamic, solve.setup(material), material)
    mesh_bytes = sum(int(a.nbytes) for a in jax.tree_util.tree_leaves(sc.model) if hasattr(a, "nbytes"))
    assert _const_bytes(jaxpr) < 0.05 * mesh_bytes
    thicker = punch(0.016)  # twice as thick: the same punch nodes, other coordinates
    assert scenarios._jitted_solve(thicker).program is solve.program
    closed_thicker = np.asarray(jax.jit(lambda m: thicker._solve_protocol(m)[0])(material))
    np.testing.assert_allclose(np.asarray(thicker.predict(material)), closed_thicker, rtol=1e-11)
    assert abs(closed_thicker[1] / closed[1] - 1) > 0.05  # a different answer: not the first mesh's


@pytest.mark.parametrize("kind", ["springs_volume", "fem_neo_hookean"])
def test_a_finishing_newton_step_reuses_its_matrix_and_equals_exact_newton(kind, monkeypatch):
    """The multigrid Newton loop (CG steps to a forcing term with Kelley's safeguard; a
    finishing step reuses the block-ELL matrix and V-cycle of the step before) converges to
    the answer of exact Newton (dense Cholesky of a fresh Hessian every step) within the
    solver tolerance, and does reuse a matrix (counted at run time: an assembly inside the
    loop's cond runs only when taken)."""
    from difftissue.solvers import static

    assemblies = []
    original = static._multigrid_matrix

    def counted(*args, **kw):
        out = original(*args, **kw)
        jax.debug.callback(lambda: assemblies.append(1))
        return out

    monkeypatch.setattr(static, "_multigrid_matrix", counted)
    model, bc, top = _punch(kind, cells=(6, 6, 5))  # a mesh of its own: traced afresh with the counter
    material = Material(1e4, 0.45, 1.0 if kind == "springs_volume" else 0.0)
    exact = solve_static(model, material, bc, linear_solver="dense")
    mg = solve_static(model, material, bc, linear_solver="multigrid")
    jax.block_until_ready(mg.displacement)
    jax.effects_barrier()
    assert bool(mg.converged) and bool(exact.converged)
    # the predictor's matrix and one per Newton step, less the reused one(s)
    assert 1 <= len(assemblies) <= int(mg.steps), (len(assemblies), int(mg.steps))
    scale = float(jnp.abs(exact.displacement).max())
    np.testing.assert_allclose(mg.displacement, exact.displacement, rtol=0, atol=1e-9 * scale)
    f_exact = float(jnp.sum(exact.reaction[top, 2]))
    np.testing.assert_allclose(float(jnp.sum(mg.reaction[top, 2])), f_exact, rtol=1e-9)


@pytest.mark.parametrize("nu", [0.3, 0.49])
def test_warm_started_spectral_estimate_of_a_v_cycle_setup_is_accurate(springs, nu):
    """The Chebyshev smoother damps ``[lambda / 30, lambda]`` with ``lambda`` 1.1 times the
    power estimate of ``lambda_max(D^-1 A)`` (at least the reference's): it must not fall
    below the true largest eigenvalue. Few power iterations suffice because they start from
    the reference's dominant eigenvector (or the previous set-up's iterate): checked against
    dense eigenvalues for a material and a deformation away from the reference (hierarchy at
    nu = 0.45, rest), where the generic start alone is far off after as many iterations."""
    from difftissue.solvers.multigrid import MultigridPreconditioner, _power_lambda_max, _safe_inverse
    from difftissue.solvers.static import solver_setup

    model, bc, _ = springs
    material = Material(1e4, nu, 1.0)
    setup = solver_setup(model, material, bc, linear_solver="multigrid", preconditioner_material=Material(1.0, 0.45, 1.0))
    assert setup.hierarchy.power_start is not None
    P = 1.0 - jnp.asarray(bc.fixed, float).reshape(-1)
    X = jnp.asarray(model.rest_points)
    previous = None
    for amplitude in (0.0, 3e-4, 6e-4):
        # a smooth deformation of up to 6 % strain (the cube is 12 mm wide)
        x = X + amplitude * jnp.stack([jnp.sin(300 * X[:, 1]), jnp.sin(250 * X[:, 2]), jnp.sin(200 * X[:, 0])], axis=1)
        ell = _assemble_ell(setup.layout, model, x, material, P)
        A = np.asarray(ell.to_scipy().todense())
        s = 1.0 / np.sqrt(np.diag(A))
        true = float(np.linalg.eigvalsh(s[:, None] * A * s[None, :]).max())
        pc = MultigridPreconditioner.build(ell, setup.hierarchy, P, previous)
        assert float(pc.fine_lambda_max) >= true, (amplitude, float(pc.fine_lambda_max), true)
        estimate, _ = _power_lambda_max(ell.mv, _safe_inverse(ell.diagonal()), previous if previous is not None else setup.hierarchy.power_start)
        generic, _ = _power_lambda_max(ell.mv, _safe_inverse(ell.diagonal()), None)
        assert 0.97 * true <= float(estimate) <= true * (1 + 1e-12), (amplitude, float(estimate), true)
        assert float(generic) < 0.9 * true  # the warm start is what makes 4 iterations enough
        previous = pc.power_vector


def test_smoothed_aggregation_is_pyamgs_with_one_spectral_estimate_per_level(springs):
    """The hierarchy is PyAMG's smoothed aggregation (same options, from its public building
    blocks) with the prolongation smoother's ``rho(D^-1 A)`` estimated once per level (and
    shared with the Chebyshev smoother): same aggregates and tentative prolongators,
    ``T - P`` proportional to PyAMG's with the factor ``rho_PyAMG / rho``, ``rho`` within 1 %
    of the dense largest eigenvalue, Galerkin coarse operators."""
    import pyamg

    from difftissue.solvers.multigrid import PROLONGATION_OMEGA, _smoothed_aggregation
    from difftissue.solvers.static import _reference_material, solver_setup

    model, bc, _ = springs
    material = Material(1e4, 0.45, 1.0)
    setup = solver_setup(model, material, bc, linear_solver="multigrid")
    P_free = 1.0 - np.asarray(bc.fixed, float).reshape(-1)
    ref = _reference_material(material, None)
    ell = _assemble_ell(setup.layout, model, jnp.asarray(model.rest_points), ref, jnp.asarray(P_free))
    A = sps.bsr_matrix(ell.to_scipy(), blocksize=(3, 3))
    B = rigid_body_modes(model.rest_points) * P_free[:, None]
    ours, coarse = _smoothed_aggregation(A, B, 60)
    ml = pyamg.smoothed_aggregation_solver(A, B=B, symmetry="hermitian", strength="symmetric", max_coarse=60, keep=True)
    assert len(ours) == len(ml.levels) - 1 >= 1
    for (Al, P, R, rho, dinv, _), lvl in zip(ours, ml.levels):
        Ad = Al.toarray()
        s = np.sqrt(dinv)
        true = float(np.linalg.eigvalsh(s[:, None] * Ad * s[None, :]).max())
        assert abs(rho - true) <= 0.01 * true, (rho, true)
        T = lvl.T.toarray()
        ours_update, pyamg_update = T - P.toarray(), T - lvl.P.toarray()
        # both are (omega / rho) D^-1 A T: equal up to the ratio of the two estimates
        factor = np.linalg.norm(pyamg_update) / np.linalg.norm(ours_update)
        assert 0.97 < factor < 1.03, factor
        np.testing.assert_allclose(factor * ours_update, pyamg_update, atol=1e-9 * np.abs(pyamg_update).max())
        np.testing.assert_allclose(ours_update, (PROLONGATION_OMEGA / rho) * (dinv[:, None] * Ad) @ T, atol=1e-12 * np.abs(T).max())
        np.testing.assert_allclose(R.toarray(), P.toarray().T)
    for k in range(len(ours)):
        Al, P, R = ours[k][:3]
        nxt = ours[k + 1][0] if k + 1 < len(ours) else coarse
        np.testing.assert_allclose(nxt.toarray(), (R @ Al @ P).toarray(), rtol=0, atol=1e-12 * abs(Al).max())


def test_block_ell_to_scipy_is_the_canonical_matrix_of_its_blocks(springs):
    """``BlockEllMatrix.to_scipy`` drops the padding slots instead of sorting every block
    (SciPy's ``sum_duplicates``): the same matrix bit for bit, in canonical form; a matrix
    whose columns are not in order (here every row reversed) takes the sorting path and gives
    the same matrix."""
    from difftissue.solvers.multigrid import BlockEllMatrix
    from difftissue.solvers.static import solver_setup

    model, bc, _ = springs
    setup = solver_setup(model, Material(1e4, 0.45, 1.0), bc, linear_solver="multigrid")
    P = jnp.asarray(1.0 - np.asarray(bc.fixed, float).reshape(-1))
    x = jnp.asarray(model.rest_points) + 1e-4 * jnp.sin(jnp.asarray(model.rest_points) * 300.0)
    ell = _assemble_ell(setup.layout, model, x, Material(1e4, 0.45, 1.0), P)
    cols = np.array(ell.cols)  # a copy: SciPy sorts in place (the layout's own array is cached)
    n, w = cols.shape
    assert np.any(np.sum(cols == np.arange(n)[:, None], axis=1) > 1)  # there is padding to drop
    blocks = np.array(ell.blocks())
    sorted_ = sps.bsr_matrix((blocks.reshape(-1, 3, 3).copy(), cols.reshape(-1).copy(), np.arange(0, n * w + 1, w)), shape=(3 * n, 3 * n))
    sorted_.sum_duplicates()
    A = ell.to_scipy()
    assert A.has_canonical_format and A.has_sorted_indices
    np.testing.assert_array_equal(A.indptr, sorted_.indptr)
    np.testing.assert_array_equal(A.indices, sorted_.indices)
    np.testing.assert_array_equal(A.data, sorted_.data)
    reversed_ = BlockEllMatrix.from_blocks(jnp.asarray(blocks[:, ::-1]), jnp.asarray(cols[:, ::-1].copy()))
    B = reversed_.to_scipy()
    np.testing.assert_array_equal(B.indices, sorted_.indices)
    np.testing.assert_array_equal(B.toarray(), sorted_.toarray())
