"""The constitutive response each elastic model implies under homogeneous deformation.

Two questions a fit's user asks of the fitted parameters, answered from the model's own energy
(not from a linear formula):

- **Surface tension** of a pre-stretched layer (:func:`surface_tension`): the in-plane force per
  unit length that a layer pre-stretched by ``lambda0`` carries, held at the in-vivo (mesh)
  state in x and y with its top and bottom free in z. The linear formula
  ``T = E (lambda0 - 1) t / (1 - nu)`` (:func:`difftissue.materials.surface_tension_from_pre_stretch`)
  overstates it by O(lambda0 - 1): 15-19 % at lambda0 = 1.05, nu = 0.45.
- **The continuum law the lattice's cubic coefficient b produces** (:func:`uniaxial_stress`,
  :func:`continuum_cubic_coefficient`): ``springs_volume`` puts ``b`` on its springs
  (``a = b k / L0^2``); in homogeneous uniaxial stress the lattice then follows
  ``sigma ~ E (eps + b_c eps^3)`` with ``b_c`` neither ``b`` nor proportional to it (the lattice
  has a nonlinearity of its own at ``b = 0``, and ``b_c`` depends on nu and on the direction).

How: the model itself (:func:`difftissue.models.make_model`) on one cell of a block mesh
(:func:`difftissue.mesh.block`, the cell shape of the specimen), deformed affinely. An affine
deformation is an exact equilibrium of a periodic lattice with one node per cell (every node is
a centre of inversion symmetry) and of any tet mesh (every tet has the same ``F``), so the energy
of that cell per unit volume is the model's exact homogenised energy density; nothing of the
model's formulas is repeated here. The free stretches (the layer's thickness; the lateral
stretches of a uniaxial bar) are solved by Newton's method on that energy; the result is
differentiated by the implicit function theorem (the last Newton step is taken with gradients,
the earlier ones without), so every function here is jit-able and differentiable in the
material's fields.

Units: SI (Pa, N/m, m); strains and stretches dimensionless.
"""

from __future__ import annotations

import contextlib
import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import MaterialError, ModelError
from .materials import Material, _is_concrete, _require_equibiaxial, biaxial_pre_stress, explicit_pre_stretch_y, material_fields, surface_tension_from_pre_stretch
from .mesh import block
from .models import LATTICE_MODELS, MESH_MODELS, make_model
from .solvers.host import ModelDerivatives

__all__ = [
    "MembraneState",
    "membrane_state",
    "surface_tension",
    "BiaxialMembraneState",
    "biaxial_membrane_state",
    "surface_tensions",
    "pre_stretch_for_surface_tension",
    "DIRECTIONS",
    "UNIAXIAL_STRAIN_RANGE",
    "uniaxial_stress",
    "continuum_cubic_coefficient",
    "surface_tension_record",
    "cubic_coefficient_record",
]

#: Lattice directions understood by :func:`uniaxial_stress` (Miller indices of the cube lattice:
#: an edge, a face diagonal, the body diagonal). The continuum models are isotropic.
DIRECTIONS = {"[100]": (1.0, 0.0, 0.0), "[110]": (1.0, 1.0, 0.0), "[111]": (1.0, 1.0, 1.0)}

#: Default engineering-strain range of :func:`continuum_cubic_coefficient` [-].
UNIAXIAL_STRAIN_RANGE = (-0.3, 0.3)

_NEWTON_STEPS = 30
_MAX_STEP = 0.1  # largest change of a stretch per Newton step [-]
_QUADRATURE_POINTS = 16


# ------------------------------------------------------------------------ the one cell
def _cell_shape(kind: str, cell_size) -> tuple[float, float, float]:
    """The cell's edge ratios ``(hx, hy, hz) / max`` (a cube for the tet models, whose
    homogeneous response does not depend on it)."""
    if kind not in MESH_MODELS:
        raise ModelError(f"unknown model {kind!r}; choose one of {MESH_MODELS}")
    if cell_size is None or not kind.startswith("springs_volume"):
        return (1.0, 1.0, 1.0)
    h = np.broadcast_to(np.asarray(cell_size, dtype=float), (3,))
    if not np.all(np.isfinite(h) & (h > 0)):
        raise ModelError(f"cell_size must be three positive lengths (hx, hy, hz) [m], got {cell_size!r}")
    h = h / h.max()
    return tuple(float(v) for v in h)


@functools.lru_cache(maxsize=32)
def _unit_cell(kind: str, shape: tuple[float, float, float]):
    """``(model, rest points (8, 3), cell volume)`` of one cell of ``shape`` (built once, eagerly
    even when first asked for inside ``jit``)."""
    # Inside a trace the cell is evaluated eagerly; outside, the mesh set-up uses its compiled
    # programs, shared with every model (under ensure_compile_time_eval they ran op by op: ~0.25 s CPU).
    with contextlib.nullcontext() if _is_concrete(jnp.zeros(())) else jax.ensure_compile_time_eval():
        mesh = block(shape, 1)
        model = make_model(mesh, kind)
    return model, np.asarray(mesh.points, dtype=float), float(np.prod(shape))


def _energy_density(kind, shape, material: Material, F):
    """Energy of the cell deformed affinely by ``F`` (3, 3) from the mesh, per unit mesh volume
    [Pa]. With ``material.pre_stretch = lambda0`` the mesh is the pre-stretched state (the
    model's convention): the elastic deformation is ``F diag(lambda0, lambda0, 1)``."""
    return _density_function(kind, shape, material)(F)


