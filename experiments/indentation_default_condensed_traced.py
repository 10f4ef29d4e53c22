"""The m = 8 sphere's condensed contact solve with the depth traced (as in _Condensation.solve_protocol's scan) and concrete.
Uses the set-up (and cached G) of experiments/indentation_default_condensed_offline.py.  PYTHONPATH=. python experiments/indentation_default_condensed_traced.py sphere 8
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from indentation_default_condensed_offline import setup  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from difftissue.scenarios import _advance, _extrapolate, _history  # noqa: E402
from difftissue.solvers.condensed import solve_condensed_contact  # noqa: E402

s = setup(sys.argv[1], float(sys.argv[2]))


def step(history, depth):
    model = s.c.contact.with_depth(depth)
    uc, ok = solve_condensed_contact(model, s.params, s.free_c, _extrapolate(history, depth), rtol=s.opts.rtol, xtol=s.opts.xtol, max_steps=s.opts.max_steps)
    return _advance(history, uc, depth), (ok, model.reaction_force(s.XC + uc, s.params))


_, (oks, fs) = jax.lax.scan(step, _history(jnp.zeros((s.k, 3))), jnp.asarray(s.depths))
print("scan: converged", np.asarray(oks), "forces x4/obs-1", 4 * np.asarray(fs) / np.asarray(s.sc.observed) - 1, flush=True)
h = _history(jnp.zeros((s.k, 3)))
for dep in s.depths:
    h, (ok, f) = jax.jit(step)(h, jnp.asarray(dep))
    print("jit step, traced depth", dep, bool(ok), flush=True)
