"""Specimen geometry shared by the targets: the compression block, the indentation specimen and
the meshed indenter cap (docs/export.md, "Indentation specimens").

A block specimen is any tet mesh: its base (min z) held and its top (max z) moved along z
(:func:`block_sets`, :func:`default_displacement`). A card fitted to an indentation experiment
(AFM sphere, cone, flat punch; analytic Hertz / Sneddon or simulated
:class:`~difftissue.scenarios.Indentation`) is exported as a complete model of that experiment: a
block ``[-Lx/2, Lx/2] x [-Ly/2, Ly/2] x [0, H]`` (:func:`difftissue.scenarios.indentation_block`
with ``symmetry="none"``), the indenter on the axis ``x = y = 0`` touching the top face ``z = H``
at depth 0 and pushed to ``depth`` along ``-z``, the base ``z = 0`` bonded (all components fixed)
or sliding (``u_z = 0`` plus the same two pinned nodes as :class:`~difftissue.scenarios.Indentation`).

:class:`IndentationSpecimen` holds the geometry and protocol, each value with where it came
from (the card's ``provenance.scenario_records``, an explicit option, or a stated default);
:func:`indentation_specimen` builds it. The writers call :func:`indentation_sets` for the node
sets and the contact penalty, :func:`check_indentation` for what a target refuses, and
:func:`febio_indenter_cap` for the triangulated sphere or cone of the FEBio and Abaqus models.

What each target gets (conversions and citations in docs/export.md):

* FEBio: flat punch -> prescribed displacement of the nodes under the punch; sphere and cone
  -> a meshed rigid indenter (FEBio 4.0 has no analytical sphere or cone): a ``tri3`` shell cap
  of a ``rigid body`` material in frictionless ``sliding-elastic`` contact with the top face,
  moved by ``rigid_displacement``.
* Abaqus (and CalculiX, which runs the same deck): sphere and cone -> a meshed rigid indenter
  (C3D4 fan of the cap, every node moved by ``(0, 0, -depth)``) in frictionless node-to-surface
  penalty contact (``*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR``, slope ``p E / h``) with
  the tissue's top faces; flat punch -> ``*BOUNDARY`` on the punch nodes.
* SOFA: sphere -> ``SphereForceField`` (penalty force field of ``Sofa.Component.MechanicalLoad``,
  fixed in space; the base is moved up by the depth, the same relative motion); flat punch ->
  ``LinearMovementProjectiveConstraint`` on the punch nodes (bonded punch only); cone refused;
  base bonded only.
* pypbd: flat punch (bonded punch, bonded base) only; sphere/cone refused.
* XPBD JSON: an ``indenter`` block with the geometry, depth and difftissue's per-node
  penalty; flat-punch files run in difftissue's own XPBD solver
  (:func:`difftissue.export.xpbd.run_xpbd_indentation`).

A ``springs_volume`` card (lattice-effective E, nu) written for a continuum target (FEBio, SOFA,
Abaqus) is recalibrated on the indentation it was fitted to
(:func:`difftissue.export.recalibration.indentation_card`, from the card's simulated scenario record).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from ..contact import FlatPunch, surface_node_areas, top_surface_nodes
from ..errors import ExportError
from ..mesh import boundary_faces
from ..scenarios import indentation_block
from .card import MaterialCard

__all__ = ["INDENTERS", "IndentationSpecimen", "indentation_specimen", "indentation_records", "indentation_sets", "block_sets",
           "default_displacement", "no_mesh_with_indentation", "check_indentation", "FEBIO_INDENTER_MATERIAL", "febio_indenter_cap"]


def block_sets(mesh, axis: int = 2, tol: float = 1e-9):
    """``(base nodes, top nodes, height [m])`` of a block specimen: the nodes within ``tol`` x the
    height of its lowest and highest ``axis`` coordinate (z); ExportError without distinct faces
    (for a mesh with tets, also when the base or the top nodes span no boundary face: a mesh
    from a file whose lowest or highest point is a vertex or an edge)."""
    pts = np.asarray(mesh.points, dtype=float)
    lo, hi = pts[:, axis].min(), pts[:, axis].max()
    t = tol * max(hi - lo, 1e-300)
    base = np.flatnonzero(pts[:, axis] <= lo + t)
    top = np.flatnonzero(pts[:, axis] >= hi - t)
    if base.size == 0 or top.size == 0 or hi <= lo:
        raise ExportError("the specimen mesh has no distinct base and top faces along z")
    tets = getattr(mesh, "tets", None)
    if tets is not None:  # a mesh from a file: its extreme nodes must form faces, not a point or an edge
        faces, _ = boundary_faces(np.asarray(tets))
        for name, nodes in (("base", base), ("top", top)):
            on = faces[np.all(np.isin(faces, nodes), axis=1)]
            tri = pts[on]
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() if on.size else 0.0
            if not area > 0.0:
                raise ExportError(f"the specimen mesh has no flat {name} face normal to z (its {name} is the boundary at the "
                                  f"{'smallest' if name == 'base' else 'largest'} z, here {nodes.size} node(s) and no face): "
                                  "the specimen is held at its base and loaded at its top; orient the mesh so that both are "
                                  "flat faces normal to z")
    return base, top, hi - lo


def default_displacement(height: float, displacement: float | None) -> float:
    """The block's top displacement [m]: ``displacement``, or by default -10 % of the ``height`` [m] (compression)."""
    d = -0.1 * height if displacement is None else float(displacement)
    if not math.isfinite(d):
        raise ExportError(f"displacement = {displacement!r} is not finite")
    return d


