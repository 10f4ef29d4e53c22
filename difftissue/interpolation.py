"""Interpolation between meshes: a nodal field of one mesh evaluated at points of another.

A reference FEM solution (FEBio, Abaqus, scikit-fem) lives on the analyst's mesh, not on
the model's. :func:`interpolation_operator` locates each query point in an element of a
source mesh and returns the element's shape functions there as a precomputed sparse
operator (:class:`InterpolationOperator`: ``indices``, ``weights``), built once in NumPy /
SciPy and applied in JAX (pure, ``jit``, ``vmap``, differentiable in the nodal values).

Elements (meshio cell names, VTK node order; meshio converts Gmsh and Abaqus orders):

- ``"tetra"``: linear tetrahedron (P1), barycentric weights;
- ``"tetra10"``: quadratic tetrahedron (P2: corners 0-3, then the mid-edge nodes of
  (0,1), (1,2), (0,2), (0,3), (1,3), (2,3)); curved (isoparametric) elements are inverted
  by Newton's method;
- ``"hexahedron"``: trilinear 8-node hexahedron (nodes 0-3 the bottom face counter-clockwise,
  4-7 above them), inverted by Newton's method;
- ``"hexahedron20"``: 20-node serendipity hexahedron (VTK_QUADRATIC_HEXAHEDRON; Abaqus C3D20,
  FEBio hex20): the 8 corners, then the mid-edge nodes of (0,1), (1,2), (2,3), (3,0), (4,5),
  (5,6), (6,7), (7,4), (0,4), (1,5), (2,6), (3,7);
- ``"hexahedron27"``: 27-node triquadratic hexahedron (VTK_TRIQUADRATIC_HEXAHEDRON; FEBio
  hex27): the 20 nodes of ``hexahedron20``, then the centres of the faces xi = -1 (corners
  0,3,7,4), xi = +1 (1,2,6,5), eta = -1 (0,1,5,4), eta = +1 (3,2,6,7), zeta = -1 (0,1,2,3),
  zeta = +1 (4,5,6,7) and the body centre.

The quadratic hexahedra are isoparametric (curved edges allowed) and inverted by Newton's
method, as the trilinear one.

Interpolation is exact for fields the element reproduces: affine fields in every element
(curved isoparametric ones included); quadratic fields in ``tetra10`` (straight edges) and in
``hexahedron20`` and ``hexahedron27`` mapped affinely (parallelepipeds, mid-side nodes at the
midpoints); on axis-aligned boxes also trilinear fields in ``hexahedron``, the serendipity
space (quadratics and the cubic and quartic terms ``x^2 y``, ``x y z``, ``x^2 y z``, ...) in
``hexahedron20`` and triquadratic fields in ``hexahedron27``. On a curved element a quadratic
field is approximated, not reproduced (the map itself is quadratic).

A query point outside the source mesh by at most ``tolerance`` [m] takes the nearest element's
shape functions extrapolated to it (still exact for affine fields); farther points raise
:class:`~difftissue.errors.PointsOutsideMeshError` naming how many and how far.
"""

from __future__ import annotations

from typing import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .errors import MeshError, PointsOutsideMeshError, UnsupportedMeshError

__all__ = ["ELEMENT_NODES", "HEX27_FACES", "HEX_EDGES", "InterpolationOperator", "interpolation_operator", "node_coordinates", "shape_functions",
           "shape_gradients"]

