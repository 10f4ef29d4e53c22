"""Loaders that turn measured-data files into typed datasets (no physics in here).

Datasets
    :class:`ForceDepthCurve` (indentation: depth [m], force [N]),
    :class:`CompressionCurve` (unconfined compression: strain [-], stress [Pa], force [N],
    displacement [m], specimen size [m]) and :class:`FEMResult` (a reference mesh with a
    ``displacement`` point field [m]).

Sign convention (every dataset, whatever the file does)
    depth, displacement and strain are **positive into the specimen** (compression
    positive); force and stress are **positive compressive** (the indenter or platen pushes
    on the specimen). Loaders flip the file's signs where needed and record the flips in
    ``metadata["signs"]``.

Units
    SI inside (m, N, Pa, s). Files declare their units (in the column names, or in a
    loader config); :data:`UNITS` lists those understood. After conversion every quantity
    is checked against a plausibility range (:data:`PLAUSIBLE_RANGES`), which catches most
    wrong units (nanometres declared as metres, newtons for an AFM curve, ...).

Loaders
    :func:`load_table` / :func:`load_force_depth` / :func:`load_compression` (generic
    CSV/TSV with declared columns), :func:`load_instron_compression` (the Instron export of
    the Tissue Phantom Material Database), :func:`load_chiaro` (Optics11 Chiaro
    nano-indenter text export), :func:`load_fem_result` (meshio), and
    :func:`load_dataset` (any of these from a config mapping).

Contact point
    :func:`find_contact` (default: a piecewise fit, linear baseline + power law with a free
    exponent, on the approach segment) and :func:`shift_to_contact` (approach segment,
    depth and force measured from the contact point).

See ``docs/data.md``.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import math
import re
import warnings
from pathlib import Path
from typing import Any, Mapping

import equinox as eqx
import numpy as np

from .errors import (
    ContactPointError,
    DataError,
    EmptyDataError,
    HeaderError,
    ImplausibleMagnitudeError,
    InconsistentDataError,
    InconsistentDataWarning,
    MalformedDataError,
    MissingColumnError,
    MissingFieldError,
    NonFiniteDataError,
    NonMonotonicError,
    UnitError,
    _cite,
)

__all__ = [
    "ForceDepthCurve",
    "CompressionCurve",
    "FEMResult",
    "Table",
    "ContactPoint",
    "UNITS",
    "QUANTITY_DIMENSIONS",
    "PLAUSIBLE_RANGES",
    "normalize_unit",
    "unit_factor",
    "parse_quantity",
    "read_text",
    "TextFile",
    "load_table",
    "load_force_depth",
    "load_compression",
    "load_instron_compression",
    "load_chiaro",
    "load_fem_result",
    "load_dataset",
    "find_contact",
    "shift_to_contact",
    "check_monotonic",
    "CONTACT_METHODS",
]

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


# ============================================================================ text
@dataclasses.dataclass(frozen=True)
class TextFile:
    """A decoded text file.

    Attributes:
        path: the file.
        lines: its lines, split at ``\\r\\n``, ``\\r`` and ``\\n`` alike (no terminators).
        encoding: the encoding used (``"utf-8"``, ``"utf-8-sig"``, ``"utf-16"``, ``"latin-1"``).
        line_endings: counts ``{"CRLF": n, "LF": n, "CR": n}``.
        sha256: hex digest of the file's bytes.
    """

    path: Path
    lines: tuple[str, ...]
    encoding: str
    line_endings: dict
    sha256: str


def read_text(path, encoding: str = "auto") -> TextFile:
    """Read and decode a text file, whatever its line endings.

    With ``encoding="auto"``: a byte-order mark selects UTF-8 or UTF-16; otherwise the file
    is decoded as UTF-8 when it is valid UTF-8, else as Latin-1 (ISO-8859-1, which decodes
    any byte; instrument software on Windows often writes it, e.g. ``µ`` as byte 0xB5).

    Raises:
        DataError: no such file, or it cannot be decoded with an explicit ``encoding``.
        EmptyDataError: the file is empty or holds only white space.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"no such file: {path}")
    raw = path.read_bytes()
    if encoding == "auto":
        if raw.startswith(b"\xef\xbb\xbf"):
            encoding = "utf-8-sig"
        elif raw.startswith((b"\xff\xfe", b"\xfe\xff")):
            encoding = "utf-16"
        else:
            try:
                raw.decode("utf-8")
                encoding = "utf-8"
            except UnicodeDecodeError:
                encoding = "latin-1"
    try:
        text = raw.decode(encoding)
    except (UnicodeDecodeError, LookupError) as e:
        raise DataError(f"cannot decode {path} as {encoding}: {e}; try encoding='auto' or 'latin-1'") from None
    if not text.strip():
        raise EmptyDataError(f"{path} is empty")
    crlf = text.count("\r\n")
    endings = {"CRLF": crlf, "LF": text.count("\n") - crlf, "CR": text.count("\r") - crlf}
    lines = re.split(r"\r\n|\r|\n", text)
    if lines and lines[-1] == "":
        lines.pop()
    return TextFile(path, tuple(lines), encoding, endings, hashlib.sha256(raw).hexdigest())


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


