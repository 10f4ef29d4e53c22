"""Measured curves as typed datasets (:class:`ForceDepthCurve`, :class:`CompressionCurve`) and
their generic loaders from declared-column tables.
"""

from __future__ import annotations

import math
import warnings
from typing import Mapping

import equinox as eqx
import numpy as np

from ..errors import DataError, InconsistentDataError, InconsistentDataWarning, NonMonotonicError, _cite
from .table import load_table, Table
from .units import _check_plausible, parse_quantity, PLAUSIBLE_RANGES


# ============================================================================ datasets
def _float_1d(x) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(-1)


def _opt_float_1d(x):
    return None if x is None else _float_1d(x)


def _opt_float(x):
    return None if x is None else float(x)


def _slice_arrays(d: dict, index) -> dict:
    return {k: np.asarray(v)[index] for k, v in d.items()}


class ForceDepthCurve(eqx.Module):
    """An indentation curve: depth and force samples in acquisition order.

    An equinox Module (a pytree whose array leaves are NumPy float64 arrays); pass
    ``curve.depth`` / ``curve.force`` to jitted code, or use ``eqx.filter_jit``.

    Attributes:
        depth: ``(n,)`` indenter position [m], **positive into the specimen**. Before
            :func:`shift_to_contact` its zero is arbitrary (an instrument coordinate);
            after it, 0 is the contact point.
        force: ``(n,)`` force on the specimen [N], **positive compressive**.
        time: ``(n,)`` time [s], or ``None``.
        channels: other columns of the file, converted to SI where their unit is known
            (e.g. ``piezo``, ``cantilever`` [m] for the Chiaro).
        metadata: ``source`` (path), ``sha256``, ``format``, ``encoding``,
            ``line_endings``, ``columns`` and ``units`` (as written in the file),
            ``signs`` (the flips applied), ``instrument`` (SI values: ``tip_radius`` [m],
            ``cantilever_stiffness`` [N/m], ...), ``turnaround_index`` (last sample of the
            approach), ``contact`` (after :func:`shift_to_contact`), ...
    """

    depth: np.ndarray = eqx.field(converter=_float_1d)
    force: np.ndarray = eqx.field(converter=_float_1d)
    time: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    channels: dict = eqx.field(default_factory=dict)
    metadata: dict = eqx.field(default_factory=dict)

    def __check_init__(self):
        n = self.depth.shape[0]
        if self.force.shape[0] != n:
            raise DataError(f"depth has {n} samples but force has {self.force.shape[0]}")
        if self.time is not None and self.time.shape[0] != n:
            raise DataError(f"depth has {n} samples but time has {self.time.shape[0]}")
        for k, v in self.channels.items():
            if np.shape(v)[:1] != (n,):
                raise DataError(f"channel {k!r} has shape {np.shape(v)}; it needs {n} samples")

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    @property
    def turnaround_index(self) -> int:
        """Index of the last sample of the approach (loading) segment.

        ``metadata["turnaround_index"]`` when the loader knows it (the Chiaro piezo
        reversal), else the first maximum of ``depth``.
        """
        i = self.metadata.get("turnaround_index")
        return int(i) if i is not None else int(np.argmax(self.depth))

    def select(self, index) -> "ForceDepthCurve":
        """The samples ``index`` (a slice, mask or index array) of every array, same metadata."""
        meta = dict(self.metadata)
        meta.pop("turnaround_index", None)
        if meta.get("data_lines") is not None and len(meta["data_lines"]) == len(self):
            meta["data_lines"] = np.asarray(meta["data_lines"])[index]
        return ForceDepthCurve(
            self.depth[index],
            self.force[index],
            None if self.time is None else self.time[index],
            channels=_slice_arrays(self.channels, index),
            metadata=meta,
        )

    def approach(self) -> "ForceDepthCurve":
        """The approach (loading) segment: samples ``0 .. turnaround_index``."""
        seg = self.select(slice(0, self.turnaround_index + 1))
        seg.metadata["segment"] = "approach"
        return seg

    def check_monotonic(self, tolerance: float = 0.0) -> "ForceDepthCurve":
        """Raise :class:`~difftissue.errors.NonMonotonicError` unless depth never falls
        more than ``tolerance`` [m] below its running maximum in the approach segment."""
        seg = slice(0, self.turnaround_index + 1)
        check_monotonic(self.depth[seg], tolerance=tolerance, what="depth", unit="m", lines=self.metadata.get("data_lines"))
        return self


