"""Experiment 4: spherical indentation of thin bonded layers: FEM vs Hertz, Dimitriadis, exact.

A rigid sphere (R = 1 mm) indents a layer of thickness h bonded to a rigid base to the depth
d = 0.01 R (so a = sqrt(R d) = 0.1 R and the sphere/paraboloid difference is negligible).
h is set from chi = sqrt(R d) / h in 0.1 .. 1. The layer is simulated with
:class:`difftissue.scenarios.Indentation` (fem_linear, frictionless penalty contact,
quarter symmetry, bonded base) on a structured quarter block of half-width 10 a + 2 h with a
uniform core (cells of 1.5 a / 8 over r <= 1.5 a and 1.5 a below the surface) graded outside
(``indentation_block``'s grading from the axis left only ~5 cells across the contact and was
5-9 % too stiff). The force is
compared with Hertz (half-space), the Dimitriadis et al. (2002) series
(:func:`difftissue.analytic.dimitriadis_force`) and the exact bonded-layer solution
(:func:`difftissue.analytic.layer_sphere_force`). Convergence: one chi is re-run on a finer
mesh.

Run:  python experiments/exp4_thin_layers.py [OUT_DIR] [--nu 0.3]
      [--cells 8,8] [--fine-cells 12,10] [--converge-chi 0.5]
Writes OUT_DIR/exp4_thin_layers.json and .png; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue import analytic  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import structured_grid  # noqa: E402
from difftissue.scenarios import Indentation, SolverOptions, graded_axis  # noqa: E402

R = 1e-3  # m
DEPTH = 0.01 * R  # m
E = 10e3  # Pa (the force ratios do not depend on it)
CHIS = (0.1, 0.25, 0.5, 0.75, 1.0)


def core_axis(length, core, core_cells, graded_cells):
    """``0 .. length`` with uniform cells of ``core / core_cells`` up to ``core``, then
    ``graded_cells`` cells growing geometrically from that size."""
    s = core / core_cells
    if length <= core * (1 + 1e-9):
        return np.linspace(0.0, length, max(int(np.ceil(length / s - 1e-9)), 1) + 1)
    return np.concatenate([np.linspace(0.0, core, core_cells + 1), core + graded_axis(length - core, graded_cells, s)[1:]])


def contact_block(half, h, a, core_cells, graded_cells):
    """Quarter block ``[0, half]^2 x [0, h]`` with a uniform core of ``1.5 a`` (radius and
    depth below the surface) around the indentation axis, graded outside it."""
    xs = core_axis(half, 1.5 * a, core_cells, graded_cells)
    zs = h - core_axis(h, 1.5 * a, core_cells, graded_cells)[::-1]
    return structured_grid(xs, xs, zs, region_names=("tissue",))


def simulate(chi, nu, cells, linear_solver):
    """Force [N] at DEPTH; ``cells = (core_cells, graded_cells)`` (see :func:`contact_block`)."""
    a = np.sqrt(R * DEPTH)
    h = a / chi
    half = 10 * a + 2 * h
    mesh = contact_block(half, h, a, *cells)
    sc = Indentation(mesh, [DEPTH], model="fem_linear", indenter="sphere", radius=R, base="bonded", symmetry="quarter", options=SolverOptions(linear_solver=linear_solver, max_steps=100))
    t0 = time.perf_counter()
    f = float(np.asarray(sc.predict(Material(E, nu)))[0])
    return f, time.perf_counter() - t0, mesh.n_nodes, h


def references(chi, nu):
    h = np.sqrt(R * DEPTH) / chi
    return {
        "hertz": float(analytic.hertz_force(DEPTH, E, nu, R)),
        "dimitriadis": float(analytic.dimitriadis_force(DEPTH, E, nu, R, h, base="bonded")),
        "exact_layer": float(analytic.layer_sphere_force(DEPTH, E, nu, R, h, base="bonded")),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=str(Path(__file__).parent / "results"))
    ap.add_argument("--nu", type=float, default=0.3)
    ap.add_argument("--cells", default="8,8", help="core cells (over 1.5 a), graded cells outside")
    ap.add_argument("--fine-cells", default="12,10")
    ap.add_argument("--converge-chi", type=float, default=0.5)
    ap.add_argument("--chis", default=",".join(str(c) for c in CHIS))
    ap.add_argument("--linear-solver", default="sparse")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cells = tuple(int(c) for c in args.cells.split(","))
    fine = tuple(int(c) for c in args.fine_cells.split(","))
    chis = [float(c) for c in args.chis.split(",")]
    nu = args.nu
    t0 = time.perf_counter()
    rows = []
    for chi in chis:
        f, dt, nodes, h = simulate(chi, nu, cells, args.linear_solver)
        ref = references(chi, nu)
        row = {"chi": chi, "thickness_m": h, "force_fem_N": f, **{f"force_{k}_N": v for k, v in ref.items()}, "fem_vs_hertz": f / ref["hertz"] - 1, "fem_vs_dimitriadis": f / ref["dimitriadis"] - 1, "fem_vs_exact": f / ref["exact_layer"] - 1, "exact_over_hertz": ref["exact_layer"] / ref["hertz"], "dimitriadis_over_hertz": ref["dimitriadis"] / ref["hertz"], "seconds": dt, "n_nodes": nodes}
        rows.append(row)
        print(f"chi {chi}: FEM/exact {f / ref['exact_layer']:.4f} ({dt:.0f} s)", flush=True)
    conv = None
    if args.converge_chi > 0:
        f_fine, dt, nodes, _ = simulate(args.converge_chi, nu, fine, args.linear_solver)
        coarse = next((r for r in rows if abs(r["chi"] - args.converge_chi) < 1e-12), None)
        ref = references(args.converge_chi, nu)
        conv = {"chi": args.converge_chi, "coarse": {"cells": cells, "force_N": None if coarse is None else coarse["force_fem_N"], "vs_exact": None if coarse is None else coarse["fem_vs_exact"]}, "fine": {"cells": fine, "n_nodes": nodes, "force_N": f_fine, "vs_exact": f_fine / ref["exact_layer"] - 1, "seconds": dt}}
        if coarse is not None:
            conv["coarse_vs_fine"] = coarse["force_fem_N"] / f_fine - 1
    result = {"experiment": "exp4_thin_layers", "sphere_radius_m": R, "depth_m": DEPTH, "youngs_modulus": E, "poisson_ratio": nu, "base": "bonded", "model": "fem_linear", "penalty": 100.0, "mesh": {"core_and_graded_cells": cells, "core": "uniform cells over r, depth <= 1.5 a", "half_width": "10 a + 2 h"}, "rows": rows, "convergence": conv, "total_seconds": time.perf_counter() - t0}
    tag = f"_nu{nu:g}"
    (out / f"exp4_thin_layers{tag}.json").write_text(json.dumps(result, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cc = np.linspace(0.05, 1.05, 60)
    h_c = np.sqrt(R * DEPTH) / cc
    fh = float(analytic.hertz_force(DEPTH, E, nu, R))
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.plot(cc, np.asarray(analytic.layer_sphere_force(DEPTH, E, nu, R, h_c, base="bonded")) / fh, "k-", label="exact bonded layer")
    ax.plot(cc, np.asarray(analytic.dimitriadis_force(DEPTH, E, nu, R, h_c, base="bonded")) / fh, "--", label="Dimitriadis (2002)")
    ax.axhline(1.0, color="0.5", lw=0.8, label="Hertz")
    ax.plot([r["chi"] for r in rows], [r["force_fem_N"] / r["force_hertz_N"] for r in rows], "o", label=f"FEM, core/graded cells {cells}")
    if conv is not None:
        ax.plot([conv["chi"]], [conv["fine"]["force_N"] / fh], "s", mfc="none", label=f"FEM finer {fine}")  # noqa: E501
    ax.set_xlabel("chi = sqrt(R d) / h")
    ax.set_ylabel("F / F_Hertz")
    ax.set_title(f"bonded layer, nu = {nu}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"exp4_thin_layers{tag}.png", dpi=110)

    print(f"\nnu = {nu}, bonded base, d = 0.01 R; mesh: {cells[0]} uniform cells over 1.5 a (a/{cells[0] / 1.5:.1f}), {cells[1]} graded outside")
    print("| chi | h/a | F_exact/F_Hertz | F_Dimitriadis/F_Hertz | F_FEM/F_Hertz | FEM vs exact | FEM vs Dimitriadis | FEM vs Hertz | time [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['chi']:g} | {1 / r['chi']:.2f} | {r['exact_over_hertz']:.4f} | {r['dimitriadis_over_hertz']:.4f} | {r['force_fem_N'] / r['force_hertz_N']:.4f} | {100 * r['fem_vs_exact']:+.1f} % | {100 * r['fem_vs_dimitriadis']:+.1f} % | {100 * r['fem_vs_hertz']:+.1f} % | {r['seconds']:.0f} |")
    if conv is not None:
        c = conv
        coarse_txt = "n/a" if c["coarse"]["vs_exact"] is None else f"{100 * c['coarse']['vs_exact']:+.2f} %"
        print(f"\nconvergence at chi = {c['chi']}: cells {cells} -> {coarse_txt} vs exact; cells {fine} ({c['fine']['n_nodes']} nodes) -> {100 * c['fine']['vs_exact']:+.2f} % vs exact")
    print(f"total {result['total_seconds']:.0f} s")


if __name__ == "__main__":
    main()