def _density_function(kind, shape, material: Material):
    """``F -> _energy_density(kind, shape, material, F)`` with the model's element terms built
    once from ``material``: a solve that derives from the material alone (the matched lattice's
    design, :func:`~difftissue.models.matched_lattice_design`) is traced and run once per
    function, not again in every gradient and Hessian of the density inside a Newton loop."""
    model, X, V = _unit_cell(kind, shape)
    terms = model.terms(material)
    X = jnp.asarray(X)

    def density(F):
        x = X @ jnp.swapaxes(F, 0, 1)
        return sum(t.total(x) for t in terms) / V

    return density


def _scalar_material(material: Material) -> Material:
    if not isinstance(material, Material):
        raise MaterialError(f"expected a Material, got {type(material).__name__}")
    leaves = {f: jnp.asarray(getattr(material, f), dtype=float) for f in material_fields(material)}
    bad = [f for f, v in leaves.items() if v.ndim != 0]
    if bad:
        raise MaterialError(f"the homogeneous response needs one material (scalar fields); {bad} have shapes {[leaves[f].shape for f in bad]}")
    return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in leaves), material, tuple(leaves.values()))


def _checked(kind, shape, material: Material) -> Material:
    """``material`` with scalar float fields; concrete values checked by the model itself (so a
    value outside its range raises the model's own error, not a runtime error from inside jit)."""
    mat = _scalar_material(material)
    if _is_concrete(mat):
        _unit_cell(kind, shape)[0].checked(mat)
    return mat


def _newton(grad, hess, y0, what: str, scale):
    """Stationary point of an energy in the unknown stretches ``y`` (shape ``(n,)``).

    ``grad(y)`` / ``hess(y)`` of the energy density [Pa]. ``_NEWTON_STEPS`` steps without
    gradients (each change limited to ``_MAX_STEP``), then one step with gradients: at a
    converged point its derivative is the implicit-function-theorem derivative
    ``-H^-1 d(grad)/d(params)``. A point whose residual exceeds ``1e3 eps scale`` (``scale`` the
    modulus [Pa]) is an error (``equinox.error_if``), so a wrong number never comes back."""

    def step(y):
        d = jnp.linalg.solve(hess(y), grad(y))
        return y - jnp.clip(d, -_MAX_STEP, _MAX_STEP)

    y = jax.lax.fori_loop(0, _NEWTON_STEPS, lambda i, y: jax.lax.stop_gradient(step(y)), jax.lax.stop_gradient(y0))
    res = jnp.max(jnp.abs(jax.lax.stop_gradient(grad(y))))
    tol = 1e3 * jnp.finfo(y.dtype).eps * jax.lax.stop_gradient(scale)
    y = eqx.error_if(y, ~(res <= tol), f"{what}: Newton's method did not converge (the state is outside the model's range, "
                     "e.g. a strain that inverts or collapses the cell)")
    return y - jnp.linalg.solve(hess(y), grad(y))


# ------------------------------------------------------------------ surface tension
class MembraneState(NamedTuple):
    """Homogeneous state of a layer pre-stretched equibiaxially by ``lambda0``, held at the mesh
    in x and y, free in z (traction-free top and bottom).

    Attributes:
        thickness_stretch: ``lambda_z`` [-], current thickness / mesh (stress-free) thickness.
        tension_per_thickness: in-plane force per unit current length per unit mesh thickness
            [Pa]: ``T / t`` with ``T`` the surface tension [N/m] of a layer of mesh thickness
            ``t``; equals ``P_xx / lambda0`` (``P`` the nominal stress per stress-free area).
        cauchy_stress: in-plane true stress ``sigma_xx = T / (lambda_z t)`` [Pa].
        nominal_stress: ``P_xx`` [Pa], force per unit stress-free area
            (``lambda0 T / t``: the force per unit *stress-free* length, per unit thickness).
    """

    thickness_stretch: jax.Array
    tension_per_thickness: jax.Array
    cauchy_stress: jax.Array
    nominal_stress: jax.Array


def membrane_state(kind: str, material: Material, *, cell_size=None) -> MembraneState:
    """The model's own equibiaxial plane-stress state at ``material.pre_stretch`` (see
    :class:`MembraneState`).

    Args:
        kind: one of :data:`difftissue.models.MODELS`.
        material: one material (scalar fields); ``pre_stretch`` is ``lambda0`` [-].
        cell_size: for ``springs_volume``, the mesh cell ``(hx, hy, hz)`` [m] (only the ratios
            matter; default a cube): the lattice's stress-free cell is it shrunk by ``1/lambda0``
            in x and y, and its finite-strain response depends on that shape. Ignored by the tet
            models (their homogeneous response does not depend on the mesh).

    The mesh is the in-vivo state in x and y (the model's convention: the stress-free state is
    the mesh shrunk by ``1/lambda0`` in x, y); the thickness follows from ``d psi / d lambda_z = 0``.
    Jit-able and differentiable in every field of ``material`` (compiled once per model and cell
    shape). Range errors of the model (``springs_volume``: ``nu >= 1/4`` and the lattice's
    ``pre_stretch_range``) are raised as the model raises them.
    """
    _require_equibiaxial(material, "membrane_state (equibiaxial)")
    if material.pre_stretch_y is not None:  # equal to pre_stretch (checked): the equibiaxial state
        material = material.replace(pre_stretch_y=None)
    shape = _cell_shape(kind, cell_size)
    mat = _checked(kind, shape, material)
    return _membrane_state(kind, shape, mat)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _membrane_state(kind, shape, mat) -> MembraneState:
    lam0 = mat.pre_stretch
    nu = mat.poisson_ratio

    density = _density_function(kind, shape, mat)

    def psi(s, lz):  # per unit mesh volume; s stretches x about the mesh
        F = jnp.diag(jnp.stack([s, jnp.ones_like(s), lz]))
        return density(F)

    one = jnp.ones_like(lam0)
    g = jax.grad(lambda y: psi(one, y[0]))
    h = jax.hessian(lambda y: psi(one, y[0]))
    lz0 = lam0 ** (-2.0 * nu / (1.0 - nu))  # the linear thickness change, as a start
    lz = _newton(g, h, jnp.atleast_1d(lz0), f"membrane state of {kind} at pre_stretch", mat.youngs_modulus)[0]
    tension = jax.grad(psi, argnums=0)(one, lz)  # d psi / d s: force per current length per mesh thickness
    return MembraneState(lz, tension, tension / lz, tension * lam0)


