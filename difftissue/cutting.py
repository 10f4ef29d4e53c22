"""Cut topology: a scalpel path, node snapping and duplication (seed 003), element removal
(seed 000), progressive closure and the opening width.

A cut is built once, on the host with NumPy, for the FULL scalpel path. By default (``snap``) nodes nearest the
cutting surface are snapped onto it (surface snapping), the deepest crossed node row onto the
cut bottom and the nodes nearest the path ends onto the ends (inside snapping), then the nodes
strictly on the open part of the surface are duplicated and every tet (and lattice cube) is
reconnected to the side its centroid lies on. On lattice specimens the ``staircase`` method
instead moves no node and opens the cube faces between cubes on either side. No element is
created. The result is a
:class:`Cut` pytree whose arrays have fixed shapes; a cut in progress at scalpel arc length
``s`` is the same topology with the pairs the scalpel has not reached yet tied together
(:class:`CutClosureModel`), so sweeping ``s`` never recompiles.

Coordinates are metres. The specimen's top surface is the plane ``z = max z`` of the mesh; the
depth ``h`` of a point is ``z_top - z``. A path with ``surface="boundary"`` lies on a (curved)
boundary surface instead: the depth is measured along the surface normal
(:class:`_SurfaceGeometry`). See ``docs/cutting.md`` ("Cut topology", "Cuts on curved surfaces").
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import CutError, DisconnectedCutError, _cite
from .mesh import Specimen, TetMesh, _build_lattice, _KUHN_TETS, mean_ratio_quality, ray_triangle_hits, signed_volumes
from .models import ElasticModel, ElementTerm, hexahedron_jacobians

__all__ = [
    "ScalpelPath",
    "CutQuality",
    "Cut",
    "Opening",
    "cut_specimen",
    "staircase_cut",
    "remove_elements",
    "opening_width",
    "closed_mask",
    "CutClosureModel",
    "connected_components",
]

#: Largest blade tilt accepted [rad] (60 degrees).
MAX_TILT = float(np.deg2rad(60.0))

#: The 6 faces of a lattice cube (local vertex ``v = bx + 2 by + 4 bz``): face ``2 a + b`` holds the
#: vertices with bit ``a`` equal to ``b``, in ascending order (corners (0,0), (1,0), (0,1), (1,1)
#: of the face).
_CUBE_FACES = np.array([[v for v in range(8) if (v >> a) & 1 == b] for a in range(3) for b in range(2)])


# =========================================================================== the path
@dataclasses.dataclass(frozen=True)
class ScalpelPath:
    """A scalpel path on the specimen's top surface.

    Attributes:
        points: ``(K, 2)`` surface points ``(x, y)`` [m], or ``(K, 3)`` points on the top
            surface (their ``z`` must equal the surface height), ``K >= 2``.
        depth: cut depth ``d`` below the top surface [m], ``> 0``. With ``through=True`` it may
            be omitted (``None``): the cut goes through the whole thickness.
        through: the cut goes through the whole specimen thickness (must be said explicitly; a
            depth at or beyond the thickness without it is refused).
        tilt: blade tilt [rad] about the path direction (0 = vertical blade). A tilted blade
            cuts the plane through the path whose normal is the horizontal path normal tilted
            by ``tilt``: at depth ``h`` the cut lies ``h tan(tilt)`` to the left of the path.
            Only straight (two-point) paths may be tilted; ``|tilt| <= 60 deg``.
        surface: ``"top"`` (the flat plane ``z = max z``; depth measured vertically) or
            ``"boundary"``: the path lies on the specimen's boundary surface, which may be
            curved (a dome, a cylinder, a block in any orientation). ``(K, 2)`` points are
            projected vertically (along -z) onto the surface below them, ``(K, 3)`` points must
            lie on the surface (within ``1e-6`` of the mesh size). The path follows the surface
            between its points, the depth is measured along the surface normal and the blade
            lies in the plane through the path and the normal (see ``docs/cutting.md``, "Cuts
            on curved surfaces"). A tilted blade needs a path along a straight line of the
            surface (a plane, a cylinder's generator).
    """

    points: Any
    depth: float | None = None
    through: bool = False
    tilt: float = 0.0
    surface: str = "top"

    def __post_init__(self):
        p = np.asarray(self.points, dtype=float)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise CutError(f"scalpel path points must be an (K, 2) or (K, 3) array of metres, got shape {p.shape}")
        if len(p) < 2:
            raise CutError(f"a scalpel path needs at least 2 points, got {len(p)}")
        if not np.all(np.isfinite(p)):
            raise CutError("scalpel path points contain NaN or infinite values")
        if self.surface not in ("top", "boundary"):
            raise CutError(f"surface must be 'top' or 'boundary', got {self.surface!r}")
        # A path on the boundary given in 3-D is checked in 3-D (its xy projection may be degenerate).
        q = p if (self.surface == "boundary" and p.shape[1] == 3) else p[:, :2]
        seg = np.linalg.norm(np.diff(q, axis=0), axis=1)
        if seg.sum() <= 0:
            raise CutError("the scalpel path has zero length (all points coincide)")
        rep = np.flatnonzero(seg <= 1e-12 * seg.sum())
        if rep.size:
            raise CutError(f"the scalpel path repeats a point (zero-length segment(s) {_cite(rep)}); remove the duplicates")
        object.__setattr__(self, "points", p)
        if self.depth is None:
            if not self.through:
                raise CutError("give the cut depth [m] (or through=True for a cut through the whole thickness)")
        else:
            d = float(self.depth)
            if not (np.isfinite(d) and d > 0):
                raise CutError(f"cut depth must be > 0 m, got {self.depth!r}")
            object.__setattr__(self, "depth", d)
        t = float(self.tilt)
        if not np.isfinite(t) or abs(t) > MAX_TILT:
            raise CutError(f"blade tilt must be within +-60 degrees ({MAX_TILT:.4f} rad), got {self.tilt!r} rad")
        if t != 0.0 and len(p) != 2:
            raise CutError("a tilted blade is supported on straight (two-point) paths only; split the cut or use tilt=0")
        object.__setattr__(self, "tilt", t)
        object.__setattr__(self, "through", bool(self.through))
        tang = np.diff(q, axis=0) / seg[:, None]
        cosang = np.einsum("ij,ij->i", tang[:-1], tang[1:])
        sharp = np.flatnonzero(cosang < 0.0)
        if sharp.size:
            raise CutError(f"the scalpel path turns by more than 90 degrees at point(s) {_cite(sharp + 1)}; such turns are not supported (cut in two pieces)")
        bad = _self_intersections(_plane_coordinates(q) if q.shape[1] == 3 else q)
        if bad:
            raise CutError(f"the scalpel path intersects itself (segments {bad[0]} and {bad[1]}); self-intersecting cuts are not supported")

    @property
    def xy(self) -> np.ndarray:
        return self.points[:, :2]

    @property
    def length(self) -> float:
        """Length [m] of the polyline through the points: horizontal on the flat top (and for
        ``(K, 2)`` points on the boundary), 3-D for ``(K, 3)`` points on the boundary (the cut's
        length along a curved surface is :attr:`Cut.length`)."""
        q = self.points if (self.surface == "boundary" and self.points.shape[1] == 3) else self.xy
        return float(np.linalg.norm(np.diff(q, axis=0), axis=1).sum())


def _plane_coordinates(p: np.ndarray) -> np.ndarray:
    """2-D coordinates of 3-D points in the plane of their two main directions (for the
    self-intersection test of a path on a surface)."""
    c = p - p.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return c @ vt[:2].T


def _self_intersections(p: np.ndarray):
    """First pair of non-adjacent segments that intersect, or None."""
    n = len(p) - 1

    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    for i in range(n):
        for j in range(i + 2, n):
            a, b, c, d = p[i], p[i + 1], p[j], p[j + 1]
            o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
            if o1 * o2 <= 0 and o3 * o4 <= 0:
                # Collinear disjoint segments give all-zero orientations: check overlap.
                if o1 == o2 == o3 == o4 == 0:
                    lo1, hi1 = np.minimum(a, b), np.maximum(a, b)
                    lo2, hi2 = np.minimum(c, d), np.maximum(c, d)
                    if np.any(hi1 < lo2) or np.any(hi2 < lo1):
                        continue
                return (i, j)
    return None


class _Geometry:
    """Cut-aligned coordinates ``(s, n, h)`` of points: arc length of the closest point on the
    path (end segments extended), signed horizontal distance from the cutting surface (positive
    to the left of the path direction) and depth below the top surface."""

    def __init__(self, path: ScalpelPath, z_top: float):
        self.z_top = z_top
        self.p = path.xy
        d = np.diff(self.p, axis=0)
        self.seg_len = np.linalg.norm(d, axis=1)
        self.tang = d / self.seg_len[:, None]
        self.normal = np.stack([-self.tang[:, 1], self.tang[:, 0]], axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.cum[-1])
        self.tan_tilt = float(np.tan(path.tilt))

    def coords(self, x: np.ndarray):
        x = np.asarray(x, dtype=float)
        h = self.z_top - x[:, 2]
        nseg = len(self.seg_len)
        # Horizontal position with the blade tilt removed (straight paths only when tilted).
        q = x[:, :2] - (h * self.tan_tilt)[:, None] * self.normal[0]
        rel = q[:, None, :] - self.p[None, :-1, :]  # (n, S, 2)
        t = np.einsum("nsk,sk->ns", rel, self.tang)
        lo = np.zeros(nseg)
        hi = self.seg_len.copy()
        lo[0] = -np.inf
        hi[-1] = np.inf
        tc = np.clip(t, lo, hi)
        closest = self.p[None, :-1, :] + tc[..., None] * self.tang[None]
        dist = np.linalg.norm(q[:, None, :] - closest, axis=2)
        k = np.argmin(dist, axis=1)
        r = np.arange(len(x))
        s = self.cum[k] + tc[r, k]
        off = q - closest[r, k]
        # Sign from the segment normal; at a vertex (clamped) use the mean normal of both segments.
        nrm = self.normal[k].copy()
        at_vertex = (tc[r, k] != t[r, k])
        if nseg > 1 and np.any(at_vertex):
            kk = k[at_vertex]
            nxt = np.where(tc[r, k][at_vertex] <= 0, np.maximum(kk - 1, 0), np.minimum(kk + 1, nseg - 1))
            m = self.normal[kk] + self.normal[nxt]
            nrm[at_vertex] = m / np.linalg.norm(m, axis=1, keepdims=True)
        sign = np.where(np.einsum("ij,ij->i", off, nrm) >= 0, 1.0, -1.0)
        n = sign * dist[r, k]
        return s, n, h

    def segment_of(self, s):
        return np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seg_len) - 1)

    def surface_xy(self, s, h):
        """Horizontal position of the cutting-surface point at arc length ``s`` and depth ``h``."""
        k = self.segment_of(s)
        base = self.p[k] + (s - self.cum[k])[:, None] * self.tang[k]
        return base + (h * self.tan_tilt)[:, None] * self.normal[0]

    def unit_normal(self, s):
        """3-D unit normal of the cutting surface at ``s``, pointing to the ``+`` side."""
        k = self.segment_of(s)
        nz = np.full(len(k), self.tan_tilt)
        v = np.concatenate([self.normal[k], nz[:, None]], axis=1)
        return v / np.linalg.norm(v, axis=1, keepdims=True)


#: Feature angle of the cut's surface patch [rad]: boundary faces whose normals differ by more
#: than this across a shared edge (a block's top edge, 90 degrees) belong to different patches.
FEATURE_ANGLE = float(np.deg2rad(30.0))


def _closest_on_triangles(x: np.ndarray, tri: np.ndarray):
    """Closest point of the triangles ``tri`` ``(T, 3, 3)`` to each point ``x`` ``(Q, 3)``:
    ``(distance (Q,), triangle (Q,), barycentric (Q, 3))`` (Ericson's region test)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    dist = np.empty(len(x))
    face = np.empty(len(x), dtype=np.int64)
    bary = np.empty((len(x), 3))
    for i, p in enumerate(x):
        ap, bp, cp = p - a, p - b, p - c
        d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
        d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
        d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            den = va + vb + vc
            w = np.stack([va / den, vb / den, vc / den], axis=1)  # interior: barycentric (a, b, c)
            # regions (checked in order; later ones only where no earlier one applies)
            vw = d1 / (d1 - d3)
            ww = d2 / (d2 - d6)
            uw = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        cand = [
            ((d1 <= 0) & (d2 <= 0), np.array([1.0, 0, 0])),
            ((d3 >= 0) & (d4 <= d3), np.array([0, 1.0, 0])),
            ((d6 >= 0) & (d5 <= d6), np.array([0, 0, 1.0])),
        ]
        done = np.zeros(len(tri), dtype=bool)
        for m, val in cand:
            m = m & ~done
            w[m] = val
            done |= m
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0) & ~done
        w[m] = np.stack([1 - vw[m], vw[m], np.zeros(m.sum())], axis=1)
        done |= m
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0) & ~done
        w[m] = np.stack([1 - ww[m], np.zeros(m.sum()), ww[m]], axis=1)
        done |= m
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0) & ~done
        w[m] = np.stack([np.zeros(m.sum()), 1 - uw[m], uw[m]], axis=1)
        q = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
        dd = np.linalg.norm(q - p, axis=1)
        k = int(np.nanargmin(dd))
        dist[i], face[i], bary[i] = dd[k], k, w[k]
    return dist, face, bary


