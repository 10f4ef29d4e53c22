"""Indentation specimens of the export writers (issue 6; docs/export.md "Indentation specimens").

Round trips: an exported flat-punch FEBio file, read back and solved in scikit-fem, against
difftissue's ``Indentation`` (``fem_linear``) on the same mesh; the pypbd flat-punch scene run in
pypbd against difftissue's solution of the scene energy; the XPBD JSON specimen run by
``run_xpbd_indentation`` against the static stable neo-Hookean solution. Plus the structure of
every writer's output, the node sets, the penalty conversion, the card's scenario records,
the CLI and the refusals.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from difftissue.cli import main
from difftissue.errors import ExportError
from difftissue.export import MaterialCard, export, read_card, write_card, xpbd_parameters
from difftissue.export.card import scenario_record
from difftissue.export.specimens import IndentationSpecimen, indentation_sets, indentation_specimen
from difftissue.export.xpbd import run_xpbd_indentation
from difftissue.scenarios import AnalyticIndentation, Indentation

E, NU = 12.0e3, 0.42
SIZE = (0.01, 0.01, 0.005)  # m
DEPTH = 1.0e-4  # m


def _card(tmp_path, model="fem_linear", nu=NU, name="skin", provenance=None):
    card = MaterialCard(model=model, name=name, provenance=provenance or {},
                        parameters={"youngs_modulus": {"value": E, "unit": "Pa", "standard_error": 100.0},
                                    "poisson_ratio": {"value": nu, "unit": "1", "standard_error": None}})
    return read_card(write_card(card, tmp_path / f"{model}-{name[:4]}.json", force=True))


def _punch(card, **kw):
    opts = dict(indenter="flat_punch", radius=2.0e-3, depth=DEPTH, size=SIZE, cells=(6, 6, 3), bonded_punch=True, steps=2)
    opts.update(kw)
    return indentation_specimen(card, **opts)


# ------------------------------------------------------------------ FEBio file reader
def _read_feb(path):
    root = ET.parse(path).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    mesh = root.find("Mesh")
    nodes = {int(n.get("id")): [float(v) for v in n.text.split(",")] for n in mesh.find("Nodes")}
    ids = sorted(nodes)
    assert ids == list(range(1, len(ids) + 1))  # 1-based, contiguous
    pts = np.array([nodes[i] for i in ids])
    elems = mesh.find("Elements")
    assert elems.get("type") == "tet4"
    tets = np.array([[int(v) - 1 for v in e.text.split(",")] for e in elems])
    sets = {ns.get("name"): np.array([int(v) - 1 for v in ns.text.split(",")]) for ns in mesh.findall("NodeSet")}
    mat = root.find("Material/material")
    bcs = []
    for bc in root.find("Boundary"):
        if bc.get("type") == "zero displacement":
            dofs = [c for c in "xyz" if bc.find(f"{c}_dof").text == "1"]
            bcs.append((bc.get("node_set"), dofs, 0.0))
        else:
            assert bc.get("type") == "prescribed displacement" and bc.find("relative").text == "0"
            assert bc.find("value").get("lc") == "1"
            bcs.append((bc.get("node_set"), [bc.find("dof").text], float(bc.find("value").text)))
    return root, pts, tets, sets, (float(mat.find("E").text), float(mat.find("v").text), mat.get("type")), bcs


def _skfem_punch_force(pts, tets, sets, material, bcs):
    """Solve the FEBio file's model (linear elasticity, its node sets and boundary conditions) in
    scikit-fem; return the punch force (positive compressive) from the reactions on ``punch``."""
    skfem = pytest.importorskip("skfem")
    from skfem.models.elasticity import linear_elasticity

    E_file, nu_file, _ = material
    lam = E_file * nu_file / ((1 + nu_file) * (1 - 2 * nu_file))
    mu = E_file / (2 * (1 + nu_file))
    m = skfem.MeshTet(pts.T.copy(), tets.T.copy())
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
    K = skfem.asm(linear_elasticity(lam, mu), basis).tocsr()
    dofs = np.asarray(basis.nodal_dofs).T  # (N, 3)
    u = np.zeros(K.shape[0])
    fixed = []
    for nset, comps, value in bcs:
        for c in comps:
            d = dofs[sets[nset], "xyz".index(c)]
            fixed.append(d)
            u[d] = value
    fixed = np.unique(np.concatenate(fixed))
    u = skfem.solve(*skfem.condense(K, np.zeros(K.shape[0]), x=u, D=fixed))
    reaction = K @ u
    return -float(reaction[dofs[sets["punch"], 2]].sum())


# ----------------------------------------------------------------------------- tests
@pytest.mark.parametrize("base, bonded", [("bonded", True), ("sliding", False)])
def test_febio_flat_punch_file_solved_in_skfem_matches_difftissue(tmp_path, base, bonded):
    """Issue 6: the exported specimen, read back from the .feb and solved in scikit-fem, gives
    difftissue's fem_linear punch force (measured 1e-13 relative: same P1 tets, same energy)."""
    card = _card(tmp_path)
    spec = _punch(card, base=base, bonded_punch=bonded, steps=1)
    path = export(card, "febio", tmp_path / "punch.feb", indentation=spec)
    root, pts, tets, sets, material, bcs = _read_feb(path)
    assert material == (E, NU, "isotropic elastic")
    # node sets: base z = 0, top z = H, punch = the top nodes within the radius
    H = SIZE[2]
    assert np.all(pts[sets["base"], 2] == 0.0) and len(sets["base"]) == 7 * 7
    assert np.allclose(pts[sets["top"], 2], H) and len(sets["top"]) == 7 * 7
    r = np.hypot(pts[:, 0], pts[:, 1])
    on_top = np.isclose(pts[:, 2], H)
    assert set(sets["punch"]) == set(np.flatnonzero(on_top & (r <= spec.radius * (1 + 1e-9))))
    assert len(sets["punch"]) == 5  # the axis node and its four neighbours at 1.67 mm
    assert bcs[-1 if not bonded else -2][0] == "punch"
    f_skfem = _skfem_punch_force(pts, tets, sets, material, bcs)

    sc = Indentation(spec.mesh(), [DEPTH], model="fem_linear", indenter="flat_punch", radius=spec.radius,
                     bonded_punch=bonded, base=base)
    f_ours = float(np.asarray(sc.predict(card.material()))[0])
    assert f_ours > 1e-3  # N, about 5 mN
    assert f_skfem == pytest.approx(f_ours, rel=1e-6)  # issue: 1 %; measured ~1e-13


