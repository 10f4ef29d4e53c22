"""Material card and simulator writers (difftissue.export)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from difftissue.errors import ExportError, OutputExistsError
from difftissue.export import (
    MaterialCard,
    abaqus_material,
    abaqus_name,
    abaqus_number,
    card_from_fit_json,
    export,
    read_card,
    write_abaqus,
    write_card,
    write_febio,
    write_sofa,
    write_vtu,
    write_xpbd,
)
from difftissue.mesh import block

E, NU = 12_000.0, 0.45


def make_card(model="fem_neo_hookean", name="skin", **extra):
    params = {
        "youngs_modulus": {"value": E, "unit": "Pa", "standard_error": 250.0},
        "poisson_ratio": {"value": NU, "unit": "1", "standard_error": None},
        "density": {"value": 1100.0, "unit": "kg/m^3", "standard_error": None},
    }
    for k, v in extra.items():
        params[k] = {"value": v, "unit": "1", "standard_error": None}
    return MaterialCard(model=model, parameters=params, name=name,
                        provenance={"scenarios": ["afm"], "data_files": [{"path": "a.csv", "sha256": "0" * 64}]})


@pytest.fixture(scope="module")
def mesh():
    return block((0.01, 0.01, 0.005), (2, 2, 1))


# ------------------------------------------------------------------ card
def test_card_round_trip(tmp_path):
    card = make_card()
    path = write_card(card, tmp_path / "material.json")
    back = read_card(path)
    assert back == card
    doc = json.loads(path.read_text())
    assert doc["card_version"] == 1 and doc["model"] == "fem_neo_hookean" and "neo-Hookean" in doc["energy"]
    assert doc["parameters"]["youngs_modulus"] == {"value": E, "unit": "Pa", "standard_error": 250.0}
    assert back.shear_modulus == pytest.approx(E / (2 * (1 + NU)))
    assert back.cubic_coefficient == 0.0 and back.pre_stretch == 1.0


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["parameters"].pop("youngs_modulus"), "parameters.youngs_modulus"),
        (lambda d: d["parameters"]["youngs_modulus"].update(value=0.0), "parameters.youngs_modulus"),
        (lambda d: d["parameters"]["youngs_modulus"].update(value=-5.0), "parameters.youngs_modulus"),
        (lambda d: d["parameters"]["poisson_ratio"].update(value=0.5), "parameters.poisson_ratio"),
        (lambda d: d["parameters"]["poisson_ratio"].update(value=-1.0), "parameters.poisson_ratio"),
        (lambda d: d["parameters"]["poisson_ratio"].update(value="NaN"), "parameters.poisson_ratio"),
        (lambda d: d["parameters"]["density"].update(value=None), "parameters.density"),
        (lambda d: d["parameters"]["youngs_modulus"].update(unit="kPa"), "parameters.youngs_modulus.unit"),
        (lambda d: d.update(card_version=2), "card_version"),
        (lambda d: d.pop("card_version"), "card_version"),
        (lambda d: d.update(model=""), "model"),
    ],
)
def test_validation_names_the_field(tmp_path, mutate, field):
    doc = make_card().to_dict()
    mutate(doc)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(ExportError, match=re.escape(field)):
        read_card(p)


def test_nan_in_json_is_refused(tmp_path):
    p = tmp_path / "nan.json"
    p.write_text(make_card().to_json().replace("12000.0", "NaN"))
    with pytest.raises(ExportError, match="youngs_modulus"):
        read_card(p)


def test_card_from_fit_json():
    doc = {
        "schema": "difftissue-fit/1",
        "parameters": {"youngs_modulus": {"value": 3000.0, "unit": "Pa", "standard_error": 30.0}},
        "fixed_parameters": {"poisson_ratio": {"value": 0.4, "unit": "1"}, "density": {"value": 1000.0, "unit": "kg/m^3"}},
        "model": "springs_volume",
        "scenarios": [{"name": "compression"}],
        "data_files": [{"path": "c.csv", "sha256": "ab"}],
        "versions": {"difftissue": "0.1.0"},
        "created": "2026-01-01T00:00:00+0000",
    }
    card = MaterialCard.from_json(json.dumps(doc))
    assert card == card_from_fit_json(doc)
    assert card.model == "springs_volume" and card.youngs_modulus == 3000.0 and card.poisson_ratio == 0.4
    assert card.parameters["youngs_modulus"]["standard_error"] == 30.0
    assert card.provenance["scenarios"] == ["compression"]
    with pytest.raises(ExportError, match="model"):
        card_from_fit_json({**doc, "model": None})


# ------------------------------------------------------------------ FEBio
def test_febio_material_and_specimen(tmp_path, mesh):
    card = make_card()
    root = ET.parse(write_febio(card, tmp_path / "m.feb")).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    mat = root.find("Material/material")
    assert mat.get("type") == "neo-Hookean" and mat.get("name") == "skin" and mat.get("id") == "1"
    assert float(mat.find("E").text) == E and float(mat.find("v").text) == NU and float(mat.find("density").text) == 1100.0

    lin = ET.parse(write_febio(make_card(model="fem_linear"), tmp_path / "l.feb")).getroot()
    assert lin.find("Material/material").get("type") == "isotropic elastic"

    full = ET.parse(write_febio(card, tmp_path / "s.feb", mesh=mesh, displacement=-5e-4)).getroot()
    assert len(full.findall("Mesh/Nodes/node")) == mesh.n_nodes
    elems = full.findall("Mesh/Elements/elem")
    assert full.find("Mesh/Elements").get("type") == "tet4" and len(elems) == mesh.n_tets
    assert [int(n) - 1 for n in elems[0].text.split(",")] == list(mesh.tets[0])
    assert full.find("MeshDomains/SolidDomain").get("mat") == "skin"
    bcs = {bc.get("type"): bc for bc in full.findall("Boundary/bc")}
    assert bcs["zero displacement"].get("node_set") == "base"
    assert float(bcs["prescribed displacement"].find("value").text) == -5e-4
    base = [int(i) - 1 for i in full.find("Mesh/NodeSet[@name='base']").text.split(",")]
    assert np.allclose(mesh.points[base, 2], 0.0) and len(base) == 9


# ------------------------------------------------------------------ SOFA
def test_sofa_conversions_both_ways(tmp_path, mesh):
    root = ET.parse(write_sofa(make_card(), tmp_path / "nh.scn")).getroot()
    ff = root.find(".//TetrahedronHyperelasticityFEMForceField")
    assert ff.get("materialName") == "NeoHookean"
    mu, lam = (float(v) for v in ff.get("ParameterSet").split())
    assert mu == pytest.approx(E / (2 * (1 + NU)), rel=1e-14)
    # back: E = mu (3 lambda + 2 mu) / (lambda + mu), nu = lambda / (2 (lambda + mu))
    assert mu * (3 * lam + 2 * mu) / (lam + mu) == pytest.approx(E, rel=1e-12)
    assert lam / (2 * (lam + mu)) == pytest.approx(NU, rel=1e-12)

    lin = ET.parse(write_sofa(make_card(model="fem_linear"), tmp_path / "lin.scn", mesh=mesh)).getroot()
    ff = lin.find(".//TetrahedronFEMForceField")
    assert float(ff.get("youngModulus")) == E and float(ff.get("poissonRatio")) == NU
    topo = lin.find(".//MeshTopology")
    assert len(topo.get("tetrahedra").split()) == 4 * mesh.n_tets
    assert len(lin.find(".//FixedProjectiveConstraint").get("indices").split()) == 9


def test_sofa_top_displacement(tmp_path, mesh):
    root = ET.parse(write_sofa(make_card(model="fem_linear"), tmp_path / "d.scn", mesh=mesh, displacement=-2e-4)).getroot()
    mv = root.find(".//LinearMovementProjectiveConstraint")
    top = np.flatnonzero(np.isclose(np.asarray(mesh.points)[:, 2], 0.005))
    assert sorted(int(i) for i in mv.get("indices").split()) == top.tolist()
    # held after t = 1: SOFA's constraint acts only before its last key time
    assert mv.get("keyTimes") == "0 1 1000000" and mv.get("relativeMovements") == "1"
    assert [float(v) for v in mv.get("movements").split()] == [0, 0, 0, 0, 0, -2e-4, 0, 0, -2e-4]
    assert float(root.get("dt")) == pytest.approx(0.1)
    # default: -10 % of the height
    root = ET.parse(write_sofa(make_card(model="fem_linear"), tmp_path / "d2.scn", mesh=mesh)).getroot()
    assert float(root.find(".//LinearMovementProjectiveConstraint").get("movements").split()[-1]) == pytest.approx(-0.0005)


def test_sofa_polynomial_springs_conversions_both_ways():
    from difftissue.export import sofa_polynomial_coefficients, springs_from_sofa_polynomial

    k, a, L0 = np.array([3.0, 5.0]), np.array([2e4, 0.0]), np.array([0.002, 0.0028])
    c = sofa_polynomial_coefficients(k, a, L0)
    np.testing.assert_allclose(c, [[3.0 * 0.002, 0.0, 2e4 * 0.002**3], [5.0 * 0.0028, 0.0, 0.0]], rtol=1e-15)
    # SOFA's force sigma(L) = a1 L + a3 L^3 at strain L = e / l0 equals k e + a e^3
    e = 1.7e-4
    L = e / L0
    np.testing.assert_allclose(c[:, 0] * L + c[:, 2] * L**3, k * e + a * e**3, rtol=1e-14)
    k2, a2 = springs_from_sofa_polynomial(c, L0)
    np.testing.assert_allclose(k2, k, rtol=1e-15)
    np.testing.assert_allclose(a2, a, rtol=1e-15)
    with pytest.raises(ExportError, match="a2"):
        springs_from_sofa_polynomial([[1.0, 0.5, 0.0]], [1.0])


def test_sofa_springs_split_both_ways():
    from difftissue.export import sofa_springs_split

    card = make_card(model="springs_volume")
    sp = sofa_springs_split(card, 0.5)
    mu, lam = card.shear_modulus, card.lame_lambda
    assert sp["lambda_f"] + 0.5 * mu == pytest.approx(lam, rel=1e-14)
    assert sp["mu_f"] + 0.5 * mu == pytest.approx(mu, rel=1e-14)
    Ef, nf = sp["youngs_modulus"], sp["poisson_ratio"]
    assert Ef / (2 * (1 + nf)) == pytest.approx(sp["mu_f"], rel=1e-12)
    assert Ef * nf / ((1 + nf) * (1 - 2 * nf)) == pytest.approx(sp["lambda_f"], rel=1e-12)
    with pytest.raises(ExportError, match="spring_fraction"):
        sofa_springs_split(card, 1.0)
    low = MaterialCard(model="springs_volume", parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": 0.1}})
    with pytest.raises(ExportError, match="negative lambda"):
        sofa_springs_split(low, 0.5)


def test_sofa_springs_scene(tmp_path):
    import jax
    import jax.numpy as jnp

    from difftissue.energies.springs import cubic_spring_energy
    from difftissue.export import sofa_springs_split
    from difftissue.models import make_model

    cube = block((0.01, 0.01, 0.01), (2, 2, 2))
    card = make_card(model="springs_volume", cubic_coefficient=2.0)
    path = write_sofa(card, tmp_path / "springs.scn", mesh=cube, law="springs")
    root = ET.parse(path).getroot()
    plugins = {e.get("name") for e in root.iter("RequiredPlugin")}
    assert {"Sofa.Component.SolidMechanics.Spring", "Sofa.Component.SolidMechanics.FEM.Elastic"} <= plugins
    ps = root.find(".//PolynomialSpringsForceField")
    assert ps.get("object1") == "@dofs" and ps.get("object2") == "@dofs"
    assert ps.get("compressible") == "1" and ps.get("computeZeroLength") == "1"
    model = make_model(cube, "springs_volume")
    i, j = (np.array(ps.get(k).split(), dtype=int) for k in ("firstObjectPoints", "secondObjectPoints"))
    np.testing.assert_array_equal(np.stack([i, j], 1), np.asarray(model.springs))
    deg = np.array(ps.get("polynomialDegree").split(), dtype=int)
    coeffs = np.array(ps.get("polynomialStiffness").split(), dtype=float).reshape(-1, 3)
    assert np.all(deg == 3) and len(deg) == len(i) == len(coeffs)
    k, a = (np.asarray(v) for v in model.spring_constants(card.material()))
    L0 = np.asarray(model.rest_lengths)
    np.testing.assert_allclose(coeffs[:, 0], 0.5 * k * L0, rtol=1e-14)
    np.testing.assert_allclose(coeffs[:, 2], a * L0**3, rtol=1e-14)
    fem = root.find(".//TetrahedronFEMForceField")
    sp = sofa_springs_split(card, 0.5)
    assert float(fem.get("youngModulus")) == pytest.approx(sp["youngs_modulus"]) and fem.get("method") == "large"
    assert "springs_volume split" in path.read_text()
    assert root.find(".//LinearMovementProjectiveConstraint") is not None

    # the represented energy, under homogeneous confined compression of one cube, against springs_volume
    one = block((0.01,) * 3, (1, 1, 1))
    m1 = make_model(one, "springs_volume")
    mat = make_card(model="springs_volume").material()
    k1, a1 = m1.spring_constants(mat)
    X = jnp.asarray(one.points)
    V = 1e-6

    def w_sofa(t):  # springs at half mu + corotational linear FEM (no rotation under diagonal F)
        F = jnp.diag(jnp.array([1.0, 1.0, 1.0 + t]))
        x = X @ F.T
        s = m1.springs
        ws = jnp.sum(cubic_spring_energy(x[s[:, 0]], x[s[:, 1]], m1.rest_lengths, 0.5 * k1, a1))
        e = F - jnp.eye(3)
        return ws + V * (sp["mu_f"] * jnp.sum(e * e) + sp["lambda_f"] / 2 * jnp.trace(e) ** 2)

    def w_sv(t):
        return m1.energy(X @ jnp.diag(jnp.array([1.0, 1.0, 1.0 + t])).T, mat)

    for t, tol in ((1e-5, 1e-4), (-0.1, 0.01), (0.1, 0.01)):  # measured: 2e-6, 0.73 %, 0.64 %
        s1, s2 = jax.grad(w_sv)(t), jax.grad(w_sofa)(t)
        assert abs(s2 - s1) <= tol * abs(s1)
    with pytest.raises(ExportError, match="specimen mesh"):
        write_sofa(card, tmp_path / "x.scn", law="springs")
    with pytest.raises(ExportError, match="law"):
        write_febio(card, tmp_path / "x.feb", law="springs")


# ------------------------------------------------------------------ Abaqus
def _inp_keywords(text):
    return [ln.split(",")[0].strip().upper() for ln in text.splitlines() if ln.startswith("*") and not ln.startswith("**")]


def test_abaqus_conversions_both_ways(tmp_path):
    text = write_abaqus(make_card(), tmp_path / "m.inp").read_text()
    assert _inp_keywords(text) == ["*MATERIAL", "*HYPERELASTIC", "*DENSITY"]
    lines = text.splitlines()
    i = lines.index("*HYPERELASTIC, NEO HOOKE")
    c10, d1 = (float(v) for v in lines[i + 1].split(","))
    mu, K = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))
    assert c10 == pytest.approx(mu / 2, rel=1e-14) and d1 == pytest.approx(2 / K, rel=1e-14)
    mu_b, K_b = 2 * c10, 2 / d1
    assert 9 * K_b * mu_b / (3 * K_b + mu_b) == pytest.approx(E, rel=1e-12)
    assert (3 * K_b - 2 * mu_b) / (2 * (3 * K_b + mu_b)) == pytest.approx(NU, rel=1e-12)
    assert float(lines[lines.index("*DENSITY") + 1]) == 1100.0

    lin = abaqus_material(make_card(model="fem_linear"))
    j = lin.index("*ELASTIC")
    assert [float(v) for v in lin[j + 1].split(",")] == [E, NU]


def test_abaqus_specimen(tmp_path, mesh):
    text = write_abaqus(make_card(), tmp_path / "s.inp", mesh=mesh).read_text()
    kws = _inp_keywords(text)
    for kw in ("*HEADING", "*NODE", "*ELEMENT", "*NSET", "*SOLID SECTION", "*MATERIAL", "*STEP", "*STATIC", "*BOUNDARY", "*END STEP"):
        assert kw in kws
    assert "*ELEMENT, TYPE=C3D4, ELSET=TISSUE" in text and "*SOLID SECTION, ELSET=TISSUE, MATERIAL=skin" in text
    # every data line of *NODE has an id and 3 coordinates
    lines = text.splitlines()
    k = lines.index("*NODE")
    assert all(len(lines[k + 1 + n].split(",")) == 4 for n in range(mesh.n_nodes))
    assert "TOP, 3, 3, -0.0005" in text


def _random_doubles(n, seed=0):
    """Finite doubles of both signs: n from raw bit patterns, n spread over the whole exponent
    range (subnormals to 1.8e308), the same n rounded to 7 digits, and edge values."""
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 0x7FF0000000000000, size=n, dtype=np.int64).view(np.float64) * rng.choice([-1.0, 1.0], size=n)
    logs = rng.uniform(-323.0, 308.0, size=n)
    spread = rng.choice([-1.0, 1.0], size=n) * 10.0 ** (logs - 1) * rng.uniform(1.0, 10.0, size=n)
    edges = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -1.7976931348623157e308,
             7.575610012003474e-06, -0.0035355339059327377, 1 / 3, -2 / 3, 0.1, 12_000.0, 0.42, 1e-5]
    short = np.array([float(f"{v:.6e}") for v in spread])  # 7 significant digits: always exact in 20 characters
    x = np.concatenate([bits, spread, short, edges])
    return x[np.isfinite(x)]


def test_abaqus_number_fits_20_characters_and_round_trips():
    """<= 20 characters always; exact when the shortest round-trip digits fit, else at most
    5e-13 relative (5e-15 for 1e-9 <= |x| < 1e10, the docstring's bounds)."""
    exact = rounded = 0
    x = _random_doubles(20_000)
    for v in x:
        s = abaqus_number(v)
        assert len(s) <= 20, (v, s)
        back = float(s)
        if len(repr(float(v))) <= 20:  # repr fits, so must be reproduced exactly
            assert back == v, (v, s)
        if back == v:
            exact += 1
            continue
        rounded += 1
        rel = abs(back - v) / abs(v)
        assert rel <= 5e-13, (v, s, rel)
        if 1e-9 <= abs(v) < 1e10:
            assert rel <= 5e-15, (v, s, rel)
    assert exact > 0.25 * len(x) and rounded > 0.25 * len(x)  # both branches exercised
    # the reported failure: 21 characters of repr, exact in 20 with a one-digit exponent
    assert abaqus_number(7.575610012003474e-06) == "7.575610012003474e-6"
    assert float(abaqus_number(0.0035355339059327377)) == 0.0035355339059327377  # ".0035355339059327377"
    assert abaqus_number(0.42) == "0.42" and abaqus_number(-0.0) == "-0.0"
    for bad in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(ExportError, match="non-finite"):
            abaqus_number(bad)


def _numeric_fields(text):
    """Every comma-separated data field of a deck that parses as a number."""
    out = []
    for ln in text.splitlines():
        if ln.startswith("*"):
            continue
        for f in ln.split(","):
            try:
                float(f)
            except ValueError:
                continue
            out.append(f.strip())
    return out


def test_abaqus_decks_have_no_number_over_20_characters(tmp_path):
    """A mesh whose coordinates and material need > 20 characters as repr: every field fits."""
    from difftissue.mesh import TetMesh

    m = block((1.0, 1.0, 1.0), (1, 1, 1))
    pts = np.asarray(m.points) * 7.575610012003474e-03 - 1.234567890123457e-4  # long negative coordinates
    card = MaterialCard(model="fem_neo_hookean", name="eco", parameters={
        "youngs_modulus": {"value": 7.575610012003474e+04 / 3}, "poisson_ratio": {"value": 0.4999 / 1.0000001},
        "density": {"value": 1070.123456789012}})
    text = write_abaqus(card, tmp_path / "long.inp", mesh=TetMesh(pts, np.asarray(m.tets))).read_text()
    fields = _numeric_fields(text)
    assert any(len(repr(float(f))) > 20 for f in fields)  # the case the formatter exists for
    assert max(len(f) for f in fields) <= 20


def test_hostile_names_are_escaped(tmp_path, mesh):
    card = make_card(name='a<&">b -- x')
    for writer, path in ((write_febio, "h.feb"), (write_sofa, "h.scn")):
        p = writer(card, tmp_path / path, mesh=mesh)
        root = ET.parse(p).getroot()  # well-formed
        names = [el.get("name") for el in root.iter() if el.get("name") == card.name]
        assert names, path
        assert '<&">' not in p.read_text()
    inp = write_abaqus(card, tmp_path / "h.inp").read_text()
    assert "*MATERIAL, NAME=a____b_--_x" in inp
    assert abaqus_name("1abc") == "M_1abc" and abaqus_name("x" * 200) == "x" * 80
    assert re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,79}", abaqus_name("ünï cødé\n*STEP"))
    # a newline in a name cannot start a keyword line in the .inp
    inj = write_abaqus(make_card(name="x\n*STEP"), tmp_path / "inj.inp").read_text()
    assert "*STEP" not in _inp_keywords(inj)


