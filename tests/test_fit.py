"""difftissue.fit: gradients, recovery, uncertainty, identifiability, multi-start, compilation,
checkpoint/resume and the output files. Small analytic scenarios stand in for the real ones."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import Material
from difftissue.analytic import hertz_force
from difftissue.errors import (
    CheckpointError,
    CheckpointMismatchError,
    FitError,
    IdentifiabilityWarning,
    OutputExistsError,
)
from difftissue.fit import FitProblem, Scenario, fit, parameter_statistics
from difftissue.report import write_fit_outputs
from difftissue.materials import MaterialParameterization, ScaledLogit

E_TRUE, NU_TRUE, B_TRUE = 5e3, 0.45, 4.0
RADIUS = 1e-3


# ------------------------------------------------------------------ toy scenarios
# The toy scenarios are pytrees (their arrays leaves, their labels and constants static): the fit
# engine then keys a problem by the CONTENT of the compiled-in leaves (the abscissa) and passes
# ``observed`` and ``sigma`` as arguments, so every test that builds the same toy curve again
# (``stress_strain_data()`` with other noise or outliers, ``hertz_data(seed=1)``) reuses the
# step and evaluation programs compiled for it by an earlier test instead of compiling its own
# (a plain dataclass is a single leaf, keyed by identity: one compilation per object).
_ARRAYS = ["abscissa", "observed", "sigma"]


def _toy_pytree(cls):
    """Register the frozen dataclass ``cls`` as a pytree: ``_ARRAYS`` are its leaves, every
    other field (name, labels, radius) is static."""
    meta = [f for f in cls.__dataclass_fields__ if f not in _ARRAYS]
    return jax.tree_util.register_dataclass(cls, data_fields=_ARRAYS, meta_fields=meta)


@_toy_pytree
@dataclass(frozen=True, eq=False)
class HertzCurve:
    """Spherical indentation force F = 4/3 E/(1-nu^2) sqrt(R) d^1.5 [N] vs depth [m]."""

    name: str
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    radius: float = RADIUS
    x_label: str = "depth [m]"
    y_label: str = "force [N]"

    def predict(self, material):
        return hertz_force(self.abscissa, material.youngs_modulus, material.poisson_ratio, self.radius)


@_toy_pytree
@dataclass(frozen=True, eq=False)
class StressStrain:
    """Uniaxial stress sigma = E (eps + b eps^3) [Pa] vs strain [1]."""

    name: str
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    x_label: str = "strain [1]"
    y_label: str = "stress [Pa]"

    def predict(self, material):
        eps = jnp.asarray(self.abscissa)
        return material.youngs_modulus * (eps + material.cubic_coefficient * eps**3)


@_toy_pytree
@dataclass(frozen=True, eq=False)
class CompressionToy:
    """Two outputs of one compression test: axial stress E eps [Pa] and lateral strain -nu eps [1],
    concatenated; nu matters through the second half."""

    name: str
    abscissa: np.ndarray  # strain, repeated for the two outputs
    observed: np.ndarray
    sigma: np.ndarray
    x_label: str = "axial strain [1]"
    y_label: str = "stress [Pa] | lateral strain [1]"

    def predict(self, material):
        eps = jnp.asarray(self.abscissa)
        half = eps.shape[0] // 2
        return jnp.concatenate([material.youngs_modulus * eps[:half], -material.poisson_ratio * eps[half:]])


@_toy_pytree
@dataclass(frozen=True, eq=False)
class Oscillation:
    """sin(b t) with many local minima in b (for multi-start)."""

    name: str
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    x_label: str = "t [s]"
    y_label: str = "signal [1]"

    def predict(self, material):
        return jnp.sin(material.cubic_coefficient * jnp.asarray(self.abscissa))


def hertz_data(seed=0, noise=0.01, n=20, name="hertz"):
    rng = np.random.default_rng(seed)
    d = np.linspace(20e-6, 200e-6, n)
    F = np.asarray(hertz_force(d, E_TRUE, NU_TRUE, RADIUS))
    sig = noise * F.max() * np.ones(n)
    return HertzCurve(name, d, F + sig * rng.normal(size=n), sig)


def compression_data(seed=1, n=10):
    rng = np.random.default_rng(seed)
    eps = np.linspace(0.01, 0.1, n)
    x = np.concatenate([eps, eps])
    clean = np.concatenate([E_TRUE * eps, -NU_TRUE * eps])
    sig = np.concatenate([np.full(n, 5.0), np.full(n, 1e-3)])
    return CompressionToy("compression", x, clean + sig * rng.normal(size=2 * n), sig)


def stress_strain_data(seed=2, n=25, noise=20.0, outliers=()):
    rng = np.random.default_rng(seed)
    eps = np.linspace(0.01, 0.4, n)
    s = E_TRUE * (eps + B_TRUE * eps**3)
    obs = s + noise * rng.normal(size=n)
    for i in outliers:
        obs[i] += 40 * noise
    return StressStrain("stress_strain", eps, obs, np.full(n, noise))


P_E_NU = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.5)})
P_E_B = MaterialParameterization(("youngs_modulus", "cubic_coefficient"))
START = Material(2e3, 0.3)


def no_identifiability_warnings():
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error", IdentifiabilityWarning)
    return ctx


# ------------------------------------------------------------------ protocol and gradient
def test_toy_scenarios_follow_the_protocol():
    assert isinstance(hertz_data(), Scenario)
    assert isinstance(compression_data(), Scenario)


@pytest.mark.parametrize("loss", ["linear", "soft_l1", "huber"])
def test_loss_gradient_matches_central_differences(loss):
    problem = FitProblem([hertz_data(), compression_data()], P_E_NU, START, loss=loss, f_scale=2.0)
    grad = jax.jit(jax.grad(problem.loss))
    loss_fn = jax.jit(problem.loss)
    for u in (jnp.array([0.9, 0.7]), jnp.array([1.7, 1.4])):
        g = np.asarray(grad(u))
        fd = np.zeros(2)
        for i in range(2):
            h = 1e-5
            e = np.zeros(2)
            e[i] = h
            fd[i] = (float(loss_fn(u + e)) - float(loss_fn(u - e))) / (2 * h)
        np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_robust_loss_definition():
    """0.5 f^2 sum rho((r/f)^2) with the scipy rho functions."""
    sc = hertz_data(noise=0.01)
    for loss, rho in {
        "soft_l1": lambda z: 2 * (np.sqrt(1 + z) - 1),
        "huber": lambda z: np.where(z <= 1, z, 2 * np.sqrt(z) - 1),
    }.items():
        f = 0.5
        problem = FitProblem(sc, P_E_NU, START, loss=loss, f_scale=f)
        linear = FitProblem(sc, P_E_NU, START)
        u = linear.parameterization.pack(Material(4e3, 0.4))
        r = np.asarray(linear.residuals(u))
        expected = 0.5 * f**2 * np.sum(rho((r / f) ** 2))
        np.testing.assert_allclose(float(problem.loss(u)), expected, rtol=1e-12)


# ------------------------------------------------------------------ shared fits (compiled once per module)
@pytest.fixture(scope="module")
def joint_fit():
    """E and nu from a Hertz curve plus a compression test with lateral strain, 3 starts."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fit([hertz_data(), compression_data()], P_E_NU, START, starts=3)
    return res, [w for w in caught if issubclass(w.category, IdentifiabilityWarning)]


