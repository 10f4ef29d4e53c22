"""Budget calibration over a load set vs the single-load calibration (docs/experiments.md).

The tuned case of experiments/budget_indentation.py (a 10 x 10 x 5 mm block of 2.5 mm cubes,
``springs_volume``, E = 10 kPa, nu = 0.45, base bonded, bonded flat punch of radius 3 mm pushed
0.1 mm; standard XPBD, Gauss-Seidel, dt = 3 ms, 10 iterations) calibrated alone, and its card
applied to the set a simulator meets: deeper pushes (0.2, 0.4 mm), a platen (0.1 mm), a sphere
(R = 10 mm, 0.2 mm) and a 4x stiffer / softer tissue; against the load-set calibration of that
set (``calibrate_for_load_set``) at the tuned budget and at the budget it proposes. Reference:
the static solve of the same model (the budget's bias alone). Errors: signed relative errors of
the indenter force of the budgeted XPBD rest state at the card's modulus. Held-out loads (not in
the set, inside its range) show the card between its nodes. Then the saturated settings
(1.25 mm cells at dt = 3 ms, 2.5 mm cells at dt = 1/60 s): sensitivity and proposal.

Run:  python experiments/budget_load_set.py   (prints Markdown tables)
"""

from __future__ import annotations

import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue.budget import _LoadSet, calibrate_for_budget, calibrate_for_load_set, indentation_load  # noqa: E402
from difftissue.errors import BudgetSaturationError  # noqa: E402
from difftissue.materials import Material  # noqa: E402
from difftissue.mesh import block  # noqa: E402
from difftissue.models import make_model  # noqa: E402
from difftissue.solvers.xpbd import XPBDSettings  # noqa: E402

SIZE = (0.01, 0.01, 0.005)
MATERIAL = Material(youngs_modulus=10e3, poisson_ratio=0.45)


def settings(dt=3e-3, substeps=1, iterations=10):
    return XPBDSettings(dt=dt, substeps=substeps, iterations=iterations, method="gauss_seidel", warm_start=False)


def the_set(mesh):
    return [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, name="punch 0.1 mm (tuned)"),
            indentation_load(mesh, "flat_punch", 2e-4, radius=3e-3, name="punch 0.2 mm"),
            indentation_load(mesh, "flat_punch", 4e-4, radius=3e-3, name="punch 0.4 mm"),
            indentation_load(mesh, "platen", 1e-4, name="platen 0.1 mm"),
            indentation_load(mesh, "sphere", 2e-4, radius=10e-3, name="sphere 0.2 mm"),
            indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=40e3, name="punch, 4x stiffer"),
            indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=2.5e3, name="punch, 4x softer")]


def held_out(mesh):
    return [indentation_load(mesh, "flat_punch", 3e-4, radius=3e-3, name="held out: punch 0.3 mm"),
            indentation_load(mesh, "sphere", 4e-4, radius=10e-3, name="held out: sphere 0.4 mm"),
            indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=20e3, name="held out: punch, 2x stiffer"),
            indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=5e3, name="held out: punch, 2x softer"),
            indentation_load(mesh, "platen", 1e-4, youngs_modulus=20e3, name="held out: platen, 2x stiffer")]


def card_errors(mesh, loads, st, card_youngs, nu=None):
    """Signed force errors of the budgeted XPBD at the card's moduli against the static reference."""
    ls = _LoadSet(mesh, make_model(mesh, "springs_volume"), MATERIAL, loads, 1e-10, 5000)
    F_ref = ls.references(ls.model, "springs_volume")
    F, s, ok = ls.response(np.array([card_youngs(E) for E in ls.youngs]), st, nu)
    assert np.all(ok)
    return F / F_ref - 1.0, s


def fmt(e):
    return f"{100 * e:+.1f} %"


