"""The XPBD JSON export of a load-set calibration the caller computed (docs/export.md, "Calibrating
the XPBD file over a load set"): the caller runs difftissue.budget.calibrate_for_load_set, the
export checks it against what it writes (setting, model kind, mesh, material, the card's E in
the stiffness range) and writes its card; the file's compliances reproduce the card's forces
when run from the file; a saturated budget is refused by calibrate_for_load_set itself, with
the proposed budget. One calibration is shared by the tests (module fixture)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from difftissue.budget import calibrate_for_load_set, indentation_load
from difftissue.errors import BudgetExtrapolationWarning, BudgetRangeError, BudgetSaturationError, ExportError
from difftissue.export import MaterialCard, export, xpbd_parameters
from difftissue.export.budget import xpbd_budget_reactions
from difftissue.mesh import block
from difftissue.solvers.xpbd import XPBDSettings

E, NU = 10e3, 0.45
DT = 2.5e-4


def _card(youngs_modulus=E, poisson_ratio=NU):
    return MaterialCard(model="stable_neo_hookean", parameters={"youngs_modulus": {"value": youngs_modulus, "unit": "Pa"},
                                                                "poisson_ratio": {"value": poisson_ratio, "unit": "1"}}, name="skin")


def _settings(dt=DT, substeps=1, iterations=10):
    return XPBDSettings(dt=dt, substeps=substeps, iterations=iterations, method="gauss_seidel", damping=float("inf"), warm_start=False)


@pytest.fixture(scope="module")
def mesh():
    return block((0.01, 0.01, 0.005), (4, 4, 2))  # 2.5 mm cells (tests/test_budget_load_set.py)


@pytest.fixture(scope="module")
def loads(mesh):
    return [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3), indentation_load(mesh, "platen", 1e-4)]


@pytest.fixture(scope="module")
def cal(mesh, loads):
    """The caller's step: the load-set calibration of the file's constraint pair at the export's budget."""
    return calibrate_for_load_set(mesh, "stable_neo_hookean", _card().material(), loads, _settings(), reference="stable_neo_hookean")


def test_xpbd_export_writes_the_callers_load_set_calibration(tmp_path, mesh, loads, cal):
    card = _card()
    path = export(card, "xpbd", tmp_path / "x.json", mesh=mesh, dt=DT, iterations=10, load_set=cal)
    doc = json.loads(path.read_text())
    rec = doc["budget_calibration"]
    print(rec["factor"], cal.factors, cal.max_error, [(r["name"], r["error"], r["sensitivity"]) for r in cal.loads])
    assert rec["method"] == "load set" and rec["factors"] == list(cal.factors) and rec["extrapolated"] is False
    assert rec["factor"] == pytest.approx(cal.factor, rel=1e-12) and rec["max_residual_error"] == cal.max_error
    assert rec["card"] == json.loads(json.dumps(cal.card()))
    v = rec["card"]["validity"]
    assert v["shapes"] == ["flat_punch", "platen"] and v["depth_range"] == [1e-4, 1e-4]
    assert v["youngs_modulus_range"] == [E, E] and v["mesh"]["cell_size"] == pytest.approx(2.5e-3, rel=1e-9)
    assert v["setting"] == {"dt": DT, "substeps": 1, "iterations": 10, "method": "gauss_seidel"}
    assert "CALIBRATED OVER A LOAD SET" in doc["validity"]
    # the written compliances are the card's E_eff (nu kept): mu V0 alpha_D = 1 with mu = f E / (2 (1 + nu))
    mu = cal.factor * E / (2 * (1 + NU))
    V0 = np.asarray(doc["per_tet"]["rest_volume"])
    np.testing.assert_allclose(np.asarray(doc["per_tet"]["deviatoric_compliance"]) * mu * V0, 1.0, rtol=1e-12)
    assert doc["lame_card"]["mu"] == pytest.approx(E / (2 * (1 + NU)), rel=1e-12)
    # everything but the calibrated numbers and their record is the uncalibrated file's
    plain = xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, calibrate=False)
    assert doc["lame_card"] == plain["lame"] and doc["per_tet"]["rest_volume"] == plain["per_tet"]["rest_volume"]
    for k in set(plain) - {"lame", "gamma", "per_unit_volume", "per_tet", "validity", "notes", "setting"}:
        assert doc[k] == plain[k], k
    # the file's numbers run by difftissue's XPBD solver at the file's budget reproduce the card's forces
    for ld, row in zip(loads, rec["card"]["loads"]):
        fixed = np.asarray(ld.bc.fixed)
        presc = np.where(fixed, np.asarray(ld.bc.displacement), 0.0)
        observe = fixed & np.any(presc != 0, axis=1)[:, None]
        got, rested = xpbd_budget_reactions(doc, fixed, presc, observe, [1.0], tol=1e-10)
        assert rested
        print(row["name"], got[0], row["calibrated"], row["reference"])
        assert got[0] == pytest.approx(row["calibrated"], rel=1e-3)
        assert abs(got[0] / row["reference"] - 1.0) <= rec["max_residual_error"] + 1e-3


