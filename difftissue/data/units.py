"""Units of measured data: the units the loaders understand, their conversion to SI and the
plausibility ranges that catch a wrong unit (no physics).
"""

from __future__ import annotations

import re
from typing import Mapping

import numpy as np

from ..errors import DataError, ImplausibleMagnitudeError, UnitError


# ============================================================================ units
#: Units understood by the loaders: normalized spelling -> (dimension, factor to SI).
#: ``µ`` (micro sign) and ``μ`` (Greek mu) are read as ``u``; spaces are ignored.
UNITS: dict[str, tuple[str, float]] = {
    # length
    "m": ("length", 1.0),
    "cm": ("length", 1e-2),
    "mm": ("length", 1e-3),
    "um": ("length", 1e-6),
    "nm": ("length", 1e-9),
    # force
    "kN": ("force", 1e3),
    "N": ("force", 1.0),
    "mN": ("force", 1e-3),
    "uN": ("force", 1e-6),
    "nN": ("force", 1e-9),
    "pN": ("force", 1e-12),
    # pressure (stress, moduli)
    "Pa": ("pressure", 1.0),
    "kPa": ("pressure", 1e3),
    "MPa": ("pressure", 1e6),
    "GPa": ("pressure", 1e9),
    # strain
    "-": ("strain", 1.0),
    "1": ("strain", 1.0),
    "mm/mm": ("strain", 1.0),
    "m/m": ("strain", 1.0),
    "%": ("strain", 1e-2),
    # time
    "s": ("time", 1.0),
    "ms": ("time", 1e-3),
    "min": ("time", 60.0),
    # stiffness
    "N/m": ("stiffness", 1.0),
    "mN/m": ("stiffness", 1e-3),
    "nN/nm": ("stiffness", 1.0),
    "pN/nm": ("stiffness", 1e-3),
    "nN/um": ("stiffness", 1e-3),
    # speed
    "m/s": ("speed", 1.0),
    "mm/s": ("speed", 1e-3),
    "um/s": ("speed", 1e-6),
    "nm/s": ("speed", 1e-9),
    "mm/min": ("speed", 1e-3 / 60.0),
    "um/min": ("speed", 1e-6 / 60.0),
}

#: The dimension of each quantity a loader column may hold.
QUANTITY_DIMENSIONS: dict[str, str] = {
    "depth": "length",
    "displacement": "length",
    "force": "force",
    "stress": "pressure",
    "true_stress": "pressure",
    "strain": "strain",
    "true_strain": "strain",
    "time": "time",
}

#: Plausible range ``(lo, hi)`` of the *largest absolute value* of each quantity [SI], per
#: regime. A column whose peak |value| falls outside raises
#: :class:`~difftissue.errors.ImplausibleMagnitudeError`. "afm": AFM / nano-indentation
#: (cantilevers, depths up to 1 mm, forces up to 1 mN); "macro": bench-top indentation of
#: tissue or phantoms; "compression": unconfined compression of a specimen.
PLAUSIBLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "afm": {"depth": (1e-10, 1e-3), "force": (1e-13, 1e-3)},
    "macro": {"depth": (1e-7, 0.2), "force": (1e-7, 1e5)},
    "compression": {
        "displacement": (1e-7, 1.0),
        "force": (1e-6, 1e6),
        "stress": (1e-3, 1e9),
        "true_stress": (1e-3, 1e10),
        "strain": (1e-5, 1.0),
        "true_strain": (1e-5, 10.0),
        "diameter": (1e-4, 1.0),
        "height": (1e-4, 1.0),
    },
}

_MICRO = str.maketrans({"\u00b5": "u", "\u03bc": "u"})


def normalize_unit(unit: str) -> str:
    """The spelling of ``unit`` used as a key of :data:`UNITS` (``µm`` -> ``um``, spaces dropped)."""
    u = str(unit).translate(_MICRO).replace(" ", "").strip()
    return {"": "-", "[-]": "-", "mm/mm.": "mm/mm"}.get(u, u)


