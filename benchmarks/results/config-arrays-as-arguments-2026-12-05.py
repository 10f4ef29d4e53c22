"""108k (cells_per_contact_radius 6) automatic 3-D sphere indentation through the config path:
SeparatelyCompiled forward (value) + one-tangent JVP. argv: model cells_per_a [direct]"""
import sys, time, resource, os, tempfile
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
from difftissue import analytic
from difftissue.config import load_config, SeparatelyCompiled
from difftissue.materials import Material

model, m = sys.argv[1], float(sys.argv[2])
direct = len(sys.argv) > 3 and sys.argv[3] == "direct"
d = np.array([10e-6, 15e-6, 20e-6])
f = np.asarray(analytic.hertz_force(d, 1e4, 0.45, 1e-3))
tmp = tempfile.mkdtemp(prefix=f"cfg-{model}-{m}-")
open(f"{tmp}/s.csv", "w").write("depth (um),force (uN)\n" + "\n".join(f"{a*1e6:.9f},{b*1e6:.12g}" for a, b in zip(d, f)) + "\n")
open(f"{tmp}/s.toml", "w").write(f"""[material]
youngs_modulus = 7e3
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus", "poisson_ratio"]
[[experiment]]
name = "s"
scenario = "indentation"
model = "{model}"
data = {{ format = "table", path = "s.csv", columns = {{ depth = "depth (um)", force = "force (uN)" }} }}
indenter = {{ shape = "sphere", radius = 1.0, length_unit = "mm" }}
length_unit = "um"
specimen = {{ geometry = "3d", cells_per_contact_radius = {m} }}
""")
t0 = time.process_time(); w0 = time.perf_counter()
cfg = load_config(f"{tmp}/s.toml")
sc = cfg.experiments[0].scenario
print("unknowns", 3 * sc.model.n_nodes, "condensed", getattr(sc, "condensation", None) is not None, flush=True)
t1 = time.process_time()
mat = Material(7e3, 0.45)
if direct:
    y = np.asarray(sc.predict(mat))
    t2 = time.process_time()
    y2, ty = jax.jvp(lambda nu: sc.predict(Material(7e3, nu)), (0.45,), (1.0,))
else:
    w = cfg.fit_scenarios()[0]
    assert isinstance(w, SeparatelyCompiled)
    y = w.evaluate(mat)
    t2 = time.process_time()
    y2, ty = jax.jvp(lambda nu: w.predict(Material(7e3, nu)), (0.45,), (1.0,))
t3 = time.process_time()
print(f"RESULT model={model} m={m} direct={direct} unknowns={3*sc.model.n_nodes} build_cpu={t1-t0:.2f} value_cpu={t2-t1:.2f} jvp_cpu={t3-t2:.2f} "
      f"total_cpu={t3-t0:.2f} wall={time.perf_counter()-w0:.2f} maxrss_gb={resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1e6:.2f}")
print("y", repr(np.asarray(y)), "jvp_y", repr(np.asarray(y2)), "tangent", repr(np.asarray(ty)))