@pytest.fixture(scope="module")
def stress_strain_fit():
    return fit(stress_strain_data(), P_E_B, Material(2e3, 0.3), method="gauss_newton")


@pytest.fixture(scope="module")
def hertz_only_fit():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fit(hertz_data(), P_E_NU, START)
    return res, [w for w in caught if issubclass(w.category, IdentifiabilityWarning)]


# ------------------------------------------------------------------ recovery and uncertainty
def test_joint_fit_recovers_e_and_nu_with_consistent_errors_and_one_compilation(joint_fit):
    res, caught = joint_fit
    hz = hertz_data()
    assert caught == []  # well posed: no identifiability warning
    assert res.converged, res.reason
    assert res.compilations == 1  # one trace of the step function for the whole loop
    assert res.steps > 3
    assert res.warnings == () and res.unidentified == ()
    E, nu = res.values["youngs_modulus"], res.values["poisson_ratio"]
    seE, senu = res.standard_errors["youngs_modulus"], res.standard_errors["poisson_ratio"]
    assert abs(E - E_TRUE) / E_TRUE < 0.02 and abs(nu - NU_TRUE) < 0.01
    assert abs(E - E_TRUE) < 3 * seE and abs(nu - NU_TRUE) < 3 * senu
    assert res.units == {"youngs_modulus": "Pa", "poisson_ratio": "1"}
    assert res.material.youngs_modulus == pytest.approx(E)
    # covariance, correlation and the standard errors agree
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance)), [seE, senu], rtol=1e-12)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0)
    assert np.allclose(res.correlation, res.correlation.T)
    # the Jacobian is w.r.t. physical parameters: dF/dE of Hertz = F/E / sigma
    np.testing.assert_allclose(res.jacobian[:20, 0], np.asarray(hz.predict(res.material)) / E / hz.sigma, rtol=1e-8)
    # s^2 = SSE/(n-p)
    n, p = 40, 2
    assert res.dof == n - p and res.residual_variance == pytest.approx(2 * res.loss / (n - p))
    # per-scenario outputs
    assert set(res.predictions) == {"hertz", "compression"}
    np.testing.assert_allclose(res.residuals["hertz"], (res.predictions["hertz"] - hz.observed) / hz.sigma)
    assert res.loss_history.shape == (res.steps + 1, 3)
    # all three starts reach the same optimum here
    np.testing.assert_allclose(res.start_losses, res.loss, rtol=1e-8)