class FEMResult(eqx.Module):
    """A reference FEM solution: the undeformed mesh and its nodal displacements.

    Attributes:
        mesh: the reference configuration (:class:`~difftissue.mesh.TetMesh`), in m.
        displacement: ``(N, 3)`` nodal displacement [m].
        metadata: ``source``, ``sha256``, ``field`` (the point-data name read),
            ``length_unit``, ``displacement_unit``, ``max_displacement`` [m].
    """

    mesh: Any
    displacement: np.ndarray
    metadata: dict = eqx.field(default_factory=dict)

    @property
    def deformed_points(self) -> np.ndarray:
        """``mesh.points + displacement`` [m]."""
        return np.asarray(self.mesh.points) + self.displacement


@dataclasses.dataclass(frozen=True, eq=False)
class Table:
    """Columns read from a CSV/TSV file by :func:`load_table`.

    Attributes:
        columns: quantity name -> ``(n,)`` float64 array in SI, signs applied.
        metadata: ``source``, ``sha256``, ``encoding``, ``line_endings``, ``delimiter``,
            ``header_line`` (1-based), ``preamble`` (the lines above the column names),
            ``columns`` (quantity -> column name), ``units`` (as written), ``signs``,
            ``data_lines`` (1-based file line of each row).
    """

    columns: dict
    metadata: dict

    def __getitem__(self, quantity: str) -> np.ndarray:
        return self.columns[quantity]

    def __contains__(self, quantity: str) -> bool:
        return quantity in self.columns

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0


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


# ============================================================================ tables
_NAN_TOKENS = {"", "na", "n/a", "nan", "-nan", "+nan", "null", "none"}


def _norm_name(s: str) -> str:
    return re.sub(r"\s+", " ", s.strip().strip('"').strip("'").translate(_MICRO)).casefold()


def _split(line: str, delimiter) -> list[str]:
    if delimiter is None:
        return line.split()
    if delimiter == "\t":
        return [f.strip().strip('"') for f in line.split("\t")]
    return [f.strip() for f in next(csv.reader([line], delimiter=delimiter, skipinitialspace=True), [])]


def _header_fields(line: str, delimiter) -> list[str]:
    fields = _split(line, delimiter)
    while fields and fields[-1] == "":
        fields.pop()
    return fields


_DELIMITERS = ("\t", ",", ";", None)
_DELIMITER_NAMES = {"\t": "tab", ",": "comma", ";": "semicolon", None: "white space"}


def _parse_float(tok: str, decimal: str) -> float:
    if decimal != ".":
        tok = tok.replace(decimal, ".")
    return float(tok)


def _is_numeric_line(line: str) -> bool:
    fields = [f for f in re.split(r"[\t,; ]+", line.strip()) if f]
    if not fields:
        return False
    try:
        for f in fields:
            float(f)
    except ValueError:
        return False
    return True


_COLUMN_KEYS = {"name", "index", "unit", "sign", "override_header_unit"}
_TABLE_KEYS = {"path", "format", "kind", "delimiter", "encoding", "decimal", "header_line", "columns", "regime", "plausible"}


def _column_specs(columns) -> dict[str, dict]:
    if not isinstance(columns, Mapping) or not columns:
        raise DataError("'columns' must map quantities to column specs, e.g. {'depth': {'name': 'Indentation (nm)', 'unit': 'nm'}}")
    specs = {}
    for q, spec in columns.items():
        if isinstance(spec, str):
            spec = {"name": spec}
        elif isinstance(spec, int) and not isinstance(spec, bool):
            spec = {"index": spec}
        elif not isinstance(spec, Mapping):
            raise DataError(f"column spec of {q!r} must be a name, an index or a mapping, got {spec!r}")
        unknown = set(spec) - _COLUMN_KEYS
        if unknown:
            raise DataError(f"column spec of {q!r} has unknown keys {sorted(unknown)}; allowed: {sorted(_COLUMN_KEYS)}")
        if ("name" in spec) == ("index" in spec):
            raise DataError(f"column spec of {q!r} needs exactly one of 'name' or 'index'")
        sign = spec.get("sign", 1)
        if sign not in (1, -1, "auto"):
            raise DataError(f"sign of {q!r} must be 1, -1 or 'auto', got {sign!r}")
        specs[str(q)] = dict(spec)
    return specs


