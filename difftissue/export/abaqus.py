"""Abaqus / CalculiX (``.inp``): the material, the compression block, the indentation specimen
and the fitted specimen, in the dialect CalculiX 2.20 also runs (docs/export.md).

Every number goes through :func:`abaqus_number` (CalculiX reads 20 characters of a field),
every label through :func:`abaqus_name`. Conversions: :func:`abaqus_material` (``*ELASTIC`` /
``*HYPERELASTIC, NEO HOOKE``, or ``*HYPERELASTIC, OGDEN, N=2`` for a card recalibrated to a two-term
Ogden law, :func:`~difftissue.export.recalibration.recalibrated_ogden_card`). Decks: :func:`abaqus_model`, :func:`abaqus_indentation_model`,
:func:`abaqus_fitted_model`; :func:`write_abaqus` writes one.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..errors import ExportError
from ..mesh import signed_volumes
from ._common import write_text
from .approximations import approximation_notes, resolve_law
from .card import MaterialCard, header_lines
from .fitted import FittedSpecimen, component_sets, load_steps
from .recalibration import indentation_card
from .specimens import (block_sets, check_indentation, default_displacement, febio_indenter_cap, indentation_sets,
                        no_mesh_with_indentation)

__all__ = ["ABAQUS_FIELD_WIDTH", "ABAQUS_ELEMENTS", "CONE_INCREMENTS_PER_CELL", "abaqus_number", "abaqus_name", "abaqus_material",
           "abaqus_reaction_print", "abaqus_element", "abaqus_quadratic", "abaqus_model", "write_abaqus", "abaqus_indenter_mesh",
           "abaqus_indentation_model", "abaqus_fitted_model"]


_ABAQUS_BAD = re.compile(r"[^A-Za-z0-9_-]")


ABAQUS_FIELD_WIDTH = 20  # characters of a numeric data field that CalculiX reads (Abaqus reads more)


def _strip_zero(s: str) -> str:
    """``0.0035`` -> ``.0035`` (one character less; Fortran and Python read both)."""
    return s[1:] if s.startswith("0.") and len(s) > 2 else s


def _number_forms(x: float, digits: int | None) -> list[str]:
    """Decimal spellings of ``x``: shortest round-trip (``digits=None``) or ``digits``
    significant digits, positional and scientific with a one-digit minimum exponent."""
    unique = digits is None
    prec = None if unique else digits - 1
    sci = np.format_float_scientific(x, precision=prec, unique=unique, trim="-", exp_digits=1)
    pos = np.format_float_positional(x, precision=None if unique else digits, unique=unique, fractional=False, trim="-")
    sign = "-" if pos.startswith("-") else ""
    return [sci, sign + _strip_zero(pos.lstrip("-"))]


def abaqus_number(x: float, width: int = ABAQUS_FIELD_WIDTH) -> str:
    """One number as an Abaqus / CalculiX data field of at most ``width`` (20) characters.

    CalculiX reads only the first 20 characters of a numeric field (``7.575610012003474e-06``,
    21 characters, was read as 7.58), so every number in an ``.inp`` deck goes through here.
    The spelling is exact when the shortest round-trip spelling fits (Python ``repr``, or the
    same digits positional without the leading ``0`` or scientific with a one-digit exponent:
    ``float(abaqus_number(x)) == x``); otherwise it keeps the most significant digits that fit,
    correctly rounded. For a finite double at least 13 significant digits always fit
    (``-d.dddddddddddde-308``), so the relative error is at most ``5e-13``; at most ``5e-15``
    for ``1e-9 <= |x| < 1e10`` (15 digits fit). Units are those of the caller (SI here).
    Raises ExportError for non-finite values.
    """
    x = float(x)
    if not math.isfinite(x):
        raise ExportError(f"cannot write the non-finite number {x!r} into an Abaqus deck")
    text = repr(x)  # the shortest round-trip spelling, most often short enough
    if len(text) <= width:
        return text
    fits = sorted((s for s in _number_forms(x, None) if len(s) <= width), key=len)
    if fits:
        return fits[0]
    for digits in range(17, 0, -1):
        fits = sorted((s for s in _number_forms(x, digits) if len(s) <= width), key=len)
        if fits:
            return fits[0]
    raise ExportError(f"{x!r} does not fit in {width} characters")  # unreachable for width >= 7


def abaqus_name(name: str) -> str:
    """A safe Abaqus label: only ``[A-Za-z0-9_-]`` (others become ``_``), starting with a
    letter (``M_`` is prefixed otherwise), at most 80 characters."""
    s = _ABAQUS_BAD.sub("_", str(name))
    if not s or not s[0].isalpha():
        s = "M_" + s
    return s[:80]


def _abaqus_comment(text: str) -> str:
    return "** " + " ".join(str(text).split())


def _hyperelastic(card: MaterialCard):
    """The two-term Ogden law a recalibrated card carries
    (``provenance["recalibration"]["hyperelastic"]``), or None."""
    rec = (card.provenance or {}).get("recalibration")
    hyper = rec.get("hyperelastic") if isinstance(rec, dict) else None
    return hyper if isinstance(hyper, dict) and hyper.get("law") == "ogden" else None


def _abaqus_law(card: MaterialCard, law: str | None) -> str:
    """The law written: ``"ogden"`` for a card recalibrated to it (``law`` None or
    ``"neo_hookean"``; ``"linear"`` is refused), else :func:`resolve_law`."""
    if _hyperelastic(card) is None:
        return resolve_law(card, law)
    if law not in (None, "neo_hookean", "ogden"):
        raise ExportError(f"law = {law!r}: the card was recalibrated to a two-term Ogden law (finite strain); export the original "
                          "card for that law")
    return "ogden"


def abaqus_material(card: MaterialCard, *, law: str | None = None, approximate: bool = False) -> list[str]:
    """Abaqus keyword lines of the material.

    * ``law="linear"``: ``*ELASTIC`` with the data line ``E, nu``.
    * ``law="neo_hookean"``: ``*HYPERELASTIC, NEO HOOKE`` with the data line ``C10, D1`` where
      ``C10 = mu / 2`` and ``D1 = 2 / K`` (Abaqus: initial shear modulus ``mu0 = 2 C10``, bulk
      modulus ``K0 = 2 / D1``), ``mu = E / (2 (1 + nu))``, ``K = E / (3 (1 - 2 nu))``. Abaqus's
      energy ``C10 (I1bar - 3) + (J - 1)^2 / D1`` differs from FEBio's at finite strain but has
      the same small-strain response (E, nu).
    * a card recalibrated to a two-term Ogden law
      (:func:`~difftissue.export.recalibration.recalibrated_ogden_card`): ``*HYPERELASTIC, OGDEN,
      N=2`` with the data line ``mu1, alpha1, mu2, alpha2, D1, D2`` (mu_i [Pa], D_i [1/Pa]; the
      same keyword and energy in Abaqus and CalculiX 2.20).
    * ``*DENSITY`` with the density.

    Inverse (tested): ``mu = 2 C10``, ``K = 2 / D1``, ``E = 9 K mu / (3 K + mu)``,
    ``nu = (3 K - 2 mu) / (2 (3 K + mu))``.
    """
    law = _abaqus_law(card, law)
    notes = approximation_notes(card, "Abaqus " + law, approximate=approximate)
    lines = [_abaqus_comment(s) for s in header_lines(card, "Abaqus", law) + notes]
    if card.name != abaqus_name(card.name):
        lines.append(_abaqus_comment(f"material name sanitised from {card.name!r}"))
    lines.append(f"*MATERIAL, NAME={abaqus_name(card.name)}")
    if law == "ogden":
        h = _hyperelastic(card)
        data = [v for pair in zip(h["mu"], h["alpha"]) for v in pair] + list(h["d"])
        lines += [f"*HYPERELASTIC, OGDEN, N={len(h['mu'])}", ", ".join(abaqus_number(v) for v in data)]
    elif law == "linear":
        lines += ["*ELASTIC", f"{abaqus_number(card.youngs_modulus)}, {abaqus_number(card.poisson_ratio)}"]
    else:
        c10 = card.shear_modulus / 2.0
        d1 = 2.0 / card.bulk_modulus
        lines += ["*HYPERELASTIC, NEO HOOKE", f"{abaqus_number(c10)}, {abaqus_number(d1)}"]
    lines += ["*DENSITY", abaqus_number(card.density)]
    return lines


def _wrap_ids(ids, per_line: int = 16) -> list[str]:
    ids = [str(int(i)) for i in ids]
    return [", ".join(ids[i:i + per_line]) for i in range(0, len(ids), per_line)]


def abaqus_reaction_print(nset: str) -> list[str]:
    """Keyword lines that print the summed reaction force [N] of node set ``nset`` to the
    ``.dat`` file: ``*NODE PRINT, NSET=<nset>, TOTALS=ONLY`` with ``RF``. Accepted by Abaqus and
    CalculiX (CalculiX writes ``total force (fx,fy,fz) for set <NSET> and time ...`` followed by
    the three sums); CalculiX ignores history output (``*OUTPUT, HISTORY`` with ``RF1, ...``)."""
    return [f"*NODE PRINT, NSET={nset}, TOTALS=ONLY", "RF"]


#: Abaqus solid elements the specimen writers can use (``element=``, ``--element``): linear
#: tets, hybrid linear tets (near-incompressible hyperelasticity), quadratic tets (midside nodes
#: added by :func:`abaqus_quadratic`) and hybrid quadratic tets. CalculiX has C3D4 and C3D10 but
#: no hybrid elements (docs/export.md, tests/test_export_calculix.py).
ABAQUS_ELEMENTS = ("C3D4", "C3D4H", "C3D10", "C3D10H")


#: Local corner pairs of the midside nodes 5..10 of an Abaqus C3D10 (1-2, 2-3, 3-1, 1-4, 2-4, 3-4).
_C3D10_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))


def abaqus_element(element: str) -> str:
    """``element`` upper-cased, checked against :data:`ABAQUS_ELEMENTS` (ExportError otherwise)."""
    e = str(element).upper()
    if e not in ABAQUS_ELEMENTS:
        raise ExportError(f"element = {element!r}: expected one of {list(ABAQUS_ELEMENTS)}")
    return e


def abaqus_quadratic(points, tets):
    """Quadratic tets from linear ones: one midside node per edge at its midpoint [m].

    Returns ``(points (N + E, 3), tets (M, 10), edges (E, 2))``: the first N points are the
    input's, point ``N + k`` is the midpoint of ``edges[k]``; each row of ``tets`` is in Abaqus
    C3D10 order (corners 1-4, then midside 1-2, 2-3, 3-1, 1-4, 2-4, 3-4). Straight edges, so
    the geometry is the linear mesh's."""
    pts = np.asarray(points, dtype=float)
    t = np.asarray(tets, dtype=np.int64)
    pairs = np.sort(t[:, np.array(_C3D10_EDGES)].reshape(-1, 2), axis=1)
    edges, inv = np.unique(pairs, axis=0, return_inverse=True)
    mid = 0.5 * (pts[edges[:, 0]] + pts[edges[:, 1]])
    return np.vstack([pts, mid]), np.hstack([t, len(pts) + inv.reshape(len(t), 6)]), edges


