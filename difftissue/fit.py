"""Fitting material parameters to measured curves: weighted (robust) least squares.

The fit works on a vector ``u`` of unconstrained reals; a
:class:`~difftissue.materials.MaterialParameterization` maps it through bounded transforms to
the fitted fields of a :class:`~difftissue.materials.Material`. Each scenario (one experiment:
an indentation curve, a compression curve, a displacement field, ...) predicts its observable
from the material; the residual vector is

    r(u) = concat_s (predict_s(material(u)) - observed_s) / sigma_s        [-]

and the loss is ``0.5 * f_scale^2 * sum(rho((r / f_scale)^2))`` with ``rho(z) = z`` (linear),
``2 (sqrt(1 + z) - 1)`` (soft_l1) or the Huber function (``z`` for ``z <= 1``, else
``2 sqrt(z) - 1``) -- the definitions of ``scipy.optimize.least_squares``.

Optimisers: optimistix Levenberg--Marquardt and Gauss--Newton on the (robustified) residual
vector, optax Adam and L-BFGS on the scalar loss. All starts of a multi-start fit run batched
with ``jax.vmap`` inside ONE jitted step function; a Python loop calls it once per step, so a
progress bar can be shown and checkpoints written, without recompiling.

After the fit, a Gauss--Newton covariance of the physical parameters, standard errors,
correlations and identifiability diagnostics are computed at the best start. See
``docs/fitting.md`` for the formulas and rules.

Units: the residuals and the loss are dimensionless (residuals are divided by ``sigma``, which
carries the unit of the observable); every parameter value and standard error is in SI
(:data:`UNITS`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._io import atomic_output, sha256_file
from .errors import (
    CheckpointError,
    CheckpointMismatchError,
    FitError,
    DiscretisationWarning,
    FitQualityWarning,
    IdentifiabilityWarning,
    OutputError,
    OutputExistsError,
)
from .materials import Material, MaterialParameterization

__all__ = [
    "Scenario",
    "FitProblem",
    "FitProgress",
    "FitResult",
    "ScenarioFit",
    "fit",
    "parameter_statistics",
    "identifiability_diagnostics",
    "assess_quality",
    "discretisation_estimate",
    "with_discretisation",
    "effective_modulus",
    "FitQuality",
    "QualityFlag",
    "PLAUSIBLE",
    "write_fit_outputs",
    "package_versions",
    "UNITS",
    "METHODS",
    "LOSSES",
    "OUTPUT_FILES",
]

#: SI unit of every material field ("1" for dimensionless).
UNITS: dict[str, str] = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "cubic_coefficient": "1",
    "density": "kg/m^3",
    "pre_stretch": "1",
    "surface_tension": "N/m",
}

#: Optimisers understood by :func:`fit`.
METHODS = ("levenberg_marquardt", "gauss_newton", "adam", "lbfgs")
#: Loss functions understood by :func:`fit` (scipy.optimize.least_squares names).
LOSSES = ("linear", "soft_l1", "huber")
#: Files written by :func:`write_fit_outputs`.
OUTPUT_FILES = ("fit.json", "material.json", "fit.png", "loss.png", "report.md")

#: Floors of the parameter scale used for relative standard errors and the scaled J^T J:
#: ``scale = max(|value|, floor)``. Parameters that may sit at zero get a natural unit.
_SCALE_FLOOR = {"poisson_ratio": 0.1, "cubic_coefficient": 1.0}

#: Identifiability thresholds (see docs/fitting.md).
CONDITION_LIMIT = 1e8
RELATIVE_SE_LIMIT = 1.0
CORRELATION_LIMIT = 0.99
#: Eigenvalues of the scaled J^T J below this fraction of the largest are treated as exactly
#: zero (no information at all): the standard errors of the parameters in that direction are inf.
_SINGULAR_FRACTION = 1e-13


# ============================================================================ protocol
@runtime_checkable
class Scenario(Protocol):
    """One experiment to fit: what it measured and how the model predicts it.

    Attributes:
        name: unique name of the scenario (used in outputs and plots).
        observed: measured values, shape ``(n,)``, SI units (N, m, Pa, ...).
        sigma: measurement scale, shape ``(n,)``, same unit as ``observed``; residuals are
            divided by it (weight ``1 / sigma``). Use the noise standard deviation when known.
        abscissa: x values for plots, shape ``(n,)``, SI units (e.g. depth in m).
        x_label: axis label of ``abscissa`` including its unit, e.g. ``"depth [m]"``.
        y_label: axis label of ``observed`` including its unit, e.g. ``"force [N]"``.

    Methods:
        predict(material): model prediction, shape ``(n,)``, same unit as ``observed``. Must be
            pure, jittable and differentiable in the material's fields.
    """

    name: str
    observed: np.ndarray
    sigma: np.ndarray
    abscissa: np.ndarray
    x_label: str
    y_label: str

    def predict(self, material: Material) -> jax.Array: ...


# ============================================================================ problem
def _robust_weight(z, loss: str):
    """``sqrt(rho(z) / z)`` for the robust loss ``rho``: smooth, positive, 1 at ``z = 0``."""
    if loss == "linear":
        return jnp.ones_like(z)
    if loss == "soft_l1":
        return jnp.sqrt(2.0 / (1.0 + jnp.sqrt(1.0 + z)))
    if loss == "huber":
        z_big = jnp.where(z <= 1.0, 1.0, z)
        return jnp.where(z <= 1.0, 1.0, jnp.sqrt((2.0 * jnp.sqrt(z_big) - 1.0) / z_big))
    raise FitError(f"unknown loss {loss!r}; choose one of {LOSSES}")


class FitProblem:
    """The residuals and loss of a fit, as pure functions of the unconstrained vector ``u``.

    Args:
        scenarios: one or more objects following :class:`Scenario` (names must be unique).
        parameterization: which material fields are fitted and through which transforms.
        base: the material whose non-fitted fields (e.g. density) are kept.
        loss: ``"linear"``, ``"soft_l1"`` or ``"huber"``.
        f_scale: residual scale of the robust loss [-] (residuals are already divided by sigma,
            so ``f_scale = 3`` down-weights points more than 3 sigma off).
    """

    def __init__(self, scenarios, parameterization: MaterialParameterization, base: Material, *, loss: str = "linear", f_scale: float = 1.0):
        if not isinstance(parameterization, MaterialParameterization):
            raise FitError(f"parameterization must be a MaterialParameterization, got {type(parameterization).__name__}")
        if not isinstance(base, Material):
            raise FitError(f"the initial material must be a Material, got {type(base).__name__}")
        if loss not in LOSSES:
            raise FitError(f"unknown loss {loss!r}; choose one of {LOSSES}")
        if not (isinstance(f_scale, (int, float)) and math.isfinite(f_scale) and f_scale > 0):
            raise FitError(f"f_scale must be a finite number > 0, got {f_scale!r}")
        if isinstance(scenarios, (str, bytes)) or not isinstance(scenarios, Sequence):
            scenarios = (scenarios,)
        scenarios = tuple(scenarios)
        if not scenarios:
            raise FitError("no scenario to fit")
        names = []
        observed, sigma = [], []
        for i, sc in enumerate(scenarios):
            name = getattr(sc, "name", None)
            if not isinstance(name, str) or not name:
                raise FitError(f"scenario {i} has no name (a non-empty str attribute 'name')")
            if name in names:
                raise FitError(f"two scenarios are named {name!r}; scenario names must be unique")
            if not callable(getattr(sc, "predict", None)):
                raise FitError(f"scenario {name!r} has no predict(material) method")
            obs = np.asarray(getattr(sc, "observed", None), dtype=float)
            sig = np.asarray(getattr(sc, "sigma", None), dtype=float)
            if obs.ndim != 1 or obs.size == 0:
                raise FitError(f"scenario {name!r}: observed must be a non-empty 1-D array, got shape {obs.shape}")
            if sig.shape != obs.shape:
                raise FitError(f"scenario {name!r}: sigma has shape {sig.shape}, observed has {obs.shape}; they must match")
            if not np.all(np.isfinite(obs)):
                raise FitError(f"scenario {name!r}: observed holds {int(np.sum(~np.isfinite(obs)))} non-finite value(s)")
            if not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
                raise FitError(f"scenario {name!r}: every sigma must be finite and > 0 (same unit as observed)")
            names.append(name)
            observed.append(obs)
            sigma.append(sig)
        self.scenarios = scenarios
        self.names = tuple(names)
        self.parameterization = parameterization
        self.fields = tuple(parameterization.fields)
        self.base = base
        self.loss_name = loss
        self.f_scale = float(f_scale)
        self._observed = tuple(observed)
        self._sigma = tuple(sigma)
        self.sizes = tuple(o.size for o in observed)
        self.n_residuals = int(sum(self.sizes))
        self.n_parameters = len(self.fields)
        # Each scenario as a pytree: its measured-data leaves (``observed``, ``sigma`` of an
        # equinox-Module scenario) are passed to the compiled functions as ARGUMENTS, with the
        # problem's observed and sigma, so that one compilation serves every specimen of the
        # same structure (see :meth:`data`, :meth:`with_data`, :meth:`structure_key`).
        self._treedefs, self._leaves, dynamic = [], [], []
        for sc in scenarios:
            leaves, treedef = jax.tree_util.tree_flatten(sc)
            self._treedefs.append(treedef)
            self._leaves.append(leaves)
            data_attrs = [getattr(sc, a, None) for a in ("observed", "sigma")]
            dynamic.append(tuple(i for i, leaf in enumerate(leaves) if eqx.is_array(leaf) and any(leaf is d for d in data_attrs)))
        self._dynamic = tuple(dynamic)

    # -------------------------------------------------------------- data as arguments
    def data(self) -> dict:
        """The problem's measured data as a pytree of arrays: ``observed`` and ``sigma`` per
        scenario (SI) and each scenario's dynamic leaves. The compiled step and evaluation take
        it as an argument (:meth:`with_data` rebuilds the problem from it inside the trace)."""
        return {
            "observed": tuple(np.asarray(o) for o in self._observed),
            "sigma": tuple(np.asarray(s) for s in self._sigma),
            "leaves": tuple(tuple(np.asarray(leaves[i]) for i in dyn) for leaves, dyn in zip(self._leaves, self._dynamic)),
        }

    def with_data(self, data) -> "FitProblem":
        """A shallow copy whose observed data, sigma and scenario data leaves are ``data``
        (arrays or tracers with the structure of :meth:`data`)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._observed = tuple(data["observed"])
        new._sigma = tuple(data["sigma"])
        scenarios = []
        for sc, treedef, leaves, dyn, values in zip(self.scenarios, self._treedefs, self._leaves, self._dynamic, data["leaves"]):
            if not dyn:
                scenarios.append(sc)
                continue
            leaves = list(leaves)
            for i, v in zip(dyn, values):
                leaves[i] = v
            scenarios.append(jax.tree_util.tree_unflatten(treedef, leaves))
        new.scenarios = tuple(scenarios)
        return new

    def _with_dynamic(self, dynamic) -> "FitProblem":
        """A shallow copy passing the scenario leaves ``dynamic`` (per scenario, leaf indices
        of ``jax.tree_util.tree_flatten(scenario)``) as data instead of compiling them in."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._dynamic = tuple(tuple(sorted(d)) for d in dynamic)
        return new

    def structure_key(self) -> tuple:
        """What the compiled step depends on besides :meth:`data`: fields, transforms, fixed
        material fields, loss, scenario names, types and pytree structures, data shapes, and a
        hash of every scenario leaf that is compiled in (arrays by content; other objects, e.g.
        a scenario that is not a pytree, by identity). Two problems with equal keys can share
        one compiled step with their own data."""
        digest, comps = self.fingerprint("", 0)
        parts = [comps[k] for k in ("fields", "transforms", "fixed material fields", "scenarios", "loss")]
        parts.append(self.sizes)
        h = hashlib.sha256()
        objects = []
        for treedef, leaves, dyn in zip(self._treedefs, self._leaves, self._dynamic):
            try:
                hash(treedef)
                parts.append(treedef)
            except TypeError:  # a static field that cannot be hashed: key by the scenario itself
                objects.append(id(leaves))
            parts.append(dyn)
            for i, leaf in enumerate(leaves):
                if i in dyn:
                    a = np.asarray(leaf)
                    h.update(f"dyn{a.shape}{a.dtype}".encode())
                elif eqx.is_array(leaf) or isinstance(leaf, np.generic):
                    a = np.ascontiguousarray(leaf)
                    h.update(f"{a.shape}{a.dtype}".encode())
                    h.update(a.tobytes())
                elif leaf is None or isinstance(leaf, (bool, int, float, complex, str)):
                    h.update(repr((type(leaf).__name__, leaf)).encode())
                else:
                    objects.append(id(leaf))
                h.update(b"|")
        parts.append(h.hexdigest())
        parts.append(tuple(objects))
        return tuple(parts)

    # -------------------------------------------------------------- pure functions
    def material(self, u) -> Material:
        """The material at unconstrained ``u`` (shape ``(p,)``)."""
        return self.parameterization.unpack(u, self.base)

    def material_from_values(self, values) -> Material:
        """The material with the fitted fields set to physical ``values`` (shape ``(p,)``, SI)."""
        return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in self.fields), self.base, tuple(values[i] for i in range(self.n_parameters)))

    def predictions_of(self, material: Material) -> list[jax.Array]:
        """Each scenario's predictions (its unit), checked against the observed shapes."""
        preds = []
        for sc, obs in zip(self.scenarios, self._observed):
            pred = jnp.asarray(sc.predict(material))
            if pred.shape != obs.shape:
                raise FitError(f"scenario {sc.name!r}: predict returned shape {pred.shape}, observed has {obs.shape}")
            preds.append(pred)
        return preds

    def _scaled(self, preds) -> jax.Array:
        return jnp.concatenate([(p - obs) / sig for p, obs, sig in zip(preds, self._observed, self._sigma)])

    def scaled_residuals_of(self, material: Material) -> jax.Array:
        """``(predict - observed) / sigma`` of all scenarios, concatenated, shape ``(n,)`` [-]."""
        return self._scaled(self.predictions_of(material))

    def evaluate_values(self, values, jac: str = "fwd"):
        """Loss, Jacobian of the robustified scaled residuals with respect to the PHYSICAL
        values ``(n, p)``, and each scenario's predictions, at ``values`` (one pass: what a
        fit needs at its start and end, compiled once)."""

        def res(v):
            preds = self.predictions_of(self.material_from_values(v))
            r = self.robust(self._scaled(preds))
            return r, (r, preds)

        jac_fn = jax.jacfwd if jac == "fwd" else jax.jacrev
        J, (r, preds) = jac_fn(res, has_aux=True)(values)
        return 0.5 * jnp.sum(r * r), J, preds

    def robust(self, r) -> jax.Array:
        """Robustified residuals ``r sqrt(rho(z)/z)``, ``z = (r/f_scale)^2``: their half sum of
        squares is the loss, so Gauss--Newton methods minimise the robust loss."""
        if self.loss_name == "linear":
            return r
        z = (r / self.f_scale) ** 2
        return r * _robust_weight(z, self.loss_name)

    def residuals_and_predictions(self, u) -> tuple[jax.Array, tuple[jax.Array, ...]]:
        """``(residuals(u), predictions)``: the robustified scaled residuals and each
        scenario's predictions (in the residuals' dtype) from one forward evaluation."""
        preds = self.predictions_of(self.material(u))
        r = self.robust(self._scaled(preds))
        return r, tuple(jnp.asarray(p, dtype=r.dtype) for p in preds)

    def residuals(self, u) -> jax.Array:
        """Robustified scaled residuals at ``u``, shape ``(n,)`` [-] (plain ones for ``linear``)."""
        return self.robust(self.scaled_residuals_of(self.material(u)))

    def residuals_of_values(self, values) -> jax.Array:
        """Robustified scaled residuals as a function of the PHYSICAL fitted values (SI)."""
        return self.robust(self.scaled_residuals_of(self.material_from_values(values)))

    def loss(self, u) -> jax.Array:
        """Loss ``0.5 f_scale^2 sum rho((r/f_scale)^2)`` [-] at ``u``."""
        r = self.residuals(u)
        return 0.5 * jnp.sum(r * r)

    def values(self, u) -> dict[str, jax.Array]:
        """Physical values of the fitted fields at ``u`` (SI)."""
        return self.parameterization.values(u)

    # -------------------------------------------------------------- fingerprint
    def fingerprint(self, method: str, n_starts: int) -> tuple[str, dict[str, str]]:
        """sha256 of the problem: fields, transforms, fixed fields of the base material,
        scenario names and types, observed data and sigma, loss, method and number of starts.

        Returns ``(hexdigest, components)``; ``components`` maps each part to its own short hash
        so a mismatch can be named. The predict functions themselves cannot be hashed: a change
        of the model code with the same data and names is not detected.
        """

        def h(b: bytes) -> str:
            return hashlib.sha256(b).hexdigest()[:16]

        fixed = {f: np.asarray(getattr(self.base, f), dtype=float).tolist() for f in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch") if f not in self.fields}
        data = hashlib.sha256()
        for obs, sig in zip(self._observed, self._sigma):
            data.update(np.ascontiguousarray(obs, dtype="<f8").tobytes())
            data.update(b"|")
            data.update(np.ascontiguousarray(sig, dtype="<f8").tobytes())
            data.update(b"||")
        comps = {
            "fields": h(repr(self.fields).encode()),
            "transforms": h(repr(tuple(repr(t) for t in self.parameterization.transforms)).encode()),
            "fixed material fields": h(json.dumps(fixed, sort_keys=True).encode()),
            "scenarios": h(repr(tuple((n, type(s).__qualname__) for n, s in zip(self.names, self.scenarios))).encode()),
            "observed data and sigma": data.hexdigest()[:16],
            "loss": h(f"{self.loss_name}:{self.f_scale!r}".encode()),
            "method": h(method.encode()),
            "number of starts": h(str(int(n_starts)).encode()),
        }
        total = hashlib.sha256(json.dumps(comps, sort_keys=True).encode()).hexdigest()
        return total, comps


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


def _plot_layout(scenario) -> dict | None:
    """The :attr:`ScenarioFit.layout` of a scenario (unwrapping a separately compiled one)."""
    sc = getattr(scenario, "inner", scenario)
    dofs = getattr(sc, "observe_dofs", None)
    model = getattr(sc, "model", None)
    if dofs is None or getattr(model, "rest_points", None) is None:
        return None
    dofs = np.asarray(dofs)
    mask = getattr(sc, "reaction_mask", None)
    forces = "" if mask is None else "".join(c for i, c in enumerate("xyz") if np.asarray(mask)[:, i].any())
    return {"kind": "fem_field", "points": np.asarray(model.rest_points)[dofs // 3], "components": dofs % 3, "force_components": forces}


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


# ============================================================================ statistics
def parameter_statistics(jacobian, values, fields, *, loss: float, absolute_sigma: bool = False):
    """Gauss--Newton covariance, standard errors and correlation of physical parameters.

    Args:
        jacobian: ``(n, p)`` Jacobian of the scaled residuals w.r.t. the physical parameters.
        values: ``(p,)`` parameter values (SI), used for scaling.
        fields: names of the parameters.
        loss: final loss (``SSE = 2 loss``).
        absolute_sigma: if true, ``cov = (J^T J)^-1`` (the sigmas are the true noise levels);
            otherwise ``cov = s^2 (J^T J)^-1`` with ``s^2 = SSE / (n - p)``.

    Returns:
        dict with ``covariance``, ``correlation``, ``standard_errors`` (arrays), ``eigenvalues``,
        ``eigenvectors`` (of the scaled ``J^T J``, ascending), ``condition_number``,
        ``residual_variance``, ``dof``, ``scales`` and ``singular`` (bool per parameter).

    Computed in scaled parameters ``theta_j / scale_j`` (``scale_j = max(|theta_j|, floor)``) by
    an eigendecomposition; directions with eigenvalue below 1e-13 of the largest carry no
    information: parameters with weight there get standard error ``inf`` and NaN covariance.
    """
    J = np.asarray(jacobian, dtype=float)
    theta = np.asarray(values, dtype=float)
    n, p = J.shape
    scales = np.array([max(abs(t), _SCALE_FLOOR.get(f, 0.0)) or 1.0 for t, f in zip(theta, fields)])
    Js = J * scales
    A = Js.T @ Js
    lam, V = np.linalg.eigh(A)
    lam_max = float(lam[-1]) if p else 0.0
    if not np.all(np.isfinite(J)):
        lam = np.full(p, np.nan)
    dof = n - p
    sse = 2.0 * float(loss)
    s2 = sse / dof if dof > 0 else float("nan")
    factor = 1.0 if absolute_sigma else s2
    if lam_max <= 0 or not np.isfinite(lam_max):
        null = np.ones(p, dtype=bool)
        cond = float("inf")
    else:
        null = lam <= _SINGULAR_FRACTION * lam_max
        cond = float(lam_max / lam[0]) if lam[0] > 0 else float("inf")
    keep = ~null
    inv = (V[:, keep] / lam[keep]) @ V[:, keep].T
    cov_s = factor * inv
    singular = np.zeros(p, dtype=bool)
    if np.any(null):
        weight = np.sum(V[:, null] ** 2, axis=1)
        singular = weight > 1e-6
    cov = cov_s * np.outer(scales, scales)
    cov[singular, :] = np.nan
    cov[:, singular] = np.nan
    var = np.diag(cov).copy()
    se = np.where(singular, np.inf, np.sqrt(np.clip(var, 0.0, None)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(np.sqrt(var), np.sqrt(var))
    corr[singular, :] = np.nan
    corr[:, singular] = np.nan
    for j in range(p):
        if not singular[j]:
            corr[j, j] = 1.0
    return {
        "covariance": cov,
        "correlation": corr,
        "standard_errors": se,
        "eigenvalues": lam,
        "eigenvectors": V,
        "condition_number": cond,
        "residual_variance": s2,
        "dof": dof,
        "scales": scales,
        "singular": singular,
    }


def identifiability_diagnostics(stats: Mapping, values, fields) -> list[tuple[str, str]]:
    """Which parameters the data do not determine, and why.

    Rules (thresholds in :data:`CONDITION_LIMIT`, :data:`RELATIVE_SE_LIMIT`,
    :data:`CORRELATION_LIMIT`):

    1. ``J^T J`` in scaled parameters is singular or has condition number > 1e8: each eigen-
       direction with eigenvalue < 1e-8 of the largest names the parameters that dominate it
       (squared eigenvector component >= 0.5, else the largest), and mentions the others involved.
    2. relative standard error ``SE / max(|value|, floor)`` > 1 (100 %).
    3. ``|correlation| > 0.99`` between two parameters (both named).

    Returns a list of ``(field, message)``.
    """
    fields = tuple(fields)
    out: list[tuple[str, str]] = []
    named: set[tuple[str, str]] = set()

    def add(field, rule, message):
        if (field, rule) not in named:
            named.add((field, rule))
            out.append((field, message))

    lam = np.asarray(stats["eigenvalues"], dtype=float)
    V = np.asarray(stats["eigenvectors"], dtype=float)
    cond = float(stats["condition_number"])
    if len(fields) and (not np.isfinite(cond) or cond > CONDITION_LIMIT):
        lam_max = float(np.nanmax(lam)) if np.any(np.isfinite(lam)) else float("nan")
        cond_txt = "singular" if not np.isfinite(cond) else f"condition number {cond:.3g} > {CONDITION_LIMIT:.0e}"
        for k in range(len(fields)):
            if np.isfinite(lam_max) and lam_max > 0 and lam[k] >= lam_max / CONDITION_LIMIT:
                continue
            w = V[:, k] ** 2
            dominant = [j for j in range(len(fields)) if w[j] >= 0.5] or [int(np.argmax(w))]
            involved = [fields[j] for j in range(len(fields)) if w[j] >= 0.01 and j not in dominant]
            for j in dominant:
                also = f"; only a combination with {', '.join(involved)} is determined" if involved else ""
                add(
                    fields[j],
                    "condition",
                    f"{fields[j]} is not determined by the data: J^T J (scaled parameters) is {cond_txt}, "
                    f"along a direction dominated by {fields[j]}{also}",
                )
    se = np.asarray(stats["standard_errors"], dtype=float)
    scales = np.asarray(stats["scales"], dtype=float)
    for j, f in enumerate(fields):
        rel = se[j] / scales[j]
        if not np.isfinite(rel) or rel > RELATIVE_SE_LIMIT:
            se_txt = "infinite" if not np.isfinite(se[j]) else f"{se[j]:.3g} {_unit_text(UNITS.get(f, ''))}".strip()
            of = f"|value| = {scales[j]:.3g}" if scales[j] > _SCALE_FLOOR.get(f, 0.0) else f"the floor scale {scales[j]:g} (|value| is smaller)"
            add(f, "se", f"{f} is not determined by the data: standard error {se_txt} exceeds 100 % of {of}")
    corr = np.asarray(stats["correlation"], dtype=float)
    for i in range(len(fields)):
        for j in range(i + 1, len(fields)):
            c = corr[i, j]
            if np.isfinite(c) and abs(c) > CORRELATION_LIMIT:
                msg = f"{fields[i]} and {fields[j]} are correlated ({c:+.4f}, |rho| > {CORRELATION_LIMIT}): the data determine a combination of them, not each"
                add(fields[i], f"corr-{fields[j]}", msg)
                add(fields[j], f"corr-{fields[i]}", msg)
    return out


# ============================================================================ quality gates
#: Plausible range of a fitted field (SI) unless :func:`fit`'s ``plausible`` (config:
#: ``fit.plausible``) widens it: outside it the fit is flagged ``implausible_value`` (an error).
PLAUSIBLE: dict[str, tuple[float, float]] = {"youngs_modulus": (1.0, 1e9)}
#: rms of the scaled residuals above this is flagged ``poor_fit`` (a warning) [-].
RMS_LIMIT = 3.0
#: lag-1 autocorrelation of a scenario's residuals above this is flagged ``systematic_residuals``.
AUTOCORRELATION_LIMIT = 0.5
#: Wald--Wolfowitz runs-test p-value below this is flagged ``systematic_residuals``.
RUNS_P_LIMIT = 0.01
#: A parameter closer to a transform bound than this fraction of its range (ScaledLogit) or of
#: its scale (Log) is flagged ``at_bound`` (an error).
BOUND_FRACTION = 1e-4
#: Residual structure is judged only where the rms residual/sigma reaches this: below it the
#: model lies within the stated noise level and the residuals' pattern is numerical noise.
STRUCTURE_MIN_RMS = 0.5
#: Minimum points of a scenario for the structure tests.
STRUCTURE_MIN_POINTS = 10
#: Quality flags that make the fit's answer unusable (severity "error"; CLI exit status 3).
QUALITY_ERRORS = ("non_finite", "not_converged", "at_bound", "implausible_value")


@dataclasses.dataclass(frozen=True)
class QualityFlag:
    """One finding of :func:`assess_quality`.

    Attributes:
        name: ``non_finite``, ``not_converged``, ``at_bound``, ``implausible_value`` (errors:
            the answer is unusable), ``poor_fit``, ``systematic_residuals`` or
            ``discretisation_error`` (warnings; the last from :func:`with_discretisation`).
        severity: ``"error"`` or ``"warning"``.
        subject: the field or scenario it concerns (None for the whole fit).
        message: one line for people.
        numbers: the quantities behind it (SI units or dimensionless).
    """

    name: str
    severity: str
    subject: str | None
    message: str
    numbers: dict


@dataclasses.dataclass(frozen=True)
class FitQuality:
    """Quality gates of a fit: the flags and, per scenario, the residual statistics
    (``rms`` of residual/sigma, ``lag1_autocorrelation``, ``runs``, ``runs_expected``, ``runs_p``)."""

    flags: tuple[QualityFlag, ...]
    scenarios: dict

    @property
    def usable(self) -> bool:
        """False when a flag of severity "error" is raised."""
        return not any(f.severity == "error" for f in self.flags)

    @property
    def errors(self) -> tuple[QualityFlag, ...]:
        return tuple(f for f in self.flags if f.severity == "error")

    @property
    def verdict(self) -> str:
        """``"ok"``, ``"warnings"`` or ``"unusable"``."""
        return "unusable" if not self.usable else ("warnings" if self.flags else "ok")

    def summary(self) -> str:
        """One line: the verdict and the flag names with their subjects."""
        if not self.flags:
            return "ok"
        names = ", ".join(f.name + (f" ({f.subject})" if f.subject else "") for f in self.flags)
        return f"{self.verdict}: {names}"

    def to_json(self) -> dict:
        return {
            "verdict": self.verdict,
            "usable": self.usable,
            "flags": [{"name": f.name, "severity": f.severity, "subject": f.subject, "message": f.message, "numbers": _jsonable(f.numbers)} for f in self.flags],
            "scenarios": _jsonable(self.scenarios),
            "thresholds": {"rms": RMS_LIMIT, "lag1_autocorrelation": AUTOCORRELATION_LIMIT, "runs_p": RUNS_P_LIMIT,
                           "bound_fraction": BOUND_FRACTION, "structure_min_rms": STRUCTURE_MIN_RMS},
        }


def lag1_autocorrelation(r) -> float:
    """Lag-1 autocorrelation of a residual sequence ``r`` [-] (NaN for fewer than 3 points or zero variance)."""
    r = np.asarray(r, dtype=float)
    if r.size < 3:
        return float("nan")
    d = r - r.mean()
    den = float(np.sum(d * d))
    return float(np.sum(d[:-1] * d[1:]) / den) if den > 0 else float("nan")


def runs_test(r) -> tuple[int, float, float]:
    """Wald--Wolfowitz runs test on the signs of ``r`` (zeros dropped).

    Returns ``(runs, expected runs, two-sided p-value)`` from the normal approximation; the
    p-value is NaN when all signs agree or fewer than 2 points remain. Too few runs means
    residuals of one sign cluster: the model misses a trend of the data.
    """
    s = np.sign(np.asarray(r, dtype=float))
    s = s[s != 0]
    n1, n2 = int(np.sum(s > 0)), int(np.sum(s < 0))
    n = n1 + n2
    runs = int(1 + np.sum(s[1:] != s[:-1])) if n else 0
    if n1 == 0 or n2 == 0 or n < 2:
        return runs, float("nan"), float("nan")
    mu = 2.0 * n1 * n2 / n + 1.0
    var = (mu - 1.0) * (mu - 2.0) / (n - 1.0)
    if var <= 0:
        return runs, mu, float("nan")
    z = (runs - mu) / math.sqrt(var)
    return runs, mu, math.erfc(abs(z) / math.sqrt(2.0))


def _bound_flags(parameterization, u, values) -> list[QualityFlag]:
    """``at_bound`` for each field whose transform is saturated (within :data:`BOUND_FRACTION`)."""
    from .materials import Log, ScaledLogit

    out = []
    for i, (f, t) in enumerate(zip(parameterization.fields, parameterization.transforms)):
        ui = float(u[i])
        unit = _unit_text(UNITS.get(f, ""))
        if isinstance(t, ScaledLogit):
            frac = 1.0 / (1.0 + math.exp(-ui)) if ui > -700 else 0.0
            for side, dist, b in (("lower", frac, t.lower), ("upper", 1.0 - frac, t.upper)):
                if dist < BOUND_FRACTION:
                    out.append(QualityFlag("at_bound", "error", f, f"{f} = {values[f]:.6g} {unit} sits at its {side} bound {b:g}: the optimum lies outside "
                                           f"[{t.lower:g}, {t.upper:g}] (widen fit.bounds, or the model does not describe the data)".replace("  ", " "),
                                           {"value": values[f], "bound": b, "side": side, "fraction_of_range": dist}))
        elif isinstance(t, Log) and ui < math.log(BOUND_FRACTION):
            out.append(QualityFlag("at_bound", "error", f, f"{f} = {values[f]:.6g} {unit} collapsed onto its lower limit {t.lower:g} "
                                   f"({math.exp(ui):.2g} of its start scale {t.scale:g})".replace("  ", " "),
                                   {"value": values[f], "bound": t.lower, "side": "lower", "fraction_of_scale": math.exp(ui)}))
    return out


def _residual_flags(scenarios) -> tuple[list[QualityFlag], dict]:
    """``poor_fit`` and ``systematic_residuals`` per scenario, and each scenario's statistics."""
    flags, stats = [], {}
    for s in scenarios:
        r = np.asarray(s.residual, dtype=float)
        rms = float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
        rho = lag1_autocorrelation(r)
        runs, expected, p = runs_test(r)
        stats[s.name] = {"points": int(r.size), "rms": rms, "lag1_autocorrelation": rho, "runs": runs, "runs_expected": expected, "runs_p": p,
                         "max_abs": float(np.max(np.abs(r))) if r.size else float("nan")}
        if np.isfinite(rms) and rms > RMS_LIMIT:
            flags.append(QualityFlag("poor_fit", "warning", s.name, f"{s.name}: rms residual/sigma {rms:.3g} > {RMS_LIMIT:g}: the model misses the data "
                                     "by more than the stated noise (or sigma is too small)", {"rms": rms}))
        if r.size >= STRUCTURE_MIN_POINTS and np.isfinite(rms) and rms >= STRUCTURE_MIN_RMS:
            why = []
            if np.isfinite(rho) and rho > AUTOCORRELATION_LIMIT:
                why.append(f"lag-1 autocorrelation {rho:.2f} > {AUTOCORRELATION_LIMIT:g}")
            if np.isfinite(p) and p < RUNS_P_LIMIT:
                why.append(f"{runs} sign runs where {expected:.1f} are expected (runs test p = {p:.2g} < {RUNS_P_LIMIT:g})")
            if why:
                flags.append(QualityFlag("systematic_residuals", "warning", s.name,
                                         f"{s.name}: systematic residuals ({'; '.join(why)}; largest abs(residual)/sigma {stats[s.name]['max_abs']:.2g}): "
                                         "the model's shape does not follow the data; the standard errors are optimistic",
                                         {"lag1_autocorrelation": rho, "runs": runs, "runs_expected": expected, "runs_p": p}))
    return flags, stats


def assess_quality(result: "FitResult", parameterization=None, *, plausible: Mapping[str, Sequence[float]] | None = None) -> FitQuality:
    """Quality gates of a fit (see ``docs/fitting.md``, "Quality").

    Errors (the answer is unusable): a non-finite value or loss (``non_finite``), a fit that did
    not converge (``not_converged``), a parameter at a transform bound (``at_bound``, needs
    ``parameterization``), a value outside its plausible range (``implausible_value``:
    :data:`PLAUSIBLE` updated by ``plausible``, ``{field: (lo, hi)}`` SI). Warnings: rms
    residual/sigma above :data:`RMS_LIMIT` (``poor_fit``), structured residuals: lag-1
    autocorrelation above :data:`AUTOCORRELATION_LIMIT` or runs-test p below
    :data:`RUNS_P_LIMIT` (``systematic_residuals``).
    """
    ranges = {**PLAUSIBLE, **{k: (float(v[0]), float(v[1])) for k, v in (plausible or {}).items()}}
    flags: list[QualityFlag] = []
    bad = [f for f in result.fields if not math.isfinite(result.values[f])]
    if bad or not math.isfinite(result.loss) or any(not np.all(np.isfinite(s.predicted)) for s in result.scenarios):
        flags.append(QualityFlag("non_finite", "error", ", ".join(bad) or None, f"non-finite result ({', '.join(bad) or 'loss or predictions'})", {"loss": result.loss}))
    if not result.converged:
        flags.append(QualityFlag("not_converged", "error", None, f"the fit did not converge ({result.reason}) after {result.steps} steps", {"steps": result.steps}))
    if parameterization is not None:
        flags += _bound_flags(parameterization, result.unconstrained, result.values)
    for f in result.fields:
        v = result.values[f]
        if f in ranges and math.isfinite(v) and not ranges[f][0] <= v <= ranges[f][1]:
            lo, hi = ranges[f]
            unit = _unit_text(UNITS.get(f, ""))
            flags.append(QualityFlag("implausible_value", "error", f, f"{f} = {v:.4g} {unit} lies outside the plausible range [{lo:g}, {hi:g}] {unit} "
                                     "(most often a unit mistake or a diverged fit; widen it with fit.plausible if the material really is so)".replace("  ", " "),
                                     {"value": v, "range": [lo, hi]}))
    res_flags, stats = _residual_flags(result.scenarios)
    return FitQuality(tuple(flags + res_flags), stats)


# ============================================================================ discretisation error
#: How :func:`discretisation_estimate` turns a coarse-mesh prediction into a parameter error.
DISCRETISATION_METHOD = "richardson_first_order"
#: Assumed order of convergence of the predictions in the cell size h [-] (P1 tets and the
#: spring lattice converge at first order in force: docs/experiments.md, experiment 1).
DISCRETISATION_ORDER = 1.0


def discretisation_estimate(result: "FitResult", coarse: Mapping[str, Mapping], skipped: Mapping[str, str] | None = None) -> dict:
    """The mesh's share of the error of each fitted value, from one evaluation per scenario on
    a coarser mesh at the optimum (no refit).

    Per scenario with a coarse prediction ``p_c`` (fine prediction ``p_f`` at the optimum, cell
    size ratio ``r = h_coarse / h_fine``), Richardson extrapolation with the assumed order
    ``q`` (:data:`DISCRETISATION_ORDER`, first order) estimates the fine mesh's error in the
    prediction: ``e = p_f - p_exact ~ (p_c - p_f) / (r^q - 1)``. The fit matched ``p_f`` to the
    data, so the mesh-converged model would have needed parameters differing by the linearised
    ``theta_fit - theta_converged ~ -(J^T J)^-1 J^T (e / sigma)`` (``J``: the fit's Jacobian of
    the scaled residuals at the optimum; rows of scenarios without an estimate count as zero).

    Args:
        result: the fit (its predictions, sigmas, Jacobian, values and standard errors).
        coarse: ``{scenario name: {"prediction": array (unit of the data), "fine_cells",
            "coarse_cells", "refinement_ratio": r [-]}}``.
        skipped: ``{scenario name: reason}`` for the scenarios without an estimate.

    Returns:
        ``{"method", "order", "status": "estimated" | "not estimated", "reason" (when not),
        "scenarios": {name: {"status", "reason" | "fine_cells", "coarse_cells",
        "refinement_ratio", "prediction_change_relative", "rms_error_over_sigma"}},
        "estimate": {field: theta_fit - theta_converged (SI)}, "relative": {field: estimate /
        value [-]}, "corrected": {field: value - estimate (SI)}, "standard_error": {field},
        "ratio_to_standard_error": {field: |estimate| / standard error [-]}}``.
    """
    skipped = dict(skipped or {})
    rec: dict = {"method": DISCRETISATION_METHOD, "order": DISCRETISATION_ORDER, "scenarios": {}}
    rows = []
    for s in result.scenarios:
        c = coarse.get(s.name)
        if c is None:
            rec["scenarios"][s.name] = {"status": "not estimated", "reason": skipped.get(s.name, "no coarse-mesh prediction")}
            rows.append(np.zeros(s.observed.size))
            continue
        e, info = _fine_mesh_error(s, c)
        rec["scenarios"][s.name] = info
        rows.append(e / np.asarray(s.sigma, dtype=float))
    if not any(v["status"] == "estimated" for v in rec["scenarios"].values()):
        reasons = "; ".join(f"{k}: {v['reason']}" for k, v in rec["scenarios"].items())
        return {**rec, "status": "not estimated", "reason": reasons}
    J = np.asarray(result.jacobian, dtype=float)
    if not np.all(np.isfinite(J)):
        return {**rec, "status": "not estimated", "reason": "the fit's Jacobian is not finite"}
    delta = -np.linalg.lstsq(J, np.concatenate(rows), rcond=None)[0]
    est = {f: float(delta[i]) for i, f in enumerate(result.fields)}
    se = dict(result.standard_errors)
    return {**rec, "status": "estimated", "estimate": est,
            "relative": {f: est[f] / abs(result.values[f]) if result.values[f] != 0 else float("nan") for f in est},
            "corrected": {f: result.values[f] - est[f] for f in est},
            "standard_error": se,
            "ratio_to_standard_error": {f: abs(est[f]) / se[f] if se[f] > 0 and math.isfinite(se[f]) else float("nan") for f in est}}


def _fine_mesh_error(s: "ScenarioFit", c: Mapping) -> tuple[np.ndarray, dict]:
    """Richardson estimate of the fine mesh's error ``p_f - p_exact`` (unit of the data) of one
    scenario, and its record (cells, ratio, relative change of the prediction [-])."""
    pf = np.asarray(s.predicted, dtype=float)
    pc = np.asarray(c["prediction"], dtype=float)
    r = float(c["refinement_ratio"])
    e = (pc - pf) / (r**DISCRETISATION_ORDER - 1.0)
    norm = float(np.linalg.norm(pf))
    info = {"status": "estimated", "fine_cells": c.get("fine_cells"), "coarse_cells": c.get("coarse_cells"), "refinement_ratio": r,
            "prediction_change_relative": float(np.linalg.norm(pc - pf) / norm) if norm > 0 else float("nan"),
            "rms_error_over_sigma": float(np.sqrt(np.mean((e / np.asarray(s.sigma, dtype=float)) ** 2)))}
    return e, info


def _discretisation_flags(rec: Mapping, units: Mapping[str, str]) -> list[QualityFlag]:
    """``discretisation_error`` (a warning) for each field whose estimate exceeds its standard error."""
    if rec.get("status") != "estimated":
        return []
    out = []
    for f, d in rec["estimate"].items():
        se, ratio = rec["standard_error"][f], rec["ratio_to_standard_error"][f]
        if math.isfinite(ratio) and ratio > 1.0:
            unit = _unit_text(units.get(f, ""))
            out.append(QualityFlag("discretisation_error", "warning", f,
                                   f"{f}: the mesh's estimated share of the error {d:+.3g} {unit} ({100 * rec['relative'][f]:+.2g} %) exceeds its "
                                   f"standard error {se:.3g} {unit} ({ratio:.3g} x): refine the specimen's cells; the mesh-converged "
                                   f"value is about {rec['corrected'][f]:.4g} {unit}".replace("  ", " "),
                                   {"estimate": d, "relative": rec["relative"][f], "standard_error": se, "ratio": ratio}))
    return out


def with_discretisation(result: "FitResult", rec: dict, *, stacklevel: int = 2) -> "FitResult":
    """``result`` with ``discretisation = rec`` and its ``discretisation_error`` quality flags
    added (each also emitted as :class:`~difftissue.errors.DiscretisationWarning`)."""
    flags = _discretisation_flags(rec, result.units)
    for flag in flags:
        warnings.warn(f"{flag.severity}: {flag.message}", DiscretisationWarning, stacklevel=stacklevel + 1)
    quality = result.quality
    if quality is not None:
        quality = FitQuality(quality.flags + tuple(flags), quality.scenarios)
    return dataclasses.replace(result, discretisation=rec, quality=quality)


def discretisation_line(rec: Mapping) -> str:
    """One line for people: each field's estimate (relative) and its ratio to the standard
    error, or why it was not estimated."""
    if rec.get("status") == "not applicable":
        return f"discretisation error: not applicable ({rec.get('reason', '')})"
    if rec.get("status") != "estimated":
        return f"discretisation error: not estimated ({rec.get('reason', '')})"
    parts = [f"{f} {100 * rec['relative'][f]:+.3g} % ({rec['ratio_to_standard_error'][f]:.3g} x its standard error)" for f in rec["estimate"]]
    cells = "; ".join(f"{k} cells {v['fine_cells']} vs {v['coarse_cells']}" for k, v in rec["scenarios"].items() if v["status"] == "estimated")
    return f"discretisation error (mesh, Richardson first order from {cells}): " + ", ".join(parts)


# ============================================================================ effective modulus
#: Half-space closed forms whose force is proportional to E / (1 - nu^2), by indenter.
_HALF_SPACE_LAWS = {"sphere": "Hertz", "flat_punch": "Sneddon flat punch", "cone": "Sneddon cone"}


def effective_modulus(result: "FitResult", scenarios) -> dict | None:
    """What a half-space indentation fit with nu fixed determines: ``E* = E / (1 - nu^2)`` [Pa].

    Every scenario must be a half-space analytic indentation (``solution == "half_space"``:
    Hertz, Sneddon), E fitted and nu not: such a curve determines E* only, and the fitted E is
    E* (1 - nu^2) at the assumed nu. Returns ``{"value", "standard_error", "unit",
    "poisson_ratio_assumed", "law", "meaning"}`` or None for any other fit.
    """
    if "youngs_modulus" not in result.fields or "poisson_ratio" in result.fields or not scenarios:
        return None
    laws = []
    for sc in scenarios:
        if getattr(sc, "solution", None) != "half_space" or getattr(sc, "indenter", None) not in _HALF_SPACE_LAWS:
            return None
        laws.append(_HALF_SPACE_LAWS[sc.indenter])
    nu = float(result.material.poisson_ratio)
    k = 1.0 - nu**2
    se = result.standard_errors["youngs_modulus"]
    return {
        "value": result.values["youngs_modulus"] / k,
        "standard_error": se / k if math.isfinite(se) else float("inf"),
        "unit": "Pa",
        "poisson_ratio_assumed": nu,
        "law": ", ".join(dict.fromkeys(laws)),
        "meaning": (f"E* = E / (1 - nu^2), the effective (indentation) modulus: what a half-space {laws[0]} fit determines. "
                    f"youngs_modulus = E* (1 - nu^2) holds only for the assumed poisson_ratio = {nu:g}, which the data do not determine"
                    + (" (nu = 0 is the indentation-modulus convention E = E*, not a tissue's nu)" if nu == 0 else "")),
    }


def effective_modulus_line(rec: Mapping) -> str:
    """One line for people: the effective modulus, its standard error and what it means."""
    se = rec["standard_error"]
    se_txt = f" ± {se:.3g}" if se is not None and math.isfinite(se) else ""
    nu = rec["poisson_ratio_assumed"]
    return (f"effective modulus E* = E/(1-nu^2) = {rec['value']:.6g}{se_txt} Pa ({rec['law']}): what the data determine; "
            f"E = {rec['value'] * (1 - nu**2):.6g} Pa only at the assumed nu = {nu:g}")


# ============================================================================ optimisers
def _tree_where(cond, new, old):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(cond, a, b), new, old)


def _strong(tree):
    """Every array leaf with its dtype made strong (not weak-typed), so the state that goes into
    the jitted step has the same avals as what comes out: no recompilation at the second step."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x)) if eqx.is_array(x) else x, tree)


def _with_forward_jacobian(f):
    """``f`` (``u (p,) -> pytree of arrays``) with a custom JVP that computes the whole Jacobian
    by forward mode (``jax.jacfwd``: p tangents in one pass) and applies it to the tangent.

    Same values and derivatives as ``f``. What changes is what a linearisation keeps: for
    ``jax.linearize`` (optimistix's Gauss--Newton family keeps the linearised function in its
    state, and carries it from step to step) the residuals are the Jacobian matrices, (n, p)
    per output, instead of every intermediate of the forward model -- 12 M floats (97 MB) per
    start on the 4,800-tet benchmark of ``benchmarks/fit.py``.
    """

    @jax.custom_jvp
    def g(u):
        return f(u)

    @g.defjvp
    def g_jvp(primals, tangents):
        (u,), (du,) = primals, tangents

        def both(v):
            out = f(v)
            return out, out

        J, out = jax.jacfwd(both, has_aux=True)(u)
        return out, jax.tree_util.tree_map(lambda Ji: Ji @ du, J)

    return g


class _Engine:
    """One optimiser: ``init(U) -> dyn`` (batched state arrays) and a vmapped ``step``."""

    def __init__(self, problem: FitProblem, method: str, *, rtol: float, atol: float, learning_rate: float, jac: str):
        self.problem = problem
        self.method = method
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.jac = jac
        self.learning_rate = float(learning_rate)
        self.traces = 0
        if method in ("levenberg_marquardt", "gauss_newton"):
            import optimistix as optx

            self._optx = optx
            cls = optx.LevenbergMarquardt if method == "levenberg_marquardt" else optx.GaussNewton
            self.solver = cls(rtol=self.rtol, atol=self.atol)
            # The predictions ride along as the solver's aux: with the residual and Jacobian
            # the solver keeps at the accepted point, they give the fit's final evaluation
            # without compiling the forward model a second time (:meth:`make_final`).
            # With jac="fwd" the Jacobian is computed whole by forward mode inside a custom JVP
            # (:func:`_with_forward_jacobian`): the linearisation the solver keeps in its state
            # is then the (n, p) matrix, not every intermediate of the forward model.
            if jac == "fwd":
                self._fn = lambda y, data: _with_forward_jacobian(problem.with_data(data).residuals_and_predictions)(y)
            else:
                self._fn = lambda y, data: problem.with_data(data).residuals_and_predictions(y)
            self._options = {"jac": jac}
            self._tags = frozenset()
        else:
            import optax

            self._optax = optax
            if method == "adam":
                self.solver = optax.adam(self.learning_rate)
            else:
                self.solver = optax.lbfgs()

    # -- optimistix ------------------------------------------------------------------
    def _residual_struct(self, u) -> jax.ShapeDtypeStruct:
        """Shape and dtype of the residual vector, without tracing the forward model: the
        residuals ``(predict - observed) / sigma`` carry the promoted dtype of ``u`` and the
        float64 data (float32 when x64 is off)."""
        dtype = jax.dtypes.canonicalize_dtype(np.result_type(u.dtype, np.float64))
        return jax.ShapeDtypeStruct((self.problem.n_residuals,), dtype)

    def _optx_init_single(self, u, data):
        f_struct = self._residual_struct(u)
        aux_struct = tuple(jax.ShapeDtypeStruct((n,), f_struct.dtype) for n in self.problem.sizes)
        return self.solver.init(self._fn, u, data, self._options, f_struct, aux_struct, self._tags)

    def init(self, U, data):
        """Batched dynamic state for starts ``U`` (shape ``(S, p)``) of the problem with ``data``.

        One jitted program per engine (retraced only for a new number of starts): the optimiser's
        initial state is built from shapes (optimistix traces the model abstractly), so running
        it eagerly would dispatch and compile every small zero-filled array separately."""
        if getattr(self, "_init", None) is None:
            if hasattr(self, "_optx"):

                def batched(U, data):
                    def one(u):
                        dyn, static = eqx.partition(self._optx_init_single(u, data), eqx.is_array)
                        if not hasattr(self, "_static"):  # keep the first one: the compiled step closes over it
                            self._static = static
                        return dyn

                    return _strong(jax.vmap(one)(U))

            else:

                def batched(U, data):
                    return _strong(jax.vmap(self.solver.init)(U))

            self._init = jax.jit(batched)
        return self._init(U, data)

    def evaluate(self, U, data):
        """``(values (S, p), loss (S,), J (S, n, p), predictions)`` of every start ``U`` (S, p):
        the physical values, the loss, the Jacobian of the robustified scaled residuals w.r.t.
        the physical values and each scenario's predictions (not jitted; see :meth:`make_evaluate`)."""
        problem = self.problem.with_data(data)
        fields = problem.fields
        values = jax.vmap(lambda u: jnp.stack([problem.values(u)[f] for f in fields]))(U)
        loss, J, preds = jax.vmap(lambda v: problem.evaluate_values(v, self.jac))(values)
        return values, loss, J, preds

    def make_evaluate(self):
        """:meth:`evaluate` jitted once per engine (at the start and the end of every fit)."""
        if getattr(self, "_evaluate", None) is None:
            self._evaluate = jax.jit(self.evaluate)
        return self._evaluate

    def make_final(self):
        """Optimistix methods: ``(U, dyn, data) -> (values, loss, J, predictions, ok)`` from the
        solver state alone, jitted once per engine -- the residual, the Jacobian (materialised
        from the linearisation the solver keeps at the accepted point) and the predictions (the
        aux) of every start, the Jacobian taken to the PHYSICAL values by the chain rule through
        the transforms. ``ok`` is False for a start whose state holds no evaluation (no step
        taken) or whose transform derivative is singular (a parameter saturated at a bound):
        :func:`fit` then uses :meth:`make_evaluate`. ``None`` for optax methods."""
        if not hasattr(self, "_optx"):
            return None
        if getattr(self, "_final", None) is None:
            template, static = self.problem, self._static
            fields = template.fields

            def final(U, dyn, data):
                problem = template.with_data(data)

                def values_of(u):
                    vals = problem.values(u)
                    return jnp.stack([vals[f] for f in fields])

                def one(u, d):
                    state = eqx.combine(d, static)
                    Ju = state.f_info.jac.as_matrix()
                    dvdu = jax.jacfwd(values_of)(u)
                    Jv = jnp.linalg.solve(dvdu.T, Ju.T).T  # Ju = Jv dv/du
                    r = state.f_info.residual
                    smallest = jnp.min(jnp.linalg.svd(dvdu, compute_uv=False))
                    ok = (state.num_steps > 0) & (smallest > 1e-100) & jnp.all(jnp.isfinite(Jv))
                    return values_of(u), 0.5 * jnp.sum(r * r), Jv, tuple(state.aux), ok

                return jax.vmap(one)(U, dyn)

            self._final = jax.jit(final)
        return self._final

    def make_step(self):
        """The ONE jitted step: ``(U, dyn, done, data) -> (U, dyn, done, status, loss)``,
        vmapped over starts (``data`` is shared by the starts: :meth:`FitProblem.data`).

        ``status``: 0 running or converged, >0 failure code (optimistix RESULTS index, or -1 for a
        non-finite loss in optax)."""
        if getattr(self, "_step", None) is None:
            one = self.single_step()

            def step(U, dyn, done, data):
                self.traces += 1  # Python side effect: runs once per trace (compilation)
                return _strong(jax.vmap(one, in_axes=(0, 0, 0, None))(U, dyn, done, data))

            self._step = jax.jit(step)
        return self._step

    def single_step(self):
        """The step of ONE start, not jitted nor vmapped: ``(u, dyn, done, data) -> (u, dyn,
        done, status, loss)``; :meth:`make_step` and :func:`difftissue.batch.fit_batch` build
        their compiled programs from it."""
        template = self.problem
        rtol, atol = self.rtol, self.atol

        if hasattr(self, "_optx"):
            solver, fn, options, tags, static = self.solver, self._fn, self._options, self._tags, self._static

            def one(u, dyn, done, data):
                state = eqx.combine(dyn, static)
                u_new, state_new, _ = solver.step(fn, u, data, options, state, tags)
                term, result = solver.terminate(fn, u_new, data, options, state_new, tags)
                dyn_new = eqx.partition(state_new, eqx.is_array)[0]
                status = _result_code(result)
                r = state_new.f_info.residual
                loss = 0.5 * jnp.sum(r * r)
                # Also stop when a trial step was rejected and the next one is below the x
                # tolerance (as SciPy's least_squares tests xtol on every trial step).
                # Optimistix tests only accepted steps: at the optimum the trial steps change
                # the loss at round-off, are rejected, and the trust region shrinks for another
                # 10-17 steps (each a forward + Jacobian) before one is accepted unchanged. The
                # result is the last accepted point, as before.
                trial = state_new.y_eval - u_new
                rejected = state_new.num_steps_since_acceptance > 0
                negligible = rejected & (jnp.linalg.norm(trial) <= atol + rtol * jnp.linalg.norm(u_new))
                finished = term | (status != 0) | negligible
                u_out = jnp.where(done, u, u_new)
                dyn_out = _tree_where(done, dyn, dyn_new)
                return u_out, dyn_out, done | finished, jnp.where(done, 0, status), loss

        else:
            optax = self._optax
            solver = self.solver
            lbfgs = self.method == "lbfgs"

            def one(u, state, done, data):
                loss_fn = template.with_data(data).loss
                if lbfgs:
                    value, grad = optax.value_and_grad_from_state(loss_fn)(u, state=state)
                    updates, state_new = solver.update(grad, state, u, value=value, grad=grad, value_fn=loss_fn)
                else:
                    value, grad = jax.value_and_grad(loss_fn)(u)
                    updates, state_new = solver.update(grad, state, u)
                u_new = optax.apply_updates(u, updates)
                if lbfgs:
                    # L-BFGS: optax's zoom line search treats a non-finite trial value (a
                    # failed static solve) as a failed decrease and shortens the step.
                    loss_new = optax.tree_utils.tree_get(state_new, "value")
                else:
                    loss_new = loss_fn(u_new)

                    # Adam: a trial point whose loss is not finite (a static solve that failed
                    # gives NaN predictions, SolverOptions(failure="nan")) is rejected and the
                    # step halved until the loss is finite (at most ADAM_MAX_HALVINGS times), as
                    # Levenberg--Marquardt shrinks its trust region; the moments keep the
                    # gradient at the accepted point u.
                    def shorter(c):
                        alpha, _, k = c
                        alpha = 0.5 * alpha
                        return alpha, loss_fn(u + alpha * updates), k + 1

                    def rejected(c):
                        return ~jnp.isfinite(c[1]) & (c[2] < ADAM_MAX_HALVINGS) & jnp.isfinite(value)

                    alpha, loss_new, _ = jax.lax.while_loop(rejected, shorter, (jnp.asarray(1.0, u.dtype), loss_new, jnp.asarray(0, jnp.int32)))
                    u_new = u + alpha * updates
                du = jnp.max(jnp.abs(u_new - u))
                small_u = du <= atol + rtol * jnp.max(jnp.abs(u_new))
                small_f = jnp.abs(loss_new - value) <= atol + rtol * jnp.abs(value)
                bad = ~jnp.isfinite(loss_new)
                finished = (small_u & small_f) | bad
                status = jnp.where(bad, -1, 0)
                u_out = jnp.where(done, u, u_new)
                state_out = _tree_where(done, state, state_new)
                loss_out = jnp.where(done, value, loss_new)  # a stopped start stays at u, whose loss is value
                return u_out, state_out, done | finished, jnp.where(done, 0, status), loss_out

        return one

    def status_message(self, code: int) -> str:
        if code == -1:
            return "non-finite loss"
        if hasattr(self, "_optx"):
            msg = _result_message(self._optx.RESULTS, code).strip().split("\n")[0]
            return f"optimistix: {msg}"
        return f"status {code}"


#: Adam: the most halvings of a step whose trial point has a non-finite loss (a failed static
#: solve) before the start stops with a non-finite loss (a 2^-12 shorter step still failing).
ADAM_MAX_HALVINGS = 12


def _result_code(result) -> jax.Array:
    """The integer code of an equinox ``Enumeration`` item (e.g. an optimistix ``RESULTS``):
    its one pytree leaf (public pytree flattening, not the private ``_value``)."""
    return jnp.asarray(jax.tree_util.tree_leaves(result)[0])


def _result_message(enumeration, code: int) -> str:
    """The message of code ``code`` of the equinox ``Enumeration`` class ``enumeration``: the
    item rebuilt from the pytree structure of one of its members, then looked up by the
    public ``enumeration[item]`` (not the private ``_index_to_message``)."""
    member = enumeration.successful
    (leaf,), treedef = jax.tree_util.tree_flatten(member)
    return enumeration[jax.tree_util.tree_unflatten(treedef, [np.asarray(code, dtype=np.asarray(leaf).dtype)])]


#: Recently used engines (compiled step and evaluation), so that fitting the same problem
#: again in a session -- a resume, a re-run with more steps, or ANOTHER SPECIMEN of the same
#: structure with its own data -- does not compile again. The key is
#: :meth:`FitProblem.structure_key` (fields, transforms, fixed fields, loss, scenario types and
#: pytree structures, a hash of the compiled-in scenario leaves; objects that are not arrays by
#: identity) and the solver options; the measured data are arguments, not part of the key. The
#: entry keeps its problem alive, so the ids in a key cannot be reused while cached.
_ENGINE_CACHE: dict = {}
_ENGINE_CACHE_SIZE = 8


def _cached_engine(problem: FitProblem, method: str, **options) -> _Engine:
    key = (problem.structure_key(), method, tuple(sorted(options.items())))
    engine = _ENGINE_CACHE.pop(key, None)
    if engine is None:
        engine = _Engine(problem, method, **options)
    _ENGINE_CACHE[key] = engine  # most recent last
    while len(_ENGINE_CACHE) > _ENGINE_CACHE_SIZE:
        _ENGINE_CACHE.pop(next(iter(_ENGINE_CACHE)))
    return engine


# ============================================================================ checkpoints
def _save_checkpoint(path: Path, *, U, dyn, done, status, history, step, fingerprint, components, method):
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(dyn)]
    arrays = {f"state_{i}": a for i, a in enumerate(leaves)}
    meta = {
        "format": "difftissue-fit-checkpoint/1",
        "fingerprint": fingerprint,
        "components": components,
        "method": method,
        "step": int(step),
        "n_state_leaves": len(leaves),
    }
    with atomic_output(path, overwrite=True) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                meta=np.array(json.dumps(meta)),
                unconstrained=np.asarray(U),
                done=np.asarray(done),
                status=np.asarray(status),
                loss_history=np.asarray(history),
                **arrays,
            )


def _load_checkpoint(path: Path, *, fingerprint, components, dyn_template):
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            data = {k: np.array(z[k]) for k in z.files if k != "meta"}
    except Exception as exc:  # noqa: BLE001 - report any unreadable file as one clear error
        raise CheckpointError(f"cannot read fit checkpoint {path}: {exc}") from exc
    if meta.get("fingerprint") != fingerprint:
        saved = meta.get("components", {})
        differ = [k for k in components if saved.get(k) != components[k]] or ["unknown"]
        raise CheckpointMismatchError(
            f"checkpoint {path} was written by a different fit problem (differs in: {', '.join(differ)}); "
            "refusing to resume from it. Delete it or choose another checkpoint path to start afresh."
        )
    leaves, treedef = jax.tree_util.tree_flatten(dyn_template)
    if meta.get("n_state_leaves") != len(leaves):
        raise CheckpointMismatchError(f"checkpoint {path} holds an optimiser state of another layout (library version changed?); delete it to start afresh")
    new_leaves = []
    for i, ref in enumerate(leaves):
        a = data[f"state_{i}"]
        if a.shape != ref.shape:
            raise CheckpointMismatchError(f"checkpoint {path}: optimiser state leaf {i} has shape {a.shape}, expected {ref.shape}; delete it to start afresh")
        new_leaves.append(jnp.asarray(a, dtype=ref.dtype))
    dyn = jax.tree_util.tree_unflatten(treedef, new_leaves)
    return (
        jnp.asarray(data["unconstrained"]),
        dyn,
        jnp.asarray(data["done"]),
        jnp.asarray(data["status"]),
        [row for row in np.asarray(data["loss_history"])],
        int(meta["step"]),
    )


# ============================================================================ fit
def _initial_starts(parameterization, initial: Material, starts, seed: int, spread: float):
    u0 = jnp.asarray(parameterization.pack(initial))
    if isinstance(starts, Material):
        starts = [starts]
    if isinstance(starts, (int, np.integer)) and not isinstance(starts, bool):
        if starts < 1:
            raise FitError(f"starts must be >= 1, got {starts}")
        if starts == 1:
            return u0[None, :]
        rng = np.random.default_rng(seed)
        extra = rng.normal(0.0, spread, size=(int(starts) - 1, u0.shape[0]))
        return jnp.concatenate([u0[None, :], u0[None, :] + jnp.asarray(extra, dtype=u0.dtype)])
    if isinstance(starts, Sequence) and starts and all(isinstance(m, Material) for m in starts):
        return jnp.stack([jnp.asarray(parameterization.pack(m), dtype=u0.dtype) for m in starts])
    raise FitError(f"starts must be an int >= 1 or a non-empty sequence of Material, got {starts!r}")


def _progress_bar(enabled: bool, total: int):
    if not enabled:
        return None
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=False,
    )


def fit(
    scenarios,
    parameterization: MaterialParameterization,
    initial: Material,
    *,
    method: str = "levenberg_marquardt",
    loss: str = "linear",
    f_scale: float = 1.0,
    starts: int | Sequence[Material] = 1,
    seed: int = 0,
    start_spread: float = 1.0,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    learning_rate: float = 0.05,
    jac: str = "fwd",
    absolute_sigma: bool = False,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 10,
    resume: bool = False,
    progress: bool = False,
    callback: Callable[[FitProgress], bool | None] | None = None,
    plausible: Mapping[str, Sequence[float]] | None = None,
) -> FitResult:
    """Fit the fields of ``parameterization`` to one or more scenarios (weighted least squares).

    Args:
        scenarios: a :class:`Scenario` or a sequence of them; a joint fit shares the parameters.
        parameterization: fitted fields and their bounded transforms.
        initial: starting material (SI); its non-fitted fields are kept fixed.
        method: ``"levenberg_marquardt"`` (default), ``"gauss_newton"`` (optimistix, on the
            residual vector), ``"adam"`` or ``"lbfgs"`` (optax, on the scalar loss).
        loss: ``"linear"``, ``"soft_l1"`` or ``"huber"``; robust losses use ``f_scale`` [-] (in
            units of sigma).
        starts: number of starts (the first is ``initial``; the others are drawn from
            ``N(u0, start_spread^2)`` in the unconstrained space with ``numpy`` generator ``seed``),
            or a sequence of starting materials. All starts run batched (``jax.vmap``) in one
            jitted step; the result reports the start with the lowest final loss.
        max_steps: total optimiser steps (a resumed fit counts the steps already taken).
        rtol, atol: stop a start when both the step in ``u`` and the change of the residuals
            (optimistix Cauchy criterion; for optax the loss) are below ``atol + rtol * |.|``.
            Default ``1e-8, 1e-10`` in float64 and ``1e-5, 1e-7`` in float32 (the dtype of ``u``).
        learning_rate: Adam step size in ``u`` (ignored by the other methods).
        jac: ``"fwd"`` or ``"bwd"``: forward- or reverse-mode Jacobian (use ``"bwd"`` for
            scenarios whose derivatives are ``custom_vjp`` only).
        absolute_sigma: covariance ``(J^T J)^-1`` (sigma is the true noise level) instead of the
            default ``s^2 (J^T J)^-1``, ``s^2 = SSE / (n - p)``.
        checkpoint: file (``.npz``) to save the unconstrained parameters of every start, the
            optimiser state, step count, loss history and a fingerprint of the problem every
            ``checkpoint_every`` steps, at the end and on interruption (written atomically:
            temporary file in the same directory, then ``os.replace``).
        resume: continue from ``checkpoint`` if it exists (else start afresh). The optimiser's
            internal state (Levenberg--Marquardt damping / trust region, Adam moments, L-BFGS
            memory) is restored, so a resumed fit takes the same steps as an uninterrupted one. A
            checkpoint of a different problem raises :class:`CheckpointMismatchError`; an
            existing checkpoint without ``resume`` raises :class:`CheckpointError`.
        progress: show a rich progress bar (on stderr) with the best loss.
        callback: called with a :class:`FitProgress` after every step; returning ``True``
            stops the fit (reason "stopped by callback"). An exception (e.g. KeyboardInterrupt)
            propagates after the checkpoint is written.
        plausible: ``{field: (lo, hi)}`` (SI) widening or narrowing :data:`PLAUSIBLE` (default
            E in [1 Pa, 1 GPa]) for the ``implausible_value`` quality gate.

    Returns:
        A :class:`FitResult`. Identifiability problems are also emitted as
        :class:`~difftissue.errors.IdentifiabilityWarning`, quality flags (:func:`assess_quality`)
        as :class:`~difftissue.errors.FitQualityWarning`.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}; choose one of {METHODS}")
    if jac not in ("fwd", "bwd"):
        raise FitError(f"jac must be 'fwd' or 'bwd', got {jac!r}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise FitError(f"max_steps must be an int >= 0, got {max_steps!r}")
    if not (isinstance(checkpoint_every, (int, np.integer)) and checkpoint_every >= 1):
        raise FitError(f"checkpoint_every must be an int >= 1, got {checkpoint_every!r}")
    if resume and checkpoint is None:
        raise FitError("resume=True needs a checkpoint path")
    problem = FitProblem(scenarios, parameterization, initial, loss=loss, f_scale=f_scale)
    U = _initial_starts(parameterization, initial, starts, seed, start_spread)
    n_starts = int(U.shape[0])
    double = U.dtype == jnp.float64
    rtol = (1e-8 if double else 1e-5) if rtol is None else float(rtol)
    atol = (1e-10 if double else 1e-7) if atol is None else float(atol)
    fingerprint, components = problem.fingerprint(method, n_starts)

    engine = _cached_engine(problem, method, rtol=rtol, atol=atol, learning_rate=learning_rate, jac=jac)
    traces_before = engine.traces
    data = problem.data()
    dyn = engine.init(U, data)
    step_fn = engine.make_step()
    done = jnp.zeros(n_starts, dtype=bool)
    status = jnp.zeros(n_starts, dtype=jnp.int32)
    history: list[np.ndarray] = []
    step = 0
    resumed_from = 0
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if ckpt is not None:
        if ckpt.exists() and ckpt.is_dir():
            raise CheckpointError(f"checkpoint {ckpt} is a directory; give a file path such as {ckpt / 'fit-checkpoint.npz'}")
        if not ckpt.parent.is_dir():
            raise CheckpointError(f"directory {ckpt.parent} of checkpoint {ckpt.name} does not exist; create it first")
        if ckpt.exists():
            if not resume:
                raise CheckpointError(f"checkpoint {ckpt} exists; pass resume=True to continue that fit, or delete it to start afresh")
            U, dyn, done, status, history, step = _load_checkpoint(ckpt, fingerprint=fingerprint, components=components, dyn_template=dyn)
            status = status.astype(jnp.int32)
            resumed_from = step
    # Values, loss, Jacobian and predictions of every start in ONE compiled program (kept with
    # the engine), used at the start (the initial losses) and at the end (covariance,
    # predictions): fewer compilations than separate loss / Jacobian / predict programs (each
    # one compiles the whole forward model).
    evaluate = engine.make_evaluate()  # compiled on its first call only
    final_from_state = engine.make_final()
    if not history and final_from_state is None:
        history.append(np.asarray(evaluate(U, data)[1]))
    # Optimistix: the first step evaluates the starts and accepts them (its loss is the initial
    # loss, recorded as history[0] below), so no separate program is compiled for the start.

    def save():
        if ckpt is not None and history:
            _save_checkpoint(ckpt, U=U, dyn=dyn, done=done, status=status, history=np.stack(history), step=step, fingerprint=fingerprint, components=components, method=method)

    stopped_by_callback = False
    bar = _progress_bar(progress, max_steps)
    task = None
    if bar is not None:
        bar.start()
        task = bar.add_task("compiling + first step", total=max_steps, completed=step, loss=f"{np.nanmin(history[-1]):.6g}" if history else "-")
    try:
        while step < max_steps and not bool(np.all(np.asarray(done))):
            U, dyn, done, new_status, losses = step_fn(U, dyn, done, data)
            status = jnp.where(new_status != 0, new_status, status).astype(jnp.int32)
            step += 1
            losses = np.asarray(losses)
            if not history:  # optimistix: step 1 evaluated and accepted the starts
                history.append(losses)
            history.append(losses)
            if bar is not None:
                bar.update(task, completed=step, loss=f"{np.nanmin(losses):.6g}", description="fitting")
            if ckpt is not None and step % checkpoint_every == 0:
                save()
            if callback is not None:
                vals = {k: np.asarray(v) for k, v in jax.vmap(problem.values)(U).items()}
                info = FitProgress(step, float(np.nanmin(losses)), losses, vals, np.asarray(done))
                if callback(info) is True:
                    stopped_by_callback = True
                    break
    except BaseException:
        if step > resumed_from:  # nothing new to save before the first step (a rerun must not find a stale checkpoint)
            save()
        raise
    finally:
        if bar is not None:
            bar.stop()
    if history:
        save()

    result = None
    if final_from_state is not None:
        *result, ok = final_from_state(U, dyn, data)
        if not bool(np.all(np.asarray(ok))):
            result = None
    all_values, final, all_J, all_preds = evaluate(U, data) if result is None else result
    if not history:  # no step taken: the loss at the start is the final one
        history.append(np.asarray(final))
        save()
    if stopped_by_callback:
        stop_reason = "stopped by callback"
    else:
        stop_reason = f"max_steps ({max_steps}) reached"
    return _fit_result(
        problem, engine, U, all_values, final, all_J, all_preds, done, status, history, step,
        stop_reason=stop_reason, absolute_sigma=absolute_sigma, method=method, loss=loss, f_scale=f_scale,
        compilations=engine.traces - traces_before, resumed_from=resumed_from, stacklevel=3, plausible=plausible,
    )


def _fit_result(problem: FitProblem, engine: _Engine, U, all_values, final, all_J, all_preds, done, status, history, step, *,
                stop_reason: str, absolute_sigma: bool, method: str, loss: str, f_scale: float, compilations: int,
                resumed_from: int = 0, warning_prefix: str = "", stacklevel: int = 2, plausible=None) -> FitResult:
    """The :class:`FitResult` of one problem from the final state of its starts: best start,
    covariance, identifiability diagnostics (emitted as warnings, prefixed by
    ``warning_prefix``) and per-scenario outputs. ``history`` is a list of ``(S,)`` loss rows."""
    fields = problem.fields
    U = jnp.asarray(U)
    history = list(history)
    final = np.asarray(final)
    history[-1] = final
    finite = np.where(np.isfinite(final), final, np.inf)
    best = int(np.argmin(finite))
    if not np.isfinite(finite[best]):
        vals = np.asarray(all_values)
        shown = "; ".join(", ".join(f"{f} = {v:.6g}" for f, v in zip(fields, row)) for row in vals.reshape(len(vals), -1)[:4])
        raise FitError(f"{warning_prefix}every start ended with a non-finite loss (at {shown}); check the initial material "
                       "(a value far outside the tissue range, e.g. youngs_modulus = 1e308, gives non-finite predictions), the transforms and the scenarios' predictions")
    done_np = np.asarray(done)
    status_np = np.asarray(status)
    start_converged = done_np & (status_np == 0)
    if start_converged[best]:
        reason = "step and residual change below rtol/atol"
    elif status_np[best] != 0:
        reason = f"failed: {engine.status_message(int(status_np[best]))}"
    else:
        reason = stop_reason
    u_best = U[best]
    material = problem.material(u_best)
    values_vec = np.asarray(all_values[best])
    J = np.asarray(all_J[best])
    stats = parameter_statistics(J, np.asarray(values_vec), problem.fields, loss=float(final[best]), absolute_sigma=absolute_sigma)
    diag = identifiability_diagnostics(stats, np.asarray(values_vec), problem.fields)
    if not start_converged[best]:
        diag = [(f, f"{msg} (evaluated where the fit stopped without converging: {reason})") for f, msg in diag]
    for _, msg in diag:
        warnings.warn(warning_prefix + msg, IdentifiabilityWarning, stacklevel=stacklevel)

    # ------------------------------------------------------------ per-scenario outputs
    scen_fits = []
    predictions, residuals = {}, {}
    for sc, obs, sig, pred_all in zip(problem.scenarios, problem._observed, problem._sigma, all_preds):
        pred = np.asarray(pred_all[best], dtype=float)
        res = (pred - obs) / sig
        absc = getattr(sc, "abscissa", None)
        absc = np.arange(obs.size, dtype=float) if absc is None else np.asarray(absc, dtype=float)
        predictions[sc.name] = pred
        residuals[sc.name] = res
        scen_fits.append(ScenarioFit(sc.name, absc, obs, sig, pred, res, str(getattr(sc, "x_label", "index")), str(getattr(sc, "y_label", "observed")),
                                     _plot_layout(sc)))
    start_vals = np.asarray(all_values)
    result = FitResult(
        material=material,
        fields=fields,
        values={f: float(values_vec[i]) for i, f in enumerate(fields)},
        units={f: UNITS.get(f, "") for f in fields},
        standard_errors={f: float(stats["standard_errors"][i]) for i, f in enumerate(fields)},
        covariance=stats["covariance"],
        correlation=stats["correlation"],
        jacobian=J,
        loss=float(final[best]),
        converged=bool(start_converged[best]),
        reason=reason,
        steps=int(step),
        best_start=best,
        start_losses=final,
        start_values=start_vals,
        start_converged=start_converged,
        loss_history=np.stack(history),
        predictions=predictions,
        residuals=residuals,
        scenarios=tuple(scen_fits),
        warnings=tuple(msg for _, msg in diag),
        unidentified=tuple(dict.fromkeys(f for f, _ in diag)),
        condition_number=float(stats["condition_number"]),
        residual_variance=float(stats["residual_variance"]),
        dof=int(stats["dof"]),
        absolute_sigma=bool(absolute_sigma),
        method=method,
        loss_function=loss,
        f_scale=float(f_scale),
        unconstrained=np.asarray(u_best),
        compilations=int(compilations),
        resumed_from=resumed_from,
    )
    result = dataclasses.replace(result, effective_modulus=effective_modulus(result, problem.scenarios))
    quality = assess_quality(result, problem.parameterization, plausible=plausible)
    for flag in quality.flags:
        warnings.warn(f"{warning_prefix}{flag.severity}: {flag.message}", FitQualityWarning, stacklevel=stacklevel)
    return dataclasses.replace(result, quality=quality)


# ============================================================================ outputs
def package_versions() -> dict[str, str | None]:
    """Installed versions of difftissue and the numerical stack (None where not installed)."""
    from ._version import __version__

    out: dict[str, str | None] = {"difftissue": __version__}
    for name in ("jax", "jaxlib", "numpy", "equinox", "optimistix", "optax", "lineax", "matplotlib"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _sha256(path: Path) -> str:
    return sha256_file(path)


def _num(x):
    """JSON number or null (strict JSON has no inf/NaN)."""
    x = float(x)
    return x if math.isfinite(x) else None


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return _num(obj)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(obj).tolist())
    return str(obj)


def _config_dir(config):
    """The folder of a config given as a path (data paths are stored relative to it), else None."""
    return Path(config).parent if isinstance(config, (str, os.PathLike)) else None


def _config_record(config):
    if config is None:
        return None
    if isinstance(config, (str, os.PathLike)):
        path = Path(config)
        if not path.is_file():
            raise OutputError(f"config file {path} does not exist")
        record: dict[str, Any] = {"path": path.name, "sha256": _sha256(path)}
        if path.suffix.lower() == ".toml":
            import tomllib

            with open(path, "rb") as fh:
                record["content"] = _jsonable(tomllib.load(fh))
        else:
            record["text"] = path.read_text(encoding="utf-8", errors="replace")
        return record
    if isinstance(config, Mapping):
        return _jsonable(config)
    raise OutputError(f"config must be a mapping or a path, got {type(config).__name__}")


def _fit_json(result: FitResult, *, config, data_files, model, scenario_names) -> dict:
    from .export import portable_path

    fields = list(result.fields)
    params = {}
    for f in fields:
        se = result.standard_errors[f]
        v = result.values[f]
        params[f] = {
            "value": _num(v),
            "unit": result.units[f],
            "standard_error": _num(se),
            "relative_standard_error": _num(se / abs(v)) if v != 0 and math.isfinite(se) else None,
        }
    model_name = None if model is None else (model if isinstance(model, str) else getattr(model, "name", None) or type(model).__name__)
    return {
        "schema": "difftissue-fit/1",
        "parameters": params,
        "fixed_parameters": {k: {"value": v, "unit": UNITS.get(k, "")} for k, v in result.material.to_dict().items() if k not in fields},
        "correlation": {"fields": fields, "matrix": _jsonable(result.correlation)},
        "covariance": {"fields": fields, "matrix": _jsonable(result.covariance), "absolute_sigma": result.absolute_sigma},
        "loss": _num(result.loss),
        "loss_function": result.loss_function,
        "f_scale": result.f_scale,
        "converged": bool(result.converged),
        "reason": result.reason,
        "steps": result.steps,
        "method": result.method,
        "starts": {"count": int(result.start_losses.size), "best": result.best_start, "final_losses": _jsonable(result.start_losses)},
        "residual_variance": _num(result.residual_variance),
        "degrees_of_freedom": result.dof,
        "condition_number": _num(result.condition_number),
        "identifiability_warnings": list(result.warnings),
        "quality": result.quality.to_json() if result.quality is not None else None,
        "effective_modulus": _jsonable(result.effective_modulus),
        "discretisation": _jsonable(result.discretisation),
        "unidentified": list(result.unidentified),
        "model": model_name,
        "scenarios": [
            {"name": s.name, "points": int(s.observed.size), "rms_scaled_residual": _num(np.sqrt(np.mean(s.residual**2)))}
            for s in result.scenarios
        ]
        if scenario_names is None
        else [{"name": str(n)} for n in scenario_names],
        "data_files": [{"path": portable_path(p, _config_dir(config)), "sha256": _sha256(Path(p))} for p in data_files],
        "versions": package_versions(),
        "config": _config_record(config),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


#: SI prefixes for plot axes, by unit: (factor, label).
_PREFIXES = {
    "m": ((1e-9, "nm"), (1e-6, "µm"), (1e-3, "mm"), (1.0, "m")),
    "N": ((1e-9, "nN"), (1e-6, "µN"), (1e-3, "mN"), (1.0, "N")),
    "Pa": ((1.0, "Pa"), (1e3, "kPa"), (1e6, "MPa"), (1e9, "GPa")),
}


def human_unit(values, unit: str) -> tuple[float, str]:
    """``(factor, label)`` such that ``values / factor`` reads well in ``label``: the largest
    prefix of ``unit`` (m, N, Pa; strain ``-``/``1`` as %) not above max|values|; other units as given."""
    v = np.asarray(values, dtype=float)
    peak = float(np.nanmax(np.abs(v))) if v.size and np.any(np.isfinite(v)) else 0.0
    if unit in ("-", "1"):
        return 0.01, "%"
    choices = _PREFIXES.get(unit)
    if not choices:
        return 1.0, unit
    best = choices[0]
    for f, label in choices:
        if peak >= f:
            best = (f, label)
    return best


def _split_label(label: str) -> tuple[str, str]:
    """``"depth [m]"`` -> ``("depth", "m")``; no unit -> ``(label, "")``."""
    import re

    m = re.match(r"^(.*?)\s*\[([^\]]*)\]\s*$", label)
    return (m.group(1), m.group(2)) if m else (label, "")


def _value_text(value: float, se: float, unit: str) -> str:
    """``"158.5 ± 0.96 Pa"`` in a human prefix of ``unit`` (SI value and standard error)."""
    f, u = human_unit([value], unit) if unit in _PREFIXES else (1.0, _unit_text(unit))
    se_txt = f" ± {se / f:.2g}" if se is not None and math.isfinite(se) else " (se not determined)"
    return f"{value / f:.4g}{se_txt} {u}".rstrip()


def _fit_title(result: FitResult) -> str:
    """The figure's title: each fitted value with its standard error, E* where named, the quality verdict."""
    parts = [f"{f} = {_value_text(result.values[f], result.standard_errors[f], result.units[f])}" for f in result.fields]
    em = result.effective_modulus
    if em is not None:
        parts.append(f"E* = E/(1-ν²) = {_value_text(em['value'], em['standard_error'], 'Pa')} (ν = {em['poisson_ratio_assumed']:g} assumed)")
    if result.quality is not None:
        parts.append(f"quality: {result.quality.summary()}")
    return "\n".join(parts)


def _plot_curve(top, bottom, s: ScenarioFit) -> None:
    """Data with sigma bars and the model against the abscissa, in human units; residuals below."""
    xname, xunit = _split_label(s.x_label)
    yname, yunit = _split_label(s.y_label)
    fx, ux = human_unit(s.abscissa, xunit)
    fy, uy = human_unit(s.observed, yunit)
    x = np.asarray(s.abscissa) / fx
    top.errorbar(x, s.observed / fy, yerr=s.sigma / fy, fmt="o", ms=3, lw=0.8, color="0.3", label="data")
    # the model as lines along each increasing run of the abscissa (a scenario may concatenate
    # several outputs or loading segments); as markers when the points are not ordered
    runs = np.split(np.arange(x.size), np.nonzero(np.diff(x) < 0)[0] + 1)
    if min(len(r) for r in runs) >= 2:
        for i, run in enumerate(runs):
            top.plot(x[run], s.predicted[run] / fy, "-", color="C0", lw=1.6, label="model" if i == 0 else None)
    else:
        top.plot(x, s.predicted / fy, "x", color="C0", ms=5, label="model")
    top.set_ylabel(f"{yname} [{uy}]" if uy else yname)
    top.legend(frameon=False)
    bottom.plot(x, s.residual, "o", ms=3, color="C3")
    bottom.set_xlabel(f"{xname} [{ux}]" if ux else xname)


def _plot_fem_field(axes, s: ScenarioFit) -> None:
    """A fem_field scenario: displacement profile (each observed component against the node's
    distance from the most displaced node, data dots, model crosses), its residuals, and the
    reaction force in its own panel (magnitude, with the direction said in the label)."""
    top, bottom, side = axes
    lay = s.layout
    nd = len(lay["components"])
    pts = np.asarray(lay["points"], dtype=float)
    comp = np.asarray(lay["components"], dtype=int)
    obs_u, pred_u, res_u = s.observed[:nd], s.predicted[:nd], s.residual[:nd]
    centre = pts[int(np.argmax(np.abs(obs_u)))]
    r = np.linalg.norm((pts - centre)[:, :2], axis=1)
    fr, ur = human_unit(r, "m")
    fu, uu = human_unit(obs_u, "m")
    for c in np.unique(comp):
        k = comp == c
        top.plot(r[k] / fr, obs_u[k] / fu, "o", ms=3.5, color=f"C{c}", alpha=0.8, label=f"u{'xyz'[c]} data")
        top.plot(r[k] / fr, pred_u[k] / fu, "x", ms=5, mew=1.4, color=f"C{c}", label=f"u{'xyz'[c]} model")
        bottom.plot(r[k] / fr, res_u[k], "o", ms=3, color=f"C{c}")
    top.set_ylabel(f"displacement [{uu}]")
    top.set_title(f"{s.name}: displacement profile")
    top.legend(frameon=False, fontsize=8, ncol=2)
    bottom.set_xlabel(f"lateral distance from the most displaced node [{ur}]")
    forces = lay["force_components"]
    if side is None:
        return
    if not forces:
        side.set_axis_off()
        return
    F_obs, F_pred, F_sig = s.observed[nd:], s.predicted[nd:], s.sigma[nd:]
    ff, uf = human_unit(F_obs, "N")
    idx = np.arange(len(forces))
    side.bar(idx - 0.15, np.abs(F_obs) / ff, 0.3, yerr=F_sig / ff, color="0.6", label="measured")
    side.bar(idx + 0.15, np.abs(F_pred) / ff, 0.3, color="C0", label="model")
    side.set_xlim(-0.75, len(forces) - 0.25)
    side.set_xticks(idx, [f"{'-' if o < 0 else '+'}{c}" for c, o in zip(forces, F_obs)])
    side.set_ylabel(f"reaction force magnitude [{uf}]")
    side.set_xlabel("reaction direction (-z: pushed into the specimen)")
    side.set_title("reaction force")
    for i, (o, p) in enumerate(zip(F_obs, F_pred)):
        side.annotate(f"{abs(o) / ff:.4g} / {abs(p) / ff:.4g}", (i, max(abs(o), abs(p)) / ff), ha="center", va="bottom", fontsize=8)
    side.legend(frameon=True, fontsize=8, loc="lower center")


def _plot_fit(result: FitResult, path: Path):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    k = len(result.scenarios)
    fem = [s.layout is not None and s.layout.get("kind") == "fem_field" for s in result.scenarios]
    cols = k + sum(fem)  # a fem_field scenario gets a second column for its force
    fig = Figure(figsize=(5.0 * cols, 6.0), layout="constrained")
    axes = fig.subplots(2, cols, height_ratios=[3, 1], squeeze=False)
    j = 0
    for s, is_fem in zip(result.scenarios, fem):
        top, bottom = axes[0, j], axes[1, j]
        bottom.sharex(top)
        if is_fem:
            side = axes[0, j + 1]
            axes[1, j + 1].set_axis_off()
            _plot_fem_field((top, bottom, side), s)
            j += 2
        else:
            _plot_curve(top, bottom, s)
            top.set_title(s.name)
            j += 1
        bottom.axhline(0.0, color="0.6", lw=0.8)
        bottom.set_ylabel("residual / sigma")
    fig.suptitle(_fit_title(result), fontsize=9)
    fig.savefig(path, format="png", dpi=110)


def _plot_loss(result: FitResult, path: Path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 3.8), layout="constrained")
    ax = fig.subplots()
    H = np.asarray(result.loss_history, dtype=float)
    steps = np.arange(H.shape[0])
    tiny = np.finfo(float).tiny
    for s in range(H.shape[1]):
        best = s == result.best_start
        ax.plot(steps, np.clip(H[:, s], tiny, None), color="C0" if best else "0.7", lw=1.8 if best else 0.8, label="best start" if best else None, zorder=3 if best else 2)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss [-]")
    ax.set_title(f"{result.method}, {H.shape[1]} start(s)")
    ax.legend(frameon=False)
    fig.savefig(path, format="png", dpi=110)