class _SurfaceGeometry:
    """Cut-aligned coordinates ``(s, n, h)`` for a path on the (possibly curved) boundary
    surface: ``s`` the arc length of the closest point ``p(s)`` on the path (a polyline on the
    surface, end segments extended), ``n = (x - p(s)) . m`` the signed distance from the blade
    (``m = tau x b``, to the left of the path seen from outside), ``h = (x - p(s)) . b`` the depth
    along ``b``, the inward surface normal made orthogonal to the path tangent ``tau``. Straight
    segments of the path along a straight line of the surface have one frame (the blade is the
    plane through the path and the normal); elsewhere the path is sampled every quarter cell
    and projected onto the surface, and frames blend at the vertices as the flat
    :class:`_Geometry`'s normals do. A tilted blade (straight paths only) shears the blade:
    at depth ``h`` it lies ``h tan(tilt)`` along ``m``.
    """

    def __init__(self, path: "ScalpelPath", points: np.ndarray, bfaces: np.ndarray, ell: float, scale: float):
        self.tan_tilt = float(np.tan(path.tilt))
        tri = points[bfaces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)
        self.bfaces, self.face_normals = bfaces, fn
        self._tri, self._cross, self._points = tri, cross, points
        # node -> incident boundary faces
        flat = bfaces.reshape(-1)
        order = np.argsort(flat, kind="stable")
        self._ptr = np.searchsorted(flat[order], np.arange(len(points) + 1))
        self._face_of = order // 3
        tol = 1e-6 * scale
        # 1. vertices of the path on the surface
        if path.points.shape[1] == 2:
            starts = np.column_stack([path.xy, np.full(len(path.xy), points[:, 2].max() + scale)])
            v_pts, v_face, v_bary = self._project(starts, np.array([0.0, 0.0, -1.0]), what="point", first=True)
        else:
            dist, v_face, v_bary = _closest_on_triangles(path.points, tri)
            bad = np.flatnonzero(dist > tol)
            if bad.size:
                k = int(bad[0])
                raise CutError(f"scalpel path point {k} {np.round(path.points[k], 9).tolist()} m is {dist[k]:.3g} m off the specimen's boundary surface "
                               f"(3-D points of a path on surface='boundary' must lie on it, within {tol:.3g} m)")
            v_pts = self._on_face(v_face, v_bary[:, 1], v_bary[:, 2])
        v_nrm = self._normals(v_face, v_bary)
        # 2. each segment: samples every quarter cell, projected; one frame where it is straight
        poly, nrm_at, straight_of = [v_pts[:1]], [v_nrm[:1]], []
        faces_hit = [v_face[:1]]
        for k in range(len(v_pts) - 1):
            a, b = v_pts[k], v_pts[k + 1]
            m = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.25 * ell))) + 1)
            t = np.linspace(0.0, 1.0, m)[1:-1]
            if path.points.shape[1] == 2:
                xy = path.xy[k] + t[:, None] * (path.xy[k + 1] - path.xy[k])
                starts = np.column_stack([xy, np.full(len(xy), points[:, 2].max() + scale)])
                sp, sf, sb = self._project(starts, np.array([0.0, 0.0, -1.0]), what="point", first=True)
            else:
                mean = v_nrm[k] + v_nrm[k + 1]
                mean /= np.linalg.norm(mean)
                sp, sf, sb = self._project(a + t[:, None] * (b - a), -mean, what="point", first=False)
            sn = self._normals(sf, sb)
            chord = b - a
            rel = sp - a
            off = rel - np.outer(rel @ chord / (chord @ chord), chord)
            straight = bool(np.all(np.linalg.norm(off, axis=1) <= 1e-6 * ell))
            if straight:
                poly.append(v_pts[k + 1 : k + 2])
                nn = np.concatenate([v_nrm[k : k + 2], sn]).mean(axis=0)
                nrm_at.append(v_nrm[k + 1 : k + 2])
                straight_of.append(nn / np.linalg.norm(nn))
            else:
                poly += [sp, v_pts[k + 1 : k + 2]]
                nrm_at += [sn, v_nrm[k + 1 : k + 2]]
                straight_of += [None] * (len(sp) + 1)
            faces_hit += [sf, v_face[k + 1 : k + 2]]
        self.p = np.concatenate(poly)
        nodal = np.concatenate(nrm_at)
        self.faces_hit = np.concatenate(faces_hit)
        d = np.diff(self.p, axis=0)
        self.seg_len = np.linalg.norm(d, axis=1)
        if np.any(self.seg_len <= 1e-12 * scale):
            raise CutError("two points of the scalpel path project onto the same surface point; remove one")
        self.tang = d / self.seg_len[:, None]
        nu = np.array([sn if sn is not None else nodal[i] + nodal[i + 1] for i, sn in enumerate(straight_of)])
        nu -= np.einsum("ij,ij->i", nu, self.tang)[:, None] * self.tang
        nlen = np.linalg.norm(nu, axis=1)
        if np.any(nlen < 1e-6):
            raise CutError("the scalpel path runs along the surface normal (it leaves the surface)")
        self.b = -nu / nlen[:, None]
        self.normal = np.cross(self.tang, self.b)  # m: the blade normal, to the + side
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.cum[-1])
        if len(self.seg_len) > 1:
            cosang = np.einsum("ij,ij->i", self.tang[:-1], self.tang[1:])
            if np.any(cosang < 0):
                raise CutError("the scalpel path, projected onto the surface, turns by more than 90 degrees")
            if self.tan_tilt != 0.0:
                raise CutError("a tilted blade on surface='boundary' needs a path along a straight line of the surface "
                               "(a plane, a cylinder's generator); this path follows a curved surface: use tilt=0")

    # ------------------------------------------------------------- surface helpers
    def _normals(self, face, bary):
        """Smooth outward normals at surface points (triangle ``face``, barycentric ``bary``):
        the barycentric mean of the vertex normals, each the area-weighted mean normal of the
        vertex's boundary faces within :data:`FEATURE_ANGLE` of the hit face (a patch's edge
        does not tilt it)."""
        out = np.empty((len(face), 3))
        cos_f = np.cos(FEATURE_ANGLE)
        for i, (f, w) in enumerate(zip(face, bary)):
            acc = np.zeros(3)
            for k, v in enumerate(self.bfaces[f]):
                inc = self._face_of[self._ptr[v] : self._ptr[v + 1]]
                keep = inc[self.face_normals[inc] @ self.face_normals[f] > cos_f]
                vn = self._cross[keep].sum(axis=0)
                acc += w[k] * vn / np.linalg.norm(vn)
            out[i] = acc / np.linalg.norm(acc)
        return out

    def _project(self, origins, direction, *, what: str, first: bool):
        """Surface points on the lines through ``origins`` along ``direction`` (entry faces):
        the first hit (``first``) or the nearest to the origin. Returns points, faces, barycentric."""
        t, u, v = ray_triangle_hits(origins, direction, self._tri, facing=-1)
        if first:
            key = np.where(np.isnan(t), np.inf, t)
        else:
            key = np.where(np.isnan(t), np.inf, np.abs(t))
        f = np.argmin(key, axis=1)
        r = np.arange(len(origins))
        miss = ~np.isfinite(key[r, f])
        if np.any(miss):
            k = int(np.flatnonzero(miss)[0])
            raise CutError(f"the scalpel path leaves the specimen's boundary surface near {np.round(origins[k], 9).tolist()} m "
                           "(no boundary face under this path point faces out along the projection)")
        uu, vv = u[r, f], v[r, f]
        bary = np.column_stack([1 - uu - vv, uu, vv])
        pts = self._on_face(f, uu, vv)
        if first:  # a vertical projection keeps the given x, y
            pts[:, :2] = origins[:, :2]
        return pts, f, bary

    def _on_face(self, f, u, v):
        """The point ``a + u (b - a) + v (c - a)`` of boundary triangle ``f`` (exactly in the
        plane of a triangle whose corners share a coordinate, e.g. the flat top's z)."""
        tri = self._tri[f]
        return tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])

    def patch(self):
        """The boundary faces of the path's surface patch: reached from the face under the path's
        start across edges whose faces' normals differ by less than :data:`FEATURE_ANGLE`.
        Raises :class:`CutError` when the path crosses onto another patch."""
        e = self.bfaces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
        key = np.sort(e, axis=1)
        _, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        owner = np.repeat(np.arange(len(self.bfaces)), 3)
        order = np.argsort(inv, kind="stable")
        inv_s = inv[order]
        first = order[:-1][inv_s[:-1] == inv_s[1:]]
        second = order[1:][inv_s[:-1] == inv_s[1:]]
        fa, fb = owner[first], owner[second]
        smooth = np.einsum("ij,ij->i", self.face_normals[fa], self.face_normals[fb]) > np.cos(FEATURE_ANGLE)
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components as cc

        nf = len(self.bfaces)
        g = coo_matrix((np.ones(int(smooth.sum())), (fa[smooth], fb[smooth])), shape=(nf, nf))
        _, label = cc(g, directed=False)
        patch = label == label[self.faces_hit[0]]
        off = ~patch[self.faces_hit]
        if np.any(off):
            k = int(np.flatnonzero(off)[0])
            raise CutError(f"the scalpel path crosses an edge of the specimen's surface (boundary faces meeting at more than "
                           f"{np.rad2deg(FEATURE_ANGLE):.0f} degrees) near {np.round(self.p[min(k, len(self.p) - 1)], 9).tolist()} m; "
                           "a cut must stay on one smooth surface")
        return patch

    # ------------------------------------------------------------- the interface of _Geometry
    def coords(self, x: np.ndarray):
        x = np.asarray(x, dtype=float)
        out = [self._coords(x[i : i + 2048]) for i in range(0, len(x), 2048)]
        if not out:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        return tuple(np.concatenate([o[j] for o in out]) for j in range(3))

    def _coords(self, x):
        nseg = len(self.seg_len)
        if self.tan_tilt != 0.0:  # one segment: remove the shear first
            h0 = (x - self.p[0]) @ self.b[0]
            q = x - (h0 * self.tan_tilt)[:, None] * self.normal[0]
        else:
            q = x
        rel = q[:, None, :] - self.p[None, :-1, :]  # (n, S, 3)
        t = np.einsum("nsk,sk->ns", rel, self.tang)
        lo = np.zeros(nseg)
        hi = self.seg_len.copy()
        lo[0] = -np.inf
        hi[-1] = np.inf
        tc = np.clip(t, lo, hi)
        closest = self.p[None, :-1, :] + tc[..., None] * self.tang[None]
        dist = np.linalg.norm(q[:, None, :] - closest, axis=2)
        k = np.argmin(dist, axis=1)
        r = np.arange(len(x))
        s = self.cum[k] + tc[r, k]
        off = q - closest[r, k]
        m = self.normal[k].copy()
        b = self.b[k].copy()
        at_vertex = tc[r, k] != t[r, k]
        if nseg > 1 and np.any(at_vertex):
            kk = k[at_vertex]
            nxt = np.where(tc[r, k][at_vertex] <= 0, np.maximum(kk - 1, 0), np.minimum(kk + 1, nseg - 1))
            mm = self.normal[kk] + self.normal[nxt]
            bb = self.b[kk] + self.b[nxt]
            m[at_vertex] = mm / np.linalg.norm(mm, axis=1, keepdims=True)
            b[at_vertex] = bb / np.linalg.norm(bb, axis=1, keepdims=True)
        h = np.einsum("ij,ij->i", off, b)
        n = np.einsum("ij,ij->i", off, m)
        if nseg > 1 and np.any(at_vertex):
            # at a vertex: the distance from the blade's vertex line, signed by the mean normal
            rest = off[at_vertex] - h[at_vertex, None] * b[at_vertex]
            n[at_vertex] = np.where(n[at_vertex] >= 0, 1.0, -1.0) * np.linalg.norm(rest, axis=1)
        if self.tan_tilt != 0.0:
            h = h0
        return s, n, h

    def segment_of(self, s):
        return np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seg_len) - 1)

    def surface_point(self, s, h):
        """The blade's point [m] at arc length ``s`` and depth ``h`` (``(Q, 3)``)."""
        s, h = np.asarray(s, dtype=float), np.asarray(h, dtype=float)
        k = self.segment_of(s)
        return self.p[k] + (s - self.cum[k])[:, None] * self.tang[k] + h[:, None] * (self.b[k] + self.tan_tilt * self.normal[k])

    def unit_normal(self, s):
        """Unit normal of the blade at ``s``, pointing to the ``+`` side."""
        k = self.segment_of(s)
        v = self.normal[k] - self.tan_tilt * self.b[k]
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def thickness(self, scale: float):
        """Depth [m] along the blade from each path vertex to the far side of the specimen (the
        first exit through the boundary)."""
        d = self.b + self.tan_tilt * self.normal
        dirs = np.concatenate([d, d[-1:]])
        t, _, _ = ray_triangle_hits(self.p, dirs, self._tri, facing=+1)
        t = np.where(t > 1e-9 * scale, t, np.nan)
        with np.errstate(all="ignore"):
            out = np.nanmin(np.where(np.isnan(t), np.inf, t), axis=1)
        return out