#: Nodes per element of the element types understood (meshio names).
ELEMENT_NODES = {"tetra": 4, "tetra10": 10, "hexahedron": 8, "hexahedron20": 20, "hexahedron27": 27}
#: The hexahedra (local coordinates in ``[-1, 1]^3``).
_HEXES = ("hexahedron", "hexahedron20", "hexahedron27")
#: meshio names that mean the same element (meshio reads Abaqus C3D4H as "tetra4").
_ALIASES = {"tetra4": "tetra", "hexahedron8": "hexahedron"}
#: Local coordinates of the hexahedron's nodes (VTK order).
_HEX_NODES = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
#: Mid-edge nodes of the quadratic hexahedra (VTK order): the corners each joins.
HEX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
#: Face-centre nodes of the 27-node hexahedron (VTK order): the corners of each face.
HEX27_FACES = ((0, 3, 7, 4), (1, 2, 6, 5), (0, 1, 5, 4), (3, 2, 6, 7), (0, 1, 2, 3), (4, 5, 6, 7))
#: Local coordinates of the nodes of the 20- and 27-node hexahedra (VTK order).
_HEX20_NODES = np.vstack([_HEX_NODES, [(_HEX_NODES[a] + _HEX_NODES[b]) / 2 for a, b in HEX_EDGES]])
_HEX27_NODES = np.vstack([_HEX20_NODES, [_HEX_NODES[list(f)].mean(axis=0) for f in HEX27_FACES], [[0.0, 0.0, 0.0]]])
#: Mid-edge nodes of the 10-node tetrahedron (VTK order): the corners each joins.
_TET10_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
#: A query is inside an element when its local coordinates are inside within this margin.
_INSIDE = 1e-10
#: Candidate elements (nearest centroids) tried per query before the exhaustive search.
_CANDIDATES = 16
_NEWTON_STEPS = 30


def _canonical(cell_type: str) -> str:
    t = _ALIASES.get(cell_type, cell_type)
    if t not in ELEMENT_NODES:
        raise UnsupportedMeshError(f"cell type {cell_type!r} cannot be interpolated; supported: {sorted(ELEMENT_NODES)} (meshio names)")
    return t


# ======================================================================= shape functions
def shape_functions(cell_type: str, xi) -> np.ndarray:
    """Shape functions ``(n, k)`` of ``cell_type`` at local coordinates ``xi`` ``(n, 3)``.

    Tetrahedra: ``xi = (xi, eta, zeta)`` with the barycentric coordinates
    ``(1 - xi - eta - zeta, xi, eta, zeta)`` of corners 0-3. Hexahedra: ``xi`` in
    ``[-1, 1]^3`` (node local coordinates: :func:`node_coordinates`); ``hexahedron20`` the
    serendipity functions (corners ``(1 + xi a)(1 + eta b)(1 + zeta c)(xi a + eta b + zeta c - 2) / 8``,
    mid-edge nodes ``(1 - xi^2)(1 + eta b)(1 + zeta c) / 4`` and permutations),
    ``hexahedron27`` the products of the 1-D quadratic Lagrange polynomials. Every set sums to
    1 at any ``xi``.
    """
    t = _canonical(cell_type)
    xi = np.atleast_2d(np.asarray(xi, dtype=float))
    if t == "hexahedron":
        return np.prod(1.0 + xi[:, None, :] * _HEX_NODES[None], axis=2) / 8.0
    if t in ("hexahedron20", "hexahedron27"):
        return _quadratic_hex(t, xi)[0]
    lam = np.concatenate([1.0 - xi.sum(axis=1, keepdims=True), xi], axis=1)
    if t == "tetra":
        return lam
    corners = lam * (2.0 * lam - 1.0)
    edges = np.stack([4.0 * lam[:, a] * lam[:, b] for a, b in _TET10_EDGES], axis=1)
    return np.concatenate([corners, edges], axis=1)


def shape_gradients(cell_type: str, xi) -> np.ndarray:
    """Derivatives ``(n, k, 3)`` of :func:`shape_functions` with respect to ``xi``."""
    t = _canonical(cell_type)
    xi = np.atleast_2d(np.asarray(xi, dtype=float))
    n = len(xi)
    if t == "hexahedron":
        f = 1.0 + xi[:, None, :] * _HEX_NODES[None]  # (n, 8, 3)
        g = np.empty((n, 8, 3))
        for d in range(3):
            others = [e for e in range(3) if e != d]
            g[:, :, d] = _HEX_NODES[None, :, d] * f[:, :, others[0]] * f[:, :, others[1]] / 8.0
        return g
    if t in ("hexahedron20", "hexahedron27"):
        return _quadratic_hex(t, xi)[1]
    dlam = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # d lambda_i / d xi
    if t == "tetra":
        return np.broadcast_to(dlam, (n, 4, 3)).copy()
    lam = np.concatenate([1.0 - xi.sum(axis=1, keepdims=True), xi], axis=1)
    corners = (4.0 * lam - 1.0)[:, :, None] * dlam[None]
    edges = np.stack([4.0 * (lam[:, a, None] * dlam[b] + lam[:, b, None] * dlam[a]) for a, b in _TET10_EDGES], axis=1)
    return np.concatenate([corners, edges], axis=1)


