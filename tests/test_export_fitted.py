"""Fitted specimens (difftissue.export.fitted, docs/export.md "Fitted specimens: fem_field and
incision"): the experiment of a fem_field or incision fit written with the fit outputs and
exported as a complete model, parsed back from the written files and solved again.

fem_field: a 3 x 3 x 2 block (fem_linear reference: base clamped, punch nodes pushed down,
one lateral face given a per-node x displacement varying with height), E fitted by difftissue,
exported to FEBio, Abaqus and SOFA, parsed back (nodes, elements, sets, per-node values, E, nu) and
solved in scikit-fem: the displacement field equals difftissue's fem_linear solution and the
reaction force the fit compared. incision: a 4 x 4 mm two-layer skin (0.5 mm cells; 1 mm
dermis in 2 cells on 1 mm of fat), a 2 mm cut through the pre-stretched dermis (fem_neo_hookean), exported to FEBio / XPBD / VTU, parsed back and solved
by difftissue's static solver: the opened widths equal Incision's.
"""

import json
from functools import partial
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from difftissue.boundary import BoundaryConditions
from difftissue.cli import main
from difftissue.errors import ExportError, OutputExistsError
from difftissue.export import MaterialCard, export, read_card, to_skfem, write_card
from difftissue.export.card import scenario_record
from difftissue.export.fitted import (
    fitted_specimen,
    fitted_specimen_from_card,
    specimen_file_name,
    specimen_record,
    write_specimen,
)
from difftissue.export.xpbd import xpbd_fitted_parameters
from difftissue.materials import Material, MaterialParameterization
from difftissue.mesh import TetMesh, block, read_mesh, write_mesh
from difftissue.models import make_model, stack_materials
from difftissue.solvers.static import solve_static

skfem = pytest.importorskip("skfem")

E, NU = 12.0e3, 0.42
MM = 1e-3


# =============================================================================== parsers
def _ids(text):
    return np.array([int(v) - 1 for v in text.split(",")], dtype=np.int64)


def parse_febio(path):
    """Nodes, tets (by domain), per-region material (E, v, F0), node sets, fixed mask and
    prescribed values (load controller at its end value 1) of a written .feb."""
    root = ET.parse(path).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    pts = np.array([[float(v) for v in n.text.split(",")] for n in root.find("Mesh/Nodes")])
    ids = [int(n.get("id")) for n in root.find("Mesh/Nodes")]
    assert ids == list(range(1, len(pts) + 1))
    mats = {}
    for m in root.find("Material").findall("material"):
        el = m.find("elastic") if m.get("type") == "prestrain elastic" else m
        F0 = m.find("prestrain/F0")
        mats[m.get("name")] = {"type": el.get("type"), "E": float(el.find("E").text), "v": float(el.find("v").text),
                               "F0": None if F0 is None else np.array([float(v) for v in F0.text.split(",")]).reshape(3, 3)}
    dom = {d.get("name"): d.get("mat") for d in root.find("MeshDomains").findall("SolidDomain")}
    tets, rid, names, eids = [], [], [], []
    for blk in root.find("Mesh").findall("Elements"):
        assert blk.get("type") == "tet4"
        names.append(blk.get("name"))
        for e in blk:
            eids.append(int(e.get("id")))
            tets.append(_ids(e.text))
            rid.append(len(names) - 1)
    assert eids == list(range(1, len(eids) + 1))
    sets = {s.get("name"): _ids(s.text) for s in root.find("Mesh").findall("NodeSet")}
    maps = {}
    md = root.find("MeshData")
    if md is not None:
        for nd in md.findall("NodeData"):
            vals = {int(n.get("lid")): float(n.text) for n in nd.findall("node")}
            maps[nd.get("name")] = (nd.get("node_set"), np.array([vals[k] for k in range(1, len(vals) + 1)]))
    n = len(pts)
    fixed = np.zeros((n, 3), dtype=bool)
    presc = np.zeros((n, 3))
    lc_end = {lc.get("id"): float(lc.findall("points/pt")[-1].text.split(",")[1]) for lc in root.find("LoadData")}
    for bc in root.find("Boundary").findall("bc"):
        nodes = sets[bc.get("node_set")]
        if bc.get("type") == "zero displacement":
            for c, d in enumerate("xyz"):
                if bc.find(f"{d}_dof").text == "1":
                    fixed[nodes, c] = True
        else:
            assert bc.get("type") == "prescribed displacement" and bc.find("relative").text == "0"
            c = "xyz".index(bc.find("dof").text)
            val = bc.find("value")
            assert val.get("type") == "map"
            nset, values = maps[val.text]
            assert nset == bc.get("node_set") and len(values) == len(nodes)
            fixed[nodes, c] = True
            presc[nodes, c] = lc_end[val.get("lc")] * values
    region_mats = [mats[dom[r]] for r in names]
    return {"points": pts, "tets": np.array(tets), "region_ids": np.array(rid), "region_names": names,
            "materials": region_mats, "sets": sets, "fixed": fixed, "prescribed": presc}


