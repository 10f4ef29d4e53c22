"""Fitted compression specimens (difftissue.export.fitted, docs/export.md "Fitted specimens:
fem_field, compression and incision"): a Compression fit's experiment (the model's block or
cylinder mesh, the platens at the last strain of the protocol, the top face as reaction set)
written as a specimen file with its protocol in the card, exported to FEBio / Abaqus / SOFA,
parsed back and solved in scikit-fem: the displacement field equals difftissue's fem_linear
solution at the last strain and the top reaction gives Compression.predict's stress there.

Cases (all fem_linear, E = 12 kPa, nu = 0.42): a 10 x 10 x 5 mm block on 2 x 2 x 2 cells with
frictionless platens (engineering; analytic: stress = E eps) and with bonded platens; a 10 mm
diameter, 5 mm high cylinder (1 radial cell, 2 in height) with bonded platens (engineering)
and with frictionless platens (true strain and stress).
"""

import json
import math
import re
from functools import partial
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from test_export_fitted import _skfem_solve, parse_abaqus, parse_febio, parse_sofa

from difftissue.cli import main
from difftissue.errors import ExportError
from difftissue.export import MaterialCard, export, read_card, write_card
from difftissue.export.card import scenario_record
from difftissue.export.fitted import (
    MAX_STRAIN_INCREMENT,
    fitted_specimen,
    fitted_specimen_from_card,
    load_steps,
    specimen_file_name,
    specimen_record,
    write_specimen,
)
from difftissue.export.xpbd import xpbd_fitted_parameters
from difftissue.mesh import block
from difftissue.scenarios import Compression, cylinder

pytest.importorskip("skfem")

E, NU = 12.0e3, 0.42
MM = 1e-3
CASES = {
    "block_frictionless": dict(shape="block", bonded=False, measure="engineering", strains=[0.02, 0.05, 0.1]),
    "block_bonded": dict(shape="block", bonded=True, measure="engineering", strains=[0.02, 0.05, 0.1]),
    "cylinder_bonded": dict(shape="cylinder", bonded=True, measure="engineering", strains=[0.05, 0.1]),
    "cylinder_frictionless_true": dict(shape="cylinder", bonded=False, measure="true", strains=[0.05, 0.1]),
}


def _card(provenance=None):
    return MaterialCard(model="fem_linear", name="fitted_lin", provenance=provenance,
                        parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}})


def _mesh(shape):
    return block((10 * MM, 10 * MM, 5 * MM), (2, 2, 2)) if shape == "block" else cylinder(10 * MM, 5 * MM, 1, 2)


def _write_case(tmp, sc):
    """What write_fit_outputs does for one scenario: the specimen file beside the card, its
    record (sha256) in the scenario record, which holds the protocol."""
    fs = fitted_specimen(sc)
    path = write_specimen(fs, tmp / specimen_file_name(sc.name))
    rec = {**scenario_record(sc), "specimen_file": specimen_record(fs, path)}
    return write_card(_card({"scenario_records": [rec]}), tmp / "material.json")


@pytest.fixture(scope="module", params=list(CASES))
def case(request, tmp_path_factory):
    c = CASES[request.param]
    sc = Compression(_mesh(c["shape"]), c["strains"], model="fem_linear", bonded=c["bonded"], measure=c["measure"], name=request.param)
    tmp = tmp_path_factory.mktemp(request.param)
    card_path = _write_case(tmp, sc)
    stress, us = sc.solve(_card().material())
    return {"name": request.param, **c, "scenario": sc, "card_path": card_path, "stress": np.asarray(stress), "u": np.asarray(us)[-1]}


def parse_sofa_ramped(path):
    """parse_sofa plus the PartialLinearMovementProjectiveConstraints: their moved directions are
    held, their value is the movement at key time 1 (held until the last key time)."""
    p = parse_sofa(path)
    root = ET.parse(path).getroot()
    node = root.find("Node")
    p["dt"] = float(root.get("dt"))
    solver = node.find("StaticSolver")
    p["newton_iterations"] = int(solver.get("newton_iterations"))
    for c in node.findall("PartialLinearMovementProjectiveConstraint"):
        idx = np.array([int(v) for v in c.get("indices").split()])
        dirs = np.flatnonzero([v == "1" for v in c.get("movedDirections").split()])
        times = [float(v) for v in c.get("keyTimes").split()]
        m = np.array([float(v) for v in c.get("movements").split()]).reshape(-1, 3)
        assert times[:2] == [0.0, 1.0] and times[-1] > 1e3 and len(m) == len(times)
        assert not m[0].any() and np.array_equal(m[1], m[-1])  # 0 at t = 0, ramped to the value at t = 1, held after
        assert not p["fixed"][idx].any()  # not also a Fixed constraint
        p["fixed"][np.ix_(idx, dirs)] = True
        p["prescribed"][np.ix_(idx, dirs)] = m[1][dirs]
    return p