def test_covariance_equals_the_exact_linear_regression_result(stress_strain_fit):
    """sigma = E eps + c eps^3 is linear in (E, c = E b): its least-squares estimate and
    covariance s^2 (X^T X)^-1 are exact; the fit's (E, b) and Gauss-Newton covariance must map
    onto them (delta method exact for a reparameterisation at the optimum)."""
    res, sc = stress_strain_fit, stress_strain_data()
    eps, w = sc.abscissa, 1.0 / sc.sigma
    X = np.stack([eps, eps**3], axis=1) * w[:, None]
    y = sc.observed * w
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    sse = np.sum((X @ beta - y) ** 2)
    cov_lin = sse / (eps.size - 2) * np.linalg.inv(X.T @ X)
    E, b = res.values["youngs_modulus"], res.values["cubic_coefficient"]
    np.testing.assert_allclose([E, E * b], beta, rtol=1e-7)
    # (E, c) = g(E, b): dg = [[1, 0], [b, E]]  ->  cov_lin = dg cov dg^T
    dg = np.array([[1.0, 0.0], [b, E]])
    np.testing.assert_allclose(dg @ res.covariance @ dg.T, cov_lin, rtol=1e-6)
    assert abs(E - E_TRUE) < 3 * res.standard_errors["youngs_modulus"]
    assert abs(b - B_TRUE) < 3 * res.standard_errors["cubic_coefficient"]


def test_absolute_sigma_drops_s2(stress_strain_fit):
    res = stress_strain_fit
    a = parameter_statistics(res.jacobian, list(res.values.values()), res.fields, loss=res.loss, absolute_sigma=True)
    b = parameter_statistics(res.jacobian, list(res.values.values()), res.fields, loss=res.loss, absolute_sigma=False)
    np.testing.assert_allclose(b["covariance"], res.covariance, rtol=1e-12)
    np.testing.assert_allclose(b["covariance"], a["covariance"] * res.residual_variance, rtol=1e-10)
    np.testing.assert_allclose(a["covariance"], np.linalg.inv(res.jacobian.T @ res.jacobian), rtol=1e-8)


@pytest.mark.parametrize("method", ["adam", "lbfgs"])
def test_optax_methods_reach_the_least_squares_optimum(method, stress_strain_fit, monkeypatch):
    import difftissue.fit.engine as F

    # a fresh engine cache (the module's restored afterwards): the toy curves share programs
    # across tests, and "one compilation" is the claim of a fit that compiles its own
    monkeypatch.setattr(F, "_ENGINE_CACHE", {})
    sc = stress_strain_data()
    ref = stress_strain_fit
    kw = {"max_steps": 1500, "learning_rate": 0.05} if method == "adam" else {"max_steps": 200}
    res = fit(sc, P_E_B, Material(2e3, 0.3), method=method, **kw)
    assert res.compilations == 1
    tol = 1e-3 if method == "adam" else 1e-6
    assert res.values["youngs_modulus"] == pytest.approx(ref.values["youngs_modulus"], rel=tol)
    assert res.values["cubic_coefficient"] == pytest.approx(ref.values["cubic_coefficient"], rel=tol)


def test_robust_loss_resists_outliers():
    sc = stress_strain_data(outliers=(3, 11, 19))
    plain = fit(sc, P_E_B, Material(2e3, 0.3))
    robust = fit(sc, P_E_B, Material(2e3, 0.3), loss="soft_l1", f_scale=2.0)
    err = lambda r: abs(r.values["youngs_modulus"] - E_TRUE) / E_TRUE  # noqa: E731
    assert err(robust) < 0.03 and err(plain) > 5 * err(robust)


# ------------------------------------------------------------------ identifiability
def test_single_hertz_curve_does_not_determine_poisson_ratio(hertz_only_fit):
    res, caught = hertz_only_fit
    assert any("poisson_ratio" in str(w.message) for w in caught)
    assert "poisson_ratio" in res.unidentified
    assert any("poisson_ratio" in w for w in res.warnings)
    assert not np.isfinite(res.standard_errors["poisson_ratio"]) or res.condition_number > 1e8
    # what the curve does determine: the indentation modulus E/(1-nu^2)
    estar = res.values["youngs_modulus"] / (1 - res.values["poisson_ratio"] ** 2)
    assert estar == pytest.approx(E_TRUE / (1 - NU_TRUE**2), rel=0.02)


def test_strongly_correlated_parameters_are_named():
    """E and b from strains below 1 %: the cubic term is invisible -> b is not determined."""
    rng = np.random.default_rng(5)
    eps = np.linspace(1e-4, 0.01, 15)
    sc = StressStrain("small", eps, E_TRUE * eps + 0.05 * rng.normal(size=15), np.full(15, 0.05))
    with pytest.warns(IdentifiabilityWarning, match="cubic_coefficient"):
        res = fit(sc, P_E_B, Material(2e3, 0.3), method="gauss_newton")
    assert "cubic_coefficient" in res.unidentified
    assert "youngs_modulus" not in [f for f in res.unidentified if f != "cubic_coefficient"] or abs(res.correlation[0, 1]) > 0.99


# ------------------------------------------------------------------ multi-start
def test_multistart_picks_the_best_start_and_draws_deterministically(monkeypatch):
    import difftissue.fit.engine as F

    monkeypatch.setattr(F, "_ENGINE_CACHE", {})  # "one compilation": whatever ran before
    t = np.linspace(0, 3, 40)
    sc = Oscillation("osc", t, np.sin(3.0 * t), np.full(40, 0.05))
    param = MaterialParameterization(("cubic_coefficient",))
    starts = [Material(1.0, 0.3, cubic_coefficient=b) for b in (0.3, 6.5, 2.6, 9.0)]
    res = fit(sc, param, starts[0], starts=starts)
    assert res.compilations == 1
    assert res.start_losses.max() > 100 * res.start_losses.min()  # some starts end in local minima
    assert res.best_start == int(np.argmin(res.start_losses)) == 2
    assert res.values["cubic_coefficient"] == pytest.approx(3.0, rel=1e-6)
    # integer starts: drawn around the initial vector with a seed, reproducibly
    a = fit(sc, param, starts[0], starts=4, seed=7, max_steps=0)
    b = fit(sc, param, starts[0], starts=4, seed=7, max_steps=0)
    c = fit(sc, param, starts[0], starts=4, seed=8, max_steps=0)
    np.testing.assert_array_equal(a.start_values, b.start_values)
    assert a.start_values[0, 0] == pytest.approx(0.3)
    assert not np.allclose(a.start_values, c.start_values)


