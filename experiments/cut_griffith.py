"""Through-crack in a thin plate under remote tension: the cut topology against Griffith.

A centre through-cut of length 2a (difftissue.cutting, node duplication on a lattice line) in a
plate W x W x t under uniaxial remote stress sigma perpendicular to the cut opens, in linear
plane-stress elasticity, to w0 = 4 sigma a / E at its centre (infinite plate). The plate is a
graded structured grid (uniform cells h near the cut, geometric growth outside), one cell
thick, bottom face on a z-roller (free thickness change: plane stress), fem_linear.

Run: python experiments/cut_griffith.py  (prints a table; ~1.5 min on 2 cores)
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.cutting import ScalpelPath, cut_specimen, opening_width  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import structured_grid  # noqa: E402
from difftissue.models import make_model  # noqa: E402
from difftissue.solvers.static import solve_static  # noqa: E402


def graded_axis(half_fine: float, h: float, half_width: float, growth: float = 1.3) -> np.ndarray:
    """Symmetric coordinates about 0: cells h up to +-half_fine, then growing by `growth`."""
    fine = np.arange(0.0, half_fine + 0.5 * h, h)
    out = list(fine)
    step = h
    while out[-1] < half_width - 1e-12:
        step *= growth
        out.append(min(out[-1] + step, half_width))
    pos = np.asarray(out)
    return np.concatenate([-pos[:0:-1], pos])


def run(a=2e-3, cells_per_a=4, W_over_a=30.0, t=0.2e-3, E=1e4, nu=0.3, sigma=10.0):
    h = a / cells_per_a
    xs = graded_axis(1.5 * a, h, 0.5 * W_over_a * a)
    ys = graded_axis(0.5 * a, h, 0.5 * W_over_a * a)
    mesh = structured_grid(xs, ys, np.array([0.0, t]))
    cut = cut_specimen(mesh, ScalpelPath([(-a, 0.0), (a, 0.0)], through=True))
    cm = cut.mesh
    W = xs[-1] - xs[0]
    bc = (
        BoundaryConditions.free(cm)
        .fix(cm, {"face": "y-min"}, "y")
        .fix(cm, {"face": "z-min"}, "z")
        .fix(cm, {"box": {"lower": [-1e-9, ys[0] - 1e-9, -1e-9], "upper": [1e-9, ys[0] + 1e-9, t + 1e-9]}}, "x")
        .add_force(cm, {"face": "y-max"}, (0.0, sigma * W * t, 0.0), distribute="area")
    )
    model = make_model(cm, "fem_linear")
    t0 = time.perf_counter()
    sol = solve_static(model, Material(E, nu), bc)
    dt = time.perf_counter() - t0
    o = opening_width(cut, jnp.asarray(cm.points) + sol.displacement)
    # Centre pairs (s = a), top and bottom: mean normal opening.
    centre = np.isclose(cut.pair_s, a, atol=1e-3 * h)
    w_centre = float(np.mean(np.asarray(o.normal_opening)[centre]))
    w_ref = 4 * sigma * a / E
    return dict(cells_per_a=cells_per_a, nodes=cm.n_nodes, pairs=cut.n_pairs, w_centre=w_centre, w_ref=w_ref, rel_err=w_centre / w_ref - 1, seconds=dt)


if __name__ == "__main__":
    print("| cells per a | nodes | pairs | w0 FEM [um] | 4 sigma a / E [um] | error | solve [s] |")
    print("|---|---|---|---|---|---|---|")
    for n in (2, 4, 8, 16, 32):
        r = run(cells_per_a=n)
        print(f"| {n} | {r['nodes']} | {r['pairs']} | {r['w_centre'] * 1e6:.3f} | {r['w_ref'] * 1e6:.3f} | {100 * r['rel_err']:+.2f} % | {r['seconds']:.1f} |", flush=True)


def oblique(angle_deg=25.0, a=3e-3, E=1e4, nu=0.3, sigma=10.0):
    """Inclined through-cut (snapped lattice) in a 20 x 20 x 1 mm plate, 1 mm cells: mean normal
    opening with fem_linear and with springs_volume, split cubes kept or dropped."""
    from difftissue.mesh import block

    mesh = block((20e-3, 20e-3, 1e-3), (20, 20, 1), origin=(-10e-3, -10e-3, 0.0))
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    path = ScalpelPath([(-a * c, -a * s), (a * c, a * s)], through=True)
    rows = []
    for policy, kinds in (("keep", ("fem_linear", "springs_volume")), ("drop", ("springs_volume",))):
        cut = cut_specimen(mesh, path, split_cubes=policy)
        cm = cut.mesh
        bc = (
            BoundaryConditions.free(cm)
            .fix(cm, {"face": "y-min"}, "y")
            .fix(cm, {"face": "z-min"}, "z")
            .fix(cm, {"box": {"lower": [-10.001e-3, -10.001e-3, -1.0], "upper": [-9.999e-3, -9.999e-3, 1.0]}}, "x")
            .add_force(cm, {"face": "y-max"}, (0.0, sigma * 20e-3 * 1e-3, 0.0), distribute="area")
        )
        for kind in kinds:
            sol = solve_static(make_model(cm, kind), Material(E, nu), bc)
            w = np.asarray(opening_width(cut, jnp.asarray(cm.points) + sol.displacement).normal_opening)
            rows.append((angle_deg, policy, kind, cut.quality.n_split_cubes, float(w.mean())))
    return rows


if __name__ == "__main__":
    print()
    print("| cut angle | split cubes | model | mean opening [um] |")
    print("|---|---|---|---|")
    for ang in (0.0, 25.0):
        for angle, policy, kind, n_split, w in oblique(ang):
            print(f"| {angle:g} deg | {n_split} ({policy}) | {kind} | {w * 1e6:.3f} |", flush=True)