def _reference(case):
    """The scenario's boundary conditions at the last strain (as Compression._solve_protocol)."""
    sc = case["scenario"]
    e = case["strains"][-1] if case["measure"] == "engineering" else -math.expm1(-case["strains"][-1])
    presc = np.where(sc.bc.fixed, np.asarray(sc.bc.displacement), 0.0)
    top = np.asarray(sc.top_mask)
    presc[top, 2] = -e * sc.height
    return np.asarray(sc.bc.fixed), presc, np.flatnonzero(top), e


@pytest.mark.parametrize("target", ["febio", "abaqus", "sofa"])
def test_compression_round_trip_through_skfem(case, target, tmp_path):
    """The written model parsed back into scikit-fem: displacement field = difftissue's fem_linear
    solution at the last strain (1e-10 of its maximum), top-platen stress = Compression.predict
    there (1e-8 relative); frictionless: the homogeneous uniaxial answer (engineering E e, true
    E e / (1 + nu e)^2 of the linear solution's current volume), 1e-9."""
    sc = case["scenario"]
    out = tmp_path / {"febio": "model.feb", "abaqus": "model.inp", "sofa": "model.scn"}[target]
    assert main(["export", str(case["card_path"]), "--to", target, "--specimen", "fitted", "--out", str(out)]) == 0
    parsed = {"febio": parse_febio, "abaqus": parse_abaqus, "sofa": parse_sofa_ramped}[target](out)
    fixed, presc, top, e = _reference(case)
    # Abaqus data fields are at most 20 characters (abaqus_number): exact where the shortest
    # round-trip spelling fits, else within its stated 5e-15 relative for these magnitudes
    same = np.testing.assert_array_equal if target != "abaqus" else partial(np.testing.assert_allclose, rtol=5e-15, atol=0)
    same(parsed["points"], np.asarray(sc.model.rest_points))
    np.testing.assert_array_equal(parsed["tets"], np.asarray(sc.model.tets))
    np.testing.assert_array_equal(parsed["fixed"], fixed)
    same(parsed["prescribed"], presc)  # the top platen at -e H, bit-exact (Abaqus: see above)
    if case["bonded"]:
        assert fixed[top].all()
    else:  # u_z of both faces, plus the rigid-body pins of Platens.apply: 3 in-plane components in all
        assert not fixed[top, :2].any() and int(fixed[:, :2].sum()) == 3
    (E_, nu_), = [(m["E"], m["v"]) for m in parsed["materials"]] if target == "febio" else parsed["materials"]
    assert E_ == E and nu_ == NU
    if target == "febio":
        np.testing.assert_array_equal(np.sort(parsed["sets"]["reaction"]), top)
    elif target == "abaqus":
        np.testing.assert_array_equal(np.sort(parsed["sets"]["REACTION"]), top)
    else:
        assert parsed["dt"] == 1.0 / load_steps(fitted_specimen(sc)) and parsed["newton_iterations"] > 1
    u_sk, r_sk = _skfem_solve(parsed, E_, nu_, top)
    assert np.abs(u_sk - case["u"]).max() <= 1e-10 * np.abs(case["u"]).max()
    force = -r_sk  # N, compressive positive
    if case["measure"] == "engineering":
        stress = force / sc.area
    else:
        x = parsed["points"] + u_sk
        t = parsed["tets"]
        vol = np.sum(np.abs(np.einsum("ij,ij->i", np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]), x[t[:, 3]] - x[t[:, 0]]))) / 6
        stress = force * (1 - e) * sc.height / vol
    assert stress > 0.05 * E * e
    assert abs(stress - case["stress"][-1]) <= 1e-8 * case["stress"][-1]
    if not case["bonded"]:  # analytic: homogeneous uniaxial stress E e, lateral strain nu e
        exact = E * e if case["measure"] == "engineering" else E * e / (1 + NU * e) ** 2  # true: F h / V, V = V0 (1 + nu e)^2 (1 - e)
        assert abs(stress - exact) <= 1e-9 * exact
    if case["bonded"]:
        assert stress > 1.05 * E * e  # the platens restrain the lateral expansion