def _abaqus_elements(points, tets, element: str):
    """``(points, connectivity)`` for ``element``: the mesh as is (C3D4, C3D4H) or with midside
    nodes (C3D10, C3D10H: :func:`abaqus_quadratic`)."""
    if element.startswith("C3D10"):
        p, t, _ = abaqus_quadratic(points, tets)
        return p, t
    return np.asarray(points, dtype=float), np.asarray(tets, dtype=np.int64)


def _element_comment(element: str) -> list[str]:
    """Header lines on the element choice (what CalculiX lacks)."""
    out = [f"element: {element}" + {"C3D4": " (linear tet)", "C3D4H": " (hybrid linear tet, for near-incompressible hyperelasticity)",
                                     "C3D10": " (quadratic tet, midside nodes at the edge midpoints)",
                                     "C3D10H": " (hybrid quadratic tet)"}[element]]
    if element.endswith("H"):
        out.append("CalculiX has no hybrid (H) elements: this deck is for Abaqus; use C3D4 or C3D10 in CalculiX (docs/export.md)")
    return out


def abaqus_model(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
                 displacement: float | None = None, element: str = "C3D4") -> str:
    """Abaqus input: the material alone, or with ``mesh`` a complete specimen: ``*NODE``,
    ``*ELEMENT, TYPE=<element>`` (:data:`ABAQUS_ELEMENTS`, default C3D4; C3D10 / C3D10H get
    midside nodes, :func:`abaqus_quadratic`), node sets ``BASE`` (min z, clamped: ``BASE, 1, 3``, not
    ``ENCASTRE``, which CalculiX rejects) and ``TOP`` (max z, moved by ``displacement`` [m] in
    direction 3, free in x and y), ``*SOLID SECTION`` and one ``*STATIC`` step (``NLGEOM=YES``
    for the neo-Hookean law) that prints the summed ``TOP`` reaction [N] to the ``.dat``
    (:func:`abaqus_reaction_print`). Runs in CalculiX 2.20 with C3D4 and C3D10
    (tests/test_export_calculix.py); CalculiX has no hybrid elements."""
    law = resolve_law(card, law)
    element = abaqus_element(element)
    mat = abaqus_material(card, law=law, approximate=approximate)
    if mesh is None:
        return "\n".join(mat) + "\n"
    pts, conn = _abaqus_elements(mesh.points, mesh.tets, element)
    base, top, height = block_sets(SimpleNamespace(points=pts))
    d = default_displacement(height, displacement)
    mname = abaqus_name(card.name)
    lines = ["*HEADING", f"difftissue specimen for material {mname} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in _element_comment(element)] + ["*NODE"]
    for i, p in enumerate(pts, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    lines.append(f"*ELEMENT, TYPE={element}, ELSET=TISSUE")
    for i, t in enumerate(conn, start=1):
        lines.append(f"{i}, " + ", ".join(str(int(n) + 1) for n in t))
    lines.append("*NSET, NSET=BASE")
    lines += _wrap_ids(base + 1)
    lines.append("*NSET, NSET=TOP")
    lines += _wrap_ids(top + 1)
    lines += [f"*SOLID SECTION, ELSET=TISSUE, MATERIAL={mname}", ","]
    lines += mat
    lines += [f"*STEP, NLGEOM={'YES' if law == 'neo_hookean' else 'NO'}", "*STATIC", "0.1, 1.0, 1e-05, 0.1",
              "*BOUNDARY", "BASE, 1, 3", "*BOUNDARY", f"TOP, 3, 3, {abaqus_number(d)}",
              "*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    lines += abaqus_reaction_print("TOP") + ["*END STEP"]
    return "\n".join(lines) + "\n"


def write_abaqus(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
                 displacement: float | None = None, force: bool = False, indentation=None, element: str = "C3D4") -> Path:
    """Write an Abaqus ``.inp`` (see :func:`abaqus_model`; conversion in :func:`abaqus_material`;
    indentation specimens: :func:`abaqus_indentation_model`, C3D4 only)."""
    if indentation is not None:
        no_mesh_with_indentation(mesh)
        if abaqus_element(element) != "C3D4":
            raise ExportError(f"element = {element!r}: the Abaqus indentation specimen is written with C3D4 only")
        return write_text(path, abaqus_indentation_model(card, indentation, law=law, approximate=approximate), force)
    return write_text(path, abaqus_model(card, mesh, law=law, approximate=approximate, displacement=displacement,
                                          element=element), force)


#: Increments per top cell size of the cone's depth in the Abaqus / CalculiX deck (the tip moves
#: at most h / this per increment; measured: h / 20 loses the node under the tip, h / 40 does not),
#: rounded up to a multiple of the protocol's steps.
CONE_INCREMENTS_PER_CELL = 50.0


#: Local nodes of the faces S1..S4 of an Abaqus / CalculiX C3D4 (1-based face number = index + 1).
_C3D4_FACES = ((0, 1, 2), (0, 3, 1), (1, 3, 2), (2, 3, 0))


def abaqus_indenter_mesh(spec, height: float, spacing: float):
    """The meshed rigid indenter of the Abaqus / CalculiX sphere and cone specimens (SI units).

    The cap of :func:`febio_indenter_cap` (rings at most ``spacing / 2`` apart, up to 96
    rings; called with ``spacing`` = half the tissue's top cell size, so the facets are at
    most a quarter of a cell) closed into a fan of C3D4 tets towards one apex node on the axis
    inside the indenter (sphere: its centre ``(0, 0, height + R)``; cone: ``(0, 0, height + 2
    r_cap / tan(theta))``, above the cap's top ring). Each tet is ``(a, c, b, apex)`` for a cap
    facet ``(a, b, c)`` whose normal faces the tissue, so its volume is positive and its face
    S1 (local nodes 1-2-3) is the facet: the contact surface is ``INDENTER, S1``.

    Returns ``(points (N, 3), tets (M, 4) 0-based, r_cap)``; the last point is the apex.
    """
    P, T, r_cap = febio_indenter_cap(spec, height, spacing, max_rings=96)
    if spec.indenter == "sphere":
        apex = np.array([0.0, 0.0, height + spec.radius])
    else:
        apex = np.array([0.0, 0.0, height + 2.0 * r_cap / math.tan(spec.half_angle)])
    pts = np.vstack([P, apex])
    tets = np.column_stack([T[:, 0], T[:, 2], T[:, 1], np.full(len(T), len(P))])
    vol = signed_volumes(pts, tets)
    if not np.all(vol > 0):
        raise ExportError(f"the meshed {spec.indenter} indenter has {int(np.sum(vol <= 0))} inverted tets (a bug)")
    return pts, tets, r_cap


def _tet_faces_on(tets, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(element index (F,), face number 1..4 (F,))`` of the C3D4 face of ``tets`` that each
    boundary triangle of ``faces`` (F, 3) is (each boundary face belongs to one tet)."""
    key = {}
    for e, t in enumerate(np.asarray(tets)):
        for k, loc in enumerate(_C3D4_FACES):
            key.setdefault(tuple(sorted(int(t[i]) for i in loc)), []).append((e, k + 1))
    out = []
    for f in np.asarray(faces):
        hit = key.get(tuple(sorted(int(v) for v in f)), [])
        if len(hit) != 1:
            raise ExportError(f"top face {f.tolist()} is not the face of exactly one tet ({len(hit)})")
        out.append(hit[0])
    arr = np.asarray(out, dtype=np.int64).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def abaqus_indentation_model(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> str:
    """Abaqus input of an indentation specimen, in the dialect that CalculiX 2.20 also runs.

    Sphere and cone: a **meshed rigid indenter** (CalculiX has no analytical rigid surface):
    the cap of :func:`abaqus_indenter_mesh` as C3D4 tets (``ELSET=INDENTER``, a dummy linear
    material ``RIGID_INDENTER``; every node of the indenter is prescribed, ``INDENTER, 1, 2``
    zero and ``INDENTER, 3, 3, -depth``, so it only translates, rigidly, and its material
    never enters), ``*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF`` (the facets ``INDENTER, S1``,
    the master), ``*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF`` (the tissue's top faces, the slave),
    ``*SURFACE INTERACTION`` with ``*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR`` and the
    slope ``K = p E / h`` [Pa/m] (difftissue's per-node penalty ``kappa_i = p E sqrt(A_i)``
    per tributary area ``A_i = h^2``, ``h`` of the top node on the axis: CalculiX's spring force
    is ``K A_i`` times the overclosure, ``A_i`` a third of the slave faces at the node), no
    ``*FRICTION`` (frictionless in both codes), ``*CONTACT PAIR, INTERACTION=INDENTER_CONTACT,
    TYPE=NODE TO SURFACE`` with ``TOP_SURF, INDENTER_SURF``. The indentation force is minus the
    summed z reaction of node set ``INDENTER``. Flat punch: ``*BOUNDARY`` ``PUNCH, 3, 3,
    -depth`` (plus ``PUNCH, 1, 2`` for a bonded punch). A bonded base is ``BASE, 1, 3``. The
    summed reaction [N] of ``PUNCH`` or ``INDENTER`` is printed to the ``.dat``
    (:func:`abaqus_reaction_print`). ``NLGEOM=YES`` for the neo-Hookean law only (the linear
    law is difftissue's small-strain ``fem_linear``; the contact is found in the deformed
    configuration either way).

    All decks run in CalculiX 2.20 (tests/test_export_calculix.py). For Abaqus the same deck is
    valid; an Abaqus user who wants a reference node (force control) may replace the indenter's
    ``*BOUNDARY`` lines by ``*RIGID BODY, ELSET=INDENTER, REF NODE=...`` (CalculiX puts the
    rotations on a separate ``ROT NODE``, which Abaqus does not know: not one dialect).
    """
    check_indentation(spec, "Abaqus")
    card = indentation_card(card, spec, law, approximate=approximate)
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    law = resolve_law(card, law)
    mat = abaqus_material(card, law=law, approximate=approximate)
    mname = abaqus_name(card.name)
    pts = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    H = s["H"]
    lines = ["*HEADING", f"difftissue indentation specimen for material {mname} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in spec.describe()]
    contact = spec.indenter in ("sphere", "cone")
    if contact:
        ipts, itets, r_cap = abaqus_indenter_mesh(spec, H, 0.5 * s["h"])
        n0, e0 = len(pts), len(tets)
        K = spec.penalty * card.youngs_modulus / s["h"]
        lines += [_abaqus_comment(t) for t in (
            f"meshed rigid {spec.indenter}: {len(itets)} facets out to r = {r_cap:.6g} m (the cap's C3D4 fan to one apex node, "
            "face S1 of each tet is a facet); every indenter node is moved by (0, 0, -depth): a rigid translation",
            f"frictionless penalty contact (node to surface): K = p E / h = {spec.penalty:g} x {card.youngs_modulus:.10g} Pa / "
            f"{s['h']:.10g} m = {K:.10g} Pa/m; spring force K A_i x overclosure at the top node with tributary area A_i, "
            "difftissue's kappa_i = p E sqrt(A_i) where A_i = h^2 (uniform top cells)",
            "Abaqus: valid as written; for force control replace the INDENTER boundary lines by *RIGID BODY, ELSET=INDENTER, "
            "REF NODE=<a new node> and load that node")]
    lines.append("*NODE")
    for i, p in enumerate(pts, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    if contact:
        for i, p in enumerate(ipts, start=n0 + 1):
            lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    lines.append("*ELEMENT, TYPE=C3D4, ELSET=TISSUE")
    for i, t in enumerate(tets, start=1):
        lines.append(f"{i}, " + ", ".join(str(int(n) + 1) for n in t))
    if contact:
        lines.append("*ELEMENT, TYPE=C3D4, ELSET=INDENTER")
        for i, t in enumerate(itets, start=e0 + 1):
            lines.append(f"{i}, " + ", ".join(str(int(n) + n0 + 1) for n in t))
    for name, arr in (("BASE", s["base"]), ("TOP", s["top"])):
        lines.append(f"*NSET, NSET={name}")
        lines += _wrap_ids(np.atleast_1d(arr) + 1)
    if spec.base == "sliding":
        lines += ["*NSET, NSET=BASE_ANCHOR", str(s["anchor"] + 1), "*NSET, NSET=BASE_OTHER", str(s["other"] + 1)]
    if spec.indenter == "flat_punch":
        lines.append("*NSET, NSET=PUNCH")
        lines += _wrap_ids(s["punch"] + 1)
    lines += [f"*SOLID SECTION, ELSET=TISSUE, MATERIAL={mname}", ","]
    lines += mat
    if contact:
        el, face = _tet_faces_on(tets, s["top_faces"])
        lines += ["*NSET, NSET=INDENTER, GENERATE", f"{n0 + 1}, {n0 + len(ipts)}, 1"]
        for k in range(1, 5):
            if np.any(face == k):
                lines.append(f"*ELSET, ELSET=TOP_S{k}")
                lines += _wrap_ids(np.sort(el[face == k]) + 1)
        lines.append("*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF")
        lines += [f"TOP_S{k}, S{k}" for k in range(1, 5) if np.any(face == k)]
        lines += ["*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF", "INDENTER, S1",
                  _abaqus_comment("the indenter's material: every indenter node is prescribed, so these constants never enter"),
                  "*SOLID SECTION, ELSET=INDENTER, MATERIAL=RIGID_INDENTER", ",",
                  "*MATERIAL, NAME=RIGID_INDENTER", "*ELASTIC", f"{abaqus_number(1e3 * card.youngs_modulus)}, 0.3",
                  "*SURFACE INTERACTION, NAME=INDENTER_CONTACT", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", abaqus_number(K),
                  "*CONTACT PAIR, INTERACTION=INDENTER_CONTACT, TYPE=NODE TO SURFACE", "TOP_SURF, INDENTER_SURF"]
    n_inc = spec.steps
    axis_top = np.flatnonzero(np.hypot(pts[s["top"], 0], pts[s["top"], 1]) <= 1e-9 * H) if spec.indenter == "cone" else []
    if spec.indenter == "cone":
        # the node-to-surface pairing loses the node under the sharp tip when the tip moves more than ~h/40 per increment;
        # a multiple of the protocol's steps, so that every depth of the protocol ends an increment (printed to the .dat)
        per_step = int(math.ceil(CONE_INCREMENTS_PER_CELL * spec.depth / s["h"] / spec.steps))
        n_inc = spec.steps * max(1, per_step)
        lines.append(_abaqus_comment(
            f"cone: {n_inc} increments, {n_inc // spec.steps} per depth step (the tip moves at most h / {CONE_INCREMENTS_PER_CELL:g} per "
            "increment: with larger ones CalculiX's node-to-surface search loses the node under the sharp tip)" + ("; the top node on "
            "the axis is held in x and y, as in difftissue's Indentation (the axisymmetric solution: under a frictionless sharp tip it "
            "is in unstable equilibrium, and without the hold it slides off the axis down one flank)" if len(axis_top) else "")))
        if len(axis_top):
            lines += ["*NSET, NSET=AXIS_TOP", str(int(s["top"][axis_top[0]]) + 1)]
    inc = abaqus_number(1.0 / n_inc)
    lines += [f"*STEP, NLGEOM={'YES' if law == 'neo_hookean' else 'NO'}, INC={max(1000, 4 * n_inc)}", "*STATIC",
              f"{inc}, 1.0, 1e-05, {inc}", "*BOUNDARY"]
    if spec.base == "bonded":
        lines.append("BASE, 1, 3")
    else:
        lines += ["BASE, 3, 3, 0.0", "BASE_ANCHOR, 1, 2, 0.0", "BASE_OTHER, 2, 2, 0.0"]
    if contact:
        lines += ["INDENTER, 1, 2, 0.0", f"INDENTER, 3, 3, {abaqus_number(-spec.depth)}"]
        if len(axis_top):
            lines.append("AXIS_TOP, 1, 2, 0.0")
    else:
        lines.append(f"PUNCH, 3, 3, {abaqus_number(-spec.depth)}")
        if spec.bonded_punch:
            lines.append("PUNCH, 1, 2, 0.0")
    lines += ["*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    lines += abaqus_reaction_print("INDENTER" if contact else "PUNCH")
    lines.append("*END STEP")
    return "\n".join(lines) + "\n"


def _refuse_pre_stretch(cards, target: str):
    lam = [c.pre_stretch for c in cards] + [c.pre_stretch_y for c in cards]
    if any(c.is_pre_stretched for c in cards):
        # dropping the pre-stretch makes the incision stress-free: nothing would open
        raise ExportError(f"{target} fitted specimen: pre_stretch {sorted(set(lam))} cannot be represented by {target}, and without it "
                          "the cut specimen is stress-free and does not open (--approximate does not apply); export the incision "
                          "to febio, xpbd or vtu")


def _quadratic_specimen(spec: FittedSpecimen):
    """``(spec with midside nodes, tets10)``: points of :func:`~difftissue.export.abaqus_quadratic`;
    a midside node is fixed / in the reaction set in a component when both edge ends are, with
    the mean of their prescribed values (the linear element's value there)."""
    pts, t10, e = abaqus_quadratic(spec.points, spec.tets)
    both = lambda m: np.concatenate([m, m[e[:, 0]] & m[e[:, 1]]])  # noqa: E731
    fixed = both(spec.fixed)
    presc = np.where(fixed, np.concatenate([spec.prescribed, 0.5 * (spec.prescribed[e[:, 0]] + spec.prescribed[e[:, 1]])]), 0.0)
    reaction = None if spec.reaction is None else both(spec.reaction)
    return dataclasses.replace(spec, points=pts, fixed=fixed, prescribed=presc, reaction=reaction), t10


def abaqus_fitted_model(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False,
                        element: str = "C3D4") -> str:
    """Abaqus input of a fitted specimen: ``*NODE``, ``*ELEMENT, TYPE=<element>, ELSET=<region>`` (C3D4 default;
    C3D10 / C3D10H: midside nodes, a node set / prescribed value where both edge ends have one),
    one ``*SOLID SECTION`` and material per region, ``*NSET`` per held / prescribed component
    (``FIXED_X``, ``PRESCRIBED_X``, ...) and ``REACTION``, and one ``*STEP`` / ``*STATIC`` whose
    ``*BOUNDARY`` gives every prescribed component its own magnitude (data lines ``node, c, c,
    value``), ramped over the step (the default amplitude of a ``*STATIC`` step), with initial and
    largest increment ``1 /`` :func:`load_steps` of the step. An incision is refused: a pre-stretched one because Abaqus has no
    prestrain gradient here, and without it the cut does not open; one without pre-stretch because it carries no load."""
    law = _abaqus_law(card, law)
    element = abaqus_element(element)
    cards = spec.region_cards(card)
    _refuse_pre_stretch(cards, "Abaqus")
    if spec.experiment == "incision":
        raise ExportError(f"Abaqus fitted specimen {spec.scenario!r}: an incision is loaded only by its pre-stretch (its boundary holds "
                          "faces at zero displacement), and this one has none, so the deck would carry no load and the cut would not "
                          "open: it cannot reproduce the fitted widths; export the incision to febio, xpbd or vtu")
    lines = ["*HEADING", f"difftissue fitted specimen {spec.scenario} for material {abaqus_name(card.name)} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in spec.describe() + _element_comment(element)]
    tets = spec.tets
    if element.startswith("C3D10"):
        spec, tets = _quadratic_specimen(spec)
    lines.append("*NODE")
    for i, p in enumerate(spec.points, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(v) for v in p))
    eid = 0
    elsets = {}
    for r, rname in enumerate(spec.region_names):
        sel = np.flatnonzero(spec.region_ids == r)
        if sel.size == 0:
            continue
        es = abaqus_name(rname).upper()
        if es in elsets.values():
            raise ExportError(f"Abaqus fitted specimen: region names {list(spec.region_names)} collide once sanitised")
        elsets[r] = es
        lines.append(f"*ELEMENT, TYPE={element}, ELSET={es}")
        for t in tets[sel]:
            eid += 1
            lines.append(f"{eid}, " + ", ".join(str(int(n) + 1) for n in t))
    sets = component_sets(spec)
    for c, (zero, nz) in zip("XYZ", sets):
        for name, arr in ((f"FIXED_{c}", zero), (f"PRESCRIBED_{c}", nz)):
            if arr.size:
                lines.append(f"*NSET, NSET={name}")
                lines += _wrap_ids(arr + 1)
    if spec.reaction is not None:
        lines.append("*NSET, NSET=REACTION")
        lines += _wrap_ids(np.flatnonzero(spec.reaction.any(axis=1)) + 1)
    done = set()
    for r, es in elsets.items():
        mname = abaqus_name(cards[r].name)
        lines += [f"*SOLID SECTION, ELSET={es}, MATERIAL={mname}", ","]
        if mname not in done:
            lines += abaqus_material(cards[r], law=law, approximate=approximate)
            done.add(mname)
    inc = abaqus_number(1.0 / load_steps(spec))
    lines += [f"*STEP, NLGEOM={'NO' if law == 'linear' else 'YES'}", "*STATIC", f"{inc}, 1.0, 1e-05, {inc}", "*BOUNDARY"]
    for c, (zero, nz) in zip("XYZ", sets):
        if zero.size:
            d = "XYZ".index(c) + 1
            lines.append(f"FIXED_{c}, {d}, {d}, 0.0")
    for ci, (zero, nz) in enumerate(sets):
        d = ci + 1
        for n in nz:
            lines.append(f"{int(n) + 1}, {d}, {d}, {abaqus_number(spec.prescribed[n, ci])}")
    lines += ["*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    if spec.reaction is not None:
        lines += abaqus_reaction_print("REACTION")
    lines.append("*END STEP")
    return "\n".join(lines) + "\n"
