"""The test suite's persistent cache of programs with host callbacks (tests/callback_cache.py):
a program read from the cache by another process runs its own callbacks, raises its own
``eqx.error_if`` and computes what a freshly compiled one computes."""

import json
import subprocess
import sys
from pathlib import Path

import callback_cache
import jax
import pytest

# One process: compile (or load) a program with an eqx.error_if, a pure_callback that returns
# values and a jax.debug.callback; report what it computed, what the callbacks saw, whether the
# check raised, and whether the program itself was read from the cache.
_PROGRAM = r"""
import json, logging, sys
sys.path.insert(0, sys.argv[2])
import callback_cache
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
status = callback_cache.install()
# JAX logs each program read from the persistent cache by name (at WARNING under log_compiles).
jax.config.update("jax_log_compiles", True)
loaded = []

class Loaded(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Persistent compilation cache hit for 'jit_program'"):
            loaded.append(record.getMessage())

logging.getLogger("jax").addHandler(Loaded())
seen = []

def host_double(x):
    seen.append(("pure", x.tolist()))
    return np.asarray(2.0 * x)

@jax.jit
def program(x):
    x = eqx.error_if(x, x < 0, "x must not be negative")
    y = jax.pure_callback(host_double, jax.ShapeDtypeStruct(x.shape, x.dtype), x)
    jax.debug.callback(lambda total: seen.append(("debug", float(total))), y.sum())
    return y + 1.0

good, bad = jnp.arange(3.0), jnp.array([1.0, -1.0, 2.0])  # one program for both
value = program(good).tolist()
try:
    jax.block_until_ready(program(bad))
    raised = ""
except Exception as error:
    raised = str(error)
print(json.dumps({"status": status, "value": value, "seen": seen, "raised": "x must not be negative" in raised, "loaded": len(loaded)}))
"""


def _run(cache: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", _PROGRAM, str(cache), str(Path(__file__).parent)], capture_output=True, text=True, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_program_read_from_the_cache_runs_its_own_callbacks_and_checks(tmp_path):
    first = _run(tmp_path / "cache")
    second = _run(tmp_path / "cache")
    for run in (first, second):
        assert run["value"] == [1.0, 3.0, 5.0]
        assert run["seen"] == [["pure", [0.0, 1.0, 2.0]], ["debug", 6.0]]
        assert run["raised"], "the eqx.error_if of the program did not raise"
    assert first["loaded"] == 0
    if first["status"] in ("installed", "not needed"):
        assert second["loaded"] == 1, second  # read from the cache, not compiled again
    else:
        pytest.skip(f"callbacks are not cached on this JAX: {first['status']}")


@pytest.mark.skipif(not jax.__version__.startswith("0.10."), reason="the backport was written against jax 0.10")
def test_the_backport_is_installed_on_the_jax_it_was_written_for():
    assert callback_cache.STATUS in ("installed", "off (DIFFTISSUE_TEST_CACHE_CALLBACKS)"), callback_cache.STATUS
