"""Volumetric locking of linear tets and the nodal-averaged (locking-free) FEM models.

Two problems at nu = 0.45, 0.49, 0.499, each on a sequence of meshes halving the cell size,
solved with the standard tets (``fem_linear`` / ``fem_neo_hookean``: the whole density per
tet) and with the nodal volumetric term (``fem_linear_nodal`` / ``fem_neo_hookean_nodal``):

(a) Bonded compression (``fem_linear``): a 1 x 1 x 0.25 block (E = 1 Pa) bonded to two rigid
    platens, compressed by 1 %; a quarter model (symmetry rollers on x = 0 and y = 0). The
    observable is the apparent modulus ``F / (A eps) / E`` (for nu -> 1/2 it grows like the
    shape factor squared: the reference is the Richardson extrapolation of the finest meshes).
    Cells along the height: 2, 4, 8, 16.
(b) Incision of a pre-tensioned membrane (``fem_neo_hookean``): 8 x 8 x 1 mm, E = 100 kPa,
    pre-stretch 1.1 in-plane, lateral faces held, base sliding (u_z = 0); a straight snapped cut
    through the whole thickness, 4 mm long, across the centre. Observable: the largest surface
    opening width. Cells per cut length: 4, 8, 16 (through the thickness: 1, 2, 4).
    One row with ``stable_neo_hookean`` (the XPBD model's energy: per-tet volume term) shows how
    it behaves at the same nu.
(c) Sphere indentation (``fem_linear``): a rigid frictionless sphere R = 1 mm (penalty contact,
    ``difftissue.scenarios.Indentation``) pressed 0.1 mm (d/R = 0.1) into a block, E = 10 kPa,
    bonded base, quarter model (rollers on x = 0 and y = 0). The block is the library's
    automatic specimen (``indentation_specimen_for``) with ``m`` cells per Hertz contact radius
    ``a = sqrt(R d)`` (uniform core of 1.5 a, cells growing by 1.3 beyond) and half-width =
    thickness = 6 a (a finite block: Hertz is a half-space). Observable: the force at the deepest
    depth (the force at 0.05 mm is kept too). Levels m: 2, 4, 8.

Observed order from three successive meshes ``p = log2((f1 - f2) / (f2 - f3))`` and Richardson
extrapolation ``f3 + (f3 - f2) / (2^p - 1)`` (with p = 1 when the sequence is not monotone).

Writes experiments/results/locking_free.json (refused if it exists unless --force).
Run: python experiments/locking_free.py [--part a|b|c|all] [--force]
Part (c) one level per process: --part c --kinds fem_linear_nodal --levels 8 --nus 0.499 --tag _nodal_0.499_8,
then --merge experiments/results/locking_free_c.json experiments/results/locking_free_c_*.json
Tables: python experiments/locking_free.py --table experiments/results/locking_free_a.json experiments/results/locking_free_b.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from difftissue.boundary import BoundaryConditions  # noqa: E402
from difftissue.cutting import ScalpelPath, cut_specimen  # noqa: E402
from difftissue.incision import Incision, IncisionOptions  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import Specimen, block  # noqa: E402
from difftissue.models import make_model  # noqa: E402
from difftissue.scenarios import Indentation, SolverOptions, indentation_specimen_for  # noqa: E402
from difftissue.solvers.static import solve_static  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
NUS = (0.45, 0.49, 0.499)

# (a) bonded compression, quarter model
W, H, STRAIN = 0.5, 0.25, 0.01
LEVELS_A = (2, 4, 8, 16)
# (b) membrane incision
L, T, C, E_B, PRE = 8e-3, 1e-3, 4e-3, 1e5, 1.1
LEVELS_B = (4, 8, 16)
# (c) sphere indentation, quarter model of the automatic specimen
R_C, E_C, EXTENT_C = 1e-3, 1e4, 6.0
DEPTHS_C = (5e-5, 1e-4)
LEVELS_C = (2, 4, 8)


def richardson(values):
    """Observed order and extrapolated value from the last three of a sequence on meshes of
    halving size: ``(p, f_inf)``; ``p`` is None (and ``f_inf`` uses p = 1) when the last
    differences change sign."""
    if len(values) < 3:
        return None, None
    f1, f2, f3 = values[-3:]
    d1, d2 = f1 - f2, f2 - f3
    if d1 * d2 <= 0 or d2 == 0:
        return None, f3 + (f3 - f2)
    p = math.log2(d1 / d2)
    if p <= 0.05:  # the differences do not shrink: no extrapolation
        return p, None
    return p, f3 + (f3 - f2) / (2.0**p - 1.0)


def table(paths):
    """Markdown tables of the result files (order and extrapolation recomputed from the values)."""
    for path in paths:
        res = json.loads(Path(path).read_text())
        for name, part in res.items():
            rows = part["rows"]
            levels = sorted({m for r in rows for m in r["levels"]})  # a row without a level shows "–" there
            scale = 1e3 if ("opening" in part["observable"] or "force" in part["observable"]) else 1.0
            unit = " (in mN)" if "force" in part["observable"] else " [mm]" if scale == 1e3 else ""
            print(f"\n{name}: {part['observable']}{unit}; levels = {part['levels']}\n")
            print("| model | nu | " + " | ".join(str(m) for m in levels) + " | observed order | Richardson | finest vs Richardson |")
            print("|---" * (len(levels) + 5) + "|")
            for r in rows:
                p, ext = richardson(r["values"])
                dev = "" if ext is None else f"{100 * (r['values'][-1] / ext - 1):+.1f} %"
                by_level = dict(zip(r["levels"], r["values"]))
                print(f"| {r['model']} | {r['poisson_ratio']} | " + " | ".join("–" if m not in by_level else f"{scale * by_level[m]:.4g}" for m in levels)
                      + f" | {'n/a' if p is None else f'{p:.2f}'} | {'none' if ext is None else f'{scale * ext:.4g}'} | {dev} |")


def apparent_modulus(kind, m, nu):
    """``F / (A eps) / E`` of the bonded block with ``m`` cells through the height."""
    mesh = block((W, W, H), (2 * m, 2 * m, m))
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}, "xyz").fix(mesh, {"face": "z-max"}, "xyz", (0.0, 0.0, -STRAIN * H))
    bc = bc.fix(mesh, {"face": "x-min"}, "x").fix(mesh, {"face": "y-min"}, "y")
    sol = solve_static(make_model(mesh, kind), Material(1.0, nu), bc, linear_solver="sparse", rtol=1e-10)
    top = np.asarray(mesh.points)[:, 2] > H - 1e-12
    return -float(jnp.sum(sol.reaction[top, 2])) / (W * W * STRAIN)


def membrane_cut(n):
    h = C / n
    spec = Specimen(block((L, L, T), (int(round(L / h)), int(round(L / h)), max(1, int(round(T / h))))), (Material(E_B, 0.45, pre_stretch=PRE),))
    return cut_specimen(spec, ScalpelPath([(0.5 * (L - C), 0.5 * L), (0.5 * (L + C), 0.5 * L)], depth=T, through=True))


def opening(kind, n, nu):
    """Largest surface opening [m] of the membrane cut with ``n`` cells along the cut."""
    cut = membrane_cut(n)
    inc = Incision(cut, model=kind, base="sliding", options=IncisionOptions(scalpel_steps=2, max_steps=100, linear_solver="sparse"))
    return float(inc.solve(Material(E_B, nu, pre_stretch=PRE)).opening.max_width)


def indentation_specimen(m):
    """The automatic sphere-indentation specimen of part (c) with ``m`` cells per contact radius."""
    return indentation_specimen_for("sphere", radius=R_C, max_depth=DEPTHS_C[-1], model="fem_linear", cells_per_contact_radius=m, extent=EXTENT_C)


def indentation_curve(kind, m, nu):
    """Force [N] of the whole specimen at each depth of ``DEPTHS_C`` (quarter model x 4), with
    ``m`` cells per contact radius; ``fem_linear`` is solved condensed onto the surface, the
    others by Newton on the whole block (sparse direct solver): the same equilibrium."""
    sc = Indentation(indentation_specimen(m).block(), DEPTHS_C, model=kind, indenter="sphere", radius=R_C, base="bonded", symmetry="quarter",
                     options=SolverOptions(linear_solver="sparse"))
    return [float(f) for f in np.asarray(sc.predict(Material(E_C, nu)))]


def indentation_force(kind, m, nu):
    """Force [N] at the deepest depth and the force-depth curve (see :func:`indentation_curve`)."""
    curve = indentation_curve(kind, m, nu)
    return curve[-1], {"depths": list(DEPTHS_C), "forces": curve}


def hertz(d, nu):
    """Hertz force [N] of the sphere on a half-space: ``4/3 E/(1-nu^2) R^1/2 d^3/2``."""
    return 4.0 / 3.0 * E_C / (1.0 - nu**2) * math.sqrt(R_C) * d**1.5


PARTS = {
    "a": ("bonded_compression", apparent_modulus, "apparent modulus F / (A eps E) [-]", "cells through the height", LEVELS_A),
    "b": ("membrane_incision", opening, "largest surface opening [m]", "cells along the cut", LEVELS_B),
    "c": ("sphere_indentation", indentation_force, "force at the deepest depth (0.1 mm) [N]", "cells per contact radius", LEVELS_C),
}


def study(fn, kinds, levels, nus=NUS):
    rows = []
    for kind in kinds:
        for nu in nus:
            t = time.process_time()
            vals, extra = [], []
            for m in levels:
                v = fn(kind, m, nu)
                if isinstance(v, tuple):  # (value, per-level details)
                    v, info = v
                    extra.append(info)
                vals.append(v)
            p, ext = richardson(vals)
            ext = float("nan") if ext is None else ext
            rows.append({"model": kind, "poisson_ratio": nu, "levels": list(levels), "values": vals, "observed_order": p, "richardson": ext,
                         "cpu_seconds": time.process_time() - t, **({"curves": extra} if extra else {})})
            print(kind, nu, " ".join(f"{v:.5g}" for v in vals), "p =", None if p is None else round(p, 2), "ext =", ext, flush=True)
    return rows


def merge(out, paths, force=False):
    """One result file from runs of single levels (``--kinds ... --levels m``): the rows of
    each (part, model, nu) joined in level order, order and extrapolation recomputed."""
    out = Path(out)
    if out.exists() and not force:
        raise SystemExit(f"{out} exists; pass --force to overwrite")
    res = {}
    for path in paths:
        for name, part in json.loads(Path(path).read_text()).items():
            dst = res.setdefault(name, {"observable": part["observable"], "levels": part["levels"], "rows": {}})
            for r in part["rows"]:
                row = dst["rows"].setdefault((r["model"], r["poisson_ratio"]), {"model": r["model"], "poisson_ratio": r["poisson_ratio"], "by_level": {}})
                for i, m in enumerate(r["levels"]):
                    row["by_level"][m] = (r["values"][i], r["curves"][i] if "curves" in r else None, r["cpu_seconds"] if len(r["levels"]) == 1 else None)
    for name, part in res.items():
        rows = []
        for row in part["rows"].values():
            ms = sorted(row["by_level"])
            vals = [row["by_level"][m][0] for m in ms]
            p, ext = richardson(vals)
            rows.append({"model": row["model"], "poisson_ratio": row["poisson_ratio"], "levels": ms, "values": vals, "observed_order": p,
                         "richardson": float("nan") if ext is None else ext, "cpu_seconds_per_level": [row["by_level"][m][2] for m in ms],
                         **({"curves": [row["by_level"][m][1] for m in ms]} if row["by_level"][ms[0]][1] is not None else {})})
        part["rows"] = sorted(rows, key=lambda r: (r["model"], r["poisson_ratio"]))
    out.write_text(json.dumps(res, indent=1))
    print("wrote", out)


def main(part="all", force=False, kinds=None, levels=None, nus=None, tag=""):
    if kinds:  # one part, chosen models / levels / nu (a rerun of rows that ran out of memory; one level per process)
        name, fn, observable, level_name, default_levels = PARTS[part]
        rows = study(fn, tuple(kinds), tuple(levels or default_levels), tuple(nus or NUS))
        out = RESULTS / f"locking_free_{part}{tag}.json"
        if out.exists() and not force:
            raise SystemExit(f"{out} exists; pass --force to overwrite")
        out.write_text(json.dumps({name: {"observable": observable, "levels": level_name, "rows": rows}}, indent=1))
        print("wrote", out)
        return
    out = RESULTS / "locking_free.json"
    if out.exists() and not force:
        raise SystemExit(f"{out} exists; pass --force to overwrite")
    res = {}
    if part in ("a", "all"):
        res["bonded_compression"] = {"observable": "apparent modulus F / (A eps E) [-]", "levels": "cells through the height",
                                     "rows": study(apparent_modulus, ("fem_linear", "fem_linear_nodal"), LEVELS_A)}
    if part in ("b", "all"):
        res["membrane_incision"] = {"observable": "largest surface opening [m]", "levels": "cells along the cut",
                                    "rows": study(opening, ("fem_neo_hookean", "fem_neo_hookean_nodal"), LEVELS_B)
                                    + study(opening, ("stable_neo_hookean",), LEVELS_B, nus=(0.499,))}
    if part in ("c", "all"):  # the nodal model's finest level needs its own process (memory): see the docstring
        res["sphere_indentation"] = {"observable": PARTS["c"][2], "levels": PARTS["c"][3],
                                     "rows": study(indentation_force, ("fem_linear", "fem_linear_nodal"), LEVELS_C)}
    RESULTS.mkdir(exist_ok=True)
    name = out if part == "all" else out.with_name(f"locking_free_{part}.json")
    name.write_text(json.dumps(res, indent=1))
    print("wrote", name)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="all", choices=("a", "b", "c", "all"))
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--kinds", nargs="+", help="only these models (with --part a, b or c)")
    ap.add_argument("--levels", nargs="+", type=int, help="mesh levels for --kinds")
    ap.add_argument("--nus", nargs="+", type=float, help="Poisson ratios for --kinds")
    ap.add_argument("--tag", default="", help="suffix of the result file for --kinds")
    ap.add_argument("--table", nargs="+", metavar="JSON", help="print the Markdown tables of result files and exit")
    ap.add_argument("--merge", nargs="+", metavar="JSON", help="OUT IN...: join single-level result files into OUT and exit")
    a = ap.parse_args()
    if a.merge:
        merge(a.merge[0], a.merge[1:], a.force)
    elif a.table:
        table(a.table)
    else:
        main(a.part, a.force, a.kinds, a.levels, a.nus, a.tag)
