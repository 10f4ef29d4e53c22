"""Exported Abaqus decks run in CalculiX (issue 16, docs/export.md "Abaqus decks in CalculiX").

Each test writes a deck with the exporter, runs it in ``ccx`` unchanged (tests/calculix.py adds
only a displacement print) and compares with difftissue's own solution of the same problem:

* (a) the material card with a block specimen (:func:`abaqus_model`: base clamped, top moved
  down 10 %), linear;
* (b) a fitted compression block (:func:`abaqus_fitted_model`), linear, bonded and frictionless
  platens;
* (c) flat-punch indentation (:func:`abaqus_indentation_model`), linear, bonded punch on a
  bonded base and frictionless punch on a sliding base;
* (d) the neo-Hookean variant of (b) (frictionless, 10 %) and of (a).

* (e) sphere and cone indentation (a meshed rigid indenter in node-to-surface penalty contact),
  linear and neo-Hookean, against difftissue's penalty contact with the analytic indenter at
  each depth step (2 %).

Linear: same P1 tetrahedra and energy, so the reaction and the displacement field agree to
CalculiX's 7 printed digits (tolerance 1e-6 relative). Neo-Hookean: CalculiX's ``NEO HOOKE`` is
``C10 (I1bar - 3) + (J - 1)^2 / D1``, difftissue's ``fem_neo_hookean`` is
``mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2``: equal at small strain, not at 10 %. So the
same problem is difftissue's static solver with CalculiX's energy (:class:`AbaqusNeoHookeModel`,
tolerance 1e-4; the issue asks 1 %), and the frictionless case is also checked against that
energy's homogeneous uniaxial solution; the difference to ``fem_neo_hookean`` is reported and
checked to be the two energies' analytic difference (1.43 % in force at 10 %).

Material values with more than 20 characters as ``repr`` (E = 12345.678901234567 Pa,
nu = 0.4234567890123457, D1 = 2/K) make the decks fail without abaqus_number.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from calculix import ccx_or_skip, parse_dat, run_deck
from scipy.optimize import brentq

from difftissue.boundary import BoundaryConditions
from difftissue.export import MaterialCard, abaqus_number, export, write_abaqus
from difftissue.export.fitted import fitted_specimen
from difftissue.export.specimens import indentation_sets, indentation_specimen
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.energies.neo_hookean import deformation_gradient, det3
from difftissue.models import ElementTerm, FEMModel, make_model
from difftissue.scenarios import Compression, Indentation, cylinder
from difftissue.solvers.static import solve_static

E, NU = 12345.678901234567, 0.4234567890123457  # Pa, 1: repr 18 characters, D1 = 2/K needs 21
MM = 1e-3
LINEAR_TOL = 1e-6  # relative: CalculiX prints 7 significant digits (5e-7)
NEO_TOL = 1e-4  # relative, same energy (asked: 1 %); measured ~1e-7, left for the Newton tolerance


def _card(model):
    return MaterialCard(model=model, name=f"ccx_{model}",
                        parameters={"youngs_modulus": {"value": E}, "poisson_ratio": {"value": NU}})


def _rel_u(u_ccx, u_ours):
    """max |u_ccx - u_ours| / max |u_ours| over all node components."""
    return float(np.abs(u_ccx - u_ours).max() / np.abs(u_ours).max())


def _report(case, du, df):
    print(f"\nCALCULIX {case}: max|du|/max|u| = {du:.2e}, reaction rel. diff = {df:.2e}")


def test_absent_ccx_skips_locally_and_fails_in_ci(monkeypatch, tmp_path):
    """No ccx on PATH: a skip with the reason outside CI, a failure when CI=true."""
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="calculix-ccx"):
        ccx_or_skip()
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI=true"):
        ccx_or_skip()


def test_long_numbers_need_the_formatter():
    """The chosen material is one that the old repr writer broke (a field > 20 characters)."""
    K = E / (3 * (1 - 2 * NU))
    assert len(repr(2 / K)) > 20 and len(abaqus_number(2 / K)) <= 20


# ---------------------------------------------- CalculiX's neo-Hookean energy in difftissue
def abaqus_neo_hooke_density(F, mu, K):
    """Abaqus / CalculiX ``NEO HOOKE`` density [Pa]: ``C10 (I1bar - 3) + (J - 1)^2 / D1`` with
    ``C10 = mu / 2``, ``D1 = 2 / K`` (abaqus_material's conversion), ``I1bar = J^(-2/3) tr(F^T F)``."""
    J = det3(F)
    i1bar = J ** (-2.0 / 3.0) * jnp.sum(F * F, axis=(-2, -1))
    return 0.5 * mu * (i1bar - 3.0) + 0.5 * K * (J - 1.0) ** 2


class AbaqusNeoHookeModel(FEMModel):
    """difftissue's FEM on the same P1 tets with CalculiX's energy (for the mesh's one region;
    mu and K from the module's E, NU): the same problem as the exported neo-Hookean deck."""

    def __init__(self, mesh):
        super().__init__(mesh, "fem_neo_hookean")

    def terms(self, material):
        mu, K = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))
        fn = lambda x, Dm_inv, V0: V0 * abaqus_neo_hooke_density(deformation_gradient(x, Dm_inv), mu, K)  # noqa: E731
        return (ElementTerm("tets", self.tets, fn, (jnp.asarray(self.tet_Dm_inv), jnp.asarray(self.tet_volumes))),)


