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
  linear tetrahedra.

``material`` is a :class:`~difftissue.materials.Material` whose fields are scalars (one
material) or arrays of shape ``(n_regions,)`` (one value per region, see
:func:`stack_materials`). Element terms are pure functions of their nodes' positions, so
the solvers get energies, forces (``jax.grad``) and element Hessians from one description.
See ``docs/theory.md`` for the formulas.
"""

from __future__ import annotations

import abc
import math
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .energies.fem import linear_elastic_energy_density, neo_hookean_energy_density
from .energies.neo_hookean import deformation_gradient, det3, rest_shape, stable_neo_hookean_energy_density
from .energies.springs import cubic_spring_energy
from .errors import InvertedElementError, MaterialError, ModelError, ModelRangeError
from .materials import Material, _is_concrete, lame_parameters
from .mesh import _CUBE_DIAGONALS, _CUBE_EDGES, _CUBE_CORNERS, TetMesh

__all__ = [
    "MODELS",
    "ElementTerm",
    "ElasticModel",
    "SpringVolumeModel",
    "StableNeoHookeanModel",
    "FEMModel",
    "make_model",
    "stack_materials",
    "hexahedron_volume",
    "hexahedron_jacobians",
]

#: Model names accepted by :func:`make_model`.
MODELS = ("springs_volume", "stable_neo_hookean", "fem_linear", "fem_neo_hookean")


class ElementTerm(eqx.Module):
    """One family of elements: ``sum_e energy(x[nodes[e]], *params[e])`` [J].

    Attributes:
        name: what the term is (``"springs"``, ``"cell_volume"``, ``"tets"``).
        nodes: ``(E, k)`` node indices of each element.
        energy: ``energy(x_e (k, 3), *params_e) -> J`` for one element (vmapped by callers).
        params: per-element parameters, each with leading dimension ``E``.
    """

    name: str = eqx.field(static=True)
    nodes: np.ndarray
    energy: Callable = eqx.field(static=True)
    params: tuple

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
    return jax.tree_util.tree_map(lambda *v: jnp.stack([jnp.asarray(a, dtype=float) for a in v]), *materials)


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


def _spring_energy(x, rest_length, stiffness, cubic):
    return cubic_spring_energy(x[0], x[1], rest_length, stiffness, cubic)


def _cell_volume_energy(x, rest_volume, bulk_stiffness):
    dv = hexahedron_volume(x) - rest_volume
    return 0.5 * bulk_stiffness * dv * dv / rest_volume


def _fem_linear_energy(x, Dm_inv, V0, lam, mu):
    return V0 * linear_elastic_energy_density(deformation_gradient(x, Dm_inv), lam, mu)


def _fem_neo_hookean_energy(x, Dm_inv, V0, lam, mu):
    return V0 * neo_hookean_energy_density(deformation_gradient(x, Dm_inv), lam, mu)


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

    @property
    def n_nodes(self) -> int:
        return int(self.rest_points.shape[0])

    @property
    def n_regions(self) -> int:
        return len(self.region_names)

    def region_values(self, material: Material) -> dict[str, jax.Array]:
        """Material fields as ``(n_regions,)`` arrays, checked for the model's valid range.

        Concrete values raise :class:`MaterialError` / :class:`ModelRangeError`; traced
        values (inside jit) are checked with ``equinox.error_if``.
        """
        R = self.n_regions
        out = {}
        for name in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch"):
            v = jnp.asarray(getattr(material, name), dtype=float)
            if v.ndim == 0:
                v = jnp.broadcast_to(v, (R,))
            if v.shape != (R,):
                raise MaterialError(f"{name} has shape {v.shape}; give a scalar or one value per region ({R}: {list(self.region_names)})")
            out[name] = v
        E, nu = out["youngs_modulus"], out["poisson_ratio"]
        bad_nu = f"poisson_ratio outside [{self.nu_min:g}, 0.5) for the {self.kind} model"
        if self.kind == "springs_volume":
            bad_nu += " (its volume term would need negative stiffness below 1/4; use stable_neo_hookean or fem_* there)"
        if _is_concrete(out):
            for name, arr in out.items():
                if not np.all(np.isfinite(np.asarray(arr))):
                    raise MaterialError(f"{name} contains NaN or infinite values: {np.asarray(arr)}")
            if not np.all(np.asarray(E) > 0):
                raise MaterialError(f"youngs_modulus must be > 0 Pa, got {np.asarray(E)}")
            nu_np = np.asarray(nu)
            if not np.all((nu_np >= self.nu_min) & (nu_np < 0.5)):
                raise ModelRangeError(f"{bad_nu}: {nu_np}")
        else:
            finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in out.values()]))
            E = eqx.error_if(E, ~finite, "material parameters contain NaN or infinite values")
            E = eqx.error_if(E, jnp.any(E <= 0), "youngs_modulus must be > 0 Pa")
            nu = eqx.error_if(nu, jnp.any((nu < self.nu_min) | (nu >= 0.5)), bad_nu)
            out["youngs_modulus"], out["poisson_ratio"] = E, nu
        return out

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
        """Nodal masses [kg]: each tet's mass ``rho V0`` shared equally by its four nodes."""
        rho = self.region_values(material)["density"][self.tet_regions]
        m = jnp.zeros(self.n_nodes).at[self.tets.reshape(-1)].add(jnp.repeat(rho * self.tet_volumes / 4.0, 4))
        return m


