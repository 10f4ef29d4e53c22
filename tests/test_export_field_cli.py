"""``difftissue export --to pbd --field-tolerance FRACTION``: the pypbd displacement-field target
(docs/export.md, "Displacement column") from the command line, through the one entry point
``difftissue.export.export``. The budget search and the field measurement themselves are
verified against fresh pypbd runs in tests/test_export_budget.py; here the target must reach the
file (``budget_calibration.field_tolerance`` and ``field_within_tolerance``), its README, and the
refusals, on the 10 mm cube (3 x 3 x 3 cubes, 1 mm compression) at the default budget only
(no budget search: cheap)."""

from __future__ import annotations

import json

import pytest

from difftissue.cli import main
from difftissue.export import MaterialCard, write_card
from test_export_budget import E, _card

_CUBE = ["--specimen", "block:10,10,10:3,3,3", "--displacement", "-1", "--unit", "mm"]


def _export(card_path, out, *extra):
    return main(["export", str(card_path), "--to", "pbd", *_CUBE, "--out", str(out), *extra])


def test_field_tolerance_flag_reaches_the_pypbd_file_met_refused_or_approximated(tmp_path, capsys):
    """springs_volume card (nu = 0.45): the pypbd lattice's converged limit is 16.7 % of max |u| off the
    card's field, so ``--field-tolerance 0.02`` is refused at once (exit 1, no file) and written with
    ``--approximate`` at the default budget (field 29.2 %, reactions within 2 %, target recorded as NOT
    met). fem_linear card (nu = 0.42, converged limit 2.11 %): ``--field-tolerance 0.3`` is met by the
    default budget (field 26.8 %), recorded as met."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    sv = write_card(_card(), tmp_path / "sv.json")
    refused = tmp_path / "refused.json"
    assert _export(sv, refused, "--field-tolerance", "0.02") == 1
    err = capsys.readouterr().err
    assert "cannot be brought within 2 % " in err and "differs from it by 16.7 %" in err and "--approximate" in err
    assert not refused.exists()

    approx = tmp_path / "approx.json"
    assert _export(sv, approx, "--field-tolerance", "0.02", "--approximate") == 0
    rec = json.loads(approx.read_text())["budget_calibration"]
    assert rec["field_tolerance"] == 0.02 and rec["field_within_tolerance"] is False
    assert rec["within_tolerance"] and rec["budget"] == "the default budget"  # the reactions are still recalibrated
    assert rec["field_error_converged"] == pytest.approx(0.1668, abs=0.005)
    assert rec["field_error"] == pytest.approx(0.2919, abs=0.02)  # as in test_export_budget (re-run there in pypbd)

    fl = write_card(MaterialCard(model="fem_linear", name="skin",
                                 parameters={"youngs_modulus": {"value": E, "unit": "Pa"}, "poisson_ratio": {"value": 0.42, "unit": "1"}}),
                    tmp_path / "fl.json")
    met = tmp_path / "met.json"
    assert _export(fl, met, "--field-tolerance", "0.3") == 0
    rec = json.loads(met.read_text())["budget_calibration"]
    assert rec["field_tolerance"] == 0.3 and rec["field_within_tolerance"] is True
    assert rec["budget"] == "the default budget" and rec["budgets_tried"] == [[pytest.approx(1 / 60), 1, 10]]
    assert rec["field_error"] == pytest.approx(0.268, abs=0.02) and rec["field_error"] <= 0.3
    assert rec["field_error_converged"] == pytest.approx(0.0211, abs=0.002)
    # without the flag the same export records no target (the flag, not a default, set it above)
    plain = tmp_path / "plain.json"
    assert _export(fl, plain) == 0
    rec0 = json.loads(plain.read_text())["budget_calibration"]
    assert rec0["field_tolerance"] is None and rec0["field_within_tolerance"] is None
    assert rec0["field_error"] == pytest.approx(rec["field_error"], rel=1e-9)

    readme = (tmp_path / "README.md").read_text()
    sections = {s.split("\n", 1)[0]: s for s in readme.split("\n## ")[1:]}
    assert "field target 2 % NOT met" in sections["approx.json"] and "converged limit of every budget: 16.7 %" in sections["approx.json"]
    assert "field target 30 % met" in sections["met.json"]
    assert "no field target (--field-tolerance)" in sections["plain.json"]


def test_field_tolerance_is_refused_where_no_field_is_measured(tmp_path, capsys):
    """Other targets, the material alone, and a target that is not a positive fraction: one line, exit 1."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    sv = write_card(_card(), tmp_path / "sv.json")
    assert main(["export", str(sv), "--to", "febio", *_CUBE, "--field-tolerance", "0.1", "--out", str(tmp_path / "x.feb")]) == 1
    assert "--field-tolerance applies to the pbd target only" in capsys.readouterr().err
    assert main(["export", str(sv), "--to", "pbd", "--field-tolerance", "0.1", "--out", str(tmp_path / "m.json")]) == 1
    assert "--field-tolerance: the scene holds the material alone" in capsys.readouterr().err
    assert _export(sv, tmp_path / "neg.json", "--field-tolerance", "-0.1") == 1
    assert "--field-tolerance = -0.1: expected a fraction > 0" in capsys.readouterr().err
    assert not any((tmp_path / n).exists() for n in ("x.feb", "m.json", "neg.json"))