def test_writers_structure_node_sets_and_penalty(tmp_path):
    """Every writer on sphere, cone and flat punch: well-formed files, the documented element
    and keyword names, 1-based ids, node-set sizes, the penalty conversion, the refusals."""
    card = _card(tmp_path, model="fem_neo_hookean", name='a<b>&"c" d')
    mesh_kw = dict(depth=2.0e-4, size=(8e-3, 8e-3, 4e-3), cells=(8, 8, 4))
    sphere = indentation_specimen(card, indenter="sphere", radius=1.0e-3, **mesh_kw)
    cone = indentation_specimen(card, indenter="cone", half_angle=math.radians(30.0), **mesh_kw)
    punch = indentation_specimen(card, indenter="flat_punch", radius=1.0e-3, bonded_punch=True, **mesh_kw)
    s = indentation_sets(sphere, sphere.mesh(), card)
    pts = np.asarray(sphere.mesh().points)
    assert len(s["base"]) == 81 and np.all(pts[s["base"], 2] == 0.0)
    assert len(s["top"]) == 81 and np.allclose(pts[s["top"], 2], 4e-3)
    assert s["h"] == pytest.approx(1e-3) and s["H"] == pytest.approx(4e-3)
    # difftissue's per-node penalty kappa_i = p E sqrt(A_i) (contact.ContactModel) on the same nodes
    from difftissue.contact import ContactModel, SphereIndenter
    from difftissue.models import make_model

    cm = ContactModel(make_model(sphere.mesh(), "fem_neo_hookean"), SphereIndenter(1e-3, surface_z=4e-3), sphere.mesh())
    np.testing.assert_array_equal(cm.contact_nodes, s["contact_nodes"])
    np.testing.assert_allclose(E * cm.penalty_factors, s["kappa"], rtol=1e-14)

    # FEBio: flat punch written; sphere and cone as a meshed rigid indenter (tests/test_export_febio_sphere.py)
    root = ET.parse(export(card, "febio", tmp_path / "p.feb", indentation=punch)).getroot()
    assert root.find("Material/material").get("name") == card.name  # escaped by the XML writer, read back intact
    assert root.find("Material/material").get("type") == "neo-Hookean"
    assert len(root.find("Mesh/NodeSet[@name='punch']").text.split(",")) == 5
    assert root.find("MeshDomains/SolidDomain").get("mat") == card.name
    assert {bc.get("type") for bc in root.find("Boundary")} == {"zero displacement", "prescribed displacement"}
    for spec, shape in ((sphere, "sphere"), (cone, "cone")):
        froot = ET.parse(export(card, "febio", tmp_path / f"{shape}.feb", indentation=spec)).getroot()
        assert froot.find("Material/material[@type='rigid body']") is not None
        assert froot.find("Contact/contact").get("type") == "sliding-elastic"

    # Abaqus: a meshed rigid indenter for sphere and cone (runs in CalculiX: tests/test_export_calculix.py), *BOUNDARY for the punch
    from difftissue.export import abaqus_indenter_mesh

    for spec, shape in ((sphere, "sphere"), (cone, "cone"), (punch, "punch")):
        text = export(card, "abaqus", tmp_path / f"{shape}.inp", indentation=spec).read_text()
        lines = text.splitlines()
        assert lines[0] == "*HEADING" and "*MATERIAL, NAME=a_b___c__d" in lines
        assert not any(ln.startswith("*") and not ln.startswith("**") and "<" in ln for ln in lines)  # the raw name only in ** comments
        n = 405
        ipts, itets, _ = abaqus_indenter_mesh(spec, 4e-3, 0.5e-3) if shape != "punch" else (np.zeros((0, 3)), np.zeros((0, 4)), 0)
        node_ids = [int(ln.split(",")[0]) for ln in lines[lines.index("*NODE") + 1:lines.index("*ELEMENT, TYPE=C3D4, ELSET=TISSUE")]]
        assert node_ids == list(range(1, n + len(ipts) + 1))  # 1-based; the indenter's nodes after the tissue's
        i = lines.index("*ELEMENT, TYPE=C3D4, ELSET=TISSUE")
        conn = np.array([[int(v) for v in ln.split(",")[1:]] for ln in lines[i + 1:i + 1 + 6 * 8 * 8 * 4]])
        assert conn.min() == 1 and conn.max() == n
        for kw in ("*NSET, NSET=BASE", "*NSET, NSET=TOP", "*SOLID SECTION, ELSET=TISSUE, MATERIAL=a_b___c__d",
                   "*HYPERELASTIC, NEO HOOKE", "*STATIC", "*END STEP"):
            assert kw in lines, kw
        assert any(ln.startswith("*STEP, NLGEOM=YES") for ln in lines)
        if shape == "punch":
            assert "*NSET, NSET=PUNCH" in lines and f"PUNCH, 3, 3, {-2e-4!r}" in lines and "PUNCH, 1, 2, 0.0" in lines
        else:
            assert "TYPE=REVOLUTION" not in text and "ANALYTICAL SURFACE" not in text
            for kw in ("*ELEMENT, TYPE=C3D4, ELSET=INDENTER", "*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF",
                       "*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF", "INDENTER, S1", "*SURFACE INTERACTION, NAME=INDENTER_CONTACT",
                       "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", repr(100.0 * E / s["h"]),
                       "*CONTACT PAIR, INTERACTION=INDENTER_CONTACT, TYPE=NODE TO SURFACE", "TOP_SURF, INDENTER_SURF",
                       "INDENTER, 1, 2, 0.0", f"INDENTER, 3, 3, {-2e-4!r}", "*NODE PRINT, NSET=INDENTER, TOTALS=ONLY"):
                assert kw in lines, kw
            # the indenter's nodes lie on the sphere / cone (the apex, last, inside it); the fan tets have positive volume
            cap = ipts[:-1]
            if shape == "sphere":
                np.testing.assert_allclose(np.linalg.norm(cap - [0, 0, 5e-3], axis=1), 1e-3, rtol=1e-12)
            else:
                np.testing.assert_allclose(cap[:, 2] - 4e-3, np.hypot(cap[:, 0], cap[:, 1]) / math.tan(math.radians(30.0)), atol=1e-15)
            # the slave surface: every top face of the tissue, once
            j = lines.index("*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF")
            n_faces = 0
            for ln in lines[j + 1:j + 5]:
                if ln.startswith("TOP_S"):
                    k = lines.index(f"*ELSET, ELSET={ln.split(',')[0]}")
                    end = next(m for m in range(k + 1, len(lines)) if lines[m].startswith("*"))
                    n_faces += len(", ".join(lines[k + 1:end]).split(","))
            assert n_faces == 2 * 8 * 8
            assert ("AXIS_TOP, 1, 2, 0.0" in lines) == (shape == "cone")

    # SOFA: sphere -> SphereForceField (stiffness p E h), punch -> projective constraints; cone refused
    root = ET.parse(export(card, "sofa", tmp_path / "s.scn", indentation=sphere)).getroot()
    sff = root.find("Node/SphereForceField")
    assert sff.get("stiffness") == repr(100.0 * E * s["h"]) and sff.get("damping") == "0"
    assert sff.get("center") == f"0 0 {4e-3 + 1e-3!r}" and sff.get("radius") == repr(1e-3)
    mov = root.find("Node/LinearMovementProjectiveConstraint")
    assert len(mov.get("indices").split()) == 81 and mov.get("movements") == f"0 0 0  0 0 {2e-4!r}  0 0 {2e-4!r}"
    assert mov.get("keyTimes") == "0 1 1000000"  # held after t = 1 (SOFA's constraint stops at its last key time)
    assert {p.get("name") for p in root.findall("RequiredPlugin")} >= {"Sofa.Component.MechanicalLoad"}
    root = ET.parse(export(card, "sofa", tmp_path / "p.scn", indentation=punch)).getroot()
    assert len(root.find("Node/FixedProjectiveConstraint").get("indices").split()) == 81
    assert len(root.find("Node/LinearMovementProjectiveConstraint").get("indices").split()) == 5
    with pytest.raises(ExportError, match="SOFA indentation specimen: a cone indenter cannot be written"):
        export(card, "sofa", tmp_path / "c.scn", indentation=cone)
    with pytest.raises(ExportError, match="frictionless flat punch .* cannot be written"):
        export(card, "sofa", tmp_path / "f.scn", indentation=indentation_specimen(card, indenter="flat_punch", radius=1e-3, **mesh_kw))
    with pytest.raises(ExportError, match="base='sliding'"):
        export(card, "sofa", tmp_path / "b.scn", indentation=indentation_specimen(card, indenter="sphere", radius=1e-3, base="sliding", **mesh_kw))

    # XPBD JSON: the indenter block carries difftissue's penalties; VTU: boundary point data
    doc = json.loads(export(card, "xpbd", tmp_path / "x.json", indentation=cone, dt=1e-3, iterations=10).read_text())
    ind = doc["specimen"]["indenter"]
    assert ind["shape"] == "cone" and ind["tip_at_depth"] == [0.0, 0.0, 4e-3 - 2e-4]
    np.testing.assert_allclose(ind["penalty"], s["kappa"]) and len(doc["specimen"]["fixed"]["all_components"]) == 81
    import meshio

    v = meshio.read(export(card, "vtu", tmp_path / "p.vtu", indentation=punch))
    b = v.point_data["boundary"]
    assert (b == 1).sum() == 81 and (b == 2).sum() == 5
    assert np.allclose(v.point_data["prescribed_displacement"][b == 2], [0.0, 0.0, -2e-4])