class CompressionCurve(eqx.Module):
    """An unconfined compression test of a cylindrical specimen.

    Attributes:
        strain: ``(n,)`` engineering (nominal) strain = displacement / height [-],
            **positive in compression**.
        stress: ``(n,)`` engineering (nominal) stress = force / initial area [Pa],
            **positive in compression**.
        force: ``(n,)`` platen force [N], positive compressive (``None`` when the file has
            only stresses and no diameter is known).
        displacement: ``(n,)`` platen displacement [m], positive in compression (``None``
            when the file has only strains and no height is known).
        time: ``(n,)`` [s] or ``None``.
        diameter, height: initial specimen diameter and height [m], when given.
        true_strain, true_stress: the file's true (logarithmic) strain [-] and true
            stress [Pa], positive in compression, when the file has them.
        metadata: ``source``, ``sha256``, ``format``, ``header`` (raw entries),
            ``instrument`` (SI), ``units``, ``signs``, ``checks`` (consistency results).
    """

    strain: np.ndarray = eqx.field(converter=_float_1d)
    stress: np.ndarray = eqx.field(converter=_float_1d)
    force: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    displacement: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    time: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    diameter: float | None = eqx.field(default=None, converter=_opt_float)
    height: float | None = eqx.field(default=None, converter=_opt_float)
    true_strain: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    true_stress: np.ndarray | None = eqx.field(default=None, converter=_opt_float_1d)
    metadata: dict = eqx.field(default_factory=dict)

    def __check_init__(self):
        n = self.strain.shape[0]
        for name in ("stress", "force", "displacement", "time", "true_strain", "true_stress"):
            v = getattr(self, name)
            if v is not None and v.shape[0] != n:
                raise DataError(f"strain has {n} samples but {name} has {v.shape[0]}")
        for name in ("diameter", "height"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise DataError(f"specimen {name} must be a positive length in m, got {v}")

    def __len__(self) -> int:
        return int(self.strain.shape[0])

    @property
    def area(self) -> float | None:
        """Initial cross-section ``pi d^2 / 4`` [m^2], or ``None`` without a diameter."""
        return None if self.diameter is None else math.pi * self.diameter**2 / 4.0

    def loading(self) -> "CompressionCurve":
        """The loading segment: samples up to the first maximum of the strain."""
        i = int(np.argmax(self.strain)) + 1
        arrays = {
            name: (None if getattr(self, name) is None else getattr(self, name)[:i])
            for name in ("strain", "stress", "force", "displacement", "time", "true_strain", "true_stress")
        }
        return CompressionCurve(**arrays, diameter=self.diameter, height=self.height, metadata={**self.metadata, "segment": "loading"})


# ============================================================================ checks
def check_monotonic(values, *, tolerance: float = 0.0, what: str = "depth", unit: str = "m", lines=None) -> None:
    """Raise :class:`~difftissue.errors.NonMonotonicError` where ``values`` fall more than
    ``tolerance`` below their running maximum (a loading segment must not go back)."""
    x = np.asarray(values, dtype=float)
    if x.size < 2:
        return
    drop = np.maximum.accumulate(x) - x
    bad = np.flatnonzero(drop > tolerance)
    if bad.size:
        where = f"data rows {_cite(bad)}"
        if lines is not None:
            where += f" (file lines {_cite(np.asarray(lines)[bad])})"
        raise NonMonotonicError(
            f"{what} decreases in the loading segment at {where}; the largest step back is "
            f"{drop.max():.3g} {unit} (tolerance {tolerance:.3g} {unit}). Raise the tolerance to the noise "
            f"level, or do not ask for monotonic loading",
            rows=bad,
            lines=() if lines is None else np.asarray(lines)[bad],
        )


def _force_depth_from_table(table: Table, *, monotonic: bool, tolerance: float, fmt: str) -> ForceDepthCurve:
    for q in ("depth", "force"):
        if q not in table:
            raise DataError(f"a force-depth curve needs a {q!r} column; declared: {sorted(table.columns)}")
    channels = {q: v for q, v in table.columns.items() if q not in ("depth", "force", "time")}
    meta = {**table.metadata, "format": fmt}
    curve = ForceDepthCurve(table["depth"], table["force"], table.columns.get("time"), channels=channels, metadata=meta)
    if monotonic:
        curve.check_monotonic(tolerance)
    return curve


def load_force_depth(config: Mapping, *, base_dir=None) -> ForceDepthCurve:
    """A :class:`ForceDepthCurve` from a CSV/TSV file with declared columns.

    ``config`` is that of :func:`load_table` with ``depth`` and ``force`` columns (optional
    ``time``; other quantities go to ``channels``), plus ``monotonic`` (bool, default
    False: require depth not to go back in the approach segment, i.e. up to its maximum)
    and ``monotonic_tolerance`` [m] (default 0).

    Example::

        load_force_depth({"path": "curve.tsv", "regime": "afm", "columns": {
            "depth": {"name": "Indentation (nm)", "unit": "nm"},
            "force": {"name": "Load (uN)", "unit": "uN", "sign": -1}}})
    """
    config = dict(config)
    monotonic = bool(config.pop("monotonic", False))
    tol = float(config.pop("monotonic_tolerance", 0.0))
    bad = set(config) & {"diameter", "height", "consistency", "rtol"}
    if bad:
        raise DataError(f"keys {sorted(bad)} belong to compression configs, not to force-depth curves")
    config.setdefault("regime", "macro")
    table = load_table(config, base_dir=base_dir)
    return _force_depth_from_table(table, monotonic=monotonic, tolerance=tol, fmt="table")


# ============================================================================ compression
def _consistency(message: str, mode: str) -> None:
    if mode == "raise":
        raise InconsistentDataError(message)
    if mode == "warn":
        warnings.warn(message, InconsistentDataWarning, stacklevel=4)


def _compare(file_values, computed, rtol: float):
    """Max |difference| relative to the computed peak, and the median ratio on the upper half."""
    computed = np.asarray(computed)
    peak = float(np.max(np.abs(computed))) if computed.size else 0.0
    dev = float(np.max(np.abs(file_values - computed))) / peak if peak > 0 else 0.0
    mask = np.abs(computed) > 0.5 * peak
    ratio = float(np.median(file_values[mask] / computed[mask])) if mask.any() else float("nan")
    return dev, ratio, dev <= rtol


def _compression_from_columns(
    cols: dict,
    *,
    diameter: float | None,
    height: float | None,
    consistency: str,
    rtol: float,
    monotonic: bool,
    tolerance: float,
    meta: dict,
    source_desc: dict,
) -> CompressionCurve:
    if consistency not in ("raise", "warn", "ignore"):
        raise DataError(f"consistency must be 'raise', 'warn' or 'ignore', got {consistency!r}")
    area = None if diameter is None else math.pi * diameter**2 / 4.0
    force = cols.get("force")
    disp = cols.get("displacement")
    strain = cols.get("strain")
    stress = cols.get("stress")
    checks = {}
    hd = source_desc.get("height", "the given height")
    dd = source_desc.get("diameter", "the given diameter")
    if strain is None:
        if disp is None or height is None:
            raise DataError("a compression curve needs a 'strain' column, or 'displacement' and the specimen 'height'")
        strain = disp / height
    elif disp is not None and height is not None:
        dev, ratio, ok = _compare(strain, disp / height, rtol)
        checks["strain_vs_displacement_over_height"] = {"max_deviation_rel_to_peak": dev, "median_ratio": ratio, "ok": ok}
        if not ok:
            _consistency(
                f"the engineering strain column disagrees with displacement / height ({hd} = {height * 1e3:.4g} mm): "
                f"max deviation {dev:.3g} of the peak strain (tolerance rtol = {rtol:g}); the column is {ratio:.4g} x the "
                f"computed strain, "
                + (f"which implies a height of {height / ratio * 1e3:.4g} mm" if ratio > 0 else "of the opposite sign: set the column's 'sign' to -1 or 'auto'"),
                consistency,
            )
    if stress is None:
        if force is None or area is None:
            raise DataError("a compression curve needs a 'stress' column, or 'force' and the specimen 'diameter'")
        stress = force / area
    elif force is not None and area is not None:
        dev, ratio, ok = _compare(stress, force / area, rtol)
        checks["stress_vs_force_over_area"] = {"max_deviation_rel_to_peak": dev, "median_ratio": ratio, "ok": ok}
        if not ok:
            _consistency(
                f"the engineering stress column disagrees with force / (pi d^2 / 4) ({dd} = {diameter * 1e3:.4g} mm): "
                f"max deviation {dev:.3g} of the peak stress (tolerance rtol = {rtol:g}); the column is {ratio:.4g} x the "
                f"computed stress, "
                + (f"which implies a diameter of {diameter / math.sqrt(ratio) * 1e3:.4g} mm" if ratio > 0 else "of the opposite sign: set the column's 'sign' to -1 or 'auto'"),
                consistency,
            )
    if force is None and area is not None:
        force = stress * area
    if disp is None and height is not None:
        disp = strain * height
    ts, tS = cols.get("true_strain"), cols.get("true_stress")
    if ts is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            expect = -np.log1p(-strain)
        dev, ratio, ok = _compare(ts, expect, rtol)
        checks["true_strain_vs_minus_log_1_minus_strain"] = {"max_deviation_rel_to_peak": dev, "ok": ok}
        if not ok and consistency != "ignore":
            warnings.warn(
                f"the true strain column is not -ln(1 - strain) (max deviation {dev:.3g} of its peak); it is kept as given",
                InconsistentDataWarning,
                stacklevel=3,
            )
    if tS is not None:
        dev, ratio, ok = _compare(tS, stress * (1.0 - strain), rtol)
        checks["true_stress_vs_stress_times_1_minus_strain"] = {"max_deviation_rel_to_peak": dev, "ok": ok}
        if not ok and consistency != "ignore":
            warnings.warn(
                f"the true stress column is not stress * (1 - strain) (the incompressible Cauchy stress; max deviation "
                f"{dev:.3g} of its peak); it is kept as given",
                InconsistentDataWarning,
                stacklevel=3,
            )
    meta = {**meta, "checks": {**meta.get("checks", {}), **checks}}
    curve = CompressionCurve(
        strain,
        stress,
        force,
        disp,
        cols.get("time"),
        diameter=diameter,
        height=height,
        true_strain=ts,
        true_stress=tS,
        metadata=meta,
    )
    if monotonic:
        i = int(np.argmax(curve.strain)) + 1
        check_monotonic(curve.strain[:i], tolerance=tolerance, what="strain", unit="", lines=meta.get("data_lines"))
    return curve


def load_compression(config: Mapping, *, base_dir=None) -> CompressionCurve:
    """A :class:`CompressionCurve` from a CSV/TSV file with declared columns.

    ``config`` is that of :func:`load_table` (default ``regime="compression"``) with some of
    the quantities ``force``, ``displacement``, ``strain``, ``stress``, ``true_strain``,
    ``true_stress``, ``time``, plus

    - ``diameter``, ``height``: the specimen's, e.g. ``"50 mm"`` or ``{"value": 50, "unit": "mm"}``;
    - ``consistency``: ``"raise"`` (default), ``"warn"`` or ``"ignore"`` when a strain or
      stress column disagrees with displacement / height or force / area by more than
      ``rtol`` (default 1e-3) of its peak;
    - ``monotonic`` (default False) and ``monotonic_tolerance`` (strain, default 0).
    """
    config = dict(config)
    diameter = config.pop("diameter", None)
    height = config.pop("height", None)
    consistency = config.pop("consistency", "raise")
    rtol = float(config.pop("rtol", 1e-3))
    monotonic = bool(config.pop("monotonic", False))
    tol = float(config.pop("monotonic_tolerance", 0.0))
    config.setdefault("regime", "compression")
    table = load_table(config, base_dir=base_dir)
    ranges = {**PLAUSIBLE_RANGES.get(config["regime"] or "", {}), **{k: tuple(v) for k, v in (config.get("plausible") or {}).items()}}
    config_dims = {"diameter": diameter, "height": height}
    d = None if diameter is None else parse_quantity(diameter, "length", what="diameter")
    h = None if height is None else parse_quantity(height, "length", what="height")
    for name, v in (("diameter", d), ("height", h)):
        if v is not None and name in ranges:
            _check_plausible(name, [v], ranges, regime=config["regime"], column=None, unit="m", si_unit="m", source=f"config value {config_dims[name]!r}")
    meta = {**table.metadata, "format": "table"}
    return _compression_from_columns(
        table.columns, diameter=d, height=h, consistency=consistency, rtol=rtol, monotonic=monotonic, tolerance=tol, meta=meta, source_desc={}
    )
