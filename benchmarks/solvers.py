"""Solver benchmarks: XPBD speed against a NumPy implementation of the same iteration (and
pypbd when installed), gradient/forward ratios, implicit-gradient cost, and the memory of a
100-iteration unrolled gradient with and without checkpointing.

Run by hand, on one core and one thread, e.g.:

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
        taskset -c 0 python benchmarks/solvers.py            # all sizes (n = 8, 12, 18, 24)
    python benchmarks/solvers.py --sizes 8,12 --reps 3      # chosen sizes
    python benchmarks/solvers.py --quick                    # smoke run (~1 min): n = 8, 3 reps

Workload (identical to shared/peerbench): a block of n^3 unit cubes, 6 tets each (Freudenthal
split), a distance constraint on every tet edge and a volume constraint on every tet, both
with stiffness 1e3 (alpha = 1e-3), dt = 1e-2, one substep, unit nodal masses, base z = 0
fixed, the rest compressed 10 % in z at the start, float32. The figure is ns per
tet-iteration = (time of 40 iterations - time of 10 iterations) / 30 / n_tets, median (and
minimum) of ``--reps`` repetitions with the implementations interleaved so they see the same
noise. Times are CPU times of the process (``time.process_time``): on one pinned thread that is
the wall time of an idle machine, and it is far less sensitive to other processes sharing the
core. The machine load (``os.getloadavg``) is printed with each section.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")  # pypbd (OpenMP): one thread, like everything else here


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
    """The same Jacobi XPBD iteration in vectorised NumPy, float32: x, y, z as three (N,)
    arrays, explicit cross/dot products, one ``np.bincount`` scatter per component, the
    per-vertex inverse mass applied once after each scatter (as in ``difftissue``)."""

    def __init__(self, X, tets, edges, fixed, k=1e3, dt=1e-2, relaxation=1.0):
        f = np.float32
        X = X.astype(f)
        self.n = n = len(X)
        self.e0, self.e1 = edges[:, 0].copy(), edges[:, 1].copy()
        self.t = [tets[:, j].copy() for j in range(4)]
        self.e_all = np.concatenate([self.e0, self.e1])
        self.t_all = np.concatenate(self.t)
        self.w = np.where(fixed, 0.0, 1.0).astype(f)
        self.L0 = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1).astype(f)
        x = X[tets]
        self.V0 = (np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6).astype(f)
        self.beta = f(k * dt**2)  # h^2 / alpha
        ce = np.bincount(edges.reshape(-1), minlength=n)
        ct = np.bincount(tets.reshape(-1), minlength=n)
        self.om_e = (relaxation / ce[edges].max(axis=1)).astype(f)
        self.om_t = (relaxation / ct[tets].max(axis=1)).astype(f)

    def _apply(self, P, idx, parts):
        w = self.w
        return [p + w * np.bincount(idx, weights=np.concatenate(c), minlength=self.n).astype(np.float32) for p, c in zip(P, parts)]

    def iterate(self, P, lam_e, lam_t):
        b = self.beta
        w = self.w
        e0, e1 = self.e0, self.e1
        d = [p[e1] - p[e0] for p in P]
        L = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        inv = 1.0 / L
        den = w[e0] + w[e1]
        dl = self.om_e * (-(b * (L - self.L0) + lam_e) / (b * den + 1.0))
        lam_e += dl
        s = inv * dl
        P = self._apply(P, self.e_all, [(-c * s, c * s) for c in d])
        t0, t1, t2, t3 = self.t
        q0 = [p[t0] for p in P]
        a1 = [p[t1] - o for p, o in zip(P, q0)]
        a2 = [p[t2] - o for p, o in zip(P, q0)]
        a3 = [p[t3] - o for p, o in zip(P, q0)]

        def cross6(u, v):
            return [(u[1] * v[2] - u[2] * v[1]) / 6, (u[2] * v[0] - u[0] * v[2]) / 6, (u[0] * v[1] - u[1] * v[0]) / 6]

        g1, g2, g3 = cross6(a2, a3), cross6(a3, a1), cross6(a1, a2)
        g0 = [-(x + y + z) for x, y, z in zip(g1, g2, g3)]
        C = a1[0] * g1[0] + a1[1] * g1[1] + a1[2] * g1[2] - self.V0
        den = sum(w[tj] * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]) for tj, g in zip(self.t, (g0, g1, g2, g3)))
        dl = self.om_t * (-(b * C + lam_t) / (b * den + 1.0))
        lam_t += dl
        return self._apply(P, self.t_all, [tuple(g[c] * dl for g in (g0, g1, g2, g3)) for c in range(3)])

    def run(self, x, iterations):
        P = [np.ascontiguousarray(x[:, c], dtype=np.float32) for c in range(3)]
        lam_e = np.zeros(len(self.e0), np.float32)
        lam_t = np.zeros(len(self.V0), np.float32)
        for _ in range(iterations):
            P = self.iterate(P, lam_e, lam_t)
        return np.stack(P, axis=1)


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

    Xf, mf = X.astype(np.float32), masses.astype(np.float32)

    def runner(iterations):
        settings = XPBDSettings(dt=dt, substeps=1, iterations=iterations, method=method)

        def run():
            t = _clock()
            out = xpbd_simulate_constraints(cons, Xf, mf, bc, settings=settings, steps=1, state=state0)
            jax.block_until_ready(out.positions)
            return _clock() - t

        run()  # compile
        return run

    return runner


def _pypbd_runner(X, x0, tets, fixed):
    """pypbd (PositionBasedDynamics, C++, double, coloured Gauss-Seidel), driven as in
    shared/peerbench: XPBD distance + volume constraints (method 6), one substep, no velocity
    iterations; the iteration count is set before each step."""
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
    model.addSolidConstraints(tm, 6, 1e3, 0.3, 1e3, False, False)
    ts = sim.getTimeStep()
    ts.setValueUInt(pbd.TimeStepController.NUM_SUB_STEPS, 1)
    ts.setValueUInt(pbd.TimeStepController.MAX_ITERATIONS_V, 0)
    pbd.TimeManager.getCurrent().setTimeStepSize(1e-2)

    def runner(iterations):
        def run():
            for i in range(len(X)):  # same start every time: compressed, at rest
                pd.setPosition(off + i, x0[i])
                pd.setVelocity(off + i, np.zeros(3))
            ts.setValueUInt(pbd.TimeStepController.MAX_ITERATIONS, iterations)
            t = _clock()
            ts.step(model)
            return _clock() - t

        return run

    return runner


# Peer figures from shared/peerbench/README.md (ns per tet-iteration, 1 thread, n = 8/12/18/24).
PEERS = {
    "plain C, gcc -O3, Jacobi": {8: 24.5, 12: 22.4, 18: 22.7, 24: 23.0},
    "pypbd 2.2.2 (C++, double, GS)": {8: 112, 12: 108, 18: 136, 24: 207},
    "NumPy vectorised (peerbench)": {8: 214, 12: 192, 18: 182, 24: 182},
    "best JAX (explicit cross/dot, YNN flag off)": {8: 45, 12: 43, 18: 43, 24: 39},
}


def _clock():
    """CPU time of this process (all its threads). The benchmark runs single-threaded and
    pinned, so CPU time equals the wall time on an idle machine, and it does not count the
    time slices other processes take on a shared one (wall times scattered by +-40 % here)."""
    return time.process_time()


def _load():
    try:
        return "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "load average n/a"


def _time(fn, reps):
    out = []
    for _ in range(reps):
        t = _clock()
        fn()
        out.append(_clock() - t)
    return out


def _self_timed(fn):
    def run():
        t = _clock()
        fn()
        return _clock() - t

    return run


def bench_xpbd(sizes, reps, methods):
    rows = []
    for n in sizes:
        mesh, X, x0, tets, edges, fixed = _workload(n)
        impl = {}
        npx = NumpyXPBD(X, tets, edges, fixed)
        impl["NumPy (same Jacobi iteration)"] = lambda it, npx=npx: _self_timed(lambda: npx.run(x0, it))
        for m in methods:
            impl[f"difftissue {m}"] = _ours(mesh, X, x0, tets, edges, fixed, m)
        pb = _pypbd_runner(X, x0, tets, fixed)
        if pb is not None:
            impl["pypbd 2.2.2 (C++, double, GS)"] = pb
        runs = {name: (f(10), f(40)) for name, f in impl.items()}
        samples = {name: [] for name in impl}
        for _ in range(reps):  # interleaved rounds
            for name, (r10, r40) in runs.items():
                t10 = r10()
                t40 = r40()
                samples[name].append((t40 - t10) / 30 / len(tets) * 1e9)
        base = statistics.median(samples["NumPy (same Jacobi iteration)"])
        for name, smp in samples.items():
            med = statistics.median(smp)
            rows.append((n, len(tets), name, med, min(smp), base / med))
        print(f"  (n = {n} done, {_load()})", flush=True)
    print("\n## XPBD ns per tet-iteration (median and minimum of the rounds; speed-up vs NumPy in the same run)\n")
    print("| n | tets | implementation | median ns / tet-iteration | min | x NumPy (medians) |")
    print("|---|---|---|---|---|---|")
    for n, nt, name, med, mn, ratio in rows:
        print(f"| {n} | {nt} | {name} | {med:.1f} | {mn:.1f} | {ratio:.2f} |")
    ours = {(n, name): med for n, _, name, med, _, _ in rows if name.startswith("difftissue jacobi")}
    if ours:
        print("\n## Our Jacobi median against the peerbench figures (peer ns / ours; > 1: we are faster)\n")
        print("| peer (peerbench README) | " + " | ".join(f"n={n}" for n in sizes) + " |")
        print("|---|" + "---|" * len(sizes))
        for peer, fig in PEERS.items():
            cells = [f"{fig[n]} / {ours[(n, 'difftissue jacobi')]:.0f} = {fig[n] / ours[(n, 'difftissue jacobi')]:.2f}" if n in fig else "-" for n in sizes]
            print(f"| {peer} | " + " | ".join(cells) + " |")
    return rows


# ----------------------------------------------------------------- gradients, memory
def _peer_objective(n, iterations, method, checkpoint=True):
    """Loss of the peerbench workload after ``iterations`` XPBD iterations (one frame) as a
    function of two parameters (edge stiffness, tet bulk-like stiffness), float32."""
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.solvers.xpbd import DistanceConstraints, VolumeConstraints, XPBDSettings, XPBDState, xpbd_simulate_constraints

    mesh, X, x0, tets, edges, fixed = _workload(n)
    L0 = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1)
    x = X[tets]
    V0 = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6
    bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(fixed))
    masses = np.ones(len(X), np.float32)
    settings = XPBDSettings(dt=1e-2, substeps=1, iterations=iterations, method=method, checkpoint=checkpoint)
    x0j = jnp.asarray(x0, jnp.float32)
    Xf = X.astype(np.float32)

    def f(p):
        cons = (DistanceConstraints(edges, L0, p[0]), VolumeConstraints(tets, V0, V0 * p[1]))
        mult = tuple(tuple(jnp.zeros(c.n_constraints, jnp.float32) for _ in c._rows()) for c in cons)
        state = XPBDState(x0j, jnp.zeros_like(x0j), mult, jnp.zeros_like(x0j))
        out = xpbd_simulate_constraints(cons, Xf, masses, bc, settings=settings, steps=1, state=state)
        return jnp.sum((out.positions - x0j) ** 2)

    return f, len(tets), jnp.array([1e3, 1e3], jnp.float32)


def _ratio_rows(fns, p, reps):
    """Interleaved timing of jitted forward / reverse / forward-mode variants."""
    import jax

    compiled = {}
    for name, f in fns.items():
        fw, rv, jf = jax.jit(f), jax.jit(jax.grad(f)), jax.jit(jax.jacfwd(f))
        for g in (fw, rv, jf):
            jax.block_until_ready(g(p))
        compiled[name] = (fw, rv, jf)
    samples = {name: ([], [], []) for name in fns}
    for _ in range(reps):
        for name, gs in compiled.items():
            for g, acc in zip(gs, samples[name]):
                acc.extend(_time(lambda g=g: jax.block_until_ready(g(p)), 1))
    return {name: tuple(statistics.median(a) for a in acc) for name, acc in samples.items()}


def bench_unrolled(n, iterations, reps):
    print(f"\n## Unrolled XPBD gradient vs forward (peerbench workload n = {n}, float32, 2 parameters; {_load()})\n")
    print("| method | iterations | tets | forward [ms] | reverse grad [ms] | grad / forward | jacfwd [ms] | jacfwd / forward |")
    print("|---|---|---|---|---|---|---|---|")
    out = []
    for method in ("jacobi", "gauss_seidel"):
        fns, nt = {}, 0
        for it in iterations:
            f, nt, p = _peer_objective(n, it, method)
            fns[it] = f
        res = _ratio_rows(fns, p, reps)
        for it, (t_f, t_r, t_j) in res.items():
            out.append((method, it, t_f, t_r, t_j))
            print(f"| {method} | {it} | {nt} | {t_f * 1e3:.1f} | {t_r * 1e3:.1f} | {t_r / t_f:.2f} | {t_j * 1e3:.1f} | {t_j / t_f:.2f} |")
    return out


def bench_model_gradients(n, n_iter, reps, static_n=()):
    """springs_volume model (hexahedral cells, cubic springs), float64: the unrolled XPBD
    gradient and the static solve's implicit gradient w.r.t. (E, nu)."""
    import jax
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.materials import Material
    from difftissue.mesh import block
    from difftissue.models import make_model
    from difftissue.solvers import solve_static
    from difftissue.solvers.xpbd import XPBDSettings, xpbd_simulate

    def problem(m):
        mesh = block(0.01, m)
        model = make_model(mesh, "springs_volume")
        top = jnp.asarray(mesh.points[:, 2] == mesh.points[:, 2].max())
        bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-3))
        return mesh, model, top, bc

    mesh, model, top, bc = problem(n)
    settings = {m: XPBDSettings(dt=1e-2, substeps=1, iterations=n_iter, method=m) for m in ("jacobi", "gauss_seidel")}

    def xpbd_out(method):
        def f(p):
            st = xpbd_simulate(model, Material(p[0], p[1]), bc, settings=settings[method], steps=1)
            return jnp.sum(st.positions[:, 0] ** 2)

        return f

    def static_out(model, top, bc, linear_solver):
        def f(p):
            sol = solve_static(model, Material(p[0], p[1]), bc, linear_solver=linear_solver)
            return jnp.sum(sol.reaction[:, 2] * top)

        return f

    p = jnp.array([5e3, 0.45])
    fns = {f"XPBD unrolled, {n_iter} iterations, jacobi": xpbd_out("jacobi"), f"XPBD unrolled, {n_iter} iterations, gauss_seidel": xpbd_out("gauss_seidel")}
    dofs = {}
    for m, ls in [(n, "dense")] + [(k, "cg") for k in static_n]:
        _, mdl, tp, b = problem(m)
        name = f"static solve, {ls} ({3 * mdl.n_nodes} DOF)"
        fns[name] = static_out(mdl, tp, b, ls)
        dofs[name] = 3 * mdl.n_nodes
    res = _ratio_rows(fns, p, reps)
    print(f"\n## Gradient cost, springs_volume model (block of {n}^3 cells for XPBD), float64, 2 parameters E and nu ({_load()})\n")
    print("| computation | forward [ms] | reverse grad [ms] | grad / forward | (grad - forward) / forward | jacfwd [ms] | jacfwd / forward |")
    print("|---|---|---|---|---|---|---|")
    for name, (f, r, j) in res.items():
        print(f"| {name} | {f * 1e3:.1f} | {r * 1e3:.1f} | {r / f:.2f} | {(r - f) / f:.2f} | {j * 1e3:.1f} | {j / f:.2f} |")
    print(
        "\n(For the static solve, 'forward' is the Newton solve and the gradient is forward + one adjoint linear solve;"
        " '(grad - forward) / forward' is the cost of the implicit gradient itself relative to the solve.)"
    )
    return res


