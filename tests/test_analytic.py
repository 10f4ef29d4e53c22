"""Analytic indentation references: formulas, literature values, limits, gradients, errors.

Literature checks (see docs/analytic.md for the sources):
- Hayes et al. (1972) flat-punch factor kappa for nu = 0.5, as tabulated in
  github.com/ImanKafian/CartilageStaticElasticModuliEstimation
  (cartilage_static_elastic_mod_estimator.py, ``poisson_inst_vals``).
- Dimitriadis et al. (2002) coefficients at nu = 0.5: 1.133, 1.283, 0.769, -0.0975 (bonded)
  and 0.884, 0.781, 0.386, 0.0048 (not bonded).
- DESIGN.md §3.5: bonded layer, chi = 0.5, nu = 0.5: exact F/F_Hertz ~= 2.16, Dimitriadis ~9 % less.

The numerical layer solutions are compiled per (base, n_nodes, bucket size); the tests reuse
a few shapes so the whole file stays well under a minute on two cores.
"""

import functools
import math
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from docblocks import assert_doctests_pass
from scipy.integrate import quad
from scipy.linalg import expm

from difftissue import analytic as an
from difftissue import errors
from difftissue.materials import indentation_modulus

DOCS = Path(__file__).resolve().parents[1] / "docs" / "analytic.md"

E, NU, R, H = 5.0e3, 0.45, 1.0e-3, 1.0e-3  # Pa, -, m, m


def sphere_force(E_, nu_, d_, h_):
    return an.layer_sphere_force(d_, E_, nu_, R, h_)


def series_force(E_, nu_, d_, h_):
    return an.dimitriadis_force(d_, E_, nu_, R, h_)


def punch_force(E_, nu_, d_, h_):
    return an.layer_flat_punch_force(d_, E_, nu_, R, h_)


@functools.partial(jax.jit, static_argnames="fn")
def value_and_grads(fn, E_, nu_, d_, h_):
    """``fn`` and its gradient in all four arguments at a batch of points, under
    ``jax.jit`` and ``jax.vmap``. One compilation per ``fn`` (for batches of 5) serves
    every test below; eager ``jax.grad`` through the layer solver would compile its
    forward and backward passes separately."""
    return jax.vmap(jax.value_and_grad(fn, argnums=(0, 1, 2, 3)))(E_, nu_, d_, h_)


# five states (E [Pa], nu, d [m], h [m]) at which gradients are checked
STATES = np.array(
    [
        [5.0e3, 0.45, 3.0e-4, 1.0e-3],
        [2.0e4, 0.30, 1.0e-4, 4.0e-4],
        [1.0e3, 0.49, 8.0e-4, 2.0e-3],
        [5.0e4, 0.00, 5.0e-5, 1.0e-3],
        [8.0e3, 0.40, 2.0e-3, 1.5e-3],
    ]
).T


@functools.lru_cache(maxsize=None)
def first_moment(nu, base="bonded"):
    """m0 = int_0^inf (1 - L(u)) du by adaptive quadrature."""
    L = jax.jit(lambda u: an.layer_compliance(u, nu, base=base))
    return quad(lambda u: 1.0 - float(L(u)), 0.0, 40.0, limit=200, epsabs=1e-13)[0]


def central_difference(f, x, rel=1e-5, abs_step=None):
    h = abs_step if abs_step is not None else rel * abs(x)
    return (f(x + h) - f(x - h)) / (2.0 * h)