def _unit_text(unit: str) -> str:
    """Unit for prose: empty for dimensionless ("1")."""
    return "" if unit == "1" else unit


def _quality_md(quality: "FitQuality | None") -> list[str]:
    """The report's "Quality" section: verdict, flags, residual statistics per scenario."""
    if quality is None:
        return []
    verdict = {"ok": "**OK**: no quality flag raised.",
               "warnings": "**Usable, with warnings** (see below).",
               "unusable": "**UNUSABLE**: do not use these values (the CLI exits with status 3)."}[quality.verdict]
    lines = ["", "## Quality", "", verdict]
    if quality.flags:
        lines += ["", "| flag | severity | subject | finding |", "|---|---|---|---|"]
        lines += [f"| {f.name} | {f.severity} | {f.subject or '-'} | {f.message} |" for f in quality.flags]
    lines += ["", "| scenario | points | rms residual/sigma | lag-1 autocorrelation | sign runs (expected) | runs test p |", "|---|---|---|---|---|---|"]
    fmt = lambda x, spec: "-" if x is None or not np.isfinite(x) else format(x, spec)  # noqa: E731
    for name, st in quality.scenarios.items():
        lines.append(f"| {name} | {st['points']} | {fmt(st['rms'], '.3g')} | {fmt(st['lag1_autocorrelation'], '.2f')} | "
                     f"{st['runs']} ({fmt(st['runs_expected'], '.1f')}) | {fmt(st['runs_p'], '.2g')} |")
    lines += ["", f"Thresholds: errors for a parameter within {BOUND_FRACTION:g} of a transform bound, a value outside its plausible range "
              f"(E in [{PLAUSIBLE['youngs_modulus'][0]:g}, {PLAUSIBLE['youngs_modulus'][1]:g}] Pa unless fit.plausible says otherwise), "
              f"non-finite values, no convergence; warnings for rms residual/sigma > {RMS_LIMIT:g}, lag-1 autocorrelation > "
              f"{AUTOCORRELATION_LIMIT:g} or runs test p < {RUNS_P_LIMIT:g} (judged where rms >= {STRUCTURE_MIN_RMS:g}); "
              "a warning where the mesh's estimated share of a value's error exceeds its standard error (discretisation_error)."]
    return lines


