"""Material validation, conversions against their formulas, lattice elasticity, transforms."""

import itertools

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from difftissue import errors
from difftissue.materials import (
    DEFAULT_TRANSFORMS,
    Identity,
    Log,
    Material,
    MaterialParameterization,
    ScaledLogit,
    bulk_modulus,
    cubic_spring_coefficient,
    distance_compliance,
    equibiaxial_pre_stress,
    lame_parameters,
    lattice_spring_constants,
    neo_hookean_xpbd_compliances,
    p_wave_modulus,
    indentation_modulus,
    pre_stretch_from_surface_tension,
    shear_modulus,
    surface_tension_from_pre_stretch,
    volume_compliance,
    volume_constraint_modulus,
    youngs_poisson_from_lame,
)

CASES = [(1e3, 0.0), (5e3, 0.25), (16.29e3, 0.3), (2e5, 0.45), (1e6, 0.49), (7.0, -0.5), (3e4, 0.499)]


@pytest.mark.parametrize("E,nu", CASES)
def test_moduli_match_formulas(E, nu):
    lam, mu = lame_parameters(E, nu)
    assert lam == pytest.approx(E * nu / ((1 + nu) * (1 - 2 * nu)), rel=1e-14)
    assert mu == pytest.approx(E / (2 * (1 + nu)), rel=1e-14)
    assert shear_modulus(E, nu) == pytest.approx(mu, rel=1e-14)
    K = bulk_modulus(E, nu)
    assert K == pytest.approx(lam + 2 * mu / 3, rel=1e-12)
    assert p_wave_modulus(E, nu) == pytest.approx(lam + 2 * mu, rel=1e-12)
    assert indentation_modulus(E, nu) == pytest.approx(E / (1 - nu**2), rel=1e-14)
    E2, nu2 = youngs_poisson_from_lame(lam, mu)
    assert E2 == pytest.approx(E, rel=1e-12) and nu2 == pytest.approx(nu, rel=1e-12, abs=1e-15)
    m = Material(E, nu)
    assert m.lame[0] == lam and m.shear_modulus == mu and m.bulk_modulus == K


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(youngs_modulus=0.0, poisson_ratio=0.3), "youngs_modulus = 0 Pa must be > 0"),
        (dict(youngs_modulus=-5.0, poisson_ratio=0.3), "youngs_modulus"),
        (dict(youngs_modulus=1e3, poisson_ratio=0.5), "incompressible limit"),
        (dict(youngs_modulus=1e3, poisson_ratio=0.7), "poisson_ratio = 0.7"),
        (dict(youngs_modulus=1e3, poisson_ratio=-1.0), "poisson_ratio"),
        (dict(youngs_modulus=float("nan"), poisson_ratio=0.3), "youngs_modulus is not finite"),
        (dict(youngs_modulus=1e3, poisson_ratio=float("inf")), "poisson_ratio is not finite"),
        (dict(youngs_modulus=1e3, poisson_ratio=0.3, density=0.0), "density"),
        (dict(youngs_modulus=1e3, poisson_ratio=0.3, pre_stretch=-1.0), "pre_stretch"),
        (dict(youngs_modulus=1e3, poisson_ratio=0.3, cubic_coefficient=float("nan")), "cubic_coefficient"),
    ],
)
def test_material_validation_names_the_field(kwargs, match):
    with pytest.raises(errors.MaterialError, match=match):
        Material(**kwargs)


def test_material_is_a_differentiable_pytree_and_traced_values_are_not_checked():
    def f(E, nu):
        m = Material(E, nu)  # values are tracers here: no Python-side check
        return m.shear_modulus

    assert jax.jit(f)(2.0e3, 0.25) == pytest.approx(800.0)
    g = jax.grad(lambda m: m.bulk_modulus)(Material(3.0e3, 0.25))
    assert isinstance(g, Material)
    assert g.youngs_modulus == pytest.approx(1.0 / (3 * (1 - 0.5)))
    with pytest.raises(errors.MaterialError, match="unknown material field"):
        Material(1.0, 0.3).replace(stiffness=2.0)
    assert Material(1.0, 0.3).replace(poisson_ratio=0.4).poisson_ratio == 0.4


# ---------------------------------------------------------------- spring lattice
def _cube_lattice_energy_density(k, strain, h):
    """Energy density of one cube's 24 springs (per-cube constants) under a small affine strain.

    In an infinite lattice every spring is shared by as many cubes as it has per-cube copies,
    so one cube's springs with per-cube constants carry exactly the energy of one cell.
    """
    corners = np.array([[(v >> 0) & 1, (v >> 1) & 1, (v >> 2) & 1] for v in range(8)], dtype=float) * h
    energy = 0.0
    for a, b in itertools.combinations(range(8), 2):
        nbits = bin(a ^ b).count("1")
        if nbits == 3:
            continue  # no body diagonals in the lattice
        d = corners[b] - corners[a]
        L0 = np.linalg.norm(d)
        n = d / L0
        ext = L0 * n @ strain @ n  # linearised extension
        kk = k.k_edge if nbits == 1 else k.k_diag
        energy += 0.5 * kk * ext**2
    return energy / h**3 + 0.5 * k.volume_modulus * np.trace(strain) ** 2


