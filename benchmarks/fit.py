"""Benchmark: fit E and nu to a 20-point force-depth curve on a ~5k-tet specimen (issue 4).


Run by hand (not in CI)::

    python benchmarks/fit.py            # default: springs_volume and fem_linear, ~5k tets

Synthetic data: the simulated spherical indentation (R = 1 mm, depths 0.01-0.2 mm) of a
bonded 4 x 4 x 1.6 mm block (quarter model, 4,800 tets, 0.2 mm cubes) at a known material, 20
depths. The fit starts from E x 1.6, nu = 0.3 and runs Levenberg-Marquardt on E and nu (a
single curve on a finite-thickness layer determines nu only weakly: expect an identifiability
warning or a large standard error). Printed per model: one forward protocol solve (first call
with compilation, then a second call), the whole fit run twice in the same process -- cold
(compilation included) and warm (the same fit again: the compiled programs are reused) --
with wall time, the process's CPU time (user + system, both cores; a load-independent
measure on a shared machine) and the XLA backend compile time (jax.monitoring), and the
load average around each fit.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jax.monitoring  # noqa: E402

from difftissue.fit import fit  # noqa: E402
from difftissue.materials import Material, MaterialParameterization, ScaledLogit  # noqa: E402
from difftissue.scenarios import Indentation, SolverOptions, indentation_block  # noqa: E402


def run(model: str, cells, points: int, max_steps: int, solver: str = "auto", fit_too: bool = True, linear_solver: str = "auto", separate: bool = False) -> dict:
    R, H = 1e-3, 1.6e-3
    mesh = indentation_block((4e-3, 4e-3, H), cells, symmetry="quarter")
    truth = Material(12e3, 0.42)
    depths = np.linspace(0.01, 0.2, points) * 1e-3
    make = lambda forces=None: Indentation(mesh, depths, forces, model=model, indenter="sphere", radius=R, symmetry="quarter", name="sphere", options=SolverOptions(failure="nan", linear_solver=linear_solver), solver=solver)  # noqa: E731
    probe = make()
    t0 = time.perf_counter()
    data = np.asarray(probe.predict(truth))
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    np.asarray(probe.predict(Material(10e3, 0.4)))
    t_forward = time.perf_counter() - t0
    if not fit_too:
        return dict(model=model, solver=solver, tets=mesh.n_tets, nodes=mesh.n_nodes, first_forward_s=t_first, forward_s=t_forward)
    sc = make(data)
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.25 if model == "springs_volume" else 0.0, 0.499)})
    if separate:  # the command line's path: the scenario compiled once, on its own (difftissue.config.SeparatelyCompiled)
        from difftissue.config import SeparatelyCompiled

        sc = SeparatelyCompiled(sc, fields=param.fields)
    timed = []
    for _ in range(2):  # cold (compiles), then warm (the same fit again)
        load0 = os.getloadavg()[0]
        with _compile_seconds() as compile_s, warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0, c0 = time.perf_counter(), time.process_time()
            res = fit([sc], param, Material(1.6 * 12e3, 0.3), max_steps=max_steps)
            t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
        timed.append(dict(wall_s=t_fit, cpu_s=c_fit, compile_s=compile_s[0], load=(load0, os.getloadavg()[0])))
    return dict(
        cold=timed[0],
        warm=timed[1],
        model=model,
        solver=("condensed" if probe.condensation is not None else "full") + f" ({linear_solver})" + (", separately compiled" if separate else ""),
        tets=mesh.n_tets,
        nodes=mesh.n_nodes,
        first_forward_s=t_first,
        forward_s=t_forward,
        steps=int(res.steps),
        E=float(res.values["youngs_modulus"]),
        nu=float(res.values["poisson_ratio"]),
        se_E=float(res.standard_errors["youngs_modulus"]),
        se_nu=float(res.standard_errors["poisson_ratio"]),
        converged=bool(res.converged),
        warnings=len(caught),
    )


@contextlib.contextmanager
def _compile_seconds():
    """Sum of XLA backend compile durations [s] while the block runs (``out[0]``)."""
    out = [0.0]

    def listener(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            out[0] += duration

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield out
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="springs_volume,fem_linear", help="models fitted (solver 'auto': fem_linear is condensed)")
    ap.add_argument("--cells", default="10,10,8", help="nx,ny,nz of the quarter block (10,10,8 -> 4,800 tets, 0.2 mm cubes)")
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--linear-solvers", default="auto", help="linear solvers of the static solves, comma-separated (auto, multigrid, sparse, dense)")
    ap.add_argument("--forward-only", action="store_true", help="time the forward protocol solves only")
    ap.add_argument("--separate", action="store_true", help="fit through SeparatelyCompiled, as the command line does (one compiled program for the prediction and its tangents)")
    ap.add_argument("--baseline", default="fem_linear", help="models whose full (uncondensed) forward solve is timed as the baseline ('' for none)")
    args = ap.parse_args()
    cells = tuple(int(c) for c in args.cells.split(","))
    print(f"# fit benchmark: jax {jax.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    print()
    print("| model | solver | tets | first forward (s, incl. compile) | forward (s) | fit cold: wall (s) / CPU (s) / XLA compile (s) / load | fit warm: wall (s) / CPU (s) / load | steps | warm fit / forward | E (truth 12000 Pa) | nu (truth 0.42) | converged |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for model in [m for m in args.baseline.split(",") if m]:
        r = run(model, cells, args.points, args.max_steps, solver="full", fit_too=False)
        print(f"| {r['model']} | full (baseline) | {r['tets']} | {r['first_forward_s']:.1f} | {r['forward_s']:.2f} | - | - | - | - | - | - | - |")
    for model, ls in [(m, ls) for m in args.models.split(",") if m for ls in args.linear_solvers.split(",")]:
        r = run(model, cells, args.points, args.max_steps, fit_too=not args.forward_only, linear_solver=ls, separate=args.separate)
        if args.forward_only:
            print(f"| {r['model']} | {ls} | {r['tets']} | {r['first_forward_s']:.1f} | {r['forward_s']:.2f} | - | - | - | - | - | - | - |", flush=True)
            continue
        c, w = r["cold"], r["warm"]
        print(
            f"| {r['model']} | {r['solver']} | {r['tets']} | {r['first_forward_s']:.1f} | {r['forward_s']:.2f} | "
            f"{c['wall_s']:.1f} / {c['cpu_s']:.1f} / {c['compile_s']:.1f} / {c['load'][0]:.1f}-{c['load'][1]:.1f} | "
            f"{w['wall_s']:.1f} / {w['cpu_s']:.1f} / {w['load'][0]:.1f}-{w['load'][1]:.1f} | {r['steps']} | "
            f"{w['wall_s'] / r['forward_s']:.1f} | {r['E']:.1f} ± {r['se_E']:.2g} | {r['nu']:.4f} ± {r['se_nu']:.2g} | {r['converged']} |",
            flush=True,
        )
    print(f"\nload after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
