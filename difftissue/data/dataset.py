"""Any dataset from a config mapping (:func:`load_dataset`)."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

from ..errors import DataError
from .contact_point import shift_to_contact
from .curves import load_compression, load_force_depth
from .fem import load_fem_result
from .instruments import load_chiaro, load_instron_compression


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
      ``displacement_unit``, ``reorient``, ``displacement_table``).

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
        kw = take({"field", "length_unit", "displacement_unit", "reorient", "displacement_table"})
        if "displacement_table" in kw and base_dir is not None and not Path(kw["displacement_table"]).is_absolute():
            kw["displacement_table"] = Path(base_dir) / kw["displacement_table"]
        return load_fem_result(path, **kw)
    raise DataError(f"unknown dataset format {fmt!r}; choose 'table', 'instron', 'chiaro' or 'fem'")
