"""Fitted-E error of the config's default (automatic) indentation specimen on exact Hertz
(sphere R = 1 mm to 20 um) or Sneddon (70 deg cone to 0.1 mm) data, E = 10 kPa, nu = 0.45 fixed.

The config is built as `difftissue fit` builds it (no `specimen`: the block of
`indentation_specimen_for`; 20 points; uniform sigma). fem_linear with nu fixed is linear in
E (the contact penalty scales with E), so the least-squares E is exact from one evaluation:
E_fit / E = sum(F_data g) / sum(g^2), g = F_model(E) / E. The mesh-corrected E is the
discretisation check's (first-order Richardson with the check's coarser specimen, linearised
through the fit's Jacobian: exact here).

    PYTHONPATH=. python experiments/indentation_default_fit.py {sphere,cone} [MODEL] [--m CELLS_PER_A] [--points N] [--solver full] [--max-steps N] [--nan-failures] [--compiled] [--out DIR]

--solver full builds the config's scenarios with ``Indentation(solver="full")`` (a Newton solve
of the whole specimen per depth, multigrid CG) in place of the condensed solve the config uses
for fem_linear under a sphere or cone (the same equilibrium to solver tolerance; the condensed
one's dense response columns ``(3 x candidates, 3 N)`` are what limits its memory at m = 8).

--compiled evaluates both meshes as the fit and the discretisation check do, through
``SeparatelyCompiled(scenario).evaluate`` (the forward-mode program: the prediction and one
zero tangent, so the condensation's custom derivative runs too) instead of ``scenario.predict``
(the primal alone).
"""
import sys, math, time, json, pathlib
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from difftissue.analytic import cone_force, hertz_force
from difftissue.config import load_config
from difftissue.materials import Material
E, NU = 1.0e4, 0.45


def write_config(ind: str, model: str, *, m=None, points=None, max_steps=None) -> pathlib.Path:
    """A fit config on exact data (200 samples of Hertz, sphere R = 1 mm to 20 um, or Sneddon,
    70 deg cone to 0.1 mm; E, NU) with the automatic 3-D block (``m`` cells per contact radius,
    None: the rule's), in a new temporary directory; returns the path of its fit.toml."""
    import tempfile

    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f"indent_{ind}_"))
    if ind == "sphere":
        R, D = 1e-3, 2e-5; dd = np.linspace(D / 200, D, 200); F = np.asarray(hertz_force(dd, E, NU, R)); ind_t = f'{{ shape = "sphere", radius = {R} }}'
    else:
        th, D = math.radians(70.0), 1e-4; dd = np.linspace(D / 200, D, 200); F = np.asarray(cone_force(dd, E, NU, th)); ind_t = '{ shape = "cone", half_angle_deg = 70.0 }'
    (tmp / "curve.csv").write_text("depth,force\n" + "".join(f"{a:.12g},{b:.12g}\n" for a, b in zip(dd, F)))
    (tmp / "fit.toml").write_text(f'''title = "exact {ind}"
[material]
youngs_modulus = {E}
poisson_ratio = {NU}
[fit]
parameters = ["youngs_modulus"]
[[experiment]]
name = "ind"
scenario = "indentation"
model = "{model}"
{'' if points is None else f'points = {points}'}
data = {{ format = "table", path = "curve.csv", columns = {{ depth = {{ name = "depth", unit = "m" }}, force = {{ name = "force", unit = "N" }} }} }}
indenter = {ind_t}
{'' if max_steps is None else f'solver = {{ max_steps = {max_steps} }}'}
specimen = {{ geometry = "3d"{'' if m is None else f', cells_per_contact_radius = {m}'} }}  # the automatic 3-D block (the config default is axisymmetric for fem sphere/cone)
''')
    return tmp / "fit.toml"


