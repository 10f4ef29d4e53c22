"""Budget-aware calibration: effective material parameters for a given XPBD budget.

Standard (real-time) XPBD with a fixed iteration budget does not converge each frame's
solve, and the state it settles to is softer than the model's static equilibrium (see
``docs/xpbd.md``). :func:`calibrate_for_budget` finds the *effective* material that makes
the budgeted XPBD solve reproduce a reference static response (the same model solved to
convergence with :func:`~difftissue.solvers.solve_static`, or a ``fem_linear`` model) at the
true material, by least squares on the relative observable mismatch with the Jacobian
taken through the unrolled XPBD loop (forward mode): the fit engine's Levenberg--Marquardt
(:func:`difftissue.fit.residuals.least_squares`, the engine of :func:`difftissue.fit.fit`),
which also gives the Gauss--Newton covariance of the calibrated fields. The result records
the setting (dt, substeps, iterations, method) it is valid for: an effective material is
only meaningful for that setting, that mesh resolution and similar loading.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .boundary import BoundaryConditions
from .errors import ConfigError, ConvergenceError, DifftissueWarning, ModelError
from .fit.residuals import ResidualProblem, least_squares
from .materials import MATERIAL_FIELDS, Identity, Material, ScaledLogit
from .models import MODELS, ElasticModel, make_model
from .solvers.static import solve_static
from .solvers.xpbd import XPBDSettings, xpbd_quasi_static

__all__ = ["BudgetCalibration", "calibrate_for_budget", "FITTABLE_FIELDS"]

#: fields that can be calibrated, with the transform to unconstrained space used for the steps
FITTABLE_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient")
_NU_LO, _NU_HI = 0.0, 0.4999


#: The unconstrained variable of each field in the optimiser (a function of the true material,
#: which sets the scale): log E (scaled by the true E), nu in (0, 0.4999) by a scaled logit, the
#: cubic coefficient as it is.
_TRANSFORMS = {
    # E within exp(+-reach) of the true value: log-like in between (a logit of E between those
    # bounds), so a saturated setting (a response insensitive to E) ends at a bound instead of
    # drifting to 1e34 x E.
    "youngs_modulus": lambda m, reach: ScaledLogit(float(m.youngs_modulus) * math.exp(-reach), float(m.youngs_modulus) * math.exp(reach)),
    "poisson_ratio": lambda m, reach: ScaledLogit(_NU_LO, _NU_HI),
    "cubic_coefficient": lambda m, reach: Identity(),
}


@dataclasses.dataclass(frozen=True)
class BudgetCalibration:
    """Result of :func:`calibrate_for_budget`.

    Attributes:
        material: the calibrated (effective) material for the budgeted XPBD setting.
        true_material: the material the reference was computed with.
        fit_fields: the calibrated fields.
        setting: ``{"dt", "substeps", "iterations", "method"}``: the XPBD setting the
            calibrated material is valid for (and only for).
        model_kind: the XPBD model kind.
        reference_kind: what the reference response came from (model kind).
        reference: the reference observable (array).
        naive: the observable of the budgeted XPBD solve at the true material.
        calibrated: the observable of the budgeted XPBD solve at the calibrated material.
        naive_error, calibrated_error: relative errors ``|obs - ref| / |ref|`` (2-norm).
        steps: optimiser steps taken (Levenberg--Marquardt trial steps after the start's
            evaluation; 0 when the naive error already met ``rtol``).
        converged: ``calibrated_error <= rtol``.
        jacobian: ``(n, p)`` derivative of the relative mismatch ``(obs - ref) / |ref|`` [-]
            with respect to the calibrated fields (SI) at the calibrated material.
        covariance: ``(p, p)`` Gauss--Newton covariance ``s^2 (J^T J)^-1`` of the calibrated
            fields (SI units squared), ``s^2 = |mismatch|^2 / (n - p)``: how well the
            observables pin the effective fields down given the mismatch left. NaN when there
            are no more observables than fields (``dof = 0``, e.g. the scalar ``"reaction"``
            with one field): the calibration then matches exactly and has no scatter to go by.
        standard_errors: ``{field: sqrt(covariance_ii)}`` (SI; NaN when ``dof = 0``).
        dof: observables minus calibrated fields.
    """

    material: Material
    true_material: Material
    fit_fields: tuple
    setting: dict
    model_kind: str
    reference_kind: str
    reference: np.ndarray
    naive: np.ndarray
    calibrated: np.ndarray
    naive_error: float
    calibrated_error: float
    steps: int
    converged: bool
    jacobian: np.ndarray | None = None
    covariance: np.ndarray | None = None
    standard_errors: dict = dataclasses.field(default_factory=dict)
    dof: int = 0

    def ratio(self, field: str = "youngs_modulus") -> float:
        """Calibrated / true value of ``field``."""
        return float(getattr(self.material, field)) / float(getattr(self.true_material, field))


def _reaction_observable(bc: BoundaryConditions):
    """Total reaction force on the nodes with a non-zero prescribed displacement, projected on
    the direction of their summed prescribed displacement (a scalar, N; with the solvers'
    reaction convention -- internal elastic force on the prescribed components -- it is
    positive when the tissue resists the prescribed motion)."""
    fixed = np.asarray(bc.fixed)
    disp = np.where(fixed, np.asarray(bc.displacement), 0.0)
    moved = np.any(np.abs(disp) > 0, axis=1)
    if not moved.any():
        raise ConfigError(
            "observable='reaction' needs nodes with a non-zero prescribed displacement "
            "(the total reaction on them is the observable); pass a function of the displacement instead"
        )
    idx = np.flatnonzero(moved)
    direction = disp[idx].sum(axis=0)
    if np.linalg.norm(direction) == 0.0:
        raise ConfigError("observable='reaction': the prescribed displacements sum to zero; pass a function instead")
    direction = jnp.asarray(direction / np.linalg.norm(direction))
    mask = jnp.asarray(fixed[idx])

    def obs(displacement, reaction):
        total = jnp.sum(jnp.where(mask, reaction[idx], 0.0), axis=0)
        return jnp.atleast_1d(jnp.dot(total, direction))

    return obs


def calibrate_for_budget(
    mesh,
    model_kind: str,
    material: Material,
    bc: BoundaryConditions,
    settings: XPBDSettings,
    *,
    reference=None,
    fit_fields=("youngs_modulus",),
    observable="reaction",
    max_steps: int = 10,
    rtol: float = 1e-3,
    tol: float = 1e-10,
    max_frames: int = 5000,
    max_log_step: float = 1.0,
) -> BudgetCalibration:
    """Effective material parameters for a budgeted XPBD setting.

    Args:
        mesh: the :class:`~difftissue.mesh.TetMesh`.
        model_kind: XPBD model kind (``"springs_volume"`` or ``"stable_neo_hookean"``).
        material: the true :class:`~difftissue.materials.Material` (scalar fields).
        bc: prescribed displacements / forces (the same for the reference and XPBD).
        settings: the target :class:`~difftissue.solvers.xpbd.XPBDSettings` (dt, substeps,
            iterations, method). ``warm_start`` should be ``False`` (standard real-time XPBD);
            with ``True`` XPBD converges to the static answer and there is nothing to calibrate.
        reference: ``None`` (the static solve of the same model kind), a model kind string
            (e.g. ``"fem_linear"``) or an :class:`~difftissue.models.ElasticModel`.
        fit_fields: fields of ``material`` to calibrate (subset of :data:`FITTABLE_FIELDS`).
            Levenberg--Marquardt (damped Gauss--Newton) also when there are more fields than
            observables.
        observable: ``"reaction"`` (total reaction force on the nodes with a non-zero
            prescribed displacement, projected on the direction of their summed prescribed
            displacement: a scalar) or a function ``f(displacement) -> array``.
        max_steps: optimiser steps allowed (after the evaluation of the true material).
        rtol: stop when the relative error is at most this.
        tol, max_frames: convergence tolerance and frame limit of the quasi-static XPBD solve.
        max_log_step: the calibrated Young's modulus stays within
            ``exp(+-max_log_step * max_steps)`` of the true one (the reach of ``max_steps``
            steps of at most ``max_log_step`` in ``log E``): a saturated setting ends at that
            bound with ``converged=False``. Must be > 0.

    Raises:
        ConfigError: unknown field / observable, bad settings or step counts.
        ModelError: a model kind XPBD or the reference cannot use.
        ConvergenceError: the reference or the budgeted XPBD solve did not come to rest.

    Warns:
        DifftissueWarning: the error did not reach ``rtol`` (``converged`` is then False);
            typically the budgeted response is saturated and no material can fix it.
    """
    # ------------------------------------------------------------------ validation
    if not isinstance(settings, XPBDSettings):
        raise ConfigError(f"settings must be an XPBDSettings, got {type(settings).__name__}")
    if settings.warm_start:
        raise ConfigError(
            "settings.warm_start=True makes quasi-static XPBD converge to the static answer for any "
            "budget; calibrate the standard real-time setting (warm_start=False)"
        )
    if not isinstance(material, Material):
        raise ConfigError(f"material must be a Material, got {type(material).__name__}")
    if model_kind not in ("springs_volume", "stable_neo_hookean"):
        raise ModelError(
            f"model_kind must be an XPBD model ('springs_volume' or 'stable_neo_hookean'), got {model_kind!r}"
        )
    if isinstance(fit_fields, str):
        fit_fields = (fit_fields,)
    fit_fields = tuple(fit_fields)
    if not fit_fields:
        raise ConfigError("fit_fields is empty")
    for f in fit_fields:
        if f not in FITTABLE_FIELDS:
            raise ConfigError(f"fit_fields: {f!r} cannot be calibrated; choose from {FITTABLE_FIELDS}")
    if len(set(fit_fields)) != len(fit_fields):
        raise ConfigError(f"fit_fields has duplicates: {fit_fields}")
    for f in fit_fields:
        if np.ndim(getattr(material, f)) != 0:
            raise ConfigError(f"material.{f} must be a scalar to be calibrated (one value per region is not supported)")
    if "poisson_ratio" in fit_fields and not (_NU_LO < float(material.poisson_ratio) < _NU_HI):
        raise ConfigError(f"poisson_ratio must lie in ({_NU_LO}, {_NU_HI}) to be calibrated")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise ConfigError(f"max_steps must be an integer >= 0, got {max_steps!r}")
    if not rtol > 0:
        raise ConfigError(f"rtol must be > 0, got {rtol!r}")
    if not max_log_step > 0:
        raise ConfigError(f"max_log_step must be > 0, got {max_log_step!r}")

    model = make_model(mesh, model_kind)
    if reference is None:
        ref_model, ref_kind = model, model_kind
    elif isinstance(reference, str):
        if reference not in MODELS:
            raise ModelError(f"reference must be one of {MODELS} or an ElasticModel, got {reference!r}")
        ref_model, ref_kind = make_model(mesh, reference), reference
    elif isinstance(reference, ElasticModel):
        ref_model, ref_kind = reference, type(reference).__name__
    else:
        raise ConfigError(f"reference must be None, a model kind or an ElasticModel, got {type(reference).__name__}")

    if observable == "reaction":
        obs = _reaction_observable(bc)
    elif callable(observable):
        user: Callable = observable

        def obs(displacement, reaction):
            return jnp.atleast_1d(jnp.asarray(user(displacement)))

    else:
        raise ConfigError(f"observable must be 'reaction' or a function of the displacement, got {observable!r}")

    # ------------------------------------------------------------------ reference
    ref_sol = solve_static(ref_model, material, bc, throw=False)
    if not bool(ref_sol.converged):
        raise ConvergenceError(f"the reference static solve ({ref_kind}) did not converge")
    y_ref = obs(ref_sol.displacement, ref_sol.reaction)
    ref_norm = float(jnp.linalg.norm(y_ref))
    if not np.isfinite(ref_norm) or ref_norm == 0.0:
        raise ConfigError("the reference observable is zero or not finite: nothing to calibrate against")

    # ------------------------------------------------------------------ budgeted XPBD
    def observe(values):
        """Budgeted observable at the fitted fields' ``values`` and whether XPBD came to rest."""
        m = _with_values(material, fit_fields, values)
        sol = xpbd_quasi_static(model, m, bc, settings=settings, tol=tol, max_steps=max_frames, throw=False)
        return obs(sol.displacement, sol.reaction), sol.converged

    def residual_fn(values, data):
        # (y - y_ref) / (|y_ref| rtol): the relative mismatch in units of the target, so that the
        # Jacobian dominates Levenberg--Marquardt's initial damping (unit in u) and the first
        # steps are nearly Gauss--Newton steps (the minimiser and the covariance do not depend
        # on this scale). A frame limit reached gives NaN, which the optimiser rejects.
        y, ok = observe(values)
        r = (y - data["reference"]) / data["norm"]
        return jnp.where(ok, r, jnp.nan), y

    observe_jit = jax.jit(observe)

    def evaluate(values):
        y, ok = observe_jit(jnp.asarray(values))
        if not bool(ok):
            raise ConvergenceError(
                f"the budgeted XPBD solve did not come to rest within {max_frames} frames "
                f"(model {model_kind}, iterations {settings.iterations}, method {settings.method}); "
                "raise max_frames or use another setting"
            )
        return y, float(jnp.linalg.norm((y - y_ref) / ref_norm))

    start = np.array([float(getattr(material, f)) for f in fit_fields])
    y_naive, naive_err = evaluate(start)
    reach = max_log_step * max(int(max_steps), 1)
    problem = ResidualProblem(residual_fn, fit_fields, [_TRANSFORMS[f](material, reach) for f in fit_fields], int(y_ref.shape[0]),
                              data={"reference": np.asarray(y_ref), "norm": np.asarray(ref_norm * rtol)})
    # The engine's first step evaluates the start (residual and Jacobian); max_steps optimiser
    # steps follow, until the relative error reaches rtol (the loss is (err / rtol)^2 / 2). With
    # max_steps = 0 or a naive error within rtol, the result holds the start's statistics.
    fit = least_squares(problem, start, method="levenberg_marquardt", max_steps=max_steps + 1,
                        stop=lambda loss: math.sqrt(2.0 * loss) <= 1.0)
    values = np.array([fit.values[f] for f in fit_fields])
    steps = max(fit.steps - 1, 0)
    y, err = evaluate(values)

    if err > rtol:
        warnings.warn(
            f"budget calibration stopped at relative error {err:.3g} after {steps} steps (naive {naive_err:.3g}): "
            "with this setting the budgeted response may be saturated (insensitive to the fitted fields; "
            "e.g. (dt c / h)^2 >> iterations); check .converged and consider a smaller dt or more substeps",
            DifftissueWarning,
            stacklevel=2,
        )
    return BudgetCalibration(
        material=_with_values(material, fit_fields, values),
        true_material=material,
        fit_fields=fit_fields,
        setting={
            "dt": float(settings.dt),
            "substeps": int(settings.substeps),
            "iterations": int(settings.iterations),
            "method": str(settings.method),
        },
        model_kind=model_kind,
        reference_kind=ref_kind,
        reference=np.asarray(y_ref),
        naive=np.asarray(y_naive),
        calibrated=np.asarray(y),
        naive_error=naive_err,
        calibrated_error=err,
        steps=steps,
        converged=err <= rtol,
        jacobian=np.asarray(fit.jacobian) * rtol,
        covariance=np.asarray(fit.covariance),
        standard_errors=dict(fit.standard_errors),
        dof=fit.dof,
    )


def _with_values(material: Material, fields, values) -> Material:
    """``material`` with ``fields`` set to ``values`` (physical, SI)."""
    kw = {name: getattr(material, name) for name in MATERIAL_FIELDS}
    for i, f in enumerate(fields):
        kw[f] = values[i]
    return Material(**kw)