# ------------------------------------------------------------------ half-space closed forms
def test_half_space_forces_match_formulas_and_broadcast_over_depth():
    d = np.array([0.0, 1e-5, 5e-5, 2e-4])
    estar = E / (1 - NU**2)
    np.testing.assert_allclose(an.hertz_force(d, E, NU, R), 4 / 3 * estar * np.sqrt(R) * d**1.5, rtol=1e-14)
    np.testing.assert_allclose(an.hertz_contact_radius(d, R), np.sqrt(R * d), rtol=1e-14)
    np.testing.assert_allclose(an.flat_punch_force(d, E, NU, R), 2 * R * estar * d, rtol=1e-14)
    np.testing.assert_allclose(an.flat_punch_contact_radius(d, R), np.full(4, R), rtol=0)
    theta = math.radians(35.0)
    np.testing.assert_allclose(an.cone_force(d, E, NU, theta), 2 / math.pi * estar * math.tan(theta) * d**2, rtol=1e-14)
    np.testing.assert_allclose(an.cone_contact_radius(d, theta), 2 * d * math.tan(theta) / math.pi, rtol=1e-14)
    assert float(indentation_modulus(E, 0.5)) == pytest.approx(4 * E / 3)
    assert an.hertz_force(d, E, NU, R).shape == (4,)
    # broadcasting: a column of moduli against a row of depths
    F = an.hertz_force(d[None, :], np.array([[1e3], [2e3]]), NU, R)
    assert F.shape == (2, 4) and np.allclose(F[1], 2 * F[0])


def test_half_space_forces_obey_sneddons_stiffness_relation():
    """dF/dd = 2 E* a(d) for every frictionless axisymmetric indenter (Sneddon 1965)."""
    d = jnp.linspace(1e-6, 3e-4, 7)
    estar = indentation_modulus(E, NU)
    theta = 0.6
    cases = [
        (lambda x: an.hertz_force(x, E, NU, R), an.hertz_contact_radius(d, R)),
        (lambda x: an.flat_punch_force(x, E, NU, R), an.flat_punch_contact_radius(d, R)),
        (lambda x: an.cone_force(x, E, NU, theta), an.cone_contact_radius(d, theta)),
    ]
    for force, a in cases:
        np.testing.assert_allclose(jax.vmap(jax.grad(force))(d), 2 * estar * a, rtol=1e-12)


def test_closed_form_gradients_match_central_differences():
    d, theta = 1.2e-4, 0.7
    fns = {
        "hertz": lambda E_, nu_, d_, g_: an.hertz_force(d_, E_, nu_, g_),
        "flat": lambda E_, nu_, d_, g_: an.flat_punch_force(d_, E_, nu_, g_),
        "cone": lambda E_, nu_, d_, g_: an.cone_force(d_, E_, nu_, g_),
    }
    for name, f in fns.items():
        geom = theta if name == "cone" else R
        args = (E, NU, d, geom)
        grads = jax.grad(f, argnums=(0, 1, 2, 3))(*args)
        for i, g in enumerate(grads):
            def fi(x, i=i):
                a = list(args)
                a[i] = x
                return float(f(*a))

            assert float(g) == pytest.approx(central_difference(fi, args[i]), rel=1e-6), (name, i)


def test_closed_forms_at_zero_depth_have_finite_gradients():
    for f in (an.hertz_force, an.flat_punch_force):
        g = jax.grad(f, argnums=(0, 1, 2))(0.0, E, NU, R)
        assert all(np.isfinite(float(x)) for x in g)
    assert float(jax.grad(an.hertz_force)(0.0, E, NU, R)) == 0.0


# ------------------------------------------------------------------------- layer kernels
def _navier_compliance(u, nu, base):
    """L(u) from a direct solution of the plane-strain Navier equations for one Fourier
    mode (displacements U(z) sin(x), W(z) cos(x), 0 <= z <= u), independent of the
    closed forms in difftissue.analytic."""
    mu, xi = 1.0, 1.0
    lam = 2 * mu * nu / (1 - 2 * nu)
    M = np.zeros((4, 4))  # y = (U, W, U', W'), y' = M y
    M[0, 2] = M[1, 3] = 1.0
    M[2, 0], M[2, 3] = (lam + 2 * mu) * xi**2 / mu, (lam + mu) * xi / mu
    M[3, 1], M[3, 2] = mu * xi**2 / (lam + 2 * mu), -(lam + mu) * xi / (lam + 2 * mu)
    P = expm(M * u)
    rows = [[lam * xi, 0, 0, lam + 2 * mu], [0, -xi, 1, 0]]  # top: s_zz = -1, s_xz = 0
    if base == "bonded":
        rows += [P[0], P[1]]  # U(h) = W(h) = 0
    else:
        rows += [P[1], P[2] - xi * P[1]]  # W(h) = 0, s_xz(h) = 0
    y0 = np.linalg.solve(np.array(rows), np.array([-1.0, 0.0, 0.0, 0.0]))
    return y0[1] * mu * xi / (1 - nu)  # relative to the half-space (1 - nu) p / (mu xi)