class BiaxialMembraneState(NamedTuple):
    """Homogeneous state of a layer pre-stretched by ``(lambda_x, lambda_y)``
    (``Material.pre_stretch``, ``pre_stretch_y``), held at the mesh in x and y, free in z.

    Attributes (the in-plane ones of shape ``(2,)``: x then y):
        thickness_stretch: ``lambda_z`` [-], current thickness / mesh (stress-free) thickness.
        tension_per_thickness: ``(T_x, T_y) / t`` [Pa]: ``T_x`` is the force along x per unit
            current length of a line along y (a cut along y is pulled open by it).
        cauchy_stress: ``(sigma_xx, sigma_yy) = (T_x, T_y) / (lambda_z t)`` [Pa].
        nominal_stress: ``(P_xx, P_yy) = (lambda_y T_x, lambda_x T_y) / t`` [Pa], force per unit
            stress-free area.
    """

    thickness_stretch: jax.Array
    tension_per_thickness: jax.Array
    cauchy_stress: jax.Array
    nominal_stress: jax.Array


def biaxial_membrane_state(kind: str, material: Material, *, cell_size=None) -> BiaxialMembraneState:
    """The model's own biaxial plane-stress state at ``material.pre_stretch_xy`` (see
    :class:`BiaxialMembraneState`); :func:`membrane_state` is its equibiaxial case.

    Args and conventions as :func:`membrane_state`: the stress-free state is the mesh shrunk by
    ``diag(1/lambda_x, 1/lambda_y, 1)``, the thickness follows from ``d psi / d lambda_z = 0``.
    Jit-able, differentiable in every field of ``material``.
    """
    shape = _cell_shape(kind, cell_size)
    material = explicit_pre_stretch_y(material)
    mat = _checked(kind, shape, material)
    return _biaxial_membrane_state(kind, shape, mat)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _biaxial_membrane_state(kind, shape, mat) -> BiaxialMembraneState:
    lx, ly = mat.pre_stretch, mat.pre_stretch_y
    nu = mat.poisson_ratio

    density = _density_function(kind, shape, mat)

    def psi(sx, sy, lz):  # per unit mesh volume; (sx, sy) stretch x and y about the mesh
        F = jnp.diag(jnp.stack([sx, sy, lz]))
        return density(F)

    one = jnp.ones_like(lx)
    g = jax.grad(lambda y: psi(one, one, y[0]))
    h = jax.hessian(lambda y: psi(one, one, y[0]))
    lz0 = (lx * ly) ** (-nu / (1.0 - nu))  # the linear thickness change, as a start
    lz = _newton(g, h, jnp.atleast_1d(lz0), f"membrane state of {kind} at (pre_stretch, pre_stretch_y)", mat.youngs_modulus)[0]
    tx, ty = jax.grad(psi, argnums=(0, 1))(one, one, lz)
    t = jnp.stack([tx, ty])
    return BiaxialMembraneState(lz, t, t / lz, t * jnp.stack([ly, lx]))


def surface_tensions(kind: str, material: Material, thickness, *, cell_size=None):
    """Surface tensions ``(T_x, T_y)`` [N/m] a layer of the model carries at an (anisotropic)
    pre-stretch ``(lambda_x, lambda_y)`` = ``(material.pre_stretch, material.pre_stretch_y)``.

    ``T_x`` is the in-plane force along x per unit in-vivo length of a line along y (so a cut
    along y gapes under ``T_x``), ``T_y`` the same across a line along x; each the Cauchy stress
    times the current thickness (:func:`biaxial_membrane_state`). Equal to
    :func:`surface_tension` twice for an equibiaxial material. Linear limit:
    ``t (sigma_x, sigma_y)`` of :func:`difftissue.materials.biaxial_pre_stress`.

    Args:
        kind, thickness, cell_size: as for :func:`surface_tension`.
        material: one material; ``pre_stretch_y`` None means ``pre_stretch``.

    Returns a ``(2,)`` array. Jit-able, differentiable.
    """
    if _is_concrete(thickness) and not np.all(np.asarray(thickness, dtype=float) > 0):
        raise MaterialError(f"layer thickness must be > 0 m, got {thickness!r}")
    return thickness * biaxial_membrane_state(kind, material, cell_size=cell_size).tension_per_thickness