def parse_abaqus(path):
    """Nodes, tets, per-region *ELASTIC (E, nu), node sets, and the *BOUNDARY of the step."""
    lines = [ln.strip() for ln in open(path, encoding="utf-8") if ln.strip() and not ln.startswith("**")]
    pts, tets, rid, elsets, sets, sections, elastic = [], [], [], [], {}, {}, {}
    fixed_lines = []
    mode = cur = None
    for ln in lines:
        if ln.startswith("*"):
            kw = [p.strip() for p in ln.split(",")]
            opts = {p.split("=")[0].upper(): p.split("=")[1] for p in kw[1:] if "=" in p}
            mode = kw[0].upper()
            if mode == "*ELEMENT":
                assert opts["TYPE"] == "C3D4"
                elsets.append(opts["ELSET"])
            elif mode == "*NSET":
                cur = opts["NSET"]
                sets[cur] = []
            elif mode == "*SOLID SECTION":
                sections[opts["ELSET"]] = opts["MATERIAL"]
            elif mode == "*MATERIAL":
                cur = opts["NAME"]
            continue
        vals = [v.strip() for v in ln.split(",") if v.strip()]
        if mode == "*NODE":
            assert int(vals[0]) == len(pts) + 1
            pts.append([float(v) for v in vals[1:]])
        elif mode == "*ELEMENT":
            tets.append([int(v) - 1 for v in vals[1:]])
            rid.append(len(elsets) - 1)
        elif mode == "*NSET":
            sets[cur] += [int(v) - 1 for v in vals]
        elif mode == "*ELASTIC":
            elastic[cur] = (float(vals[0]), float(vals[1]))
        elif mode == "*BOUNDARY":
            fixed_lines.append(vals)
    n = len(pts)
    fixed = np.zeros((n, 3), dtype=bool)
    presc = np.zeros((n, 3))
    for vals in fixed_lines:
        nodes = np.array(sets[vals[0]]) if vals[0] in sets else np.array([int(vals[0]) - 1])
        d1, d2 = int(vals[1]), int(vals[2])
        for d in range(d1, d2 + 1):
            fixed[nodes, d - 1] = True
            presc[nodes, d - 1] = float(vals[3]) if len(vals) > 3 else 0.0
    return {"points": np.array(pts), "tets": np.array(tets), "region_ids": np.array(rid), "region_names": elsets,
            "materials": [elastic[sections[e]] for e in elsets], "sets": {k: np.array(v) for k, v in sets.items()},
            "fixed": fixed, "prescribed": presc}


