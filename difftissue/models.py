"""Elastic models of a specimen: total energy as a sum of per-element terms.

Four models share one interface (``energy(x, material)``, ``terms(material)``):

- ``"springs_volume"`` (:class:`SpringVolumeModel`, our real-time model): cubic springs on
  the cube lattice (12 edges + 12 face diagonals per cell) with isotropic constants plus a
  per-cell volume term carrying the missing bulk stiffness ``lambda - mu``. Exactly
  isotropic linear elasticity at small strain for ``1/4 <= nu < 1/2``; strain stiffening
  from the cubic coefficient.
- ``"stable_neo_hookean"`` (:class:`StableNeoHookeanModel`): Macklin & Müller (2021) with
  ``lambda' = lambda + mu``, the energy XPBD's stable neo-Hookean constraints minimise.
- ``"fem_linear"`` and ``"fem_neo_hookean"`` (:class:`FEMModel`): the reference FEM on
  linear tetrahedra. ``"fem_linear_nodal"`` and ``"fem_neo_hookean_nodal"`` are the same
  energies with the ``lambda`` term evaluated on node patches (nodal-averaged dilatation,
  Bonet & Burton 1998): locking-free for nearly incompressible materials (nu -> 1/2), see
  ``docs/materials.md``.

``material`` is a :class:`~difftissue.materials.Material` whose fields are scalars (one
material) or arrays of shape ``(n_regions,)`` (one value per region, see
:func:`stack_materials`). Element terms are pure functions of their nodes' positions, so
the solvers get energies, forces (``jax.grad``) and element Hessians from one description.

Pre-tension: a region whose ``pre_stretch`` is ``lambda0`` has as stress-free state the mesh
shrunk by ``1/lambda0`` in x and y (the surface plane; z is the thickness direction), so the
mesh itself is the pre-stretched state. Tets use ``Dm_inv diag(lambda0, lambda0, 1)`` and
rest volume ``V / lambda0^2``; springs get the rest lengths and geometric factors of the shrunk
cell, cells the rest volume ``V / lambda0^2``. ``lambda0 = 1`` reproduces the unstretched model
bit for bit. See ``docs/theory.md`` for the formulas.
"""

from __future__ import annotations

import abc
import math
from typing import Callable, ClassVar, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .energies.fem import (
    linear_elastic_energy_density,
    neo_hookean_energy_density,
    nodal_dilatation_energy,
    nodal_dilatation_hessian,
    nodal_volume_energy,
    nodal_volume_hessian,
)
from .energies.neo_hookean import deformation_gradient, det3, rest_shape, stable_neo_hookean_energy_density
from .energies.springs import cubic_spring_energy, cubic_spring_hessian
from .errors import InvertedElementError, MaterialError, ModelError, ModelRangeError
from .materials import Material, _is_concrete, explicit_pre_stretch_y, lame_parameters, material_fields
from .mesh import _CUBE_DIAGONALS, _CUBE_EDGES, _CUBE_CORNERS, TetMesh, node_patches

__all__ = [
    "MODELS",
    "NODAL_FEM_MODELS",
    "LATTICE_VARIANTS",
    "PRE_STRETCH_LATTICES",
    "LATTICE_MODELS",
    "MESH_MODELS",
    "ElementTerm",
    "ElasticModel",
    "SpringVolumeModel",
    "StableNeoHookeanModel",
    "FEMModel",
    "make_model",
    "matched_lattice_design",
    "MATCHED_PRE_STRETCH_RANGE",
    "stack_materials",
    "hexahedron_volume",
    "hexahedron_jacobians",
]

#: Model names accepted by :func:`make_model`.
MODELS = ("springs_volume", "stable_neo_hookean", "fem_linear", "fem_neo_hookean")
#: The FEM models with a node-based volumetric term (:class:`FEMModel` with
#: ``volumetric="nodal"``), also accepted by :func:`make_model`.
NODAL_FEM_MODELS = ("fem_linear_nodal", "fem_neo_hookean_nodal")
#: How :class:`SpringVolumeModel` builds the lattice of a pre-stretched region: ``"stress_free"``
#: (the default: spring factors of the cell shrunk by ``1/lambda0``), ``"mesh"`` (the mesh
#: cell's factors, only rest lengths and rest volumes shrunk) or ``"matched"`` (the mesh cell's
#: factors scaled per spring class and a lattice pre-stretch of its own, matched to the
#: neo-Hookean's tension and incremental moduli: :func:`matched_lattice_design`).
PRE_STRETCH_LATTICES = ("stress_free", "mesh", "matched")
#: The model names of ``springs_volume`` with ``pre_stretch_lattice="mesh"`` and ``"matched"``
#: (:class:`SpringVolumeModel`), accepted by :func:`make_model`; their ``kind`` is ``"springs_volume"``.
LATTICE_VARIANTS = ("springs_volume_mesh_lattice", "springs_volume_matched_lattice")
_VARIANT_OF_LATTICE = {"mesh": "springs_volume_mesh_lattice", "matched": "springs_volume_matched_lattice"}
#: Every model name of :class:`SpringVolumeModel` (the cube lattice): ``"springs_volume"`` and
#: :data:`LATTICE_VARIANTS`. A check for "a lattice model" (a cube lattice needed, lattice-effective
#: values, ``nu >= 1/4``) tests a model name against this tuple.
LATTICE_MODELS = ("springs_volume",) + LATTICE_VARIANTS
#: The model names of a tet mesh's elements (:data:`MODELS`) and the lattice variants
#: (:data:`LATTICE_VARIANTS`): every name :func:`make_model` accepts except the nodal FEM models.
MESH_MODELS = MODELS + LATTICE_VARIANTS


class ElementTerm(eqx.Module):
    """One family of elements: ``sum_e energy(x[nodes[e]], *params[e])`` [J].

    Attributes:
        name: what the term is (``"springs"``, ``"cell_volume"``, ``"tets"``).
        nodes: ``(E, k)`` node indices of each element.
        energy: ``energy(x_e (k, 3), *params_e) -> J`` for one element (vmapped by callers).
        params: per-element parameters, each with leading dimension ``E``.
        hessian: optional ``hessian(x_e, *params_e) -> (3k, 3k)`` [J/m^2] of ``energy``
            (node-major: row ``3 v + i`` is node ``v``, component ``i``), for an element whose
            Hessian has a cheaper exact form than ``jax.hessian`` of ``energy``; tested against it.
    """

    name: str = eqx.field(static=True)
    nodes: np.ndarray
    energy: Callable = eqx.field(static=True)
    params: tuple
    hessian: Callable | None = eqx.field(static=True, default=None)

    def element_energies(self, x):
        """Energy of every element [J], shape ``(E,)``."""
        return jax.vmap(self.energy)(x[self.nodes], *self.params)

    def total(self, x):
        """Sum of the element energies [J]."""
        return jnp.sum(self.element_energies(x))


def stack_materials(materials: Sequence[Material]) -> Material:
    """One :class:`Material` whose fields are arrays ``(n_regions,)`` from one material per region."""
    materials = list(materials)
    if not materials:
        raise MaterialError("need at least one material")
    if any(m.pre_stretch_y is not None for m in materials):  # anisotropic somewhere: lambda_y = lambda_x elsewhere
        materials = [explicit_pre_stretch_y(m) for m in materials]
    return jax.tree_util.tree_map(lambda *v: jnp.stack([jnp.asarray(a, dtype=float) for a in v]), *materials)


#: The messages of :meth:`ElasticModel.region_values`'s checks of a traced material (an
#: ``equinox.error_if`` inside a compiled program), for :func:`material_error_type`.
NONFINITE_MATERIAL_MESSAGE = "material parameters contain NaN or infinite values"
NONPOSITIVE_YOUNGS_MODULUS_MESSAGE = "youngs_modulus must be > 0 Pa"
#: ``.format(name=...)`` for ``pre_stretch`` / ``pre_stretch_y``
NONPOSITIVE_PRE_STRETCH_MESSAGE = "{name} must be > 0 (1 = no pre-tension)"
#: the start of the Poisson's ratio range message (the model's range and name follow)
POISSON_RANGE_MESSAGE_START = "poisson_ratio outside ["


def material_error_type(message: str) -> type | None:
    """The named error a traced material check's ``message`` stands for (raised by a
    library-compiled program: :class:`~difftissue.errors.MaterialError` for a NaN, a
    non-positive modulus or pre-stretch, :class:`~difftissue.errors.ModelRangeError` for a
    Poisson's ratio outside the model's range), None for any other message."""
    pre_stretch = tuple(NONPOSITIVE_PRE_STRETCH_MESSAGE.format(name=n) for n in ("pre_stretch", "pre_stretch_y"))
    if message in (NONFINITE_MATERIAL_MESSAGE, NONPOSITIVE_YOUNGS_MODULUS_MESSAGE) + pre_stretch:
        return MaterialError
    if message.startswith(POISSON_RANGE_MESSAGE_START):
        return ModelRangeError
    return None


class CheckedMaterial(Material):
    """A :class:`Material` whose fields are ``(n_regions,)`` arrays already range-checked by
    one model's :meth:`ElasticModel.checked` (internal to the solvers: the model skips its
    checks for it). Valid only with the model that checked it."""


