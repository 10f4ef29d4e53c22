"""Curved incision against the flat one as R grows: max surface width and surface profile
(docs/dev/geometry.md, "Incision on a curved surface"). Usage: python benchmarks/curved_incision_convergence.py [model]."""
import sys, time
import numpy as np, jax
jax.config.update("jax_enable_x64", True)
from difftissue.cutting import ScalpelPath, cut_specimen
from difftissue.incision import Incision, IncisionOptions
from difftissue.materials import Material
from difftissue.mesh import block, curved_top, Specimen, TetMesh
MM = 1e-3
model = sys.argv[1] if len(sys.argv) > 1 else "fem_linear"
M = Material(2e5, 0.45, pre_stretch=1.05)
size, res = (10 * MM, 6 * MM, 2 * MM), (10, 6, 4)
b = block(size, res, origin=(-5 * MM, -3 * MM, 0.0))
flat_mesh = TetMesh(b.points, b.tets, b.region_ids, b.region_names)
OPT = IncisionOptions(scalpel_steps=1, rtol=1e-10)
path2 = [(-2 * MM, 0.0), (2 * MM, 0.0)]

def run(mesh, surface):
    t = time.process_time()
    cut = cut_specimen(Specimen(mesh, (M,)), ScalpelPath(path2, depth=1 * MM, surface=surface))
    r = Incision(cut, model=model, options=OPT).solve(M)
    sw = np.asarray(r.opening.surface_width)
    return cut, sw, float(np.max(sw)), time.process_time() - t

cut0, sw0, w0, t0 = run(flat_mesh, "top")
print(f"flat: max width {w0 * 1e6:.4f} um, {len(sw0)} surface pairs, {cut0.n_pairs} pairs ({t0:.1f} s CPU)")
for shape in ("sphere", "cylinder"):
    for R in (25, 50, 100, 200, 400, 1e4):
        m = curved_top(flat_mesh, R * MM, shape=shape)
        cut, sw, w, t = run(m, "boundary")
        same = cut.n_pairs == cut0.n_pairs and len(sw) == len(sw0)
        prof = np.max(np.abs(sw - sw0)) / w0 if len(sw) == len(sw0) else np.nan
        print(f"{shape:8s} R = {R:7g} mm: max width {w * 1e6:.4f} um, rel diff {(w - w0) / w0:+.3e}, profile max rel diff {prof:.3e}, "
              f"R x diff {(w - w0) / w0 * R:+.3f} mm, same pairs {same}, cut length {cut.length * 1e3:.5f} mm ({t:.1f} s)")
