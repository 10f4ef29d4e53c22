"""In-process: warm multigrid solve_static (called directly, as benchmarks/static.py's
multigrid-direct) and PyAMG's own solve of the same (linearised) system, interleaved, medians
of CPU times. Usage: inproc.py SIZE MODEL REPS"""
import sys, time, json, os
sys.path.insert(0, os.environ["PYTHONPATH"] + "/benchmarks")
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
import static as B
import pyamg, scipy.sparse as sps
from difftissue.materials import Material
from difftissue.solvers import solve_static
import difftissue.solvers.static as st
from difftissue.solvers.sparse import assemble_csr_data, sparse_pattern
from difftissue.solvers.multigrid import rigid_body_modes
n, kind, reps = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
mesh, model, bc, top, material = B._problem(n, kind)
def ours(E):
    sol = solve_static(model, Material(E, 0.45), bc, linear_solver="multigrid", rtol=B.RTOL, cg_rtol=B.RTOL)
    return float(jnp.sum(sol.reaction[top, 2])), int(sol.steps), int(sol.linear_steps)
F, steps, cg = ours(1e4)
free = ~np.asarray(bc.fixed).reshape(-1); u_fixed = np.asarray(bc.displacement).reshape(-1) * ~free
data = st._element_data(model, jnp.asarray(model.rest_points), material)
pat = sparse_pattern([t_.nodes for t_ in model.terms(material)], model.n_nodes)
K = sps.csr_matrix((np.asarray(assemble_csr_data(pat, data, jnp.ones(pat.n))), pat.indices, pat.indptr), shape=(pat.n, pat.n))
P = free.astype(float); A = sps.diags(P) @ K @ sps.diags(P) + sps.diags(1 - P); b = -P * (K @ u_fixed)
Bm = rigid_body_modes(np.asarray(mesh.points)) * P[:, None]
ml = pyamg.smoothed_aggregation_solver(sps.bsr_matrix(A, blocksize=(3, 3)), B=Bm, max_coarse=60)
to, tp = [], []
for r in range(reps):
    t = time.process_time(); Fo = ours(1e4); to.append(time.process_time() - t)
    res = []
    t = time.process_time(); x = ml.solve(b, tol=B.RTOL, accel="cg", maxiter=500, residuals=res); tp.append(time.process_time() - t)
Fp = float(np.sum((K @ (x + u_fixed)).reshape(-1, 3)[top, 2]))
out = dict(model=kind, unknowns=3 * mesh.n_nodes, newton_steps=steps, cg_max=cg, ours_cpu=to, pyamg_cpu=tp, pyamg_its=len(res) - 1,
           ours_median=float(np.median(to)), pyamg_median=float(np.median(tp)), ratio=float(np.median(to) / np.median(tp)),
           force=F, force_pyamg_linearised=Fp, load=os.getloadavg()[0], code=os.environ.get("PYTHONPATH"))
print("RESULT " + json.dumps(out), flush=True)