def _locate_header(text: TextFile, names: list[str], delimiter, header_line):
    """Find the column-name row: ``(line index, delimiter, fields)``."""
    lines = text.lines
    wanted = [_norm_name(n) for n in names]
    candidates = [delimiter] if delimiter != "auto" else list(_DELIMITERS)
    if header_line is not None:
        i = int(header_line) - 1
        if not 0 <= i < len(lines):
            raise HeaderError(f"header_line {header_line} is outside {text.path} ({len(lines)} lines)")
        best = None
        for d in candidates:
            fields = _header_fields(lines[i], d)
            score = sum(w in {_norm_name(f) for f in fields} for w in wanted)
            if best is None or score > best[0] or (score == best[0] and len(fields) > len(best[2])):
                best = (score, d, fields)
        return i, best[1], best[2]
    for i, line in enumerate(lines):
        low = _norm_name(line)
        if not all(w in low for w in wanted):
            continue
        for d in candidates:
            fields = _header_fields(line, d)
            if set(wanted) <= {_norm_name(f) for f in fields}:
                return i, d, fields
    # Not found: name the most likely header row in the error.
    best_i, best_score = None, 0
    for i, line in enumerate(lines[:2000]):
        for d in candidates:
            fields = {_norm_name(f) for f in _header_fields(line, d)}
            score = sum(w in fields for w in wanted)
            if score > best_score:
                best_i, best_score = i, score
    if best_i is None:
        first_numeric = next((i for i, line in enumerate(lines) if _is_numeric_line(line)), None)
        if first_numeric is None:
            raise EmptyDataError(
                f"{text.path} holds no column names {names} and no numeric rows (a truncated file, or only a header?)"
            )
        best_i = next((i for i in range(first_numeric - 1, -1, -1) if lines[i].strip()), None)
        if best_i is None:
            raise MissingColumnError(
                f"{text.path} has no header row (its data start at line {first_numeric + 1}); "
                f"declare columns by 'index' instead of 'name'",
                column=names[0],
            )
    d = next((c for c in candidates if c is not None and len(_header_fields(lines[best_i], c)) > 1), None if None in candidates else candidates[0])
    fields = _header_fields(lines[best_i], d)
    have = {_norm_name(f) for f in fields}
    missing = next(n for n, w in zip(names, wanted) if w not in have)
    raise MissingColumnError(
        f"column {missing!r} not found in {text.path}; the columns (line {best_i + 1}) are: {fields}",
        column=missing,
        available=fields,
    )


def _parse_rows(text: TextFile, start: int, delimiter, indices: dict[str, int], n_fields: int, decimal: str):
    """Parse the rows after line ``start - 1``; returns ``({quantity: values}, line numbers)``."""
    cols = {q: [] for q in indices}
    line_no = []
    need = max(list(indices.values()) + [n_fields - 1])
    if delimiter in ("\t", None):
        rows = ((i, _split(line, delimiter)) for i, line in enumerate(text.lines[start:], start) if line.strip())
    else:
        body = [(i, line) for i, line in enumerate(text.lines[start:], start) if line.strip()]
        reader = csv.reader((line for _, line in body), delimiter=delimiter, skipinitialspace=True)
        rows = ((i, [f.strip() for f in fields]) for (i, _), fields in zip(body, reader))
    for i, fields in rows:
        if len(fields) <= need:
            raise MalformedDataError(
                f"line {i + 1} of {text.path} has {len(fields)} field(s) but the header has {n_fields} "
                f"({_DELIMITER_NAMES.get(delimiter, repr(delimiter))}-separated): a truncated or shifted row? "
                f"Line: {text.lines[i][:80]!r}",
                rows=[len(line_no)],
                lines=[i + 1],
            )
        for q, j in indices.items():
            tok = fields[j]
            try:
                v = _parse_float(tok, decimal)
            except ValueError:
                if tok.strip().casefold() in _NAN_TOKENS:
                    v = math.nan
                else:
                    hint = " (decimal commas? pass decimal=',')" if decimal == "." and re.fullmatch(r"[-+]?\d+,\d+", tok) else ""
                    raise MalformedDataError(
                        f"cannot read a number from {tok!r} (column {j + 1}) on line {i + 1} of {text.path}{hint}",
                        rows=[len(line_no)],
                        lines=[i + 1],
                    ) from None
            cols[q].append(v)
        line_no.append(i + 1)
    return {q: np.asarray(v, dtype=float) for q, v in cols.items()}, np.asarray(line_no, dtype=int)


def _check_finite(cols: dict, names: dict, lines: np.ndarray, path) -> None:
    parts, all_rows = [], set()
    for q, v in cols.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            parts.append(f"column {names[q]!r} at data rows {_cite(bad)} (file lines {_cite(lines[bad])})")
            all_rows.update(bad.tolist())
    if parts:
        rows = sorted(all_rows)
        raise NonFiniteDataError(
            f"NaN, infinite or empty values in {path}: " + "; ".join(parts),
            rows=rows,
            lines=lines[rows],
        )


