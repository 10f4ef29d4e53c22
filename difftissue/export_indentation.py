"""Indentation specimens for the export writers (docs/export.md, "Indentation specimens").

A card fitted to an indentation experiment (AFM sphere, cone, flat punch; analytic Hertz /
Sneddon or simulated :class:`~difftissue.scenarios.Indentation`) is exported as a complete
model of that experiment: a block ``[-Lx/2, Lx/2] x [-Ly/2, Ly/2] x [0, H]``
(:func:`difftissue.scenarios.indentation_block` with ``symmetry="none"``), the indenter on the
axis ``x = y = 0`` touching the top face ``z = H`` at depth 0 and pushed to ``depth`` along
``-z``, the base ``z = 0`` bonded (all components fixed) or sliding (``u_z = 0`` plus the
same two pinned nodes as :class:`~difftissue.scenarios.Indentation`).

:class:`IndentationSpecimen` holds the geometry and protocol, each value with where it came
from (the card's ``provenance.scenario_records``, an explicit option, or a stated default);
:func:`indentation_specimen` builds it; :func:`scenario_record` writes the record a fit puts
into its card. The writers (``difftissue.export`` and ``difftissue.pbd``) call
:func:`indentation_sets` for the node sets and the contact penalty.

What each target gets (conversions and citations in docs/export.md):

* FEBio: flat punch -> prescribed displacement of the nodes under the punch; sphere and cone
  -> a meshed rigid indenter (FEBio 4.0 has no analytical sphere or cone): a ``tri3`` shell cap
  of a ``rigid body`` material in frictionless ``sliding-elastic`` contact with the top face,
  moved by ``rigid_displacement``.
* Abaqus (and CalculiX, which runs the same deck): sphere and cone -> a meshed rigid indenter
  (C3D4 fan of the cap, every node moved by ``(0, 0, -depth)``) in frictionless node-to-surface
  penalty contact (``*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR``, slope ``p E / h``) with
  the tissue's top faces; flat punch -> ``*BOUNDARY`` on the punch nodes.

A ``springs_volume`` card (lattice-effective E, nu) written for a continuum target (FEBio, SOFA,
Abaqus) is recalibrated on the indentation it was fitted to (:func:`recalibrated_indentation_card`,
from the card's simulated scenario record).
* SOFA: sphere -> ``SphereForceField`` (penalty force field of ``Sofa.Component.MechanicalLoad``,
  fixed in space; the base is moved up by the depth, the same relative motion); flat punch ->
  ``LinearMovementProjectiveConstraint`` on the punch nodes (bonded punch only); cone refused;
  base bonded only.
* pypbd: flat punch (bonded punch, bonded base) only; sphere/cone refused.
* XPBD JSON: an ``indenter`` block with the geometry, depth and difftissue's per-node
  penalty; flat-punch files run in difftissue's own XPBD solver (:func:`run_xpbd_indentation`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from .errors import ExportError

__all__ = ["IndentationSpecimen", "indentation_specimen", "scenario_record", "indentation_sets", "run_xpbd_indentation", "INDENTERS",
           "recalibrated_indentation_card", "indentation_card"]

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
        from .scenarios import indentation_block

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


def scenario_record(scenario) -> dict | None:
    """JSON record of a scenario's experiment for a material card (``provenance.scenario_records``).

    Indentation scenarios (:class:`~difftissue.scenarios.AnalyticIndentation`,
    :class:`~difftissue.scenarios.Indentation`) record the indenter, its size, the largest
    depth and the number of points (and for the analytic ones the layer thickness and base);
    :class:`~difftissue.scenarios.FEMField` and :class:`~difftissue.incision.Incision` record
    ``experiment`` (``"fem_field"`` / ``"incision"``), difftissue's ``model`` (and the incision's
    quantity, cut length and depth); :class:`~difftissue.scenarios.Compression` records
    ``experiment = "compression"``, ``model`` and its protocol
    (:func:`difftissue.export_fitted.compression_protocol`: platens, measure, strains, nominal
    strains, height, area, top displacement); their mesh and boundary conditions go into a
    specimen file (:mod:`difftissue.export_fitted`, written by ``write_fit_outputs``); other
    scenarios record their name and type only. Returns ``None`` for an object without a name.
    """
    name = getattr(scenario, "name", None)
    if name is None:
        return None
    rec: dict[str, Any] = {"name": str(name), "type": type(scenario).__name__}
    x = getattr(scenario, "abscissa", None)
    tname = type(scenario).__name__
    if tname == "AnalyticIndentation":
        rec["experiment"] = "indentation"
        rec["indenter"] = scenario.indenter
        rec["half_angle" if scenario.indenter == "cone" else "radius"] = float(scenario.size)
        rec["thickness"] = None if scenario.thickness is None else float(scenario.thickness)
        rec["base"] = scenario.base
        rec["solution"] = scenario.solution
    elif tname == "Indentation":
        from .contact import ConeIndenter, SphereIndenter

        rec["experiment"] = "indentation"
        geom = getattr(getattr(scenario, "model", None), "indenter", None)
        if isinstance(geom, SphereIndenter):
            rec["indenter"], rec["radius"] = "sphere", float(geom.radius)
        elif isinstance(geom, ConeIndenter):
            rec["indenter"], rec["half_angle"] = "cone", float(geom.half_angle)
        elif getattr(scenario, "punch_mask", None) is not None:
            # the punch radius is not stored: record the effective one, the outermost punch node ring
            mask = np.asarray(scenario.punch_mask)
            pts = np.asarray(scenario.model.rest_points)
            nodes = np.flatnonzero(mask[:, 2])
            lo_xy, hi_xy = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
            axis = np.zeros(2) if float(getattr(scenario, "force_multiplier", 1.0)) == 4.0 else 0.5 * (lo_xy + hi_xy)
            rec["indenter"] = "flat_punch"
            rec["radius"] = float(np.max(np.hypot(pts[nodes, 0] - axis[0], pts[nodes, 1] - axis[1])))
            rec["radius_note"] = "effective punch radius: the outermost node ring under the punch"
            rec["bonded_punch"] = bool(np.all(mask[nodes, :2]))
        fixed = np.asarray(scenario.bc.fixed)
        zr = np.asarray(scenario.model.rest_points)[:, 2]
        bottom = np.flatnonzero(np.abs(zr - zr.min()) <= 1e-9 * max(float(np.ptp(zr)), 1e-300))
        if bottom.size:
            rec["base"] = "bonded" if np.all(fixed[bottom]) else "sliding"
        rest = np.asarray(getattr(scenario.model, "rest_points", np.zeros((0, 3))))
        if rest.size:
            lo, hi = rest.min(axis=0), rest.max(axis=0)
            mult = float(getattr(scenario, "force_multiplier", 1.0))
            span = hi - lo
            rec["block_size"] = [float(span[0] * (2 if mult == 4.0 else 1)), float(span[1] * (2 if mult == 4.0 else 1)), float(span[2])]
            rec["symmetry"] = "quarter" if mult == 4.0 else "none"
            cells = _uniform_block_cells(scenario.model, rec["block_size"], rec["symmetry"])
            if cells is not None:
                rec["cells"] = cells
                rec["cells_note"] = ("the fit's mesh: indentation_block(block_size, cells, symmetry='none') of uniform cells"
                                     + (" (the fit modelled the x >= 0, y >= 0 quarter with half the x and y cells)" if mult == 4.0 else ""))
        model = getattr(scenario, "model", None)
        rec["model"] = str(getattr(getattr(model, "base", model), "kind", "")) or None
        factors = getattr(model, "penalty_factors", None)
        if getattr(model, "penalty", None) is not None:  # ContactModel keeps the penalty given
            rec["penalty"] = float(model.penalty)
        elif factors is not None:  # ContactModel: penalty_factors = penalty sqrt(A_i)
            from .contact import surface_node_areas

            _, area = surface_node_areas(_model_mesh(model), np.asarray(model.contact_nodes))
            rec["penalty"] = float(np.median(np.asarray(factors) / np.sqrt(area)))
    elif tname in ("FEMField", "Incision"):
        # the experiment itself goes into a specimen file beside the card (difftissue.export_fitted)
        rec["experiment"] = "fem_field" if tname == "FEMField" else "incision"
        model = getattr(scenario, "model", None)
        rec["model"] = str(getattr(getattr(model, "base", model), "kind", "")) if model is not None else None
        if tname == "Incision":
            rec["quantity"] = scenario.quantity
            rec["cut_length"] = float(scenario.cut.length)
            rec["cut_depth"] = float(scenario.cut.depth)
    elif tname == "Compression":
        from .export_fitted import compression_protocol

        rec["experiment"] = "compression"
        rec["model"] = str(scenario.model.kind)
        rec.update(compression_protocol(scenario))
    if x is not None and np.size(x) and rec.get("experiment") == "indentation":
        rec["max_depth"] = float(np.max(x))
        rec["points"] = int(np.size(x))
        if tname == "Indentation":
            rec["depths"] = [float(v) for v in np.asarray(x).reshape(-1)]
    return rec


def _model_mesh(model):
    """The :class:`~difftissue.mesh.TetMesh` of an elastic model (rest points, tets)."""
    from .mesh import TetMesh

    return TetMesh(np.asarray(model.rest_points), np.asarray(model.tets))


def _uniform_block_cells(model, size, symmetry: str) -> list[int] | None:
    """Full-block cell counts ``[nx, ny, nz]`` when the model's mesh is exactly
    :func:`~difftissue.scenarios.indentation_block` ``(size, cells, symmetry)`` with uniform
    cells (its quarter with half the x and y cells for ``symmetry="quarter"``), else None."""
    from .scenarios import indentation_block

    p = np.asarray(model.rest_points, dtype=float)
    t = np.asarray(model.tets)
    span = float(np.linalg.norm(np.ptp(p, axis=0)))
    counts = []
    for a in range(3):
        c = np.sort(p[:, a])
        counts.append(int(np.sum(np.diff(c) > 1e-9 * span)))
    if min(counts) < 1 or len(t) != 6 * counts[0] * counts[1] * counts[2]:
        return None
    try:
        ref = indentation_block(size, counts, symmetry=symmetry)
    except Exception:
        return None
    if np.shape(ref.points) != p.shape or not np.allclose(ref.points, p, rtol=0, atol=1e-9 * span) or not np.array_equal(ref.tets, t):
        return None
    k = 2 if symmetry == "quarter" else 1
    return [k * counts[0], k * counts[1], counts[2]]


def _records(card) -> list[dict]:
    recs = (card.provenance or {}).get("scenario_records") or []
    return [r for r in recs if isinstance(r, Mapping) and r.get("experiment") == "indentation"]


def indentation_specimen(card=None, *, indenter: str | None = None, radius: float | None = None,
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
    contact ``penalty`` (used unless ``penalty`` is given; else 100).
    """
    rec: Mapping = {}
    recs = _records(card) if card is not None else []
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
            src["size"] = (f"ASSUMED: the fitted model is a half-space; block H = max(10 a, 5 depth), lateral max(2 H, 20 a) "
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


def indentation_sets(spec: IndentationSpecimen, mesh, card) -> dict:
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
    from .contact import FlatPunch, surface_node_areas, top_surface_nodes
    from .mesh import boundary_faces

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


def run_xpbd_indentation(doc: Mapping, *, tol: float = 1e-9, max_steps: int = 100_000, warm_start: bool = True,
                         iterations: int | None = None) -> dict:
    """Run an XPBD JSON indentation specimen (``write_xpbd(..., indentation=...)``, a flat punch)
    with difftissue's own XPBD solver, from the file's numbers only.

    The constraints are the file's: :class:`~difftissue.solvers.xpbd.StableNeoHookeanConstraints`
    with ``mu``, ``lambda' = lambda_shifted`` and the per-tet rest volumes, ``Dm^-1`` from the
    positions; masses, held components and the punch nodes (moved to ``u_z = -depth``, and
    ``u_x = u_y = 0`` for a bonded punch) from ``specimen``; ``dt``, ``substeps``,
    ``iterations`` from ``setting`` (``iterations`` overrides it). Solved by
    :func:`~difftissue.solvers.xpbd.xpbd_quasi_static_constraints` at each depth of
    ``indenter.depth_steps`` in turn, with ``warm_start`` (default True: the rest state is the
    energy minimum whatever the iteration budget; False: standard XPBD, softer with a small
    budget). Sphere and cone specimens are refused: difftissue's XPBD solver has no contact
    constraint (the ``indenter`` block is for an engine that has one).

    Warm-started XPBD is not unconditionally stable: measured on a 4 x 4 x 2 block of 2.5 mm
    cubes (E = 12 kPa, nu = 0.42), ``dt = 1e-3`` s diverges while ``dt = 2e-4`` s converges in
    374 frames to the static punch force within 1e-8. A non-finite state raises
    :class:`~difftissue.errors.ConvergenceError` (give the file a smaller ``dt``).

    Returns ``{"depths": [m], "forces": [N] (punch reaction along +z, positive compressive),
    "converged": [bool], "steps": [int]}``.
    """
    import jax.numpy as jnp

    from .boundary import BoundaryConditions
    from .solvers.xpbd import StableNeoHookeanConstraints, XPBDSettings, xpbd_quasi_static_constraints

    if doc.get("format") != "difftissue-xpbd/1":
        raise ExportError(f"not a difftissue-xpbd/1 document (format = {doc.get('format')!r})")
    spec = doc.get("specimen") or {}
    if spec.get("experiment") != "indentation":
        raise ExportError("the XPBD document holds no indentation specimen (write it with indentation=...)")
    ind = spec["indenter"]
    if ind["shape"] != "flat_punch":
        raise ExportError(f"difftissue's XPBD solver has no contact constraint: the {ind['shape']} indenter of this file "
                          "(its 'indenter' block: geometry, depth, per-node penalty) is for an XPBD engine with contact; "
                          "only flat-punch specimens run here")
    pts = np.asarray(spec["positions"], dtype=float)
    tets = np.asarray(spec["tets"], dtype=np.int64)
    Ds = np.stack([pts[tets[:, k + 1]] - pts[tets[:, 0]] for k in range(3)], axis=-1)
    Dm_inv = np.linalg.inv(Ds)
    V0 = np.asarray(doc["per_tet"]["rest_volume"], dtype=float)
    lame = doc["lame"]
    cons = StableNeoHookeanConstraints(tets, Dm_inv, V0, np.full(len(tets), lame["mu"]), np.full(len(tets), lame["lambda_shifted"]))
    n = len(pts)
    fixed = np.zeros((n, 3), dtype=bool)
    fx = spec["fixed"]
    if "all_components" in fx:
        fixed[np.asarray(fx["all_components"], dtype=np.int64)] = True
    for c, axis in (("x", 0), ("y", 1), ("z", 2)):
        if c in fx:
            fixed[np.asarray(fx[c], dtype=np.int64), axis] = True
    punch = np.asarray(ind["nodes"], dtype=np.int64)
    fixed[punch, 2] = True
    if ind.get("bonded"):
        fixed[punch, :2] = True
    st = doc["setting"]
    settings = XPBDSettings(dt=st["dt"], substeps=int(st["substeps"]), iterations=int(iterations or st["iterations"]),
                            damping=float("inf"), warm_start=warm_start)
    masses = jnp.asarray(spec["masses"])
    out = {"depths": [], "forces": [], "converged": [], "steps": []}
    for d in ind["depth_steps"]:
        disp = np.zeros((n, 3))
        disp[punch, 2] = -float(d)
        bc = BoundaryConditions(fixed, jnp.asarray(disp), jnp.zeros((n, 3)))
        sol = xpbd_quasi_static_constraints((cons,), jnp.asarray(pts), masses, bc, settings=settings, tol=tol,
                                            max_steps=max_steps, throw=False)
        force = -float(np.asarray(sol.reaction)[punch, 2].sum())
        if not math.isfinite(force):
            from .errors import ConvergenceError

            raise ConvergenceError(f"XPBD diverged (non-finite state) at depth {float(d):.6g} m with dt = {st['dt']:.6g} s, "
                                   f"{settings.iterations} iterations: warm-started XPBD needs a smaller time step on this mesh; "
                                   "export the file with a smaller --dt")
        out["depths"].append(float(d))
        out["forces"].append(force)
        out["converged"].append(bool(sol.converged))
        out["steps"].append(int(sol.steps))
    return out


# ============================================================================ recalibration
#: Largest number of fitted depths an indentation recalibration solves (evenly picked, the last included).
RECALIBRATION_DEPTHS = 4


def _same(a, b) -> bool:
    return a is not None and b is not None and math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=0.0)


