"""Helpers shared by the export modules: the unit statement, number and XML formatting, atomic
text output. Imports only the standard library and difftissue's I/O helpers."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

from .._io import atomic_output
from .._version import __version__
from ..errors import ExportError

__all__ = ["UNITS", "UNITS_LINE", "finite", "difftissue_version", "fmt", "xml_comment", "xml_text", "write_text"]

#: The unit statement every written file carries (cards: the ``units`` field; files: a comment).
UNITS = "m, N, Pa, s (density kg/m^3)"
UNITS_LINE = "units: " + UNITS


def finite(v, where: str) -> float:
    """``v`` as a finite float; :class:`~difftissue.errors.ExportError` naming ``where`` otherwise."""
    if isinstance(v, bool) or v is None:
        raise ExportError(f"{where} = {v!r} is not a number")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ExportError(f"{where} = {v!r} is not a number") from None
    if not math.isfinite(f):
        raise ExportError(f"{where} = {v!r} is not finite")
    return f


def difftissue_version() -> str:
    """The difftissue version written into cards and file headers."""
    return __version__


def fmt(x: float) -> str:
    """A number in an XML file: the shortest round-trip spelling (``repr``)."""
    return repr(float(x))


def xml_comment(text: str) -> ET.Element:
    """An XML comment holding ``text`` (``--`` and a trailing ``-`` are not allowed inside one)."""
    return ET.Comment(" " + text.replace("--", "- -").rstrip("-") + " ")


def xml_text(root: ET.Element) -> str:
    """``root`` as an indented XML document with its declaration, ending in a newline."""
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_text(path, text: str, force: bool) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; an existing file is refused unless ``force``."""
    with atomic_output(path, overwrite=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