def load_table(config: Mapping, *, base_dir=None) -> Table:
    """Read declared columns of a CSV/TSV file into SI arrays.

    ``config`` keys (unknown keys are refused):

    - ``path`` (required): the file; relative paths are taken from ``base_dir``.
    - ``columns`` (required): quantity -> spec, a spec being a column name, a 0-based
      index, or a mapping ``{"name" | "index", "unit", "sign", "override_header_unit"}``.
      ``unit`` defaults to the unit written in the column name (``"Load (uN)"`` -> uN); a
      declared unit that contradicts the name raises :class:`UnitError` unless
      ``override_header_unit`` is true. ``sign`` is 1, -1 or ``"auto"`` (flip so that the
      value of largest magnitude is positive).
    - ``delimiter``: ``","``, ``"\\t"``, ``";"``, ``None`` (white space) or ``"auto"``
      (default: whichever splits the header row into the declared names).
    - ``encoding``: ``"auto"`` (default; see :func:`read_text`), ``"utf-8"``, ``"latin-1"``, ...
    - ``decimal``: ``"."`` (default) or ``","``.
    - ``header_line``: 1-based line number of the column-name row; default: the first line
      that holds every declared name. ``False`` for files without names (columns by index).
    - ``regime``: plausibility ranges to apply, a key of :data:`PLAUSIBLE_RANGES`
      (default ``"macro"``), or ``None`` for no check; ``plausible``: ``{quantity: (lo, hi)}``
      overrides [SI].

    Raises:
        DataError and its subclasses: see ``docs/data.md`` (missing columns, non-finite
        values, malformed rows, unknown or implausible units, empty files).
    """
    config = dict(config)
    unknown = set(config) - _TABLE_KEYS
    if unknown:
        raise DataError(f"unknown table config keys {sorted(unknown)}; allowed: {sorted(_TABLE_KEYS)}")
    if "path" not in config:
        raise DataError("table config needs a 'path'")
    path = Path(config["path"])
    if base_dir is not None and not path.is_absolute():
        path = Path(base_dir) / path
    specs = _column_specs(config.get("columns"))
    delimiter = config.get("delimiter", "auto")
    if delimiter not in (*_DELIMITERS, "auto"):
        raise DataError(f"delimiter must be one of ',', '\\t', ';', None (white space) or 'auto', got {delimiter!r}")
    decimal = config.get("decimal", ".")
    regime = config.get("regime", "macro")
    if regime is not None and regime not in PLAUSIBLE_RANGES:
        raise DataError(f"unknown regime {regime!r}; choose one of {sorted(PLAUSIBLE_RANGES)} or None")
    ranges = dict(PLAUSIBLE_RANGES.get(regime, {})) if regime is not None else {}
    ranges.update({k: tuple(v) for k, v in (config.get("plausible") or {}).items()})

    text = read_text(path, config.get("encoding", "auto"))
    header_line = config.get("header_line")
    by_name = {q: s["name"] for q, s in specs.items() if "name" in s}
    if header_line is False:
        if by_name:
            raise DataError(f"header_line=False (no header row) needs columns by 'index', but {sorted(by_name)} are given by name")
        first = next((i for i, line in enumerate(text.lines) if _is_numeric_line(line)), None)
        if first is None:
            raise EmptyDataError(f"{path} holds no numeric rows")
        d = delimiter if delimiter != "auto" else max(_DELIMITERS, key=lambda d: len(_split(text.lines[first], d)))
        h, fields = first - 1, [f"column {j}" for j in range(len(_split(text.lines[first], d)))]
    else:
        if not by_name and header_line is None:
            raise DataError("columns given by index need header_line (the 1-based line of the column names) or header_line=False")
        h, d, fields = _locate_header(text, list(by_name.values()), delimiter, header_line)
    norm_fields = [_norm_name(f) for f in fields]
    indices, names, units, factors, signs = {}, {}, {}, {}, {}
    for q, s in specs.items():
        if "name" in s:
            try:
                j = fields.index(s["name"])
            except ValueError:
                try:
                    j = norm_fields.index(_norm_name(s["name"]))
                except ValueError:
                    raise MissingColumnError(
                        f"column {s['name']!r} not found in {path}; the columns (line {h + 1}) are: {fields}",
                        column=s["name"],
                        available=fields,
                    ) from None
        else:
            j = int(s["index"])
            if not 0 <= j < len(fields):
                raise MissingColumnError(
                    f"column index {j} for {q!r} is outside the {len(fields)} columns of {path}: {fields}", column=str(j), available=fields
                )
        indices[q] = j
        names[q] = fields[j]
        dim = QUANTITY_DIMENSIONS.get(q)
        in_name = _unit_in_name(fields[j]) if header_line is not False else None
        declared = s.get("unit")
        if declared is None:
            if in_name is None or (normalize_unit(in_name) not in UNITS and dim is not None):
                if dim == "strain" and in_name is None:
                    declared = "-"
                else:
                    raise UnitError(
                        f"column {fields[j]!r} ({q}): "
                        + ("no unit is declared and the name carries none" if in_name is None else f"unknown unit {in_name!r} in the column name")
                        + f"; declare 'unit' in its spec ({_accepted(dim)})"
                    )
            else:
                declared = in_name
        elif in_name is not None and normalize_unit(in_name) in UNITS and normalize_unit(in_name) != normalize_unit(declared):
            if not s.get("override_header_unit", False):
                raise UnitError(
                    f"column {fields[j]!r} ({q}) is declared in {declared!r} but its name says {in_name!r}; "
                    f"drop 'unit' to use the name's unit, or set override_header_unit=True if the name is wrong"
                )
        factors[q] = unit_factor(declared, dim, what=f"{q} (column {fields[j]!r})") if dim is not None or normalize_unit(declared) in UNITS else 1.0
        units[q] = declared
        signs[q] = s.get("sign", 1)

    raw, lines = _parse_rows(text, h + 1, d, indices, len(fields), decimal)
    if lines.size == 0:
        raise EmptyDataError(f"{path} has a header (line {h + 1}) but no data rows after it")
    _check_finite(raw, names, lines, path)
    columns = {}
    for q, v in raw.items():
        v = v * factors[q]
        if signs[q] == "auto":
            k = int(np.argmax(np.abs(v))) if v.size else 0
            signs[q] = -1 if v.size and v[k] < 0 else 1
        v = v * signs[q]
        if regime is not None or q in ranges:
            _check_plausible(q, v, ranges, regime=regime, column=names[q], unit=units[q], si_unit=_SI_UNIT.get(QUANTITY_DIMENSIONS.get(q), "SI"))
        columns[q] = v
    meta = {
        "source": str(path),
        "sha256": text.sha256,
        "encoding": text.encoding,
        "line_endings": text.line_endings,
        "delimiter": d,
        "header_line": h + 1 if header_line is not False else None,
        "preamble": list(text.lines[: max(h, 0)]),
        "columns": names,
        "units": units,
        "signs": signs,
        "regime": regime,
        "data_lines": lines,
    }
    return Table(columns, meta)


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