def _model(mesh, model):
    """difftissue's model of the exported law: fem_linear, or CalculiX's neo-Hookean energy."""
    return make_model(mesh, "fem_linear") if model == "fem_linear" else AbaqusNeoHookeModel(mesh)


# -------------------------------------------------------------- (a) card + block specimen
def _block_solution(mesh, model, d):
    """difftissue's static solution of abaqus_model's specimen: base clamped, top u_z = d."""
    p = np.asarray(mesh.points)
    base, top = np.isclose(p[:, 2], p[:, 2].min()), np.isclose(p[:, 2], p[:, 2].max())
    fixed = np.zeros(p.shape, dtype=bool)
    disp = np.zeros(p.shape)
    fixed[base] = True
    fixed[top, 2] = True
    disp[top, 2] = d
    bc = BoundaryConditions(fixed, disp, np.zeros_like(disp))
    sol = solve_static(_model(mesh, model), Material(E, NU), bc)
    fem = None if model == "fem_linear" else solve_static(make_model(mesh, model), Material(E, NU), bc)
    fem = None if fem is None else (np.asarray(fem.displacement), float(np.asarray(fem.reaction)[top, 2].sum()))
    return np.asarray(sol.displacement), float(np.asarray(sol.reaction)[top, 2].sum()), fem


@pytest.mark.parametrize("model", ["fem_linear", "fem_neo_hookean"])
def test_card_block_specimen(model, tmp_path):
    """(a) / (d): write_abaqus(card, mesh=block) run in CalculiX = difftissue's solution."""
    mesh = block((10 * MM, 10 * MM, 5 * MM), (2, 2, 2))
    deck = write_abaqus(_card(model), tmp_path / "block.inp", mesh=mesh)
    assert "BASE, 1, 3" in deck.read_text()
    run = run_deck(deck, tmp_path / "ccx")
    u, f, fem = _block_solution(mesh, model, -0.1 * 5 * MM)
    f_ccx = run.totals["TOP"][2]
    du, df = _rel_u(run.displacement, u), abs(f_ccx - f) / abs(f)
    _report(f"card block {model}", du, df)
    if fem is not None:  # the model-form difference at 10 %, bonded: measured 1.3 % of max |u|
        gap_u, gap_f = _rel_u(run.displacement, fem[0]), abs(f_ccx - fem[1]) / abs(fem[1])
        print(f"CALCULIX card block vs fem_neo_hookean: max|du|/max|u| = {gap_u:.2e}, reaction {gap_f:.2e}")
        assert 1e-3 < gap_u < 0.03 and gap_f < 0.01
    assert f < 0 and abs(run.totals["TOP"][:2]).max() <= 1e-9 * abs(f)  # compressive, no net shear
    tol = LINEAR_TOL if model == "fem_linear" else NEO_TOL
    assert du <= tol and df <= tol


