"""The config schema: the keys each table allows, their defaults and units, and the validators
that read one value each and raise :class:`~difftissue.errors.ConfigError` with the key's path
in front (``experiment[0].indenter.radius: must be a positive length in m, got -1``).

Nothing here builds a scenario or loads data: the other modules of :mod:`difftissue.config`
call these validators on the tables of a parsed TOML file. The underscore helpers are private
to the package (shared by its modules), not part of the public API.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError

#: Scenario kinds understood in ``experiment[i].scenario``.
SCENARIOS = ("analytic_indentation", "indentation", "compression", "fem_field", "incision")
#: Material fields (``[material]`` keys, ``fit.parameters`` entries) and their SI units.
FIELDS = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "cubic_coefficient": "1",
    "density": "kg/m^3",
    "pre_stretch": "1",
    "pre_stretch_y": "1",
}
_POSITIVE_FIELDS = ("youngs_modulus", "density", "pre_stretch", "pre_stretch_y")
_LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9}
_MESH_UNITS = ("m", "cm", "mm", "um", "µm")

_TOP_KEYS = ("title", "description", "material", "fit", "experiment")
_FIT_KEYS = (
    "parameters", "bounds", "method", "loss", "f_scale", "starts", "seed", "start_spread", "max_steps",
    "rtol", "atol", "learning_rate", "jac", "absolute_sigma", "checkpoint_every", "separate_compilation",
    "plausible", "start", "discretisation_check", "tissue",
)

#: ``fit.tissue``: the range of Young's modulus [Pa] a fitted E of that material class is
#: expected in. Deliberately wide envelopes (whole decades around the spread of published
#: moduli, which differ by method: indentation, tension, elastography, AFM), meant to catch a
#: unit slip, a wrong contact point or a diverged fit, not to judge a measurement; a fitted E
#: outside is the quality warning ``outside_tissue_range``. Narrow or widen with
#: ``fit.plausible`` (an error outside that range).
TISSUE_RANGES: dict[str, tuple[float, float]] = {
    "cell": (1e1, 1e5),
    "hydrogel": (1e1, 1e6),
    "brain": (1e2, 1e5),
    "fat": (1e2, 1e5),
    "liver": (1e2, 1e6),
    "kidney": (1e2, 1e6),
    "breast": (1e2, 1e6),
    "muscle": (1e3, 1e7),
    "skin": (1e3, 1e8),
    "silicone": (1e3, 1e7),
    "cartilage": (1e4, 1e8),
    "tendon": (1e7, 1e10),
}
_COMMON_EXPERIMENT_KEYS = ("name", "scenario", "data", "sigma", "points", "length_unit")
_EXPERIMENT_KEYS = {
    "analytic_indentation": _COMMON_EXPERIMENT_KEYS + ("indenter", "solution", "thickness", "base", "max_depth", "contact_offset"),
    "indentation": _COMMON_EXPERIMENT_KEYS + ("model", "indenter", "specimen", "base", "rollers", "max_depth", "penalty", "solver",
                                             "min_cells_per_contact_radius", "under_resolved", "contact_offset"),
    "compression": _COMMON_EXPERIMENT_KEYS + ("model", "specimen", "platens", "rollers", "measure", "max_strain", "solver"),
    "fem_field": ("name", "scenario", "data", "model", "prescribed", "observe", "reaction", "displacement_sigma", "force_sigma", "solver",
                  "reference_mesh", "specimen", "tolerance"),
    "incision": ("name", "scenario", "data", "sigma", "length_unit", "model", "specimen", "cut", "boundary", "scalpel_steps", "solver"),
}
_DATA_FORMATS = {
    "analytic_indentation": ("chiaro", "table"),
    "indentation": ("chiaro", "table"),
    "compression": ("instron", "table"),
    "fem_field": ("fem",),
    "incision": ("inline", "table"),
}
_SOLVER_KEYS = ("rtol", "xtol", "max_steps", "linear_solver")


# ============================================================================ helpers
def _fail(path: str, message: str):
    text = f"{path}: {message}" if path else message
    raise ConfigError(" ".join(str(text).split()))


def _show(value) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Mapping):
        return "a table"
    return str(value)


def _join(path: str, key) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def _table(value, path: str, allowed: Sequence[str], required: Sequence[str] = ()) -> dict:
    if not isinstance(value, Mapping):
        _fail(path, f"must be a table, got {_show(value)}")
    for k in value:
        if k not in allowed:
            where = path if path else "config"
            _fail(where, f"unknown key {k!r}; allowed: {', '.join(allowed)}")
    for k in required:
        if k not in value:
            _fail(_join(path, k), "missing (required)")
    return dict(value)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _number(value, path: str, *, what: str = "a number", finite: bool = True, check=None, rule: str = "") -> float:
    if not _is_number(value):
        _fail(path, f"must be {what}, got {_show(value)}")
    v = float(value)
    if finite and not math.isfinite(v):
        _fail(path, f"must be {what}, got {_show(value)}")
    if check is not None and not check(v):
        _fail(path, f"must be {rule or what}, got {_show(value)}")
    return v


def _positive(value, path: str, unit: str = "") -> float:
    u = f" in {unit}" if unit else ""
    return _number(value, path, what=f"a positive number{u}", check=lambda v: v > 0)


def _integer(value, path: str, *, minimum: int = 0) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        _fail(path, f"must be an integer >= {minimum}, got {_show(value)}")
    return int(value)


def _bool(value, path: str) -> bool:
    if not isinstance(value, bool):
        _fail(path, f"must be true or false, got {_show(value)}")
    return value


def _choice(value, path: str, choices: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in choices:
        _fail(path, f"must be one of {', '.join(repr(c) for c in choices)}; got {_show(value)}")
    return value


def _string(value, path: str) -> str:
    if not isinstance(value, str) or not value.strip():
        _fail(path, f"must be a non-empty string, got {_show(value)}")
    return value


def _unit_of(table: Mapping, path: str, units: Sequence[str] = tuple(_LENGTH_UNITS)) -> tuple[str, float]:
    if "length_unit" not in table:
        return "m", 1.0
    u = _choice(table["length_unit"], _join(path, "length_unit"), tuple(units))
    return u, _LENGTH_UNITS[u]


def _length(value, path: str, unit: tuple[str, float]) -> float:
    name, factor = unit
    return _number(value, path, what=f"a positive length in {name}", check=lambda v: v > 0) * factor


def _lengths(value, path: str, unit: tuple[str, float], n: int = 3) -> tuple[float, ...]:
    if _is_number(value):
        value = [value] * n
    if not isinstance(value, list) or len(value) != n:
        _fail(path, f"must be {n} positive lengths in {unit[0]} (a list), got {_show(value)}")
    return tuple(_length(v, _join(path, i), unit) for i, v in enumerate(value))


def _counts(value, path: str, n: int = 3) -> tuple[int, ...]:
    if isinstance(value, int) and not isinstance(value, bool):
        value = [value] * n
    if not isinstance(value, list) or len(value) != n:
        _fail(path, f"must be {n} cell counts (a list of integers >= 1), got {_show(value)}")
    return tuple(_integer(v, _join(path, i), minimum=1) for i, v in enumerate(value))


def _sigma(value, path: str, observed: np.ndarray, unit: str):
    """``sigma`` key: a number (SI unit of the observable), ``"rms"``, or ``{relative = r}``."""
    if value == "rms":
        return None
    if isinstance(value, Mapping):
        t = _table(value, path, ("relative",), ("relative",))
        r = _number(t["relative"], _join(path, "relative"), what="a positive fraction", check=lambda v: v > 0)
        scale = float(np.max(np.abs(observed))) if observed.size else 0.0
        return r * (scale if scale > 0 else 1.0)
    return _number(value, path, what=f"a positive number in {unit}, 'rms' or {{ relative = r }}", check=lambda v: v > 0)


def _resolve(base_dir: Path, value, path: str, *, must_exist: bool = True) -> Path:
    p = Path(os.path.expanduser(_string(value, path)))
    if not p.is_absolute():
        p = base_dir / p
    if must_exist and not p.is_file():
        _fail(path, f"file not found: {p}")
    return p


def _reraise(path: str, e: Exception):
    """Re-raise a difftissue error with the key path in front (same type where possible)."""
    msg = " ".join(f"{path}: {e}".split())
    try:
        new = type(e)(msg)
    except Exception:  # pragma: no cover - classes with other signatures
        new = ConfigError(msg)
    raise new from e


def _points(e: Mapping, path: str, default: int | None = 20) -> int | None:
    if "points" not in e:
        return default
    v = e["points"]
    if v == "all":
        return None
    return _integer(v, _join(path, "points"), minimum=2)


def _material_values(fields: Mapping, path: str) -> dict:
    """Material fields of a TOML table, each checked (positive, nu in (-1, 0.5), finite) with a
    one-line error naming ``path.key``."""
    vals = {}
    for k, v in fields.items():
        p = _join(path, k)
        if k in _POSITIVE_FIELDS:
            vals[k] = _positive(v, p, FIELDS[k] if FIELDS[k] != "1" else "")
        elif k == "poisson_ratio":
            vals[k] = _number(v, p, check=lambda x: -1.0 < x < 0.5, rule="a number in (-1, 0.5) (0.5 is the incompressible limit; use e.g. 0.49 or 0.499)")
        else:
            vals[k] = _number(v, p, what="a finite number")
    return vals
