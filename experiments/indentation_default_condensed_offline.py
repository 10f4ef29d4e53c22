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
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from indentation_default_fit import E, NU, write_config  # noqa: E402
from difftissue.config import load_config  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.scenarios import _advance, _extrapolate, _history  # noqa: E402
from difftissue.solvers.condensed import CondensedParameters, linear_response_columns, solve_condensed_contact  # noqa: E402


def setup(ind: str, m: float) -> SimpleNamespace:
    """The config's scenario (fem_linear, 4 points, the automatic 3-D block at ``m`` cells per
    contact radius), its condensation ``c``, the condensed parameters at E (G cached in
    /tmp/indent_G_{ind}_m{m}.npz), the free candidate components, depths, rest points, options."""
    sc = load_config(write_config(ind, "fem_linear", m=m, points=4)).experiments[0].scenario
    c = sc.condensation
    N = c.base.n_nodes
    print(ind, m, "nodes", N, "unknowns", 3 * N, "cand nodes", c.nodes.size, "cond dofs", c.dofs.size, "Z GB", c.dofs.size * 3 * N * 8 / 1e9)
    f = f"/tmp/indent_G_{ind}_m{m:g}.npz"
    if not os.path.exists(f):
        t0 = time.process_time()
        Z, G = linear_response_columns(c.base, Material(youngs_modulus=E, poisson_ratio=NU), c.free, c.dofs, linear_solver="sparse")
        G = np.asarray(G)
        del Z
        print("G: cpu", time.process_time() - t0, "s, condition number", np.linalg.cond(G), flush=True)
        np.savez(f, G=G)
    G = np.load(f)["G"]
    S_free = np.linalg.inv(G)
    S_free = 0.5 * (S_free + S_free.T)
    k = c.nodes.size
    S = np.zeros((3 * k, 3 * k))
    S[np.ix_(c.rows, c.rows)] = S_free
    return SimpleNamespace(sc=sc, c=c, k=k, params=CondensedParameters(jnp.asarray(S), E * jnp.asarray(c.penalty_factors)), free_c=~c.contact_fixed,
                           depths=np.asarray(sc.abscissa), XC=jnp.asarray(c.contact.rest_points), opts=sc.options)


def main(ind: str, m: float):
    s = setup(ind, m)
    pf, h = [], _history(jnp.zeros((s.k, 3)))
    for dep in s.depths:
        model = s.c.contact.with_depth(dep)
        uc, ok = solve_condensed_contact(model, s.params, s.free_c, _extrapolate(h, dep), rtol=s.opts.rtol, xtol=s.opts.xtol, max_steps=s.opts.max_steps)
        pf.append(float(model.reaction_force(s.XC + uc, s.params)))
        h = _advance(h, uc, dep)
        print(f"depth {dep:.4g} m: converged {bool(ok)}, force (quarter) {pf[-1]:.6g} N", flush=True)
    pf = 4.0 * np.asarray(pf)  # the quarter block's force, x 4 (as the scenario reports it)
    obs = np.asarray(s.sc.observed)
    r = json.load(open(f"experiments/results/indentation_default_fit_{ind}_fem_linear_m{m:g}_p4_s200.json"))
    pc = obs * (1 + np.asarray(r["coarse_err_per_depth"]))
    g, gc = pf / E, pc / E
    Efit = float(obs @ g / (g @ g))
    e_rel = float(g @ ((gc - g) / (r["ratio"] - 1.0)) / (g @ g))
    print(json.dumps({"indenter": ind, "model": "fem_linear", "cells_per_contact_radius": m, "offline_condensed": True, "candidate_dofs": int(s.c.dofs.size),
                      "force_err_per_depth": list(pf / obs - 1), "E_fit_err": Efit / E - 1, "E_corrected_err": Efit * (1 + e_rel) / E - 1}))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
