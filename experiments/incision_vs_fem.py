"""Incision of a pre-tensioned two-layer skin: the physical models against the reference FEM.

Specimen (as experiments/surrogate_fit.py): 12 x 12 mm, cells of `cell` mm; "dermis" 2 mm
(E = 200 kPa, nu = 0.45, pre-stretch lambda0), "fat" 4 mm (E = 5 kPa, nu = 0.45, none); lateral
faces held in x and y at the mesh (the in-vivo, stretched state), base clamped
(difftissue.incision.incision_boundary). Straight snapped cut along x through the centre,
length 6 mm, depth 2 mm (the dermis; on a lattice line: no split cubes).

Reference (seed 002): fem_neo_hookean with the duplicated pairs tied by the closure penalty,
released as the scalpel advances (Incision.progress: one equilibrium per scalpel position, each
from the previous). Physical models: stable_neo_hookean and springs_volume, the same cut
(Incision.solve: pre-tensioned equilibrium, scalpel in 4 steps, opened equilibrium).

Per lambda0 in 1.0, 1.05, 1.10, 1.15: max surface width, relative error of the max width and
the RMS error of all pair widths relative to the RMS reference width.

Writes experiments/results/incision_vs_fem.json, .png, incision_opened.png (surface view and
cross-section of the reference at lambda0 = 1.10) and the VTU series
experiments/results/incision_vtu/incision.pvd (reference, lambda0 = 1.10, one file per scalpel
position). Existing outputs are refused unless --force.

Run: python experiments/incision_vs_fem.py [--cell 1.0] [--force]
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
from difftissue.incision import Incision, IncisionOptions, depth_profile, plot_incision, write_incision_series  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import layered_skin  # noqa: E402

SIZE, DERMIS, FAT, DEPTH, LENGTH = 12e-3, 2e-3, 4e-3, 2e-3, 6e-3
SKIN, FATM = Material(2e5, 0.45), Material(5e3, 0.45)
RESULTS = Path(__file__).resolve().parent / "results"


def specimen(cell=1e-3):
    n = int(round(SIZE / cell))
    spec = layered_skin([("dermis", DERMIS, SKIN, int(round(DERMIS / cell))), ("fat", FAT, FATM, int(round(FAT / cell)))], size=(SIZE, SIZE), resolution=(n, n))
    y = 0.5 * SIZE
    return cut_specimen(spec, ScalpelPath([(0.5 * (SIZE - LENGTH), y), (0.5 * (SIZE + LENGTH), y)], depth=DEPTH))


def main(lams=(1.0, 1.05, 1.10, 1.15), cell=1e-3, force=False, picture_lam=1.10):
    cut = specimen(cell)
    print(f"cut mesh: {cut.mesh.n_nodes} nodes, {cut.mesh.n_tets} tets, {cut.n_pairs} pairs; {cut.quality}", flush=True)
    opts = IncisionOptions(scalpel_steps=4)
    ref = Incision(cut, model="fem_neo_hookean", fitted_regions=("dermis",), options=opts)
    phys = {k: Incision(cut, model=k, fitted_regions=("dermis",), options=opts) for k in ("stable_neo_hookean", "springs_volume")}
    positions = np.concatenate([LENGTH * np.arange(1, 7) / 6.0, [np.inf]])
    rows, progress = [], {}
    pair_s, pair_depth = np.asarray(cut.pair_s), np.asarray(cut.pair_depth)
    for lam in lams:
        mat = SKIN.replace(pre_stretch=lam)
        t0 = time.perf_counter()
        us, widths, mx = ref.progress(mat, positions)
        us, widths, mx = np.asarray(us), np.asarray(widths), np.asarray(mx)
        t_ref = time.perf_counter() - t0
        w_ref = widths[-1]
        progress[lam] = {"scalpel_position": [float(p) if np.isfinite(p) else None for p in positions], "max_surface_width": mx.tolist(), "pair_width": widths.tolist()}
        row = {"pre_stretch": lam, "reference": {"max_width": float(mx[-1]), "rms_width": float(np.sqrt(np.mean(w_ref**2))), "seconds": t_ref}}
        if lam == picture_lam:
            plot_incision(cut, us[-1], RESULTS / "incision_opened.png", title=f"fem_neo_hookean incision, lambda0 = {lam}", overwrite=force)
            vtu = RESULTS / "incision_vtu"
            vtu.mkdir(exist_ok=True)
            write_incision_series(vtu, cut, us, np.where(np.isfinite(positions), positions, np.inf), overwrite=force)
            d, w = depth_profile(cut, w_ref)
            row["reference"]["centre_depth_profile"] = {"depth": d.tolist(), "width": np.asarray(w).tolist()}
        for kind, inc in phys.items():
            t0 = time.perf_counter()
            res = inc.solve(mat)
            w = np.asarray(res.opening.width)
            dt = time.perf_counter() - t0
            entry = {"max_width": float(res.opening.max_width), "seconds": dt, "pair_width": w.tolist()}
            if row["reference"]["max_width"] > 1e-9:
                entry["max_width_error"] = float(res.opening.max_width) / row["reference"]["max_width"] - 1.0
                entry["profile_rms_error"] = float(np.sqrt(np.mean((w - w_ref) ** 2)) / np.sqrt(np.mean(w_ref**2)))
            row[kind] = entry
        row["reference"]["pair_width"] = w_ref.tolist()
        rows.append(row)
        print(json.dumps({k: (v if not isinstance(v, dict) else {kk: vv for kk, vv in v.items() if kk != "pair_width"}) for k, v in row.items()}), flush=True)
    out = {
        "specimen": {"size": SIZE, "cell": cell, "dermis": DERMIS, "fat": FAT, "skin": SKIN.to_dict(), "fat_material": FATM.to_dict(), "lateral": "held", "base": "clamped"},
        "cut": {"length": LENGTH, "depth": DEPTH, "pairs": cut.n_pairs, "nodes": cut.mesh.n_nodes, "pair_s": pair_s.tolist(), "pair_depth": pair_depth.tolist(), "quality": str(cut.quality)},
        "rows": rows,
        "reference_progress": {str(k): v for k, v in progress.items()},
    }
    stem = "incision_vs_fem" if abs(cell - 1e-3) < 1e-12 else f"incision_vs_fem_cell{cell * 1e3:g}mm"
    with atomic_output(RESULTS / f"{stem}.json", overwrite=force) as tmp:
        Path(tmp).write_text(json.dumps(out, indent=1))
    _plot(out, positions, RESULTS / f"{stem}.png", force)
    print()
    print("| lambda0 | FEM max width [mm] | stable_neo_hookean [mm] | error | profile rms | springs_volume [mm] | error | profile rms |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = [f"{r['pre_stretch']:.2f}", f"{r['reference']['max_width'] * 1e3:.4f}"]
        for k in ("stable_neo_hookean", "springs_volume"):
            e = r[k]
            cells += [f"{e['max_width'] * 1e3:.4f}", f"{100 * e['max_width_error']:+.1f} %" if "max_width_error" in e else "-", f"{100 * e['profile_rms_error']:.1f} %" if "profile_rms_error" in e else "-"]
        print("| " + " | ".join(cells) + " |")


def _plot(out, positions, path, force):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    s_plot = np.where(np.isfinite(positions), positions, LENGTH * 1.1) * 1e3
    for r in out["rows"]:
        lam = r["pre_stretch"]
        prog = out["reference_progress"][str(lam)]
        a1.plot(s_plot, np.asarray(prog["max_surface_width"]) * 1e3, "o-", label=f"lambda0 = {lam:.2f}")
    a1.set_xlabel("scalpel position s [mm] (last point: all released)")
    a1.set_ylabel("max surface width [mm]")
    a1.set_title("reference FEM incision: opening over scalpel progress")
    a1.legend(fontsize=8)
    ps = np.asarray(out["cut"]["pair_s"])
    pd = np.asarray(out["cut"]["pair_depth"])
    surf = pd < 1e-9
    order = np.argsort(ps[surf])
    for r, c in zip(out["rows"], ("C0", "C1", "C2", "C3")):
        lam = r["pre_stretch"]
        a2.plot(ps[surf][order] * 1e3, np.asarray(r["reference"]["pair_width"])[surf][order] * 1e3, "-", color=c, label=f"FEM {lam:.2f}")
        a2.plot(ps[surf][order] * 1e3, np.asarray(r["stable_neo_hookean"]["pair_width"])[surf][order] * 1e3, "--", color=c)
        a2.plot(ps[surf][order] * 1e3, np.asarray(r["springs_volume"]["pair_width"])[surf][order] * 1e3, ":", color=c)
    a2.set_xlabel("arc length along the cut [mm]")
    a2.set_ylabel("surface width [mm]")
    a2.set_title("after the cut: FEM (-), stable NH (--), springs (:)")
    a2.legend(fontsize=8)
    fig.tight_layout()
    with atomic_output(path, overwrite=force) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", type=float, default=1.0, help="cell size [mm]")
    ap.add_argument("--force", action="store_true", help="overwrite existing outputs")
    a = ap.parse_args()
    main(cell=a.cell * 1e-3, force=a.force)
