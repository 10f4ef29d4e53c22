"""Cut openings of the two-layer staircase specimen (experiments/cut_staircase.py) with the
library's ``springs_volume_matched_lattice`` (docs/dev/cut-openings-finite-strain.md, section 7
and "The library model at 0.5 mm"): max surface width [mm].

One case (cell [mm], lambda0, angle [deg]):

    PYTHONPATH=. python experiments/cut_matched_lattice.py 0.5 1.15 0

All eight cases of a cell size (0 and 25 deg; the linear limit lambda0 = 1.001, reported per unit
pre-strain, 1.05, 1.10, 1.15) in one process, so the compiled programs are reused, written to
experiments/results/cut_convergence_springs_matched_lattice_cell{h}mm.json (``--lams`` /
``--angles`` run a subset and merge it into the file's rows):

    PYTHONPATH=. python experiments/cut_convergence.py --springs 0.5 --model springs_volume_matched_lattice

The table of every cell size in those files against the P2 reference (the level-6 Richardson
values of cut_convergence_p2.json, 25 deg via the whole-square rotation ratio, as
``cut_convergence.py --table``) and against design S's screen
(``cut_lattice_tangent.py screen``, rows of cut_lattice_screens.jsonl with a lattice stretch and
unit volume factor), with the observed order where a case has three cell sizes:

    PYTHONPATH=. python experiments/cut_matched_lattice.py --table
"""

import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
MODEL = "springs_volume_matched_lattice"


def one_case(cell, lam, angle):
    """Max surface width [mm] of one case (cell [mm], lambda0, angle [deg]) and the CPU seconds."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from cut_staircase import path, specimen, surface_measures

    from difftissue.cutting import cut_specimen
    from difftissue.incision import Incision, IncisionOptions
    from difftissue.materials import Material

    t0 = time.process_time()
    cut = cut_specimen(specimen(cell * 1e-3), path(angle), method="staircase")
    inc = Incision(cut, model=MODEL, fitted_regions=("dermis",),
                   options=IncisionOptions(scalpel_steps=1, linear_solver="sparse"))
    res = inc.solve(Material(2e5, 0.45).replace(pre_stretch=lam))
    wmax, _ = surface_measures(cut, res.opening.width)
    return dict(cell_mm=cell, angle=angle, pre_stretch=lam, max_width_mm=wmax * 1e3, cpu=time.process_time() - t0)


def screen_widths(path=HERE / "results" / "cut_lattice_screens.jsonl"):
    """Design S's screened max width [mm] per (cell [mm], angle, lambda0): the screen rows with a
    lattice stretch and a unit volume factor (the later row of a case wins)."""
    out = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r.get("lattice_stretch") is not None and r["factors"][4] == 1.0:
            out[(r["cell_mm"], r["angle"], round(r["pre_stretch"], 9))] = r["max_width_mm"]
    return out


def table():
    """Markdown: per case and cell size the library width, its error against the reference and
    its difference from the screen; the observed order and Richardson value from three cell
    sizes, or the second-order extrapolation from two."""
    import numpy as np

    from cut_convergence import LINEAR, springs_table

    screen = screen_widths()
    lines = ["| cut | λ0 | reference | cell [mm] | library width | vs reference | vs screen | own order | extrapolated (vs reference) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for ln in springs_table("max_width", MODEL):
        lam = ln["pre_stretch"]
        scale = 1.0 / (lam - 1.0) if lam == LINEAR else 1.0
        lab = "linear limit" if lam == LINEAR else f"{lam:.2f}"
        for i, (h, v, e) in enumerate(zip(ln["cells"], ln["values"], ln["errors"])):
            s = screen.get((round(h, 9), ln["angle"], round(lam, 9)))
            vs = f"{100 * (v / (s * scale) - 1):+.4f} %" if s is not None else "-"
            last = i == len(ln["cells"]) - 1
            order = f"{ln['order_own']:.2f}" if last and np.isfinite(ln["order_own"]) else "-"
            ext = "-"
            if last and np.isfinite(ln["richardson"]):
                ext = f"{ln['richardson']:.4f} ({100 * ln['richardson_error']:+.1f} %)" + (", order 2 assumed" if ln["order_assumed"] else "")
            lines.append(f"| {ln['angle']:g}° | {lab} | {ln['reference']:.4f} | {h:.3g} | {v:.6f} | {100 * e:+.1f} % | {vs} | {order} | {ext} |")
    print("\n".join(lines))


def main():
    if sys.argv[1:] == ["--table"]:
        table()
        return
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    cell, lam, angle = (float(a) for a in sys.argv[1:4])
    print(json.dumps(one_case(cell, lam, angle)))


if __name__ == "__main__":
    main()