def test_refusals_one_clear_line(tmp_path):
    card = _card(tmp_path)
    spec = _punch(card)
    from difftissue.mesh import block

    sphere = indentation_specimen(card, indenter="sphere", radius=1e-3, depth=1e-4, size=SIZE, cells=(2, 2, 2))
    cases = [
        ("not both", lambda: export(card, "febio", tmp_path / "a.feb", mesh=block((0.01,) * 3, (2, 2, 2)), indentation=spec)),
        ("takes its depth", lambda: export(card, "abaqus", tmp_path / "a.inp", displacement=-1e-4, indentation=spec)),
        ("a sphere indenter needs frictionless contact", lambda: export(card, "pbd", tmp_path / "a.json", indentation=sphere)),
        ("bonded flat punch", lambda: export(card, "pbd", tmp_path / "a.json", indentation=_punch(card, bonded_punch=False))),
        ("records no indentation scenario", lambda: indentation_specimen(card)),
        ("no indentation scenario named 'x'", lambda: indentation_specimen(card, scenario="x")),
        ("not below the block height", lambda: indentation_specimen(card, indenter="sphere", radius=1e-3, depth=0.01, size=SIZE)),
        ("half_angle in", lambda: IndentationSpecimen(indenter="cone", depth=1e-4, size=SIZE, cells=(2, 2, 2), half_angle=2.0)),
        ("positive finite", lambda: IndentationSpecimen(indenter="sphere", depth=-1e-4, size=SIZE, cells=(2, 2, 2), radius=1e-3)),
        ("positive radius", lambda: IndentationSpecimen(indenter="flat_punch", depth=1e-4, size=SIZE, cells=(2, 2, 2))),
        ("expected one of", lambda: IndentationSpecimen(indenter="wedge", depth=1e-4, size=SIZE, cells=(2, 2, 2), radius=1e-3)),
        ("law='springs'", lambda: export(card, "sofa", tmp_path / "a.scn", law="springs", indentation=spec)),
        ("no contact constraint", lambda: run_xpbd_indentation(xpbd_parameters(card, dt=1e-3, iterations=10, indentation=sphere))),
    ]
    for match, call in cases:
        with pytest.raises(ExportError, match=match) as err:
            call()
        assert "\n" not in str(err.value), match
    assert not any(tmp_path.glob("a.*"))  # nothing written by a refused export


