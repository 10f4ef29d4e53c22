"""pypbd and XPBD exports reproduce the fitted experiment at their written budget (docs/export.md
"Budget recalibration"); the pypbd displacement field is measured, stated and, with a field target, met or refused.

Each check writes the file with the exporter, runs the *file* at the budget it states (pypbd in
a fresh process: ``run_pbd_budget``; the XPBD JSON in difftissue's own XPBD solver, standard
XPBD with multipliers reset, from the file's per-tet numbers) and compares the reactions with
the card's own model solved independently by difftissue's static solver: at most 2 % per
load state.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from difftissue.boundary import BoundaryConditions
from difftissue.errors import ExportError
from difftissue.export import MaterialCard, export, xpbd_parameters
from difftissue.export.budget import MAX_BUDGET_ERROR, xpbd_budget_reactions
from difftissue.export.specimens import IndentationSpecimen, indentation_sets
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.export.pypbd import write_pbd
from difftissue.export.pypbd_runner import read_pbd_scene
from difftissue.solvers.static import solve_static
from xpbd_budget_memo import remember_xpbd_budget_runs

E, NU = 12.0e3, 0.45

_RUNNER = """
import json, sys
from difftissue.export.pypbd_runner import read_pbd_scene, run_pbd_budget
scene = read_pbd_scene(sys.argv[2])
r = run_pbd_budget(scene, scene["budget_calibration"]["load_fractions"])
open(sys.argv[1], "w").write(json.dumps({"reactions": r.reactions.tolist(), "converged": r.converged.tolist(),
                                         "positions": r.positions[-1].tolist(),
                                         "steps": r.steps.tolist(), "setting": [r.dt, r.substeps, r.iterations]}))
