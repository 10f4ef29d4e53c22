"""Estimates from the measured data alone, before any model runs: the effective or Young's
modulus of a curve (the data-driven start of E), the cubic coefficient b matched from two
model curves (the start of b), and the plausibility checks that warn of a likely unit mistake
(:class:`~difftissue.errors.ImplausibleUnitWarning`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..data import UNITS, normalize_unit
from ..errors import ImplausibleUnitWarning
from ..materials import Material
from .schema import _fail, _join

#: Young's moduli [Pa] a soft-tissue indentation can plausibly give (cells ~10 Pa to tendon ~1 GPa);
#: an effective modulus outside, estimated from the deepest point, points to a unit mistake.
PLAUSIBLE_MODULUS = (1.0, 1.0e9)
#: Deepest indentation / indenter radius (sphere, flat punch) considered plausible.
PLAUSIBLE_DEPTH_OVER_RADIUS = (1.0e-3, 1.0)


def _unit_hint(factor: float, declared: str | None) -> str:
    """'values in m declared as mm'-style hint for a length scale off by ``factor`` (> 1: too large)."""
    d = normalize_unit(declared) if declared else None
    if d in UNITS:
        f0 = UNITS[d][1]
        candidates = [u for u, (dim, f) in UNITS.items() if dim == "length" and u != d and 0.3 < f0 / f / factor < 3.0]
        if candidates:
            return f"depths given in {candidates[0]} but declared as {d}"
    return f"a depth unit off by a factor of about {factor:.3g}"


def _effective_modulus(depth: float, force: float, kw: Mapping) -> float:
    """The effective modulus E/(1 - nu^2) [Pa] of one (depth [m], force [N]) point: Hertz for a
    sphere, Sneddon for a flat punch or a cone (half-space)."""
    shape = kw["indenter"]
    if shape == "sphere":
        return 3.0 * force / (4.0 * math.sqrt(kw["radius"]) * depth**1.5)
    if shape == "flat_punch":
        return force / (2.0 * kw["radius"] * depth)
    return math.pi * force / (2.0 * math.tan(kw["half_angle"]) * depth**2)


def _indentation_shape(depth, kw: Mapping) -> np.ndarray:
    """``g(d)`` [N/Pa] with ``F = E_eff g(d)`` on a half-space: Hertz ``4/3 sqrt(R) d^1.5`` (sphere),
    Sneddon ``2 a d`` (flat punch) and ``2/pi tan(alpha) d^2`` (cone); depth in m."""
    d = np.clip(np.asarray(depth, dtype=float), 0.0, None)
    shape = kw["indenter"]
    if shape == "sphere":
        return 4.0 / 3.0 * math.sqrt(kw["radius"]) * d**1.5
    if shape == "flat_punch":
        return 2.0 * kw["radius"] * d
    return 2.0 / math.pi * math.tan(kw["half_angle"]) * d**2


def _indentation_estimate(depth, force, sigma, kw: Mapping) -> tuple[float, str, str] | None:
    """The effective modulus E/(1 - nu^2) [Pa] that fits ``F = E_eff g(d)`` best (weighted least
    squares, one parameter, closed form), or None when the curve has no positive force."""
    g = _indentation_shape(depth, kw)
    w = 1.0 / np.asarray(sigma, dtype=float) ** 2 * np.ones_like(g)
    den = float(np.sum(w * g * g))
    E = float(np.sum(w * g * np.asarray(force, dtype=float))) / den if den > 0 else float("nan")
    if not (math.isfinite(E) and E > 0):
        return None
    law = {"sphere": "Hertz", "flat_punch": "Sneddon flat punch", "cone": "Sneddon cone"}[kw["indenter"]]
    return E, "effective", f"{law} half-space slope of the force-depth curve"


#: Fraction of the largest strain used for the small-strain slope of a compression curve.
SMALL_STRAIN_FRACTION = 0.25


def _compression_estimate(strain, stress) -> tuple[float, str, str] | None:
    """Small-strain Young's modulus [Pa]: the least-squares slope through the origin of stress vs
    strain over the points up to :data:`SMALL_STRAIN_FRACTION` of the largest strain (at least 3)."""
    x, y = np.abs(np.asarray(strain, dtype=float)), np.abs(np.asarray(stress, dtype=float))
    order = np.argsort(x)
    x, y = x[order], y[order]
    n = max(3, int(np.sum(x <= SMALL_STRAIN_FRACTION * x.max()))) if x.size else 0
    x, y = x[:n], y[:n]
    den = float(np.sum(x * x))
    E = float(np.sum(x * y)) / den if den > 0 else float("nan")
    if not (math.isfinite(E) and E > 0):
        return None
    return E, "young", f"small-strain slope of stress vs strain (strain <= {x.max():.3g})"


#: Experiment kinds whose prediction is proportional to E at fixed nu and b (stress or force):


#: the data-driven start of the cubic coefficient uses them.
_CUBIC_START_KINDS = ("compression", "indentation")


def _cubic_estimate(observed, sigma, at_b0, at_b1, b0: float, b1: float) -> tuple[float, float] | str:
    """The cubic coefficient b [-] that best matches a measured curve, from two model
    predictions at the start's E: ``at_b0`` with b = ``b0`` and ``at_b1`` with b = ``b1``
    (same unit as ``observed``, Pa or N; ``sigma`` its uncertainty).

    A compression stress or indentation force is proportional to E at fixed nu and b, and
    nearly linear in b over a few units, so ``observed ~ alpha (s0 + (b - b0) d)`` with
    ``d = (s1 - s0) / (b1 - b0)``: weighted linear least squares in ``(alpha, alpha (b - b0))``,
    then ``b = b0 + gamma / alpha``. ``alpha`` [-] is the factor between the data's modulus and
    the start's. The model's own nonlinearity (large strain, volume term) is in ``s0``, so it is
    not mistaken for strain stiffening: a polynomial ``E (eps + b eps^3)`` fitted to the data
    alone would not give the model's b (:doc:`fitting`, Starting values).

    Returns ``(b, alpha)``, or a reason (str) when there is no estimate: an evaluation failed,
    the prediction does not depend on b (a model without cubic springs), or ``alpha <= 0``.
    """
    y = np.asarray(observed, dtype=float)
    s0, s1 = np.asarray(at_b0, dtype=float), np.asarray(at_b1, dtype=float)
    if not (np.all(np.isfinite(s0)) and np.all(np.isfinite(s1))):
        return "the model evaluation at the start failed"
    d = (s1 - s0) / (b1 - b0)
    if not np.max(np.abs(d)) > 1e-9 * np.max(np.abs(s0)):
        return "the model's prediction does not depend on the cubic coefficient"
    w = 1.0 / np.broadcast_to(np.asarray(sigma, dtype=float), y.shape)
    A = np.c_[s0 * w, d * w]
    (alpha, gamma), *_ = np.linalg.lstsq(A, y * w, rcond=None)
    if not (math.isfinite(alpha) and alpha > 0 and math.isfinite(gamma)):
        return f"the data do not match the model's curve at any positive scale (scale {alpha:.3g})"
    b = float(b0 + gamma / alpha)
    # Its standard error (residual variance, delta method): where b's effect on the curve is
    # nearly a change of scale (an indentation curve at small strain), E and b trade off and
    # the estimate is noise; then the config's b stays the start.
    n = y.size
    if n > 2:
        r = A @ np.array([alpha, gamma]) - y * w
        try:
            cov = np.linalg.inv(A.T @ A) * float(r @ r) / (n - 2)
        except np.linalg.LinAlgError:
            return "the curve's shape does not determine b (its effect is a change of scale)"
        grad = np.array([-gamma / alpha**2, 1.0 / alpha])
        se = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
        if not se <= CUBIC_START_MAX_SE:
            return (f"the curve's shape does not determine b well enough for a start (estimate {b:.3g} +/- {se:.2g}: its effect is "
                    "nearly a change of scale, traded off against E)")
    return b, float(alpha)


#: Largest standard error [-] of a data-driven start of the cubic coefficient b; above it the
#: config's b is the start (the curve's shape does not determine b).
CUBIC_START_MAX_SE = 0.5


def _inside(value: float, lower: float | None, upper: float | None, margin: float = 0.05) -> float:
    """``value`` kept strictly inside ``(lower, upper)`` (None: unbounded): a value outside (or
    within ``margin`` of the range from a finite bound) moves to that distance from the bound."""
    if lower is not None and upper is not None and math.isfinite(lower) and math.isfinite(upper):
        pad = margin * (upper - lower)
        return float(min(max(value, lower + pad), upper - pad))
    if lower is not None and math.isfinite(lower) and value <= lower:
        return float(lower + margin * max(abs(lower), 1.0))
    return float(value)


def _data_start(experiments, material, options: Mapping) -> tuple[Any, dict | None]:
    """The initial material with E from the data (``fit.start = "data"``, the default): the
    geometric mean of the experiments' estimates (an effective modulus times ``1 - nu^2`` at
    the config's nu). Returns ``(material, record)``; the record (None when no experiment gives
    an estimate) says what was used: ``value``, ``config_value``, ``from``."""
    ests = [(e.name, *e.modulus_estimate) for e in experiments if e.modulus_estimate is not None]
    if not ests:
        return material, None
    nu = float(material.poisson_ratio)
    vals = [v * (1.0 - nu**2) if kind == "effective" else v for _, v, kind, _ in ests]
    E0 = float(np.exp(np.mean(np.log(vals))))
    lo, hi = options.get("_bounds", {}).get("youngs_modulus", (0.0, math.inf))
    if not lo < E0 < hi:  # outside the config's bounds: a point well inside them
        if lo > 0 and math.isfinite(hi):
            E0 = math.sqrt(lo * hi)
        else:
            E0 = 2.0 * lo if E0 <= lo else 0.5 * hi
    start = Material(**{**material.to_dict(), "youngs_modulus": E0})
    how = "; ".join(f"{name}: {how} {v:.4g} Pa" + (f" -> E = {v * (1 - nu**2):.4g} Pa at nu = {nu:g}" if kind == "effective" and nu != 0 else "")
                    for name, v, kind, how in ests)
    return start, {"youngs_modulus": {"value": E0, "config_value": float(material.youngs_modulus), "from": how}}


def _plausibility(path: str, depth: np.ndarray, force: np.ndarray, kw: Mapping, curve) -> tuple[str, ...]:
    """Warn (:class:`~difftissue.errors.ImplausibleUnitWarning`) when the depths do not fit the
    indenter (deepest point beyond the radius, or below 1e-3 of it) or the deepest point implies
    an effective modulus outside :data:`PLAUSIBLE_MODULUS`: most often a unit mistake. Returns
    the messages (also emitted as warnings)."""
    units = (curve.metadata.get("units") or {}) if hasattr(curve, "metadata") else {}
    declared = units.get("depth") or units.get("indentation")
    i = int(np.argmax(depth))
    dmax, fmax = float(depth[i]), float(force[i])
    out = []
    if "radius" in kw:
        ratio = dmax / kw["radius"]
        lo, hi = PLAUSIBLE_DEPTH_OVER_RADIUS
        if not lo <= ratio <= hi:
            factor = 10.0 ** (3 * round(math.log10(ratio / math.sqrt(lo * hi)) / 3))  # the nearest power of 1000
            where = "deeper than" if ratio > hi else "below 1e-3 of"
            out.append(f"{path}: the deepest point {dmax:.4g} m is {ratio:.3g} x the indenter radius {kw['radius']:.4g} m "
                       f"({where} the radius): most likely {_unit_hint(factor, declared)}; check data.columns.depth.unit "
                       f"and indenter.length_unit (a wrong unit scales the fitted modulus by a large factor)")
    if fmax > 0 and dmax > 0:
        E = _effective_modulus(dmax, fmax, kw)
        lo, hi = PLAUSIBLE_MODULUS
        if not lo <= E <= hi:
            out.append(f"{path}: the deepest point ({dmax:.4g} m, {fmax:.4g} N) implies an effective modulus of {E:.3g} Pa, "
                       f"outside the {lo:g} Pa .. {hi:g} Pa of soft tissue: check the units of the force and depth columns "
                       f"(declared: depth in {declared or '?'}, force in {units.get('force', '?')}) and of the indenter")
    for msg in out:
        warnings.warn(msg, ImplausibleUnitWarning, stacklevel=3)
    return tuple(out)


#: Largest nominal compressive strain [-] considered plausible: beyond it the specimen would be
#: squashed to a tenth of its height, which points to a unit or height mistake.
PLAUSIBLE_MAX_STRAIN = 0.9
#: Largest strain [-] below which a strain column declared in percent most likely holds fractions.
PERCENT_SUSPECT_STRAIN = 0.01


def _compression_plausibility(path: str, curve, strain: np.ndarray, stress: np.ndarray, measure: str) -> tuple[str, ...]:
    """Warn (:class:`~difftissue.errors.ImplausibleUnitWarning`) when a compression curve's rows
    used do not look like a soft-tissue test: a nominal strain beyond
    :data:`PLAUSIBLE_MAX_STRAIN` (a displacement unit or specimen height off), a strain column
    declared in % whose largest value is below :data:`PERCENT_SUSPECT_STRAIN` (fractions
    declared as percent), or a small-strain modulus (:func:`_compression_estimate`) outside
    :data:`PLAUSIBLE_MODULUS`. A nominal strain >= 1 (the platen through the specimen) is an
    error. Returns the messages (also emitted as warnings)."""
    units = (curve.metadata.get("units") or {}) if hasattr(curve, "metadata") else {}
    strain_key = "strain" if measure == "engineering" else "true_strain"
    declared = units.get(strain_key)
    nominal = np.asarray(strain, dtype=float) if measure == "engineering" else -np.expm1(-np.asarray(strain, dtype=float))
    smax = float(np.max(nominal)) if nominal.size else 0.0
    if declared is None and curve.height is not None:
        source = (f"displacement / height (displacement in {units.get('displacement', '?')}, height {curve.height:.4g} m): "
                  "check the displacement column's unit and the specimen height")
    else:
        source = f"the {strain_key} column, declared in {declared or '?'}: check its unit"
    out = []
    if smax >= 1.0:
        _fail(_join(path, "data"), f"the largest nominal compressive strain used is {smax:.4g} (>= 1: the platen would pass through the specimen); "
              f"the strain is {source}, or set max_strain")
    if smax > PLAUSIBLE_MAX_STRAIN:
        out.append(f"{path}: the largest nominal compressive strain used is {smax:.4g}, beyond {PLAUSIBLE_MAX_STRAIN:g} (the specimen "
                   f"squashed to {100 * (1 - smax):.2g} % of its height): most likely a unit or height mistake; the strain is {source}")
    if declared is not None and declared.strip() == "%" and smax < PERCENT_SUSPECT_STRAIN:
        out.append(f"{path}: the {strain_key} column is declared in % and its largest value is {100 * smax:.4g} % (a strain of {smax:.3g}): "
                   f"most likely fractions declared as percent; if the file holds fractions give its unit as \"-\" "
                   f"(a wrong unit scales the fitted modulus by 100)")
    est = _compression_estimate(strain, stress)
    if est is not None:
        lo, hi = PLAUSIBLE_MODULUS
        if not lo <= est[0] <= hi:
            stress_key = "stress" if measure == "engineering" else "true_stress"
            out.append(f"{path}: the {est[2]} is {est[0]:.3g} Pa, outside the {lo:g} Pa .. {hi:g} Pa of soft tissue: check the units of "
                       f"the {stress_key} (declared: {units.get(stress_key) or ('force in ' + units.get('force', '?') + ' over the area')}) "
                       f"and of the strain ({source})")
    for msg in out:
        warnings.warn(msg, ImplausibleUnitWarning, stacklevel=3)
    return tuple(out)
