"""Why the first depth of the m = 8 sphere's condensed solve is "not converged" with the depth traced: _condensed_newton
with its exit quantities returned (residual, tol, stall_tol, the polishing step's residual g2, steps). Needs the cached G (see
experiments/indentation_default_condensed_offline.py).  PYTHONPATH=. python experiments/indentation_default_condensed_stall.py sphere 8
"""
import inspect
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from indentation_default_condensed_offline import setup  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import difftissue.solvers.condensed as C  # noqa: E402

s = setup(sys.argv[1], float(sys.argv[2]))
params, free_c, XC, opts, depths, k = s.params, s.free_c, s.XC, s.opts, s.depths, s.k
c = s.c
src = inspect.getsource(C._condensed_newton)
src = src.replace("def _condensed_newton(", "def newton_dbg(")
src = src.replace("    return jnp.where(better, u2, u), ok", "    return jnp.where(better, u2, u), ok, dict(rn=jnp.linalg.norm(g), tol=tol, stall_tol=stall_tol, stable=stable, g2=jnp.linalg.norm(g2), steps=_s[2])")
src = src.replace("u, g, _, ok, _ = jax.lax.while_loop", "_s = u, g, _, ok, _ = jax.lax.while_loop")
ns = dict(C.__dict__); exec(src, ns); newton_dbg = ns["newton_dbg"]
model0 = c.contact
def run(depth, u0):
    return newton_dbg(params.stiffness, params.kappa, depth, u0, jnp.asarray(free_c).reshape(-1), rest=XC, indenter=model0.indenter, rtol=opts.rtol, atol=0.0, xtol=opts.xtol, max_steps=opts.max_steps)
dep = float(depths[0]); u0 = jnp.zeros(3 * k)
for name, f in (("eager-depth", lambda: run(dep, u0)), ("traced-depth", lambda: jax.jit(run)(jnp.asarray(dep), u0))):
    u, ok, info = f(); print(name, "ok", bool(ok), {a: float(b) for a, b in info.items()}, flush=True)