# ----------------------------------------------------------------- hexahedral cells
_XI = 2.0 * _CUBE_CORNERS.astype(float) - 1.0  # (8, 3) reference corners in [-1, 1]^3
_GAUSS = _XI / math.sqrt(3.0)  # 2x2x2 Gauss points, weight 1 each


def _hex_shape_gradients() -> np.ndarray:
    """dN_v/dxi_d at the 8 Gauss points: ``(8 points, 8 nodes, 3)``."""
    g = np.empty((8, 8, 3))
    for p, xi in enumerate(_GAUSS):
        for v in range(8):
            f = 1.0 + _XI[v] * xi
            for d in range(3):
                g[p, v, d] = _XI[v, d] / 8.0 * np.prod(np.delete(f, d))
    return g


_HEX_DN = _hex_shape_gradients()


def hexahedron_jacobians(x):
    """Jacobian determinants ``det(dx/dxi)`` of a trilinear hexahedron at its 8 Gauss points.

    Args:
        x: ``(8, 3)`` node positions [m], local order ``v = bx + 2 by + 4 bz``.

    Returns:
        ``(8,)`` determinants [m^3 per unit reference volume].
    """
    J = jnp.einsum("vi,pvd->pid", x, _HEX_DN)
    return det3(J)


def hexahedron_volume(x):
    """Exact volume [m^3] of a trilinear hexahedron (2x2x2 Gauss integration of ``det J``,
    exact because ``det J`` is at most quadratic in each reference coordinate)."""
    return jnp.sum(hexahedron_jacobians(x))


def _hex_volume_tensor() -> np.ndarray:
    """``T (24, 24, 24)`` with :func:`hexahedron_volume` ``= T x x x / 6`` for the flattened node
    positions ``x (24,)`` (node-major) [-].

    ``det J = eps_ijk eps_abc J_ia J_jb J_kc / 6`` and ``J_ia = sum_v x_vi dN_va`` is linear in
    ``x``, so the volume (a sum of ``det J`` over the Gauss points) is a homogeneous cubic form:
    its gradient is ``T x x / 2`` and its Hessian ``T x``, exactly.
    """
    eps = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, k], eps[i, k, j] = 1.0, -1.0
    return np.einsum("ijk,abc,pva,pwb,pzc->viwjzk", eps, eps, _HEX_DN, _HEX_DN, _HEX_DN).reshape(24, 24, 24)


_HEX_VOLUME_T = _hex_volume_tensor()


def _spring_energy(x, rest_length, stiffness, cubic):
    return cubic_spring_energy(x[0], x[1], rest_length, stiffness, cubic)


def _spring_hessian(x, rest_length, stiffness, cubic):
    """Hessian ``(6, 6)`` [J/m^2] of :func:`_spring_energy` (closed form,
    :func:`~difftissue.energies.springs.cubic_spring_hessian`)."""
    return cubic_spring_hessian(x[0], x[1], rest_length, stiffness, cubic)


def _volume_penalty(volume, rest_volume, bulk_stiffness):
    """``(lambda - mu) (V - V0)^2 / (2 V0)`` [J] of a cell of volume ``V`` [m^3]."""
    dv = volume - rest_volume
    return 0.5 * bulk_stiffness * dv * dv / rest_volume


def _cell_volume_energy(x, rest_volume, bulk_stiffness):
    return _volume_penalty(hexahedron_volume(x), rest_volume, bulk_stiffness)


def _cell_volume_hessian(x, rest_volume, bulk_stiffness):
    """Hessian ``(24, 24)`` [J/m^2] of :func:`_cell_volume_energy`: the energy is
    ``psi(V(x))`` with ``V`` the cubic form of :func:`_hex_volume_tensor`, so
    ``H = psi''(V) grad V grad V^T + psi'(V) T x`` (one matrix product per cell instead of 24
    reverse passes of ``jax.hessian``)."""
    xf = x.reshape(-1)
    # T x as a (576, 24) matrix times x: under vmap one matrix product for all cells (a
    # (24, 24, 24) tensor times a vector is batched element by element: 0.30 against 0.17 s
    # for 32,000 cells).
    hess_v = (jnp.asarray(_HEX_VOLUME_T.reshape(576, 24), dtype=xf.dtype) @ xf).reshape(24, 24)
    grad_v = 0.5 * (hess_v @ xf)
    volume = jnp.dot(grad_v, xf) / 3.0
    d_psi = jax.grad(_volume_penalty)
    d1 = d_psi(volume, rest_volume, bulk_stiffness)
    d2 = jax.grad(d_psi)(volume, rest_volume, bulk_stiffness)
    return d2 * jnp.outer(grad_v, grad_v) + d1 * hess_v


def _fem_linear_energy(x, Dm_inv, V0, lam, mu):
    return V0 * linear_elastic_energy_density(deformation_gradient(x, Dm_inv), lam, mu)


def _fem_neo_hookean_energy(x, Dm_inv, V0, lam, mu):
    return V0 * neo_hookean_energy_density(deformation_gradient(x, Dm_inv), lam, mu)


def _fem_linear_shear_energy(x, Dm_inv, V0, mu):
    """``V0 mu eps:eps`` [J]: the linear tet energy without its ``lambda`` term."""
    return V0 * linear_elastic_energy_density(deformation_gradient(x, Dm_inv), 0.0, mu)


def _fem_neo_hookean_shear_energy(x, Dm_inv, V0, mu):
    """``V0 mu/2 (I1 - 3 - 2 ln J)`` [J]: the neo-Hookean tet energy without its ``lambda`` term."""
    return V0 * neo_hookean_energy_density(deformation_gradient(x, Dm_inv), 0.0, mu)


def _stable_neo_hookean_energy(x, Dm_inv, V0, mu, lam_shift):
    return V0 * stable_neo_hookean_energy_density(deformation_gradient(x, Dm_inv), mu, lam_shift)


