"""Levenberg--Marquardt with Marquardt's scaling (difftissue.fit.marquardt)."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from difftissue.fit.marquardt import ScaledLevenbergMarquardt

jax.config.update("jax_enable_x64", True)

T = jnp.linspace(0.0, 1.0, 25)
TRUTH = (np.log(2.0), 0.3)  # (log amplitude, decay rate)


def _residuals(y, scale):
    """An exponential decay ``A exp(-k t)`` fitted in parameters ``y = (log A, k) / scale``:
    the same problem in other units for each ``scale``."""
    log_amplitude, rate = y * scale
    model = jnp.exp(log_amplitude - rate * T)
    data = 2.0 * jnp.exp(-0.3 * T)
    return 1e3 * (model - data)  # residuals / sigma with sigma = 1e-3


def _iterates(solver, scale, steps):
    """The accepted points of ``solver``'s first ``steps`` steps, in the physical parameters
    (the step loop of :class:`difftissue.fit.engine.Engine`: ``init`` then ``step``)."""
    y = jnp.array([0.3, 0.8]) / scale
    f_struct = jax.ShapeDtypeStruct((T.size,), jnp.float64)
    fn = lambda y, scale: (_residuals(y, scale), None)  # noqa: E731  (solvers take fn -> (out, aux))
    state = solver.init(fn, y, scale, {}, f_struct, None, frozenset())
    out = []
    for _ in range(steps):
        y, state, _ = solver.step(fn, y, scale, {}, state, frozenset())
        out.append(np.asarray(y) * np.asarray(scale))
    return np.array(out)


def test_scaled_levenberg_marquardt_finds_the_least_squares_minimum():
    sol = optx.least_squares(_residuals, ScaledLevenbergMarquardt(rtol=1e-10, atol=1e-12), jnp.array([0.3, 0.8]), args=jnp.ones(2), max_steps=100)
    np.testing.assert_allclose(sol.value, TRUTH, rtol=1e-9, atol=1e-12)


def test_scaled_levenberg_marquardt_is_invariant_to_parameter_units():
    """Marquardt's damping lambda diag(J^T J) makes the iterates independent of the units of
    the parameters; optimistix's lambda I does not (this test fails for it)."""
    scales = (jnp.ones(2), jnp.array([1e3, 1e-2]))
    scaled = [_iterates(ScaledLevenbergMarquardt(rtol=1e-12, atol=1e-14), s, 6) for s in scales]
    np.testing.assert_allclose(scaled[0], scaled[1], rtol=1e-8, atol=1e-10)
    plain = [_iterates(optx.LevenbergMarquardt(rtol=1e-12, atol=1e-14), s, 6) for s in scales]
    assert np.max(np.abs(plain[0] - plain[1])) > 1e-3


def test_scaled_descent_refuses_a_pytree_of_parameters():
    with pytest.raises(ValueError, match="flat parameter vector"):
        optx.least_squares(lambda y, a: jnp.stack([y["a"] - 1.0]), ScaledLevenbergMarquardt(rtol=1e-8, atol=1e-10), {"a": jnp.array(0.0)}, max_steps=3)
