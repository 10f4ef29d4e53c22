"""Exports that run (issue 16, findings 3-7): what the files must contain for FEBio, SOFA and
Abaqus / CalculiX to run them and report the fitted quantity, and the export folder's README.

FEBio: reaction sets are prescribed (FEBio records reactions only on prescribed dofs) and a
``<logfile>`` writes them; SOFA: every ``RequiredPlugin`` before the first ``Node``, an explicit
``StaticSolver`` with a linear solver, a ``WriteState`` output; units in every file; Abaqus
elements C3D4 / C3D4H / C3D10 / C3D10H, C3D10 run in CalculiX, C3D4H refused by it.
"""

from __future__ import annotations

import importlib.util
import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from calculix import run_ccx, run_deck

from difftissue.cli import main
from difftissue.errors import ExportError
from difftissue.export import (
    MODEL_ENERGIES,
    UNITS,
    MaterialCard,
    abaqus_model,
    abaqus_quadratic,
    export,
    portable_path,
    write_card,
    write_febio,
    write_sofa,
)
from difftissue.export.specimens import indentation_specimen
from difftissue.mesh import block

E, NU = 12e3, 0.45


def _card(model="fem_neo_hookean"):
    return MaterialCard(model=model, name="skin", parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}})


@pytest.fixture(scope="module")
def mesh():
    return block((0.01, 0.01, 0.005), (2, 2, 1))


def test_springs_volume_energy_names_the_cell_volume_term():
    text = MODEL_ENERGIES["springs_volume"]
    assert "per-cell volume term" in text and "hexahedral" in text and "per-tetrahedron" not in text
    assert "lattice-effective" in text


def test_febio_block_logs_the_top_reaction(tmp_path, mesh):
    root = ET.parse(write_febio(_card(), tmp_path / "b.feb", mesh=mesh)).getroot()
    log = root.find("Output/logfile/node_data")
    top = root.find("Mesh/NodeSet[@name='top']").text
    assert log.get("data") == "Rx;Ry;Rz" and log.text == top and log.get("file") == "reaction_top.txt"
    pre = [bc for bc in root.find("Boundary") if bc.get("node_set") == "top"]
    assert [bc.get("type") for bc in pre] == ["prescribed displacement"]


@pytest.mark.parametrize("indenter", ["sphere", "cone"])
def test_febio_contact_reads_the_base_from_prescribed_zero(tmp_path, indenter):
    """The indentation force of a meshed indenter is the base reaction: the base is held by
    ``prescribed displacement`` 0 (not ``zero displacement``), logged with the rigid body's force."""
    size = {"radius": 2e-3} if indenter == "sphere" else {"half_angle": 1.0}
    spec = indentation_specimen(_card(), indenter=indenter, depth=1e-4, size=(0.01, 0.01, 0.005), cells=(4, 4, 2), steps=2, **size)
    root = ET.parse(export(_card(), "febio", tmp_path / "s.feb", indentation=spec)).getroot()
    base = [bc for bc in root.find("Boundary") if bc.get("node_set") == "base"]
    assert {bc.get("type") for bc in base} == {"prescribed displacement"} and sorted(bc.find("dof").text for bc in base) == ["x", "y", "z"]
    assert all(float(bc.find("value").text) == 0.0 for bc in base)
    log = root.find("Output/logfile")
    assert log.find("node_data").text == root.find("Mesh/NodeSet[@name='base']").text
    rigid = root.find("Material/material[@type='rigid body']").get("id")
    assert log.find("rigid_body_data").text == rigid and log.find("rigid_body_data").get("data") == "Fx;Fy;Fz"


def _plugins_first(root):
    kids = list(root)
    first_node = next(i for i, k in enumerate(kids) if k.tag == "Node")
    return all(i < first_node for i, k in enumerate(kids) if k.tag == "RequiredPlugin")


@pytest.mark.parametrize("kind", ["block", "indentation", "material"])
def test_sofa_plugins_first_explicit_solver_and_output(tmp_path, mesh, kind):
    card = _card()
    if kind == "indentation":
        spec = indentation_specimen(card, indenter="flat_punch", radius=2e-3, depth=1e-4, size=(0.01, 0.01, 0.005), cells=(4, 4, 2),
                                    bonded_punch=True, steps=2)
        path = export(card, "sofa", tmp_path / "i.scn", indentation=spec)
    else:
        path = write_sofa(card, tmp_path / "b.scn", mesh=mesh if kind == "block" else None)
    root = ET.parse(path).getroot()
    assert _plugins_first(root)
    assert f"units: {UNITS}" in path.read_text()
    if kind == "material":
        return
    solver = root.find(".//StaticSolver")
    assert int(solver.get("newton_iterations")) >= 10 and float(solver.get("relative_residual_tolerance_threshold")) <= 1e-8
    assert float(solver.get("absolute_correction_tolerance_threshold")) > 0
    assert root.find(".//SparseLDLSolver") is not None
    out = root.find(".//WriteState")
    assert out.get("writeX") == "1" and out.get("writeF") == "1" and float(out.get("period")) == float(root.get("dt"))
    assert "Sofa.Component.Playback" in {p.get("name") for p in root.iter("RequiredPlugin")}