# ------------------------------------------------------------------------------ models
class ElasticModel(eqx.Module):
    """Common data and methods of the elastic models.

    Attributes:
        kind: the model name (one of :data:`MODELS`).
        rest_points: ``(N, 3)`` rest positions [m].
        tets: ``(M, 4)`` tetrahedra (for masses and inversion checks).
        tet_regions: ``(M,)`` region of each tet.
        tet_Dm_inv: ``(M, 3, 3)`` inverse rest edge matrices [1/m].
        tet_volumes: ``(M,)`` rest volumes [m^3].
        region_names: names of the regions.
    """

    kind: str = eqx.field(static=True)
    rest_points: np.ndarray
    tets: np.ndarray
    tet_regions: np.ndarray
    tet_Dm_inv: np.ndarray
    tet_volumes: np.ndarray
    region_names: tuple[str, ...] = eqx.field(static=True)
    #: Poisson-ratio range the model represents: [nu_min, 1/2).
    nu_min: float = eqx.field(static=True)
    #: True when the energy is exactly proportional to Young's modulus at fixed positions and
    #: fixed other material fields (every stiffness is ``E`` times a function of ``nu`` and the
    #: geometry, also under differentiation). Then a displacement-controlled equilibrium
    #: without applied forces does not depend on ``E`` and every reaction force is proportional
    #: to it (:attr:`difftissue.scenarios.Indentation.prediction_scales_with_youngs_modulus`).
    #: False unless a model states it (and a test checks it).
    energy_linear_in_youngs_modulus: ClassVar[bool] = False

    @property
    def n_nodes(self) -> int:
        return int(self.rest_points.shape[0])

    @property
    def model_name(self) -> str:
        """The name :func:`make_model` builds this model from, recorded by the scenarios
        (``kind`` unless a variant of the same law; a wrapper such as a contact model reports
        its ``base``'s)."""
        base = getattr(self, "base", None)
        return base.model_name if isinstance(base, ElasticModel) else self.kind

    @property
    def n_regions(self) -> int:
        return len(self.region_names)

    def checked(self, material: Material) -> "CheckedMaterial":
        """``material`` with per-region fields, range-checked once (see :meth:`region_values`).

        A solver that evaluates the energy many times (Newton steps, line searches, Hessians)
        checks the material once with this and passes the result on: the checks under jit are
        ``equinox.error_if`` callbacks, and repeating them in every evaluation made the
        compiled programs of small simulations several times larger (374 callbacks in the
        one-cube compression protocol).
        """
        if isinstance(material, CheckedMaterial):
            return material
        p = self.region_values(material)
        return CheckedMaterial(**p)

    def region_values(self, material: Material) -> dict[str, jax.Array]:
        """Material fields as ``(n_regions,)`` arrays, checked for the model's valid range.

        Concrete values raise :class:`MaterialError` / :class:`ModelRangeError`; traced
        values (inside jit) are checked with ``equinox.error_if``. A :class:`CheckedMaterial`
        (from :meth:`checked`) is returned as it is.
        """
        if isinstance(material, CheckedMaterial):
            return {name: getattr(material, name) for name in material_fields(material)}
        R = self.n_regions
        out = {}
        for name in material_fields(material):
            raw = getattr(material, name)
            if isinstance(raw, jax.core.Tracer):
                v = jnp.asarray(raw, dtype=float)
                if v.ndim == 0:
                    v = jnp.broadcast_to(v, (R,))
            else:
                # Concrete: broadcast in NumPy (the same values; an eager jnp.broadcast_to
                # compiles a one-operation program of its own).
                a = np.asarray(raw, dtype=float)
                v = jnp.asarray(np.broadcast_to(a, (R,)) if a.ndim == 0 else a, dtype=float)
            if v.shape != (R,):
                raise MaterialError(f"{name} has shape {v.shape}; give a scalar or one value per region ({R}: {list(self.region_names)})")
            out[name] = v
        E, nu = out["youngs_modulus"], out["poisson_ratio"]
        bad_nu = f"{POISSON_RANGE_MESSAGE_START}{self.nu_min:g}, 0.5) for the {self.kind} model"
        if self.kind == "springs_volume":
            bad_nu += " (its volume term would need negative stiffness below 1/4; use stable_neo_hookean or fem_* there)"
        if _is_concrete(out):
            for name, arr in out.items():
                if not np.all(np.isfinite(np.asarray(arr))):
                    raise MaterialError(f"{name} contains NaN or infinite values: {np.asarray(arr)}")
            if not np.all(np.asarray(E) > 0):
                raise MaterialError(f"youngs_modulus must be > 0 Pa, got {np.asarray(E)}")
            for name in ("pre_stretch", "pre_stretch_y"):
                if name in out and not np.all(np.asarray(out[name]) > 0):
                    raise MaterialError(f"{NONPOSITIVE_PRE_STRETCH_MESSAGE.format(name=name)}, got {np.asarray(out[name])}")
            nu_np = np.asarray(nu)
            if not np.all((nu_np >= self.nu_min) & (nu_np < 0.5)):
                raise ModelRangeError(f"{bad_nu}: {nu_np}")
        else:
            finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in out.values()]))
            E = eqx.error_if(E, ~finite, NONFINITE_MATERIAL_MESSAGE)
            E = eqx.error_if(E, jnp.any(E <= 0), NONPOSITIVE_YOUNGS_MODULUS_MESSAGE)
            for name in ("pre_stretch", "pre_stretch_y"):
                if name in out:
                    out[name] = eqx.error_if(out[name], jnp.any(out[name] <= 0), NONPOSITIVE_PRE_STRETCH_MESSAGE.format(name=name))
            nu = eqx.error_if(nu, jnp.any((nu < self.nu_min) | (nu >= 0.5)), bad_nu)
            out["youngs_modulus"], out["poisson_ratio"] = E, nu
        return out

    def stress_free_tets(self, pre_stretch, pre_stretch_y=None):
        """Inverse rest edge matrices and rest volumes of the tets' stress-free state.

        A region pre-stretched by ``(lambda_x, lambda_y)`` is stress-free when shrunk by
        ``diag(1/lambda_x, 1/lambda_y, 1)``: ``Dm_inv_eff = Dm_inv diag(lambda_x, lambda_y, 1)``
        [1/m] (so the elastic deformation gradient is ``F_mesh diag(lambda_x, lambda_y, 1)``) and
        ``V0_eff = V0 / (lambda_x lambda_y)`` [m^3]. Exact (bit for bit) at ``lambda = 1``; with
        ``lambda_y = lambda_x`` bit for bit the equibiaxial result.

        Args:
            pre_stretch: ``(n_regions,)`` pre-stretch ``lambda_x`` per region [-] (``region_values``).
            pre_stretch_y: ``(n_regions,)`` ``lambda_y`` per region [-]; None: ``lambda_x``.

        Returns:
            ``(Dm_inv_eff (M, 3, 3), V0_eff (M,))``, differentiable in both pre-stretches.
        """
        lx = jnp.asarray(pre_stretch)[self.tet_regions]
        ly = lx if pre_stretch_y is None else jnp.asarray(pre_stretch_y)[self.tet_regions]
        scale = jnp.stack([lx, ly, jnp.ones_like(lx)], axis=-1)
        return jnp.asarray(self.tet_Dm_inv) * scale[:, None, :], jnp.asarray(self.tet_volumes) / (lx * ly)

    @abc.abstractmethod
    def terms(self, material: Material) -> tuple[ElementTerm, ...]:
        """The element terms whose energies sum to the model's elastic energy."""

    def energy(self, x, material: Material):
        """Total elastic energy [J] at node positions ``x`` (N, 3) [m]."""
        return sum(t.total(x) for t in self.terms(material))

    def tet_jacobians(self, x):
        """``det F`` of every tet at positions ``x`` (volume ratio; <= 0 means inverted)."""
        return det3(deformation_gradient(x[self.tets], self.tet_Dm_inv))

    def min_volume_ratio(self, x):
        """Smallest element volume ratio ``V / V0`` at ``x`` (<= 0: an element is inverted)."""
        return jnp.min(self.tet_jacobians(x))

    def lumped_masses(self, material: Material):
        """Nodal masses [kg]: each tet's mass ``rho V0`` shared equally by its four nodes.

        ``V0`` is the mesh volume: ``density`` is referred to the mesh (the pre-stretched
        state when ``pre_stretch`` differs from 1).
        """
        rho = self.region_values(material)["density"][self.tet_regions]
        m = jnp.zeros(self.n_nodes).at[self.tets.reshape(-1)].add(jnp.repeat(rho * self.tet_volumes / 4.0, 4))
        return m


# Mesh set-up on concrete arrays: one compiled program each (not one per operation). Not in
# NumPy, although the geometry helpers take NumPy input (difftissue.energies.volume.array_namespace):
# a NumPy evaluation differs in the last bit, which moves a fit by round-off and took a
# degenerate static solve (an unheld node under a cone's apex, tests/test_static.py) past its
# Newton step limit.
_jit_rest_shape = jax.jit(rest_shape)
_jit_hexahedron_volumes = jax.jit(jax.vmap(hexahedron_volume))
_jit_hexahedron_jacobians = jax.jit(jax.vmap(hexahedron_jacobians))


def _tet_geometry(mesh: TetMesh):
    Dm_inv, V0 = _jit_rest_shape(np.asarray(mesh.points, dtype=float)[mesh.tets])
    Dm_inv, V0 = np.asarray(Dm_inv), np.asarray(V0)
    bad = np.flatnonzero(~(V0 > 0))
    if bad.size:
        raise InvertedElementError(f"{bad.size} tet(s) have non-positive rest volume: elements {bad[:8].tolist()}", bad)
    return Dm_inv, V0


def _base_fields(mesh: TetMesh, kind: str, nu_min: float) -> dict:
    if not isinstance(mesh, TetMesh):
        raise ModelError(f"expected a TetMesh, got {type(mesh).__name__}")
    Dm_inv, V0 = _tet_geometry(mesh)
    return dict(
        kind=kind,
        rest_points=np.asarray(mesh.points, dtype=float),
        tets=mesh.tets,
        tet_regions=mesh.region_ids,
        tet_Dm_inv=Dm_inv,
        tet_volumes=V0,
        region_names=mesh.region_names,
        nu_min=nu_min,
    )


class FEMModel(ElasticModel):
    """Reference FEM on linear tets: ``sum_e V0_e Psi(F_e)`` with the linear (small-strain) or
    compressible neo-Hookean ``Psi = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2`` density.

    ``volumetric="element"`` (default) evaluates the whole density per tet. Linear tets then
    *lock* for nearly incompressible materials (nu >= ~0.45: every tet must keep its volume,
    more constraints than the mesh has degrees of freedom), so displacements converge slowly
    and from the stiff side. ``volumetric="nodal"`` keeps the ``lambda``-free part per tet
    (``mu eps:eps``, resp. ``mu/2 (I1 - 3 - 2 ln J_e)``) and evaluates the ``lambda`` term per
    node patch on the patch's volume-averaged dilatation (``lambda/2 theta_n^2`` resp.
    ``lambda/2 (ln J_n)^2``, :func:`nodal_volume_energy`; one patch per node and region, so a
    pressure may jump across a material interface): one volume constraint per node instead of
    per tet, no locking. Under a homogeneous deformation both give exactly the same energy
    (any strain), so the continuum law is unchanged; only the discretisation differs.

    Attributes (besides :class:`ElasticModel`'s):
        volumetric: ``"element"`` or ``"nodal"``.
        patch_nodes, patch_tets, patch_local_tets, patch_valid, patch_regions: the node patches
            of :func:`node_patches` (``None`` for ``volumetric="element"``).
    """

    volumetric: str = eqx.field(static=True)
    energy_linear_in_youngs_modulus: ClassVar[bool] = True  # lambda and mu are E times functions of nu
    patch_nodes: np.ndarray | None
    patch_tets: np.ndarray | None
    patch_local_tets: np.ndarray | None
    patch_valid: np.ndarray | None
    patch_regions: np.ndarray | None

    def __init__(self, mesh: TetMesh, kind: str = "fem_linear", *, volumetric: str = "element"):
        if kind not in ("fem_linear", "fem_neo_hookean"):
            raise ModelError(f"FEMModel kind must be 'fem_linear' or 'fem_neo_hookean', got {kind!r}")
        if volumetric not in ("element", "nodal"):
            raise ModelError(f"volumetric must be 'element' (per-tet energy) or 'nodal' (nodal-averaged dilatation), got {volumetric!r}")
        for k, v in _base_fields(mesh, kind, -1.0).items():
            setattr(self, k, v)
        self.volumetric = volumetric
        patches = node_patches(self.tets, self.tet_regions) if volumetric == "nodal" else (None,) * 5
        self.patch_nodes, self.patch_tets, self.patch_local_tets, self.patch_valid, self.patch_regions = patches

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.tet_regions
        Dm_inv, V0 = self.stress_free_tets(p["pre_stretch"], p.get("pre_stretch_y"))
        if self.volumetric == "element":
            fn = _fem_linear_energy if self.kind == "fem_linear" else _fem_neo_hookean_energy
            return (ElementTerm("tets", self.tets, fn, (Dm_inv, V0, lam[r], mu[r])),)
        shear = _fem_linear_shear_energy if self.kind == "fem_linear" else _fem_neo_hookean_shear_energy
        volume, volume_hessian = (nodal_dilatation_energy, nodal_dilatation_hessian) if self.kind == "fem_linear" else (nodal_volume_energy, nodal_volume_hessian)
        ids = self.patch_tets
        weights = jnp.where(self.patch_valid, V0[ids] / 4.0, 0.0)
        return (
            ElementTerm("tets", self.tets, shear, (Dm_inv, V0, mu[r])),
            ElementTerm("node_volume", self.patch_nodes, volume, (self.patch_local_tets, Dm_inv[ids], weights, lam[self.patch_regions]), hessian=volume_hessian),
        )


