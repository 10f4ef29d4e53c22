"""The host solves of small models (difftissue.solvers.host) and of small compression specimens
(Compression.solve_on_host, used by SeparatelyCompiled): the same numbers as the compiled
protocol, tangents checked against the compiled JVP and against central finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import Material
from difftissue.config import compile as cc
from difftissue.config import SeparatelyCompiled, compile_cache_info
from difftissue.errors import ConvergenceError, ModelError
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.scenarios import Compression, SolverOptions
from difftissue.solvers import host

jax.config.update("jax_enable_x64", True)

MODELS = ["springs_volume", "fem_linear", "fem_neo_hookean", "stable_neo_hookean"]
STRAINS = [0.05, 0.1, 0.2, 0.3]
FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "pre_stretch")


def _material(E=2.0e4, nu=0.45, b=-1.0, lam=1.0):
    return Material(E, nu, cubic_coefficient=b, pre_stretch=lam)


def _scenario(model, cells=(1, 1, 1), **kw):
    mesh = block((0.01, 0.01, 0.01), cells)
    return Compression(mesh, STRAINS, model=model, **kw)


def _compiled(sc, m, fields):
    """The compiled protocol's stress and its JVPs along unit tangents of ``fields`` (one program)."""
    def f(v):
        return sc.predict(m.replace(**{k: v[i] for i, k in enumerate(fields)}))

    v0 = jnp.asarray([float(getattr(m, k)) for k in fields])
    y, T = jax.vmap(lambda t: jax.jvp(f, (v0,), (t,)))(jnp.eye(len(fields)))
    return np.asarray(y[0]), np.asarray(T)


@pytest.mark.parametrize("model,setup", [(m, "frictionless") for m in MODELS] + [("springs_volume", "bonded")])
def test_the_host_protocol_equals_the_compiled_one(model, setup):
    """Stresses and their tangents in E, nu and b (and the pre-stretch where the model has one)
    equal the compiled protocol's (``predict`` and its JVP) to 1e-10 relative (tangents that
    vanish, d/d nu of a linear uniaxial stress: to 1e-10 of the stress per unit of the field),
    on one cube with frictionless platens and on a 2 x 2 x 2 block (27 nodes) with bonded platens."""
    sc = _scenario(model) if setup == "frictionless" else _scenario(model, cells=(2, 2, 2), bonded=True)
    assert sc.solves_on_host
    m = _material()
    fields = FIELDS if model == "springs_volume" else FIELDS[:2]
    y, T = sc.solve_on_host(m, {f: np.eye(len(fields))[i] for i, f in enumerate(fields)})
    y_c, T_c = _compiled(sc, m, fields)
    np.testing.assert_allclose(y, y_c, rtol=1e-10, atol=0)
    for i, f in enumerate(fields):
        scale = np.max(np.abs(y)) / abs(float(getattr(m, f)))
        np.testing.assert_allclose(T[i], T_c[i], rtol=1e-10, atol=1e-10 * scale, err_msg=f)


@pytest.mark.parametrize("model", ["springs_volume", "fem_neo_hookean"])
def test_host_tangents_match_central_differences(model):
    """d stress / d field from the implicit function theorem against central differences of
    the host protocol itself (relative step 1e-4; the solves converge to round-off)."""
    sc = _scenario(model)
    m = _material(b=-1.0, lam=1.02) if model == "springs_volume" else _material()
    fields = FIELDS if model == "springs_volume" else FIELDS[:2]
    _, T = sc.solve_on_host(m, {f: np.eye(len(fields))[i] for i, f in enumerate(fields)})
    for i, f in enumerate(fields):
        v = float(getattr(m, f))
        h = 1e-4 * abs(v)
        up, _ = sc.solve_on_host(m.replace(**{f: v + h}))
        down, _ = sc.solve_on_host(m.replace(**{f: v - h}))
        fd = (up - down) / (2 * h)
        np.testing.assert_allclose(T[i], fd, rtol=1e-6, atol=1e-8 * np.max(np.abs(fd)), err_msg=f)


def test_a_failed_solve_raises_or_gives_nan_from_that_strain_on():
    """Two Newton steps allowed: the jump from 2 % to 50 % strain needs more and fails.
    ``failure="nan"``: NaN from there on, as the compiled protocol (the same pattern and the
    same finite values); ``failure="raise"``: ConvergenceError naming the strain."""
    m = _material()
    strains = [0.01, 0.02, 0.5, 0.55]
    mesh = block((0.01, 0.01, 0.01), (1, 1, 1))
    nan = Compression(mesh, strains, model="fem_neo_hookean", options=SolverOptions(max_steps=2, failure="nan"))
    y, T = nan.solve_on_host(m, {"youngs_modulus": np.ones(1)})
    y_c = np.asarray(nan.predict(m))
    np.testing.assert_array_equal(np.isnan(y), [False, False, True, True])
    np.testing.assert_array_equal(np.isnan(y_c), np.isnan(y))
    assert np.all(np.isnan(T[:, 2:])) and np.all(np.isfinite(T[:, :2]))
    np.testing.assert_allclose(y[:2], y_c[:2], rtol=1e-10)
    raising = Compression(mesh, strains, model="fem_neo_hookean", options=SolverOptions(max_steps=2, failure="raise"))
    with pytest.raises(ConvergenceError, match="at strain 0.5"):
        raising.solve_on_host(m)