# ------------------------------------------------------------------ approximations
@pytest.mark.parametrize("writer, suffix", [(write_febio, "feb"), (write_sofa, "scn"), (write_abaqus, "inp")])
def test_cubic_refused_or_approximated(tmp_path, writer, suffix):
    card = make_card(model="fem_neo_hookean", cubic_coefficient=2.0)
    with pytest.raises(ExportError, match="cubic_coefficient.*approximate"):
        writer(card, tmp_path / f"c.{suffix}")
    assert not (tmp_path / f"c.{suffix}").exists()
    text = writer(card, tmp_path / f"c.{suffix}", approximate=True).read_text()
    # fem_neo_hookean does not use b: the measured error of dropping it is zero, with its sign
    assert "APPROXIMATION: cubic_coefficient b = 2 dropped" in text and "+0 % at 10 %" in text


def test_pre_stretch_refused_or_approximated(tmp_path):
    card = make_card(pre_stretch=1.1)
    with pytest.raises(ExportError, match="pre_stretch"):
        write_abaqus(card, tmp_path / "p.inp")
    assert "pre_stretch = 1.1 dropped" in write_abaqus(card, tmp_path / "p.inp", approximate=True).read_text()
    with pytest.raises(ExportError, match="pre_stretch"):
        write_sofa(card, tmp_path / "p.scn")