def node_coordinates(cell_type: str) -> np.ndarray:
    """Local coordinates ``(k, 3)`` of the nodes of ``cell_type`` in its (VTK) node order."""
    t = _canonical(cell_type)
    if t in _HEXES:
        return {"hexahedron": _HEX_NODES, "hexahedron20": _HEX20_NODES, "hexahedron27": _HEX27_NODES}[t].copy()
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    if t == "tetra":
        return corners
    return np.vstack([corners, [(corners[a] + corners[b]) / 2 for a, b in _TET10_EDGES]])


def _quadratic_hex(t: str, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions ``(n, k)`` and their derivatives ``(n, k, 3)`` of the 20-node
    (serendipity) or 27-node (triquadratic) hexahedron."""
    x = xi[:, None, :]  # (n, 1, 3): the 1-D factors at the node coordinates -1, 0, 1 (axis 1)
    if t == "hexahedron27":
        a = _HEX27_NODES.astype(int) + 1  # (27, 3) indices into the factors
        # 1-D quadratic Lagrange polynomials on {-1, 0, 1}
        f = np.concatenate([x * (x - 1.0) / 2.0, 1.0 - x**2, x * (x + 1.0) / 2.0], axis=1)  # (n, 3, 3)
        df = np.concatenate([x - 0.5, -2.0 * x, x + 0.5], axis=1)
    else:
        a = _HEX20_NODES.astype(int) + 1
        f = np.concatenate([1.0 - x, 1.0 - x**2, 1.0 + x], axis=1)
        df = np.concatenate([-np.ones_like(x), -2.0 * x, np.ones_like(x)], axis=1)
    fx, fy, fz = f[:, a[:, 0], 0], f[:, a[:, 1], 1], f[:, a[:, 2], 2]  # (n, k)
    P = fx * fy * fz
    dP = np.stack([df[:, a[:, 0], 0] * fy * fz, fx * df[:, a[:, 1], 1] * fz, fx * fy * df[:, a[:, 2], 2]], axis=2)
    if t == "hexahedron27":
        return P, dP
    # serendipity: corners (1 + xi a)(1 + eta b)(1 + zeta c)(xi a + eta b + zeta c - 2) / 8, mid-edge nodes the products / 4
    c = _HEX_NODES  # the corners' signs
    s = xi @ c.T - 2.0  # (n, 8)
    N = np.concatenate([P[:, :8] * s / 8.0, P[:, 8:] / 4.0], axis=1)
    G = np.concatenate([(dP[:, :8] * s[:, :, None] + P[:, :8, None] * c[None]) / 8.0, dP[:, 8:] / 4.0], axis=1)
    return N, G


# ============================================================================ operator
class InterpolationOperator(eqx.Module):
    """A precomputed sparse interpolation: row ``q`` is ``sum_j weights[q, j] * values[indices[q, j]]``.

    Attributes:
        indices: ``(n, k)`` source node of each weight (padding rows repeat node 0 with weight 0).
        weights: ``(n, k)`` shape-function values [-] (each row sums to 1).
        elements: ``(n,)`` the element each point was found in (index into the source's
            cells of type ``cell_types[element_types[q]]``).
        element_types: ``(n,)`` index of that element's type in ``cell_types``.
        cell_types: the source's cell types (meshio names).
        distances: ``(n,)`` distance [m] from each point to the source mesh (0 inside).
        n_source: number of nodes of the source mesh.
    """

    indices: np.ndarray
    weights: np.ndarray
    elements: np.ndarray
    element_types: np.ndarray
    cell_types: tuple = eqx.field(static=True)
    distances: np.ndarray
    n_source: int = eqx.field(static=True)

    @property
    def n_points(self) -> int:
        return int(self.indices.shape[0])

    def __call__(self, values):
        """The field at the query points: ``values`` ``(n_source, ...)`` -> ``(n, ...)``.
        Linear in ``values``; pure JAX (jit, vmap over a leading batch via ``jax.vmap``,
        forward and reverse differentiation)."""
        values = jnp.asarray(values)
        if values.shape[0] != self.n_source:
            raise MeshError(f"the field has {values.shape[0]} rows; the source mesh has {self.n_source} nodes")
        w = jnp.asarray(self.weights, dtype=values.dtype if jnp.issubdtype(values.dtype, jnp.floating) else None)
        gathered = values[jnp.asarray(self.indices)]  # (n, k, ...)
        return jnp.einsum("nk,nk...->n...", w, gathered)

    def as_sparse(self):
        """The operator as a ``scipy.sparse.csr_matrix`` ``(n, n_source)``."""
        import scipy.sparse as sp

        n, k = self.indices.shape
        rows = np.repeat(np.arange(n), k)
        return sp.csr_matrix((self.weights.reshape(-1), (rows, self.indices.reshape(-1))), shape=(n, self.n_source))


# =========================================================================== location
def _local_coordinates(t: str, X: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local coordinates of points ``q`` ``(m, 3)`` in elements ``X`` ``(m, k, 3)`` and whether
    the inversion converged ``(m,)``. Tetrahedra: the affine map of the corners (exact for
    ``tetra``), then Newton on the isoparametric map for ``tetra10`` and the hexahedra (from the
    element's centre)."""
    m = len(q)
    if t in ("tetra", "tetra10"):
        J = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)  # columns
        xi = np.linalg.solve(J, (q - X[:, 0])[:, :, None])[:, :, 0]
        if t == "tetra":
            return xi, np.ones(m, dtype=bool)
    else:
        xi = np.zeros((m, 3))
    scale = np.linalg.norm(X.max(axis=1) - X.min(axis=1), axis=1)
    done = np.zeros(m, dtype=bool)
    act = np.arange(m)  # the rows still iterated (a converged row keeps its coordinates)
    for _ in range(_NEWTON_STEPS):
        Xa, xa = X[act], xi[act]
        r = np.einsum("mk,mkd->md", shape_functions(t, xa), Xa) - q[act]
        ok = np.linalg.norm(r, axis=1) <= 1e-13 * scale[act]
        done[act] = ok
        act, Xa, xa, r = act[~ok], Xa[~ok], xa[~ok], r[~ok]
        if act.size == 0:
            break
        J = np.einsum("mkd,mke->mde", Xa, shape_gradients(t, xa))
        with np.errstate(all="ignore"):
            step = np.linalg.solve(J, r[:, :, None])[:, :, 0]
        step = np.where(np.isfinite(step), step, 0.0)
        xi[act] = np.clip(xa - step, -4.0, 4.0)  # far candidates: keep the iteration bounded
    return xi, done


