"""Anisotropic in-plane pre-stretch (``Material.pre_stretch_y``): the stress-free state is the
mesh shrunk by ``diag(1/lambda_x, 1/lambda_y, 1)`` in all four models and the XPBD constraints.

One two-layer specimen (2 x 2 x 2 cubes of 1 mm, regions "top" and "bottom") serves every
equilibrium test, so each model is compiled once (as in tests/test_pretension.py).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.optimize import brentq

from difftissue.boundary import BoundaryConditions
from difftissue.constitutive import biaxial_membrane_state, membrane_state, pre_stretch_for_surface_tension, surface_tension, surface_tensions
from difftissue.errors import MaterialError, ModelRangeError
from difftissue.materials import (Material, MaterialParameterization, biaxial_pre_stress, equibiaxial_pre_stress, explicit_pre_stretch_y,
                                  lame_parameters)
from difftissue.mesh import block, layered_skin
from difftissue.models import MODELS, _cell_spring_factor_ratio_slopes, _cell_spring_factor_slopes, _cell_spring_factors, make_model, stack_materials
from difftissue.solvers.static import solve_static
from difftissue.solvers.xpbd import constraint_energy, xpbd_constraints

L, T = 2e-3, 1e-3  # lateral size, thickness of each layer [m]
E, NU = 1e4, 0.45
LX, LY = 1.08, 1.03  # an anisotropic pre-stretch (tension across Langer's lines along x)


@pytest.fixture(scope="module")
def mesh():
    m = Material(E, NU)
    return layered_skin([("top", T, m, 1), ("bottom", T, m, 1)], size=(L, L), resolution=(2, 2)).mesh


@pytest.fixture(scope="module")
def models(mesh):
    return {kind: make_model(mesh, kind) for kind in MODELS}


def _both(lx, ly, **kw):
    return stack_materials([Material(E, NU, pre_stretch=lx, pre_stretch_y=ly, **kw)] * 2)


def _rigid_only(mesh):
    p = mesh.points
    o = int(np.argmin(np.linalg.norm(p, axis=1)))
    ax = int(np.argmin(np.linalg.norm(p - [L, 0, 0], axis=1)))
    ay = int(np.argmin(np.linalg.norm(p - [0, L, 0], axis=1)))
    return BoundaryConditions.free(mesh).fix(mesh, [o]).fix(mesh, [ax], "yz").fix(mesh, [ay], "z")


def _lateral_held(mesh):
    bc = BoundaryConditions.free(mesh)
    for face, comp in (("x-min", "x"), ("x-max", "x"), ("y-min", "y"), ("y-max", "y"), ("z-min", "z")):
        bc = bc.fix(mesh, {"face": face}, comp)
    return bc


def _neo_hookean_biaxial(lx, ly, E_=E, nu=NU):
    """Compressible neo-Hookean ``Psi = mu/2 (I1 - 3 - 2 ln J) + lam/2 (ln J)^2`` stretched by
    ``diag(lx, ly, lz)`` from its stress-free state with ``sigma_zz = 0``: ``(lz, P_xx, P_yy,
    sigma_xx, sigma_yy)``; ``P = mu (F - F^-T) + lam ln J F^-T`` (closed form up to the root lz)."""
    lam, mu = (float(v) for v in lame_parameters(E_, nu))
    lz = brentq(lambda z: mu * (z * z - 1.0) + lam * math.log(lx * ly * z), 0.5, 1.5, xtol=1e-16, rtol=1e-15)
    J = lx * ly * lz
    P = [mu * (l - 1.0 / l) + lam * math.log(J) / l for l in (lx, ly)]
    s = [(mu * (l * l - 1.0) + lam * math.log(J)) / J for l in (lx, ly)]
    return lz, P[0], P[1], s[0], s[1]


# --------------------------------------------------------------- (1) bit for bit
@pytest.mark.parametrize("kind", MODELS)
def test_equal_pre_stretches_are_the_equibiaxial_model_bit_for_bit(mesh, models, kind):
    """pre_stretch_y = pre_stretch gives the equibiaxial energy and forces bit for bit (eager and
    jitted), and a pre_stretch_y of None leaves the pytree's leaves those of before."""
    rng = np.random.default_rng(0)
    x = jnp.asarray(mesh.points) * jnp.array([0.98, 0.97, 1.01]) + 1e-5 * rng.standard_normal(mesh.points.shape)
    model = models[kind]
    iso = stack_materials([Material(E, NU, 0.3, pre_stretch=1.07), Material(E, NU, 0.3, pre_stretch=1.02)])
    an = explicit_pre_stretch_y(iso)
    assert len(jax.tree_util.tree_leaves(iso)) == 5 and len(jax.tree_util.tree_leaves(an)) == 6
    energy = jax.jit(lambda x_, m_: model.energy(x_, m_))
    force = jax.jit(jax.grad(lambda x_, m_: model.energy(x_, m_)))
    assert float(model.energy(x, iso)) == float(model.energy(x, an))
    assert float(energy(x, iso)) == float(energy(x, an))
    assert np.array_equal(np.asarray(force(x, iso)), np.asarray(force(x, an)))
    if kind == "springs_volume":
        for a, b in zip(model.spring_parameters(iso), model.spring_parameters(an)):
            assert np.array_equal(np.asarray(a), np.asarray(b))