def no_mesh_with_indentation(mesh) -> None:
    """Refuse a block mesh given together with an indentation specimen."""
    if mesh is not None:
        raise ExportError("give either a block specimen (mesh) or an indentation specimen, not both")


INDENTERS = ("sphere", "cone", "flat_punch")


@dataclasses.dataclass(frozen=True)
class IndentationSpecimen:
    """Geometry and protocol of an indentation specimen (SI units).

    Attributes:
        indenter: ``"sphere"``, ``"cone"`` or ``"flat_punch"``.
        depth: final indenter depth [m] (> 0), reached over ``steps`` equal increments.
        size: ``(Lx, Ly, H)`` [m] of the block.
        cells: ``(nx, ny, nz)`` cells of the block.
        radius: sphere or punch radius [m]; half_angle: cone half-angle [rad].
        base: ``"bonded"`` or ``"sliding"``; bonded_punch: punch nodes fixed in x and y too.
        penalty: difftissue's dimensionless contact penalty (per-node ``kappa_i = penalty E sqrt(A_i)``).
        steps: load increments; refine, core: graded cells (first cell size [m] at the axis and
            the surface, kept uniform within ``core`` [m]; :func:`~difftissue.scenarios.indentation_block`),
            ``None``: uniform cells; sources: ``{field: where the value came from}``.
    """

    indenter: str
    depth: float
    size: tuple[float, float, float]
    cells: tuple[int, int, int]
    radius: float | None = None
    half_angle: float | None = None
    base: str = "bonded"
    bonded_punch: bool = False
    penalty: float = 100.0
    steps: int = 10
    refine: float | None = None
    core: float | None = None
    sources: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.indenter not in INDENTERS:
            raise ExportError(f"indenter = {self.indenter!r}: expected one of {list(INDENTERS)}")
        for name in ("depth", "penalty"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ExportError(f"indentation {name} = {v!r} must be a positive finite number")
        if len(self.size) != 3 or not all(math.isfinite(v) and v > 0 for v in self.size):
            raise ExportError(f"indentation block size = {self.size!r}: expected three positive lengths [m]")
        if len(self.cells) != 3 or not all(int(n) == n and n >= 1 for n in self.cells):
            raise ExportError(f"indentation cells = {self.cells!r}: expected three positive integers")
        if self.indenter == "cone":
            if self.half_angle is None or not 0.0 < self.half_angle < math.pi / 2:
                raise ExportError(f"a cone needs half_angle in (0, pi/2) rad, got {self.half_angle!r}")
        elif self.radius is None or not (math.isfinite(self.radius) and self.radius > 0):
            raise ExportError(f"a {self.indenter} needs a positive radius [m], got {self.radius!r}")
        if self.base not in ("bonded", "sliding"):
            raise ExportError(f"base = {self.base!r}: expected 'bonded' or 'sliding'")
        if int(self.steps) != self.steps or self.steps < 1:
            raise ExportError(f"steps = {self.steps!r} must be a positive integer")
        if self.depth >= self.size[2]:
            raise ExportError(f"depth = {self.depth:g} m is not below the block height H = {self.size[2]:g} m")

    def mesh(self):
        """The block (``indentation_block(size, cells, symmetry="none")``, axis at x = y = 0)."""
        return indentation_block(self.size, self.cells, symmetry="none", refine=self.refine, core=self.core)

    def contact_radius(self) -> float:
        """Small-strain contact radius [m] at ``depth``: ``sqrt(R d)`` (Hertz), ``2 d tan(theta) / pi``
        (Sneddon cone), ``R`` (punch)."""
        if self.indenter == "sphere":
            return math.sqrt(self.radius * self.depth)
        if self.indenter == "cone":
            return 2.0 * self.depth * math.tan(self.half_angle) / math.pi
        return float(self.radius)

    def describe(self) -> list[str]:
        """Comment lines: every value and where it came from."""
        geo = (f"sphere radius R = {self.radius:.10g} m" if self.indenter == "sphere" else
               f"cone half-angle = {self.half_angle:.10g} rad ({math.degrees(self.half_angle):.6g} deg)" if self.indenter == "cone" else
               f"flat punch radius = {self.radius:.10g} m ({'bonded' if self.bonded_punch else 'frictionless'} punch face)")
        lines = [
            f"indentation specimen: {geo}, on the axis x = y = 0, touching the top face z = H at depth 0, pushed along -z",
            f"depth = {self.depth:.10g} m in {self.steps} equal steps; block {self.size[0]:.10g} x {self.size[1]:.10g} x "
            f"{self.size[2]:.10g} m (x, y centred, 0 <= z <= H), {self.cells[0]} x {self.cells[1]} x {self.cells[2]} cells "
            + ("" if self.refine is None else f"graded from {self.refine:.6g} m at the axis and the surface (uniform within {self.core:.6g} m) ")
            + f"of 6 tets; base z = 0 {self.base}" + (" (u_z = 0, one node pinned in x and y, one in y)" if self.base == "sliding" else
                                                    " (all components fixed)"),
        ]
        if self.indenter != "flat_punch":
            lines.append(f"frictionless contact; difftissue's penalty factor {self.penalty:g} (kappa_i = penalty E sqrt(A_i) per node)")
        for k, v in sorted(self.sources.items()):
            lines.append(f"{k}: {v}")
        return lines

    def to_dict(self) -> dict[str, Any]:
        return {"indenter": self.indenter, "depth": self.depth, "size": list(self.size), "cells": list(self.cells),
                "radius": self.radius, "half_angle": self.half_angle, "base": self.base, "bonded_punch": self.bonded_punch,
                "penalty": self.penalty, "steps": self.steps, "refine": self.refine, "core": self.core,
                "axis": [0.0, 0.0], "sources": dict(self.sources),
                "unit": "m, rad"}


def indentation_records(card: MaterialCard) -> list[dict]:
    """The card's indentation scenario records (``provenance.scenario_records`` with ``experiment = "indentation"``)."""
    recs = (card.provenance or {}).get("scenario_records") or []
    return [r for r in recs if isinstance(r, Mapping) and r.get("experiment") == "indentation"]


def indentation_specimen(card: MaterialCard | None = None, *, indenter: str | None = None, radius: float | None = None,
                         half_angle: float | None = None, depth: float | None = None, size=None, cells=None,
                         base: str | None = None, bonded_punch: bool | None = None, penalty: float | None = None, steps: int = 10,
                         scenario: str | None = None) -> IndentationSpecimen:
    """The indentation specimen for ``card``: explicit options first, then the card's
    ``provenance.scenario_records`` (the first indentation record, or the one named ``scenario``),
    then defaults; every value's origin goes into ``sources`` (and into the written file).

    Defaults where neither gives a value: ``depth`` = the record's ``max_depth``; block height
    ``H`` = the record's layer ``thickness`` or else ``10 a`` (``a`` the small-strain contact
    radius at ``depth``; a half-space represented by a finite block, see docs/export.md),
    lateral size ``2 H`` (or ``20 a``, whichever is larger); cells ``(10, 10, 6)``; base
    ``bonded`` (an analytic ``lubricated`` base becomes ``sliding``); ``bonded_punch`` the
    record's (a simulated flat punch), else False (frictionless punch face). A simulated
    record's block comes with the fit's uniform ``cells`` (used unless ``cells`` is given) and
    contact ``penalty`` (used unless ``penalty`` is given; else 100). An axisymmetric record
    (:meth:`~difftissue.scenarios.AxisymmetricIndentation.record`: the fit simulated the
    meridian plane of a cylinder) gives a 3-D block by the same defaults (its layer thickness
    when its cylinder was a layer, else the half-space block): the fitted E is the continuum's.
    """
    rec: Mapping = {}
    recs = indentation_records(card) if card is not None else []
    if scenario is not None:
        named = [r for r in recs if r.get("name") == scenario]
        if not named:
            raise ExportError(f"the card records no indentation scenario named {scenario!r} (recorded: {[r.get('name') for r in recs]})")
        rec = named[0]
    elif recs:
        rec = recs[0]
    src: dict[str, str] = {}
    where = f"card scenario record {rec.get('name')!r}" if rec else ""

    def pick(name, explicit, recname=None):
        if explicit is not None:
            src[name] = "explicit option"
            return explicit
        v = rec.get(recname or name) if rec else None
        if v is not None:
            src[name] = where
            return v
        return None

    ind = pick("indenter", indenter)
    if ind is None:
        raise ExportError("an indentation specimen needs the indenter (sphere, cone, flat_punch): the card records no indentation "
                          "scenario; give it explicitly (--indenter, --radius / --half-angle, --depth)")
    r = pick("radius", radius) if ind != "cone" else None
    th = pick("half_angle", half_angle) if ind == "cone" else None
    d = pick("depth", depth, "max_depth")
    if d is None:
        raise ExportError("an indentation specimen needs the final depth: the card records none; give --depth")
    if ind == "cone" and th is None:
        raise ExportError("a cone specimen needs its half-angle (--half-angle)")
    if ind != "cone" and r is None:
        raise ExportError(f"a {ind} specimen needs its radius (--radius)")
    tmp = IndentationSpecimen(indenter=ind, depth=float(d), size=(1.0, 1.0, 2.0 * float(d) + 1.0), cells=(1, 1, 1),
                              radius=None if r is None else float(r), half_angle=None if th is None else float(th))
    a = tmp.contact_radius()
    if size is not None:
        size = tuple(float(v) for v in size)
        src["size"] = "explicit option"
    else:
        thick = rec.get("thickness") if rec else None
        blk = rec.get("block_size") if rec else None
        axi = rec.get("geometry") == "axisymmetric" if rec else False
        if axi and (rec.get("specimen") or {}).get("thickness_given") and rec.get("height"):
            thick = rec["height"]  # the fit's axisymmetric cylinder was a layer of its own thickness
        if blk:
            size = tuple(float(v) for v in blk)
            src["size"] = where + " (simulated block)"
        elif thick:
            H = float(thick)
            L = max(2.0 * H, 20.0 * a)
            size = (L, L, H)
            src["size"] = f"H = layer thickness from {where}; lateral size max(2 H, 20 a) with a = {a:.6g} m (assumed)"
        else:
            H = max(10.0 * a, 5.0 * float(d))
            L = max(2.0 * H, 20.0 * a)
            size = (L, L, H)
            fitted = (f"the fit simulated a half-space axisymmetrically ({where}: a cylinder of radius {float(rec.get('radius_of_specimen', 0.0)):.6g} m); "
                      if axi else "")
            src["size"] = (f"ASSUMED: {fitted}the fitted model is a half-space; block H = max(10 a, 5 depth), lateral max(2 H, 20 a) "
                           f"with the contact radius a = {a:.6g} m at the final depth (Hertz/Sneddon); the finite block is stiffer "
                           "than the half-space (see docs/export.md)")
    refine = core = None
    if cells is not None:
        cells = tuple(int(v) for v in cells)
        src["cells"] = "explicit option (uniform cells)"
    elif rec and rec.get("cells") and src.get("size", "").startswith(where) and list(size) == list(rec.get("block_size") or []):
        cells = tuple(int(v) for v in rec["cells"])
        src["cells"] = f"{where}: the fit's mesh (uniform cells)"
    else:
        # resolve the contact: first cell a/3 (punch: R/4), uniform within 1.2 a (1.1 R), 6 graded cells beyond
        refine = a / 3.0 if ind != "flat_punch" else a / 4.0
        core = 1.2 * a if ind != "flat_punch" else 1.1 * a
        n_core = max(1, int(round(core / refine)))
        half = n_core + 6
        cells = (2 * half, 2 * half, half)
        if refine >= min(size[0], size[1]) / 2 / half:
            refine = core = None
        src["cells"] = (f"default {cells}: " + ("uniform" if refine is None else
                        f"graded, first cell {refine:.6g} m at the axis and the surface, uniform within {core:.6g} m of them"))
    if base is None:
        rb = rec.get("base") if rec else None
        if rb is not None:
            base = "sliding" if rb in ("lubricated", "sliding") else "bonded"
            src["base"] = where + (f" ({rb!r})" if rb != base else "")
        else:
            base = "bonded"
            src["base"] = "default (bonded)"
    else:
        src["base"] = "explicit option"
    bp = pick("bonded_punch", bonded_punch) if ind == "flat_punch" else None
    pen = pick("penalty", penalty) if ind != "flat_punch" else penalty
    if pen is None:
        pen = 100.0
        if ind != "flat_punch":
            src["penalty"] = "default (100)"
    return IndentationSpecimen(indenter=ind, depth=float(d), size=size, cells=cells, radius=None if r is None else float(r),
                               half_angle=None if th is None else float(th), base=base, bonded_punch=bool(bp),
                               penalty=float(pen), steps=int(steps), refine=refine, core=core, sources=src)


def indentation_sets(spec: IndentationSpecimen, mesh, card: MaterialCard) -> dict:
    """Node sets and contact data of ``spec`` on ``mesh`` (0-based node ids).

    Returns ``base`` (z = 0 nodes), ``top`` (z = H nodes), ``anchor`` / ``other`` (the sliding
    base's pinned nodes: ``anchor`` fixed in x and y, ``other`` in y, as in
    :class:`~difftissue.scenarios.Indentation`), ``punch`` (flat punch: top nodes within the
    radius), ``top_faces`` (boundary triangles on the top face, outward +z), ``contact_nodes``
    and ``kappa`` [N/m] (difftissue's per-node penalty ``penalty * E * sqrt(A_i)``, ``A_i`` the
    node's tributary boundary area), ``h`` [m] (``sqrt(A)`` of the top node on the axis: the
    length that turns difftissue's per-node penalty into a per-area one, or one stiffness for
    all nodes, exact for the nodes in contact where the cells are uniform), ``H``.
    """
    p = np.asarray(mesh.points, dtype=float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    tol = 1e-9 * float(np.linalg.norm(hi - lo))
    base = np.flatnonzero(np.abs(p[:, 2] - lo[2]) <= tol)
    top = np.flatnonzero(np.abs(p[:, 2] - hi[2]) <= tol)
    anchor = base[np.argmin(np.hypot(p[base, 0], p[base, 1]))]
    other = base[np.argmax(np.abs(p[base, 0] - p[anchor, 0]))]
    faces, _ = boundary_faces(np.asarray(mesh.tets))
    on_top = np.all(np.abs(p[faces, 2] - hi[2]) <= tol, axis=1)
    top_faces = faces[on_top]
    n = np.cross(p[top_faces[:, 1]] - p[top_faces[:, 0]], p[top_faces[:, 2]] - p[top_faces[:, 0]])
    flip = n[:, 2] < 0
    top_faces[flip] = top_faces[flip][:, [0, 2, 1]]
    ids, area = surface_node_areas(mesh, top_surface_nodes(mesh))
    out = {"base": base, "top": top, "anchor": int(anchor), "other": int(other), "top_faces": top_faces,
           "contact_nodes": np.asarray(ids, dtype=np.int64), "kappa": spec.penalty * card.youngs_modulus * np.sqrt(area),
           "h": float(np.sqrt(area[np.argmin(np.hypot(p[ids, 0], p[ids, 1]))])), "H": float(hi[2] - lo[2])}
    if spec.indenter == "flat_punch":
        out["punch"] = np.asarray(FlatPunch(spec.radius, axis_xy=(0.0, 0.0), bonded=spec.bonded_punch).nodes(mesh), dtype=np.int64)
    return out


_WHY = {
    ("SOFA", "cone"): ("the SOFA scene has no cone: SOFA's ConicalForceField (Sofa.Component.MechanicalLoad) was not "
                       "checked against difftissue's cone penetration; export the cone to Abaqus or the XPBD JSON"),
}


def check_indentation(spec, target: str, *, cone: bool = True, sphere: bool = True, sliding: bool = True,
               frictionless_punch: bool = True) -> None:
    """Refuse (one ExportError line) what ``target`` cannot represent of the indentation ``spec``."""
    for shape, ok in (("cone", cone), ("sphere", sphere)):
        if spec.indenter == shape and not ok:
            raise ExportError(f"{target} indentation specimen: a {shape} indenter cannot be written: " + _WHY[(target, shape)])
    if spec.base == "sliding" and not sliding:
        raise ExportError(f"{target} indentation specimen: base='sliding' (u_z = 0, x and y free) cannot be written: "
                          f"{target}'s moved/fixed nodes hold all three components; use base='bonded' (--base bonded)")
    if spec.indenter == "flat_punch" and not spec.bonded_punch and not frictionless_punch:
        raise ExportError(f"{target} indentation specimen: a frictionless flat punch (u_z prescribed, x and y free) cannot be "
                          f"written: {target} prescribes all three components of moved nodes; use bonded_punch=True (--bonded-punch)")


FEBIO_INDENTER_MATERIAL = "rigid_indenter"


def febio_indenter_cap(spec, height: float, spacing: float, *, max_rings: int = 48):
    """Triangulated cap of a sphere or cone indenter for the FEBio specimen (SI units).

    The indenter's tip touches the top face ``z = height`` on the axis ``x = y = 0``; the
    sphere's centre is ``(0, 0, height + R)``, the cone's tip ``(0, 0, height)``. The cap
    extends to the horizontal radius ``r_cap``: sphere ``min(3 sqrt(R d), R)`` (3x the
    small-strain contact radius, at most the hemisphere), cone ``3 d tan(theta)`` (3x the
    radius where the cone crosses the undeformed surface at the final depth ``d``, which
    exceeds the contact radius ``2 d tan(theta) / pi``). Rings ``k = 0..n`` (ring ``k`` has
    ``6 k`` nodes, the tip is ring 0) at equal polar angles (sphere) or equal radii (cone),
    ``n = ceil(arc length / (spacing / 2))`` clipped to ``[4, max_rings]`` (``spacing`` [m]: the
    tissue's top cell size; the rings are then at most ``spacing / 2`` apart unless clipped),
    zipped into ``tri3`` facets whose normal ``(x1 - x0) x (x2 - x0)`` points away from the
    indenter's interior (towards the tissue).

    Returns ``(points (N, 3), tris (M, 3) 0-based, r_cap)``.
    """
    if not (math.isfinite(spacing) and spacing > 0):
        raise ExportError(f"indenter cap spacing = {spacing!r} must be a positive length [m]")
    d = spec.depth
    if spec.indenter == "sphere":
        R = spec.radius
        r_cap = min(3.0 * math.sqrt(R * d), R)
        theta_max = math.asin(r_cap / R) if r_cap < R else 0.5 * math.pi
        arc = R * theta_max
    elif spec.indenter == "cone":
        r_cap = 3.0 * d * math.tan(spec.half_angle)
        arc = r_cap / math.sin(spec.half_angle)
    else:
        raise ExportError(f"no indenter cap for a {spec.indenter!r} indenter (sphere and cone only)")
    n = int(min(max(4, math.ceil(arc / (0.5 * spacing))), max_rings))
    pts = [(0.0, 0.0, float(height))]
    rings = [[0]]
    for k in range(1, n + 1):
        if spec.indenter == "sphere":
            th = theta_max * k / n
            r, z = R * math.sin(th), height + R - R * math.cos(th)
        else:
            r = r_cap * k / n
            z = height + r / math.tan(spec.half_angle)
        ids = []
        for m in range(6 * k):
            phi = 2.0 * math.pi * m / (6 * k)
            ids.append(len(pts))
            pts.append((r * math.cos(phi), r * math.sin(phi), z))
        rings.append(ids)
    tris = []
    for k in range(1, n + 1):
        inner, outer = rings[k - 1], rings[k]
        ni, no = len(inner), len(outer)
        if ni == 1:
            tris += [(inner[0], outer[j], outer[(j + 1) % no]) for j in range(no)]
            continue
        i = j = 0
        while i < ni or j < no:  # zip the two rings by angle: ni + no triangles
            if j < no and (i >= ni or (j + 1) / no <= (i + 1) / ni):
                tris.append((inner[i % ni], outer[j], outer[(j + 1) % no]))
                j += 1
            else:
                tris.append((inner[i], outer[j % no], inner[(i + 1) % ni]))
                i += 1
    P = np.asarray(pts, dtype=float)
    T = np.asarray(tris, dtype=np.int64)
    # orient every facet away from the indenter's interior (sphere: from the centre; cone: outward and down)
    nrm = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    c = P[T].mean(axis=1)
    if spec.indenter == "sphere":
        out = c - np.array([0.0, 0.0, height + spec.radius])
    else:
        rho = np.hypot(c[:, 0], c[:, 1])
        out = np.stack([c[:, 0] * math.cos(spec.half_angle) / np.maximum(rho, 1e-300),
                        c[:, 1] * math.cos(spec.half_angle) / np.maximum(rho, 1e-300),
                        -np.full(len(c), math.sin(spec.half_angle))], axis=1)
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    T[flip] = T[flip][:, [0, 2, 1]]
    return P, T, float(r_cap)
