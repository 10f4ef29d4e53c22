"""Least squares of a residual function through the fit engine (difftissue.fit.residuals):
values and standard errors against closed forms and finite-difference covariances."""

import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.errors import FitError
from difftissue.fit.residuals import ResidualProblem, least_squares
from difftissue.materials import Identity, Log


def _line_problem(x, y):
    def residual_fn(values, data):
        pred = values[0] + values[1] * data["x"]
        return pred - data["y"], pred

    return ResidualProblem(residual_fn, ("intercept", "slope"), (Identity(), Identity()), x.size, data={"x": x, "y": y})


def test_straight_line_matches_ordinary_least_squares():
    """A linear model: the values are the normal-equation solution and the standard errors the
    textbook ``sqrt(s^2 diag((X^T X)^-1))``, ``s^2 = SSE / (n - 2)`` (computed here by NumPy)."""
    rng = np.random.default_rng(4)
    x = np.linspace(0.0, 2.0, 15)
    y = 0.7 - 1.3 * x + 0.05 * rng.normal(size=x.size)
    res = least_squares(_line_problem(x, y), [0.0, 0.0])
    X = np.column_stack([np.ones_like(x), x])
    beta, sse, *_ = np.linalg.lstsq(X, y, rcond=None)
    s2 = float(sse[0]) / (x.size - 2)
    se = np.sqrt(s2 * np.diag(np.linalg.inv(X.T @ X)))
    assert res.converged and res.dof == 13
    # the engine stops once the step left is below 1e-4 standard errors (engine.STATIONARY_STEP)
    np.testing.assert_allclose([res.values["intercept"], res.values["slope"]], beta, rtol=0, atol=1e-4 * se.min())
    np.testing.assert_allclose([res.standard_errors["intercept"], res.standard_errors["slope"]], se, rtol=1e-7)
    np.testing.assert_allclose(res.residuals, X @ beta - y, atol=3e-4 * se.max())
    np.testing.assert_allclose(res.predictions, X @ beta, atol=3e-4 * se.max())
    np.testing.assert_allclose(res.loss, 0.5 * float(sse[0]), rtol=1e-8)


def _decay_problem(t, y):
    def residual_fn(values, data):
        pred = values[0] * jnp.exp(-values[1] * data["t"])
        return (pred - data["y"]) / 0.01, pred

    return ResidualProblem(residual_fn, ("amplitude", "rate"), (Log(), Log()), t.size, data={"t": t, "y": y})


def test_nonlinear_fit_standard_errors_equal_the_finite_difference_covariance():
    """``y = A exp(-k t)`` through log transforms: the Jacobian the engine uses (w.r.t. the
    physical values) equals a central-difference one in float64, and the standard errors equal
    ``sqrt(diag(s^2 (J^T J)^-1))`` with that finite-difference Jacobian."""
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 3.0, 12)
    y = 2.0 * np.exp(-0.8 * t) + 0.01 * rng.normal(size=t.size)
    problem = _decay_problem(t, y)
    res = least_squares(problem, [1.0, 1.0])
    assert res.converged
    v = np.array([res.values["amplitude"], res.values["rate"]])

    def r(values):
        return (values[0] * np.exp(-values[1] * t) - y) / 0.01

    J_fd = np.empty((t.size, 2))
    for j in range(2):
        h = 1e-6 * v[j]
        e = np.zeros(2)
        e[j] = h
        J_fd[:, j] = (r(v + e) - r(v - e)) / (2 * h)
    np.testing.assert_allclose(res.jacobian, J_fd, rtol=1e-7, atol=1e-7 * np.abs(J_fd).max())
    loss, J_engine, _ = problem.evaluate_values(jnp.asarray(v))  # the gradient check of the new function
    np.testing.assert_allclose(np.asarray(J_engine), J_fd, rtol=1e-7, atol=1e-7 * np.abs(J_fd).max())
    s2 = float(np.sum(r(v) ** 2)) / (t.size - 2)
    cov_fd = s2 * np.linalg.inv(J_fd.T @ J_fd)
    np.testing.assert_allclose([res.standard_errors["amplitude"], res.standard_errors["rate"]], np.sqrt(np.diag(cov_fd)), rtol=1e-6)
    np.testing.assert_allclose(res.covariance, cov_fd, rtol=1e-6)
    assert 0.0 < res.standard_errors["rate"] < 0.05 * v[1]
    np.testing.assert_allclose(float(loss), res.loss, rtol=1e-10)


def test_stop_ends_the_loop_and_dof_zero_gives_nan_errors():
    x = np.array([0.0, 1.0])
    y = np.array([1.0, 3.0])
    res = least_squares(_line_problem(x, y), [0.0, 0.0], stop=lambda loss: True)
    assert res.stopped and not res.converged and res.steps == 1  # stopped after the start's evaluation
    assert res.values == {"intercept": 0.0, "slope": 0.0}
    full = least_squares(_line_problem(x, y), [0.0, 0.0])
    assert full.dof == 0 and np.isnan(full.standard_errors["slope"])  # an exact fit: no scatter to estimate s^2
    np.testing.assert_allclose([full.values["intercept"], full.values["slope"]], [1.0, 2.0], rtol=1e-9)


