"""Materials: isotropic elastic parameters, their conversions and fitting transforms.

All quantities are SI: Young's modulus and Lamé parameters in Pa, lengths in m,
spring constants in N/m, cubic spring coefficients in N/m^3, density in kg/m^3.

The conversions are plain functions of arrays so they work under ``jax.jit``,
``jax.grad`` and ``jax.vmap``. See ``docs/materials.md`` for the formulas and their
limits (the cell-size factor of the spring constants, the Cauchy relation of a pure
central-spring lattice, the lambda' = lambda + mu shift of stable neo-Hookean XPBD).
"""

from __future__ import annotations

import abc
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import MaterialError, ModelRangeError

__all__ = [
    "Material",
    "MATERIAL_FIELDS",
    "material_fields",
    "explicit_pre_stretch_y",
    "lame_parameters",
    "shear_modulus",
    "bulk_modulus",
    "p_wave_modulus",
    "indentation_modulus",
    "youngs_poisson_from_lame",
    "LatticeSpringConstants",
    "lattice_spring_constants",
    "cubic_spring_coefficient",
    "volume_constraint_modulus",
    "XPBDCompliances",
    "neo_hookean_xpbd_compliances",
    "distance_compliance",
    "volume_compliance",
    "equibiaxial_pre_stress",
    "biaxial_pre_stress",
    "surface_tension_from_pre_stretch",
    "pre_stretch_from_surface_tension",
    "Transform",
    "Identity",
    "Linear",
    "Log",
    "ScaledLogit",
    "MaterialParameterization",
    "DEFAULT_TRANSFORMS",
    "LATTICE_MODELS",
]

#: Discrete lattice models understood by :func:`lattice_spring_constants`.
LATTICE_MODELS = ("isotropic_volume", "pure_lattice")


def _is_concrete(tree) -> bool:
    """True when every leaf of ``tree`` has a value now (no tracer inside jit/grad/vmap).

    The one helper the package uses to decide between Python-side checks with clear errors
    (concrete values) and ``equinox.error_if`` (traced values).
    """
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


#: SI unit of every material field a fit or a card may hold ("1" for dimensionless); the one
#: table :data:`difftissue.fit.UNITS` and :data:`difftissue.export.card.PARAMETER_UNITS` name.
FIELD_UNITS: dict[str, str] = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "cubic_coefficient": "1",
    "density": "kg/m^3",
    "pre_stretch": "1",
    "pre_stretch_y": "1",
    "surface_tension": "N/m",
}

#: Every field of :class:`Material`, in order. ``pre_stretch_y`` may be None (isotropic
#: pre-stretch); :func:`material_fields` lists the fields one material holds.
MATERIAL_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch", "pre_stretch_y")


def material_fields(material) -> tuple[str, ...]:
    """The fields ``material`` holds values for: :data:`MATERIAL_FIELDS` without
    ``pre_stretch_y`` when it is None (isotropic pre-stretch)."""
    return MATERIAL_FIELDS if getattr(material, "pre_stretch_y", None) is not None else MATERIAL_FIELDS[:-1]