@pytest.mark.parametrize("base", an.BASES)
def test_layer_compliance_matches_a_direct_navier_solution(base):
    u = np.array([0.05, 0.3, 1.0, 2.5, 6.0])
    for nu in (0.0, 0.3, 0.45, 0.499):
        expected = [_navier_compliance(x, nu, base) for x in u]
        np.testing.assert_allclose(an.layer_compliance(u, nu, base=base), expected, rtol=1e-9)
    L = an.layer_compliance(np.array([0.0, 1e-6, 40.0]), 0.3, base=base)
    assert float(L[0]) == 0.0 and float(L[2]) == pytest.approx(1.0, abs=1e-15)


# ---------------------------------------------------------------------- flat punch on layer
# Hayes et al. (1972), nu = 0.5 column, a/h = 0.2 ... 2.0 (see module docstring for the source)
HAYES_A_OVER_H = np.array([0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0])
HAYES_KAPPA_NU_05 = np.array([1.281, 1.683, 2.211, 2.855, 3.609, 4.469, 5.441, 6.528, 7.735, 9.069])


@pytest.fixture(scope="module")
def kappa_nu05():
    return np.asarray(an.hayes_kappa(HAYES_A_OVER_H, 0.5))


def test_hayes_kappa_reproduces_hayes_table(kappa_nu05):
    rel = kappa_nu05 / HAYES_KAPPA_NU_05 - 1
    # Up to a/h = 0.6 the table is matched within 0.1 %; beyond, our converged
    # values are up to 0.9 % higher (at a/h = 2), growing smoothly with a/h. The Nystrom
    # solution is converged to 1e-9 there (test below), so we attribute the drift to the
    # 1972 numerics; 1 % is the stated tolerance.
    assert np.all(np.abs(rel[:3]) < 1.5e-3)
    assert np.all(np.abs(rel) < 1e-2)
    assert np.all(np.diff(rel) >= -2e-4)


def test_hayes_kappa_is_converged_and_tends_to_one_for_thick_layers():
    lam = np.array([1e-4, 1.0, 5.0, 10.0])
    k32 = np.asarray(an.hayes_kappa(lam, 0.5))
    k64 = np.asarray(an.hayes_kappa(lam, 0.5, n_nodes=64))
    np.testing.assert_allclose(k32, k64, rtol=1e-6)  # 7e-7 at a/h = 10, < 1e-9 below 5
    np.testing.assert_allclose(k32[:2], k64[:2], rtol=1e-10)
    assert (k32[0] - 1) / 1e-4 == pytest.approx(2 * first_moment(0.5) / math.pi, rel=1e-3)  # first order: 2 m0 a / (pi h)


def test_thin_layer_limits_of_the_flat_punch():
    lam = np.array([2.5, 5.0, 10.0])
    # compressible bonded layer: confined compression, F = pi a^2 M d / h
    nu = 0.3
    ratio = np.asarray(an.hayes_kappa(lam, nu)) / (math.pi / 2 * (1 - nu) ** 2 / (1 - 2 * nu) * lam)
    assert ratio[2] == pytest.approx(1.0, abs=0.03) and np.all(np.diff(ratio) < 0)
    c0, _ = np.linalg.solve(np.stack([np.ones(2), 1 / lam[1:]], 1), ratio[1:])  # Richardson, 1/lam error
    assert c0 == pytest.approx(1.0, abs=2e-3)
    # incompressible bonded layer (frictionless top): p = 3 mu d (a^2 - r^2) / (4 h^3)
    ratio = np.asarray(an.hayes_kappa(lam, 0.5)) / (3 * math.pi * lam**3 / 64)
    assert np.all(np.diff(ratio) < 0) and ratio[2] < 1.75
    c0 = np.linalg.solve(np.stack([np.ones(3), 1 / lam, 1 / lam**2], 1), ratio)[0]
    assert c0 == pytest.approx(1.0, abs=0.06)  # slow (1/lam) approach; three-term fit


