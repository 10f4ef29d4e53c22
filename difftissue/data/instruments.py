"""Loaders for instrument exports: the Instron compression CSV of the Tissue Phantom Material
Database and the Optics11 Chiaro nano-indenter text export.
"""

from __future__ import annotations

import re
import warnings
from typing import Any, Mapping

import numpy as np

from ..errors import DataError, HeaderError, InconsistentDataWarning, MissingColumnError
from .curves import _compression_from_columns, CompressionCurve, ForceDepthCurve
from .table import _header_fields, _is_numeric_line, _norm_name, load_table, read_text
from .units import _check_plausible, _NUMBER, _unit_in_name, parse_quantity, PLAUSIBLE_RANGES, unit_factor


_INSTRON_COLUMNS = {
    "time": "time",
    "compression": "displacement",
    "extension": "displacement",
    "load": "force",
    "engineering strain": "strain",
    "engineering stress": "stress",
    "true strain": "true_strain",
    "true stress": "true_stress",
}


def _column_quantity(name: str, table: Mapping[str, str]) -> str | None:
    base = _norm_name(re.sub(r"[\(\[][^\(\)\[\]]*[\)\]]\s*$", "", name))
    return table.get(base)


def load_instron_compression(
    path,
    *,
    consistency: str = "raise",
    rtol: float = 1e-3,
    monotonic: bool = True,
    monotonic_tolerance: float = 0.0,
    encoding: str = "auto",
) -> CompressionCurve:
    """Read an Instron compression export (the Tissue Phantom Material Database layout).

    The file starts with a sample name, the test kind and ``Key: value;`` lines
    (``Cylinder Diameter: 50mm;``, ``Cylinder Height: 30mm;``, ``Speed (mm/min): 10;``,
    ``Machine: ...;``, ``Load cell: 1kN;``), then a comma-separated table whose column names
    carry their units (``Time (s)``, ``Compression (mm)``, ``Load (N)``, ``Engineering Strain
    [-]``, ``Engineering Stress (kPa)``, ``True Strain [-]``, ``True Stress (kPa)``).

    Every column is oriented so that compression is positive (``metadata["signs"]`` records
    the flips: in the bundled file compression and load are positive while the strain and
    stress columns are negative). The strain and stress columns are checked against
    compression / height and load / (pi d^2/4) with the header's dimensions, to ``rtol`` of
    their peak (``consistency``: ``"raise"``, ``"warn"``, ``"ignore"``). The true strain and
    stress are compared with ``-ln(1 - strain)`` and ``stress (1 - strain)`` (warning only),
    the crosshead speed with the header's, the peak load with the load cell's capacity.

    Raises:
        HeaderError: no diameter or height in the header, or no column row (truncated file).
        InconsistentDataError: strain or stress columns disagree with the header's dimensions.
        and the errors of :func:`load_table`.
    """
    text = read_text(path, encoding)
    lines = text.lines
    h = None
    for i, line in enumerate(lines[:-1]):
        if "," in line and not _is_numeric_line(line):
            nxt = next((x for x in lines[i + 1 :] if x.strip()), "")
            if _is_numeric_line(nxt):
                h = i
                break
    if h is None:
        raise HeaderError(
            f"{path}: no column row (Time, Compression, Load, ...) found in its {len(lines)} lines; "
            f"is the file truncated, or not an Instron export?"
        )
    header, name, kind = {}, None, None
    for line in lines[:h]:
        s = line.strip().rstrip(";").strip()
        if not s:
            continue
        if ":" in s:
            k, v = s.split(":", 1)
            header[k.strip()] = v.strip()
        elif name is None:
            name = s
        else:
            kind = s
    hkeys = {_norm_name(k): k for k in header}

    def entry(*names):
        for n in names:
            if n in hkeys:
                return hkeys[n], header[hkeys[n]]
        return None, None

    instrument: dict[str, Any] = {"sample": name, "test": kind}
    dims = {}
    for q, keys in (("diameter", ("cylinder diameter", "diameter")), ("height", ("cylinder height", "height"))):
        k, v = entry(*keys)
        if k is None:
            raise HeaderError(
                f"{path}: the header (lines 1-{h}) has no {q} entry ('Cylinder {q.capitalize()}: ...;'); "
                f"header entries: {sorted(header)}"
            )
        unit = _unit_in_name(k)
        dims[q] = parse_quantity(f"{v}{unit}" if unit and re.fullmatch(_NUMBER, v.strip()) else v, "length", what=f"header {k!r}")
        _check_plausible(q, [dims[q]], PLAUSIBLE_RANGES["compression"], regime="compression", column=None, unit="m", si_unit="m", source=f"header entry '{k}: {v}'")
    k, v = entry("speed (mm/min)", "speed")
    if k is not None:
        unit = _unit_in_name(k) or ""
        instrument["speed"] = parse_quantity(f"{v}{unit}" if unit and re.fullmatch(_NUMBER, v.strip()) else v, "speed", what=f"header {k!r}")
    k, v = entry("machine")
    if k is not None:
        instrument["machine"] = v
    k, v = entry("load cell")
    if k is not None:
        instrument["load_cell_capacity"] = parse_quantity(v, "force", what=f"header {k!r}")

    fields = _header_fields(lines[h], ",")
    columns = {}
    for f in fields:
        q = _column_quantity(f, _INSTRON_COLUMNS)
        if q is not None and q not in columns:
            columns[q] = {"name": f, "sign": "auto"}
    for q, label in (("displacement", "Compression (mm)"), ("force", "Load (N)")):
        if q not in columns:
            raise MissingColumnError(f"{path}: no {label.split(' (')[0]} column; the columns (line {h + 1}) are: {fields}", column=label, available=fields)
    table = load_table({"path": str(path), "columns": columns, "delimiter": ",", "header_line": h + 1, "regime": "compression", "encoding": text.encoding})
    meta = {
        **table.metadata,
        "format": "instron-csv",
        "header": header,
        "instrument": {**instrument, "diameter": dims["diameter"], "height": dims["height"]},
    }
    checks = {}
    t, x, F = table.columns.get("time"), table["displacement"], table["force"]
    if t is not None and "speed" in instrument and np.ptp(t) > 0:
        slope = float(np.polyfit(t, x, 1)[0])
        checks["speed_ratio"] = slope / instrument["speed"]
        if abs(checks["speed_ratio"] - 1.0) > 0.05:
            warnings.warn(
                f"{path}: the crosshead moves at {slope * 6e4:.4g} mm/min but the header says {instrument['speed'] * 6e4:.4g} mm/min",
                InconsistentDataWarning,
                stacklevel=2,
            )
    if "load_cell_capacity" in instrument:
        checks["peak_load_over_capacity"] = float(np.max(np.abs(F))) / instrument["load_cell_capacity"]
        if checks["peak_load_over_capacity"] > 1.0:
            warnings.warn(
                f"{path}: the peak load {np.max(np.abs(F)):.4g} N exceeds the load cell's capacity {instrument['load_cell_capacity']:.4g} N",
                InconsistentDataWarning,
                stacklevel=2,
            )
    meta["checks"] = checks
    return _compression_from_columns(
        table.columns,
        diameter=dims["diameter"],
        height=dims["height"],
        consistency=consistency,
        rtol=rtol,
        monotonic=monotonic,
        tolerance=monotonic_tolerance,
        meta=meta,
        source_desc={"height": "header height", "diameter": "header diameter"},
    )