def _fit_record(card, spec: IndentationSpecimen, own: str) -> tuple[Mapping | None, list[str]]:
    """The card's simulated indentation record that ``spec`` is the experiment of (fitted with
    model ``own``), or None and the reasons each record does not fit."""
    why = []
    for r in _records(card):
        name = r.get("name")
        missing = [k for k in ("model", "depths", "block_size", "cells", "base") if not r.get(k)]
        if r.get("type") != "Indentation":
            why.append(f"{name!r} is a {r.get('type')} record (a closed form, no simulated specimen)")
        elif missing:
            why.append(f"{name!r} lacks {missing} (a card written before the record held the fit's mesh and depths, or a mesh that is "
                       "no uniform indentation_block)")
        elif r["model"] != own:
            why.append(f"{name!r} was fitted with model {r['model']!r}, not {own!r}")
        elif r.get("indenter") != spec.indenter or r.get("base") != spec.base or not all(
                _same(a, b) for a, b in zip(r["block_size"], spec.size)) or (
                spec.indenter == "cone" and not _same(r.get("half_angle"), spec.half_angle)) or (
                spec.indenter != "cone" and not _same(r.get("radius"), spec.radius)) or (
                spec.indenter == "flat_punch" and bool(r.get("bonded_punch")) != spec.bonded_punch):
            why.append(f"{name!r} is another experiment (indenter, size, base or block differ from the specimen's)")
        else:
            return r, why
    return None, why or ["the card records no indentation scenario"]


