"""Test configuration: float64 everywhere (gradient checks need it), headless plots, and JAX's
persistent compilation cache, so that a second run of the suite (or a test file whose
subprocesses compile the same programs) loads compiled programs instead of compiling again.

The cache lives in ``$DIFFTISSUE_TEST_JAX_CACHE`` or ``~/.cache/difftissue-tests/jax``
(``$XDG_CACHE_HOME`` respected); ``DIFFTISSUE_TEST_JAX_CACHE=off`` disables it."""

import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def _cache_dir() -> Path | None:
    chosen = os.environ.get("DIFFTISSUE_TEST_JAX_CACHE", "")
    if chosen.lower() in ("off", "0", "none"):
        return None
    if chosen:
        return Path(chosen).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "difftissue-tests" / "jax"


_CACHE = _cache_dir()
if _CACHE is not None:
    try:
        _CACHE.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: run without the cache
        _CACHE = None
if _CACHE is not None:
    jax.config.update("jax_compilation_cache_dir", str(_CACHE))
    # Cache every program that took over half a second to compile, however small.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
