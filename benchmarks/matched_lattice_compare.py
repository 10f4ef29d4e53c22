"""Matched lattice design: main's implementation (before the closed-form design) against this
one. Make the old module first (commit 7e3b09f is the last with the old design):

    git show 7e3b09f:difftissue/models.py | sed 's/^from \\./from difftissue./' > OLD_DIR/old_models.py
    OLD_DIR=... PYTHONPATH=. python benchmarks/matched_lattice_compare.py
"""
import os
import sys; sys.path.insert(0, os.environ["OLD_DIR"])
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import old_models as O
from difftissue import models as N
lam0 = np.array([1.0, 1.001, 1.002, 0.95, 0.97, 1.05, 1.10, 1.12, 1.15, 1.2, 0.95, 1.2, 1.15, 1.08])
nu = np.array([0.45] * 10 + [0.25, 0.25, 0.499, 0.3])
def f(mod):
    return lambda l, n: mod._matched_cube_designs(l, n)
yo, yn = np.asarray(f(O)(lam0, nu)), np.asarray(f(N)(lam0, nu))
print("value max rel", np.max(np.abs(yn - yo) / np.abs(yo)))
print("bit equal at 1:", np.array_equal(yn[0], yo[0]))
for name, g in (("jvp lam0", lambda m: jax.jvp(f(m), (jnp.asarray(lam0), jnp.asarray(nu)), (jnp.ones(len(lam0)), jnp.zeros(len(lam0))))[1]),
                ("jvp nu", lambda m: jax.jvp(f(m), (jnp.asarray(lam0), jnp.asarray(nu)), (jnp.zeros(len(lam0)), jnp.ones(len(lam0))))[1]),
                ("vjp lam0,nu", lambda m: jnp.concatenate(jax.grad(lambda l, n: jnp.sum(f(m)(l, n) * jnp.arange(1, 8)), argnums=(0, 1))(jnp.asarray(lam0), jnp.asarray(nu))))):
    a, b = np.asarray(g(O)), np.asarray(g(N))
    print(name, "max rel", np.max(np.abs(b - a) / np.maximum(np.abs(a), 1e-300)), "max abs", np.max(np.abs(b - a)), "max |a|", np.max(np.abs(a)))
# closed-form tangents against jax.hessian of the old densities
shape = jnp.ones(3); gg = jnp.asarray(N._cell_spring_factors(np.ones((1, 3)))[0])
c, s, lz, lam, mu = jnp.array([0.4, 1.6, 0.9, 1.01]), 1.13, 0.82, 9.0, 1.0
F0 = jnp.diag(jnp.array([1.0, 1.0, lz]))
dens = lambda F: O._matched_cell_density(c, s, F, shape, gg, lam, mu)
P, A = N._matched_cell_tangent(c, s, lz, shape, gg, lam, mu)
print("cell P", np.max(np.abs(P - jax.grad(dens)(F0))), "A", np.max(np.abs(A - jax.hessian(dens)(F0))), np.max(np.abs(A)))
nh = lambda F: O.neo_hookean_energy_density(F @ jnp.diag(jnp.array([1.15, 1.15, 1.0])), lam, mu) / 1.15**2
P, A = N._pre_stretched_neo_hookean_tangent(1.15, 0.79, lam, mu)
F0 = jnp.diag(jnp.array([1.0, 1.0, 0.79]))
print("nh P", np.max(np.abs(P - jax.grad(nh)(F0))), "A", np.max(np.abs(A - jax.hessian(nh)(F0))))
a = np.asarray(jax.jvp(f(O), (jnp.asarray(lam0), jnp.asarray(nu)), (jnp.zeros(len(lam0)), jnp.ones(len(lam0))))[1])
b = np.asarray(jax.jvp(f(N), (jnp.asarray(lam0), jnp.asarray(nu)), (jnp.zeros(len(lam0)), jnp.ones(len(lam0))))[1])
np.set_printoptions(precision=3, linewidth=200)
print("old d/dnu rows 0..3\n", a[:4], "\nnew\n", b[:4])
print("rel err per row (norm)", np.linalg.norm(b - a, axis=1) / np.linalg.norm(a, axis=1))