def test_what_is_not_solved_on_the_host_says_so():
    """More than HOST_MAX_NODES nodes, true stress or an iterative linear solver: not on the host
    (solves_on_host False) and solve_on_host raises ModelError."""
    big = _scenario("fem_linear", cells=(4, 4, 3))
    assert big.model.n_nodes > host.HOST_MAX_NODES
    true = _scenario("fem_linear", measure="true")
    cg = _scenario("fem_linear", options=SolverOptions(linear_solver="cg"))
    for sc in (big, true, cg):
        assert not sc.solves_on_host
        with pytest.raises(ModelError, match="solve_on_host"):
            sc.solve_on_host(_material())


def test_model_derivatives_are_the_models_own_and_shared_between_equal_structures():
    """Energy, gradient, Hessian and the mixed material derivative equal jax's of
    ``model.energy`` at every row of batches below, at and above HOST_BATCH (padding and
    chunks); two meshes of the same structure and sizes share one compiled program."""
    mesh = block((0.01, 0.01, 0.01), (1, 1, 1))
    model = make_model(mesh, "springs_volume")
    m = model.checked(_material(b=2.0, lam=1.01))
    rng = np.random.default_rng(0)
    x = np.asarray(mesh.points)[None] + 1e-3 * rng.standard_normal((host.HOST_BATCH + 4, model.n_nodes, 3))
    e, g, H, D, mv = host.model_derivatives(model, m, x)
    e1, g1, H1, D1, mv1 = host.model_derivatives(model, m, x[:3])
    np.testing.assert_array_equal(e[:3], e1)
    np.testing.assert_array_equal(H[:3], H1)
    # jax's derivatives of model.energy, each jitted once for both rows (op by op, the Hessian and
    # the mixed derivative dispatched hundreds of small programs)
    grad = jax.jit(lambda z: jax.grad(model.energy)(z, m).reshape(-1))
    hessian = jax.jit(lambda z: jax.hessian(lambda y: model.energy(y.reshape(-1, 3), m))(z.reshape(-1)))
    mixed = jax.jit(lambda z: jax.jacfwd(lambda mm: jax.grad(model.energy)(z, mm).reshape(-1))(m))
    for i in (0, host.HOST_BATCH + 3):
        xi = jnp.asarray(x[i])
        np.testing.assert_allclose(e[i], model.energy(xi, m), rtol=1e-13)
        np.testing.assert_allclose(g[i], grad(xi), rtol=1e-10, atol=1e-12 * np.max(np.abs(g[i])))
        Hj = hessian(xi)
        np.testing.assert_allclose(H[i], Hj, rtol=1e-10, atol=1e-12 * np.max(np.abs(Hj)))
        Dj = mixed(xi)
        for f in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "pre_stretch"):
            np.testing.assert_allclose(getattr(D, f)[i], getattr(Dj, f), rtol=1e-10, atol=1e-12 * np.max(np.abs(getattr(Dj, f))))
        np.testing.assert_allclose(mv[i], model.min_volume_ratio(xi), rtol=1e-13)
    n = len(host._PROGRAMS)
    other = make_model(block((0.02, 0.022, 0.02), (1, 1, 1)), "springs_volume")
    host.model_derivatives(other, other.checked(_material()), np.asarray(other.rest_points)[None])
    assert len(host._PROGRAMS) == n


def test_separately_compiled_solves_small_compression_on_the_host():
    """SeparatelyCompiled (forward mode) takes the host path for a one-cube compression (no
    protocol compiled) with the numbers of the compiled protocol (HOST_SOLVES False) to 1e-10."""
    sc = _scenario("springs_volume")
    m = _material()
    before = compile_cache_info()["compilations"]
    on_host = SeparatelyCompiled(sc, n_tangents=2)
    y = on_host.evaluate(m)
    jac = jax.jacfwd(lambda E, b: on_host.predict(Material(E, 0.45, cubic_coefficient=b)), argnums=(0, 1))(2.0e4, -1.0)
    assert compile_cache_info()["compilations"] == before
    try:
        cc.HOST_SOLVES = False
        compiled = SeparatelyCompiled(sc, n_tangents=2)
        y_c = compiled.evaluate(m)
        jac_c = jax.jacfwd(lambda E, b: compiled.predict(Material(E, 0.45, cubic_coefficient=b)), argnums=(0, 1))(2.0e4, -1.0)
    finally:
        cc.HOST_SOLVES = True
    assert compile_cache_info()["compilations"] == before + 1
    np.testing.assert_allclose(y, y_c, rtol=1e-10)
    for a, b in zip(jac, jac_c):
        np.testing.assert_allclose(a, b, rtol=1e-10)