def test_layer_flat_punch_force_and_lubricated_base():
    d = np.array([1e-5, 2e-5])
    F = an.layer_flat_punch_force(d, E, 0.5, R, R)
    np.testing.assert_allclose(F, an.flat_punch_force(d, E, 0.5, R) * an.hayes_kappa(1.0, 0.5), rtol=1e-14)
    k_lub = [float(an.hayes_kappa(1.0, nu, base="lubricated")) for nu in (0.0, 0.3, 0.5)]
    assert np.ptp(k_lub) < 1e-12 and 1.0 < k_lub[0] < float(an.hayes_kappa(1.0, 0.0))


# ------------------------------------------------------------------------- sphere on layer
CHI_TABLE = np.array([0.1, 0.2, 0.5, 1.0])


@pytest.fixture(scope="module")
def sphere_table():
    nu = np.array([[0.5], [0.45]])
    exact = np.asarray(an.layer_sphere_factor(CHI_TABLE[None, :], nu))
    dim = np.asarray(an.dimitriadis_factor(CHI_TABLE[None, :], nu))
    return exact, dim


def test_design_check_exact_and_dimitriadis_at_chi_05(sphere_table):
    """DESIGN.md §3.5: F/F_Hertz ~= 2.16 (exact) and ~9 % less (Dimitriadis) at chi = 0.5, nu = 0.5."""
    exact, dim = sphere_table
    assert exact[0, 2] == pytest.approx(2.16, abs=0.01)  # 2.1562
    assert dim[0, 2] == pytest.approx(1.9774, abs=1e-4)
    assert 0.07 < 1 - dim[0, 2] / exact[0, 2] < 0.10  # 8.3 % less


def test_series_and_exact_agree_for_thick_layers(sphere_table):
    exact, dim = sphere_table
    assert np.all(np.abs(dim[:, 0] / exact[:, 0] - 1) < 3e-3)  # chi = 0.1
    assert np.all(np.abs(dim[:, 1] / exact[:, 1] - 1) < 1.2e-2)  # chi = 0.2
    assert np.all(dim[:, 2:] < exact[:, 2:])  # the series is low for thinner layers
    # chi -> 0: Hertz, with slope 2 m0 / pi (Dimitriadis' -2 alpha0 / pi is 0.5 % higher)
    f = np.asarray(an.layer_sphere_factor(np.array([0.0, 1e-4]), 0.5))
    m0 = first_moment(0.5)
    assert f[0] == 1.0
    assert (f[1] - 1) / 1e-4 == pytest.approx(2 * m0 / math.pi, rel=2e-3)
    c1 = float(an.dimitriadis_coefficients(0.5)[0])
    assert c1 == pytest.approx(2 * m0 / math.pi, rel=6e-3)


def test_dimitriadis_coefficients_match_the_paper():
    c = [float(x) for x in an.dimitriadis_coefficients(0.5)]
    np.testing.assert_allclose(c, [1.133, 1.283, 0.769, -0.0975], atol=6e-4)
    c = [float(x) for x in an.dimitriadis_coefficients(0.5, base="lubricated")]
    np.testing.assert_allclose(c, [0.884, 0.781, 0.386, 0.0048], atol=6e-4)
    chi = 0.3
    poly = 1 + 1.133 * chi + 1.283 * chi**2 + 0.769 * chi**3 - 0.0975 * chi**4
    assert float(an.dimitriadis_factor(chi, 0.5)) == pytest.approx(poly, rel=2e-4)


