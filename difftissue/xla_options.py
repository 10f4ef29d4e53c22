"""XLA compiler options per compiled program, in one place: the option sets, what each trades
(measured on a CPU, jaxlib 0.10), and the rule that picks them for a program
(:func:`compiler_options`).

Options are passed per program (``jax.jit(..., compiler_options=...)`` or
``Lowered.compile(compiler_options=...)``): nothing global, no ``XLA_FLAGS`` edit. They apply
on a CPU backend only; on a GPU the programs compile with XLA's defaults. An option the
installed jaxlib does not know is left out (:func:`compiler_options`): the program then
compiles with the defaults.

Option sets:

- :data:`OLDER_FUSION` (``xla_cpu_use_fusion_emitters=False``): XLA's older element-wise
  fusion instead of the fusion emitters (the default since jaxlib 0.5). Compiles the static
  physics programs faster and with less memory: the host derivative program of an 8-node
  ``springs_volume`` model 0.9 s CPU instead of 1.6 s (run time the same, 0.36 vs
  0.33-0.42 ms a call); set for the whole process, compile CPU of the static and scenario test
  files -24 to -26 % and a cold 105,903-unknown ``springs_volume`` multigrid-direct solve
  18.0 -> 15.7 s CPU, peak memory 1.69 -> 1.36 GB, warm run +3 %. Results differ from the
  default compilation in the last bits (~1e-16 relative). NOT for the XPBD Jacobi iteration
  (:mod:`difftissue.solvers.xpbd`), which runs ~40 % slower with it: XPBD, dynamics and
  XPBD-budget programs keep the defaults.
- :data:`LOW_OPTIMISATION` (``xla_backend_optimization_level=0``): XLA's backend optimisation
  level 0. Compiles small programs faster and runs them slower: the one-cube compression
  protocol 4.0 -> 2.8 s CPU to compile, 3 -> 6 ms to run; a spectral batched fit step 6.3 ->
  4.0 s to compile, 0.074 -> 0.087 s to run (with :data:`OLDER_FUSION` too: 1.6 s to
  compile, the same run time). Results agree with the default level to ~1e-12 relative.
- :data:`SERIAL_SCHEDULER` (``xla_cpu_enable_concurrency_optimized_scheduler=False``): XLA's
  concurrency-optimised CPU scheduler off; it deadlocked batched Levenberg--Marquardt steps of
  simulated compressions in earlier jaxlib versions.

Programs (:data:`PROGRAMS`): ``"host_derivatives"`` (the compiled model derivatives of
:mod:`difftissue.solvers.host`), ``"static"`` (:func:`~difftissue.solvers.static.solve_static`,
the scenarios' compiled protocols, the :class:`~difftissue.config.SeparatelyCompiled` programs
of static scenarios), ``"small_static"`` (the latter for a model of at most
``difftissue.config.compile.SMALL_MODEL_NODES`` nodes), ``"batch"`` and ``"batch_spectral"``
(the batched fit programs of :func:`~difftissue.fit.fit_batch`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["OLDER_FUSION", "LOW_OPTIMISATION", "SERIAL_SCHEDULER", "PROGRAMS", "compiler_options", "known_options", "staged", "ProgramJit"]

#: XLA's older element-wise CPU fusion (see the module docstring).
OLDER_FUSION = {"xla_cpu_use_fusion_emitters": False}

#: XLA's backend optimisation level 0: faster compilation, slower run (module docstring).
LOW_OPTIMISATION = {"xla_backend_optimization_level": 0}

#: XLA's concurrency-optimised CPU scheduler off (module docstring).
SERIAL_SCHEDULER = {"xla_cpu_enable_concurrency_optimized_scheduler": False}

#: ``{program kind: XLA options on a CPU backend}`` (see the module docstring).
PROGRAMS = {
    "host_derivatives": OLDER_FUSION,
    "static": OLDER_FUSION,
    "small_static": {**OLDER_FUSION, **LOW_OPTIMISATION},
    "batch": SERIAL_SCHEDULER,
    "batch_spectral": {**SERIAL_SCHEDULER, **LOW_OPTIMISATION, **OLDER_FUSION},
}


@functools.lru_cache(maxsize=None)
def _known(backend: str, name: str, value) -> bool:
    """Whether the installed jaxlib compiles a trivial program on the default ``backend`` (part
    of the cache key) with the option
    ``name=value`` (an unknown option raises "No such compile option")."""
    import jax

    try:
        jax.jit(lambda x: x + 1.0).lower(1.0).compile(compiler_options={name: value})
    except RuntimeError as err:  # jax.errors.JaxRuntimeError
        if "No such compile option" not in str(err):
            raise
        return False
    return True


def known_options(options: dict, backend: str = "cpu") -> dict:
    """``options`` without those the installed jaxlib does not know on ``backend`` (JAX's
    default backend)."""
    return {k: v for k, v in options.items() if _known(backend, k, v)}


def compiler_options(program: str, backend: str | None = None) -> dict | None:
    """The XLA options of a ``program`` kind (a key of :data:`PROGRAMS`) for ``backend``
    (default: JAX's default backend): its option set on a CPU, less the options this jaxlib
    does not know; None (XLA's defaults) on another backend or when none is left."""
    if program not in PROGRAMS:
        raise KeyError(f"unknown program kind {program!r} (choose from {sorted(PROGRAMS)})")
    backend = backend or jax.default_backend()
    if backend != "cpu":
        return None
    return known_options(PROGRAMS[program], backend) or None


def staged() -> bool:
    """Whether the caller is being traced into an outer program (``jax.jit``, ``lax.scan``,
    ``jax.eval_shape``, ...): an array created now is a tracer there. ``jax.vmap``, ``jax.jvp``
    and ``jax.grad`` alone do not stage (their jitted calls are still compiled on their own)."""
    return isinstance(jnp.zeros(()), jax.core.Tracer)


class ProgramJit:
    """``jax.jit(fn, **jit_kwargs)`` compiled with the XLA options of a ``program`` kind
    (:func:`compiler_options`) when called on its own, with concrete arguments. Called while an
    outer program is traced (:func:`staged`) or with a traced argument (``jax.grad``,
    ``jax.vmap``, ...: JAX may stage the call into another program) it is a plain ``jax.jit``,
    under the options of the program it ends up in (JAX accepts ``compiler_options`` on the
    outermost ``jax.jit`` only)."""

    def __init__(self, fn, program: str, **jit_kwargs):
        if program not in PROGRAMS:
            raise KeyError(f"unknown program kind {program!r} (choose from {sorted(PROGRAMS)})")
        self.fn, self.program, self._jit_kwargs = fn, program, jit_kwargs
        self._jits: dict = {}  # {options (sorted items): jax.jit}

    def jitted(self, *args, **kwargs):
        """The ``jax.jit`` function a call with these arguments goes through now."""
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((args, kwargs)))
        options = None if traced or staged() else compiler_options(self.program)
        key = tuple(sorted(options.items())) if options else ()
        jitted = self._jits.get(key)
        if jitted is None:
            jitted = self._jits[key] = jax.jit(self.fn, compiler_options=options, **self._jit_kwargs)
        return jitted

    def __call__(self, *args, **kwargs):
        return self.jitted(*args, **kwargs)(*args, **kwargs)