# ------------------------------------------------------------ the stress-free state
def test_spring_factors_are_those_of_the_anisotropically_shrunk_cell():
    h = np.array([[1.0, 1.0, 1.0], [1.2, 0.9, 1.1], [1e-3, 1.1e-3, 0.8e-3]])
    g1, slope, c = _cell_spring_factors(h), _cell_spring_factor_slopes(h), _cell_spring_factor_ratio_slopes(h)
    for lx, ly in ((1.1, 1.0), (0.95, 1.15), (1.2, 1.05)):
        shrunk = _cell_spring_factors(h * [1.0 / lx, 1.0 / ly, 1.0])
        mine = g1 + (1.0 / (lx * ly) - 1.0) * slope + (lx / ly - 1.0) * c[..., 0] + (ly / lx - 1.0) * c[..., 1]
        np.testing.assert_allclose(mine, shrunk, rtol=1e-13, atol=1e-15)


def test_spring_rest_lengths_and_volumes_of_the_shrunk_state(mesh, models):
    sv = models["springs_volume"]
    mat = stack_materials([Material(E, NU, pre_stretch=LX, pre_stretch_y=LY), Material(E, NU)])
    rest, k, a = sv.spring_parameters(mat)
    p = np.asarray(mesh.points)
    d = p[sv.springs[:, 1]] - p[sv.springs[:, 0]]
    scale = np.where(sv.spring_regions[:, None] == 0, [1.0 / LX, 1.0 / LY, 1.0], 1.0)
    np.testing.assert_allclose(np.asarray(rest), np.linalg.norm(d * scale, axis=1), rtol=1e-14)
    vol = np.asarray(sv.cell_rest_volumes(mat))
    np.testing.assert_allclose(vol, np.where(sv.cell_regions == 0, 1.0 / (LX * LY), 1.0) * 1e-9, rtol=1e-13)


@pytest.mark.parametrize("kind", MODELS)
def test_free_specimen_relaxes_to_the_shrunk_state(mesh, models, kind):
    """Only rigid motion removed: the specimen shrinks by (1/lambda_x, 1/lambda_y) in x, y; no stress."""
    sol = solve_static(models[kind], _both(LX, LY), _rigid_only(mesh))
    p = mesh.points
    expected = np.stack([(1.0 / LX - 1.0) * p[:, 0], (1.0 / LY - 1.0) * p[:, 1], 0.0 * p[:, 2]], axis=1)
    np.testing.assert_allclose(np.asarray(sol.displacement), expected, rtol=0, atol=1e-9 * L)
    assert float(jnp.max(jnp.abs(sol.reaction))) < 1e-12 * E * L * L


