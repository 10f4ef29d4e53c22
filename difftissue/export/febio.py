"""FEBio 4.0 (``.feb``, febio_spec 4.0): the material, the compression block, the indentation
specimen and the fitted specimen (docs/export.md).

Conversions: :func:`febio_material` (E and nu directly; ``neo-Hookean`` / ``isotropic elastic``,
``prestrain elastic`` for a pre-stretch). Models: :func:`febio_model` (material alone or a block),
:func:`febio_indentation_model`, :func:`febio_fitted_model`; :func:`write_febio` writes one.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import ExportError
from ._common import finite, fmt, write_text, xml_comment, xml_text
from .approximations import approximation_notes, resolve_law
from .card import MaterialCard, header_lines
from .fitted import FittedSpecimen, component_sets, load_steps
from .recalibration import indentation_card
from .specimens import (FEBIO_INDENTER_MATERIAL, block_sets, check_indentation, default_displacement, febio_indenter_cap,
                        indentation_sets, no_mesh_with_indentation)

__all__ = ["febio_material", "febio_prestrain_gradient", "pre_stretch_from_febio_gradient", "pre_stretches_from_febio_gradient", "febio_model", "write_febio",
           "febio_indentation_model", "febio_fitted_model"]


def febio_material(card: MaterialCard, *, law: str | None = None, approximate: bool = False, mat_id: int = 1) -> ET.Element:
    """The FEBio ``<Material>`` element for ``card``.

    Conversion: none needed, FEBio takes Young's modulus and Poisson's ratio directly.

    * ``law="neo_hookean"`` -> ``<material type="neo-Hookean"><E>E</E><v>nu</v>`` whose energy is
      ``W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2`` with ``mu, lambda`` the Lamé parameters
      of ``(E, nu)``: identical to difftissue's ``fem_neo_hookean`` and to the small-strain
      response of every model.
    * ``law="linear"`` -> ``type="isotropic elastic"`` (same ``E``, ``v``).
    * ``<density>`` is the card's density [kg/m^3].

    The default law is ``neo_hookean`` for cards of a finite-strain model (``springs_volume``,
    ``fem_neo_hookean``, ``stable_neo_hookean``, also within a joint ``"hertz; springs_volume"``)
    and ``linear`` otherwise (``fem_linear`` and the analytic solutions: ``hertz``, ...). A nonzero
    ``cubic_coefficient`` is refused unless ``approximate``, which drops it and records the error
    in a comment. A ``pre_stretch`` other than 1 wraps the material in FEBio's
    ``<material type="prestrain elastic">`` with ``<elastic type=...>`` (the law above) and
    ``<prestrain type="prestrain gradient"><ramp>1.0</ramp><F0>l,0,0,0,l,0,0,0,1</F0>``
    (:func:`febio_prestrain_gradient`); a ``pre_stretch_y`` (anisotropic) gives
    ``F0 = diag(pre_stretch, pre_stretch_y, 1)``.
    """
    law = resolve_law(card, law)
    notes = approximation_notes(card, "FEBio " + law, approximate=approximate, pre_stretch_ok=True)
    lam0, lam_y = card.pre_stretch, card.pre_stretch_y
    mats = ET.Element("Material")
    for line in header_lines(card, "FEBio", law) + notes:
        mats.append(xml_comment(line))
    etype = "neo-Hookean" if law == "neo_hookean" else "isotropic elastic"
    if not card.is_pre_stretched:
        m = ET.SubElement(mats, "material", {"id": str(mat_id), "name": card.name, "type": etype})
        ET.SubElement(m, "density").text = fmt(card.density)
        ET.SubElement(m, "E").text = fmt(card.youngs_modulus)
        ET.SubElement(m, "v").text = fmt(card.poisson_ratio)
        return mats
    if card.is_anisotropic_pre_stretch:
        E, nu = card.youngs_modulus, card.poisson_ratio
        sx = E * ((lam0 - 1.0) + nu * (lam_y - 1.0)) / (1.0 - nu * nu)
        sy = E * ((lam_y - 1.0) + nu * (lam0 - 1.0)) / (1.0 - nu * nu)
        mats.append(xml_comment(
            f"anisotropic pre-tension: pre_stretch lambda_x = {lam0:.10g}, pre_stretch_y lambda_y = {lam_y:.10g} (the stress-free "
            f"state is the mesh shrunk by diag(1/lambda_x, 1/lambda_y, 1)): prestrain gradient F0 = diag(lambda_x, lambda_y, 1); "
            f"small-strain biaxial pre-stresses E (eps_x + nu eps_y) / (1 - nu^2) = {sx:.6g} Pa, (x <-> y) {sy:.6g} Pa"))
    else:
        sigma0 = card.youngs_modulus * (lam0 - 1.0) / (1.0 - card.poisson_ratio)
        mats.append(xml_comment(
            f"pre-tension: pre_stretch lambda0 = {lam0:.10g} in x and y (the stress-free state is the mesh shrunk by 1/lambda0 "
            f"in x and y): prestrain gradient F0 = diag(lambda0, lambda0, 1); small-strain equibiaxial pre-stress "
            f"E (lambda0 - 1) / (1 - nu) = {sigma0:.6g} Pa"))
    m = ET.SubElement(mats, "material", {"id": str(mat_id), "name": card.name, "type": "prestrain elastic"})
    ET.SubElement(m, "density").text = fmt(card.density)
    el = ET.SubElement(m, "elastic", {"type": etype})
    ET.SubElement(el, "density").text = fmt(card.density)
    ET.SubElement(el, "E").text = fmt(card.youngs_modulus)
    ET.SubElement(el, "v").text = fmt(card.poisson_ratio)
    pre = ET.SubElement(m, "prestrain", {"type": "prestrain gradient"})
    ET.SubElement(pre, "ramp").text = "1.0"
    ET.SubElement(pre, "F0").text = febio_prestrain_gradient(lam0, lam_y if card.is_anisotropic_pre_stretch else None)
    return mats


def febio_prestrain_gradient(pre_stretch: float, pre_stretch_y: float | None = None) -> str:
    """FEBio ``<F0>`` text of difftissue's pre-stretch: ``diag(lambda_x, lambda_y, 1)`` row by row.

    FEBio's ``prestrain elastic`` evaluates its ``elastic`` material at ``F Fp`` with ``Fp`` the
    prestrain gradient (map from the stress-free to the reference configuration, Maas et al.
    2016); difftissue's pre-stretch makes the stress-free state the mesh shrunk by
    ``diag(1/lambda_x, 1/lambda_y, 1)``, so ``Fp = diag(lambda_x, lambda_y, 1)``
    (``pre_stretch_y`` None: ``lambda_y = lambda_x = pre_stretch``). Inverses:
    :func:`pre_stretch_from_febio_gradient` (equibiaxial), :func:`pre_stretches_from_febio_gradient`.
    """
    lam0 = finite(pre_stretch, "pre_stretch")
    if lam0 <= 0:
        raise ExportError(f"pre_stretch = {lam0:g} must be > 0")
    lam_y = lam0 if pre_stretch_y is None else finite(pre_stretch_y, "pre_stretch_y")
    if lam_y <= 0:
        raise ExportError(f"pre_stretch_y = {lam_y:g} must be > 0")
    return ",".join(fmt(v) for v in (lam0, 0.0, 0.0, 0.0, lam_y, 0.0, 0.0, 0.0, 1.0))


def pre_stretches_from_febio_gradient(text: str) -> tuple[float, float]:
    """``(lambda_x, lambda_y)`` from an FEBio ``<F0>`` of the form ``diag(lambda_x, lambda_y, 1)``
    (others refused)."""
    try:
        F = np.array([float(v) for v in str(text).split(",")]).reshape(3, 3)
    except ValueError:
        raise ExportError(f"F0 = {text!r}: expected 9 comma-separated numbers") from None
    if not (np.allclose(F, np.diag(np.diag(F)), rtol=0, atol=0) and F[2, 2] == 1.0):
        raise ExportError(f"F0 = {text!r} is not an in-plane pre-stretch diag(lx, ly, 1)")
    return float(F[0, 0]), float(F[1, 1])


def pre_stretch_from_febio_gradient(text: str) -> float:
    """``lambda0`` from an FEBio ``<F0>`` of the form ``diag(lambda0, lambda0, 1)`` (others refused)."""
    try:
        F = np.array([float(v) for v in str(text).split(",")]).reshape(3, 3)
    except ValueError:
        raise ExportError(f"F0 = {text!r}: expected 9 comma-separated numbers") from None
    if not (np.allclose(F, np.diag(np.diag(F)), rtol=0, atol=0) and F[0, 0] == F[1, 1] and F[2, 2] == 1.0):
        raise ExportError(f"F0 = {text!r} is not an in-plane equibiaxial pre-stretch diag(l, l, 1)")
    return float(F[0, 0])


def febio_model(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
                displacement: float | None = None, steps: int = 10) -> ET.Element:
    """A complete ``<febio_spec version="4.0">`` tree (material only when ``mesh`` is None).

    With a mesh: nodes, ``tet4`` elements, a ``SolidDomain``, the base (min z) fixed with
    ``zero displacement`` and the top (max z) moved by ``displacement`` [m] along z
    (``prescribed displacement`` ramped by a linear load curve over ``steps`` static steps).
    Default displacement: -10 % of the height (compression).
    """
    root = ET.Element("febio_spec", {"version": "4.0"})
    ET.SubElement(root, "Module", {"type": "solid"})
    mats = febio_material(card, law=law, approximate=approximate)
    if mesh is None:
        root.append(mats)
        return root
    base, top, height = block_sets(mesh)
    d = default_displacement(height, displacement)
    ctrl = ET.SubElement(root, "Control")
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(int(steps))
    ET.SubElement(ctrl, "step_size").text = fmt(1.0 / steps)
    root.append(mats)
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(np.asarray(mesh.points, dtype=float), start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(fmt(c) for c in p)
    elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": "tissue"})
    for i, t in enumerate(np.asarray(mesh.tets), start=1):
        ET.SubElement(elems, "elem", {"id": str(i)}).text = ",".join(str(int(n) + 1) for n in t)
    ET.SubElement(meshel, "NodeSet", {"name": "base"}).text = ",".join(str(int(n) + 1) for n in base)
    ET.SubElement(meshel, "NodeSet", {"name": "top"}).text = ",".join(str(int(n) + 1) for n in top)
    doms = ET.SubElement(root, "MeshDomains")
    ET.SubElement(doms, "SolidDomain", {"name": "tissue", "mat": card.name})
    bnd = ET.SubElement(root, "Boundary")
    fix = ET.SubElement(bnd, "bc", {"name": "fixed_base", "node_set": "base", "type": "zero displacement"})
    for dof in ("x_dof", "y_dof", "z_dof"):
        ET.SubElement(fix, dof).text = "1"
    pre = ET.SubElement(bnd, "bc", {"name": "top_displacement", "node_set": "top", "type": "prescribed displacement"})
    ET.SubElement(pre, "dof").text = "z"
    ET.SubElement(pre, "value", {"lc": "1"}).text = fmt(d)
    ET.SubElement(pre, "relative").text = "0"
    _febio_ramp_and_output(root, {"top": ",".join(str(int(n) + 1) for n in top)})
    return root


def _febio_static_root(comments, steps: int) -> ET.Element:
    """``<febio_spec version="4.0">`` with ``comments``, the solid ``Module`` and a STATIC
    ``Control`` of ``steps`` time steps of ``1/steps`` (the specimen models' common head)."""
    root = ET.Element("febio_spec", {"version": "4.0"})
    for line in comments:
        root.append(xml_comment(line))
    ET.SubElement(root, "Module", {"type": "solid"})
    ctrl = ET.SubElement(root, "Control")
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(int(steps))
    ET.SubElement(ctrl, "step_size").text = fmt(1.0 / steps)
    return root


def _febio_ramp_and_output(root: ET.Element, reactions: Mapping[str, str] | None = None, rigid: Sequence[int] = ()) -> None:
    """FEBio ``LoadData`` (load controller 1: a linear ramp 0 -> 1 over the step) and ``Output``:
    the plot file (displacement, stress, reaction forces) and a ``<logfile>`` that writes the
    reaction force [N] of each node set in ``reactions`` (``{set name: "1,2,..."}``, 1-based
    ids: ``<node_data data="Rx;Ry;Rz" file="reaction_<set>.txt" delim=",">ids</node_data>``,
    one line per node and step; sum them) and of each rigid material id in ``rigid``
    (``<rigid_body_data data="Fx;Fy;Fz">id</rigid_body_data>``). FEBio reports reactions only
    on prescribed degrees of freedom, so the writers prescribe 0 (``prescribed displacement``)
    rather than ``zero displacement`` on every set listed here."""
    ld = ET.SubElement(root, "LoadData")
    lc = ET.SubElement(ld, "load_controller", {"id": "1", "name": "ramp", "type": "loadcurve"})
    ET.SubElement(lc, "interpolate").text = "LINEAR"
    pts = ET.SubElement(lc, "points")
    ET.SubElement(pts, "pt").text = "0,0"
    ET.SubElement(pts, "pt").text = "1,1"
    out = ET.SubElement(root, "Output")
    plot = ET.SubElement(out, "plotfile", {"type": "febio"})
    for var in ("displacement", "stress", "reaction forces"):
        ET.SubElement(plot, "var", {"type": var})
    if reactions or rigid:
        log = ET.SubElement(out, "logfile")
        for name, ids in (reactions or {}).items():
            ET.SubElement(log, "node_data", {"data": "Rx;Ry;Rz", "name": f"reaction_{name}", "file": f"reaction_{name}.txt",
                                             "delim": ","}).text = ids
        for rid in rigid:
            ET.SubElement(log, "rigid_body_data", {"data": "Fx;Fy;Fz", "name": f"rigid_{rid}_force", "file": f"rigid_{rid}_force.txt",
                                                   "delim": ","}).text = str(int(rid))


def _febio_zero_prescribed(bnd: ET.Element, name: str, nset: str, dofs: str) -> None:
    """Hold ``dofs`` (e.g. ``"xyz"``) of node set ``nset`` at 0 by ``prescribed displacement``
    (value 0, one BC per dof) instead of ``zero displacement``: FEBio records reaction forces
    only for prescribed degrees of freedom, and this set's reaction is reported."""
    for d in dofs:
        bc = ET.SubElement(bnd, "bc", {"name": f"{name}_{d}", "node_set": nset, "type": "prescribed displacement"})
        ET.SubElement(bc, "dof").text = d
        ET.SubElement(bc, "value", {"lc": "1"}).text = "0.0"
        ET.SubElement(bc, "relative").text = "0"


def write_febio(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
                displacement: float | None = None, force: bool = False, indentation=None) -> Path:
    """Write an FEBio ``.feb`` file (febio_spec 4.0): the material alone, with ``mesh`` a
    complete compression specimen (see :func:`febio_model`), or with ``indentation`` (an
    :class:`~difftissue.export.specimens.IndentationSpecimen`) an indentation specimen
    (:func:`febio_indentation_model`). Conversion: :func:`febio_material`."""
    if indentation is not None:
        no_mesh_with_indentation(mesh)
        text = xml_text(febio_indentation_model(card, indentation, law=law, approximate=approximate))
        return write_text(path, text, force)
    text = xml_text(febio_model(card, mesh, law=law, approximate=approximate, displacement=displacement))
    return write_text(path, text, force)


def febio_indentation_model(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """FEBio 4.0 model of an indentation specimen (:class:`~difftissue.export.specimens.IndentationSpecimen`).

    Tissue (all indenters): nodes ``1..N`` (``<Nodes name="specimen">``), ``tet4`` elements
    ``1..Nt`` (``tissue``), node sets ``base``, ``top`` (and ``base_anchor``, ``base_other``
    for a sliding base); the base ``z = 0`` is ``zero displacement`` x, y, z (bonded) or z only
    plus ``base_anchor`` (x, y) and ``base_other`` (y) (sliding).

    Flat punch: the ``prescribed displacement`` (``dof`` z, ``-depth`` ramped by load
    controller 1 over ``spec.steps`` static steps) of the node set ``punch`` (top nodes within
    the radius), plus ``zero displacement`` x, y of the same set for a bonded punch. The punch
    force is the sum of the ``reaction forces`` (plot variable) over ``punch``.

    Sphere and cone: a meshed rigid indenter, as FEBio users model one (FEBio 4.0 has no
    analytical sphere or cone): the cap of :func:`febio_indenter_cap` (``tri3`` shells, nodes
    ``N+1..``, elements ``Nt+1..``) in a ``ShellDomain`` of a ``<material type="rigid body">``
    (``center_of_mass`` at the sphere centre / cone tip), ``rigid_fixed`` x, y and the three
    rotations, ``rigid_displacement`` z = ``-depth`` (load controller 1); frictionless
    ``sliding-elastic`` contact (``fric_coeff`` 0) on the ``SurfacePair`` with the tissue's top
    face as ``primary`` and the indenter cap as ``secondary``, penalty method (``laugon`` 0,
    ``auto_penalty`` 0) with ``penalty = p E / h`` [Pa/m], difftissue's per-node penalty
    ``kappa_i = p E sqrt(A_i)`` per tributary area (``h = sqrt(A)`` of the top node on the
    axis). The indentation force is minus the sum of the base's ``reaction forces`` along z
    (static equilibrium, no other loads). Keyword sources: docs/export.md.
    """
    check_indentation(spec, "FEBio")
    card = indentation_card(card, spec, law, approximate=approximate)
    contact = spec.indenter in ("sphere", "cone")
    if contact and card.name == FEBIO_INDENTER_MATERIAL:
        raise ExportError(f"FEBio indentation specimen: the card's name {card.name!r} is the indenter's rigid material name; "
                          "rename the card (its 'name')")
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    pts_t = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    H = s["H"]
    root = _febio_static_root(spec.describe(), spec.steps)
    mats = febio_material(card, law=law, approximate=approximate)
    root.append(mats)
    if contact:
        cap_pts, cap_tris, r_cap = febio_indenter_cap(spec, H, spacing=s["h"])
        centre = (0.0, 0.0, H + spec.radius) if spec.indenter == "sphere" else (0.0, 0.0, H)
        mats.append(xml_comment(
            "the indenter: a rigid body (FEBio 'rigid body' material; E and v are used only by FEBio's auto-penalty, "
            "which this file does not use); center_of_mass = " + ("the sphere centre (0, 0, H + R)" if spec.indenter == "sphere"
                                                                  else "the cone tip (0, 0, H)")))
        rig = ET.SubElement(mats, "material", {"id": "2", "name": FEBIO_INDENTER_MATERIAL, "type": "rigid body"})
        ET.SubElement(rig, "density").text = fmt(card.density)
        ET.SubElement(rig, "E").text = fmt(card.youngs_modulus)
        ET.SubElement(rig, "v").text = fmt(card.poisson_ratio)
        ET.SubElement(rig, "center_of_mass").text = ",".join(fmt(c) for c in centre)
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(pts_t, start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(fmt(c) for c in p)
    n_t = len(pts_t)
    if contact:
        meshel.append(xml_comment(
            f"indenter cap: {len(cap_pts)} nodes on the {spec.indenter} (tip at (0, 0, H)), {len(cap_tris)} tri3 facets, "
            f"horizontal radius {r_cap:.6g} m (contact radius at the final depth {spec.contact_radius():.6g} m); "
            "facet normals point away from the indenter, towards the tissue"))
        cnodes = ET.SubElement(meshel, "Nodes", {"name": "indenter"})
        for i, p in enumerate(cap_pts, start=n_t + 1):
            ET.SubElement(cnodes, "node", {"id": str(i)}).text = ",".join(fmt(c) for c in p)
    elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": "tissue"})
    for i, t in enumerate(tets, start=1):
        ET.SubElement(elems, "elem", {"id": str(i)}).text = ",".join(str(int(n) + 1) for n in t)
    if contact:
        shells = ET.SubElement(meshel, "Elements", {"type": "tri3", "name": "indenter_shell"})
        for i, t in enumerate(cap_tris, start=len(tets) + 1):
            ET.SubElement(shells, "elem", {"id": str(i)}).text = ",".join(str(int(n) + n_t + 1) for n in t)
    ids = lambda a: ",".join(str(int(n) + 1) for n in np.atleast_1d(a))  # noqa: E731
    ET.SubElement(meshel, "NodeSet", {"name": "base"}).text = ids(s["base"])
    ET.SubElement(meshel, "NodeSet", {"name": "top"}).text = ids(s["top"])
    if spec.base == "sliding":
        ET.SubElement(meshel, "NodeSet", {"name": "base_anchor"}).text = ids(s["anchor"])
        ET.SubElement(meshel, "NodeSet", {"name": "base_other"}).text = ids(s["other"])
    if not contact:
        ET.SubElement(meshel, "NodeSet", {"name": "punch"}).text = ids(s["punch"])
    else:
        surf = ET.SubElement(meshel, "Surface", {"name": "tissue_top"})
        for i, f in enumerate(s["top_faces"], start=1):
            ET.SubElement(surf, "tri3", {"id": str(i)}).text = ids(f)
        csurf = ET.SubElement(meshel, "Surface", {"name": "indenter_surface"})
        for i, f in enumerate(cap_tris, start=1):
            ET.SubElement(csurf, "tri3", {"id": str(i)}).text = ",".join(str(int(n) + n_t + 1) for n in f)
        pair = ET.SubElement(meshel, "SurfacePair", {"name": "indentation_contact"})
        ET.SubElement(pair, "primary").text = "tissue_top"
        ET.SubElement(pair, "secondary").text = "indenter_surface"
    doms = ET.SubElement(root, "MeshDomains")
    ET.SubElement(doms, "SolidDomain", {"name": "tissue", "mat": card.name})
    if contact:
        sd = ET.SubElement(doms, "ShellDomain", {"name": "indenter_shell", "mat": FEBIO_INDENTER_MATERIAL})
        # FERigidShellDomain parameter; a rigid body's thickness only sets its mass (irrelevant here: static, all dofs prescribed)
        ET.SubElement(sd, "shell_thickness").text = fmt(0.01 * (spec.radius if spec.indenter == "sphere" else r_cap))
    bnd = ET.SubElement(root, "Boundary")

    def zero(name, nset, dofs):
        bc = ET.SubElement(bnd, "bc", {"name": name, "node_set": nset, "type": "zero displacement"})
        for dof in ("x_dof", "y_dof", "z_dof"):
            ET.SubElement(bc, dof).text = "1" if dof[0] in dofs else "0"

    if contact and spec.base == "bonded":  # the indentation force is read from the base: prescribed 0
        _febio_zero_prescribed(bnd, "fixed_base", "base", "xyz")
    elif contact:
        _febio_zero_prescribed(bnd, "sliding_base", "base", "z")
    elif spec.base == "bonded":
        zero("fixed_base", "base", "xyz")
    else:
        zero("sliding_base", "base", "z")
    if spec.base == "sliding":
        zero("base_anchor", "base_anchor", "xy")
        zero("base_other", "base_other", "y")
    if not contact:
        pre = ET.SubElement(bnd, "bc", {"name": "punch_displacement", "node_set": "punch", "type": "prescribed displacement"})
        ET.SubElement(pre, "dof").text = "z"
        ET.SubElement(pre, "value", {"lc": "1"}).text = fmt(-spec.depth)
        ET.SubElement(pre, "relative").text = "0"
        if spec.bonded_punch:
            zero("punch_bonded", "punch", "xy")
    else:
        rigid = ET.SubElement(root, "Rigid")
        rigid.append(xml_comment("rb: the rigid material's name, as in the FEBio 4 documentation (rigid_fixed, rigid_displacement); "
                                  "NOT VERIFIED for every FEBio 4 release: GIBBON's febio_spec 4.0 demos give the material id (2) "
                                  "instead; use 2 if this FEBio rejects the name"))
        fx = ET.SubElement(rigid, "rigid_bc", {"name": "indenter_fixed", "type": "rigid_fixed"})
        ET.SubElement(fx, "rb").text = FEBIO_INDENTER_MATERIAL
        for dof, v in (("Rx_dof", "1"), ("Ry_dof", "1"), ("Rz_dof", "0"), ("Ru_dof", "1"), ("Rv_dof", "1"), ("Rw_dof", "1")):
            ET.SubElement(fx, dof).text = v
        mv = ET.SubElement(rigid, "rigid_bc", {"name": "indenter_depth", "type": "rigid_displacement"})
        ET.SubElement(mv, "rb").text = FEBIO_INDENTER_MATERIAL
        ET.SubElement(mv, "dof").text = "z"
        ET.SubElement(mv, "value", {"lc": "1"}).text = fmt(-spec.depth)
        ET.SubElement(mv, "relative").text = "0"
        eps = spec.penalty * card.youngs_modulus / s["h"]
        cont = ET.SubElement(root, "Contact")
        cont.append(xml_comment(
            f"frictionless penalty contact: traction = penalty x penetration, penalty = p E / h = {spec.penalty:g} x "
            f"{card.youngs_modulus:.6g} Pa / {s['h']:.6g} m = {eps:.6g} Pa/m, difftissue's per-node kappa_i = p E sqrt(A_i) "
            "per tributary area A_i (h = sqrt(A) of the top node on the axis); set auto_penalty 1 (penalty then a scale "
            "factor) or laugon 1 (augmented Lagrangian) for FEBio's own choices"))
        c = ET.SubElement(cont, "contact", {"name": "indentation", "type": "sliding-elastic", "surface_pair": "indentation_contact"})
        for tag, val in (("laugon", "0"), ("penalty", fmt(eps)), ("auto_penalty", "0"), ("two_pass", "0"),
                         ("fric_coeff", "0.0"), ("tension", "0"), ("search_radius", fmt(max(spec.depth, r_cap)))):
            ET.SubElement(c, tag).text = val
    logs = {"base": ids(s["base"])} if contact else {"punch": ids(s["punch"])}
    _febio_ramp_and_output(root, logs, rigid=(len(mats.findall("material")),) if contact else ())
    return root


def febio_fitted_model(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False, steps: int | None = None) -> ET.Element:
    """FEBio 4.0 model of a fitted specimen.

    Nodes ``1..N`` (the specimen's order); ``tet4`` elements grouped by region (``<Elements
    name=<region>>``, numbered ``1..M`` region after region) in one ``SolidDomain`` per region;
    materials: the card's (:func:`~difftissue.export.febio_material`, a ``prestrain elastic``
    with ``F0 = diag(lambda0, lambda0, 1)`` where ``pre_stretch != 1``) on the fitted regions,
    one per fixed region otherwise. Per component ``c``: ``<NodeSet name="fixed_c">`` (held at
    zero: ``zero displacement`` with ``c_dof`` 1; the reaction set's components are instead
    prescribed 0, FEBio records reactions only there) and ``<NodeSet name="prescribed_c">`` with
    ``<MeshData><NodeData name="prescribed_uc" node_set="prescribed_c" data_type="scalar">``
    (``<node lid="k">``: the k-th node of the set, 1-based) and a ``prescribed displacement``
    BC (``<dof>c</dof>``, ``<value lc="1" type="map">prescribed_uc</value>``, ``relative`` 0),
    ramped by load controller 1 over ``steps`` static steps (default :func:`load_steps`: 10, a
    compression at most :data:`MAX_STRAIN_INCREMENT` nominal strain per step). fem_field and
    compression: ``<NodeSet name="reaction">`` (the reaction force is the sum of the ``reaction
    forces`` plot variable over it; a compression's top platen). Incision: ``cut_plus`` / ``cut_minus`` (pair k's original and duplicate, in pair
    order); the pairs are not tied, so the static solution is the opened state.
    """
    law = resolve_law(card, law)
    cards = spec.region_cards(card)
    steps = load_steps(spec) if steps is None else int(steps)
    root = _febio_static_root(spec.describe(), steps)
    mats = ET.SubElement(root, "Material")
    names: dict[int, str] = {}
    mat_id = 0
    for c in cards:
        if id(c) in names:
            continue
        mat_id += 1
        el = febio_material(c, law=law, approximate=approximate, mat_id=mat_id)
        for child in list(el):
            mats.append(child)
        names[id(c)] = c.name
    if len(set(names.values())) != len(names):
        raise ExportError(f"FEBio fitted specimen: material names {sorted(names.values())} collide; rename the card")
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(spec.points, start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(fmt(v) for v in p)
    eid = 0
    for r, rname in enumerate(spec.region_names):
        sel = np.flatnonzero(spec.region_ids == r)
        if sel.size == 0:
            continue
        elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": rname})
        for t in spec.tets[sel]:
            eid += 1
            ET.SubElement(elems, "elem", {"id": str(eid)}).text = ",".join(str(int(n) + 1) for n in t)
    ids = lambda a: ",".join(str(int(n) + 1) for n in np.atleast_1d(a))  # noqa: E731
    sets = component_sets(spec, reaction_prescribed=True)
    for c, (zero, nz) in zip("xyz", sets):
        if zero.size:
            ET.SubElement(meshel, "NodeSet", {"name": f"fixed_{c}"}).text = ids(zero)
        if nz.size:
            ET.SubElement(meshel, "NodeSet", {"name": f"prescribed_{c}"}).text = ids(nz)
    if spec.reaction is not None:
        ET.SubElement(meshel, "NodeSet", {"name": "reaction"}).text = ids(np.flatnonzero(spec.reaction.any(axis=1)))
    if spec.pairs is not None:
        ET.SubElement(meshel, "NodeSet", {"name": "cut_plus"}).text = ids(spec.pairs[:, 0])
        ET.SubElement(meshel, "NodeSet", {"name": "cut_minus"}).text = ids(spec.pairs[:, 1])
    doms = ET.SubElement(root, "MeshDomains")
    for r, rname in enumerate(spec.region_names):
        if np.any(spec.region_ids == r):
            ET.SubElement(doms, "SolidDomain", {"name": rname, "mat": cards[r].name})
    if any(nz.size for _, nz in sets):
        md = ET.SubElement(root, "MeshData")
        for ci, (c, (_, nz)) in enumerate(zip("xyz", sets)):
            if nz.size:
                nd = ET.SubElement(md, "NodeData", {"name": f"prescribed_u{c}", "node_set": f"prescribed_{c}", "data_type": "scalar"})
                for k, n in enumerate(nz, start=1):
                    ET.SubElement(nd, "node", {"lid": str(k)}).text = fmt(spec.prescribed[n, ci])
    bnd = ET.SubElement(root, "Boundary")
    for c, (zero, nz) in zip("xyz", sets):
        if zero.size:
            bc = ET.SubElement(bnd, "bc", {"name": f"fixed_{c}", "node_set": f"fixed_{c}", "type": "zero displacement"})
            for d in "xyz":
                ET.SubElement(bc, f"{d}_dof").text = "1" if d == c else "0"
        if nz.size:
            bc = ET.SubElement(bnd, "bc", {"name": f"prescribed_{c}", "node_set": f"prescribed_{c}", "type": "prescribed displacement"})
            ET.SubElement(bc, "dof").text = c
            ET.SubElement(bc, "value", {"lc": "1", "type": "map"}).text = f"prescribed_u{c}"
            ET.SubElement(bc, "relative").text = "0"
    _febio_ramp_and_output(root, {"reaction": ids(np.flatnonzero(spec.reaction.any(axis=1)))} if spec.reaction is not None else None)
    return root