def _isotropic_energy_density(lam, mu, eps):
    return 0.5 * lam * np.trace(eps) ** 2 + mu * np.sum(eps * eps)


@pytest.mark.parametrize("nu", [0.25, 0.3, 0.45, 0.49])
def test_isotropic_volume_lattice_reproduces_isotropic_elasticity(nu):
    m = Material(2.0e5, nu)
    h = 1e-3
    k = lattice_spring_constants(m, h)
    lam, mu = m.lame
    assert k.k_edge == pytest.approx(mu * h / 4) and k.k_diag == pytest.approx(mu * h / 2)
    assert k.volume_modulus == pytest.approx(lam - mu)
    assert volume_constraint_modulus(m) == pytest.approx(lam - mu)
    rng = np.random.default_rng(1)
    for _ in range(5):
        a = rng.normal(size=(3, 3)) * 1e-3
        eps = 0.5 * (a + a.T)
        assert _cube_lattice_energy_density(k, eps, h) == pytest.approx(_isotropic_energy_density(lam, mu, eps), rel=1e-12)


@pytest.mark.parametrize("nu", [0.1, 0.25, 1 / 3])
def test_pure_lattice_matches_c11_c12_with_cauchy_relation(nu):
    E, h = 1.0e4, 2e-3
    m = Material(E, nu)
    k = lattice_spring_constants(m, h, model="pure_lattice")
    assert k.k_edge == pytest.approx((1 - 3 * nu) * E * h / (4 * (1 + nu) * (1 - 2 * nu)), rel=1e-12, abs=1e-12)
    assert k.k_diag == pytest.approx(nu * E * h / (2 * (1 + nu) * (1 - 2 * nu)), rel=1e-12)
    lam, mu = m.lame
    C11, C12, C44 = lam + 2 * mu, lam, lam  # Cauchy: C44 = C12
    rng = np.random.default_rng(2)
    for _ in range(5):
        a = rng.normal(size=(3, 3)) * 1e-3
        e = 0.5 * (a + a.T)
        cubic = 0.5 * C11 * np.sum(np.diag(e) ** 2) + C12 * (e[0, 0] * e[1, 1] + e[1, 1] * e[2, 2] + e[0, 0] * e[2, 2]) + 2 * C44 * (e[0, 1] ** 2 + e[1, 2] ** 2 + e[0, 2] ** 2)
        assert _cube_lattice_energy_density(k, e, h) == pytest.approx(cubic, rel=1e-12)
        if nu == 0.25:  # isotropic only there
            assert _cube_lattice_energy_density(k, e, h) == pytest.approx(_isotropic_energy_density(lam, mu, e), rel=1e-12)


def test_lattice_model_ranges_are_refused_with_reasons():
    with pytest.raises(errors.ModelRangeError, match="unstable.*volume term"):
        lattice_spring_constants(Material(1e4, 0.45), 1e-3, model="pure_lattice")
    with pytest.raises(errors.ModelRangeError, match="no shear stiffness|vanish"):
        lattice_spring_constants(Material(1e4, -0.2), 1e-3, model="pure_lattice")
    with pytest.raises(errors.ModelRangeError, match="1/4 <= nu"):
        lattice_spring_constants(Material(1e4, 0.2), 1e-3)
    with pytest.raises(errors.ModelRangeError, match="unknown lattice model"):
        lattice_spring_constants(Material(1e4, 0.3), 1e-3, model="springs")
    with pytest.raises(errors.MaterialError, match="cell_size"):
        lattice_spring_constants(Material(1e4, 0.3), -1e-3)


def test_cubic_spring_coefficient_follows_the_uniaxial_law():
    m = Material(1e4, 0.45, cubic_coefficient=3.0)
    h = 1e-3
    k = lattice_spring_constants(m, h)
    assert k.a_edge == pytest.approx(3.0 * k.k_edge / h**2)
    assert k.a_diag == pytest.approx(3.0 * k.k_diag / (2 * h**2))
    # F = k x + a x^3 with x = eps L0 equals k L0 (eps + b eps^3).
    eps, L0, kk = 0.1, 2e-3, 5.0
    a = cubic_spring_coefficient(kk, L0, 3.0)
    assert kk * eps * L0 + a * (eps * L0) ** 3 == pytest.approx(kk * L0 * (eps + 3.0 * eps**3))