class Material(eqx.Module):
    """An isotropic, (optionally) strain-stiffening, pre-stretched tissue material.

    A pytree: every field is a differentiable leaf, so ``jax.grad`` of any function of a
    ``Material`` returns a ``Material`` of derivatives.

    Attributes:
        youngs_modulus: small-strain Young's modulus ``E`` [Pa], > 0.
        poisson_ratio: small-strain Poisson's ratio ``nu`` [-], in (-1, 1/2).
        cubic_coefficient: strain-stiffening coefficient ``b`` [-] of the *springs* of the
            ``springs_volume`` lattice: a spring of rest length ``L0`` and linear stiffness
            ``k`` gets ``a = b k / L0^2`` (force ``k x + a x^3``), i.e. ``sigma = E (eps +
            b eps^3)`` along each spring. The lattice as a material follows that law with a
            different ``b_c`` (:func:`difftissue.constitutive.continuum_cubic_coefficient`;
            nonzero at ``b = 0``); the FEM and stable neo-Hookean models ignore ``b``.
        density: mass density [kg/m^3], > 0 (soft tissue is close to 1000-1100).
        pre_stretch: in-plane pre-stretch ``lambda0`` [-] of a pre-tensioned layer (skin) along
            x, and along y too unless ``pre_stretch_y`` is given; 1 means no pre-tension. The
            stress-free state is the mesh shrunk by ``1/lambda0`` in x (and y).
            See :func:`difftissue.constitutive.surface_tension` for the surface tension [N/m]
            a model's layer carries (:func:`surface_tension_from_pre_stretch` is the linear
            formula).
        pre_stretch_y: in-plane pre-stretch ``lambda_y`` [-] along y, > 0, for an anisotropic
            pre-tension (skin along and across Langer's lines): the stress-free state is the
            mesh shrunk by ``diag(1/pre_stretch, 1/pre_stretch_y, 1)``. None (the default)
            means equal to ``pre_stretch`` (equibiaxial), and leaves the pytree's leaves
            exactly those of an isotropic material. The two surface tensions:
            :func:`difftissue.constitutive.surface_tensions`.

    Construction with concrete values validates the ranges and raises
    :class:`~difftissue.errors.MaterialError` naming the field. Inside ``jit`` the values
    are traced and cannot be checked here; fitting goes through bounded transforms
    (:class:`MaterialParameterization`) that keep them in range, and the solvers check
    with ``equinox.error_if``.
    """

    youngs_modulus: float | jax.Array
    poisson_ratio: float | jax.Array
    cubic_coefficient: float | jax.Array = 0.0
    density: float | jax.Array = 1000.0
    pre_stretch: float | jax.Array = 1.0
    pre_stretch_y: float | jax.Array | None = None

    def __check_init__(self):
        checks = (
            ("youngs_modulus", "Pa", lambda v: v > 0, "must be > 0"),
            ("poisson_ratio", "", lambda v: -1.0 < v < 0.5, "must lie in (-1, 0.5)"),
            ("cubic_coefficient", "", lambda v: True, ""),
            ("density", "kg/m^3", lambda v: v > 0, "must be > 0"),
            ("pre_stretch", "", lambda v: v > 0, "must be > 0"),
            ("pre_stretch_y", "", lambda v: v > 0, "must be > 0"),
        )
        for name, unit, ok, rule in checks:
            value = getattr(self, name)
            if value is None and name == "pre_stretch_y":
                continue
            if not _is_concrete(value):
                continue
            arr = np.asarray(value, dtype=float)
            if not np.all(np.isfinite(arr)):
                raise MaterialError(f"{name} is not finite ({value!r}); every material parameter must be a finite number")
            for v in arr.reshape(-1):
                if not ok(float(v)):
                    extra = ""
                    if name == "poisson_ratio" and v >= 0.5:
                        extra = " (0.5 is the incompressible limit, where the bulk modulus is infinite; use e.g. 0.49 or 0.499)"
                    raise MaterialError(f"{name} = {float(v):g}{' ' + unit if unit else ''} {rule}{extra}")

    # Convenience views -----------------------------------------------------------
    @property
    def lame(self) -> tuple[jax.Array, jax.Array]:
        """Lamé parameters ``(lambda, mu)`` [Pa]."""
        return lame_parameters(self.youngs_modulus, self.poisson_ratio)

    @property
    def shear_modulus(self) -> jax.Array:
        """Shear modulus ``mu = E / (2 (1 + nu))`` [Pa]."""
        return shear_modulus(self.youngs_modulus, self.poisson_ratio)

    @property
    def bulk_modulus(self) -> jax.Array:
        """Bulk modulus ``K = E / (3 (1 - 2 nu))`` [Pa]."""
        return bulk_modulus(self.youngs_modulus, self.poisson_ratio)

    @property
    def is_equibiaxial(self) -> bool:
        """True when the pre-stretch is equibiaxial by construction (``pre_stretch_y`` is None)."""
        return self.pre_stretch_y is None

    @property
    def pre_stretch_xy(self) -> tuple:
        """``(lambda_x, lambda_y)`` [-]: ``pre_stretch`` and ``pre_stretch_y`` (``pre_stretch``
        itself when ``pre_stretch_y`` is None)."""
        return self.pre_stretch, (self.pre_stretch if self.pre_stretch_y is None else self.pre_stretch_y)

    def replace(self, **changes) -> "Material":
        """A copy with some fields changed (validated again). ``pre_stretch_y=None`` makes the
        pre-stretch equibiaxial again."""
        fields = {k: getattr(self, k) for k in MATERIAL_FIELDS}
        unknown = set(changes) - set(fields)
        if unknown:
            raise MaterialError(f"unknown material field(s) {sorted(unknown)}; known: {sorted(fields)}")
        fields.update(changes)
        return Material(**fields)

    def to_dict(self) -> dict[str, float]:
        """Plain-float dictionary (SI units), e.g. for JSON."""
        return {
            "youngs_modulus": float(self.youngs_modulus),
            "poisson_ratio": float(self.poisson_ratio),
            "cubic_coefficient": float(self.cubic_coefficient),
            "density": float(self.density),
            "pre_stretch": float(self.pre_stretch),
            **({} if self.pre_stretch_y is None else {"pre_stretch_y": float(self.pre_stretch_y)}),
        }