def main():
    import argparse
    _ap = argparse.ArgumentParser()
    _ap.add_argument("indenter", choices=["sphere", "cone"])
    _ap.add_argument("model", nargs="?", default="fem_linear")
    _ap.add_argument("--out", default="experiments/results")
    _ap.add_argument("--points", type=int, default=None, help="data points fitted (default: the config's, 20)")
    _ap.add_argument("--m", type=float, default=None, help="cells per contact radius (default: the rule's)")
    _ap.add_argument("--solver", choices=["auto", "full"], default="auto", help="Indentation(solver=...): the config's 'auto' (condensed for fem_linear) or 'full'")
    _ap.add_argument("--max-steps", type=int, default=None, help="the config's solver.max_steps (default: SolverOptions', 50)")
    _ap.add_argument("--compiled", action="store_true", help="evaluate through SeparatelyCompiled(...).evaluate (the fit's and the check's forward-mode program) instead of scenario.predict")
    _ap.add_argument("--nan-failures", action="store_true", help="SolverOptions(failure='nan'): a depth whose solve fails predicts NaN (shows which depths fail) instead of raising")
    _args = _ap.parse_args()
    if _args.nan_failures:
        import functools
        import difftissue.config.builders as _builders
        _builders.SolverOptions = functools.partial(_builders.SolverOptions, failure="nan")
    if _args.solver != "auto":
        import functools
        import difftissue.config.builders as _builders
        _builders.Indentation = functools.partial(_builders.Indentation, solver=_args.solver)
    ind, model = _args.indenter, _args.model
    out_dir = pathlib.Path(_args.out)
    cfg = load_config(write_config(ind, model, m=_args.m, points=_args.points, max_steps=_args.max_steps))
    ex = cfg.experiments[0]
    for n in ex.notes: print("NOTE", n[:400])
    sc = ex.scenario
    depth = np.asarray(sc.depth) if hasattr(sc, "depth") else None
    mat = Material(youngs_modulus=E, poisson_ratio=NU)
    if _args.compiled:
        from difftissue.config import SeparatelyCompiled
        predict = lambda s, m: SeparatelyCompiled(s).evaluate(m)  # noqa: E731
    else:
        predict = lambda s, m: s.predict(m)  # noqa: E731
    t0 = time.process_time(); pf = np.asarray(predict(sc, mat)); tf = time.process_time() - t0
    obs = np.asarray(sc.observed) if hasattr(sc, "observed") else None
    print("depths", len(pf), "obs", None if obs is None else obs[-1])
    t0 = time.process_time(); csc, info = ex.coarsen(); pc = np.asarray(predict(csc, mat)); tc = time.process_time() - t0
    g, gc = pf / E, pc / E
    Efit = float(obs @ g / (g @ g))
    r = info["refinement_ratio"]
    e_rel = float(g @ ((gc - g) / (r - 1.0)) / (g @ g))  # E_fit - E_conv = -E_fit*... ; corrected = E_fit (1 + e_rel)
    Ecorr = Efit * (1 + e_rel)
    out = {"indenter": ind, "model": model, "cells_per_contact_radius": (info.get("specimen") or {}).get("cells_per_contact_radius"),
           "points": len(pf), "coarse_nodes": int(np.prod(np.asarray(info["coarse_cells"]) + 1)) if isinstance(info["coarse_cells"], list) else None, "nodes": int(np.prod(np.asarray(info["fine_cells"]) + 1)) if isinstance(info.get("fine_cells"), list) else None, "specimen": info.get("specimen"),
           "coarse_cells": info["coarse_cells"], "ratio": r, "force_err_maxdepth": float(pf[-1] / obs[-1] - 1), "coarse_force_err_maxdepth": float(pc[-1] / obs[-1] - 1),
           "solver": _args.solver, "max_steps": _args.max_steps, "compiled": _args.compiled, "E_fit_err": Efit / E - 1, "E_corrected_err": Ecorr / E - 1, "cpu_fine_s": tf, "cpu_coarse_s": tc,
           "force_err_per_depth": list(pf / obs - 1), "coarse_err_per_depth": list(pc / obs - 1)}
    print(json.dumps(out))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"indentation_default_fit_{ind}_{model}{'' if _args.m is None else f'_m{_args.m:g}'}{'' if _args.points is None else f'_p{_args.points}'}{'' if _args.solver == 'auto' else f'_{_args.solver}'}{'' if _args.max_steps is None else f'_s{_args.max_steps}'}{'_compiled' if _args.compiled else ''}.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
