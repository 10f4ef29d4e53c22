"""The Levenberg--Marquardt step on the host (difftissue.fit.host): the same iterates, stopping
and results as the compiled engine (difftissue.fit.engine) to 1e-10, on a closed-form scenario
(several starts, a bounded parameter, trial points whose evaluation fails) and on the Ecoflex
demo fit through the CLI (every float of fit.json); the transforms' NumPy path and derivative."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import Material
from difftissue.fit import fit
from difftissue.fit import host as fit_host
from difftissue.fit.problem import FitProblem
from difftissue.materials import DEFAULT_TRANSFORMS, Identity, Log, MaterialParameterization, ScaledLogit

jax.config.update("jax_enable_x64", True)


# ------------------------------------------------------------------ transforms
@pytest.mark.parametrize("transform", [Identity(), Log(scale=1e3), Log(lower=0.5, scale=2.0), ScaledLogit(-3.0, 5.0), ScaledLogit(-1.0, 0.5)])
def test_transform_numpy_path_and_derivative(transform):
    """NumPy input is computed in NumPy (equal to the JAX path to 1e-15); ``derivative`` is
    ``d forward / d u`` (float64, against jax.grad and central differences)."""
    for u in (-30.0, -2.5, -0.3, 0.0, 0.7, 4.0, 30.0):
        value = transform.forward(np.float64(u))
        assert isinstance(value, (np.ndarray, np.generic, float))
        np.testing.assert_allclose(value, float(transform.forward(jnp.asarray(u))), rtol=1e-15, atol=1e-300)
        d = transform.derivative(np.float64(u))
        np.testing.assert_allclose(d, float(jax.grad(transform.forward)(jnp.asarray(u))), rtol=1e-14, atol=1e-300)
        np.testing.assert_allclose(float(transform.derivative(jnp.asarray(u))), d, rtol=1e-14, atol=1e-300)
        if abs(u) < 5:
            h = 1e-6
            fd = (transform.forward(np.float64(u + h)) - transform.forward(np.float64(u - h))) / (2 * h)
            np.testing.assert_allclose(d, fd, rtol=1e-7)
            # inverse: NumPy in, NumPy out, the same as the JAX path
            back = transform.inverse(np.float64(value))
            assert isinstance(back, (np.ndarray, np.generic, float))
            np.testing.assert_allclose(back, u, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(back, float(transform.inverse(jnp.asarray(value))), rtol=1e-15, atol=1e-15)


def test_pack_of_concrete_materials_is_numpy():
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio", "cubic_coefficient"),
                                     transforms={"cubic_coefficient": ScaledLogit(-3.0, 5.0)})
    u = param.pack(Material(1.5e4, 0.45, cubic_coefficient=-1.0))
    assert isinstance(u, np.ndarray) and u.dtype == np.float64
    traced = jax.jit(lambda E: param.pack(Material(E, 0.45, cubic_coefficient=-1.0)))(1.5e4)
    np.testing.assert_allclose(u, np.asarray(traced), rtol=1e-15)


# ------------------------------------------------------------------ a closed-form scenario
class _Cubic:
    """``sigma = E (eps + b eps^3)`` [Pa], NaN where ``b > fail_above`` (a failed solve): a
    scenario that 'solves on the host' (NumPy predictions and tangents) and predicts in JAX
    for the compiled engine."""

    x_label, y_label = "strain [-]", "stress [Pa]"
    solves_on_host = True

    def __init__(self, name, eps, observed, fail_above=np.inf):
        self.name = name
        self.abscissa = np.asarray(eps, dtype=float)
        self.observed = np.asarray(observed, dtype=float)
        self.sigma = np.full_like(self.observed, 0.01 * np.max(np.abs(self.observed)))
        self.fail_above = fail_above
        self.host_calls = 0

    def predict(self, m):
        e = jnp.asarray(self.abscissa)
        y = m.youngs_modulus * (e + m.cubic_coefficient * e**3)
        return jnp.where(m.cubic_coefficient > self.fail_above, jnp.nan, y)

    def predict_and_tangents_on_host(self, m, tangents):
        self.host_calls += 1
        e = self.abscissa
        E, b = float(m.youngs_modulus), float(m.cubic_coefficient)
        y = E * (e + b * e**3)
        K = len(next(iter(tangents.values())))
        tE = np.asarray(tangents.get("youngs_modulus", np.zeros(K)))
        tb = np.asarray(tangents.get("cubic_coefficient", np.zeros(K)))
        JT = tE[:, None] * (e + b * e**3)[None] + tb[:, None] * (E * e**3)[None]
        if b > self.fail_above:
            return np.full_like(y, np.nan), np.full_like(JT, np.nan)
        return y, JT


def _problem_data(fail_above=np.inf):
    rng = np.random.default_rng(3)
    eps = np.linspace(0.02, 0.4, 20)
    obs = 1.6e4 * (eps - 1.6 * eps**3) * (1 + 0.01 * rng.normal(size=eps.size))
    sc2 = np.linspace(-0.3, 0.3, 15)
    obs2 = 1.6e4 * (sc2 - 1.6 * sc2**3) + 30.0 * rng.normal(size=sc2.size)
    return [_Cubic("a", eps, obs, fail_above), _Cubic("b", sc2, obs2, fail_above)]


PARAM = MaterialParameterization(("youngs_modulus", "cubic_coefficient"), transforms={"cubic_coefficient": ScaledLogit(-3.0, 5.0)})


def _both(scenarios, **kw):
    """The fit with the host engine and with the compiled engine."""
    on_host = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0), **kw)
    before = fit_host.HOST_STEPS
    fit_host.HOST_STEPS = False
    try:
        compiled = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0), **kw)
    finally:
        fit_host.HOST_STEPS = before
    return on_host, compiled


def _assert_same(a, b, rtol=1e-10):
    assert a.steps == b.steps and a.converged == b.converged and a.reason == b.reason and a.best_start == b.best_start
    for f in a.fields:
        np.testing.assert_allclose(a.values[f], b.values[f], rtol=rtol)
        np.testing.assert_allclose(a.standard_errors[f], b.standard_errors[f], rtol=rtol)
    np.testing.assert_allclose(a.loss, b.loss, rtol=rtol)
    np.testing.assert_allclose(a.loss_history, b.loss_history, rtol=rtol)
    np.testing.assert_allclose(a.start_values, b.start_values, rtol=rtol)
    np.testing.assert_allclose(a.start_losses, b.start_losses, rtol=rtol)
    np.testing.assert_array_equal(a.start_converged, b.start_converged)
    np.testing.assert_allclose(a.jacobian, b.jacobian, rtol=rtol)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=rtol)
    np.testing.assert_allclose(np.asarray(a.unconstrained), np.asarray(b.unconstrained), rtol=rtol, atol=1e-12)
    for k in a.predictions:
        np.testing.assert_allclose(a.predictions[k], b.predictions[k], rtol=rtol)


def test_host_engine_takes_the_compiled_engines_steps():
    scenarios = _problem_data()
    on_host, compiled = _both(scenarios)
    assert on_host.compilations == 0 and compiled.compilations >= 1  # the host engine compiled nothing
    assert scenarios[0].host_calls > 0
    assert on_host.converged and on_host.steps >= 3
    _assert_same(on_host, compiled)


def test_host_engine_without_steps_evaluates_the_start():
    """max_steps = 0: no step, the final evaluation at the start (the evaluate path)."""
    on_host, compiled = _both(_problem_data(), max_steps=0)
    assert on_host.steps == 0
    _assert_same(on_host, compiled)


def test_host_engine_with_several_starts_and_failing_trial_points():
    """Three starts (one far away, whose steps run into the region where the evaluation fails:
    rejected trial points, a shrinking trust region) give the same iterates and loss history."""
    scenarios = _problem_data(fail_above=2.0)
    starts = [Material(1.0e4, 0.49, cubic_coefficient=0.0), Material(4.0e4, 0.49, cubic_coefficient=4.5),
              Material(3.0e3, 0.49, cubic_coefficient=-2.5)]
    on_host, compiled = _both(scenarios, starts=starts, max_steps=40)
    _assert_same(on_host, compiled)
    assert on_host.loss_history.shape[1] == 3


def test_host_engine_only_where_it_applies():
    """A robust loss, Gauss--Newton, reverse Jacobians or a scenario that does not solve on the
    host keep the compiled engine; so does HOST_STEPS = False."""
    scenarios = _problem_data()
    problem = FitProblem(scenarios, PARAM, Material(1.0e4, 0.49))
    assert fit_host.host_capable(problem, "levenberg_marquardt", "linear", "fwd", np.float64)
    assert not fit_host.host_capable(problem, "levenberg_marquardt", "soft_l1", "fwd", np.float64)
    assert not fit_host.host_capable(problem, "gauss_newton", "linear", "fwd", np.float64)
    assert not fit_host.host_capable(problem, "levenberg_marquardt", "linear", "bwd", np.float64)
    assert not fit_host.host_capable(problem, "levenberg_marquardt", "linear", "fwd", np.float32)
    scenarios[1].solves_on_host = False
    assert not fit_host.host_capable(FitProblem(scenarios, PARAM, Material(1.0e4, 0.49)), "levenberg_marquardt", "linear", "fwd", np.float64)
    result = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0))
    assert result.compilations >= 1


def test_host_engine_checkpoint_resume(tmp_path):
    """A host fit interrupted by a callback and resumed from its checkpoint ends where an
    uninterrupted one does (the host state is saved and restored)."""
    scenarios = _problem_data()
    full = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0))
    ck = tmp_path / "ck.npz"
    first = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0), checkpoint=ck, callback=lambda p: p.step >= 2)
    assert first.steps == 2 and ck.exists()
    resumed = fit(scenarios, PARAM, Material(1.0e4, 0.49, cubic_coefficient=0.0), checkpoint=ck, resume=True)
    assert resumed.steps == full.steps
    np.testing.assert_allclose([resumed.values[f] for f in PARAM.fields], [full.values[f] for f in PARAM.fields], rtol=1e-14)


# ------------------------------------------------------------------ the Ecoflex demo through the CLI
def _floats(x, path=""):
    if isinstance(x, dict):
        for k, v in x.items():
            yield from _floats(v, f"{path}/{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _floats(v, f"{path}[{i}]")
    elif isinstance(x, float):
        yield path, x


def test_ecoflex_fit_json_is_the_compiled_engines(tmp_path):
    """`difftissue fit` of the Ecoflex demo (one cube solved on the host, so the steps run on the
    host) writes the fit.json of the compiled engine: every float to 1e-10 relative (the
    timestamps aside), the same steps, convergence and start."""
    import importlib.resources as ir

    from difftissue import cli

    cfg = ir.files("difftissue").joinpath("configs/ecoflex_compression.toml")
    assert cli.main(["fit", str(cfg), "--out", str(tmp_path / "host"), "--force", "--no-progress"]) == 0
    before = fit_host.HOST_STEPS
    fit_host.HOST_STEPS = False
    try:
        assert cli.main(["fit", str(cfg), "--out", str(tmp_path / "compiled"), "--force", "--no-progress"]) == 0
    finally:
        fit_host.HOST_STEPS = before
    a = json.loads((tmp_path / "host" / "fit.json").read_text())
    b = json.loads((tmp_path / "compiled" / "fit.json").read_text())
    fa, fb = dict(_floats(a)), dict(_floats(b))
    assert fa.keys() == fb.keys() and len(fa) > 40
    for k in fa:
        if "created" in k or "seconds" in k or "time" in k:
            continue
        assert fa[k] == pytest.approx(fb[k], rel=1e-10, abs=1e-300), k
    for k in ("steps", "converged", "reason", "method"):
        assert a[k] == b[k]
