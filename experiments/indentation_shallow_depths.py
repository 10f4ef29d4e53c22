"""Shallow depths of the default-config indentation fits (docs/dev/indentation-resolution.md):
cells per contact radius at each depth (Indentation.resolution on the configs
experiments/indentation_default_fit.py builds), the stored per-depth force errors of its runs,
and the least-squares E (exact: fem_linear at fixed nu is linear in E) with all depths, without
those below 1 and below 2 cells per contact radius, for uniform sigma (the config's) and for
sigma proportional to the force. No solve: about 10 s.

    PYTHONPATH=. python experiments/indentation_shallow_depths.py
"""
import math, numpy as np, pathlib, tempfile, warnings
from difftissue import analytic
from difftissue.config import load_config
for ind in ("sphere", "cone"):
    tmp = pathlib.Path(tempfile.mkdtemp())
    if ind == "sphere":
        R, D = 1e-3, 2e-5; dd = np.linspace(D/200, D, 200); F = np.asarray(analytic.hertz_force(dd, 1e4, 0.45, R)); t = f'{{ shape = "sphere", radius = {R} }}'
    else:
        th, D = math.radians(70.0), 1e-4; dd = np.linspace(D/200, D, 200); F = np.asarray(analytic.cone_force(dd, 1e4, 0.45, th)); t = '{ shape = "cone", half_angle_deg = 70.0 }'
    (tmp/"curve.csv").write_text("depth,force\n" + "".join(f"{a:.12g},{b:.12g}\n" for a, b in zip(dd, F)))
    (tmp/"fit.toml").write_text(f'''title = "x"
[material]
youngs_modulus = 1e4
poisson_ratio = 0.45
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "ind"
scenario = "indentation"
model = "fem_linear"
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "m" }}, force = {{ name = "force", unit = "N" }} }} }}
indenter = {t}
specimen = {{ geometry = "3d" }}  # the automatic 3-D block (the config default is axisymmetric for fem sphere/cone)
''')
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        cfg = load_config(tmp/"fit.toml")
    r = cfg.experiments[0].provenance["resolution"]
    print(ind, [ (round(f["depth"]/D,3), round(f["cells_per_contact_radius"],3)) for f in r["flagged"]], r["cells_per_contact_radius_range"], [x.category.__name__ for x in w])
    import json
    sc = cfg.experiments[0].scenario; sc = getattr(sc, "scenario", sc)
    m = sc.resolution().cells_per_contact_radius
    d = json.load(open(f"/work/wt-shallow/experiments/results/indentation_default_fit_{ind}_fem_linear.json"))
    for i in range(6):
        print(f"  m={m[i]:.2f} err={100*d['force_err_per_depth'][i]:+.1f}%   m={m[i]/2:.2f} err={100*d['coarse_err_per_depth'][i]:+.1f}%")
    print("  m>=1 fine max err", max(e for mm, e in zip(m, d['force_err_per_depth']) if mm >= 1), "coarse m in [1,2]", [round(100*e,1) for mm, e in zip(m/2, d['coarse_err_per_depth']) if mm >= 1])
    e = np.asarray(d['force_err_per_depth']); o = np.asarray(sc.observed); keep = sc.resolution().keep
    def efit(k): return float(np.sum(o[k]**2 * (1+e[k])) / np.sum(o[k]**2 * (1+e[k])**2) - 1)
    keep2 = sc.resolution(2.0).keep
    print(f"  E err all {100*efit(np.ones_like(keep)):+.2f}%  drop<1: {100*efit(keep):+.2f}% ({(~keep).sum()} dropped)  drop<2: {100*efit(keep2):+.2f}% ({(~keep2).sum()} dropped)")
    def erel(k): return float(np.sum(1+e[k]) / np.sum((1+e[k])**2) - 1)
    print(f"  sigma ∝ F: E err all {100*erel(np.ones_like(keep)):+.2f}%  drop<1: {100*erel(keep):+.2f}%  drop<2: {100*erel(keep2):+.2f}%")