def test_febio_prestrain(tmp_path, mesh):
    from difftissue.export import febio_prestrain_gradient, pre_stretch_from_febio_gradient
    from difftissue.materials import equibiaxial_pre_stress

    card = make_card(pre_stretch=1.08)
    root = ET.parse(write_febio(card, tmp_path / "pre.feb", mesh=mesh)).getroot()
    mats = root.findall("./Material/material")
    assert len(mats) == 1 and mats[0].get("type") == "prestrain elastic" and mats[0].get("name") == "skin"
    el = mats[0].find("elastic")
    assert el.get("type") == "neo-Hookean" and float(el.find("E").text) == E and float(el.find("v").text) == NU
    assert float(mats[0].find("density").text) == 1100.0
    pre = mats[0].find("prestrain")
    assert pre.get("type") == "prestrain gradient" and float(pre.find("ramp").text) == 1.0
    F0 = np.array(pre.find("F0").text.split(","), dtype=float).reshape(3, 3)
    np.testing.assert_array_equal(F0, np.diag([1.08, 1.08, 1.0]))
    # both ways
    assert pre_stretch_from_febio_gradient(pre.find("F0").text) == 1.08
    assert pre_stretch_from_febio_gradient(febio_prestrain_gradient(0.97)) == 0.97
    with pytest.raises(ExportError, match="equibiaxial"):
        pre_stretch_from_febio_gradient("1.1,0,0,0,1.2,0,0,0,1")
    with pytest.raises(ExportError, match="9 comma"):
        pre_stretch_from_febio_gradient("1,2")
    # the comment quotes the card's pre-stress sigma0 = E (lambda0 - 1) / (1 - nu)
    sigma0 = float(equibiaxial_pre_stress(card.material()))
    assert f"{sigma0:.6g} Pa" in (tmp_path / "pre.feb").read_text()
    # linear law: the isotropic elastic material is wrapped the same way; material alone too
    lin = ET.parse(write_febio(card, tmp_path / "pre_lin.feb", law="linear")).getroot()
    assert lin.find("./Material/material/elastic").get("type") == "isotropic elastic"
    # cubic stiffening is still refused
    with pytest.raises(ExportError, match="cubic_coefficient"):
        write_febio(make_card(pre_stretch=1.08, cubic_coefficient=1.0), tmp_path / "c.feb")


