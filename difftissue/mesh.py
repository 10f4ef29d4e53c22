"""Tetrahedral tissue meshes: the :class:`TetMesh` pytree, generators, validation and file I/O.

Coordinates are in metres. Tetrahedra are positively oriented:
``(x1 - x0) . ((x2 - x0) x (x3 - x0)) > 0``. Structured specimens (``block``,
``layered_skin``) also carry the cube-lattice spring topology of DESIGN.md §3.1
(:class:`CubeLattice`).

Topology (index arrays) is computed once on the host with NumPy when a mesh is built;
only ``points`` is meant to be differentiated. See ``docs/meshes.md``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import itertools
import math
import warnings
from pathlib import Path
from typing import Any, Sequence

import equinox as eqx
import numpy as np

from ._io import atomic_output
from .errors import (
    DegenerateElementError,
    DuplicateElementError,
    EmptyMeshError,
    IndexOutOfRangeError,
    InvertedElementError,
    MaterialError,
    MeshError,
    ModelError,
    NonFiniteCoordinatesError,
    NonManifoldSurfaceWarning,
    UnsupportedMeshError,
    UnusedNodesWarning,
    _cite,
)
from .materials import Material
from .selectors import select_nodes  # noqa: F401  (re-exported for convenience)

__all__ = [
    "TetMesh",
    "CubeLattice",
    "Specimen",
    "node_patches",
    "Finding",
    "block",
    "curved_top",
    "structured_grid",
    "graded_axis",
    "graded_cells",
    "refined_axis",
    "layered_skin",
    "layer_node_heights",
    "default_skin_layers",
    "signed_volumes",
    "mean_ratio_quality",
    "validate_arrays",
    "unique_edges",
    "boundary_faces",
    "surface",
    "to_meshio",
    "from_meshio",
    "read_mesh",
    "inspect_file",
    "write_mesh",
    "select_nodes",
    "LENGTH_UNITS",
    "WRITE_FORMATS",
]

#: Length units accepted on import, with their factor to metres.
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}

#: Local faces of a positively oriented tet, each oriented with an outward normal;
#: face ``i`` is opposite vertex ``i``.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])

# Cube-local vertex v = bx + 2 by + 4 bz.
_CUBE_CORNERS = np.array([[(v >> 0) & 1, (v >> 1) & 1, (v >> 2) & 1] for v in range(8)])
#: The 12 cube edges (vertex pairs differing in one bit), then the 12 face diagonals (two bits).
_CUBE_EDGES = np.array([[a, b] for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])
_CUBE_DIAGONALS = np.array([[a, b] for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 2])
#: Freudenthal (Kuhn) split of a cube into 6 tets along the 0-7 diagonal: one tet per axis order.
_KUHN_TETS = np.array([[0, 1 << p[0], (1 << p[0]) | (1 << p[1]), 7] for p in itertools.permutations(range(3))])


# ---------------------------------------------------------------- geometry kernels
def ray_triangle_hits(origins: np.ndarray, direction: np.ndarray, tri: np.ndarray, *, facing: int, eps: float = 1e-9):
    """Intersections [m along ``direction``] of the lines ``origins + t direction`` (``(Q, 3)`` points, ``(Q, 3)`` or
    ``(3,)`` directions) with the triangles ``tri`` ``(T, 3, 3)`` (Moller-Trumbore, barycentric
    tolerance ``eps``): ``(t, u, v)`` arrays ``(Q, T)``, ``t = nan`` where the line misses.
    ``facing=-1`` keeps the triangles whose (outward) normal is against the direction (entry
    faces), ``+1`` those along it (exit faces)."""
    d = np.broadcast_to(np.asarray(direction, dtype=float), origins.shape)
    a = tri[:, 0]
    e1, e2 = tri[:, 1] - a, tri[:, 2] - a
    normal = np.cross(e1, e2)
    out_t = np.full((len(origins), len(tri)), np.nan)
    out_u = np.zeros_like(out_t)
    out_v = np.zeros_like(out_t)
    for i, (c, n) in enumerate(zip(origins, d)):
        side = normal @ n
        h = np.cross(n, e2)
        det = np.einsum("ij,ij->i", e1, h)
        ok = (facing * side > 0) & (np.abs(det) > 0)
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        sv = c - a
        u = inv * np.einsum("ij,ij->i", sv, h)
        q = np.cross(sv, e1)
        v = inv * (q @ n)
        t = inv * np.einsum("ij,ij->i", e2, q)
        hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)
        out_t[i] = np.where(hit, t, np.nan)
        out_u[i], out_v[i] = u, v
    return out_t, out_u, out_v


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume ``(x1 - x0) . ((x2 - x0) x (x3 - x0)) / 6`` of each tet [m^3].

    THE host-side (NumPy) signed tet volume: meshes, cutting, exporters and external-solver
    runners call this; traced code calls :func:`difftissue.energies.volume.tet_signed_volume`
    (the same formula in JAX; they agree to 3e-16 of the largest volume, tested). It lives
    here, not in ``energies``, because the data loaders may import the mesh but not physics.
    """
    p = np.asarray(points, dtype=float)
    t = np.asarray(tets)
    x0 = p[t[:, 0]]
    return np.einsum("ij,ij->i", p[t[:, 1]] - x0, np.cross(p[t[:, 2]] - x0, p[t[:, 3]] - x0)) / 6.0