def _discretisation_md(rec: Mapping | None) -> list[str]:
    """The report's "Discretisation error" section (nothing when the check was off)."""
    if rec is None or rec.get("status") == "not applicable":
        return []
    lines = ["", "## Discretisation error", ""]
    if rec.get("status") == "estimated":
        lines += ["| parameter | estimate (fit - mesh-converged) | relative | standard error | estimate / SE | mesh-converged value |", "|---|---|---|---|---|---|"]
        for f, d in rec["estimate"].items():
            lines.append(f"| {f} | {d:+.4g} | {100 * rec['relative'][f]:+.3g} % | {rec['standard_error'][f]:.4g} | "
                         f"{rec['ratio_to_standard_error'][f]:.3g} | {rec['corrected'][f]:.6g} |")
        lines.append("")
    lines.append("| scenario | status | cells (fit / coarse) | prediction change | reason |")
    lines.append("|---|---|---|---|---|")
    for k, v in rec["scenarios"].items():
        if v["status"] == "estimated":
            lines.append(f"| {k} | estimated | {v['fine_cells']} / {v['coarse_cells']} | {100 * v['prediction_change_relative']:.3g} % | - |")
        else:
            lines.append(f"| {k} | not estimated | - | - | {v['reason']} |")
    lines += ["", "One evaluation at the fitted values on a mesh of about half the cells in each direction, no refit; "
              "Richardson extrapolation assuming first-order convergence in the cell size gives the fit mesh's error in the "
              "predictions, converted to the parameters through the fit's Jacobian (linearised). An estimate, not a bound: "
              "see docs/fitting.md, \"Discretisation error\"."]
    return lines