# ======================================================================== the result
@dataclasses.dataclass(frozen=True)
class CutQuality:
    """Element quality after the cut (mean-ratio quality, 1 = regular tet, <= 0 inverted).

    Attributes:
        min_quality_before, min_quality_after: smallest tet quality before / after snapping.
        threshold: the reporting threshold; ``n_below_threshold`` tets are below it after the
            cut, ``worst_elements`` the (up to 8) lowest.
        n_snapped: nodes moved onto the cutting surface, bottom or ends.
        max_snap_distance: largest node move [m]; ``max_snap_relative`` the same divided by the
            node's local edge length.
        min_cell_jacobian_ratio: for lattice specimens, smallest ratio of a cube's Gauss-point
            Jacobian after / before snapping (None without lattice).
        n_duplicated: duplicated nodes (= pairs).
        n_removed: removed tets (element removal).
        n_cut_faces: tet faces opened by the cut (between a ``+`` and a ``-`` tet).
        n_off_surface: duplicated nodes not on the cutting surface (where snapping a node would
            have ruined a tet, the opened faces follow the mesh instead; 0 on lattices).
        n_bridging_tets: tets wholly inside the cut's extent (all corners between the ends and
            above the bottom) with corners strictly on both sides of the cutting surface (the surface passes through them; they stay on one side, by centroid, and
            bridge the cut locally; 0 when snapping aligned the mesh with the cut).
        n_split_cubes: lattice cubes with duplicated nodes and corners strictly on both sides
            (None without lattice; 0 for a staircase cut, whose ``split_cubes`` is None);
            ``split_cubes`` says whether they were dropped from the
            lattice (``"drop"``) or kept, bridging the cut (``"keep"``); ``n_split_cubes_kept``
            counts the split cubes kept anyway (all with ``"keep"``; with ``"drop"`` those that
            alone hold a node, which would otherwise have no spring).
        cut_area: area of the opened faces [m^2] (the faces between the two sides on the open
            part of the cut); ``ideal_area`` the area of the ideal cutting surface, path length
            x depth / cos(tilt) [m^2]. Their ratio is about 1 for snapped cuts and
            ``|cos theta| + |sin theta|`` for a staircase cut at angle ``theta`` to the lattice.
        max_normal_distance: largest distance of a node of the opened faces from the ideal
            cutting surface [m] (0 when every opened face lies on it).
    """

    min_quality_before: float
    min_quality_after: float
    threshold: float
    n_below_threshold: int
    worst_elements: tuple[int, ...]
    n_snapped: int
    max_snap_distance: float
    max_snap_relative: float
    min_cell_jacobian_ratio: float | None
    n_duplicated: int
    n_removed: int = 0
    n_cut_faces: int = 0
    n_off_surface: int = 0
    n_bridging_tets: int = 0
    n_split_cubes: int | None = None
    split_cubes: str | None = None
    n_split_cubes_kept: int | None = None
    cut_area: float | None = None
    ideal_area: float | None = None
    max_normal_distance: float | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def __str__(self) -> str:
        s = (
            f"cut quality: min tet quality {self.min_quality_before:.3g} -> {self.min_quality_after:.3g}, "
            f"{self.n_below_threshold} tet(s) below {self.threshold:g}; {self.n_snapped} node(s) snapped "
            f"(max move {self.max_snap_distance:.3g} m = {self.max_snap_relative:.2f} local edge); "
            f"{self.n_duplicated} duplicated"
        )
        if self.min_cell_jacobian_ratio is not None:
            s += f"; min cube Jacobian ratio {self.min_cell_jacobian_ratio:.3g}"
        s += f"; {self.n_cut_faces} face(s) opened, {self.n_off_surface} duplicated node(s) off the cutting surface, {self.n_bridging_tets} tet(s) bridging"
        if self.n_split_cubes is not None and self.split_cubes is None:
            s += f", {self.n_split_cubes} cube(s) split"
        elif self.n_split_cubes is not None:
            s += f", {self.n_split_cubes} cube(s) split ({'dropped from the lattice' if self.split_cubes == 'drop' else 'kept, bridging the cut'}"
            if self.split_cubes == "drop" and self.n_split_cubes_kept:
                s += f"; {self.n_split_cubes_kept} kept: they alone hold a node"
            s += ")"
        if self.n_removed:
            s += f"; {self.n_removed} tet(s) removed"
        if self.cut_area is not None and self.ideal_area:
            s += (
                f"; opened area {self.cut_area:.4g} m^2 = {self.cut_area / self.ideal_area:.3f} x the ideal surface's, "
                f"max distance from it {self.max_normal_distance:.3g} m"
            )
        return s


class Cut(eqx.Module):
    """A cut specimen: the new mesh with duplicated nodes and the pair bookkeeping.

    Attributes:
        mesh: the cut :class:`~difftissue.mesh.TetMesh` (duplicates appended after the original
            nodes; same tets in the same order, reconnected; the lattice rebuilt when the
            specimen has one).
        pairs: ``(P, 2)`` node pairs ``(original, duplicate)``; the original is used by the tets
            on the ``+`` side (left of the path direction), the duplicate by those on the ``-``
            side. For element removal: ``(+ side node, - side node)`` facing each other across
            the removed slab.
        pair_s: ``(P,)`` arc length along the path [m] of each pair.
        pair_depth: ``(P,)`` depth below the top surface [m].
        pair_normal: ``(P, 3)`` unit normal of the cutting surface, pointing to the ``+`` side.
        pair_rest_offset: ``(P, 3)`` rest ``X_a - X_b`` (zero for snapped pairs).
        tet_side: ``(M,)`` +1 / -1 side of each tet that touches a duplicated node, else 0.
        surface_pairs: indices into ``pairs`` of the pairs on the top surface, sorted by ``s``.
        node_origin: ``(N',)`` index of each new node in the original mesh.
        materials: the specimen's materials when a :class:`Specimen` was cut, else None.
        length, depth: cut length and depth [m]; method ``"snap"``, ``"staircase"`` or ``"remove"``; through.
        quality: the :class:`CutQuality` report.
    """

    mesh: TetMesh
    pairs: np.ndarray
    pair_s: np.ndarray
    pair_depth: np.ndarray
    pair_normal: np.ndarray
    pair_rest_offset: np.ndarray
    tet_side: np.ndarray
    surface_pairs: np.ndarray
    node_origin: np.ndarray
    materials: Any
    length: float = eqx.field(static=True)
    depth: float = eqx.field(static=True)
    method: str = eqx.field(static=True)
    through: bool = eqx.field(static=True)
    quality: CutQuality = eqx.field(static=True)

    @property
    def n_pairs(self) -> int:
        return int(self.pairs.shape[0])

    def specimen(self) -> Specimen:
        """The cut mesh with the materials of the specimen that was cut."""
        if self.materials is None:
            raise CutError("this cut was made on a bare TetMesh: no materials to attach (cut a Specimen, or build Specimen(cut.mesh, materials))")
        return Specimen(self.mesh, self.materials)


# ==================================================================== helpers (host)
def _as_mesh(specimen):
    if isinstance(specimen, Specimen):
        return specimen.mesh, specimen.materials
    if isinstance(specimen, TetMesh):
        return specimen, None
    raise CutError(f"expected a TetMesh or Specimen to cut, got {type(specimen).__name__}")