class StableNeoHookeanModel(ElasticModel):
    """Stable neo-Hookean tets (Macklin & Müller 2021) with ``lambda' = lambda + mu`` so the
    small-strain response is the material's (E, nu)."""

    energy_linear_in_youngs_modulus: ClassVar[bool] = True  # lambda + mu and mu are E times functions of nu

    def __init__(self, mesh: TetMesh):
        for k, v in _base_fields(mesh, "stable_neo_hookean", -1.0).items():
            setattr(self, k, v)

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.tet_regions
        Dm_inv, V0 = self.stress_free_tets(p["pre_stretch"], p.get("pre_stretch_y"))
        return (ElementTerm("tets", self.tets, _stable_neo_hookean_energy, (Dm_inv, V0, mu[r], (lam + mu)[r])),)


def _cell_spring_factors(cell_size: np.ndarray) -> np.ndarray:
    """Geometric factors ``g`` (k = mu g) of the 24 springs of each box cell ``(C, 24)`` [m].

    For a box with edges (hx, hy, hz) and volume V, isotropic spring elasticity
    (lambda_s = mu_s = mu) requires

        edge along a:            g_a  = V (3 - h_a^2 (1/h_b^2 + 1/h_c^2)) / (4 h_a^2)
        diagonal in plane (a,b): g_ab = V (h_a^2 + h_b^2) / (4 h_a^2 h_b^2)

    which reduce to h/4 and h/2 for a cube (DESIGN.md §3.1).
    """
    h = np.asarray(cell_size, dtype=float)
    V = np.prod(h, axis=1)
    out = np.empty((len(h), 24))
    for s, (a, b) in enumerate(_CUBE_EDGES):
        ax = int(np.log2(a ^ b))
        others = [d for d in range(3) if d != ax]
        out[:, s] = V * (3.0 - h[:, ax] ** 2 * (1.0 / h[:, others[0]] ** 2 + 1.0 / h[:, others[1]] ** 2)) / (4.0 * h[:, ax] ** 2)
    for s, (a, b) in enumerate(_CUBE_DIAGONALS):
        ax = [d for d in range(3) if (a ^ b) >> d & 1]
        out[:, 12 + s] = V * (h[:, ax[0]] ** 2 + h[:, ax[1]] ** 2) / (4.0 * h[:, ax[0]] ** 2 * h[:, ax[1]] ** 2)
    return out


def _cell_spring_factor_slopes(cell_size: np.ndarray) -> np.ndarray:
    """Derivatives ``dg/ds`` [m] of the 24 spring factors of each box cell ``(C, 24)`` with
    respect to ``s = lambda0^-2``, for the cell shrunk in x and y by ``1/lambda0``.

    With ``(hx, hy) -> (hx, hy) / lambda0`` every factor of :func:`_cell_spring_factors` is
    affine in ``s``: ``g(lambda0) = g(1) + (s - 1) dg/ds`` with, for ``V = hx hy hz``,

        edge along x or y:  -V / (4 hz^2)        edge along z:       3 V / (4 hz^2)
        diagonal in (x, y):  0                   diagonal in (x|y, z): V / (4 hz^2)

    (insert the shrunk edges into the formulas of :func:`_cell_spring_factors`).
    """
    h = np.asarray(cell_size, dtype=float)
    unit = np.prod(h, axis=1) / (4.0 * h[:, 2] ** 2)
    out = np.empty((len(h), 24))
    for s, (a, b) in enumerate(_CUBE_EDGES):
        out[:, s] = 3.0 * unit if (a ^ b) == 4 else -unit
    for s, (a, b) in enumerate(_CUBE_DIAGONALS):
        out[:, 12 + s] = unit if (a ^ b) & 4 else 0.0
    return out


def _cell_spring_factor_ratio_slopes(cell_size: np.ndarray) -> np.ndarray:
    """Coefficients ``(C, 24, 2)`` [m] of ``(rho - 1, 1/rho - 1)``, ``rho = lambda_x / lambda_y``,
    in the 24 spring factors of each box cell shrunk by ``diag(1/lambda_x, 1/lambda_y, 1)``.

    With ``q = 1/(lambda_x lambda_y)`` and ``u_a = V / (4 h_a^2)`` the factors of
    :func:`_cell_spring_factors` of the shrunk cell are exactly

        edge along x:  3 u_x rho - u_y / rho - u_z q     edge along y: 3 u_y / rho - u_x rho - u_z q
        edge along z:  3 u_z q - u_x rho - u_y / rho     diagonal in (x, y): u_x rho + u_y / rho
        diagonal in (x, z): u_z q + u_x rho              diagonal in (y, z): u_z q + u_y / rho

    so ``g = g(1) + (q - 1) dg/ds + (rho - 1) c_x + (1/rho - 1) c_y`` with ``dg/ds`` of
    :func:`_cell_spring_factor_slopes` (``q = s`` when ``lambda_x = lambda_y``, where the last
    two terms vanish exactly) and ``(c_x, c_y)`` returned here.
    """
    h = np.asarray(cell_size, dtype=float)
    V = np.prod(h, axis=1)
    ux, uy = V / (4.0 * h[:, 0] ** 2), V / (4.0 * h[:, 1] ** 2)
    out = np.zeros((len(h), 24, 2))
    for s, (a, b) in enumerate(_CUBE_EDGES):
        bit = a ^ b
        out[:, s, 0] = 3.0 * ux if bit == 1 else -ux
        out[:, s, 1] = 3.0 * uy if bit == 2 else -uy
    for s, (a, b) in enumerate(_CUBE_DIAGONALS):
        bit = a ^ b
        out[:, 12 + s, 0] = ux if bit & 1 else 0.0
        out[:, 12 + s, 1] = uy if bit & 2 else 0.0
    return out


def _admissible_pre_stretch(g: np.ndarray, slope: np.ndarray) -> tuple[float, float]:
    """Range ``(lo, hi)`` of ``lambda0`` keeping every ``g + (lambda0^-2 - 1) slope >= 0``."""
    lo, hi = 0.0, math.inf
    with np.errstate(divide="ignore", invalid="ignore"):
        pos, neg = slope > 0, slope < 0
        if np.any(pos):
            smin = np.max(1.0 - g[pos] / slope[pos])  # s = lambda0^-2 must stay >= smin
            hi = math.inf if smin <= 0 else float(smin**-0.5)
        if np.any(neg):
            smax = np.min(1.0 + g[neg] / (-slope[neg]))  # s <= smax
            lo = float(smax**-0.5)
    return lo, hi


# --------------------------------------------------------------- the matched lattice's design
#: Pre-stretch range [-] of :func:`matched_lattice_design` (and of the ``"matched"`` lattice):
#: the continuation from ``lambda0 = 1`` converges there with positive factors for
#: ``1/4 <= nu <= 0.499`` and cube cells (tests/test_matched_lattice.py; at ``lambda0 = 0.9``,
#: ``nu = 0.49`` an out-of-plane edge factor turns negative).
MATCHED_PRE_STRETCH_RANGE = (0.95, 1.2)
_MATCH_CONTINUATION_STEPS = 16  # steps of the continuation in lambda0 from 1
_MATCH_NEWTON_STEPS = 4  # Newton steps per continuation step
_MATCH_POLISH_STEPS = 3  # Newton steps at lambda0 after the continuation
_MATCH_TOLERANCE = 1e-10  # largest residual / mu accepted
_CELL_PAIRS = np.array(list(_CUBE_EDGES) + list(_CUBE_DIAGONALS))