"""


def _card(model="springs_volume"):
    return MaterialCard(model=model, parameters={"youngs_modulus": {"value": E, "unit": "Pa"},
                                                 "poisson_ratio": {"value": NU, "unit": "1"}}, name="skin")


def _run_pbd_file(tmp_path, path) -> dict:
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    out = tmp_path / "run.json"
    proc = subprocess.run([sys.executable, "-c", _RUNNER, str(out), str(path)], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(out.read_text())


def _static(card, mesh, fixed_nodes, moved, dvec, fractions, field=False):
    """The card's own model on the specimen (independent of the exporter's code path): the
    reaction per fraction, and with ``field`` also the displacement field [m] at the last."""
    model = make_model(mesh, card.model)
    out = []
    for f in fractions:
        bc = BoundaryConditions.free(mesh).fix(mesh, fixed_nodes, "xyz").fix(mesh, moved, "xyz", tuple(f * np.asarray(dvec)))
        sol = solve_static(model, card.material(), bc, load_steps=2)
        out.append(float(np.sum(np.asarray(sol.reaction)[moved] @ (np.asarray(dvec) / np.linalg.norm(dvec)))))
    return (np.asarray(out), np.asarray(sol.displacement)) if field else np.asarray(out)


def _field_error(run, mesh, u_ref):
    """max |u_pypbd - u_card| / max |u_card| at the last load state (pypbd gives positions)."""
    u = np.asarray(run["positions"]) - np.asarray(mesh.points)
    return float(np.abs(u - u_ref).max() / np.abs(u_ref).max())


def _block_sets(mesh):
    z = np.asarray(mesh.points)[:, 2]
    return np.flatnonzero(np.isclose(z, z.min())), np.flatnonzero(np.isclose(z, z.max()))


def test_pypbd_block_reproduces_the_card_at_the_default_budget(tmp_path):
    """A springs_volume card on a 10 mm cube, bonded platens, 10 % compression, written at the
    default budget (dt = 1/60 s, 10 iterations): pypbd runs the file to within 2 % of the card's
    reactions at the four load states (the card's own values give +21 ... +26 %)."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    card = _card()
    mesh = block((0.01,) * 3, (3, 3, 3))
    path = export(card, "pbd", tmp_path / "block.json", mesh=mesh, displacement=-1e-3)
    scene = read_pbd_scene(path)
    rec = scene["budget_calibration"]
    assert scene["setting"] == {"dt": pytest.approx(1 / 60), "substeps": 1, "iterations": 10}
    assert rec["budget"] == "the default budget" and any("RECALIBRATED" in n for n in scene["notes"])
    base, top = _block_sets(mesh)
    ref, u_ref = _static(card, mesh, base, top, (0.0, 0.0, -1e-3), rec["load_fractions"], field=True)
    np.testing.assert_allclose(rec["reference_reactions"], ref, rtol=1e-8)
    run = _run_pbd_file(tmp_path, path)
    assert all(run["converged"]) and run["setting"] == [pytest.approx(1 / 60), 1, 10]
    err = np.asarray(run["reactions"]) / ref - 1.0
    du = _field_error(run, mesh, u_ref)
    print(f"\npypbd block at its budget: reaction errors {err}, max|du|/max|u| {du:.4g}, converged limit "
          f"{rec['field_error_converged']:.4g}, weight {rec['weight_field_share']:.4g}")
    assert np.max(np.abs(err)) <= MAX_BUDGET_ERROR, err  # measured: see docs/export.md
    assert np.max(np.abs(np.asarray(rec["signed_error_before"]))) > 0.1  # the card's own values are far off here
    # the field is NOT within 2 % and the file says so: the recorded error is the file's (re-run here), measured 0.2919;
    # 0.1668 of the card's springs_volume field is the pypbd lattice itself (per-tet volume constraints; the converged
    # limit of every budget, docs/dev/pypbd-fields.md); the weight pypbd adds moves the particles by 0.0305 of max |u|
    assert du == pytest.approx(rec["field_error"], rel=1e-6)
    assert du == pytest.approx(0.2919, abs=0.02)
    assert rec["field_error_converged"] == pytest.approx(0.1668, abs=0.005)
    assert rec["weight_field_share"] == pytest.approx(0.0305, rel=0.1)
    assert rec["field_tolerance"] is None and any(n.startswith("DISPLACEMENT FIELD") and "29.2 %" in n for n in scene["notes"])


def test_pypbd_flat_punch_reproduces_the_card_at_the_default_budget(tmp_path):
    """Bonded flat punch (R = 3 mm, 5 nodes) 0.1 mm into a 10 x 10 x 5 mm block (4 x 4 x 2 cubes),
    bonded base: pypbd at the written budget within 2 % of the card's springs_volume punch force."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    card = _card()
    spec = IndentationSpecimen(indenter="flat_punch", depth=1e-4, size=(0.01, 0.01, 0.005), cells=(4, 4, 2), radius=3e-3,
                               base="bonded", bonded_punch=True, steps=4)
    path = export(card, "pbd", tmp_path / "punch.json", indentation=spec)
    scene = read_pbd_scene(path)
    rec = scene["budget_calibration"]
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    ref, u_ref = _static(card, mesh, s["base"], s["punch"], (0.0, 0.0, -1e-4), rec["load_fractions"], field=True)
    np.testing.assert_allclose(rec["reference_reactions"], ref, rtol=1e-8)
    run = _run_pbd_file(tmp_path, path)
    assert all(run["converged"])
    err = np.asarray(run["reactions"]) / ref - 1.0
    du = _field_error(run, mesh, u_ref)
    print(f"\npypbd flat punch at its budget: reaction errors {err}, max|du|/max|u| {du:.4g}, converged limit "
          f"{rec['field_error_converged']:.4g}, weight {rec['weight_field_share']:.4g}")
    assert np.max(np.abs(err)) <= MAX_BUDGET_ERROR, err
    # field: measured 0.6635 at this budget, 0.3581 of it the lattice (per-tet vs the card's per-cube volume term under a
    # bonded punch on two cell layers); the punch specimen's own weight moves it by 0.239 of max |u| in a running pypbd scene
    assert du == pytest.approx(rec["field_error"], rel=1e-6)
    assert du == pytest.approx(0.6635, abs=0.03)
    assert rec["field_error_converged"] == pytest.approx(0.3581, abs=0.01)
    assert rec["weight_field_share"] == pytest.approx(0.239, rel=0.1)


def test_pypbd_field_target_is_met_by_a_chosen_budget_or_refused(tmp_path):
    """``field_tolerance``: the displacement field becomes a target too. A fem_linear card (nu = 0.42) on the 10 mm cube:
    the pypbd lattice's converged limit is 2.11 % off the card's field, so a 3 % target is reachable: the exporter
    tries the default budget (26.8 %), 1 ... 16 substeps, and CHOOSES 32 substeps (measured 1.96 %; the reactions within
    2 %); the file re-run in a fresh process gives that field. A 2 % target on the springs_volume card (lattice 16.7 %)
    is refused without running a budget, and written with the miss stated under approximate=True."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the check needs it")
    card = MaterialCard(model="fem_linear", parameters={"youngs_modulus": {"value": E, "unit": "Pa"},
                                                        "poisson_ratio": {"value": 0.42, "unit": "1"}}, name="skin")
    mesh = block((0.01,) * 3, (3, 3, 3))
    path = write_pbd(card, tmp_path / "field.json", mesh=mesh, displacement=-1e-3, field_tolerance=0.03)
    scene = read_pbd_scene(path)
    rec = scene["budget_calibration"]
    assert scene["setting"] == {"dt": pytest.approx(1 / 60), "substeps": 32, "iterations": 10} and rec["budget"].startswith("CHOSEN")
    assert [b[1:] for b in rec["budgets_tried"]] == [[1, 10], [1, 20], [2, 10], [4, 10], [8, 10], [16, 10], [32, 10]]
    assert rec["field_within_tolerance"] and rec["field_error_converged"] == pytest.approx(0.0211, abs=0.002)
    base, top = _block_sets(mesh)
    ref, u_ref = _static(card, mesh, base, top, (0.0, 0.0, -1e-3), rec["load_fractions"], field=True)
    run = _run_pbd_file(tmp_path, path)
    du = _field_error(run, mesh, u_ref)
    print(f"\npypbd field target 3 %: {scene['setting']}, max|du|/max|u| {du:.4g}, reactions {np.asarray(run['reactions']) / ref - 1}")
    assert du <= 0.03 and du == pytest.approx(0.0196, abs=0.003)
    assert np.max(np.abs(np.asarray(run["reactions"]) / ref - 1.0)) <= MAX_BUDGET_ERROR
    with pytest.raises(ExportError, match=r"cannot be brought within 2 % .* differs from it by 16.7 %"):
        write_pbd(_card(), tmp_path / "no.json", mesh=mesh, displacement=-1e-3, field_tolerance=0.02)
    sc = read_pbd_scene(write_pbd(_card(), tmp_path / "approx.json", mesh=mesh, displacement=-1e-3, field_tolerance=0.02,
                                  approximate=True))
    r2 = sc["budget_calibration"]
    assert r2["field_tolerance"] == 0.02 and r2["field_within_tolerance"] is False and r2["within_tolerance"]
    assert any(n.startswith("APPROXIMATION: the displacement field cannot") for n in sc["notes"])
    with pytest.raises(ExportError, match="material alone"):
        write_pbd(_card(), tmp_path / "m.json", field_tolerance=0.02)