def parse_sofa(path):
    """Rest positions, tets, force-field E and nu, the held components (Fixed / PartialFixed
    projective constraints) and prescribed values (position - rest_position) of a .scn."""
    root = ET.parse(path).getroot()
    node = root.find("Node")
    mo = node.find("MechanicalObject")
    rest = np.array([float(v) for v in mo.get("rest_position").split()]).reshape(-1, 3)
    pos = np.array([float(v) for v in mo.get("position").split()]).reshape(-1, 3)
    topo = node.find("MeshTopology")
    np.testing.assert_array_equal(np.array([float(v) for v in topo.get("position").split()]).reshape(-1, 3), rest)
    tets = np.array([int(v) for v in topo.get("tetrahedra").split()]).reshape(-1, 4)
    ff = node.find("TetrahedronFEMForceField")
    fixed = np.zeros(rest.shape, dtype=bool)
    for c in node.findall("FixedProjectiveConstraint"):
        fixed[[int(v) for v in c.get("indices").split()]] = True
    for c in node.findall("PartialFixedProjectiveConstraint"):
        dirs = np.array([v == "1" for v in c.get("fixedDirections").split()])
        idx = np.array([int(v) for v in c.get("indices").split()])
        fixed[np.ix_(idx, np.flatnonzero(dirs))] = True
    assert np.all(pos[~fixed] == rest[~fixed])  # free components start at rest
    return {"points": rest, "tets": tets, "materials": [(float(ff.get("youngModulus")), float(ff.get("poissonRatio")))],
            "fixed": fixed, "prescribed": np.where(fixed, pos - rest, 0.0), "sets": {}}


# ============================================================================== fem_field
@pytest.fixture(scope="module")
def fem_fit(tmp_path_factory):
    """A fem_field fit (E from 8 kPa) and its outputs, with the specimen file."""
    from difftissue.fit import fit
    from difftissue.report import write_fit_outputs
    from difftissue.scenarios import FEMField

    tmp = tmp_path_factory.mktemp("femfield")
    H = 0.005
    mesh = block((0.01, 0.01, H), (3, 3, 2))
    p = np.asarray(mesh.points)
    bottom = np.isclose(p[:, 2], 0.0)
    punch = np.isclose(p[:, 2], H) & (np.hypot(p[:, 0] - 0.005, p[:, 1] - 0.005) <= 0.0036)
    side = np.isclose(p[:, 0], 0.01) & ~bottom
    fixed = np.zeros((len(p), 3), dtype=bool)
    disp = np.zeros((len(p), 3))
    fixed[bottom] = True
    fixed[punch, 2] = True
    disp[punch, 2] = -1e-4
    fixed[side, 0] = True
    disp[side, 0] = 3e-5 * p[side, 2] / H  # a per-node field: varies with height
    assert punch.sum() >= 4 and len(np.unique(disp[side, 0])) >= 2
    truth = Material(E, NU)
    ref = solve_static(make_model(mesh, "fem_linear"), truth, BoundaryConditions(fixed, disp, np.zeros_like(disp)))
    path = write_mesh(tmp / "ref.vtu", mesh, point_data={
        "displacement": np.asarray(ref.displacement), "bottom": bottom.astype(np.int32), "punch": punch.astype(np.int32),
        "side": side.astype(np.int32), "reaction": np.asarray(ref.reaction)})
    back = read_mesh(path)
    sc = FEMField(back, back.point_data["displacement"], model="fem_linear",
                  prescribed=[{"set": "bottom"}, {"set": "punch", "components": "z"}, {"set": "side", "components": "x"}],
                  reaction={"set": "punch", "field": "reaction", "components": "z"})
    res = fit([sc], MaterialParameterization(("youngs_modulus",)), Material(8e3, NU))
    assert res.converged and res.values["youngs_modulus"] == pytest.approx(E, rel=1e-8)
    out = tmp / "fit"
    paths = write_fit_outputs(res, out, model="fem_linear", scenarios=[sc])
    return {"scenario": sc, "paths": paths, "out": out, "result": res, "fixed": fixed, "disp": disp}