# ------------------------------------------------------------------ checkpoint / resume
class Interrupt:
    def __init__(self, at):
        self.at = at

    def __call__(self, info):
        if info.step == self.at:
            raise KeyboardInterrupt


@pytest.mark.parametrize("method, loss", [("levenberg_marquardt", "linear"), ("gauss_newton", "soft_l1")])
def test_the_final_evaluation_from_the_solver_state_equals_a_fresh_one(method, loss, monkeypatch):
    """Optimistix fits take the final loss, Jacobian and predictions from the solver's state (no
    second compilation of the forward model); they must equal a fresh evaluation at the result."""
    import difftissue.fit.engine as F

    scs = [hertz_data(), compression_data()]
    calls = []
    original = F.Engine.evaluate
    monkeypatch.setattr(F.Engine, "evaluate", lambda self, U, data: calls.append(1) or original(self, U, data))
    monkeypatch.setattr(F, "_ENGINE_CACHE", {})  # a fresh engine (the module's cached ones kept for the other tests)
    res = fit(scs, P_E_NU, START, method=method, loss=loss, starts=2)
    assert res.converged
    assert not calls  # the evaluation program was never traced
    problem = FitProblem(scs, P_E_NU, START, loss=loss)
    values, lossv, J, preds = jax.jit(lambda U: F.Engine(problem, method, rtol=1e-8, atol=1e-10, learning_rate=1e-3, jac="fwd").evaluate(U, problem.data()))(jnp.asarray(res.unconstrained)[None])
    assert float(lossv[0]) == pytest.approx(res.loss, rel=1e-12)
    np.testing.assert_allclose(res.jacobian, np.asarray(J[0]), rtol=1e-10, atol=1e-12 * np.abs(res.jacobian).max())
    for name, p in zip(problem.names, preds):
        np.testing.assert_allclose(np.asarray(res.predictions[name]), np.asarray(p[0]), rtol=1e-12)
    assert res.loss_history[0, 0] == pytest.approx(float(problem.loss(jnp.asarray(_start_u(problem, START)))), rel=1e-12)


def _start_u(problem, material):
    return problem.parameterization.pack(material)


def test_a_saturated_transform_falls_back_to_a_fresh_evaluation():
    """At a bound where a transform's derivative is exactly 0 (nu's logistic at u = 60) the
    Jacobian in the physical values cannot be recovered from the solver's: the state path
    reports not ok and :func:`fit` evaluates afresh."""
    import difftissue.fit.engine as F

    problem = FitProblem([hertz_data(), compression_data()], P_E_NU, START)
    engine = F.Engine(problem, "levenberg_marquardt", rtol=1e-8, atol=1e-10, learning_rate=1e-3, jac="fwd")
    data = problem.data()
    U = jnp.stack([jnp.asarray(_start_u(problem, START)), jnp.asarray(_start_u(problem, START))])
    dyn = engine.init(U, data)
    U1, dyn1, *_ = engine.make_step()(U, dyn, jnp.zeros(2, dtype=bool), data)
    *_, ok = engine.make_final()(U1, dyn1, data)
    assert np.all(np.asarray(ok))
    *_, ok = engine.make_final()(U1.at[1, 1].set(60.0), dyn1, data)
    assert np.asarray(ok).tolist() == [True, False]
    *_, ok = engine.make_final()(U, dyn, data)  # the initial state holds no evaluation
    assert not np.any(np.asarray(ok))


@pytest.mark.filterwarnings("ignore::difftissue.errors.IdentifiabilityWarning", "ignore::difftissue.errors.FitQualityWarning")
def test_a_refit_with_another_method_reuses_the_evaluation_program(monkeypatch):
    """The evaluation program (values, loss, Jacobian and predictions at the start and the end of
    an Adam or L-BFGS fit) depends on the problem and ``jac``, not on the method or its options: a
    refit of the same problem with L-BFGS after Adam traces it no second time, and it evaluates
    the L-BFGS fit's own points; another ``jac`` is another program."""
    import difftissue.fit.engine as F

    traced = []
    original = F.Engine.evaluate
    monkeypatch.setattr(F.Engine, "evaluate", lambda self, U, data: traced.append((self.method, self.jac)) or original(self, U, data))
    monkeypatch.setattr(F, "_ENGINE_CACHE", {})
    scs = [hertz_data(), compression_data()]
    a = fit(scs, P_E_NU, START, method="adam", learning_rate=0.05, max_steps=3)
    b = fit(scs, P_E_NU, START, method="lbfgs", max_steps=3)
    assert traced == [("adam", "fwd")]
    problem = FitProblem(scs, P_E_NU, START)
    assert b.loss_history[0, 0] == a.loss_history[0, 0] == pytest.approx(float(problem.loss(jnp.asarray(_start_u(problem, START)))), rel=1e-12)
    assert not np.allclose(b.unconstrained, a.unconstrained)
    assert b.loss == pytest.approx(float(problem.loss(jnp.asarray(b.unconstrained))), rel=1e-12)
    fit(scs, P_E_NU, START, method="lbfgs", max_steps=3, jac="bwd")
    assert traced == [("adam", "fwd"), ("lbfgs", "bwd")]


