"""Seed 003 surrogate fitted to the physical opening of a pre-tensioned layered specimen.

Specimen: 12 x 12 mm, 1 mm cells; top layer "dermis" 2 mm (2 cells, E = 200 kPa, nu = 0.45,
pre-stretch lambda0), bottom layer "fat" 4 mm (4 cells, E = 5 kPa, nu = 0.45, no pre-stretch);
lateral faces held in x and y (the mesh is the in-vivo state), bottom clamped. Straight cut
along x through the centre, length 6 mm, depth 2 mm (the dermis), fem_neo_hookean. For each
lambda0 the widths of all duplicated pairs (difftissue.cutting.opening_width) against their
depth are fitted by the surrogate w = min(c (d - h)/(1 - alpha), w_max) (w_max = inf):

  A: alpha = 1 - 1/lambda0 (DESIGN.md §3.6), one c shared by all lambda0;
  B: alpha = 1 - 1/lambda0, c fitted per lambda0 (equivalently q = c/(1 - alpha) per lambda0).

Run: python experiments/surrogate_fit.py   (prints a table)
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.cutting import ScalpelPath, cut_specimen, opening_width  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import layered_skin  # noqa: E402
from difftissue.models import make_model, stack_materials  # noqa: E402
from difftissue.opening_surrogate import alpha_from_pre_stretch, fit_surrogate  # noqa: E402
from difftissue.solvers.static import solve_static  # noqa: E402

SIZE, DERMIS, FAT, DEPTH = 12e-3, 2e-3, 4e-3, 2e-3


def main(lams=(1.05, 1.10, 1.15), kind="fem_neo_hookean"):
    skin = Material(2e5, 0.45)
    fat = Material(5e3, 0.45)
    spec = layered_skin([("dermis", DERMIS, skin, 2), ("fat", FAT, fat, 4)], size=(SIZE, SIZE), resolution=(12, 12))
    cut = cut_specimen(spec, ScalpelPath([(3e-3, 6e-3), (9e-3, 6e-3)], depth=DEPTH))
    cm = cut.mesh
    bc = BoundaryConditions.free(cm)
    for face in ("x-min", "x-max", "y-min", "y-max"):
        bc = bc.fix(cm, {"face": face}, "xy")
    bc = bc.fix(cm, {"face": "z-min"})
    model = make_model(cm, kind)
    depths, widths, rows = [], [], []
    for lam0 in lams:
        mat = stack_materials([skin.replace(pre_stretch=lam0), fat])
        t0 = time.perf_counter()
        sol = solve_static(model, mat, bc, load_steps=2)
        o = opening_width(cut, cm.points + sol.displacement)
        w = np.asarray(o.width)
        h = np.clip(np.asarray(cut.pair_depth), 0.0, DEPTH)
        depths.append(h)
        widths.append(w)
        rows.append((lam0, float(o.max_width), float(np.mean(np.asarray(o.surface_width))), time.perf_counter() - t0))
    alphas = [float(alpha_from_pre_stretch(x)) for x in lams]
    shared = fit_surrogate(depths, widths, DEPTH, alpha=alphas)
    print(f"{kind}, {cut.n_pairs} pairs, cut 6 mm x {DEPTH * 1e3:g} mm")
    print("| lambda0 | max surface width [mm] | mean surface width [mm] | A: shared c, rms / rms(w) | B: c per lambda0 | B: rms / rms(w) |")
    print("|---|---|---|---|---|---|")
    off = 0
    for k, (lam0, mx, mean, dt) in enumerate(rows):
        n = depths[k].size
        rA = shared.residuals[off:off + n]
        off += n
        own = fit_surrogate(depths[k], widths[k], DEPTH, alpha=alphas[k])
        relA = np.sqrt(np.mean(rA**2)) / np.sqrt(np.mean(widths[k] ** 2))
        print(f"| {lam0:.2f} | {mx * 1e3:.4f} | {mean * 1e3:.4f} | {relA:.3f} | {own.c:.4f} | {own.relative_rms:.3f} |")
    print(f"A: shared c = {shared.c:.4f}, overall relative rms {shared.relative_rms:.3f}")


if __name__ == "__main__":
    main()
