"""Statistics of a fit: Gauss--Newton covariance and identifiability, the quality gates, the
discretisation-error estimate and the effective modulus of a half-space fit.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from .._io import jsonable
from ..errors import DiscretisationWarning
from ..materials import Log, ScaledLogit
from .problem import UNITS, unit_text

if TYPE_CHECKING:  # annotations only: result.py imports this module
    from .result import FitResult, ScenarioFit


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


# ============================================================================ statistics
def parameter_statistics(jacobian, values, fields, *, loss: float, absolute_sigma: bool = False, floors: Mapping[str, float] | None = None):
    """Gauss--Newton covariance, standard errors and correlation of physical parameters.

    Args:
        jacobian: ``(n, p)`` Jacobian of the scaled residuals w.r.t. the physical parameters.
        values: ``(p,)`` parameter values (SI), used for scaling.
        fields: names of the parameters.
        loss: final loss (``SSE = 2 loss``).
        absolute_sigma: if true, ``cov = (J^T J)^-1`` (the sigmas are the true noise levels);
            otherwise ``cov = s^2 (J^T J)^-1`` with ``s^2 = SSE / (n - p)``.
        floors: scale floors of parameters that are not material fields (e.g. a scenario's
            contact offset, which may sit at 0: its natural size), added to the built-in ones.

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
    floor = {**_SCALE_FLOOR, **(floors or {})}
    scales = np.array([max(abs(t), floor.get(f, 0.0)) or 1.0 for t, f in zip(theta, fields)])
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


def identifiability_diagnostics(stats: Mapping, values, fields, *, floors: Mapping[str, float] | None = None,
                                units: Mapping[str, str] | None = None) -> list[tuple[str, str]]:
    """Which parameters the data do not determine, and why.

    Rules (thresholds in :data:`CONDITION_LIMIT`, :data:`RELATIVE_SE_LIMIT`,
    :data:`CORRELATION_LIMIT`):

    1. ``J^T J`` in scaled parameters is singular or has condition number > 1e8: each eigen-
       direction with eigenvalue < 1e-8 of the largest names the parameters that dominate it
       (squared eigenvector component >= 0.5, else the largest), and mentions the others involved.
    2. relative standard error ``SE / max(|value|, floor)`` > 1 (100 %).
    3. ``|correlation| > 0.99`` between two parameters (both named).

    ``floors`` and ``units``: scale floors and units of parameters that are not material
    fields (as :func:`parameter_statistics`'s ``floors``).

    Returns a list of ``(field, message)``.
    """
    fields = tuple(fields)
    floor = {**_SCALE_FLOOR, **(floors or {})}
    unit_of = {**UNITS, **(units or {})}
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
            se_txt = "infinite" if not np.isfinite(se[j]) else f"{se[j]:.3g} {unit_text(unit_of.get(f, ''))}".strip()
            of = f"|value| = {scales[j]:.3g}" if scales[j] > floor.get(f, 0.0) else f"the floor scale {scales[j]:g} (|value| is smaller)"
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
            the answer is unusable), ``poor_fit``, ``systematic_residuals``,
            ``discretisation_error`` (warnings; the last from :func:`with_discretisation`), and
            from a config fit's checks ``outside_tissue_range`` and ``lattice_pre_stretch_bias``
            (warnings: :mod:`difftissue.config.fitconfig`).
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
            "flags": [{"name": f.name, "severity": f.severity, "subject": f.subject, "message": f.message, "numbers": jsonable(f.numbers)} for f in self.flags],
            "scenarios": jsonable(self.scenarios),
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


def _bound_flags(parameterization, u, values, units=None) -> list[QualityFlag]:
    """``at_bound`` for each field whose transform is saturated (within :data:`BOUND_FRACTION`)."""
    out = []
    for i, (f, t) in enumerate(zip(parameterization.fields, parameterization.transforms)):
        ui = float(u[i])
        unit = unit_text((units or UNITS).get(f, ""))
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
        flags += _bound_flags(parameterization, result.unconstrained, result.values, result.units)
    for f in result.fields:
        v = result.values[f]
        if f in ranges and math.isfinite(v) and not ranges[f][0] <= v <= ranges[f][1]:
            lo, hi = ranges[f]
            unit = unit_text(UNITS.get(f, ""))
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
#: Observed orders [-] a three-level estimate accepts (:func:`discretisation_estimate` with a
#: ``"prediction_coarser"``); outside it the levels are not taken to be in the asymptotic range.
OBSERVED_ORDER_RANGE = (0.5, 4.0)
#: Largest relative misfit [-] of the coarser pair's change against the finer pair's change
#: scaled by one factor (``|d2 - rho d1| / |d2|``, sigma-weighted) a three-level estimate accepts.
OBSERVED_ORDER_MISFIT = 0.5