def test_interrupted_fit_resumes_to_the_same_optimum(tmp_path, joint_fit):
    scs = [hertz_data(), compression_data()]
    ref = joint_fit[0]  # the same problem (3 starts), uninterrupted
    ckpt = tmp_path / "fit.npz"
    with pytest.raises(KeyboardInterrupt):
        fit(scs, P_E_NU, START, starts=3, checkpoint=ckpt, checkpoint_every=100, callback=Interrupt(4))
    assert ckpt.is_file() and not list(tmp_path.glob(".fit.tmp-*"))
    res = fit(scs, P_E_NU, START, starts=3, checkpoint=ckpt, resume=True)
    assert res.resumed_from == 4
    assert res.compilations == 0  # same scenarios and options: the step compiled before is reused
    assert res.steps == ref.steps  # step count continues; LM state restored -> same path
    for f in P_E_NU.fields:
        assert res.values[f] == pytest.approx(ref.values[f], rel=1e-6)
    np.testing.assert_allclose(res.loss_history, ref.loss_history, rtol=1e-6)
    # a finished checkpoint without resume=True is refused; with resume it is a no-op
    with pytest.raises(CheckpointError, match="resume=True"):
        fit(scs, P_E_NU, START, starts=3, checkpoint=ckpt)


def test_adam_resume_restores_moments(tmp_path):
    sc = stress_strain_data()
    ref = fit(sc, P_E_B, Material(2e3, 0.3), method="adam", max_steps=60)
    ckpt = tmp_path / "adam.npz"
    first = fit(sc, P_E_B, Material(2e3, 0.3), method="adam", max_steps=25, checkpoint=ckpt, checkpoint_every=5, progress=True)
    assert first.steps == 25 and not first.converged and first.reason == "max_steps (25) reached"
    res = fit(sc, P_E_B, Material(2e3, 0.3), method="adam", max_steps=60, checkpoint=ckpt, resume=True)
    assert res.resumed_from == 25 and res.steps == 60
    np.testing.assert_allclose(res.unconstrained, ref.unconstrained, rtol=1e-10)
    # a callback returning True stops the fit
    seen = []
    with pytest.warns(IdentifiabilityWarning, match="without converging"):  # 3 steps: far from the optimum
        stopped = fit(sc, P_E_B, Material(2e3, 0.3), method="adam", max_steps=60, callback=lambda info: seen.append(info.step) or info.step == 3)
    assert stopped.steps == 3 and stopped.reason == "stopped by callback" and seen == [1, 2, 3]


def test_resume_refuses_a_checkpoint_of_another_problem(tmp_path):
    ckpt = tmp_path / "c.npz"
    with pytest.warns(IdentifiabilityWarning):
        fit(hertz_data(seed=0), P_E_NU, START, checkpoint=ckpt, max_steps=0)  # writes the checkpoint
    with pytest.raises(CheckpointMismatchError, match="observed data"):
        fit(hertz_data(seed=1), P_E_NU, START, checkpoint=ckpt, resume=True)
    with pytest.raises(CheckpointMismatchError, match="method"):
        fit(hertz_data(seed=0), P_E_NU, START, method="gauss_newton", checkpoint=ckpt, resume=True)
    with pytest.raises(CheckpointMismatchError, match="fields"):
        fit(hertz_data(seed=0), MaterialParameterization(("youngs_modulus",)), START, checkpoint=ckpt, resume=True)


# ------------------------------------------------------------------ bad input
def test_bad_options_fail_clearly():
    sc = hertz_data()
    with pytest.raises(FitError, match="unknown method 'newton'"):
        fit(sc, P_E_NU, START, method="newton")
    with pytest.raises(FitError, match="unknown loss"):
        fit(sc, P_E_NU, START, loss="cauchy")
    with pytest.raises(FitError, match="sigma"):
        fit(HertzCurve("bad", sc.abscissa, sc.observed, np.zeros_like(sc.sigma)), P_E_NU, START)
    with pytest.raises(FitError, match="unique"):
        fit([sc, sc], P_E_NU, START)
    with pytest.raises(FitError, match="checkpoint"):
        fit(sc, P_E_NU, START, resume=True)


# ------------------------------------------------------------------ outputs
PNG = b"\x89PNG\r\n\x1a\n"