def mean_ratio_quality(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Mean-ratio quality ``12 (3 |V|)^(2/3) / sum(l_ij^2)`` of each tet, signed by its volume.

    1 for a regular tetrahedron, towards 0 for slivers and needles, negative when inverted.
    """
    p = np.asarray(points, dtype=float)
    t = np.asarray(tets)
    vol = signed_volumes(p, t)
    l2 = sum(np.sum((p[t[:, a]] - p[t[:, b]]) ** 2, axis=1) for a, b in _TET_EDGES)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 12.0 * np.cbrt(3.0 * np.abs(vol)) ** 2 / l2
    return np.sign(vol) * np.nan_to_num(q)


def unique_edges(tets: np.ndarray) -> np.ndarray:
    """Sorted unique edges ``(E, 2)`` (``i < j``) of a tet mesh."""
    t = np.asarray(tets)
    e = np.sort(t[:, _TET_EDGES].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def _all_faces(tets: np.ndarray):
    t = np.asarray(tets)
    faces = t[:, _TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces, inverse.reshape(-1), counts


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary triangles (faces of exactly one tet), outward-oriented for positive tets.

    Returns:
        ``(faces (F, 3), owner (F,))``: node indices of each face and the tet it belongs to.
    """
    faces, inverse, counts = _all_faces(tets)
    once = counts[inverse] == 1
    owner = np.repeat(np.arange(len(tets)), 4)[once]
    return faces[once], owner


# -------------------------------------------------------------------------- findings
@dataclasses.dataclass(frozen=True)
class Finding:
    """One validation finding.

    Attributes:
        severity: ``"error"``, ``"warning"`` or ``"note"``.
        kind: the error or warning class that describes it (e.g. ``InvertedElementError``).
        message: what is wrong, citing node or element indices.
        indices: the offending node or element indices.
    """

    severity: str
    kind: type
    message: str
    indices: tuple[int, ...] = ()

    def to_dict(self) -> dict:
        return {"severity": self.severity, "kind": self.kind.__name__, "message": self.message, "count": len(self.indices)}


def validate_arrays(
    points: np.ndarray,
    tets: np.ndarray,
    *,
    volume_tolerance: float = 1e-8,
    orientation: str = "strict",
) -> list[Finding]:
    """Check a tet mesh and return every finding (nothing is raised).

    Checks, in order: empty mesh; non-finite coordinates; node indices out of range;
    tets with repeated nodes; duplicate tets; inverted tets (signed volume < -tol) and
    degenerate tets (``|V| <= tol``), where ``tol = volume_tolerance * L^3`` and ``L`` is
    the median edge length; unused nodes (warning); boundary edges not shared by exactly
    two boundary faces, or faces shared by more than two tets (non-manifold, warning).

    Args:
        orientation: ``"strict"`` reports negatively oriented tets as inverted
            (:class:`InvertedElementError`); ``"any"`` accepts either node ordering (for
            reference meshes from tools that do not orient tets; :func:`read_mesh`
            renumbers them) and reports only a note.
    """
    pts = np.asarray(points, dtype=float)
    t = np.asarray(tets)
    out: list[Finding] = []
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        return [Finding("error", EmptyMeshError, f"points must be a non-empty (N, 3) array, got shape {pts.shape}")]
    if t.ndim != 2 or t.shape[1] != 4 or len(t) == 0:
        return [Finding("error", EmptyMeshError, f"tets must be a non-empty (M, 4) integer array, got shape {t.shape}")]
    if not np.issubdtype(t.dtype, np.integer):
        return [Finding("error", IndexOutOfRangeError, f"tets must hold integer node indices, got dtype {t.dtype}")]
    bad_nodes = np.flatnonzero(~np.all(np.isfinite(pts), axis=1))
    if bad_nodes.size:
        out.append(Finding("error", NonFiniteCoordinatesError, f"{bad_nodes.size} node(s) have NaN or infinite coordinates: nodes {_cite(bad_nodes)}", tuple(bad_nodes)))
    bad_idx = np.flatnonzero(np.any((t < 0) | (t >= len(pts)), axis=1))
    if bad_idx.size:
        out.append(Finding("error", IndexOutOfRangeError, f"{bad_idx.size} tet(s) reference node indices outside [0, {len(pts)}): elements {_cite(bad_idx)}", tuple(bad_idx)))
        return out  # geometry cannot be evaluated
    s = np.sort(t, axis=1)
    repeated = np.flatnonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))
    if repeated.size:
        out.append(Finding("error", DegenerateElementError, f"{repeated.size} tet(s) repeat a node: elements {_cite(repeated)}", tuple(repeated)))
    _, first, inverse = np.unique(s, axis=0, return_index=True, return_inverse=True)
    dup = np.flatnonzero(first[inverse.reshape(-1)] != np.arange(len(t)))
    if dup.size:
        out.append(Finding("error", DuplicateElementError, f"{dup.size} tet(s) duplicate an earlier tet's nodes: elements {_cite(dup)} (first copies {_cite(first[inverse.reshape(-1)[dup]])})", tuple(dup)))
    if not bad_nodes.size:
        e = unique_edges(t)
        lengths = np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1)
        scale = float(np.median(lengths)) if lengths.size else 0.0
        tol = volume_tolerance * scale**3
        vol = signed_volumes(pts, t)
        rep = np.zeros(len(t), dtype=bool)
        rep[repeated] = True
        degenerate = np.flatnonzero((np.abs(vol) <= tol) & ~rep)
        inverted = np.flatnonzero(vol < -tol)
        if degenerate.size:
            out.append(Finding("error", DegenerateElementError, f"{degenerate.size} tet(s) have |volume| <= {tol:.3g} m^3 ({volume_tolerance:g} x median edge^3): elements {_cite(degenerate)}", tuple(degenerate)))
        if inverted.size:
            if orientation == "strict":
                out.append(Finding("error", InvertedElementError, f"{inverted.size} tet(s) are inverted (negative signed volume): elements {_cite(inverted)}; if the mesher uses the opposite node ordering, read it with reorient=True (CLI: --reorient)", tuple(inverted)))
            else:
                out.append(Finding("note", InvertedElementError, f"{inverted.size} tet(s) have negative node ordering and are renumbered to positive orientation: elements {_cite(inverted)}", tuple(inverted)))
    used = np.zeros(len(pts), dtype=bool)
    used[t.reshape(-1)] = True
    unused = np.flatnonzero(~used)
    if unused.size:
        out.append(Finding("warning", UnusedNodesWarning, f"{unused.size} node(s) belong to no tet: nodes {_cite(unused)}", tuple(unused)))
    faces, inverse, counts = _all_faces(t)
    over = np.flatnonzero(counts > 2)
    if over.size:
        out.append(Finding("warning", NonManifoldSurfaceWarning, f"{over.size} face(s) are shared by more than two tets (overlapping elements)", tuple(over)))
    bfaces = faces[counts[inverse] == 1]
    if len(bfaces):
        be = np.sort(bfaces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
        uniq, ecount = np.unique(be, axis=0, return_counts=True)
        nm = uniq[ecount != 2]
        if len(nm):
            nodes = np.unique(nm)
            out.append(Finding("warning", NonManifoldSurfaceWarning, f"{len(nm)} surface edge(s) are not shared by exactly two boundary faces (non-manifold surface) at nodes {_cite(nodes)}", tuple(nodes)))
    return out


def _raise_findings(findings: Sequence[Finding], stacklevel: int = 3) -> None:
    errors = [f for f in findings if f.severity == "error"]
    for f in findings:
        if f.severity == "warning":
            warnings.warn(f.message, f.kind, stacklevel=stacklevel)
    if errors:
        first = errors[0]
        more = f" (and {len(errors) - 1} more problem(s): " + "; ".join(e.message for e in errors[1:]) + ")" if len(errors) > 1 else ""
        raise first.kind(first.message + more, first.indices)


# ---------------------------------------------------------------------------- lattice
class CubeLattice(eqx.Module):
    """Cube-lattice spring topology of a structured specimen (DESIGN.md §3.1).

    Each cube has springs on its 12 edges and on both diagonals of its 6 faces. Springs
    shared by neighbouring cubes are stored once; ``multiplicity`` counts the cubes holding
    each one (an interior edge 4, a boundary edge 2 or 1, an interior face diagonal 2, a
    boundary face diagonal 1), so a per-cube spring constant ``k`` assembles to ``m k``.

    Attributes:
        cubes: ``(C, 8)`` node indices; local vertex ``v = bx + 2 by + 4 bz``.
        springs: ``(S, 2)`` unique springs (node pairs, ``i < j``).
        spring_kind: ``(S,)`` 0 for a cube edge, 1 for a face diagonal.
        multiplicity: ``(S,)`` number of cubes holding each spring.
        cube_springs: ``(C, 24)`` indices into ``springs``: the 12 edges, then 12 diagonals.
        cell_size: ``(C, 3)`` cube edge lengths ``(hx, hy, hz)`` [m].
        cube_region_ids: ``(C,)`` region of each cube.
    """

    cubes: np.ndarray
    springs: np.ndarray
    spring_kind: np.ndarray
    multiplicity: np.ndarray
    cube_springs: np.ndarray
    cell_size: np.ndarray
    cube_region_ids: np.ndarray

    @property
    def n_cubes(self) -> int:
        return int(self.cubes.shape[0])

    @property
    def n_springs(self) -> int:
        return int(self.springs.shape[0])


def _build_lattice(cubes: np.ndarray, points: np.ndarray, cube_region_ids: np.ndarray) -> CubeLattice:
    pairs = np.concatenate([_CUBE_EDGES, _CUBE_DIAGONALS])  # (24, 2)
    glob = np.sort(cubes[:, pairs], axis=2).reshape(-1, 2)
    springs, inverse = np.unique(glob, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    kind = np.zeros(len(springs), dtype=np.int8)
    kind[inverse.reshape(-1, 24)[:, 12:].reshape(-1)] = 1
    cell = points[cubes[:, 7]] - points[cubes[:, 0]]
    return CubeLattice(
        cubes=cubes.astype(np.int32),
        springs=springs.astype(np.int32),
        spring_kind=kind,
        multiplicity=np.bincount(inverse, minlength=len(springs)).astype(np.int32),
        cube_springs=inverse.reshape(-1, 24).astype(np.int32),
        cell_size=cell,
        cube_region_ids=cube_region_ids.astype(np.int32),
    )


# ---------------------------------------------------------------------------- TetMesh
class TetMesh(eqx.Module):
    """A tetrahedral mesh with regions, fields and (for structured specimens) a spring lattice.

    A pytree (equinox Module). ``points`` is the differentiable leaf; the index arrays are
    NumPy arrays computed at construction.

    Attributes:
        points: ``(N, 3)`` node coordinates [m].
        tets: ``(M, 4)`` positively oriented tetrahedra (node indices).
        region_ids: ``(M,)`` region index of each tet, in ``[0, len(region_names))``.
        region_names: name of each region (static).
        edges: ``(E, 2)`` unique tet edges.
        boundary_faces: ``(F, 3)`` outward-oriented boundary triangles.
        boundary_face_tets: ``(F,)`` the tet each boundary face belongs to.
        point_data: per-node fields, each with leading dimension ``N``.
        cell_data: per-tet fields, each with leading dimension ``M``.
        lattice: :class:`CubeLattice` for structured specimens, else ``None``.
    """

    points: Any
    tets: np.ndarray
    region_ids: np.ndarray
    region_names: tuple[str, ...] = eqx.field(static=True)
    edges: np.ndarray
    boundary_faces: np.ndarray
    boundary_face_tets: np.ndarray
    point_data: dict
    cell_data: dict
    lattice: CubeLattice | None

    def __init__(
        self,
        points,
        tets,
        region_ids=None,
        region_names: Sequence[str] | None = None,
        *,
        point_data: dict | None = None,
        cell_data: dict | None = None,
        lattice: CubeLattice | None = None,
        validate: bool = True,
        volume_tolerance: float = 1e-8,
    ):
        """Build a mesh and compute its topology.

        Args:
            points: ``(N, 3)`` coordinates [m].
            tets: ``(M, 4)`` node indices, positively oriented.
            region_ids: ``(M,)`` region of each tet (default all 0).
            region_names: names of the regions (default ``region_0``, ...).
            point_data, cell_data: named fields (leading dimension N or M).
            lattice: cube-lattice springs (set by the structured generators).
            validate: run :func:`validate_arrays` and raise the first error (warnings are
                emitted as Python warnings).
            volume_tolerance: degenerate-volume tolerance relative to (median edge)^3.
        """
        pts = np.asarray(points, dtype=float)
        t = np.asarray(tets)
        if validate:
            _raise_findings(validate_arrays(pts, t, volume_tolerance=volume_tolerance))
        t = t.astype(np.int32)
        rid = np.zeros(len(t), dtype=np.int32) if region_ids is None else np.asarray(region_ids).astype(np.int32).reshape(-1)
        if rid.shape != (len(t),):
            raise MeshError(f"region_ids must have one entry per tet ({len(t)}), got shape {rid.shape}")
        if len(rid) and rid.min() < 0:
            raise MeshError(f"region_ids must be >= 0: elements {_cite(np.flatnonzero(rid < 0))}")
        n_regions = int(rid.max()) + 1 if len(rid) else 1
        names = tuple(region_names) if region_names is not None else tuple(f"region_{i}" for i in range(n_regions))
        if len(names) < n_regions:
            raise MeshError(f"{len(names)} region name(s) for region ids up to {n_regions - 1}")
        if len(set(names)) != len(names):
            raise MeshError(f"region names repeat: {list(names)}")
        pd = {str(k): np.asarray(v) for k, v in (point_data or {}).items()}
        cd = {str(k): np.asarray(v) for k, v in (cell_data or {}).items()}
        for k, v in pd.items():
            if v.shape[:1] != (len(pts),):
                raise MeshError(f"point field {k!r} has shape {v.shape}; its first dimension must be the node count {len(pts)}")
        for k, v in cd.items():
            if v.shape[:1] != (len(t),):
                raise MeshError(f"cell field {k!r} has shape {v.shape}; its first dimension must be the tet count {len(t)}")
        self.points = pts
        self.tets = t
        self.region_ids = rid
        self.region_names = names
        self.edges = unique_edges(t).astype(np.int32)
        bf, owner = boundary_faces(t)
        self.boundary_faces = bf.astype(np.int32)
        self.boundary_face_tets = owner.astype(np.int32)
        self.point_data = pd
        self.cell_data = cd
        self.lattice = lattice

    # ------------------------------------------------------------------ properties
    @property
    def n_nodes(self) -> int:
        return int(np.shape(self.points)[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def volumes(self) -> np.ndarray:
        """Signed volume of each tet [m^3]."""
        return signed_volumes(np.asarray(self.points), self.tets)

    def quality(self) -> np.ndarray:
        """Mean-ratio quality of each tet (1 = regular, negative = inverted)."""
        return mean_ratio_quality(np.asarray(self.points), self.tets)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lower, upper)`` [m]."""
        p = np.asarray(self.points)
        return p.min(axis=0), p.max(axis=0)

    def region_volumes(self) -> dict[str, float]:
        """Total volume of each region [m^3]."""
        v = self.volumes()
        return {name: float(v[self.region_ids == i].sum()) for i, name in enumerate(self.region_names)}

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Surface triangle mesh: ``(node_ids (K,), triangles (F, 3))`` with triangles indexing ``node_ids``."""
        return surface(self)

    def validate(self, *, volume_tolerance: float = 1e-8) -> list[Finding]:
        """All validation findings for the current coordinates (see :func:`validate_arrays`)."""
        return validate_arrays(np.asarray(self.points), self.tets, volume_tolerance=volume_tolerance)

    def with_points(self, points) -> "TetMesh":
        """Same topology, new coordinates (e.g. a deformed configuration); not re-validated."""
        return eqx.tree_at(lambda m: m.points, self, points)


def surface(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """Surface of a mesh as ``(node_ids, triangles)``; triangles index into ``node_ids``."""
    nodes, local = np.unique(mesh.boundary_faces, return_inverse=True)
    return nodes.astype(np.int32), local.reshape(-1, 3).astype(np.int32)


# -------------------------------------------------------------------------- generators
def _as3(v, what: str, kind=float) -> tuple:
    arr = np.atleast_1d(np.asarray(v, dtype=float))
    if arr.size == 1:
        arr = np.repeat(arr, 3)
    if arr.shape != (3,):
        raise MeshError(f"{what} must be one number or three, got {v!r}")
    if kind is int:
        if not np.all(arr == np.round(arr)) or np.any(arr < 1):
            raise MeshError(f"{what} must be positive whole numbers of cells, got {v!r}")
        return tuple(int(a) for a in arr)
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise MeshError(f"{what} must be positive finite lengths in metres, got {v!r}")
    return tuple(float(a) for a in arr)


def structured_grid(
    xs,
    ys,
    zs,
    *,
    cube_region_ids=None,
    region_names: Sequence[str] | None = None,
) -> TetMesh:
    """A rectilinear grid of boxes, each split into 6 tets (Freudenthal split along its 0-7 diagonal).

    The split is conforming: every interior face is shared by exactly two tets. The mesh
    carries the :class:`CubeLattice` of the boxes.

    Args:
        xs, ys, zs: strictly increasing node coordinates along each axis [m].
        cube_region_ids: ``(nz, ny, nx)`` or flat region id per box (x fastest).
        region_names: names of the regions.
    """
    axes = []
    for name, c in (("xs", xs), ("ys", ys), ("zs", zs)):
        c = np.asarray(c, dtype=float).reshape(-1)
        if c.size < 2 or not np.all(np.isfinite(c)) or not np.all(np.diff(c) > 0):
            raise MeshError(f"{name} must be at least two strictly increasing finite coordinates, got {c!r}")
        axes.append(c)
    xs, ys, zs = axes
    nx, ny, nz = len(xs) - 1, len(ys) - 1, len(zs) - 1
    Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
    points = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def node(i, j, k):
        return i + (nx + 1) * (j + (ny + 1) * k)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    cubes = np.stack([node(i + c[0], j + c[1], k + c[2]) for c in _CUBE_CORNERS], axis=1)
    tets = cubes[:, _KUHN_TETS].reshape(-1, 4)
    neg = signed_volumes(points, tets) < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    n_cubes = len(cubes)
    cid = np.zeros(n_cubes, dtype=np.int32) if cube_region_ids is None else np.asarray(cube_region_ids).reshape(-1).astype(np.int32)
    if cid.shape != (n_cubes,):
        raise MeshError(f"cube_region_ids must have {n_cubes} entries, got {cid.shape}")
    lattice = _build_lattice(cubes, points, cid)
    return TetMesh(points, tets, np.repeat(cid, 6), region_names, lattice=lattice)


def graded_cells(length: float, first: float, core: float, growth: float) -> int:
    """Cells of :func:`graded_axis` over ``length`` [m]: ``core / first`` uniform ones plus the
    fewest geometric ones (ratio <= ``growth``) that reach ``length``."""
    n_core = max(1, int(round(core / first)))
    rest = length - n_core * first
    if rest <= first:
        return n_core + 1
    return n_core + int(math.ceil(math.log1p(rest * (growth - 1.0) / first) / math.log(growth) - 1e-9))


def graded_axis(length: float, cells: int, first: float | None = None, *, core: float | None = None) -> np.ndarray:
    """Node coordinates ``0 .. length`` [m] with ``cells`` cells growing geometrically from
    ``first`` [m] (uniform when ``first`` is None or ``>= length / cells``).

    With ``core`` [m], cells of size ``first`` are kept uniform up to ``core`` (rounded to
    whole cells) and grow geometrically only beyond it: a contact region that widens with
    depth stays resolved (linear tets need about ten cells across the contact radius).
    """
    length, cells = float(length), int(cells)
    if not (length > 0 and cells >= 1):
        raise ModelError(f"an axis needs a positive length and >= 1 cell, got {length}, {cells}")
    if core is not None and first is not None and 0 < core < length:
        n_core = max(1, int(round(core / first)))
        if n_core >= cells:
            raise ModelError(f"a uniform core of {core:g} m with cells of {first:g} m needs {n_core} cells; give more than that ({cells} given)")
        c = n_core * first
        if c >= length:
            return np.linspace(0.0, length, cells + 1)
        outer = graded_axis(length - c, cells - n_core, first)
        return np.concatenate([np.linspace(0.0, c, n_core + 1), c + outer[1:]])
    if first is None or first >= length / cells or cells == 1:
        # (one cell spans the length whatever its first size: brentq would have no root)
        return np.linspace(0.0, length, cells + 1)
    if first <= 0:
        raise ModelError(f"first cell size must be > 0 m, got {first}")
    from scipy.optimize import brentq

    # the sum first (q^n - 1)/(q - 1) exceeds first q^(n-1): the root lies below (length/first)^(1/(n-1))
    hi = min(1e3, 1.0001 * (length / first) ** (1.0 / (cells - 1)))
    q = brentq(lambda q: first * (q**cells - 1.0) / (q - 1.0) - length, 1.0 + 1e-12, hi)
    x = np.concatenate([[0.0], np.cumsum(first * q ** np.arange(cells))])
    x[-1] = length
    return x


def refined_axis(length: float, cells: int, center: float, first: float, *, core: float | None = None) -> np.ndarray:
    """Node coordinates ``0 .. length`` [m] with ``cells`` cells, finest (``first`` [m]) at
    ``center`` [m] and growing geometrically towards both ends (:func:`graded_axis` on each
    side; with ``core`` [m] uniform within ``core`` of ``center``). The cells are shared between
    the two sides in proportion to their lengths (at least one each); a ``center`` on an end
    grades one side only."""
    L, n, c = float(length), int(cells), float(center)
    if not (np.isfinite(c) and -1e-12 * L <= c <= L * (1 + 1e-12)):
        raise MeshError(f"the refinement centre {center!r} m must lie in [0, {L:g}] m")
    tol = 1e-9 * L
    sides = [s for s in (c, L - c) if s > tol]
    if core is not None and any(core >= s for s in sides):
        raise MeshError(f"core {core:g} m reaches past a side of the axis (the refinement line at {c:g} m of {L:g} m): "
                        "give a core shorter than the distance to each side it grades")
    if c <= tol:
        return graded_axis(L, n, first, core=core)
    if c >= L - tol:
        return L - graded_axis(L, n, first, core=core)[::-1]
    if n < 2:
        raise MeshError(f"refining about an interior point needs at least two cells along the axis, got {n}")
    n_left = min(n - 1, max(1, int(round(n * c / L))))
    left = c - graded_axis(c, n_left, first, core=core)[::-1]
    right = c + graded_axis(L - c, n - n_left, first, core=core)
    x = np.concatenate([left, right[1:]])
    x[0], x[-1] = 0.0, L
    return x


def node_patches(tets: np.ndarray, tet_regions: np.ndarray):
    """The node patches of the nodal volumetric term: one per (node, region) pair.

    A patch is the set of tets of one region around one node; its nodes are those tets' nodes.
    Patches are padded to fixed widths: extra node slots repeat the patch's own node, extra
    tet slots point to tet 0 with ``valid = False``.

    Args:
        tets: ``(M, 4)`` tetrahedra; tet_regions: ``(M,)`` region of each.

    Returns:
        ``(nodes (P, k), tet_ids (P, T), local_tets (P, T, 4), valid (P, T), regions (P,))``:
        patch node indices (the patch's own node first), the global tet of each slot, its
        nodes as indices into the patch's nodes, whether the slot is a real tet, the region.
    """
    tets = np.asarray(tets, dtype=np.int64)
    reg = np.asarray(tet_regions, dtype=np.int64)
    M = tets.shape[0]
    R = int(reg.max()) + 1 if M else 1
    node = tets.reshape(-1)
    tet = np.repeat(np.arange(M), 4)
    key = node * R + reg[tet]
    order = np.argsort(key, kind="stable")
    key, tet = key[order], tet[order]
    patch_keys, start, count = np.unique(key, return_index=True, return_counts=True)
    P, T = patch_keys.size, int(count.max())
    slot = np.arange(key.size) - np.repeat(start, count)
    pid = np.repeat(np.arange(P), count)
    tet_ids = np.zeros((P, T), dtype=np.int64)
    valid = np.zeros((P, T), dtype=bool)
    tet_ids[pid, slot], valid[pid, slot] = tet, True
    own = patch_keys // R
    cand = tets[tet_ids]  # (P, T, 4)
    cand = np.where(valid[:, :, None], cand, own[:, None, None]).reshape(P, 4 * T)
    cand = np.where(cand == own[:, None], -1, cand)  # the own node sorts first
    srt = np.sort(cand, axis=1)
    new = np.ones_like(srt, dtype=bool)
    new[:, 1:] = srt[:, 1:] != srt[:, :-1]
    k = int(new.sum(axis=1).max())
    col = np.cumsum(new, axis=1) - 1
    nodes = np.repeat(own[:, None], k, axis=1)
    rows = np.nonzero(new)
    vals = srt[rows]
    nodes[rows[0], col[rows]] = np.where(vals < 0, own[rows[0]], vals)
    # local index of every candidate: its rank among the row's distinct values
    pos = np.empty_like(col)
    np.put_along_axis(pos, np.argsort(cand, axis=1, kind="stable"), col, axis=1)
    local = pos.reshape(P, T, 4)
    local = np.where(valid[:, :, None], local, 0)
    return nodes.astype(np.int32), tet_ids.astype(np.int32), local.astype(np.int32), valid, (patch_keys % R).astype(np.int32)


def block(size, resolution, *, origin=(0.0, 0.0, 0.0), region_name: str = "tissue") -> TetMesh:
    """A rectangular block of ``resolution`` cubes split into 6 tets each.

    Args:
        size: ``(Lx, Ly, Lz)`` or one edge length [m].
        resolution: ``(nx, ny, nz)`` or one number of cells per axis.
        origin: lower corner [m].
        region_name: name of its single region.

    Example: ``block((0.01, 0.01, 0.005), (10, 10, 5))`` is a 10 x 10 x 5 mm block of 1 mm cubes.
    """
    L = _as3(size, "size")
    n = _as3(resolution, "resolution", int)
    o = np.asarray(origin, dtype=float).reshape(3)
    return structured_grid(*(o[a] + np.linspace(0.0, L[a], n[a] + 1) for a in range(3)), region_names=(region_name,))


def curved_top(mesh: TetMesh, radius: float, *, shape: str = "sphere", center=(0.0, 0.0)) -> TetMesh:
    """A block whose flat top ``z = max z`` is bent onto a convex sphere or cylinder of ``radius`` [m].

    Each node moves along z by the sag of the curved top above it times its height fraction,
    ``z' = z + s(x, y) (z - z_min) / (z_max - z_min)``, with ``s = sqrt(R^2 - rho^2) - R`` and
    ``rho`` the distance from the vertical axis through ``center`` [m] (``shape="sphere"``: a
    dome whose apex is at ``(center, z_max)``) or from the vertical plane ``y = center[1]``
    (``shape="cylinder"``: a cylinder along x, its crest the line ``y = center[1]``). The base
    stays flat and the topology, regions and fields are kept. Meant for curved test specimens
    (a dome or a cylinder's outer face on a block, e.g. from :func:`block` or
    :func:`~difftissue.scenarios.indentation_block`).

    Raises:
        MeshError: the top reaches beyond the sphere or cylinder (``rho >= R``) or the sag is
            not smaller than the block's height (the cells would fold).
    """
    R = float(radius)
    if not np.isfinite(R) or R <= 0:
        raise MeshError(f"curved_top radius must be a positive finite number [m], got {radius!r}")
    if shape not in ("sphere", "cylinder"):
        raise MeshError(f"curved_top shape must be 'sphere' or 'cylinder', got {shape!r}")
    p = np.array(mesh.points, dtype=float)
    cx, cy = (float(v) for v in center)
    rho = np.hypot(p[:, 0] - cx, p[:, 1] - cy) if shape == "sphere" else np.abs(p[:, 1] - cy)
    if np.any(rho >= R):
        raise MeshError(f"the top reaches {rho.max():.6g} m from the {shape}'s axis, beyond its radius {R:.6g} m")
    z0, z1 = p[:, 2].min(), p[:, 2].max()
    sag = np.sqrt(R * R - rho * rho) - R
    if np.min(sag) <= -(z1 - z0):
        raise MeshError(f"the sag of the curved top ({-np.min(sag):.6g} m) must be smaller than the block's height ({z1 - z0:.6g} m)")
    p[:, 2] = p[:, 2] + sag * (p[:, 2] - z0) / (z1 - z0)
    return TetMesh(p, mesh.tets, mesh.region_ids, mesh.region_names, point_data=mesh.point_data, cell_data=mesh.cell_data)


def default_skin_layers() -> list[tuple[str, float, Material]]:
    """Illustrative three-layer skin, outermost first: ``(name, thickness [m], Material)``.

    Epidermis 0.1 mm (E = 1 MPa), dermis 1.5 mm (E = 200 kPa), hypodermis 5 mm (E = 5 kPa);
    nu = 0.48-0.49, density 1100 / 1100 / 970 kg/m^3. Dermis and hypodermis sit inside the
    literature ranges collected in DESIGN.md §3.7 (dermis 0.1-1 MPa at low strain, hypodermis a
    few kPa); the epidermis is simply taken stiffer than the dermis. They are a starting point
    to be fitted, not measured values.
    """
    return [
        ("epidermis", 1.0e-4, Material(1.0e6, 0.48, density=1100.0)),
        ("dermis", 1.5e-3, Material(2.0e5, 0.48, density=1100.0)),
        ("hypodermis", 5.0e-3, Material(5.0e3, 0.49, density=970.0)),
    ]


class Specimen(eqx.Module):
    """A mesh together with one :class:`Material` per region (in region-id order)."""

    mesh: TetMesh
    materials: tuple[Material, ...]

    def __check_init__(self):
        if len(self.materials) != len(self.mesh.region_names):
            raise MaterialError(f"{len(self.materials)} material(s) for {len(self.mesh.region_names)} region(s) {list(self.mesh.region_names)}")

    def material(self, region: str) -> Material:
        """Material of a region by name."""
        try:
            return self.materials[self.mesh.region_names.index(region)]
        except ValueError:
            raise MaterialError(f"no region {region!r}; regions are {list(self.mesh.region_names)}") from None

    def cell_fields(self) -> dict[str, np.ndarray]:
        """Per-tet material fields (SI) for export: ``youngs_modulus``, ``poisson_ratio``, ..."""
        mats = self.materials
        if any(m.pre_stretch_y is not None for m in mats):  # a pre_stretch_y column, = pre_stretch where none is given
            mats = [m if m.pre_stretch_y is not None else m.replace(pre_stretch_y=m.pre_stretch) for m in mats]
        table = np.array([[float(v) for v in m.to_dict().values()] for m in mats])
        keys = list(mats[0].to_dict())
        return {k: table[self.mesh.region_ids, c] for c, k in enumerate(keys)}


def layered_skin(
    layers: Sequence[tuple] | None = None,
    size=(0.02, 0.02),
    resolution=(20, 20),
    *,
    cell_size: float | None = None,
    grading=None,
    refine: float | None = None,
    refine_at=None,
    core=None,
) -> Specimen:
    """A layered skin specimen (epidermis / dermis / hypodermis style), one region per layer.

    The skin surface is the plane ``z = total thickness``; the base of the deepest layer is
    ``z = 0``. Layers are listed from the outer surface inwards.

    Args:
        layers: ``[(name, thickness [m], material), ...]`` or with a fourth entry, the number
            of cells through that layer. ``material`` is a :class:`Material` or a dict of its
            fields. Default: :func:`default_skin_layers`.
        size: lateral size ``(Lx, Ly)`` [m].
        resolution: lateral number of cells ``(nx, ny)``.
        cell_size: target cell height [m] for layers without a cell count; default the mean
            lateral cell size. Each layer gets ``max(1, floor(thickness / cell_size + 1/2))`` cells.
        grading: ``{layer name: ratio}``: the cells through that layer grow geometrically, each
            ``ratio`` times as high as the cell above it (``ratio > 1``: finest at the layer's
            top, e.g. under the skin surface; ``< 1``: finest at its base; 1: uniform). The
            heights ``h_k = h_0 ratio^k`` (k = 0 at the top) fill the thickness exactly. A
            layer needs at least two cells to be graded.
        refine: lateral refinement: the cells are ``refine`` [m] wide at the lines
            ``x = refine_at[0]`` and ``y = refine_at[1]`` and grow geometrically away from them
            (:func:`refined_axis`; e.g. around a cut), keeping ``resolution`` cells per axis.
        refine_at: ``(x, y)`` [m] of the refinement lines (default the centre of the top).
        core: ``w`` or ``(wx, wy)`` [m]: the cells stay ``refine`` wide within this distance
            of the lines (e.g. half the cut length along the cut) and grow only beyond it.

    Returns:
        A :class:`Specimen` whose mesh has region names = layer names (region id = layer
        index, outermost 0) and a :class:`CubeLattice`.
    """
    layers = list(default_skin_layers() if layers is None else layers)
    if not layers:
        raise MeshError("layered_skin needs at least one layer")
    Lx, Ly = (float(v) for v in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    nx, ny = (int(v) for v in np.broadcast_to(np.asarray(resolution), (2,)))
    if not (Lx > 0 and Ly > 0):
        raise MeshError(f"size must be positive lateral lengths in metres, got {size!r}")
    if nx < 1 or ny < 1:
        raise MeshError(f"resolution must be positive numbers of cells, got {resolution!r}")
    if refine is None:
        if refine_at is not None or core is not None:
            raise MeshError("refine_at and core need refine (the lateral cell size at the refinement lines)")
        xs, ys = np.linspace(0, Lx, nx + 1), np.linspace(0, Ly, ny + 1)
    else:
        if not (np.isfinite(float(refine)) and float(refine) > 0):
            raise MeshError(f"refine must be a positive lateral cell size in metres, got {refine!r}")
        at = (0.5 * Lx, 0.5 * Ly) if refine_at is None else tuple(float(v) for v in np.asarray(refine_at, dtype=float).reshape(-1))
        if len(at) != 2:
            raise MeshError(f"refine_at must be a point (x, y) in metres, got {refine_at!r}")
        cores = (None, None) if core is None else tuple(float(v) for v in np.broadcast_to(np.asarray(core, dtype=float), (2,)))
        if core is not None and not all(np.isfinite(c) and c > 0 for c in cores):
            raise MeshError(f"core must be one or two positive lengths in metres, got {core!r}")
        xs = refined_axis(Lx, nx, at[0], float(refine), core=cores[0])
        ys = refined_axis(Ly, ny, at[1], float(refine), core=cores[1])
    h = float(cell_size) if cell_size is not None else 0.5 * (Lx / nx + Ly / ny)
    names, mats, thick, ncells = [], [], [], []
    for entry in layers:
        if not isinstance(entry, (tuple, list)) or len(entry) not in (3, 4):
            raise MeshError(f"each layer must be (name, thickness, material[, cells]), got {entry!r}")
        name, t, mat = entry[0], float(entry[1]), entry[2]
        if not (np.isfinite(t) and t > 0):
            raise MeshError(f"layer {name!r}: thickness must be > 0 m, got {entry[1]!r}")
        if isinstance(mat, dict):
            mat = Material(**mat)
        if not isinstance(mat, Material):
            raise MaterialError(f"layer {name!r}: material must be a Material or a dict of its fields, got {type(mat).__name__}")
        n = int(entry[3]) if len(entry) == 4 else max(1, int(np.floor(t / h + 0.5)))
        if n < 1:
            raise MeshError(f"layer {name!r}: needs at least one cell through its thickness")
        names.append(str(name))
        mats.append(mat)
        thick.append(t)
        ncells.append(n)
    ratios = _layer_grading(grading, names, ncells)
    # Stack from the base (deepest layer, z = 0) upwards.
    zs = [0.0]
    cube_layer = []
    for idx in reversed(range(len(layers))):
        base = zs[-1]
        zs.extend(base + layer_node_heights(thick[idx], ncells[idx], ratios[idx])[1:])
        cube_layer.extend([idx] * ncells[idx])
    cube_ids = np.repeat(np.asarray(cube_layer, dtype=np.int32), nx * ny)
    mesh = structured_grid(xs, ys, np.asarray(zs), cube_region_ids=cube_ids, region_names=names)
    return Specimen(mesh, tuple(mats))


def layer_node_heights(thickness: float, cells: int, ratio: float = 1.0) -> np.ndarray:
    """Node heights ``0 .. thickness`` [m] above the base of a layer of ``cells`` cells whose
    heights grow by ``ratio`` from the top down: the cell at the top is ``h_0 = thickness
    (ratio - 1) / (ratio^cells - 1)`` high, the one below it ``h_0 ratio``, ... (uniform for
    ``ratio = 1``). The end points are exact (0 and ``thickness``)."""
    t, n, r = float(thickness), int(cells), float(ratio)
    if not (np.isfinite(t) and t > 0) or n < 1:
        raise MeshError(f"a layer needs a positive thickness and >= 1 cell, got {thickness!r}, {cells!r}")
    if not (np.isfinite(r) and r > 0):
        raise MeshError(f"grading ratio must be a positive finite number (1 = uniform), got {ratio!r}")
    if r == 1.0:
        return t * np.arange(n + 1) / n
    h = r ** np.arange(n)  # from the top down, h_0 = 1
    depth = np.concatenate([[0.0], np.cumsum(h)]) / h.sum()  # 0 .. 1 from the top
    z = t * (1.0 - depth[::-1])  # from the base up
    z[0], z[-1] = 0.0, t
    return z


def _layer_grading(grading, names: list[str], ncells: list[int]) -> list[float]:
    """The grading ratio of each layer from ``layered_skin``'s ``grading`` mapping."""
    ratios = [1.0] * len(names)
    if grading is None:
        return ratios
    if not isinstance(grading, dict):
        raise MeshError(f"grading must be a mapping {{layer name: ratio}}, got {grading!r}")
    for name, r in grading.items():
        if name not in names:
            raise MeshError(f"grading names layer {name!r}; the layers are {names}")
        i = names.index(name)
        try:
            r = float(r)
        except (TypeError, ValueError):
            raise MeshError(f"layer {name!r}: grading ratio must be a positive number, got {grading[name]!r}") from None
        if not (np.isfinite(r) and r > 0):
            raise MeshError(f"layer {name!r}: grading ratio must be a positive finite number (1 = uniform), got {grading[name]!r}")
        if ncells[i] < 2 and r != 1.0:
            raise MeshError(f"layer {name!r}: grading needs at least two cells through the layer (it has {ncells[i]})")
        ratios[i] = r
    return ratios


# ------------------------------------------------------------------------------ meshio
#: Formats :func:`write_mesh` writes, by file suffix.
WRITE_FORMATS = {".vtu": "vtu", ".msh": "gmsh22", ".xdmf": "xdmf", ".mesh": "medit"}
_REGION_KEYS = ("region_id", "gmsh:physical", "medit:ref", "CellEntityIds", "cell_tags")
_SKIP_POINT_KEYS = ("gmsh:dim_tags", "medit:ref")
_SKIP_CELL_KEYS = ("gmsh:physical", "gmsh:geometrical", "medit:ref", "region_id")


def to_meshio(mesh: TetMesh, *, point_data: dict | None = None, cell_data: dict | None = None, region_key: str = "region_id", tag_offset: int = 0):
    """A ``meshio.Mesh`` of the tets with region ids, region names and fields.

    Region names go to ``field_data`` as ``{name: [tag, 3]}`` (the Gmsh convention) with
    ``tag = region_id + tag_offset``.
    """
    import meshio

    pd = {**mesh.point_data, **{k: np.asarray(v) for k, v in (point_data or {}).items()}}
    cd = {**mesh.cell_data, **{k: np.asarray(v) for k, v in (cell_data or {}).items()}}
    for k, v in pd.items():
        if v.shape[:1] != (mesh.n_nodes,):
            raise MeshError(f"point field {k!r} has shape {v.shape}; expected first dimension {mesh.n_nodes}")
    for k, v in cd.items():
        if v.shape[:1] != (mesh.n_tets,):
            raise MeshError(f"cell field {k!r} has shape {v.shape}; expected first dimension {mesh.n_tets}")
    tags = (mesh.region_ids + tag_offset).astype(np.int32)
    cells = {region_key: [tags]}
    if region_key == "gmsh:physical":
        cells["gmsh:geometrical"] = [tags]
    cells.update({k: [v] for k, v in cd.items()})
    field = {name: np.array([i + tag_offset, 3]) for i, name in enumerate(mesh.region_names)}
    return meshio.Mesh(np.asarray(mesh.points, dtype=float), [("tetra", mesh.tets)], point_data=pd, cell_data=cells, field_data=field)


def _insert_vtu_field_data(path: Path, field_data: dict[str, np.ndarray]) -> None:
    """meshio's VTU writer drops field_data (its reader reads it): add a VTK <FieldData> block."""
    if not field_data:
        return
    arrays = "".join(
        f'<DataArray type="Int64" Name="{_xml_escape(k)}" NumberOfTuples="{len(v)}" format="ascii">{" ".join(str(int(x)) for x in v)}</DataArray>'
        for k, v in field_data.items()
    )
    text = path.read_text()
    marker = "<UnstructuredGrid>"
    if marker not in text:
        raise MeshError(f"unexpected VTU layout written by meshio in {path}")
    path.write_text(text.replace(marker, f"{marker}\n<FieldData>{arrays}</FieldData>", 1))


def _xml_escape(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def write_mesh(path, mesh: TetMesh, *, point_data: dict | None = None, cell_data: dict | None = None, overwrite: bool = False) -> Path:
    """Write a mesh atomically: VTU (``.vtu``), Gmsh 2.2 binary (``.msh``), XDMF (``.xdmf``, inline XML) or Medit (``.mesh``).

    Region ids are stored as ``region_id`` cell data (VTU, XDMF), Gmsh physical tags
    ``region_id + 1`` (msh) or Medit references ``region_id + 1``. Region names are kept by
    VTU (a VTK ``FieldData`` block) and msh (physical names) only; XDMF and Medit files come
    back with ``region_<id>`` names. VTU and msh round-trip points, tets, regions and float
    fields bit-exactly; XDMF (inline XML) to ~1e-15 relative.
    An existing file is refused unless ``overwrite``.
    """
    import meshio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise MeshError(f"cannot write {path.name}: supported suffixes are {sorted(WRITE_FORMATS)}")
    fmt = WRITE_FORMATS[suffix]
    key, offset, kwargs = {
        "vtu": ("region_id", 0, {}),
        "xdmf": ("region_id", 0, {"data_format": "XML"}),
        "gmsh22": ("gmsh:physical", 1, {"binary": True}),
        "medit": ("medit:ref", 1, {}),
    }[fmt]
    m = to_meshio(mesh, point_data=point_data, cell_data=cell_data, region_key=key, tag_offset=offset)
    if fmt == "medit":
        if m.point_data or len(m.cell_data) > 1:
            raise MeshError("Medit .mesh files hold only region references; write .vtu, .xdmf or .msh to keep fields")
        m.field_data = {}
    with atomic_output(path, overwrite=overwrite) as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            meshio.write(tmp, m, file_format=fmt, **kwargs)
        if fmt == "vtu":
            _insert_vtu_field_data(tmp, m.field_data)
    return path


@dataclasses.dataclass
class _RawMesh:
    points: np.ndarray
    tets: np.ndarray
    region_ids: np.ndarray
    region_names: tuple[str, ...]
    point_data: dict
    cell_data: dict
    notes: list


def _from_meshio_raw(m, length_unit: str = "m") -> _RawMesh:
    if length_unit not in LENGTH_UNITS:
        raise MeshError(f"unknown length unit {length_unit!r}; choose one of {sorted(LENGTH_UNITS)}")
    types = [c.type for c in m.cells]
    tet_blocks = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not tet_blocks:
        quad = [t for t in types if t.startswith("tetra")]
        if quad:
            raise UnsupportedMeshError(f"the file holds {sorted(set(quad))} cells; difftissue handles linear 4-node tetrahedra only")
        raise UnsupportedMeshError(f"the file holds no tetrahedra (cell types: {sorted(set(types)) or 'none'})")
    notes = []
    others = sorted(set(types) - {"tetra"})
    if others:
        notes.append(f"ignored non-tetrahedral cells: {others}")
    tets = np.concatenate([m.cells[i].data for i in tet_blocks]).astype(np.int64)
    cd_all = {}
    for key, blocks in m.cell_data.items():
        cd_all[key] = np.concatenate([np.asarray(blocks[i]) for i in tet_blocks])
    region_key = next((k for k in _REGION_KEYS if k in cd_all), None)
    names_by_tag = {int(v[0]): str(k) for k, v in (m.field_data or {}).items() if np.size(v) >= 2 and int(np.asarray(v).reshape(-1)[1]) == 3}
    if region_key is None:
        rid = np.zeros(len(tets), dtype=np.int32)
        names = ("region_0",)
    elif region_key == "region_id":
        rid = cd_all[region_key].astype(np.int32).reshape(-1)
        n = max(int(rid.max()) + 1 if len(rid) else 1, (max(names_by_tag) + 1) if names_by_tag else 0)
        names = tuple(names_by_tag.get(i, f"region_{i}") for i in range(n))
    else:
        tags = cd_all[region_key].astype(np.int64).reshape(-1)
        all_tags = np.unique(np.concatenate([tags, np.array(sorted(names_by_tag), dtype=np.int64)]))
        rid = np.searchsorted(all_tags, tags).astype(np.int32)
        names = tuple(names_by_tag.get(int(t), f"region_{int(t)}") for t in all_tags)
        if region_key != "region_id":
            notes.append(f"regions from cell data {region_key!r} (tags {all_tags.tolist()} -> ids 0..{len(all_tags) - 1})")
    cell_data = {k: v for k, v in cd_all.items() if k not in _SKIP_CELL_KEYS and k != region_key}
    point_data = {k: np.asarray(v) for k, v in m.point_data.items() if k not in _SKIP_POINT_KEYS}
    points = np.asarray(m.points, dtype=float)
    if points.shape[1] == 2:
        raise UnsupportedMeshError("the file holds 2-D points; tetrahedral meshes need 3-D coordinates")
    points = points * LENGTH_UNITS[length_unit]
    return _RawMesh(points, tets, rid, names, point_data, cell_data, notes)


def _reorient(raw: _RawMesh) -> np.ndarray:
    vol = signed_volumes(raw.points, raw.tets)
    tets = raw.tets.copy()
    neg = vol < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return tets


def from_meshio(m, *, length_unit: str = "m", reorient: bool = False) -> TetMesh:
    """A :class:`TetMesh` from a ``meshio.Mesh`` (tetra cells only; other cells are ignored).

    Args:
        length_unit: unit of the coordinates in ``m`` (``"m"``, ``"cm"``, ``"mm"``, ``"um"``);
            converted to metres.
        reorient: renumber negatively oriented tets (for meshers that do not orient them);
            by default they are refused as inverted.
    """
    raw = _from_meshio_raw(m, length_unit)
    tets = raw.tets
    if reorient:
        _raise_findings([f for f in validate_arrays(raw.points, tets, orientation="any") if f.severity == "error"])
        tets = _reorient(raw)
    return TetMesh(raw.points, tets, raw.region_ids, raw.region_names, point_data=raw.point_data, cell_data=raw.cell_data)


def read_mesh(path, *, length_unit: str = "m", reorient: bool = False) -> TetMesh:
    """Read a tet mesh with meshio (VTU, XDMF, Gmsh msh, Medit, and other meshio formats).

    Region ids are taken from ``region_id``, ``gmsh:physical``, ``medit:ref`` or
    ``CellEntityIds`` cell data, region names from field data. See :func:`from_meshio`.
    """
    return from_meshio(_read_meshio(path), length_unit=length_unit, reorient=reorient)


def _read_meshio(path):
    import meshio

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"no such mesh file: {path}")
    captured = io.StringIO()
    try:
        # meshio prints to stderr and calls sys.exit when no reader accepts a file.
        with warnings.catch_warnings(), contextlib.redirect_stderr(captured), contextlib.redirect_stdout(captured):
            warnings.simplefilter("ignore")
            return meshio.read(path)
    except meshio.ReadError as e:
        raise MeshError(f"cannot read {path}: {e}") from None
    except (SystemExit, Exception) as e:
        detail = captured.getvalue().strip().replace("\n", " ") or f"{type(e).__name__}: {e}"
        raise MeshError(f"cannot read {path} ({detail}); check the file format and suffix") from None


def inspect_file(path, *, length_unit: str = "m", reorient: bool = False) -> tuple[TetMesh | None, list[Finding], list[str]]:
    """Read a mesh file without raising on validation problems (used by ``difftissue info``).

    Returns ``(mesh or None when it has errors, findings, notes)``.
    """
    raw = _from_meshio_raw(_read_meshio(path), length_unit)
    findings = validate_arrays(raw.points, raw.tets, orientation="any" if reorient else "strict")
    if any(f.severity == "error" for f in findings):
        return None, findings, raw.notes
    tets = _reorient(raw) if reorient else raw.tets
    mesh = TetMesh(raw.points, tets, raw.region_ids, raw.region_names, point_data=raw.point_data, cell_data=raw.cell_data, validate=False)
    return mesh, findings, raw.notes