def surface_tension(kind: str, material: Material, thickness, *, cell_size=None):
    """Surface tension ``T`` [N/m] a layer of the model carries at ``material.pre_stretch``.

    ``T`` is the in-plane force per unit length of a cut line in the in-vivo (pre-stretched,
    mesh) state: the Cauchy stress times the current thickness,
    ``T = t P_xx(lambda0, lambda0, lambda_z) / lambda0`` with ``P`` the model's nominal stress
    and ``lambda_z`` its traction-free thickness stretch (:func:`membrane_state`). Per unit
    *stress-free* length it is ``lambda0 T``.

    Args:
        kind: one of :data:`difftissue.models.MODELS`.
        material: one material; ``pre_stretch`` is ``lambda0``.
        thickness: the layer's thickness ``t`` in the mesh [m], > 0 (its stress-free thickness:
            the model shrinks only x and y).
        cell_size: the lattice cell of ``springs_volume`` (see :func:`membrane_state`).

    As ``lambda0 -> 1`` it tends to the linear ``E (lambda0 - 1) t / (1 - nu)``
    (:func:`difftissue.materials.surface_tension_from_pre_stretch`) with a relative difference
    O(lambda0 - 1) (measured in docs/theory.md §7). Jit-able, differentiable.
    """
    if _is_concrete(thickness) and not np.all(np.asarray(thickness, dtype=float) > 0):
        raise MaterialError(f"layer thickness must be > 0 m, got {thickness!r}")
    return thickness * membrane_state(kind, material, cell_size=cell_size).tension_per_thickness


def pre_stretch_for_surface_tension(kind: str, material: Material, tension, thickness, *, cell_size=None):
    """The pre-stretch ``lambda0`` [-] at which a layer of the model carries the surface tension
    ``tension`` [N/m]: the inverse of :func:`surface_tension` in ``pre_stretch`` (the other fields
    of ``material`` are kept; its ``pre_stretch`` is ignored).

    Args:
        kind, material, cell_size: as for :func:`surface_tension`.
        tension: the surface tension ``T`` [N/m] (force per unit in-vivo length), >= 0 and below
            what the model can carry.
        thickness: the layer's mesh thickness ``t`` [m], > 0.

    Newton's method in ``(lambda0, lambda_z)`` on the membrane state's two conditions
    (traction-free thickness, in-plane force ``T / t``; see :func:`membrane_state`) from the
    linear inverse (:func:`difftissue.materials.pre_stretch_from_surface_tension`, which gives a
    smaller ``lambda0``: the models carry less than the linear tension). Jit-able, differentiable in
    ``material``, ``tension`` and ``thickness``; a tension the model cannot reach (or one that
    needs a ``lambda0`` outside ``springs_volume``'s range) is an error.
    """
    if _is_concrete(thickness) and not np.all(np.asarray(thickness, dtype=float) > 0):
        raise MaterialError(f"layer thickness must be > 0 m, got {thickness!r}")
    if _is_concrete(tension) and not (np.all(np.isfinite(np.asarray(tension, dtype=float))) and np.all(np.asarray(tension, dtype=float) >= 0)):
        raise MaterialError(f"surface tension must be a finite number >= 0 N/m, got {tension!r}")
    if material.pre_stretch_y is not None:
        raise MaterialError("pre_stretch_for_surface_tension inverts the equibiaxial surface tension; the material has a "
                            "pre_stretch_y (anisotropic pre-stretch): give it without one (pre_stretch_y=None), or solve "
                            "surface_tensions(...) = (T_x, T_y) for both pre-stretches")
    shape = _cell_shape(kind, cell_size)
    mat = _checked(kind, shape, material.replace(pre_stretch=1.0) if _is_concrete(material) else material)
    target = jnp.asarray(tension, dtype=float) / jnp.asarray(thickness, dtype=float)
    return _pre_stretch_for(kind, shape, mat, target)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _pre_stretch_for(kind, shape, mat, target):
    """``lambda0`` with ``tension_per_thickness(lambda0) = target`` [Pa].

    One Newton solve in ``(lambda0, lambda_z)`` of the membrane state's two conditions (the
    thickness is traction-free, ``d psi / d lambda_z = 0``, and the in-plane force is the target,
    ``d psi / d s = target``: :func:`_membrane_state`'s equations with ``lambda0`` unknown), not a
    Newton solve in ``lambda0`` around the thickness solve: the same root, one loop instead of
    one nested in another (the nested form compiled for ~15 s, its gradient ~25 s)."""

    def residual(y):
        density = _density_function(kind, shape, eqx.tree_at(lambda m: m.pre_stretch, mat, y[0]))

        def psi(s, lz):  # per unit mesh volume; s stretches x about the mesh (as in _membrane_state)
            F = jnp.diag(jnp.stack([s, jnp.ones_like(s), lz]))
            return density(F)

        one = jnp.ones_like(y[0])
        return jnp.stack([jax.grad(psi, argnums=1)(one, y[1]), jax.grad(psi, argnums=0)(one, y[1]) - target])

    lam_lin = 1.0 + target * (1.0 - mat.poisson_ratio) / mat.youngs_modulus
    lz0 = lam_lin ** (-2.0 * mat.poisson_ratio / (1.0 - mat.poisson_ratio))  # the linear thickness change
    y = _newton(residual, jax.jacfwd(residual), jnp.stack([lam_lin, lz0]), f"pre-stretch of {kind} for a surface tension",
                mat.youngs_modulus)
    return y[0]


# ------------------------------------------------------------------- uniaxial stress
def _frame(direction: str, shape) -> np.ndarray:
    if direction not in DIRECTIONS:
        raise ModelError(f"direction must be one of {sorted(DIRECTIONS)} (lattice axes: edge, face diagonal, body diagonal), got {direction!r}")
    hx, hy, hz = shape
    if direction == "[110]" and hx != hy or direction == "[111]" and not hx == hy == hz:
        raise ModelError(f"direction {direction} is a symmetry axis only of cells with equal edges in its plane; the cell is {shape}")
    n = np.asarray(DIRECTIONS[direction]) / np.linalg.norm(DIRECTIONS[direction])
    m = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [0.0, 1.0, 0.0])
    m = m / np.linalg.norm(m)
    return np.stack([n, m, np.cross(n, m)], axis=1)  # columns n, m, p