# ------------------------------------------------------------------ XPBD and VTU
def test_xpbd(tmp_path, mesh):
    card = make_card()
    doc = json.loads(write_xpbd(card, tmp_path / "x.json", dt=1 / 60, iterations=10, mesh=mesh, calibrate=False).read_text())
    mu, lam = card.shear_modulus, card.lame_lambda
    assert doc["setting"] == {"dt": 1 / 60, "iterations": 10, "substeps": 1, "substep": 1 / 60}
    assert doc["per_unit_volume"]["deviatoric_compliance"] == pytest.approx(1 / mu)
    assert doc["per_unit_volume"]["hydrostatic_compliance"] == pytest.approx(1 / (lam + mu))
    assert doc["gamma"] == pytest.approx(1 + mu / (lam + mu))
    v0 = np.asarray(doc["per_tet"]["rest_volume"])
    assert v0.sum() == pytest.approx(0.01 * 0.01 * 0.005)
    assert np.allclose(doc["per_tet"]["hydrostatic_alpha_tilde"], 1 / ((lam + mu) * v0) * 60**2)
    spec = doc["specimen"]
    assert len(spec["positions"]) == mesh.n_nodes and len(spec["tets"]) == mesh.n_tets
    assert sum(spec["masses"]) == pytest.approx(1100.0 * 0.01 * 0.01 * 0.005)
    assert len(spec["fixed"]) == 9 and len(spec["moved"]) == 9 and spec["displacement"][2] == pytest.approx(-0.0005)
    assert "specimen" not in json.loads(write_xpbd(card, tmp_path / "alone.json", dt=1 / 60, iterations=10).read_text())
    with pytest.raises(ExportError, match="dt"):
        write_xpbd(card, tmp_path / "y.json", dt=0.0, iterations=10)
    with pytest.raises(ExportError, match="iterations"):
        write_xpbd(card, tmp_path / "y.json", dt=0.01, iterations=0)