def discretisation_estimate(result: "FitResult", coarse: Mapping[str, Mapping], skipped: Mapping[str, str] | None = None) -> dict:
    """The mesh's share of the error of each fitted value, from one evaluation per scenario on
    a coarser mesh at the optimum (no refit).

    Per scenario with a coarse prediction ``p_c`` (fine prediction ``p_f`` at the optimum, cell
    size ratio ``r = h_coarse / h_fine``), Richardson extrapolation with the assumed order
    ``q`` (:data:`DISCRETISATION_ORDER`, first order, unless the scenario's entry gives its
    ``order``) estimates the fine mesh's error in the
    prediction: ``e = p_f - p_exact ~ (p_c - p_f) / (r^q - 1)``. The fit matched ``p_f`` to the
    data, so the mesh-converged model would have needed parameters differing by the linearised
    ``theta_fit - theta_converged ~ -(J^T J)^-1 J^T (e / sigma)`` (``J``: the fit's Jacobian of
    the scaled residuals at the optimum; rows of scenarios without an estimate count as zero).

    Args:
        result: the fit (its predictions, sigmas, Jacobian, values and standard errors).
        coarse: ``{scenario name: {"prediction": array (unit of the data), "fine_cells",
            "coarse_cells", "refinement_ratio": r [-]}}``, optionally ``"order"`` (that
            scenario's order of convergence ``q`` [-], default :data:`DISCRETISATION_ORDER`).
            With ``"prediction_coarser"`` (a third level, cell size ratio ``r`` again to the
            coarse mesh) the order is observed instead of assumed: with the sigma-weighted
            changes ``d1 = p_c - p_f`` and ``d2 = p_cc - p_c`` projected onto the columns of
            the scenario's Jacobian (the part that moves the parameters), ``rho = d1.d2 /
            d1.d1`` and ``q = ln(rho) / ln(r)``, capped at the entry's ``"max_order"`` where given (the
            element's order: a faster observed order means one level was luckily accurate, and
            the cap gives the larger, safer error). The scenario gets no estimate (status ``"not estimated"``
            and the reason in its record, its rows count as zero) where the levels are not
            monotone (``rho <= 1``: the change does not shrink as the cells do), ``q`` lies
            outside :data:`OBSERVED_ORDER_RANGE`, or the two changes are not proportional
            (misfit above :data:`OBSERVED_ORDER_MISFIT`).
        skipped: ``{scenario name: reason}`` for the scenarios without an estimate.

    Returns:
        ``{"method" (``"richardson_first_order"``, or ``"richardson"`` when a scenario gives
        another order), "order" (the order used, or ``"per scenario"``), "status": "estimated" | "not estimated", "reason" (when not),
        "scenarios": {name: {"status", "reason" | "fine_cells", "coarse_cells",
        "refinement_ratio", "prediction_change_relative", "rms_error_over_sigma"}},
        "estimate": {field: theta_fit - theta_converged (SI)}, "relative": {field: estimate /
        value [-]}, "corrected": {field: value - estimate (SI)}, "standard_error": {field},
        "ratio_to_standard_error": {field: |estimate| / standard error [-]}}``.
    """
    skipped = dict(skipped or {})
    rec: dict = {"method": DISCRETISATION_METHOD, "order": DISCRETISATION_ORDER, "scenarios": {}}
    rows = []
    J_all = np.asarray(result.jacobian, dtype=float)
    start = 0
    for s in result.scenarios:
        J_s, start = J_all[start:start + s.observed.size], start + s.observed.size
        c = coarse.get(s.name)
        if c is None:
            rec["scenarios"][s.name] = {"status": "not estimated", "reason": skipped.get(s.name, "no coarse-mesh prediction")}
            rows.append(np.zeros(s.observed.size))
            continue
        e, info = _fine_mesh_error(s, c, J_s)
        rec["scenarios"][s.name] = info
        rows.append(np.zeros(s.observed.size) if e is None else e / np.asarray(s.sigma, dtype=float))
    orders = {v["order"] for v in rec["scenarios"].values() if v["status"] == "estimated"}
    if orders and orders != {DISCRETISATION_ORDER}:  # not first order throughout: say which
        rec["method"] = "richardson"
        rec["order"] = orders.pop() if len(orders) == 1 else "per scenario"
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