# ------------------------------------------------------------------ elastic moduli
def lame_parameters(youngs_modulus, poisson_ratio):
    """Lamé parameters ``(lambda, mu)`` [Pa] from ``E`` [Pa] and ``nu``.

    ``lambda = E nu / ((1 + nu)(1 - 2 nu))``, ``mu = E / (2 (1 + nu))``.
    """
    E, nu = youngs_modulus, poisson_ratio
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E / (2.0 * (1.0 + nu))
    return lam, mu


def shear_modulus(youngs_modulus, poisson_ratio):
    """Shear modulus ``mu = E / (2 (1 + nu))`` [Pa]."""
    return youngs_modulus / (2.0 * (1.0 + poisson_ratio))


def bulk_modulus(youngs_modulus, poisson_ratio):
    """Bulk modulus ``K = E / (3 (1 - 2 nu))`` [Pa]."""
    return youngs_modulus / (3.0 * (1.0 - 2.0 * poisson_ratio))


def p_wave_modulus(youngs_modulus, poisson_ratio):
    """Confined (P-wave) modulus ``lambda + 2 mu = E (1 - nu) / ((1 + nu)(1 - 2 nu))`` [Pa]."""
    E, nu = youngs_modulus, poisson_ratio
    return E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


def indentation_modulus(youngs_modulus, poisson_ratio):
    """Indentation (plane-strain) modulus ``E* = E / (1 - nu^2)`` [Pa] used by Hertz/Sneddon."""
    return youngs_modulus / (1.0 - poisson_ratio**2)


def youngs_poisson_from_lame(lam, mu):
    """Inverse of :func:`lame_parameters`: ``(E, nu)`` from ``(lambda, mu)`` [Pa]."""
    E = mu * (3.0 * lam + 2.0 * mu) / (lam + mu)
    nu = lam / (2.0 * (lam + mu))
    return E, nu


# ------------------------------------------------------------------ spring lattice
class LatticeSpringConstants(NamedTuple):
    """Per-cube spring constants of the cube lattice (DESIGN.md §3.1).

    Each cube carries springs on its 12 edges and on both diagonals of its 6 faces. The
    constants are *per cube*: a spring shared by ``m`` cubes has total stiffness ``m k``
    (an interior edge is shared by 4 cubes, an interior face diagonal by 2).

    Attributes:
        k_edge: linear stiffness of an edge spring per cube [N/m].
        k_diag: linear stiffness of a face-diagonal spring per cube [N/m].
        a_edge: cubic coefficient of an edge spring per cube [N/m^3] (force ``k x + a x^3``).
        a_diag: cubic coefficient of a face-diagonal spring per cube [N/m^3].
        volume_modulus: bulk stiffness the tetrahedral volume term must add [Pa]
            (``lambda - mu`` for ``isotropic_volume``, 0 for ``pure_lattice``).
    """

    k_edge: jax.Array
    k_diag: jax.Array
    a_edge: jax.Array
    a_diag: jax.Array
    volume_modulus: jax.Array