def _tet_geometry(mesh: TetMesh):
    Dm_inv, V0 = rest_shape(jnp.asarray(mesh.points)[mesh.tets])
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
    compressible neo-Hookean ``Psi = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2`` density."""

    def __init__(self, mesh: TetMesh, kind: str = "fem_linear"):
        if kind not in ("fem_linear", "fem_neo_hookean"):
            raise ModelError(f"FEMModel kind must be 'fem_linear' or 'fem_neo_hookean', got {kind!r}")
        for k, v in _base_fields(mesh, kind, -1.0).items():
            setattr(self, k, v)

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.tet_regions
        fn = _fem_linear_energy if self.kind == "fem_linear" else _fem_neo_hookean_energy
        return (ElementTerm("tets", self.tets, fn, (self.tet_Dm_inv, self.tet_volumes, lam[r], mu[r])),)


class StableNeoHookeanModel(ElasticModel):
    """Stable neo-Hookean tets (Macklin & Müller 2021) with ``lambda' = lambda + mu`` so the
    small-strain response is the material's (E, nu)."""

    def __init__(self, mesh: TetMesh):
        for k, v in _base_fields(mesh, "stable_neo_hookean", -1.0).items():
            setattr(self, k, v)

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.tet_regions
        return (ElementTerm("tets", self.tets, _stable_neo_hookean_energy, (self.tet_Dm_inv, self.tet_volumes, mu[r], (lam + mu)[r])),)


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


class SpringVolumeModel(ElasticModel):
    """Cubic springs on the cube lattice plus a per-cell volume term (our real-time model).

    Per cell of edges ``(hx, hy, hz)`` the springs get ``k = mu g`` with the geometric factors
    of :func:`_cell_spring_factors` (``mu h / 4`` and ``mu h / 2`` for cubes), cubic
    coefficients ``a = b k / L0^2``, and the cell carries the volume energy
    ``(lambda - mu) (V - V0)^2 / (2 V0)`` with ``V`` the exact trilinear-hexahedron volume.
    Per cell this is exactly isotropic linear elasticity at small strain, so a homogeneous
    strain is reproduced exactly, free boundaries included (a per-tet volume term would put
    the bulk traction on a different tributary area than the springs at free edges).

    Attributes (besides :class:`ElasticModel`'s):
        springs: ``(S, 2)`` unique springs; rest_lengths ``(S,)`` [m].
        spring_factors: ``(S, R)`` sum over the cells of region r holding spring s of g [m].
        cells: ``(C, 8)`` cell nodes; cell_regions ``(C,)``; cell_volumes ``(C,)`` [m^3].
    """

    springs: np.ndarray
    rest_lengths: np.ndarray
    spring_factors: np.ndarray
    cells: np.ndarray
    cell_regions: np.ndarray
    cell_volumes: np.ndarray

    def __init__(self, mesh: TetMesh):
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
        R = len(mesh.region_names)
        factors = np.zeros((lat.n_springs, R))
        np.add.at(factors, (lat.cube_springs.reshape(-1), np.repeat(lat.cube_region_ids, 24)), g.reshape(-1))
        p = np.asarray(mesh.points)
        self.springs = lat.springs
        self.rest_lengths = np.linalg.norm(p[lat.springs[:, 1]] - p[lat.springs[:, 0]], axis=1)
        self.spring_factors = factors
        self.cells = lat.cubes
        self.cell_regions = lat.cube_region_ids
        self.cell_volumes = np.asarray(jax.vmap(hexahedron_volume)(jnp.asarray(p[lat.cubes])))

    def spring_constants(self, material: Material):
        """Per-spring ``(k [N/m], a [N/m^3])`` assembled over the cells holding each spring."""
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        k = self.spring_factors @ mu
        a = (self.spring_factors @ (p["cubic_coefficient"] * mu)) / self.rest_lengths**2
        return k, a

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        k, a = self.spring_constants(material)
        bulk = (lam - mu)[self.cell_regions]
        return (
            ElementTerm("springs", self.springs, _spring_energy, (self.rest_lengths, k, a)),
            ElementTerm("cell_volume", self.cells, _cell_volume_energy, (self.cell_volumes, bulk)),
        )

    def min_volume_ratio(self, x):
        rest = jax.vmap(hexahedron_jacobians)(jnp.asarray(self.rest_points)[self.cells])
        now = jax.vmap(hexahedron_jacobians)(x[self.cells])
        return jnp.minimum(jnp.min(now / rest), super().min_volume_ratio(x))


def make_model(mesh: TetMesh, kind: str = "springs_volume") -> ElasticModel:
    """Build a model of ``mesh``: one of :data:`MODELS`."""
    if kind == "springs_volume":
        return SpringVolumeModel(mesh)
    if kind == "stable_neo_hookean":
        return StableNeoHookeanModel(mesh)
    if kind in ("fem_linear", "fem_neo_hookean"):
        return FEMModel(mesh, kind)
    raise ModelError(f"unknown model {kind!r}; choose one of {MODELS}")