def test_compression_record_and_specimen_file(case):
    """The card's scenario record holds the protocol; the specimen read back is the model's mesh
    with the platens at the last strain, the top face z as the reaction set."""
    sc = case["scenario"]
    card = read_card(case["card_path"])
    rec, = card.provenance["scenario_records"]
    fixed, presc, top, e = _reference(case)
    assert rec["experiment"] == "compression" and rec["model"] == "fem_linear" and rec["type"] == "Compression"
    assert rec["platens"] == ("bonded" if case["bonded"] else "frictionless") and rec["measure"] == case["measure"]
    assert rec["strains"] == case["strains"] and rec["nominal_strains"][-1] == e
    assert rec["height"] == sc.height == pytest.approx(5 * MM, rel=1e-14) and rec["area"] == sc.area
    assert rec["top_displacement"] == -e * sc.height and rec["specimen_file"]["format"] == "difftissue-specimen/1"
    if case["shape"] == "block":
        assert sc.area == pytest.approx(1e-4, rel=1e-12)
    else:  # the polygonal cross-section, a little less than the circle's
        assert 0.6 * math.pi * 25e-6 < sc.area < math.pi * 25e-6
    spec = fitted_specimen_from_card(card, case["card_path"])
    assert spec.experiment == "compression" and spec.protocol["platens"] == rec["platens"]
    np.testing.assert_array_equal(spec.points, np.asarray(sc.model.rest_points))
    np.testing.assert_array_equal(spec.fixed, fixed)
    np.testing.assert_array_equal(spec.prescribed, presc)
    np.testing.assert_array_equal(np.flatnonzero(spec.reaction[:, 2]), top)
    assert not spec.reaction[:, :2].any()


def test_compression_xpbd_and_vtu(case, tmp_path):
    card = read_card(case["card_path"])
    spec = fitted_specimen_from_card(card, case["card_path"])
    doc = xpbd_fitted_parameters(card, spec, dt=1e-3, iterations=10, calibrate=False)  # the conversion (budget: test_export_xpbd_fitted.py)
    sp = doc["specimen"]
    assert sp["experiment"] == "compression" and sp["protocol"]["strains"] == case["strains"]
    assert sp["load_steps"] == load_steps(spec) and sp["reaction"]["z"] == np.flatnonzero(spec.reaction[:, 2]).tolist()
    presc = np.zeros_like(spec.prescribed)
    for n, c, v in sp["prescribed_displacement"]:
        presc[n, c] = v
    np.testing.assert_array_equal(presc, spec.prescribed)
    from difftissue.mesh import read_mesh

    v = read_mesh(export(card, "vtu", tmp_path / "s.vtu", fitted=spec))
    np.testing.assert_array_equal(np.asarray(v.point_data["reaction_set"]).reshape(-1, 3) != 0, spec.reaction)


def test_finite_strain_protocol_is_ramped(tmp_path):
    """40 % nominal strain (the Ecoflex example's range): FEBio, Abaqus and SOFA reach it in
    increments of at most MAX_STRAIN_INCREMENT = 2 % (20 steps); small strains keep 10."""
    mesh = block((10 * MM, 10 * MM, 10 * MM), (1, 1, 2))
    sc = Compression(mesh, [0.1, 0.25, 0.4], model="fem_neo_hookean", bonded=True, name="big")
    small = Compression(mesh, [0.01], model="fem_neo_hookean", name="small")
    spec, spec_small = fitted_specimen(sc), fitted_specimen(small)
    assert load_steps(spec) == 20 and load_steps(spec_small) == 10 and MAX_STRAIN_INCREMENT == 0.02
    card = MaterialCard(model="fem_neo_hookean", parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}})
    febio = ET.parse(export(card, "febio", tmp_path / "m.feb", fitted=spec)).getroot()
    assert febio.find("Control/time_steps").text == "20" and float(febio.find("Control/step_size").text) == 0.05
    assert febio.find("Material/material").get("type") == "neo-Hookean"
    pts = [tuple(float(v) for v in p.text.split(",")) for p in febio.findall("LoadData/load_controller/points/pt")]
    assert pts == [(0.0, 0.0), (1.0, 1.0)]  # linear ramp of the NodeData values
    inp = export(card, "abaqus", tmp_path / "m.inp", fitted=spec).read_text().splitlines()
    i = inp.index("*STATIC")
    assert inp[i + 1] == "0.05, 1.0, 1e-05, 0.05" and inp[i - 1] == "*STEP, NLGEOM=YES"
    sofa = ET.parse(export(card, "sofa", tmp_path / "m.scn", fitted=spec)).getroot()
    assert float(sofa.get("dt")) == 0.05
    mv, = sofa.findall("Node/PartialLinearMovementProjectiveConstraint")
    assert mv.get("movedDirections") == "1 1 1"  # bonded
    assert mv.get("movements").split()[-1] == repr(-0.4 * 0.01)
    assert "TetrahedronHyperelasticityFEMForceField" in ET.tostring(sofa, encoding="unicode")
    mesh_inp = export(card, "abaqus", tmp_path / "s.inp", fitted=spec_small).read_text()
    assert "0.1, 1.0, 1e-05, 0.1" in mesh_inp