def test_fit_outputs_write_and_record_the_specimen_file(fem_fit):
    from difftissue.report import write_fit_outputs

    paths, sc = fem_fit["paths"], fem_fit["scenario"]
    name = specimen_file_name("fem_field")
    assert name == "specimen-fem_field.vtu" and name in paths and paths[name].is_file()
    card = read_card(paths["material.json"])
    rec = card.provenance["scenario_records"][0]
    assert rec["experiment"] == "fem_field" and rec["model"] == "fem_linear"
    assert rec["specimen_file"]["path"] == name and len(rec["specimen_file"]["sha256"]) == 64
    spec = fitted_specimen_from_card(card, paths["material.json"])
    np.testing.assert_array_equal(spec.points, np.asarray(sc.model.rest_points))
    np.testing.assert_array_equal(spec.tets, np.asarray(sc.model.tets))
    np.testing.assert_array_equal(spec.fixed, fem_fit["fixed"])
    np.testing.assert_array_equal(spec.prescribed, fem_fit["disp"])  # bit-exact through the VTU
    np.testing.assert_array_equal(spec.reaction, np.asarray(sc.reaction_mask))
    # the overwrite rule covers the specimen file; --force rewrites it
    (fem_fit["out"] / "material.json").rename(fem_fit["out"] / "material.keep")
    try:
        for f in ("fit.json", "fit.png", "loss.png", "report.md"):
            (fem_fit["out"] / f).rename(fem_fit["out"] / (f + ".keep"))
        with pytest.raises(OutputExistsError, match="specimen-fem_field.vtu"):
            write_fit_outputs(fem_fit["result"], fem_fit["out"], model="fem_linear", scenarios=[sc])
        assert not (fem_fit["out"] / "material.json").exists()  # nothing written
    finally:
        for f in ("material.json", "fit.json", "fit.png", "loss.png", "report.md"):
            src = fem_fit["out"] / (f + ".keep") if f != "material.json" else fem_fit["out"] / "material.keep"
            if src.exists():
                src.rename(fem_fit["out"] / f)


def _skfem_solve(parsed, E_, nu_, reaction_nodes):
    card = MaterialCard(model="fem_linear", parameters={"youngs_modulus": {"value": E_}, "poisson_ratio": {"value": nu_}})
    mesh = TetMesh(parsed["points"], parsed["tets"])
    sk = to_skfem(card, mesh)
    K, dofs = sk["stiffness"], sk["dofs"]
    u = np.zeros(K.shape[0])
    u[dofs[parsed["fixed"]]] = parsed["prescribed"][parsed["fixed"]]
    u = skfem.solve(*skfem.condense(K, np.zeros_like(u), x=u, D=dofs[parsed["fixed"]]))
    return u[dofs], float((K @ u)[dofs[reaction_nodes, 2]].sum())