def _outside(t: str, xi: np.ndarray) -> np.ndarray:
    """How far local coordinates lie outside the reference element (0 inside) [-]."""
    if t in _HEXES:
        return np.maximum(np.abs(xi).max(axis=1) - 1.0, 0.0) / 2.0
    lam = np.concatenate([1.0 - xi.sum(axis=1, keepdims=True), xi], axis=1)
    return np.maximum(-lam.min(axis=1), 0.0)


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from points ``p`` to triangles ``abc`` (all ``(m, 3)``), exact (Ericson, Real-Time
    Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(all="ignore"):
        denom = va + vb + vc
        v_face, w_face = vb / denom, vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    closest = a + v_face[:, None] * ab + w_face[:, None] * ac
    cases = [
        ((d1 <= 0) & (d2 <= 0), a),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[:, None] * ab),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[:, None] * ac),
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + t_bc[:, None] * (c - b)),
    ]
    taken = np.zeros(len(p), dtype=bool)
    for cond, point in cases:
        use = cond & ~taken
        closest = np.where(use[:, None], point, closest)
        taken |= use
    return np.linalg.norm(p - closest, axis=1)


def _distance(t: str, X: np.ndarray, q: np.ndarray, xi: np.ndarray, outside: np.ndarray) -> np.ndarray:
    """Distance [m] from ``q`` to each element (0 inside). Tetrahedra: exact, to the faces of
    the corners' tetrahedron; hexahedra: to the point at the local coordinates clamped to the
    element (an upper bound, close to the distance for points near the element)."""
    d = np.zeros(len(q))
    out = outside > _INSIDE
    if not out.any():
        return d
    Xo, qo = X[out], q[out]
    if t in ("tetra", "tetra10"):
        faces = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
        d[out] = np.min([_point_triangle_distance(qo, Xo[:, i], Xo[:, j], Xo[:, k]) for i, j, k in faces], axis=0)
    else:
        xc = np.clip(xi[out], -1.0, 1.0)
        d[out] = np.linalg.norm(np.einsum("mk,mkd->md", shape_functions(t, xc), Xo) - qo, axis=1)
    return d