# ---------------------------------------------------------- (b) fitted compression block
def _compression(model, bonded, strains=(0.05, 0.1), shape="block"):
    mesh = block((10 * MM, 10 * MM, 5 * MM), (2, 2, 2)) if shape == "block" else cylinder(10 * MM, 5 * MM, 1, 2)
    return Compression(mesh, list(strains), model=model, bonded=bonded, measure="engineering", name=f"c_{model}_{bonded}")


def _run_compression(sc, model, tmp_path):
    """The fitted deck run in CalculiX; difftissue's solution of the specimen's boundary
    conditions with the exported law's energy (:func:`_model`); Compression.solve's last
    displacement and top force [N, compressive positive] (the fitted model's prediction)."""
    spec = fitted_specimen(sc)
    deck = export(_card(model), "abaqus", tmp_path / "compression.inp", fitted=spec)
    run = run_deck(deck, tmp_path / "ccx")
    bc = BoundaryConditions(spec.fixed, spec.prescribed, np.zeros(spec.prescribed.shape))
    sol = solve_static(_model(spec.mesh(), model), Material(E, NU), bc)
    react = np.flatnonzero(spec.reaction[:, 2])
    stress, us = sc.solve(_card(model).material())
    return run, np.asarray(sol.displacement), -float(np.asarray(sol.reaction)[react, 2].sum()), np.asarray(us)[-1], \
        float(np.asarray(stress)[-1]) * sc.area


@pytest.mark.parametrize("shape", ["block", "cylinder"])
@pytest.mark.parametrize("bonded", [True, False], ids=["bonded", "frictionless"])
def test_fitted_compression_linear(bonded, shape, tmp_path):
    """(b): the fitted compression deck (REACTION = the top face) of the block and of the
    cylinder (10 mm diameter, 5 mm high: ``cylinder(10 mm, 5 mm, 1, 2)``) = difftissue's
    solution, which is Compression.solve's (the fit's prediction)."""
    sc = _compression("fem_linear", bonded, shape=shape)
    run, u, force, u_sc, force_sc = _run_compression(sc, "fem_linear", tmp_path)
    assert _rel_u(u, u_sc) <= 1e-10 and force == pytest.approx(force_sc, rel=1e-10)
    f_ccx = -run.totals["REACTION"][2]
    du, df = _rel_u(run.displacement, u), abs(f_ccx - force) / force
    _report(f"fitted compression linear {shape} {'bonded' if bonded else 'frictionless'}", du, df)
    if not bonded:  # homogeneous uniaxial stress: E e exactly
        assert f_ccx / sc.area == pytest.approx(E * 0.1, rel=LINEAR_TOL)
    else:  # the platens restrain the lateral expansion
        assert f_ccx / sc.area > 1.05 * E * 0.1
    assert du <= LINEAR_TOL and df <= LINEAR_TOL


# ------------------------------------------------------------------ (d) neo-Hookean
def _abaqus_neo_hooke_uniaxial(stretch):
    """Nominal stress [Pa] of CalculiX's NEO HOOKE (mu = 2 C10, K = 2 / D1) in homogeneous
    uniaxial stress at axial stretch ``stretch``: lateral stretch from sigma_lateral = 0."""
    mu, K = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))

    def cauchy(l1, l2):  # principal Cauchy stresses (axial, lateral)
        J = l1 * l2 * l2
        b1, b2 = J ** (-2 / 3) * l1 ** 2, J ** (-2 / 3) * l2 ** 2
        ib = (b1 + 2 * b2) / 3
        return mu / J * (b1 - ib) + K * (J - 1), mu / J * (b2 - ib) + K * (J - 1)

    l2 = brentq(lambda x: cauchy(stretch, x)[1], 0.5, 2.0, xtol=1e-15)
    return cauchy(stretch, l2)[0] * l2 * l2  # force / A0 = sigma * current area / A0 = sigma l2^2