def test_vtu_cell_fields(tmp_path, mesh):
    import meshio

    card = make_card()
    m = meshio.read(write_vtu(card, mesh, tmp_path / "m.vtu"))
    cd = {k: np.concatenate(v) for k, v in m.cell_data.items()}
    assert np.all(cd["youngs_modulus"] == E) and np.all(cd["poisson_ratio"] == NU)
    assert np.allclose(cd["shear_modulus"], card.shear_modulus) and cd["density"].shape == (mesh.n_tets,)
    z = np.asarray(mesh.points)[:, 2]
    np.testing.assert_array_equal(m.point_data["boundary"], np.where(np.isclose(z, 0), 1.0, np.where(np.isclose(z, 0.005), 2.0, 0.0)))
    np.testing.assert_allclose(m.point_data["prescribed_displacement"][:, 2], np.where(np.isclose(z, 0.005), -0.0005, 0.0))


def test_refuses_to_overwrite(tmp_path, mesh):
    card = make_card()
    for to, name in (("febio", "o.feb"), ("sofa", "o.scn"), ("abaqus", "o.inp"), ("vtu", "o.vtu")):
        p = export(card, to, tmp_path / name, mesh=mesh)
        before = p.read_bytes()
        with pytest.raises(OutputExistsError):
            export(card, to, p, mesh=mesh)
        assert p.read_bytes() == before
        export(card, to, p, mesh=mesh, force=True)
    with pytest.raises(OutputExistsError):
        write_card(card, tmp_path / "o.feb")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ------------------------------------------------------------------ CLI
