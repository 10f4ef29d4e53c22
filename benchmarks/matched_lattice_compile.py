"""Matched lattice design: main's implementation (before the closed-form design) against this
one. Make the old module first (commit 7e3b09f is the last with the old design):

    git show 7e3b09f:difftissue/models.py | sed 's/^from \\./from difftissue./' > OLD_DIR/old_models.py
    OLD_DIR=... PYTHONPATH=. python benchmarks/matched_lattice_compile.py REPS CASE...  (cases: design design_jvp design_grad energy energy_value_and_grad)
"""
import os
import sys, time, json, statistics
sys.path.insert(0, os.environ["OLD_DIR"])
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import old_models as O
from difftissue import models as N
from difftissue.materials import Material
from difftissue.mesh import block

def ct(fn, *args):
    jax.clear_caches()
    t0 = time.process_time(); low = jax.jit(fn).lower(*args); t1 = time.process_time()
    low.compile(); t2 = time.process_time()
    return t1 - t0, t2 - t1, len(low.as_text())

l0, nu = jnp.array([1.12, 1.0]), jnp.array([0.45, 0.45])
mesh = block((4e-3, 4e-3, 2e-3), (4, 4, 2))
x = jnp.asarray(mesh.points)
def cases(m):
    d = lambda l, n: m._matched_cube_designs(l, n)
    model = m.make_model(mesh, "springs_volume_matched_lattice")
    e = lambda x, lam: model.energy(x, Material(2e5, 0.45, pre_stretch=lam))
    return {"design": (d, (l0, nu)),
            "design_jvp": (lambda l, n: jax.jvp(d, (l, n), (jnp.ones_like(l), jnp.zeros_like(n))), (l0, nu)),
            "design_grad": (lambda l, n: jax.grad(lambda l: jnp.sum(d(l, n)))(l), (l0, nu)),
            "energy": (e, (x, jnp.asarray(1.1))),
            "energy_value_and_grad": (jax.value_and_grad(e, argnums=(0, 1)), (x, jnp.asarray(1.1)))}
res = {}
reps = int(sys.argv[1]) if len(sys.argv) > 1 else 2
for r in range(reps):
    for tag, m in (("old", O), ("new", N)):
        for k, (f, a) in cases(m).items():
            if k not in sys.argv[2:]:
                continue
            res.setdefault((k, tag), []).append(ct(f, *a))
            print(r, tag, k, [round(v, 2) for v in res[(k, tag)][-1][:2]], res[(k, tag)][-1][2], flush=True)
print("case                   | old trace+compile s (hlo chars) | new trace+compile s (hlo chars) | ratio")
for k in sys.argv[2:]:
    o, n = res[(k, "old")], res[(k, "new")]
    mo = statistics.median([a + b for a, b, _ in o]); mn = statistics.median([a + b for a, b, _ in n])
    print(f"{k:22s} | {mo:6.2f} ({[round(a+b,2) for a,b,_ in o]}, {o[0][2]}) | {mn:6.2f} ({[round(a+b,2) for a,b,_ in n]}, {n[0][2]}) | {mo/mn:5.1f}x", flush=True)
