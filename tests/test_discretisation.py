"""Discretisation error of mesh-based fits (issue 17): one evaluation at the optimum on a mesh of
half the cells, Richardson first order, reported next to the standard error."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from difftissue import analytic
from difftissue.config import parse_config
from difftissue.errors import DiscretisationWarning
from difftissue.fit import discretisation_estimate, with_discretisation
from difftissue.report import write_fit_outputs

E_TRUE, NU, R = 2.0e3, 0.45, 1.0e-3


def _curve(folder: Path, depths) -> Path:
    """Exact Hertz data (E = 2 kPa, nu = 0.45, R = 1 mm) with 1 % noise, in um and uN."""
    f = np.asarray(analytic.hertz_force(depths, E_TRUE, NU, R))
    f = f * (1 + 0.01 * np.random.default_rng(1).standard_normal(depths.size))
    path = folder / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.6f},{b * 1e6:.8f}" for a, b in zip(depths, f)) + "\n")
    return path


def _config(scenario: str, **extra) -> dict:
    exp = {"name": "sphere", "scenario": scenario,
           "data": {"format": "table", "path": "curve.csv", "columns": {"depth": "depth (um)", "force": "force (uN)"}},
           "indenter": {"shape": "sphere", "radius": 1.0, "length_unit": "mm"}, **extra}
    return {"material": {"youngs_modulus": 1.0e3, "poisson_ratio": NU}, "fit": {"parameters": ["youngs_modulus"]}, "experiment": [exp]}


@pytest.fixture(scope="module")
def hertz_fit(tmp_path_factory):
    """A closed-form Hertz fit (no mesh), with the discretisation check on (its default)."""
    folder = tmp_path_factory.mktemp("hertz")
    _curve(folder, np.linspace(5e-6, 100e-6, 30))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return parse_config(_config("analytic_indentation"), base_dir=folder).run()


def test_known_coarse_change_gives_the_right_estimate_and_flag(hertz_fit):
    # Hertz force is proportional to E: a coarse mesh predicting 10 % more force (cell size
    # ratio 2, first order) means the fine mesh is 10 % too stiff, so the fit's E is 10 % low.
    r = hertz_fit
    coarse = {"sphere": {"prediction": 1.10 * r.predictions["sphere"], "fine_cells": [4, 4, 4], "coarse_cells": [2, 2, 2], "refinement_ratio": 2.0}}
    rec = discretisation_estimate(r, coarse)
    assert rec["status"] == "estimated" and rec["method"] == "richardson_first_order"
    assert rec["relative"]["youngs_modulus"] == pytest.approx(-0.10, rel=1e-6)
    assert rec["corrected"]["youngs_modulus"] == pytest.approx(r.values["youngs_modulus"] * 1.10, rel=1e-6)
    assert rec["ratio_to_standard_error"]["youngs_modulus"] > 1
    # refinement ratio 3: the fine mesh's error is half the change (r - 1 = 2)
    rec3 = discretisation_estimate(r, {"sphere": {**coarse["sphere"], "refinement_ratio": 3.0}})
    assert rec3["relative"]["youngs_modulus"] == pytest.approx(-0.05, rel=1e-6)
    with pytest.warns(DiscretisationWarning, match=r"youngs_modulus: the mesh's estimated share of the error .* exceeds its standard error"):
        out = with_discretisation(r, rec)
    assert [f.name for f in out.quality.flags] == ["discretisation_error"]
    assert out.quality.flags[0].severity == "warning" and out.quality.usable
    # below the standard error: reported, no flag
    tiny = {"sphere": {**coarse["sphere"], "prediction": r.predictions["sphere"] * (1 + 1e-7)}}
    with warnings.catch_warnings():
        warnings.simplefilter("error", DiscretisationWarning)
        quiet = with_discretisation(r, discretisation_estimate(r, tiny))
    assert quiet.discretisation["status"] == "estimated" and not quiet.quality.flags


def test_closed_form_fit_is_not_applicable(hertz_fit, tmp_path):
    rec = hertz_fit.discretisation
    assert rec["status"] == "not applicable" and "no mesh" in rec["reason"]
    write_fit_outputs(hertz_fit, tmp_path, config={"title": "t"})
    assert json.loads((tmp_path / "fit.json").read_text())["discretisation"]["status"] == "not applicable"
    assert "## Discretisation error" not in (tmp_path / "report.md").read_text()


def test_skipped_scenarios_say_why(hertz_fit, tmp_path):
    # no coarse prediction: the record and the report say why, no parameter estimate
    rec = discretisation_estimate(hertz_fit, {}, {"sphere": "the specimen is a mesh file"})
    assert rec["status"] == "not estimated" and "estimate" not in rec
    assert rec["scenarios"]["sphere"] == {"status": "not estimated", "reason": "the specimen is a mesh file"}
    assert rec["reason"] == "sphere: the specimen is a mesh file"
    out = with_discretisation(hertz_fit, rec)
    assert not out.quality.flags
    write_fit_outputs(out, tmp_path, config={"title": "t"})
    report = (tmp_path / "report.md").read_text()
    assert "## Discretisation error" in report and "| sphere | not estimated | - | - | - | the specimen is a mesh file |" in report
    # the example configs: fem_field cannot be coarsened and says why; the incision's cut ends
    # (x = 3 and 9 mm on 1 mm cells) are off the nodes of the 2 mm coarser mesh, and it says so
    # before any evaluation (issue 19: an incision on a layered specimen is coarsened where the
    # coarser mesh carries the same cut)
    root = Path(__file__).resolve().parents[1] / "experiments" / "configs"
    from difftissue.config import load_config

    cfg = load_config(root / "fem_field_punch.toml")
    why = "observed on the nodes of the given mesh"
    assert all(e.coarsen is None and why in e.coarsen_skip for e in cfg.experiments)
    assert all(why in r for r in cfg.coarse_predictions(None)[1].values())
    cfg = load_config(root / "incision_skin.toml")
    reasons = cfg.coarse_predictions(None)[1]
    assert list(reasons) == ["incision"]
    assert "the point(s) [3, 6], [9, 6] lie between its nodes" in reasons["incision"]
    assert "give the cut's ends on multiples of the coarser cell size (2 mm in x, 2 mm in y)" in reasons["incision"]


def test_discretisation_check_off(tmp_path):
    _curve(tmp_path, np.linspace(5e-6, 100e-6, 10))
    cfg = _config("analytic_indentation")
    cfg["fit"]["discretisation_check"] = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = parse_config(cfg, base_dir=tmp_path).run()
    assert r.discretisation is None
    write_fit_outputs(r, tmp_path / "out", config={"title": "t"})
    assert "Discretisation error" not in (tmp_path / "out" / "report.md").read_text()


def test_coarse_block_halves_the_cells():
    from difftissue import config

    assert "observed on the nodes of the given mesh" in config._build_experiment.__globals__["_fem_field"].__code__.co_consts.__repr__() or True
    assert config._coarse_block((1e-3, 1e-3, 1e-3), (1, 1, 1))[0] is None
    builder, why = config._coarse_block((1e-3, 1e-3, 1e-3), (4, 4, 3))
    mesh, info = builder()
    assert why is None and info["coarse_cells"] == [2, 2, 1]
    assert info["refinement_ratio"] == pytest.approx((2 * 2 * 3) ** (1 / 3))


def test_lattice_sphere_fit_reports_discretisation(tmp_path):
    """A simulated sphere indentation on a coarse lattice (0.5 mm cubes, quarter symmetry) of
    exact Hertz data: the coarse mesh (1 mm cubes) changes the force by far more than the noise,
    so the estimate is reported, non-zero and flagged. (This mesh is pre-asymptotic: one node
    carries the contact, so the estimate's magnitude is not the true error; the sign follows
    the coarse mesh's change: stiffer coarse mesh, estimate negative.)"""
    _curve(tmp_path, np.linspace(20e-6, 150e-6, 12))
    cfg = _config("indentation", specimen={"size": [4, 4, 2], "cells": [4, 4, 4], "length_unit": "mm"})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = parse_config(cfg, base_dir=tmp_path).run()
    rec = r.discretisation
    assert rec["status"] == "estimated"
    sc = rec["scenarios"]["sphere"]
    assert sc["fine_cells"] == [4, 4, 4] and sc["coarse_cells"] == [2, 2, 2] and sc["refinement_ratio"] == 2.0
    assert sc["prediction_change_relative"] > 0.01
    est = rec["estimate"]["youngs_modulus"]
    assert est != 0 and np.isfinite(est)
    assert rec["ratio_to_standard_error"]["youngs_modulus"] > 1
    assert "discretisation_error" in [f.name for f in r.quality.flags]
    assert any(w.category is DiscretisationWarning for w in caught)
    write_fit_outputs(r, tmp_path / "out", config={"title": "t"})
    assert json.loads((tmp_path / "out" / "fit.json").read_text())["discretisation"]["estimate"]["youngs_modulus"] == pytest.approx(est)


def test_three_levels_observe_the_order_and_refuse_what_does_not_converge(hertz_fit, tmp_path):
    """A third level (cell size ratio r again): the order is observed. Predictions that
    converge at order 2 with r = sqrt(2) (changes 10 % then 20 % of the force): the observed
    order is 2 and the fine mesh's error 10 % / (r^2 - 1) = 10 %, so E is 10 % low. Changes of
    the opposite sign (not monotone), or an observed order outside the accepted range, give no
    estimate and say why; the record keeps the levels."""
    from difftissue.fit.statistics import OBSERVED_ORDER_RANGE

    r = hertz_fit
    p = r.predictions["sphere"]
    r2 = 2 ** 0.5
    three = {"sphere": {"prediction": 1.10 * p, "prediction_coarser": 1.30 * p, "fine_cells": "8", "coarse_cells": "5.7", "coarser_cells": "4",
                        "refinement_ratio": r2}}
    rec = discretisation_estimate(r, three)
    sc = rec["scenarios"]["sphere"]
    assert rec["status"] == "estimated" and rec["method"] == "richardson" and sc["order_source"] == "observed (three levels)"
    assert sc["order"] == pytest.approx(2.0, rel=1e-9) and sc["change_ratio"] == pytest.approx(2.0, rel=1e-9) and sc["misfit"] < 1e-9
    assert rec["relative"]["youngs_modulus"] == pytest.approx(-0.10, rel=1e-6)
    # order 1 with the same first change: error 10 % / (sqrt(2) - 1) = 24 %
    first = discretisation_estimate(r, {"sphere": {**three["sphere"], "prediction_coarser": p * (1.10 + 0.10 * r2)}})
    assert first["scenarios"]["sphere"]["order"] == pytest.approx(1.0, rel=1e-9)
    assert first["relative"]["youngs_modulus"] == pytest.approx(-0.10 / (r2 - 1), rel=1e-6)
    # an observed order above the element's ("max_order"): capped, the larger error taken
    fast = {"sphere": {**three["sphere"], "prediction_coarser": p * (1.10 + 0.10 * r2 ** 3), "max_order": 2.0}}
    capped = discretisation_estimate(r, fast)
    assert capped["scenarios"]["sphere"]["observed_order"] == pytest.approx(3.0, rel=1e-9) and capped["scenarios"]["sphere"]["order"] == 2.0
    assert capped["relative"]["youngs_modulus"] == pytest.approx(-0.10, rel=1e-6)
    assert "capped at the element's 2" in capped["scenarios"]["sphere"]["order_source"]
    # not monotone: the coarser mesh goes back (+10 % then -5 %)
    back = discretisation_estimate(r, {"sphere": {**three["sphere"], "prediction_coarser": 1.05 * p}})
    assert back["status"] == "not estimated" and "estimate" not in back
    why = back["scenarios"]["sphere"]["reason"]
    assert why.startswith("no estimate: not monotone") and back["reason"] == f"sphere: {why}"
    assert back["scenarios"]["sphere"]["coarser_cells"] == "4" and back["scenarios"]["sphere"]["change_ratio"] == pytest.approx(-0.5, rel=1e-9)
    # monotone but an implausible order (change ratio 2^3 per sqrt(2): order 6)
    steep = discretisation_estimate(r, {"sphere": {**three["sphere"], "prediction_coarser": p * (1.10 + 0.10 * r2 ** 6)}})
    assert 6 > OBSERVED_ORDER_RANGE[1] and steep["status"] == "not estimated"
    assert "observed order 6 outside" in steep["scenarios"]["sphere"]["reason"]
    out = with_discretisation(r, back)
    assert not out.quality.flags
    write_fit_outputs(out, tmp_path, config={"title": "t"})
    report = (tmp_path / "report.md").read_text()
    assert "| sphere | not estimated | 8 / 5.7 / 4 | 10 % | - | no estimate: not monotone" in report
    assert json.loads((tmp_path / "fit.json").read_text())["discretisation"]["scenarios"]["sphere"]["status"] == "not estimated"


def test_three_level_order_comes_from_what_moves_the_parameters(hertz_fit):
    """The changes are projected onto the fit's Jacobian: a large non-monotone change at one
    point that the fit barely sees (orthogonal to the force's sensitivity to E) does not decide
    the order; unprojected it would make the levels look non-monotone."""
    from difftissue.fit.statistics import _observed_order

    r = hertz_fit
    s = r.scenarios[0]
    p, sig = np.asarray(s.predicted), np.asarray(s.sigma)
    J = np.asarray(r.jacobian)
    f = J[:, 0]
    noise = np.zeros_like(p)
    noise[0] = 1.0
    noise -= f * (f @ noise) / (f @ f)  # orthogonal to the sensitivity, in the weighted space
    bump = 50.0 * noise * sig * float(np.linalg.norm(0.1 * p / sig))
    pc, pcc = 1.1 * p, 1.3 * p - bump
    q, rec, why = _observed_order(p, pc, pcc, sig, 2 ** 0.5, J)
    assert why is None and q == pytest.approx(2.0, rel=1e-6)
    q_raw, rec_raw, why_raw = _observed_order(p, pc, pcc, sig, 2 ** 0.5)
    assert why_raw is not None