def _cli(*args, cwd, capsys, monkeypatch):
    """``difftissue ARGS`` run in this process (``main``, as the console script calls it; that
    ``python -m difftissue`` reaches ``main`` is tests/test_cli.py's): exit status, stdout, stderr.
    In-process saves a Python + JAX start and the export's compilations per call."""
    from difftissue.cli import main

    monkeypatch.chdir(cwd)
    capsys.readouterr()
    try:
        code = main(list(args))
    except SystemExit as e:  # argparse's usage errors
        code = e.code
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["difftissue", *args], code, out, err)


def test_cli_export(tmp_path, capsys, monkeypatch):
    def _cli_here(*args):
        return _cli(*args, cwd=tmp_path, capsys=capsys, monkeypatch=monkeypatch)

    write_card(make_card(), tmp_path / "material.json")
    r = _cli_here("export", "material.json", "--to", "abaqus", "--out", "m.inp", "--specimen", "block:10,10,5:2,2,1")
    assert r.returncode == 0, r.stderr
    assert "*HYPERELASTIC, NEO HOOKE" in (tmp_path / "m.inp").read_text()
    r = _cli_here("export", "material.json", "--to", "xpbd", "--out", "x.json", "--dt", "0.01", "--iterations", "10")
    assert r.returncode == 0, r.stderr and (tmp_path / "x.json").is_file()
    # refusal to overwrite, then bad card: one line, exit 1
    r = _cli_here("export", "material.json", "--to", "abaqus", "--out", "m.inp")
    assert r.returncode == 1 and "exists" in r.stderr
    doc = make_card().to_dict()
    doc["parameters"]["poisson_ratio"]["value"] = 0.7
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    r = _cli_here("export", "bad.json", "--to", "febio", "--out", "b.feb")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "parameters.poisson_ratio" in r.stderr
    assert not (tmp_path / "b.feb").exists()
    r = _cli_here("export", "material.json", "--to", "vtu", "--out", "m.vtu")
    assert r.returncode == 2 and "--specimen" in r.stderr


@pytest.mark.parametrize("model, law", [("hertz", "linear"), ("fem_linear", "linear"), ("springs_volume", "neo_hookean"),
                                        ("hertz; springs_volume", "neo_hookean"), ("stable_neo_hookean", "neo_hookean")])
def test_default_law_follows_the_model(model, law):
    card = make_card(model=model)
    assert card.energy  # every card states its energy
    kw = abaqus_material(card, approximate="springs_volume" in model)  # lattice values: tests/test_export_mismatch.py
    assert ("*HYPERELASTIC, NEO HOOKE" in kw) == (law == "neo_hookean") and ("*ELASTIC" in kw) == (law == "linear")
