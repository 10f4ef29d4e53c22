"""Solver benchmarks: XPBD speed against a NumPy implementation of the same iteration (and
pypbd when installed), gradient/forward ratios, implicit-gradient cost, and the memory of a
100-iteration unrolled gradient with and without checkpointing.

Run by hand, on one core and one thread, e.g.:

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
        taskset -c 0 python benchmarks/solvers.py            # all sizes (n = 8, 12, 18, 24)
    python benchmarks/solvers.py --sizes 8 12 --reps 3      # quicker

Workload (identical to shared/peerbench): a block of n^3 unit cubes, 6 tets each (Freudenthal
split), a distance constraint on every tet edge and a volume constraint on every tet, both
with stiffness 1e3 (alpha = 1e-3), dt = 1e-2, one substep, unit nodal masses, base z = 0
fixed, the rest compressed 10 % in z at the start, float32. The figure is ns per
tet-iteration = (time of 40 iterations - time of 10 iterations) / 30 / n_tets, median of
``--reps`` repetitions with the implementations interleaved so they see the same noise.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np


def _workload(n):
    from difftissue.mesh import block

    mesh = block(float(n), n)
    X = np.asarray(mesh.points, dtype=np.float64)
    tets = mesh.tets.astype(np.int64)
    edges = mesh.edges.astype(np.int64)
    x0 = X.copy()
    x0[:, 2] *= 0.9
    fixed = X[:, 2] == 0.0
    return mesh, X, x0, tets, edges, fixed


# ----------------------------------------------------------------------- NumPy XPBD
class NumpyXPBD:
    """The same Jacobi XPBD iteration in vectorised NumPy (bincount scatters), float32."""

    def __init__(self, X, tets, edges, fixed, k=1e3, dt=1e-2, relaxation=1.0):
        f = np.float32
        self.X = X.astype(f)
        self.tets, self.edges = tets, edges
        self.w = np.where(fixed, 0.0, 1.0).astype(f)
        self.L0 = np.linalg.norm(self.X[edges[:, 1]] - self.X[edges[:, 0]], axis=1)
        x = self.X[tets]
        self.V0 = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6
        self.alpha_t = f(1.0 / k / dt**2)
        n = len(X)
        ce = np.bincount(edges.reshape(-1), minlength=n)
        ct = np.bincount(tets.reshape(-1), minlength=n)
        self.om_e = (relaxation / ce[edges].max(axis=1)).astype(f)
        self.om_t = (relaxation / ct[tets].max(axis=1)).astype(f)
        self.n = n

    def _scatter(self, idx, vals):
        out = np.empty((self.n, 3), np.float32)
        for c in range(3):
            out[:, c] = np.bincount(idx.reshape(-1), weights=vals[..., c].reshape(-1), minlength=self.n)
        return out

    def iterate(self, x, lam_e, lam_t):
        e, t, w, a = self.edges, self.tets, self.w, self.alpha_t
        d = x[e[:, 1]] - x[e[:, 0]]
        L = np.sqrt(np.einsum("ij,ij->i", d, d))
        nrm = d / L[:, None]
        C = L - self.L0
        den = w[e[:, 0]] + w[e[:, 1]] + a
        dl = self.om_e * (-C - a * lam_e) / den
        lam_e += dl
        g = np.stack([-nrm, nrm], axis=1) * (w[e][..., None] * dl[:, None, None])
        dx = self._scatter(e, g)
        p = x[t]
        a1, a2, a3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
        g1, g2, g3 = np.cross(a2, a3) / 6, np.cross(a3, a1) / 6, np.cross(a1, a2) / 6
        g0 = -(g1 + g2 + g3)
        grads = np.stack([g0, g1, g2, g3], axis=1)
        Ct = np.einsum("ij,ij->i", a1, g1) - self.V0
        wt = w[t]
        den = np.einsum("ek,ekc,ekc->e", wt, grads, grads) + a
        dl = self.om_t * (-Ct - a * lam_t) / den
        lam_t += dl
        dx += self._scatter(t, grads * (wt[..., None] * dl[:, None, None]))
        return x + dx

    def run(self, x, iterations):
        lam_e = np.zeros(len(self.edges), np.float32)
        lam_t = np.zeros(len(self.tets), np.float32)
        for _ in range(iterations):
            x = self.iterate(x, lam_e, lam_t)
        return x


# ------------------------------------------------------------------------ ours (JAX)
def _ours(mesh, X, x0, tets, edges, fixed, method):
    import jax
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.solvers.xpbd import DistanceConstraints, VolumeConstraints, XPBDSettings, XPBDState, xpbd_simulate_constraints

    k = 1e3
    L0 = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1)
    x = X[tets]
    V0 = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6
    cons = (DistanceConstraints(edges, L0, np.full(len(edges), k)), VolumeConstraints(tets, V0, V0 * k))
    bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(fixed))
    masses = np.ones(len(X))
    dt = jnp.float32(1e-2)
    state0 = XPBDState(jnp.asarray(x0, jnp.float32), jnp.zeros_like(jnp.asarray(x0, jnp.float32)),
                       tuple(tuple(jnp.zeros(c.n_constraints, jnp.float32) for _ in c._rows()) for c in cons), jnp.zeros((len(X), 3), jnp.float32))

    def runner(iterations):
        settings = XPBDSettings(dt=dt, substeps=1, iterations=iterations, method=method)

        def run():
            out = xpbd_simulate_constraints(cons, X.astype(np.float32), masses.astype(np.float32), bc, settings=settings, steps=1, state=state0)
            return jax.block_until_ready(out.positions)

        run()  # compile
        return run

    return runner


def _pypbd_runner(X, x0, tets, fixed):
    try:
        import pypbd as pbd
    except ImportError:
        return None
    sim = pbd.Simulation.getCurrent()
    sim.initDefault()
    model = sim.getModel()
    model.addTetModel(X.astype(np.float64), tets.astype(np.int32).reshape(-1))
    tm = model.getTetModels()[-1]
    pd = model.getParticles()
    off = tm.getIndexOffset()
    for i in range(len(X)):
        pd.setMass(off + i, 0.0 if fixed[i] else 1.0)
        pd.setPosition(off + i, x0[i])
    model.addSolidConstraints(tm, 6, 1e3, 0.3, 1e3, False, False)
    ts = sim.getTimeStep()

    def runner(iterations):
        ts.setValueUInt(pbd.TimeStepController.MAX_ITERATIONS, iterations)

        def run():
            ts.step(model)

        return run

    return runner


def _time(fn, reps):
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def bench_xpbd(sizes, reps, methods):
    rows = []
    for n in sizes:
        mesh, X, x0, tets, edges, fixed = _workload(n)
        impl = {}
        npx = NumpyXPBD(X, tets, edges, fixed)
        impl["numpy"] = lambda it, npx=npx: (lambda: npx.run(x0.astype(np.float32), it))
        for m in methods:
            r = _ours(mesh, X, x0, tets, edges, fixed, m)
            impl[f"difftissue {m}"] = r
        pb = _pypbd_runner(X, x0, tets, fixed)
        if pb is not None:
            impl["pypbd (C++, double, GS)"] = pb
        runs = {name: (f(10), f(40)) for name, f in impl.items()}
        samples = {name: [] for name in impl}
        for _ in range(reps):  # interleaved rounds
            for name, (r10, r40) in runs.items():
                t10 = _time(r10, 1)[0]
                t40 = _time(r40, 1)[0]
                samples[name].append((t40 - t10) / 30 / len(tets) * 1e9)
        base = statistics.median(samples["numpy"])
        for name, s in samples.items():
            med = statistics.median(s)
            rows.append((n, len(tets), name, med, base / med))
    print("\n## XPBD ns per tet-iteration (median; speed-up vs NumPy in the same run)\n")
    print("| n | tets | implementation | ns / tet-iteration | x NumPy |")
    print("|---|---|---|---|---|")
    for n, nt, name, med, ratio in rows:
        print(f"| {n} | {nt} | {name} | {med:.1f} | {ratio:.2f} |")
    return rows


# ----------------------------------------------------------------- gradients, memory
def bench_gradients(n_iter=30, n=6):
    import jax
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.materials import Material
    from difftissue.models import make_model
    from difftissue.solvers import solve_static
    from difftissue.solvers.xpbd import XPBDSettings, xpbd_simulate

    mesh = __import__("difftissue.mesh", fromlist=["block"]).block(0.01, n)
    model = make_model(mesh, "springs_volume")
    top = mesh.points[:, 2] == mesh.points[:, 2].max()
    bc0 = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"})
    settings = XPBDSettings(dt=1e-2, substeps=1, iterations=n_iter, method="gauss_seidel")

    def xpbd_out(p):
        bc = bc0.fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-3))
        st = xpbd_simulate(model, Material(p[0], p[1]), bc, settings=settings, steps=1)
        return jnp.sum(st.positions[:, 0] ** 2)

    def static_out(p):
        bc = bc0.fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-3))
        sol = solve_static(model, Material(p[0], p[1]), bc)
        return jnp.sum(sol.reaction[:, 2] * top)

    p = jnp.array([5e3, 0.45])
    rows = []
    for name, f in (("XPBD unrolled, %d iterations" % n_iter, xpbd_out), ("static solve (Newton)", static_out)):
        fwd = jax.jit(f)
        rev = jax.jit(jax.grad(f))
        jfw = jax.jit(jax.jacfwd(f))
        for g in (fwd, rev, jfw):
            jax.block_until_ready(g(p))
        t_f = statistics.median(_time(lambda: jax.block_until_ready(fwd(p)), 5))
        t_r = statistics.median(_time(lambda: jax.block_until_ready(rev(p)), 5))
        t_j = statistics.median(_time(lambda: jax.block_until_ready(jfw(p)), 5))
        rows.append((name, t_f, t_r, t_j))
    print(f"\n## Gradient cost ({mesh.n_tets} tets, springs_volume, 2 parameters E and nu)\n")
    print("| computation | forward [ms] | reverse grad [ms] | grad / forward | jacfwd [ms] | jacfwd / forward |")
    print("|---|---|---|---|---|---|")
    for name, f, r, j in rows:
        print(f"| {name} | {f * 1e3:.1f} | {r * 1e3:.1f} | {r / f:.2f} | {j * 1e3:.1f} | {j / f:.2f} |")
    print("\n(For the static solve, 'forward' is the Newton solve; the gradient adds one linear solve.)")
    return rows


def bench_memory(n=8, n_iter=100):
    import jax
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.materials import Material
    from difftissue.models import make_model
    from difftissue.solvers.xpbd import XPBDSettings, xpbd_simulate

    mesh = __import__("difftissue.mesh", fromlist=["block"]).block(0.01, n)
    model = make_model(mesh, "springs_volume")
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-3))
    print(f"\n## Peak temporary memory of a {n_iter}-iteration unrolled reverse-mode gradient ({mesh.n_tets} tets)\n")
    print("| checkpointing | XLA temp buffers [MiB] |")
    print("|---|---|")
    for ckpt in (True, False):
        settings = XPBDSettings(dt=1e-2, substeps=1, iterations=n_iter, method="jacobi", checkpoint=ckpt)

        def f(p):
            st = xpbd_simulate(model, Material(p[0], p[1]), bc, settings=settings, steps=1)
            return jnp.sum(st.positions[:, 0] ** 2)

        compiled = jax.jit(jax.grad(f)).lower(jnp.array([5e3, 0.45])).compile()
        mem = compiled.memory_analysis()
        print(f"| {'on' if ckpt else 'off'} | {mem.temp_size_in_bytes / 2**20:.1f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 12, 18, 24])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--methods", nargs="+", default=["jacobi", "gauss_seidel"])
    ap.add_argument("--skip", nargs="*", default=[], choices=["xpbd", "gradients", "memory"])
    args = ap.parse_args(argv)
    import jax

    print(f"jax {jax.__version__}, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}, python {sys.version.split()[0]}")
    if "xpbd" not in args.skip:
        bench_xpbd(args.sizes, args.reps, args.methods)
    jax.config.update("jax_enable_x64", True)
    if "gradients" not in args.skip:
        bench_gradients()
    if "memory" not in args.skip:
        bench_memory()


if __name__ == "__main__":
    main()
