"""SOFA (``.scn``): the force field, the compression block (also as difftissue's spring lattice),
the indentation specimen and the fitted specimen (docs/export.md).

Conversions: :func:`sofa_force_field` (``TetrahedronFEMForceField`` / ``NeoHookean`` Lamé
parameters), :func:`sofa_polynomial_coefficients` and :func:`sofa_springs_split` (the lattice as
``PolynomialSpringsForceField`` plus a corotational FEM). Scenes: :func:`sofa_scene`,
:func:`sofa_indentation_scene`, :func:`sofa_fitted_scene`; :func:`write_sofa` writes one.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import ExportError
from ..models import SpringVolumeModel
from ._common import finite, fmt, write_text, xml_comment, xml_text
from .approximations import approximation_notes, resolve_law
from .card import MaterialCard, header_lines
from .fitted import FittedSpecimen, load_steps
from .recalibration import indentation_card
from .specimens import block_sets, check_indentation, default_displacement, indentation_sets, no_mesh_with_indentation

__all__ = ["sofa_force_field", "sofa_polynomial_coefficients", "springs_from_sofa_polynomial", "sofa_springs_split", "sofa_scene",
           "write_sofa", "sofa_indentation_scene", "sofa_fitted_scene"]


def sofa_force_field(card: MaterialCard, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """The SOFA force field for ``card``.

    * ``law="linear"`` -> ``<TetrahedronFEMForceField youngModulus="E" poissonRatio="nu" method="large"/>``
      (corotational linear elasticity; ``method="small"`` would be strictly linear).
    * ``law="neo_hookean"`` -> ``<TetrahedronHyperelasticityFEMForceField materialName="NeoHookean"
      ParameterSet="mu lambda"/>`` with ``mu = E / (2 (1 + nu))`` and
      ``lambda = E nu / ((1 + nu)(1 - 2 nu))``. SOFA's ``NeoHookean.h`` reads
      ``parameterArray[0]`` as mu and ``parameterArray[1]`` as lambda, energy
      ``mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2`` (Bonet & Wood), the same energy as FEBio's
      neo-Hookean. Older SOFA documentation listed ``[mu, k]``; check the SOFA version in use.

    Inverse (tested): ``E = mu (3 lambda + 2 mu) / (lambda + mu)``, ``nu = lambda / (2 (lambda + mu))``.
    """
    law = resolve_law(card, law)
    approximation_notes(card, "SOFA " + law, approximate=approximate)
    if law == "linear":
        return ET.Element("TetrahedronFEMForceField", {"name": card.name, "youngModulus": fmt(card.youngs_modulus),
                                                       "poissonRatio": fmt(card.poisson_ratio), "method": "large"})
    return ET.Element("TetrahedronHyperelasticityFEMForceField", {
        "name": card.name, "materialName": "NeoHookean",
        "ParameterSet": f"{fmt(card.shear_modulus)} {fmt(card.lame_lambda)}"})


def sofa_polynomial_coefficients(stiffness, cubic, rest_length) -> np.ndarray:
    """difftissue spring constants -> ``PolynomialSpringsForceField`` strain coefficients.

    SOFA's spring force is ``sigma(L) = a1 L + a2 L^2 + ... + an L^n`` of the strain
    ``L = (l - l0) / l0`` (cross section 1), so difftissue's tension ``k e + a e^3`` with
    ``e = L l0`` gives ``a1 = k l0`` [N], ``a2 = 0``, ``a3 = a l0^3`` [N].

    Args:
        stiffness: ``k`` [N/m] per spring; cubic: ``a`` [N/m^3]; rest_length: ``l0`` [m].

    Returns:
        ``(S, 3)`` coefficients ``[a1, a2, a3]`` [N] per spring (degree 3).
    """
    k, a, L0 = (np.asarray(v, dtype=float) for v in (stiffness, cubic, rest_length))
    k, a, L0 = np.broadcast_arrays(k, a, L0)
    return np.stack([k * L0, np.zeros_like(k), a * L0**3], axis=-1)


def springs_from_sofa_polynomial(coefficients, rest_length):
    """Inverse of :func:`sofa_polynomial_coefficients`: ``k = a1 / l0``, ``a = a3 / l0^3``
    (a nonzero ``a2`` has no difftissue counterpart and is refused)."""
    c = np.asarray(coefficients, dtype=float)
    L0 = np.asarray(rest_length, dtype=float)
    if c.shape[-1] != 3:
        raise ExportError(f"expected degree-3 coefficients [a1, a2, a3], got shape {c.shape}")
    if np.any(c[..., 1] != 0.0):
        raise ExportError("a2 != 0: a quadratic strain term (tension/compression asymmetric) has no difftissue counterpart")
    return c[..., 0] / L0, c[..., 2] / L0**3


def sofa_springs_split(card: MaterialCard, spring_fraction: float = 0.5) -> dict:
    """How a ``springs_volume`` card is split between SOFA's springs and a corotational FEM.

    SOFA has no per-cell volume-penalty force field, so the bulk term of ``springs_volume`` is
    carried by a ``TetrahedronFEMForceField`` (``method="large"``). A cube lattice with spring
    constants ``c mu g`` has Lamé parameters ``(c mu, c mu)``; the FEM adds
    ``lambda_f = lambda - c mu``, ``mu_f = (1 - c) mu`` so the sum is exactly (lambda, mu) at
    small strain for any ``0 <= c < 1`` (``c = spring_fraction``). The cubic coefficients of the
    springs are kept whole, so the cubic stiffening is difftissue's. Returns ``c``, ``lambda_f``,
    ``mu_f`` and the FEM's ``youngs_modulus`` / ``poisson_ratio``
    (``E_f = mu_f (3 lambda_f + 2 mu_f) / (lambda_f + mu_f)``, ``nu_f = lambda_f / (2 (lambda_f + mu_f))``).
    Inverse: ``lambda = c mu + lambda_f``, ``mu = c mu + mu_f`` (tested).
    """
    c = finite(spring_fraction, "spring_fraction")
    if not 0.0 <= c < 1.0:
        raise ExportError(f"spring_fraction = {c:g} must lie in [0, 1) (the FEM needs a positive shear modulus)")
    mu, lam = card.shear_modulus, card.lame_lambda
    lam_f, mu_f = lam - c * mu, (1.0 - c) * mu
    if lam_f < 0:
        raise ExportError(f"spring_fraction = {c:g} leaves the FEM a negative lambda ({lam_f:.6g} Pa) at nu = {card.poisson_ratio:g}; "
                          f"use spring_fraction <= {lam / mu:.4g}")
    return {"spring_fraction": c, "lambda_f": lam_f, "mu_f": mu_f,
            "youngs_modulus": mu_f * (3 * lam_f + 2 * mu_f) / (lam_f + mu_f), "poisson_ratio": lam_f / (2 * (lam_f + mu_f))}


def _sofa_law(card: MaterialCard, law: str | None) -> str:
    return "springs" if law == "springs" else resolve_law(card, law)


def sofa_scene(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
               displacement: float | None = None, spring_fraction: float = 0.5, steps: int = 10) -> ET.Element:
    """A SOFA scene: the force field in a ``Node`` (material alone), or with ``mesh`` a static
    specimen: ``MeshTopology`` (points, tetrahedra), ``MechanicalObject``, ``MeshMatrixMass``
    (``massDensity``), ``StaticSolver`` + ``SparseLDLSolver``, the force field(s), a
    ``FixedProjectiveConstraint`` on the base (min z) and a ``LinearMovementProjectiveConstraint``
    moving the top (max z) by ``displacement`` [m] along z over ``steps`` steps of ``dt = 1/steps``
    (:func:`_sofa_ramp`: ``keyTimes="0 1 1000000"``, held after t = 1; it prescribes all three
    components of the top nodes).

    ``law="springs"`` (needs ``mesh``, a structured block): difftissue's spring lattice as one
    ``PolynomialSpringsForceField`` (``object1 = object2 = @dofs``, degree-3 strain polynomials
    from :func:`sofa_polynomial_coefficients` with the springs scaled by ``spring_fraction``,
    ``compressible="1"``) plus the corotational ``TetrahedronFEMForceField`` of
    :func:`sofa_springs_split` for the rest of the stiffness.
    """
    law = _sofa_law(card, law)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": fmt(1.0 / steps)})
    if law == "springs":
        if mesh is None:
            raise ExportError("law='springs' writes one SOFA spring per lattice edge: it needs a specimen mesh (--specimen)")
        if getattr(mesh, "lattice", None) is None:
            raise ExportError("law='springs' needs a structured block with a cube lattice (difftissue.mesh.block)")
        notes = approximation_notes(card, "SOFA springs", approximate=approximate, cubic_ok=True)
        split = sofa_springs_split(card, spring_fraction)
        notes = notes + [
            f"springs_volume split: springs carry {split['spring_fraction']:g} of mu (PolynomialSpringsForceField, full cubic "
            f"coefficients), a corotational TetrahedronFEMForceField carries lambda_f = {split['lambda_f']:.10g} Pa, "
            f"mu_f = {split['mu_f']:.10g} Pa; exact at small strain, finite-strain stress within about 1 % of springs_volume "
            "at 10 % strain (docs/export.md)"]
    else:
        notes = approximation_notes(card, "SOFA " + law, approximate=approximate)
    for line in header_lines(card, "SOFA", law) + notes:
        root.append(xml_comment(line))
    plugins = {"linear": ["Sofa.Component.SolidMechanics.FEM.Elastic"], "neo_hookean": ["Sofa.Component.SolidMechanics.FEM.HyperElastic"],
               "springs": ["Sofa.Component.SolidMechanics.Spring", "Sofa.Component.SolidMechanics.FEM.Elastic"]}[law]
    for plugin in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": plugin})
    if mesh is None:
        node = ET.SubElement(root, "Node", {"name": "tissue"})
        node.append(xml_comment("add a tetrahedral topology and a MechanicalObject here"))
        node.append(sofa_force_field(card, law=law, approximate=True))
        return root
    for p in _SOFA_SPECIMEN_PLUGINS:  # every RequiredPlugin before the first Node that uses it
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    base, top, height = block_sets(mesh)
    d = default_displacement(height, displacement)
    _sofa_specimen_node(node, card, mesh, dt=1.0 / steps)
    if law == "springs":
        model = SpringVolumeModel(mesh)
        # pre-stretch is dropped (and noted) for this target: springs of the unstretched lattice
        k, a = (np.asarray(v, dtype=float) for v in model.spring_constants(card.material().replace(pre_stretch=1.0, pre_stretch_y=None)))
        split = sofa_springs_split(card, spring_fraction)
        coeffs = sofa_polynomial_coefficients(split["spring_fraction"] * k, a, model.rest_lengths)
        springs = np.asarray(model.springs)
        ET.SubElement(node, "PolynomialSpringsForceField", {
            "name": card.name + "_springs", "object1": "@dofs", "object2": "@dofs",
            "firstObjectPoints": " ".join(str(int(i)) for i in springs[:, 0]),
            "secondObjectPoints": " ".join(str(int(i)) for i in springs[:, 1]),
            "polynomialDegree": " ".join("3" for _ in range(len(springs))),
            "polynomialStiffness": " ".join(fmt(c) for c in coeffs.reshape(-1)),
            "computeZeroLength": "1", "compressible": "1"})
        ET.SubElement(node, "TetrahedronFEMForceField", {"name": card.name + "_bulk", "youngModulus": fmt(split["youngs_modulus"]),
                                                         "poissonRatio": fmt(split["poisson_ratio"]), "method": "large"})
    else:
        node.append(sofa_force_field(card, law=law, approximate=True))
    ET.SubElement(node, "FixedProjectiveConstraint", {"name": "fixed_base", "indices": " ".join(str(int(i)) for i in base)})
    ET.SubElement(node, "LinearMovementProjectiveConstraint", {
        "name": "top_displacement", "template": "Vec3d", "indices": " ".join(str(int(i)) for i in top),
        **_sofa_ramp(d)})
    return root


#: SOFA plugins of a static specimen scene (solver, direct linear solver, mass, state, topology, projective
#: constraints, WriteState output).
_SOFA_SPECIMEN_PLUGINS = ("Sofa.Component.ODESolver.Backward", "Sofa.Component.LinearSolver.Direct", "Sofa.Component.Mass",
                          "Sofa.Component.StateContainer", "Sofa.Component.Topology.Container.Constant",
                          "Sofa.Component.Constraint.Projective", "Sofa.Component.Playback")


def _sofa_static_solver(node: ET.Element, size: float) -> None:
    """``StaticSolver`` with explicit Newton settings and a direct linear solver: at most 25
    Newton iterations per step, converged when the correction is below ``1e-12 size`` [m]
    (``size``: the specimen's diagonal) or 1e-10 of the displacement, or the residual below
    1e-10 of the first one (absolute residual test off: -1); ``SparseLDLSolver`` on 3x3
    blocks. SOFA's own defaults differ between releases, hence explicit."""
    ET.SubElement(node, "StaticSolver", {"newton_iterations": "25", "absolute_correction_tolerance_threshold": fmt(1e-12 * size),
                                         "relative_correction_tolerance_threshold": "1e-10",
                                         "absolute_residual_tolerance_threshold": "-1",
                                         "relative_residual_tolerance_threshold": "1e-10"})
    ET.SubElement(node, "SparseLDLSolver", {"template": "CompressedRowSparseMatrixMat3x3d"})


def _sofa_output(node: ET.Element, dt: float, name: str = "tissue") -> None:
    """A ``WriteState`` (Sofa.Component.Playback) writing positions [m] and forces [N] of every
    node each step ``dt`` [s] to ``<name>_state.txt`` (after the ``MechanicalObject``). The
    reaction at a held node is minus its force entry; NOT run in SOFA here."""
    ET.SubElement(node, "WriteState", {"name": f"{name}_output", "filename": f"{name}_state.txt", "period": fmt(dt),
                                       "time": "0", "writeX": "1", "writeV": "0", "writeF": "1"})


def _sofa_ramp(dz: float) -> dict:
    """Attributes of a ``LinearMovementProjectiveConstraint`` moving its nodes by ``(0, 0, dz)``
    [m] from t = 0 to t = 1 and HOLDING them there: SOFA's constraint acts only while a later
    key time exists (``findKeyTimes`` in LinearMovementProjectiveConstraint.inl sets
    ``finished`` only for ``t <`` a key time), so with ``keyTimes="0 1"`` alone the nodes would be
    free at t = 1, the last step; a third key time far later with the same movement holds them."""
    m = f"0 0 {fmt(dz)}"
    return {"keyTimes": "0 1 1000000", "movements": f"0 0 0  {m}  {m}", "relativeMovements": "1"}


def _sofa_specimen_node(node: ET.Element, card: MaterialCard, mesh, *, dt: float) -> None:
    """The static solver and sparse LDL solver (:func:`_sofa_static_solver`), tet topology of
    ``mesh`` [m], its ``MechanicalObject``, a ``MeshMatrixMass`` of the card's density [kg/m^3]
    and the ``WriteState`` output (:func:`_sofa_output`, every ``dt`` [s]) inside the tissue node."""
    pts = np.asarray(mesh.points, dtype=float)
    _sofa_static_solver(node, float(np.linalg.norm(np.ptp(pts, axis=0))))
    ET.SubElement(node, "MeshTopology", {"name": "topology", "position": " ".join(fmt(c) for c in pts.reshape(-1)),
                                         "tetrahedra": " ".join(str(int(n)) for n in np.asarray(mesh.tets).reshape(-1))})
    ET.SubElement(node, "MechanicalObject", {"name": "dofs", "template": "Vec3d", "src": "@topology"})
    ET.SubElement(node, "MeshMatrixMass", {"massDensity": fmt(card.density)})
    _sofa_output(node, dt)


def write_sofa(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
               displacement: float | None = None, spring_fraction: float = 0.5, force: bool = False, indentation=None) -> Path:
    """Write a SOFA ``.scn`` scene (see :func:`sofa_scene`; conversions in :func:`sofa_force_field`,
    :func:`sofa_polynomial_coefficients`, :func:`sofa_springs_split`; indentation specimens:
    :func:`sofa_indentation_scene`)."""
    if indentation is not None:
        no_mesh_with_indentation(mesh)
        if law == "springs":
            raise ExportError("law='springs' is written for the compression block only, not for an indentation specimen")
        return write_text(path, xml_text(sofa_indentation_scene(card, indentation, law=law, approximate=approximate)), force)
    return write_text(path, xml_text(sofa_scene(card, mesh, law=law, approximate=approximate, displacement=displacement,
                                                  spring_fraction=spring_fraction)), force)


def sofa_indentation_scene(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """SOFA scene of an indentation specimen (base bonded only).

    Sphere: ``SphereForceField`` (``Sofa.Component.MechanicalLoad``; force on every point inside
    the sphere ``stiffness * (R - |x - c|)`` along the outward normal, i.e. difftissue's
    per-node penalty force with one ``stiffness`` = ``p E h`` for all nodes), fixed at the
    centre ``(0, 0, H + R)``, with ``damping="0"``; the indentation is the base moved up by
    ``depth`` (``LinearMovementProjectiveConstraint`` on the base, all components, over
    ``steps`` steps): the same relative motion, and a static equilibrium does not depend on
    the frame. Flat punch: base fixed, punch nodes moved by ``(0, 0, -depth)`` (bonded punch
    only: the constraint prescribes all components). Cone: refused (``ConicalForceField``'s
    angle and inside/outside conventions were not verified).
    """
    check_indentation(spec, "SOFA", cone=False, sliding=False, frictionless_punch=False)
    card = indentation_card(card, spec, law, approximate=approximate)
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    law = resolve_law(card, law)
    notes = approximation_notes(card, "SOFA " + law, approximate=approximate)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": fmt(1.0 / spec.steps)})
    for line in header_lines(card, "SOFA", law) + notes + spec.describe():
        root.append(xml_comment(line))
    plugins = ["Sofa.Component.SolidMechanics.FEM.Elastic" if law == "linear" else "Sofa.Component.SolidMechanics.FEM.HyperElastic",
               *_SOFA_SPECIMEN_PLUGINS]
    if spec.indenter == "sphere":
        plugins.append("Sofa.Component.MechanicalLoad")
    for p in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    _sofa_specimen_node(node, card, mesh, dt=1.0 / spec.steps)
    node.append(sofa_force_field(card, law=law, approximate=True))
    join = lambda a: " ".join(str(int(i)) for i in np.atleast_1d(a))  # noqa: E731
    if spec.indenter == "sphere":
        k = spec.penalty * card.youngs_modulus * s["h"]
        node.append(xml_comment(
            f"SphereForceField stiffness = p E h = {spec.penalty:g} * {card.youngs_modulus:.10g} Pa * {s['h']:.10g} m = {k:.10g} N/m "
            "(difftissue's kappa_i of an interior top node; edge nodes differ, docs/export.md); the sphere is fixed and the "
            f"base moves up by the depth {spec.depth:.10g} m"))
        ET.SubElement(node, "SphereForceField", {"name": "indenter", "template": "Vec3d",
                                                 "center": f"0 0 {fmt(s['H'] + spec.radius)}", "radius": fmt(spec.radius),
                                                 "stiffness": fmt(k), "damping": "0"})
        ET.SubElement(node, "LinearMovementProjectiveConstraint", {
            "name": "base_displacement", "template": "Vec3d", "indices": join(s["base"]),
            **_sofa_ramp(spec.depth)})
    else:
        ET.SubElement(node, "FixedProjectiveConstraint", {"name": "fixed_base", "indices": join(s["base"])})
        ET.SubElement(node, "LinearMovementProjectiveConstraint", {
            "name": "punch_displacement", "template": "Vec3d", "indices": join(s["punch"]),
            **_sofa_ramp(-spec.depth)})
    return root


def sofa_fitted_scene(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """SOFA scene of a fitted specimen with one material and no pre-stretch (a fem_field or
    compression fit).

    fem_field: the prescribed displacements are initial positions held by projective constraints: the
    ``MechanicalObject`` gets ``rest_position`` = the reference mesh and ``position`` = the
    reference moved by the prescribed values on the prescribed components (the free ones start
    at rest); ``FixedProjectiveConstraint`` (all three components prescribed) and
    ``PartialFixedProjectiveConstraint`` with ``fixedDirections`` (some) hold them: both zero
    the Newton correction of those components (``projectResponse``) and leave the positions
    alone (``projectPosition`` is empty), and SOFA's ``TetrahedronFEMForceField`` (``reinit``)
    and ``TetrahedronHyperelasticityFEMForceField`` (``init``) take their rest shape from the
    ``MechanicalObject``'s rest position (SOFA source, docs/export.md). ``StaticSolver`` +
    ``SparseLDLSolver``; ``MeshTopology`` of the reference mesh; ``MeshMatrixMass`` of the
    card's density. Several region materials or a pre-stretch (an incision) are refused.

    compression (finite strain: the platen displacement is ramped, not imposed at once, which
    would invert the top layer of tets): ``position`` = ``rest_position`` = the mesh; the nodes
    with a nonzero prescribed value (the top platen) are moved by one
    ``PartialLinearMovementProjectiveConstraint`` per (held components, value) group with
    ``movedDirections`` = the held components (bonded ``1 1 1``, frictionless ``0 0 1``),
    ``keyTimes="0 1 1000000"`` and ``movements`` ``0``, the prescribed value, the prescribed
    value: in SOFA's source it sets ``x = x0 + m(t)`` on the moved directions (``x0`` the
    positions when it first projects) and zeroes their Newton correction only while a later key
    time exists, so the value is held after ``t = 1`` (a key time of 1 alone would free the top
    at ``t = 1``). The root ``dt`` is ``1 /`` :func:`load_steps`, so the ramp takes that many
    steps; run a few more for the Newton iterations to settle. The held-at-zero components
    (bottom platen, rigid-body pins) are Fixed / PartialFixed as above. ``StaticSolver`` gets
    ``newton_iterations="25"`` and tight correction / residual thresholds (its defaults are 1
    iteration and 1e-5 absolute, too coarse for a millimetre specimen).
    """
    law = resolve_law(card, law)
    cards = spec.region_cards(card)
    if any(c.is_pre_stretched for c in cards):
        raise ExportError("SOFA fitted specimen: a pre-stretch (an incision) cannot be written for SOFA (no prestrain in its tetrahedral "
                          "force fields), and without it the cut specimen does not open; export the incision to febio, xpbd or vtu")
    used = {id(cards[r]) for r in np.unique(spec.region_ids)}
    if len(used) > 1:
        raise ExportError(f"SOFA fitted specimen: {len(used)} region materials; this SOFA scene holds one force field with one "
                          "material; export to febio, abaqus, xpbd or vtu")
    notes = approximation_notes(card, "SOFA " + law, approximate=approximate)
    ramp = spec.experiment == "compression"
    steps = load_steps(spec)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": fmt(1.0 / steps) if ramp else "1"})
    for line in header_lines(card, "SOFA", law) + notes + spec.describe():
        root.append(xml_comment(line))
    if ramp:
        root.append(xml_comment(f"prescribed displacements: the top platen is moved by PartialLinearMovementProjectiveConstraint from 0 "
                                 f"at t = 0 to its prescribed value at t = 1 ({steps} steps of dt = 1/{steps}) and held there after; "
                                 "run a few more steps for the Newton iterations to settle; zero components held by "
                                 "(Partial)FixedProjectiveConstraint"))
    else:
        root.append(xml_comment("prescribed displacements: MechanicalObject position = rest_position + prescribed value on the held "
                                 "components, held by (Partial)FixedProjectiveConstraint; each StaticSolver step is a Newton solve from "
                                 "the current positions: run a few steps until the positions stop changing"))
    plugins = ["Sofa.Component.SolidMechanics.FEM.Elastic" if law == "linear" else "Sofa.Component.SolidMechanics.FEM.HyperElastic",
               *_SOFA_SPECIMEN_PLUGINS]
    for p in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    rest = spec.points
    _sofa_static_solver(node, float(np.linalg.norm(np.ptp(rest, axis=0))))
    moving = (spec.fixed & (spec.prescribed != 0.0)).any(axis=1) if ramp else np.zeros(len(rest), dtype=bool)
    pos = rest + np.where(spec.fixed & ~moving[:, None], spec.prescribed, 0.0)
    flat = lambda a: " ".join(fmt(v) for v in np.asarray(a, dtype=float).reshape(-1))  # noqa: E731
    ET.SubElement(node, "MeshTopology", {"name": "topology", "position": flat(rest),
                                         "tetrahedra": " ".join(str(int(n)) for n in spec.tets.reshape(-1))})
    ET.SubElement(node, "MechanicalObject", {"name": "dofs", "template": "Vec3d", "position": flat(pos), "rest_position": flat(rest)})
    ET.SubElement(node, "MeshMatrixMass", {"massDensity": fmt(card.density)})
    _sofa_output(node, float(root.get("dt", "1")))
    node.append(sofa_force_field(card, law=law, approximate=True))
    patterns = {}
    for n in np.flatnonzero(spec.fixed.any(axis=1) & ~moving):
        patterns.setdefault(tuple(bool(v) for v in spec.fixed[n]), []).append(int(n))
    for pat, nodes in sorted(patterns.items(), reverse=True):
        tag = "".join(c for c, b in zip("xyz", pat) if b)
        idx = " ".join(str(n) for n in nodes)
        if all(pat):
            ET.SubElement(node, "FixedProjectiveConstraint", {"name": f"prescribed_{tag}", "indices": idx})
        else:
            ET.SubElement(node, "PartialFixedProjectiveConstraint", {"name": f"prescribed_{tag}", "template": "Vec3d", "indices": idx,
                                                                     "fixedDirections": " ".join("1" if b else "0" for b in pat)})
    groups: dict[tuple, list[int]] = {}
    for n in np.flatnonzero(moving):
        pat = tuple(bool(v) for v in spec.fixed[n])
        groups.setdefault((pat, tuple(float(v) if b else 0.0 for v, b in zip(spec.prescribed[n], pat))), []).append(int(n))
    for k, ((pat, value), nodes) in enumerate(sorted(groups.items())):
        m = " ".join(fmt(v) for v in value)
        ET.SubElement(node, "PartialLinearMovementProjectiveConstraint", {
            "name": f"moved_{''.join(c for c, b in zip('xyz', pat) if b)}_{k}", "template": "Vec3d",
            "indices": " ".join(str(n) for n in nodes), "movedDirections": " ".join("1" if b else "0" for b in pat),
            "keyTimes": "0 1 1000000", "movements": f"0 0 0  {m}  {m}"})
    return root