def test_compression_specimen_errors(tmp_path):
    """A compression record without its protocol, with unknown platens, or whose top
    displacement disagrees with the file is refused with one line; pypbd refuses frictionless platens;
    --specimen block:... still writes the typed block."""
    sc = Compression(block((10 * MM, 10 * MM, 5 * MM), (1, 1, 1)), [0.05, 0.1], model="fem_linear", name="c")
    card_path = _write_case(tmp_path, sc)
    card = read_card(card_path)
    rec, = card.provenance["scenario_records"]
    assert fitted_specimen_from_card(card, card_path).protocol["top_displacement"] == -0.1 * 5 * MM
    for k, (change, why) in enumerate(((("top_displacement", rec["top_displacement"] * 0.5), "disagree"),
                                       (("height", None), "needs its protocol"), (("platens", "glued"), "platens 'glued'"))):
        r = dict(rec)
        if change[1] is None:
            del r[change[0]]
        else:
            r[change[0]] = change[1]
        bad = write_card(_card({"scenario_records": [r]}), tmp_path / f"bad{k}.json")
        with pytest.raises(ExportError, match=why) as err:
            fitted_specimen_from_card(read_card(bad), bad)
        assert "\n" not in str(err.value)
    with pytest.raises(ExportError, match="frictionless platens hold u_z only"):
        export(card, "pbd", tmp_path / "x.out", fitted=fitted_specimen_from_card(card, card_path))
    # the typed block specimen (not the fitted one) is unchanged
    out = tmp_path / "block.feb"
    assert main(["export", str(card_path), "--to", "febio", "--specimen", "block:10,10,5:2,2,2", "--out", str(out)]) == 0
    root = ET.parse(out).getroot()
    assert [b.get("name") for b in root.findall("Boundary/bc")] == ["fixed_base", "top_displacement"]
    assert float(root.find("Boundary/bc[@name='top_displacement']/value").text) == pytest.approx(-0.5 * MM, rel=1e-12)
    assert len(root.findall("Mesh/Nodes/node")) == 27


def test_cli_fit_of_the_ecoflex_example_writes_and_exports_the_specimen(tmp_path, capsys):
    """``difftissue fit`` of the packaged Ecoflex example (springs_volume, frictionless platens,
    20 strains up to 40 %) writes specimen-ecoflex.vtu and the protocol in the card;
    ``difftissue export --specimen fitted`` writes the 10 mm cube with the top platen at the
    last strain, ramped in 20 steps (the fitted cubic term needs --approximate)."""
    from pathlib import Path

    import difftissue

    cfg = Path(difftissue.__file__).parent / "configs" / "ecoflex_compression.toml"
    out = tmp_path / "fit"
    assert main(["fit", str(cfg), "--out", str(out)]) == 0
    capsys.readouterr()
    assert (out / "specimen-ecoflex.vtu").is_file()
    card = read_card(out / "material.json")
    rec, = card.provenance["scenario_records"]
    assert rec["experiment"] == "compression" and rec["model"] == "springs_volume" and rec["platens"] == "frictionless"
    assert len(rec["strains"]) == 20 and 0.39 < rec["strains"][-1] <= 0.4 and rec["height"] == 0.01
    assert rec["top_displacement"] == -rec["strains"][-1] * 0.01 and card.cubic_coefficient != 0.0
    feb = tmp_path / "ecoflex.feb"
    assert main(["export", str(out / "material.json"), "--to", "febio", "--specimen", "fitted", "--out", str(feb)]) == 1
    assert "cubic_coefficient" in capsys.readouterr().err
    assert main(["export", str(out / "material.json"), "--to", "febio", "--specimen", "fitted", "--approximate", "--out", str(feb)]) == 0
    assert "fitted compression specimen of scenario 'ecoflex'" in capsys.readouterr().out
    p = parse_febio(feb)
    np.testing.assert_allclose(p["points"].max(axis=0) - p["points"].min(axis=0), [0.01] * 3, rtol=1e-14)
    top = np.flatnonzero(np.isclose(p["points"][:, 2], 0.01))
    assert top.size == 4 and np.all(p["prescribed"][top, 2] == rec["top_displacement"])
    np.testing.assert_array_equal(np.sort(p["sets"]["reaction"]), top)
    # springs_volume values are lattice-effective: recalibrated to neo-Hookean on this experiment (tests/test_export_mismatch.py)
    text = feb.read_text()
    e_new = float(re.search(r"E = ([0-9.e+-]+) Pa = [0-9.e+-]+ x the card's", text).group(1))
    assert "RECALIBRATED for the continuum neo_hookean law (APPROXIMATION: b dropped)" in text and e_new != card.youngs_modulus
    assert p["materials"][0]["type"] == "neo-Hookean" and p["materials"][0]["E"] == pytest.approx(e_new, rel=1e-9)
    assert ET.parse(feb).getroot().find("Control/time_steps").text == "20"
    for target, suffix in (("abaqus", "inp"), ("sofa", "scn"), ("vtu", "vtu")):
        assert main(["export", str(out / "material.json"), "--to", target, "--specimen", "fitted", "--approximate",
                     "--out", str(tmp_path / f"ecoflex.{suffix}")]) == 0