# ------------------------------------------------------------- (2) membrane stresses
def test_neo_hookean_plate_is_the_closed_form_biaxial_state(mesh, models):
    """fem_neo_hookean plate, lateral faces held, z free: the reactions per unit stress-free
    length are (P_xx, P_yy) t, the thickness lambda_z t and the membrane state's Cauchy stresses
    (sigma_xx, sigma_yy) those of the closed form, to 1e-8 (solver rtol 1e-10)."""
    p = mesh.points
    xmax, ymax, top = np.isclose(p[:, 0], L), np.isclose(p[:, 1], L), np.isclose(p[:, 2], 2 * T)
    lz, Pxx, Pyy, sxx, syy = _neo_hookean_biaxial(LX, LY)
    sol = solve_static(models["fem_neo_hookean"], _both(LX, LY), _lateral_held(mesh))
    fx = float(jnp.sum(sol.reaction[xmax, 0])) / (L / LY)  # per unit stress-free length of the x-max face
    fy = float(jnp.sum(sol.reaction[ymax, 1])) / (L / LX)
    assert fx == pytest.approx(Pxx * 2 * T, rel=1e-8)
    assert fy == pytest.approx(Pyy * 2 * T, rel=1e-8)
    np.testing.assert_allclose(np.asarray(sol.displacement[top, 2]), (lz - 1.0) * 2 * T, rtol=1e-8)
    st = biaxial_membrane_state("fem_neo_hookean", Material(E, NU, pre_stretch=LX, pre_stretch_y=LY))
    assert float(st.thickness_stretch) == pytest.approx(lz, rel=1e-12)
    np.testing.assert_allclose(np.asarray(st.cauchy_stress), [sxx, syy], rtol=1e-10)
    np.testing.assert_allclose(np.asarray(st.nominal_stress), [Pxx, Pyy], rtol=1e-10)
    assert sxx > syy > 0  # the higher stretch carries the higher tension


@pytest.mark.parametrize("kind", ["springs_volume", "stable_neo_hookean"])
def test_plate_reactions_are_the_models_homogeneous_response(mesh, models, kind):
    """springs_volume and stable neo-Hookean plates (lateral faces held): the reaction per unit
    current length is the model's own surface tension (T_x, T_y) of the layer (constitutive.py,
    the one-cell homogeneous response), to 1e-8."""
    p = mesh.points
    xmax, ymax = np.isclose(p[:, 0], L), np.isclose(p[:, 1], L)
    sol = solve_static(models[kind], _both(LX, LY), _lateral_held(mesh))
    T_xy = np.asarray(surface_tensions(kind, Material(E, NU, pre_stretch=LX, pre_stretch_y=LY), 2 * T, cell_size=(1e-3, 1e-3, 1e-3)))
    fx = float(jnp.sum(sol.reaction[xmax, 0])) / L
    fy = float(jnp.sum(sol.reaction[ymax, 1])) / L
    np.testing.assert_allclose([fx, fy], T_xy, rtol=1e-8)
    assert T_xy[0] > T_xy[1] > 0


def test_surface_tensions_reduce_to_the_equibiaxial_ones():
    m = Material(2e5, 0.45, pre_stretch=1.05)
    for kind in MODELS:
        t_iso = float(surface_tension(kind, m, 1e-3))
        t_xy = np.asarray(surface_tensions(kind, m.replace(pre_stretch_y=1.05), 1e-3))
        np.testing.assert_allclose(t_xy, [t_iso, t_iso], rtol=1e-12)
        assert float(membrane_state(kind, m.replace(pre_stretch_y=1.05)).tension_per_thickness) == float(membrane_state(kind, m).tension_per_thickness)
    # the linear limit: t E (eps_x + nu eps_y) / (1 - nu^2)
    small = Material(2e5, 0.45, pre_stretch=1.0004, pre_stretch_y=1.0001)
    lin = np.asarray(biaxial_pre_stress(small)) * 1e-3
    np.testing.assert_allclose(np.asarray(surface_tensions("fem_linear", small, 1e-3)), lin, rtol=1e-3)


# ------------------------------------------------------------------- (4) gradients
def test_reaction_gradients_in_both_pre_stretches_match_central_differences(mesh, models):
    """d(reactions, thickness)/d(lambda_x, lambda_y) of the held plate (implicit differentiation,
    float64) vs central differences, rtol 1e-5: springs_volume and fem_neo_hookean."""
    p = mesh.points
    xmax, ymax, top = np.isclose(p[:, 0], L), np.isclose(p[:, 1], L), np.isclose(p[:, 2], 2 * T)
    bc = _lateral_held(mesh)
    for kind in ("springs_volume", "fem_neo_hookean"):
        model = models[kind]

        def output(q, model=model):
            mat = eqx.tree_at(lambda m: (m.pre_stretch, m.pre_stretch_y), _both(1.0, 1.0), (jnp.full(2, q[0]), jnp.full(2, q[1])))
            sol = solve_static(model, mat, bc, rtol=1e-12)
            return jnp.stack([jnp.sum(sol.reaction[xmax, 0]), jnp.sum(sol.reaction[ymax, 1]), 1e3 * jnp.mean(sol.displacement[top, 2])]) / (E * L * T)

        # one program gives the Jacobian (forward mode) and, as its auxiliary output, the value
        # of the same primal solve: the four difference evaluations reuse it
        jac_and_value = jax.jit(jax.jacfwd(lambda q, output=output: (lambda y: (y, y))(output(q)), has_aux=True))

        def value(q):
            return jac_and_value(q)[1]

        q0 = jnp.array([LX, LY])
        jac = np.asarray(jac_and_value(q0)[0])
        assert abs(jac[0, 0]) > abs(jac[0, 1]) > 0 and abs(jac[1, 1]) > abs(jac[1, 0]) > 0
        h = 1e-6
        for i in range(2):
            dq = jnp.zeros(2).at[i].set(h)
            fd = (np.asarray(value(q0 + dq)) - np.asarray(value(q0 - dq))) / (2 * h)
            np.testing.assert_allclose(jac[:, i], fd, rtol=1e-5, atol=1e-8 * np.max(np.abs(jac)))


