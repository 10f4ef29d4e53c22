"""Budget-aware calibration of a real-time XPBD *indentation* (issue 6): before/after table.

A bonded flat punch (radius 3 mm, the 5 central top nodes) indents a 10 x 10 x 5 mm block
(4 x 4 x 2 cubes of 2.5 mm, ``springs_volume``, E = 10 kPa, nu = 0.45, rho = 1000 kg/m^3,
base bonded) by 0.1 mm. The budgeted solver is standard XPBD (multipliers reset per frame),
Gauss-Seidel, 1 substep, dt = 3 ms, with 5, 10 or 20 iterations, run to rest
(``xpbd_quasi_static``). ``calibrate_for_budget`` fits the effective E so that the budgeted
punch force equals the reference: the static solution of the same model, or of the linear
FEM (``fem_linear``) on the same mesh. Errors are relative errors of the punch force.

Run:  python experiments/budget_indentation.py   (prints the Markdown table of docs/budget.md)
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.budget import calibrate_for_budget  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import block  # noqa: E402
from difftissue.solvers.xpbd import XPBDSettings  # noqa: E402

SIZE = (0.01, 0.01, 0.005)  # m
CELLS = (4, 4, 2)
PUNCH_RADIUS = 3e-3  # m
DEPTH = 1e-4  # m
MATERIAL = Material(youngs_modulus=10e3, poisson_ratio=0.45)


def punch_problem():
    """Mesh and boundary conditions of the flat-punch indentation (bonded punch and base)."""
    mesh = block(SIZE, CELLS)
    p = np.asarray(mesh.points)
    top = np.abs(p[:, 2] - SIZE[2]) < 1e-12
    r = np.hypot(p[:, 0] - SIZE[0] / 2, p[:, 1] - SIZE[1] / 2)
    punch = np.flatnonzero(top & (r <= PUNCH_RADIUS))
    bc = (BoundaryConditions.free(mesh)
          .fix(mesh, {"face": "z-min"})
          .fix(mesh, punch, "xyz", (0.0, 0.0, -DEPTH)))
    return mesh, bc, punch


def main() -> None:
    mesh, bc, punch = punch_problem()
    print(f"block {SIZE} m, {mesh.n_tets} tets, {punch.size} punch nodes, depth {DEPTH} m\n")
    print("| reference | iterations | naive error | calibrated error | E_cal / E | GN steps | time [s] |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for ref in ("same", "fem_linear"):
        for it in (5, 10, 20):
            settings = XPBDSettings(dt=3e-3, substeps=1, iterations=it, method="gauss_seidel", warm_start=False)
            t0 = time.perf_counter()
            kw = {} if ref == "same" else {"reference": "fem_linear"}
            cal = calibrate_for_budget(mesh, "springs_volume", MATERIAL, bc, settings, **kw)
            name = "same model (static)" if ref == "same" else "fem_linear (static)"
            print(f"| {name} | {it} | {100 * cal.naive_error:.1f} % | {cal.calibrated_error:.1e} | {cal.ratio():.3f} | "
                  f"{cal.steps} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
