"""Analytic and semi-analytic indentation references (DESIGN.md §3.5).

Rigid, frictionless, axisymmetric indenters pressed a depth ``d`` [m] into a linear
elastic solid of Young's modulus ``E`` [Pa] and Poisson's ratio ``nu`` [-]. Forces are in
N, lengths in m. Every function is a pure ``jax.numpy`` expression of its array arguments:
it broadcasts over arrays of depths (and of the other arguments), and works under
``jax.jit``, ``jax.grad`` and ``jax.vmap``. The indentation (plane-strain) modulus
``E* = E / (1 - nu^2)`` is :func:`difftissue.materials.indentation_modulus`.

Half-space (closed forms)
    - :func:`hertz_force` -- sphere (paraboloid) of radius ``R``:
      ``F = 4/3 E* sqrt(R) d^(3/2)``, contact radius ``a = sqrt(R d)``
      (Hertz 1882; Johnson, *Contact Mechanics*, 1985, ch. 3 and 5).
    - :func:`flat_punch_force` -- cylinder of radius ``a``: ``F = 2 a E* d``
      (Boussinesq; Sneddon 1965, Int. J. Eng. Sci. 3, 47-57).
    - :func:`cone_force` -- cone of half-angle ``theta``:
      ``F = (2/pi) E* tan(theta) d^2``, ``a = 2 d tan(theta) / pi`` (Sneddon 1965).

Layer of thickness ``h`` on a rigid base, bonded or lubricated (frictionless)
    - :func:`hayes_kappa`, :func:`layer_flat_punch_force` -- flat punch,
      ``F = 2 a E* d kappa(a/h, nu)`` (Hayes, Keer, Herrmann & Mockros 1972,
      J. Biomech. 5, 541-551). ``kappa`` is computed here by solving the Fredholm integral
      equation of the second kind of the problem, not read from a table.
    - :func:`layer_sphere_force`, :func:`layer_sphere_factor`,
      :func:`layer_sphere_contact_radius` -- paraboloidal (Hertz-type) indenter on the
      layer, the same integral equation with the contact radius fixed by the condition
      of zero edge pressure. Numerically exact (converged to about 1e-9 with the defaults).
    - :func:`dimitriadis_force`, :func:`dimitriadis_factor`,
      :func:`dimitriadis_coefficients` -- the fitted series of Dimitriadis, Horkay,
      Maresca, Kachar & Chadwick (2002, Biophys. J. 82, 2798-2810),
      ``F = F_Hertz [1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4]``,
      ``chi = sqrt(R d) / h`` (:func:`layer_chi`).

The layer solutions
-------------------
The surface of a layer (shear modulus ``mu``) under an axisymmetric normal pressure with
Hankel transform ``P(xi)`` deflects by ``w(r) = (1 - nu)/mu int_0^inf P(xi) L(xi h)
J0(xi r) dxi`` (:func:`layer_compliance` gives ``L``; ``L = 1`` is the half-space). With
``kappa = 3 - 4 nu`` (Lebedev & Ufliand 1958, J. Appl. Math. Mech. (PMM) 22; Vorovich,
Aleksandrov & Babeshko 1974):

    bonded base:      L(u) = (2 kappa sinh 2u - 4u) / (2 kappa cosh 2u + 1 + kappa^2 + 4u^2)
    lubricated base:  L(u) = (cosh 2u - 1) / (sinh 2u + 2u)

(``tests/test_analytic.py`` checks both against a direct solution of the Navier equations
for one Fourier mode.) Writing the pressure as ``P(xi) = int_0^a g(t) cos(xi t) dt`` and
inverting the Abel operator turns the mixed boundary-value problem into

    g(x) - (2 lam / pi) int_0^1 k(x, y) g(y) dy = g0(x),      0 <= x <= 1,
    k(x, y) = int_0^inf M(u) cos(lam u x) cos(lam u y) du,    M = 1 - L,  lam = a / h,

with ``g0 = 1`` for the flat punch (``kappa = int_0^1 g``) and
``g0 = d - (a^2/R) x^2`` for the paraboloid (the formulation of Hayes et al. 1972 for the
bonded layer; Dhaliwal & Rau 1970 for the thick layer). For the paraboloid, bounded pressure at the edge
requires ``g(1) = 0``; this fixes ``a``. With ``g = d g1 - (a^2/R) g2``:
``rho = g2(1)/g1(1) = d R / a^2``, ``chi = lam sqrt(rho)`` and
``F / F_Hertz = 3/2 (rho G1 - G2) / rho^(3/2)``, ``G_i = int_0^1 g_i`` (1 for Hertz).

The integral equation is solved by Nyström's method (``n_nodes`` Gauss-Legendre nodes on
[0, 1]); ``k`` by composite Gauss-Legendre quadrature on ``u`` in [0, 24] (``M`` decays
like ``u^2 exp(-2u)``). The contact radius comes from a Newton iteration on ``log(a/h)``
that runs on stopped gradients, followed by one differentiable Newton step: derivatives
are those of the implicit function theorem (exact at convergence, no backpropagation
through the iterations).

Validity: linear elasticity, small strain, frictionless contact, paraboloid in place of
the sphere (``a << R``) as in Hertz. The quadratures are validated for ``a/h <= 10``
(:data:`MAX_ASPECT_RATIO`) and ``chi <= 4`` (:data:`MAX_CHI`); concrete inputs beyond
are refused. The Dimitriadis series is a fit valid for ``chi`` below about 1 (it is 8 %
low at ``chi = 0.5`` and 20 % low at ``chi = 1`` for ``nu = 0.5``, see ``docs/analytic.md``).

Validation follows :class:`difftissue.materials.Material`: concrete (non-traced) inputs
are checked and bad values raise :class:`~difftissue.errors.MaterialError` (``E``,
``nu``) or :class:`~difftissue.errors.DifftissueError` (geometry, options); traced values
inside ``jit``/``grad`` are not checked.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .errors import DifftissueError, MaterialError
from .materials import _is_concrete, indentation_modulus

__all__ = [
    "BASES",
    "MAX_ASPECT_RATIO",
    "MAX_CHI",
    "hertz_force",
    "hertz_contact_radius",
    "flat_punch_force",
    "flat_punch_contact_radius",
    "cone_force",
    "cone_contact_radius",
    "layer_chi",
    "layer_compliance",
    "hayes_kappa",
    "layer_flat_punch_force",
    "layer_sphere_factor",
    "layer_sphere_force",
    "layer_sphere_contact_radius",
    "dimitriadis_coefficients",
    "dimitriadis_factor",
    "dimitriadis_force",
]

#: Layer base conditions: ``"bonded"`` (no slip on the rigid base) and ``"lubricated"``
#: (frictionless base: no normal displacement, no shear traction). Dimitriadis et al.
#: call the second one "not bonded".
BASES = ("bonded", "lubricated")

#: Largest contact radius / layer thickness ``a/h`` the layer quadratures are validated for.
MAX_ASPECT_RATIO = 10.0

#: Largest ``chi = sqrt(R d)/h`` accepted by :func:`layer_sphere_force` (``a/h`` stays below
#: :data:`MAX_ASPECT_RATIO`: ``a/h -> 2 chi`` for a thin incompressible bonded layer).
MAX_CHI = 4.0

_U_MAX = 24.0  # M(u) < 1e-17 beyond
_U_PANEL = 0.5
_U_ORDER = 16
_NEWTON_STEPS = 10
_DEFAULT_NODES = 32


# ------------------------------------------------------------------------ validation
def _check(name, value, ok, rule, unit="", error=DifftissueError):
    """Raise ``error`` if a concrete ``value`` is not finite or fails ``ok`` anywhere."""
    if value is None or not _is_concrete(value):
        return
    arr = np.asarray(value, dtype=float).reshape(-1)
    if not np.all(np.isfinite(arr)):
        raise error(f"{name} is not finite ({value!r})")
    bad = arr[~ok(arr)]
    if bad.size:
        u = f" {unit}" if unit else ""
        raise error(f"{name} = {float(bad[0]):g}{u} {rule}")


def _check_depth(depth):
    _check("depth", depth, lambda v: v >= 0, "must be >= 0 (indentation depth into the surface)", "m")


def _check_length(name, value):
    _check(name, value, lambda v: v > 0, "must be > 0", "m")


def _check_material(youngs_modulus, poisson_ratio):
    _check("youngs_modulus", youngs_modulus, lambda v: v > 0, "must be > 0", "Pa", MaterialError)
    _check_nu(poisson_ratio)


def _check_nu(poisson_ratio):
    _check(
        "poisson_ratio",
        poisson_ratio,
        lambda v: (v > -1.0) & (v <= 0.5),
        "must lie in (-1, 0.5] (0.5 is the incompressible limit, allowed in these closed forms)",
        error=MaterialError,
    )


def _check_angle(half_angle):
    _check(
        "half_angle",
        half_angle,
        lambda v: (v > 0) & (v < math.pi / 2),
        "rad must lie in (0, pi/2) (half-angle between the cone axis and its surface)",
    )


def _check_options(base, n_nodes):
    if base not in BASES:
        raise DifftissueError(f"unknown layer base {base!r}; choose one of {BASES}")
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, (int, np.integer)) or n_nodes < 8:
        raise DifftissueError(f"n_nodes must be an integer >= 8, got {n_nodes!r}")


def _float_dtype(*args):
    return jnp.result_type(*args, float)


# ------------------------------------------------------------------- half-space forms
def hertz_force(depth, youngs_modulus, poisson_ratio, radius):
    """Hertz force ``F = 4/3 E* sqrt(R) d^(3/2)`` [N] of a rigid sphere on a half-space.

    Args:
        depth: indentation depth ``d`` [m], >= 0 (any shape).
        youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        radius: sphere radius ``R`` [m], > 0.

    Returns:
        Force [N], the broadcast shape of the arguments. The sphere is the paraboloid
        ``r^2 / (2R)`` (``a << R``); Hertz (1882), Johnson (1985) ch. 5.
    """
    _check_depth(depth)
    _check_material(youngs_modulus, poisson_ratio)
    _check_length("radius", radius)
    estar = indentation_modulus(youngs_modulus, poisson_ratio)
    return 4.0 / 3.0 * estar * jnp.sqrt(radius) * jnp.power(depth, 1.5)


def hertz_contact_radius(depth, radius):
    """Hertz contact radius ``a = sqrt(R d)`` [m] (depth ``d`` [m] >= 0, radius ``R`` [m] > 0).

    Its derivative in ``d`` is infinite at ``d = 0``.
    """
    _check_depth(depth)
    _check_length("radius", radius)
    return jnp.sqrt(radius * depth)


def flat_punch_force(depth, youngs_modulus, poisson_ratio, radius):
    """Flat-ended cylinder on a half-space: ``F = 2 a E* d`` [N] (Boussinesq, Sneddon 1965).

    Args:
        depth: indentation depth ``d`` [m], >= 0.
        youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        radius: punch radius ``a`` [m], > 0 (the contact radius for every depth).
    """
    _check_depth(depth)
    _check_material(youngs_modulus, poisson_ratio)
    _check_length("radius", radius)
    return 2.0 * radius * indentation_modulus(youngs_modulus, poisson_ratio) * depth


def flat_punch_contact_radius(depth, radius):
    """Contact radius [m] of a flat punch: its radius ``a`` [m], broadcast against ``depth`` [m]."""
    _check_depth(depth)
    _check_length("radius", radius)
    depth = jnp.asarray(depth, dtype=_float_dtype(depth, radius))
    return jnp.broadcast_to(jnp.asarray(radius, dtype=depth.dtype), jnp.broadcast_shapes(jnp.shape(depth), jnp.shape(radius)))


def cone_force(depth, youngs_modulus, poisson_ratio, half_angle):
    """Rigid cone on a half-space: ``F = (2/pi) E* tan(theta) d^2`` [N] (Sneddon 1965).

    Args:
        depth: indentation depth ``d`` [m], >= 0.
        youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        half_angle: half-angle ``theta`` [rad] between axis and flank, in (0, pi/2).
    """
    _check_depth(depth)
    _check_material(youngs_modulus, poisson_ratio)
    _check_angle(half_angle)
    estar = indentation_modulus(youngs_modulus, poisson_ratio)
    return 2.0 / math.pi * estar * jnp.tan(half_angle) * depth**2


def cone_contact_radius(depth, half_angle):
    """Sneddon contact radius of a cone, ``a = 2 d tan(theta) / pi`` [m] (``d`` [m], ``theta`` [rad])."""
    _check_depth(depth)
    _check_angle(half_angle)
    return 2.0 / math.pi * jnp.tan(half_angle) * depth


def layer_chi(depth, radius, thickness):
    """``chi = sqrt(R d) / h`` [-]: Hertz contact radius over layer thickness.

    Gradient-safe at ``d = 0`` (returns 0 with zero gradient there; the true derivative
    is infinite but every force below multiplies it by ``d^(3/2)``).

    Args:
        depth: ``d`` [m], >= 0.  radius: ``R`` [m], > 0.  thickness: ``h`` [m], > 0.
    """
    _check_depth(depth)
    _check_length("radius", radius)
    _check_length("thickness", thickness)
    return _safe_chi(depth, radius, thickness)


def _safe_chi(depth, radius, thickness):
    depth = jnp.asarray(depth, dtype=_float_dtype(depth, radius, thickness))
    pos = depth > 0
    d = jnp.where(pos, depth, 1.0)
    return jnp.where(pos, jnp.sqrt(radius * d) / thickness, 0.0)


# ---------------------------------------------------------------------- layer kernels
def _kernel_complement(u, nu, base):
    """``M(u) = 1 - L(u)``, written without cancellation or overflow for large ``u``."""
    e2 = jnp.exp(-2.0 * u)
    if base == "bonded":
        k = 3.0 - 4.0 * nu
        c = 1.0 + k * k + 4.0 * u * u
        # 1 - L = (2k e^{-2u} + c + 4u) / (2k cosh 2u + c), times e^{-2u}/e^{-2u}
        return e2 * (2.0 * k * e2 + c + 4.0 * u) / (k * (1.0 + e2 * e2) + c * e2)
    # lubricated: 1 - L = (1 + 2u - e^{-2u}) / (sinh 2u + 2u)
    small = u < 1e-4
    us = jnp.where(small, 1.0, u)
    e2s = jnp.exp(-2.0 * us)
    big = 2.0 * e2s * (1.0 + 2.0 * us - e2s) / (1.0 - e2s * e2s + 4.0 * us * e2s)
    return jnp.where(small, 1.0 - u / 2.0, big)


def layer_compliance(u, poisson_ratio, *, base="bonded"):
    """Surface compliance ``L(u)`` [-] of a layer on a rigid base relative to a half-space.

    A normal surface pressure of wavenumber ``xi`` [1/m] deflects a layer of thickness ``h``
    by ``L(xi h)`` times the half-space deflection ``(1 - nu) p / (mu xi)``; ``u = xi h``.

    - ``base="bonded"``: ``L = (2k sinh 2u - 4u) / (2k cosh 2u + 1 + k^2 + 4u^2)``,
      ``k = 3 - 4 nu``; ``L ~ u (1 - 2nu) / (2 (1-nu)^2)`` as ``u -> 0`` (confined compression).
    - ``base="lubricated"``: ``L = (cosh 2u - 1) / (sinh 2u + 2u)``, independent of ``nu``;
      ``L ~ u/2`` as ``u -> 0``.

    Both tend to 1 as ``u -> inf``. Lebedev & Ufliand (1958); Vorovich et al. (1974).
    """
    _check_options(base, _DEFAULT_NODES)
    _check_nu(poisson_ratio)
    _check("u", u, lambda v: v >= 0, "must be >= 0 (u = wavenumber x thickness)")
    u = jnp.asarray(u, dtype=_float_dtype(u, poisson_ratio))
    return 1.0 - _kernel_complement(u, poisson_ratio, base)


@functools.lru_cache(maxsize=None)
def _gauss_legendre_01(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


@functools.lru_cache(maxsize=None)
def _u_rule():
    x, w = np.polynomial.legendre.leggauss(_U_ORDER)
    edges = np.arange(0.0, _U_MAX + 0.5 * _U_PANEL, _U_PANEL)
    lo, hi = edges[:-1, None], edges[1:, None]
    nodes = 0.5 * (hi - lo) * x[None, :] + 0.5 * (hi + lo)
    weights = np.broadcast_to(0.5 * (hi - lo) * w[None, :], nodes.shape)
    return nodes.reshape(-1), weights.reshape(-1)


def _kernel(lam, nu, x_rows, x_cols, base):
    """``k(x_i, y_j) = int M(u) cos(lam u x_i) cos(lam u y_j) du`` by quadrature."""
    dtype = x_cols.dtype
    u, wu = (jnp.asarray(a, dtype=dtype) for a in _u_rule())
    mw = wu * _kernel_complement(u, nu, base)
    cr = jnp.cos(lam * x_rows[:, None] * u[None, :])
    cc = jnp.cos(lam * x_cols[:, None] * u[None, :])
    return (cr * mw[None, :]) @ cc.T


def _nodes(n, dtype):
    x, w = _gauss_legendre_01(n)
    return jnp.asarray(x, dtype=dtype), jnp.asarray(w, dtype=dtype)


def _kappa_scalar(lam, nu, base, n):
    dtype = _float_dtype(lam, nu)
    x, w = _nodes(n, dtype)
    K = _kernel(lam, nu, x, x, base)
    A = jnp.eye(n, dtype=dtype) - (2.0 * lam / math.pi) * K * w[None, :]
    g = jnp.linalg.solve(A, jnp.ones((n,), dtype))
    return w @ g


def _sphere_parts(lam, nu, base, n):
    """``(rho, F/F_Hertz)`` of the paraboloid at contact radius ``a = lam h``."""
    dtype = _float_dtype(lam, nu)
    x, w = _nodes(n, dtype)
    xe = jnp.concatenate([x, jnp.ones((1,), dtype)])
    K = _kernel(lam, nu, xe, x, base)  # (n + 1, n): last row at x = 1
    c = 2.0 * lam / math.pi
    A = jnp.eye(n, dtype=dtype) - c * K[:n] * w[None, :]
    G = jnp.linalg.solve(A, jnp.stack([jnp.ones((n,), dtype), x * x], axis=1))
    edge = 1.0 + c * (K[n] * w) @ G  # g1(1), g2(1): both right-hand sides are 1 at x = 1
    integral = w @ G
    rho = edge[1] / edge[0]
    factor = 1.5 * (rho * integral[0] - integral[1]) / rho**1.5
    return rho, factor


def _sphere_scalar(chi, nu, base, n):
    """``(F/F_Hertz, a/h)`` for ``chi = sqrt(R d)/h``; Newton on ``s = log(a/h)``."""
    pos = chi > 0
    log_chi = jnp.log(jnp.where(pos, chi, 1.0))

    def log_rho_and_factor(s, nu_):
        rho, factor = _sphere_parts(jnp.exp(s), nu_, base, n)
        return jnp.log(rho), factor

    nu_c, log_chi_c = jax.lax.stop_gradient(nu), jax.lax.stop_gradient(log_chi)

    def newton(_, s):  # residual r(s) = s + log(rho)/2 - log(chi): log chi(a/h) - log chi
        (log_rho, _), (dlog_rho, _) = jax.jvp(lambda t: log_rho_and_factor(t, nu_c), (s,), (jnp.ones_like(s),))
        step = (s + 0.5 * log_rho - log_chi_c) / (1.0 + 0.5 * dlog_rho)
        return s - jnp.clip(step, -0.5, 0.5)

    s = jax.lax.fori_loop(0, _NEWTON_STEPS, newton, log_chi_c)  # Hertz start: a = sqrt(R d)
    s = jax.lax.stop_gradient(s)
    # Implicit function theorem, applied as one Newton step whose slopes are held constant:
    # delta = -r(s, theta) / r_s is ~1e-16 in value but carries d s*/d theta = -r_theta / r_s,
    # and factor(s*) = factor(s) + factor_s delta (first order exact at the root).
    _, (dlog_rho, dfactor) = jax.jvp(lambda t: log_rho_and_factor(t, nu_c), (s,), (jnp.ones_like(s),))
    log_rho, factor = log_rho_and_factor(s, nu)
    delta = -(s + 0.5 * log_rho - log_chi) / (1.0 + 0.5 * dlog_rho)
    factor = factor + dfactor * delta
    lam = jnp.exp(s) * (1.0 + delta)
    return jnp.where(pos, factor, 1.0), jnp.where(pos, lam, 0.0)


@functools.partial(jax.jit, static_argnames=("base", "n_nodes"))
def _sphere_jit(chi, nu, *, base, n_nodes):
    return jax.vmap(functools.partial(_sphere_scalar, base=base, n=n_nodes))(chi, nu)


@functools.partial(jax.jit, static_argnames=("base", "n_nodes"))
def _kappa_jit(aspect_ratio, nu, *, base, n_nodes):
    return jax.vmap(functools.partial(_kappa_scalar, base=base, n=n_nodes))(aspect_ratio, nu)


def _bucketed(fn, x, nu, pad, **static):
    """Apply the jitted 1-D ``fn`` to broadcast ``(x, nu)``, padded to a bucket length
    (8, 16, 32, ...) so that scalars and short arrays share one compilation."""
    dtype = _float_dtype(x, nu)
    x, nu = jnp.broadcast_arrays(jnp.asarray(x, dtype), jnp.asarray(nu, dtype))
    shape, size = x.shape, x.size
    bucket = max(8, 1 << max(size - 1, 0).bit_length())
    xf = jnp.concatenate([x.reshape(-1), jnp.full((bucket - size,), pad, dtype)])
    nf = jnp.concatenate([nu.reshape(-1), jnp.full((bucket - size,), 0.3, dtype)])
    out = fn(xf, nf, **static)
    if isinstance(out, tuple):
        return tuple(o[:size].reshape(shape) for o in out)
    return out[:size].reshape(shape)


def _sphere(chi, nu, *, base, n_nodes):
    return _bucketed(_sphere_jit, chi, nu, 0.5, base=base, n_nodes=n_nodes)


def _kappa(aspect_ratio, nu, *, base, n_nodes):
    return _bucketed(_kappa_jit, aspect_ratio, nu, 0.5, base=base, n_nodes=n_nodes)


# --------------------------------------------------------------------- flat punch on layer
def hayes_kappa(aspect_ratio, poisson_ratio, *, base="bonded", n_nodes=_DEFAULT_NODES):
    """Thickness factor ``kappa(a/h, nu)`` [-] of a flat punch on a layer (Hayes et al. 1972).

    ``F = 2 a E* d kappa`` for a rigid flat-ended cylinder of radius ``a`` on a layer of
    thickness ``h`` on a rigid base; ``kappa -> 1`` as ``a/h -> 0`` (half-space). Hayes et
    al. write it ``G = P (1 - nu) / (4 a kappa w)``. Computed by solving the integral
    equation (module docstring) with ``n_nodes`` Nyström nodes; with the default 32 it is
    converged to 1e-9 for ``a/h <= 5`` and 7e-7 at ``a/h = 10``. Reference values: ``kappa(1, 0.5) = 3.619``
    (Hayes' table: 3.609), ``kappa(2, 0.5) = 9.149`` (Hayes: 9.069); see docs/analytic.md.

    Args:
        aspect_ratio: ``a/h`` [-], in [0, :data:`MAX_ASPECT_RATIO`].
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        base: ``"bonded"`` (Hayes' case) or ``"lubricated"`` (frictionless base).
        n_nodes: Nyström nodes on [0, 1] (static).
    """
    _check_options(base, n_nodes)
    _check_nu(poisson_ratio)
    _check(
        "aspect_ratio",
        aspect_ratio,
        lambda v: (v >= 0) & (v <= MAX_ASPECT_RATIO),
        f"must lie in [0, {MAX_ASPECT_RATIO:g}] (contact radius / layer thickness; the quadrature is validated up to {MAX_ASPECT_RATIO:g})",
    )
    dtype = _float_dtype(aspect_ratio, poisson_ratio)
    return _kappa(jnp.asarray(aspect_ratio, dtype), jnp.asarray(poisson_ratio, dtype), base=base, n_nodes=int(n_nodes))


def layer_flat_punch_force(depth, youngs_modulus, poisson_ratio, radius, thickness, *, base="bonded", n_nodes=_DEFAULT_NODES):
    """Flat punch on a layer: ``F = 2 a E* d kappa(a/h, nu)`` [N] (Hayes et al. 1972).

    Args:
        depth: indentation depth ``d`` [m], >= 0.
        youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        radius: punch radius ``a`` [m], > 0.
        thickness: layer thickness ``h`` [m], > 0, with ``a/h <= MAX_ASPECT_RATIO``.
        base: ``"bonded"`` or ``"lubricated"``.
        n_nodes: Nyström nodes (static).
    """
    _check_depth(depth)
    _check_material(youngs_modulus, poisson_ratio)
    _check_length("radius", radius)
    _check_length("thickness", thickness)
    kappa = hayes_kappa(jnp.asarray(radius) / jnp.asarray(thickness), poisson_ratio, base=base, n_nodes=n_nodes)
    return flat_punch_force(depth, youngs_modulus, poisson_ratio, radius) * kappa


# ------------------------------------------------------------------------ sphere on layer
def _check_chi(chi):
    _check(
        "chi",
        chi,
        lambda v: (v >= 0) & (v <= MAX_CHI),
        f"must lie in [0, {MAX_CHI:g}] (chi = sqrt(R d)/h; the layer solution is validated up to {MAX_CHI:g})",
    )


def layer_sphere_factor(chi, poisson_ratio, *, base="bonded", n_nodes=_DEFAULT_NODES):
    """Exact ``F / F_Hertz`` [-] of a paraboloid on a layer on a rigid base, vs ``chi = sqrt(R d)/h``.

    Solves the layer integral equation with the contact radius from zero edge pressure
    (module docstring). Limits: 1 as ``chi -> 0`` (slope ``2 m0 / pi``,
    ``m0 = int_0^inf (1 - L)``); for a thin incompressible bonded layer
    ``F / F_Hertz -> 3 pi chi^3 / 8`` (``F -> 2 pi mu R^2 d^3 / h^3``), for a thin
    compressible bonded layer ``-> 3 pi (1-nu)^2 chi / (4 (1-2nu))`` (confined
    compression). At ``chi = 0.5``, ``nu = 0.5`` (bonded) it is 2.156.

    Args:
        chi: ``sqrt(R d)/h`` [-], in [0, :data:`MAX_CHI`].
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        base: ``"bonded"`` or ``"lubricated"`` (the lubricated result does not depend on ``nu``).
        n_nodes: Nyström nodes (static).
    """
    _check_options(base, n_nodes)
    _check_nu(poisson_ratio)
    _check_chi(chi)
    dtype = _float_dtype(chi, poisson_ratio)
    factor, _ = _sphere(jnp.asarray(chi, dtype), jnp.asarray(poisson_ratio, dtype), base=base, n_nodes=int(n_nodes))
    return factor


def _layer_sphere_checks(depth, youngs_modulus, poisson_ratio, radius, thickness, base, n_nodes):
    _check_options(base, n_nodes)
    _check_depth(depth)
    if youngs_modulus is not None:
        _check_material(youngs_modulus, poisson_ratio)
    else:
        _check_nu(poisson_ratio)
    _check_length("radius", radius)
    _check_length("thickness", thickness)
    if all(_is_concrete(v) for v in (depth, radius, thickness)):
        _check_chi(np.sqrt(np.asarray(radius, float) * np.asarray(depth, float)) / np.asarray(thickness, float))


def layer_sphere_force(depth, youngs_modulus, poisson_ratio, radius, thickness, *, base="bonded", n_nodes=_DEFAULT_NODES):
    """Force [N] of a rigid sphere (paraboloid) on an elastic layer on a rigid base.

    ``F = F_Hertz(d) * layer_sphere_factor(sqrt(R d)/h, nu)``, the numerically exact
    solution of the layer contact problem (see :func:`layer_sphere_factor`).

    Args:
        depth: indentation depth ``d`` [m], >= 0 (any shape; vectorised).
        youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        radius: sphere radius ``R`` [m], > 0.
        thickness: layer thickness ``h`` [m], > 0; ``sqrt(R d)/h <= MAX_CHI``.
        base: ``"bonded"`` or ``"lubricated"``.
        n_nodes: Nyström nodes (static).
    """
    _layer_sphere_checks(depth, youngs_modulus, poisson_ratio, radius, thickness, base, n_nodes)
    chi = _safe_chi(depth, radius, thickness)
    dtype = _float_dtype(chi, poisson_ratio)
    factor, _ = _sphere(chi, jnp.asarray(poisson_ratio, dtype), base=base, n_nodes=int(n_nodes))
    estar = indentation_modulus(youngs_modulus, poisson_ratio)
    return 4.0 / 3.0 * estar * jnp.sqrt(radius) * jnp.power(depth, 1.5) * factor


def layer_sphere_contact_radius(depth, poisson_ratio, radius, thickness, *, base="bonded", n_nodes=_DEFAULT_NODES):
    """Contact radius ``a`` [m] of a sphere (paraboloid) on a layer (zero edge pressure).

    ``a -> sqrt(R d)`` (Hertz) for a thick layer; ``a -> 2 sqrt(R d)`` for a thin
    incompressible bonded layer and ``sqrt(2 R d)`` for a thin compressible one.

    Args:
        depth: ``d`` [m], >= 0.  poisson_ratio: ``nu`` [-].  radius: ``R`` [m], > 0.
        thickness: ``h`` [m], > 0.  base, n_nodes: as in :func:`layer_sphere_force`.
    """
    _layer_sphere_checks(depth, None, poisson_ratio, radius, thickness, base, n_nodes)
    chi = _safe_chi(depth, radius, thickness)
    dtype = _float_dtype(chi, poisson_ratio)
    _, lam = _sphere(chi, jnp.asarray(poisson_ratio, dtype), base=base, n_nodes=int(n_nodes))
    return lam * thickness


# --------------------------------------------------------------------------- Dimitriadis
def dimitriadis_coefficients(poisson_ratio, *, base="bonded"):
    """Coefficients ``(c1, c2, c3, c4)`` [-] of the Dimitriadis et al. (2002) series.

    ``F / F_Hertz = 1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4`` with

        c1 = -2 alpha0 / pi,             c2 = 4 alpha0^2 / pi^2,
        c3 = -8 (alpha0^3 + 4 pi^2 beta0 / 15) / pi^3,
        c4 = 16 alpha0 (alpha0^3 + 3 pi^2 beta0 / 5) / pi^4,

    bonded:      ``alpha0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2) / (1 - nu)``,
                 ``beta0 = (0.6387 - 1.0277 nu + 1.5164 nu^2) / (1 - nu)``;
    lubricated ("not bonded"): ``alpha0 = -0.347 (3 - 2 nu) / (1 - nu)``,
                 ``beta0 = 0.056 (5 - 2 nu) / (1 - nu)``.

    At ``nu = 0.5`` (bonded): 1.133, 1.283, 0.769, -0.0975. The sign of ``c4`` follows
    from the general expression above (as implemented in AtomicJ,
    github.com/pawelHerm/AtomicJ, HertzianThinSampleParaboloidChadwick.java); some AFM
    tools hard-code ``+0.0975`` for the quartic term (a 0.6 % difference at chi = 0.5).

    Args:
        poisson_ratio: ``nu`` [-], in (-1, 0.5].
        base: ``"bonded"`` or ``"lubricated"``.
    """
    _check_options(base, _DEFAULT_NODES)
    _check_nu(poisson_ratio)
    nu = jnp.asarray(poisson_ratio, dtype=_float_dtype(poisson_ratio))
    if base == "bonded":
        alpha = -(1.2876 - 1.4678 * nu + 1.3442 * nu**2) / (1.0 - nu)
        beta = (0.6387 - 1.0277 * nu + 1.5164 * nu**2) / (1.0 - nu)
    else:
        alpha = -0.347 * (3.0 - 2.0 * nu) / (1.0 - nu)
        beta = 0.056 * (5.0 - 2.0 * nu) / (1.0 - nu)
    pi = math.pi
    c1 = -2.0 * alpha / pi
    c2 = 4.0 * alpha**2 / pi**2
    c3 = -8.0 / pi**3 * (alpha**3 + 4.0 * pi**2 * beta / 15.0)
    c4 = 16.0 * alpha / pi**4 * (alpha**3 + 3.0 * pi**2 * beta / 5.0)
    return c1, c2, c3, c4


def dimitriadis_factor(chi, poisson_ratio, *, base="bonded"):
    """Dimitriadis et al. (2002) ``F / F_Hertz`` [-] for ``chi = sqrt(R d)/h`` >= 0.

    A fitted series, accurate for small ``chi`` (under 1 % below ``chi = 0.2``) and
    increasingly low above (bonded, nu = 0.5: -8 % at ``chi = 0.5``, -20 % at 1 against
    :func:`layer_sphere_factor`). See :func:`dimitriadis_coefficients`.
    """
    _check("chi", chi, lambda v: v >= 0, "must be >= 0 (chi = sqrt(R d)/h)")
    c1, c2, c3, c4 = dimitriadis_coefficients(poisson_ratio, base=base)
    chi = jnp.asarray(chi, dtype=_float_dtype(chi, poisson_ratio))
    return 1.0 + chi * (c1 + chi * (c2 + chi * (c3 + chi * c4)))


def dimitriadis_force(depth, youngs_modulus, poisson_ratio, radius, thickness, *, base="bonded"):
    """Force [N] of a sphere on a thin layer by the Dimitriadis et al. (2002) series.

    ``F = 4/3 E* sqrt(R) d^(3/2) [1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4]``,
    ``chi = sqrt(R d)/h``; ``E*`` = ``E / (1 - nu^2)``, which at ``nu = 0.5`` is the
    paper's ``16 E / 9`` prefactor.

    Args:
        depth: ``d`` [m], >= 0.  youngs_modulus: ``E`` [Pa], > 0.
        poisson_ratio: ``nu`` [-], in (-1, 0.5].  radius: ``R`` [m], > 0.
        thickness: ``h`` [m], > 0.  base: ``"bonded"`` or ``"lubricated"`` ("not bonded").
    """
    _check_depth(depth)
    _check_material(youngs_modulus, poisson_ratio)
    _check_length("radius", radius)
    _check_length("thickness", thickness)
    chi = _safe_chi(depth, radius, thickness)
    factor = dimitriadis_factor(chi, poisson_ratio, base=base)
    estar = indentation_modulus(youngs_modulus, poisson_ratio)
    return 4.0 / 3.0 * estar * jnp.sqrt(radius) * jnp.power(depth, 1.5) * factor
