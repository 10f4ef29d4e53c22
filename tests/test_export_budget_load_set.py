"""The XPBD JSON export calibrated over a load set (docs/export.md, "Calibrating the XPBD file
over a load set"): the file carries the card of difftissue.budget.calibrate_for_load_set (its
factor and validity range), its compliances reproduce the card's forces when run from the file,
and a saturated budget is refused with the proposed budget."""

from __future__ import annotations

import json

import numpy as np
import pytest

from difftissue.budget import calibrate_for_load_set, indentation_load
from difftissue.errors import BudgetRangeError, BudgetSaturationError, ExportError
from difftissue.export import MaterialCard, export, xpbd_parameters
from difftissue.export.budget import ExportLoadSet, xpbd_budget_reactions
from difftissue.mesh import block
from difftissue.solvers.xpbd import XPBDSettings

E, NU = 10e3, 0.45
DT = 2.5e-4


def _card():
    return MaterialCard(model="stable_neo_hookean", parameters={"youngs_modulus": {"value": E, "unit": "Pa"},
                                                                "poisson_ratio": {"value": NU, "unit": "1"}}, name="skin")


@pytest.fixture(scope="module")
def mesh():
    return block((0.01, 0.01, 0.005), (4, 4, 2))  # 2.5 mm cells (tests/test_budget_load_set.py)


@pytest.fixture(scope="module")
def loads(mesh):
    return [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3), indentation_load(mesh, "platen", 1e-4)]


def test_xpbd_export_over_a_load_set_writes_the_card_and_its_range(tmp_path, mesh, loads):
    card = _card()
    path = export(card, "xpbd", tmp_path / "x.json", mesh=mesh, dt=DT, iterations=10, load_set=loads)
    doc = json.loads(path.read_text())
    rec = doc["budget_calibration"]
    settings = XPBDSettings(dt=DT, substeps=1, iterations=10, method="gauss_seidel", damping=float("inf"), warm_start=False)
    cal = calibrate_for_load_set(mesh, "stable_neo_hookean", card.material(), loads, settings, reference="stable_neo_hookean")
    print(rec["factor"], cal.factors, cal.max_error, [(r["name"], r["error"], r["sensitivity"]) for r in cal.loads])
    assert rec["method"] == "load set" and rec["factors"] == pytest.approx(list(cal.factors), rel=1e-9)
    assert rec["factor"] == pytest.approx(cal.factor, rel=1e-9) and rec["max_residual_error"] == pytest.approx(cal.max_error, rel=1e-6)
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


def test_xpbd_load_set_refusals(mesh, loads):
    card = _card()
    # the card's modulus outside the set's stiffness range: refused before anything is written
    stiff = [indentation_load(mesh, "flat_punch", 1e-4, radius=3e-3, youngs_modulus=2 * E)]
    with pytest.raises(BudgetRangeError, match="Young's modulus"):
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, load_set=stiff)
    with pytest.raises(ExportError, match="pypbd"):
        export(card, "pbd", "unused.json", mesh=mesh, load_set=loads)
    with pytest.raises(ExportError, match="calibrate=False"):
        xpbd_parameters(card, dt=DT, iterations=10, mesh=mesh, load_set=loads, calibrate=False)
    with pytest.raises(ExportError, match="mesh"):
        xpbd_parameters(card, dt=DT, iterations=10, load_set=loads)


def test_xpbd_load_set_saturated_budget_is_refused_with_a_proposal(mesh, loads):
    """dt = 3 ms with 10 iterations and one substep on 2.5 mm cells: the budgeted stable neo-Hookean punch does not
    come to rest within 5000 frames; refused, the error carrying the measured substep proposal (2 substeps carry it)."""
    with pytest.raises(BudgetSaturationError) as info:
        xpbd_parameters(_card(), dt=3e-3, iterations=10, mesh=mesh, load_set=ExportLoadSet(loads, propose=("substeps",)))
    print(info.value)
    prop = info.value.proposal
    assert prop is not None and "substeps = " in str(info.value)
    assert prop.substeps is not None and prop.substeps_sensitivity >= 0.5
