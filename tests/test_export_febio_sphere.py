"""FEBio sphere and cone indentation specimens: a meshed rigid indenter (tri3 shell cap of a
``rigid body`` material) in frictionless ``sliding-elastic`` contact with the tissue's top face,
driven by ``rigid_displacement`` (docs/export.md, "Indentation specimens").

FEBio is not run here (it does not install from PyPI): the file is checked for structure, the
FEBio 4.0 section order, the indenter geometry (nodes on the sphere / cone, coverage of the
contact radius, facet orientation, a closed-manifold cap whose area matches the analytic cap),
id consistency, the references between sections, the tissue part against the flat-punch writer's,
the load curve and the penalty conversion.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections import Counter

import numpy as np
import pytest

from difftissue.errors import ExportError
from difftissue.export import FEBIO_INDENTER_MATERIAL, MaterialCard, export, febio_indenter_cap
from difftissue.export.specimens import indentation_sets, indentation_specimen

E, NU = 12.0e3, 0.42
SIZE = (8e-3, 8e-3, 4e-3)
CELLS = (8, 8, 4)
H = SIZE[2]


def _card(name="skin", model="fem_neo_hookean"):
    return MaterialCard(model=model, name=name, provenance={},
                        parameters={"youngs_modulus": {"value": E, "unit": "Pa"}, "poisson_ratio": {"value": NU, "unit": "1"}})


def _parse(path):
    root = ET.parse(path).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    return root


def _ints(text):
    return [int(v) for v in text.split(",")]


def _nodes(root):
    out = {}
    for block in root.find("Mesh").findall("Nodes"):
        for n in block:
            i = int(n.get("id"))
            assert i not in out  # unique across the Nodes blocks
            out[i] = [float(v) for v in n.text.split(",")]
    return out


def _check_ids(root):
    nodes = _nodes(root)
    assert sorted(nodes) == list(range(1, len(nodes) + 1))  # 1-based, contiguous
    eids = [int(e.get("id")) for block in root.find("Mesh").findall("Elements") for e in block]
    assert sorted(eids) == list(range(1, len(eids) + 1)) and len(set(eids)) == len(eids)
    for block in root.find("Mesh").findall("Elements"):
        for e in block:
            assert all(v in nodes for v in _ints(e.text))
    return nodes


@pytest.mark.parametrize("base", ["bonded", "sliding"])
def test_febio_sphere_specimen(tmp_path, base):
    card = _card()
    R, d = 1.0e-3, 5.0e-5
    spec = indentation_specimen(card, indenter="sphere", radius=R, depth=d, size=SIZE, cells=CELLS, base=base, steps=4)
    root = _parse(export(card, "febio", tmp_path / "sphere.feb", indentation=spec))
    # FEBio 4.0 section order (FEBioXML/FEBioImport.cpp registers Rigid as a top-level section of 4.0)
    assert [c.tag for c in root if isinstance(c.tag, str)] == [
        "Module", "Control", "Material", "Mesh", "MeshDomains", "Boundary", "Rigid", "Contact", "LoadData", "Output"]
    nodes = _check_ids(root)
    mesh = root.find("Mesh")
    tissue_block, cap_block = mesh.findall("Nodes")
    assert (tissue_block.get("name"), cap_block.get("name")) == ("specimen", "indenter")
    cap_ids = [int(n.get("id")) for n in cap_block]
    cap = np.array([nodes[i] for i in cap_ids])
    # the cap nodes lie on the sphere of radius R about (0, 0, H + R), the tip touches the top face on the axis
    centre = np.array([0.0, 0.0, H + R])
    np.testing.assert_allclose(np.linalg.norm(cap - centre, axis=1), R, rtol=1e-12)
    assert cap[:, 2].min() == pytest.approx(H, abs=1e-15) and np.all(cap[:, 2] <= H + R + 1e-15)
    a = math.sqrt(R * d)
    r_cap = np.hypot(cap[:, 0], cap[:, 1]).max()
    assert r_cap == pytest.approx(3.0 * a, rel=1e-12) and r_cap >= 2.0 * a  # covers the contact radius with margin
    # rigid material, referenced by the shell domain and the rigid BCs
    mats = {m.get("name"): m for m in root.find("Material").findall("material")}
    rig = mats[FEBIO_INDENTER_MATERIAL]
    assert rig.get("type") == "rigid body" and rig.get("id") == "2" and mats["skin"].get("id") == "1"
    assert [float(v) for v in rig.find("center_of_mass").text.split(",")] == pytest.approx(list(centre), abs=1e-15)
    assert float(rig.find("density").text) > 0
    doms = root.find("MeshDomains")
    assert doms.find("SolidDomain").get("mat") == "skin" and doms.find("SolidDomain").get("name") == "tissue"
    sd = doms.find("ShellDomain")
    assert sd.get("mat") == FEBIO_INDENTER_MATERIAL and float(sd.find("shell_thickness").text) > 0
    elems = {e.get("name"): e for e in mesh.findall("Elements")}
    assert set(elems) == {"tissue", "indenter_shell"} and sd.get("name") == "indenter_shell"
    assert elems["tissue"].get("type") == "tet4" and elems["indenter_shell"].get("type") == "tri3"
    assert all(set(_ints(e.text)) <= set(cap_ids) for e in elems["indenter_shell"])
    assert all(max(_ints(e.text)) < cap_ids[0] for e in elems["tissue"])
    # surfaces and the pair: defined before the SurfacePair (FEBioMeshSection4 looks them up while parsing)
    tags = [c.tag for c in mesh if isinstance(c.tag, str)]
    surfaces = {s.get("name"): s for s in mesh.findall("Surface")}
    assert tags.index("SurfacePair") > max(i for i, t in enumerate(tags) if t == "Surface")
    pair = mesh.find("SurfacePair")
    assert pair.find("primary").text == "tissue_top" and pair.find("secondary").text == "indenter_surface"
    assert set(surfaces) == {"tissue_top", "indenter_surface"}
    contact = root.find("Contact/contact")
    assert contact.get("type") == "sliding-elastic" and contact.get("surface_pair") == pair.get("name")
    assert float(contact.find("fric_coeff").text) == 0.0 and contact.find("laugon").text == "0"
    assert contact.find("auto_penalty").text == "0" and contact.find("tension").text == "0"
    s = indentation_sets(spec, spec.mesh(), card)
    assert float(contact.find("penalty").text) == pytest.approx(spec.penalty * E / s["h"], rel=1e-14)
    # facet orientation: tissue top +z (outward), indenter facets away from the centre (towards the tissue)
    def normals(surf):
        f = np.array([[nodes[i] for i in _ints(t.text)] for t in surf])
        return np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), f.mean(axis=1)
    n_top, c_top = normals(surfaces["tissue_top"])
    assert np.all(n_top[:, 2] > 0) and np.allclose(c_top[:, 2], H)
    assert len(surfaces["tissue_top"]) == len(s["top_faces"]) == 2 * CELLS[0] * CELLS[1]
    n_cap, c_cap = normals(surfaces["indenter_surface"])
    assert np.all(np.einsum("ij,ij->i", n_cap, c_cap - centre) > 0)
    assert [_ints(t.text) for t in surfaces["indenter_surface"]] == [_ints(e.text) for e in elems["indenter_shell"]]
    # rigid boundary conditions: x, y and the rotations fixed, z prescribed to -depth by load controller 1
    rbcs = {b.get("type"): b for b in root.find("Rigid").findall("rigid_bc")}
    assert set(rbcs) == {"rigid_fixed", "rigid_displacement"}
    assert all(b.find("rb").text == FEBIO_INDENTER_MATERIAL for b in rbcs.values())
    fixed = rbcs["rigid_fixed"]
    assert {k: fixed.find(k).text for k in ("Rx_dof", "Ry_dof", "Rz_dof", "Ru_dof", "Rv_dof", "Rw_dof")} == {
        "Rx_dof": "1", "Ry_dof": "1", "Rz_dof": "0", "Ru_dof": "1", "Rv_dof": "1", "Rw_dof": "1"}
    move = rbcs["rigid_displacement"]
    assert move.find("dof").text == "z" and move.find("relative").text == "0"
    lc_id = move.find("value").get("lc")
    lc = root.find(f"LoadData/load_controller[@id='{lc_id}']")
    assert lc.get("type") == "loadcurve"
    last_t, last_v = (float(v) for v in lc.find("points")[-1].text.split(","))
    assert last_t == 1.0 and float(move.find("value").text) * last_v == -d  # the displacement ends at -depth
    assert int(root.find("Control/time_steps").text) * float(root.find("Control/step_size").text) == pytest.approx(last_t)

    # the tissue part is the flat-punch writer's: same nodes, tets, base/top sets and base boundary conditions
    punch = indentation_specimen(card, indenter="flat_punch", radius=R, depth=d, size=SIZE, cells=CELLS, base=base, steps=4)
    proot = _parse(export(card, "febio", tmp_path / "punch.feb", indentation=punch))
    pm = proot.find("Mesh")
    assert [n.text for n in pm.find("Nodes")] == [n.text for n in tissue_block]
    assert [e.text for e in pm.find("Elements")] == [e.text for e in elems["tissue"]]
    for name in ("base", "top") + (("base_anchor", "base_other") if base == "sliding" else ()):
        assert mesh.find(f"NodeSet[@name='{name}']").text == pm.find(f"NodeSet[@name='{name}']").text
    base_bcs = lambda r: [(b.attrib, [(c.tag, c.text) for c in b]) for b in r.find("Boundary")  # noqa: E731
                          if b.get("node_set", "").startswith("base")]
    # the sphere's force is read from the base: held by prescribed displacement 0 (FEBio records
    # reactions only there), the punch's base by zero displacement; the held dofs are the same
    held = lambda r: sorted((b.get("node_set"), d) for b in r.find("Boundary") if b.get("node_set", "").startswith("base")  # noqa: E731
                            for d in ([b.find("dof").text] if b.get("type") == "prescribed displacement" else
                                      [c for c in "xyz" if b.find(f"{c}_dof").text == "1"]))
    assert held(root) == held(proot) and len(held(root)) == (3 if base == "bonded" else 4)
    pre = [b for b in root.find("Boundary") if b.get("type") == "prescribed displacement"]
    assert {b.get("node_set") for b in pre} == {"base"} and all(float(b.find("value").text) == 0.0 for b in pre)
    assert root.find("Output/logfile/node_data").text == mesh.find("NodeSet[@name='base']").text
    assert len(base_bcs(proot)) == (1 if base == "bonded" else 3) and mesh.find("NodeSet[@name='punch']") is None
    canon = lambda m: (m.attrib, [(c.tag, c.text) for c in m])  # noqa: E731
    assert canon(root.find("Material/material[@id='1']")) == canon(proot.find("Material/material"))


@pytest.mark.parametrize("shape", ["sphere", "cone"])
def test_indenter_cap_is_a_closed_oriented_cap_with_the_analytic_area(shape):
    """The cap mesh: positive facets, every interior edge shared by two facets with opposite
    orientation (consistently oriented manifold), the boundary is the outer ring, the area
    within 1 % of the analytic spherical cap / cone lateral area."""
    card = _card()
    kw = dict(radius=1.0e-3) if shape == "sphere" else dict(half_angle=math.radians(60.0))
    spec = indentation_specimen(card, indenter=shape, depth=2.0e-5, size=SIZE, cells=CELLS, **kw)
    P, T, r_cap = febio_indenter_cap(spec, H, spacing=2.0e-5)
    assert T.min() == 0 and T.max() == len(P) - 1 and len(np.unique(T)) == len(P)
    area = 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)
    assert np.all(area > 0)
    directed = Counter((int(a), int(b)) for t in T for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])))
    assert max(directed.values()) == 1  # no edge traversed twice in the same direction: consistent orientation
    undirected = Counter(tuple(sorted(e)) for e in directed)
    boundary = {v for e, c in undirected.items() if c == 1 for v in e}
    assert set(undirected.values()) <= {1, 2}
    rho = np.hypot(P[:, 0], P[:, 1])
    assert boundary == set(np.flatnonzero(np.isclose(rho, r_cap, rtol=1e-12)))
    if shape == "sphere":
        R = spec.radius
        np.testing.assert_allclose(np.linalg.norm(P - [0, 0, H + R], axis=1), R, rtol=1e-12)
        exact = 2 * math.pi * R * R * (1 - math.sqrt(1 - (r_cap / R) ** 2))
        assert r_cap == pytest.approx(3 * math.sqrt(R * spec.depth), rel=1e-12)
    else:
        th = spec.half_angle
        np.testing.assert_allclose(P[:, 2], H + rho / math.tan(th), rtol=1e-13)
        exact = math.pi * r_cap * r_cap / math.sin(th)
        assert r_cap == pytest.approx(3 * spec.depth * math.tan(th)) and r_cap > 2 * spec.contact_radius()
    assert area.sum() == pytest.approx(exact, rel=1e-2)


def test_febio_cone_specimen_and_hemisphere_cap(tmp_path):
    card = _card(model="fem_linear")
    th = math.radians(70.0)
    cone = indentation_specimen(card, indenter="cone", half_angle=th, depth=1.0e-4, size=SIZE, cells=CELLS)
    root = _parse(export(card, "febio", tmp_path / "cone.feb", indentation=cone))
    nodes = _check_ids(root)
    cap = np.array([nodes[int(n.get("id"))] for n in root.find("Mesh/Nodes[@name='indenter']")])
    rho = np.hypot(cap[:, 0], cap[:, 1])
    np.testing.assert_allclose(cap[:, 2], H + rho / math.tan(th), rtol=1e-13)
    assert rho.max() >= 2 * cone.contact_radius()
    com = [float(v) for v in root.find(f"Material/material[@name='{FEBIO_INDENTER_MATERIAL}']/center_of_mass").text.split(",")]
    assert com == pytest.approx([0.0, 0.0, H])
    assert root.find("Material/material[@id='1']").get("type") == "isotropic elastic"
    # a deep sphere (3 sqrt(R d) > R): the cap is the hemisphere
    deep = indentation_specimen(card, indenter="sphere", radius=1.0e-3, depth=2.0e-4, size=SIZE, cells=CELLS)
    P, T, r_cap = febio_indenter_cap(deep, H, spacing=1e-3)
    assert r_cap == 1.0e-3 and P[:, 2].max() == pytest.approx(H + 1.0e-3)


def test_febio_indentation_refusal_is_one_line(tmp_path):
    card = _card(name=FEBIO_INDENTER_MATERIAL)
    spec = indentation_specimen(card, indenter="sphere", radius=1.0e-3, depth=5.0e-5, size=SIZE, cells=(2, 2, 2))
    with pytest.raises(ExportError) as e:
        export(card, "febio", tmp_path / "x.feb", indentation=spec)
    assert "\n" not in str(e.value) and "rigid material name" in str(e.value)
    assert not (tmp_path / "x.feb").exists()
    with pytest.raises(ExportError, match="spacing"):
        febio_indenter_cap(spec, H, spacing=0.0)
    with pytest.raises(ExportError, match="sphere and cone only"):
        febio_indenter_cap(indentation_specimen(card, indenter="flat_punch", radius=1e-3, depth=5e-5, size=SIZE, cells=(2, 2, 2)),
                           H, spacing=1e-3)