def cubic_spring_coefficient(linear_stiffness, rest_length, cubic_coefficient):
    """Cubic coefficient ``a = b k / L0^2`` [N/m^3] of a spring ``F = k x + a x^3``.

    With extension ``x = eps L0`` this gives ``F = k L0 (eps + b eps^3)``: the spring follows
    the uniaxial law ``sigma = E (eps + b eps^3)`` of the material.
    """
    return cubic_coefficient * linear_stiffness / rest_length**2


def _concrete_nu_check(nu, ok, message, error=ModelRangeError):
    if _is_concrete(nu):
        arr = np.asarray(nu, dtype=float).reshape(-1)
        bad = arr[~np.vectorize(ok)(arr)] if arr.size else arr
        if bad.size:
            raise error(message.format(nu=float(bad[0])))


def lattice_spring_constants(material: Material, cell_size, model: str = "isotropic_volume") -> LatticeSpringConstants:
    """Per-cube spring constants of the cube lattice of spacing ``cell_size`` [m].

    Assembled per cube, the lattice has long-wavelength stiffness
    ``C11 = (K1 + 2 K2)/h``, ``C12 = C44 = K2/h`` with ``K1 = 4 k_edge``, ``K2 = 2 k_diag``.

    Models:
        ``"isotropic_volume"`` (default, our model): isotropic springs
            ``k_edge = mu h / 4``, ``k_diag = mu h / 2`` (C11 = 3 mu, C12 = C44 = mu) plus a
            tetrahedral volume term of bulk stiffness ``lambda - mu`` (``volume_modulus``),
            which restores ``C11 = lambda + 2 mu``, ``C12 = lambda``. Exactly isotropic at small
            strain for ``1/4 <= nu < 1/2``. Below ``nu = 1/4`` the volume term would need
            negative stiffness; this is refused (use the FEM or the stable neo-Hookean model).
        ``"pure_lattice"`` (seed 000 with the cell size the paper omits):
            ``k_edge = (2 mu - lambda) h / 4``, ``k_diag = lambda h / 2``. Matches C11 and C12
            but obeys the Cauchy relation C44 = C12 = lambda, so it is isotropic only at
            ``nu = 1/4``; refused for ``nu > 1/3`` (``k_edge < 0``: unstable) and ``nu <= 0``
            (``k_diag <= 0``: no shear stiffness).

    The cubic coefficient follows :func:`cubic_spring_coefficient` with the spring rest
    lengths ``h`` (edges) and ``sqrt(2) h`` (diagonals).
    """
    if model not in LATTICE_MODELS:
        raise ModelRangeError(f"unknown lattice model {model!r}; choose one of {LATTICE_MODELS}")
    h = cell_size
    if _is_concrete(h) and not np.all(np.asarray(h, dtype=float) > 0):
        raise MaterialError(f"cell_size must be > 0 m, got {h!r}")
    lam, mu = material.lame
    nu = material.poisson_ratio
    if model == "isotropic_volume":
        _concrete_nu_check(
            nu,
            lambda v: v >= 0.25,
            "poisson_ratio = {nu:g} < 1/4: the cubic-spring + volume model is exactly isotropic only for "
            "1/4 <= nu < 1/2, because its isotropic springs already carry lambda_s = mu and the volume term "
            "(stiffness lambda - mu) would have to be negative. Use the FEM or the stable neo-Hookean model "
            "for nu < 1/4 (soft tissue is 0.45-0.499).",
        )
        k_edge = mu * h / 4.0
        k_diag = mu * h / 2.0
        volume = lam - mu
    else:
        _concrete_nu_check(
            nu,
            lambda v: 0.0 < v <= 1.0 / 3.0,
            "poisson_ratio = {nu:g} is outside (0, 1/3] for a pure spring lattice: its edge springs "
            "k_edge = (2 mu - lambda) h / 4 turn negative above nu = 1/3 (the lattice is unstable) and its "
            "diagonal springs k_diag = lambda h / 2 vanish at nu <= 0. Tissue-like nu (0.45-0.5) needs the "
            "volume term: use model='isotropic_volume' (isotropic springs + volume constraints).",
        )
        k_edge = (2.0 * mu - lam) * h / 4.0
        k_diag = lam * h / 2.0
        volume = jnp.zeros_like(jnp.asarray(lam))
    b = material.cubic_coefficient
    a_edge = cubic_spring_coefficient(k_edge, h, b)
    a_diag = cubic_spring_coefficient(k_diag, math.sqrt(2.0) * h, b)
    return LatticeSpringConstants(k_edge, k_diag, a_edge, a_diag, volume)