def test_write_fit_outputs(tmp_path, joint_fit):
    res = joint_fit[0]
    data = tmp_path / "curve.csv"
    data.write_text("depth,force\n1,2\n")
    cfg = tmp_path / "fit.toml"
    cfg.write_text('[fit]\nmethod = "levenberg_marquardt"\n')
    out = tmp_path / "out"
    paths = write_fit_outputs(res, out, config=cfg, data_files=[data], model="hertz")
    assert sorted(p.name for p in out.iterdir()) == ["fit.json", "fit.png", "loss.png", "material.json", "report.md"]
    card = json.loads((out / "material.json").read_text())
    assert card["card_version"] == 1 and card["model"] == "hertz"
    assert card["parameters"]["youngs_modulus"]["value"] == pytest.approx(res.values["youngs_modulus"])
    doc = json.loads((out / "fit.json").read_text())
    E = doc["parameters"]["youngs_modulus"]
    assert E["unit"] == "Pa" and E["value"] == pytest.approx(res.values["youngs_modulus"])
    assert E["standard_error"] == pytest.approx(res.standard_errors["youngs_modulus"])
    assert doc["parameters"]["poisson_ratio"]["unit"] == "1"
    assert doc["correlation"]["fields"] == ["youngs_modulus", "poisson_ratio"]
    assert np.allclose(doc["correlation"]["matrix"], res.correlation)
    assert doc["loss"] == pytest.approx(res.loss) and doc["converged"] is True
    assert doc["model"] == "hertz" and [s["name"] for s in doc["scenarios"]] == ["hertz", "compression"]
    import hashlib

    # no host directories (issue 16): an absolute data path without a config folder is stored by name
    assert doc["data_files"] == [{"path": data.name, "sha256": hashlib.sha256(data.read_bytes()).hexdigest()}]
    assert {"difftissue", "jax", "jaxlib", "numpy", "equinox", "optimistix", "optax"} <= set(doc["versions"])
    assert doc["config"]["content"] == {"fit": {"method": "levenberg_marquardt"}}
    for name in ("fit.png", "loss.png"):
        blob = paths[name].read_bytes()
        assert blob.startswith(PNG) and len(blob) > 5000
    report = (out / "report.md").read_text()
    assert "| youngs_modulus |" in report and "Pa" in report and "## Correlations" in report
    # refusal to overwrite, naming the file; force=True overwrites
    with pytest.raises(OutputExistsError, match=re.escape(str(out / "fit.json"))):
        write_fit_outputs(res, out)
    write_fit_outputs(res, out, force=True, config={"note": "second"})
    assert json.loads((out / "fit.json").read_text())["config"] == {"note": "second"}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_outputs_of_an_unidentified_fit_are_strict_json(tmp_path, hertz_only_fit):
    res = hertz_only_fit[0]
    write_fit_outputs(res, tmp_path / "o")
    text = (tmp_path / "o" / "fit.json").read_text()
    assert "Infinity" not in text and "NaN" not in text
    doc = json.loads(text)
    assert doc["unidentified"] and "poisson_ratio" in doc["unidentified"]
    assert "poisson_ratio" in (tmp_path / "o" / "report.md").read_text().split("## Warnings")[1]


