"""Indentation cards recalibrated for continuum targets (issue 16).

A ``springs_volume`` card holds lattice-effective (E, nu). Exported as an indentation specimen to
a continuum target (Abaqus / CalculiX, FEBio, SOFA with a tet force field), E is recalibrated on
the experiment the card was fitted to (its scenario record: indenter, block, the fit's mesh,
depths; :func:`~difftissue.export.recalibration.recalibrated_indentation_card`). Verified: the
fitted flat-punch card exported to Abaqus and run in CalculiX reproduces the fit's data within
2 %; the card's own values are far off. The "data" are forces the springs_volume model gives at
the card's values (a fit to them returns those values exactly), so the fit's prediction is the
data.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from calculix import run_deck

from difftissue.errors import ExportError
from difftissue.export import MaterialCard, export
from difftissue.export.card import scenario_record
from difftissue.export.recalibration import recalibrated_indentation_card
from difftissue.export.specimens import indentation_specimen
from difftissue.materials import Material
from difftissue.scenarios import Indentation, indentation_block

E, NU = 14.1e3, 0.4635  # the springs_volume card
MM = 1e-3
DEPTHS = [0.05 * MM, 0.1 * MM, 0.15 * MM, 0.2 * MM]


@pytest.fixture(scope="module")
def punch_fit():
    """A bonded flat punch (the top nodes within 3.1 mm: effective radius 2.5 mm) on a bonded
    10 x 10 x 5 mm block of 4 x 4 x 2 cubes, springs_volume, four depths to 0.2 mm; the card
    records the scenario as a fit does (``scenario_record``)."""
    mesh = indentation_block((10 * MM, 10 * MM, 5 * MM), (4, 4, 2), symmetry="none")
    geo = dict(indenter="flat_punch", radius=3.1 * MM, bonded_punch=True, model="springs_volume", name="punch")
    data = np.asarray(Indentation(mesh, DEPTHS, **geo).predict(Material(E, NU)))
    sc = Indentation(mesh, DEPTHS, data, **geo)
    card = MaterialCard(model="springs_volume", name="tissue",
                        parameters={"youngs_modulus": {"value": E, "standard_error": 100.0}, "poisson_ratio": {"value": NU}},
                        provenance={"scenario_records": [scenario_record(sc)]})
    return card, data


def test_record_holds_the_fitted_experiment(punch_fit):
    card, _ = punch_fit
    rec = card.provenance["scenario_records"][0]
    assert rec["model"] == "springs_volume" and rec["cells"] == [4, 4, 2] and rec["symmetry"] == "none"
    assert rec["depths"] == DEPTHS and rec["block_size"] == pytest.approx([0.01, 0.01, 0.005])
    spec = indentation_specimen(card)
    assert spec.cells == (4, 4, 2) and spec.refine is None and "the fit's mesh" in spec.sources["cells"]
    assert spec.radius == pytest.approx(2.5e-3) and spec.bonded_punch and spec.depth == DEPTHS[-1]
    # a quarter-symmetric fit records the full block's cells
    q = Indentation(indentation_block((10 * MM, 10 * MM, 5 * MM), (2, 2, 2)), [1e-4], model="fem_linear", indenter="sphere",
                    radius=2 * MM, symmetry="quarter", penalty=50.0)
    rq = scenario_record(q)
    assert rq["cells"] == [4, 4, 2] and rq["symmetry"] == "quarter" and rq["penalty"] == pytest.approx(50.0, rel=1e-12)


def test_recalibration_factor_and_notes(punch_fit):
    card, data = punch_fit
    spec = indentation_specimen(card)
    new = recalibrated_indentation_card(card, spec, "linear")
    rec = new.provenance["recalibration"]
    assert new.model == "fem_linear" and new.poisson_ratio == NU and 0.4 < rec["factor"] < 0.8
    assert rec["depths"] == DEPTHS and np.allclose(rec["reaction_card_model"], data, rtol=1e-9)
    assert min(rec["signed_error_before"]) > 0.3 and max(abs(v) for v in rec["signed_error_after"]) < 0.02
    assert new.parameters["youngs_modulus"]["recalibrated_from"] == E
    assert "the specimen's mesh is the fit's" in " ".join(rec["notes"])
    # the least-squares factor: the recalibrated fem_linear forces on the specimen are c x those at the card's values
    f_new = np.asarray(Indentation(spec.mesh(), DEPTHS, model="fem_linear", indenter="flat_punch", radius=spec.radius,
                                   bonded_punch=True).predict(new.material()))
    np.testing.assert_allclose(f_new, rec["factor"] * np.asarray(rec["reaction_law_at_card_values"]), rtol=1e-8)


@pytest.mark.parametrize("law", ["linear", "neo_hookean"])
def test_punch_card_exported_to_abaqus_reproduces_the_data_in_calculix(punch_fit, tmp_path, law):
    """The recalibrated punch deck run in CalculiX gives the fit's force at the last depth within
    2 % (measured +0.094 % linear, -0.34 % neo-Hookean: the least-squares compromise over the four
    depths and, neo-Hookean, CalculiX's NEO HOOKE energy); the card's values, written unchanged
    (no record, approximate), are more than 30 % stiffer."""
    card, data = punch_fit
    deck = export(card, "abaqus", tmp_path / "punch.inp", indentation=indentation_specimen(card), law=law)
    text = deck.read_text()
    assert f"** RECALIBRATED for the continuum {law} law" in text
    f_ccx = -run_deck(deck, tmp_path / "ccx").totals["PUNCH"][2]
    bare = MaterialCard(model=card.model, name=card.name, parameters=card.parameters)
    raw = export(bare, "abaqus", tmp_path / "raw.inp", indentation=indentation_specimen(card), law=law, approximate=True)
    assert "APPROXIMATION: model mismatch" in raw.read_text()
    f_raw = -run_deck(raw, tmp_path / "ccx_raw").totals["PUNCH"][2]
    print(f"\nCALCULIX recalibrated punch card ({law}): data {data[-1]:.6g} N, CalculiX {f_ccx:.6g} N "
          f"({f_ccx / data[-1] - 1:+.2e}), card values {f_raw:.6g} N ({f_raw / data[-1] - 1:+.2e})")
    assert f_ccx == pytest.approx(data[-1], rel=0.02)
    assert f_raw > 1.3 * data[-1]


def test_febio_and_sofa_write_the_recalibrated_modulus(punch_fit, tmp_path):
    card, _ = punch_fit
    spec = indentation_specimen(card)
    new = recalibrated_indentation_card(card, spec, "neo_hookean")
    feb = export(card, "febio", tmp_path / "p.feb", indentation=spec)
    root = ET.parse(feb).getroot()
    assert float(root.find("Material/material/E").text) == pytest.approx(new.youngs_modulus, rel=1e-14)
    assert "RECALIBRATED for the continuum neo_hookean law" in feb.read_text()
    scn = export(card, "sofa", tmp_path / "p.scn", indentation=spec).read_text()
    assert "RECALIBRATED for the continuum neo_hookean law" in scn


def test_refused_without_a_matching_record(punch_fit, tmp_path):
    """No simulated record of the specimen's experiment: refused with the reason (one line), or
    with approximate the card's values and the measured error noted."""
    card, _ = punch_fit
    bare = MaterialCard(model=card.model, name=card.name, parameters=card.parameters)
    spec = indentation_specimen(card)
    with pytest.raises(ExportError, match=r"cannot be recalibrated: no simulated springs_volume indentation record") as e:
        export(bare, "abaqus", tmp_path / "a.inp", indentation=spec)
    assert "\n" not in str(e.value) and not (tmp_path / "a.inp").exists()
    other = indentation_specimen(card, radius=2.0 * MM)
    with pytest.raises(ExportError, match="'punch' is another experiment"):
        export(card, "febio", tmp_path / "b.feb", indentation=other)
    with pytest.raises(ExportError, match="cubic_coefficient b = 2"):
        b = MaterialCard(model=card.model, name=card.name, provenance=card.provenance,
                         parameters={**card.parameters, "cubic_coefficient": {"value": 2.0}})
        export(b, "abaqus", tmp_path / "c.inp", indentation=spec)
    text = export(bare, "abaqus", tmp_path / "a.inp", indentation=spec, approximate=True).read_text()
    assert "APPROXIMATION: model mismatch" in text and "RECALIBRATED" not in text
    e_written = float(re.search(r"\*HYPERELASTIC, NEO HOOKE\n([^,]+),", text).group(1))
    assert e_written == pytest.approx(bare.shear_modulus / 2, rel=1e-14)
