"""Test configuration: float64 everywhere (gradient checks need it), headless plots, and JAX's
persistent compilation cache, so that a second run of the suite (or a test file whose
subprocesses compile the same programs) loads compiled programs instead of compiling again.

The cache lives in ``$DIFFTISSUE_TEST_JAX_CACHE`` or ``~/.cache/difftissue-tests/jax``
(``$XDG_CACHE_HOME`` respected); ``DIFFTISSUE_TEST_JAX_CACHE=off`` disables it. Every program is
written, however short its compilation, and so are the programs with host callbacks (every
``eqx.error_if``), which JAX itself never writes (tests/callback_cache.py; their cache is the
subdirectory ``with-host-callbacks``): a second run of the suite compiles almost nothing.

One OpenBLAS thread (``OPENBLAS_NUM_THREADS=1`` unless set): jaxlib's CPU LAPACK kernels (the
dense Cholesky of every small static solve) run in SciPy's OpenBLAS, whose worker threads
busy-wait; on the suite's shared cores one evaluation of a 125-node indentation protocol
cost 0.3-10 s CPU with them and 0.064 s without (docs/dev/performance-history.md, 2026-12-05).
It must be set before NumPy / SciPy load OpenBLAS, i.e. before ``import jax``."""

import faulthandler
import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import callback_cache  # noqa: E402
import jax  # noqa: E402
import pytest  # noqa: E402

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
# Programs with host callbacks (every eqx.error_if, pure_callback, jax.debug.callback) are cached
# too: tests/callback_cache.py, a backport of upstream JAX's support. Their entries go to a
# directory of their own, which a process without the backport never reads: it would load such
# a program without its callbacks (a crash).
if callback_cache.install() == "installed" and _CACHE is not None:
    _CACHE = _CACHE / "with-host-callbacks"
if _CACHE is not None:
    try:
        _CACHE.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: run without the cache
        _CACHE = None
if _CACHE is not None:
    jax.config.update("jax_compilation_cache_dir", str(_CACHE))
    # Cache every program, however short its compilation: a warm run reads the thousands of
    # small programs (op-by-op dispatch, helpers) instead of compiling them again.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_report_header(config):
    return f"JAX persistent compilation cache: {_CACHE or 'off'}; programs with host callbacks cached: {callback_cache.STATUS}"


# --- A crashed xdist worker must never hang or fail the run (docs/dev/test-suite.md) ---------
#
# A worker that dies (a SIGSEGV inside XLA-compiled code, seen once late in a full run) is
# replaced by xdist; with ``--dist loadfile`` the dead worker's files go back to the queue with
# the test it was running still pending, so the replacement runs that test again. xdist reports
# the crash as a failure all the same, and pytest-rerunfailures (``--reruns 2 --only-rerun
# crashed``) cannot turn it into a re-run because the file scheduler does not implement
# ``mark_test_pending``. The scheduler below does: the crashed test is already pending again,
# so marking it is a no-op that tells rerunfailures the re-run will happen. A test that crashes
# its worker three times still fails.

try:
    from xdist.scheduler import LoadFileScheduling
except ImportError:  # xdist not installed: one process, nothing to schedule
    LoadFileScheduling = None

if LoadFileScheduling is not None:

    class _LoadFileSchedulingRerunsCrashed(LoadFileScheduling):
        """``--dist loadfile`` whose crashed test is re-run by pytest-rerunfailures."""

        def _reschedule(self, node) -> None:
            super()._reschedule(node)
            # A worker runs a test only once it knows the next one (or is told to shut down), so a
            # node left with fewer than two pending tests never reports a completion, and the
            # scheduler reschedules only on completions. The replacement of a crashed worker gets
            # ONE work unit (xdist gives two only in the initial distribution); when that unit is
            # the crashed test alone, the run deadlocked at the end (reproduced with a synthetic
            # crash in the last test of a file). Give such a node more work, or shut it down.
            while not node.shutting_down and node in self.assigned_work and self._pending_of(self.assigned_work[node]) < 2:
                if not self.workqueue:
                    node.shutdown()
                    break
                self._assign_work_unit(node)

        def mark_test_pending(self, item: str) -> None:
            # remove_node() (called before this, when the worker went down) has put the whole
            # work unit of the crashed worker back into the queue, ``item`` included and not
            # completed, and re-scheduled it: nothing is left to do.
            return None


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    if LoadFileScheduling is not None and config.getvalue("dist") == "loadfile":
        return _LoadFileSchedulingRerunsCrashed(config, log)
    return None


# A watchdog on the xdist controller: should the run ever stop making progress (the one
# observed crash left the controller waiting on idle workers until CI's limit), dump every
# thread's stack and exit after DIFFTISSUE_TEST_SESSION_LIMIT seconds (default 75 minutes; the
# suite takes 15-40 minutes on 2 loaded cores), so that CI ends with a diagnosis instead of a
# silent time-out. ``0`` turns it off. Per-test hangs inside a worker are pytest-timeout's
# (``timeout`` in pyproject.toml).
_SESSION_LIMIT_S = float(os.environ.get("DIFFTISSUE_TEST_SESSION_LIMIT", 75 * 60))


def pytest_sessionstart(session):
    config = session.config
    is_worker = hasattr(config, "workerinput")
    distributed = bool(getattr(config.option, "numprocesses", None))
    if _SESSION_LIMIT_S > 0 and distributed and not is_worker:
        faulthandler.dump_traceback_later(_SESSION_LIMIT_S, exit=True)


def pytest_sessionfinish(session):
    faulthandler.cancel_dump_traceback_later()
