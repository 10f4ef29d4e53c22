"""Write data/punch_reference.vtu, the synthetic reference used by fem_field_punch.toml.

A 10 x 10 x 5 mm block (6 x 6 x 3 cubes, bonded base) indented 0.1 mm by a frictionless flat
punch of radius 2.6 mm, solved with the linear FEM at E = 12 kPa, nu = 0.42. The file holds
the `displacement` [m] and `reaction` [N] point fields and the node-set masks `bottom` and
`punch` (1 = member). Run from the repository root:

    python experiments/configs/make_punch_reference.py
"""

from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue import Material, block, write_mesh  # noqa: E402
from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.models import make_model  # noqa: E402
from difftissue.solvers import solve_static  # noqa: E402

mesh = block((0.01, 0.01, 0.005), (6, 6, 3))
p = np.asarray(mesh.points)
bottom = np.isclose(p[:, 2], 0.0)
punch = np.isclose(p[:, 2], 0.005) & (np.hypot(p[:, 0] - 0.005, p[:, 1] - 0.005) <= 2.6e-3)
bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(bottom)).fix(mesh, np.flatnonzero(punch), "z", (0, 0, -1e-4))
sol = solve_static(make_model(mesh, "fem_linear"), Material(12e3, 0.42), bc)
out = Path(__file__).resolve().parent / "data" / "punch_reference.vtu"
write_mesh(out, mesh, point_data={
    "displacement": np.asarray(sol.displacement),
    "reaction": np.asarray(sol.reaction),
    "bottom": bottom.astype(np.int32),
    "punch": punch.astype(np.int32),
}, overwrite=True)
print(f"wrote {out}: {mesh.n_nodes} nodes, punch force {float(-np.asarray(sol.reaction)[punch, 2].sum()) * 1e3:.4f} mN")