# ============================================================================ Chiaro
# header key (normalized, without unit) -> (instrument key, dimension or None)
_CHIARO_HEADER = {
    "tip radius": ("tip_radius", "length"),
    "k": ("cantilever_stiffness", "stiffness"),
    "calibration factor": ("calibration_factor", None),
    "e[eff]": ("effective_modulus", "pressure"),
    "p[max]": ("peak_load", "force"),
    "max load": ("max_load_setpoint", "force"),
    "piezo speed": ("piezo_speed", "speed"),
    "x-position": ("x_position", "length"),
    "y-position": ("y_position", "length"),
    "z-position": ("z_position", "length"),
    "z surface": ("z_surface", "length"),
    "smduration": ("sm_duration", "time"),
    "slope": ("slope", "stiffness"),
}
_CHIARO_TEXT = {"device": "device", "software version": "software_version", "control mode": "control_mode", "measurement": "measurement", "model": "model", "date": "date", "time": "time", "status": "status"}
_CHIARO_COLUMNS = {"time": "time", "load": "force", "indentation": "indentation", "cantilever": "cantilever", "piezo": "piezo", "auxiliary": "auxiliary"}


def _parse_chiaro_header(lines) -> tuple[dict, str | None]:
    header, name = {}, None
    for line in lines:
        tokens = [t.strip() for t in line.split("\t")]
        while tokens and tokens[-1] == "":
            tokens.pop()
        if not tokens:
            continue
        if len(tokens) >= 2 and len(tokens) % 2 == 0:
            pairs = list(zip(tokens[::2], tokens[1::2]))
        elif len(tokens) >= 2:
            pairs = [(tokens[0], " ".join(tokens[1:]))]
        else:
            t = tokens[0]
            m = re.fullmatch(rf"(.*\S)\s+({_NUMBER})", t)
            if m and not t.endswith(":"):
                pairs = [(m.group(1), m.group(2))]
            elif ":" in t:
                k, v = t.split(":", 1)
                pairs = [(k, v.strip())]
            elif name is None:
                name = t
                continue
            else:
                pairs = [(t, "")]
        for k, v in pairs:
            header[k.strip().rstrip(":").strip()] = v
    return header, name


