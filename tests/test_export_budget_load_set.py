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
    """The caller's step: the load-set calibration of the file's constraint pair at the export's budget.

    One optimiser step (``max_steps=1``; the default fit takes 3 here, each a budgeted solve of both loads with its
    Jacobian): what these tests check is that the export writes and reproduces the calibration it is given, whichever
    card that is; the fit's convergence is test_budget_load_set's."""
    return calibrate_for_load_set(mesh, "stable_neo_hookean", _card().material(), loads, _settings(), reference="stable_neo_hookean",
                                  max_steps=1)


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
    come to rest; calibrate_for_load_set (the caller's step before the export) refuses, the error carrying the measured
    substep proposal (2 substeps carry it).

    The punch's frames keep oscillating: the largest position change per frame was 0.71, 0.62, 0.78, 0.42 and 0.84 mm
    (8x the 0.1 mm depth) after 200, 500, 1000, 2000 and 5000 frames (measured 2026-12-05), so 500 frames
    (max_frames; the default 5000 ran that non-resting solve ten times longer) show the same refusal. At 2 substeps the
    punch rests in 16 frames, the platen in 9."""
    card = _card()
    with pytest.raises(BudgetSaturationError) as info:
        cal = calibrate_for_load_set(mesh, "stable_neo_hookean", card.material(), loads, _settings(dt=3e-3),
                                     reference="stable_neo_hookean", propose=("substeps",), max_frames=500)
        export(card, "xpbd", tmp_path / "x.json", mesh=mesh, dt=3e-3, iterations=10, load_set=cal)
    print(info.value)
    prop = info.value.proposal
    assert prop is not None and "substeps = " in str(info.value)
    assert prop.substeps is not None and prop.substeps_sensitivity >= 0.5
    assert not (tmp_path / "x.json").exists()


# ----------------------------------------------------------------------------- the command line: --load-set FILE
_LOAD_SET_TOML = """
[budget]
length_unit = "mm"
reference = "stable_neo_hookean"

[[budget.loads]]
shape = "flat_punch"
depth = 0.1
radius = 3

[[budget.loads]]
shape = "platen"
depth = 0.1
"""


def _cli_export(tmp_path, *extra, toml=_LOAD_SET_TOML, card=None):
    from difftissue.cli import main
    from difftissue.export import write_card

    write_card(card or _card(), tmp_path / "material.json", force=True)
    (tmp_path / "loads.toml").write_text(toml)
    argv = [str(tmp_path / "material.json"), "--to", "xpbd", "--out", str(tmp_path / "x.json"), "--force", "--dt", str(DT),
            "--iterations", "10", "--load-set", str(tmp_path / "loads.toml")]
    return main(["export", *argv, *extra])


def test_cli_load_set_file_is_the_python_calibration(tmp_path, monkeypatch, capsys, mesh, loads, cal):
    """`difftissue export --to xpbd --specimen block:... --load-set FILE`: the file's [budget] table becomes the loads the
    Python path builds (the same boundary conditions), calibrate_for_load_set is called with the export's budget, the
    card's material and the file's reference, and the JSON written is the Python export's. The calibration itself is
    the module's (the call is checked, then answered with the fixture: no second calibration)."""
    import difftissue.budget

    calls = []

    def fake(mesh_, model_kind, material, loads_, settings, **kw):
        calls.append(1)
        assert model_kind == "stable_neo_hookean" and kw == {"reference": "stable_neo_hookean"}
        assert float(material.youngs_modulus) == E and float(material.poisson_ratio) == NU
        assert (settings.dt, settings.substeps, settings.iterations, settings.method, settings.warm_start) == (DT, 1, 10, "gauss_seidel", False)
        assert np.asarray(mesh_.points).shape == np.asarray(mesh.points).shape
        np.testing.assert_allclose(np.asarray(mesh_.points), np.asarray(mesh.points), rtol=0, atol=1e-15)
        assert [(ld.shape, ld.youngs_modulus) for ld in loads_] == [("flat_punch", None), ("platen", None)]
        for got, want in zip(loads_, loads):
            assert got.depth == pytest.approx(want.depth, rel=1e-12)
            np.testing.assert_array_equal(np.asarray(got.bc.fixed), np.asarray(want.bc.fixed))
            np.testing.assert_allclose(np.asarray(got.bc.displacement), np.asarray(want.bc.displacement), rtol=1e-12, atol=0)
        return cal

    monkeypatch.setattr(difftissue.budget, "calibrate_for_load_set", fake)
    assert _cli_export(tmp_path, "--specimen", "block:10,10,5:4,4,2") == 0
    assert calls == [1]
    out = capsys.readouterr().out
    assert "calibrated over 2 loads" in out and f"{100 * cal.max_error:.3g} %" in out
    doc = json.loads((tmp_path / "x.json").read_text())
    py = json.loads(export(_card(), "xpbd", tmp_path / "py.json", mesh=mesh, dt=DT, iterations=10, load_set=cal).read_text())
    assert doc["budget_calibration"] == py["budget_calibration"] and doc["per_tet"] == py["per_tet"]
    assert doc["validity"] == py["validity"] and "CALIBRATED OVER A LOAD SET" in doc["validity"]
    readme = (tmp_path / "README.md").read_text()
    print(readme)
    assert "- CALIBRATED OVER A LOAD SET (--load-set): E_eff = " in readme
    assert "indenter shapes flat_punch, platen; depths 0.0001 ... 0.0001 m; tissue moduli 1e+04 ... 1e+04 Pa; cells of 0.0025 m" in readme
    for row in cal.loads:
        assert f"{row['name']} {100 * row['error']:+.3g} %" in readme
    assert "recalibrated: nothing" not in readme and "EXTRAPOLATED" not in readme


def test_cli_load_set_usage_and_early_refusals(tmp_path, monkeypatch, capsys):
    """Wrong combinations and a card outside the file's moduli are refused before anything is calibrated."""
    import difftissue.budget

    def never(*a, **k):
        raise AssertionError("calibrated although the input was refused")

    monkeypatch.setattr(difftissue.budget, "calibrate_for_load_set", never)
    spec = ("--specimen", "block:10,10,5:4,4,2")
    cases = [
        ((), _LOAD_SET_TOML, 2, "--load-set needs the simulator's mesh"),
        (spec + ("--specimen", "fitted"), _LOAD_SET_TOML, 2, "not fitted"),
        (spec, _LOAD_SET_TOML.replace('length_unit = "mm"', 'length_unit = "mm"\nyoungs_moduli = [20e3, 40e3]'), 1,
         "Young's modulus 10000 Pa lies outside the load set's moduli 20000 ... 40000 Pa"),
        (spec, _LOAD_SET_TOML.replace('length_unit = "mm"\n', ''), 1, "budget.loads[0].depth: 0.1 m is not less than the mesh's height"),
        (spec, _LOAD_SET_TOML.replace('"platen"', '"cone"'), 1, "budget.loads[1].shape: must be one of flat_punch, sphere, platen, got 'cone'"),
        (spec, _LOAD_SET_TOML.replace("[budget]", "[budgets]"), 1, "unknown key 'budgets'; allowed: budget"),
        (spec, _LOAD_SET_TOML.replace("depth = 0.1\nradius = 3", "depth = 0.1"), 1, "budget.loads[0]: missing key 'radius'"),
        (spec, "[budget\n", 1, "invalid TOML"),
    ]
    for extra, toml, rc, msg in cases:
        assert _cli_export(tmp_path, *extra, toml=toml) == rc, msg
        err = capsys.readouterr().err
        assert msg in err, (msg, err)
        assert "calibrating" not in err
    from difftissue.cli import main

    card = str(tmp_path / "material.json")
    assert main(["export", card, "--to", "pbd", "--out", str(tmp_path / "p.json"), "--load-set", str(tmp_path / "loads.toml"), *spec]) == 2
    assert "--load-set calibrates the XPBD JSON (--to xpbd), not --to pbd" in capsys.readouterr().err
    assert main(["export", card, "--to", "xpbd", "--dt", "1e-3", "--iterations", "10", "--out", str(tmp_path / "y.json"),
                 "--extrapolate", *spec]) == 2
    assert "--extrapolate applies to --load-set" in capsys.readouterr().err
    assert main(["export", card, "--to", "xpbd", "--dt", "1e-3", "--iterations", "10", "--out", str(tmp_path / "y.json"),
                 "--load-set", str(tmp_path / "nosuch.toml"), *spec]) == 1
    assert "load-set file not found" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists() and not (tmp_path / "y.json").exists()


_GOOD = {"length_unit": "mm", "loads": [{"shape": "flat_punch", "depth": 0.1, "radius": 3.0}, {"shape": "platen", "depth": 0.2}]}


def _with(path, value):
    """_GOOD with the key at ``path`` (a tuple of keys / indices) set to ``value`` (None: removed)."""
    raw = json.loads(json.dumps(_GOOD))
    t = raw
    for k in path[:-1]:
        t = t[k]
    if value is None:
        del t[path[-1]]
    else:
        t[path[-1]] = value
    return raw


@pytest.mark.parametrize("path, value, msg", [
    (("lenght_unit",), "mm", "budget: unknown key 'lenght_unit'; allowed: length_unit, youngs_moduli"),
    (("loads",), None, "budget: missing key 'loads'"),
    (("loads",), [], "budget.loads: must be one or more [[budget.loads]] tables"),
    (("length_unit",), "inch", "budget.length_unit: must be one of 'm', 'cm', 'mm', 'um'"),
    (("youngs_moduli",), "10 kPa", "budget.youngs_moduli: must be a non-empty list of Young's moduli in Pa"),
    (("youngs_moduli",), [10e3, -5e3], "budget.youngs_moduli[1]: must be > 0 Pa, got -5000.0"),
    (("reference",), "hertz", "budget.reference: must be one of springs_volume, stable_neo_hookean, fem_linear, fem_neo_hookean"),
    (("propose",), "yes", "budget.propose: must be true, false or a list of 'iterations' and/or 'substeps'"),
    (("propose",), ["dt"], "budget.propose: must be true, false or a list"),
    (("max_steps",), -1, "budget.max_steps: must be an integer >= 0"),
    (("effective_poisson",), "no", "budget.effective_poisson: must be true or false"),
    (("loads", 0, "shape"), "punch", "budget.loads[0].shape: must be one of flat_punch, sphere, platen, got 'punch'"),
    (("loads", 0, "shape"), None, "budget.loads[0]: missing key 'shape'"),
    (("loads", 1, "depth"), None, "budget.loads[1]: missing key 'depth'"),
    (("loads", 1, "depth"), "0.2 mm", "budget.loads[1].depth: must be a number in mm, got '0.2 mm'"),
    (("loads", 1, "depth"), -0.2, "budget.loads[1].depth: must be > 0 mm"),
    (("loads", 1, "depth"), 5.0, "budget.loads[1].depth: 0.005 m is not less than the mesh's height 0.005 m"),
    (("loads", 1, "length_unit"), "m", "budget.loads[1].depth: 0.2 m is not less than the mesh's height"),
    (("loads", 0, "radius"), None, "budget.loads[0]: missing key 'radius' (the flat_punch's radius)"),
    (("loads", 0, "radius"), 3000.0, "budget.loads[0].radius: the flat_punch's radius 3 m covers the whole top face"),
    (("loads", 1, "radius"), 3.0, "budget.loads[1].radius: a platen moves the whole top face: it has no radius"),
    (("loads", 1, "youngs_moduli"), [0.0], "budget.loads[1].youngs_moduli[0]: must be > 0 Pa"),
    (("loads", 1, "stiffness"), 1.0, "budget.loads[1]: unknown key 'stiffness'"),
    (("loads", 0), "punch", "budget.loads[0]: must be a table"),
])
def test_load_set_table_bad_input(mesh, path, value, msg):
    from difftissue.budget import parse_load_set
    from difftissue.errors import ConfigError

    with pytest.raises(ConfigError) as info:
        parse_load_set(_with(path, value), mesh, _card().material())
    assert msg in str(info.value), str(info.value)


def test_load_set_table_units_moduli_and_a_sphere(mesh):
    """Lengths in the table's unit (a load's own unit wins), one load per modulus (a load's own list wins), the same
    boundary conditions as indentation_load with SI lengths; a sphere whose contact patch covers the face is refused,
    as is an indenter under which no top node lies."""
    from difftissue.budget import indentation_load, parse_load_set
    from difftissue.errors import ConfigError

    raw = {"length_unit": "mm", "youngs_moduli": [5e3, 20e3], "effective_poisson": True, "propose": ["substeps"], "max_steps": 5,
           "loads": [{"shape": "flat_punch", "depth": 0.1, "radius": 3.0},
                     {"shape": "sphere", "depth": 2e-4, "radius": 0.01, "length_unit": "m", "youngs_moduli": [10e3], "name": "ball"}]}
    spec = parse_load_set(raw, mesh, _card().material())
    assert [(ld.shape, ld.youngs_modulus, ld.label()) for ld in spec.loads] == [
        ("flat_punch", 5e3, "flat_punch 0.1 mm E 5000 Pa"), ("flat_punch", 20e3, "flat_punch 0.1 mm E 2e+04 Pa"), ("sphere", 10e3, "ball")]
    assert spec.youngs_modulus_range == (5e3, 20e3) and spec.reference is None
    assert spec.options == {"effective_poisson": True, "propose": ("substeps",), "max_steps": 5}
    want = indentation_load(mesh, "sphere", 2e-4, radius=0.01)
    np.testing.assert_array_equal(np.asarray(spec.loads[2].bc.fixed), np.asarray(want.bc.fixed))
    np.testing.assert_array_equal(np.asarray(spec.loads[2].bc.displacement), np.asarray(want.bc.displacement))
    assert spec.loads[0].depth == pytest.approx(1e-4, rel=1e-12)
    with pytest.raises(ConfigError, match=r"budget.loads\[0\].radius: the sphere's contact radius sqrt\(2 radius depth\) = 0.1 m"):
        parse_load_set({"loads": [{"shape": "sphere", "depth": 1e-3, "radius": 5.0}]}, mesh, _card().material())
    odd = block((0.01, 0.01, 0.005), (3, 3, 1))  # no node on the axis
    with pytest.raises(ConfigError, match=r"budget.loads\[0\]: indentation_load: no top node under the flat_punch"):
        parse_load_set({"loads": [{"shape": "flat_punch", "depth": 1e-4, "radius": 5e-4}]}, odd, _card().material())


def test_cli_load_set_saturation_is_reported_and_nothing_written(tmp_path, monkeypatch, capsys):
    """The calibration's BudgetSaturationError (its message carries the proposal) ends the command with status 1 and
    the message on one line; no file is written. (The saturation itself is measured by the Python test above.)"""
    import difftissue.budget

    def saturated(*a, **k):
        raise BudgetSaturationError("XPBD at dt = 0.003 s ... is saturated [at the true modulus]; a budget that carries it "
                                    "(measured): substeps = 2", sensitivity=np.array([0.2, 0.3]), proposal=None)

    monkeypatch.setattr(difftissue.budget, "calibrate_for_load_set", saturated)
    assert _cli_export(tmp_path, "--specimen", "block:10,10,5:4,4,2") == 1
    err = capsys.readouterr().err
    assert "difftissue: error: XPBD at dt = 0.003 s" in err and err.rstrip().endswith("substeps = 2")
    assert not (tmp_path / "x.json").exists() and not (tmp_path / "README.md").exists()


def test_cli_load_set_extrapolate_writes_the_end_factor_and_says_so(tmp_path, monkeypatch, capsys, cal):
    """A card at 2 E with the file's moduli [E]: refused before calibrating without --extrapolate; with it the end
    factor is written, the warning printed, and README.md says EXTRAPOLATED (the module's calibration answers)."""
    import difftissue.budget

    monkeypatch.setattr(difftissue.budget, "calibrate_for_load_set", lambda *a, **k: cal)
    toml = _LOAD_SET_TOML.replace('length_unit = "mm"', f'length_unit = "mm"\nyoungs_moduli = [{E}]')
    spec = ("--specimen", "block:10,10,5:4,4,2")
    assert _cli_export(tmp_path, *spec, toml=toml, card=_card(youngs_modulus=2 * E)) == 1
    assert "pass --extrapolate" in capsys.readouterr().err and not (tmp_path / "x.json").exists()
    with pytest.warns(BudgetExtrapolationWarning, match="Young's modulus"):
        assert _cli_export(tmp_path, *spec, "--extrapolate", toml=toml, card=_card(youngs_modulus=2 * E)) == 0
    rec = json.loads((tmp_path / "x.json").read_text())["budget_calibration"]
    assert rec["extrapolated"] is True and rec["effective_youngs_modulus"] == pytest.approx(2 * E * cal.factor, rel=1e-12)
    assert "- EXTRAPOLATED (--extrapolate)" in (tmp_path / "README.md").read_text()
