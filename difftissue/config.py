"""Fit configs: a TOML file -> scenarios, parameterization, initial material and fit options.

A config has three parts (the full schema, with every key, is in ``docs/configuration.md``)::

    [material]                 # initial values, SI
    youngs_modulus = 1e4
    poisson_ratio = 0.45

    [fit]
    parameters = ["youngs_modulus", "cubic_coefficient"]
    bounds = { cubic_coefficient = [-3.0, 5.0] }

    [[experiment]]
    name = "ecoflex"
    scenario = "compression"
    data = { format = "instron", path = "data/EF10_50T_A1.csv" }   # relative to this file

Every key is checked before anything heavy happens: an unknown key, a value of the wrong type
or outside its range raises :class:`~difftissue.errors.ConfigError` whose one-line message
starts with the key's path, e.g. ``experiment[0].indenter.radius: must be a positive length
in m, got -1``. Errors raised while loading the data or building a scenario are re-raised
with the experiment's path in front.

Lengths are in metres unless the table that holds them gives ``length_unit``.

:func:`load_config` reads a file, :func:`parse_config` a mapping; both return a
:class:`FitConfig`, whose :meth:`FitConfig.run` calls :func:`difftissue.fit.fit`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, DifftissueError

__all__ = ["FitConfig", "Experiment", "load_config", "parse_config", "SCENARIOS", "FIELDS"]

#: Scenario kinds understood in ``experiment[i].scenario``.
SCENARIOS = ("analytic_indentation", "indentation", "compression", "fem_field", "incision")
#: Material fields (``[material]`` keys, ``fit.parameters`` entries) and their SI units.
FIELDS = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "cubic_coefficient": "1",
    "density": "kg/m^3",
    "pre_stretch": "1",
}
_POSITIVE_FIELDS = ("youngs_modulus", "density", "pre_stretch")
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
    "analytic_indentation": _COMMON_EXPERIMENT_KEYS + ("indenter", "solution", "thickness", "base", "max_depth"),
    "indentation": _COMMON_EXPERIMENT_KEYS + ("model", "indenter", "specimen", "base", "rollers", "max_depth", "penalty", "solver"),
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


def _downsample_rows(x: np.ndarray, *, x_max: float | None, points: int | None, path: str, key: str, unit: str) -> np.ndarray:
    """Indices of the loading-segment samples kept: up to ``x_max``, thinned to ``points``
    samples evenly spread in x.

    The samples kept are measured points (no interpolation): for each of ``points`` targets
    ``x_max / points, ..., x_max`` the first sample whose running maximum of x reaches it, so
    the abscissa is strictly increasing even when the data step back by noise.
    """
    x = np.asarray(x, dtype=float)
    cm = np.maximum.accumulate(x) if x.size else x
    keep = np.ones(x.size, dtype=bool) if x_max is None else cm <= x_max * (1 + 1e-12)
    n_keep = int(np.sum(keep))
    if points is None:
        sel = np.flatnonzero(keep & (x > 0))  # x <= 0: at or before contact (recorded by _record_thinning)
    else:
        if n_keep == 0 or cm[n_keep - 1] <= 0:
            sel = np.array([], dtype=int)
        else:
            top = cm[n_keep - 1]
            grid = np.linspace(top / points, top, points)
            sel = np.unique(np.clip(np.searchsorted(cm[:n_keep], grid, side="left"), 0, n_keep - 1))
            sel = sel[x[sel] > 0]
    if sel.size < 2:
        limit = f" up to {key} = {x_max:g} {unit}" if x_max is not None else ""
        _fail(path, f"only {sel.size} usable data point(s){limit}; the data reach {np.max(x) if x.size else float('nan'):.4g} {unit}")
    return sel


# ====================================================================== rows used (provenance)
#: Depth steps back by more than this fraction of the depth range count as out of order
#: (smaller ones are noise, which the thinning skips).
_OUT_OF_ORDER = 0.05


def _row_labels(curve) -> tuple[np.ndarray, str]:
    """How to name the curve's samples to a user: the 1-based file lines when the loader
    recorded them, else the 0-based data-row indices."""
    lines = curve.metadata.get("data_lines") if hasattr(curve, "metadata") else None
    if lines is not None and len(lines) == len(curve):
        return np.asarray(lines, dtype=int), "file lines"
    return np.arange(len(curve)), "data rows"


def _cite_rows(labels: np.ndarray, idx, kind: str, limit: int = 8) -> str:
    from .errors import _cite

    return f"{kind} {_cite(np.asarray(labels)[np.asarray(idx, dtype=int)], limit)}"


def _out_of_order(x: np.ndarray) -> np.ndarray:
    """Indices where the abscissa (depth, strain) breaks 'rise to the largest value, then
    (optionally) fall': a step back of more than :data:`_OUT_OF_ORDER` of its range before the
    largest value, or a rise after it."""
    if x.size < 3:
        return np.array([], dtype=int)
    tol = _OUT_OF_ORDER * float(np.ptp(x))
    top = int(np.argmax(x))
    up, down = x[: top + 1], x[top + 1 :]
    back = np.flatnonzero(np.maximum.accumulate(up) - up > tol)
    again = np.flatnonzero(down - np.minimum.accumulate(down) > tol) + top + 1 if down.size else np.array([], dtype=int)
    return np.concatenate([back, again]).astype(int)


#: The abscissa of each kind of measured curve, as :func:`_loading_order` and
#: :func:`_record_thinning` name it: (quantity, "the deepest point"-style phrase, max key, unit,
#: why rows <= 0 are left out).
_ABSCISSA = {
    "depth": ("depth", "the deepest point", "max_depth", "m", "at or before the contact point; the models need depth > 0"),
    "strain": ("strain", "the largest strain", "max_strain", "", "at or before the platen touches; the model needs strain > 0"),
}


def _loading_order(x: np.ndarray, labels: np.ndarray, kind: str, *, turnaround: int | None, sort: bool, path: str, record: list,
                   what: str = "depth") -> np.ndarray:
    """Indices of a curve's loading segment, in loading order; appends what was reordered or
    left out (and why) to ``record``. ``x``: the abscissa (depth [m] or strain [-]);
    ``labels``/``kind``: the rows' names (:func:`_row_labels`); ``what``: a key of :data:`_ABSCISSA`.

    The loading segment ends at ``turnaround`` (a loader's, e.g. the Chiaro's piezo reversal)
    or at the largest ``x``; the rows after it (unloading) are left out. Rows in another order
    (``x`` falling back before its largest value or rising after it) are refused
    (:class:`~difftissue.errors.NonMonotonicError`, naming them) unless ``sort``: then all rows
    are sorted by ``x``.
    """
    from .errors import NonMonotonicError

    name, top_name = _ABSCISSA[what][:2]
    x = np.asarray(x, dtype=float)
    if turnaround is None:
        bad = _out_of_order(x)
        if bad.size and not sort:
            top = int(np.argmax(x))
            raise NonMonotonicError(
                f"{path}: the {name} column is not a loading curve (nor loading then unloading): its rows are out of order at "
                f"{_cite_rows(labels, bad, kind)}; a fit would keep only the rows up to {top_name} "
                f"({kind[:-1]} {labels[top]}, {top + 1} of {x.size} rows). Sort the file's rows "
                f"by {name}, or set sort = true in the experiment's data table if they are one loading curve in another order",
                rows=bad, lines=labels[bad] if kind == "file lines" else ())
        if sort:
            order = np.argsort(x, kind="stable")
            if np.any(order != np.arange(x.size)):
                record.append({"action": "reordered", "rows": [int(i) for i in labels[order]], "reason": f"sorted by {name} (data.sort = true)"})
            return order
    top = int(np.argmax(x)) if turnaround is None else int(turnaround)
    if top + 1 < x.size:
        rest = np.arange(top + 1, x.size)
        record.append({"action": "left out", "rows": [int(i) for i in labels[rest]],
                       "reason": f"after {top_name} ({kind[:-1]} {labels[top]}): the unloading segment"})
    return np.arange(top + 1)


def _loading_rows(curve, *, sort: bool, path: str, record: list) -> np.ndarray:
    """:func:`_loading_order` of a force-depth curve (its depth; the loader's turnaround, if any)."""
    labels, kind = _row_labels(curve)
    turn = curve.turnaround_index if curve.metadata.get("turnaround_index") is not None else None
    return _loading_order(np.asarray(curve.depth, dtype=float), labels, kind, turnaround=turn, sort=sort, path=path, record=record)


def _record_thinning(labels: np.ndarray, rows: np.ndarray, sel: np.ndarray, x: np.ndarray, *, x_max, points, record: list,
                     what: str = "depth") -> None:
    """Append the loading rows not in ``sel`` to ``record``, by reason: ``x`` (depth or strain,
    ``what``: a key of :data:`_ABSCISSA`) <= 0, beyond ``x_max``, or not among the ``points``
    samples kept."""
    name, _, key, unit, why_zero = _ABSCISSA[what]
    left = np.setdiff1d(np.arange(rows.size), sel)
    d = x[rows]
    cm = np.maximum.accumulate(d) if d.size else d
    reasons = (
        (d[left] <= 0, f"{name} <= 0 ({why_zero})"),
        (cm[left] > (np.inf if x_max is None else x_max * (1 + 1e-12)), f"beyond {key} = {x_max:.4g}{' ' + unit if unit else ''}" if x_max is not None else ""),
    )
    done = np.zeros(left.size, dtype=bool)
    for mask, why in reasons:
        m = mask & ~done
        if m.any():
            record.append({"action": "left out", "rows": [int(i) for i in labels[rows[left[m]]]], "reason": why})
        done |= m
    if (~done).any():
        why = (f"thinned to points = {points} samples evenly spread in {name}" if points is not None else f"a step back in {name} (noise)")
        record.append({"action": "left out", "rows": [int(i) for i in labels[rows[left[~done]]]], "reason": why})


def _provenance_note(path: str, prov: dict) -> str:
    """One line: how many rows of the file the fit uses, and what was left out and why."""
    from .errors import _cite

    names = prov["row_names"]
    parts = [f"{st['action']} {len(st['rows'])} ({names} {_cite(st['rows'], 6)}): {st['reason']}" for st in prov["steps"]]
    return (f"{path}: the fit uses {prov['rows_used']} of the {prov['rows_loaded']} rows loaded from {Path(prov['file']).name} "
            f"({prov['loaded']})" + ("; " + "; ".join(parts) if parts else ""))


# ============================================================================ result types
@dataclasses.dataclass(frozen=True)
class Experiment:
    """One built experiment: its scenario and where its data came from."""

    name: str
    kind: str
    model: str | None
    scenario: Any
    data_files: tuple[Path, ...]
    notes: tuple[str, ...] = ()
    #: rows of the data file used by the fit: ``file``, ``rows_loaded`` (by the loader),
    #: ``loaded`` (which rows the loader returned), ``rows_used``,
    #: ``row_names`` ("file lines" or "data rows"), ``used`` (their names, in fit order),
    #: ``steps`` (``{"action": "left out" | "reordered", "rows": [...], "reason": ...}``)
    provenance: dict | None = None
    #: plausibility warnings of the data (e.g. :class:`~difftissue.errors.ImplausibleUnitWarning`)
    warnings: tuple[str, ...] = ()
    #: the data's own modulus estimate for a data-driven start: ``(value [Pa], kind, how)`` with
    #: kind ``"effective"`` (E / (1 - nu^2), indentation) or ``"young"`` (E, compression)
    modulus_estimate: tuple[float, str, str] | None = None
    #: builds the same experiment on a coarser mesh (about half the cells in each direction,
    #: same geometry and protocol) for the discretisation estimate: a callable returning
    #: ``(scenario, info)``, info ``{"fine_cells", "coarse_cells", "refinement_ratio"}``
    #: (ratio: coarse / fine cell size [-]); None when it cannot be coarsened
    coarsen: Any = None
    #: why the experiment has no discretisation estimate (None when :attr:`coarsen` is given)
    coarsen_skip: str | None = None


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """A validated fit config, ready to run.

    Attributes:
        path: the config file (None when parsed from a mapping).
        raw: the parsed TOML (a dict).
        material: initial :class:`~difftissue.materials.Material` (SI): the config's
            [material], with E from the data unless ``fit.start = "material"`` (and, once
            :meth:`run` has chosen it, the cubic coefficient: :meth:`start_cubic_coefficient`).
        parameterization: fitted fields and their transforms.
        options: keyword arguments for :func:`difftissue.fit.fit` (method, loss, starts, ...).
        experiments: the built experiments, in file order.
        start: the data-driven start (see :func:`_data_start`), or None.
    """

    path: Path | None
    raw: dict
    material: Any
    parameterization: Any
    options: dict
    experiments: tuple[Experiment, ...]
    #: where the initial values came from when the data chose them (``fit.start = "data"``):
    #: ``{field: {"value", "config_value", "from"}}``; None when the config's [material] is the start.
    #: E is chosen when the config is read; the cubic coefficient b by :meth:`run` (it needs two
    #: model evaluations, see :meth:`start_cubic_coefficient`)
    start: dict | None = None
    #: ``fit.start``: ``"data"`` (E and b from the data unless ...) or ``"material"`` (the
    #: config's [material] is the start)
    start_mode: str = "data"

    @property
    def scenarios(self) -> tuple:
        return tuple(e.scenario for e in self.experiments)

    @property
    def config_material(self):
        """``[material]`` as written in the config (:attr:`material` is the fit's start, whose E
        may come from the data: :attr:`start`)."""
        if not self.start:
            return self.material
        from .materials import Material

        return Material(**{**self.material.to_dict(), **{f: d["config_value"] for f, d in self.start.items()}})

    @property
    def data_files(self) -> tuple[Path, ...]:
        seen: dict[Path, None] = {}
        for e in self.experiments:
            for p in e.data_files:
                seen.setdefault(p, None)
        return tuple(seen)

    @property
    def data_provenance(self) -> list[dict]:
        """Per experiment with measured rows: ``{"experiment": name, **Experiment.provenance}``."""
        return [{"experiment": e.name, **e.provenance} for e in self.experiments if e.provenance is not None]

    @property
    def data_warnings(self) -> list[str]:
        """The plausibility warnings of every experiment's data (e.g. a likely unit mistake)."""
        return [w for e in self.experiments for w in e.warnings]

    @property
    def model_name(self) -> str:
        """The models used, e.g. ``"springs_volume"`` or ``"hertz; springs_volume"``."""
        names = dict.fromkeys(e.model or "analytic" for e in self.experiments)
        return "; ".join(names)

    def fit_scenarios(self, separate_compilation: bool | None = None) -> tuple:
        """The scenarios handed to :func:`~difftissue.fit.fit`: the simulated ones wrapped in
        :class:`SeparatelyCompiled` unless ``separate_compilation`` (default: the config's
        ``fit.separate_compilation``, true) is false."""
        sep = self.options.get("separate_compilation", True) if separate_compilation is None else separate_compilation
        if not sep:
            return self.scenarios
        mode = "reverse" if (self.options.get("method") in ("adam", "lbfgs") or self.options.get("jac") == "bwd") else "forward"
        n_tangents = len(self.parameterization.fields)
        return tuple(SeparatelyCompiled(e.scenario, mode=mode, n_tangents=n_tangents) if e.kind != "analytic_indentation" else e.scenario for e in self.experiments)

    def run(self, **overrides):
        """Fit: :func:`difftissue.fit.fit` with the config's options updated by ``overrides``
        (e.g. ``checkpoint=``, ``resume=``, ``progress=``, ``starts=``)."""
        from .fit import fit

        opts = {**self.options, **overrides}
        check = opts.pop("discretisation_check", True)
        tissue = opts.pop("tissue", None)
        scenarios = self.fit_scenarios(opts.pop("separate_compilation", None))
        if any(isinstance(sc, SeparatelyCompiled) and sc.mode == "reverse" for sc in scenarios):
            # Reverse-mode scenarios (Adam, L-BFGS) have vector-Jacobian products only: the
            # fit's final Jacobian must be reverse mode too.
            if opts.get("jac", "bwd") != "bwd":
                raise ConfigError(
                    f"fit.method = {opts.get('method')!r} differentiates the separately compiled scenarios in reverse mode: "
                    "fit.jac must be 'bwd' (or leave it out), or set fit.separate_compilation = false"
                )
            opts["jac"] = "bwd"
        object.__setattr__(self, "last_scenarios", scenarios)  # for the failures of SeparatelyCompiled
        self.check_reaction_signs(scenarios)
        self.start_cubic_coefficient(scenarios)
        result = fit(scenarios, self.parameterization, self.material, **opts)
        result = tissue_range_check(result, tissue)
        return self.check_discretisation(result) if check else result

    def coarse_predictions(self, material) -> tuple[dict, dict]:
        """Each coarsenable experiment's prediction at ``material`` on its coarser mesh (one
        forward evaluation each, no refit), for :func:`~difftissue.fit.discretisation_estimate`.

        Returns ``(coarse, skipped)``: ``{name: {"prediction" (unit of the data), "fine_cells",
        "coarse_cells", "refinement_ratio"}}`` and ``{name: reason}`` for the experiments
        without an estimate (no mesh, a mesh file, observed on given nodes, or a coarse
        evaluation that failed: its message is the reason)."""
        coarse, skipped = {}, {}
        for e in self.experiments:
            if e.coarsen is None:
                skipped[e.name] = e.coarsen_skip or "this scenario cannot be coarsened"
                continue
            try:
                sc, info = e.coarsen()
                wrapped = SeparatelyCompiled(sc)
                pred = np.asarray(wrapped.evaluate(material), dtype=float)
            except DifftissueError as err:
                skipped[e.name] = f"the coarser mesh could not be built: {err}"
                continue
            if not np.all(np.isfinite(pred)):
                why = wrapped.failures[-1] if getattr(wrapped, "failures", None) else "non-finite prediction"
                skipped[e.name] = f"the evaluation on the coarser mesh {info['coarse_cells']} failed: {why}"
                continue
            coarse[e.name] = {**info, "prediction": pred}
        return coarse, skipped

    def check_discretisation(self, result):
        """``result`` with its discretisation estimate (``result.discretisation``, the
        ``discretisation_error`` quality flag and :class:`~difftissue.errors.DiscretisationWarning`
        where the estimate exceeds the standard error): one evaluation per experiment on a
        coarser mesh at the fitted material (:meth:`coarse_predictions`). A fit of closed-form
        scenarios only gets ``{"status": "not applicable", "reason"}`` (no mesh)."""
        from .fit import DISCRETISATION_METHOD, discretisation_estimate, with_discretisation

        if all(e.kind == "analytic_indentation" for e in self.experiments):
            rec = {"method": DISCRETISATION_METHOD, "status": "not applicable", "reason": "closed-form scenarios only: no mesh, no discretisation error"}
            return dataclasses.replace(result, discretisation=rec)
        coarse, skipped = self.coarse_predictions(result.material)
        return with_discretisation(result, discretisation_estimate(result, coarse, skipped), stacklevel=3)

    def start_cubic_coefficient(self, scenarios=None) -> dict | None:
        """Before a fit (``fit.start = "data"``, the default, and b in ``fit.parameters``): start
        the cubic coefficient b from the data. Each compression or simulated indentation
        experiment is evaluated at the start (E from the data) with the config's b and with b
        one unit away (two forward solves; with separate compilation through the function the
        fit then reuses) and :func:`_cubic_estimate` gives the b that matches the measured
        curve; several experiments give their mean. The start is kept inside
        ``fit.bounds.cubic_coefficient`` (:func:`_inside`). Updates :attr:`material` and
        :attr:`start` (``start["cubic_coefficient"]``: ``value``, ``config_value``, ``from``)
        and returns that record; None (and the config's b stays the start) when the start is
        pinned, b is not fitted, or no experiment determines it (the reason is then recorded
        with ``value`` = the config's b)."""
        from .materials import Material

        field = "cubic_coefficient"
        if self.start_mode != "data" or field not in self.parameterization.fields or (self.start or {}).get(field):
            return None
        scenarios = self.fit_scenarios() if scenarios is None else scenarios
        b0 = float(self.material.cubic_coefficient)
        t = dict(zip(self.parameterization.fields, self.parameterization.transforms))[field]
        lo, hi = getattr(t, "lower", None), getattr(t, "upper", None)
        b1 = b0 + 1.0 if hi is None or b0 + 1.0 < hi else b0 - 1.0 if lo is None or b0 - 1.0 > lo else 0.5 * (b0 + hi)
        ests, why = [], []
        for e, sc in zip(self.experiments, scenarios):
            if e.kind not in _CUBIC_START_KINDS:
                continue
            at = []
            for b in (b0, b1):
                m = Material(**{**self.material.to_dict(), field: b})
                at.append(sc.evaluate(m) if isinstance(sc, SeparatelyCompiled) else np.asarray(sc.predict(m), dtype=float))
            est = _cubic_estimate(np.asarray(e.scenario.observed), np.asarray(e.scenario.sigma), at[0], at[1], b0, b1)
            if isinstance(est, str):
                why.append(f"{e.name}: {est}")
            else:
                ests.append((e.name, *est))
        if not ests:
            if why:
                rec = {"value": b0, "config_value": b0, "from": f"the config's material.{field}", "no_estimate": "; ".join(why)}
                object.__setattr__(self, "start", {**(self.start or {}), field: rec})
            return None
        b = float(np.mean([v for _, v, _ in ests]))
        inside = _inside(b, lo, hi)
        how = "; ".join(f"{name}: the model's curve at E = {float(self.material.youngs_modulus):.4g} Pa matched to the data's "
                        f"(linearised in b between b = {b0:g} and {b1:g}, scale {alpha:.3g}) gives b = {v:.4g}" for name, v, alpha in ests)
        if inside != b:
            how += f"; kept inside fit.bounds.cubic_coefficient = [{lo:g}, {hi:g}] (estimate {b:.4g})"
        rec = {"value": inside, "config_value": b0, "from": how}
        object.__setattr__(self, "material", Material(**{**self.material.to_dict(), field: inside}))
        object.__setattr__(self, "start", {**(self.start or {}), field: rec})
        return rec

    def check_reaction_signs(self, scenarios=None) -> None:
        """Before a fit: raise :class:`~difftissue.errors.ReactionSignError` for a ``fem_field``
        experiment whose measured reaction force has the opposite sign of the model's reaction
        at the initial material (one forward solve; with separate compilation it compiles the
        function the fit then reuses)."""
        scenarios = self.fit_scenarios() if scenarios is None else scenarios
        for i, (e, sc) in enumerate(zip(self.experiments, scenarios)):
            check = getattr(e.scenario, "check_reaction_sign", None)
            if e.kind != "fem_field" or check is None or getattr(e.scenario, "reaction_mask", None) is None:
                continue
            pred = sc.evaluate(self.material) if isinstance(sc, SeparatelyCompiled) else np.asarray(sc.predict(self.material))
            try:
                check(pred)
            except DifftissueError as err:
                _reraise(f"experiment[{i}]", err)


def tissue_range_check(result, tissue: str | None):
    """``result`` with the quality warning ``outside_tissue_range`` added (and emitted as
    :class:`~difftissue.errors.FitQualityWarning`) when its fitted Young's modulus lies outside
    :data:`TISSUE_RANGES` of the stated ``tissue`` (config ``fit.tissue``); unchanged when no
    tissue is stated or E was not fitted."""
    from .errors import FitQualityWarning
    from .fit import FitQuality, QualityFlag

    if tissue is None or "youngs_modulus" not in result.values or result.quality is None:
        return result
    lo, hi = TISSUE_RANGES[tissue]
    E = float(result.values["youngs_modulus"])
    if not math.isfinite(E) or lo <= E <= hi:
        return result
    flag = QualityFlag(
        "outside_tissue_range", "warning", "youngs_modulus",
        f"youngs_modulus = {E:.4g} Pa lies outside [{lo:g}, {hi:g}] Pa, the range expected for fit.tissue = {tissue!r}: check the data's units, "
        "the contact point and the model (or state another tissue)",
        {"value": E, "range": [lo, hi], "tissue": tissue},
    )
    warnings.warn(f"warning: {flag.message}", FitQualityWarning, stacklevel=3)
    return dataclasses.replace(result, quality=FitQuality(result.quality.flags + (flag,), result.quality.scenarios))


def _compiled_per_shape(fn):
    """``fn`` compiled ahead of time for the shapes of the arguments it is called with (float64
    arrays), once per shape.

    A ``jax.jit`` function called both inside a callback (a fit's compiled step calls the
    scenario through :func:`jax.pure_callback`) and outside it is compiled twice: JAX keys its
    cache on that context. The ahead-of-time executable is one compilation for both."""
    import jax
    import jax.numpy as jnp

    jitted = jax.jit(fn)
    compiled: dict[tuple, Any] = {}

    def call(*args):
        shapes = tuple(np.shape(a) for a in args)
        if shapes not in compiled:
            compiled[shapes] = jitted.lower(*(jax.ShapeDtypeStruct(sh, jnp.float64) for sh in shapes)).compile()
        return compiled[shapes](*args)

    return call


_MATERIAL_LEAVES = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")


class SeparatelyCompiled:
    """A scenario whose prediction and derivative are compiled once each, on their own.

    :func:`difftissue.fit.fit` traces the scenario's ``predict`` into several jitted functions
    (the batched loss, the optimiser step with its Jacobian, the final Jacobian, the final
    prediction). For a simulated scenario (a scan of static solves with implicit gradients)
    each of these XLA compilations takes seconds to tens of seconds, which dominates a small
    fit. This wrapper compiles ``material -> prediction`` and its Jacobian-vector product
    (``mode="forward"``: Levenberg--Marquardt / Gauss--Newton with forward Jacobians) or
    vector-Jacobian product (``mode="reverse"``: Adam, L-BFGS, ``jac = "bwd"``) once, and the
    fit's compiled code calls them through :func:`jax.pure_callback` (batched calls run one
    after the other). The numbers are the same; only the compilation is shared. The material
    must have scalar fields.

    In forward mode one call gives the prediction and all the tangents of a Jacobian (one
    model solve per ``jax.jacfwd``), so it supports ``jax.jvp`` and ``jax.jacfwd`` (what the
    fit's forward Jacobians use) but not ``jax.linearize`` or reverse mode: use
    ``mode="reverse"`` for those.

    An evaluation at an invalid material (E <= 0, nu outside (-1, 0.5), non-finite values) or
    one whose static solve fails returns NaN instead of raising, so that Levenberg--Marquardt
    rejects that trial point (shrinking its trust region) rather than the fit aborting; the
    failures' messages are kept in :attr:`failures`.
    """

    def __init__(self, scenario, *, mode: str = "forward", n_tangents: int = 1):
        """
        Args:
            scenario: a scenario with ``predict(material)`` and the data attributes.
            mode: ``"forward"`` or ``"reverse"`` (see the class docstring).
            n_tangents: forward mode: the number of tangents a Jacobian call pushes through
                (the number of fitted parameters); primal-only calls run the same program with
                that many zero tangents, so one program serves both.
        """
        import jax
        import jax.numpy as jnp

        from .materials import Material

        if mode not in ("forward", "reverse"):
            raise ConfigError(f"mode must be 'forward' or 'reverse', got {mode!r}")
        self.inner = scenario
        self.mode = mode
        #: messages of the model evaluations that failed (returned NaN) during fits
        self.failures: list[str] = []
        #: model solves run so far: ``"value"`` (prediction only) and ``"value_and_tangents"``
        #: (prediction and the tangents of a Jacobian, forward mode)
        self.calls = {"value": 0, "value_and_tangents": 0}
        for k in ("name", "observed", "sigma", "abscissa", "x_label", "y_label"):
            setattr(self, k, getattr(scenario, k))
        n = int(np.asarray(scenario.observed).size)
        n_leaves = len(_MATERIAL_LEAVES)

        def f(v):
            return scenario.predict(Material(*(v[i] for i in range(n_leaves))))

        out = jax.ShapeDtypeStruct((n,), jnp.float64)
        vec = jax.ShapeDtypeStruct((n_leaves,), jnp.float64)

        def valid(v) -> bool:
            v = np.asarray(v, dtype=float)
            return bool(np.all(np.isfinite(v)) and v[0] > 0 and -1.0 < v[1] < 0.5 and v[3] > 0 and v[4] > 0)

        def guarded(fn, v, *args, shape=(n,)):
            # An invalid material (optimistix evaluates the Jacobian of a discarded branch at an
            # all-zero placeholder) or a failed solve gives NaN instead of an exception, so the
            # optimiser rejects that trial point instead of the whole fit aborting.
            if not valid(v):
                return None if shape is None else np.full(shape, np.nan)
            try:
                return fn(jnp.asarray(v, dtype=jnp.float64), *(jnp.asarray(a, dtype=jnp.float64) for a in args))
            except Exception as e:  # a static solve that failed to converge, an inverted element, ...
                self.failures.append(" ".join(str(e).split())[-300:])
                return None if shape is None else np.full(shape, np.nan)

        if mode == "forward":
            # ONE compiled program gives the prediction and its derivatives along a batch of
            # tangents: the model is solved once, the tangents (one implicit linear solve each
            # per load step) are batched. A primal-only call runs it with zero tangents (their
            # linear solves stop at once), so nothing is compiled twice.
            # Compiled ahead of time per tangent count (_compiled_per_shape).
            both = _compiled_per_shape(jax.vmap(lambda v, t: jax.jvp(f, (v,), (t,)), in_axes=(None, 0), out_axes=(None, 0)))
            n_zero = max(int(n_tangents), 1)

            def run(v, T):
                y, JT = both(v, T)
                return np.asarray(y, dtype=np.float64), np.asarray(JT, dtype=np.float64)

            def host_f(v):
                self.calls["value"] += 1
                return guarded(lambda vv: run(vv, np.zeros((n_zero, n_leaves)))[0], v)

            def host_tangents(v, T):
                # One model solve, all the tangents of a Jacobian.
                self.calls["value_and_tangents"] += 1
                v, T = np.asarray(v, dtype=float), np.asarray(T, dtype=float)
                res = guarded(lambda vv, tt: run(vv, tt), v, T, shape=None)
                return res if res is not None else (np.full(n, np.nan), np.full((T.shape[0], n), np.nan))

            def host_rows(V, T):
                # Several materials (the starts of a multi-start fit): one call per material.
                V, T = np.asarray(V, dtype=float), np.asarray(T, dtype=float)
                ys, jts = np.empty((V.shape[0], n)), np.empty((V.shape[0], n))
                groups: dict[bytes, list[int]] = {}
                for i, row in enumerate(V):
                    groups.setdefault(row.tobytes(), []).append(i)
                for rows in groups.values():
                    y, jt = host_tangents(V[rows[0]], T[rows])
                    ys[rows], jts[rows] = y, jt
                return ys, jts

            @jax.custom_batching.custom_vmap
            def value_and_tangent(v, t):
                y, jt = jax.pure_callback(host_tangents, (out, jax.ShapeDtypeStruct((1, n), jnp.float64)), v, t[None], vmap_method="sequential")
                return y, jt[0]

            @value_and_tangent.def_vmap
            def _value_and_tangents(axis_size, in_batched, v, t):
                v_batched, t_batched = in_batched
                T = t if t_batched else jnp.broadcast_to(t, (axis_size, n_leaves))
                if not v_batched:  # the Jacobian's tangents at one material: the prediction is not batched
                    y, JT = jax.pure_callback(host_tangents, (out, jax.ShapeDtypeStruct((axis_size, n), jnp.float64)), v, T, vmap_method="sequential")
                    return (y, JT), (False, True)
                rows = jax.ShapeDtypeStruct((axis_size, n), jnp.float64)
                Y, JT = jax.pure_callback(host_rows, (rows, rows), v, T, vmap_method="sequential")
                return (Y, JT), (True, True)

            self._host_f = host_f

            def call_f(v):
                return jax.pure_callback(host_f, out, v, vmap_method="sequential")

            @jax.custom_jvp
            def call(v):
                return call_f(v)

            @call.defjvp
            def _call_jvp(primals, tangents):
                # The prediction comes with its tangents from the same call (one model solve per
                # Jacobian: jax.jacfwd's tangents arrive batched, see _value_and_tangents).
                (v,), (t,) = primals, tangents
                return value_and_tangent(v, t)

        else:
            fwd = _compiled_per_shape(f)
            vjp = _compiled_per_shape(lambda v, ct: jax.vjp(f, v)[1](ct)[0])

            def host_f(v):
                return np.asarray(guarded(fwd, v), dtype=np.float64)

            self._host_f = host_f

            def call_f(v):
                return jax.pure_callback(host_f, out, v, vmap_method="sequential")

            def host_vjp(v, ct):
                out = np.asarray(guarded(vjp, v, ct), dtype=np.float64)
                return out if out.shape == (n_leaves,) else np.full(n_leaves, np.nan)

            @jax.custom_vjp
            def call(v):
                return call_f(v)

            def _fwd(v):
                return call_f(v), v

            def _bwd(v, ct):
                return (jax.pure_callback(host_vjp, vec, v, ct, vmap_method="sequential"),)

            call.defvjp(_fwd, _bwd)
        self._call = call

    def evaluate(self, material) -> np.ndarray:
        """The prediction at ``material`` on the host, through the same compiled function the
        fit calls (no extra compilation); NaN where the evaluation fails."""
        return self._host_f(np.array([float(getattr(material, k)) for k in _MATERIAL_LEAVES]))

    def predict(self, material):
        import jax.numpy as jnp

        v = jnp.stack([jnp.asarray(getattr(material, k), dtype=jnp.float64).reshape(()) for k in _MATERIAL_LEAVES])
        return self._call(v)


# ============================================================================ parsing
def load_config(path) -> FitConfig:
    """Read, validate and build a TOML fit config; relative paths are taken from its folder."""
    import tomllib

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(" ".join(f"{path}: invalid TOML: {e}".split())) from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    return parse_config(raw, base_dir=path.parent, path=path)


def parse_config(raw: Mapping, *, base_dir=".", path=None) -> FitConfig:
    """Validate and build a config given as a mapping (the parsed TOML)."""
    base_dir = Path(base_dir)
    top = _table(raw, "", _TOP_KEYS, ("material", "fit", "experiment"))
    for k in ("title", "description"):
        if k in top:
            _string(top[k], k)
    material = _parse_material(top["material"])
    param, options = _parse_fit(top["fit"], material)
    exps = top["experiment"]
    if not isinstance(exps, list) or not exps:
        _fail("experiment", "must be one or more [[experiment]] tables")
    # Structure first (cheap), then the data and the models.
    names = []
    for i, e in enumerate(exps):
        p = f"experiment[{i}]"
        if not isinstance(e, Mapping):
            _fail(p, f"must be a table, got {_show(e)}")
        if "scenario" not in e:
            _fail(_join(p, "scenario"), f"missing (required); one of {', '.join(SCENARIOS)}")
        kind = _choice(e["scenario"], _join(p, "scenario"), SCENARIOS)
        _table(e, p, _EXPERIMENT_KEYS[kind], ("data",))
        name = _string(e["name"], _join(p, "name")) if "name" in e else f"{kind}_{i}"
        if name in names:
            _fail(_join(p, "name"), f"{name!r} is used by experiment[{names.index(name)}] too; names must be unique")
        names.append(name)
    built = tuple(_build_experiment(e, f"experiment[{i}]", names[i], base_dir, material=material) for i, e in enumerate(exps))
    _check_model_ranges(built, material, param)
    start = None
    start_mode = options.pop("start", "data")
    if start_mode == "data" and "youngs_modulus" in param.fields:
        material, start = _data_start(built, material, options)
        if start is not None:  # the transforms are scaled at the start (u = 0 there)
            param, _ = _parse_fit(top["fit"], material)
    options.pop("_bounds", None)
    return FitConfig(
        path=None if path is None else Path(path),
        raw=dict(raw),
        material=material,
        parameterization=param,
        options=options,
        experiments=built,
        start=start,
        start_mode=start_mode,
    )


def _check_model_ranges(experiments, material, param) -> None:
    """springs_volume represents nu in [0.25, 0.5) only: the fit must stay there."""
    springs = [i for i, e in enumerate(experiments) if e.model == "springs_volume"]
    if not springs:
        return
    who = f"the springs_volume model (experiment[{springs[0]}])"
    nu = float(material.poisson_ratio)
    if nu < 0.25:
        _fail("material.poisson_ratio", f"{who} needs nu in [0.25, 0.5), got {nu:g}; use stable_neo_hookean or fem_* below 0.25")
    if "poisson_ratio" in param.fields:
        t = dict(zip(param.fields, param.transforms))["poisson_ratio"]
        lo = getattr(t, "lower", None)
        if lo is None or lo < 0.25:
            _fail("fit.bounds.poisson_ratio", f"{who} needs nu in [0.25, 0.5): give bounds such as [0.25, 0.499] (got {'none' if lo is None else f'lower bound {lo:g}'})")


def _parse_material(value):
    from .materials import Material

    t = _table(value, "material", tuple(FIELDS), ("youngs_modulus", "poisson_ratio"))
    return Material(**_material_values(t, "material"))


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


def _parse_fit(value, material):
    from .fit import LOSSES, METHODS
    from .materials import Identity, Log, MaterialParameterization, ScaledLogit

    t = _table(value, "fit", _FIT_KEYS, ("parameters",))
    params = t["parameters"]
    if isinstance(params, str):
        params = [params]
    if not isinstance(params, list) or not params:
        _fail("fit.parameters", f"must be a non-empty list of material fields ({', '.join(FIELDS)}), got {_show(params)}")
    for i, f in enumerate(params):
        if not isinstance(f, str) or f not in FIELDS:
            _fail(f"fit.parameters[{i}]", f"unknown material field {_show(f)}; choose from {', '.join(FIELDS)}")
        if params.index(f) != i:
            _fail(f"fit.parameters[{i}]", f"{f!r} is listed twice")
    bounds = _table(t.get("bounds", {}), "fit.bounds", tuple(FIELDS))
    transforms = {}
    for f in params:
        x0 = float(getattr(material, f))
        if f in bounds:
            p = f"fit.bounds.{f}"
            b = bounds[f]
            if not isinstance(b, list) or len(b) != 2 or not all(_is_number(v) for v in b):
                _fail(p, f"must be [lower, upper] (numbers; inf allowed), got {_show(b)}")
            lo, hi = float(b[0]), float(b[1])
            if math.isnan(lo) or math.isnan(hi) or not lo < hi:
                _fail(p, f"needs lower < upper, got [{lo:g}, {hi:g}]")
            if f in _POSITIVE_FIELDS and lo < 0:
                _fail(p, f"the lower bound of {f} must be >= 0 (it must stay positive), got {lo:g}")
            if f == "poisson_ratio" and (lo < -1 or hi > 0.5):
                _fail(p, f"bounds of poisson_ratio must lie within [-1, 0.5], got [{lo:g}, {hi:g}]")
            if not lo < x0 < hi:
                _fail(p, f"the initial value material.{f} = {x0:g} must lie strictly inside [{lo:g}, {hi:g}]")
            if math.isfinite(lo) and math.isfinite(hi):
                transforms[f] = ScaledLogit(lo, hi)
            elif math.isfinite(lo):
                transforms[f] = Log(lower=lo, scale=x0 - lo)
            elif math.isfinite(hi):
                _fail(p, "an upper bound alone is not supported; give a finite lower bound too")
            else:
                if f in _POSITIVE_FIELDS or f == "poisson_ratio":
                    _fail(p, f"{f} needs a finite lower bound")
                transforms[f] = Identity()
        elif f in _POSITIVE_FIELDS:
            transforms[f] = Log(scale=x0)  # u = 0 at the initial value
    for f in bounds:
        if f not in params:
            _fail(f"fit.bounds.{f}", f"{f!r} is not fitted (not in fit.parameters)")
    param = MaterialParameterization(tuple(params), transforms)

    opts: dict[str, Any] = {}
    if "method" in t:
        opts["method"] = _choice(t["method"], "fit.method", METHODS)
    if "loss" in t:
        opts["loss"] = _choice(t["loss"], "fit.loss", LOSSES)
    if "f_scale" in t:
        opts["f_scale"] = _positive(t["f_scale"], "fit.f_scale")
    if "starts" in t:
        opts["starts"] = _integer(t["starts"], "fit.starts", minimum=1)
    if "seed" in t:
        opts["seed"] = _integer(t["seed"], "fit.seed")
    if "start_spread" in t:
        opts["start_spread"] = _positive(t["start_spread"], "fit.start_spread")
    if "max_steps" in t:
        opts["max_steps"] = _integer(t["max_steps"], "fit.max_steps")
    for k in ("rtol", "atol", "learning_rate"):
        if k in t:
            opts[k] = _positive(t[k], f"fit.{k}")
    if "jac" in t:
        opts["jac"] = _choice(t["jac"], "fit.jac", ("fwd", "bwd"))
    if "absolute_sigma" in t:
        opts["absolute_sigma"] = _bool(t["absolute_sigma"], "fit.absolute_sigma")
    if "checkpoint_every" in t:
        opts["checkpoint_every"] = _integer(t["checkpoint_every"], "fit.checkpoint_every", minimum=1)
    if "separate_compilation" in t:
        opts["separate_compilation"] = _bool(t["separate_compilation"], "fit.separate_compilation")
    if "plausible" in t:
        opts["plausible"] = _plausible_ranges(t["plausible"], params)
    if "tissue" in t:
        opts["tissue"] = _choice(t["tissue"], "fit.tissue", tuple(TISSUE_RANGES))
    opts["start"] = _choice(t.get("start", "data"), "fit.start", ("data", "material"))
    if "discretisation_check" in t:
        opts["discretisation_check"] = _bool(t["discretisation_check"], "fit.discretisation_check")
    opts["_bounds"] = {f: (float(b[0]), float(b[1])) for f, b in bounds.items()}
    return param, opts


def _plausible_ranges(value, params) -> dict:
    """``fit.plausible = { youngs_modulus = [lo, hi] }`` (SI): the range outside which a fitted
    value is flagged ``implausible_value`` (default E in [1 Pa, 1 GPa])."""
    t = _table(value, "fit.plausible", tuple(FIELDS))
    out = {}
    for f, b in t.items():
        p = f"fit.plausible.{f}"
        if not isinstance(b, list) or len(b) != 2 or not all(_is_number(v) for v in b) or not float(b[0]) < float(b[1]):
            _fail(p, f"must be [lower, upper] with lower < upper ({FIELDS[f] if FIELDS[f] != '1' else 'dimensionless'}), got {_show(b)}")
        out[f] = (float(b[0]), float(b[1]))
    return out


def _solver_options(e: Mapping, path: str):
    from .scenarios import SolverOptions

    if "solver" not in e:
        return SolverOptions()
    p = _join(path, "solver")
    t = _table(e["solver"], p, _SOLVER_KEYS)
    kw: dict[str, Any] = {}
    for k in ("rtol", "xtol"):
        if k in t:
            kw[k] = _positive(t[k], _join(p, k))
    if "max_steps" in t:
        kw["max_steps"] = _integer(t["max_steps"], _join(p, "max_steps"), minimum=1)
    if "linear_solver" in t:
        kw["linear_solver"] = _choice(t["linear_solver"], _join(p, "linear_solver"), ("auto", "multigrid", "sparse", "dense", "cg"))
    return SolverOptions(**kw)


def _model(e: Mapping, path: str, default: str) -> str:
    from .models import MODELS

    return _choice(e.get("model", default), _join(path, "model"), MODELS)


def _points(e: Mapping, path: str, default: int | None = 20) -> int | None:
    if "points" not in e:
        return default
    v = e["points"]
    if v == "all":
        return None
    return _integer(v, _join(path, "points"), minimum=2)


def _load_data(e: Mapping, path: str, kind: str, base_dir: Path):
    from .data import load_dataset

    p = _join(path, "data")
    d = e["data"]
    if not isinstance(d, Mapping):
        _fail(p, f"must be a table such as {{ format = \"{_DATA_FORMATS[kind][0]}\", path = \"...\" }}, got {_show(d)}")
    d = dict(d)
    if "format" not in d:
        _fail(_join(p, "format"), f"missing (required); for a {kind} experiment one of {', '.join(repr(f) for f in _DATA_FORMATS[kind])}")
    fmt = _choice(d["format"], _join(p, "format"), _DATA_FORMATS[kind])
    if "path" not in d:
        _fail(_join(p, "path"), "missing (required): the data file, relative to the config file")
    file = _resolve(base_dir, d["path"], _join(p, "path"))
    if fmt == "table":
        tk = d.get("kind", "compression" if kind == "compression" else "force_depth")
        want = "compression" if kind == "compression" else "force_depth"
        if tk != want:
            _fail(_join(p, "kind"), f"a {kind} experiment needs a {want!r} table, got {_show(tk)}")
        d["kind"] = want
    d["path"] = str(file)
    if "displacement_table" in d:
        d["displacement_table"] = str(_resolve(base_dir, d["displacement_table"], _join(p, "displacement_table")))
    if "sort" in d:
        if kind not in ("analytic_indentation", "indentation", "compression"):
            _fail(_join(p, "sort"), "only force-depth (indentation) and compression data can be sorted (by depth, by strain)")
        d["sort"] = _bool(d["sort"], _join(p, "sort"))
    sort = d.pop("sort", False)
    if fmt == "instron":  # rows out of order: refused (or sorted) by the config with the rows named, as for indentation
        d.setdefault("monotonic", False)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            dataset = load_dataset(d)
    except DifftissueError as err:
        _reraise(p, err)
    notes = tuple(f"{p}: {w.category.__name__}: {' '.join(str(w.message).split())}" for w in caught)
    if kind in ("analytic_indentation", "indentation", "compression"):
        return dataset, file, notes, sort
    return dataset, file, notes


def _build_experiment(e: Mapping, path: str, name: str, base_dir: Path, *, material=None) -> Experiment:
    kind = e["scenario"]
    if kind == "incision":
        return _incision(e, path, name, base_dir, material)
    builder = {"analytic_indentation": _analytic, "indentation": _indentation, "compression": _compression, "fem_field": _fem_field}[kind]
    return builder(e, path, name, base_dir)


def _force_depth(e, path, base_dir, kind):
    """Load an indentation curve and choose the rows the fit uses; returns ``curve, file, notes,
    depth, force, sigma, unit, provenance`` (see :attr:`Experiment.provenance`)."""
    curve, file, notes, sort = _load_data(e, path, kind, base_dir)
    unit = _unit_of(e, path)
    max_depth = _length(e["max_depth"], _join(path, "max_depth"), unit) if "max_depth" in e else None
    if np.max(curve.depth) <= 0:
        _fail(_join(path, "data"), "no positive depth in the data; for an AFM file set data.contact = true (depth from the contact point)")
    steps: list[dict] = []
    rows = _loading_rows(curve, sort=sort, path=_join(path, "data"), record=steps)
    points = _points(e, path)
    sel = _downsample_rows(curve.depth[rows], x_max=max_depth, points=points, path=_join(path, "max_depth" if max_depth else "data"), key="max_depth", unit="m")
    labels, kind_name = _row_labels(curve)
    _record_thinning(labels, rows, sel, np.asarray(curve.depth, dtype=float), x_max=max_depth, points=points, record=steps)
    used = rows[sel]
    loaded = "every data row of the file"
    if str(curve.metadata.get("segment", "")).startswith("approach from contact"):
        loaded = f"the approach from the detected contact point ({kind_name[:-1]} {labels[0]}) to the turnaround (data.contact = true)"
    prov = {"file": str(file), "rows_loaded": len(curve), "loaded": loaded, "rows_used": int(used.size), "row_names": kind_name,
            "used": [int(i) for i in labels[used]], "steps": steps}
    depth, force = np.asarray(curve.depth, dtype=float)[used], np.asarray(curve.force, dtype=float)[used]
    sigma = _sigma(e.get("sigma", "rms"), _join(path, "sigma"), force, "N")
    notes = tuple(notes) + (_provenance_note(path, prov),)
    return curve, file, notes, depth, force, sigma, unit, prov


#: Young's moduli [Pa] a soft-tissue indentation can plausibly give (cells ~10 Pa to tendon ~1 GPa);
#: an effective modulus outside, estimated from the deepest point, points to a unit mistake.
PLAUSIBLE_MODULUS = (1.0, 1.0e9)
#: Deepest indentation / indenter radius (sphere, flat punch) considered plausible.
PLAUSIBLE_DEPTH_OVER_RADIUS = (1.0e-3, 1.0)


def _unit_hint(factor: float, declared: str | None) -> str:
    """'values in m declared as mm'-style hint for a length scale off by ``factor`` (> 1: too large)."""
    from .data import UNITS, normalize_unit

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
    from .materials import Material

    start = Material(**{**material.to_dict(), "youngs_modulus": E0})
    how = "; ".join(f"{name}: {how} {v:.4g} Pa" + (f" -> E = {v * (1 - nu**2):.4g} Pa at nu = {nu:g}" if kind == "effective" and nu != 0 else "")
                    for name, v, kind, how in ests)
    return start, {"youngs_modulus": {"value": E0, "config_value": float(material.youngs_modulus), "from": how}}


def _plausibility(path: str, depth: np.ndarray, force: np.ndarray, kw: Mapping, curve) -> tuple[str, ...]:
    """Warn (:class:`~difftissue.errors.ImplausibleUnitWarning`) when the depths do not fit the
    indenter (deepest point beyond the radius, or below 1e-3 of it) or the deepest point implies
    an effective modulus outside :data:`PLAUSIBLE_MODULUS`: most often a unit mistake. Returns
    the messages (also emitted as warnings)."""
    from .errors import ImplausibleUnitWarning

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


def _indenter(e, path, curve, kind):
    p = _join(path, "indenter")
    if "indenter" not in e:
        _fail(p, "missing (required): e.g. { shape = \"sphere\", radius = 27.5e-6 }")
    t = _table(e["indenter"], p, ("shape", "radius", "half_angle_deg", "bonded", "length_unit"), ("shape",))
    shape = _choice(t["shape"], _join(p, "shape"), ("sphere", "flat_punch", "cone"))
    unit = _unit_of(t, p)
    kw: dict[str, Any] = {"indenter": shape}
    if shape == "cone":
        for k in ("radius", "bonded"):
            if k in t:
                _fail(_join(p, k), "not used by a cone (give half_angle_deg)")
        if "half_angle_deg" not in t:
            _fail(_join(p, "half_angle_deg"), "missing (required for a cone): the half-angle in degrees")
        deg = _number(t["half_angle_deg"], _join(p, "half_angle_deg"), check=lambda v: 0 < v < 90, rule="an angle in degrees in (0, 90)")
        kw["half_angle"] = math.radians(deg)
    else:
        if "half_angle_deg" in t:
            _fail(_join(p, "half_angle_deg"), f"not used by a {shape} (give radius)")
        if "radius" not in t:
            _fail(_join(p, "radius"), f"missing (required for a {shape}): a length in {unit[0]}, or \"instrument\" for the tip radius in the data file")
        r = t["radius"]
        if r == "instrument":
            inst = getattr(curve, "metadata", {}).get("instrument", {}) or {}
            if not inst.get("tip_radius"):
                _fail(_join(p, "radius"), "\"instrument\": the data file records no tip radius; give the radius as a length")
            kw["radius"] = float(inst["tip_radius"])
        else:
            kw["radius"] = _length(r, _join(p, "radius"), unit)
        if "bonded" in t:
            if shape != "flat_punch" or kind != "indentation":
                _fail(_join(p, "bonded"), "only a simulated flat punch (scenario \"indentation\") can be bonded")
            kw["bonded_punch"] = _bool(t["bonded"], _join(p, "bonded"))
    return kw


def _analytic(e, path, name, base_dir) -> Experiment:
    from .scenarios import AnalyticIndentation

    curve, file, notes, depth, force, sigma, unit, prov = _force_depth(e, path, base_dir, "analytic_indentation")
    kw = _indenter(e, path, curve, "analytic_indentation")
    solution = _choice(e.get("solution", "half_space"), _join(path, "solution"), ("half_space", "exact_layer", "dimitriadis"))
    thickness = _length(e["thickness"], _join(path, "thickness"), unit) if "thickness" in e else None
    if solution != "half_space" and thickness is None:
        _fail(_join(path, "thickness"), f"missing (required by solution = {solution!r}): the layer thickness in {unit[0]}")
    if solution == "half_space" and thickness is not None:
        _fail(_join(path, "thickness"), "not used by solution = 'half_space'; choose 'exact_layer' or 'dimitriadis' for a layer")
    base = _choice(e.get("base", "bonded"), _join(path, "base"), ("bonded", "lubricated"))
    if kw["indenter"] == "cone" and solution != "half_space":
        _fail(_join(path, "solution"), "a cone has only the 'half_space' solution")
    if kw["indenter"] == "flat_punch" and solution == "dimitriadis":
        _fail(_join(path, "solution"), "'dimitriadis' is for a sphere; a flat punch on a layer uses 'exact_layer' (Hayes)")
    try:
        sc = AnalyticIndentation(depth, force, thickness=thickness, solution=solution, base=base, sigma=sigma, name=name, **kw)
    except DifftissueError as err:
        _reraise(path, err)
    model = {"sphere": "hertz", "flat_punch": "sneddon_flat_punch", "cone": "sneddon_cone"}[kw["indenter"]] if solution == "half_space" else f"{solution}_{kw['indenter']}"
    return Experiment(name, "analytic_indentation", model, sc, (file,), notes, prov, _plausibility(path, depth, force, kw, curve),
                      _indentation_estimate(depth, force, sigma, kw), coarsen_skip="a closed-form solution: no mesh, no discretisation error")


def _compression(e, path, name, base_dir) -> Experiment:
    from .mesh import block
    from .scenarios import Compression, cylinder

    curve, file, notes, x, y, prov = _stress_strain(e, path, base_dir)
    measure = _choice(e.get("measure", "engineering"), _join(path, "measure"), ("engineering", "true"))
    plausibility = _compression_plausibility(path, curve, x, y, measure)
    sigma = _sigma(e.get("sigma", "rms"), _join(path, "sigma"), y, "Pa")
    platens = _choice(e.get("platens", "frictionless"), _join(path, "platens"), ("frictionless", "bonded"))
    rollers = _rollers(e["rollers"], _join(path, "rollers")) if "rollers" in e else ()
    model = _model(e, path, "springs_volume")
    options = _solver_options(e, path)
    p = _join(path, "specimen")
    spec = _table(e.get("specimen", {}), p, ("shape", "size", "cells", "diameter", "height", "cells_radial", "cells_height", "mesh", "length_unit", "reorient"))
    files = [file]
    coarse_mesh, skip = None, _MESH_FILE_SKIP
    if "mesh" in spec:
        mesh, mfile = _mesh_file(spec, p, base_dir)
        files.append(mfile)
    else:
        shape = _choice(spec.get("shape", "block"), _join(p, "shape"), ("block", "cylinder"))
        unit = _unit_of(spec, p)
        h_data = curve.height or 0.01
        d_data = curve.diameter or h_data
        if shape == "block":
            for k in ("diameter", "height", "cells_radial", "cells_height"):
                if k in spec:
                    _fail(_join(p, k), "not used by shape = 'block' (give size and cells)")
            # default: a cube of the specimen's height (frictionless platens: any shape gives the same answer)
            size = _lengths(spec["size"], _join(p, "size"), unit) if "size" in spec else (h_data, h_data, h_data)
            cells = _counts(spec.get("cells", [2, 2, 2]), _join(p, "cells"))
            mesh = block(size, cells)
            coarse_mesh, skip = _coarse_block(size, cells)
        else:
            for k in ("size", "cells"):
                if k in spec:
                    _fail(_join(p, k), "not used by shape = 'cylinder' (give diameter, height, cells_radial, cells_height)")
            dia = _length(spec["diameter"], _join(p, "diameter"), unit) if "diameter" in spec else d_data
            hei = _length(spec["height"], _join(p, "height"), unit) if "height" in spec else h_data
            nr = _integer(spec.get("cells_radial", 4), _join(p, "cells_radial"), minimum=1)
            nh = _integer(spec.get("cells_height", 4), _join(p, "cells_height"), minimum=1)
            if model == "springs_volume":
                _fail(_join(path, "model"), "a cylinder mesh has no cube lattice: use 'stable_neo_hookean', 'fem_linear' or 'fem_neo_hookean' (or a block: with frictionless platens any shape gives the same answer)")
            mesh = cylinder(dia, hei, nr, nh)
            coarse_mesh, skip = _coarse_cylinder(dia, hei, nr, nh)
    try:
        sc = Compression(mesh, x, y, model=model, bonded=platens == "bonded", measure=measure, rollers=rollers, sigma=sigma, options=options, name=name)
    except DifftissueError as err:
        _reraise(path, err)
    coarsen = None
    if coarse_mesh is not None:
        def coarsen():
            m, info = coarse_mesh()
            return Compression(m, x, y, model=model, bonded=platens == "bonded", measure=measure, rollers=rollers, sigma=sigma, options=options, name=name), info
    return Experiment(name, "compression", model, sc, tuple(files), notes, prov, plausibility, _compression_estimate(x, y),
                      coarsen=coarsen, coarsen_skip=skip)


def _stress_strain(e, path, base_dir):
    """Load a compression curve and choose the rows the fit uses, as :func:`_force_depth` does
    for indentation: the loading segment (unloading left out), rows out of order refused or
    sorted (``data.sort``), strain <= 0 and beyond ``max_strain`` left out, thinned to
    ``points``; every row accounted for. Returns ``curve, file, notes, strain, stress,
    provenance`` (strain [-] and stress [Pa] in the ``measure`` asked for; see
    :attr:`Experiment.provenance`)."""
    curve, file, notes, sort = _load_data(e, path, "compression", base_dir)
    measure = _choice(e.get("measure", "engineering"), _join(path, "measure"), ("engineering", "true"))
    if measure == "engineering":
        x, y = curve.strain, curve.stress
    else:
        if curve.true_strain is None or curve.true_stress is None:
            _fail(_join(path, "measure"), "'true' needs true strain and true stress columns in the data; use 'engineering'")
        x, y = curve.true_strain, curve.true_stress
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    max_strain = None
    if "max_strain" in e:
        max_strain = _number(e["max_strain"], _join(path, "max_strain"), check=lambda v: 0 < v < 1, rule="a strain in (0, 1)")
    if x.size and np.max(x) <= 0:
        _fail(_join(path, "data"), "no positive strain in the data (compression is positive: set the strain or displacement column's sign to -1 or \"auto\")")
    steps: list[dict] = []
    labels, kind_name = _row_labels(curve)
    rows = _loading_order(x, labels, kind_name, turnaround=None, sort=sort, path=_join(path, "data"), record=steps, what="strain")
    points = _points(e, path)
    sel = _downsample_rows(x[rows], x_max=max_strain, points=points, path=_join(path, "max_strain" if max_strain else "data"), key="max_strain", unit="")
    _record_thinning(labels, rows, sel, x, x_max=max_strain, points=points, record=steps, what="strain")
    used = rows[sel]
    prov = {"file": str(file), "rows_loaded": len(curve), "loaded": "every data row of the file", "rows_used": int(used.size),
            "row_names": kind_name, "used": [int(i) for i in labels[used]], "steps": steps}
    notes = tuple(notes) + (_provenance_note(path, prov),)
    return curve, file, notes, x[used], y[used], prov


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
    from .errors import ImplausibleUnitWarning

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


#: Why an experiment on a mesh file has no discretisation estimate.
_MESH_FILE_SKIP = "the specimen is a mesh file: difftissue cannot build a coarser version of it (give size and cells to get the estimate)"


def _halved(counts) -> tuple[tuple[int, ...], list[float]]:
    """Half the cells in each direction (at least 1) and each direction's fine / coarse ratio [-]."""
    coarse = tuple(max(1, int(n) // 2) for n in counts)
    return coarse, [n / c for n, c in zip(counts, coarse)]


def _size_ratio(ratios) -> float:
    """Coarse / fine cell size [-] from per-direction ratios: the geometric mean (h ~ cell volume^(1/3))."""
    return float(np.prod(ratios) ** (1.0 / len(ratios)))


def _coarse_block(size, cells, **kw):
    """``(builder, None)`` of a block of about half the cells (``builder() -> (mesh, info)``), or
    ``(None, reason)`` when every direction already has one cell."""
    from .mesh import block

    coarse, ratios = _halved(cells)
    if coarse == tuple(cells):
        return None, f"the specimen has one cell in each direction ({list(cells)}): there is no coarser mesh"
    info = {"fine_cells": list(cells), "coarse_cells": list(coarse), "refinement_ratio": _size_ratio(ratios)}
    return (lambda: (block(size, coarse, **kw), info)), None


def _coarse_cylinder(dia, hei, nr, nh):
    """Like :func:`_coarse_block` for a cylinder of ``nr`` radial and ``nh`` axial cells."""
    from .scenarios import cylinder

    (cr, ch), (rr, rh) = _halved((nr, nh))
    if (cr, ch) == (nr, nh):
        return None, "the cylinder has one radial and one axial cell: there is no coarser mesh"
    info = {"fine_cells": {"radial": nr, "height": nh}, "coarse_cells": {"radial": cr, "height": ch}, "refinement_ratio": _size_ratio((rr, rr, rh))}
    return (lambda: (cylinder(dia, hei, cr, ch), info)), None


def _mesh_file(spec: dict, p: str, base_dir: Path):
    from .mesh import read_mesh

    for k in spec:
        if k not in ("mesh", "length_unit", "reorient"):
            _fail(_join(p, k), "not used with 'mesh' (a mesh file takes only length_unit and reorient)")
    unit = _unit_of(spec, p, _MESH_UNITS)
    file = _resolve(base_dir, spec["mesh"], _join(p, "mesh"))
    reorient = _bool(spec.get("reorient", False), _join(p, "reorient"))
    try:
        return read_mesh(file, length_unit=unit[0], reorient=reorient), file
    except DifftissueError as err:
        _reraise(_join(p, "mesh"), err)


def _indentation(e, path, name, base_dir) -> Experiment:
    from .scenarios import Indentation, indentation_block

    curve, file, notes, depth, force, sigma, unit, prov = _force_depth(e, path, base_dir, "indentation")
    kw = _indenter(e, path, curve, "indentation")
    model = _model(e, path, "springs_volume")
    base = _choice(e.get("base", "bonded"), _join(path, "base"), ("bonded", "sliding"))
    rollers = _rollers(e["rollers"], _join(path, "rollers")) if "rollers" in e else ()
    penalty = _positive(e["penalty"], _join(path, "penalty")) if "penalty" in e else 100.0
    if "penalty" in e and kw["indenter"] == "flat_punch":
        _fail(_join(path, "penalty"), "not used by a flat punch (its displacement is prescribed)")
    options = _solver_options(e, path)
    p = _join(path, "specimen")
    if "specimen" not in e:
        _fail(p, "missing (required): e.g. { size = [2e-3, 2e-3, 1e-3], cells = [6, 6, 4], symmetry = \"quarter\" } or { mesh = \"specimen.vtu\", length_unit = \"mm\" }")
    spec = _table(e["specimen"], p, ("shape", "size", "cells", "symmetry", "refine", "core", "mesh", "length_unit", "reorient"))
    files = [file]
    symmetry = "none"
    coarse_mesh, skip = None, _MESH_FILE_SKIP
    if "mesh" in spec:
        mesh, mfile = _mesh_file(spec, p, base_dir)
        files.append(mfile)
    else:
        _choice(spec.get("shape", "block"), _join(p, "shape"), ("block",))
        sunit = _unit_of(spec, p)
        if "size" not in spec:
            _fail(_join(p, "size"), f"missing (required): [Lx, Ly, H] of the whole specimen in {sunit[0]}")
        size = _lengths(spec["size"], _join(p, "size"), sunit)
        cells = _counts(spec.get("cells", [6, 6, 4]), _join(p, "cells"))
        symmetry = _choice(spec.get("symmetry", "quarter"), _join(p, "symmetry"), ("quarter", "none"))
        refine = _length(spec["refine"], _join(p, "refine"), sunit) if "refine" in spec else None
        if refine is not None and model == "springs_volume":
            _fail(_join(p, "refine"), "graded cells are not cubes: use model 'fem_linear', 'fem_neo_hookean' or 'stable_neo_hookean' with refine")
        core = _length(spec["core"], _join(p, "core"), sunit) if "core" in spec else None
        if core is not None:
            if refine is None:
                _fail(_join(p, "core"), "needs refine (the size of the uniform cells kept within core of the axis and the surface)")
            reach = min(size[0] / 2, size[1] / 2, size[2])
            if not core < reach:
                _fail(_join(p, "core"), f"must be smaller than the half-width and the height of the specimen ({reach / sunit[1]:.6g} {sunit[0]}), got {spec['core']!r}")
            if core < refine:
                _fail(_join(p, "core"), f"must be at least one cell of refine ({refine / sunit[1]:.6g} {sunit[0]}), got {spec['core']!r}")
        try:
            mesh = indentation_block(size, cells, symmetry=symmetry, refine=refine, core=core)
        except DifftissueError as err:
            _reraise(p, err)
        coarse_mesh, skip = _coarse_indentation_block(size, cells, symmetry, refine, core)
        if depth.max() >= size[2]:
            _fail(_join(path, "max_depth"), f"the deepest point ({depth.max():.3g} m) reaches the specimen's height ({size[2]:.3g} m)")
    try:
        sc = Indentation(mesh, depth, force, model=model, base=base, symmetry=symmetry, rollers=rollers, penalty=penalty, sigma=sigma, options=options, name=name, **kw)
    except DifftissueError as err:
        _reraise(path, err)
    coarsen = None
    if coarse_mesh is not None:
        def coarsen():
            m, info = coarse_mesh()
            return Indentation(m, depth, force, model=model, base=base, symmetry=symmetry, rollers=rollers, penalty=penalty, sigma=sigma, options=options, name=name, **kw), info
    return Experiment(name, "indentation", model, sc, tuple(files), notes, prov, _plausibility(path, depth, force, kw, curve),
                      _indentation_estimate(depth, force, sigma, kw), coarsen=coarsen, coarsen_skip=skip)


def _coarse_indentation_block(size, cells, symmetry: str, refine, core=None):
    """Like :func:`_coarse_block` for :func:`~difftissue.scenarios.indentation_block`: half the
    cells, the same size and symmetry; a graded block doubles its first cell ``refine`` [m]
    (keeping the uniform ``core`` [m], which then holds half as many cells)."""
    from .scenarios import indentation_block

    coarse, ratios = _halved(cells)
    if coarse == tuple(cells):
        return None, f"the specimen has one cell in each direction ({list(cells)}): there is no coarser mesh"
    info = {"fine_cells": list(cells), "coarse_cells": list(coarse), "refinement_ratio": _size_ratio(ratios)}
    r2 = None if refine is None else 2.0 * refine
    if core is not None:
        try:
            indentation_block(size, coarse, symmetry=symmetry, refine=r2, core=core)
        except DifftissueError as err:
            return None, f"the coarser block (cells {list(coarse)}, refine {r2:.6g} m, core {core:.6g} m) cannot be built: {err}"
    return (lambda: (indentation_block(size, coarse, symmetry=symmetry, refine=r2, core=core), info)), None


def _node_set_spec(value, path: str):
    if isinstance(value, str):
        return _string(value, path)
    if isinstance(value, Mapping):
        from .selectors import selector_from_dict

        try:
            selector_from_dict(dict(value))
        except DifftissueError as err:
            _reraise(path, err)
        except (TypeError, KeyError, ValueError) as err:
            _fail(path, f"not a valid selector: {err}")
        return dict(value)
    _fail(path, f"must be the name of a point-data node set or a selector table, got {_show(value)}")


def _components(value, path: str) -> str:
    if not isinstance(value, str) or not value or any(c not in "xyz" for c in value) or len(set(value)) != len(value):
        _fail(path, f"must be letters from 'xyz' (e.g. \"z\" or \"xyz\"), got {_show(value)}")
    return value


def _rollers(value, path: str) -> tuple:
    """``rollers``: a list of face names (``"x-min"``: the face's normal component held) or
    tables ``{ set = selector-or-mask-name, components = "x" }``; returns
    :class:`~difftissue.boundary.Roller` objects."""
    from .boundary import ROLLER_FACES, Roller

    if not isinstance(value, list):
        _fail(path, f"must be a list of faces such as [\"x-min\", \"y-min\"] or tables {{ set = ..., components = \"x\" }}, got {_show(value)}")
    out = []
    for i, entry in enumerate(value):
        q = _join(path, i)
        if isinstance(entry, str):
            _choice(entry, q, tuple(ROLLER_FACES))
            out.append(Roller(entry))
            continue
        t = _table(entry, q, ("set", "components"), ("set", "components"))
        nodes = _node_set_spec(t["set"], _join(q, "set"))
        comps = _components(t["components"], _join(q, "components"))
        if len(comps) == 3:
            _fail(_join(q, "components"), "a roller holding x, y and z is a clamp: leave at least one component free")
        out.append(Roller(nodes, comps))
    return tuple(out)


def _fem_field(e, path, name, base_dir) -> Experiment:
    from .scenarios import FEMField

    p = _join(path, "prescribed")
    if "prescribed" not in e:
        _fail(p, "missing (required): the node sets whose displacement the reference prescribed, e.g. [{ set = \"bottom\" }, { set = \"punch\", components = \"z\" }]")
    pres = e["prescribed"]
    if not isinstance(pres, list) or not pres:
        _fail(p, f"must be a non-empty list of tables {{ set = ..., components = \"xyz\" }}, got {_show(pres)}")
    prescribed = []
    for i, entry in enumerate(pres):
        q = _join(p, i)
        t = _table(entry, q, ("set", "components"), ("set",))
        prescribed.append({"set": _node_set_spec(t["set"], _join(q, "set")), "components": _components(t.get("components", "xyz"), _join(q, "components"))})
    observe = _node_set_spec(e["observe"], _join(path, "observe")) if "observe" in e else None
    reaction = None
    if "reaction" in e:
        q = _join(path, "reaction")
        t = _table(e["reaction"], q, ("set", "components", "force", "field"), ("set",))
        comps = _components(t.get("components", "z"), _join(q, "components"))
        reaction = {"set": _node_set_spec(t["set"], _join(q, "set")), "components": comps}
        if ("force" in t) == ("field" in t):
            _fail(q, "give exactly one of 'force' (total force in N, one value per component) or 'field' (a nodal reaction point field of the file)")
        if "force" in t:
            f = t["force"]
            f = [f] if _is_number(f) else f
            if not isinstance(f, list) or len(f) != len(comps):
                _fail(_join(q, "force"), f"must be {len(comps)} number(s) in N (one per component {comps!r}), got {_show(t['force'])}")
            reaction["force"] = [_number(v, _join(_join(q, "force"), j), what="a force in N") for j, v in enumerate(f)]
        else:
            reaction["field"] = _string(t["field"], _join(q, "field"))
    ds = _positive(e["displacement_sigma"], _join(path, "displacement_sigma"), "m") if "displacement_sigma" in e else None
    fs = _positive(e["force_sigma"], _join(path, "force_sigma"), "N") if "force_sigma" in e else None
    if fs is not None and reaction is None:
        _fail(_join(path, "force_sigma"), "needs a 'reaction' to compare")
    model = _model(e, path, "fem_linear")
    options = _solver_options(e, path)
    mode = _choice(e.get("reference_mesh", "interpolate" if "specimen" in e else "own"), _join(path, "reference_mesh"), ("own", "interpolate"))
    if mode == "interpolate" and "specimen" not in e:
        _fail(_join(path, "specimen"), "missing (required with reference_mesh = \"interpolate\"): the model's own mesh, e.g. { cells = [8, 8, 4] } "
              "(a block spanning the reference's bounding box) or { mesh = \"model.vtu\", length_unit = \"mm\" }")
    if mode == "own":
        for k in ("specimen", "tolerance"):
            if k in e:
                _fail(_join(path, k), "not used with reference_mesh = \"own\" (the model runs on the reference's mesh)")
    tolerance = _number(e["tolerance"], _join(path, "tolerance"), what="a distance >= 0 in m", check=lambda v: v >= 0) if "tolerance" in e else None
    result, file, notes = _load_data(e, path, "fem_field", base_dir)
    if mode == "own":
        if result.mesh is None:
            _fail(_join(path, "reference_mesh"), f"the reference holds {sorted(result.cells)} cells, not linear tetrahedra the model can run on: "
                  "give a 'specimen' (the model's own mesh) and the reference is interpolated onto it")
        try:
            sc = FEMField(result.mesh, result.displacement, prescribed=prescribed, model=model, observe=observe, reaction=reaction, displacement_sigma=ds, force_sigma=fs, options=options, name=name)
        except DifftissueError as err:
            _reraise(path, err)
        return Experiment(name, "fem_field", model, sc, (file,), notes,
                          coarsen_skip="the displacements are observed on the nodes of the given mesh: a coarser mesh has no such nodes")
    specimen, files, coarse_mesh, skip = _fem_field_specimen(e, path, base_dir, result)
    kw = dict(prescribed=prescribed, model=model, observe=observe, reaction=reaction, displacement_sigma=ds, force_sigma=fs, options=options, name=name, tolerance=tolerance)
    try:
        sc = FEMField(result, result.displacement, specimen=specimen, **kw)
    except DifftissueError as err:
        _reraise(path, err)
    coarsen = None
    if coarse_mesh is not None:
        def coarsen():
            m, info = coarse_mesh()
            return FEMField(result, result.displacement, specimen=m, **kw), info
    return Experiment(name, "fem_field", model, sc, (file, *files), notes, coarsen=coarsen, coarsen_skip=skip)


def _fem_field_specimen(e, path, base_dir, result):
    """The model's own mesh of an interpolated fem_field: ``(mesh, extra files, coarse builder,
    skip reason)``. A block defaults to the reference's bounding box."""
    from .mesh import block

    p = _join(path, "specimen")
    spec = _table(e["specimen"], p, ("shape", "size", "origin", "cells", "mesh", "length_unit", "reorient"))
    if "mesh" in spec:
        mesh, mfile = _mesh_file(spec, p, base_dir)
        return mesh, (mfile,), None, _MESH_FILE_SKIP
    _choice(spec.get("shape", "block"), _join(p, "shape"), ("block",))
    unit = _unit_of(spec, p)
    if "cells" not in spec:
        _fail(_join(p, "cells"), "missing (required): the model's cells [nx, ny, nz] (the block spans the reference's bounding box unless size and origin are given)")
    cells = _counts(spec["cells"], _join(p, "cells"))
    lo, hi = result.points.min(axis=0), result.points.max(axis=0)
    size = _lengths(spec["size"], _join(p, "size"), unit) if "size" in spec else tuple(float(v) for v in hi - lo)
    if "origin" in spec:
        o = spec["origin"]
        if not isinstance(o, list) or len(o) != 3:
            _fail(_join(p, "origin"), f"must be 3 coordinates in {unit[0]} (a list), got {_show(o)}")
        origin = tuple(_number(v, _join(_join(p, "origin"), i), what=f"a coordinate in {unit[0]}") * unit[1] for i, v in enumerate(o))
    else:
        origin = tuple(float(v) for v in lo)
    if min(size) <= 0:
        _fail(_join(p, "size"), f"the reference is flat (bounding box {size} m): give size")
    try:
        mesh = block(size, cells, origin=origin)
    except DifftissueError as err:
        _reraise(p, err)
    coarse_mesh, skip = _coarse_block(size, cells, origin=origin)
    return mesh, (), coarse_mesh, skip


# ============================================================================ incision
_INCISION_QUANTITIES = ("surface_width", "max_width", "width_over_length")
_LAYER_KEYS = ("name", "thickness", "cells", "grading", "fitted") + tuple(FIELDS)


def _incision_data(e: Mapping, path: str, base_dir: Path, unit: tuple[str, float]):
    """``data`` of an incision: ``{ quantity, value }``, ``{ quantity = "surface_width",
    positions, widths }`` (inline, lengths in ``length_unit``) or ``{ format = "table", path }``
    (CSV with header ``position,width``)."""
    p = _join(path, "data")
    d = e["data"]
    if not isinstance(d, Mapping):
        _fail(p, f"must be a table such as {{ quantity = \"max_width\", value = 0.8 }}, got {_show(d)}")
    fmt = _choice(d.get("format", "inline"), _join(p, "format"), _DATA_FORMATS["incision"])
    files: tuple[Path, ...] = ()
    if fmt == "table":
        t = _table(d, p, ("format", "path", "quantity"), ("path",))
        q = _choice(t.get("quantity", "surface_width"), _join(p, "quantity"), ("surface_width",))
        file = _resolve(base_dir, t["path"], _join(p, "path"))
        try:
            arr = np.genfromtxt(file, delimiter=",", names=True)
        except (ValueError, OSError) as err:
            _fail(_join(p, "path"), f"cannot read {file.name} as CSV with a header line 'position,width': {err}")
        names = arr.dtype.names or ()
        if "position" not in names or "width" not in names:
            _fail(_join(p, "path"), f"{file.name} needs the columns 'position' and 'width' (in {unit[0]}), found {list(names)}")
        pos, w = np.atleast_1d(arr["position"]) * unit[1], np.atleast_1d(arr["width"]) * unit[1]
        if pos.size < 1 or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(w))):
            _fail(_join(p, "path"), f"{file.name}: positions and widths must be finite numbers")
        return q, pos, w, (file,)
    q = _choice(d.get("quantity"), _join(p, "quantity"), _INCISION_QUANTITIES) if "quantity" in d else _fail(_join(p, "quantity"), f"missing (required); one of {', '.join(_INCISION_QUANTITIES)}")
    if q == "surface_width":
        t = _table(d, p, ("format", "quantity", "positions", "widths"), ("positions", "widths"))
        pos, w = t["positions"], t["widths"]
        if not isinstance(pos, list) or not isinstance(w, list) or not pos or len(pos) != len(w):
            _fail(_join(p, "widths"), f"positions and widths must be two lists of the same non-zero length (in {unit[0]})")
        pos = np.array([_number(v, _join(_join(p, "positions"), i), what=f"a length in {unit[0]}") for i, v in enumerate(pos)]) * unit[1]
        w = np.array([_number(v, _join(_join(p, "widths"), i), what=f"a width in {unit[0]}", check=lambda x: x >= 0, rule=f"a width >= 0 in {unit[0]}") for i, v in enumerate(w)]) * unit[1]
        return q, pos, w, files
    t = _table(d, p, ("format", "quantity", "value"), ("value",))
    if q == "max_width":
        v = _length(t["value"], _join(p, "value"), unit)
    else:
        v = _number(t["value"], _join(p, "value"), what="a positive ratio w/l", check=lambda x: x > 0)
    return q, None, np.array([v]), files


def _incision(e, path, name, base_dir, material) -> Experiment:
    from .cutting import ScalpelPath, cut_specimen
    from .incision import Incision, IncisionOptions
    from .materials import Material
    from .mesh import Specimen, layered_skin

    unit = _unit_of(e, path)
    model = _model(e, path, "stable_neo_hookean")
    quantity, positions, observed, files = _incision_data(e, path, base_dir, unit)
    unit_y = "1" if quantity == "width_over_length" else "m"
    sigma = _sigma(e.get("sigma", "rms"), _join(path, "sigma"), observed, unit_y)
    # specimen: layers (the fitted ones take [material]) or a mesh file (every region fitted)
    p = _join(path, "specimen")
    if "specimen" not in e:
        _fail(p, "missing (required): e.g. { size = [12, 12], cells = [12, 12], layers = [{ name = \"dermis\", thickness = 2, cells = 2, fitted = true }, ...] }")
    spec = _table(e["specimen"], p, ("size", "cells", "layers", "refine", "refine_at", "core", "mesh", "length_unit", "reorient"))
    files = list(files)
    fitted = None
    if "mesh" in spec:
        for k in ("size", "cells", "layers", "refine", "refine_at", "core"):
            if k in spec:
                _fail(_join(p, k), "not used with 'mesh' (every region of a mesh file takes [material])")
        mesh, mfile = _mesh_file(spec, p, base_dir)
        files.append(mfile)
        specimen = Specimen(mesh, (material,) * len(mesh.region_names))
    else:
        sunit = _unit_of(spec, p) if "length_unit" in spec else unit
        for k in ("size", "layers"):
            if k not in spec:
                _fail(_join(p, k), "missing (required)")
        size = _lengths(spec["size"], _join(p, "size"), sunit, n=2)
        cells = _counts(spec.get("cells", [12, 12]), _join(p, "cells"), n=2)
        lp = _join(p, "layers")
        if not isinstance(spec["layers"], list) or not spec["layers"]:
            _fail(lp, "must be a non-empty list of tables { name, thickness, cells, fitted | material fields }")
        layers, fitted, grading = [], [], {}
        for i, lay in enumerate(spec["layers"]):
            q = _join(lp, i)
            t = _table(lay, q, _LAYER_KEYS, ("name", "thickness"))
            lname = _string(t["name"], _join(q, "name"))
            thick = _length(t["thickness"], _join(q, "thickness"), sunit)
            nc = _integer(t.get("cells", 1), _join(q, "cells"), minimum=1)
            if "grading" in t:
                grading[lname] = _positive(t["grading"], _join(q, "grading"))
                if nc < 2:
                    _fail(_join(q, "grading"), f"needs at least two cells through the layer (cells = {nc})")
            is_fitted = _bool(t.get("fitted", False), _join(q, "fitted"))
            fields = {k: t[k] for k in FIELDS if k in t}
            if is_fitted:
                if fields:
                    _fail(_join(q, sorted(fields)[0]), "a fitted layer takes its material from [material]; remove the field or set fitted = false")
                mat = material
                fitted.append(lname)
            else:
                for k in ("youngs_modulus", "poisson_ratio"):
                    if k not in t:
                        _fail(_join(q, k), "missing (required for a layer that is not fitted)")
                mat = Material(**_material_values(fields, q))
            layers.append((lname, thick, mat, nc))
        if not fitted:
            _fail(lp, "no layer has fitted = true: the [material] must apply to at least one layer")
        lateral = {}
        if "refine" in spec:
            lateral["refine"] = _length(spec["refine"], _join(p, "refine"), sunit)
            if "refine_at" in spec:
                at = spec["refine_at"]
                if not isinstance(at, list) or len(at) != 2:
                    _fail(_join(p, "refine_at"), f"must be a point [x, y] on the top surface in {sunit[0]}, got {_show(at)}")
                lateral["refine_at"] = tuple(_number(v, _join(_join(p, "refine_at"), i), what=f"a coordinate in {sunit[0]}") * sunit[1] for i, v in enumerate(at))
                if not all(0 <= a <= s for a, s in zip(lateral["refine_at"], size)):
                    _fail(_join(p, "refine_at"), f"must lie on the top surface, within [0, {size[0] / sunit[1]:g}] x [0, {size[1] / sunit[1]:g}] {sunit[0]}")
            if "core" in spec:
                lateral["core"] = _lengths(spec["core"], _join(p, "core"), sunit, n=2)
        else:
            for k in ("refine_at", "core"):
                if k in spec:
                    _fail(_join(p, k), "needs refine (the lateral cell size at the refinement lines)")
        try:
            specimen = layered_skin(layers, size=size, resolution=cells, grading=grading or None, **lateral)
        except DifftissueError as err:
            _reraise(p, err)
    # the cut
    cp = _join(path, "cut")
    if "cut" not in e:
        _fail(cp, "missing (required): e.g. { path = [[3, 6], [9, 6]], depth = 2 } (lengths in length_unit)")
    c = _table(e["cut"], cp, ("path", "depth", "through", "tilt_deg", "method"), ("path",))
    pts = c["path"]
    if not isinstance(pts, list) or len(pts) < 2 or not all(isinstance(q, list) and len(q) in (2, 3) for q in pts):
        _fail(_join(cp, "path"), f"must be a list of >= 2 points [x, y] on the top surface in {unit[0]}, got {_show(pts)}")
    pts = [[_number(v, _join(_join(cp, "path"), i), what=f"a coordinate in {unit[0]}") * unit[1] for v in q] for i, q in enumerate(pts)]
    depth = _length(c["depth"], _join(cp, "depth"), unit) if "depth" in c else None
    through = _bool(c.get("through", False), _join(cp, "through"))
    tilt = math.radians(_number(c.get("tilt_deg", 0.0), _join(cp, "tilt_deg"), what="an angle in degrees"))
    method = _choice(c.get("method", "snap"), _join(cp, "method"), ("snap", "remove"))
    try:
        scalpel = ScalpelPath(pts, depth=depth, through=through, tilt=tilt)
    except DifftissueError as err:
        _reraise(cp, err)
    try:
        cut = cut_specimen(specimen, scalpel, method=method)
    except DifftissueError as err:
        _reraise(cp, err)
    bp = _join(path, "boundary")
    b = _table(e.get("boundary", {}), bp, ("lateral", "base", "rollers"))
    lateral = _choice(b.get("lateral", "held"), _join(bp, "lateral"), ("held", "roller", "free"))
    base = _choice(b.get("base", "clamped"), _join(bp, "base"), ("clamped", "sliding"))
    rollers = _rollers(b["rollers"], _join(bp, "rollers")) if "rollers" in b else ()
    steps = _integer(e.get("scalpel_steps", 4), _join(path, "scalpel_steps"), minimum=1)
    so = _solver_options(e, path)
    options = IncisionOptions(scalpel_steps=steps, rtol=so.rtol, xtol=so.xtol, max_steps=so.max_steps, linear_solver=so.linear_solver, failure=so.failure)
    if model == "springs_volume" and getattr(cut.mesh, "lattice", None) is None:
        _fail(_join(path, "model"), "an imported mesh has no cube lattice: use 'stable_neo_hookean', 'fem_linear' or 'fem_neo_hookean'")
    try:
        sc = Incision(cut, model=model, quantity=quantity, positions=positions, observed=observed, sigma=sigma, fitted_regions=fitted, lateral=lateral, base=base, rollers=rollers, options=options, name=name)
    except DifftissueError as err:
        _reraise(path, err)
    notes = (f"{path}: {cut.quality}",)
    return Experiment(name, "incision", model, sc, tuple(files), notes,
                      coarsen_skip="the cut is snapped to this mesh's nodes: a coarser mesh makes a different cut, so the change would not be the mesh's alone")