def load_chiaro(
    path,
    *,
    depth: str = "raw",
    encoding: str = "auto",
    check_consistency: bool = True,
) -> ForceDepthCurve:
    """Read an Optics11 Chiaro nano-indentation text export.

    Layout: a metadata header (``k (N/m)``, ``Tip radius (um)``, ``Calibration factor``,
    the instrument's Hertz fit ``E[eff] (Pa)`` and ``E[v=0.500] (Pa)``, profile settings,
    date, device, ...), a blank line, then a tab-separated table ``Time (s)``, ``Load (uN)``,
    ``Indentation (nm)``, ``Cantilever (nm)``, ``Piezo (nm)``, ``Auxiliary``. The software
    writes Latin-1 (``µ`` is byte 0xB5) with mixed CRLF / LF / CR line endings; both are
    handled (UTF-8 copies too). Units are taken from the column and header names.

    Args:
        depth: ``"raw"`` (default): depth = piezo - cantilever deflection [m], the sample
            surface position up to a constant, defined before contact too, for
            :func:`find_contact`; ``"instrument"``: the instrument's ``Indentation``
            column, zeroed at its own contact point and clamped to 0 before it.
        check_consistency: warn (:class:`~difftissue.errors.InconsistentDataWarning`)
            when the load is not ``k`` x cantilever deflection within 2 %, or when the
            instrument's indentation is not piezo - cantilever - constant.

    Returns:
        the whole curve (approach and retraction) with ``metadata["turnaround_index"]`` at
        the piezo's reversal; ``metadata["instrument"]`` holds SI values
        (``tip_radius`` [m], ``cantilever_stiffness`` [N/m], ``effective_modulus`` [Pa],
        ``youngs_modulus`` [Pa] with ``poisson_ratio_assumed``, ``contact_depth`` [m] and
        ``contact_index`` of the instrument's own contact point in the raw depth, ...);
        ``channels`` hold ``piezo``, ``cantilever``, ``instrument_indentation`` [m] and
        ``auxiliary`` (as written).

    Raises:
        HeaderError: the column row is missing (truncated file) or the header lacks the
            tip radius or the cantilever stiffness.
        and the errors of :func:`load_table` (regime ``"afm"``).
    """
    if depth not in ("raw", "instrument"):
        raise DataError(f"depth must be 'raw' or 'instrument', got {depth!r}")
    text = read_text(path, encoding)
    lines = text.lines
    h = None
    for i, line in enumerate(lines):
        fields = _header_fields(line, "\t")
        qs = {_column_quantity(f, _CHIARO_COLUMNS) for f in fields}
        if {"time", "force"} <= qs or ("force" in qs and ("indentation" in qs or "piezo" in qs)):
            h = i
            break
    if h is None:
        numeric = any(_is_numeric_line(line) for line in lines)
        raise HeaderError(
            f"{path}: no column row (Time (s), Load (uN), Indentation (nm), ...) in its {len(lines)} lines"
            + ("" if numeric else "; the file ends inside the metadata header (truncated?)")
        )
    header, name = _parse_chiaro_header(lines[:h])
    instrument: dict[str, Any] = {"name": name}
    for k, v in header.items():
        base = _norm_name(re.sub(r"[\(\[][^\(\)\[\]]*[\)\]]\s*$", "", k))
        if base in _CHIARO_HEADER:
            key, dim = _CHIARO_HEADER[base]
            try:
                x = float(v)
            except ValueError:
                continue
            unit = _unit_in_name(k)
            instrument[key] = x * (unit_factor(unit, dim, what=f"header {k!r}") if dim and unit else 1.0)
        elif base in _CHIARO_TEXT:
            instrument[_CHIARO_TEXT[base]] = v
        else:
            m = re.fullmatch(r"e\[v=(" + _NUMBER + r")\]", base)
            if m:
                try:
                    unit = _unit_in_name(k) or "Pa"
                    instrument["youngs_modulus"] = float(v) * unit_factor(unit, "pressure", what=f"header {k!r}")
                    instrument["poisson_ratio_assumed"] = float(m.group(1))
                except ValueError:
                    pass
    for key, label in (("tip_radius", "Tip radius (um)"), ("cantilever_stiffness", "k (N/m)")):
        if key not in instrument:
            raise HeaderError(
                f"{path}: the header (lines 1-{h}) has no {label!r} entry; it is needed to interpret the curve "
                f"(a truncated or edited header?). Header entries: {sorted(header)}"
            )
    fields = _header_fields(lines[h], "\t")
    columns = {}
    for f in fields:
        q = _column_quantity(f, _CHIARO_COLUMNS)
        if q is not None and q not in columns:
            spec = {"name": f}
            if q == "auxiliary":
                spec["unit"] = "-"
            columns[q] = spec
    need = ["force"] + (["piezo", "cantilever"] if depth == "raw" else ["indentation"])
    for q in need:
        if q not in columns:
            label = {"force": "Load (uN)", "piezo": "Piezo (nm)", "cantilever": "Cantilever (nm)", "indentation": "Indentation (nm)"}[q]
            raise MissingColumnError(
                f"{path}: no {label!r} column (needed for depth={depth!r}); the columns (line {h + 1}) are: {fields}", column=label, available=fields
            )
    table = load_table(
        {"path": str(path), "columns": columns, "delimiter": "\t", "header_line": h + 1, "regime": None, "encoding": text.encoding}
    )
    col = table.columns
    for q in ("piezo", "cantilever", "indentation"):
        if q in col:
            unit = table.metadata["units"][q]
            unit_factor(unit, "length", what=f"column {table.metadata['columns'][q]!r}")  # must be a length
            _check_plausible("depth", col[q], PLAUSIBLE_RANGES["afm"], regime="afm", column=table.metadata["columns"][q], unit=unit, si_unit="m")
    _check_plausible("force", col["force"], PLAUSIBLE_RANGES["afm"], regime="afm", column=table.metadata["columns"]["force"], unit=table.metadata["units"]["force"], si_unit="N")
    force = col["force"]
    channels = {}
    for q, name in (("piezo", "piezo"), ("cantilever", "cantilever"), ("indentation", "instrument_indentation"), ("auxiliary", "auxiliary")):
        if q in col:
            channels[name] = col[q]
    checks = {}
    if "piezo" in channels and "cantilever" in channels:
        raw_depth = channels["piezo"] - channels["cantilever"]
        turn = int(np.argmax(channels["piezo"]))
    else:
        raw_depth = None
        turn = int(np.argmax(col["indentation"]))
    if "cantilever" in channels:
        c = channels["cantilever"]
        cc = float(c @ c)
        if cc > 0:
            checks["load_over_k_deflection"] = float(c @ force) / cc / instrument["cantilever_stiffness"]
            if check_consistency and abs(checks["load_over_k_deflection"] - 1.0) > 0.02:
                warnings.warn(
                    f"{path}: the load is {checks['load_over_k_deflection']:.4g} x k * cantilever deflection "
                    f"(k = {instrument['cantilever_stiffness']:g} N/m from the header); expected 1",
                    InconsistentDataWarning,
                    stacklevel=2,
                )
    if raw_depth is not None and "instrument_indentation" in channels:
        ind = channels["instrument_indentation"]
        on = ind > 0
        if on.any():
            offs = raw_depth[on] - ind[on]
            instrument["contact_depth"] = float(np.median(offs))
            instrument["contact_index"] = int(np.argmax(on))
            checks["instrument_indentation_offset_spread"] = float(np.ptp(offs))
            if check_consistency and np.ptp(offs) > 1e-9:
                warnings.warn(
                    f"{path}: the instrument's indentation is not piezo - cantilever - constant (spread {np.ptp(offs):.3g} m)",
                    InconsistentDataWarning,
                    stacklevel=2,
                )
    d = raw_depth if depth == "raw" else col["indentation"]
    if depth == "raw":
        _check_plausible("depth", d, PLAUSIBLE_RANGES["afm"], regime="afm", column="Piezo - Cantilever", unit="m", si_unit="m")
    meta = {
        **table.metadata,
        "format": "chiaro-txt",
        "regime": "afm",
        "depth_definition": "piezo - cantilever (raw, arbitrary zero)" if depth == "raw" else "instrument indentation (zero at the instrument's contact, 0 before it)",
        "header": header,
        "instrument": instrument,
        "checks": checks,
        "turnaround_index": turn,
    }
    return ForceDepthCurve(d, force, col.get("time"), channels=channels, metadata=meta)