def uniaxial_stress(kind: str, material: Material, strain, *, direction: str = "[100]", cell_size=None):
    """Nominal stress [Pa] of the model in homogeneous uniaxial stress.

    A bar of the model stretched to engineering strain ``strain`` (``lambda - 1``, -1 < strain)
    along ``direction`` with traction-free lateral faces: the five other components of the
    (symmetric) stretch tensor minimise the energy. Returns ``P = d psi / d lambda``, the force
    per unit stress-free area, the stress of ``sigma = E (eps + b eps^3)`` read as nominal stress
    against engineering strain.

    Args:
        kind: one of :data:`difftissue.models.MODELS`.
        material: one material; its ``pre_stretch`` is ignored (the bar starts stress-free).
        strain: engineering strain(s) [-], scalar or array (vectorised).
        direction: a lattice direction of :data:`DIRECTIONS` (``"[100]"``: along a cell edge).
            The tet models are isotropic; the lattice is only at small strain.
        cell_size: ``springs_volume``'s cell ``(hx, hy, hz)`` (default a cube); ``"[110]"`` needs
            ``hx = hy``, ``"[111]"`` a cube (symmetry axes only, where the response is uniaxial).

    Jit-able, differentiable in ``material`` and ``strain``. Concrete values are solved by the
    same Newton iteration on the host, with one small compiled program for the cell's gradient
    and Hessian (agreeing with the jitted solve to ~1e-14): a report's many calls then compile
    in well under a second instead of several seconds. A strain where the iteration does not
    converge raises :class:`~difftissue.errors.ModelError` (under jit: a runtime error).
    """
    shape = _cell_shape(kind, cell_size)
    _frame(direction, shape)
    mat = _bar_material(kind, shape, material)
    eps = jnp.asarray(strain, dtype=jnp.result_type(float))
    if _is_concrete(eps) and not np.all(np.asarray(eps) > -1.0):
        raise ModelError(f"strain must be > -1 (engineering strain, stretch 1 + strain > 0), got {np.asarray(eps)}")
    if _is_concrete((mat, eps)):
        # Concrete values (a report, a script): Newton's method on the host with one small
        # compiled program (the cell's gradient and Hessian), not the jitted solve below,
        # whose compilation costs seconds for a few milliseconds of arithmetic.
        # Padded with zeros (stress 0) to a multiple of the quadrature's point count, as below:
        # one compiled program for every call of a report.
        flat = np.asarray(eps, dtype=float).reshape(-1)
        n = flat.shape[0]
        flat = np.concatenate([flat, np.zeros(-n % _QUADRATURE_POINTS)])
        return jnp.asarray(_uniaxial_stress_host(kind, shape, _frame(direction, shape), mat, flat)[:n].reshape(eps.shape))
    Q = jnp.asarray(_frame(direction, shape), dtype=eps.dtype)
    flat = eps.reshape(-1)
    n = flat.shape[0]
    if _is_concrete(eps) and n % _QUADRATURE_POINTS:
        # Concrete strains padded with zeros (stress 0) to a multiple of the quadrature's point
        # count: every call of a fit's report then runs ONE compiled program per model
        # (compiling it costs seconds; evaluating it milliseconds).
        flat = jnp.concatenate([flat, jnp.zeros(_QUADRATURE_POINTS - n % _QUADRATURE_POINTS, dtype=flat.dtype)])
    return _uniaxial_stress(kind, shape, Q, mat, flat)[:n].reshape(eps.shape)


def _bar_material(kind, shape, material: Material) -> Material:
    """The checked scalar material of :func:`uniaxial_stress`'s bar: the pre-stretches ignored
    (the bar starts stress-free)."""
    if material.pre_stretch_y is not None:
        material = material.replace(pre_stretch_y=None)
    mat = _checked(kind, shape, material)
    return eqx.tree_at(lambda m: m.pre_stretch, mat, jnp.ones_like(mat.pre_stretch))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _uniaxial_stress(kind, shape, Q, mat, eps):
    """Nominal stress along ``Q[:, 0]`` at the strains ``eps`` (one program for every direction)."""
    nu = mat.poisson_ratio
    density = _density_function(kind, shape, mat)

    def psi(lam, y):
        S = jnp.stack([jnp.stack([lam, y[0], y[1]]), jnp.stack([y[0], y[2], y[3]]), jnp.stack([y[1], y[3], y[4]])])
        return density(Q @ S @ Q.T)

    def one(e):
        lam = 1.0 + e
        lt = lam ** (-nu)
        zero = jnp.zeros_like(lt)
        y0 = jnp.stack([zero, zero, lt, zero, lt])
        y = _newton(jax.grad(lambda y: psi(lam, y)), jax.hessian(lambda y: psi(lam, y)), y0, f"uniaxial stress of {kind}", mat.youngs_modulus)
        return jax.grad(psi, argnums=0)(lam, y)

    return jax.vmap(one)(eps)