def test_card_scenario_records_from_fit_outputs(tmp_path):
    """write_fit_outputs(scenario_records=...) puts the experiment into the card, and
    indentation_specimen rebuilds it from there (every value's origin recorded)."""
    import jax.numpy as jnp

    from difftissue.fit import fit
    from difftissue.report import write_fit_outputs
    from difftissue.materials import Material, MaterialParameterization

    depths = np.linspace(1e-6, 8e-6, 6)
    from difftissue import analytic

    forces = np.asarray(analytic.hertz_force(jnp.asarray(depths), 200.0, 0.0, 25e-6))
    sc = AnalyticIndentation(depths, forces, indenter="sphere", radius=25e-6, name="afm")
    result = fit([sc], MaterialParameterization(("youngs_modulus",)), Material(150.0, 0.0))
    paths = write_fit_outputs(result, tmp_path / "fit", model="hertz", scenario_records=[scenario_record(sc)])
    card = read_card(paths["material.json"])
    assert card.youngs_modulus == pytest.approx(200.0, rel=1e-6)
    (rec,) = card.provenance["scenario_records"]
    assert rec == {"name": "afm", "type": "AnalyticIndentation", "experiment": "indentation", "indenter": "sphere",
                   "radius": 25e-6, "thickness": None, "base": "bonded", "solution": "half_space",
                   "max_depth": pytest.approx(8e-6), "points": 6}
    spec = indentation_specimen(card)
    assert (spec.indenter, spec.radius, spec.depth, spec.base) == ("sphere", 25e-6, pytest.approx(8e-6), "bonded")
    assert spec.sources["radius"] == "card scenario record 'afm'" and "ASSUMED" in spec.sources["size"]
    a = math.sqrt(25e-6 * 8e-6)
    assert spec.size[2] == pytest.approx(max(10 * a, 5 * 8e-6)) and spec.size[0] == pytest.approx(2 * spec.size[2])
    # a simulated flat punch records its effective radius, bonding and base
    mesh = _punch(card).mesh()
    ind = Indentation(mesh, [5e-5, 1e-4], model="fem_linear", indenter="flat_punch", radius=2.1e-3, bonded_punch=True,
                      base="sliding", name="punch")
    rec = scenario_record(ind)
    assert rec["indenter"] == "flat_punch" and rec["radius"] == pytest.approx(10e-3 / 6) and rec["bonded_punch"] is True
    assert rec["base"] == "sliding" and rec["block_size"] == pytest.approx(list(SIZE)) and rec["max_depth"] == 1e-4
    spec = indentation_specimen(MaterialCard(model="fem_linear", parameters=card.parameters, provenance={"scenario_records": [rec]}),
                                cells=(6, 6, 3))
    assert (spec.indenter, spec.bonded_punch, spec.base, spec.size) == ("flat_punch", True, "sliding", pytest.approx(SIZE))
    assert len(indentation_sets(spec, spec.mesh(), card)["punch"]) == 5


