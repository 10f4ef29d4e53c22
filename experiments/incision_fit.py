"""Pre-stretch recovered from FEM-generated incision widths.

Data: the surface width profile of the reference FEM incision (fem_neo_hookean, scalpel
released progressively) of experiments/incision_vs_fem.py (read from
experiments/results/incision_vs_fem.json: same specimen, cut and boundary conditions), for
lambda0 = 1.05, 1.10, 1.15. Each profile is fitted with the physical models (stable_neo_hookean
and springs_volume), E and nu of the dermis known, lambda0 fitted (Levenberg-Marquardt from
lambda0 = 1.02, `difftissue.fit.fit`, the model compiled once per model through
`difftissue.config.SeparatelyCompiled`).

Writes experiments/results/incision_fit.json (refused if it exists unless --force) and prints
a table.

Run: python experiments/incision_fit.py [--models stable_neo_hookean,springs_volume] [--lams 1.05,1.10,1.15]
     [--start 1.02] [--out incision_fit.json] [--force]
(~10-15 min per fit on the loaded 2-core machine: each model evaluation is a sparse solve of
3,600 unknowns plus its tangent.)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from difftissue._io import atomic_output  # noqa: E402
from difftissue.config import SeparatelyCompiled  # noqa: E402
from difftissue.fit import fit  # noqa: E402
from difftissue.incision import Incision, IncisionOptions  # noqa: E402
from difftissue.materials import MaterialParameterization  # noqa: E402

import incision_vs_fem as ivf  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


class _Data:
    """Observed widths with the prediction of a shared (compiled once) scenario."""

    def __init__(self, model, observed, sigma):
        self.name, self.abscissa, self.x_label, self.y_label = "incision", model.abscissa, model.x_label, model.y_label
        self.observed = np.asarray(observed, dtype=float)
        self.sigma = np.full_like(self.observed, sigma)
        self.predict = model.predict


def main(models=("stable_neo_hookean", "springs_volume"), force=False, lams=(1.05, 1.10, 1.15), start=1.02, out="incision_fit.json"):
    ref = json.loads((RESULTS / "incision_vs_fem.json").read_text())
    cut = ivf.specimen(ref["specimen"]["cell"])
    ps, pd = np.asarray(ref["cut"]["pair_s"]), np.asarray(ref["cut"]["pair_depth"])
    np.testing.assert_allclose(ps, cut.pair_s)  # the same cut
    surf = np.flatnonzero(pd < 1e-12)
    surf = surf[np.argsort(ps[surf])]
    rows = []
    for kind in models:
        # one scenario (one compilation) per model; the data of each lambda0 share it
        model = SeparatelyCompiled(Incision(cut, model=kind, positions=ps[surf], fitted_regions=("dermis",), options=IncisionOptions(scalpel_steps=4)))
        for r in ref["rows"]:
            lam = r["pre_stretch"]
            if not any(abs(lam - x) < 1e-12 for x in lams):
                continue
            widths = np.asarray(r["reference"]["pair_width"])[surf]
            sc = _Data(model, widths, 0.01 * widths.max())
            t0 = time.perf_counter()
            res = fit([sc], MaterialParameterization(("pre_stretch",)), ivf.SKIN.replace(pre_stretch=start), max_steps=30)
            lam_fit = float(res.values["pre_stretch"])
            pred = np.asarray(res.predictions[sc.name])
            row = {
                "model": kind,
                "true_pre_stretch": lam,
                "fitted_pre_stretch": lam_fit,
                "relative_error": lam_fit / lam - 1.0,
                "error_of_strain": (lam_fit - 1.0) / (lam - 1.0) - 1.0,
                "standard_error": float(res.standard_errors["pre_stretch"]),
                "converged": bool(res.converged),
                "steps": int(res.steps),
                "seconds": time.perf_counter() - t0,
                "rms_residual_over_rms_width": float(np.sqrt(np.mean((pred - widths) ** 2)) / np.sqrt(np.mean(widths**2))),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    with atomic_output(RESULTS / out, overwrite=force) as tmp:
        Path(tmp).write_text(json.dumps({"data": "experiments/results/incision_vs_fem.json (reference FEM surface widths)", "start": start, "rows": rows}, indent=1))
    print()
    print("| model | lambda0 true | lambda0 fitted | error | error in lambda0 - 1 | rms residual / rms width |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        rr = r["rms_residual_over_rms_width"]
        print(f"| {r['model']} | {r['true_pre_stretch']:.2f} | {r['fitted_pre_stretch']:.4f} | {100 * r['relative_error']:+.2f} % | {100 * r['error_of_strain']:+.1f} % | {100 * rr:.1f} % |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="stable_neo_hookean,springs_volume")
    ap.add_argument("--lams", default="1.05,1.10,1.15", help="pre-stretches of the reference rows to fit")
    ap.add_argument("--start", type=float, default=1.02, help="initial lambda0")
    ap.add_argument("--out", default="incision_fit.json", help="file name in experiments/results/")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    main(tuple(a.models.split(",")), force=a.force, lams=tuple(float(x) for x in a.lams.split(",")), start=a.start, out=a.out)