def _start_md(start) -> list[str]:
    """report.md's "Starting values": each field whose start the data chose (or tried to)."""
    if not start:
        return []
    lines = ["", "## Starting values", "", "| parameter | start | config's [material] | from |", "|---|---|---|---|"]
    for f, d in start.items():
        how = f"{d['from']} (no estimate from the data: {d['no_estimate']})" if d.get("no_estimate") else d["from"]
        lines.append(f"| {f} | {d['value']:.6g} | {d['config_value']:.6g} | {how} |")
    return lines + ["", 'fit.start = "material" starts from the config\'s [material] instead.']


def _report_md(result: FitResult, record: dict, names: Sequence[str]) -> str:
    lines = ["# Fit report", ""]
    lines.append(f"Model: {record['model'] or '(not given)'}; scenarios: {', '.join(names)}.")
    lines.append(
        f"Method {result.method}, loss {result.loss_function}"
        + (f" (f_scale {result.f_scale:g})" if result.loss_function != "linear" else "")
        + f", {int(result.start_losses.size)} start(s) (best: {result.best_start})."
    )
    lines.append(f"**{'Converged' if result.converged else 'Not converged'}** after {result.steps} steps: {result.reason}. Final loss {result.loss:.6g}."
                 + (f" Quality: {result.quality.summary()}." if result.quality is not None else ""))
    lines += ["", "## Parameters", "", "| parameter | value | standard error | relative | unit |", "|---|---|---|---|---|"]
    for f in result.fields:
        v, se = result.values[f], result.standard_errors[f]
        rel = f"{100 * se / abs(v):.3g} %" if v != 0 and math.isfinite(se) else "-"
        se_txt = f"{se:.4g}" if math.isfinite(se) else "not determined"
        lines.append(f"| {f} | {v:.6g} | {se_txt} | {rel} | {_unit_text(result.units[f]) or '-'} |")
    if result.effective_modulus is not None:
        em = result.effective_modulus
        se = em["standard_error"]
        lines += ["", f"**Effective modulus E\\* = E/(1-nu^2) = {em['value']:.6g}"
                  + (f" ± {se:.4g}" if math.isfinite(se) else "") + f" Pa** ({em['law']}). {em['meaning']}."]
    cov_txt = "(J^T J)^-1 (absolute sigma)" if result.absolute_sigma else f"s^2 (J^T J)^-1 with s^2 = SSE/(n-p) = {result.residual_variance:.4g} (n-p = {result.dof})"
    lines += ["", f"Standard errors from the Gauss-Newton covariance {cov_txt}; condition number of J^T J (scaled) {result.condition_number:.3g}."]
    if record["fixed_parameters"]:
        lines += ["", "Fixed: " + ", ".join(f"{k} = {d['value']:g}{' ' + _unit_text(d['unit']) if _unit_text(d['unit']) else ''}" for k, d in record["fixed_parameters"].items()) + "."]
    lines += _start_md(record.get("start"))
    lines += _quality_md(result.quality)
    lines += _discretisation_md(result.discretisation)
    if len(result.fields) > 1:
        lines += ["", "## Correlations", "", "| | " + " | ".join(result.fields) + " |", "|---" * (len(result.fields) + 1) + "|"]
        for i, f in enumerate(result.fields):
            cells = [f"{c:+.3f}" if np.isfinite(c) else "-" for c in result.correlation[i]]
            lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", "## Warnings", ""]
    data_warnings = [f"- data: {w}" for w in record.get("data_warnings", ())]
    lines += data_warnings + [f"- {w}" for w in result.warnings] or ["None from the data or identifiability checks (every parameter is determined by the data); the fit's quality flags are under Quality."]
    if record.get("data_rows"):
        lines += ["", "## Data rows", "", "| experiment | file | rows used | rows loaded | left out or reordered |", "|---|---|---|---|---|"]
        for d in record["data_rows"]:
            steps = "; ".join(f"{st['action']} {len(st['rows'])}: {st['reason']}" for st in d["steps"]) or "-"
            lines.append(f"| {d['experiment']} | `{Path(d['file']).name}` | {d['rows_used']} | {d['rows_loaded']} ({d['loaded']}) | {steps} |")
        lines += ["", "The row numbers are in `fit.json` (`data_rows`)."]
    lines += ["", "## Scenarios", "", "| scenario | points | rms residual / sigma |", "|---|---|---|"]
    for s in result.scenarios:
        lines.append(f"| {s.name} | {s.observed.size} | {np.sqrt(np.mean(s.residual ** 2)):.4g} |")
    lines += ["", "## Files", "", "- `fit.json`: parameters, uncertainty, versions", "- `material.json`: the material card for `difftissue export`", "- `fit.png`: data vs model with residuals", "- `loss.png`: loss history"]
    for d in record["data_files"]:
        lines.append(f"- data `{d['path']}` (sha256 `{d['sha256']}`)")
    lines += ["", "Versions: " + ", ".join(f"{k} {v}" for k, v in record["versions"].items() if v) + "."]
    return "\n".join(lines) + "\n"