def main() -> None:
    t0 = time.process_time()
    mesh = block(SIZE, (4, 4, 2))
    loads, extra = the_set(mesh), held_out(mesh)
    names = [ld.label() for ld in loads + extra]
    cols, notes = {}, []
    for sub in (1, 2):
        st = settings(substeps=sub)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            single = calibrate_for_budget(mesh, "springs_volume", MATERIAL, loads[0].bc, st)
        r = single.ratio()
        e, s = card_errors(mesh, loads + extra, st, lambda E: E * r)
        cols[f"single-load card, {sub} substep(s) (E x {r:.4f})"] = (e, s)
        for label, kw, subset in (("load-set card", {}, loads), ("load-set card + effective nu", {"effective_poisson": True}, loads),
                                  ("load-set card without the 4x stiffer load", {}, loads[:5] + loads[6:])):
            try:
                cal = calibrate_for_load_set(mesh, "springs_volume", MATERIAL, subset, st, **kw)
            except BudgetSaturationError as err:
                notes.append(f"{label}, {sub} substep(s): REFUSED: {err}")
                continue
            e, s = card_errors(mesh, loads + extra, st, cal.effective_youngs_modulus, cal.poisson_ratio if kw else None)
            lo, hi = cal.validity["youngs_modulus_range"]
            for i, ld in enumerate(loads + extra):  # outside this card's stiffness range: not its use
                E = MATERIAL.youngs_modulus if ld.youngs_modulus is None else ld.youngs_modulus
                if not lo <= E <= hi:
                    e[i], s[i] = np.nan, np.nan
            cols[f"{label}, {sub} substep(s) (factors {', '.join(f'{f:.4f}' for f in cal.factors)}; nu {cal.poisson_ratio:.4f})"] = (e, s)
        print(f"... {sub} substep(s) done, {time.process_time() - t0:.0f} s CPU", flush=True)

    keys = list(cols)
    print("\n| load | " + " | ".join(f"({i + 1})" for i in range(len(keys))) + " |")
    print("|---|" + "---:|" * len(keys))
    for i, n in enumerate(names):
        print(f"| {n} | " + " | ".join("-" if np.isnan(cols[k][0][i]) else f"{fmt(cols[k][0][i])} (s {cols[k][1][i]:.2f})" for k in keys) + " |")
    n_set = len(loads)
    print("| **max abs over the set** | " + " | ".join(f"**{100 * np.nanmax(np.abs(cols[k][0][:n_set])):.1f} %**" for k in keys) + " |")
    print("| **max abs, held out (in range)** | " + " | ".join(f"**{100 * np.nanmax(np.abs(cols[k][0][n_set:])):.1f} %**" for k in keys) + " |")
    print()
    for i, k in enumerate(keys):
        print(f"({i + 1}) {k}")
    for n in notes:
        print("\n" + n)

    print("\nSaturated settings (set: punch 0.1 mm and platen 0.1 mm):\n")
    print("| cells | dt | iterations | min d log F / d log E | proposal (measured) | CPU [s] |")
    print("|---|---:|---:|---:|---|---:|")
    for cells, dt in (((8, 8, 4), 3e-3), ((4, 4, 2), 1.0 / 60.0)):
        m = block(SIZE, cells)
        pair = [indentation_load(m, "flat_punch", 1e-4, radius=3e-3), indentation_load(m, "platen", 1e-4)]
        t1 = time.process_time()
        try:
            calibrate_for_load_set(m, "springs_volume", MATERIAL, pair, settings(dt=dt))
            print(f"| {SIZE[0] / cells[0] * 1e3:g} mm | {dt:.4g} | 10 | not saturated | - | |")
        except BudgetSaturationError as err:
            p = err.proposal
            print(f"| {SIZE[0] / cells[0] * 1e3:g} mm | {dt:.4g} s | 10 | {min(err.sensitivity):.3f} | iterations {p.iterations} "
                  f"(s {p.iterations_sensitivity:.2f}) or substeps {p.substeps} (s {p.substeps_sensitivity:.2f}) | "
                  f"{time.process_time() - t1:.0f} |", flush=True)
    print(f"\ntotal {time.process_time() - t0:.0f} s CPU")


if __name__ == "__main__":
    main()