def test_xpbd_block_reproduces_the_card_at_its_budget_and_refuses_a_saturated_one(tmp_path, monkeypatch):
    """The XPBD JSON of the same cube at dt = 2.5e-4 s, 10 iterations: difftissue's XPBD solver
    (standard XPBD, multipliers reset) running the file's per-tet compliances is within 2 % of
    the card's springs_volume reactions; at dt = 1e-3 s no single factor reaches 2 %: refused
    with a suggested budget, and --approximate states the signed error.

    The approximate export repeats the refused one's search (60 XPBD runs to rest): it takes
    those runs' results from the refused call (tests/xpbd_budget_memo.py; the rest of the
    exporter runs again). The file check below runs XPBD itself."""
    card = _card()
    mesh = block((0.01,) * 3, (3, 3, 3))
    doc = json.loads(export(card, "xpbd", tmp_path / "x.json", mesh=mesh, displacement=-1e-3, dt=2.5e-4, iterations=10).read_text())
    rec = doc["budget_calibration"]
    assert rec["within_tolerance"] and doc["setting"]["multipliers"].startswith("reset")
    base, top = _block_sets(mesh)
    ref = _static(card, mesh, base, top, (0.0, 0.0, -1e-3), rec["load_fractions"])
    n = len(doc["specimen"]["positions"])
    fixed = np.zeros((n, 3), dtype=bool)
    fixed[base] = fixed[top] = True
    presc = np.zeros((n, 3))
    presc[top, 2] = -1e-3
    observe = np.zeros((n, 3), dtype=bool)
    observe[top] = True
    got, rested = xpbd_budget_reactions(doc, fixed, presc, observe, rec["load_fractions"])  # the file's numbers, factor 1
    assert rested
    err = got / ref - 1.0
    assert np.max(np.abs(err)) <= MAX_BUDGET_ERROR, err
    runs = remember_xpbd_budget_runs(monkeypatch)
    with pytest.raises(ExportError, match="a budget that reaches it"):
        xpbd_parameters(card, dt=1e-3, iterations=10, mesh=mesh, displacement=-1e-3)
    approx = xpbd_parameters(card, dt=1e-3, iterations=10, mesh=mesh, displacement=-1e-3, approximate=True)
    assert not approx["budget_calibration"]["within_tolerance"]
    assert any(n.startswith("APPROXIMATION: XPBD at dt = 0.001") for n in approx["notes"])
    assert runs["reused"] == runs["runs"] > 0  # the approximate export asked for exactly the refused one's runs