def write_fit_outputs(
    result: FitResult,
    out_dir,
    *,
    config=None,
    data_files: Sequence[str | os.PathLike] = (),
    model=None,
    scenario_names: Sequence[str] | None = None,
    force: bool = False,
    scenario_records: Sequence[dict] | None = None,
    scenarios: Sequence | None = None,
    data: Sequence[Mapping] = (),
    data_warnings: Sequence[str] = (),
    start: Mapping | None = None,
) -> dict[str, Path]:
    """Write ``fit.json``, ``material.json``, ``fit.png``, ``loss.png`` and ``report.md`` into
    ``out_dir``, and ``specimen-<name>.vtu`` for each simulated ``fem_field``, ``compression``
    or ``incision`` scenario among ``scenarios``.

    ``material.json`` is the versioned material card (:class:`~difftissue.export.MaterialCard`)
    that ``difftissue export`` reads: model, energy, parameters with units and standard
    errors, provenance.

    Args:
        result: a :class:`FitResult`.
        out_dir: output directory (created if missing).
        config: the run's configuration: a mapping (stored as is) or a config file path
            (stored with its sha256 and, for TOML, its parsed content).
        data_files: measured-data files used by the fit; each is recorded with its sha256.
        model: model name (str) or object (its ``name`` or type name is recorded).
        scenario_names: names to record instead of the result's scenarios.
        scenario_records: per-scenario experiment records for the card
            (:func:`difftissue.export_indentation.scenario_record`: indenter, radius, depths, ...),
            used by ``difftissue export --specimen indentation``; default (with ``scenarios``)
            ``scenario_record(s)`` of each scenario.
        scenarios: the fitted scenarios: each :class:`~difftissue.scenarios.FEMField`,
            :class:`~difftissue.scenarios.Compression` and :class:`~difftissue.incision.Incision`
            gets its specimen file
            (:func:`difftissue.export_fitted.write_specimen`: mesh, fixed masks, prescribed
            displacements, regions, cut pairs), recorded with its sha256 in its scenario record
            (``specimen_file``), which ``difftissue export --specimen fitted`` reads.
        data: the rows of each data file the fit used and those it reordered or left out, with
            why (:attr:`difftissue.config.FitConfig.data_provenance`); recorded as ``data_rows``
            in ``fit.json`` and in the report's "Data rows" section.
        data_warnings: plausibility warnings of the data (a likely unit mistake, ...); recorded
            as ``data_warnings`` in ``fit.json`` and first under the report's "Warnings".
        start: where the initial values came from when the data chose them
            (:attr:`difftissue.config.FitConfig.start`); recorded as ``start`` in ``fit.json``.
        force: overwrite existing output files. Without it, an existing file among the five
            (or a specimen file to be written) raises :class:`~difftissue.errors.OutputExistsError`
            naming it, before anything is written.

    Every file is written atomically (temporary file beside it, then ``os.replace``).

    Returns:
        ``{file name: path}`` of the written files.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory")
    paths = {name: out / name for name in OUTPUT_FILES}
    specimens = {}
    if scenarios is not None:
        from .export_fitted import fitted_specimen, specimen_file_name
        from .export_indentation import scenario_record

        if scenario_records is None:
            scenario_records = [scenario_record(s) for s in scenarios]
        for s in scenarios:
            sp = fitted_specimen(s)
            if sp is None:
                continue
            fname = specimen_file_name(sp.scenario)
            if fname in specimens:
                raise OutputError(f"scenarios {specimens[fname].scenario!r} and {sp.scenario!r} would share the specimen file {fname}: give them distinct names")
            specimens[fname] = sp
        paths.update({fname: out / fname for fname in specimens})
    if not force:
        for p in paths.values():
            if p.exists():
                raise OutputExistsError(f"{p} exists; refusing to overwrite it (choose another output directory or pass force=True / --force)")
    for p in data_files:
        if not Path(p).is_file():
            raise OutputError(f"data file {p} does not exist")
    names = list(scenario_names) if scenario_names is not None else list(result.scenario_names)
    record = _fit_json(result, config=config, data_files=data_files, model=model, scenario_names=scenario_names)
    record["data_warnings"] = [str(w) for w in data_warnings]
    record["data_rows"] = [dict(d) for d in data]
    record["start"] = _jsonable(start) if start else None
    out.mkdir(parents=True, exist_ok=True)
    with atomic_output(paths["fit.json"], overwrite=force) as tmp:
        tmp.write_text(json.dumps(record, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    from .export import card_from_fit

    if specimens:
        from .export_fitted import specimen_record, write_specimen

        scenario_records = [dict(r) if r else r for r in scenario_records]
        for fname, sp in specimens.items():
            write_specimen(sp, paths[fname], force=force)
            matched = [r for r in scenario_records if r and r.get("name") == sp.scenario]
            if not matched:
                scenario_records.append({"name": sp.scenario, "experiment": sp.experiment, "model": sp.model})
                matched = scenario_records[-1:]
            for r in matched:
                r["specimen_file"] = specimen_record(sp, paths[fname])
    model_name = None if model is None else (model if isinstance(model, str) else getattr(model, "name", None) or type(model).__name__)
    card = card_from_fit(result, model=model_name or "unspecified", scenario_names=names, data_files=data_files,
                         scenario_records=scenario_records, base_dir=_config_dir(config))
    with atomic_output(paths["material.json"], overwrite=force) as tmp:
        tmp.write_text(card.to_json(), encoding="utf-8")
    with atomic_output(paths["fit.png"], overwrite=force) as tmp:
        _plot_fit(result, tmp)
    with atomic_output(paths["loss.png"], overwrite=force) as tmp:
        _plot_loss(result, tmp)
    with atomic_output(paths["report.md"], overwrite=force) as tmp:
        tmp.write_text(_report_md(result, record, names), encoding="utf-8")
    if force:
        _remove_stale_specimens(out, keep=set(specimens))
    return paths


def _remove_stale_specimens(out: Path, keep: set) -> list[Path]:
    """Remove the ``specimen-*.vtu`` files of an earlier fit in ``out`` that this fit did not
    write (``--force``: the folder then holds one fit's outputs, not a mix of two)."""
    removed = []
    for p in sorted(out.glob("specimen-*.vtu")):
        if p.name not in keep:
            p.unlink()
            removed.append(p)
    return removed
