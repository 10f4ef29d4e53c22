"""What a fit returns: :class:`FitResult`, :class:`ScenarioFit` (per scenario, for plots) and
:class:`FitProgress` (what a callback sees).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from ..materials import Material
from .statistics import discretisation_line, effective_modulus_line, FitQuality


# ============================================================================ result
@dataclasses.dataclass(frozen=True)
class ScenarioFit:
    """Data and model of one scenario at the fitted material (SI units).

    ``residual`` is the scaled residual ``(predicted - observed) / sigma`` [-].
    """

    name: str
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    predicted: np.ndarray
    residual: np.ndarray
    x_label: str
    y_label: str
    #: for plots of scenarios that are not one curve: a ``fem_field``'s
    #: ``{"kind": "fem_field", "points": (nd, 3) [m], "components": (nd,), "force_components": "z"}``
    layout: dict | None = None


def plot_layout(scenario) -> dict | None:
    """The :attr:`ScenarioFit.layout` of a scenario (unwrapping a separately compiled one)."""
    sc = getattr(scenario, "inner", scenario)
    dofs = getattr(sc, "observe_dofs", None)
    model = getattr(sc, "model", None)
    if dofs is None or getattr(model, "rest_points", None) is None:
        return None
    dofs = np.asarray(dofs)
    mask = getattr(sc, "reaction_mask", None)
    forces = "" if mask is None else "".join(c for i, c in enumerate("xyz") if np.asarray(mask)[:, i].any())
    # a reference interpolated onto the model is observed at its own nodes
    points = getattr(sc, "observed_points", None)
    points = np.asarray(model.rest_points if points is None else points)
    return {"kind": "fem_field", "points": points[dofs // 3], "components": dofs % 3, "force_components": forces}


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit` (all values SI, see :data:`UNITS`).

    Attributes:
        material: the fitted material of the best start.
        fields: names of the fitted fields, in the order of every matrix below.
        values: fitted value of each field.
        units: SI unit of each field.
        standard_errors: standard error of each field (``inf`` where the data do not determine it).
        covariance: ``(p, p)`` covariance of the physical parameters (NaN rows/columns where
            not determined).
        correlation: ``(p, p)`` correlation matrix.
        jacobian: ``(n, p)`` Jacobian of the (robustified) scaled residuals w.r.t. the physical
            parameters at the optimum.
        loss: final loss of the best start [-].
        converged: whether the best start met the tolerances (not max_steps, not a failure).
        reason: why the best start stopped, in words.
        steps: number of optimiser steps taken (counted over resumes).
        best_start: index of the best start.
        start_losses: final loss of every start, shape ``(S,)``.
        start_values: fitted values of every start, shape ``(S, p)``.
        start_converged: convergence flag of every start, shape ``(S,)``.
        loss_history: ``(steps + 1, S)`` loss of every start after each step (row 0: initial).
        predictions, residuals: per scenario name, the model prediction (unit of the data) and
            scaled residual ``(predicted - observed) / sigma`` at the best start.
        scenarios: :class:`ScenarioFit` per scenario (for plots).
        warnings: identifiability warnings (also emitted as :class:`IdentifiabilityWarning`).
        unidentified: fields named by those warnings.
        condition_number: of ``J^T J`` in scaled parameters (``inf`` when singular).
        residual_variance: ``s^2 = SSE / (n - p)`` (NaN when ``n <= p``).
        dof: ``n - p``.
        absolute_sigma: whether the covariance is ``(J^T J)^-1`` (sigma taken as absolute) instead of
            ``s^2 (J^T J)^-1``.
        method, loss_function, f_scale: the options of the fit.
        unconstrained: the optimiser's vector ``u`` of the best start.
        compilations: how many times the step function was traced (1 in a healthy fit).
        resumed_from: step count read from a checkpoint (0 for a fresh fit).
        quality: the quality gates (:func:`assess_quality`): flags such as ``at_bound``,
            ``not_converged`` (errors: the answer is unusable) or ``systematic_residuals``
            (warnings), each also emitted as :class:`~difftissue.errors.FitQualityWarning`.
        effective_modulus: for a half-space indentation fit (Hertz/Sneddon) with nu not
            fitted, what the data determine: ``E* = E / (1 - nu^2)`` [Pa] with its standard
            error, the assumed nu and the meaning (:func:`effective_modulus`); else None.
        discretisation: the mesh's share of the error of each fitted value
            (:func:`discretisation_estimate`; set by a config fit, ``fit.discretisation_check``);
            None when not checked.
    """

    material: Material
    fields: tuple[str, ...]
    values: dict[str, float]
    units: dict[str, str]
    standard_errors: dict[str, float]
    covariance: np.ndarray
    correlation: np.ndarray
    jacobian: np.ndarray
    loss: float
    converged: bool
    reason: str
    steps: int
    best_start: int
    start_losses: np.ndarray
    start_values: np.ndarray
    start_converged: np.ndarray
    loss_history: np.ndarray
    predictions: dict[str, np.ndarray]
    residuals: dict[str, np.ndarray]
    scenarios: tuple[ScenarioFit, ...]
    warnings: tuple[str, ...]
    unidentified: tuple[str, ...]
    condition_number: float
    residual_variance: float
    dof: int
    absolute_sigma: bool
    method: str
    loss_function: str
    f_scale: float
    unconstrained: np.ndarray
    compilations: int
    resumed_from: int = 0
    quality: "FitQuality | None" = None
    effective_modulus: dict | None = None
    discretisation: dict | None = None

    @property
    def scenario_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.scenarios)

    def summary(self) -> str:
        """A few lines: each parameter with its standard error and unit, loss and convergence."""
        lines = []
        for f in self.fields:
            se = self.standard_errors[f]
            unit = "" if self.units[f] == "1" else f" {self.units[f]}"
            lines.append(f"{f} = {self.values[f]:.6g} ± {se:.3g}{unit}")
        lines.append(f"loss = {self.loss:.6g}; {'converged' if self.converged else 'NOT converged'} after {self.steps} steps ({self.reason})")
        lines.extend(f"warning: {w}" for w in self.warnings)
        if self.effective_modulus is not None:
            lines.append(effective_modulus_line(self.effective_modulus))
        if self.discretisation is not None and self.discretisation.get("status") != "not applicable":
            lines.append(discretisation_line(self.discretisation))
        if self.quality is not None:
            lines.append(f"quality: {self.quality.summary()}")
        return "\n".join(lines)


class FitProgress(NamedTuple):
    """What :func:`fit` passes to its ``callback`` after every step.

    Attributes:
        step: steps taken so far.
        loss: lowest loss over the starts [-].
        losses: loss of every start, shape ``(S,)``.
        values: physical values of every start, ``{field: array (S,)}`` (SI).
        done: which starts have stopped, shape ``(S,)``.
    """

    step: int
    loss: float
    losses: np.ndarray
    values: dict[str, np.ndarray]
    done: np.ndarray
