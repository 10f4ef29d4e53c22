"""Benchmark: many indentation fits -- a serial loop of fit calls vs fit_batch vs sharded (issue 7).

Run by hand (not in CI)::

    python benchmarks/batch.py                       # 16 specimens of 3,072 tets (~30-60 min on a loaded 2-core machine)
    python benchmarks/batch.py --quick               # smoke run: 4 specimens of 384 tets

Workload: a bonded 4 x 4 x 1.6 mm block, quarter model (``indentation_block``, 8 x 8 x 8 cells:
3,072 tets, 729 nodes), ``fem_linear`` (condensed penalty contact: one factorisation per
material) indented by a sphere of R = 1 mm at 8 depths from 0.02 to 0.2 mm. Every specimen has
its own true material (E uniform in 8-16 kPa, nu in 0.35-0.48, seeded), 1 % Gaussian noise
and its own start (1.4 E, nu = 0.3); Levenberg-Marquardt fits E and nu.

Each mode runs in its own child process (cold: it compiles what it needs, and its peak
resident memory ``ru_maxrss`` is its own):

- ``serial``: a Python loop of single ``fit`` calls, as a user writes it (the first call
  compiles; since this benchmark's change the others reuse that compilation);
- ``serial-spectral``: the same loop with each scenario switched to the spectral solver by
  hand (``scenario.spectral_variant(required=True)`` before its fit; the first call computes
  the mesh's eigendecomposition, inside the timed loop);
- ``serial-recompile``: the same loop with the engine cache cleared before each fit, i.e.
  how ``fit`` behaved before (one compilation per specimen); a few fits, extrapolated;
- ``batched``: one ``fit_batch`` call, then a second one on new data (warm: no compile); it
  picks the spectral solver itself (``spectral=None``, its default rule);
- ``batched-factorised``: the same with ``fit_batch(spectral=False)`` (a dense factorisation
  per specimen, step and tangent: fit_batch before the spectral solver);
- ``sharded``: ``fit_batch(devices=4)`` on 4 simulated CPU devices
  (``XLA_FLAGS=--xla_force_host_platform_device_count=4``) on the same 2 cores;
- ``scaling``: ``fit_batch`` on the first 1, 2, 4, 8 specimens (each size compiles; 16 is
  the ``batched`` run).

Printed: Markdown tables with the ratios against the serial loop of the same run, the load
average, and a PNG plot (``--plot``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
import warnings

HERE = os.path.dirname(os.path.abspath(__file__))


def _setup(args):
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from difftissue import Material
    from difftissue.materials import MaterialParameterization, ScaledLogit
    from difftissue.scenarios import Indentation, SolverOptions, indentation_block

    cells = tuple(int(c) for c in args.cells.split(","))
    mesh = indentation_block((4e-3, 4e-3, 1.6e-3), cells, symmetry="quarter")
    depths = np.linspace(0.02, 0.2, args.points) * 1e-3
    kw = dict(model=args.model, indenter="sphere", radius=1e-3, symmetry="quarter", options=SolverOptions(failure="nan"), name="sphere")
    probe = Indentation(mesh, depths, **kw)
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.499)})

    def specimens(n, seed):
        rng = np.random.default_rng(seed)
        out, starts, truths = [], [], []
        for _ in range(n):
            E, nu = 8e3 + 8e3 * rng.random(), 0.35 + 0.13 * rng.random()
            f = np.asarray(probe.predict(Material(E, nu)))  # one compiled forward for all
            noise = 0.01 * f.max()
            out.append(Indentation(mesh, depths, f + noise * rng.normal(size=f.size), sigma=noise, **kw))
            starts.append(Material(1.4 * E, 0.3))
            truths.append((E, nu))
        return out, starts, truths

    return mesh, param, specimens


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child(mode: str, args) -> dict:
    import numpy as np

    warnings.simplefilter("ignore")
    mesh, param, specimens = _setup(args)
    import jax

    from difftissue import fit as fitmod
    from difftissue.fit import engine as fit_engine
    from difftissue.fit import fit_batch

    B = args.specimens
    specs, starts, truths = specimens(B, seed=args.seed)
    load0 = os.getloadavg()[0]
    rss0 = _rss_mib()
    out: dict = {"mode": mode, "tets": mesh.n_tets, "nodes": mesh.n_nodes, "specimens": B, "devices": len(jax.devices()), "rss_before_mib": rss0}
    opts = dict(max_steps=args.max_steps)
    if mode in ("serial", "serial-recompile", "serial-spectral"):
        n = min(args.recompile_fits, B) if mode == "serial-recompile" else B
        times, cpus, steps, vals = [], [], [], []
        for sc, m0 in zip(specs[:n], starts[:n]):
            if mode == "serial-recompile":
                fit_engine._ENGINE_CACHE.clear()
            t, c = time.perf_counter(), time.process_time()
            if mode == "serial-spectral":
                sc = sc.spectral_variant(required=True)
            r = fitmod.fit(sc, param, m0, **opts)
            times.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
            steps.append(r.steps)
            vals.append([r.values["youngs_modulus"], r.values["poisson_ratio"], bool(r.converged)])
        out.update(times=times, cpus=cpus, total_s=float(sum(times)), total_cpu_s=float(sum(cpus)), steps=steps, values=vals)
    elif mode in ("batched", "sharded", "batched-factorised"):
        dev = args.devices if mode == "sharded" else None
        if mode == "batched-factorised":
            opts["spectral"] = False
        t, c = time.perf_counter(), time.process_time()
        r = fit_batch(specs, param, starts, devices=dev, **opts)
        out["cold_s"], out["cold_cpu_s"] = time.perf_counter() - t, time.process_time() - c
        out.update(compilations=r.compilations, batch_steps=r.batch_steps, steps=r.steps.tolist(), padding=r.padding,
                   values=[[v[0], v[1], bool(c)] for v, c in zip(r.values.tolist(), r.converged)], devices_used=list(r.devices))
        specs2, starts2, _ = specimens(B, seed=args.seed + 1)
        t, c = time.perf_counter(), time.process_time()
        r2 = fit_batch(specs2, param, starts2, devices=dev, **opts)
        out["warm_s"], out["warm_cpu_s"] = time.perf_counter() - t, time.process_time() - c
        out["warm_compilations"] = r2.compilations
        out["warm_batch_steps"] = r2.batch_steps
    elif mode == "scaling":
        rows = []
        for n in [int(x) for x in args.scaling.split(",") if int(x) < B]:  # n = B: the batched run
            t = time.perf_counter()
            r = fit_batch(specs[:n], param, starts[:n], **opts)
            cold = time.perf_counter() - t
            rows.append({"n": n, "cold_s": cold, "batch_steps": r.batch_steps, "rss_mib": _rss_mib()})
        out["rows"] = rows
    else:
        raise SystemExit(f"unknown mode {mode}")
    out["truths"] = truths
    out["rss_peak_mib"] = _rss_mib()
    ru = resource.getrusage(resource.RUSAGE_SELF)
    out["cpu_s"] = ru.ru_utime + ru.ru_stime
    out["load_start"], out["load_end"] = load0, os.getloadavg()[0]
    return out


def start_child(mode: str, argv: list[str], devices: int | None = None):
    env = dict(os.environ)
    if devices:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--child", mode, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    return proc, time.perf_counter()


def finish_child(mode: str, started) -> dict | None:
    proc, t = started
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        sys.stderr.write(stderr[-5000:])
        print(f"<!-- {mode}: FAILED (rc {proc.returncode}) -->", flush=True)
        return None
    line = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")][-1]
    res = json.loads(line[len("RESULT "):])
    res["process_s"] = time.perf_counter() - t
    print(f"<!-- {mode}: done in {res['process_s']:.0f} s (load {res['load_start']:.1f} -> {res['load_end']:.1f}) -->", flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--specimens", type=int, default=16)
    ap.add_argument("--cells", default="8,8,8", help="nx,ny,nz of the quarter block (8,8,8 -> 3,072 tets)")
    ap.add_argument("--points", type=int, default=8, help="depths per curve")
    ap.add_argument("--model", default="fem_linear")
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--devices", type=int, default=4, help="simulated CPU devices of the sharded run")
    ap.add_argument("--scaling", default="1,2,4,8,16", help="batch sizes of the scaling run ('' to skip)")
    ap.add_argument("--recompile-fits", type=int, default=2, help="fits of the serial-recompile run (extrapolated to all specimens)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip", default="", help="comma-separated modes to skip (serial-recompile, sharded, scaling)")
    ap.add_argument("--plot", default=None, help="PNG path of the plot (wall time vs number of specimens)")
    ap.add_argument("--json", default=None, help="also write the raw results to this JSON file")
    ap.add_argument("--quick", action="store_true", help="smoke run: 4 specimens, 4 x 4 x 4 cells, scaling 1,2,4")
    ap.add_argument("--parallel", action="store_true", help="run the modes' child processes at the same time (on a machine shared with other "
                    "work all modes then see the same load; wall times include the contention between them)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.quick:
        args.specimens, args.cells, args.scaling, args.points = 4, "4,4,4", "1,2,4", 6
    if args.child:
        print("RESULT " + json.dumps(child(args.child, args)), flush=True)
        return
    argv = ["--specimens", str(args.specimens), "--cells", args.cells, "--points", str(args.points), "--model", args.model,
            "--max-steps", str(args.max_steps), "--devices", str(args.devices), "--scaling", args.scaling,
            "--recompile-fits", str(args.recompile_fits), "--seed", str(args.seed)]
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    import jax
    import numpy as np

    print(f"# fit_batch benchmark ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})\n")
    print(f"- {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, jax {jax.__version__}; "
          f"load average at the start {os.getloadavg()[0]:.1f} (other processes share the cores)")
    res = {}
    modes = [m for m in ("serial", "serial-spectral", "serial-recompile", "batched", "batched-factorised", "sharded", "scaling")
             if m not in skip and not (m == "scaling" and not args.scaling)]
    if args.parallel:
        print(f"- the modes {', '.join(modes)} ran as concurrent child processes")
    running = {}
    for mode in modes:
        running[mode] = start_child(mode, argv, devices=args.devices if mode == "sharded" else None)
        if not args.parallel:
            out = finish_child(mode, running.pop(mode))
            if out is not None:
                res[mode] = out
    for mode, started in running.items():
        out = finish_child(mode, started)
        if out is not None:
            res[mode] = out
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    s = res["serial"]
    B = s["specimens"]
    print(f"- specimens: {B} x {s['tets']} tets ({s['nodes']} nodes), {args.model}, sphere R = 1 mm, {args.points} depths, "
          f"E and nu by Levenberg-Marquardt (max {args.max_steps} steps)\n")
    serial_total = s["total_s"]
    warm_serial = float(np.mean(s["times"][1:])) if B > 1 else s["times"][0]
    print("## 16-specimen batch: wall time (each mode in its own cold process)\n" if B == 16 else f"## {B}-specimen batch\n")
    print("| mode | wall [s] | per specimen [s] | speed-up vs serial loop (wall) | CPU [s] | speed-up (CPU) | steps | peak RSS [MiB] | load avg (start-end) |")
    print("|---|---|---|---|---|---|---|---|---|")
    serial_cpu = s["total_cpu_s"]
    print(f"| serial loop of `fit` (first call compiles) | {serial_total:.1f} | {serial_total / B:.2f} | 1.00 | {serial_cpu:.1f} | 1.00 | {sum(s['steps'])} total | {s['rss_peak_mib']:.0f} | {s['load_start']:.1f}-{s['load_end']:.1f} |")
    if "serial-spectral" in res:
        r = res["serial-spectral"]
        print(f"| serial loop of `fit`, spectral solver by hand (`spectral_variant`, first fit decomposes) | {r['total_s']:.1f} | {r['total_s'] / B:.2f} | {serial_total / r['total_s']:.2f} | "
              f"{r['total_cpu_s']:.1f} | {serial_cpu / r['total_cpu_s']:.2f} | {sum(r['steps'])} total | {r['rss_peak_mib']:.0f} | {r['load_start']:.1f}-{r['load_end']:.1f} |")
    if "serial-recompile" in res:
        r = res["serial-recompile"]
        per = float(np.mean(r["times"]))
        cper = float(np.mean(r["cpus"]))
        print(f"| serial loop, recompiling per fit (before this change; {len(r['times'])} fits, extrapolated) | {per * B:.1f} (est.) | {per:.2f} | {serial_total / (per * B):.2f} | {cper * B:.1f} (est.) | {serial_cpu / (cper * B):.2f} | - | {r['rss_peak_mib']:.0f} | {r['load_start']:.1f}-{r['load_end']:.1f} |")
    for mode, name in (("batched", "`fit_batch` (spectral, compiles)"), ("batched-factorised", "`fit_batch(spectral=False)` (compiles)"), ("sharded", f"`fit_batch(devices={args.devices})`, {args.devices} simulated CPU devices (compiles)")):
        if mode in res:
            r = res[mode]
            print(f"| {name} | {r['cold_s']:.1f} | {r['cold_s'] / B:.2f} | **{serial_total / r['cold_s']:.2f}** | {r['cold_cpu_s']:.1f} | {serial_cpu / r['cold_cpu_s']:.2f} | {r['batch_steps']} batched | {r['rss_peak_mib']:.0f} | {r['load_start']:.1f}-{r['load_end']:.1f} |")
            print(f"| {name.replace('(compiles)', '')}, second batch (compiled) | {r['warm_s']:.1f} | {r['warm_s'] / B:.2f} | {serial_total / r['warm_s']:.2f} | {r['warm_cpu_s']:.1f} | {serial_cpu / r['warm_cpu_s']:.2f} | {r['warm_batch_steps']} batched | | |")
    print(f"\nWarm (compiled) serial fit: {warm_serial:.2f} s per specimen (CPU {float(np.mean(s['cpus'][1:])) if B > 1 else s['cpus'][0]:.2f} s); first serial fit (with compilation) {s['times'][0]:.1f} s (CPU {s['cpus'][0]:.1f} s).")
    if "batched" in res:
        r = res["batched"]
        print(f"Warm vs warm: batched {r['warm_s'] / B:.2f} s per specimen vs serial {warm_serial:.2f} s: {warm_serial * B / r['warm_s']:.2f}x.")
        diffs = [abs(a[0] - b[0]) / b[0] for a, b in zip(r["values"], s["values"])]
        print(f"Largest relative difference of E between batched and serial: {max(diffs):.2e}; converged: batched {sum(v[2] for v in r['values'])}/{B}, serial {sum(v[2] for v in s['values'])}/{B}.")
    for mode in ("serial-spectral", "batched-factorised"):
        if mode in res:
            r = res[mode]
            diffs = [abs(a[0] - b[0]) / b[0] for a, b in zip(r["values"], s["values"])]
            dnu = [abs(a[1] - b[1]) for a, b in zip(r["values"], s["values"])]
            print(f"{mode}: largest relative difference of E vs serial {max(diffs):.2e}, of nu {max(dnu):.2e}; converged {sum(v[2] for v in r['values'])}/{B}.")
    if "batched" in res:
        r = res["batched"]
        dnu = [abs(a[1] - b[1]) for a, b in zip(r["values"], s["values"])]
        print(f"batched: largest difference of nu vs serial {max(dnu):.2e}.")
    if "sharded" in res:
        r = res["sharded"]
        diffs = [abs(a[0] - b[0]) / b[0] for a, b in zip(r["values"], s["values"])]
        print(f"Sharded: devices {', '.join(r['devices_used'])}, padding {r['padding']}; largest relative difference of E vs serial {max(diffs):.2e}.")
    if "scaling" in res or "batched" in res:
        rows = list(res.get("scaling", {}).get("rows", []))
        if "batched" in res:
            r = res["batched"]
            rows.append({"n": B, "cold_s": r["cold_s"], "batch_steps": r["batch_steps"], "rss_mib": r["rss_peak_mib"]})
        print("\n## Wall time vs number of specimens (batched, including compilation; serial = the serial run's first n fits)\n")
        print("| specimens | batched [s] | serial loop [s] | speed-up | batched steps | peak RSS of the process [MiB] |")
        print("|---|---|---|---|---|---|")
        for row in rows:
            n = row["n"]
            ser = float(sum(s["times"][:n]))
            print(f"| {n} | {row['cold_s']:.1f} | {ser:.1f} | {ser / row['cold_s']:.2f} | {row['batch_steps']} | {row['rss_mib']:.0f} |")
    print(f"\nLoad average at the end {os.getloadavg()[0]:.1f}.")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    if args.plot and "batched" in res:
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure

        n = np.array([r["n"] for r in rows])
        fig = Figure(figsize=(6.0, 4.2), layout="constrained")
        ax = fig.subplots()
        ns = np.arange(1, B + 1)
        ax.plot(ns, np.cumsum(s["times"]), "o-", ms=3, color="0.4", label="serial loop of fit (first call compiles)")
        if "serial-recompile" in res:
            per = float(np.mean(res["serial-recompile"]["times"]))
            ax.plot(ns, per * ns, ":", color="C3", label="serial, recompiling per fit (before; extrapolated)")
        ax.plot(n, [r["cold_s"] for r in rows], "s-", color="C0", label="fit_batch (incl. compile)")
        ax.plot([B], [res["batched"]["warm_s"]], "s", color="C0", mfc="none", label="fit_batch, second batch (compiled)")
        if "sharded" in res:
            ax.plot([B], [res["sharded"]["cold_s"]], "D", color="C2", label=f"fit_batch, {args.devices} simulated devices (incl. compile)")
        ax.set_xlabel("number of specimens")
        ax.set_ylabel("wall time [s]")
        ax.set_title(f"{s['tets']}-tet indentation fits (E, nu), 2-core CPU")
        ax.legend(frameon=False, fontsize=8)
        fig.savefig(args.plot, dpi=110)
        print(f"\nPlot: {args.plot}")


if __name__ == "__main__":
    main()