# ============================================================================ contact
#: Contact-point methods of :func:`find_contact`.
CONTACT_METHODS = ("power_law", "ratio_of_variances", "instrument")


@dataclasses.dataclass(frozen=True)
class ContactPoint:
    """A contact point found by :func:`find_contact`.

    Attributes:
        method: the method used.
        depth: contact position in the curve's depth coordinate [m].
        force: baseline force at contact [N] (the fitted baseline for ``power_law``, the
            median of the 50 samples before contact for the other methods).
        index: first sample (in the approach) whose depth stays beyond ``depth``.
        exponent: fitted exponent ``p`` of the contact part (``power_law``), else ``None``.
        baseline_slope: slope of the linear baseline [N/m] (``power_law``; else 0).
        amplitude: ``c`` of ``c (z - z0)^p`` [N/m^p] (``power_law``), else ``None``.
        rms: root-mean-square residual of the fit [N] (``power_law``), else ``None``.
        interval: ``(lo, hi)`` [m], the contact depths whose residual sum of squares is
            within ``4 s^2`` of the best (``s^2`` = residual variance; a rough 2-sigma
            profile interval that assumes white noise), or ``None``.
    """

    method: str
    depth: float
    force: float
    index: int
    exponent: float | None = None
    baseline_slope: float = 0.0
    amplitude: float | None = None
    rms: float | None = None
    interval: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _sse_grid(z, F, z0s, ps, sums):
    """Residual sum of squares of ``F ~ a + b z + c (z - z0)_+^p`` for every ``(z0, p)``.

    ``z, F`` are normalized samples; points with ``z <= min(z0s)`` are dropped by the caller
    from ``z, F`` (they only enter ``sums``: (n, Σz, Σz², ΣF, ΣzF, ΣF²) over all points).
    """
    n, Sz, Szz, SF, SzF, SFF = sums
    out = np.empty((len(z0s), len(ps)))
    U0 = np.clip(z[None, :] - z0s[:, None], 0.0, None)
    for j, p in enumerate(ps):
        G = U0**p
        Sg = G.sum(1)
        Szg = G @ z
        Sgg = np.einsum("ij,ij->i", G, G)
        SgF = G @ F
        A = np.empty((len(z0s), 3, 3))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = n, Sz, Sg
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2] = Sz, Szz, Szg
        A[:, 2, 0], A[:, 2, 1], A[:, 2, 2] = Sg, Szg, Sgg
        b = np.stack([np.full(len(z0s), SF), np.full(len(z0s), SzF), SgF], axis=1)
        A[:, 2, 2] += 1e-12 * (1.0 + Sgg)  # ridge: a candidate with no point beyond it
        x = np.linalg.solve(A, b[..., None])[..., 0]
        out[:, j] = SFF - np.einsum("ij,ij->i", x, b)
    return out