def test_kernels_check_grads(mesh, models):
    rng = np.random.default_rng(1)
    x = jnp.asarray(mesh.points) * jnp.array([0.98, 0.99, 1.01]) + 1e-5 * rng.standard_normal(mesh.points.shape)
    base = _both(1.0, 1.0)

    def with_pre(q):
        return eqx.tree_at(lambda m: (m.pre_stretch, m.pre_stretch_y), base, (q[:2], q[2:]))

    # check_grads on jitted functions: one program per derivative instead of every operation
    # compiled on its own
    q0 = jnp.array([1.07, 1.02, 1.03, 1.05])
    check_grads(jax.jit(lambda q: models["fem_linear"].stress_free_tets(q[:2], q[2:])), (q0,), order=2, modes=("fwd", "rev"))
    sv = models["springs_volume"]
    check_grads(jax.jit(lambda q: sv.spring_parameters(with_pre(q))), (q0,), order=1, modes=("fwd", "rev"))
    check_grads(jax.jit(lambda q: sv.cell_rest_volumes(with_pre(q))), (q0,), order=2, modes=("fwd", "rev"))
    check_grads(jax.jit(lambda q: sv.energy(x, with_pre(q)) / (E * T**3)), (q0,), order=1, modes=("fwd", "rev"), rtol=1e-6)
    m = Material(2e5, 0.45, pre_stretch=1.06, pre_stretch_y=1.02)
    check_grads(jax.jit(lambda q: surface_tensions("springs_volume", eqx.tree_at(lambda m: (m.pre_stretch, m.pre_stretch_y), m, (q[0], q[1])), 1e-3)),
                (jnp.array([1.06, 1.02]),), order=1, modes=("fwd",), rtol=1e-5)


# ----------------------------------------------------------------------------- XPBD
def test_xpbd_constraints_honour_the_anisotropic_pre_stretch(mesh, models):
    """The XPBD constraint energy is the model's energy: equal for springs_volume, plus the
    constant sum V0_eff (3 mu / 2 + mu^2 / (2 lam')) for stable neo-Hookean."""
    rng = np.random.default_rng(2)
    x = jnp.asarray(mesh.points) * jnp.array([0.97, 0.98, 1.02]) + 1e-5 * rng.standard_normal(mesh.points.shape)
    mat = stack_materials([Material(E, NU, pre_stretch=LX, pre_stretch_y=LY), Material(E, NU)])
    sv, snh = models["springs_volume"], models["stable_neo_hookean"]
    cons = xpbd_constraints(sv, mat)
    assert float(constraint_energy(cons, x)) == pytest.approx(float(sv.energy(x, mat)), rel=1e-12)
    shrunk = jnp.asarray(mesh.points) * jnp.array([1 / LX, 1 / LY, 1.0])
    top = np.asarray(sv.spring_regions) == 0
    np.testing.assert_allclose(np.asarray(cons[0].values(shrunk))[0][top], 0.0, atol=1e-15)
    lam, mu = (float(v) for v in lame_parameters(E, NU))
    V_eff = np.asarray(snh.stress_free_tets(jnp.array([LX, 1.0]), jnp.array([LY, 1.0]))[1])
    const = np.sum(V_eff) * (1.5 * mu + mu * mu / (2 * (lam + mu)))
    assert float(constraint_energy(xpbd_constraints(snh, mat), x)) - const == pytest.approx(float(snh.energy(x, mat)), rel=1e-9)