def _temp_mib(f, p):
    import jax

    compiled = jax.jit(jax.grad(f)).lower(p).compile()
    return compiled.memory_analysis().temp_size_in_bytes / 2**20


def bench_memory_peer(n=8, n_iter=100):
    print(f"\n## XLA temporary memory of a {n_iter}-iteration unrolled reverse-mode gradient (peerbench workload n = {n}, float32, Jacobi)\n")
    print("| checkpointing | XLA temp buffers [MiB] |")
    print("|---|---|")
    for ckpt in (True, False):
        f, nt, p = _peer_objective(n, n_iter, "jacobi", checkpoint=ckpt)
        print(f"| {'on' if ckpt else 'off'} | {_temp_mib(f, p):.1f} |")


def bench_memory(n=8, n_iter=100):
    import jax.numpy as jnp

    from difftissue.boundary import BoundaryConditions
    from difftissue.materials import Material
    from difftissue.mesh import block
    from difftissue.models import make_model
    from difftissue.solvers.xpbd import XPBDSettings, xpbd_simulate

    mesh = block(0.01, n)
    model = make_model(mesh, "springs_volume")
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-3))
    print(f"\n## XLA temporary memory of a {n_iter}-iteration unrolled reverse-mode gradient (springs_volume, {n}^3 cells, float64, Jacobi)\n")
    print("| checkpointing | XLA temp buffers [MiB] |")
    print("|---|---|")
    for ckpt in (True, False):
        settings = XPBDSettings(dt=1e-2, substeps=1, iterations=n_iter, method="jacobi", checkpoint=ckpt)

        def f(p):
            st = xpbd_simulate(model, Material(p[0], p[1]), bc, settings=settings, steps=1)
            return jnp.sum(st.positions[:, 0] ** 2)

        print(f"| {'on' if ckpt else 'off'} | {_temp_mib(f, jnp.array([5e3, 0.45])):.1f} |")


YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def bench_flag(sizes, reps):
    """Jacobi ns per tet-iteration with and without the YNN flag, in alternating child processes."""
    import subprocess

    base = os.environ.get("XLA_FLAGS", "")
    res = {False: {n: [] for n in sizes}, True: {n: [] for n in sizes}}
    for _ in range(reps):
        for flag in (False, True):
            env = dict(os.environ, XLA_FLAGS=(base + " " + YNN_FLAG).strip() if flag else base)
            cmd = [sys.executable, __file__, "--sizes", ",".join(map(str, sizes)), "--reps", "3", "--methods", "jacobi", "--_child"]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
            for line in out.splitlines():
                if line.startswith("CHILD"):
                    _, n, v = line.split()
                    res[flag][int(n)].append(float(v))
    print(f"\n## XLA flag `{YNN_FLAG}` (Jacobi, median ns / tet-iteration over {reps} alternating processes; {_load()})\n")
    print("| n | default flags | with the flag | default / flag |")
    print("|---|---|---|---|")
    for n in sizes:
        a, b = statistics.median(res[False][n]), statistics.median(res[True][n])
        print(f"| {n} | {a:.1f} | {b:.1f} | {a / b:.2f} |")


def _child(sizes):
    for n in sizes:
        mesh, X, x0, tets, edges, fixed = _workload(n)
        f = _ours(mesh, X, x0, tets, edges, fixed, "jacobi")
        r10, r40 = f(10), f(40)
        s = []
        for _ in range(5):
            t10 = r10()
            s.append((r40() - t10) / 30 / len(tets) * 1e9)
        print("CHILD", n, statistics.median(s))