def test_thin_layer_limits_of_the_sphere():
    chi = np.array([2.0, 3.0, 4.0])
    nu = 0.3  # compressible: confined compression, F = pi M R d^2 / h, a^2 = 2 R d
    f = np.asarray(an.layer_sphere_factor(chi, nu))
    np.testing.assert_allclose(f / (3 * math.pi / 4 * (1 - nu) ** 2 / (1 - 2 * nu) * chi), 1.0, atol=0.012)
    a = np.asarray(an.layer_sphere_contact_radius(chi**2 * H**2 / R, nu, R, H))
    a = a / np.sqrt(2 * R * chi**2 * H**2 / R)
    assert np.all(np.diff(a) > 0) and a[-1] == pytest.approx(1.0, abs=0.03)  # 0.95, 0.97, 0.98
    # incompressible: F = 2 pi mu R^2 d^3 / h^3, a = 2 sqrt(R d); approached like 1/chi
    f = np.asarray(an.layer_sphere_factor(chi, 0.5))
    ratio = f / (3 * math.pi / 8 * chi**3)
    assert np.all(np.diff(ratio) < 0)
    c0 = np.linalg.solve(np.stack([np.ones(3), 1 / chi, 1 / chi**2], 1), ratio)[0]
    assert c0 == pytest.approx(1.0, abs=0.06)
    a = np.asarray(an.layer_sphere_contact_radius(chi**2 * H**2 / R, 0.5, R, H)) / (chi * H)
    assert np.all(np.diff(a) > 0) and 1.6 < a[-1] < 2.0


def test_layer_sphere_is_converged():
    chi = np.array([0.5, 2.0, 4.0])
    f32 = np.asarray(an.layer_sphere_factor(chi, 0.5))
    f64 = np.asarray(an.layer_sphere_factor(chi, 0.5, n_nodes=64))
    np.testing.assert_allclose(f32, f64, rtol=1e-9)


@pytest.fixture(scope="module")
def lubricated_table():
    nu = np.array([[0.5], [0.0]])
    return np.asarray(an.layer_sphere_factor(CHI_TABLE[None, :], nu, base="lubricated"))


def test_lubricated_sphere_is_nu_independent_and_softer_than_bonded(lubricated_table, sphere_table):
    assert np.ptp(lubricated_table, axis=0).max() < 1e-12
    f = np.asarray(an.layer_sphere_factor(np.array([0.5, 4.0]), 0.3, base="lubricated"))
    assert f[0] == pytest.approx(lubricated_table[0, 2], rel=1e-12)
    assert np.all(lubricated_table[0] < sphere_table[0][1])  # below the bonded nu = 0.45 values
    # first order: 2 m0 / pi with m0 = 1.1676 for every nu; Dimitriadis' "not bonded"
    # series has -2 alpha0 / pi, 19 % higher at nu = 0.5 (docs/analytic.md)
    m0 = first_moment(0.3, "lubricated")
    assert m0 == pytest.approx(first_moment(0.5, "lubricated"), rel=1e-12)
    assert m0 == pytest.approx(1.1676, abs=1e-4)
    c1 = float(an.dimitriadis_coefficients(0.5, base="lubricated")[0])
    assert c1 / (2 * m0 / math.pi) == pytest.approx(1.189, abs=2e-3)


def test_sphere_stiffness_equals_flat_punch_stiffness_at_the_contact_radius():
    """dF/dd = 2 a E* kappa(a/h): the incremental stiffness of a frictionless contact is
    that of a flat punch of the current contact radius. Checks the contact radius (zero
    edge pressure), the force and the implicit-function gradient against the independent
    flat-punch solve (bonded base; the lubricated base differs only in the kernel)."""
    nu = np.full(5, 0.5)
    d = np.array([1e-6, 5e-5, 2.5e-4, 1e-3, 4e-3])
    _, grads = value_and_grads(sphere_force, np.full(5, E), nu, d, np.full(5, H))
    a = an.layer_sphere_contact_radius(d, nu, R, H)
    expected = 2 * a * indentation_modulus(E, nu) * an.hayes_kappa(a / H, nu)
    np.testing.assert_allclose(grads[2], expected, rtol=1e-10)


