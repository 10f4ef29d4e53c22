"""Budget-aware calibration: effective material parameters for a given XPBD budget.

Standard (real-time) XPBD with a fixed iteration budget does not converge each frame's
solve, and the state it settles to is softer than the model's static equilibrium (see
``docs/xpbd.md``). :func:`calibrate_for_budget` finds the *effective* material that makes
the budgeted XPBD solve reproduce a reference static response (the same model solved to
convergence with :func:`~difftissue.solvers.solve_static`, or a ``fem_linear`` model) at the
true material, by a few Gauss--Newton steps on the observable mismatch with the gradient
taken through the unrolled XPBD loop (forward mode, ``jax.jacfwd``). The result records
the setting (dt, substeps, iterations, method) it is valid for: an effective material is
only meaningful for that setting, that mesh resolution and similar loading.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .boundary import BoundaryConditions
from .errors import ConfigError, ConvergenceError, DifftissueWarning, ModelError
from .materials import Material
from .models import MODELS, ElasticModel, make_model
from .solvers.static import solve_static
from .solvers.xpbd import XPBDSettings, xpbd_quasi_static

__all__ = ["BudgetCalibration", "calibrate_for_budget", "FITTABLE_FIELDS"]

#: fields that can be calibrated, with the transform to unconstrained space used for the steps
FITTABLE_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient")
_NU_LO, _NU_HI = 0.0, 0.4999


def _to_u(field, v):
    if field == "youngs_modulus":
        return jnp.log(v)
    if field == "poisson_ratio":
        t = (v - _NU_LO) / (_NU_HI - _NU_LO)
        return jnp.log(t) - jnp.log1p(-t)
    return jnp.asarray(v, dtype=float)


def _from_u(field, u):
    if field == "youngs_modulus":
        return jnp.exp(u)
    if field == "poisson_ratio":
        return _NU_LO + (_NU_HI - _NU_LO) * jax.nn.sigmoid(u)
    return u


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
        steps: Gauss--Newton steps taken.
        converged: ``calibrated_error <= rtol``.
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
            Gauss--Newton with a minimum-norm step when there are more fields than observables.
        observable: ``"reaction"`` (total reaction force on the nodes with a non-zero
            prescribed displacement, projected on the direction of their summed prescribed
            displacement: a scalar) or a function ``f(displacement) -> array``.
        max_steps: Gauss--Newton steps allowed.
        rtol: stop when the relative error is at most this.
        tol, max_frames: convergence tolerance and frame limit of the quasi-static XPBD solve.
        max_log_step: largest step per iteration in the unconstrained variables (log E).

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
    def residual(u):
        m = _replace(material, fit_fields, u)
        sol = xpbd_quasi_static(model, m, bc, settings=settings, tol=tol, max_steps=max_frames, throw=False)
        y = obs(sol.displacement, sol.reaction)
        r = (y - y_ref) / ref_norm
        return r, (y, sol.converged)

    jac = jax.jit(jax.jacfwd(residual, has_aux=True))
    res_only = jax.jit(residual)

    def evaluate(u):
        r, (y, ok) = res_only(u)
        if not bool(ok):
            raise ConvergenceError(
                f"the budgeted XPBD solve did not come to rest within {max_frames} frames "
                f"(model {model_kind}, iterations {settings.iterations}, method {settings.method}); "
                "raise max_frames or use another setting"
            )
        return r, y

    u = jnp.stack([_to_u(f, jnp.asarray(getattr(material, f), dtype=float)) for f in fit_fields])
    r, y = evaluate(u)
    y_naive = y
    err = float(jnp.linalg.norm(r))
    naive_err = err
    steps = 0
    while err > rtol and steps < max_steps:
        J, _ = jac(u)
        J = jnp.atleast_2d(J.reshape(r.shape[0], u.shape[0]))
        du = -jnp.linalg.lstsq(J, r)[0]
        big = float(jnp.max(jnp.abs(du)))
        if not np.isfinite(big) or big == 0.0:
            break
        if big > max_log_step:
            du = du * (max_log_step / big)
        # backtracking: accept the first step that lowers the error
        for _ in range(6):
            r_new, y_new = evaluate(u + du)
            err_new = float(jnp.linalg.norm(r_new))
            if err_new < err:
                break
            du = du / 2
        steps += 1
        if not err_new < err:
            break
        u, r, y, err = u + du, r_new, y_new, err_new

    if err > rtol:
        warnings.warn(
            f"budget calibration stopped at relative error {err:.3g} after {steps} steps (naive {naive_err:.3g}): "
            "with this setting the budgeted response may be saturated (insensitive to the fitted fields; "
            "e.g. (dt c / h)^2 >> iterations); check .converged and consider a smaller dt or more substeps",
            DifftissueWarning,
            stacklevel=2,
        )
    return BudgetCalibration(
        material=_replace(material, fit_fields, u),
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
    )


def _replace(material: Material, fields, u) -> Material:
    kw = {name: getattr(material, name) for name in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")}
    for i, f in enumerate(fields):
        kw[f] = _from_u(f, u[i])
    return Material(**kw)
