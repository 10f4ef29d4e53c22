"""One cut opening of the two-layer staircase specimen (experiments/cut_staircase.py) with the
library's ``springs_volume_matched_lattice``: max surface width [mm] at a cell size, pre-stretch
and cut angle (docs/dev/cut-openings-finite-strain.md, section 7: the check that the library
model reproduces the screened widths).

    PYTHONPATH=. python experiments/cut_matched_lattice.py 0.5 1.15 0    # cell [mm], lambda0, angle [deg]
"""

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

from cut_staircase import path, specimen, surface_measures  # noqa: E402

from difftissue.cutting import cut_specimen  # noqa: E402
from difftissue.incision import Incision, IncisionOptions  # noqa: E402
from difftissue.materials import Material  # noqa: E402


def main():
    cell, lam, angle = (float(a) for a in sys.argv[1:4])
    t0 = time.process_time()
    cut = cut_specimen(specimen(cell * 1e-3), path(angle), method="staircase")
    inc = Incision(cut, model="springs_volume_matched_lattice", fitted_regions=("dermis",),
                   options=IncisionOptions(scalpel_steps=1, linear_solver="sparse"))
    res = inc.solve(Material(2e5, 0.45).replace(pre_stretch=lam))
    wmax, _ = surface_measures(cut, res.opening.width)
    print(json.dumps(dict(cell_mm=cell, angle=angle, pre_stretch=lam, max_width_mm=wmax * 1e3, cpu=time.process_time() - t0)))


if __name__ == "__main__":
    main()