@pytest.mark.parametrize("target", ["febio", "abaqus", "sofa"])
def test_fem_field_round_trip_through_skfem(fem_fit, target, tmp_path):
    """The written FEBio / Abaqus / SOFA model, parsed back into scikit-fem, gives difftissue's
    fem_linear displacement field (1e-10 relative) and the fitted reaction force (1e-8; asked: 1 %)."""
    paths, sc = fem_fit["paths"], fem_fit["scenario"]
    out = tmp_path / {"febio": "model.feb", "abaqus": "model.inp", "sofa": "model.scn"}[target]
    assert main(["export", str(paths["material.json"]), "--to", target, "--specimen", "fitted", "--out", str(out)]) == 0
    card = read_card(paths["material.json"])
    parsed = {"febio": parse_febio, "abaqus": parse_abaqus, "sofa": parse_sofa}[target](out)
    # Abaqus data fields are at most 20 characters (abaqus_number): exact where the shortest
    # round-trip spelling fits, else within its stated 5e-15 relative for these magnitudes
    same = np.testing.assert_array_equal if target != "abaqus" else partial(np.testing.assert_allclose, rtol=5e-15, atol=0)
    same(parsed["points"], np.asarray(sc.model.rest_points))
    np.testing.assert_array_equal(parsed["tets"], np.asarray(sc.model.tets))
    np.testing.assert_array_equal(parsed["fixed"], np.asarray(sc.bc.fixed))
    presc = np.where(sc.bc.fixed, np.asarray(sc.bc.displacement), 0.0)
    if target == "sofa":  # position = rest + u: the prescribed value comes back up to the rounding of the sum
        np.testing.assert_allclose(parsed["prescribed"], presc, rtol=0, atol=1e-15)
    else:
        same(parsed["prescribed"], presc)
    if target == "sofa":
        (E_, nu_), = parsed["materials"]
        react = np.flatnonzero(np.asarray(sc.reaction_mask)[:, 2])  # SOFA has no node-set output; the record's set
    elif target == "febio":
        (mat,) = parsed["materials"]
        assert mat["type"] == "isotropic elastic" and mat["F0"] is None
        E_, nu_ = mat["E"], mat["v"]
        react = parsed["sets"]["reaction"]
        assert {"fixed_x", "fixed_y", "fixed_z", "prescribed_x", "prescribed_z"} <= set(parsed["sets"])
    else:
        (E_, nu_), = parsed["materials"]
        react = parsed["sets"]["REACTION"]
    same([E_, nu_], [card.youngs_modulus, card.poisson_ratio])
    np.testing.assert_array_equal(np.sort(react), np.flatnonzero(np.asarray(sc.reaction_mask)[:, 2]))
    u_sk, r_sk = _skfem_solve(parsed, E_, nu_, react)
    sol = sc.solve(card.material())
    u_ours = np.asarray(sol.displacement)
    assert np.abs(u_sk - u_ours).max() <= 1e-10 * np.abs(u_ours).max()
    r_fit = float(np.asarray(sc.predict(card.material()))[-1])
    assert abs(r_fit) > 1e-3 and abs(r_sk - r_fit) <= 1e-8 * abs(r_fit)  # N
    assert abs(r_sk - sc.observed[-1]) <= 1e-6 * abs(sc.observed[-1])  # the force the fit matched


def test_fem_field_xpbd_and_vtu(fem_fit, tmp_path):
    paths, sc = fem_fit["paths"], fem_fit["scenario"]
    card = read_card(paths["material.json"])
    spec = fitted_specimen_from_card(card, paths["material.json"])
    doc = xpbd_fitted_parameters(card, spec, dt=1e-3, iterations=20, calibrate=False)  # the conversion (budget: test_export_xpbd_fitted.py)
    sp = doc["specimen"]
    assert sp["experiment"] == "fem_field" and doc["format"] == "difftissue-xpbd/1"
    presc = np.zeros((len(spec.points), 3))
    for n, c, v in sp["prescribed_displacement"]:
        presc[n, c] = v
    np.testing.assert_array_equal(presc, spec.prescribed)
    assert sp["fixed"]["x"] == np.flatnonzero(spec.fixed[:, 0]).tolist()
    assert doc["per_tet"]["mu"][0] == pytest.approx(card.shear_modulus, rel=1e-15)
    v = read_mesh(export(card, "vtu", tmp_path / "s.vtu", fitted=spec))
    np.testing.assert_array_equal(np.asarray(v.cell_data["youngs_modulus"]), card.youngs_modulus)
    np.testing.assert_array_equal(np.asarray(v.point_data["prescribed_displacement"]).reshape(-1, 3), spec.prescribed)


