"""Mesh convergence of simulated sphere and cone indentation on the automatic specimen.

fem_linear (condensed contact), quarter model, bonded base, on
:func:`difftissue.scenarios.indentation_specimen_for` blocks with m = a / refine cells per
contact radius at the largest depth. For each level: the force at the largest depth against
Hertz (sphere) or Sneddon (cone); Richardson extrapolation from the three finest levels (the
observed order p from the ratios of the differences); the relative error of each level
against the extrapolated force and the fit ``err = C m^-p`` used by
:data:`~difftissue.scenarios.INDENTATION_FORCE_ERROR`. A second table varies the block's
extent (half-width = thickness, in contact radii) at fixed m against the exact bonded-layer
factor :func:`~difftissue.analytic.layer_sphere_factor`.

    python experiments/indentation_resolution.py [--indenters sphere] [--levels 2 3 4 6] [--extents 50 100 200 400]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.optimize import brentq  # noqa: E402

from difftissue.analytic import cone_force, hertz_force, layer_sphere_factor  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.scenarios import HALF_SPACE_EXTENT, Indentation, indentation_specimen_for  # noqa: E402

E, NU = 1.0e4, 0.45
CASES = {
    # sphere R = 1 mm to d/R = 0.02 (a = 0.141 mm; an exact sphere and Hertz's paraboloid differ by ~0.2 %)
    "sphere": {"radius": 1e-3, "max_depth": 2e-5},
    # 70 degree cone to 0.1 mm (a = 0.175 mm)
    "cone": {"half_angle": math.radians(70.0), "max_depth": 1e-4},
}


def force(indenter: str, m: float, extent: float = HALF_SPACE_EXTENT) -> tuple[float, dict]:
    case = CASES[indenter]
    spec = indentation_specimen_for(indenter, cells_per_contact_radius=m, extent=extent, **case)
    mesh = spec.block()
    kw = {"radius": case["radius"]} if indenter == "sphere" else {"half_angle": case["half_angle"]}
    d = case["max_depth"]
    t0 = time.process_time()
    sc = Indentation(mesh, [0.5 * d, d], model="fem_linear", indenter=indenter, base="bonded", symmetry="quarter", **kw)
    f = float(np.asarray(sc.predict(Material(youngs_modulus=E, poisson_ratio=NU)))[-1])
    ref = float(hertz_force(d, E, NU, case["radius"]) if indenter == "sphere" else cone_force(d, E, NU, case["half_angle"]))
    return f, {"m": m, "extent": extent, "cells": list(spec.cells), "nodes": int(mesh.points.shape[0]), "force_N": f,
               "vs_analytic": f / ref - 1.0, "cpu_s": time.process_time() - t0, "contact_radius_m": spec.contact_radius}


def richardson(h, f):
    """Observed order and extrapolated value from the last three (h decreasing) levels."""
    (h1, h2, h3), (f1, f2, f3) = h[-3:], f[-3:]
    ratio = (f1 - f2) / (f2 - f3)
    p = brentq(lambda p: (h1**p - h2**p) / (h2**p - h3**p) - ratio, 0.05, 8.0)
    return p, f3 - (f2 - f3) / ((h2 / h3) ** p - 1.0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--indenters", nargs="+", default=["sphere", "cone"])
    ap.add_argument("--levels", nargs="+", type=float, default=[2, 3, 4, 6])
    ap.add_argument("--extents", nargs="*", type=float, default=[])
    ap.add_argument("--extent-level", type=float, default=4)
    ap.add_argument("--out", default="experiments/results/indentation_resolution.json")
    args = ap.parse_args()
    out = {}
    for ind in args.indenters:
        rows = []
        for m in args.levels:
            f, r = force(ind, m)
            rows.append(r)
            print(ind, json.dumps(r), flush=True)
        h = np.array([1.0 / r["m"] for r in rows])
        fs = np.array([r["force_N"] for r in rows])
        p, f_inf = richardson(h, fs)
        err = fs / f_inf - 1.0
        # err = C m^-p fitted (log-log least squares) on the three finest levels
        sl = slice(-3, None)
        slope, icpt = np.polyfit(np.log([r["m"] for r in rows])[sl], np.log(np.abs(err[sl])), 1)
        C, q = float(math.copysign(math.exp(icpt), err[-1])), float(-slope)
        ref = rows[-1]["force_N"] / (1.0 + rows[-1]["vs_analytic"])
        chosen = next((r["m"] for r, e in zip(rows, err) if abs(e) <= 0.01), None)
        out[ind] = {"rows": [{**r, "error_vs_extrapolated": float(e)} for r, e in zip(rows, err)], "order": float(p),
                    "extrapolated_N": float(f_inf), "extrapolated_vs_analytic": float(f_inf / ref - 1.0), "fit_C": C, "fit_p": q,
                    "coarsest_within_1pc": chosen}
        print(f"\n{ind}: observed order {p:.3f}, extrapolated force {f_inf:.6g} N ({100 * (f_inf / ref - 1):+.2f} % vs analytic), "
              f"err = {C:.4g} m^-{q:.3f}, coarsest level within 1 %: m = {chosen}")
        print("| m = a/refine | cells (quarter) | nodes | force vs analytic | vs extrapolated | CPU s |\n|---|---|---|---|---|---|")
        for r, e in zip(rows, err):
            print(f"| {r['m']:g} | {r['cells']} | {r['nodes']} | {100 * r['vs_analytic']:+.2f} % | {100 * e:+.2f} % | {r['cpu_s']:.0f} |")
    if args.extents and "sphere" in args.indenters:
        rows = []
        for x in args.extents:
            f, r = force("sphere", args.extent_level, extent=x)
            r["layer_factor_exact"] = float(layer_sphere_factor(1.0 / x, NU, base="bonded")) - 1.0
            rows.append(r)
            print("extent", json.dumps(r), flush=True)
        out["extent"] = rows
        print(f"\n| extent (a) | cells (quarter) | force vs Hertz | change from the largest | exact layer stiffening (chi = 1/extent) |\n|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['extent']:g} | {r['cells']} | {100 * r['vs_analytic']:+.2f} % | {100 * (r['force_N'] / rows[-1]['force_N'] - 1):+.2f} % | "
                  f"{100 * r['layer_factor_exact']:+.2f} % |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
