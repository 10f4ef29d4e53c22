"""Text files and tables: decoding any line ending and encoding, locating the header, parsing
declared columns into SI arrays (:func:`load_table`).
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import math
import re
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import DataError, EmptyDataError, HeaderError, MalformedDataError, MissingColumnError, NonFiniteDataError, UnitError, _cite
from .units import _accepted, _check_plausible, _MICRO, _SI_UNIT, _unit_in_name, normalize_unit, PLAUSIBLE_RANGES, QUANTITY_DIMENSIONS, unit_factor, UNITS


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