def test_fitted_specimen_errors(fem_fit, tmp_path, capsys):
    paths = fem_fit["paths"]
    card_path = paths["material.json"]
    card = read_card(card_path)
    spec = fitted_specimen_from_card(card, card_path)
    out = str(tmp_path / "m.feb")
    # a card without a specimen record
    bare = write_card(MaterialCard(model="fem_linear", parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}}),
                      tmp_path / "bare.json")
    assert main(["export", str(bare), "--to", "febio", "--specimen", "fitted", "--out", out]) == 1
    assert "records no fitted specimen file" in capsys.readouterr().err
    # several specimens and no --scenario; a foreign format tag
    two = [{"name": n, "experiment": "fem_field", "specimen_file": {"path": f"specimen-{n}.vtu", "sha256": "0" * 64,
                                                                     "format": "difftissue-specimen/1"}} for n in ("a", "b")]
    many = MaterialCard(model="fem_linear", parameters=card.parameters, provenance={"scenario_records": two})
    with pytest.raises(ExportError, match="choose one with --scenario"):
        fitted_specimen_from_card(many, tmp_path / "material.json")
    two[0]["specimen_file"]["format"] = "other/1"
    with pytest.raises(ExportError, match="format 'other/1'"):
        fitted_specimen_from_card(many, tmp_path / "material.json", scenario="a")
    # no such scenario
    assert main(["export", str(card_path), "--to", "febio", "--specimen", "fitted", "--scenario", "nosuch", "--out", out]) == 1
    assert "no fitted specimen for scenario 'nosuch'" in capsys.readouterr().err
    # a card moved away from its specimen file
    moved = tmp_path / "moved" / "material.json"
    moved.parent.mkdir()
    moved.write_bytes(card_path.read_bytes())
    assert main(["export", str(moved), "--to", "febio", "--specimen", "fitted", "--out", out]) == 1
    err = capsys.readouterr().err
    assert "specimen-fem_field.vtu" in err and "is missing" in err and len(err.strip().splitlines()) == 1
    # an altered specimen file
    (moved.parent / "specimen-fem_field.vtu").write_bytes(paths["specimen-fem_field.vtu"].read_bytes() + b" ")
    assert main(["export", str(moved), "--to", "febio", "--specimen", "fitted", "--out", out]) == 1
    assert "altered or replaced" in capsys.readouterr().err
    # targets that cannot represent it: one line each
    for target, why in (("pbd", "per-node prescribed displacements"),):
        with pytest.raises(ExportError, match=why):
            export(card, target, tmp_path / "x.out", fitted=spec)
        assert main(["export", str(card_path), "--to", target, "--specimen", "fitted", "--out", str(tmp_path / "y.out")]) == 1
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    # options of other specimens are usage errors
    assert main(["export", str(card_path), "--to", "febio", "--specimen", "fitted", "--depth", "1", "--out", out]) == 2
    assert main(["export", str(card_path), "--to", "febio", "--specimen", "fitted", "--displacement", "1", "--out", out]) == 2
    with pytest.raises(ExportError, match="own mesh"):
        export(card, "febio", tmp_path / "z.feb", fitted=spec, mesh=block((1, 1, 1), (1, 1, 1)))


# ============================================================================== incision
LAM0 = 1.05
SKIN, FAT = Material(2e5, 0.45), Material(5e3, 0.45)


@pytest.fixture(scope="module")
def incision_case(tmp_path_factory):
    from difftissue.cutting import ScalpelPath, cut_specimen
    from difftissue.incision import Incision, IncisionOptions
    from difftissue.mesh import layered_skin

    spec = layered_skin([("dermis", 1 * MM, SKIN, 2), ("fat", 1 * MM, FAT, 1)], size=(4 * MM, 4 * MM), resolution=(8, 8))
    cut = cut_specimen(spec, ScalpelPath([(1 * MM, 2 * MM), (3 * MM, 2 * MM)], depth=1 * MM))
    sc = Incision(cut, model="fem_neo_hookean", fitted_regions=("dermis",), quantity="surface_width",
                  options=IncisionOptions(scalpel_steps=1, rtol=1e-12), name="skin cut")
    card = MaterialCard(model="fem_neo_hookean", name="dermis_fit", parameters={
        "youngs_modulus": {"value": SKIN.youngs_modulus}, "poisson_ratio": {"value": SKIN.poisson_ratio},
        "pre_stretch": {"value": LAM0}})
    tmp = tmp_path_factory.mktemp("incision")
    fs = fitted_specimen(sc)
    path = write_specimen(fs, tmp / specimen_file_name(sc.name))
    rec = {**scenario_record(sc), "specimen_file": specimen_record(fs, path)}
    card = MaterialCard(model=card.model, name=card.name, parameters=card.parameters, provenance={"scenario_records": [rec]})
    card_path = write_card(card, tmp / "material.json")
    res = sc.solve(card.material())
    return {"scenario": sc, "cut": cut, "card_path": card_path, "card": card, "result": res}


