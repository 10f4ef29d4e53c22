"""XLA CPU settings difftissue needs before JAX starts its CPU backend.

``--xla_cpu_enable_concurrency_optimized_scheduler=false``: with XLA's concurrency-optimised
scheduler (the default in jaxlib 0.10), a batched Levenberg--Marquardt step of simulated
compressions (``fit_batch`` of three 288-tet bonded ``Compression`` specimens) deadlocked in
3 of 3 runs on the 2-core CPU machine: every XLA worker thread waiting, no CPU time (gdb:
all threads in ``Eigen::ThreadPool::WaitForWork``); with the flag it finished in 4 of 4
(17-21 s). Single-start fits and ``jax.vmap`` of the forward model alone did not hang. Other
projects report the same kind of wedge on vmapped CPU graphs (PyAutoFit issues #1528, #1530,
where ``--xla_cpu_multi_thread_eigen=false`` was their workaround; it did not help here).

The flag only changes how XLA orders independent operations of one program; it is appended
to ``XLA_FLAGS`` at import unless the variable already names it (set it yourself to choose),
or ``DIFFTISSUE_KEEP_XLA_FLAGS=1``. XLA reads ``XLA_FLAGS`` when the CPU backend starts (the
first computation), so importing difftissue after a JAX computation cannot apply it:
:func:`difftissue.fit.fit_batch` then warns.
"""

from __future__ import annotations

import os
import sys

FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"


def configure() -> bool:
    """Append ``FLAG=false`` to ``XLA_FLAGS`` if it is not there; True if the flag is (now) set
    by the environment before JAX's backend starts."""
    flags = os.environ.get("XLA_FLAGS", "")
    if FLAG in flags:
        return True
    if os.environ.get("DIFFTISSUE_KEEP_XLA_FLAGS", "") not in ("", "0"):
        return False
    if "jax" not in sys.modules:  # no JAX yet, so no backend: set the flag without importing JAX
        os.environ["XLA_FLAGS"] = (flags + f" {FLAG}=false").strip()
        return True
    try:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            return False
    except (ImportError, AttributeError):  # private: JAX 0.10 has no public "backend started?" query; without it, set the variable anyway
        pass
    os.environ["XLA_FLAGS"] = (flags + f" {FLAG}=false").strip()
    return True


def active() -> bool:
    """Whether the running CPU backend was started with the flag (read from the environment)."""
    return FLAG in os.environ.get("XLA_FLAGS", "")
