"""Sphere on a dome: Hertz's effective radius on a curved surface, and mesh convergence.

A rigid sphere of radius R1 presses along -z on the apex of an elastic dome of radius R2 (the
top of a graded quarter block bent onto a sphere, ``difftissue.mesh.curved_top``), fem_linear,
bonded base. Hertz: F = 4/3 E* sqrt(R) d^1.5 with 1/R = 1/R1 + 1/R2. The same mesh with a flat
top indented by a sphere of radius R (the Hertz-equivalent flat problem) separates the finite
size and the discretisation (shared by both) from the curvature (the feature under test).

Run: PYTHONPATH=. python experiments/curved_indentation.py [m ...]   (cells per contact radius)
     PYTHONPATH=. python experiments/curved_indentation.py --sweep     (R2 = 1, 2, 4 mm at m = 3)
"""
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from difftissue.analytic import hertz_force  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import curved_top  # noqa: E402
from difftissue.scenarios import Indentation, _graded_cells, indentation_block  # noqa: E402

E, NU = 1e4, 0.3
R1 = R2 = 1e-3
REFF = 1.0 / (1.0 / R1 + 1.0 / R2)
A = 0.05e-3  # contact radius at the largest depth [m]
D = A * A / REFF  # largest depth [m]
HALF, H = 0.6e-3, 0.6e-3  # quarter half-width and height [m]: 12 contact radii


def meshes(m):
    refine = A / m
    n = _graded_cells(HALF, refine, 1.5 * A, 1.3)
    flat = indentation_block((2 * HALF, 2 * HALF, H), (n, n, n), symmetry="quarter", refine=refine, core=1.5 * A)
    return flat, curved_top(flat, R2)


def run(m, depths=(0.5 * D, D)):
    mat = Material(youngs_modulus=E, poisson_ratio=NU)
    flat, dome = meshes(m)
    t = time.process_time()
    f_dome = np.asarray(Indentation(dome, depths, model="fem_linear", radius=R1, symmetry="quarter", surface="boundary").predict(mat))
    f_flat = np.asarray(Indentation(flat, depths, model="fem_linear", radius=REFF, symmetry="quarter").predict(mat))
    hz = np.asarray(hertz_force(np.asarray(depths), E, NU, REFF))
    return dome.n_nodes, f_dome / hz, f_flat / hz, f_dome / f_flat, time.process_time() - t


def sweep_r2(m=3, radii=(1e-3, 2e-3, 4e-3)):
    """F_dome / F_flat(R) at m cells per a for domes of several radii (same R1, same a)."""
    global R2, REFF, D
    print("| R2 [mm] | R [mm] | F_dome / F_Hertz (d/2, d) | F_flat(R) / F_Hertz (d/2, d) | F_dome / F_flat(R) (d/2, d) |")
    print("|---|---|---|---|---|")
    for r2 in radii:
        R2, REFF = r2, 1.0 / (1.0 / R1 + 1.0 / r2)
        D = A * A / REFF
        n, rd, rf, r, cpu = run(m, depths=(0.5 * D, D))
        print(f"| {r2 * 1e3:g} | {REFF * 1e3:.4g} | {rd[0]:.4f}, {rd[1]:.4f} | {rf[0]:.4f}, {rf[1]:.4f} | {r[0]:.4f}, {r[1]:.4f} |", flush=True)


if __name__ == "__main__":
    if sys.argv[1:] == ["--sweep"]:
        sweep_r2()
        sys.exit(0)
    ms = [float(v) for v in sys.argv[1:]] or [2, 3, 4, 6]
    print(f"R1 = R2 = {R1 * 1e3:g} mm, R = {REFF * 1e3:g} mm, a = {A * 1e3:g} mm at d = {D * 1e6:g} um, quarter {HALF * 1e3:g} x {HALF * 1e3:g} x {H * 1e3:g} mm, E = {E:g} Pa, nu = {NU}")
    print("| cells per a | nodes | F_dome / F_Hertz (d/2, d) | F_flat(R) / F_Hertz (d/2, d) | F_dome / F_flat(R) (d/2, d) | CPU s |")
    print("|---|---|---|---|---|---|")
    for m in ms:
        n, rd, rf, r, cpu = run(m)
        print(f"| {m:g} | {n} | {rd[0]:.4f}, {rd[1]:.4f} | {rf[0]:.4f}, {rf[1]:.4f} | {r[0]:.4f}, {r[1]:.4f} | {cpu:.1f} |", flush=True)