# ------------------------------------------------------------------------ refusals
def test_bad_and_unsupported_input_is_refused(models, mesh):
    for bad in (0.0, -1.1, float("nan")):
        with pytest.raises(MaterialError, match="pre_stretch_y"):
            Material(E, NU, pre_stretch_y=bad)
    x = jnp.asarray(mesh.points)
    mat = eqx.tree_at(lambda m: m.pre_stretch_y, _both(1.0, 1.0), jnp.array([0.0, 1.0]))  # bypasses __check_init__
    for kind in MODELS:
        with pytest.raises(MaterialError, match="pre_stretch_y"):
            models[kind].energy(x, mat)
    an = Material(E, NU, pre_stretch=1.05, pre_stretch_y=1.02)
    with pytest.raises(MaterialError, match="equibiaxial"):
        equibiaxial_pre_stress(an)
    with pytest.raises(MaterialError, match="equibiaxial"):
        membrane_state("fem_linear", an)
    with pytest.raises(MaterialError, match="pre_stretch_y"):
        pre_stretch_for_surface_tension("fem_linear", an, 1.0, 1e-3)
    # the springs lattice: x edges of a cube get the factor (3 rho - 1/rho - q)/4 (rho = lx/ly)
    cube = make_model(block(1e-3, 1), "springs_volume")
    cube.energy(jnp.asarray(block(1e-3, 1).points), Material(E, NU, pre_stretch=1.0, pre_stretch_y=1.2))
    with pytest.raises(ModelRangeError, match="pre_stretch_y"):
        cube.energy(jnp.asarray(block(1e-3, 1).points), Material(E, NU, pre_stretch=0.8, pre_stretch_y=1.3))


def test_parameterization_fits_pre_stretch_y_of_an_equibiaxial_base():
    param = MaterialParameterization(("pre_stretch", "pre_stretch_y"))
    base = Material(E, NU, pre_stretch=1.05)
    u = param.pack(base)
    np.testing.assert_allclose(np.asarray(u), np.log([1.05, 1.05]), rtol=1e-14)
    m = param.unpack(jnp.log(jnp.array([1.1, 1.02])), base)
    assert float(m.pre_stretch) == pytest.approx(1.1) and float(m.pre_stretch_y) == pytest.approx(1.02)
    assert Material(E, NU).to_dict().keys() == {"youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch"}
    assert Material(E, NU, pre_stretch_y=1.1).to_dict()["pre_stretch_y"] == 1.1


# -------------------------------------------------------------------------- export
def test_card_and_febio_export_of_an_anisotropic_pre_stretch():
    from difftissue.errors import ExportError
    from difftissue.export import MaterialCard, febio_material, pre_stretch_from_febio_gradient, pre_stretches_from_febio_gradient
    from difftissue.export.approximations import approximation_notes

    params = {"youngs_modulus": {"value": 2e5}, "poisson_ratio": {"value": 0.45}, "pre_stretch": {"value": 1.08}, "pre_stretch_y": {"value": 1.03}}
    card = MaterialCard(model="fem_neo_hookean", parameters=params, name="skin")
    m = card.material()
    assert (float(m.pre_stretch), float(m.pre_stretch_y)) == (1.08, 1.03) and card.is_anisotropic_pre_stretch
    iso = MaterialCard(model="fem_neo_hookean", parameters={k: v for k, v in params.items() if k != "pre_stretch_y"}, name="skin")
    assert iso.pre_stretch_y == 1.08 and iso.material().pre_stretch_y is None and not iso.is_anisotropic_pre_stretch
    F0 = febio_material(card).find(".//F0").text
    assert pre_stretches_from_febio_gradient(F0) == (1.08, 1.03)
    with pytest.raises(ExportError, match="equibiaxial"):
        pre_stretch_from_febio_gradient(F0)
    assert pre_stretch_from_febio_gradient(febio_material(iso).find(".//F0").text) == 1.08
    # only y pre-stretched: still written (and refused where a target cannot hold it)
    only_y = MaterialCard(model="fem_neo_hookean", parameters={**params, "pre_stretch": {"value": 1.0}}, name="skin")
    assert pre_stretches_from_febio_gradient(febio_material(only_y).find(".//F0").text) == (1.0, 1.03)
    with pytest.raises(ExportError, match="pre_stretch_y = 1.03"):
        approximation_notes(only_y, "scikit-fem linear elasticity", approximate=False)