def test_xpbd_load_set_outside_the_stiffness_range_refused_or_extrapolated(tmp_path, mesh, cal):
    stiff = _card(youngs_modulus=2 * E)  # the set's range is [E, E]
    with pytest.raises(BudgetRangeError, match="Young's modulus"):
        xpbd_parameters(stiff, dt=DT, iterations=10, mesh=mesh, load_set=cal)
    with pytest.warns(BudgetExtrapolationWarning, match="Young's modulus"):
        path = export(stiff, "xpbd", tmp_path / "x.json", mesh=mesh, dt=DT, iterations=10, load_set=cal, extrapolate=True)
    rec = json.loads(path.read_text())["budget_calibration"]
    assert rec["extrapolated"] is True and rec["factor"] == pytest.approx(cal.factor, rel=1e-12)  # the end factor
    assert rec["effective_youngs_modulus"] == pytest.approx(2 * E * cal.factor, rel=1e-12)


def test_xpbd_load_set_refusals(mesh, loads, cal):
    card = _card()
    with pytest.raises(BudgetRangeError, match="dt"):  # another budget
        xpbd_parameters(card, dt=2 * DT, iterations=10, mesh=mesh, load_set=cal)
    with pytest.raises(BudgetRangeError, match="iterations"):
        xpbd_parameters(card, dt=DT, iterations=20, mesh=mesh, load_set=cal)
    with pytest.raises(BudgetRangeError, match="cell size"):  # another mesh
        xpbd_parameters(card, dt=DT, iterations=10, mesh=block((0.01, 0.01, 0.005), (2, 2, 1)), load_set=cal)
    with pytest.raises(ExportError, match="mesh"):
        xpbd_parameters(card, dt=DT, iterations=10, load_set=cal)
    with pytest.raises(ExportError, match="springs_volume"):  # calibrated for another constraint model
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, load_set=dataclasses.replace(cal, model_kind="springs_volume"))
    with pytest.raises(ExportError, match="Poisson ratio"):  # calibrated for another tissue
        xpbd_parameters(_card(poisson_ratio=0.3), dt=DT, iterations=10, mesh=mesh, load_set=cal)
    with pytest.raises(ExportError, match="calibrate_for_load_set"):  # the loads, not their calibration
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, load_set=loads)
    with pytest.raises(ExportError, match="pypbd"):
        export(card, "pbd", "unused.json", mesh=mesh, load_set=cal)
    with pytest.raises(ExportError, match="calibrate=False"):
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, load_set=cal, calibrate=False)
    with pytest.raises(ExportError, match="extrapolate"):
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, extrapolate=True)


def test_saturated_budget_is_refused_by_the_calibration_with_a_proposal(tmp_path, mesh, loads):
    """dt = 3 ms with 10 iterations and one substep on 2.5 mm cells: the budgeted stable neo-Hookean punch does not
    come to rest within 5000 frames; calibrate_for_load_set (the caller's step before the export) refuses, the error
    carrying the measured substep proposal (2 substeps carry it)."""
    card = _card()
    with pytest.raises(BudgetSaturationError) as info:
        cal = calibrate_for_load_set(mesh, "stable_neo_hookean", card.material(), loads, _settings(dt=3e-3),
                                     reference="stable_neo_hookean", propose=("substeps",))
        export(card, "xpbd", tmp_path / "x.json", mesh=mesh, dt=3e-3, iterations=10, load_set=cal)
    print(info.value)
    prop = info.value.proposal
    assert prop is not None and "substeps = " in str(info.value)
    assert prop.substeps is not None and prop.substeps_sensitivity >= 0.5
    assert not (tmp_path / "x.json").exists()