def recalibrated_indentation_card(card, spec: IndentationSpecimen, law: str, *, approximate: bool = False):
    """``card`` (a lattice model, :func:`~difftissue.export.model_mismatch`) recalibrated to the
    continuum ``law`` on the indentation experiment it was fitted to.

    The fitted experiment comes from the card's scenario record (:func:`scenario_record` of a
    simulated :class:`~difftissue.scenarios.Indentation`: indenter, radius or half-angle, base,
    block size, the fit's uniform cells and symmetry, penalty, depths, model) and must be the
    experiment of ``spec`` (same indenter, size, base; the cells may differ). Two solves in
    difftissue at up to :data:`RECALIBRATION_DEPTHS` of the fitted depths: the card's own model
    on the fit's mesh at the card's values (what the fit matched to the data), and the target's
    continuum model (:data:`~difftissue.export.LAW_MODELS`) on the specimen's mesh with the
    specimen's contact, at the same values. Every energy here, the contact penalty included,
    is proportional to E, so ``E' = c E`` with the least-squares ``c`` reproduces one depth
    exactly, several up to the two models' different depth dependence (the residuals are
    noted); nu is kept (a force-depth curve of one indenter does not determine it), b is
    dropped (``approximate`` needed when b != 0). The mesh of ``spec`` enters the target's
    solve, so a specimen meshed unlike the fit is recalibrated for its own discretisation.
    Returns a new card (model ``fem_linear`` / ``fem_neo_hookean``) whose
    ``provenance["recalibration"]`` holds the factor, both forces and the notes for the file
    headers (:func:`difftissue.export_fitted.recalibrated_from_reactions`). Refused (one line)
    when the card holds no matching simulated record."""
    from .export import LAW_MODELS, _model_parts, model_mismatch
    from .export_fitted import recalibrated_from_reactions
    from .materials import Material
    from .scenarios import Indentation, indentation_block

    why = model_mismatch(card, law)
    own = next(m for m in _model_parts(card.model) if m in ("springs_volume",))
    rec, reasons = _fit_record(card, spec, own)
    if rec is None:
        raise ExportError(f"{why}; the indentation card cannot be recalibrated: no simulated {own} indentation record matches the "
                          f"specimen ({'; '.join(reasons)}); pass approximate=True (--approximate) to write the card's values with the "
                          "measured error noted")
    if card.cubic_coefficient != 0.0 and not approximate:
        raise ExportError(f"cubic_coefficient b = {card.cubic_coefficient:g} cannot be represented by the continuum {law} law; pass "
                          "approximate=True (--approximate) to recalibrate E alone (b dropped, the residual per depth noted)")
    depths = np.asarray([d for d in rec["depths"] if d > 0.0], dtype=float)
    if depths.size == 0:
        raise ExportError(f"indentation record {rec.get('name')!r} has no positive depth to recalibrate on")
    idx = np.unique(np.round(np.linspace(0, depths.size - 1, min(RECALIBRATION_DEPTHS, depths.size))).astype(int))
    sel = depths[idx]
    sym = rec.get("symmetry", "none")
    cells = [int(v) for v in rec["cells"]]
    if sym == "quarter":
        cells = [cells[0] // 2, cells[1] // 2, cells[2]]
    geo = dict(indenter=spec.indenter, radius=spec.radius, half_angle=spec.half_angle, bonded_punch=spec.bonded_punch, base=spec.base)
    fit = Indentation(indentation_block(rec["block_size"], cells, symmetry=sym), sel, model=own, symmetry=sym,
                      penalty=float(rec.get("penalty") or 100.0), name=str(rec.get("name")), **geo)
    ref = np.asarray(fit.predict(card.material()), dtype=float)
    target = Indentation(spec.mesh(), sel, model=LAW_MODELS[law], symmetry="none", axis_xy=(0.0, 0.0), penalty=spec.penalty, **geo)
    tgt = np.asarray(target.predict(Material(card.youngs_modulus, card.poisson_ratio)), dtype=float)
    mesh_note = ("the specimen's mesh is the fit's" if list(spec.cells) == [int(v) for v in rec["cells"]] and spec.refine is None else
                 f"the specimen's mesh ({spec.cells[0]} x {spec.cells[1]} x {spec.cells[2]} cells) differs from the fit's "
                 f"({rec['cells'][0]} x {rec['cells'][1]} x {rec['cells'][2]}): E is recalibrated for the specimen's discretisation")
    return recalibrated_from_reactions(
        card, law, own, why, ref, tgt, scenario=str(rec.get("name")),
        states=f"depth(s) {[float(f'{d:.6g}') for d in sel]} m (indentation force)",
        record={"depths": sel.tolist()},
        extra_notes=[f"indentation: {own} on the fit's mesh ({sym} symmetry) against {LAW_MODELS[law]} on the specimen with its "
                     f"contact (penalty {spec.penalty:g}); {mesh_note}"])


def indentation_card(card, spec: IndentationSpecimen, law: str | None, *, approximate: bool = False):
    """The card a continuum target (FEBio, SOFA with a tet force field, Abaqus) writes for
    the indentation specimen ``spec``: ``card`` itself, or for a lattice card
    (:func:`~difftissue.export.model_mismatch`) the card recalibrated on its fitted indentation
    (:func:`recalibrated_indentation_card`); where that is impossible, ``approximate`` keeps the
    card's values (the file then notes the measured error) and otherwise it is refused."""
    from .export import _law, model_mismatch

    lw = _law(card, law)
    if not model_mismatch(card, lw):
        return card
    if approximate and _fit_record(card, spec, "springs_volume")[0] is None:
        return card
    return recalibrated_indentation_card(card, spec, lw, approximate=approximate)
