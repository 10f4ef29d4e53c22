"""Counts of the XLA programs a test process obtains: compiled (``jax.monitoring``'s public
backend-compile events) or loaded from the persistent compilation cache (its public cache-hit
events). ``with ObtainedPrograms() as got: ...`` then ``got.count == {"compiled": 0, "loaded": 0}``
when the block obtained no program."""

import jax

_TOTALS = {"compiled": 0, "loaded": 0}


def _count_compiled(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        _TOTALS["compiled"] += 1


def _count_loaded(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        _TOTALS["loaded"] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compiled)
jax.monitoring.register_event_listener(_count_loaded)


class ObtainedPrograms:
    """Programs compiled and loaded between ``__enter__`` and ``__exit__`` (``count``)."""

    def __enter__(self):
        self._start = dict(_TOTALS)
        return self

    def __exit__(self, *exc):
        self.count = {k: _TOTALS[k] - self._start[k] for k in _TOTALS}
        return False
