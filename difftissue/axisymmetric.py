"""Axisymmetric continuum model: a body of revolution in its meridian (r, z) plane.

Sphere and cone indentation on the axis of a cylinder is axisymmetric (torsionless): the
displacement is ``u_r(r, z), u_z(r, z)``, and the deformation gradient in ``(r, theta, z)``
is::

    F = [[d r/d R,  0,      d r/d Z],
         [0,        r / R,  0      ],
         [d z/d R,  0,      d z/d Z]]

with the hoop stretch ``r / R``. A 2-D mesh of the meridian half-plane (``r >= 0``) then
carries the whole 3-D problem, so the contact zone can be resolved with tens of cells per
contact radius at the cost of a few thousand nodes (a 3-D block needs about 400 000 nodes for
1 % force error, docs/dev/axisymmetric-indentation.md).

Discretisation: linear triangles in ``(r, z)``, one quadrature point at the centroid (rest
radius ``R_c``): the in-plane gradient is exact for a linear triangle, the hoop stretch is
``r_c / R_c`` of the current centroid radius, and the element energy is
``2 pi R_c A Psi(F)`` (``2 pi R_c A`` is exactly the volume of the triangle's ring). Any 3-D
density ``Psi(F)`` applies: the linear (``fem_linear``) and the compressible neo-Hookean
(``fem_neo_hookean``) densities of :mod:`difftissue.energies.fem` and the stable neo-Hookean
density (``stable_neo_hookean``, :func:`~difftissue.energies.neo_hookean.stable_neo_hookean_energy_density`
with ``lam' = lambda + mu``, as the 3-D :class:`~difftissue.models.StableNeoHookeanModel`), all
finite-strain exact in this kinematics. The axisymmetric stable neo-Hookean is the continuum
law of the XPBD constraints on a converged mesh: it tells the stable neo-Hookean material's E
and nu, not what a coarse 3-D tet mesh of it does.

The nodes are stored as 3-D points ``(r, 0, z)`` so that the static solver, the sparse Hessian
path, the contact penalty and the indenters of :mod:`difftissue.contact` work unchanged: the
``y`` component is a dummy, fixed at zero on every node (:func:`axisymmetric_boundary_conditions`);
the element energies do not depend on it.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .boundary import BoundaryConditions
from .contact import ConeIndenter, ContactModel, SphereIndenter, adopt_base_fields
from .energies.fem import linear_elastic_energy_density, neo_hookean_energy_density
from .energies.neo_hookean import stable_neo_hookean_energy_density
from .errors import BoundaryConditionError, InvertedElementError, ModelError
from .materials import Material, _is_concrete, lame_parameters
from .mesh import graded_axis, graded_cells
from .models import CheckedMaterial, ElasticModel, ElementTerm

__all__ = [
    "AXISYMMETRIC_MODELS",
    "AxisymmetricMesh",
    "axisymmetric_cylinder",
    "AxisymmetricModel",
    "AxisymmetricContactModel",
    "axisymmetric_boundary_conditions",
    "top_edge_rings",
]

#: Constitutive models the axisymmetric model supports (any 3-D density of ``F``; the
#: springs_volume lattices are 3-D element forms with no axisymmetric counterpart).
AXISYMMETRIC_MODELS = ("fem_linear", "fem_neo_hookean", "stable_neo_hookean")


class AxisymmetricMesh(eqx.Module):
    """Triangles of the meridian half-plane ``r >= 0`` of a body of revolution.

    Attributes:
        points: ``(N, 2)`` node coordinates ``(r, z)`` [m], ``r >= 0``.
        triangles: ``(M, 3)`` node indices, counter-clockwise in ``(r, z)`` (positive area).
    """

    points: np.ndarray
    triangles: np.ndarray

    def __init__(self, points, triangles):
        p = np.asarray(points, dtype=float)
        t = np.asarray(triangles, dtype=np.int32)
        if p.ndim != 2 or p.shape[1] != 2 or not np.all(np.isfinite(p)):
            raise ModelError(f"axisymmetric points must be a finite (N, 2) array of (r, z) [m], got shape {p.shape}")
        if np.any(p[:, 0] < 0):
            raise ModelError("axisymmetric points need r >= 0 (the meridian half-plane)")
        if t.ndim != 2 or t.shape[1] != 3 or t.size == 0 or t.min() < 0 or t.max() >= len(p):
            raise ModelError(f"triangles must be an (M, 3) array of node indices in [0, {len(p)})")
        area = _areas(p, t)
        if np.any(~(area > 0)):
            bad = np.flatnonzero(~(area > 0))
            raise InvertedElementError(f"{bad.size} triangle(s) have non-positive area (clockwise or degenerate): {bad[:8].tolist()}", bad)
        self.points, self.triangles = p, t

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    def points3(self) -> np.ndarray:
        """``(N, 3)`` points ``(r, 0, z)`` [m]: the meridian plane as the x-z plane."""
        return np.column_stack([self.points[:, 0], np.zeros(len(self.points)), self.points[:, 1]])


def _areas(p, t):
    e1, e2 = p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def axisymmetric_cylinder(radius: float, height: float, *, first: float | None = None, core: float | None = None,
                          growth: float = 1.15, cells: tuple[int, int] | None = None) -> AxisymmetricMesh:
    """Meridian mesh of a cylinder ``0 <= r <= radius``, ``0 <= z <= height`` [m], top at ``z = height``.

    Cells of size ``first`` [m] are uniform within ``core`` [m] of the axis and of the top
    surface and grow geometrically (ratio at most ``growth``) beyond, in r and in depth; each
    quadrilateral cell is split into two triangles along alternating diagonals (a chequerboard,
    so the mesh has no preferred direction at the contact). ``first=None``: ``cells = (nr, nz)``
    uniform cells.

    Raises:
        ModelError: non-positive sizes, ``growth <= 1`` or neither ``first`` nor ``cells``.
    """
    R, H = float(radius), float(height)
    if not (R > 0 and H > 0 and math.isfinite(R) and math.isfinite(H)):
        raise ModelError(f"cylinder radius and height must be positive [m], got {radius!r}, {height!r}")
    if first is None:
        if cells is None:
            raise ModelError("give first (the cell size at the contact [m]) or cells=(nr, nz)")
        rs, ds = np.linspace(0.0, R, int(cells[0]) + 1), np.linspace(0.0, H, int(cells[1]) + 1)
    else:
        first = float(first)
        if not (first > 0 and growth > 1):
            raise ModelError(f"first must be > 0 m and growth > 1, got {first!r}, {growth!r}")
        c = first if core is None else max(float(core), first)
        rs = graded_axis(R, graded_cells(R, first, c, growth), first, core=c)
        ds = graded_axis(H, graded_cells(H, first, c, growth), first, core=c)
    zs = H - ds[::-1]
    nr, nz = len(rs), len(zs)
    rr, zz = np.meshgrid(rs, zs, indexing="ij")
    pts = np.column_stack([rr.ravel(), zz.ravel()])
    i, j = np.meshgrid(np.arange(nr - 1), np.arange(nz - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    n00, n10, n01, n11 = i * nz + j, (i + 1) * nz + j, i * nz + j + 1, (i + 1) * nz + j + 1
    flip = (i + j) % 2 == 1
    # counter-clockwise in (r, z): r to the right, z up
    t1 = np.where(flip[:, None], np.stack([n00, n10, n01], 1), np.stack([n00, n10, n11], 1))
    t2 = np.where(flip[:, None], np.stack([n10, n11, n01], 1), np.stack([n00, n11, n01], 1))
    return AxisymmetricMesh(pts, np.concatenate([t1, t2]))


# ----------------------------------------------------------------------------- model
def _ring_F(x, Dm_inv, R_c):
    """3x3 deformation gradient in ``(r, theta, z)`` of a linear triangle with nodes ``x (3, 3)``
    (``(r, 0, z)``), inverse rest edge matrix ``Dm_inv (2, 2)`` [1/m] and rest centroid radius
    ``R_c`` [m]."""
    rz = x[:, jnp.array([0, 2])]
    Ds = jnp.stack([rz[1] - rz[0], rz[2] - rz[0]], axis=1)  # columns: edges
    F2 = Ds @ Dm_inv
    hoop = jnp.mean(x[:, 0]) / R_c
    zero = jnp.zeros((), dtype=x.dtype)
    return jnp.array([[F2[0, 0], zero, F2[0, 1]], [zero, hoop, zero], [F2[1, 0], zero, F2[1, 1]]])


def _axisym_linear_energy(x, Dm_inv, R_c, V0, lam, mu):
    return V0 * linear_elastic_energy_density(_ring_F(x, Dm_inv, R_c), lam, mu)


def _axisym_neo_hookean_energy(x, Dm_inv, R_c, V0, lam, mu):
    return V0 * neo_hookean_energy_density(_ring_F(x, Dm_inv, R_c), lam, mu)


def _axisym_stable_neo_hookean_energy(x, Dm_inv, R_c, V0, lam, mu):
    return V0 * stable_neo_hookean_energy_density(_ring_F(x, Dm_inv, R_c), mu, lam + mu)


_AXISYMMETRIC_ENERGIES = {"fem_linear": _axisym_linear_energy, "fem_neo_hookean": _axisym_neo_hookean_energy,
                          "stable_neo_hookean": _axisym_stable_neo_hookean_energy}


def _ring_jacobian(x, Dm_inv, R_c):
    F = _ring_F(x, Dm_inv, R_c)
    return (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) * F[1, 1]


class AxisymmetricModel(ElasticModel):
    """Axisymmetric FEM on linear triangles of the meridian plane (module docstring).

    The :class:`~difftissue.models.ElasticModel` fields hold the triangles: ``tets`` ``(M, 3)``,
    ``tet_Dm_inv`` ``(M, 2, 2)`` [1/m] (inverse rest edge matrices in ``(r, z)``),
    ``tet_volumes`` ``(M,)`` [m^3] (ring volumes ``2 pi R_c A``); ``ring_radii`` ``(M,)`` [m]
    the rest centroid radii. One region; no pre-stretch (a pre-stretched layer is not
    modelled axisymmetrically: refused).
    """

    ring_radii: np.ndarray
    energy_linear_in_youngs_modulus: ClassVar[bool] = True  # lambda and mu are E times functions of nu

    def __init__(self, mesh: AxisymmetricMesh, kind: str = "fem_linear"):
        if not isinstance(mesh, AxisymmetricMesh):
            raise ModelError(f"AxisymmetricModel needs an AxisymmetricMesh, got {type(mesh).__name__}")
        if kind not in AXISYMMETRIC_MODELS:
            raise ModelError(f"the axisymmetric model supports {AXISYMMETRIC_MODELS}, got {kind!r} "
                             "(the springs_volume lattices are 3-D element forms: use a 3-D Indentation)")
        p, t = mesh.points, mesh.triangles
        Dm = np.stack([p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]], axis=2)  # (M, 2 coords, 2 edges)
        area = 0.5 * (Dm[:, 0, 0] * Dm[:, 1, 1] - Dm[:, 0, 1] * Dm[:, 1, 0])
        R_c = p[t, 0].mean(axis=1)
        self.kind = kind
        self.rest_points = mesh.points3()
        self.tets = t
        self.tet_regions = np.zeros(len(t), dtype=np.int32)
        self.tet_Dm_inv = np.linalg.inv(Dm)
        self.tet_volumes = 2.0 * np.pi * R_c * area
        self.region_names = ("tissue",)
        self.nu_min = -1.0
        self.ring_radii = R_c

    def region_values(self, material: Material) -> dict[str, jax.Array]:
        """:meth:`ElasticModel.region_values`, and ``pre_stretch`` must be 1 (no pre-tension in
        the axisymmetric model: :class:`~difftissue.errors.ModelError`, or an equinox runtime
        error when traced)."""
        if isinstance(material, CheckedMaterial):
            return super().region_values(material)
        p = dict(super().region_values(material))
        for name in ("pre_stretch", "pre_stretch_y"):
            if name not in p:
                continue
            v = p[name]
            msg = f"the axisymmetric model has no {name} (pre-tension is modelled in 3-D only): give 1"
            if _is_concrete({name: v}):
                if not np.all(np.asarray(v) == 1.0):
                    raise ModelError(f"{msg}, got {np.asarray(v)}")
            else:
                p["youngs_modulus"] = eqx.error_if(p["youngs_modulus"], jnp.any(v != 1.0), msg)
        return p

    def terms(self, material):
        p = self.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = self.tet_regions
        fn = _AXISYMMETRIC_ENERGIES[self.kind]
        return (ElementTerm("triangles", self.tets, fn, (self.tet_Dm_inv, self.ring_radii, self.tet_volumes, lam[r], mu[r])),)

    def tet_jacobians(self, x):
        """``det F`` (in-plane determinant times the hoop stretch) of every triangle."""
        return jax.vmap(_ring_jacobian)(x[self.tets], jnp.asarray(self.tet_Dm_inv), jnp.asarray(self.ring_radii))

    def stress_free_tets(self, pre_stretch, pre_stretch_y=None):
        raise ModelError("the axisymmetric model has no pre-stretch")

    def lumped_masses(self, material: Material):
        """Nodal masses [kg]: each ring's mass ``rho V0`` shared equally by its three nodes."""
        rho = self.region_values(material)["density"][self.tet_regions]
        return jnp.zeros(self.n_nodes).at[self.tets.reshape(-1)].add(jnp.repeat(rho * self.tet_volumes / 3.0, 3))