def _node_lengths(mesh: TetMesh, points: np.ndarray):
    """Per-node lateral and vertical local edge lengths [m] (min over incident edges).

    Lattice specimens use the structural springs (cube edges): horizontal ones for the lateral
    length, vertical ones for the vertical length. Other meshes use the tet edges for both.
    """
    n = len(points)
    if mesh.lattice is not None:
        e = mesh.lattice.springs[mesh.lattice.spring_kind == 0]
    else:
        e = mesh.edges
    vec = points[e[:, 1]] - points[e[:, 0]]
    ln = np.linalg.norm(vec, axis=1)

    def per_node(mask):
        out = np.full(n, np.inf)
        np.minimum.at(out, e[mask, 0], ln[mask])
        np.minimum.at(out, e[mask, 1], ln[mask])
        return out

    if mesh.lattice is not None:
        vertical = np.abs(vec[:, 2]) > 0.5 * ln
        lat, vert = per_node(~vertical), per_node(vertical)
        lat = np.where(np.isfinite(lat), lat, vert)
        vert = np.where(np.isfinite(vert), vert, lat)
    else:
        lat = vert = per_node(np.ones(len(e), dtype=bool))
    fallback = float(np.median(ln))
    lat = np.where(np.isfinite(lat), lat, fallback)
    vert = np.where(np.isfinite(vert), vert, fallback)
    return lat, vert, e


def _top_faces(mesh: TetMesh, points, z_top, tol):
    bf = mesh.boundary_faces
    top = bf[np.all(np.abs(points[bf][:, :, 2] - z_top) <= tol, axis=1)]
    if len(top) == 0:
        raise CutError("the specimen has no flat top surface at z = max z to cut from")
    return top


def _inside_footprint(xy: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """Whether each 2-D point lies in the union of the triangles ``tri`` (T, 3, 2)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1 = b - a, c - a
    den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    ok = np.abs(den) > 0
    a, v0, v1, den = a[ok], v0[ok], v1[ok], den[ok]
    out = np.zeros(len(xy), dtype=bool)
    for i, p in enumerate(xy):
        r = p - a
        l1 = (r[:, 0] * v1[:, 1] - r[:, 1] * v1[:, 0]) / den
        l2 = (v0[:, 0] * r[:, 1] - v0[:, 1] * r[:, 0]) / den
        out[i] = bool(np.any((l1 >= -tol) & (l2 >= -tol) & (l1 + l2 <= 1 + tol)))
    return out


def _footprint_boundary_distance(xy: np.ndarray, top: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance of 2-D points to the outline of the top surface (edges of one top face)."""
    e = np.sort(top[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    outline = uniq[cnt == 1]
    a, b = points[outline[:, 0], :2], points[outline[:, 1], :2]
    ab = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    out = np.empty(len(xy))
    for i, p in enumerate(xy):
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / L2, 0.0, 1.0)
        out[i] = np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1))
    return out


