"""Why the first depth of the m = 8 sphere's condensed solve is "not converged" with the depth traced: _condensed_newton
with its exit quantities returned (residual, tol, stall_tol, the polishing step's residual g2, steps). Needs the cached G (see
experiments/indentation_default_condensed_offline.py).  PYTHONPATH=. python experiments/indentation_default_condensed_stall.py sphere 8
"""
import sys, inspect
exec(open("experiments/indentation_default_condensed_offline.py").read().split("pf, h = [], _history")[0])
import difftissue.solvers.condensed as C
src = inspect.getsource(C._condensed_newton)
src = src.replace("def _condensed_newton(", "def newton_dbg(")
src = src.replace("return u_new, g_new, step, ok, done", "return u_new, g_new, step, ok, done")
src = src.replace("    return jnp.where(better, u2, u), ok", "    return jnp.where(better, u2, u), ok, dict(rn=jnp.linalg.norm(g), tol=tol, stall_tol=stall_tol, stable=stable, g2=jnp.linalg.norm(g2), steps=_s[2])")
src = src.replace("u, g, _, ok, _ = jax.lax.while_loop", "_s = u, g, _, ok, _ = jax.lax.while_loop")
ns = dict(C.__dict__); exec(src, ns); newton_dbg = ns["newton_dbg"]
model0 = c.contact
from difftissue.solvers.condensed import _condensed_energy
def run(depth, u0):
    return newton_dbg(params.stiffness, params.kappa, depth, u0, jnp.asarray(free_c).reshape(-1), rest=XC, indenter=model0.indenter, rtol=opts.rtol, atol=0.0, xtol=opts.xtol, max_steps=opts.max_steps)
dep = float(depths[0]); u0 = jnp.zeros(3 * k)
for name, f in (("eager-depth", lambda: run(dep, u0)), ("traced-depth", lambda: jax.jit(run)(jnp.asarray(dep), u0))):
    u, ok, info = f(); print(name, "ok", bool(ok), {a: float(b) for a, b in info.items()}, flush=True)
