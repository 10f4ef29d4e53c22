"""Contact and scenarios: each against its analytic limit, gradients against finite differences,
bad input refused with named errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import analytic, errors
from difftissue.contact import ConeIndenter, ContactModel, FlatPunch, SphereIndenter
from difftissue.materials import Material
from difftissue.mesh import block, read_mesh, write_mesh
from difftissue.models import make_model
from difftissue.scenarios import (
    AnalyticIndentation,
    Compression,
    FEMField,
    Indentation,
    cylinder,
    graded_axis,
    indentation_block,
    recover_lattice,
)
from difftissue.solvers import solve_static
from difftissue.boundary import BoundaryConditions


def _fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


# ------------------------------------------------------------------ compression
@pytest.fixture(scope="module")
def cube():
    return block((0.01, 0.01, 0.01), (2, 2, 2))


def test_frictionless_compression_is_homogeneous_uniaxial_stress(cube):
    strains = [1e-3, 1e-2, 0.05]
    lin = Compression(cube, strains, model="fem_linear")
    np.testing.assert_allclose(lin.predict(Material(16e3, 0.45)), 16e3 * np.array(strains), rtol=1e-9)
    springs = Compression(cube, [1e-4], model="springs_volume")
    np.testing.assert_allclose(springs.predict(Material(16e3, 0.3)), 1.6, rtol=1e-3)
    # bonded platens restrain the lateral expansion: stiffer than E eps
    bonded = Compression(cube, [1e-3], model="fem_linear", bonded=True)
    assert float(bonded.predict(Material(16e3, 0.45))[0]) > 1.05 * 16.0


def test_true_stress_matches_incompressible_neo_hookean(cube):
    eps_true = np.array([0.05, 0.1, 0.15, 0.2])
    sc = Compression(cube, eps_true, model="fem_neo_hookean", measure="true")
    mat = Material(3e3, 0.4999)
    lam = np.exp(-eps_true)  # stretch along the load
    mu = 3e3 / (2 * 1.4999)
    expected = mu * (1 / lam - lam**2)  # compressive true stress of incompressible neo-Hookean
    np.testing.assert_allclose(sc.predict(mat), expected, rtol=1e-2)


def test_compression_gradient_matches_finite_differences(cube):
    sc = Compression(cube, [0.05, 0.2], model="springs_volume")
    base = dict(youngs_modulus=16e3, poisson_ratio=0.4, cubic_coefficient=2.0)

    # one compiled program gives the gradient and every value of the differences (instead of
    # the protocol's primal, JVP and transposed programs compiled one by one)
    value_and_grad = jax.jit(jax.value_and_grad(lambda p: sc.predict(Material(*p[:2], cubic_coefficient=p[2]))[-1]))
    p0 = jnp.array([16e3, 0.4, 2.0])
    g = value_and_grad(p0)[1]

    def out(i, v):
        return value_and_grad(p0.at[i].set(v))[0]

    fd = [
        _fd(lambda v: out(0, v), 16e3, 1.0),
        _fd(lambda v: out(1, v), 0.4, 1e-6),
        _fd(lambda v: out(2, v), 2.0, 1e-5),
    ]
    np.testing.assert_allclose([float(v) for v in g], [float(v) for v in fd], rtol=1e-5)
    # the cubic coefficient stiffens
    assert float(out(2, 2.0)) > float(out(2, 0.0))


def test_cylinder_mesh_has_the_right_volume():
    m = cylinder(0.05, 0.03, cells_radial=4, cells_height=2)
    np.testing.assert_allclose(m.volumes().sum(), np.pi * 0.025**2 * 0.03, rtol=0.03)
    assert m.volumes().min() > 0


# -------------------------------------------------------------------- analytic
def test_analytic_indentation_is_the_closed_forms():
    d = np.linspace(1e-6, 1e-5, 5)
    F = np.asarray(analytic.hertz_force(d, 1e3, 0.5, 1e-4))
    sc = AnalyticIndentation(d, F, indenter="sphere", radius=1e-4)
    np.testing.assert_allclose(sc.predict(Material(1e3, 0.4999999)), F, rtol=1e-6)
    layer = AnalyticIndentation(d, F, indenter="sphere", radius=1e-4, thickness=5e-5, solution="dimitriadis")
    np.testing.assert_allclose(layer.predict(Material(1e3, 0.45)), analytic.dimitriadis_force(d, 1e3, 0.45, 1e-4, 5e-5), rtol=1e-12)
    with pytest.raises(errors.ConfigError, match="radius"):
        AnalyticIndentation(d, F, indenter="sphere")
    with pytest.raises(errors.ConfigError, match="thickness"):
        AnalyticIndentation(d, F, indenter="sphere", radius=1e-4, solution="exact_layer")
    with pytest.raises(errors.DataError, match="NaN"):
        AnalyticIndentation(d, F * np.nan, indenter="sphere", radius=1e-4)
    # the exact layer solution's range (chi = sqrt(R d)/h <= 4) is checked on the depths when
    # the scenario is built: a fit passes them to its compiled programs as arguments
    with pytest.raises(errors.DifftissueError, match="chi = .* must lie in"):
        AnalyticIndentation(d * 1e4, F, indenter="sphere", radius=1e-4, thickness=1e-5, solution="exact_layer")


# ---------------------------------------------------------------- indentation
def test_flat_punch_matches_hayes_on_a_refined_mesh():
    a, H = 1e-3, 5e-3
    mesh = indentation_block((25 * a, 25 * a, H), (16, 16, 16), symmetry="quarter", refine=a / 10)
    d = [1e-5]
    sc = Indentation(mesh, d, model="fem_linear", indenter="flat_punch", radius=a, symmetry="quarter")
    F = float(sc.predict(Material(10e3, 0.3))[0])
    hayes = float(analytic.layer_flat_punch_force(1e-5, 10e3, 0.3, a, H))
    assert F == pytest.approx(hayes, rel=0.03)  # measured 1.5 % (linear tets, graded mesh)


@pytest.fixture(scope="module")
def small_sphere():
    R, H = 1e-3, 1e-3
    mesh = indentation_block((4e-3, 4e-3, H), (8, 8, 6), symmetry="quarter", refine=0.03e-3)
    return mesh, Indentation(mesh, [2e-5, 4e-5], model="fem_linear", indenter="sphere", radius=R, symmetry="quarter")


def test_sphere_contact_is_frictionless_and_barely_penetrates(small_sphere):
    mesh, sc = small_sphere
    mat = Material(10e3, 0.4)
    forces, us = sc.solve(mat)
    assert np.all(np.diff(np.asarray(forces)) > 0) and float(forces[0]) > 0
    model = sc.model.with_depth(4e-5)
    x = jnp.asarray(mesh.points) + us[-1]
    pen = np.asarray(model.penetrations(x))
    assert pen.max() < 0.01 * 4e-5  # penalty 100: about 0.3 % of the depth
    assert int((pen > 0).sum()) >= 3  # several nodes in contact
    # force balance: the indenter force equals the base reaction (quarter model, x4)
    sol = solve_static(model, mat, sc.bc, initial_displacement=us[-1])
    bottom = np.flatnonzero(np.isclose(np.asarray(mesh.points)[:, 2], 0.0))
    np.testing.assert_allclose(4 * float(jnp.sum(sol.reaction[bottom, 2])), float(forces[-1]), rtol=1e-6)


def test_sphere_force_gradient_matches_finite_differences(small_sphere):
    _, sc = small_sphere

    # one compiled program for the gradient and the four difference evaluations
    value_and_grad = jax.jit(jax.value_and_grad(lambda E, nu: sc.predict(Material(E, nu))[-1], argnums=(0, 1)))

    def f(E, nu):
        return value_and_grad(E, nu)[0]

    g = value_and_grad(10e3, 0.4)[1]
    np.testing.assert_allclose(float(g[0]), float(_fd(lambda v: f(v, 0.4), 10e3, 1.0)), rtol=1e-5)
    # steps large enough that the solver tolerance (1e-9) is far below the difference
    np.testing.assert_allclose(float(g[1]), float(_fd(lambda v: f(10e3, v), 0.4, 1e-4)), rtol=1e-5)


def test_indenters_geometry_and_errors():
    s = SphereIndenter(1e-3, surface_z=0.0)
    assert float(s.penetration(jnp.array([0.0, 0.0, 0.0]), 1e-4)) == pytest.approx(1e-4)
    c = ConeIndenter(np.deg2rad(45), surface_z=0.0)
    # a point on the surface at radius r is inside by (d - r) sin 45
    assert float(c.penetration(jnp.array([1e-5, 0.0, 0.0]), 3e-5)) == pytest.approx(2e-5 * np.sin(np.pi / 4))
    with pytest.raises(errors.ModelError, match="radius"):
        SphereIndenter(-1.0)
    with pytest.raises(errors.ModelError, match="half_angle"):
        ConeIndenter(2.0)
    mesh = block((1e-3, 1e-3, 1e-3), (2, 2, 2))
    with pytest.raises(errors.ModelError, match="FlatPunch"):
        ContactModel(make_model(mesh, "fem_linear"), FlatPunch(1e-4), mesh)
    with pytest.raises(errors.BoundaryConditionError, match="refine"):
        FlatPunch(1e-6, axis_xy=(0.25e-3, 0.25e-3)).nodes(mesh)
    with pytest.raises(errors.DataError, match="non-decreasing"):
        Indentation(mesh, [2e-5, 1e-5], model="fem_linear", indenter="sphere", radius=1e-3)
    with pytest.raises(errors.ConfigError, match="radius"):
        Indentation(mesh, [1e-5], model="fem_linear", indenter="sphere")
    with pytest.raises(errors.BoundaryConditionError, match="quarter"):
        Indentation(block((1e-3,) * 3, 2, origin=(-5e-4, -5e-4, 0)), [1e-5], model="fem_linear", radius=1e-3, symmetry="quarter")


def test_graded_axis():
    x = graded_axis(1.0, 10, 0.01)
    assert x[0] == 0 and x[-1] == 1.0 and x[1] == pytest.approx(0.01)
    assert np.all(np.diff(np.diff(x)) > 0)
    np.testing.assert_allclose(graded_axis(1.0, 4), [0, 0.25, 0.5, 0.75, 1.0])
    c = graded_axis(1.0, 20, 0.01, core=0.05)
    np.testing.assert_allclose(c[:6], np.arange(6) * 0.01)  # uniform core of 5 cells
    assert c[-1] == 1.0 and len(c) == 21 and np.all(np.diff(c[5:]) >= 0.01 - 1e-15)
    with pytest.raises(errors.ModelError, match="core"):
        graded_axis(1.0, 4, 0.01, core=0.05)
    m = indentation_block((1.0, 1.0, 0.5), (12, 12, 10), refine=0.01, core=0.04)
    assert m.volumes().min() > 0


# ------------------------------------------------------------------ FEM field
def test_fem_field_reproduces_its_reference_and_recovers_the_lattice(tmp_path):
    mesh = block((0.01, 0.01, 0.005), (4, 4, 2))
    p = np.asarray(mesh.points)
    bottom = np.isclose(p[:, 2], 0.0)
    punch = np.isclose(p[:, 2], 0.005) & (np.hypot(p[:, 0] - 0.005, p[:, 1] - 0.005) <= 0.0026)
    truth = Material(12e3, 0.42)
    bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(bottom)).fix(mesh, np.flatnonzero(punch), "z", (0, 0, -1e-4))
    for kind in ("fem_linear", "springs_volume"):
        ref = solve_static(make_model(mesh, kind), truth, bc)
        path = write_mesh(
            tmp_path / f"ref_{kind}.vtu",
            mesh,
            point_data={"displacement": np.asarray(ref.displacement), "bottom": bottom.astype(np.int32), "punch": punch.astype(np.int32), "reaction": np.asarray(ref.reaction)},
        )
        back = read_mesh(path)
        assert back.lattice is None and recover_lattice(back).lattice is not None
        sc = FEMField(
            back,
            back.point_data["displacement"],
            prescribed=[{"set": "bottom"}, {"set": "punch", "components": "z"}],
            model=kind,
            reaction={"set": "punch", "field": "reaction", "components": "z"},
        )
        np.testing.assert_allclose(sc.predict(truth), sc.observed, rtol=1e-8, atol=1e-10 * np.abs(sc.observed).max())
        assert sc.observed[-1] == pytest.approx(float(jnp.sum(ref.reaction[punch, 2])))
        # a different material does not reproduce it
        assert np.abs(np.asarray(sc.predict(Material(12e3, 0.3))) - sc.observed).max() > 1e-3 * np.abs(sc.observed).max()
    with pytest.raises(errors.ConfigError, match="nosuch"):
        FEMField(back, back.point_data["displacement"], prescribed=[{"set": "nosuch"}])
    with pytest.raises(errors.ConfigError, match="prescribed"):
        FEMField(
            back,
            back.point_data["displacement"],
            prescribed=[{"set": "bottom"}, {"set": "punch", "components": "z"}],
            reaction={"set": "punch", "force": [1.0], "components": "x"},
        )


def test_recover_lattice_refuses_unstructured_meshes():
    m = cylinder(0.01, 0.01, 2, 2)
    with pytest.raises(errors.ModelError, match="lattice"):
        recover_lattice(m)


# ------------------------------------------------- indenter depth and failed solves
@pytest.fixture(scope="module")
def depth_sphere():
    """245 nodes: enough for a two-level multigrid hierarchy."""
    mesh = indentation_block((4e-3, 4e-3, 1e-3), (6, 6, 4), symmetry="quarter", refine=0.05e-3)
    return mesh, Indentation(mesh, [2e-5, 4e-5], model="fem_linear", indenter="sphere", radius=1e-3, symmetry="quarter", solver="full")


@pytest.mark.parametrize("solver", ["dense", "multigrid"])
def test_indenter_depth_derivative_matches_central_differences(depth_sphere, solver):
    """d(force)/d(depth) through solve_static: the depth is a differentiated leaf of the
    ContactModel (implicit function theorem), forward and reverse mode."""
    sc, mat = depth_sphere[1], Material(10e3, 0.4)

    def force(depth):
        model = sc.model.with_depth(depth)
        sol = solve_static(model, mat, sc.bc, linear_solver=solver, rtol=1e-12, cg_rtol=1e-12, preconditioner_material=mat)
        return model.reaction_force(jnp.asarray(model.rest_points) + sol.displacement, mat)

    # One compiled program gives the value, the reverse-mode gradient and the forward-mode
    # tangent; the two difference evaluations reuse it (three separate programs compiled ~1.5x
    # as long; the executions are milliseconds on this mesh).
    @jax.jit
    def value_reverse_forward(x):
        v, g = jax.value_and_grad(force)(x)
        return v, g, jax.jvp(force, (x,), (1.0,))[1]

    def value(x):
        return value_reverse_forward(x)[0]

    d = 4e-5
    _, g, t = (float(a) for a in value_reverse_forward(d))
    fd = float(_fd(value, d, 1e-3 * d))  # measured agreement 3e-10 (dense), 7e-10 (multigrid)
    assert g == pytest.approx(fd, rel=1e-5)
    assert t == pytest.approx(g, rel=1e-9)
    assert g > 1.2 * float(value(d)) / d  # Hertz: dF/dd = 1.5 F/d, not the secant


@pytest.mark.parametrize("solver", ["full", "condensed"])
def test_contact_offset_derivative_of_indentation(depth_sphere, solver):
    mesh, sc = depth_sphere
    if solver == "condensed":
        sc = Indentation(mesh, [2e-5, 4e-5], model="fem_linear", indenter="sphere", radius=1e-3, symmetry="quarter", solver="condensed")
    mat = Material(10e3, 0.4)
    f = lambda c: sc.predict(mat, c)  # noqa: E731
    # one compiled program: the forces, their reverse- and forward-mode derivatives (the
    # difference evaluations reuse it)
    value_reverse_forward = jax.jit(lambda c: (f(c), jax.jacrev(f)(c), jax.jacfwd(f)(c)))
    _, J, Jf = (np.asarray(a) for a in value_reverse_forward(0.0))
    h = 4e-8
    fd = np.asarray((value_reverse_forward(h)[0] - value_reverse_forward(-h)[0]) / (2 * h))
    np.testing.assert_allclose(J, fd, rtol=1e-5)
    np.testing.assert_allclose(Jf, J, rtol=1e-9)
    np.testing.assert_allclose(sc.predict(mat, 0.0), sc.predict(mat), rtol=0)


def test_failed_solve_gives_nan_values_and_derivatives_in_both_modes(cube):
    """SolverOptions(failure="nan"): value, forward tangent and reverse gradient all NaN (a
    ``where`` mask gave a zero, finite gradient at a failed point).

    One compiled program (the scenario is its argument: the strains are arrays, the options
    static) gives the value, the reverse-mode gradient (its primal is the value) and the
    forward-mode tangent. The control runs the same program, with the same options, on a
    strain its one Newton step does solve: finite, and consistent (the stress of a
    displacement-controlled test is proportional to E, so d/dE = value / E)."""
    from difftissue.scenarios import SolverOptions

    @jax.jit
    def value_reverse_forward(sc, E):
        out = lambda E: sc.predict(Material(E, 0.45))[0]  # noqa: E731
        return (*jax.value_and_grad(out)(E), jax.jvp(out, (E,), (1.0,))[1])

    options = SolverOptions(max_steps=1, failure="nan", linear_solver="dense")
    failing = Compression(cube, [0.3], model="fem_neo_hookean", options=options)
    value, grad, tangent = (float(a) for a in value_reverse_forward(failing, 1e3))
    assert np.isnan(value) and np.isnan(grad) and np.isnan(tangent)
    ok = Compression(cube, [1e-3], model="fem_neo_hookean", options=options)
    value, grad, tangent = (float(a) for a in value_reverse_forward(ok, 1e3))
    assert np.isfinite(value) and value > 0.9 * 1e3 * 1e-3
    assert grad == pytest.approx(value / 1e3, rel=1e-8) and tangent == pytest.approx(grad, rel=1e-9)


def test_an_equal_scenario_rebuilt_reuses_the_compiled_protocol(cube, caplog):
    """A scenario built again from equal inputs (as each export of a card rebuilds its
    specimen) shares the first one's executable, also after the first object is gone, and so
    does one with other measured data, or other strains of the same count (the arrays are
    arguments of the program, not constants), with its own correct values; a scenario that
    differs in anything compiled in (here the number of strains) gets its own."""
    import gc
    import logging

    from difftissue import scenarios

    mat = Material(16e3, 0.45)
    first = Compression(cube, [1e-3, 1e-2], model="fem_linear")
    expected = np.asarray(first.predict(mat))
    program = scenarios._jitted_solve(first).program
    del first
    gc.collect()
    again = Compression(block((0.01, 0.01, 0.01), (2, 2, 2)), [1e-3, 1e-2], model="fem_linear")
    assert scenarios._jitted_solve(again).program is program
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        np.testing.assert_allclose(again.predict(mat), expected, rtol=0)
    assert [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()] == []
    measured = Compression(cube, [1e-3, 1e-2], [15.0, 170.0], model="fem_linear")
    assert scenarios._jitted_solve(measured).program is program
    np.testing.assert_allclose(measured.predict(mat), expected, rtol=0)
    other = Compression(cube, [1e-3, 2e-2], model="fem_linear")
    assert scenarios._jitted_solve(other).program is program
    np.testing.assert_allclose(other.predict(mat), [16.0, 320.0], rtol=1e-9)
    longer = Compression(cube, [1e-3, 1e-2, 2e-2], model="fem_linear")
    assert scenarios._jitted_solve(longer).program is not program
    np.testing.assert_allclose(longer.predict(mat), [16.0, 160.0, 320.0], rtol=1e-9)


def test_a_first_prediction_inside_jit_leaves_no_tracer_behind():
    """A scenario whose first ``predict`` runs inside ``jax.jit`` (a user's own jit, a fit)
    caches its compiled protocol with concrete arrays: a second jit and a plain call of the same
    scenario work (they raised UnexpectedTracerError when the cache held the first trace's
    tracers) and give the same forces."""
    mesh = indentation_block((4e-3, 4e-3, 1.6e-3), (3, 3, 2), symmetry="quarter")
    sc = Indentation(mesh, np.array([0.05e-3, 0.1e-3]), model="springs_volume", radius=1e-3, symmetry="quarter")
    first = np.asarray(jax.jit(lambda E: sc.predict(Material(E, 0.3)))(1e4))
    second = np.asarray(jax.jit(lambda E: 2.0 * sc.predict(Material(E, 0.3)))(1e4)) / 2.0
    plain = np.asarray(sc.predict(Material(1e4, 0.3)))
    assert np.all(first < 0) or np.all(first > 0)
    np.testing.assert_allclose(second, first, rtol=1e-12)
    np.testing.assert_allclose(plain, first, rtol=1e-12)


def test_a_failure_inside_a_compiled_protocol_raises_its_named_error():
    """A scenario's predict outside jit (SolverOptions.failure = "raise"): a static solve that
    fails raises ConvergenceError with the solver's message, a model's range check of the
    material ModelRangeError, not JAX's runtime error with the callback's traceback and
    equinox's advice to use filter_jit."""
    from difftissue.models import material_error_type
    from difftissue.scenarios import AxisymmetricIndentation, SolverOptions

    stalled = AxisymmetricIndentation([1e-5, 2e-5], indenter="sphere", radius=1e-3, cells_per_contact_radius=3, options=SolverOptions(max_steps=1))
    with pytest.raises(errors.ConvergenceError, match=r"^static solve did not converge within max_steps Newton steps \(raise max_steps"):
        stalled.predict(Material(1e4, 0.45))
    lattice = Indentation(block((2e-3, 2e-3, 1e-3), (2, 2, 1)), [1e-5], model="springs_volume", indenter="sphere", radius=1e-3, symmetry="quarter")
    with pytest.raises(errors.ModelRangeError, match=r"^poisson_ratio outside \[0.25, 0.5\) for the springs_volume model"):
        lattice.predict(Material(1e4, 0.1))
    assert material_error_type("youngs_modulus must be > 0 Pa") is errors.MaterialError
    assert material_error_type("pre_stretch must be > 0 (1 = no pre-tension)") is errors.MaterialError
    assert material_error_type("static solve produced NaN or infinite values") is None
