"""Rigid frictionless indenters and compression platens.

Two ways a rigid body loads the tissue, both differentiable:

- **Penalty contact** (:class:`SphereIndenter`, :class:`ConeIndenter`): the contact region
  is unknown, so every candidate surface node ``i`` carries the energy
  ``kappa_i / 2 * max(p_i, 0)^2`` of its penetration ``p_i`` [m] into the indenter. The
  penalty ``kappa_i = penalty * E * A_i / h_i`` [N/m] scales with the stiffest Young's modulus
  ``E``, the node's tributary surface area ``A_i`` and its local size ``h_i = sqrt(A_i)``, so
  the penetration relative to the local deformation is about ``1 / penalty`` whatever the
  material and mesh (default ``penalty = 100``; see ``docs/contact.md`` for the measured bias).
  The contact is frictionless: the penalty force is normal to the indenter surface.
  :class:`ContactModel` adds these terms to any :class:`~difftissue.models.ElasticModel`, so
  the static solver minimises elastic + contact energy with Newton's method and
  differentiates the equilibrium implicitly, as without contact.
- **Prescribed displacement** (:class:`FlatPunch`, :class:`Platens`): a flat rigid face in
  full contact moves its nodes with it. Frictionless: only the normal (z) component is
  prescribed and the nodes slide; bonded: all three components. The reaction force is the
  sum of the static solution's reactions over those nodes.

Conventions: by default the tissue surface is the plane ``z = surface_z`` with the tissue
below it and the indenter approaches along ``-z``. On a curved surface (any boundary of a mesh
from file) the indenter is given by its approach direction ``axis_direction`` (unit, into the
tissue) and the position ``contact_point`` [m] of its tip at depth 0 (:func:`place_indenter`
finds it: the first contact of the indenter moving along its axis onto the surface), and the
candidate nodes are the boundary nodes whose outward normal faces the indenter
(:func:`facing_surface_nodes`). ``depth`` [m] is positive into the tissue, along the axis;
reaction forces are reported positive when they push the indenter back (compressive), in N,
along the axis.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .boundary import BoundaryConditions
from .errors import BoundaryConditionError, ModelError
from .materials import Material
from .mesh import TetMesh, ray_triangle_hits
from .models import ElasticModel, ElementTerm
from .selectors import BoundingBoxFace

__all__ = [
    "BASE_FIELDS",
    "adopt_base_fields",
    "Indenter",
    "SphereIndenter",
    "ConeIndenter",
    "FlatPunch",
    "Platens",
    "ContactModel",
    "surface_node_areas",
    "contact_force",
    "top_surface_nodes",
    "boundary_node_normals",
    "facing_surface_nodes",
    "surface_point_on_axis",
    "place_indenter",
]


def _positive(name: str, value, unit: str = "m") -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ModelError(f"{name} must be a positive finite number [{unit}], got {value!r}")
    return v


def _safe_norm(v, axis=-1):
    # sqrt(|v|^2 + tiny): differentiable at 0 (a node exactly on the axis or at the apex).
    return jnp.sqrt(jnp.sum(v * v, axis=axis) + jnp.finfo(v.dtype).tiny ** 0.5)


# --------------------------------------------------------------------- indenters
def _unit3(name: str, v) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or not np.linalg.norm(a) > 0:
        raise ModelError(f"{name} must be a non-zero finite 3-vector, got {v!r}")
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


def _point3(name: str, v) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ModelError(f"{name} must be a finite 3-vector [m], got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclasses.dataclass(frozen=True, kw_only=True)
class Indenter:
    """Geometry of a rigid axisymmetric indenter.

    Two ways to place it:

    - on a flat top surface (default): the tip is at ``(axis_xy[0], axis_xy[1], surface_z -
      depth)``, the indenter approaches along ``-z``;
    - anywhere (a curved surface): ``axis_direction`` is the unit approach direction (into
      the tissue) and ``contact_point`` [m] the tip's position at depth 0; the tip is at
      ``contact_point + depth * axis_direction`` (``axis_xy`` and ``surface_z`` then stay at
      their defaults). :func:`place_indenter` computes the contact point of the first contact.

    A frozen (hashable) dataclass: the geometry is static data of a compiled solve, the
    ``depth`` [m] is passed separately and may be traced, so a ``lax.scan`` over a depth
    protocol compiles once. Subclasses define :meth:`penetration` and :meth:`touch_depth`.
    """

    axis_xy: tuple[float, float] = (0.0, 0.0)
    surface_z: float = 0.0
    axis_direction: tuple[float, float, float] | None = None
    contact_point: tuple[float, float, float] | None = None

    def __post_init__(self):
        object.__setattr__(self, "axis_xy", (float(self.axis_xy[0]), float(self.axis_xy[1])))
        object.__setattr__(self, "surface_z", float(self.surface_z))
        if self.axis_direction is None and self.contact_point is None:
            return
        if self.axis_direction is None or self.contact_point is None:
            raise ModelError("an indenter placed off the flat top needs both axis_direction and contact_point [m]")
        if self.axis_xy != (0.0, 0.0) or self.surface_z != 0.0:
            raise ModelError("give either axis_xy and surface_z (approach along -z onto a flat top) or axis_direction and contact_point, not both")
        object.__setattr__(self, "axis_direction", _unit3("axis_direction", self.axis_direction))
        object.__setattr__(self, "contact_point", _point3("contact_point", self.contact_point))

    @property
    def on_flat_top(self) -> bool:
        """True for the default placement (along -z onto the plane ``z = surface_z``)."""
        return self.axis_direction is None

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """``(contact_point (3,) [m], axis_direction (3,))``: the tip at depth 0 and the unit
        approach direction, for either placement."""
        if self.on_flat_top:
            return np.array([self.axis_xy[0], self.axis_xy[1], self.surface_z]), np.array([0.0, 0.0, -1.0])
        return np.asarray(self.contact_point, dtype=float), np.asarray(self.axis_direction, dtype=float)

    def tip(self, depth):
        """Position [m] of the tip (the leading point on the axis) at ``depth``, shape ``(3,)``."""
        d = jnp.asarray(depth, dtype=float)
        if self.on_flat_top:
            return jnp.stack([jnp.full_like(d, self.axis_xy[0]), jnp.full_like(d, self.axis_xy[1]), self.surface_z - d])
        return jnp.asarray(self.contact_point) + d * jnp.asarray(self.axis_direction)

    def axial_radial(self, x, depth):
        """``(t, r)`` of points ``x (..., 3)`` relative to the tip at ``depth``: ``t`` [m] the
        distance behind the tip along the axis (towards the indenter's body, ``-axis_direction``),
        ``r`` [m] the distance from the axis (smoothed at 0, see ``_safe_norm``)."""
        rel = x - self.tip(depth)
        n = jnp.asarray(self.axis_direction)
        s = rel @ n
        return -s, _safe_norm(rel - s[..., None] * n)

    def distance_from_axis(self, x):
        """Distance [m] of points ``x (..., 3)`` from the indenter axis."""
        if self.on_flat_top:
            return jnp.hypot(x[..., 0] - self.axis_xy[0], x[..., 1] - self.axis_xy[1])
        rel = x - jnp.asarray(self.contact_point)
        n = jnp.asarray(self.axis_direction)
        return jnp.linalg.norm(rel - (rel @ n)[..., None] * n, axis=-1)

    def penetration(self, x, depth):
        """Penetration [m] of points ``x (..., 3)`` into the indenter at ``depth`` (> 0 inside)."""
        raise NotImplementedError

    def touch_depth(self, points) -> np.ndarray:
        """Depth [m] at which each of the fixed ``points (K, 3)`` [m] first touches the indenter
        moving along its axis (``inf`` where it never touches the indenter's front)."""
        raise NotImplementedError

    def _axial_radial_np(self, points) -> tuple[np.ndarray, np.ndarray]:
        # NumPy (t, r) of points relative to the tip at depth 0: t along the approach direction
        c, n = self.frame()
        rel = np.asarray(points, dtype=float).reshape(-1, 3) - c
        t = rel @ n
        return t, np.linalg.norm(rel - t[:, None] * n, axis=1)

    def _placement_record(self) -> dict:
        if self.on_flat_top:
            return {}
        return {"axis_direction": list(self.axis_direction), "contact_point": list(self.contact_point)}


@dataclasses.dataclass(frozen=True)
class SphereIndenter(Indenter):
    """Rigid sphere of ``radius`` [m] (Hertz / Dimitriadis geometry)."""

    radius: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "radius", _positive("sphere radius", self.radius))

    def penetration(self, x, depth):
        if self.on_flat_top:
            c = self.tip(depth) + jnp.array([0.0, 0.0, self.radius])
        else:
            c = self.tip(depth) - self.radius * jnp.asarray(self.axis_direction)
        return self.radius - _safe_norm(x - c)

    def touch_depth(self, points) -> np.ndarray:
        t, r = self._axial_radial_np(points)
        R = self.radius
        return np.where(r <= R, t + R - np.sqrt(np.maximum(R * R - r * r, 0.0)), np.inf)

    def record(self) -> dict:
        """The indenter in a material card's scenario record: ``{"indenter": "sphere", "radius": R [m]}``
        (plus ``axis_direction`` and ``contact_point`` [m] when placed off the flat top)."""
        return {"indenter": "sphere", "radius": float(self.radius), **self._placement_record()}


@dataclasses.dataclass(frozen=True)
class ConeIndenter(Indenter):
    """Rigid cone of ``half_angle`` [rad] between its axis and its surface (Sneddon geometry).

    The penetration is the distance to the cone surface in the meridian plane,
    ``(z_tip - z) sin(theta) + r cos(theta)`` with the sign flipped; it is exact on the
    lateral surface, which is all a cone touches when it goes less deep than its height.
    """

    half_angle: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        if not (0.0 < float(self.half_angle) < np.pi / 2):
            raise ModelError(f"cone half_angle must lie in (0, pi/2) rad, got {self.half_angle!r}")

    def penetration(self, x, depth):
        if self.on_flat_top:
            tip = self.tip(depth)
            r = _safe_norm(x[..., :2] - tip[:2])
            dz = x[..., 2] - tip[2]
        else:
            dz, r = self.axial_radial(x, depth)
        return dz * np.sin(self.half_angle) - r * np.cos(self.half_angle)

    def touch_depth(self, points) -> np.ndarray:
        t, r = self._axial_radial_np(points)
        return t + r / np.tan(self.half_angle)

    def record(self) -> dict:
        """The indenter in a material card's scenario record: ``{"indenter": "cone", "half_angle": theta [rad]}``
        (plus ``axis_direction`` and ``contact_point`` [m] when placed off the flat top)."""
        return {"indenter": "cone", "half_angle": float(self.half_angle), **self._placement_record()}


def surface_node_areas(mesh: TetMesh, nodes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Boundary nodes and their tributary surface areas [m^2] (a third of each face).

    Args:
        nodes: restrict to these node ids (they must be on the boundary).

    Returns:
        ``(node_ids (K,), areas (K,))``.
    """
    p = np.asarray(mesh.points, dtype=float)
    f = mesh.boundary_faces
    a = 0.5 * np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1)
    area = np.zeros(len(p))
    np.add.at(area, f.reshape(-1), np.repeat(a / 3.0, 3))
    ids = np.flatnonzero(area > 0) if nodes is None else np.asarray(nodes, dtype=np.int64).reshape(-1)
    if nodes is not None and np.any(area[ids] <= 0):
        bad = ids[area[ids] <= 0]
        raise BoundaryConditionError(f"contact nodes must lie on the boundary; nodes {bad[:8].tolist()} are interior")
    return ids.astype(np.int32), area[ids]


def _mirrored_areas(mesh: TetMesh, ids: np.ndarray, planes: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Tributary areas [m^2] of nodes ``ids`` without the boundary faces that lie on the mirror
    ``planes`` (interior faces of the whole specimen), and the number of mirror copies of each
    node (2 per plane it lies on)."""
    p = np.asarray(mesh.points, dtype=float)
    copies = np.ones(len(p))
    f = mesh.boundary_faces
    keep = np.ones(len(f), dtype=bool)
    for plane in planes:
        if not isinstance(plane, str) or plane.count("-") != 1 or plane.split("-")[0] not in "xyz" or plane.split("-")[1] not in ("min", "max"):
            raise BoundaryConditionError(f"mirror planes must be faces of the bounding box such as 'x-min', got {plane!r}")
        on = BoundingBoxFace(*plane.split("-"), tolerance=1e-9).mask(p)  # type: ignore[arg-type]
        copies[on] *= 2.0
        keep &= ~np.all(on[f], axis=1)
    a = 0.5 * np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1)
    area = np.zeros(len(p))
    np.add.at(area, f[keep].reshape(-1), np.repeat(a[keep] / 3.0, 3))
    return area[ids], copies[ids]


def top_surface_nodes(mesh: TetMesh, *, tolerance: float = 1e-9) -> np.ndarray:
    """Boundary nodes on the top plane ``z = max z`` (within ``tolerance`` x the mesh size)."""
    p = np.asarray(mesh.points)
    lo, hi = p.min(axis=0), p.max(axis=0)
    tol = tolerance * float(np.linalg.norm(hi - lo))
    ids, _ = surface_node_areas(mesh)
    return ids[np.abs(p[ids, 2] - hi[2]) <= tol]


def _mirror_face_mask(mesh: TetMesh, planes: Sequence[str]) -> np.ndarray:
    """True for the boundary faces that lie on the mirror ``planes`` (bounding-box faces)."""
    p = np.asarray(mesh.points, dtype=float)
    f = mesh.boundary_faces
    on_plane = np.zeros(len(f), dtype=bool)
    for plane in planes:
        if not isinstance(plane, str) or plane.count("-") != 1 or plane.split("-")[0] not in "xyz" or plane.split("-")[1] not in ("min", "max"):
            raise BoundaryConditionError(f"mirror planes must be faces of the bounding box such as 'x-min', got {plane!r}")
        on = BoundingBoxFace(*plane.split("-"), tolerance=1e-9).mask(p)  # type: ignore[arg-type]
        on_plane |= np.all(on[f], axis=1)
    return on_plane


def boundary_node_normals(mesh: TetMesh, *, mirror_planes: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boundary nodes, their tributary areas [m^2] and outward unit normals.

    The normal of a node is the area-weighted mean of the outward normals of its boundary faces
    (``TetMesh.boundary_faces`` are outward-oriented), the area a third of each face. Faces on
    ``mirror_planes`` (bounding-box faces such as ``"x-min"``, symmetry planes of a part model)
    are left out: they are interior to the whole specimen.

    Returns:
        ``(node_ids (K,), areas (K,), normals (K, 3))``, the nodes with a positive area.
    """
    p = np.asarray(mesh.points, dtype=float)
    f = mesh.boundary_faces[~_mirror_face_mask(mesh, mirror_planes)] if mirror_planes else mesh.boundary_faces
    cross = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])  # 2 x area x unit normal
    area = np.zeros(len(p))
    np.add.at(area, f.reshape(-1), np.repeat(0.5 * np.linalg.norm(cross, axis=1) / 3.0, 3))
    acc = np.zeros((len(p), 3))
    for k in range(3):
        np.add.at(acc, f[:, k], cross)
    ids = np.flatnonzero(area > 0)
    nrm = acc[ids]
    length = np.linalg.norm(nrm, axis=1)
    # a node whose faces' normals cancel (a knife edge) has no normal: NaN, never facing
    nrm = np.where(length[:, None] > 0, nrm / np.where(length > 0, length, 1.0)[:, None], np.nan)
    return ids.astype(np.int32), area[ids], nrm


def facing_surface_nodes(mesh: TetMesh, axis_direction, *, mirror_planes: Sequence[str] = (), min_cosine: float = 1e-6) -> np.ndarray:
    """Boundary nodes that face an indenter approaching along ``axis_direction``: the outward
    normal ``n`` (:func:`boundary_node_normals`) has ``n . axis_direction < -min_cosine``.

    On a flat top surface approached along -z these are the top nodes (those on its edges
    included, their normal leaning out but still up); on a dome or a cylinder, the half the
    indenter sees. Nodes on the far side of a thin part or in an undercut also face the
    indenter when their normal does; the contact candidates are meant for a surface that the
    axis meets once."""
    d = np.asarray(_unit3("axis_direction", axis_direction))
    ids, _, nrm = boundary_node_normals(mesh, mirror_planes=mirror_planes)
    with np.errstate(invalid="ignore"):
        keep = (nrm @ d) < -float(min_cosine)
    return ids[keep]


def surface_point_on_axis(mesh: TetMesh, axis_point, axis_direction, *, mirror_planes: Sequence[str] = ()) -> np.ndarray:
    """The point [m] where the indenter axis first meets the boundary surface: the line through
    ``axis_point`` [m] along the unit ``axis_direction``, coming from ``-infinity``, intersected
    with the boundary triangles that face it (outward normal against the direction).

    Raises:
        BoundaryConditionError: the axis misses the surface.
    """
    c = np.asarray(_point3("axis_point", axis_point))
    n = np.asarray(_unit3("axis_direction", axis_direction))
    f = mesh.boundary_faces[~_mirror_face_mask(mesh, mirror_planes)] if mirror_planes else mesh.boundary_faces
    t = ray_triangle_hits(c[None], n, np.asarray(mesh.points, dtype=float)[f], facing=-1)[0][0]
    hit = np.isfinite(t)
    if not np.any(hit):
        raise BoundaryConditionError(f"the indenter axis through {c.tolist()} m along {n.tolist()} misses the specimen's surface")
    return c + float(np.min(t[hit])) * n


def place_indenter(indenter: Indenter, mesh: TetMesh, *, axis_point=None, axis_direction=(0.0, 0.0, -1.0), contact_point=None,
                   nodes=None, mirror_planes: Sequence[str] = ()) -> Indenter:
    """``indenter`` placed on the (curved) surface of ``mesh`` with its depth measured from the
    first contact.

    The axis runs through ``axis_point`` [m] along ``axis_direction`` (the approach, into the
    tissue). With ``contact_point`` [m] given, the tip is there at depth 0. Otherwise the tip at
    depth 0 is where the indenter, moving along its axis from outside, first touches a node of
    ``nodes`` (default: :func:`facing_surface_nodes`): the depth is measured from the first
    contact. On a smooth surface whose normal at the axis point is the axis (the top of a dome,
    a cylinder's crest) this is the surface point on the axis (:func:`surface_point_on_axis`).

    Raises:
        BoundaryConditionError: the axis misses the surface, or a given ``contact_point`` lets the
            indenter penetrate a node at depth 0.
    """
    n = _unit3("axis_direction", axis_direction)
    if nodes is None:
        nodes = facing_surface_nodes(mesh, n, mirror_planes=mirror_planes)
    nodes = np.asarray(nodes, dtype=np.int64)
    if nodes.size == 0:
        raise BoundaryConditionError("no boundary node faces the indenter")
    p = np.asarray(mesh.points, dtype=float)
    scale = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    if contact_point is None:
        if axis_point is None:
            raise BoundaryConditionError("place_indenter needs axis_point or contact_point [m]")
        s = surface_point_on_axis(mesh, axis_point, n, mirror_planes=mirror_planes)
        trial = dataclasses.replace(indenter, axis_xy=(0.0, 0.0), surface_z=0.0, axis_direction=n, contact_point=tuple(s))
        d0 = float(np.min(trial.touch_depth(p[nodes])))
        if not np.isfinite(d0):
            raise BoundaryConditionError("no surface node comes under the indenter moving along its axis")
        return dataclasses.replace(trial, contact_point=tuple(s + d0 * np.asarray(n)))
    placed = dataclasses.replace(indenter, axis_xy=(0.0, 0.0), surface_z=0.0, axis_direction=n, contact_point=_point3("contact_point", contact_point))
    d0 = float(np.min(placed.touch_depth(p[nodes])))
    if d0 < -1e-9 * scale:
        raise BoundaryConditionError(f"at contact_point {list(placed.contact_point)} m the indenter already penetrates the surface by {-d0:.3g} m at depth 0")
    return placed


@dataclasses.dataclass(frozen=True)
class _PenaltyEnergy:
    # energy(x_e (1, 3), kappa, depth) of one candidate node; hashable (a static field).
    indenter: Indenter

    def __call__(self, x_e, kappa, depth):
        return 0.5 * kappa * jnp.maximum(self.indenter.penetration(x_e[0], depth), 0.0) ** 2


#: The :class:`~difftissue.models.ElasticModel` fields a contact model takes from its base model.
BASE_FIELDS = ("kind", "rest_points", "tets", "tet_regions", "tet_Dm_inv", "tet_volumes", "region_names", "nu_min")


def adopt_base_fields(model, base) -> None:
    """Set ``model``'s :data:`BASE_FIELDS` to ``base``'s (in a contact model's ``__init__``)."""
    for k in BASE_FIELDS:
        setattr(model, k, getattr(base, k))


class ContactModel(ElasticModel):
    """An :class:`~difftissue.models.ElasticModel` plus frictionless penalty contact with a
    rigid indenter: pass it to :func:`~difftissue.solvers.static.solve_static` instead of
    the base model.

    Attributes (besides the base model's):
        base: the elastic model.
        indenter: a :class:`SphereIndenter` or :class:`ConeIndenter` (static geometry).
        depth: indenter depth [m] (a leaf: :meth:`with_depth` does not recompile).
        contact_nodes: ``(K,)`` candidate surface nodes.
        penalty: the dimensionless penalty given (static).
        penalty_factors: ``(K,)`` ``penalty * A_i / h_i`` [m]; ``kappa_i`` = this x the largest
            Young's modulus of the material. The penalty scales with ``E`` also under
            differentiation, so the computed force is exactly proportional to ``E`` (as for a
            truly rigid indenter) and its gradient is that of the function computed.
    """

    base: ElasticModel
    indenter: Indenter = eqx.field(static=True)
    depth: jax.Array
    contact_nodes: np.ndarray
    penalty_factors: np.ndarray
    penalty: float = eqx.field(static=True, default=100.0)

    def __init__(self, base: ElasticModel, indenter: Indenter, mesh: TetMesh, *, depth=0.0, nodes=None, penalty: float = 100.0,
                 mirror_planes: Sequence[str] = ()):
        """
        Args:
            base: the elastic model of ``mesh``.
            indenter: the rigid indenter.
            mesh: the mesh of ``base`` (for the surface).
            depth: indenter depth [m].
            nodes: candidate contact nodes (default: the top surface, see
                :func:`top_surface_nodes`); they must be boundary nodes.
            penalty: dimensionless penalty ``kappa_i h_i / (E A_i)``; larger is stiffer contact
                (less penetration) but a worse-conditioned Newton system.
            mirror_planes: faces of the mesh's bounding box (``"x-min"``, ...) that are symmetry
                planes: the mesh is the part of a specimen mirrored there (e.g. the quarter
                model of :func:`~difftissue.scenarios.indentation_block`). A node on ``k`` such
                planes gets ``2^-k`` of the whole specimen's penalty ``kappa_i`` (its area
                ``A_i`` and length ``h_i = sqrt(A_i)`` taken from the mirrored surface, the faces
                on the planes left out), so the part's contact forces times the number of
                mirror images are the whole specimen's.
        """
        if not isinstance(base, ElasticModel) or isinstance(base, ContactModel):
            raise ModelError("ContactModel needs a plain ElasticModel as base (one indenter per model)")
        if not isinstance(indenter, (SphereIndenter, ConeIndenter)):
            raise ModelError(
                f"penalty contact supports SphereIndenter and ConeIndenter, got {type(indenter).__name__}; "
                "a FlatPunch or Platens is applied as boundary conditions (.apply)"
            )
        if np.shape(mesh.points) != np.shape(base.rest_points) or not np.allclose(mesh.points, base.rest_points):
            raise ModelError("ContactModel: mesh does not match the base model's rest points")
        penalty = _positive("penalty", penalty, "-")
        ids, area = surface_node_areas(mesh, top_surface_nodes(mesh) if nodes is None else nodes)
        if ids.size == 0:
            raise BoundaryConditionError("no candidate contact nodes on the surface")
        copies = np.ones(len(ids))
        if mirror_planes:
            area, copies = _mirrored_areas(mesh, ids, mirror_planes)
        adopt_base_fields(self, base)
        self.base = base
        self.indenter = indenter
        self.depth = jnp.asarray(depth, dtype=float)
        self.contact_nodes = ids
        # the whole specimen's kappa = penalty E (copies A_i) / sqrt(copies A_i), shared by the copies
        self.penalty_factors = penalty * np.sqrt(copies * area) / copies
        self.penalty = float(penalty)

    @property
    def energy_linear_in_youngs_modulus(self) -> bool:  # type: ignore[override]
        """The base model's: the penalty ``kappa_i`` is the largest Young's modulus times a
        constant, so scaling every modulus scales the contact energy alike."""
        return bool(self.base.energy_linear_in_youngs_modulus)

    def with_depth(self, depth) -> "ContactModel":
        """The same model with the indenter at ``depth`` [m] (traceable: no recompile)."""
        return eqx.tree_at(lambda m: m.depth, self, jnp.asarray(depth, dtype=float))

    def _kappa(self, material: Material):
        E = jnp.max(self.base.region_values(material)["youngs_modulus"])
        return E * self.penalty_factors

    def terms(self, material):
        n = self.contact_nodes.shape[0]
        depth = jnp.broadcast_to(self.depth, (n,))
        contact = ElementTerm("contact", self.contact_nodes[:, None], _PenaltyEnergy(self.indenter), (self._kappa(material), depth))
        return tuple(self.base.terms(material)) + (contact,)

    def min_volume_ratio(self, x):
        return self.base.min_volume_ratio(x)

    def penetrations(self, x):
        """Penetration [m] of every candidate node at positions ``x`` (> 0: in contact)."""
        return self.indenter.penetration(x[self.contact_nodes], self.depth)

    def contact_energy(self, x, material: Material, depth=None):
        """Penalty energy [J] at positions ``x`` and indenter ``depth`` (default: the model's)."""
        p = self.indenter.penetration(x[self.contact_nodes], self.depth if depth is None else depth)
        return 0.5 * jnp.sum(self._kappa(material) * jnp.maximum(p, 0.0) ** 2)

    def reaction_force(self, x, material: Material):
        """Force [N] the tissue exerts on the indenter against its approach direction (along +z
        on a flat top; positive compressive).

        ``dE_contact / d depth`` at fixed nodes: the sum of the penalty forces' axial parts.
        """
        return jax.grad(lambda d: self.contact_energy(x, material, d))(self.depth)

    def contact_radius(self, x):
        """Largest distance [m] from the axis of a node in contact at positions ``x``."""
        r = self.indenter.distance_from_axis(x[self.contact_nodes])
        return jnp.max(jnp.where(self.penetrations(x) > 0, r, 0.0))


def contact_force(model: ContactModel, solution, material: Material):
    """Indentation force [N] (positive compressive) of a static solution of a :class:`ContactModel`."""
    x = jnp.asarray(model.rest_points) + solution.displacement
    return model.reaction_force(x, material)


# ------------------------------------------------------- displacement-type contact
def _nodes_in_disc(mesh: TetMesh, radius: float, axis_xy, surface_z: float, tol: float):
    p = np.asarray(mesh.points)
    ids = top_surface_nodes(mesh)
    on_top = ids[np.abs(p[ids, 2] - surface_z) <= tol]
    r = np.hypot(p[on_top, 0] - axis_xy[0], p[on_top, 1] - axis_xy[1])
    return on_top[r <= radius + tol]


class FlatPunch(eqx.Module):
    """Rigid flat cylindrical punch of ``radius`` [m] in full contact (Sneddon / Hayes geometry).

    Applied as prescribed displacements of the top-surface nodes within ``radius`` of the
    axis: ``u_z = -depth`` (frictionless: the nodes slide freely) or ``u = (0, 0, -depth)``
    (``bonded=True``). With a mesh, the effective punch radius is that of the outermost node
    ring inside ``radius``.
    """

    radius: float = eqx.field(static=True)
    axis_xy: tuple[float, float] = eqx.field(static=True, default=(0.0, 0.0))
    bonded: bool = eqx.field(static=True, default=False)

    def __init__(self, radius, *, axis_xy=(0.0, 0.0), bonded: bool = False):
        self.radius = _positive("punch radius", radius)
        self.axis_xy = (float(axis_xy[0]), float(axis_xy[1]))
        self.bonded = bool(bonded)

    def nodes(self, mesh: TetMesh, *, tolerance: float = 1e-9) -> np.ndarray:
        """Top-surface nodes under the punch."""
        p = np.asarray(mesh.points)
        size = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
        ids = _nodes_in_disc(mesh, self.radius, self.axis_xy, float(p[:, 2].max()), tolerance * size)
        if ids.size == 0:
            raise BoundaryConditionError(f"no surface node lies under the punch of radius {self.radius:g} m at {self.axis_xy}; refine the mesh")
        return ids

    def apply(self, mesh: TetMesh, bc: BoundaryConditions, depth) -> BoundaryConditions:
        """``bc`` with the punch nodes' displacements prescribed for ``depth`` [m]."""
        return _prescribe(bc, self.nodes(mesh), depth, "xyz" if self.bonded else "z")

    def effective_radius(self, points, nodes) -> float:
        """Radius [m] of the outermost ring of ``nodes`` (the nodes under the punch, :meth:`nodes`)
        around the punch axis: the punch radius the mesh represents (at most :attr:`radius`)."""
        p = np.asarray(points, dtype=float)[np.asarray(nodes, dtype=np.int64)]
        return float(np.max(np.hypot(p[:, 0] - self.axis_xy[0], p[:, 1] - self.axis_xy[1])))

    def record(self, points, nodes) -> dict:
        """The punch in a material card's scenario record: ``indenter``, the effective ``radius`` [m]
        of the mesh's ``nodes`` under the punch (:meth:`effective_radius`; the exported specimen is
        meshed anew, so the radius the fit's mesh represented is what it needs), ``radius_note``
        and ``bonded_punch``."""
        return {"indenter": "flat_punch", "radius": self.effective_radius(points, nodes),
                "radius_note": "effective punch radius: the outermost node ring under the punch", "bonded_punch": self.bonded}


class Platens(eqx.Module):
    """Two rigid parallel platens compressing a specimen along z (unconfined compression).

    The bottom platen at ``z = min z`` is fixed, the top one at ``z = max z`` moves down by
    the displacement. ``bonded=False`` (frictionless, the ideal lubricated test): only
    ``u_z`` is prescribed on both faces, and the in-plane rigid modes are removed by fixing
    ``u_x, u_y`` of the bottom node nearest the axis and ``u_y`` (or ``u_x``) of one more
    bottom node — which carry no force in the homogeneous solution. ``bonded=True`` (no
    slip, barrelling): all components of both faces are prescribed.
    """

    bonded: bool = eqx.field(static=True, default=False)

    def faces(self, mesh: TetMesh, *, tolerance: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """``(bottom_nodes, top_nodes)``."""
        p = np.asarray(mesh.points)
        lo, hi = p.min(axis=0), p.max(axis=0)
        tol = tolerance * float(np.linalg.norm(hi - lo))
        return np.flatnonzero(np.abs(p[:, 2] - lo[2]) <= tol), np.flatnonzero(np.abs(p[:, 2] - hi[2]) <= tol)

    def apply(self, mesh: TetMesh, bc: BoundaryConditions, displacement, *, symmetry_planes: Sequence[str] = ()) -> BoundaryConditions:
        """``bc`` with the platens applied for a top-platen ``displacement`` [m] (positive down).

        Args:
            symmetry_planes: ``"x"`` and/or ``"y"``: the model is cut by the plane through the
                specimen's axis normal to x (or y), which already carries ``u_x = 0`` (``u_y =
                0``); then the in-plane pinning uses those planes.
        """
        bottom, top = self.faces(mesh)
        comps = "xyz" if self.bonded else "z"
        bc = _prescribe(bc, bottom, 0.0, comps)
        bc = _prescribe(bc, top, displacement, comps)
        if not self.bonded:
            p = np.asarray(mesh.points)
            c = p[bottom, :2].mean(axis=0)
            sym = set(symmetry_planes)
            if not {"x", "y"} <= sym:
                # a plane normal to x already holds translation x and rotation about z: only
                # translation y is left, and pinning u_y anywhere carries no force (u_x of a
                # node off the plane is not zero in the homogeneous solution: it stays free)
                anchor = bottom[np.argmin(np.linalg.norm(p[bottom, :2] - c, axis=1))]
                bc = bc.fix(mesh, np.array([anchor]), "".join(a for a in "xy" if a not in sym))
                if not sym:
                    # a second bottom node away from the anchor along x stops rotation about z
                    d = p[bottom, :2] - p[anchor, :2]
                    other = bottom[np.argmax(np.abs(d[:, 0]) - 1e-3 * np.abs(d[:, 1]))]
                    bc = bc.fix(mesh, np.array([other]), "y")
        return bc


def _prescribe(bc: BoundaryConditions, nodes: np.ndarray, depth_or_value, components: str) -> BoundaryConditions:
    nodes = np.asarray(nodes, dtype=np.int64)
    comps = [{"x": 0, "y": 1, "z": 2}[c] for c in components]
    fixed = np.array(bc.fixed, copy=True)
    mask = np.zeros_like(fixed)
    for c in comps:
        mask[nodes, c] = True
    fixed |= mask
    if not any(isinstance(v, jax.core.Tracer) for v in (bc.displacement, depth_or_value)):
        # NumPy on concrete values: no per-operation compilation while a scenario is built.
        current = np.asarray(bc.displacement)
        target = np.zeros_like(current)
        target[nodes, 2] = -np.asarray(depth_or_value, dtype=current.dtype)
        return BoundaryConditions(fixed, jnp.asarray(np.where(mask, target, current)), bc.force)
    target = jnp.zeros_like(bc.displacement).at[nodes, 2].set(-jnp.asarray(depth_or_value, dtype=bc.displacement.dtype))
    disp = jnp.where(jnp.asarray(mask), target, bc.displacement)
    return BoundaryConditions(fixed, disp, bc.force)
