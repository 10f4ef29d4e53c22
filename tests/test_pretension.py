"""Pre-stretch (pre-tension) in the four models and in the XPBD constraints.

A region with ``pre_stretch = lambda0`` is stress-free when the mesh is shrunk by
``1/lambda0`` in x and y (docs/theory.md, "Pre-stretch"). One two-layer specimen (2 x 2 x 2
cubes of 1 mm, regions "top" and "bottom") serves every equilibrium test, so each model is
compiled once.
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
from difftissue.errors import MaterialError, ModelRangeError
from difftissue.materials import Material, equibiaxial_pre_stress, lame_parameters, pre_stretch_from_surface_tension, surface_tension_from_pre_stretch
from difftissue.mesh import block, layered_skin
from difftissue.models import MODELS, _cell_spring_factor_slopes, _cell_spring_factors, make_model, stack_materials
from difftissue.solvers.static import solve_static
from difftissue.solvers.xpbd import constraint_energy, xpbd_constraints

L, T = 2e-3, 1e-3  # lateral size, thickness of each layer [m]
E, NU = 1e4, 0.45


@pytest.fixture(scope="module")
def mesh():
    m = Material(E, NU)
    return layered_skin([("top", T, m, 1), ("bottom", T, m, 1)], size=(L, L), resolution=(2, 2)).mesh


@pytest.fixture(scope="module")
def models(mesh):
    return {kind: make_model(mesh, kind) for kind in MODELS}


def _materials(lam_top, lam_bottom, E_top=E, nu=NU):
    return stack_materials([Material(E_top, nu, pre_stretch=lam_top), Material(E, nu, pre_stretch=lam_bottom)])


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


# --------------------------------------------------------------- exact plane-stress states
def _plane_stress_exact(kind, lam0, E_=E, nu=NU):
    """Equibiaxial stretch lam0 of the stress-free state, sigma_zz = 0: ``(lambda_z, P_xx)``
    with ``P_xx`` the nominal stress [Pa] per stress-free area (closed forms of the energies)."""
    lam, mu = (float(v) for v in lame_parameters(E_, nu))
    if kind == "fem_linear":
        ez = -2.0 * nu / (1.0 - nu) * (lam0 - 1.0)
        return 1.0 + ez, E_ * (lam0 - 1.0) / (1.0 - nu)
    if kind == "fem_neo_hookean":  # P = mu (F - F^-T) + lam ln J F^-T
        lz = brentq(lambda z: mu * (z * z - 1.0) + lam * math.log(lam0 * lam0 * z), 0.5, 1.5, xtol=1e-15)
        return lz, mu * (lam0 - 1.0 / lam0) + lam * math.log(lam0 * lam0 * lz) / lam0
    if kind == "stable_neo_hookean":  # P = mu F - mu cof F + lam' (J - 1) cof F, lam' = lam + mu
        ls = lam + mu
        lz = lam0**2 * (mu + ls) / (mu + ls * lam0**4)
        J = lam0 * lam0 * lz
        return lz, mu * lam0 - mu * lam0 * lz + ls * (J - 1.0) * lam0 * lz
    raise AssertionError(kind)


# ----------------------------------------------------------------------------- (a)
@pytest.mark.parametrize("kind", MODELS)
def test_free_specimen_relaxes_to_the_shrunk_state(mesh, models, kind):
    """Only rigid motion removed: the specimen shrinks by 1/lambda0 in x, y; no stress."""
    lam0 = 1.05
    sol = solve_static(models[kind], _materials(lam0, lam0), _rigid_only(mesh))
    p = mesh.points
    expected = np.stack([(1.0 / lam0 - 1.0) * p[:, 0], (1.0 / lam0 - 1.0) * p[:, 1], 0.0 * p[:, 2]], axis=1)
    np.testing.assert_allclose(np.asarray(sol.displacement), expected, rtol=0, atol=1e-9 * L)  # solver rtol 1e-10
    assert float(jnp.max(jnp.abs(sol.reaction))) < 1e-12 * E * L * L
    assert abs(float(sol.energy)) < 1e-20 * E * L**3


# ----------------------------------------------------------------------------- (b)
@pytest.mark.parametrize("kind", ["fem_linear", "fem_neo_hookean", "stable_neo_hookean"])
def test_held_plate_reaction_and_thickness_exact(mesh, models, kind):
    """Lateral faces held, z free: the reaction per unit stress-free edge length is
    P_xx t (fem_linear: exactly sigma0 t), the thickness follows lambda_z (closed forms)."""
    p = mesh.points
    xmax, top = np.isclose(p[:, 0], L), np.isclose(p[:, 2], 2 * T)
    for lam0 in (1.01, 1.1):
        mat = _materials(lam0, lam0)
        sol = solve_static(models[kind], mat, _lateral_held(mesh))
        lz, Pxx = _plane_stress_exact(kind, lam0)
        force_per_length = float(jnp.sum(sol.reaction[xmax, 0])) / (L / lam0)  # per stress-free length
        assert force_per_length == pytest.approx(Pxx * 2 * T, rel=1e-9)
        np.testing.assert_allclose(np.asarray(sol.displacement[top, 2]), (lz - 1.0) * 2 * T, rtol=1e-9)
        if kind == "fem_linear":
            sigma0 = float(equibiaxial_pre_stress(Material(E, NU, pre_stretch=lam0)))
            assert force_per_length == pytest.approx(sigma0 * 2 * T, rel=1e-12)
            tension = float(surface_tension_from_pre_stretch(Material(E, NU, pre_stretch=lam0), 2 * T))
            assert force_per_length == pytest.approx(tension, rel=1e-12)


@pytest.mark.parametrize("kind", ["fem_neo_hookean", "stable_neo_hookean", "springs_volume"])
def test_held_plate_linear_limit(mesh, models, kind):
    """Reaction per unit stress-free length -> sigma0 t as lambda0 -> 1: within 3 % at
    lambda0 = 1.01 and 0.3 % at 1.001 (measured: neo-Hookean -1.9 % / -0.19 %, stable
    neo-Hookean -1.9 % / -0.19 %, springs -2.5 % / -0.25 %: an error O(lambda0 - 1));
    thickness change within the same tolerance (measured -1.0 %, -0.9 %, -0.4 % at 1.01)."""
    p = mesh.points
    xmax, top = np.isclose(p[:, 0], L), np.isclose(p[:, 2], 2 * T)
    for lam0, tol in ((1.01, 0.03), (1.001, 0.003)):
        sol = solve_static(models[kind], _materials(lam0, lam0), _lateral_held(mesh))
        sigma0 = E * (lam0 - 1.0) / (1.0 - NU)
        force_per_length = float(jnp.sum(sol.reaction[xmax, 0])) / (L / lam0)
        assert force_per_length == pytest.approx(sigma0 * 2 * T, rel=tol)
        dz_lin = -2.0 * NU / (1.0 - NU) * (lam0 - 1.0) * 2 * T
        np.testing.assert_allclose(np.asarray(sol.displacement[top, 2]), dz_lin, rtol=tol)


# ----------------------------------------------------------------------------- (c)
@pytest.mark.parametrize("kind", MODELS)
def test_only_the_top_layer_pre_stretched(mesh, models, kind):
    """Top layer lambda0 = 1.05, bottom 1, lateral faces held: only the top layer carries
    stress and changes thickness (exact closed forms; springs_volume within 5 % of the
    linear limit, which its lattice reproduces at small strain)."""
    p = mesh.points
    xmax = np.isclose(p[:, 0], L)
    top, mid = np.isclose(p[:, 2], 2 * T), np.isclose(p[:, 2], T)
    lam0 = 1.05 if kind != "springs_volume" else 1.01
    sol = solve_static(models[kind], _materials(lam0, 1.0), _lateral_held(mesh))
    u = np.asarray(sol.displacement)
    force_per_length = float(jnp.sum(sol.reaction[xmax, 0])) / (L / lam0)
    np.testing.assert_allclose(u[mid, 2], 0.0, atol=1e-12 * T)  # the bottom layer stays stress-free
    assert np.allclose(u[:, :2], 0.0)
    if kind == "springs_volume":
        sigma0 = E * (lam0 - 1.0) / (1.0 - NU)
        assert force_per_length == pytest.approx(sigma0 * T, rel=0.05)
        np.testing.assert_allclose(u[top, 2], -2.0 * NU / (1.0 - NU) * (lam0 - 1.0) * T, rtol=0.05)
    else:
        lz, Pxx = _plane_stress_exact(kind, lam0)
        assert force_per_length == pytest.approx(Pxx * T, rel=1e-9)
        np.testing.assert_allclose(u[top, 2], (lz - 1.0) * T, rtol=1e-9)


# ----------------------------------------------------------------------------- (d)
def test_equilibrium_gradients_match_central_differences(mesh, models):
    """d/d(lambda0_top, E_top, nu) of the bent bilayer (only rigid motion removed) by implicit
    differentiation vs central differences (fem_neo_hookean, finite strain; the springs'
    pre-stretch kernels and energy, which the same implicit tangent differentiates, are
    checked by check_grads below)."""
    model, bc = models["fem_neo_hookean"], _rigid_only(mesh)
    p = mesh.points
    corner = int(np.argmin(np.linalg.norm(p - [L, L, 2 * T], axis=1)))
    centre = int(np.argmin(np.linalg.norm(p - [L / 2, L / 2, 0.0], axis=1)))

    def output(q):
        lam_top, E_top, nu = q[0], 1e4 * q[1], q[2]
        mat = eqx.tree_at(
            lambda m: (m.youngs_modulus, m.poisson_ratio, m.pre_stretch),
            _materials(1.0, 1.0),
            (jnp.stack([E_top, jnp.asarray(E)]), jnp.stack([nu, nu]), jnp.stack([lam_top, jnp.asarray(1.0)])),
        )
        u = solve_static(model, mat, bc).displacement
        return jnp.stack([u[corner, 0], u[corner, 2], u[centre, 2]]) / T

    # jitted: one compiled program for the seven evaluations and one for the Jacobian, instead
    # of op-by-op dispatch (a compilation per primitive) around the solve
    output = jax.jit(output)
    q0 = jnp.array([1.04, 2.0, 0.42])
    jac = np.asarray(jax.jit(jax.jacfwd(output))(q0))
    assert np.all(np.abs(jac[:, 0]) > 1e-3)  # lambda0 moves every output
    h = 1e-6
    for i in range(3):
        dq = jnp.zeros(3).at[i].set(h)
        fd = (np.asarray(output(q0 + dq)) - np.asarray(output(q0 - dq))) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=2e-5, atol=1e-7 * np.max(np.abs(jac)))


def test_kernels_check_grads(mesh, models):
    rng = np.random.default_rng(1)
    x = jnp.asarray(mesh.points) * jnp.array([0.98, 0.99, 1.01]) + 1e-5 * rng.standard_normal(mesh.points.shape)
    base = _materials(1.0, 1.0)

    def with_pre(l):
        return eqx.tree_at(lambda m: m.pre_stretch, base, l)

    l0 = jnp.array([1.07, 1.02])
    # (jitted: check_grads evaluates each function many times; compiled programs per mode
    # instead of op-by-op dispatch, the same numbers to round-off)
    fem = models["fem_linear"]
    check_grads(jax.jit(lambda l: fem.stress_free_tets(l)), (l0,), order=2, modes=("fwd", "rev"))
    sv = models["springs_volume"]
    check_grads(jax.jit(lambda l: sv.spring_parameters(with_pre(l))), (l0,), order=1, modes=("fwd", "rev"))
    check_grads(jax.jit(lambda l: sv.cell_rest_volumes(with_pre(l))), (l0,), order=2, modes=("fwd", "rev"))
    for kind in ("springs_volume", "fem_neo_hookean"):  # the other tet models share stress_free_tets
        check_grads(jax.jit(lambda l, m=models[kind]: m.energy(x, with_pre(l)) / (E * T**3)), (l0,), order=1, modes=("fwd", "rev"), rtol=1e-6)


# ------------------------------------------------------------------ springs geometry
def test_spring_factors_are_those_of_the_shrunk_cell():
    h = np.array([[1.0, 1.0, 1.0], [1.2, 0.9, 1.1], [1e-3, 1.1e-3, 0.8e-3]])
    g1, slope = _cell_spring_factors(h), _cell_spring_factor_slopes(h)
    for lam0 in (0.9, 1.0, 1.1, 1.2):
        shrunk = _cell_spring_factors(h * [1.0 / lam0, 1.0 / lam0, 1.0])
        np.testing.assert_allclose(g1 + (lam0**-2 - 1.0) * slope, shrunk, rtol=1e-13, atol=1e-15)


def test_spring_rest_lengths_and_volumes_of_the_shrunk_state(mesh, models):
    sv = models["springs_volume"]
    lam0 = 1.08
    rest, k, a = sv.spring_parameters(_materials(lam0, 1.0))
    p = np.asarray(mesh.points)
    d = p[sv.springs[:, 1]] - p[sv.springs[:, 0]]
    scale = np.where(sv.spring_regions == 0, 1.0 / lam0, 1.0)[:, None] * [1.0, 1.0, 0.0] + [0.0, 0.0, 1.0]
    np.testing.assert_allclose(np.asarray(rest), np.linalg.norm(d * scale, axis=1), rtol=1e-14)
    vol = np.asarray(sv.cell_rest_volumes(_materials(lam0, 1.0)))
    np.testing.assert_allclose(vol, np.where(sv.cell_regions == 0, lam0**-2, 1.0) * 1e-9, rtol=1e-13)
    # interface springs are one element per region: shared horizontal springs at z = T appear twice
    on_interface = np.all(np.isclose(p[sv.springs, 2], T), axis=1)
    assert set(np.asarray(sv.spring_regions)[on_interface]) == {0, 1}


def test_pre_stretch_one_is_the_unstretched_model(models, mesh):
    """lambda0 = 1 leaves the parameters untouched (bit for bit)."""
    sv = models["springs_volume"]
    rest, k, a = sv.spring_parameters(Material(E, NU, cubic_coefficient=2.0))
    assert np.array_equal(np.asarray(rest), sv.rest_lengths)
    assert np.array_equal(np.asarray(k), sv.spring_factors * float(lame_parameters(E, NU)[1]))
    Dm, V = models["fem_linear"].stress_free_tets(jnp.ones(2))
    assert np.array_equal(np.asarray(Dm), models["fem_linear"].tet_Dm_inv) and np.array_equal(np.asarray(V), models["fem_linear"].tet_volumes)


# ------------------------------------------------------------------------- XPBD
def test_xpbd_constraints_honour_pre_stretch(mesh, models):
    """The XPBD constraint energy is the model's energy with pre-stretch: equal for
    springs_volume, plus the constant sum V0_eff (3 mu / 2 + mu^2 / (2 lam')) for stable
    neo-Hookean; the shrunk state is a zero of the pre-stretched layer's spring constraints."""
    rng = np.random.default_rng(2)
    x = jnp.asarray(mesh.points) * jnp.array([0.97, 0.98, 1.02]) + 1e-5 * rng.standard_normal(mesh.points.shape)
    lam0 = 1.06
    mat = _materials(lam0, 1.0)
    sv, snh = models["springs_volume"], models["stable_neo_hookean"]
    cons = xpbd_constraints(sv, mat)
    assert float(constraint_energy(cons, x)) == pytest.approx(float(sv.energy(x, mat)), rel=1e-12)
    shrunk = jnp.asarray(mesh.points) * jnp.array([1 / lam0, 1 / lam0, 1.0])
    top = np.asarray(sv.spring_regions) == 0
    np.testing.assert_allclose(np.asarray(cons[0].values(shrunk))[0][top], 0.0, atol=1e-15)
    lam, mu = (float(v) for v in lame_parameters(E, NU))
    V_eff = np.asarray(snh.stress_free_tets(jnp.array([lam0, 1.0]))[1])
    const = np.sum(V_eff) * (1.5 * mu + mu * mu / (2 * (lam + mu)))
    e_xpbd = float(constraint_energy(xpbd_constraints(snh, mat), x))
    assert e_xpbd - const == pytest.approx(float(snh.energy(x, mat)), rel=1e-9)


# ----------------------------------------------------------------------------- (e)
def test_bad_pre_stretch_raises(models, mesh):
    for bad in (0.0, -1.1, float("nan")):
        with pytest.raises(MaterialError, match="pre_stretch"):
            Material(E, NU, pre_stretch=bad)
    x = jnp.asarray(mesh.points)
    for bad in (0.0, -1.0, float("nan")):
        mat = eqx.tree_at(lambda m: m.pre_stretch, _materials(1.0, 1.0), jnp.array([bad, 1.0]))  # bypasses __check_init__
        for kind in MODELS:
            with pytest.raises(MaterialError, match="pre_stretch"):
                models[kind].energy(x, mat)
    mat = eqx.tree_at(lambda m: m.pre_stretch, _materials(1.0, 1.0), jnp.array([0.0, 1.0]))
    with pytest.raises(Exception, match="pre_stretch must be > 0"):
        model = models["fem_linear"]
        jax.jit(lambda x_, m_: model.energy(x_, m_))(x, mat).block_until_ready()


def test_springs_refuse_pre_stretch_beyond_the_lattice_range():
    """Cubes shrunk in x, y by 1/lambda0 have z edges whose factor (h/4) (3s - 2) (s = lambda0^-2)
    turns negative above lambda0 = sqrt(3/2)."""
    model = make_model(block(1e-3, 1), "springs_volume")
    lo, hi = model.pre_stretch_range[0]
    assert hi == pytest.approx(math.sqrt(1.5), rel=1e-12)
    assert lo == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-12)  # x and y edges: factor 2 - s
    model.energy(jnp.asarray(block(1e-3, 1).points), Material(E, NU, pre_stretch=1.2))
    with pytest.raises(ModelRangeError, match="pre_stretch"):
        model.energy(jnp.asarray(block(1e-3, 1).points), Material(E, NU, pre_stretch=1.25))


def test_surface_tension_conversion_is_the_linear_plane_stress_relation():
    m = Material(2e5, 0.45, pre_stretch=1.03)
    t = 1.5e-3
    T_ = float(surface_tension_from_pre_stretch(m, t))
    assert T_ == pytest.approx(2e5 * 0.03 / 0.55 * t, rel=1e-14)
    assert float(pre_stretch_from_surface_tension(m, T_, t)) == pytest.approx(1.03, rel=1e-14)