def _fem_neo_hookean_uniaxial(stretch):
    """The same for difftissue's fem_neo_hookean, ``mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2``:
    Cauchy stress ``mu (b - I) / J + lambda ln J / J``."""
    mu = E / (2 * (1 + NU))
    lam = E * NU / ((1 + NU) * (1 - 2 * NU))

    def cauchy(l1, l2):
        J = l1 * l2 * l2
        return (mu * (l1 ** 2 - 1) + lam * math.log(J)) / J, (mu * (l2 ** 2 - 1) + lam * math.log(J)) / J

    l2 = brentq(lambda x: cauchy(stretch, x)[1], 0.5, 2.0, xtol=1e-15)
    return cauchy(stretch, l2)[0] * l2 * l2


def test_fitted_compression_neo_hookean(tmp_path):
    """(d): neo-Hookean frictionless compression to 10 %: CalculiX = difftissue with CalculiX's
    energy, and = that energy's homogeneous uniaxial solution; difftissue's own fem_neo_hookean
    (Compression.solve, a different energy at finite strain) differs by the model form."""
    sc = _compression("fem_neo_hookean", bonded=False)
    run, u, force, u_sc, force_sc = _run_compression(sc, "fem_neo_hookean", tmp_path)
    f_ccx = -run.totals["REACTION"][2]
    exact = -_abaqus_neo_hooke_uniaxial(0.9) * sc.area
    assert abs(f_ccx - exact) <= NEO_TOL * exact and abs(force - exact) <= 1e-9 * exact
    du, df = _rel_u(run.displacement, u), abs(f_ccx - force) / force
    _report("fitted compression neo-Hookean frictionless", du, df)
    gap_u, gap_f = _rel_u(run.displacement, u_sc), abs(f_ccx - force_sc) / force_sc
    print(f"CALCULIX fitted compression vs fem_neo_hookean: max|du|/max|u| = {gap_u:.2e}, force {gap_f:.2e}")
    assert du <= NEO_TOL and df <= NEO_TOL
    # the gap is the model form: the two energies' homogeneous answers differ by the same 1.4 %
    fem = -_fem_neo_hookean_uniaxial(0.9) * sc.area
    assert force_sc == pytest.approx(fem, rel=1e-9)
    assert abs(gap_f - abs(exact - fem) / fem) <= NEO_TOL and 0.005 < gap_f < 0.03