def test_cli_export_indentation(tmp_path, capsys):
    card = _card(tmp_path, provenance={"scenario_records": [{"name": "afm", "experiment": "indentation", "indenter": "sphere",
                                                             "radius": 1e-3, "max_depth": 2e-4, "thickness": 4e-3,
                                                             "base": "bonded"}]})
    cpath = tmp_path / "card.json"
    write_card(card, cpath)
    out = tmp_path / "punch.feb"
    assert main(["export", str(cpath), "--to", "febio", "--specimen", "indentation", "--indenter", "flat_punch",
                 "--radius", "1", "--depth", "0.1", "--block", "8,8,4", "--cells", "8,8,4", "--bonded-punch", "--out", str(out)]) == 0
    assert "flat_punch indentation specimen, depth 0.0001 m" in capsys.readouterr().out
    root = ET.parse(out).getroot()
    assert float(root.find("Boundary/bc[@name='punch_displacement']/value").text) == -1e-4
    assert len(root.find("Mesh/NodeSet[@name='punch']").text.split(",")) == 5
    # from the card's record (sphere, radius, depth, layer thickness) to Abaqus
    inp = tmp_path / "afm.inp"
    assert main(["export", str(cpath), "--to", "abaqus", "--specimen", "indentation", "--cells", "4,4,2", "--out", str(inp)]) == 0
    text = inp.read_text()
    assert "*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF" in text and "** radius: card scenario record 'afm'" in text
    assert f"INDENTER, 3, 3, {-2e-4!r}" in text
    capsys.readouterr()
    # the same record to FEBio: a meshed rigid sphere (tests/test_export_febio_sphere.py)
    assert main(["export", str(cpath), "--to", "febio", "--specimen", "indentation", "--cells", "4,4,2",
                 "--out", str(tmp_path / "s.feb")]) == 0
    froot = ET.parse(tmp_path / "s.feb").getroot()
    assert float(froot.find("Rigid/rigid_bc[@type='rigid_displacement']/value").text) == -2e-4
    capsys.readouterr()
    # refusals are one line, exit 1 (export) / 2 (usage)
    assert main(["export", str(cpath), "--to", "pbd", "--specimen", "indentation", "--out", str(tmp_path / "p.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert "pypbd: a sphere indenter needs frictionless contact" in err and "\n" not in err
    assert main(["export", str(cpath), "--to", "febio", "--specimen", "indentation", "--displacement", "-0.1",
                 "--out", str(tmp_path / "d.feb")]) == 2
    assert main(["export", str(cpath), "--to", "febio", "--specimen", "block:1,1,1:1,1,1", "--radius", "1",
                 "--out", str(tmp_path / "r.feb")]) == 2
    assert not (tmp_path / "p.json").exists() and not (tmp_path / "d.feb").exists()


_RUNNER = """
import json, sys
from difftissue.export.pypbd_runner import read_pbd_scene, run_pbd_scene
r = run_pbd_scene(read_pbd_scene(sys.argv[2]), rtol=1e-4, max_steps=20000, check_every=50)
open(sys.argv[1], "w").write(json.dumps({"displacement": r.displacement.tolist(), "reaction": r.reaction.tolist(),
                                         "converged": r.converged, "steps": r.steps, "dt": r.dt}))
"""


def test_pypbd_flat_punch_round_trip(tmp_path):
    """The pypbd flat-punch scene (bonded punch, bonded base) run in pypbd against difftissue's
    solution of the energy the scene minimises (springs + per-tet volume, pbd_reference_model)."""
    pytest.importorskip("pypbd", reason="pypbd (PyPI) has no wheel for this platform/Python; the round trip needs it")
    from difftissue.boundary import BoundaryConditions
    from difftissue.export.pypbd_runner import pbd_reference_model, read_pbd_scene, scene_forces
    from difftissue.solvers.static import solve_static

    card = _card(tmp_path, model="springs_volume", nu=0.45)
    spec = _punch(card, radius=3.0e-3, cells=(4, 4, 2))  # 2.5 mm cubes, punch = 5 nodes
    from difftissue.export.pypbd import write_pbd

    path = write_pbd(card, tmp_path / "punch.json", indentation=spec, calibrate=False)  # the card's own lattice energy
    scene = read_pbd_scene(path)
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    assert scene["boundary"]["fixed"] == s["base"].tolist() and scene["boundary"]["moved"] == s["punch"].tolist()
    assert scene["boundary"]["displacement"] == [0.0, 0.0, -DEPTH] and len(s["punch"]) == 5
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = tmp_path / "res.json"
    proc = subprocess.run([sys.executable, "-c", _RUNNER, str(res), str(path)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = json.loads(res.read_text())
    assert run["converged"], run["steps"]

    bc = BoundaryConditions.free(mesh).fix(mesh, s["base"], "xyz").fix(mesh, s["punch"], "xyz", (0.0, 0.0, -DEPTH))
    ref = solve_static(pbd_reference_model(mesh), card.material(), bc)
    f_ref = -float(np.asarray(ref.reaction)[s["punch"], 2].sum())
    g = scene_forces(scene, np.asarray(mesh.points) + np.asarray(ref.displacement))
    free = np.setdiff1d(np.arange(mesh.n_nodes), np.concatenate([s["base"], s["punch"]]))
    assert np.abs(g[free]).max() <= 1e-10 * f_ref  # the scene energy is the reference model's
    f_pbd = -float(np.asarray(run["reaction"])[s["punch"], 2].sum())
    assert f_ref > 5e-3  # N
    assert f_pbd == pytest.approx(f_ref, rel=1e-3)  # measured: see docs/export.md
    np.testing.assert_allclose(np.asarray(run["displacement"]), np.asarray(ref.displacement), atol=1e-3 * DEPTH)


def test_xpbd_json_flat_punch_runs_to_the_static_force(tmp_path):
    """run_xpbd_indentation on the exported XPBD JSON (file numbers only) against the static
    stable neo-Hookean punch force on the same mesh."""
    card = _card(tmp_path, model="stable_neo_hookean")
    spec = _punch(card, radius=3.0e-3, cells=(4, 4, 2), steps=1)
    doc = xpbd_parameters(card, dt=2e-4, iterations=10, indentation=spec, calibrate=False)  # the card's own compliances
    run = run_xpbd_indentation(doc, tol=1e-10, max_steps=5000)
    sc = Indentation(spec.mesh(), [DEPTH], model="stable_neo_hookean", indenter="flat_punch", radius=3.0e-3, bonded_punch=True)
    f_ref = float(np.asarray(sc.predict(card.material()))[0])
    assert run["converged"] == [True] and f_ref > 1e-2
    assert run["forces"][0] == pytest.approx(f_ref, rel=1e-6)  # measured 1.1e-8
    from difftissue.errors import ConvergenceError

    doc["setting"]["dt"] = 1e-2  # warm-started XPBD diverges at this step on 2.5 mm cells: a clear error, no NaN
    with pytest.raises(ConvergenceError, match="smaller"):
        run_xpbd_indentation(doc, tol=1e-10, max_steps=300)


# ------------------------------------------------------------------ effective modulus (issue 17)
def _hertz_fit(tmp_path, nu, name="fit"):
    """A Hertz half-space fit of E* = 200 Pa with nu fixed at ``nu``: outputs in tmp_path/name."""
    import jax.numpy as jnp

    from difftissue import analytic
    from difftissue.fit import fit
    from difftissue.report import write_fit_outputs
    from difftissue.materials import Material, MaterialParameterization

    depths = np.linspace(1e-6, 8e-6, 12)
    forces = np.asarray(analytic.hertz_force(jnp.asarray(depths), 200.0, 0.0, 25e-6))  # E* = 200 Pa
    sc = AnalyticIndentation(depths, forces, indenter="sphere", radius=25e-6, name="afm")
    result = fit([sc], MaterialParameterization(("youngs_modulus",)), Material(150.0, nu))
    return result, write_fit_outputs(result, tmp_path / name, model="hertz")


def test_a_hertz_fit_with_nu_fixed_reports_the_effective_modulus(tmp_path):
    result, paths = _hertz_fit(tmp_path, 0.45)
    em = result.effective_modulus
    assert em["value"] == pytest.approx(200.0, rel=1e-6) and em["poisson_ratio_assumed"] == 0.45 and em["law"] == "Hertz"
    assert result.values["youngs_modulus"] == pytest.approx(200.0 * (1 - 0.45**2), rel=1e-6)
    rec = json.loads(paths["fit.json"].read_text())
    assert rec["effective_modulus"]["value"] == pytest.approx(200.0, rel=1e-6) and "E* = E / (1 - nu^2)" in rec["effective_modulus"]["meaning"]
    assert "Effective modulus E\\* = E/(1-nu^2) = 200" in paths["report.md"].read_text()
    card = read_card(paths["material.json"])
    assert card.provenance["effective_modulus"]["poisson_ratio_assumed"] == 0.45
    assert read_card(paths["fit.json"]).provenance["effective_modulus"]["value"] == pytest.approx(200.0, rel=1e-6)
    # nu fixed at a tissue's value: exported as is, the header says E rests on that nu
    export(card, "febio", tmp_path / "a.feb")
    assert "E rests on the assumed nu = 0.45" in (tmp_path / "a.feb").read_text()


def test_export_refuses_an_effective_modulus_fitted_at_nu_0_unless_nu_is_stated(tmp_path, capsys):
    from difftissue.errors import EffectiveModulusError

    _, paths = _hertz_fit(tmp_path, 0.0)
    card = read_card(paths["material.json"])
    with pytest.raises(EffectiveModulusError, match=r"effective modulus E\* = E/\(1-nu\^2\).*State the tissue's nu"):
        export(card, "febio", tmp_path / "x.feb")
    assert not (tmp_path / "x.feb").exists()
    export(card, "febio", tmp_path / "conv.feb", nu=0.45)  # explicit conversion
    mat = ET.parse(tmp_path / "conv.feb").getroot().find(".//material")
    assert float(mat.find("E").text) == pytest.approx(200.0 * (1 - 0.45**2), rel=1e-6) and float(mat.find("v").text) == 0.45
    export(card, "febio", tmp_path / "approx.feb", approximate=True)
    text = (tmp_path / "approx.feb").read_text()
    assert "APPROXIMATION: E = 200 Pa is the effective modulus" in text and "<v>0.0</v>" in text
    # the CLI: one line naming the reason and the ways out; --nu converts
    assert main(["export", str(paths["material.json"]), "--to", "febio", "--out", str(tmp_path / "c.feb")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--nu 0.45" in err and "--approximate" in err and "refit with poisson_ratio fixed" in err
    assert main(["export", str(paths["material.json"]), "--to", "febio", "--out", str(tmp_path / "c.feb"), "--nu", "0.49"]) == 0
    assert "<v>0.49</v>" in (tmp_path / "c.feb").read_text()


def test_cli_export_indentation_from_an_axisymmetric_fit_record(tmp_path, capsys):
    """A card fitted with the axisymmetric model (the config's default for a FEM sphere) exports
    a 3-D block: the half-space block of the defaults, the record's indenter, depth, base and
    penalty, and a source line saying the fit was axisymmetric; a layer keeps its thickness."""
    from difftissue.scenarios import AxisymmetricIndentation

    axi = AxisymmetricIndentation([5e-5, 1e-4], indenter="sphere", radius=1e-3, model="fem_linear", base="sliding", penalty=50.0, name="axi",
                                  cells_per_contact_radius=2)
    rec = scenario_record(axi)
    assert rec["geometry"] == "axisymmetric" and "block_size" not in rec
    card = _card(tmp_path, provenance={"scenario_records": [rec]})
    spec = indentation_specimen(card, cells=(4, 4, 2))
    a = math.sqrt(1e-3 * 1e-4)
    assert (spec.indenter, spec.radius, spec.depth, spec.base, spec.penalty) == ("sphere", 1e-3, 1e-4, "sliding", 50.0)
    assert spec.size == pytest.approx((20 * a, 20 * a, 10 * a)) and "simulated a half-space axisymmetrically" in spec.sources["size"]
    cpath = tmp_path / "axi-card.json"
    write_card(card, cpath)
    inp = tmp_path / "axi.inp"
    assert main(["export", str(cpath), "--to", "abaqus", "--specimen", "indentation", "--cells", "4,4,2", "--out", str(inp)]) == 0
    assert "sphere indentation specimen, depth 0.0001 m" in capsys.readouterr().out
    assert "axisymmetrically" in inp.read_text()
    # the fit's cylinder a layer of 3 mm: the block keeps that thickness
    layer = AxisymmetricIndentation([5e-5, 1e-4], indenter="sphere", radius=1e-3, model="fem_linear", thickness=3e-3, name="layer",
                                    cells_per_contact_radius=2)
    spec = indentation_specimen(_card(tmp_path, name="layer", provenance={"scenario_records": [scenario_record(layer)]}), cells=(4, 4, 2))
    assert spec.size[2] == pytest.approx(3e-3) and spec.size[0] == pytest.approx(max(6e-3, 20 * a))