def _sizes(text):
    return [int(v) for v in text.replace(",", " ").split()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=str, nargs="+", default=["8,12,18,24"], help="n values, e.g. 8,12,18,24 or 8 12")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--methods", nargs="+", default=["jacobi", "gauss_seidel"])
    ap.add_argument("--quick", action="store_true", help="smoke run: n = 8, 3 repetitions, small gradient problems, no flag check")
    ap.add_argument("--skip", nargs="*", default=[], choices=["xpbd", "unrolled", "gradients", "memory", "flag"])
    ap.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    sizes = _sizes(" ".join(args.sizes))
    if args.quick:
        sizes, args.reps = [8], 3
    import jax

    if args._child:
        _child(sizes)
        return
    import platform

    print(
        f"jax {jax.__version__}, jaxlib {jax.lib.__version__ if hasattr(jax.lib, '__version__') else '?'}, python {sys.version.split()[0]}, "
        f"numpy {np.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, affinity {sorted(os.sched_getaffinity(0))}"
    )
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}; {_load()}", flush=True)
    skip = set(args.skip)
    if "xpbd" not in skip:
        bench_xpbd(sizes, args.reps, args.methods)
    if "unrolled" not in skip:
        bench_unrolled(8 if not args.quick else 6, (30,) if args.quick else (30, 100), args.reps)
    if "memory" not in skip:
        bench_memory_peer()
    if "flag" not in skip and not args.quick:
        bench_flag([8, 18], 3)
    jax.config.update("jax_enable_x64", True)
    if "gradients" not in skip:
        bench_model_gradients(6, 30, 3 if args.quick else 5, static_n=() if args.quick else (10,))
    if "memory" not in skip:
        bench_memory()
    print(f"\n(end: {_load()})")


if __name__ == "__main__":
    main()