def _uniaxial_stress_host(kind, shape, Q, mat, eps, fields=()):
    """:func:`_uniaxial_stress` for concrete values: the same Newton iteration (``_NEWTON_STEPS``
    limited steps, a residual check, one final step) on the host, the cell's gradient and
    Hessian from :class:`~difftissue.solvers.host.ModelDerivatives` (one compiled program per
    model structure, for every material, cell shape and strain count, shared with the host
    solves of small specimens). The positions are linear in the stretch tensor
    ``S = [[lam, y0, y1], [y0, y2, y3], [y1, y3, y4]]`` (``x = X (Q S Q^T)^T``), so the
    gradient and Hessian in ``(lam, y)`` are ``J^T g`` and ``J^T H J`` with the constant
    ``J = dx / d(lam, y)`` (24, 6). Returns ``P`` (B,) [Pa]; with ``fields`` (material field
    names) ``(P, dP)``, ``dP`` ``(len(fields), B)`` the derivatives of ``P`` with respect to
    those fields at the solution (implicit function theorem: ``dP = dg_lam - H_lam,y
    H_y,y^-1 dg_y`` with ``dg = J^T d(gradient)/d(field)`` from the same program; zero for the
    ignored pre-stretches). A point that does not converge raises :class:`ModelError`."""
    model, X, V = _unit_cell(kind, shape)
    checked = model.checked(mat)
    entries = [((0, 0),), ((0, 1), (1, 0)), ((0, 2), (2, 0)), ((1, 1),), ((1, 2), (2, 1)), ((2, 2),)]
    J = np.empty((X.size, len(entries)))
    for c, ij in enumerate(entries):
        B = np.zeros((3, 3))
        for i, j in ij:
            B[i, j] = 1.0
        J[:, c] = (X @ (Q @ B @ Q.T).T).reshape(-1)
    lam = 1.0 + eps
    nu = float(mat.poisson_ratio)
    lt = lam ** (-nu)
    zero = np.zeros_like(lt)
    y = np.stack([zero, zero, lt, zero, lt], axis=1)

    cell = ModelDerivatives(model)
    Jy = J[:, 1:]

    def derivatives(y):
        p = np.concatenate([lam[:, None], y], axis=1)
        _, g, H, _, _ = cell(checked, (p @ J.T).reshape(-1, *X.shape))
        g, H = g / V, H / V
        return g @ J, Jy.T @ H @ Jy  # (B, 5, 5); a three-operand np.einsum took ~0.4 ms a call

    for _ in range(_NEWTON_STEPS):
        gy, Hy = derivatives(y)
        d = np.linalg.solve(Hy, gy[:, 1:, None])[..., 0]
        y = y - np.clip(d, -_MAX_STEP, _MAX_STEP)
    gy, Hy = derivatives(y)
    res = np.max(np.abs(gy[:, 1:]), axis=1)
    bad = ~(res <= 1e3 * np.finfo(float).eps * float(mat.youngs_modulus))
    if np.any(bad):
        raise ModelError(f"uniaxial stress of {kind}: Newton's method did not converge at strain {eps[bad].tolist()} (the state is "
                         "outside the model's range, e.g. a strain that inverts or collapses the cell)")
    y = y - np.linalg.solve(Hy, gy[:, 1:, None])[..., 0]
    if not fields:
        return derivatives(y)[0][:, 0]
    p = np.concatenate([lam[:, None], y], axis=1)
    _, g, H, dgdm, _ = cell(checked, (p @ J.T).reshape(-1, *X.shape))
    H_ly, H_yy = np.einsum("i,bij,jc->bc", J[:, 0], H / V, Jy), Jy.T @ (H / V) @ Jy
    dP = np.zeros((len(fields), eps.shape[0]))
    for k, name in enumerate(fields):
        if name in ("pre_stretch", "pre_stretch_y"):
            continue  # ignored: the bar starts stress-free
        dg = np.sum(np.asarray(getattr(dgdm, name)), axis=-1) / V @ J  # (B, 6): d(J^T g)/d(field)
        dP[k] = dg[:, 0] - np.einsum("bc,bc->b", H_ly, np.linalg.solve(H_yy, dg[:, 1:, None])[..., 0])
    return (g / V @ J)[:, 0], dP


def _quadrature(strain_range):
    """Gauss-Legendre points and weights of :func:`continuum_cubic_coefficient` on ``strain_range``."""
    lo, hi = (float(v) for v in strain_range)
    if not (-1.0 < lo < hi and math.isfinite(hi)) or lo == 0.0 and hi == 0.0:
        raise ModelError(f"strain_range must be (lo, hi) with -1 < lo < hi, got {strain_range!r}")
    x, w = np.polynomial.legendre.leggauss(_QUADRATURE_POINTS)
    return 0.5 * (hi - lo) * x + 0.5 * (hi + lo), 0.5 * (hi - lo) * w


def _continuum_cubic_coefficient_gradient(kind: str, material: Material, fields, *, strain_range=UNIAXIAL_STRAIN_RANGE,
                                          direction: str = "[100]", cell_size=None) -> np.ndarray:
    """Derivatives of :func:`continuum_cubic_coefficient` with respect to the material ``fields``
    (concrete values), exact: the host Newton's solutions differentiated by the implicit function
    theorem (:func:`_uniaxial_stress_host`), ``d b_c = int d(P/E) eps^3 / int eps^6``."""
    eps, w = _quadrature(strain_range)
    shape = _cell_shape(kind, cell_size)
    Q = _frame(direction, shape)
    mat = _bar_material(kind, shape, material)
    P, dP = _uniaxial_stress_host(kind, shape, Q, mat, eps, tuple(fields))
    E = float(material.youngs_modulus)
    d_resid = dP / E
    for k, f in enumerate(fields):
        if f == "youngs_modulus":
            d_resid[k] -= P / E**2
    return np.sum(w * d_resid * eps**3, axis=1) / np.sum(w * eps**6)


