"""Convergence bias of budgeted (real-time) XPBD: effective stiffness vs. iteration budget.

A soft block (liver-like) is indented by a bonded flat punch; the effective stiffness is the
punch reaction force divided by the depth. Standard XPBD (multipliers reset at every frame,
kept across the iterations of the frame) with dt = 1/60 s and one substep is run with
fully damped frames (velocities zeroed) from rest until the largest position change in a
frame is below 1e-9 x the block size (the state a real-time simulator with that budget
settles to; at most 2000 frames), and the punch force it reports (from the multipliers of
the last frame) is compared with the converged static answer of the same model
(``solve_static``).

Run:  python experiments/xpbd_budget.py  [--quick]
Prints a Markdown table (copied into docs/xpbd.md).
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import block  # noqa: E402
from difftissue.models import make_model  # noqa: E402
from difftissue.solvers.static import solve_static  # noqa: E402
from difftissue.solvers.xpbd import XPBDSettings, xpbd_quasi_static  # noqa: E402

SIZE = (0.02, 0.02, 0.01)  # m
CELLS = (4, 4, 2)  # 5 mm cubes
MATERIAL = Material(youngs_modulus=10e3, poisson_ratio=0.45, cubic_coefficient=0.0, density=1000.0)
DT = 1.0 / 60.0
DEPTH = 0.5e-3  # m, 5 % of the thickness
PUNCH_RADIUS = 0.0051  # m: the 3 x 3 central top nodes
ITERATIONS = (1, 2, 5, 10, 20, 50, 100)
TOL = 1e-9
MAX_FRAMES = 2_000


def setup():
    mesh = block(SIZE, CELLS, origin=(-SIZE[0] / 2, -SIZE[1] / 2, 0.0))
    p = np.asarray(mesh.points)
    top = p[:, 2] > SIZE[2] - 1e-9
    punch = np.flatnonzero(top & (np.hypot(p[:, 0], p[:, 1]) < PUNCH_RADIUS))
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, punch, "xyz", (0.0, 0.0, -DEPTH))
    return mesh, bc, punch


def punch_force(reaction, punch):
    return -float(jnp.sum(reaction[punch, 2]))  # N, pushing the punch back up


def wave_number(model, mesh):
    """(dt c / h)^2 with the P-wave speed c and the cell size h: the budget-bias scale."""
    lam, mu = MATERIAL.lame
    c = np.sqrt(float(lam + 2 * mu) / float(MATERIAL.density))
    h = SIZE[0] / CELLS[0]
    return (DT * c / h) ** 2


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only iterations 1, 10, 100")
    args = ap.parse_args()
    iterations = (1, 10, 100) if args.quick else ITERATIONS
    mesh, bc, punch = setup()
    rows = []
    header = None
    for kind in ("springs_volume", "stable_neo_hookean"):
        model = make_model(mesh, kind)
        ref = solve_static(model, MATERIAL, bc)
        f_static = punch_force(ref.reaction, punch)
        k_static = f_static / DEPTH
        header = header or f"(dt c/h)^2 = {wave_number(model, mesh):.0f}"
        for method in ("jacobi", "gauss_seidel"):
            for it in iterations:
                s = XPBDSettings(dt=DT, substeps=1, iterations=it, method=method, warm_start=False)
                t0 = time.perf_counter()
                rest = xpbd_quasi_static(model, MATERIAL, bc, settings=s, tol=TOL, max_steps=MAX_FRAMES, throw=False)
                wall = time.perf_counter() - t0
                r_rest = punch_force(rest.reaction, punch) / f_static
                frames = int(rest.steps) if bool(rest.converged) else f">{MAX_FRAMES}"
                rows.append((kind, method, it, r_rest, frames, k_static))
                print(f"  {kind:18s} {method:12s} it={it:3d}  ratio {r_rest:.4f}  frames {frames}  ({wall:.1f} s)", flush=True)
    print()
    print(f"Mesh: block {SIZE[0]*100:g} x {SIZE[1]*100:g} x {SIZE[2]*100:g} cm, {CELLS[0]} x {CELLS[1]} x {CELLS[2]} cubes of 5 mm "
          f"({mesh.n_nodes} nodes, {mesh.n_tets} tets); E = {MATERIAL.youngs_modulus/1e3:g} kPa, nu = {MATERIAL.poisson_ratio}, "
          f"rho = {MATERIAL.density:g} kg/m^3, linear springs (b = 0); base clamped, bonded flat punch (3 x 3 top nodes, "
          f"radius ~5 mm) pushed {DEPTH*1e3:g} mm; dt = 1/60 s, 1 substep, standard XPBD (multipliers reset per frame), "
          f"fully damped frames; {header}.")
    print()
    print("Effective stiffness ratio (punch force of budgeted XPBD / converged static solution of the same model):")
    print()
    print("| model | method | iterations | stiffness ratio at rest | frames to rest |")
    print("|---|---|---:|---:|---:|")
    for kind, method, it, r_rest, frames, _ in rows:
        print(f"| {kind} | {method} | {it} | {r_rest:.4f} | {frames} |")
    print()
    for kind in ("springs_volume", "stable_neo_hookean"):
        k = next(r[5] for r in rows if r[0] == kind)
        print(f"Converged static punch stiffness ({kind}): {k:.4g} N/m")


if __name__ == "__main__":
    main()