def connected_components(tets: np.ndarray, n_nodes: int) -> tuple[int, np.ndarray]:
    """Connected components of the nodes linked through tets: ``(count, label per node)``.

    Nodes in no tet get their own labels (they count as components).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as cc

    t = np.asarray(tets)
    rows = np.repeat(t[:, 0], 3)
    cols = t[:, 1:].reshape(-1)
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_nodes, n_nodes))
    return cc(g, directed=False)


def _check_connectivity(tets, points, n_before: int, allow_disconnect: bool):
    used = np.zeros(len(points), dtype=bool)
    used[np.asarray(tets).reshape(-1)] = True
    count, labels = connected_components(tets, len(points))
    labels = np.where(used, labels, -1)
    comps = [lab for lab in np.unique(labels) if lab >= 0]
    if len(comps) <= n_before or allow_disconnect:
        return len(comps)
    sizes = sorted(((int(np.sum(labels == lab)), lab) for lab in comps), reverse=True)
    parts = []
    for size, lab in sizes[1:]:
        p = points[labels == lab]
        parts.append(f"{size} node(s) in the box {np.round(p.min(axis=0), 9).tolist()} - {np.round(p.max(axis=0), 9).tolist()} m")
    raise DisconnectedCutError(
        f"the cut splits the specimen into {len(comps)} parts (it had {n_before}); the part(s) cut off: "
        + "; ".join(parts)
        + ". Pass allow_disconnect=True if that is intended (a static solve then needs each part held)"
    )


def _n_components(mesh: TetMesh) -> int:
    used = np.zeros(mesh.n_nodes, dtype=bool)
    used[mesh.tets.reshape(-1)] = True
    _, labels = connected_components(mesh.tets, mesh.n_nodes)
    return len(np.unique(labels[used]))


class _Prepared(NamedTuple):
    mesh: TetMesh
    materials: Any
    points: np.ndarray
    geom: Any  # _Geometry (flat top) or _SurfaceGeometry (surface="boundary")
    depth: float
    through: bool
    open_start: bool
    open_end: bool
    lat: np.ndarray
    vert: np.ndarray
    struct_edges: np.ndarray
    scale: float
    #: surface="boundary" only: the nodes of the cut's surface patch (depth 0 by definition) and
    #: the boundary faces of the patch (a node on them may move along the curved surface).
    patch_nodes: np.ndarray | None = None
    patch_faces: np.ndarray | None = None


def _outline_distance(x: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """3-D distance of points ``x`` to the outline of a set of boundary ``faces`` (edges of one face)."""
    e = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    outline = uniq[cnt == 1]
    if len(outline) == 0:
        return np.full(len(x), np.inf)
    a, b = points[outline[:, 0]], points[outline[:, 1]]
    ab = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    out = np.empty(len(x))
    for i, q in enumerate(x):
        t = np.clip(np.einsum("ij,ij->i", q - a, ab) / L2, 0.0, 1.0)
        out[i] = np.min(np.linalg.norm(a + t[:, None] * ab - q, axis=1))
    return out


def _prepare_surface(mesh: TetMesh, materials, path: ScalpelPath) -> _Prepared:
    """:func:`_prepare` for a path on the boundary surface (``surface="boundary"``)."""
    pts = np.asarray(mesh.points, dtype=float)
    scale = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    lat, vert, struct = _node_lengths(mesh, pts)
    ell = float(np.median(lat))
    geom = _SurfaceGeometry(path, pts, mesh.boundary_faces, ell, scale)
    patch = geom.patch()
    thick = geom.thickness(scale)
    if not np.all(np.isfinite(thick)):
        k = int(np.flatnonzero(~np.isfinite(thick))[0])
        raise CutError(f"the blade at {np.round(geom.p[k], 9).tolist()} m finds no far side of the specimen along the surface normal")
    if path.through:
        depth = float(thick.max())
        if path.depth is not None and path.depth > depth * (1 + 1e-9):
            raise CutError(f"cut depth {path.depth:.6g} m exceeds the specimen thickness under the path, {depth:.6g} m along the surface normal")
    else:
        k = int(np.argmin(thick))
        if path.depth >= thick[k] * (1 - 1e-9):
            raise CutError(
                f"cut depth {path.depth:.6g} m reaches or exceeds the specimen thickness {thick[k]:.6g} m (along the blade from the surface "
                f"at {np.round(geom.p[k], 9).tolist()} m); a cut through the whole thickness must be asked for with through=True"
            )
        depth = float(path.depth)
    faces = mesh.boundary_faces[patch]
    ends = _outline_distance(geom.p[[0, -1]], faces, pts)
    open_start, open_end = bool(ends[0] <= 1e-6 * ell), bool(ends[1] <= 1e-6 * ell)
    nodes = np.zeros(len(pts), dtype=bool)
    nodes[faces.reshape(-1)] = True
    return _Prepared(mesh, materials, pts, geom, depth, path.through, open_start, open_end, lat, vert, struct, scale, nodes, patch)


def _prepare(specimen, path: ScalpelPath) -> _Prepared:
    if not isinstance(path, ScalpelPath):
        raise CutError(f"path must be a ScalpelPath, got {type(path).__name__}")
    mesh, materials = _as_mesh(specimen)
    if path.surface == "boundary":
        return _prepare_surface(mesh, materials, path)
    pts = np.asarray(mesh.points, dtype=float)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = float(np.linalg.norm(hi - lo))
    z_top = float(hi[2])
    thickness = float(hi[2] - lo[2])
    ztol = 1e-9 * scale
    if path.points.shape[1] == 3:
        off = np.abs(path.points[:, 2] - z_top)
        if np.any(off > 1e-6 * scale):
            k = int(np.argmax(off))
            raise CutError(f"scalpel path point {k} has z = {path.points[k, 2]:.6g} m; the top surface is at z = {z_top:.6g} m (3-D path points must lie on it)")
    if path.through:
        if path.depth is not None and path.depth > thickness * (1 + 1e-9):
            raise CutError(f"cut depth {path.depth:.6g} m exceeds the specimen thickness {thickness:.6g} m")
        depth = thickness
    else:
        if path.depth >= thickness * (1 - 1e-9):
            raise CutError(
                f"cut depth {path.depth:.6g} m reaches or exceeds the specimen thickness {thickness:.6g} m; "
                "a cut through the whole thickness must be asked for with through=True"
            )
        depth = float(path.depth)
    if path.tilt != 0.0:
        shift = depth * abs(np.tan(path.tilt))
    else:
        shift = 0.0
    lat, vert, struct = _node_lengths(mesh, pts)
    ell = float(np.median(lat))
    top = _top_faces(mesh, pts, z_top, ztol)
    tri = pts[top][:, :, :2]
    # Sample the path (and, for a tilted blade, its bottom line) and check it lies on the top.
    samples = []
    for a, b in zip(path.xy[:-1], path.xy[1:]):
        m = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.25 * ell))) + 1)
        samples.append(a + np.linspace(0, 1, m)[:, None] * (b - a))
    samples = np.concatenate(samples)
    inside = _inside_footprint(samples, tri, 1e-9)
    if not np.all(inside):
        k = int(np.flatnonzero(~inside)[0])
        raise CutError(
            f"the scalpel path leaves the specimen's top surface at ({samples[k, 0]:.6g}, {samples[k, 1]:.6g}) m; "
            f"the specimen spans x {lo[0]:.6g}..{hi[0]:.6g}, y {lo[1]:.6g}..{hi[1]:.6g} m"
        )
    geom = _Geometry(path, z_top)
    if shift > 0:
        bottom = samples + depth * np.tan(path.tilt) * geom.normal[0]
        if not np.all(_inside_footprint(bottom, tri, 1e-9)):
            raise CutError("the tilted blade leaves the specimen below the surface (its bottom line is outside the footprint)")
    ends = _footprint_boundary_distance(path.xy[[0, -1]], top, pts)
    open_start, open_end = bool(ends[0] <= 1e-6 * ell), bool(ends[1] <= 1e-6 * ell)
    return _Prepared(mesh, materials, pts, geom, depth, path.through, open_start, open_end, lat, vert, struct, scale)


def _acceptable(q_new, q_old, guard):
    """A snapped tet is acceptable when positive and not below ``min(guard, q_old / 2)`` (a tet
    that was already poor may stay poor, but snapping may not ruin it)."""
    return (q_new > 0) & (q_new >= np.minimum(guard, 0.5 * q_old))


#: The vertical, +z (a flat top's outward normal).
_UP = np.array([0.0, 0.0, 1.0])


class _Mover:
    """Moves nodes one at a time, refusing a move that would push an incident tet below the
    quality ``guard`` (or invert it), or move a boundary node off its boundary faces (the
    specimen's shape and volume never change)."""

    def __init__(self, pts, tets, guard, bfaces, free_faces=None):
        self.pts, self.tets, self.guard = pts, tets, guard
        # boundary faces whose normals do not constrain a move (a curved surface patch)
        self.free_faces = free_faces
        order = np.argsort(tets.reshape(-1), kind="stable")
        self.ptr = np.searchsorted(tets.reshape(-1)[order], np.arange(len(pts) + 1))
        self.tet_of = order // 4
        p = pts[bfaces]
        nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        self.bnormals = nrm
        border = np.argsort(bfaces.reshape(-1), kind="stable")
        self.bptr = np.searchsorted(bfaces.reshape(-1)[border], np.arange(len(pts) + 1))
        self.bface_of = border // 3

    def incident(self, v):
        return self.tet_of[self.ptr[v] : self.ptr[v + 1]]

    def normals(self, v):
        """Distinct unit normals of the boundary faces at node ``v`` (the free faces left out)."""
        fv = self.bface_of[self.bptr[v] : self.bptr[v + 1]]
        if self.free_faces is not None:
            fv = fv[~self.free_faces[fv]]
        nv = self.bnormals[fv]
        out: list[np.ndarray] = []
        for n in nv:
            if not any(abs(float(n @ m)) > 1 - 1e-9 for m in out):
                out.append(n)
        return out

    def tangential(self, v, move) -> bool:
        size = float(np.linalg.norm(move))
        return all(abs(float(n @ move)) <= 1e-9 * size for n in self.normals(v))

    def try_move(self, v, new) -> bool:
        old = self.pts[v].copy()
        if np.array_equal(old, new):
            return True
        if not self.tangential(v, new - old):
            return False
        ts = self.tets[self.incident(v)]
        q_old = mean_ratio_quality(self.pts, ts)
        self.pts[v] = new
        if len(ts) and np.any(~_acceptable(mean_ratio_quality(self.pts, ts), q_old, self.guard)):
            self.pts[v] = old
            return False
        return True


def _snap(prep: _Prepared, phases: Sequence[np.ndarray], guard: float):
    """Surface, end and bottom snapping. Returns new points, snapped mask, ``(s, h)`` of every
    node after snapping, and the moved-node mask."""
    g, d = prep.geom, prep.depth
    pts0 = prep.points
    s, n, h = g.coords(pts0)
    lat, vert = prep.lat, prep.vert
    L = g.length
    tol = 1e-9 * lat
    curved = prep.patch_nodes is not None
    if curved:
        h[prep.patch_nodes] = 0.0  # the nodes of the cut's surface lie at depth 0
    mover = _Mover(pts0.copy(), prep.mesh.tets, guard, prep.mesh.boundary_faces, free_faces=prep.patch_faces)
    s_lo = np.zeros(len(pts0)) if prep.open_start else -0.5 * lat
    s_hi = np.full(len(pts0), L) if prep.open_end else L + 0.5 * lat
    depth_ok = h < d + 0.5 * vert if not prep.through else np.ones(len(pts0), dtype=bool)
    on = (np.abs(n) <= tol) & (s >= s_lo - tol) & (s <= s_hi + tol) & depth_ok
    snapped = on.copy()
    # A node is moved by at most half the crossing edge's length, never from below the bottom
    # region, and never so that an incident tet falls below the quality guard; an edge whose
    # endpoints cannot move is left (a bridge across the open part of the cut is refused later
    # by _check_bridges).

    def move_onto_blade(v, target, up, rate_of, reach) -> bool:
        # Node v to ``target`` on the blade; a node on another boundary face (a side face),
        # whose move would leave that face, slides along it instead, normal to ``up`` (the
        # blade's depth direction reversed), by the signed distance n[v] over the rate
        # ``rate_of(direction, segment)`` at which that slide approaches the blade.
        if mover.tangential(v, target - pts0[v]):
            if mover.try_move(v, target):
                snapped[v] = True
                return True
            return False
        side = [m for m in mover.normals(v) if abs(float(m @ up)) < 1 - 1e-9]
        if len(side) != 1:
            return False
        dvec = np.cross(up, side[0])
        dvec /= np.linalg.norm(dvec)
        rate = rate_of(dvec, g.segment_of(s[v : v + 1])[0])
        if abs(rate) < 0.3 or abs(n[v] / rate) > reach:
            return False
        target = pts0[v] - (n[v] / rate) * dvec
        s_t, n_t, _ = g.coords(target[None])
        if abs(n_t[0]) > 1e-9 * lat[v]:
            return False
        if mover.try_move(v, target):
            s[v] = s_t[0]
            snapped[v] = True
            return True
        return False

    def snap_to_curved(v, reach) -> bool:
        # A node of the surface patch goes to the path point (it stays on the surface, to the
        # path's chord accuracy), any other to the blade point at its own depth.
        target = g.surface_point(s[v : v + 1], h[v : v + 1])[0]
        if np.linalg.norm(target - pts0[v]) <= 1e-12 * lat[v]:
            target = pts0[v]  # already on the blade (round-off): not a move
        k = g.segment_of(s[v : v + 1])[0]
        return move_onto_blade(v, target, -g.b[k], lambda dvec, k: float(dvec @ g.normal[k]), reach)

    def snap_to_surface(v, reach) -> bool:
        if curved:
            return snap_to_curved(v, reach)
        # flat: the blade point at the node's height; a side-face node slides horizontally
        target = np.array([*g.surface_xy(s[v : v + 1], h[v : v + 1])[0], pts0[v, 2]])
        return move_onto_blade(v, target, _UP, lambda dvec, k: float(dvec[:2] @ g.normal[k]), reach)

    for e in phases:
        i, j = e[:, 0], e[:, 1]
        cross = (n[i] * n[j] < 0) & ~snapped[i] & ~snapped[j] & (np.abs(n[i]) > tol[i]) & (np.abs(n[j]) > tol[j])
        if not np.any(cross):
            continue
        i, j = i[cross], j[cross]
        t = n[i] / (n[i] - n[j])
        sc = s[i] + t * (s[j] - s[i])
        hc = h[i] + t * (h[j] - h[i])
        ok = (sc >= np.minimum(s_lo[i], s_lo[j])) & (sc <= np.maximum(s_hi[i], s_hi[j]))
        if not prep.through:
            ok &= hc < d + 0.5 * np.minimum(vert[i], vert[j])
        i, j = i[ok], j[ok]
        ai, aj = np.abs(n[i]) / lat[i], np.abs(n[j]) / lat[j]
        tie = np.isclose(ai, aj, rtol=1e-9, atol=0.0)
        pick_i = (ai < aj) | (tie & (n[i] > 0))
        first = np.where(pick_i, i, j)
        second = np.where(pick_i, j, i)
        elen = np.linalg.norm(pts0[i] - pts0[j], axis=1)
        for k in np.argsort(np.minimum(ai, aj), kind="stable"):
            a, b = int(first[k]), int(second[k])
            if snapped[a] or snapped[b]:
                continue
            reach = (0.5 + 1e-9) * max(elen[k], min(lat[a], lat[b]))
            if depth_ok[a] and abs(n[a]) <= reach and snap_to_surface(a, reach):
                continue
            if depth_ok[b] and abs(n[b]) <= reach:
                snap_to_surface(b, reach)
    s_new, h_new = s.copy(), h.copy()

    def place(v, sv, hv) -> bool:
        if curved:
            target = g.surface_point(np.array([sv]), np.array([hv]))[0]
            if np.linalg.norm(target - mover.pts[v]) <= 1e-12 * lat[v]:
                target = mover.pts[v].copy()
        else:
            xy = g.surface_xy(np.array([sv]), np.array([hv]))[0]
            target = np.array([xy[0], xy[1], g.z_top - hv])
        if mover.try_move(v, target):
            s_new[v], h_new[v] = sv, hv
            return True
        return False

    # End snapping (ends inside the specimen only): the snapped nodes nearest an end go onto
    # it, one per depth level (seed 003 §3.1).
    for s_end, is_open in ((0.0, prep.open_start), (L, prep.open_end)):
        if is_open:
            continue
        cand = np.flatnonzero(snapped & (np.abs(s - s_end) < 0.5 * lat))
        cand = cand[np.argsort(np.abs(s[cand] - s_end), kind="stable")]
        taken: list[int] = []
        for c in cand:
            if any(abs(h[c] - h[o]) < 0.5 * min(vert[c], vert[o]) for o in taken):
                continue
            if place(int(c), s_end, h[c]):
                taken.append(int(c))
    # Bottom snapping (seed 003 §3.2, §3.4): per column the snapped node nearest the cut bottom
    # within half a cell goes onto it, unless it lies on a layer interface (case 1 of §3.4: an
    # interface the blade has not reached, or has just passed, is not moved).
    if not prep.through:
        regions = prep.mesh.region_ids
        tets = prep.mesh.tets
        rmin = np.full(len(pts0), np.iinfo(np.int32).max)
        rmax = np.full(len(pts0), -1)
        np.minimum.at(rmin, tets.reshape(-1), np.repeat(regions, 4))
        np.maximum.at(rmax, tets.reshape(-1), np.repeat(regions, 4))
        one_layer = rmin == rmax
        near = np.where(h <= d, d - h <= 0.5 * vert, h - d < 0.5 * vert)
        cand = np.flatnonzero(snapped & near & (h > 1e-9 * vert) & (one_layer | (np.abs(h - d) <= tol)))
        cand = cand[np.argsort(np.abs(h[cand] - d), kind="stable")]
        taken = []
        for c in cand:
            if any(abs(s_new[c] - s_new[o]) < 0.5 * min(lat[c], lat[o]) for o in taken):
                continue
            if place(int(c), s_new[c], d):
                taken.append(int(c))
        # §3.4 case 2: where no node went onto the bottom (the nearest lies on a layer interface,
        # or is the surface row), a node of the layer the blade tip is in (an incident tet spans
        # the bottom depth), up to one cell away, goes onto it, so the cut reaches into that layer.
        spans = (h[tets].min(axis=1) < d) & (h[tets].max(axis=1) > d)
        reg_at_d = np.full(len(pts0), -1)
        reg_at_d[tets[spans].reshape(-1)] = np.repeat(regions[spans], 4)
        lateral = snapped | (np.abs(n) <= (0.5 + 1e-9) * lat)
        cand = np.flatnonzero(
            one_layer & (reg_at_d == rmin) & (np.abs(h - d) < vert) & (h > 1e-9 * vert) & lateral & (s >= s_lo) & (s <= s_hi)
        )
        cand = cand[np.argsort(np.abs(h[cand] - d), kind="stable")]
        for c in cand:
            if any(abs(s_new[c] - s_new[o]) < 0.5 * min(lat[c], lat[o]) for o in taken):
                continue
            if place(int(c), s_new[c], d):
                taken.append(int(c))
                snapped[c] = True
    pts = mover.pts
    moved_any = np.any(pts != pts0, axis=1)
    return pts, snapped, s_new, h_new, moved_any


def _interior_faces(tets):
    """Interior faces ``(F, 3)`` and the two tets sharing each."""
    t = np.asarray(tets)
    faces = t[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    owner = np.repeat(np.arange(len(t)), 4)
    order = np.argsort(inverse, kind="stable")
    inv_sorted = inverse[order]
    twice = counts[inv_sorted] == 2
    first = order[twice][0::2]
    second = order[twice][1::2]
    return faces[first], owner[first], owner[second]


def _quality(before_pts, after_pts, tets, *, threshold, min_quality, moved, lat, lattice_before, lattice_after, n_dup, n_removed=0, extra=None):
    q0 = mean_ratio_quality(before_pts, tets)
    q1 = mean_ratio_quality(after_pts, tets)
    bad = np.flatnonzero(~_acceptable(q1, q0, min_quality))
    if bad.size:
        vol = signed_volumes(after_pts, tets)[bad]
        inverted = bad[vol < 0]
        kind = "inverted" if inverted.size else "degenerate"
        raise CutError(
            f"snapping onto the cut leaves {bad.size} {kind} tet(s) (mean-ratio quality below min({min_quality:g}, half its quality before)): elements {_cite(bad)} "
            f"(qualities {np.round(q1[bad[:8]], 4).tolist()}); refine the mesh near the cut, move the path off the nodes, or use method='remove'",
            bad,
        )
    move = np.linalg.norm(after_pts - before_pts, axis=1)
    jac = None
    if lattice_before is not None:
        j0 = np.asarray(jax.vmap(hexahedron_jacobians)(jnp.asarray(before_pts[lattice_before])))
        j1 = np.asarray(jax.vmap(hexahedron_jacobians)(jnp.asarray(after_pts[lattice_after])))
        ratio = (j1 / j0).min(axis=1)
        jac = float(ratio.min())
        badc = np.flatnonzero(ratio <= min_quality)
        if badc.size:
            raise CutError(f"snapping onto the cut inverts or flattens {badc.size} lattice cube(s): cubes {_cite(badc)} (Jacobian ratio {np.round(ratio[badc[:8]], 4).tolist()})", badc)
    order = np.argsort(q1)
    return CutQuality(
        min_quality_before=float(q0.min()),
        min_quality_after=float(q1.min()),
        threshold=float(threshold),
        n_below_threshold=int(np.sum(q1 < threshold)),
        worst_elements=tuple(int(i) for i in order[: min(8, len(order))] if q1[i] < threshold),
        n_snapped=int(np.sum(moved)),
        max_snap_distance=float(move.max()) if len(move) else 0.0,
        max_snap_relative=float(np.max(move / lat)) if len(move) else 0.0,
        min_cell_jacobian_ratio=jac,
        n_duplicated=int(n_dup),
        n_removed=int(n_removed),
        **(extra or {}),
    )


def _surface_order(pair_s, pair_depth, scale):
    surf = np.flatnonzero(np.abs(pair_depth) <= 1e-9 * scale)
    return surf[np.argsort(pair_s[surf], kind="stable")].astype(np.int32)


# ============================================================================ snapping
def cut_specimen(
    specimen,
    path: ScalpelPath,
    *,
    method: str = "snap",
    allow_disconnect: bool = False,
    quality_threshold: float = 0.1,
    min_quality: float = 0.01,
    split_cubes: str = "drop",
) -> Cut:
    """Cut a specimen along a scalpel path (the whole path at once; see :class:`CutClosureModel`
    for a cut in progress).

    ``method="snap"`` (seed 003): the nodes nearest the cutting surface are snapped onto it —
    for every mesh edge the surface crosses (structural cube edges first on lattice specimens,
    then any remaining tet edge), its endpoint nearer the surface relative to its local edge
    length, ties to the ``+`` side, a move refused if it would ruin an incident tet or take a
    boundary node off its boundary faces — then, per column, the snapped node nearest the cut
    bottom goes onto the bottom (seed 003 §3.2, §3.4; layer interfaces are not moved) and at each
    end inside the specimen the node nearest the end goes onto it. Every tet is put on the side
    of its centroid; the faces between a ``+`` and a ``-`` tet on the open part of the cut
    (between the ends, above the bottom; an end on the specimen's outline counts as open) are
    the cut faces, and their nodes are duplicated except the crack front (nodes also on an uncut
    ``+``/``-`` face). Tets and lattice cubes on the ``-`` side (right of the path direction)
    use the duplicates. ``method="staircase"`` (lattice specimens): no node moves; the cut
    follows the cube faces between the cubes whose centres lie on either side of the path, so
    every cube stays a box on one side (see :func:`staircase_cut`). ``method="remove"``
    (seed 000): see :func:`remove_elements`.

    Args:
        specimen: a :class:`~difftissue.mesh.TetMesh` or :class:`~difftissue.mesh.Specimen`
            (block, layered_skin or an imported mesh; imported meshes have no lattice, so only
            tets are reconnected and the ``springs_volume`` model is unavailable on them).
        path: the :class:`ScalpelPath`.
        allow_disconnect: accept a cut that splits off a part (refused by default with
            :class:`~difftissue.errors.DisconnectedCutError` naming the part).
        quality_threshold: tets below this mean-ratio quality are counted in the report.
        min_quality: tets below ``min(min_quality, half their quality before)`` (or inverted,
            or lattice cubes whose Jacobian ratio falls below it) are refused with
            :class:`~difftissue.errors.CutError`; snapping moves that would cause that are not made.
        split_cubes: lattice cubes the cut passes through (diagonally; they cannot be split
            without new elements): ``"drop"`` them from the lattice (default: the spring model
            loses their stiffness, the tets are unaffected) or ``"keep"`` them on the side of
            their centroid (their springs and volume term then bridge the cut). On a 25-degree
            through-cut in a plate under tension the springs_volume opening was -48 % of FEM's
            with "keep" and +25 % with "drop" (+12 % on a lattice-aligned cut): see docs/cutting.md.
            Not used by ``method="staircase"``, which splits no cube.

    Returns:
        A :class:`Cut`.
    """
    if method == "remove":
        return remove_elements(specimen, path, allow_disconnect=allow_disconnect, quality_threshold=quality_threshold)
    if method not in ("snap", "staircase"):
        raise CutError(f"method must be 'snap', 'staircase' or 'remove', got {method!r}")
    if split_cubes not in ("keep", "drop"):
        raise CutError(f"split_cubes must be 'keep' or 'drop', got {split_cubes!r}")
    if method == "staircase":
        return staircase_cut(specimen, path, allow_disconnect=allow_disconnect, quality_threshold=quality_threshold)
    split_cube_policy = split_cubes
    prep = _prepare(specimen, path)
    mesh = prep.mesh
    n_before = _n_components(mesh)
    phases = [prep.struct_edges, mesh.edges] if mesh.lattice is not None else [mesh.edges]
    new_pts, snapped, s, h, moved = _snap(prep, phases, min_quality)
    g = prep.geom
    tets = mesh.tets
    # Sides of all tets by centroid; the cut faces are the faces between a + and a - tet whose
    # centroid lies on the open part of the cut (between the ends, above the bottom).
    s_c, n_c, h_c = g.coords(new_pts[tets].mean(axis=1))
    side = np.where(n_c >= 0, 1, -1).astype(np.int8)
    faces, owner_a, owner_b = _interior_faces(tets)
    interface = side[owner_a] != side[owner_b]
    fs, fn, fh = g.coords(new_pts[faces].mean(axis=1))
    L = g.length
    in_s = (fs > (-np.inf if prep.open_start else 1e-9 * L)) & (fs < (np.inf if prep.open_end else L * (1 - 1e-9)))
    in_h = np.ones(len(fh), dtype=bool) if prep.through else fh < prep.depth * (1 - 1e-9)
    cut_face = interface & in_s & in_h
    front = np.zeros(len(new_pts), dtype=bool)
    front[faces[interface & ~cut_face].reshape(-1)] = True
    dup = np.zeros(len(new_pts), dtype=bool)
    dup[faces[cut_face].reshape(-1)] = True
    dup &= ~front
    D = np.flatnonzero(dup)
    if D.size == 0:
        raise CutError(
            f"the cut (length {L:.4g} m, depth {prep.depth:.4g} m) duplicates no node: it is too short or too shallow "
            f"for the mesh (local edge ~{float(np.median(prep.lat)):.3g} m); refine the mesh or lengthen the cut"
        )
    N = len(new_pts)
    dup_index = np.full(N, -1)
    dup_index[D] = N + np.arange(D.size)
    touches = np.any(dup[tets], axis=1)
    tet_side = np.where(touches, side, 0).astype(np.int8)
    new_tets = tets.copy()
    m = (tet_side < 0)[:, None] & dup[tets]
    new_tets[m] = dup_index[tets[m]]
    all_pts = np.concatenate([new_pts, new_pts[D]])
    node_origin = np.concatenate([np.arange(N), D]).astype(np.int32)
    _, n_new, _ = g.coords(new_pts)
    off_surface = int(np.sum(np.abs(n_new[D]) > 1e-6 * prep.lat[D]))
    # Tets with corners strictly on both sides inside the cut (the cut passes through them).
    tn = n_new[tets]
    ttol = 1e-6 * prep.lat[tets]
    s_t, h_t = s[tets], h[tets]
    in_cut = np.all((s_t > (-np.inf if prep.open_start else 0.0)) & (s_t < (np.inf if prep.open_end else L)), axis=1)
    if not prep.through:
        in_cut &= np.all(h_t < prep.depth * (1 - 1e-9), axis=1)
    bridging = int(np.sum(np.any(tn > ttol, axis=1) & np.any(tn < -ttol, axis=1) & in_cut))
    lattice = None
    lat_cubes = None
    split_cubes = None
    split_kept = None
    if mesh.lattice is not None:
        cubes = mesh.lattice.cubes
        _, nc, _ = g.coords(new_pts[cubes].mean(axis=1))
        cube_side = np.where(nc >= 0, 1, -1)
        new_cubes = cubes.copy()
        mc = (cube_side < 0)[:, None] & dup[cubes]
        new_cubes[mc] = dup_index[cubes[mc]]
        lat_cubes = cubes
        # A cube with duplicated nodes and nodes strictly on both sides: its springs bridge the cut.
        tol = 1e-6 * prep.lat[cubes]
        nn = n_new[cubes]
        split = np.any(dup[cubes], axis=1) & np.any(nn > tol, axis=1) & np.any(nn < -tol, axis=1)
        split_cubes = int(split.sum())
        keep = np.ones(len(cubes), dtype=bool)
        if split_cubes and split_cube_policy == "drop":
            keep = ~split
            # A split cube that alone holds a node (no other cube has it) stays: a node without
            # springs would leave the spring model singular.
            held = np.zeros(len(all_pts), dtype=bool)
            held[new_cubes[keep].reshape(-1)] = True
            keep |= split & np.any(~held[new_cubes], axis=1)
        split_kept = int(np.sum(split & keep))
        lattice = _build_lattice(new_cubes[keep], all_pts, mesh.lattice.cube_region_ids[keep])
        # Snapped cubes are no longer boxes: keep each cube's box edge lengths from before the
        # snapping (the spring factors of springs_volume derive from them; rest lengths and
        # volumes come from the snapped points).
        lattice = eqx.tree_at(lambda lt: lt.cell_size, lattice, mesh.lattice.cell_size[keep])
    quality = _quality(
        prep.points, new_pts, tets, threshold=quality_threshold, min_quality=min_quality, moved=moved, lat=prep.lat,
        lattice_before=lat_cubes, lattice_after=lat_cubes, n_dup=D.size,
        extra=dict(n_cut_faces=int(cut_face.sum()), n_off_surface=off_surface, n_bridging_tets=bridging, n_split_cubes=split_cubes,
                   split_cubes=split_cube_policy if mesh.lattice is not None else None, n_split_cubes_kept=split_kept,
                   **_opened_geometry(new_pts, faces[cut_face], g, prep)),
    )
    return _cut_from_duplicates(mesh, prep, g, all_pts, new_tets, lattice, D, dup_index, s, h, tet_side, node_origin, quality,
                                method="snap", n_before=n_before, allow_disconnect=allow_disconnect)


def _cut_from_duplicates(mesh, prep, g, all_pts, new_tets, lattice, D, dup_index, s, h, tet_side, node_origin, quality, *,
                         method: str, n_before: int, allow_disconnect: bool) -> "Cut":
    """The :class:`Cut` of a mesh whose nodes ``D`` were duplicated (copies ``dup_index[D]``):
    the new mesh (point data copied to the duplicates), the connectivity check, and the pairs
    with their path coordinates ``s``, ``h`` [m] (shared by the snapped and the staircase cut)."""
    pd = {k: np.concatenate([v, v[D]]) for k, v in mesh.point_data.items()}
    new_mesh = TetMesh(all_pts, new_tets, mesh.region_ids, mesh.region_names, point_data=pd, cell_data=mesh.cell_data, lattice=lattice, validate=False)
    _check_connectivity(new_tets, all_pts, n_before, allow_disconnect)
    pair_s, pair_h = s[D], h[D]
    return Cut(
        mesh=new_mesh,
        pairs=np.stack([D, dup_index[D]], axis=1).astype(np.int32),
        pair_s=pair_s,
        pair_depth=pair_h,
        pair_normal=g.unit_normal(pair_s),
        pair_rest_offset=np.zeros((D.size, 3)),
        tet_side=tet_side,
        surface_pairs=_surface_order(pair_s, pair_h, prep.scale),
        node_origin=node_origin,
        materials=prep.materials,
        length=g.length,
        depth=prep.depth,
        method=method,
        through=prep.through,
        quality=quality,
    )


def _opened_geometry(points, faces, g: "_Geometry", prep: "_Prepared") -> dict:
    """Geometric error of the opened faces ``(F, 3)`` triangles or ``(F, 4)`` lattice quads
    (corners in :data:`_CUBE_FACES` order) against the ideal cutting surface: their area, the
    ideal area (path length x depth / cos(tilt)) [m^2] and the largest distance of their nodes
    from the ideal surface [m] (the horizontal offset times cos(tilt))."""
    p = points[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(cross, axis=1)
    if faces.shape[1] == 3:
        area = 0.5 * area
    nodes = np.unique(faces.reshape(-1))
    _, n, _ = g.coords(points[nodes])
    cos_tilt = 1.0 / np.sqrt(1.0 + g.tan_tilt**2)
    return dict(
        cut_area=float(area.sum()),
        ideal_area=float(g.length * prep.depth / cos_tilt),
        max_normal_distance=float(np.max(np.abs(n)) * cos_tilt) if nodes.size else 0.0,
    )


def _cube_faces(cubes: np.ndarray):
    """Interior faces of a cube lattice: ``(F, 4)`` node quads and the two cubes sharing each."""
    quads = cubes[:, _CUBE_FACES].reshape(-1, 4)
    _, inverse, counts = np.unique(np.sort(quads, axis=1), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    twice = counts[inverse[order]] == 2
    first, second = order[twice][0::2], order[twice][1::2]
    return quads[first], first // 6, second // 6


def staircase_cut(specimen, path: ScalpelPath, *, allow_disconnect: bool = False, quality_threshold: float = 0.1) -> Cut:
    """Cut a lattice specimen along cube faces (a staircase, face-aligned or voxel cut; no node
    moves).

    Every lattice cube is put on the side of the cutting surface its centre lies on (``+`` to
    the left of the path direction, a centre on the surface counts as ``+``). The opened faces
    are the cube faces between a ``+`` and a ``-`` cube whose centre-to-centre segment crosses
    the cutting surface on the open part of the cut (between the path ends, above the cut
    depth; an end on the specimen's outline counts as open, a through-cut has no bottom).
    Their nodes are duplicated except the crack front (nodes also on a face between a ``+`` and
    a ``-`` cube that is not opened); cubes and their 6 tets on the ``-`` side use the
    duplicates. So every cube stays the undistorted box it was, wholly on one side: the
    ``springs_volume`` lattice is intact on both sides of the cut and no cube is split,
    dropped or left bridging the cut. The price is geometric: the opened faces are a staircase
    within about half a cell of the ideal surface; the ends and the depth round to the nearest
    lattice face. :class:`CutQuality` reports the staircase's area against the ideal surface's
    (``|cos theta| + |sin theta|`` times for a vertical cut at angle ``theta`` to the lattice) and
    its largest distance from it. On a path along a lattice line the result equals
    ``method="snap"`` (no node is snapped there either).

    Args:
        specimen: a structured :class:`~difftissue.mesh.TetMesh` or
            :class:`~difftissue.mesh.Specimen` (``block``, ``layered_skin``, ``structured_grid``:
            a cube lattice whose cubes are split into 6 tets each). Other meshes are refused
            with :class:`~difftissue.errors.CutError`.
        path, allow_disconnect, quality_threshold: as in :func:`cut_specimen`.

    Returns:
        A :class:`Cut` with ``method == "staircase"``; its quality counts ``n_cut_faces`` in
        tet faces (two per opened cube face).
    """
    prep = _prepare(specimen, path)
    mesh, g = prep.mesh, prep.geom
    cmap = _tet_cube_map(mesh)
    if cmap is None:
        raise CutError(
            "method='staircase' cuts along the faces of a cube lattice: it needs a structured specimen "
            "(difftissue.mesh.block, layered_skin or structured_grid) whose tets are the 6-tets-per-cube split of its lattice; "
            "this mesh has " + ("no lattice" if mesh.lattice is None else "tets that do not match its lattice")
            + " (use method='snap' or 'remove')"
        )
    n_before = _n_components(mesh)
    pts = prep.points
    cubes = mesh.lattice.cubes
    cs, cn, ch = g.coords(pts[cubes].mean(axis=1))
    cube_side = np.where(cn >= 0, 1, -1).astype(np.int8)
    quads, ca, cb = _cube_faces(cubes)
    interface = cube_side[ca] != cube_side[cb]
    # Where the centre-to-centre segment crosses the cutting surface.
    den = np.where(interface, cn[ca] - cn[cb], 1.0)
    t = np.where(interface, cn[ca] / den, 0.5)
    sc = cs[ca] + t * (cs[cb] - cs[ca])
    hc = ch[ca] + t * (ch[cb] - ch[ca])
    L = g.length
    # A crossing exactly at an end or at the depth (a cube centre there) is not opened: the
    # tolerance makes that tie independent of round-off (the cut rounds inwards).
    in_s = (sc > (-np.inf if prep.open_start else 1e-9 * L)) & (sc < (np.inf if prep.open_end else L * (1 - 1e-9)))
    in_h = np.ones(len(hc), dtype=bool) if prep.through else hc < prep.depth * (1 - 1e-9)
    cut_face = interface & in_s & in_h
    N = len(pts)
    front = np.zeros(N, dtype=bool)
    front[quads[interface & ~cut_face].reshape(-1)] = True
    dup = np.zeros(N, dtype=bool)
    dup[quads[cut_face].reshape(-1)] = True
    dup &= ~front
    D = np.flatnonzero(dup)
    if D.size == 0:
        raise CutError(
            f"the staircase cut (length {L:.4g} m, depth {prep.depth:.4g} m) opens no node: it crosses no cube face between cube "
            f"centres inside the cut; the lattice (cells ~{float(np.median(prep.lat)):.3g} m) is too coarse for it: refine or lengthen the cut"
        )
    dup_index = np.full(N, -1)
    dup_index[D] = N + np.arange(D.size)
    tets = mesh.tets
    side = cube_side[cmap]
    tet_side = np.where(np.any(dup[tets], axis=1), side, 0).astype(np.int8)
    new_tets = tets.copy()
    m = (tet_side < 0)[:, None] & dup[tets]
    new_tets[m] = dup_index[tets[m]]
    new_cubes = cubes.copy()
    m = (cube_side < 0)[:, None] & dup[cubes]
    new_cubes[m] = dup_index[cubes[m]]
    all_pts = np.concatenate([pts, pts[D]])
    node_origin = np.concatenate([np.arange(N), D]).astype(np.int32)
    lattice = _build_lattice(new_cubes, all_pts, mesh.lattice.cube_region_ids)
    lattice = eqx.tree_at(lambda lt: lt.cell_size, lattice, mesh.lattice.cell_size)
    s, n, h = g.coords(pts)
    if prep.patch_nodes is not None:
        h[prep.patch_nodes] = 0.0
    quality = _quality(
        pts, pts, tets, threshold=quality_threshold, min_quality=0.0, moved=np.zeros(N, dtype=bool), lat=prep.lat,
        lattice_before=cubes, lattice_after=cubes, n_dup=D.size,
        extra=dict(n_cut_faces=2 * int(cut_face.sum()), n_off_surface=int(np.sum(np.abs(n[D]) > 1e-6 * prep.lat[D])), n_bridging_tets=0,
                   n_split_cubes=0, **_opened_geometry(pts, quads[cut_face], g, prep)),
    )
    return _cut_from_duplicates(mesh, prep, g, all_pts, new_tets, lattice, D, dup_index, s, h, tet_side, node_origin, quality,
                                method="staircase", n_before=n_before, allow_disconnect=allow_disconnect)


# ===================================================================== element removal
def _tet_cube_map(mesh: TetMesh):
    """Cube of each tet for structured specimens (6 Freudenthal tets per cube, in order)."""
    lat = mesh.lattice
    if lat is None or mesh.n_tets != 6 * lat.n_cubes:
        return None
    expect = np.sort(lat.cubes[:, _KUHN_TETS].reshape(-1, 4), axis=1)
    if not np.array_equal(np.sort(mesh.tets, axis=1), expect):
        return None
    return np.repeat(np.arange(lat.n_cubes), 6)


def remove_elements(specimen, path: ScalpelPath, *, allow_disconnect: bool = False, quality_threshold: float = 0.1) -> Cut:
    """Cut by removing the elements the cutting surface crosses (seed 000, the simple alternative).

    A tet is removed when it has nodes on both sides of the cutting surface (a node on the
    surface counts as ``+``) and one of its edges crosses the surface strictly inside the cut
    (between the path ends, above the bottom). On lattice specimens the whole cube of such a
    tet is removed (its 6 tets and its springs), so the lattice stays consistent. Nodes left in
    no element are dropped. ``pairs`` then hold the nodes facing each other across the removed
    slab (``+`` side, ``-`` side: matched by the nearest ``(s, depth)``), with their rest offset,
    so :func:`opening_width` measures the gap (its rest value is the slab width).
    """
    prep = _prepare(specimen, path)
    mesh, g = prep.mesh, prep.geom
    n_before = _n_components(mesh)
    pts = prep.points
    s, n, h = g.coords(pts)
    if prep.patch_nodes is not None:
        h[prep.patch_nodes] = 0.0
    tol = 1e-9 * prep.lat
    plus = n >= -tol
    e = mesh.edges
    i, j = e[:, 0], e[:, 1]
    cross = plus[i] != plus[j]
    nn = np.where(plus, np.maximum(n, 0.0), n)
    den = np.where(cross, nn[i] - nn[j], 1.0)
    t = nn[i] / den
    sc = s[i] + t * (s[j] - s[i])
    hc = h[i] + t * (h[j] - h[i])
    L = g.length
    inside = cross & (sc > (-np.inf if prep.open_start else 1e-9 * L)) & (sc < (np.inf if prep.open_end else L * (1 - 1e-9)))
    if not prep.through:
        inside &= hc < prep.depth * (1 - 1e-9)
    cut_edges = e[inside]
    key = np.sort(cut_edges, axis=1)
    tet_edges = np.sort(mesh.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]], axis=2)
    if len(key):
        edge_ids = {tuple(k) for k in key.tolist()}
        crossed = np.array([any((a, b) in edge_ids for a, b in te) for te in tet_edges.tolist()])
    else:
        crossed = np.zeros(mesh.n_tets, dtype=bool)
    lattice = None
    cube_keep = None
    if mesh.lattice is not None:
        cmap = _tet_cube_map(mesh)
        if cmap is None:
            raise CutError("element removal on a lattice needs the 6-tets-per-cube layout of block/layered_skin; this mesh's tets do not match its lattice")
        cube_cut = np.zeros(mesh.lattice.n_cubes, dtype=bool)
        cube_cut[cmap[crossed]] = True
        crossed = cube_cut[cmap]
        cube_keep = ~cube_cut
    if not np.any(crossed):
        raise CutError(f"the cut (length {L:.4g} m, depth {prep.depth:.4g} m) crosses no element; it is too short or too shallow for the mesh")
    keep = ~crossed
    if not np.any(keep):
        raise CutError("element removal would remove every element")
    kept_tets = mesh.tets[keep]
    used = np.zeros(len(pts), dtype=bool)
    used[kept_tets.reshape(-1)] = True
    old_of_new = np.flatnonzero(used)
    new_of_old = np.full(len(pts), -1)
    new_of_old[old_of_new] = np.arange(len(old_of_new))
    new_pts = pts[old_of_new]
    new_tets = new_of_old[kept_tets]
    if cube_keep is not None:
        cubes = new_of_old[mesh.lattice.cubes[cube_keep]]
        lattice = _build_lattice(cubes, new_pts, mesh.lattice.cube_region_ids[cube_keep])
    _check_connectivity(new_tets, new_pts, n_before, allow_disconnect)
    # Pairs across the gap: nodes of removed tets that remain, + side matched to - side.
    rim = np.zeros(len(pts), dtype=bool)
    rim[mesh.tets[crossed].reshape(-1)] = True
    rim &= used
    in_range = (s >= -1e-9 * L) & (s <= L * (1 + 1e-9)) & (h <= prep.depth * (1 + 1e-9) if not prep.through else True)
    P = np.flatnonzero(rim & plus & in_range)
    M = np.flatnonzero(rim & ~plus & in_range)
    pairs = np.zeros((0, 2), dtype=np.int32)
    ps = np.zeros(0)
    ph = np.zeros(0)
    if P.size and M.size:
        dist = (s[P][:, None] - s[M][None, :]) ** 2 + (h[P][:, None] - h[M][None, :]) ** 2
        partner = M[np.argmin(dist, axis=1)]
        pairs = np.stack([new_of_old[P], new_of_old[partner]], axis=1).astype(np.int32)
        ps, ph = s[P], h[P]
    q = mean_ratio_quality(new_pts, new_tets)
    order = np.argsort(q)
    quality = CutQuality(
        min_quality_before=float(mean_ratio_quality(pts, mesh.tets).min()),
        min_quality_after=float(q.min()),
        threshold=float(quality_threshold),
        n_below_threshold=int(np.sum(q < quality_threshold)),
        worst_elements=tuple(int(k) for k in order[:8] if q[k] < quality_threshold),
        n_snapped=0,
        max_snap_distance=0.0,
        max_snap_relative=0.0,
        min_cell_jacobian_ratio=None,
        n_duplicated=0,
        n_removed=int(crossed.sum()),
    )
    pd = {k: v[old_of_new] for k, v in mesh.point_data.items()}
    cd = {k: v[keep] for k, v in mesh.cell_data.items()}
    new_mesh = TetMesh(new_pts, new_tets, mesh.region_ids[keep], mesh.region_names, point_data=pd, cell_data=cd, lattice=lattice, validate=False)
    rest = new_pts[pairs[:, 0]] - new_pts[pairs[:, 1]] if len(pairs) else np.zeros((0, 3))
    return Cut(
        mesh=new_mesh,
        pairs=pairs,
        pair_s=ps,
        pair_depth=ph,
        pair_normal=g.unit_normal(ps) if len(ps) else np.zeros((0, 3)),
        pair_rest_offset=rest,
        tet_side=np.zeros(len(new_tets), dtype=np.int8),
        surface_pairs=_surface_order(ps, ph, prep.scale),
        node_origin=old_of_new.astype(np.int32),
        materials=prep.materials,
        length=L,
        depth=prep.depth,
        method="remove",
        through=prep.through,
        quality=quality,
    )


# ======================================================================= differentiable
class Opening(NamedTuple):
    """Opening of a cut at positions ``x`` (all lengths in metres).

    Attributes:
        width: ``(P,)`` distance between the two nodes of each pair.
        normal_opening: ``(P,)`` separation across the cut, ``(x_a - x_b) . n`` (``a`` on the
            ``+`` side): positive when the cut opens, negative if the faces overlap.
        surface_s: ``(Q,)`` arc length of the surface pairs, sorted.
        surface_width: ``(Q,)`` width profile along the cut at the top surface.
        max_width: largest surface width.
        width_over_length: ``max_width / length``.
    """

    width: jax.Array
    normal_opening: jax.Array
    surface_s: jax.Array
    surface_width: jax.Array
    max_width: jax.Array
    width_over_length: jax.Array


def _safe_norm(v):
    sq = jnp.sum(v * v, axis=-1)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def opening_width(cut: Cut, x, *, length=None) -> Opening:
    """Opening widths of ``cut`` at deformed positions ``x`` ``(N', 3)`` [m] (pure jnp,
    differentiable in ``x``; the gradient of a width is zero at a closed pair, not NaN).

    Args:
        length: cut length for ``w / l`` [m] (default the full cut length; pass the scalpel
            position for a cut in progress).
    """
    x = jnp.asarray(x)
    if x.shape != (cut.mesh.n_nodes, 3):
        raise CutError(f"positions must have shape ({cut.mesh.n_nodes}, 3) for this cut mesh, got {x.shape}")
    if cut.n_pairs == 0:
        raise CutError("this cut has no node pairs to measure an opening on")
    a, b = cut.pairs[:, 0], cut.pairs[:, 1]
    diff = x[a] - x[b]
    width = _safe_norm(diff)
    normal = jnp.sum(diff * jnp.asarray(cut.pair_normal), axis=1)
    surf = cut.surface_pairs
    if surf.size == 0:
        raise CutError("this cut has no node pair on the top surface")
    sw = width[surf]
    mx = jnp.max(sw)
    L = cut.length if length is None else length
    return Opening(width, normal, jnp.asarray(cut.pair_s[surf]), sw, mx, mx / L)


def closed_mask(cut: Cut, s):
    """Pairs the scalpel has not reached at arc length ``s`` [m]: ``pair_s > s`` (jnp, traceable)."""
    return jnp.asarray(cut.pair_s) > s


def _closure_energy(x, rest_offset, k):
    d = (x[0] - x[1]) - rest_offset
    return 0.5 * k * jnp.sum(d * d)


class CutClosureModel(ElasticModel):
    """A model of a cut specimen whose not-yet-cut pairs are tied by a penalty (seed 002).

    The energy is the base model's plus ``sum_p c_p k / 2 |(x_a - x_b) - (X_a - X_b)|^2`` over the
    pairs, with ``c_p = 1`` for closed pairs (``pair_s > s``) and 0 for open ones, and
    ``k = penalty_factor * max(E) * h`` (``h`` the median edge length; the constant is held
    out of differentiation, so gradients are those of the cut specimen with tied pairs). The
    closure weights are an array leaf: a jitted function of ``s`` sweeping the scalpel through
    the cut compiles once. The residual gap of a closed pair is ``~ force / k``, i.e. about
    ``1 / penalty_factor`` of the opening the pair would have if released.

    Use it like any :class:`~difftissue.models.ElasticModel` with
    :func:`~difftissue.solvers.static.solve_static`.
    """

    base: ElasticModel
    pairs: np.ndarray
    rest_offset: np.ndarray
    closed: Any
    #: median edge length of the cut mesh [m] (a 0-d array: a mesh value, so not static,
    #: which would split the compiled programs of meshes of one structure)
    edge_length: Any
    penalty_factor: float = eqx.field(static=True)

    def __init__(self, base: ElasticModel, cut: Cut, s, *, penalty_factor: float = 1e4):
        """Args:
            base: a model built on ``cut.mesh`` (``make_model(cut.mesh, kind)``).
            cut: the :class:`Cut`.
            s: scalpel position: arc length along the path [m] (may be traced); pairs with
                ``pair_s > s`` are tied. ``-inf`` ties all (nothing cut yet), ``cut.length``
                releases all.
            penalty_factor: closure stiffness relative to ``max(E) * median edge``.
        """
        if not isinstance(base, ElasticModel):
            raise CutError(f"base must be an ElasticModel built on cut.mesh, got {type(base).__name__}")
        if base.n_nodes != cut.mesh.n_nodes:
            raise CutError(f"the base model has {base.n_nodes} nodes but the cut mesh has {cut.mesh.n_nodes}: build it with make_model(cut.mesh, ...)")
        if not penalty_factor > 0:
            raise CutError(f"penalty_factor must be > 0, got {penalty_factor!r}")
        for f in dataclasses.fields(ElasticModel):
            setattr(self, f.name, getattr(base, f.name))
        self.base = base
        self.pairs = cut.pairs
        self.rest_offset = cut.pair_rest_offset
        if s is None:
            raise CutError("give the scalpel position s [m] (-inf: nothing cut yet; cut.length: the whole cut)")
        s_val = jnp.asarray(s, dtype=float)
        self.closed = (closed_mask(cut, s_val)).astype(float)
        e = cut.mesh.edges
        p = np.asarray(cut.mesh.points)
        self.edge_length = np.asarray(np.median(np.linalg.norm(p[e[:, 1]] - p[e[:, 0]], axis=1)), dtype=float)
        self.penalty_factor = float(penalty_factor)

    def terms(self, material):
        terms = tuple(self.base.terms(material))
        if self.pairs.shape[0] == 0:
            return terms
        E = self.base.region_values(material)["youngs_modulus"]
        k = jax.lax.stop_gradient(self.penalty_factor * jnp.max(E) * self.edge_length)
        return terms + (ElementTerm("cut_closure", self.pairs, _closure_energy, (jnp.asarray(self.rest_offset), k * self.closed)),)

    def region_values(self, material):
        return self.base.region_values(material)

    def min_volume_ratio(self, x):
        return self.base.min_volume_ratio(x)