@pytest.mark.parametrize("target, suffix", [("febio", "feb"), ("sofa", "scn"), ("abaqus", "inp")])
def test_files_and_card_state_their_units(tmp_path, mesh, target, suffix):
    assert f"units: {UNITS}" in export(_card(), target, tmp_path / f"m.{suffix}").read_text()
    xp = json.loads(export(_card(), "xpbd", tmp_path / f"x-{target}.json", dt=1e-3, iterations=10).read_text())
    assert xp["units"] == UNITS
    card_path = write_card(_card(), tmp_path / f"material-{target}.json")
    doc = json.loads(card_path.read_text())
    assert doc["units"] == UNITS
    doc["units"] = "mm, N, MPa, s"
    with pytest.raises(ExportError, match="units"):
        MaterialCard.from_dict(doc)


def test_portable_paths(tmp_path):
    cfg = tmp_path / "cfg"
    (cfg / "data").mkdir(parents=True)
    f = cfg / "data" / "curve.csv"
    f.write_text("0,0\n")
    assert portable_path(f, cfg) == "data/curve.csv"
    assert portable_path(f) == "curve.csv" and portable_path(tmp_path / "elsewhere.csv", cfg) == "elsewhere.csv"
    assert portable_path("data/curve.csv") == "data/curve.csv" and portable_path("../x.csv") == "x.csv"


def test_cli_export_writes_a_readme(tmp_path, capsys):
    write_card(MaterialCard(model="springs_volume", name="skin", parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}}),
               tmp_path / "material.json")
    out = tmp_path / "exports"
    out.mkdir()
    base = ["export", str(tmp_path / "material.json"), "--specimen", "block:10,10,5:2,2,1"]
    assert main([*base, "--to", "abaqus", "--out", str(out / "m.inp")]) == 1
    assert "model mismatch" in capsys.readouterr().err
    assert main([*base, "--to", "abaqus", "--approximate", "--out", str(out / "m.inp")]) == 0
    assert main([*base, "--to", "febio", "--approximate", "--out", str(out / "m.feb")]) == 0
    text = (out / "README.md").read_text()
    assert "## m.inp" in text and "## m.feb" in text and f"units: {UNITS}" in text
    assert "ccx -i m" in text and "febio4 -i m.feb" in text and "APPROXIMATION: model mismatch" in text
    assert str(tmp_path) not in text
    assert main([*base, "--to", "abaqus", "--approximate", "--force", "--out", str(out / "m.inp")]) == 0
    assert (out / "README.md").read_text().count("## m.inp") == 1  # the section is replaced, not repeated
    # real-time files: the README states the budget, whether the exporter chose it, and the recalibration
    assert main([*base, "--to", "xpbd", "--dt", "0.00025", "--iterations", "10", "--out", str(out / "x.json")]) == 0
    sec = (out / "README.md").read_text().split("## x.json")[1].split("\n## ")[0]
    assert "- budget: dt = 0.00025 s, substeps = 1, iterations = 10 (as given" in sec
    assert "- RECALIBRATED for this budget: stiffness x " in sec and "after (within tolerance)" in sec
    assert "- recalibrated: RECALIBRATED for this budget" in sec
    if importlib.util.find_spec("pypbd") is not None:
        assert main([*base, "--to", "pbd", "--out", str(out / "p.json")]) == 0
        sec = (out / "README.md").read_text().split("## p.json")[1].split("\n## ")[0]
        assert re.search(r"- budget: dt = 0.0166667 s, substeps = \d+, iterations = \d+ \((the default budget|CHOSEN by the exporter)", sec)
        assert "- RECALIBRATED for this budget: stiffness x " in sec and "gravity not included" in sec


# ------------------------------------------------------------------ Abaqus elements
def test_quadratic_tets_have_midside_nodes(mesh):
    pts, t10, edges = abaqus_quadratic(mesh.points, mesh.tets)
    assert t10.shape == (mesh.n_tets, 10) and len(pts) == mesh.n_nodes + len(edges)
    t = np.asarray(mesh.tets)
    for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))):
        np.testing.assert_allclose(pts[t10[:, 4 + k]], 0.5 * (pts[t[:, a]] + pts[t[:, b]]), rtol=0, atol=0)
    with pytest.raises(ExportError, match="element"):
        abaqus_model(_card(), mesh, element="C3D8")
    with pytest.raises(ExportError, match="Abaqus option"):
        export(_card(), "febio", "x.feb", mesh=mesh, element="C3D10")


def test_calculix_runs_c3d10_and_rejects_hybrid_elements(tmp_path, mesh):
    """C3D10 runs in CalculiX; the linear block's force is below C3D4's (C3D4 locks at nu = 0.45:
    measured 0.2647 N vs 0.1510 N). C3D4H / C3D10H: ccx stops with 'unknown element type'."""
    card = _card("fem_linear")
    f = {}
    for el in ("C3D4", "C3D10"):
        deck = tmp_path / f"{el}.inp"
        deck.write_text(abaqus_model(card, mesh, element=el))
        f[el] = -run_deck(deck, tmp_path / el).totals["TOP"][2]
    assert 0 < f["C3D10"] < 0.8 * f["C3D4"]
    for el in ("C3D4H", "C3D10H"):
        text = abaqus_model(card, mesh, element=el)
        assert f"*ELEMENT, TYPE={el}, ELSET=TISSUE" in text and "CalculiX has no hybrid" in text
        rc, out = run_ccx(text, tmp_path / f"{el}-run")
        assert f"{el}" in out and "is an unknown element type" in out