def test_bad_problems_raise():
    with pytest.raises(FitError, match="one Transform per field"):
        ResidualProblem(lambda v, d: (v, v), ("a", "b"), (Identity(),), 2)
    with pytest.raises(FitError, match="unique"):
        ResidualProblem(lambda v, d: (v, v), ("a", "a"), (Identity(), Identity()), 2)
    bad = ResidualProblem(lambda v, d: (jnp.concatenate([v, v]), v), ("a",), (Identity(),), 2)
    with pytest.raises(FitError, match="shapes"):
        least_squares(bad, [1.0])
    with pytest.raises(FitError, match="method"):
        least_squares(_line_problem(np.zeros(3), np.zeros(3)), [0.0, 0.0], method="newton")


def test_exact_data_stop_when_the_gauss_newton_step_left_is_below_the_x_tolerance(monkeypatch):
    """Noise-free data: the loss left at the optimum is round-off, which a step can still halve,
    so the statistical stop never holds and the damped steps crawl below the x tolerance. The
    engine stops at the first accepted point whose Gauss--Newton step is below ``atol + rtol
    |u|``: fewer steps than with the statistical stop alone, at the same point to that tolerance.
    """
    from difftissue.fit import engine

    t = np.linspace(0.0, 3.0, 12)
    y = 2.0 * np.exp(-0.8 * t)
    new = least_squares(_decay_problem(t, y), [1.0, 1.0])
    assert new.converged
    np.testing.assert_allclose([new.values["amplitude"], new.values["rate"]], [2.0, 0.8], rtol=1e-8)

    statistical = engine._stationary

    def statistical_only(J, r, u, rtol, atol):
        return statistical(J, r, u, 0.0, 0.0) & jnp.any(r != 0)  # x test off: |delta| < 0 never holds

    monkeypatch.setattr(engine, "_stationary", statistical_only)
    old = least_squares(_decay_problem(t, y), [1.0, 1.0])  # a new problem: compiled again with the patch
    assert new.steps < old.steps
    u_new = np.log([new.values["amplitude"], new.values["rate"]])
    u_old = np.log([old.values["amplitude"], old.values["rate"]])
    np.testing.assert_allclose(u_new, u_old, rtol=1e-8, atol=1e-10)


def test_stationary_tests_the_gauss_newton_step_left():
    from difftissue.fit.engine import STATIONARY_STEP, _stationary

    J = jnp.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    u = jnp.array([1.0, -3.0])
    # residual in the range of J: delta = J^+ r = (1e-9, -2e-9) is all fit, none of it scatter
    r = J @ jnp.array([1e-9, -2e-9])
    assert bool(_stationary(J, r, u, 1e-8, 1e-10))  # below atol + rtol |u| = (1.01e-8, 3.01e-8)
    assert not bool(_stationary(J, 100.0 * r, u, 1e-8, 1e-10))  # 100x: above it, and no scatter
    # the same step with a little scatter orthogonal to J's range: still far above 1e-4
    # standard errors; with large scatter the step is statistically negligible
    scatter = jnp.cross(J[:, 0], J[:, 1])
    assert not bool(_stationary(J, 100.0 * r + 1e-6 * scatter, u, 1e-8, 1e-10))
    assert bool(_stationary(J, 100.0 * r + scatter, u, 0.0, 0.0))
    tiny_fit = (STATIONARY_STEP / 10) * jnp.linalg.norm(scatter) * J @ jnp.array([1.0, 0.0]) / jnp.linalg.norm(J @ jnp.array([1.0, 0.0]))
    assert bool(_stationary(J, scatter + tiny_fit, u, 0.0, 0.0))


def test_a_minimum_on_a_kink_of_the_residuals_ends_the_fit():
    """Residuals with a kink (``|b - 2|``, as a discretised contact's force has where a node
    enters contact) whose least-squares minimum sits on the kink: the one-sided Gauss--Newton
    steps (0.5 and 0.8 standard errors) point at each other, Levenberg--Marquardt creeps
    towards the kink with rejected trial steps, and neither the x tolerance (0 here) nor the
    Gauss--Newton step left ends the fit. It ends once a rejected trial step is below
    ``STATIONARY_STEP`` standard errors (76 steps without that rule, ending only when b lands on
    2 exactly; 30 with it), at the kink to within that."""
    from difftissue.fit.engine import STATIONARY_STEP

    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 12)
    g = 1.0 + t**2
    y = 1.0 + 2.0 * t - 0.02 * g + 0.01 * rng.normal(size=t.size)

    def residual_fn(values, data):
        pred = values[0] + values[1] * data["t"] + 2.0 * jnp.abs(values[1] - 2.0) * data["g"]
        return (pred - data["y"]) / 0.01, pred

    problem = ResidualProblem(residual_fn, ("a", "b"), (Identity(), Identity()), t.size, data={"t": t, "y": y, "g": g})
    res = least_squares(problem, [0.3, 2.7], max_steps=100, rtol=0.0, atol=0.0)
    assert res.converged and res.steps < 50, (res.converged, res.steps)
    assert abs(res.values["b"] - 2.0) <= STATIONARY_STEP * res.standard_errors["b"]