def _spring_classes(d: np.ndarray) -> np.ndarray:
    """Class ``(S,)`` of springs with directions ``d`` ``(S, 3)``: 0 in-plane edge (x or y), 1
    out-of-plane edge (z), 2 in-plane face diagonal (x-y face), 3 out-of-plane face diagonal."""
    nz = np.abs(d) > 1e-9 * np.abs(d).max(axis=1, keepdims=True)
    edge, in_plane = nz.sum(axis=1) == 1, ~nz[:, 2]
    return np.where(edge, np.where(in_plane, 0, 1), np.where(in_plane, 2, 3)).astype(np.int32)


_CELL_CLASSES = _spring_classes((_CUBE_CORNERS[_CELL_PAIRS[:, 1]] - _CUBE_CORNERS[_CELL_PAIRS[:, 0]]).astype(float))


def _inverse_products(f):
    """``(F^-1_Ji F^-1_Lk, F^-1_Jk F^-1_Li)`` indexed ``[i, J, k, L]`` for ``F = diag(f)``."""
    Fi = jnp.diag(1.0 / f)
    return jnp.einsum("ji,lk->ijkl", Fi, Fi), jnp.einsum("jk,li->ijkl", Fi, Fi)


def _matched_cell_tangent(c, s, lz, shape, g, lam, mu):
    """First Piola stress ``P (3, 3)`` and tangent ``A = d2 psi / dF2 (3, 3, 3, 3)`` [Pa], in
    closed form, of the energy per unit mesh volume of one cell of edges ``shape`` ``(3,)``
    (``hx = hy``) of the ``springs_volume`` lattice at ``F = diag(1, 1, lz)``: its spring classes
    scaled by ``c`` ``(4,)`` (:func:`_spring_classes`), its rest state the cell shrunk by ``1/s``
    in x and y (rest lengths and rest volume ``V / s^2``), cubic coefficient 0; the model's own
    cell (:func:`_spring_energy`, :func:`_cell_volume_energy`, the factors ``g`` ``(24,)`` [m] of
    :func:`_cell_spring_factors`).

    A spring of mesh vector ``d``, ``x = F d``, ``l = |x|``, ``n = x / l``, rest length ``L``
    and ``k = mu g c`` gives ``P = t x d^T / V`` and ``A_iJkL = (k n_i n_k + t (delta_ik -
    n_i n_k)) d_J d_L / V`` with ``t = k (l - L) / l``; the volume term (the trilinear volume
    of the affinely deformed box is ``J V``, ``J = det F``), ``psi = (lambda - mu) (J V -
    V_r)^2 / (2 V_r V)``, gives ``P = p J F^-T`` with ``p = (lambda - mu) (J s^2 - 1)`` and
    ``A_iJkL = (lambda - mu) s^2 J^2 F^-1_Ji F^-1_Lk + p J (F^-1_Ji F^-1_Lk - F^-1_Jk F^-1_Li)``
    (tests/test_matched_lattice.py compares both with ``jax.hessian`` of the cell's energy)."""
    one = jnp.ones_like(lz)
    f = jnp.stack([one, one, lz])
    X = jnp.asarray(_CUBE_CORNERS, dtype=float) * shape
    d0 = X[_CELL_PAIRS[:, 1]] - X[_CELL_PAIRS[:, 0]]
    rest = jnp.linalg.norm(d0 * jnp.stack([1.0 / s, 1.0 / s, jnp.ones_like(s)]), axis=1)
    V = shape[0] * shape[1] * shape[2]
    k = mu * g * c[_CELL_CLASSES]
    x = d0 * f
    l = jnp.linalg.norm(x, axis=1)
    n = x / l[:, None]
    t = k * (l - rest) / l
    nn = n[:, :, None] * n[:, None, :]
    ks = k[:, None, None] * nn + t[:, None, None] * (jnp.eye(3) - nn)
    p = (lam - mu) * (lz * s * s - 1.0)
    ji_lk, jk_li = _inverse_products(f)
    P = jnp.einsum("s,si,sj->ij", t, x, d0) / V + p * lz * jnp.diag(1.0 / f)
    A = (jnp.einsum("sik,sj,sl->ijkl", ks, d0, d0) / V + (lam - mu) * (s * s * lz * lz) * ji_lk
         + p * lz * (ji_lk - jk_li))
    return P, A


def _pre_stretched_neo_hookean_tangent(lam0, lz, lam, mu):
    """``P (3, 3)`` and ``A (3, 3, 3, 3)`` [Pa], in closed form, of
    ``neo_hookean_energy_density(F G) / lambda0^2``, ``G = diag(lambda0, lambda0, 1)`` (the
    neo-Hookean pre-stretched by ``lambda0``, per unit volume of the mesh), at ``F =
    diag(1, 1, lz)``: with ``F_e = F G``, ``J = det F_e``, ``P_e = mu F_e + (lambda ln J - mu)
    F_e^-T`` and ``A_e,iJkL = mu delta_ik delta_JL + lambda F_e^-1_Ji F_e^-1_Lk - (lambda ln J -
    mu) F_e^-1_Jk F_e^-1_Li``, ``P_iJ = P_e,iJ G_J / lambda0^2`` and ``A_iJkL = A_e,iJkL G_J G_L
    / lambda0^2`` (``ln J = log1p(J - 1)`` with ``J - 1`` formed without cancellation)."""
    one = jnp.ones_like(lam0)
    fe, G = jnp.stack([lam0, lam0, lz]), jnp.stack([lam0, lam0, one])
    log_j = jnp.log1p((lam0 - 1.0) * (lam0 + 1.0) * lz + (lz - 1.0))
    q = lam * log_j - mu
    ji_lk, jk_li = _inverse_products(fe)
    eye = jnp.eye(3)
    Pe = mu * jnp.diag(fe) + q * jnp.diag(1.0 / fe)
    Ae = mu * jnp.einsum("ik,jl->ijkl", eye, eye) + lam * ji_lk - q * jk_li
    w = 1.0 / (lam0 * lam0)
    return Pe * G[None, :] * w, Ae * (G[None, :, None, None] * G[None, None, None, :]) * w


def _plane_stress_moduli(P, A):
    """``(P_zz, (P_xx, K_xxxx, K_xxyy, K_xyxy, A_xzxz))`` [Pa] from a stress ``P (3, 3)`` and
    tangent ``A (3, 3, 3, 3)`` at ``F = diag(1, 1, lz)``: the in-plane moduli ``K`` condensed over
    ``F_zz`` (plane stress)."""
    A = A.reshape(9, 9)
    ip = jnp.array([0, 1, 3, 4])
    K = A[jnp.ix_(ip, ip)] - jnp.outer(A[ip, 8], A[8, ip]) / A[8, 8]
    return P[2, 2], jnp.stack([P[0, 0], K[0, 0], K[0, 3], K[1, 1], A[2, 2]])


def _match_residual(y, args):
    """Residual / mu of the match (unknowns ``y = (c_1..c_4, s, lz, lz_nh)``)."""
    lam0, lam, mu, shape, g = args
    pzz_nh, target = _plane_stress_moduli(*_pre_stretched_neo_hookean_tangent(lam0, y[6], lam, mu))
    pzz, m = _plane_stress_moduli(*_matched_cell_tangent(y[:4], y[4], y[5], shape, g, lam, mu))
    return jnp.concatenate([jnp.stack([pzz, pzz_nh]), m - target]) / mu


def _match_newton(y, args):
    return y - jnp.linalg.solve(jax.jacfwd(_match_residual)(y, args), _match_residual(y, args))


