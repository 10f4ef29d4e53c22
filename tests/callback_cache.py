"""Programs with host callbacks in the test process's persistent compilation cache.

JAX (up to at least jax 0.10.2) never writes a program that holds a host callback to its
persistent compilation cache: ``eqx.error_if`` (every range check of a traced material),
``jax.pure_callback`` (``SeparatelyCompiled``, the sparse host solve) and ``jax.debug.callback``
all are host callbacks, so most of the suite's large programs were compiled again on every run,
warm cache or not (docs/dev/test-suite.md, stop 39). Upstream JAX lifted the restriction (pull
request 38405, "Make persistent compilation cache support host callbacks"): a CPU callback is
referred to in the program only by its index into the executable's list of callbacks (custom call
``xla_ffi_python_cpu_callback``, attribute ``index``), no function pointer is in the HLO or in
the serialized executable, so a cached executable works once it is loaded with the *current*
lowering's callbacks; jaxlib's ``Client.deserialize_executable`` takes them
(``host_callbacks=``).

:func:`install` does the same for the test process on the JAX versions that lack it: the cache
write no longer refuses such a program, and a cache read hands the callbacks of the lowering that
asked for the program to ``deserialize_executable``. The cache key is the hash of that lowering's
module (the callbacks' indices, operand and result types included), so a program read from the
cache runs the callbacks of the program that was traced now, in the order its module refers to
them. ``tests/test_callback_cache.py`` checks across processes that a program read from the cache
still raises its ``eqx.error_if`` and calls its callbacks.

This touches JAX internals (``jax._src.compiler``, ``jax._src.compilation_cache``): it is for the
test suite only, never imported by the library, and it installs itself only where those
functions have the signatures it was written against; anywhere else it leaves JAX as it is (the
suite is then slower, not different) and says why in :data:`STATUS`.
``DIFFTISSUE_TEST_CACHE_CALLBACKS=off`` turns it off.
"""

import inspect
import os
import threading

try:
    from jax._src import compilation_cache, compiler
except ImportError as _error:  # a JAX without these modules: nothing to install
    compilation_cache = compiler = None
    _IMPORT_ERROR = str(_error)

#: Why the backport is or is not installed (a test and the suite's header report it).
STATUS = "not installed"

_local = threading.local()


def _signature_is(function, names) -> bool:
    try:
        return list(inspect.signature(function).parameters)[: len(names)] == list(names)
    except (TypeError, ValueError):
        return False


class _BackendWithCallbacks:
    """The backend, whose ``deserialize_executable`` loads the executable with ``callbacks``."""

    def __init__(self, backend, callbacks):
        self._backend = backend
        self._callbacks = callbacks

    def deserialize_executable(self, serialized, executable_devices, compile_options=None):
        return self._backend.deserialize_executable(serialized, executable_devices, compile_options, host_callbacks=self._callbacks)

    def __getattr__(self, name):
        return getattr(self._backend, name)


def install() -> str:
    """Install the backport if this JAX needs it and matches it; returns :data:`STATUS`."""
    global STATUS
    if os.environ.get("DIFFTISSUE_TEST_CACHE_CALLBACKS", "").lower() in ("off", "0", "no"):
        STATUS = "off (DIFFTISSUE_TEST_CACHE_CALLBACKS)"
        return STATUS
    if compiler is None:
        STATUS = f"not installed: {_IMPORT_ERROR}"
        return STATUS
    write = getattr(compiler, "_cache_write", None)
    compile_or_get = getattr(compiler, "compile_or_get_cached", None)
    read = getattr(compilation_cache, "get_executable_and_time", None)
    if write is None or compile_or_get is None or read is None:
        STATUS = "not installed: this JAX has no _cache_write / compile_or_get_cached / get_executable_and_time"
        return STATUS
    if getattr(compile_or_get, "_difftissue_callbacks", False):
        return STATUS
    try:
        refuses = "because it uses host" in inspect.getsource(write)  # its log message
    except (OSError, TypeError):
        refuses = False
    if not refuses:
        STATUS = "not needed: this JAX's cache write does not refuse host callbacks"
        return STATUS
    if not (
        _signature_is(write, ("cache_key", "compile_time_secs", "module_name", "backend", "executable", "host_callbacks"))
        and _signature_is(compile_or_get, ("backend", "computation", "devices", "compile_options", "host_callbacks"))
        and _signature_is(read, ("cache_key", "compile_options", "backend", "executable_devices"))
    ):
        STATUS = "not installed: JAX's cache functions have other signatures than this backport expects"
        return STATUS

    def compile_or_get_cached(backend, computation, devices, compile_options, host_callbacks, *args, **kwargs):
        outer = getattr(_local, "callbacks", None)
        _local.callbacks = list(host_callbacks)
        try:
            return compile_or_get(backend, computation, devices, compile_options, host_callbacks, *args, **kwargs)
        finally:
            _local.callbacks = outer

    def cache_write(cache_key, compile_time_secs, module_name, backend, executable, host_callbacks):
        return write(cache_key, compile_time_secs, module_name, backend, executable, ())

    def get_executable_and_time(cache_key, compile_options, backend, executable_devices):
        callbacks = getattr(_local, "callbacks", None)
        if callbacks:
            backend = _BackendWithCallbacks(backend, callbacks)
        return read(cache_key, compile_options, backend, executable_devices)

    compile_or_get_cached._difftissue_callbacks = True
    compiler.compile_or_get_cached = compile_or_get_cached
    compiler._cache_write = cache_write
    compilation_cache.get_executable_and_time = get_executable_and_time
    STATUS = "installed"
    return STATUS
