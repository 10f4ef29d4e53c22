"""The fit engine's stop at the forward model's precision (FitProblem.precision_floor): on
noise-free simulated data a fit ends once its residuals are within the scenarios' stated
``prediction_rtol`` of the data, instead of spending steps on the model's round-off."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.errors import FitError
from difftissue.fit import fit
from difftissue.fit.problem import FitProblem
from difftissue.materials import Material, MaterialParameterization
from difftissue.scenarios import SolverOptions
from difftissue.solvers.static import prediction_rtol

TRUE_E = 12e3


class _RoundOffScenario:
    """A stiffening force curve ``F = E d (1 + d/d0)`` whose prediction carries a relative
    'round-off' of 3e-7 that jumps with E (as an iterative solve converged to ~1e-7 does: above
    the x tolerance of log E, so only the floor ends the fit early): noise
    of the model, not of the data. ``prediction_rtol`` says how precise the predictions are."""

    def __init__(self, prediction_rtol_value):
        self.name = "curve"
        self.abscissa = np.linspace(1e-5, 2e-4, 12)
        self.x_label, self.y_label = "depth [m]", "force [N]"
        self.prediction_rtol = prediction_rtol_value
        self.observed = np.asarray(self._clean(TRUE_E))
        self.sigma = np.full_like(self.observed, np.sqrt(np.mean(self.observed**2)))

    def _clean(self, E):
        d = jnp.asarray(self.abscissa)
        return E * d * (1.0 + d / 1e-4)

    def predict(self, material):
        E = material.youngs_modulus
        # round-off is not differentiated (the implicit tangents of a solve are clean)
        wiggle = jax.lax.stop_gradient(3e-7 * jnp.sin(1e7 * E / TRUE_E + jnp.arange(self.abscissa.size)))
        return self._clean(E) * (1.0 + wiggle)


def test_a_fit_on_noise_free_data_stops_at_the_precision_floor():
    param = MaterialParameterization(("youngs_modulus",))
    start = Material(2.0 * TRUE_E, 0.4)
    stated = fit([_RoundOffScenario(1e-6)], param, start, max_steps=40)
    silent = fit([_RoundOffScenario(0.0)], param, start, max_steps=40)
    assert stated.converged
    # the floor: |r| <= |1e-6 observed / sigma| = 1e-6 sqrt(n)
    assert np.sqrt(2.0 * stated.loss) <= 1e-6 * np.sqrt(12)
    assert stated.steps < silent.steps
    # and the point is as good as the model's precision allows
    np.testing.assert_allclose(stated.values["youngs_modulus"], TRUE_E, rtol=3e-6)


def test_the_floor_is_the_stated_precision_of_the_observed_data():
    sc = _RoundOffScenario(1e-8)
    problem = FitProblem([sc], MaterialParameterization(("youngs_modulus",)), Material(TRUE_E, 0.4))
    np.testing.assert_allclose(float(problem.precision_floor()), 1e-8 * np.linalg.norm(sc.observed / sc.sigma), rtol=1e-12)
    assert float(FitProblem([_RoundOffScenario(0.0)], MaterialParameterization(("youngs_modulus",)), Material(TRUE_E, 0.4)).precision_floor()) == 0.0
    with pytest.raises(FitError, match="prediction_rtol"):
        FitProblem([_RoundOffScenario(-1.0)], MaterialParameterization(("youngs_modulus",)), Material(TRUE_E, 0.4))


def test_simulated_scenarios_state_their_solver_precision():
    assert SolverOptions().prediction_rtol == prediction_rtol(1e-9, 1e-8) == 1e-8
    assert SolverOptions(rtol=1e-6, xtol=1e-9).prediction_rtol == 1e-6
