"""A config fit of Young's modulus alone: the first Jacobian call (compile + run) and three more
calls of `SeparatelyCompiled._host_tangents` along E, for a 3-D sphere indentation (quarter block
12 x 12 x 8 cells, 1,521 nodes, sparse solver, 5 depths). Run with PYTHONPATH of the tree to
measure: `python benchmarks/e_only_primal_program.py stable_neo_hookean`. CPU seconds (process time)."""
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
from difftissue.scenarios import Indentation, indentation_block
from difftissue.materials import Material
from difftissue.config.compile import SeparatelyCompiled

mesh = indentation_block((4e-3, 4e-3, 2e-3), (12, 12, 8), symmetry="quarter")
depth = np.linspace(2e-5, 1e-4, 5)
mat = Material(2e4, 0.45)
sc0 = Indentation(mesh, depth, np.ones(5), model=sys.argv[1], indenter="sphere", radius=1e-3, sigma=np.ones(5) * 1e-4)
force = np.asarray(sc0.predict(mat))
sc = Indentation(mesh, depth, force, model=sys.argv[1], indenter="sphere", radius=1e-3, sigma=np.abs(force) * 0.01)
c = SeparatelyCompiled(sc, fields=("youngs_modulus",))
v = np.array([2e4, 0.45, 0.0, 1000.0, 1.0, 1.0])[:len(c._leaves)]
T = np.zeros((1, len(c._leaves))); T[0, 0] = 1.0
t0 = time.process_time(); y, J = c._host_tangents(v, T); t1 = time.process_time()
times = []
for i in range(3):
    a = time.process_time(); y2, J2 = c._host_tangents(v * (1 + 0.01 * (i + 1)), T); times.append(time.process_time() - a)
print(sys.argv[1], "first call (compile+run) %.2f s, runs %s s, y0=%.12e J0=%.12e" % (t1 - t0, ["%.2f" % t for t in times], y[-1], J[0, -1]), "scales", c.scales_with_youngs_modulus)
