"""Static-solve scaling benchmark: a bonded block under a bonded flat punch, nu = 0.45.

For each size (one child process per size and solver, so that peak memory is the solver's
own) it measures, in float64:

- ``multigrid`` (difftissue): cold solve (mesh pattern, PyAMG hierarchy, compilation and the
  solve), warm solve (the compiled program again, new E), and the implicit gradient
  ``d F / d (E, nu)`` of the punch force by reverse mode (``value_and_grad`` minus a forward),
  compiled inside ``jit`` with the mesh closed over (as the scenarios do: XLA embeds the
  arrays as constants); ``multigrid-direct``: the same with ``solve_static`` called as a
  function (its arrays are arguments of its own program); ``multigrid-scenario``: the same
  punch as an :class:`~difftissue.scenarios.Indentation` (bonded flat punch of radius
  0.2 L, one depth), ``predict`` cold and warm (the scenario compiles its protocol with
  the mesh and the solver setup as arguments), no gradient;
- ``sparse`` (difftissue's sparse direct path: CHOLMOD through cholespy), ``superlu`` (the
  previous default above 3,000 unknowns: SciPy's SuperLU through the same host callback) and
  ``dense`` (Cholesky), where they fit;
- ``pyamg``: PyAMG's own solver on the same matrix: the same smoothed-aggregation hierarchy
  (``smoothed_aggregation_solver`` with the rigid-body modes, 3x3 blocks), PyAMG's default
  block Gauss-Seidel smoothing and CG acceleration, the same relative residual 1e-10 —
  the alternative a user would write with SciPy;
- ``skfem``: scikit-fem assembly of the same linear tets plus that PyAMG solve (fem_linear
  only): a user's complete alternative.

Times are wall seconds (the machine's 2 cores; JAX uses both, SciPy/PyAMG one) and process
CPU seconds; peak memory is the child's maximum resident set. Every solver's punch force is
printed, and the relative difference to the multigrid force.

    python benchmarks/static.py --sizes 8,12,16,20 --models fem_linear,springs_volume
    python benchmarks/static.py --sizes 26,32,40 --solvers multigrid,pyamg   # large, minutes
    python benchmarks/static.py --quick                                      # smoke run

Results go to ``benchmarks/results/static.{json,md,png}`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
RTOL = 1e-10
DEPTH = 1e-4  # punch displacement [m]


def _problem(n, kind):
    import jax.numpy as jnp
    import numpy as np

    from difftissue.boundary import BoundaryConditions
    from difftissue.materials import Material
    from difftissue.mesh import block
    from difftissue.models import make_model

    L, H = 0.02, 0.01
    mesh = block((L, L, H), (2 * n, 2 * n, n))
    model = make_model(mesh, kind)
    X = np.asarray(mesh.points)
    fixed = np.zeros(X.shape, bool)
    fixed[np.isclose(X[:, 2], 0.0)] = True
    top = np.isclose(X[:, 2], H) & (np.hypot(X[:, 0] - L / 2, X[:, 1] - L / 2) <= 0.2 * L + 1e-12)
    fixed[top] = True
    disp = np.zeros(X.shape)
    disp[top, 2] = -DEPTH
    bc = BoundaryConditions(fixed, jnp.asarray(disp), jnp.zeros(X.shape))
    return mesh, model, bc, np.flatnonzero(top), Material(1e4, 0.45)


def _child(args):
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from difftissue.materials import Material
    from difftissue.solvers import solve_static

    n, kind, solver = args.size, args.model, args.solver
    mesh, model, bc, top, material = _problem(n, kind)
    out = {"size": n, "model": kind, "solver": solver, "unknowns": 3 * mesh.n_nodes, "elements": int(mesh.tets.shape[0]),
           "backend": jax.default_backend(), "device": jax.devices()[0].device_kind}

    def clock():
        return time.perf_counter(), time.process_time()

    def since(t):
        return time.perf_counter() - t[0], time.process_time() - t[1]

    if solver == "multigrid-scenario":
        from difftissue.scenarios import Indentation, SolverOptions

        t = clock()
        L = 0.02
        sc = Indentation(mesh, [DEPTH], indenter="flat_punch", radius=0.2 * L, bonded_punch=True, base="bonded", model=kind,
                         options=SolverOptions(rtol=RTOL, linear_solver="multigrid"))
        out["build_wall"], out["build_cpu"] = since(t)
        t = clock()
        out["force"] = float(sc.predict(Material(1e4, 0.45))[0])
        out["cold_wall"], out["cold_cpu"] = since(t)
        t = clock()
        float(sc.predict(Material(2e4, 0.45))[0])
        out["warm_wall"], out["warm_cpu"] = since(t)
    elif solver in ("multigrid", "multigrid-direct", "sparse", "dense", "superlu"):
        linear = {"superlu": "sparse", "multigrid-direct": "multigrid"}.get(solver, solver)
        if solver == "superlu":
            import difftissue.solvers.sparse as sp

            sp._cholesky_solve = lambda *a: None  # benchmark only: force the LU branch

        def force(E, nu):
            sol = solve_static(model, Material(E, nu), bc, linear_solver=linear, rtol=RTOL, cg_rtol=RTOL)
            return jnp.sum(sol.reaction[top, 2]), (sol.steps, sol.linear_steps)

        # As in a fit: the solve is compiled once (inside jit, the mesh closed over), then called
        # with new materials. "multigrid-direct": solve_static called as a function (its arrays
        # are arguments of its own compiled program, not constants of an enclosing one).
        f = force if solver == "multigrid-direct" else jax.jit(force)
        t = clock()
        F, (steps, cg) = f(1e4, 0.45)
        F = float(F)
        out["cold_wall"], out["cold_cpu"] = since(t)
        out["newton_steps"], out["cg_iterations"] = int(steps), int(cg)
        print("COLD " + json.dumps(out), file=sys.stderr, flush=True)  # progress: what a long run has measured so far
        t = clock()
        F2 = float(f(2e4, 0.45)[0])
        out["warm_wall"], out["warm_cpu"] = since(t)
        out["force"] = F
        if kind == "fem_linear" and abs(F2 - 2 * F) > 1e-6 * abs(F):
            raise SystemExit(f"force not linear in E: {F2} vs 2 x {F}")
        if args.gradient:
            vg = jax.value_and_grad(lambda E, nu: force(E, nu)[0], argnums=(0, 1))
            vg = vg if solver == "multigrid-direct" else jax.jit(vg)
            jax.block_until_ready(vg(1e4, 0.45))  # compile
            t = clock()
            _, g = vg(1.5e4, 0.45)
            jax.block_until_ready(g)
            w, c = since(t)
            out["value_and_grad_wall"], out["value_and_grad_cpu"] = w, c
            out["dF_dE"], out["dF_dnu"] = float(g[0]), float(g[1])
    elif solver in ("pyamg", "skfem"):
        import pyamg
        import scipy.sparse as sps

        from difftissue.solvers.multigrid import rigid_body_modes

        free = ~np.asarray(bc.fixed).reshape(-1)
        u_fixed = np.asarray(bc.displacement).reshape(-1) * ~free
        t = clock()
        if solver == "skfem":
            import skfem
            from skfem.models.elasticity import lame_parameters, linear_elasticity

            if kind != "fem_linear":
                raise SystemExit("skfem baseline: fem_linear only")
            m = skfem.MeshTet(np.asarray(mesh.points).T.copy(), np.asarray(mesh.tets).T.copy())
            basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
            K = linear_elasticity(*lame_parameters(1e4, 0.45)).assemble(basis)
            perm = basis.nodal_dofs.T.reshape(-1)  # skfem's DOF numbers in difftissue's order (x0, y0, z0, x1, ...)
            K = K[perm][:, perm]
        else:
            import difftissue.solvers.static as st
            from difftissue.solvers.sparse import assemble_csr_data, sparse_pattern

            data = st._element_data(model, jnp.asarray(model.rest_points), material)
            pat = sparse_pattern([t_.nodes for t_ in model.terms(material)], model.n_nodes)
            # P = 1 everywhere: the plain stiffness K (the pattern's diagonal term 1 - P is 0)
            K = sps.csr_matrix((np.asarray(assemble_csr_data(pat, data, jnp.ones(pat.n))), pat.indices, pat.indptr), shape=(pat.n, pat.n))
        K = sps.csr_matrix(K)
        # the same projected system as difftissue: P K P + (I - P), right-hand side -P K u_fixed
        P = free.astype(float)
        A = sps.diags(P) @ K @ sps.diags(P) + sps.diags(1 - P)
        b = -P * (K @ u_fixed)
        out["assembly_wall"], out["assembly_cpu"] = since(t)
        t = clock()
        B = rigid_body_modes(np.asarray(mesh.points)) * P[:, None]
        ml = pyamg.smoothed_aggregation_solver(sps.bsr_matrix(A, blocksize=(3, 3)), B=B, max_coarse=60)
        out["setup_wall"], out["setup_cpu"] = since(t)
        res = []
        t = clock()
        x = ml.solve(b, tol=RTOL, accel="cg", maxiter=500, residuals=res)
        out["solve_wall"], out["solve_cpu"] = since(t)
        out["cg_iterations"] = len(res) - 1
        out["levels"] = len(ml.levels)
        out["force"] = float(np.sum((K @ (x + u_fixed)).reshape(-1, 3)[top, 2]))
        out["cold_wall"] = out["assembly_wall"] + out["setup_wall"] + out["solve_wall"]
        out["cold_cpu"] = out["assembly_cpu"] + out["setup_cpu"] + out["solve_cpu"]
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    stats = jax.devices()[0].memory_stats()  # None on the CPU backend
    if stats and "peak_bytes_in_use" in stats:
        out["device_peak_gb"] = stats["peak_bytes_in_use"] / 1e9
    print("RESULT " + json.dumps(out), flush=True)


def _run(size, model, solver, gradient, timeout):
    cmd = [sys.executable, __file__, "--child", "--size", str(size), "--model", model, "--solver", solver]
    if gradient:
        cmd.append("--gradient")
    t = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        return {"size": size, "model": model, "solver": solver, "error": f"timeout after {timeout} s", **_partial(e.stderr)}
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
    return {"size": size, "model": model, "solver": solver, "error": " | ".join(tail)[-300:], "wall": time.perf_counter() - t, **_partial(p.stderr)}


def _partial(stderr):
    """The cold-solve figures a child printed before it failed or timed out (``{"partial": ...}``)."""
    if isinstance(stderr, bytes):
        stderr = stderr.decode(errors="replace")
    for line in (stderr or "").splitlines():
        if line.startswith("COLD "):
            return {"partial": json.loads(line[5:])}
    return {}


def _table(rows):
    lines = [
        "| model | unknowns | solver | backend | cold wall [s] | warm wall [s] | CPU cold [s] | CG its | grad/forward | peak RSS [GB] | device peak [GB] | force rel. diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ref = {}  # the force of difftissue's multigrid solve (closure or direct) of the same size
    for solver in ("multigrid-direct", "multigrid"):
        ref.update({(r["model"], r["size"]): r["force"] for r in rows if r.get("solver") == solver and "force" in r})
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['model']} | size {r['size']} | {r['solver']} | | {r['error']} | | | | | | | |")
            continue
        warm = r.get("warm_wall", r.get("solve_wall"))
        ratio = ""
        if "value_and_grad_wall" in r:
            ratio = f"{(r['value_and_grad_wall'] - r['warm_wall']) / r['warm_wall']:.2f}"
        f0 = ref.get((r["model"], r["size"]))
        diff = f"{abs(r['force'] - f0) / abs(f0):.1e}" if f0 else ""
        backend = r.get("backend", "cpu") if r["solver"].startswith(("multigrid", "sparse", "dense", "superlu")) else "cpu (SciPy)"
        device_peak = f"{r['device_peak_gb']:.2f}" if "device_peak_gb" in r else ""
        lines.append(
            f"| {r['model']} | {r['unknowns']:,} | {r['solver']} | {backend} | {r['cold_wall']:.2f} | {warm:.2f} | {r['cold_cpu']:.2f} | {r.get('cg_iterations', '')} | {ratio}"
            f" | {r['peak_rss_gb']:.2f} | {device_peak} | {diff} |"
        )
    return "\n".join(lines)


def _plot(rows, path):
    """Log-log CPU time against unknowns: our warm solve, PyAMG's own solve (same hierarchy
    kind and tolerance), scikit-fem assembly + PyAMG, and the direct solvers."""
    import matplotlib.pyplot as plt
    import numpy as np

    def cpu(r):
        if r["solver"] in ("pyamg",):
            return r["solve_cpu"]
        if r["solver"] == "skfem":
            return r["cold_cpu"]
        return r["warm_cpu"]

    labels = {
        "multigrid": "difftissue multigrid (solve compiled in a closure, as in fits)",
        "multigrid-direct": "difftissue multigrid (solve_static called directly)",
        "multigrid-scenario": "difftissue multigrid (Indentation.predict)",
        "pyamg": "PyAMG's own solver (solve)",
        "skfem": "scikit-fem assembly + PyAMG setup + solve",
        "sparse": "sparse Cholesky (cholespy)",
        "superlu": "SuperLU (the previous default)",
    }
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    for ax, model in zip(axes, ("fem_linear", "springs_volume")):
        for k, (solver, style) in enumerate((("multigrid", "o-"), ("multigrid-direct", "o-."), ("pyamg", "s--"), ("skfem", "^:"), ("sparse", "d-."), ("superlu", "x-."), ("multigrid-scenario", "v-"))):
            pts = sorted((r["unknowns"], cpu(r)) for r in rows if r["model"] == model and r["solver"] == solver and "error" not in r)
            if pts:
                x, y = np.array(pts).T
                ax.loglog(x, y, style, color=f"C{k}", label=labels[solver])
        xs = np.array([5e3, 1.2e6])
        ax.loglog(xs, 3e-5 * xs ** 1.0, "k:", lw=0.8, label="slope 1")
        ax.set_title(f"{model}: block under a flat punch, nu = 0.45")
        ax.set_xlabel("unknowns")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("process CPU time [s]")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int)
    ap.add_argument("--model", default="fem_linear")
    ap.add_argument("--solver", default="multigrid")
    ap.add_argument("--gradient", action="store_true")
    ap.add_argument("--sizes", default="8,12,16,20", help="block cells n (2n x 2n x n cubes, 6 tets each)")
    ap.add_argument("--models", default="fem_linear,springs_volume")
    ap.add_argument("--solvers", default="multigrid,pyamg,skfem,sparse,superlu")
    ap.add_argument("--direct-max", type=int, default=120_000, help="skip direct solvers above this many unknowns")
    ap.add_argument("--gradient-max", type=int, default=500_000, help="skip the multigrid gradient above this many unknowns")
    ap.add_argument("--timeout", type=int, default=1800)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "static"))
    args = ap.parse_args()
    if args.child:
        return _child(args)
    if args.quick:
        args.sizes, args.models, args.solvers = "6", "fem_linear", "multigrid,pyamg,sparse"
    rows = []
    if os.path.exists(args.out + ".json"):
        rows = [r for r in json.load(open(args.out + ".json"))]
    for n in [int(s) for s in args.sizes.split(",")]:
        for model in args.models.split(","):
            for solver in args.solvers.split(","):
                if solver == "skfem" and model != "fem_linear":
                    continue
                unknowns = 3 * (2 * n + 1) ** 2 * (n + 1)
                if solver in ("sparse", "superlu", "dense") and unknowns > args.direct_max:
                    continue
                gradient = solver in ("multigrid", "multigrid-direct") and unknowns <= args.gradient_max
                r = _run(n, model, solver, gradient, args.timeout)
                r["load"] = os.getloadavg()[0]
                print(json.dumps(r), flush=True)
                rows = [q for q in rows if (q["size"], q["model"], q["solver"]) != (n, model, solver)] + [r]
                json.dump(rows, open(args.out + ".json", "w"), indent=1)
    rows.sort(key=lambda r: (r["model"], r.get("unknowns", 0), r["solver"]))
    table = _table(rows)
    with open(args.out + ".md", "w") as f:
        f.write("# Static solve benchmark (benchmarks/static.py)\n\n" + table + "\n")
    _plot(rows, args.out + ".png")
    print(table)


if __name__ == "__main__":
    main()