# ------------------------------------------------------------------ docs
def test_docs_example_runs(tmp_path, monkeypatch):
    from docblocks import exec_blocks, python_blocks

    assert python_blocks("fitting.md")
    monkeypatch.chdir(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        print(exec_blocks("fitting.md"), end="")
    assert (tmp_path / "fit-out" / "fit.json").is_file()


def test_forward_jacobian_wrapper_has_the_derivatives_of_the_function():
    """``_with_forward_jacobian`` (the Jacobian by jacfwd inside a custom JVP) changes what a
    linearisation stores, not the values or derivatives: JVP, VJP and linearize against the
    plain function, and check_grads (forward and reverse) against finite differences."""
    from jax.test_util import check_grads

    from difftissue.fit.engine import _with_forward_jacobian

    def f(u):
        return jnp.sin(u[0]) * jnp.exp(u[1]) + u ** 3, (u[0] * u[1] ** 2, jnp.cos(u))

    g = _with_forward_jacobian(f)
    u, t = jnp.array([0.3, -0.7]), jnp.array([1.1, 0.4])
    np.testing.assert_allclose(g(u)[0], f(u)[0], rtol=0)
    for a, b in zip(jax.tree_util.tree_leaves(jax.jvp(g, (u,), (t,))), jax.tree_util.tree_leaves(jax.jvp(f, (u,), (t,)))):
        np.testing.assert_allclose(a, b, rtol=1e-14)
    np.testing.assert_allclose(jax.jacrev(lambda v: g(v)[0])(u), jax.jacfwd(lambda v: f(v)[0])(u), rtol=1e-14)
    _, lin = jax.linearize(lambda v: g(v)[0], u)
    np.testing.assert_allclose(lin(t), jax.jvp(lambda v: f(v)[0], (u,), (t,))[1], rtol=1e-14)
    check_grads(lambda v: g(v)[0], (u,), order=1, modes=("fwd", "rev"))
    check_grads(lambda v: g(v)[1][1], (u,), order=1, modes=("fwd", "rev"))


# ------------------------------------------------------------------ quality gates (issue 17)
def test_runs_test_and_autocorrelation_tell_waves_from_noise():
    from difftissue.fit import lag1_autocorrelation, runs_test

    rng = np.random.default_rng(0)
    noise = rng.normal(size=200)
    wave = np.sin(np.linspace(0, 6 * np.pi, 200))
    assert abs(lag1_autocorrelation(noise)) < 0.2 and runs_test(noise)[2] > 0.01
    runs, expected, p = runs_test(wave)
    assert lag1_autocorrelation(wave) > 0.9 and runs == 6 and expected > 90 and p < 1e-10
    assert runs_test(np.array([1.0, -1.0, 1.0, -1.0]))[0] == 4


def test_a_straight_line_through_a_curve_is_flagged_systematic():
    """E only (b = 0 fixed) on a cubic-stiffening curve: converged, but the residuals are a wave."""
    from difftissue.errors import FitQualityWarning

    data = stress_strain_data()
    with pytest.warns(FitQualityWarning, match="systematic residuals"):
        r = fit(data, MaterialParameterization(("youngs_modulus",)), Material(2e3, 0.3))
    q = r.quality
    assert r.converged and q.usable and q.verdict == "warnings"
    names = {f.name for f in q.flags}
    assert {"systematic_residuals", "poor_fit"} <= names
    st = q.scenarios["stress_strain"]
    assert st["lag1_autocorrelation"] > 0.5 and st["runs_p"] < 0.01 and st["rms"] > 3


def test_a_good_fit_raises_no_quality_flag():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = fit(stress_strain_data(), P_E_B, Material(2e3, 0.3))
    assert r.quality.verdict == "ok" and r.quality.flags == () and r.quality.summary() == "ok"


def test_unusable_fits_are_flagged_as_errors():
    """A bound that excludes the optimum, an E outside the plausible range, and max_steps = 1."""
    from difftissue.fit import assess_quality

    data = stress_strain_data()
    with pytest.warns(Warning):
        at_bound = fit(data, MaterialParameterization(("youngs_modulus", "cubic_coefficient"), {"cubic_coefficient": ScaledLogit(-1.0, 1.0)}), Material(2e3, 0.3))
    flags = {f.name: f for f in at_bound.quality.flags}
    assert not at_bound.quality.usable and flags["at_bound"].subject == "cubic_coefficient" and flags["at_bound"].numbers["side"] == "upper"
    with pytest.warns(Warning):
        stopped = fit(data, P_E_B, Material(2e3, 0.3), max_steps=1)
    assert "not_converged" in {f.name for f in stopped.quality.errors}
    good = fit(data, P_E_B, Material(2e3, 0.3))
    absurd = assess_quality(good, plausible={"youngs_modulus": (1e6, 1e9)})
    assert [f.name for f in absurd.errors] == ["implausible_value"] and "1e+06" in absurd.errors[0].message
    assert assess_quality(good, plausible={"youngs_modulus": (1.0, 1e4)}).usable


def test_quality_is_written_to_fit_json_and_report(tmp_path):
    data = stress_strain_data()
    with pytest.warns(Warning):
        r = fit(data, MaterialParameterization(("youngs_modulus",)), Material(2e3, 0.3))
    write_fit_outputs(r, tmp_path)
    rec = json.loads((tmp_path / "fit.json").read_text())
    assert rec["quality"]["verdict"] == "warnings" and rec["quality"]["usable"] is True
    assert {f["name"] for f in rec["quality"]["flags"]} >= {"systematic_residuals", "poor_fit"}
    assert rec["quality"]["scenarios"]["stress_strain"]["runs_p"] < 0.01
    report = (tmp_path / "report.md").read_text()
    assert "## Quality" in report and "systematic_residuals" in report and "Usable, with warnings" in report


# ------------------------------------------------------------------ plots people read (issue 17)
def test_plot_units_are_chosen_by_magnitude():
    from difftissue.report import human_unit

    assert human_unit([4.8e-8, 1e-9], "N") == (1e-9, "nN")
    assert human_unit([1.2e-5], "m") == (1e-6, "µm")
    assert human_unit([-0.0137], "N") == (1e-3, "mN")
    assert human_unit([15840.0], "Pa") == (1e3, "kPa") and human_unit([2e6], "Pa") == (1e6, "MPa")
    assert human_unit([0.4], "-") == (0.01, "%") and human_unit([3.0], "s") == (1.0, "s")


def test_fit_plot_title_has_values_uncertainty_and_quality(tmp_path):
    from difftissue.report import _fit_title

    r = fit(stress_strain_data(), P_E_B, Material(2e3, 0.3))
    title = _fit_title(r)
    assert re.search(r"youngs_modulus = 5\.\d+ ± 0\.\d+ kPa", title) and "cubic_coefficient = " in title and "quality: ok" in title
    write_fit_outputs(r, tmp_path)
    import matplotlib.image

    assert matplotlib.image.imread(tmp_path / "fit.png").shape[0] > 500


# ------------------------------------------------------------------ bad starts and stale outputs
def test_a_start_whose_loss_is_not_finite_is_named_in_the_error():
    with pytest.raises(FitError, match=r"youngs_modulus = 1e\+308"):
        fit(hertz_data(), P_E_NU, Material(1e308, 0.45), max_steps=3)


def test_force_removes_the_specimen_files_of_an_earlier_fit(hertz_only_fit, tmp_path):
    out = tmp_path / "fit"
    out.mkdir()
    stale = out / "specimen-earlier.vtu"
    stale.write_text("a specimen of another fit")
    write_fit_outputs(hertz_only_fit[0], out, model="hertz", force=True)
    assert not stale.exists()
    assert (out / "fit.json").exists()


# ------------------------------------------------------- failed trial points, reverse mode
def _pull_scenario():
    """Mean top displacement [m] of a neo-Hookean unit cube pulled by 25 N, solved with
    max_steps = 3 and failure = "nan": the solve converges for E >= 70 Pa and fails (NaN) below
    about 50 Pa. Trial points are recorded (E, prediction)."""
    from difftissue.boundary import BoundaryConditions
    from difftissue.mesh import block
    from difftissue.models import make_model
    from difftissue.scenarios import SolverOptions, _solve

    mesh = block(1.0, 1)
    model = make_model(mesh, "fem_neo_hookean")
    top = np.asarray(mesh.points)[:, 2] == 1.0
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).add_force(mesh, {"face": "z-max"}, (0.0, 0.0, 25.0))
    opts = SolverOptions(max_steps=3, failure="nan", linear_solver="dense")
    seen = []

    @dataclass(frozen=True, eq=False)
    class Pull:
        name: str
        abscissa: np.ndarray
        observed: np.ndarray
        sigma: np.ndarray
        x_label: str = "force [N]"
        y_label: str = "displacement [m]"

        def predict(self, material):
            u = jnp.mean(_solve(model, material, bc, None, opts).displacement[top, 2])
            jax.debug.callback(lambda E, v: seen.append((float(E), float(v))), material.youngs_modulus, u)
            return u[None]

    probe = Pull("probe", np.array([25.0]), np.zeros(1), np.ones(1))
    # jitted: one program instead of the solve's operations dispatched (compiled) one by one
    observed = np.asarray(jax.jit(lambda E: probe.predict(Material(E, 0.3)))(150.0))
    return Pull("pull", np.array([25.0]), observed, 1e-3 * np.ones(1)), seen