@pytest.mark.parametrize("fn", [sphere_force, series_force, punch_force], ids=lambda f: f.__name__)
def test_layer_gradients_match_central_differences_under_jit_and_vmap(fn):
    """Float64 central differences, rtol 1e-6, at five states. The layer solutions are
    smooth functions of their inputs at fixed quadrature; the Newton iteration converges
    to ~1e-15 and its derivative comes from the implicit function theorem, so the same
    tolerance as the closed forms holds (observed agreement 1e-9 to 1e-11). The values
    computed under jit + vmap equal the eager ones."""
    values, grads = value_and_grads(fn, *STATES)
    np.testing.assert_allclose(values, fn(*STATES), rtol=1e-12)
    for i in range(4):
        step = np.full(5, 1e-5) if i == 1 else 1e-5 * STATES[i]  # absolute step for nu
        up, down = STATES.copy(), STATES.copy()
        up[i] += step
        down[i] -= step
        fd = (np.asarray(fn(*up)) - np.asarray(fn(*down))) / (2 * step)
        np.testing.assert_allclose(grads[i], fd, rtol=1e-6, err_msg=f"{fn.__name__}, argument {i}")


def test_layer_forces_at_zero_depth_and_thick_layer():
    d = jnp.array([0.0, 1e-9])
    for fn in (an.layer_sphere_force, an.dimitriadis_force):
        F = fn(d, E, NU, R, H)
        assert float(F[0]) == 0.0
        assert float(F[1]) == pytest.approx(float(an.hertz_force(1e-9, E, NU, R)), rel=2e-3)
    for fn in (sphere_force, series_force):
        _, g = value_and_grads(fn, np.full(5, E), np.full(5, NU), np.zeros(5), np.full(5, H))
        assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g[2]) == 0.0)
    F_thick = an.layer_sphere_force(1e-6, E, NU, R, 1.0)  # chi = 1e-3
    assert float(F_thick) == pytest.approx(float(an.hertz_force(1e-6, E, NU, R)), rel=2e-3)


def test_float32_inputs_compute_in_float32():
    k = an.hayes_kappa(np.float32(1.0), np.float32(0.5))
    assert k.dtype == jnp.float32 and float(k) == pytest.approx(3.61873585, rel=1e-4)
    F = an.hertz_force(np.float32(1e-4), np.float32(E), np.float32(NU), np.float32(R))
    assert F.dtype == jnp.float32