# ------------------------------------------------------------- (c) flat-punch indentation
@pytest.mark.parametrize("base, bonded", [("bonded", True), ("sliding", False)])
def test_flat_punch_linear(base, bonded, tmp_path):
    """(c): the flat-punch deck (PUNCH moved down, bonded or frictionless) = difftissue's
    Indentation force and static displacement field."""
    card = _card("fem_linear")
    depth = 1e-4
    spec = indentation_specimen(card, indenter="flat_punch", radius=2 * MM, depth=depth, size=(10 * MM, 10 * MM, 5 * MM),
                                cells=(4, 4, 2), base=base, bonded_punch=bonded, steps=1)
    deck = export(card, "abaqus", tmp_path / "punch.inp", indentation=spec)
    run = run_deck(deck, tmp_path / "ccx")
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    f_ours = float(np.asarray(Indentation(mesh, [depth], model="fem_linear", indenter="flat_punch", radius=spec.radius,
                                          bonded_punch=bonded, base=base).predict(card.material()))[0])
    p = np.asarray(mesh.points)
    fixed, disp = np.zeros(p.shape, dtype=bool), np.zeros(p.shape)
    if base == "bonded":
        fixed[s["base"]] = True
    else:
        fixed[s["base"], 2] = True
        fixed[s["anchor"], :2] = True
        fixed[s["other"], 1] = True
    fixed[s["punch"], 2] = True
    disp[s["punch"], 2] = -depth
    if bonded:
        fixed[s["punch"], :2] = True
    sol = solve_static(make_model(mesh, "fem_linear"), card.material(), BoundaryConditions(fixed, disp, np.zeros_like(disp)))
    f_static = -float(np.asarray(sol.reaction)[s["punch"], 2].sum())
    assert f_static == pytest.approx(f_ours, rel=1e-9)  # the same problem as Indentation's
    f_ccx = -run.totals["PUNCH"][2]
    du, df = _rel_u(run.displacement, np.asarray(sol.displacement)), abs(f_ccx - f_ours) / f_ours
    _report(f"flat punch {base} base, {'bonded' if bonded else 'frictionless'} punch", du, df)
    assert f_ours > 1e-3 and du <= LINEAR_TOL and df <= LINEAR_TOL


# ------------------------------------------- (e) sphere / cone: meshed rigid indenter
@pytest.mark.parametrize("indenter, geometry, depth, model", [
    ("sphere", {"radius": 5 * MM}, 0.15 * MM, "fem_linear"),
    ("sphere", {"radius": 5 * MM}, 0.15 * MM, "fem_neo_hookean"),
    ("cone", {"half_angle": math.radians(70.0)}, 0.25 * MM, "fem_linear"),
    ("cone", {"half_angle": math.radians(70.0)}, 0.25 * MM, "fem_neo_hookean")])
def test_sphere_and_cone(indenter, geometry, depth, model, tmp_path):
    """(e): the sphere / cone deck (meshed rigid indenter, node-to-surface penalty contact with
    difftissue's penalty K = p E / h) = difftissue's Indentation (penalty contact with the
    analytic indenter) on the same 4 x 4 x 2 mm block of 8 x 8 x 4 cells, at each of the four
    depth steps (the cone deck's increments are a multiple of the steps): the contact
    discretisations differ (faceted vs analytic indenter), so 2 % on the force and on
    max |du| / max |u| (issue 16). Neo-Hookean: the deck's ``NEO HOOKE`` (``NLGEOM=YES``)
    against ``fem_neo_hookean`` (the two energies differ at finite strain). Measured at the last
    depth: sphere -0.50 % force, 0.78 % of max |u| (linear), -0.092 %, 0.78 % (neo-Hookean); cone
    +0.015 %, 0.22 % (linear), +0.16 %, 0.84 % (neo-Hookean). The cone's apex node is held on the
    axis in both codes (``AXIS_TOP``; Indentation holds a top node under a cone's apex): without
    that hold each code's node slides off the tip down a different flank (docs/dev/calculix-cone.md)."""
    card = _card(model)
    spec = indentation_specimen(card, indenter=indenter, depth=depth, size=(4 * MM, 4 * MM, 2 * MM), cells=(8, 8, 4), steps=4,
                                **geometry)
    deck = export(card, "abaqus", tmp_path / f"{indenter}.inp", indentation=spec)
    text = deck.read_text()
    assert "TYPE=REVOLUTION" not in text and "*CONTACT PAIR, INTERACTION=INDENTER_CONTACT, TYPE=NODE TO SURFACE" in text
    run = run_deck(deck, tmp_path / "ccx")
    mesh = spec.mesh()
    assert ("*STEP, NLGEOM=YES" in text) == (model == "fem_neo_hookean")
    assert ("AXIS_TOP, 1, 2, 0.0" in text) == (indenter == "cone")
    sc = Indentation(mesh, [depth * (k + 1) / 4 for k in range(4)], model=model, indenter=indenter, base="bonded",
                     radius=geometry.get("radius"), half_angle=geometry.get("half_angle"))
    forces, us = (np.asarray(a) for a in sc.solve(card.material()))
    n = mesh.n_nodes
    p = np.asarray(mesh.points)
    if indenter == "cone":  # difftissue holds the top node under the apex on the axis, as the deck does
        apex = np.flatnonzero((np.hypot(p[:, 0], p[:, 1]) <= 1e-12) & (p[:, 2] == p[:, 2].max()))
        assert apex.size == 1 and np.all(us[:, apex, :2] == 0.0) and np.all(us[:, apex, 2] < 0)
    dat = (tmp_path / "ccx" / "job.dat").read_text()
    for k in range(4):
        totals, u_ccx, t = parse_dat(dat, run.displacement.shape[0], time=(k + 1) / 4)
        assert t == pytest.approx((k + 1) / 4, abs=1e-6)  # every depth step ends an increment
        f_ccx = -totals["INDENTER"][2]
        du, df = _rel_u(u_ccx[:n], us[k]), (f_ccx - forces[k]) / forces[k]
        _report(f"{indenter} bonded base (meshed rigid indenter), {model}, depth {1e3 * depth * (k + 1) / 4:g} mm", du, df)
        assert forces[k] > 1e-4 and abs(df) <= 0.02 and du <= 0.02
    assert np.allclose(run.displacement[n:], [0.0, 0.0, -depth], rtol=0, atol=1e-6 * depth)  # the indenter translates rigidly
    lateral = abs(run.totals["INDENTER"][:2]).max() / -run.totals["INDENTER"][2]
    print(f"CALCULIX {indenter}: largest lateral indenter force / indentation force = {lateral:.2e}")
    if indenter == "sphere":  # nearly none (measured 0.4 %: the facets are not axisymmetric)
        assert lateral <= 0.01
    # cone: measured 35 %: the node under the tip springs against ONE facet, whose lateral push its x, y hold (AXIS_TOP) takes