def continuum_cubic_coefficient(kind: str, material: Material, *, strain_range=UNIAXIAL_STRAIN_RANGE, direction: str = "[100]", cell_size=None):
    """The ``b_c`` of the continuum law ``sigma = E (eps + b_c eps^3)`` that matches the model's
    uniaxial-stress response best over ``strain_range``.

    Continuous least squares of ``P(eps)/E - eps`` (:func:`uniaxial_stress`, nominal stress)
    against ``eps^3`` on ``[eps_lo, eps_hi]``:
    ``b_c = int (P/E - eps) eps^3 d eps / int eps^6 d eps``, by 16-point Gauss-Legendre quadrature.
    On a symmetric range the even part of the response (tension/compression asymmetry, which no
    ``eps + b eps^3`` law has) does not enter ``b_c``.

    For ``springs_volume`` this maps the lattice's spring coefficient ``material.cubic_coefficient``
    to the continuum one; at ``b = 0`` it is the lattice's own nonlinearity (nonzero). For the
    tet models (which ignore ``cubic_coefficient``) it is their energy's own cubic part
    (``fem_linear``: 0). Returns ``b_c`` [-]; jit-able, differentiable in ``material``.
    """
    eps, w = _quadrature(strain_range)
    P = uniaxial_stress(kind, material, jnp.asarray(eps), direction=direction, cell_size=cell_size)
    if _is_concrete((P, material.youngs_modulus)):  # NumPy: no compiled program per operation
        resid = np.asarray(P) / float(material.youngs_modulus) - eps
        return jnp.asarray(np.sum(w * resid * eps**3) / np.sum(w * eps**6))
    resid = P / jnp.asarray(material.youngs_modulus, dtype=float) - eps
    return jnp.sum(w * resid * eps**3) / np.sum(w * eps**6)


# ------------------------------------------------------------------- report records
def _linearised_se(gradient, fields, covariance):
    """``sqrt(g^T C g)`` with ``g = gradient()`` (called only with a usable covariance of the
    ``fields``); None without a covariance or where a variance is not finite."""
    if covariance is None or not fields:
        return None
    C = np.asarray(covariance, dtype=float)
    if C.shape != (len(fields), len(fields)) or not np.all(np.isfinite(C)):
        return None
    g = np.asarray(gradient(), dtype=float)
    var = float(g @ C @ g)
    return math.sqrt(var) if math.isfinite(var) and var >= 0 else None


def _delta_se(fn, material: Material, fields, covariance):
    """Standard error of ``fn(material)`` from the covariance [physical units] of the fitted
    ``fields``, linearised: ``sqrt(g^T C g)`` with ``g`` by central differences (relative step
    1e-6: the record needs a few digits, and the compiled forward program is reused; the
    functions' own derivatives are exact and tested). None without a covariance or where a
    variance is not finite."""

    def gradient():
        grad = []
        for f in fields:
            v = float(getattr(material, f))
            h = 1e-6 * max(abs(v), 1e-3)
            up, down = (float(fn(eqx.tree_at(lambda m: getattr(m, f), material, jnp.asarray(v + s)))) for s in (h, -h))
            grad.append((up - down) / (2.0 * h))
        return grad

    return _linearised_se(gradient, tuple(fields), covariance)


def surface_tension_record(kind: str, material: Material, layers, *, fields=(), covariance=None) -> dict:
    """``fit.json``'s record of the surface tension a fitted pre-stretched layer carries.

    Args:
        kind: the model.
        material: the fitted material (scalar fields).
        layers: ``[(name, thickness [m], cell_size (3,) [m] or None), ...]`` the layers the
            material applies to (their tensions add).
        fields, covariance: the fitted fields and their covariance (physical units), for the
            standard error (linearised: ``sqrt(g^T C g)``); None: no standard error.

    Returns a plain-JSON dict: ``value`` [N/m] (the model's own, :func:`surface_tension`),
    ``standard_error``, ``linearised_surface_tension`` (``E (lambda0 - 1) t / (1 - nu)``), the
    layers, ``model`` and the definition in words.
    """
    layers = [(str(n), float(t), None if c is None else tuple(float(v) for v in np.asarray(c).reshape(3))) for n, t, c in layers]
    if material.pre_stretch_y is not None:
        return _biaxial_surface_tension_record(kind, material, layers, fields=fields, covariance=covariance)

    def total(m):
        return sum(surface_tension(kind, m, t, cell_size=c) for _, t, c in layers)

    value = float(total(material))
    t_sum = sum(t for _, t, _ in layers)
    lin = float(surface_tension_from_pre_stretch(material, t_sum))
    se = _delta_se(total, material, tuple(fields), covariance)
    lz = [float(membrane_state(kind, material, cell_size=c).thickness_stretch) for _, _, c in layers]
    return {
        "value": value,
        "unit": "N/m",
        "standard_error": se,
        "model": kind,
        "pre_stretch": float(material.pre_stretch),
        "layers": [{"name": n, "thickness": t, "cell_size": None if c is None or kind not in LATTICE_MODELS else list(c), "thickness_stretch": z}
                   for (n, t, c), z in zip(layers, lz)],
        "linearised_surface_tension": lin,
        "linearised_over_model": lin / value if value != 0 else None,
        "definition": ("in-plane force per unit length of a cut line in the in-vivo (pre-stretched) state, from the model's own "
                       "equibiaxial stress with traction-free top and bottom: Cauchy stress x current thickness = t P_xx / lambda0 "
                       "(t the layer's mesh thickness, P the nominal stress); per unit stress-free length it is lambda0 times this. "
                       "linearised_surface_tension = E (lambda0 - 1) t / (1 - nu) is the small-strain formula"),
    }