def _fine_mesh_error(s: "ScenarioFit", c: Mapping, J_s: np.ndarray | None = None) -> tuple[np.ndarray | None, dict]:
    """Richardson estimate of the fine mesh's error ``p_f - p_exact`` (unit of the data) of one
    scenario, and its record (cells, ratio, order and where it came from, relative change of
    the prediction [-]); ``(None, record)`` when a three-level check refuses (the record says
    why). ``J_s``: the fit's Jacobian rows of this scenario (scaled residuals), for the
    three-level check."""
    pf = np.asarray(s.predicted, dtype=float)
    pc = np.asarray(c["prediction"], dtype=float)
    sigma = np.asarray(s.sigma, dtype=float)
    r = float(c["refinement_ratio"])
    norm = float(np.linalg.norm(pf))
    base = {"fine_cells": c.get("fine_cells"), "coarse_cells": c.get("coarse_cells"), "refinement_ratio": r,
            "prediction_change_relative": float(np.linalg.norm(pc - pf) / norm) if norm > 0 else float("nan")}
    if "specimen" in c:  # an automatically chosen specimen: its rule's record (resolution, tabulated force error)
        base["specimen"] = dict(c["specimen"])
    if "geometry" in c:  # an incision: the cut's realised geometry on each level (the same cut)
        base["geometry"] = dict(c["geometry"])
    if "prediction_coarser" in c:
        q, levels, why = _observed_order(pf, pc, np.asarray(c["prediction_coarser"], dtype=float), sigma, r, J_s)
        base.update(coarser_cells=c.get("coarser_cells"), order_source="observed (three levels)", **levels)
        if why is not None:
            return None, {"status": "not estimated", "reason": why, **base}
        if "max_order" in c and q > float(c["max_order"]):  # faster than the element can converge: a lucky level; take the element's order
            q = float(c["max_order"])
            base["order_source"] = f"observed {levels['observed_order']:.3g}, capped at the element's {q:g} (three levels)"
    else:
        q = float(c.get("order", DISCRETISATION_ORDER))
        base["order_source"] = "assumed"
    e = (pc - pf) / (r**q - 1.0)
    rms_f = float(np.sqrt(np.mean(pf**2)))
    info = {"status": "estimated", **base, "order": q, "rms_error_over_sigma": float(np.sqrt(np.mean((e / sigma) ** 2))),
            "relative_error": float(np.sqrt(np.mean(e**2))) / rms_f if rms_f > 0 else float("nan")}
    return e, info


def _observed_order(pf, pc, pcc, sigma, r, J_s=None) -> tuple[float, dict, str | None]:
    """Order of convergence observed on three levels of cell size ratio ``r`` (fine, coarse,
    coarser predictions): ``(q, record, reason it is refused or None)``. The sigma-weighted
    changes are projected onto the columns of ``J_s`` (the scenario's Jacobian of the scaled
    residuals; None: not projected): the part of the mesh error the fitted parameters absorb.
    Unprojected, the shallow depths of an indentation (a contact radius of one or two cells on
    the coarser meshes, far from the asymptotic range) decide the ratio though they barely move
    the fit."""
    d1, d2 = (pc - pf) / sigma, (pcc - pc) / sigma
    if J_s is not None and J_s.size and np.all(np.isfinite(J_s)):
        proj = J_s @ np.linalg.pinv(J_s)
        d1, d2 = proj @ d1, proj @ d2
    n1, n2 = float(d1 @ d1), float(d2 @ d2)
    if not (math.isfinite(n1) and math.isfinite(n2)):
        return float("nan"), {}, "no estimate: a prediction on the coarse or coarser mesh is not finite"
    if n1 == 0.0:  # the coarse mesh changed nothing: no discretisation error measurable
        return 1.0, {"change_ratio": float("nan"), "observed_order": float("nan"), "misfit": 0.0}, None
    rho = float(d1 @ d2) / n1
    misfit = float(np.linalg.norm(d2 - rho * d1) / math.sqrt(n2)) if n2 > 0 else 0.0
    rec = {"change_ratio": rho, "misfit": misfit}
    if not rho > 1.0:
        return float("nan"), {**rec, "observed_order": float("nan")}, (
            f"no estimate: not monotone (the change from the coarse to the coarser mesh is {rho:.3g} x the change from the fit mesh "
            "to the coarse; converging predictions need > 1)")
    q = math.log(rho) / math.log(r)
    rec["observed_order"] = q
    lo, hi = OBSERVED_ORDER_RANGE
    if not lo <= q <= hi:
        return q, rec, f"no estimate: observed order {q:.3g} outside [{lo:g}, {hi:g}] (the levels are not in the asymptotic range)"
    if misfit > OBSERVED_ORDER_MISFIT:
        return q, rec, (f"no estimate: the changes between the three levels are not proportional (misfit {misfit:.2g} > {OBSERVED_ORDER_MISFIT:g}; "
                        "the depths converge differently)")
    return q, rec, None