def _evaluate(t, X, conn, cand, q):
    """``(outside, distance, xi)`` of the query points ``q`` ``(m, 3)`` in candidate elements
    ``cand`` ``(m,)``."""
    Xe = X[conn[cand]]
    xi, ok = _local_coordinates(t, Xe, q)
    out = np.where(ok, _outside(t, xi), np.inf)
    dist = _distance(t, Xe, q, xi, np.where(ok, out, 1.0))
    return out, dist, xi


def interpolation_operator(points, cells: Mapping[str, np.ndarray], queries, *, tolerance: float | None = None,
                           what: str = "points") -> InterpolationOperator:
    """Locate ``queries`` in a mesh and return the interpolation of its nodal fields there.

    Args:
        points: ``(N, 3)`` node coordinates of the source mesh [m].
        cells: ``{cell type: (M, k) node indices}`` (``"tetra"``, ``"tetra10"``,
            ``"hexahedron"``, ``"hexahedron20"``, ``"hexahedron27"``; meshio names and VTK
            node order).
        queries: ``(n, 3)`` points [m] at which the field is wanted.
        tolerance: a point at most this far outside the mesh [m] is accepted (the nearest
            element's shape functions, extrapolated); default 1e-6 x the source mesh's
            bounding-box diagonal.
        what: what the points are, for error messages (e.g. ``"reference nodes"``).

    Raises:
        PointsOutsideMeshError: some points are farther than ``tolerance`` from every
            element (the message gives how many, their largest and smallest distance and the
            tolerance; ``indices`` are the query indices, ``distances`` their distances [m]).
        UnsupportedMeshError: an unsupported cell type, or no cells.
        MeshError: malformed arrays (shapes, indices out of range).
    """
    from scipy.spatial import cKDTree

    X = np.asarray(points, dtype=float)
    q = np.asarray(queries, dtype=float).reshape(-1, 3) if np.size(queries) else np.zeros((0, 3))
    if X.ndim != 2 or X.shape[1] != 3 or not np.all(np.isfinite(X)):
        raise MeshError(f"points must be a finite (N, 3) array [m], got shape {X.shape}")
    if not np.all(np.isfinite(q)):
        raise MeshError(f"the {what} must be finite coordinates [m]")
    blocks = []
    for name, conn in cells.items():
        t = _canonical(name)
        conn = np.asarray(conn, dtype=np.int64)
        if conn.ndim != 2 or conn.shape[1] != ELEMENT_NODES[t]:
            raise MeshError(f"{name} cells must be an (M, {ELEMENT_NODES[t]}) array of node indices, got shape {conn.shape}")
        if len(conn) == 0:
            continue
        if conn.min() < 0 or conn.max() >= len(X):
            raise MeshError(f"{name} cells index nodes outside [0, {len(X)})")
        blocks.append((t, conn))
    if not blocks:
        raise UnsupportedMeshError("the source mesh has no volume cells to interpolate in (tetra, tetra10, hexahedron, hexahedron20 "
                                   "or hexahedron27)")
    diag = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    tol = 1e-6 * diag if tolerance is None else float(tolerance)
    if not (np.isfinite(tol) and tol >= 0):
        raise MeshError(f"tolerance must be a distance >= 0 m, got {tolerance!r}")
    n = len(q)
    kmax = max(ELEMENT_NODES[t] for t, _ in blocks)
    best_out = np.full(n, np.inf)
    best_dist = np.full(n, np.inf)
    best_idx = np.zeros((n, kmax), dtype=np.int64)
    best_w = np.zeros((n, kmax))
    best_el = np.zeros(n, dtype=np.int64)
    best_type = np.zeros(n, dtype=np.int64)

    def take(bi, t, conn, rows, cand, out, dist, xi):
        # rows: distinct query indices, one candidate each.
        # a candidate wins when it contains the point and the best so far does not, or both are
        # outside and it is nearer (inside candidates are equivalent: continuity of the field)
        inside, best_inside = out <= _INSIDE, best_out[rows] <= _INSIDE
        better = (inside & ~best_inside) | (~inside & ~best_inside & (dist < best_dist[rows]))
        r = rows[better]
        best_out[r], best_dist[r] = out[better], dist[better]
        k = ELEMENT_NODES[t]
        best_idx[r] = 0
        best_w[r] = 0.0
        best_idx[r, :k] = conn[cand[better]]
        best_w[r, :k] = shape_functions(t, xi[better])
        best_el[r] = cand[better]
        best_type[r] = bi

    for bi, (t, conn) in enumerate(blocks):
        Xe = X[conn]
        centroids = Xe.mean(axis=1)
        k = min(_CANDIDATES, len(conn))
        _, near = cKDTree(centroids).query(q, k=k)
        near = np.asarray(near).reshape(n, k)
        for j in range(k):
            rows = np.arange(n)
            out, dist, xi = _evaluate(t, X, conn, near[:, j], q)
            take(bi, t, conn, rows, near[:, j], out, dist, xi)
    # exhaustive search (elements whose bounding box, widened by the tolerance, holds the point)
    # for the points no nearby element contains: graded meshes, slivers, points just outside
    for bi, (t, conn) in enumerate(blocks):
        Xe = X[conn]
        lo, hi = Xe.min(axis=1) - tol, Xe.max(axis=1) + tol
        in_box = np.all((q >= lo.min(axis=0)) & (q <= hi.max(axis=0)), axis=1)
        for p in np.flatnonzero((best_out > _INSIDE) & in_box):
            cand = np.flatnonzero(np.all((q[p] >= lo) & (q[p] <= hi), axis=1))
            if cand.size == 0:
                continue
            out, dist, xi = _evaluate(t, X, conn, cand, np.broadcast_to(q[p], (cand.size, 3)))
            j = int(np.argmin(np.where(out <= _INSIDE, -1.0, dist)))  # one candidate per point: inside first, else the nearest
            take(bi, t, conn, np.array([p]), cand[j:j + 1], out[j:j + 1], dist[j:j + 1], xi[j:j + 1])
    distance = np.where(best_out <= _INSIDE, 0.0, best_dist)
    far = np.flatnonzero(distance > tol)
    if far.size:
        d = distance[far]
        raise PointsOutsideMeshError(
            f"{far.size} of the {n} {what} lie outside the mesh they are interpolated in, by {d.min():.4g} to {d.max():.4g} m "
            f"(tolerance {tol:.4g} m; the mesh spans {X.min(axis=0).tolist()} to {X.max(axis=0).tolist()} m); check that both meshes "
            f"use the same length unit and origin, or raise the tolerance to accept points that far (they take the nearest "
            f"element's values, extrapolated)",
            indices=far, distances=d)
    return InterpolationOperator(best_idx, best_w, best_el, best_type, tuple(t for t, _ in blocks), distance, len(X))