def unit_factor(unit: str, dimension: str | None = None, *, what: str = "value") -> float:
    """Factor that converts ``unit`` to SI; checks that the unit measures ``dimension``.

    Raises:
        UnitError: the unit is unknown, or of another dimension; the message lists the
            units accepted for the dimension.
    """
    key = normalize_unit(unit)
    if key not in UNITS:
        raise UnitError(f"unknown unit {unit!r} for {what}; {_accepted(dimension)}")
    dim, factor = UNITS[key]
    if dimension is not None and dim != dimension:
        raise UnitError(f"unit {unit!r} of {what} measures {dim}, not {dimension}; {_accepted(dimension)}")
    return factor


def _accepted(dimension: str | None) -> str:
    if dimension is None:
        return f"known units: {', '.join(UNITS)}"
    return f"accepted {dimension} units: {', '.join(u for u, (d, _) in UNITS.items() if d == dimension)}"


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse_quantity(text, dimension: str | None = None, *, what: str = "value") -> float:
    """A number with a unit (``"50mm"``, ``"27.5 um"``, ``{"value": 50, "unit": "mm"}``,
    ``(50, "mm")``) converted to SI. A bare number is taken as SI already."""
    if isinstance(text, Mapping):
        unknown = set(text) - {"value", "unit"}
        if unknown or "value" not in text:
            raise DataError(f"{what}: expected {{'value': ..., 'unit': ...}}, got {dict(text)!r}")
        return float(text["value"]) * unit_factor(text.get("unit", "m" if dimension == "length" else "-"), dimension, what=what)
    if isinstance(text, (tuple, list)) and len(text) == 2:
        return float(text[0]) * unit_factor(text[1], dimension, what=what)
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return float(text)
    m = re.fullmatch(rf"\s*({_NUMBER})\s*(\S*)\s*;?\s*", str(text))
    if not m:
        raise DataError(f"{what}: cannot read a number with a unit from {text!r}")
    value, unit = float(m.group(1)), m.group(2)
    if not unit:
        return value
    return value * unit_factor(unit, dimension, what=what)


def _unit_in_name(name: str) -> str | None:
    """The unit written in a column name: ``"Load (uN)"`` -> ``"uN"``, ``"Strain [-]"`` -> ``"-"``."""
    m = re.search(r"[\(\[]\s*([^\(\)\[\]]*?)\s*[\)\]]\s*$", name)
    return m.group(1) if m else None


def _check_plausible(quantity: str, values, ranges: Mapping, *, regime: str, column: str | None, unit: str, si_unit: str, source: str | None = None) -> None:
    if quantity not in ranges:
        return
    lo, hi = ranges[quantity]
    x = np.abs(np.asarray(values, dtype=float))
    peak = float(x.max()) if x.size else 0.0
    if lo <= peak <= hi:
        return
    dim = QUANTITY_DIMENSIONS.get(quantity)
    hint = ""
    declared = normalize_unit(unit) if unit else None
    if dim is not None and declared in UNITS:
        f0 = UNITS[declared][1]
        fits = [u for u, (d, f) in UNITS.items() if d == dim and u != declared and lo <= peak / f0 * f <= hi]
        if fits:
            hint = f"; the values would be plausible in {' or '.join(repr(u) for u in fits)}"
    side = "above" if peak > hi else "below"
    raise ImplausibleMagnitudeError(
        f"{quantity} ({source or f'column {column!r}, declared in {unit!r}'}): the largest |value| is {peak:.4g} {si_unit}, "
        f"{side} the plausible range [{lo:.0e}, {hi:.0e}] {si_unit} for {regime!r} data{hint}. "
        f"Check the unit, or pass plausible={{{quantity!r}: (lo, hi)}} to widen the range"
    )


_SI_UNIT = {"length": "m", "force": "N", "pressure": "Pa", "strain": "-", "time": "s"}