@pytest.fixture(scope="module")
def pull():
    """One pull scenario for the four reverse-mode cases, one reverse-mode ``SeparatelyCompiled``
    of it, and its prediction and gradient at a failing trial point: its solve, gradient and
    separately compiled programs are compiled once for the module (the cases clear the recorded
    trial points themselves)."""
    from difftissue.config import SeparatelyCompiled

    sc, seen = _pull_scenario()
    separately_compiled = SeparatelyCompiled(sc, mode="reverse")
    # The prediction and its gradient at E = 40 Pa, in the failing region, evaluated once for
    # the four cases by the separately compiled prediction and vector-Jacobian programs of the
    # scenario (the programs the separate=True cases run: no program compiled for the premise
    # alone). They are NaN, not an exception: SeparatelyCompiled records every exception of an
    # evaluation in ``failures``.
    premise = jax.jit(jax.value_and_grad(lambda E: separately_compiled.predict(Material(E, 0.3))[0]))(40.0)
    assert separately_compiled.failures == []
    return sc, seen, separately_compiled, np.array([float(premise[0]), float(premise[1])])


@pytest.mark.filterwarnings("ignore::difftissue.errors.IdentifiabilityWarning", "ignore::difftissue.errors.FitQualityWarning")
@pytest.mark.parametrize("method,separate", [("adam", False), ("adam", True), ("lbfgs", False), ("lbfgs", True)])
def test_reverse_mode_fit_rejects_a_failed_trial_point(method, separate, pull):
    """A trial point whose static solve fails gives a NaN loss and gradient (failure="nan");
    Adam halves the step, L-BFGS's line search shortens it: the fit continues to the optimum
    instead of stopping with a non-finite loss (Adam did) or raising."""
    sc, seen, separately_compiled, premise = pull
    assert np.isnan(premise).all()  # the premise: a failing region (value and gradient)
    seen.clear()
    kw = {"learning_rate": 1.5, "max_steps": 300} if method == "adam" else {"max_steps": 100}
    target = separately_compiled if separate else sc
    # Adam's first step is learning_rate in log E: 200 exp(-1.5) = 45 Pa, a failing trial point.
    res = fit(target, MaterialParameterization(("youngs_modulus",)), Material(200.0, 0.3), method=method, jac="bwd", **kw)
    failed = [E for E, v in seen if not np.isfinite(v)]
    assert failed, seen  # the fit did meet a failing trial point (L-BFGS: its line search, at E = 27 Pa)
    if method == "adam":
        assert failed and min(failed) == pytest.approx(200.0 * np.exp(-1.5), rel=1e-6), seen[:5]
    assert res.values["youngs_modulus"] == pytest.approx(150.0, rel=1e-5)
    assert np.isfinite(res.loss)


@pytest.mark.parametrize("jac", ["fwd", "bwd"])
def test_a_start_whose_solve_fails_is_reported_as_infeasible(jac, pull):
    """A start in the failing region (E = 40 Pa: the static solve fails, NaN with
    failure="nan") cannot be stepped from -- the optimiser accepts its start, there is no
    accepted point to fall back to -- so the fit says the start is infeasible (not "ended
    with a non-finite loss", which read like a failure on the way)."""
    sc, seen, _, _ = pull
    with pytest.raises(FitError, match=r"every start is infeasible: the loss at the starting point is not finite \(at youngs_modulus = 40\)"):
        fit(sc, MaterialParameterization(("youngs_modulus",)), Material(40.0, 0.3), jac=jac, max_steps=20)
