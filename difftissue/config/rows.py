"""The measured rows a fit uses: loading a data file named by an experiment's ``data`` table,
the loading segment in loading order (rows out of order refused or sorted, unloading left out),
thinning to ``points`` samples up to ``max_depth`` / ``max_strain``, and the record of every
row loaded, used or left out and why (:attr:`~difftissue.config.Experiment.provenance`).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..data import load_dataset
from ..errors import DifftissueError, NonMonotonicError, _cite
from .schema import (
    _DATA_FORMATS,
    _bool,
    _choice,
    _fail,
    _join,
    _length,
    _number,
    _points,
    _reraise,
    _resolve,
    _show,
    _sigma,
    _unit_of,
)

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
    names = prov["row_names"]
    parts = [f"{st['action']} {len(st['rows'])} ({names} {_cite(st['rows'], 6)}): {st['reason']}" for st in prov["steps"]]
    return (f"{path}: the fit uses {prov['rows_used']} of the {prov['rows_loaded']} rows loaded from {Path(prov['file']).name} "
            f"({prov['loaded']})" + ("; " + "; ".join(parts) if parts else ""))


def _load_data(e: Mapping, path: str, kind: str, base_dir: Path):
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