def _biaxial_surface_tension_record(kind, material, layers, *, fields, covariance) -> dict:
    """:func:`surface_tension_record` of an anisotropic pre-stretch: ``value`` is ``T_x``,
    ``value_y`` is ``T_y`` (:func:`surface_tensions`)."""

    def total(m, i):
        return sum(surface_tensions(kind, m, t, cell_size=c)[i] for _, t, c in layers)

    tx, ty = float(total(material, 0)), float(total(material, 1))
    t_sum = sum(t for _, t, _ in layers)
    lin = [float(v) * t_sum for v in biaxial_pre_stress(material)]
    se = [_delta_se(lambda m, i=i: total(m, i), material, tuple(fields), covariance) for i in (0, 1)]
    lz = [float(biaxial_membrane_state(kind, material, cell_size=c).thickness_stretch) for _, _, c in layers]
    return {
        "value": tx,
        "value_y": ty,
        "unit": "N/m",
        "standard_error": se[0],
        "standard_error_y": se[1],
        "model": kind,
        "pre_stretch": float(material.pre_stretch),
        "pre_stretch_y": float(material.pre_stretch_y),
        "layers": [{"name": n, "thickness": t, "cell_size": None if c is None or kind not in LATTICE_MODELS else list(c), "thickness_stretch": z}
                   for (n, t, c), z in zip(layers, lz)],
        "linearised_surface_tension": lin[0],
        "linearised_surface_tension_y": lin[1],
        "linearised_over_model": lin[0] / tx if tx != 0 else None,
        "definition": ("anisotropic pre-stretch (pre_stretch along x, pre_stretch_y along y): value is T_x, the in-plane force along x "
                       "per unit in-vivo length of a line along y (a cut along y gapes under it), value_y is T_y; each from the "
                       "model's own biaxial stress with traction-free top and bottom (Cauchy stress x current thickness). "
                       "linearised_surface_tension(_y) = t E (eps_x + nu eps_y) / (1 - nu^2) (and x <-> y) is the small-strain formula"),
    }


def cubic_coefficient_record(material: Material, *, cell_size=None, strain_range=UNIAXIAL_STRAIN_RANGE, fields=(), covariance=None) -> dict:
    """``fit.json``'s record of what the ``springs_volume`` lattice's ``cubic_coefficient`` means
    as a continuum law (:func:`continuum_cubic_coefficient`): ``b_c`` along the lattice's
    edge [100] (``value``) and its face and body diagonals, ``b_c`` at ``b = 0`` (the lattice's
    own nonlinearity), the ratio ``(b_c(b) - b_c(0)) / b`` (at ``b = 0``: over ``[0, 1]``), the
    stress at the ends of the range
    (with the neo-Hookean FEM's, for comparison), and the misfit of the continuum law there."""
    b = float(material.cubic_coefficient)
    lo, hi = (float(v) for v in strain_range)
    kw = dict(strain_range=(lo, hi), cell_size=cell_size)
    shape = _cell_shape("springs_volume", cell_size)
    dirs = [d for d in DIRECTIONS if d == "[100]" or shape == (1.0, 1.0, 1.0)]

    def b_c(bb, d):
        return float(continuum_cubic_coefficient("springs_volume", material.replace(cubic_coefficient=bb), direction=d, **kw))

    by_dir = {d: b_c(b, d) for d in dirs}
    at_zero = {d: b_c(0.0, d) for d in dirs}
    # the mean slope over [0, b] (over [0, 1] at b = 0); the response is close to linear in b
    slope = {d: (by_dir[d] - at_zero[d]) / b if b != 0.0 else b_c(1.0, d) - at_zero[d] for d in dirs}
    ends = np.array([lo, hi])
    E = float(material.youngs_modulus)
    lattice_ends = np.asarray(uniaxial_stress("springs_volume", material, ends, cell_size=cell_size)) / E
    b100 = by_dir["[100]"]
    # The exact gradient (implicit function theorem on the host Newton), not central
    # differences: b_c is a small difference (P/E - eps against eps^3) of Newton solutions, whose
    # round-off differences of relative step 1e-6 turned into ~1e-7 relative error of the
    # standard error (and a last-bit change of the compiled cell program moved it by 8e-8).
    se = _linearised_se(lambda: _continuum_cubic_coefficient_gradient("springs_volume", material, fields, **kw), fields, covariance)
    return {
        "value": b100,
        "unit": "1",
        "standard_error": se,
        "direction": "[100] (along a cell edge)",
        "by_direction": by_dir,
        "at_lattice_b_zero": at_zero,
        "continuum_b_per_lattice_b": slope,
        "lattice_cubic_coefficient": b,
        "strain_range": [lo, hi],
        "stress_over_E_at_range_ends": {"strain": [lo, hi], "lattice": lattice_ends.tolist(), "continuum_law": (ends + b100 * ends**3).tolist()},
        "cell_size": None if cell_size is None else [float(v) for v in np.asarray(cell_size).reshape(3)],
        "definition": ("b_c of the continuum uniaxial law sigma = E (eps + b_c eps^3) (nominal stress, engineering strain, "
                       "lateral faces traction-free) that fits the springs_volume lattice's homogeneous uniaxial response best "
                       "(continuous least squares over strain_range). cubic_coefficient is the lattice's spring coefficient "
                       "(a = b k / L0^2), not this continuum b: give a continuum solver b_c, for the strain range stated"),
    }