def _power_law_contact(z, F, *, exponent, exponent_range):
    n = len(z)
    zm, zs = float(z.mean()), float(np.ptp(z))
    Fm, Fs = float(F.mean()), float(np.ptp(F))
    zc, Fc = (z - zm) / zs, (F - Fm) / Fs
    sums = (n, zc.sum(), zc @ zc, Fc.sum(), zc @ Fc, Fc @ Fc)
    # Search window: from the smallest depth to where the force has made half its rise.
    k = max(5, n // 20)
    f0 = float(np.median(Fc[:k]))
    half = np.flatnonzero(Fc >= f0 + 0.5 * (Fc.max() - f0))
    hi = zc[half[0]] if half.size else zc.max()
    lo = zc.min()
    if exponent is not None:
        pgrid = np.array([float(exponent)])
    else:
        pgrid = np.linspace(exponent_range[0], exponent_range[1], 9)

    # The coarse stage runs on at most ~2000 evenly strided samples (sums rescaled); the
    # refinements use every sample beyond the smallest candidate (the contact region).
    stride = max(1, n // 2000)
    zc_s, Fc_s = zc[::stride], Fc[::stride]
    m = len(zc_s)
    sums_s = (m, zc_s.sum(), zc_s @ zc_s, Fc_s.sum(), zc_s @ Fc_s, Fc_s @ Fc_s)

    def stage(z0s, ps, coarse=False):
        if coarse:
            sel = zc_s > z0s.min()
            return _sse_grid(zc_s[sel], Fc_s[sel], z0s, ps, sums_s)
        sel = zc > z0s.min()
        return _sse_grid(zc[sel], Fc[sel], z0s, ps, sums)

    z0s = np.linspace(lo, hi, 120)
    s = stage(z0s, pgrid, coarse=True)
    i, j = np.unravel_index(np.argmin(s), s.shape)
    z0, p = z0s[i], pgrid[j]
    step = coarse_step = z0s[1] - z0s[0]
    dp = (pgrid[1] - pgrid[0]) if pgrid.size > 1 else 0.0
    for _ in range(3):
        z0s = np.linspace(max(lo, z0 - 2 * step), min(hi, z0 + 2 * step), 41)
        ps = pgrid if exponent is not None else np.unique(np.clip(np.linspace(p - dp, p + dp, 9), *exponent_range))
        s = stage(z0s, ps)
        i, j = np.unravel_index(np.argmin(s), s.shape)
        z0, p = z0s[i], ps[j]
        step, dp = z0s[1] - z0s[0], dp / 4
    smin = float(s.min())
    # Residuals at the optimum; their lag-1 autocorrelation rho inflates the variance of
    # the sum of squares by (1 + rho) / (1 - rho) (AR(1) noise) for the interval below.
    g = np.clip(zc - z0, 0.0, None) ** p
    A = np.stack([np.ones(n), zc, g], axis=1)
    coef, *_ = np.linalg.lstsq(A, Fc, rcond=None)
    res = Fc - A @ coef
    rho = float(np.clip((res[1:] @ res[:-1]) / max(res @ res, 1e-300), 0.0, 0.99))
    var = smin / max(n - 4, 1) * (1.0 + rho) / (1.0 - rho)
    # Profile of the sum of squares over z0 (minimised over p) for the interval.
    span = 2 * coarse_step
    z0s = np.linspace(max(lo, z0 - span), min(hi, z0 + span), 161)
    ps = pgrid if exponent is not None else np.unique(np.clip(np.linspace(p - 0.5, p + 0.5, 21), *exponent_range))
    prof = stage(z0s, ps).min(axis=1)
    ok = z0s[prof <= smin + 4.0 * var]
    interval = (float(ok.min()) * zs + zm, float(ok.max()) * zs + zm) if ok.size else None
    rms = float(np.sqrt(np.mean((A @ coef - Fc) ** 2))) * Fs
    z0_si = float(z0) * zs + zm
    slope = float(coef[1]) * Fs / zs
    force0 = Fm + Fs * (float(coef[0]) + float(coef[1]) * float(z0))
    amplitude = float(coef[2] * Fs / zs**p)
    return z0_si, force0, float(p), slope, amplitude, rms, interval


def _ratio_of_variances(F, window):
    n = len(F)
    N = int(window) if window is not None else max(10, n // 50)
    if n < 2 * N + 2:
        raise ContactPointError(f"the approach has {n} samples, too few for a ratio-of-variances window of {N}")
    c1 = np.concatenate([[0.0], np.cumsum(F)])
    c2 = np.concatenate([[0.0], np.cumsum(F * F)])
    i = np.arange(N, n - N)
    mb = (c1[i] - c1[i - N]) / N
    vb = (c2[i] - c2[i - N]) / N - mb**2
    ma = (c1[i + 1 + N] - c1[i + 1]) / N
    va = (c2[i + 1 + N] - c2[i + 1]) / N - ma**2
    rov = va / np.maximum(vb, 1e-300)
    return int(i[np.argmax(rov)])


def find_contact(
    curve: ForceDepthCurve,
    *,
    method: str = "power_law",
    exponent: float | None = None,
    exponent_range: tuple[float, float] = (1.0, 3.0),
    window: int | None = None,
) -> ContactPoint:
    """Find the contact point of an indentation curve, on its approach segment.

    Methods:

    - ``"power_law"`` (default): least-squares fit of
      ``F(z) = a + b z + c (z - z0)_+^p`` (a linear baseline, to absorb offset and drift,
      plus a power law after contact) over the whole approach. For each ``(z0, p)`` the
      model is linear in ``(a, b, c)``, so the fit is an exact grid search on ``z0`` and
      ``p`` (coarse, then refined twice), no starting guess, no local minima. ``p`` is
      free in ``exponent_range`` (a sphere gives 1.5, a cone 2, a flat punch 1) unless
      ``exponent`` fixes it. It uses every sample, so it is robust to noise, and locates
      the contact where the force starts to rise *in the shape* of the loading curve.
    - ``"ratio_of_variances"`` (Gavara 2016, Sci. Rep. 6:21267): the sample that maximises
      var(next ``window`` forces) / var(previous ``window`` forces). No model, but
      sensitive to the window and to correlated noise; given for comparison.
    - ``"instrument"``: the instrument's own contact (``metadata["instrument"]
      ["contact_depth"]``, from :func:`load_chiaro` with ``depth="raw"``).

    Raises:
        ContactPointError: too few samples, or no force rise above the baseline noise.
    """
    if method not in CONTACT_METHODS:
        raise ContactPointError(f"unknown contact method {method!r}; choose one of {CONTACT_METHODS}")
    seg = curve.approach()
    z, F = seg.depth, seg.force
    n = len(z)
    if n < 20:
        raise ContactPointError(f"the approach segment has {n} samples; at least 20 are needed to find a contact point")
    if method == "instrument":
        inst = curve.metadata.get("instrument", {})
        if "contact_depth" not in inst:
            raise ContactPointError("the curve has no instrument contact point (metadata['instrument']['contact_depth'])")
        z0 = float(inst["contact_depth"])
        idx = _first_beyond(z, z0)
        return ContactPoint("instrument", z0, _force_before(F, idx), idx)
    k = max(5, n // 10)
    noise = 1.4826 * float(np.median(np.abs(np.diff(F[: max(k, 10)]) - np.median(np.diff(F[: max(k, 10)]))))) / math.sqrt(2)
    rise = float(np.max(F[-k:])) - float(np.median(F[:k]))
    if not rise > 10 * noise or np.ptp(z) <= 0:
        raise ContactPointError(
            f"the force rises by {rise:.3g} N over the approach, not clearly above the baseline noise ({noise:.3g} N): "
            f"the curve may not reach contact"
        )
    if method == "ratio_of_variances":
        i = _ratio_of_variances(F, window)
        return ContactPoint("ratio_of_variances", float(z[i]), _force_before(F, i + 1), _first_beyond(z, float(z[i])))
    lo, hi = exponent_range
    if not 0 < lo < hi:
        raise ContactPointError(f"exponent_range must be 0 < lo < hi, got {exponent_range}")
    z0, f0, p, slope, amp, rms, interval = _power_law_contact(z, F, exponent=exponent, exponent_range=(float(lo), float(hi)))
    return ContactPoint("power_law", z0, f0, _first_beyond(z, z0), p, slope, amp, rms, interval)


def _force_before(F, idx: int, n: int = 50) -> float:
    """Median force of the (up to) ``n`` samples before ``idx``: the baseline at contact."""
    seg = np.asarray(F)[max(idx - n, 0) : max(idx, 1)]
    return float(np.median(seg))


def _first_beyond(z, z0) -> int:
    """First index after which ``z`` stays above ``z0``."""
    below = np.flatnonzero(np.asarray(z) <= z0)
    return int(below[-1]) + 1 if below.size else 0


def shift_to_contact(
    curve: ForceDepthCurve,
    contact: ContactPoint | None = None,
    *,
    method: str = "power_law",
    exponent: float | None = None,
    baseline: str = "tilt",
    keep_precontact: bool = False,
    monotonic: bool = False,
    monotonic_tolerance: float = 0.0,
) -> ForceDepthCurve:
    """The approach segment measured from the contact point.

    ``depth - contact.depth`` and ``force - baseline(depth)``, where the baseline is the
    fitted line (``baseline="tilt"``, default: removes offset and drift), the force at
    contact only (``"offset"``), or nothing (``"none"``). Samples before
    ``contact.index`` are dropped unless ``keep_precontact``. ``contact`` defaults to
    :func:`find_contact` with ``method`` and ``exponent``. With ``monotonic``, the result
    must not step back by more than ``monotonic_tolerance`` [m]
    (:class:`~difftissue.errors.NonMonotonicError`).
    """
    if baseline not in ("tilt", "offset", "none"):
        raise DataError(f"baseline must be 'tilt', 'offset' or 'none', got {baseline!r}")
    if contact is None:
        contact = find_contact(curve, method=method, exponent=exponent)
    seg = curve.approach()
    depth = seg.depth - contact.depth
    if baseline == "tilt":
        force = seg.force - (contact.force + contact.baseline_slope * depth)
    elif baseline == "offset":
        force = seg.force - contact.force
    else:
        force = seg.force
    start = 0 if keep_precontact else contact.index
    lines = seg.metadata.get("data_lines")
    meta = {
        **seg.metadata,
        "contact": contact.to_dict(),
        "baseline": baseline,
        "segment": "approach from contact" if not keep_precontact else "approach",
    }
    if lines is not None:
        meta["data_lines"] = np.asarray(lines)[: len(seg)][start:]
    out = ForceDepthCurve(
        depth[start:],
        force[start:],
        None if seg.time is None else seg.time[start:],
        channels=_slice_arrays(seg.channels, slice(start, None)),
        metadata=meta,
    )
    if monotonic:
        check_monotonic(out.depth, tolerance=monotonic_tolerance, what="depth", unit="m", lines=meta.get("data_lines"))
    return out


# ============================================================================ FEM
def load_fem_result(
    path,
    *,
    field: str = "displacement",
    length_unit: str = "m",
    displacement_unit: str | None = None,
    reorient: bool = False,
) -> FEMResult:
    """A reference FEM result: a tet mesh (any meshio format) with a nodal displacement field.

    Args:
        field: the point-data name of the displacement.
        length_unit: unit of the coordinates in the file (converted to m).
        displacement_unit: unit of the displacement (default: ``length_unit``).
        reorient: passed to :func:`~difftissue.mesh.read_mesh`.

    Raises:
        MissingFieldError: no such point field (the message lists those present) or it is
            not ``(N, 3)``.
        NonFiniteDataError: NaN or infinite displacements (``rows`` are node indices).
        ImplausibleMagnitudeError: displacements larger than 10 x the mesh's size (a unit
            mismatch between coordinates and displacements).
        MeshError: the file cannot be read as a valid tet mesh.
    """
    from .mesh import LENGTH_UNITS, read_mesh

    du = displacement_unit or length_unit
    if normalize_unit(du) not in LENGTH_UNITS and du not in LENGTH_UNITS:
        raise UnitError(f"unknown displacement unit {du!r}; choose one of {sorted(LENGTH_UNITS)}")
    mesh = read_mesh(path, length_unit=length_unit, reorient=reorient)
    if field not in mesh.point_data:
        raise MissingFieldError(f"{path} has no point field {field!r}; its point fields are: {sorted(mesh.point_data) or 'none'}")
    u = np.asarray(mesh.point_data[field], dtype=float)
    if u.ndim != 2 or u.shape != (mesh.n_nodes, 3):
        raise MissingFieldError(f"point field {field!r} of {path} has shape {u.shape}; a displacement needs ({mesh.n_nodes}, 3)")
    bad = np.flatnonzero(~np.isfinite(u).all(axis=1))
    if bad.size:
        raise NonFiniteDataError(f"point field {field!r} of {path} has NaN or infinite values at nodes {_cite(bad)}", rows=bad)
    u = u * LENGTH_UNITS.get(du, LENGTH_UNITS.get(normalize_unit(du), 1.0))
    lo, hi = mesh.bounds()
    size = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    umax = float(np.linalg.norm(u, axis=1).max()) if len(u) else 0.0
    if size > 0 and umax > 10 * size:
        raise ImplausibleMagnitudeError(
            f"the largest displacement in {path} is {umax:.4g} m, more than 10 x the mesh's diagonal ({size:.4g} m); "
            f"are the displacements in another unit than the coordinates? (displacement_unit={du!r})"
        )
    meta = {
        "source": str(path),
        "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
        "format": "meshio",
        "field": field,
        "length_unit": length_unit,
        "displacement_unit": du,
        "max_displacement": umax,
    }
    return FEMResult(mesh, u, meta)


# ============================================================================ dispatch
def load_dataset(config: Mapping, *, base_dir=None):
    """Load any dataset from a config mapping (e.g. a table of a TOML file).

    ``config["format"]``:

    - ``"table"`` (default) with ``kind`` = ``"force_depth"`` or ``"compression"``: see
      :func:`load_force_depth` / :func:`load_compression`;
    - ``"instron"``: :func:`load_instron_compression` (keys ``path``, ``consistency``,
      ``rtol``, ``monotonic``, ``monotonic_tolerance``, ``encoding``);
    - ``"chiaro"``: :func:`load_chiaro` (keys ``path``, ``depth``, ``encoding``), then, with
      ``contact = true`` or a method name, :func:`shift_to_contact` (keys ``exponent``,
      ``baseline``, ``keep_precontact``, ``monotonic``, ``monotonic_tolerance``);
    - ``"fem"``: :func:`load_fem_result` (keys ``path``, ``field``, ``length_unit``,
      ``displacement_unit``, ``reorient``).

    Relative paths are taken from ``base_dir``.
    """
    config = dict(config)
    fmt = config.pop("format", "table")
    if "path" not in config:
        raise DataError(f"a {fmt!r} dataset config needs a 'path'")
    path = Path(config.pop("path"))
    if base_dir is not None and not path.is_absolute():
        path = Path(base_dir) / path

    def take(allowed):
        unknown = set(config) - set(allowed)
        if unknown:
            raise DataError(f"unknown keys {sorted(unknown)} for format {fmt!r}; allowed: {sorted(allowed) + ['format', 'path']}")
        return dict(config)

    if fmt == "table":
        kind = config.pop("kind", "force_depth")
        cfg = {**config, "path": str(path)}
        if kind == "force_depth":
            return load_force_depth(cfg)
        if kind == "compression":
            return load_compression(cfg)
        raise DataError(f"unknown table kind {kind!r}; choose 'force_depth' or 'compression'")
    if fmt == "instron":
        return load_instron_compression(path, **take({"consistency", "rtol", "monotonic", "monotonic_tolerance", "encoding"}))
    if fmt == "chiaro":
        kw = take({"depth", "encoding", "check_consistency", "contact", "exponent", "baseline", "keep_precontact", "monotonic", "monotonic_tolerance"})
        contact = kw.pop("contact", False)
        load_kw = {k: kw.pop(k) for k in ("depth", "encoding", "check_consistency") if k in kw}
        curve = load_chiaro(path, **load_kw)
        if not contact:
            if kw:
                raise DataError(f"keys {sorted(kw)} need contact = true")
            return curve
        method = "power_law" if contact is True else str(contact)
        return shift_to_contact(curve, method=method, **kw)
    if fmt == "fem":
        return load_fem_result(path, **take({"field", "length_unit", "displacement_unit", "reorient"}))
    raise DataError(f"unknown dataset format {fmt!r}; choose 'table', 'instron', 'chiaro' or 'fem'")