# ----------------------------------------------------- incision: not representable, refused
@pytest.mark.parametrize("pre_stretch", [1.05, 1.0])
def test_abaqus_incision_is_refused_with_the_reason(pre_stretch, tmp_path):
    """The exporter writes no Abaqus incision deck (docs/export.md): with a pre-stretch Abaqus
    has no prestrain gradient here (and the stress-free cut does not open, so --approximate does
    not apply); without one the specimen carries no load. Both refused in one line, no file."""
    from difftissue.cutting import ScalpelPath, cut_specimen
    from difftissue.errors import ExportError
    from difftissue.incision import Incision, IncisionOptions
    from difftissue.mesh import layered_skin

    skin, fat = Material(200e3, 0.45, pre_stretch=pre_stretch), Material(5e3, 0.45)
    mesh = layered_skin([("dermis", 1 * MM, skin, 1), ("fat", 1 * MM, fat, 1)], size=(4 * MM, 4 * MM), resolution=(4, 4))
    cut = cut_specimen(mesh, ScalpelPath([(1 * MM, 2 * MM), (3 * MM, 2 * MM)], depth=1 * MM))
    sc = Incision(cut, model="fem_neo_hookean", fitted_regions=("dermis",), quantity="surface_width",
                  options=IncisionOptions(scalpel_steps=1), name="cut")
    card = MaterialCard(model="fem_neo_hookean", name="dermis", parameters={
        "youngs_modulus": {"value": 200e3}, "poisson_ratio": {"value": 0.45}, "pre_stretch": {"value": pre_stretch}})
    why = "cannot be represented by Abaqus" if pre_stretch != 1.0 else "carry no load and the cut would not open"
    for approximate in (False, True):
        with pytest.raises(ExportError, match=why) as e:
            export(card, "abaqus", tmp_path / "cut.inp", fitted=fitted_specimen(sc), approximate=approximate)
        assert "\n" not in str(e.value) and not (tmp_path / "cut.inp").exists()
