"""The condensed contact solve of the automatic 3-D block, outside the config's compiled program
(diagnostic for the m = 8 sphere, whose config evaluation failed: "the contact solve on the
candidate nodes did not converge" at every depth, with max_steps 50 and 200).

Builds the config of experiments/indentation_default_fit.py (fem_linear, 4 points, geometry "3d",
cells_per_contact_radius M), computes the compliance G of the condensation's candidate degrees of
freedom eagerly (linear_response_columns, sparse Cholesky; cached in /tmp/indent_G_{IND}_m{M}.npz),
then solves the 4 depths as _Condensation.solve_protocol does (S = G^-1, penalty E * factors,
the extrapolated start, the scenario's SolverOptions) and prints the forces' errors, the fitted E
and the corrected E (the coarse forces from the config run's JSON, its check level m/2).

    PYTHONPATH=. python experiments/indentation_default_condensed_offline.py sphere 8
"""
import sys, os, json, math, time, pathlib, tempfile
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from difftissue.config import load_config
from difftissue.analytic import cone_force, hertz_force
ind, m = sys.argv[1], float(sys.argv[2])
E, NU = 1e4, 0.45
tmp = pathlib.Path(tempfile.mkdtemp())
if ind == "sphere":
    R, D = 1e-3, 2e-5; dd = np.linspace(D/200, D, 200); F = np.asarray(hertz_force(dd, E, NU, R)); ind_t = f'{{ shape = "sphere", radius = {R} }}'
else:
    th, D = math.radians(70.0), 1e-4; dd = np.linspace(D/200, D, 200); F = np.asarray(cone_force(dd, E, NU, th)); ind_t = '{ shape = "cone", half_angle_deg = 70.0 }'
(tmp/"curve.csv").write_text("depth,force\n" + "".join(f"{a:.12g},{b:.12g}\n" for a, b in zip(dd, F)))
(tmp/"fit.toml").write_text(f'''title = "x"
[material]
youngs_modulus = {E}
poisson_ratio = {NU}
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "ind"
scenario = "indentation"
model = "fem_linear"
points = 4
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "m" }}, force = {{ name = "force", unit = "N" }} }} }}
indenter = {ind_t}
specimen = {{ geometry = "3d", cells_per_contact_radius = {m} }}
''')
cfg = load_config(tmp/"fit.toml"); sc = cfg.experiments[0].scenario
c = sc.condensation
N = c.base.n_nodes
print(ind, m, "nodes", N, "unknowns", 3*N, "cand nodes", c.nodes.size, "cond dofs", c.dofs.size, "Z GB", c.dofs.size*3*N*8/1e9)
import jax.numpy as jnp
from difftissue.materials import Material
from difftissue.solvers.condensed import CondensedParameters, linear_response_columns, solve_condensed_contact
from difftissue.scenarios import _advance, _extrapolate, _history
mat = Material(youngs_modulus=E, poisson_ratio=NU)
f = f"/tmp/indent_G_{ind}_m{m:g}.npz"
if not os.path.exists(f):
    t0 = time.process_time()
    Z, G = linear_response_columns(c.base, mat, c.free, c.dofs, linear_solver="sparse")
    G = np.asarray(G); del Z
    print("G: cpu", time.process_time() - t0, "s, condition number", np.linalg.cond(G), flush=True)
    np.savez(f, G=G)
G = np.load(f)["G"]
S_free = np.linalg.inv(G); S_free = 0.5 * (S_free + S_free.T)
k = c.nodes.size
S = np.zeros((3 * k, 3 * k)); S[np.ix_(c.rows, c.rows)] = S_free
params = CondensedParameters(jnp.asarray(S), E * jnp.asarray(c.penalty_factors))
free_c = ~c.contact_fixed
depths, XC, opts = np.asarray(sc.abscissa), jnp.asarray(c.contact.rest_points), sc.options
pf, h = [], _history(jnp.zeros((k, 3)))
for dep in depths:
    model = c.contact.with_depth(dep)
    uc, ok = solve_condensed_contact(model, params, free_c, _extrapolate(h, dep), rtol=opts.rtol, xtol=opts.xtol, max_steps=opts.max_steps)
    pf.append(float(model.reaction_force(XC + uc, params))); h = _advance(h, uc, dep)
    print(f"depth {dep:.4g} m: converged {bool(ok)}, force (quarter) {pf[-1]:.6g} N", flush=True)
pf = 4.0 * np.asarray(pf)  # the quarter block's force, x 4 (as the scenario reports it)
obs = np.asarray(sc.observed)
r = json.load(open(f"experiments/results/indentation_default_fit_{ind}_fem_linear_m{m:g}_p4_s200.json"))
pc = obs * (1 + np.asarray(r["coarse_err_per_depth"]))
g, gc = pf / E, pc / E
Efit = float(obs @ g / (g @ g)); e_rel = float(g @ ((gc - g) / (r["ratio"] - 1.0)) / (g @ g))
print(json.dumps({"indenter": ind, "model": "fem_linear", "cells_per_contact_radius": m, "offline_condensed": True, "candidate_dofs": int(c.dofs.size),
                  "force_err_per_depth": list(pf / obs - 1), "E_fit_err": Efit / E - 1, "E_corrected_err": Efit * (1 + e_rel) / E - 1}))