def test_incision_specimen_file_round_trip(incision_case):
    sc, cut = incision_case["scenario"], incision_case["cut"]
    assert specimen_file_name(sc.name) == "specimen-skin_cut.vtu"
    spec = fitted_specimen_from_card(read_card(incision_case["card_path"]), incision_case["card_path"])
    assert spec.experiment == "incision" and spec.model == "fem_neo_hookean" and spec.fitted_regions == ("dermis",)
    np.testing.assert_array_equal(spec.pairs, cut.pairs)
    np.testing.assert_array_equal(spec.surface_pairs, cut.surface_pairs)
    np.testing.assert_array_equal(spec.pair_s, cut.pair_s)
    np.testing.assert_array_equal(spec.fixed, sc.bc.fixed)
    assert spec.region_materials["fat"]["youngs_modulus"] == FAT.youngs_modulus
    assert spec.region_materials["fat"]["pre_stretch"] == 1.0


def test_incision_round_trip_febio_reproduces_the_opening(incision_case, tmp_path):
    """The FEBio model parsed back is the cut mesh (duplicated coincident pairs, region
    materials, F0 = diag(l0, l0, 1) on the dermis only, lateral faces held in x, y and base
    clamped); difftissue's static solve of the parsed model opens the cut as Incision does."""
    sc, cut, card = incision_case["scenario"], incision_case["cut"], incision_case["card"]
    out = tmp_path / "incision.feb"
    assert main(["export", str(incision_case["card_path"]), "--to", "febio", "--specimen", "fitted", "--out", str(out)]) == 0
    p = parse_febio(out)
    X = np.asarray(cut.mesh.points)
    np.testing.assert_array_equal(p["points"], X)
    plus, minus = p["sets"]["cut_plus"], p["sets"]["cut_minus"]
    np.testing.assert_array_equal(np.stack([plus, minus], axis=1), cut.pairs)
    assert len(p["points"]) == len(np.asarray(cut.mesh.points)) and plus.size == 6  # 3 columns x 2 depths (tips not split)
    np.testing.assert_array_equal(X[plus], X[minus] + np.asarray(cut.pair_rest_offset))
    # the cut mesh's tets, grouped by region
    order = np.argsort(np.asarray(cut.mesh.region_ids), kind="stable")
    np.testing.assert_array_equal(p["tets"], np.asarray(cut.mesh.tets)[order])
    assert p["region_names"] == list(cut.mesh.region_names) == ["dermis", "fat"]
    derm, fat = p["materials"]
    assert derm["type"] == fat["type"] == "neo-Hookean"
    np.testing.assert_array_equal(derm["F0"], np.diag([LAM0, LAM0, 1.0]))
    assert fat["F0"] is None and fat["E"] == FAT.youngs_modulus and derm["E"] == SKIN.youngs_modulus
    np.testing.assert_array_equal(p["fixed"], sc.bc.fixed)
    assert not p["prescribed"].any()
    # difftissue's own static solve of the parsed-back specimen
    mesh = TetMesh(p["points"], p["tets"], p["region_ids"], p["region_names"])
    mats = stack_materials([Material(m["E"], m["v"], pre_stretch=1.0 if m["F0"] is None else m["F0"][0, 0]) for m in p["materials"]])
    sol = solve_static(make_model(mesh, "fem_neo_hookean"), mats, BoundaryConditions(p["fixed"], p["prescribed"], np.zeros_like(p["prescribed"])),
                       rtol=1e-12)
    x = p["points"] + np.asarray(sol.displacement)
    w = np.linalg.norm(x[plus] - x[minus], axis=1)
    w_ref = np.asarray(incision_case["result"].opening.width)
    assert w_ref.max() > 1e-5  # m: the cut opened (about 0.05 mm)
    assert np.abs(w - w_ref).max() <= 1e-8 * w_ref.max()
    surf = np.asarray(cut.surface_pairs)
    pred = np.asarray(sc.predict(card.material()))
    np.testing.assert_allclose(np.interp(sc.positions, np.asarray(cut.pair_s)[surf], w[surf]), pred, rtol=0, atol=1e-8 * w_ref.max())