def volume_constraint_modulus(material: Material, model: str = "isotropic_volume") -> jax.Array:
    """Bulk stiffness [Pa] of the volume term: ``lambda - mu`` with isotropic springs,
    ``K = lambda + 2 mu / 3`` when the volume term stands alone (no springs)."""
    lam, mu = material.lame
    if model == "isotropic_volume":
        return lam - mu
    if model == "volume_only":
        return lam + 2.0 * mu / 3.0
    raise ModelRangeError(f"unknown volume model {model!r}; choose 'isotropic_volume' or 'volume_only'")


# ------------------------------------------------------------------- XPBD compliances
def distance_compliance(stiffness):
    """XPBD compliance ``alpha = 1 / k`` [m/N] of a distance constraint of stiffness ``k`` [N/m]."""
    return 1.0 / stiffness


def volume_compliance(rest_volume, bulk_stiffness):
    """XPBD compliance ``alpha = V0 / K`` [m^3/Pa] of ``C = V - V0`` [m^3] (energy ``K (V - V0)^2 / (2 V0)``).

    Args:
        rest_volume: tetrahedron rest volume ``V0`` [m^3].
        bulk_stiffness: bulk stiffness ``K`` [Pa] this constraint carries.
    """
    return rest_volume / bulk_stiffness


class XPBDCompliances(NamedTuple):
    """Stable neo-Hookean XPBD constraint data for one tetrahedron (Macklin & Müller 2021).

    Attributes:
        deviatoric: compliance of ``C_D = sqrt(tr F^T F)``: ``1 / (mu V0)`` [1/(Pa m^3)].
        hydrostatic: compliance of ``C_H = det F - gamma``: ``1 / (lambda' V0)`` [1/(Pa m^3)].
        gamma: rest offset ``1 + mu / lambda'`` [-].
    """

    deviatoric: jax.Array
    hydrostatic: jax.Array
    gamma: jax.Array


def neo_hookean_xpbd_compliances(material: Material, rest_volume) -> XPBDCompliances:
    """Compliances of the stable neo-Hookean constraint pair with ``lambda' = lambda + mu``.

    The shift ``lambda' = lambda + mu`` makes the small-strain response equal the linear
    material (E, nu); using ``lambda`` itself gives, for example, an effective Poisson ratio
    of 0.167 at nu = 0.3.
    """
    lam, mu = material.lame
    lam_shift = lam + mu
    return XPBDCompliances(
        deviatoric=1.0 / (mu * rest_volume),
        hydrostatic=1.0 / (lam_shift * rest_volume),
        gamma=1.0 + mu / lam_shift,
    )