@jax.custom_jvp
def _match_solution(lam0, lam, mu, shape, g):
    """The root ``y (7,)`` of :func:`_match_residual`: Newton continuation in ``lambda0`` from the
    default lattice at 1, then Newton steps at ``lambda0``; its derivative is the implicit
    function theorem's (``dy = -(dR/dy)^-1 dR``, the JVP rule below, transposed for reverse
    mode), not a derivative through the iterations."""
    def newton(i, y):  # continuation step i // _MATCH_NEWTON_STEPS + 1, then the polish at lambda0 (t = 1)
        t = jnp.minimum(i // _MATCH_NEWTON_STEPS + 1, _MATCH_CONTINUATION_STEPS) / _MATCH_CONTINUATION_STEPS
        return _match_newton(y, (1.0 + t * (lam0 - 1.0), lam, mu, shape, g))

    n = _MATCH_CONTINUATION_STEPS * _MATCH_NEWTON_STEPS + _MATCH_POLISH_STEPS
    return jax.lax.fori_loop(0, n, newton, jnp.ones(7, dtype=jnp.result_type(lam0, float)))  # one traced Newton step


@_match_solution.defjvp
def _match_solution_jvp(primals, tangents):
    y = _match_solution(*primals)
    _, dr = jax.jvp(lambda *a: _match_residual(y, a), primals, tangents)
    return y, -jnp.linalg.solve(jax.jacfwd(_match_residual)(y, primals), dr)


def _matched_design(lam0, nu, shape, g):
    lam0, nu = jnp.asarray(lam0, dtype=float), jnp.asarray(nu, dtype=float)
    lam, mu = 2.0 * nu / (1.0 - 2.0 * nu), jnp.ones_like(nu)  # the match depends on lambda / mu only
    args = (lam0, lam, mu, shape, g)
    y = _match_solution(*args)
    res = jnp.max(jnp.abs(jax.lax.stop_gradient(_match_residual(y, args))))
    ok = (res <= _MATCH_TOLERANCE) & jnp.all(jax.lax.stop_gradient(y[:5]) > 0)
    exact = jax.lax.stop_gradient(jnp.where(lam0 == 1.0, 1.0 - y, 0.0))  # the default lattice bit for bit at lambda0 = 1
    return y + exact, ok


_matched_designs = jax.jit(jax.vmap(_matched_design, in_axes=(0, 0, None, None)))  # compiled once per number of values


def _matched_cube_designs(lam0, nu):
    """``y (n, 7)`` of :func:`_matched_design` for a cube cell at ``lam0``, ``nu`` (both
    ``(n,)``), with the convergence check: :class:`ModelRangeError` when concrete, an
    ``equinox.error_if`` when traced."""
    shape = np.ones(3)
    y, ok = _matched_designs(lam0, nu, jnp.asarray(shape), jnp.asarray(_cell_spring_factors(shape[None])[0]))
    msg = "matched lattice: the match of the neo-Hookean's tension and moduli did not converge (or a factor turned non-positive)"
    if _is_concrete(ok):
        if not bool(np.all(np.asarray(ok))):
            raise ModelRangeError(f"{msg} at pre_stretch {np.asarray(lam0)[~np.asarray(ok)]}")
        return y
    return eqx.error_if(y, ~jnp.all(ok), msg)


def matched_lattice_design(pre_stretch, poisson_ratio):
    """Spring-class factors and lattice pre-stretch of the matched lattice
    (``springs_volume_matched_lattice``) at an equibiaxial pre-stretch.

    The lattice's cells keep the mesh cell's spring constants times a factor per spring class,
    ``c = (in-plane edges, out-of-plane edges, in-plane face diagonals, out-of-plane face
    diagonals)``, and their rest state is the cell shrunk by ``1/s`` in x and y (rest lengths and
    rest volume), ``s`` the lattice's own pre-stretch; the volume term is unchanged. ``(c, s)``
    and the thickness stretch solve, at the mesh state (x and y held, z free), exactly:
    ``P_zz = 0`` and the neo-Hookean's (``fem_neo_hookean``, pre-stretched by ``lambda0``)
    tension ``P_xx`` and incremental moduli ``A_xxxx``, ``A_xxyy``, ``A_xyxy`` (in plane, condensed
    over ``F_zz``) and ``A_xzxz`` (transverse shear). At ``lambda0 = 1`` the default lattice
    (``c = 1``, ``s = 1``) is the solution and the system is regular, so ``(c, s)`` leaves it
    smoothly (``c - 1 = O(lambda0 - 1)``, ``s - lambda0 = O((lambda0 - 1)^2)``); ``lambda0 = 1``
    gives ``c = 1``, ``s = 1`` exactly. The cell's and the neo-Hookean's stress and tangent are
    in closed form; Newton continuation from ``lambda0 = 1`` (one ``fori_loop``), then Newton
    steps at ``lambda0``; the derivative is the implicit function theorem's (a ``custom_jvp``,
    forward and reverse) in ``pre_stretch`` and ``poisson_ratio``. The match does not depend on
    Young's modulus (both energies are proportional to it).

    Scope (anything else raises, or inside ``jit`` fails with ``equinox.error_if``): cubic
    coefficient 0 (the neo-Hookean target has no cubic term; checked by the model), equibiaxial
    pre-stretch (with ``lambda_x != lambda_y`` the in-plane moduli are no longer x-y symmetric
    and outnumber the factors; checked by the model), ``pre_stretch`` in
    :data:`MATCHED_PRE_STRETCH_RANGE`, ``1/4 <= nu < 1/2`` (converged with positive factors up to
    ``nu = 0.499``; a failed solve raises), cube cells (the match is defined for any ``hx = hy``
    cell, but with ``hz`` 10-20 % off ``hx`` an edge factor turns negative by ``lambda0 = 1.05``-``1.10``).

    Args:
        pre_stretch: ``lambda0`` [-], scalar or ``(n,)``.
        poisson_ratio: ``nu`` [-], broadcast with ``pre_stretch``.

    Returns:
        ``(c, s)``: class factors [-] of shape ``(..., 4)`` and ``s`` [-] of the shape of
        ``pre_stretch``.
    """
    lam0, nu = jnp.broadcast_arrays(jnp.asarray(pre_stretch, dtype=float), jnp.asarray(poisson_ratio, dtype=float))
    lam0 = _check_matched_range(lam0, nu)
    y = _matched_cube_designs(lam0.reshape(-1), nu.reshape(-1))
    return y[:, :4].reshape(lam0.shape + (4,)), y[:, 4].reshape(lam0.shape)


def _check_matched_range(lam0, nu):
    lo, hi = MATCHED_PRE_STRETCH_RANGE
    msg = (f"pre_stretch outside [{lo:g}, {hi:g}] or poisson_ratio outside [0.25, 0.5), the range of the matched lattice "
           "(springs_volume_matched_lattice); use springs_volume_mesh_lattice, springs_volume or the fem models")
    bad = lambda l, n: (l < lo) | (l > hi) | (n < 0.25) | (n >= 0.5)  # noqa: E731
    if _is_concrete((lam0, nu)):
        if np.any(bad(np.asarray(lam0), np.asarray(nu))):
            raise ModelRangeError(f"{msg}: pre_stretch {np.asarray(lam0)}, poisson_ratio {np.asarray(nu)}")
        return lam0
    return eqx.error_if(lam0, jnp.any(bad(lam0, nu)), msg)


class SpringVolumeModel(ElasticModel):
    """Cubic springs on the cube lattice plus a per-cell volume term (our real-time model).

    Per cell of edges ``(hx, hy, hz)`` the springs get ``k = mu g`` with the geometric factors
    of :func:`_cell_spring_factors` (``mu h / 4`` and ``mu h / 2`` for cubes), cubic
    coefficients ``a = b k / L0^2``, and the cell carries the volume energy
    ``(lambda - mu) (V - V0)^2 / (2 V0)`` with ``V`` the exact trilinear-hexahedron volume.
    Per cell this is exactly isotropic linear elasticity at small strain, so a homogeneous
    strain is reproduced exactly, free boundaries included (a per-tet volume term would put
    the bulk traction on a different tributary area than the springs at free edges).

    Pre-stretch ``lambda0`` of a region: its cells' stress-free state is the cell shrunk by
    ``1/lambda0`` in x and y. The springs get that state's rest lengths
    ``L0 sqrt(1 + c (lambda0^-2 - 1))`` (``c`` the in-plane fraction of ``L0^2``) and geometric
    factors (:func:`_cell_spring_factor_slopes`), the cells the rest volume ``V / lambda0^2``.
    An anisotropic pre-stretch ``(lambda_x, lambda_y)`` (``Material.pre_stretch_y``) shrinks the
    cell by ``diag(1/lambda_x, 1/lambda_y, 1)``: rest lengths
    ``L0 sqrt(1 + c (sx - 1) + c_y (sy - sx))`` (``s = lambda^-2``, ``c_y`` the y fraction),
    factors of :func:`_cell_spring_factor_ratio_slopes`, rest volume ``V / (lambda_x lambda_y)``;
    with ``lambda_y = lambda_x`` all of it is bit for bit the equibiaxial model.

    ``pre_stretch_lattice="mesh"`` (model name ``"springs_volume_mesh_lattice"``) keeps the spring
    factors of the mesh cell and shrinks only the rest lengths and the rest volume. Its
    linear response about the stress-free state is isotropic only to O(lambda0 - 1), but at
    finite pre-stretch its response is closer to the neo-Hookean continuum's: the stress-free
    lattice of cubes has in-plane edge factors ``2 - lambda0^-2`` and out-of-plane edge factors
    ``3 lambda0^-2 - 2`` times a cube's (1.24 and 0.27 at 1.15), and
    carries 3 / 6 / 8 % less surface tension than ``fem_neo_hookean`` at lambda0 = 1.05 / 1.10 /
    1.15 (nu = 0.45) and opens an incision 4 / 11 / 16 % less at any cell size; the mesh lattice
    carries 3 / 6 / 9 % more tension and opens it 5 / 10 / 14 % wider (docs/experiments.md, "Cut
    openings at resolution"). Equal to the default at ``lambda0 = 1`` bit for bit; no
    pre-stretch range limit.

    ``pre_stretch_lattice="matched"`` (model name ``"springs_volume_matched_lattice"``) scales the
    mesh cell's spring constants of a pre-stretched region per spring class (in-plane edges,
    out-of-plane edges, in-plane and out-of-plane face diagonals) and shrinks its rest lengths
    and rest volumes by a lattice pre-stretch ``s`` of its own instead of ``lambda0``, with
    ``(c, s)`` from :func:`matched_lattice_design`: the cell then carries the neo-Hookean's
    tension and incremental in-plane and transverse-shear moduli at ``lambda0`` exactly. Equal to
    the default at ``lambda0 = 1`` bit for bit; scope: :data:`MATCHED_PRE_STRETCH_RANGE`,
    equibiaxial pre-stretch, cubic coefficient 0 and cube cells in pre-stretched regions
    (anything else raises :class:`ModelRangeError`).
    A spring shared by cells of different regions is one element per region (their rest
    lengths differ when the regions' pre-stretches do).

    Attributes (besides :class:`ElasticModel`'s):
        springs: ``(S, 2)`` spring elements (one per lattice spring and region holding it);
            rest_lengths ``(S,)`` [m] in the mesh; spring_regions ``(S,)``.
        spring_factors: ``(S,)`` sum over the cells of the element's region holding the spring
            of ``g`` [m]; spring_factor_slopes ``(S,)`` [m] the same sum of ``dg/ds``.
        spring_in_plane: ``(S,)`` ``(dx^2 + dy^2) / L0^2`` of each spring in the mesh [-];
            spring_in_plane_y ``(S,)`` its part ``dy^2 / L0^2``.
        spring_factor_ratio_slopes: ``(S, 2)`` [m] the sums of the coefficients of
            :func:`_cell_spring_factor_ratio_slopes` (anisotropic pre-stretch).
        cell_factor_terms: ``(C, 24, 4)`` [m] per cell and spring ``(g, dg/ds, c_x, c_y)``, for
            the range check of an anisotropic pre-stretch.
        cells: ``(C, 8)`` cell nodes; cell_regions ``(C,)``; cell_volumes ``(C,)`` [m^3];
            cell_jacobians ``(C, 8)`` the cells' ``det(dx/dxi)`` at their Gauss points in the
            mesh [m^3] (the reference of :meth:`min_volume_ratio`).
        pre_stretch_range: ``(n_regions, 2)`` range of ``lambda0`` per region for which no
            spring factor of its cells turns negative.
        pre_stretch_lattice: one of :data:`PRE_STRETCH_LATTICES` (see above).
        spring_classes: ``(S,)`` class of each spring (:func:`_spring_classes`: 0 in-plane edge,
            1 out-of-plane edge, 2 in-plane face diagonal, 3 out-of-plane face diagonal).
        region_cubes: per region, whether its cells are cubes of one size (the matched
            lattice needs cubes where it is pre-stretched).
    """

    springs: np.ndarray
    rest_lengths: np.ndarray
    energy_linear_in_youngs_modulus: ClassVar[bool] = True  # k = mu g, a = b k / L0^2, lambda - mu: E times functions of nu
    spring_regions: np.ndarray
    spring_factors: np.ndarray
    spring_factor_slopes: np.ndarray
    spring_in_plane: np.ndarray
    spring_in_plane_y: np.ndarray
    spring_factor_ratio_slopes: np.ndarray
    cell_factor_terms: np.ndarray
    cells: np.ndarray
    cell_regions: np.ndarray
    cell_volumes: np.ndarray
    cell_jacobians: np.ndarray
    pre_stretch_range: np.ndarray
    spring_classes: np.ndarray
    region_cubes: np.ndarray
    pre_stretch_lattice: str = eqx.field(static=True)

    @property
    def model_name(self) -> str:
        """``"springs_volume"``, or the variant's name (:data:`LATTICE_VARIANTS`): a fit's record
        names the variant it ran."""
        return _VARIANT_OF_LATTICE.get(self.pre_stretch_lattice, self.kind)

    def __init__(self, mesh: TetMesh, *, pre_stretch_lattice: str = "stress_free"):
        if pre_stretch_lattice not in PRE_STRETCH_LATTICES:
            raise ModelError(f"pre_stretch_lattice must be one of {PRE_STRETCH_LATTICES}, got {pre_stretch_lattice!r}")
        self.pre_stretch_lattice = pre_stretch_lattice
        for k, v in _base_fields(mesh, "springs_volume", 0.25).items():
            setattr(self, k, v)
        lat = mesh.lattice
        if lat is None:
            raise ModelError(
                "the springs_volume model needs a structured specimen with a cube lattice (difftissue.mesh.block or "
                "layered_skin); for imported meshes use 'stable_neo_hookean', 'fem_linear' or 'fem_neo_hookean'"
            )
        g = _cell_spring_factors(lat.cell_size)
        if np.any(g < 0):
            c = int(np.argmin(g.min(axis=1)))
            raise ModelError(
                f"cell {c} has edge lengths {lat.cell_size[c].tolist()} m: too elongated for an isotropic spring lattice "
                "(an edge spring would need negative stiffness; each edge must satisfy h_a^2 (1/h_b^2 + 1/h_c^2) <= 3, "
                "e.g. aspect ratios up to sqrt(2)). Use more cells through thin layers (cell_size=...) or the "
                "stable_neo_hookean / fem models"
            )
        slope = _cell_spring_factor_slopes(lat.cell_size)
        ratio = _cell_spring_factor_ratio_slopes(lat.cell_size)
        if pre_stretch_lattice in ("mesh", "matched"):  # the mesh cell's factors at every pre-stretch
            slope, ratio = np.zeros_like(slope), np.zeros_like(ratio)
        R = len(mesh.region_names)
        rows = (lat.cube_springs.reshape(-1), np.repeat(lat.cube_region_ids, 24))
        factors = np.zeros((lat.n_springs, R))
        np.add.at(factors, rows, g.reshape(-1))
        slopes = np.zeros((lat.n_springs, R))
        np.add.at(slopes, rows, slope.reshape(-1))
        ratio_slopes = np.zeros((lat.n_springs, R, 2))
        np.add.at(ratio_slopes, rows, ratio.reshape(-1, 2))
        held = np.zeros((lat.n_springs, R), dtype=bool)
        held[rows] = True
        spring_ids, regions = np.nonzero(held)  # sorted by spring: one element per region holding it
        ranges = np.empty((R, 2))
        for r in range(R):
            in_r = lat.cube_region_ids == r
            ranges[r] = _admissible_pre_stretch(g[in_r].reshape(-1), slope[in_r].reshape(-1)) if np.any(in_r) else (0.0, math.inf)
        if pre_stretch_lattice == "matched":
            ranges[:] = MATCHED_PRE_STRETCH_RANGE
        cubes = []
        for r in range(R):
            h = lat.cell_size[lat.cube_region_ids == r]
            cubes.append(bool(len(h) and np.all(np.abs(h - h[0, 0]) <= 1e-9 * h[0, 0])))  # cubes of one size
        p = np.asarray(mesh.points)
        self.springs = lat.springs[spring_ids]
        d = p[self.springs[:, 1]] - p[self.springs[:, 0]]
        self.rest_lengths = np.linalg.norm(d, axis=1)
        self.spring_regions = regions.astype(np.int32)
        self.spring_factors = factors[spring_ids, regions]
        self.spring_factor_slopes = slopes[spring_ids, regions]
        self.spring_in_plane = (d[:, 0] ** 2 + d[:, 1] ** 2) / self.rest_lengths**2
        self.spring_in_plane_y = d[:, 1] ** 2 / self.rest_lengths**2
        self.spring_classes = _spring_classes(d)
        self.region_cubes = np.array(cubes, dtype=bool)  # an array, not a static field: meshes of one structure share programs
        self.spring_factor_ratio_slopes = ratio_slopes[spring_ids, regions]
        self.cell_factor_terms = np.concatenate([g[..., None], slope[..., None], ratio], axis=-1)
        self.cells = lat.cubes
        self.cell_regions = lat.cube_region_ids
        self.cell_jacobians = np.asarray(_jit_hexahedron_jacobians(np.asarray(p[lat.cubes], dtype=float)))
        self.cell_volumes = np.asarray(_jit_hexahedron_volumes(np.asarray(p[lat.cubes], dtype=float)))
        self.pre_stretch_range = ranges

    def checked(self, material: Material) -> "CheckedMaterial":
        """As :meth:`ElasticModel.checked`, with the lattice's pre-stretch range checked too."""
        if isinstance(material, CheckedMaterial):
            return material
        p = self.region_values(material)
        if self.pre_stretch_lattice == "matched":
            p["pre_stretch"] = self._check_matched(p)
        elif "pre_stretch_y" in p:
            p["pre_stretch"], p["pre_stretch_y"] = self._check_pre_stretch_xy(p["pre_stretch"], p["pre_stretch_y"])
        else:
            p["pre_stretch"] = self._check_pre_stretch(p["pre_stretch"])
        return CheckedMaterial(**p)

    def _anisotropic_cell_factors(self, lx, ly):
        """``(C, 24)`` spring factors [m] of the cells shrunk by ``diag(1/lambda_x, 1/lambda_y, 1)``."""
        r = self.cell_regions
        q, rho, irho = 1.0 / (lx * ly) - 1.0, lx / ly - 1.0, ly / lx - 1.0
        t = jnp.asarray(self.cell_factor_terms)
        return t[..., 0] + t[..., 1] * q[r, None] + t[..., 2] * rho[r, None] + t[..., 3] * irho[r, None]

    def _check_pre_stretch_xy(self, lx, ly):
        msg = (
            "(pre_stretch, pre_stretch_y) outside the range the springs_volume lattice represents for these cells (a spring "
            "factor of the cell shrunk by diag(1/pre_stretch, 1/pre_stretch_y, 1) would turn negative); use cells of "
            "other proportions or the stable_neo_hookean / fem models"
        )
        if _is_concrete((lx, ly)):
            g = np.asarray(self._anisotropic_cell_factors(jnp.asarray(lx), jnp.asarray(ly)))
            bad = np.flatnonzero(np.min(g, axis=1) < 0)
            if bad.size:
                r = int(self.cell_regions[bad[0]])
                raise ModelRangeError(f"{msg}: region {self.region_names[r]!r} has (pre_stretch, pre_stretch_y) = "
                                      f"({np.asarray(lx)[r]:g}, {np.asarray(ly)[r]:g}), cell {int(bad[0])}")
            return lx, ly
        ok = jnp.all(self._anisotropic_cell_factors(lx, ly) >= 0)
        return eqx.error_if(lx, ~ok, msg), ly

    def _check_pre_stretch(self, lam0):
        lo, hi = self.pre_stretch_range[:, 0], self.pre_stretch_range[:, 1]
        msg = (
            "pre_stretch outside the range the springs_volume lattice represents for these cells (a spring factor of the "
            "shrunk cell would turn negative); use flatter cells or the stable_neo_hookean / fem models"
        )
        if _is_concrete(lam0):
            v = np.asarray(lam0)
            bad = (v < lo) | (v > hi)
            if np.any(bad):
                r = int(np.argmax(bad))
                raise ModelRangeError(f"{msg}: region {self.region_names[r]!r} has pre_stretch {v[r]:g}, allowed [{lo[r]:.4g}, {hi[r]:.4g}]")
            return lam0
        return eqx.error_if(lam0, jnp.any((lam0 < lo) | (lam0 > hi)), msg)

    def _check_matched(self, p):
        """The matched lattice's scope (see the class docstring) on region values ``p``; returns
        ``pre_stretch`` (with an ``equinox.error_if`` attached when traced)."""
        lx = p["pre_stretch"]
        ly = p.get("pre_stretch_y", lx)
        b, nu = p["cubic_coefficient"], p["poisson_ratio"]
        shaped = self.region_cubes
        what = "the matched lattice (springs_volume_matched_lattice) is defined for "
        msgs = (what + "an equibiaxial pre-stretch only (pre_stretch_y = pre_stretch); use springs_volume_mesh_lattice or springs_volume",
                what + "cubic_coefficient 0 only in pre-stretched regions (its match is to the neo-Hookean); use springs_volume_mesh_lattice",
                what + "cube cells only, where pre-stretched (with hz off hx an edge factor soon turns negative)")
        if _is_concrete((lx, ly, b, shaped)):
            lxn, lyn, bn, shaped = (np.asarray(v) for v in (lx, ly, b, shaped))
            stretched = (lxn != 1.0) | (lyn != 1.0)
            for bad, m in zip((lxn != lyn, stretched & (bn != 0.0), stretched & ~shaped), msgs):
                if np.any(bad):
                    r = int(np.argmax(bad))
                    raise ModelRangeError(f"{m}: region {self.region_names[r]!r} has pre_stretch {lxn[r]:g}, "
                                          f"pre_stretch_y {lyn[r]:g}, cubic_coefficient {bn[r]:g}")
        else:
            stretched = (lx != 1.0) | (ly != 1.0)
            for bad, m in zip((lx != ly, stretched & (b != 0.0), stretched & ~jnp.asarray(shaped, dtype=bool)), msgs):
                lx = eqx.error_if(lx, jnp.any(bad), m)
        return _check_matched_range(lx, nu)

    def _matched(self, material: Material):
        """``(c (n_regions, 4), s (n_regions,))`` of the matched lattice per region
        (:func:`matched_lattice_design`)."""
        p = self.region_values(material)
        lam0 = p["pre_stretch"] if isinstance(material, CheckedMaterial) else self._check_matched(p)
        # A pre-stretched region has cube cells (_check_matched); an unstretched one gets
        # c = 1, s = 1 exactly whatever its cells: the cube's design serves every region.
        y = _matched_cube_designs(lam0, p["poisson_ratio"])
        return y[:, :4], y[:, 4]

    def spring_parameters(self, material: Material, _matched=None):
        """Per spring element ``(L0 [m], k [N/m], a [N/m^3])`` of the stress-free state."""
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.spring_regions
        if self.pre_stretch_lattice == "matched":
            c, s = self._matched(material) if _matched is None else _matched
            g = self.spring_factors * c[r, self.spring_classes]
            rest = self.rest_lengths * jnp.sqrt(1.0 + self.spring_in_plane * (1.0 / (s * s) - 1.0)[r])
        elif "pre_stretch_y" in p:
            lx, ly = (p["pre_stretch"], p["pre_stretch_y"]) if isinstance(material, CheckedMaterial) else self._check_pre_stretch_xy(p["pre_stretch"], p["pre_stretch_y"])
            dsx = 1.0 / (lx * lx) - 1.0
            dsy = 1.0 / (ly * ly) - 1.0
            dq = 1.0 / (lx * ly) - 1.0  # = dsx bit for bit when lx = ly, where the ratio terms are exactly 0
            c = self.spring_factor_ratio_slopes
            g = self.spring_factors + self.spring_factor_slopes * dq[r] + c[:, 0] * (lx / ly - 1.0)[r] + c[:, 1] * (ly / lx - 1.0)[r]
            rest = self.rest_lengths * jnp.sqrt(1.0 + self.spring_in_plane * dsx[r] + self.spring_in_plane_y * (dsy - dsx)[r])
        else:
            lam0 = p["pre_stretch"] if isinstance(material, CheckedMaterial) else self._check_pre_stretch(p["pre_stretch"])
            ds = 1.0 / (lam0 * lam0) - 1.0  # s - 1, exactly 0 at lambda0 = 1
            g = self.spring_factors + self.spring_factor_slopes * ds[r]
            rest = self.rest_lengths * jnp.sqrt(1.0 + self.spring_in_plane * ds[r])
        k = g * mu[r]
        a = g * (p["cubic_coefficient"] * mu)[r] / rest**2
        return rest, k, a

    def spring_constants(self, material: Material):
        """Per spring element ``(k [N/m], a [N/m^3])`` (see :meth:`spring_parameters`)."""
        _, k, a = self.spring_parameters(material)
        return k, a

    def cell_rest_volumes(self, material: Material, _matched=None):
        """Stress-free cell volumes ``V / (lambda_x lambda_y)`` [m^3], shape ``(C,)`` (the matched
        lattice: ``V / s^2``, ``s`` its lattice pre-stretch)."""
        if self.pre_stretch_lattice == "matched":
            s = (self._matched(material) if _matched is None else _matched)[1][self.cell_regions]
            return jnp.asarray(self.cell_volumes) / (s * s)
        p = self.region_values(material)
        lx = p["pre_stretch"][self.cell_regions]
        ly = p["pre_stretch_y"][self.cell_regions] if "pre_stretch_y" in p else lx
        return jnp.asarray(self.cell_volumes) / (lx * ly)

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        matched = self._matched(material) if self.pre_stretch_lattice == "matched" else None
        rest, k, a = self.spring_parameters(material, matched)
        bulk = (lam - mu)[self.cell_regions]
        return (
            ElementTerm("springs", self.springs, _spring_energy, (rest, k, a), hessian=_spring_hessian),
            ElementTerm("cell_volume", self.cells, _cell_volume_energy, (self.cell_rest_volumes(material, matched), bulk),
                        hessian=_cell_volume_hessian),
        )

    def min_volume_ratio(self, x):
        now = jax.vmap(hexahedron_jacobians)(x[self.cells])
        return jnp.minimum(jnp.min(now / self.cell_jacobians), super().min_volume_ratio(x))


def make_model(mesh: TetMesh, kind: str = "springs_volume") -> ElasticModel:
    """Build a model of ``mesh``: one of :data:`MODELS`, :data:`NODAL_FEM_MODELS` or
    :data:`LATTICE_VARIANTS` (``"fem_linear_nodal"`` is ``FEMModel(mesh, "fem_linear",
    volumetric="nodal")``, its ``kind`` is ``"fem_linear"``: the same continuum law;
    ``"springs_volume_mesh_lattice"`` is ``SpringVolumeModel(mesh, pre_stretch_lattice="mesh")``,
    ``"springs_volume_matched_lattice"`` ``SpringVolumeModel(mesh, pre_stretch_lattice="matched")``)."""
    for lattice, name in _VARIANT_OF_LATTICE.items():
        if kind == name:
            return SpringVolumeModel(mesh, pre_stretch_lattice=lattice)
    if kind in NODAL_FEM_MODELS:
        return FEMModel(mesh, kind.removesuffix("_nodal"), volumetric="nodal")
    if kind == "springs_volume":
        return SpringVolumeModel(mesh)
    if kind == "stable_neo_hookean":
        return StableNeoHookeanModel(mesh)
    if kind in ("fem_linear", "fem_neo_hookean"):
        return FEMModel(mesh, kind)
    raise ModelError(f"unknown model {kind!r}; choose one of {MODELS + NODAL_FEM_MODELS + LATTICE_VARIANTS}")