#: Without a statistical error to compare with (a standard error of NaN or 0: no residual
#: degrees of freedom, as a one-datum incision fit, or an exact fit), the ``discretisation_error``
#: flag is raised where the mesh's estimated error of a prediction exceeds this fraction of it
#: (rms over the experiment's points) [-]: 2 %, about the precision of a measured width or force.
DISCRETISATION_FLAG_RELATIVE = 0.02


def _discretisation_flags(rec: Mapping, units: Mapping[str, str]) -> list[QualityFlag]:
    """``discretisation_error`` (a warning) for each field whose estimate exceeds its standard
    error; where the standard error is NaN or 0 (no residual degrees of freedom: the data are
    matched exactly, so there is no statistical error to compare with), for each field with a
    non-zero estimate when an experiment's prediction carries an estimated mesh error above
    :data:`DISCRETISATION_FLAG_RELATIVE` of it. A standard error of ``inf`` (the data do not
    determine the field) raises no flag."""
    if rec.get("status") != "estimated":
        return []
    worst = max((v["relative_error"] for v in rec["scenarios"].values() if v.get("status") == "estimated" and math.isfinite(v.get("relative_error", math.nan))), default=0.0)
    out = []
    for f, d in rec["estimate"].items():
        se, ratio = rec["standard_error"][f], rec["ratio_to_standard_error"][f]
        unit = unit_text(units.get(f, ""))
        if math.isfinite(ratio) and ratio > 1.0:
            out.append(QualityFlag("discretisation_error", "warning", f,
                                   f"{f}: the mesh's estimated share of the error {d:+.3g} {unit} ({100 * rec['relative'][f]:+.2g} %) exceeds its "
                                   f"standard error {se:.3g} {unit} ({ratio:.3g} x): refine the specimen's cells; the mesh-converged "
                                   f"value is about {rec['corrected'][f]:.4g} {unit}".replace("  ", " "),
                                   {"estimate": d, "relative": rec["relative"][f], "standard_error": se, "ratio": ratio}))
        elif (math.isnan(se) or se == 0.0) and d != 0.0 and math.isfinite(d) and worst > DISCRETISATION_FLAG_RELATIVE:
            out.append(QualityFlag("discretisation_error", "warning", f,
                                   f"{f}: the mesh's estimated share of the error is {d:+.3g} {unit} ({100 * rec['relative'][f]:+.2g} %): the mesh "
                                   f"changes the fitted prediction by about {100 * worst:.2g} % (above {100 * DISCRETISATION_FLAG_RELATIVE:g} %), and "
                                   f"the fit has no standard error to compare it with (no residual degrees of freedom: the data are matched "
                                   f"exactly): refine the specimen's cells; the mesh-converged value is about {rec['corrected'][f]:.4g} {unit}".replace("  ", " "),
                                   {"estimate": d, "relative": rec["relative"][f], "standard_error": se, "ratio": ratio,
                                    "prediction_error_relative": worst, "limit": DISCRETISATION_FLAG_RELATIVE}))
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
    def vs_se(f):
        ratio = rec["ratio_to_standard_error"][f]
        return f"{ratio:.3g} x its standard error" if math.isfinite(ratio) else "no standard error to compare with"
    parts = [f"{f} {100 * rec['relative'][f]:+.3g} % ({vs_se(f)})" for f in rec["estimate"]]
    est = {k: v for k, v in rec["scenarios"].items() if v["status"] == "estimated"}
    orders = {float(v.get("order", DISCRETISATION_ORDER)) for v in est.values()}
    if orders == {1.0}:
        how, cells = "first order", "; ".join(f"{k} cells {v['fine_cells']} vs {v['coarse_cells']}" for k, v in est.items())
    else:
        how = "order " + " / ".join(f"{q:g}" for q in sorted(orders))
        cells = "; ".join(f"{k} cells {v['fine_cells']} vs {v['coarse_cells']} (order {float(v.get('order', DISCRETISATION_ORDER)):g})"
                          for k, v in est.items())
    return f"discretisation error (mesh, Richardson {how} from {cells}): " + ", ".join(parts)


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