# ------------------------------------------------------------------ pre-tension
def equibiaxial_pre_stress(material: Material):
    """Linear equibiaxial in-plane pre-stress ``sigma0 = E (lambda0 - 1) / (1 - nu)`` [Pa].

    Small-strain plane-stress relation for a layer stretched by ``lambda0`` in both in-plane
    directions and free through its thickness. The models' own stress at finite ``lambda0``:
    :func:`difftissue.constitutive.membrane_state`.
    """
    _require_equibiaxial(material, "equibiaxial_pre_stress")
    eps0 = material.pre_stretch - 1.0
    return material.youngs_modulus * eps0 / (1.0 - material.poisson_ratio)


def _require_equibiaxial(material: Material, what: str) -> None:
    """Raise :class:`MaterialError` when ``material`` has a ``pre_stretch_y`` differing from
    ``pre_stretch`` (or one not known yet, inside jit)."""
    if material.pre_stretch_y is None:
        return
    if _is_concrete((material.pre_stretch, material.pre_stretch_y)) and np.array_equal(np.asarray(material.pre_stretch), np.asarray(material.pre_stretch_y)):
        return
    raise MaterialError(f"{what} is the equibiaxial (pre_stretch_y = pre_stretch) formula, but the material has pre_stretch_y = "
                        f"{material.pre_stretch_y!r} and pre_stretch = {material.pre_stretch!r}; use biaxial_pre_stress or "
                        "difftissue.constitutive.surface_tensions for an anisotropic pre-stretch")


def biaxial_pre_stress(material: Material):
    """Linear in-plane pre-stresses ``(sigma_x, sigma_y)`` [Pa] of a layer pre-stretched by
    ``(lambda_x, lambda_y)`` and free through its thickness (small-strain plane stress):
    ``sigma_x = E (eps_x + nu eps_y) / (1 - nu^2)``, ``eps = lambda - 1``. Equals
    :func:`equibiaxial_pre_stress` twice when ``lambda_x = lambda_y``."""
    lx, ly = material.pre_stretch_xy
    ex, ey = lx - 1.0, ly - 1.0
    E, nu = material.youngs_modulus, material.poisson_ratio
    c = E / (1.0 - nu * nu)
    return c * (ex + nu * ey), c * (ey + nu * ex)


def surface_tension_from_pre_stretch(material: Material, thickness):
    """Linearised surface tension ``T = sigma0 t = E (lambda0 - 1) t / (1 - nu)`` [N/m] of a
    layer of thickness ``t`` [m] (small-strain, equibiaxial).

    It overstates the tension the models carry by O(lambda0 - 1): 15-19 % at lambda0 = 1.05,
    31-40 % at 1.10 (nu = 0.45). The model's own: :func:`difftissue.constitutive.surface_tension`.
    """
    return equibiaxial_pre_stress(material) * thickness


def pre_stretch_from_surface_tension(material: Material, surface_tension, thickness):
    """Inverse of :func:`surface_tension_from_pre_stretch`: ``lambda0 = 1 + T (1 - nu) / (E t)``
    (linear: a model reaches the tension ``T`` at a larger ``lambda0``)."""
    if _is_concrete(thickness) and not np.all(np.asarray(thickness, dtype=float) > 0):
        raise MaterialError(f"layer thickness must be > 0 m, got {thickness!r}")
    return 1.0 + surface_tension * (1.0 - material.poisson_ratio) / (material.youngs_modulus * thickness)


def explicit_pre_stretch_y(material: Material) -> Material:
    """``material`` with ``pre_stretch_y`` set: ``pre_stretch`` where it is None (the same
    physics; the pytree then has the ``pre_stretch_y`` leaf, e.g. to stack with anisotropic
    materials or to differentiate in ``lambda_y``). Works on traced values."""
    if material.pre_stretch_y is not None:
        return material
    return eqx.tree_at(lambda m: m.pre_stretch_y, material, material.pre_stretch, is_leaf=lambda x: x is None)