def test_incision_xpbd_vtu_and_refusals(incision_case, tmp_path):
    card, cut = incision_case["card"], incision_case["cut"]
    spec = fitted_specimen_from_card(card, incision_case["card_path"])
    doc = xpbd_fitted_parameters(card, spec, dt=1e-3, iterations=10, calibrate=False)  # the conversion (budget: test_export_xpbd_fitted.py)
    sp = doc["specimen"]
    assert sp["experiment"] == "incision" and sp["cut"]["pairs"] == np.asarray(cut.pairs).tolist()
    assert [r["name"] for r in sp["regions"]] == ["dermis", "fat"] and sp["regions"][0]["pre_stretch"] == LAM0
    lam = np.array(doc["per_tet"]["pre_stretch"])
    rid = np.asarray(cut.mesh.region_ids)
    assert np.all(lam[rid == 0] == LAM0) and np.all(lam[rid == 1] == 1.0)
    v = read_mesh(export(card, "vtu", tmp_path / "s.vtu", fitted=spec))
    pre = np.asarray(v.cell_data["pre_stretch"]).reshape(-1)
    assert np.all(pre[rid == 0] == LAM0) and np.all(pre[rid == 1] == 1.0)
    assert np.all(np.asarray(v.cell_data["youngs_modulus"]).reshape(-1)[rid == 1] == FAT.youngs_modulus)
    for target in ("abaqus", "sofa", "pbd"):
        with pytest.raises(ExportError) as e:
            export(card, target, tmp_path / "m.out", fitted=spec)
        assert "\n" not in str(e.value)
    with pytest.raises(ExportError, match="does not open"):
        export(card, "abaqus", tmp_path / "m.inp", fitted=spec, approximate=True)


def test_cli_fit_writes_the_specimen_and_refuses_to_overwrite_it(fem_fit, tmp_path, capsys):
    """``difftissue fit`` of a fem_field config writes specimen-<name>.vtu with the outputs;
    ``export --specimen fitted`` reads it; a second fit into the same folder refuses an existing
    specimen file before fitting (unless --force)."""
    ref = fem_fit["out"].parent / "ref.vtu"
    cfg = tmp_path / "fit.toml"
    cfg.write_text(f'''
[material]
youngs_modulus = 8.0e3
poisson_ratio = {NU}

[fit]
parameters = ["youngs_modulus"]

[[experiment]]
name = "punch"
scenario = "fem_field"
model = "fem_linear"
data = {{ format = "fem", path = "{ref}", field = "displacement", length_unit = "m" }}
prescribed = [{{ set = "bottom" }}, {{ set = "punch", components = "z" }}, {{ set = "side", components = "x" }}]
reaction = {{ set = "punch", components = "z", field = "reaction" }}
''')
    out = tmp_path / "out"
    assert main(["fit", str(cfg), "--out", str(out)]) == 0
    capsys.readouterr()
    assert (out / "specimen-punch.vtu").is_file()
    card = read_card(out / "material.json")
    assert card.youngs_modulus == pytest.approx(E, rel=1e-8)
    assert main(["export", str(out / "material.json"), "--to", "febio", "--specimen", "fitted", "--out", str(tmp_path / "m.feb")]) == 0
    assert "fitted fem_field specimen of scenario 'punch'" in capsys.readouterr().out
    for f in ("fit.json", "material.json", "fit.png", "loss.png", "report.md", "config.toml"):
        (out / f).unlink()
    assert main(["fit", str(cfg), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "specimen-punch.vtu exists" in err and not (out / "fit.json").exists()