def test_bonded_compression_to_pypbd_reproduces_the_fitted_curve_at_its_budget(tmp_path):
    """The fitted bonded block compression (10 x 10 x 5 mm, 4 x 4 x 2 cubes, 2 / 5 / 10 %) exported
    to pypbd at the default budget (dt = 1/60 s, 10 iterations): the exporter recalibrates the
    constraint stiffnesses on the protocol, and pypbd running the *file* at that budget gives
    the fitted engineering stress curve (``Compression.predict`` at the card's values) within
    2 % at every strain (docs/export.md "Budget recalibration")."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    import os
    import subprocess
    import sys

    from difftissue.export.pypbd_runner import read_pbd_scene

    c = CASES["block_bonded"]
    mesh = block((10 * MM, 10 * MM, 5 * MM), (4, 4, 2))  # 2.5 mm cubes: the pypbd spring lattice needs (near-)cubic cells
    sc = Compression(mesh, c["strains"], model="fem_linear", bonded=True, measure="engineering", name="bonded")
    card_path = _write_case(tmp_path, sc)
    card = read_card(card_path)
    path = export(card, "pbd", tmp_path / "scene.json", fitted=fitted_specimen_from_card(card, card_path))
    scene = read_pbd_scene(path)
    rec = scene["budget_calibration"]
    assert rec["load_fractions"] == pytest.approx([0.2, 0.5, 1.0]) and scene["fitted_specimen"]["scenario"] == "bonded"
    # no budget given: the default (1/60 s, 1, 10) is tried first; here it does not reach 2 % on every strain, so the
    # exporter chooses (and states) the first budget that does
    assert rec["budgets_tried"][0] == [pytest.approx(1 / 60), 1, 10] and rec["setting"] == scene["setting"]
    assert rec["budget"].startswith("CHOSEN") == (scene["setting"]["substeps"] != 1 or scene["setting"]["iterations"] != 10)
    runner = ("import json, sys\nfrom difftissue.export.pypbd_runner import read_pbd_scene, run_pbd_budget\n"
              "s = read_pbd_scene(sys.argv[1]); r = run_pbd_budget(s, s['budget_calibration']['load_fractions'])\n"
              "print(json.dumps({'R': r.reactions.tolist(), 'ok': r.converged.tolist()}))")
    proc = subprocess.run([sys.executable, "-c", runner, str(path)], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(run["ok"])
    stress_pbd = np.asarray(run["R"]) / scene["fitted_specimen"]["protocol"]["area"]
    fitted = np.abs(np.asarray(sc.predict(card.material())))  # the fitted curve: engineering stress [Pa]
    err = stress_pbd / fitted - 1.0
    print("pypbd fitted bonded compression:", scene["setting"], rec["budgets_tried"], "before", rec["signed_error_before"], "after", err.tolist(),
          "factor", rec["factor"], "field", rec["field_error"], "converged limit", rec["field_error_converged"], "weight", rec["weight_field_share"])
    assert np.max(np.abs(err)) <= 0.02, err  # measured: see docs/export.md
    # the field is stated, not a target here: measured 0.143 at the chosen 8 substeps, 0.046 of the fem_linear card's field
    # being the pypbd lattice's converged limit (docs/export.md, "Displacement column")
    assert rec["field_tolerance"] is None and rec["field_error"] == pytest.approx(0.143, abs=0.02)
    assert rec["field_error_converged"] == pytest.approx(0.0463, abs=0.005)