def _field_value(material: Material, field: str):
    """``material``'s value of ``field``; ``pre_stretch_y`` is ``pre_stretch`` when None."""
    if field == "pre_stretch_y" and material.pre_stretch_y is None:
        return material.pre_stretch
    return getattr(material, field)


# -------------------------------------------------------------- fitting transforms
def _xp(u):
    """NumPy for NumPy input (floats, NumPy arrays and scalars: no JAX dispatch, nothing
    compiled), ``jax.numpy`` otherwise (JAX arrays, tracers): the rule of
    :func:`difftissue.energies.volume.array_namespace`, which this module cannot import (the
    data loaders import it and must not import the physics)."""
    return np if isinstance(u, (float, int, np.ndarray, np.generic)) else jnp


def _sigmoid(u):
    """The logistic function ``1 / (1 + exp(-u))``: ``jax.nn.sigmoid`` for JAX input, that
    formula in NumPy for NumPy input (``exp(-u) = inf`` for very negative ``u`` gives 0)."""
    if _xp(u) is np:
        with np.errstate(over="ignore"):
            return 1.0 / (1.0 + np.exp(-np.asarray(u, dtype=float)))
    return jax.nn.sigmoid(u)


class Transform(eqx.Module):
    """A smooth bijection from an unconstrained real ``u`` to a bounded parameter value."""

    @abc.abstractmethod
    def forward(self, u):
        """Parameter value from unconstrained ``u`` (NumPy in, NumPy out; JAX arrays and
        tracers otherwise)."""

    @abc.abstractmethod
    def derivative(self, u):
        """``d value / d u`` at ``u`` (NumPy in, NumPy out; JAX arrays and tracers otherwise)."""

    @abc.abstractmethod
    def inverse(self, value):
        """Unconstrained ``u`` from a parameter value (must lie strictly inside the bounds)."""


class Identity(Transform):
    """``value = u`` (unbounded parameters such as the cubic coefficient)."""

    def forward(self, u):
        return u

    def derivative(self, u):
        return _xp(u).ones_like(u)

    def inverse(self, value):
        return value


class Linear(Transform):
    """``value = scale * u``: unbounded parameters of a natural size ``scale`` [unit of the
    parameter], e.g. an indentation's contact offset (``scale`` of a few micrometres), so that
    the optimiser works with numbers of order one."""

    scale: float = 1.0

    def __check_init__(self):
        if _is_concrete(self.scale) and not (math.isfinite(float(self.scale)) and float(self.scale) > 0):
            raise MaterialError(f"Linear needs a finite scale > 0, got {self.scale!r}")

    def forward(self, u):
        return self.scale * u

    def derivative(self, u):
        return self.scale * _xp(u).ones_like(u)

    def inverse(self, value):
        _check_bounds(value, None, None)
        return value / self.scale


class Log(Transform):
    """``value = lower + scale * exp(u)``: positive parameters (E, density, pre-stretch).

    ``scale`` [unit of the parameter] sets the value at ``u = 0`` so the optimiser works
    with numbers of order one.
    """

    lower: float = 0.0
    scale: float = 1.0

    def forward(self, u):
        return self.lower + self.scale * _xp(u).exp(u)

    def derivative(self, u):
        return self.scale * _xp(u).exp(u)

    def inverse(self, value):
        _check_bounds(value, self.lower, None)
        return _xp(value).log((value - self.lower) / self.scale)


class ScaledLogit(Transform):
    """``value = lower + (upper - lower) * sigmoid(u)``: doubly bounded parameters (nu)."""

    lower: float = -1.0
    upper: float = 0.5

    def __check_init__(self):
        if not self.upper > self.lower:
            raise MaterialError(f"ScaledLogit needs upper > lower, got ({self.lower}, {self.upper})")

    def forward(self, u):
        return self.lower + (self.upper - self.lower) * _sigmoid(u)

    def derivative(self, u):
        s = _sigmoid(u)
        return (self.upper - self.lower) * (s * (1.0 - s))  # as JAX's derivative of the logistic

    def inverse(self, value):
        _check_bounds(value, self.lower, self.upper)
        s = (value - self.lower) / (self.upper - self.lower)
        xp = _xp(value)
        return xp.log(s) - xp.log1p(-s)


