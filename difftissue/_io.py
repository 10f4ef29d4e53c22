"""Small file helpers: atomic writes that never overwrite what a user gave us by accident, and
strict-JSON conversion of records (:func:`jsonable`)."""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import sys
import tempfile
import tomllib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .errors import ConfigError, OutputError, OutputExistsError

__all__ = ["atomic_output", "sha256_file", "json_number", "jsonable", "read_toml"]


def read_toml(path, what: str = "config") -> dict:
    """The TOML file ``path`` as a dict.

    Raises:
        ConfigError: the file is missing (``"<what> file not found: ..."``), is not UTF-8 text
            or is not valid TOML (one line, naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{what} file not found: {path}")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(" ".join(f"{path}: invalid TOML: {e}".split())) from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


@contextlib.contextmanager
def atomic_output(path, *, overwrite: bool = False):
    """Yield a temporary path beside ``path``; on success move it onto ``path`` atomically.

    The temporary file keeps the suffix of ``path`` so writers that infer the format from
    the extension (meshio) still work. If the body raises, the temporary file is removed and
    ``path`` is untouched. An existing ``path`` is refused unless ``overwrite`` is true.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path} exists; refusing to overwrite it (choose another path or pass overwrite/--force)")
    if not path.parent.is_dir():
        raise OutputError(f"directory {path.parent} does not exist; create it first")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.tmp-", suffix="".join(path.suffixes) or None, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    # mkstemp creates the file 0600; give it the permissions a normal open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def sha256_file(path) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB chunks (provenance of data files)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def json_number(x):
    """JSON number or null (strict JSON has no inf/NaN)."""
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(obj):
    """``obj`` as strict-JSON data: mappings and sequences recursively, NumPy and JAX arrays as
    lists, non-finite floats as None, paths as strings, anything else as its ``str``."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return json_number(obj)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    jax = sys.modules.get("jax")  # a JAX array exists only once JAX is imported; no import here
    if isinstance(obj, np.ndarray) or (jax is not None and isinstance(obj, jax.Array)):
        return jsonable(np.asarray(obj).tolist())
    return str(obj)