def test_xpbd_compliances():
    m = Material(3e3, 0.45)
    lam, mu = m.lame
    V0 = 2e-9
    c = neo_hookean_xpbd_compliances(m, V0)
    assert c.deviatoric == pytest.approx(1 / (mu * V0))
    assert c.hydrostatic == pytest.approx(1 / ((lam + mu) * V0))
    assert c.gamma == pytest.approx(1 + mu / (lam + mu))
    assert distance_compliance(250.0) == pytest.approx(4e-3)
    assert volume_compliance(V0, lam - mu) == pytest.approx(V0 / (lam - mu))


def test_pre_stretch_and_surface_tension_round_trip():
    m = Material(2e5, 0.48, pre_stretch=1.05)
    assert equibiaxial_pre_stress(m) == pytest.approx(2e5 * 0.05 / 0.52)
    T = surface_tension_from_pre_stretch(m, 1.5e-3)
    assert T == pytest.approx(2e5 * 0.05 / 0.52 * 1.5e-3)
    assert pre_stretch_from_surface_tension(m, T, 1.5e-3) == pytest.approx(1.05)
    with pytest.raises(errors.MaterialError, match="thickness"):
        pre_stretch_from_surface_tension(m, T, 0.0)


# ---------------------------------------------------------------- transforms
def _central_difference(f, u, h=1e-6):
    return (f(u + h) - f(u - h)) / (2 * h)


@pytest.mark.parametrize("transform", [Log(), Log(scale=1e3), Log(lower=1.0, scale=0.1), ScaledLogit(), ScaledLogit(0.0, 0.499), Identity()])
def test_transforms_are_bijective_and_differentiable(transform):
    rng = np.random.default_rng(3)
    for u in rng.normal(size=7) * 2:
        v = transform.forward(u)
        assert float(transform.inverse(v)) == pytest.approx(u, rel=1e-9, abs=1e-9)
        g = jax.grad(lambda x: transform.forward(x))(u)
        fd = _central_difference(lambda x: float(transform.forward(x)), float(u), h=1e-6 * max(1.0, abs(u)))
        assert float(g) == pytest.approx(fd, rel=1e-7)
        gi = jax.grad(lambda x: transform.inverse(x))(v)
        assert float(gi) * float(g) == pytest.approx(1.0, rel=1e-9)


@settings(max_examples=50, deadline=None)
@given(st.floats(-0.999, 0.499), st.floats(1.0, 1e7))
def test_default_transforms_round_trip(nu, E):
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio"))
    m = Material(E, nu)
    back = param.unpack(param.pack(m), base=Material(1.0, 0.0))
    assert float(back.youngs_modulus) == pytest.approx(E, rel=1e-10)
    assert float(back.poisson_ratio) == pytest.approx(nu, rel=1e-9, abs=1e-11)


def test_transform_bounds_are_enforced():
    with pytest.raises(errors.MaterialError, match="upper bound"):
        ScaledLogit(0.0, 0.499).inverse(0.5)
    with pytest.raises(errors.MaterialError, match="lower bound"):
        Log().inverse(0.0)
    with pytest.raises(errors.MaterialError, match="upper > lower"):
        ScaledLogit(0.5, 0.1)
    with pytest.raises(errors.MaterialError, match="non-finite"):
        Log().inverse(float("nan"))
    # Any real u maps strictly inside the bounds.
    for u in (-50.0, 0.0, 50.0):
        v = float(ScaledLogit(0.0, 0.499).forward(u))
        assert 0.0 <= v <= 0.499


def test_parameterization_gradient_matches_finite_differences():
    param = MaterialParameterization(
        ("youngs_modulus", "poisson_ratio", "cubic_coefficient"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.499)}
    )
    base = Material(1.0, 0.3, density=1050.0)
    u0 = param.pack(Material(5e3, 0.45, cubic_coefficient=2.0))

    def objective(u):
        m = param.unpack(u, base)
        lam, mu = m.lame
        return lam * 1e-3 + mu**2 * 1e-6 + m.cubic_coefficient * m.youngs_modulus * 1e-4 + m.density * 0

    g = np.asarray(jax.grad(objective)(u0))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1e-6
        fd = (objective(u0 + e) - objective(u0 - e)) / 2e-6
        assert g[i] == pytest.approx(float(fd), rel=1e-6)
    m = param.unpack(u0, base)
    assert float(m.density) == 1050.0 and float(m.poisson_ratio) == pytest.approx(0.45)
    assert jax.jit(lambda u: param.unpack(u, base).youngs_modulus)(u0) == pytest.approx(5e3)


def test_parameterization_errors():
    with pytest.raises(errors.MaterialError, match="unknown material field"):
        MaterialParameterization(("stiffness",))
    with pytest.raises(errors.MaterialError, match="repeat"):
        MaterialParameterization(("youngs_modulus", "youngs_modulus"))
    with pytest.raises(errors.MaterialError, match="not fitted"):
        MaterialParameterization(("youngs_modulus",), transforms={"poisson_ratio": ScaledLogit()})
    assert set(DEFAULT_TRANSFORMS) == {"youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch", "pre_stretch_y"}