def top_edge_rings(mesh: AxisymmetricMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes of the top surface ``z = max z``, sorted by r, their ring areas [m^2]
    (``2 pi`` times the integral of ``r N_i`` over the top edges: the tributary area of the
    whole ring) and tributary lengths [m] (half the adjacent edges)."""
    p = mesh.points
    top = p[:, 1].max()
    tol = 1e-9 * float(np.ptp(p, axis=0).max())
    ids = np.flatnonzero(np.abs(p[:, 1] - top) <= tol)
    ids = ids[np.argsort(p[ids, 0])]
    r = p[ids, 0]
    L = np.diff(r)
    area = np.zeros(len(ids))
    length = np.zeros(len(ids))
    area[:-1] += 2.0 * np.pi * L * (2.0 * r[:-1] + r[1:]) / 6.0
    area[1:] += 2.0 * np.pi * L * (r[:-1] + 2.0 * r[1:]) / 6.0
    length[:-1] += 0.5 * L
    length[1:] += 0.5 * L
    return ids.astype(np.int32), area, length


class AxisymmetricContactModel(ContactModel):
    """:class:`~difftissue.contact.ContactModel` of an :class:`AxisymmetricModel`: frictionless
    penalty contact of a rigid sphere or cone on the axis with the top-surface rings.

    Each top node ``i`` is a ring of area ``A_i`` (:func:`top_edge_rings`) and tributary length
    ``l_i``; its penalty is ``kappa_i = penalty * E * A_i / l_i`` [N/m], the 3-D rule
    ``penalty * E * A / h`` with the ring's width as its local size, so the penetration
    relative to the local deformation is about ``1 / penalty`` as in 3-D. The reaction force
    is the whole specimen's (the rings are full rings).
    """

    def __init__(self, base: AxisymmetricModel, indenter, mesh: AxisymmetricMesh, *, depth=0.0, penalty: float = 100.0):
        if not isinstance(base, AxisymmetricModel):
            raise ModelError("AxisymmetricContactModel needs an AxisymmetricModel as base")
        if not isinstance(indenter, (SphereIndenter, ConeIndenter)) or not indenter.on_flat_top or indenter.axis_xy != (0.0, 0.0):
            raise ModelError("the axisymmetric contact takes a SphereIndenter or ConeIndenter on the axis r = 0 approaching along -z")
        penalty = float(penalty)
        if not (math.isfinite(penalty) and penalty > 0):
            raise ModelError(f"penalty must be a positive number, got {penalty!r}")
        ids, area, length = top_edge_rings(mesh)
        if ids.size < 2:
            raise BoundaryConditionError("the axisymmetric mesh has no top edge")
        adopt_base_fields(self, base)
        self.base = base
        self.indenter = indenter
        self.depth = jnp.asarray(depth, dtype=float)
        self.contact_nodes = ids
        self.penalty_factors = penalty * area / length
        self.penalty = penalty

    def min_volume_ratio(self, x):
        return self.base.min_volume_ratio(x)


def axisymmetric_boundary_conditions(mesh: AxisymmetricMesh, *, base: str = "bonded") -> BoundaryConditions:
    """Boundary conditions of a cylinder's meridian mesh: the dummy ``y`` component fixed on
    every node, ``u_r = 0`` on the axis ``r = 0``, the base ``z = min z`` ``"bonded"`` (both
    components) or ``"sliding"`` (``u_z = 0``); the outer radius is free."""
    p = mesh.points
    tol = 1e-9 * float(np.ptp(p, axis=0).max())
    fixed = np.zeros((mesh.n_nodes, 3), dtype=bool)
    fixed[:, 1] = True
    fixed[np.abs(p[:, 0]) <= tol, 0] = True
    bottom = np.abs(p[:, 1] - p[:, 1].min()) <= tol
    if base == "bonded":
        fixed[bottom, 0] = fixed[bottom, 2] = True
    elif base == "sliding":
        fixed[bottom, 2] = True
    else:
        raise BoundaryConditionError(f"base must be 'bonded' or 'sliding', got {base!r}")
    zeros = jnp.asarray(np.zeros((mesh.n_nodes, 3)), dtype=jnp.result_type(float))
    return BoundaryConditions(fixed, zeros, zeros)
