"""The discretisation estimate of a config incision fit (issue 19): the same cut on a layered
specimen of half the cells, evaluated at the fitted pre-stretch; refused, with the reason and
what to change, where the coarser mesh cannot carry the same cut."""

import json
import math
import warnings

import pytest

from difftissue.config import parse_config
from difftissue.errors import DiscretisationWarning
from difftissue.report import write_fit_outputs

#: the datum [mm]: the model on this mesh opens 0.19 mm at pre_stretch 1.05 and 0.29 mm at 1.08
WIDTH_MM = 0.25


def _config(cut=((2, 2), (6, 2)), depth=1, cells=(8, 4), layer_cells=(2, 2)):
    """A 4 mm cut 1 mm deep (through the fitted dermis, onto the fat) in an 8 x 4 mm specimen of
    1 mm lateral cells, two cells through each 1 mm layer: halving gives 2 mm cells with the
    cut's ends and depth still on nodes. One datum, the max width, fitted by pre_stretch
    (stable_neo_hookean, the incision's default model)."""
    e = {"name": "wound", "scenario": "incision", "model": "stable_neo_hookean", "length_unit": "mm",
         "data": {"quantity": "max_width", "value": WIDTH_MM},
         "specimen": {"size": [8, 4], "cells": list(cells), "layers": [
             {"name": "dermis", "thickness": 1, "cells": layer_cells[0], "fitted": True},
             {"name": "fat", "thickness": 1, "cells": layer_cells[1], "youngs_modulus": 5e3, "poisson_ratio": 0.45}]},
         "cut": {"path": [list(p) for p in cut], "depth": depth}, "scalpel_steps": 2}
    return {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": 1.05},
            "fit": {"parameters": ["pre_stretch"]}, "experiment": [e]}


@pytest.fixture(scope="module")
def fitted():
    """One fit shared by the assertions (about 35 s CPU: the fit and one coarse evaluation)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = parse_config(_config()).run()
    return result, caught


def test_incision_fit_gets_an_estimate_with_the_expected_sign(fitted):
    result, _ = fitted
    rec = result.discretisation
    assert rec["status"] == "estimated", rec
    sc = rec["scenarios"]["wound"]
    assert sc["fine_cells"] == {"lateral": [8, 4], "layers": [2, 2]}
    assert sc["coarse_cells"] == {"lateral": [4, 2], "layers": [1, 1]}
    assert sc["refinement_ratio"] == pytest.approx(2.0)
    # the same cut on both meshes: nothing snapped, the same opened area
    geo = sc["geometry"]
    assert geo["coarse"]["max_snap_distance"] == 0.0 and geo["coarse"]["cut_area"] == pytest.approx(geo["fine"]["cut_area"], rel=1e-9)
    assert geo["fine"]["cut_length"] == pytest.approx(4e-3) and geo["fine"]["cut_depth"] == pytest.approx(1e-3)
    # halving again (2 x 1 cells of 4 mm) cannot carry the cut: two levels, first order assumed
    assert sc["order_source"] == "assumed" and "first order assumed" in geo["third_level"]
    # the coarser mesh opens less, so the fine mesh opens too little too: the fit's pre_stretch
    # is too high and the mesh-converged value lower (but still a pre-stretch)
    lam = result.values["pre_stretch"]
    assert 1.05 < lam < 1.08
    assert rec["estimate"]["pre_stretch"] > 0
    assert 1.0 < rec["corrected"]["pre_stretch"] < lam
    assert sc["relative_error"] > 0.1  # 2 mm / 1 mm cells: far from converged


def test_one_datum_fit_is_flagged_without_a_standard_error(fitted):
    # one width, one parameter: no residual degrees of freedom, the standard error is NaN, so
    # the flag compares the mesh's error of the prediction with 2 % instead
    result, caught = fitted
    assert result.dof == 0 and math.isnan(result.standard_errors["pre_stretch"])
    flags = [f for f in result.quality.flags if f.name == "discretisation_error"]
    assert [f.subject for f in flags] == ["pre_stretch"]
    assert "no standard error to compare it with" in flags[0].message
    assert flags[0].numbers["prediction_error_relative"] > 0.02
    assert any(issubclass(w.category, DiscretisationWarning) and "pre_stretch" in str(w.message) for w in caught)


def test_fit_json_and_report_carry_the_estimate(fitted, tmp_path):
    result, _ = fitted
    write_fit_outputs(result, tmp_path, config={"title": "t"})
    rec = json.loads((tmp_path / "fit.json").read_text())["discretisation"]
    assert rec["status"] == "estimated" and rec["scenarios"]["wound"]["geometry"]["coarse"]["cut_depth"] == pytest.approx(1e-3)
    report = (tmp_path / "report.md").read_text()
    assert "## Discretisation error" in report and "| none (no residual degrees of freedom) | - |" in report


def test_cut_off_the_coarser_nodes_gets_the_reason():
    # x = 1 mm and a depth of 0.5 mm are nodes of the fit's mesh but not of the 2 mm one
    cfg = parse_config(_config(cut=((1, 2), (6, 2)), depth=0.5))
    coarse, skipped = cfg.coarse_predictions(cfg.material)  # refused before any evaluation
    assert coarse == {}
    why = skipped["wound"]
    assert "the point(s) [1, 2] lie between its nodes" in why and "the depth 0.5 lies between its node planes" in why
    assert "give the cut's ends on multiples of the coarser cell size (2 mm in x, 2 mm in y)" in why
    assert "its depth on one of its node depths (0, 1, 2 mm)" in why


def test_a_third_level_where_the_cut_stays_on_the_nodes():
    # 0.5 mm cells, four through each layer: 1 mm and 2 mm cells both carry the cut (ratio 2 each)
    exp = parse_config(_config(cells=(16, 8), layer_cells=(4, 4))).experiments[0]
    sc, info = exp.coarsen()
    assert sc is not None and info["coarse_cells"] == {"lateral": [8, 4], "layers": [2, 2]}
    assert "coarser" in info and info["geometry"]["coarser"]["max_snap_distance"] == 0.0
    _, cells = info["coarser"]()
    assert cells == {"lateral": [4, 2], "layers": [1, 1]}
