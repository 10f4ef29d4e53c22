"""The m = 8 sphere's condensed contact solve with the depth traced (as in _Condensation.solve_protocol's scan) and concrete.
Needs the G cached by experiments/indentation_default_condensed_offline.py.  PYTHONPATH=. python experiments/indentation_default_condensed_traced.py sphere 8
"""
import sys
exec(open("experiments/indentation_default_condensed_offline.py").read().split("pf, h = [], _history")[0])
def step(history, depth):
    model = c.contact.with_depth(depth)
    uc, ok = solve_condensed_contact(model, params, free_c, _extrapolate(history, depth), rtol=opts.rtol, xtol=opts.xtol, max_steps=opts.max_steps)
    return _advance(history, uc, depth), (ok, model.reaction_force(XC + uc, params))
_, (oks, fs) = jax.lax.scan(step, _history(jnp.zeros((k, 3))), jnp.asarray(depths))
print("scan: converged", np.asarray(oks), "forces x4/obs-1", 4 * np.asarray(fs) / np.asarray(sc.observed) - 1, flush=True)
h = _history(jnp.zeros((k, 3)))
for dep in depths:
    h2, (ok, f) = jax.jit(step)(h, jnp.asarray(dep)); h = h2
    print("jit step, traced depth", dep, bool(ok), flush=True)
