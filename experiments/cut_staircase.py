"""Staircase (face-aligned) against snapped cuts: springs_volume openings of an aligned and a
25-degree incision in a pre-tensioned two-layer skin, against the neo-Hookean FEM.

Specimen (as experiments/incision_vs_fem.py): 12 x 12 mm, cubic cells of `cell` mm; "dermis"
2 mm (E = 200 kPa, nu = 0.45, pre-stretch lambda0), "fat" 4 mm (E = 5 kPa, nu = 0.45, none);
lateral faces held in x and y at the mesh, base clamped. Cut: 6 mm long, 2 mm deep (the
dermis), centred on the top, at 0 deg (along x, on a lattice line) or 25 deg to x.

Per cell size and angle:
- springs_volume on the snapped cut (method="snap", split cubes dropped: the default),
- springs_volume on the staircase cut (method="staircase"; at 0 deg it is the same cut),
- fem_neo_hookean on the snapped cut (the reference on that mesh; linear tets, far from
  converged: the script extrapolates it over the cell sizes, Richardson with the observed order).
Each is `Incision.solve` (pre-tensioned equilibrium, scalpel in one step, opened equilibrium).
Outputs per (model, lambda0): the max surface width and the surface opening area (trapezoid of
the surface widths over arc length, zero at the two crack tips) / cut length = mean surface width.

Writes experiments/results/cut_staircase_cell{h}mm.json per cell size (rows already in the file
are kept unless --force); `--linear`: lambda0 = 1.001 only (the linear limit, compared in
docs/cutting.md with the converged P2 reference of the aligned cut), written to
cut_staircase_linear_cell{h}mm.json; `--plate`: the inclined through-cut plate of
experiments/cut_griffith.py with the staircase cut; `--table` prints the tables from the JSON
files present. CPU time (time.process_time) is recorded per solve. Measured on 2 shared cores:
42 s (1 mm), 105 s (0.667 mm), 422 s (0.5 mm) per cell size; --linear 43 s + 199 s.

Run: python experiments/cut_staircase.py --cell 1 --cell 0.6666666666666666 --cell 0.5 --table
     python experiments/cut_staircase.py --linear --cell 1 --cell 0.5
     python experiments/cut_staircase.py --plate
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue._io import atomic_output  # noqa: E402
from difftissue.cutting import ScalpelPath, cut_specimen  # noqa: E402
from difftissue.incision import Incision, IncisionOptions  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import layered_skin  # noqa: E402

SIZE, DERMIS, FAT, DEPTH, LENGTH = 12e-3, 2e-3, 4e-3, 2e-3, 6e-3
SKIN, FATM = Material(2e5, 0.45), Material(5e3, 0.45)
RESULTS = Path(__file__).resolve().parent / "results"
LAMS = (1.05, 1.10)


def specimen(cell):
    n = int(round(SIZE / cell))
    layers = [("dermis", DERMIS, SKIN, int(round(DERMIS / cell))), ("fat", FAT, FATM, int(round(FAT / cell)))]
    return layered_skin(layers, size=(SIZE, SIZE), resolution=(n, n))


def path(angle_deg):
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    m = 0.5 * SIZE
    return ScalpelPath([(m - 0.5 * LENGTH * c, m - 0.5 * LENGTH * s), (m + 0.5 * LENGTH * c, m + 0.5 * LENGTH * s)], depth=DEPTH)


def surface_measures(cut, width):
    """Max surface width and mean surface width (opening area / length; zero at the tips) [m]."""
    w = np.asarray(width)[cut.surface_pairs]
    s = np.asarray(cut.pair_s)[cut.surface_pairs]
    inside = (s > 0) & (s < cut.length)
    ss = np.concatenate([[0.0], s[inside], [cut.length]])
    ww = np.concatenate([[0.0], w[inside], [0.0]])
    return float(w.max()), float(np.sum(0.5 * (ww[1:] + ww[:-1]) * np.diff(ss)) / cut.length)


def run_cell(cell, lams=LAMS, done=()):
    """Rows of one cell size [m]; ``done``: rows already computed (kept, not recomputed)."""
    spec = specimen(cell)
    opts = IncisionOptions(scalpel_steps=1, linear_solver="sparse")
    out = {"cell": cell, "nodes": spec.mesh.n_nodes, "rows": []}
    for angle in (0.0, 25.0):
        cuts = {m: cut_specimen(spec, path(angle), method=m) for m in ("snap", "staircase")}
        a, b = cuts["snap"], cuts["staircase"]
        same = bool(np.array_equal(a.pairs, b.pairs) and np.array_equal(a.mesh.tets, b.mesh.tets) and np.array_equal(np.asarray(a.mesh.points), np.asarray(b.mesh.points)))
        runs = [("fem_neo_hookean", "snap"), ("springs_volume", "snap")] + ([] if same else [("springs_volume", "staircase")])
        for kind, method in runs:
            cut = cuts[method]
            old = {r["pre_stretch"]: dict(r, same_as_snap=same) for r in done if (r["angle"], r["model"], r["method"]) == (angle, kind, method)}
            if all(lam in old for lam in lams):
                out["rows"] += [old[lam] for lam in lams]
                continue
            inc = Incision(cut, model=kind, fitted_regions=("dermis",), options=opts)
            for lam in lams:
                t0 = time.process_time()
                res = inc.solve(SKIN.replace(pre_stretch=lam))
                wmax, wmean = surface_measures(cut, res.opening.width)
                row = dict(angle=angle, model=kind, method=method, same_as_snap=bool(same), pre_stretch=lam, max_width=wmax, mean_width=wmean,
                           cpu_seconds=time.process_time() - t0, pairs=cut.n_pairs, quality=cut.quality.to_dict())
                out["rows"].append(row)
                print(json.dumps({k: v for k, v in row.items() if k != "quality"}), flush=True)
    return out


def plate(angle_deg=25.0, a=3e-3, E=1e4, nu=0.3, sigma=10.0):
    """The inclined through-cut of experiments/cut_griffith.py (oblique): 2a = 6 mm in a
    20 x 20 x 1 mm plate of 1 mm cubes, remote tension sigma along y, linear; mean normal
    opening over the pairs with fem_linear (snapped cut) and springs_volume on the snapped cut
    (split cubes dropped / kept) and on the staircase cut."""
    from difftissue.boundary import BoundaryConditions
    from difftissue.cutting import opening_width
    from difftissue.mesh import block
    from difftissue.models import make_model
    from difftissue.solvers.static import solve_static

    mesh = block((20e-3, 20e-3, 1e-3), (20, 20, 1), origin=(-10e-3, -10e-3, 0.0))
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    p = ScalpelPath([(-a * c, -a * s), (a * c, a * s)], through=True)
    rows = []
    for method, policy, kinds in (("snap", "keep", ("fem_linear", "springs_volume")), ("snap", "drop", ("springs_volume",)), ("staircase", "drop", ("fem_linear", "springs_volume"))):
        cut = cut_specimen(mesh, p, method=method, split_cubes=policy)
        cm = cut.mesh
        bc = (
            BoundaryConditions.free(cm)
            .fix(cm, {"face": "y-min"}, "y")
            .fix(cm, {"face": "z-min"}, "z")
            .fix(cm, {"box": {"lower": [-10.001e-3, -10.001e-3, -1.0], "upper": [-9.999e-3, -9.999e-3, 1.0]}}, "x")
            .add_force(cm, {"face": "y-max"}, (0.0, sigma * 20e-3 * 1e-3, 0.0), distribute="area")
        )
        for kind in kinds:
            t0 = time.process_time()
            sol = solve_static(make_model(cm, kind), Material(E, nu), bc)
            w = np.asarray(opening_width(cut, np.asarray(cm.points) + np.asarray(sol.displacement)).normal_opening)
            rows.append(dict(angle=angle_deg, method=method, split_cubes=policy if method == "snap" else None, model=kind,
                             n_split=cut.quality.n_split_cubes, mean_opening=float(w.mean()), cpu_seconds=time.process_time() - t0))
    return rows


def _order(f, h):
    """Observed order p and extrapolated value from values ``f`` at cell sizes ``h`` (3 values,
    any ratios): solve (f1 - f2)/(f2 - f3) = (h1^p - h2^p)/(h2^p - h3^p)."""
    from scipy.optimize import brentq

    f1, f2, f3 = f
    h1, h2, h3 = h
    r = (f1 - f2) / (f2 - f3)
    g = lambda p: (h1**p - h2**p) / (h2**p - h3**p) - r  # noqa: E731
    try:
        p = brentq(g, 0.05, 6.0)
    except ValueError:
        return float("nan"), f3 + (f3 - f2) * h3 / (h2 - h3)
    return p, f3 + (f3 - f2) * h3**p / (h2**p - h3**p)


def table():
    """Print the convergence tables from the JSON files present (values in mm; observed order
    from three cell sizes, else first order assumed; the extrapolated value)."""
    data = sorted((json.loads(p.read_text()) for p in RESULTS.glob("cut_staircase_cell*mm.json")), key=lambda d: -d["cell"])
    hs = [d["cell"] for d in data]
    for quantity in ("max_width", "mean_width"):
        print(f"\n{quantity} [mm]\n")
        print("| angle | lambda0 | model, cut | " + " | ".join(f"h = {h:.3g} mm" for h in hs) + " | observed order | extrapolated |")
        print("|---|---|---|" + "---|" * (len(hs) + 2))
        for angle in (0.0, 25.0):
            for lam in LAMS:
                for kind, method in (("fem_neo_hookean", "snap"), ("springs_volume", "snap"), ("springs_volume", "staircase")):
                    vals = []
                    for d in data:
                        hit = [r for r in d["rows"] if r["angle"] == angle and r["pre_stretch"] == lam and r["model"] == kind
                               and (r["method"] == method or (method == "staircase" and r["same_as_snap"] and r["method"] == "snap"))]
                        vals.append(hit[0][quantity] if hit else float("nan"))
                    if len(vals) == 3:
                        p, ext = _order(vals, hs)
                    else:
                        p, ext = 1.0, vals[-1] + (vals[-1] - vals[-2]) * hs[-1] / (hs[-2] - hs[-1])
                    cells = [f"{v * 1e3:.4f}" for v in vals]
                    print(f"| {angle:g} deg | {lam:.2f} | {kind}, {method} | " + " | ".join(cells) + f" | {p:.2f} | {ext * 1e3:.4f} |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cell", type=float, action="append", help="cell size [mm] (repeatable)")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--plate", action="store_true", help="the inclined through-cut plate of cut_griffith.py (0 and 25 deg)")
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--linear", action="store_true", help="lambda0 = 1.001 only (the linear limit, w / (lambda0 - 1) against the docs' converged reference)")
    a = ap.parse_args()
    for c in a.cell or []:
        t0 = time.process_time()
        f = RESULTS / f"cut_staircase{'_linear' if a.linear else ''}_cell{c:g}mm.json"
        done = json.loads(f.read_text())["rows"] if f.exists() and not a.force else ()
        res = run_cell(c * 1e-3, lams=(1.001,) if a.linear else LAMS, done=done)
        res["cpu_seconds_total"] = time.process_time() - t0
        res["cell"] = c
        with atomic_output(f, overwrite=True) as tmp:
            Path(tmp).write_text(json.dumps(res, indent=1))
    if a.plate:
        rows = plate(0.0) + plate(25.0)
        with atomic_output(RESULTS / "cut_staircase_plate.json", overwrite=a.force) as tmp:
            Path(tmp).write_text(json.dumps(rows, indent=1))
        print("| cut angle | cut | model | mean normal opening [um] |")
        print("|---|---|---|---|")
        for r in rows:
            cut = r["method"] if r["method"] == "staircase" else f"snap, {r['n_split']} split ({r['split_cubes']})"
            print(f"| {r['angle']:g} deg | {cut} | {r['model']} | {r['mean_opening'] * 1e6:.3f} |")
    if a.table:
        table()