# ------------------------------------------------------------------------------ validation
@pytest.mark.parametrize(
    "call,error,match",
    [
        (lambda: an.hertz_force(-1e-6, E, NU, R), errors.DifftissueError, "depth = -1e-06 m must be >= 0"),
        (lambda: an.hertz_force(np.array([0.0, -1.0]), E, NU, R), errors.DifftissueError, "depth"),
        (lambda: an.hertz_force(1e-6, E, NU, 0.0), errors.DifftissueError, "radius = 0 m must be > 0"),
        (lambda: an.flat_punch_force(1e-6, E, NU, -1e-3), errors.DifftissueError, "radius"),
        (lambda: an.hertz_force(1e-6, -E, NU, R), errors.MaterialError, "youngs_modulus"),
        (lambda: an.hertz_force(1e-6, E, 0.6, R), errors.MaterialError, r"poisson_ratio = 0.6 must lie in \(-1, 0.5\]"),
        (lambda: an.hertz_force(1e-6, E, -1.0, R), errors.MaterialError, "poisson_ratio"),
        (lambda: an.hertz_force(float("nan"), E, NU, R), errors.DifftissueError, "depth is not finite"),
        (lambda: an.cone_force(1e-6, E, NU, 0.0), errors.DifftissueError, r"half_angle = 0 rad must lie in \(0, pi/2\)"),
        (lambda: an.cone_force(1e-6, E, NU, math.pi / 2), errors.DifftissueError, "half_angle"),
        (lambda: an.cone_contact_radius(1e-6, 2.0), errors.DifftissueError, "half_angle"),
        (lambda: an.layer_sphere_force(1e-6, E, NU, R, 0.0), errors.DifftissueError, "thickness = 0 m"),
        (lambda: an.layer_sphere_force(1e-6, E, NU, R, H, base="glued"), errors.DifftissueError, "unknown layer base 'glued'"),
        (lambda: an.layer_sphere_force(1e-6, E, NU, R, H, n_nodes=4), errors.DifftissueError, "n_nodes"),
        (lambda: an.layer_sphere_force(0.1, E, NU, R, H), errors.DifftissueError, r"chi = 10 must lie in \[0, 4\]"),
        (lambda: an.layer_sphere_factor(-0.1, NU), errors.DifftissueError, "chi"),
        (lambda: an.hayes_kappa(11.0, NU), errors.DifftissueError, "aspect_ratio = 11"),
        (lambda: an.layer_flat_punch_force(1e-6, E, NU, 1e-2, 1e-4), errors.DifftissueError, "aspect_ratio = 100"),
        (lambda: an.dimitriadis_force(-1e-6, E, NU, R, H), errors.DifftissueError, "depth"),
        (lambda: an.dimitriadis_factor(0.5, 0.7), errors.MaterialError, "poisson_ratio"),
        (lambda: an.layer_compliance(1.0, NU, base="slippery"), errors.DifftissueError, "unknown layer base"),
    ],
)
def test_invalid_inputs_raise_named_errors(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_incompressible_limit_is_accepted_and_traced_values_are_not_checked():
    assert np.isfinite(float(an.hertz_force(1e-6, E, 0.5, R)))
    # inside jit the values are tracers: no Python-side check (as for Material)
    F = jax.jit(lambda d: an.hertz_force(d, E, NU, R))(-1.0)
    assert np.isnan(float(F))


# ------------------------------------------------------------------------------------ docs
def test_docs_examples_run():
    assert_doctests_pass(DOCS)


def test_docs_table_is_what_the_code_computes(sphere_table):
    exact, dim = sphere_table
    text = DOCS.read_text()
    block = text.split("<!-- table: bonded sphere -->", 1)[1].split("\n\n", 1)[0]
    rows = [r for r in block.strip().splitlines() if re.match(r"\|\s*\d", r)]
    assert len(rows) == len(CHI_TABLE)
    for i, row in enumerate(rows):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert float(cells[0]) == CHI_TABLE[i]
        numbers = [float(c.replace("−", "-").rstrip("%").strip()) for c in cells[1:]]
        for j, k in enumerate((0, 1)):  # nu = 0.5, 0.45: exact, Dimitriadis, difference %
            e, s, diff = numbers[3 * j : 3 * j + 3]
            assert e == pytest.approx(exact[k, i], abs=6e-4)
            assert s == pytest.approx(dim[k, i], abs=6e-4)
            assert diff == pytest.approx(100 * (dim[k, i] / exact[k, i] - 1), abs=0.06)


def test_docs_lubricated_table_is_what_the_code_computes(lubricated_table):
    text = DOCS.read_text()
    block = text.split("<!-- table: lubricated sphere -->", 1)[1].split("\n\n", 1)[0]
    rows = [r for r in block.strip().splitlines() if re.match(r"\|\s*\d", r)]
    series = {nu: np.asarray(an.dimitriadis_factor(CHI_TABLE, nu, base="lubricated")) for nu in (0.5, 0.45)}
    assert len(rows) == len(CHI_TABLE)
    for i, row in enumerate(rows):
        cells = [float(c.strip().replace("−", "-").rstrip("%").strip()) for c in row.strip().strip("|").split("|")]
        assert cells[0] == CHI_TABLE[i]
        assert cells[1] == pytest.approx(lubricated_table[0, i], abs=6e-4)
        for j, nu in enumerate((0.5, 0.45)):
            s, diff = cells[2 + 2 * j], cells[3 + 2 * j]
            assert s == pytest.approx(series[nu][i], abs=6e-4)
            assert diff == pytest.approx(100 * (series[nu][i] / lubricated_table[0, i] - 1), abs=0.06)