def _check_bounds(value, lower, upper):
    if not _is_concrete(value):
        return
    v = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(v)):
        raise MaterialError(f"cannot transform non-finite value {value!r}")
    if lower is not None and not np.all(v > lower):
        raise MaterialError(f"value {value!r} must lie strictly above the lower bound {lower}")
    if upper is not None and not np.all(v < upper):
        raise MaterialError(f"value {value!r} must lie strictly below the upper bound {upper}")


#: Default transforms per material field: log for positive fields, scaled logit for nu.
DEFAULT_TRANSFORMS: dict[str, Transform] = {
    "youngs_modulus": Log(scale=1e3),
    "poisson_ratio": ScaledLogit(-1.0, 0.5),
    "cubic_coefficient": Identity(),
    "density": Log(scale=1e3),
    "pre_stretch": Log(),
    "pre_stretch_y": Log(),
}


class MaterialParameterization(eqx.Module):
    """Maps a vector of unconstrained reals to the fitted fields of a :class:`Material`.

    Example::

        param = MaterialParameterization(("youngs_modulus", "poisson_ratio"),
                                         transforms={"poisson_ratio": ScaledLogit(0.0, 0.499)})
        u = param.pack(Material(5e3, 0.45))         # unconstrained vector, shape (2,)
        material = param.unpack(u, base=Material(1.0, 0.3, density=1050.0))

    Fields not fitted are taken from ``base``. ``unpack`` is differentiable in ``u``.
    """

    fields: tuple[str, ...] = eqx.field(static=True)
    transforms: tuple[Transform, ...]

    def __init__(self, fields, transforms: dict[str, Transform] | None = None):
        fields = tuple(fields)
        known = tuple(DEFAULT_TRANSFORMS)
        bad = [f for f in fields if f not in known]
        if bad:
            raise MaterialError(f"cannot fit unknown material field(s) {bad}; known: {list(known)}")
        if len(set(fields)) != len(fields):
            raise MaterialError(f"fitted fields repeat: {list(fields)}")
        transforms = dict(transforms or {})
        extra = set(transforms) - set(fields)
        if extra:
            raise MaterialError(f"transforms given for fields that are not fitted: {sorted(extra)}")
        self.fields = fields
        self.transforms = tuple(transforms.get(f, DEFAULT_TRANSFORMS[f]) for f in fields)

    def pack(self, material: Material) -> jax.Array | np.ndarray:
        """Unconstrained vector ``u`` (shape ``(len(fields),)``) of the fitted fields: a NumPy
        array for a material of concrete values (nothing is dispatched to JAX), a JAX array
        when a field is traced."""
        values = [_field_value(material, f) for f in self.fields]
        if _is_concrete(values):  # NumPy: nothing dispatched to JAX (one compiled program per operation)
            dtype = jax.dtypes.canonicalize_dtype(float)
            return np.stack([np.asarray(t.inverse(np.asarray(v, dtype=dtype)), dtype=dtype) for v, t in zip(values, self.transforms)])
        return jnp.stack([jnp.asarray(t.inverse(v), dtype=float) for v, t in zip(values, self.transforms)])

    def values(self, u) -> dict[str, jax.Array]:
        """Physical values of the fitted fields from ``u``."""
        return {f: t.forward(u[i]) for i, (f, t) in enumerate(zip(self.fields, self.transforms))}

    def unpack(self, u, base: Material) -> Material:
        """``base`` with the fitted fields replaced by their values at ``u``."""
        vals = self.values(u)
        if "pre_stretch_y" in self.fields:  # fitting lambda_y of an equibiaxial base too
            base = explicit_pre_stretch_y(base)
        # eqx.tree_at keeps the result a valid pytree under tracing without re-validation.
        return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in self.fields), base, tuple(vals[f] for f in self.fields))
