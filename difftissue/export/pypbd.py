"""pypbd scenes from material cards (``difftissue-pbd/1``, docs/export.md): :func:`pbd_scene` /
:func:`write_pbd` (material, block, bonded flat punch) and :func:`write_fitted_pbd` (a fitted
compression with bonded platens), recalibrated for the written budget by running pypbd
(:func:`difftissue.export.budget.pbd_budget_calibration`).

Reading and running a scene, and the pypbd conventions the conversion relies on:
:mod:`difftissue.export.pypbd_runner`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ExportError, ModelError
from ..models import LATTICE_MODELS, SpringVolumeModel
from ..scenarios import recover_lattice
from ._common import finite, write_text
from .approximations import approximation_notes
from .budget import card_reference_field, card_reference_reactions, field_error, load_fractions, pbd_budget_calibration
from .card import header_lines
from .fitted import FittedSpecimen
from .pypbd_runner import PYPBD_GRAVITY, SCENE_FORMAT, pbd_reference_model, signed_tet_volumes
from .recalibration import recalibration_fractions
from .specimens import block_sets, default_displacement, indentation_sets

__all__ = ["DEFAULT_BUDGET", "pbd_scene", "write_pbd", "write_fitted_pbd"]


_CONSTRAINTS = ("xpbd", "fem")


def _lumped_masses(points, tets, density) -> np.ndarray:
    v = np.abs(signed_tet_volumes(points, tets))
    m = np.zeros(len(points))
    np.add.at(m, tets.reshape(-1), np.repeat(density * v / 4.0, 4))
    return m


#: The budget written when the user pins none: (dt [s], substeps, iterations).
DEFAULT_BUDGET = (1.0 / 60.0, 1, 10)


def pbd_scene(card, mesh=None, *, constraints: str = "xpbd", dt: float | None = None, substeps: int | None = None,
              iterations: int | None = None, approximate: bool = False, displacement: float | None = None, indentation=None,
              calibrate: bool = True, load_fractions=None, field_tolerance: float | None = None) -> dict:
    """A pypbd scene for ``card`` (a :class:`~difftissue.export.MaterialCard`) as a JSON-ready dict.

    ``constraints="xpbd"`` (default): difftissue's spring lattice as XPBD distance constraints
    plus XPBD volume constraints, i.e. the energy

        sum_springs k/2 (|x_i - x_j| - L0)^2 + sum_tets (lambda - mu) (V - V0)^2 / (2 V0)

    with the spring constants ``k`` of :class:`~difftissue.models.SpringVolumeModel` (``mu h/4``
    per cube edge, ``mu h/2`` per face diagonal, summed over the cells holding the spring)
    and pypbd volume stiffness ``k_V = (lambda - mu) / (6 V0)`` per tet (the factor 6: the notes of
    :mod:`~difftissue.export.pypbd_runner`). difftissue's ``springs_volume`` puts the volume term on each cube (exact
    trilinear volume) instead of on its six tets; both agree for any deformation that is
    homogeneous within each cube. Needs ``nu >= 1/4`` (``lambda >= mu``: a negative pypbd
    stiffness would be a negative compliance) and, with a mesh, a structured block
    (:func:`difftissue.mesh.block`). The cubic coefficient cannot be represented by XPBD
    distance constraints: refused unless ``approximate`` (then dropped and noted).

    ``constraints="fem"``: pypbd ``FEMTetConstraint`` with the card's ``E`` and ``nu`` per tet.
    In pypbd 2.2.2 this is a PBD constraint whose converged response does not depend on ``E``
    (:mod:`~difftissue.export.pypbd_runner` notes), so it is written only with ``approximate=True`` and says so in ``notes``.

    Without ``mesh`` the scene holds the material alone: the Lamé parameters and the
    coefficients to build the constraints for any cube lattice. With ``mesh`` it is a complete
    specimen: particles (rest positions [m], lumped masses ``rho V/4`` per tet node [kg]),
    tets (0-based, positively oriented), constraints, base (min z) and top (max z) particles
    static (mass 0), the top moved by ``displacement`` [m] along z (default -10 % of the
    height), and the time setting ``dt`` [s], ``substeps``, ``iterations`` it is meant for.

    ``indentation`` (an :class:`~difftissue.export.specimens.IndentationSpecimen`, instead of
    ``mesh``): a flat-punch specimen with a bonded punch and a bonded base: base particles
    static, the particles under the punch static and moved by ``(0, 0, -depth)``. A pypbd
    particle is either static (all components held) or free, so a frictionless punch or a
    sliding base cannot be written; sphere and cone indenters are refused (pypbd's collision
    handling is rigid-body / distance-field collision with position-based restitution and
    friction, not a static frictionless contact that :func:`run_pbd_scene` could drive to
    equilibrium).

    With a specimen (``constraints="xpbd"``) the stiffnesses are recalibrated for the budget on
    its reactions (:func:`~difftissue.export.budget.pbd_budget_calibration`), and the displacement
    field pypbd comes to rest in at the last load state is measured against the card's model
    (``budget_calibration.field_error``, ``max |du| / max |u|``), with the part of it that no
    budget removes (``field_error_converged``: the scene energy's exact minimum against the card's
    model) and the weight's share (``weight_field_share``: pypbd applies gravity). ``field_tolerance``
    (e.g. 0.02) makes the field a target too: a budget is accepted only when the field error is
    within it as well (an unpinned budget is searched for, a pinned one refused with a suggested
    budget), and the export is refused (written with the miss noted under ``approximate``) when
    the converged limit already exceeds it.
    """
    pinned = dt is not None or substeps is not None or iterations is not None
    dt = DEFAULT_BUDGET[0] if dt is None else dt
    substeps = DEFAULT_BUDGET[1] if substeps is None else substeps
    iterations = DEFAULT_BUDGET[2] if iterations is None else iterations
    if constraints not in _CONSTRAINTS:
        raise ExportError(f"constraints = {constraints!r}: expected one of {list(_CONSTRAINTS)}")
    dt = finite(dt, "dt")
    if dt <= 0:
        raise ExportError(f"dt = {dt:g} s must be > 0")
    for name, v in (("iterations", iterations), ("substeps", substeps)):
        if isinstance(v, bool) or int(v) != v or v < 1:
            raise ExportError(f"{name} = {v!r} must be a positive integer")
    ind_sets = None
    if indentation is not None:
        if mesh is not None:
            raise ExportError("give either a block specimen (mesh) or an indentation specimen, not both")
        if displacement is not None:
            raise ExportError("displacement is the compression block's top displacement; an indentation specimen takes its depth")
        if indentation.indenter != "flat_punch":
            raise ExportError(f"pypbd: a {indentation.indenter} indenter needs frictionless contact, which the pypbd scene cannot "
                              "represent (pypbd's collision detection is for rigid bodies / distance fields with position-based "
                              "restitution and friction, not a static penalty contact); export a flat punch, or use FEBio / "
                              "Abaqus / SOFA / the XPBD JSON for a sphere")
        if indentation.base != "bonded" or not indentation.bonded_punch:
            raise ExportError("pypbd: a particle is either static (all components held) or free, so only a bonded base and a "
                              "bonded flat punch (bonded_punch=True, --bonded-punch) can be written")
        mesh = indentation.mesh()
        ind_sets = indentation_sets(indentation, mesh, card)
    E, nu, rho = card.youngs_modulus, card.poisson_ratio, card.density
    mu, lam = card.shear_modulus, card.lame_lambda
    notes: list[str] = []
    if constraints == "xpbd":
        notes += approximation_notes(card, "pypbd XPBD distance + volume constraints", approximate=approximate)
        if lam < mu * (1.0 - 1e-12):
            raise ExportError(
                f"poisson_ratio = {nu:g} < 0.25: the spring lattice needs a volume stiffness lambda - mu = {lam - mu:.6g} Pa < 0, "
                "which pypbd's XPBD volume constraint cannot take (a negative stiffness is a negative compliance); "
                "use constraints='fem' or another target")
        energy = ("sum_springs k/2 (|xi - xj| - L0)^2 + sum_tets (lambda - mu) (V - V0)^2 / (2 V0) "
                  "(pypbd XPBD distance constraints, stiffness k [N/m]; XPBD volume constraints, stiffness (lambda - mu) / (6 V0))")
        if card.model.strip() not in LATTICE_MODELS:  # the variants are springs_volume without pre-stretch (never written here)
            notes.append(f"the card's model is {card.model!r}; the scene uses the spring lattice + volume energy, "
                         "which has the same small-strain response (E, nu) and differs at finite strain")
    else:
        if not approximate:
            raise ExportError(
                "constraints='fem': pypbd 2.2.2's FEMTetConstraint is a PBD constraint (PositionBasedDynamics::"
                "solve_FEMTetraConstraint, no compliance): its converged static response is rigid and does not depend on "
                "youngs_modulus (E only sets a 1e-6 cut-off), so it cannot represent the card; pass approximate=True "
                "(--approximate) to write it anyway for iteration-count-tuned use")
        notes += approximation_notes(card, "pypbd FEMTetConstraint (St. Venant-Kirchhoff, PBD)", approximate=True)
        if not 0.0 <= nu <= 0.49:
            raise ExportError(f"poisson_ratio = {nu:g}: pypbd's FEMTetConstraint skips tets with nu outside [0, 0.49]")
        notes.append("APPROXIMATION: pypbd FEMTetConstraint is position-based (no compliance): the stiffness of the "
                     "scene depends on dt and the iteration count, and its converged static response is rigid; "
                     "E does not set a static stiffness (docs/export.md, pypbd)")
        energy = "St. Venant-Kirchhoff tets projected as PBD constraints C = U_tet -> 0 (pypbd FEMTetConstraint)"
    scene: dict[str, Any] = {
        "format": SCENE_FORMAT,
        "engine": "pypbd (PositionBasedDynamics Python bindings), checked with 2.2.2",
        "constraints": constraints,
        "energy": energy,
        "material": card.name,
        "model": card.model,
        "parameters": {"youngs_modulus": E, "poisson_ratio": nu, "density": rho, "mu": mu, "lambda": lam},
        "setting": {"dt": dt, "substeps": int(substeps), "iterations": int(iterations)},
        "gravity": list(PYPBD_GRAVITY),
        "header": header_lines(card, "pypbd"),
        "notes": notes,
        "card_provenance": card.provenance,
    }
    if mesh is None:
        if field_tolerance is not None:
            raise ExportError("field_tolerance: the scene holds the material alone (no specimen), so there is no field to measure")
        if constraints == "xpbd":
            scene["lattice_rules"] = {
                "distance_stiffness_per_cell": {"cube_edge": mu / 4.0, "face_diagonal": mu / 2.0,
                                                "unit": "N/m per m of cube edge h (k = value * h, summed over the cells holding the spring)"},
                "volume_stiffness": {"value": (lam - mu) / 6.0, "unit": "Pa; divide by the tet rest volume V0 [m^3] for pypbd's stiffness"},
            }
        else:
            scene["fem"] = {"youngs_modulus": E, "poisson_ratio": nu}
        return scene

    pts = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets, dtype=np.int64)
    vol = signed_tet_volumes(pts, tets)
    if np.any(vol <= 0):
        raise ExportError(f"{int(np.sum(vol <= 0))} tet(s) are not positively oriented; pypbd's volume constraint needs V > 0")
    if ind_sets is None:
        base, top, height = block_sets(mesh)
        dvec = [0.0, 0.0, default_displacement(height, displacement)]
        bnote = "static particles; 'moved' ones are displaced by 'displacement' [m] (all components prescribed)"
    else:
        base, top = ind_sets["base"], ind_sets["punch"]
        dvec = [0.0, 0.0, -float(indentation.depth)]
        bnote = ("indentation by a bonded flat punch: 'fixed' = base (z = 0), 'moved' = the particles under the punch, "
                 "displaced by 'displacement' [m] (all components prescribed)")
        scene["indentation"] = indentation.to_dict()
        scene["header"] = scene["header"] + indentation.describe()
    masses = _lumped_masses(pts, tets, rho)
    masses[base] = 0.0
    masses[top] = 0.0
    scene["particles"] = {"positions": pts.tolist(), "masses": masses.tolist(),
                          "unit": "m, kg; mass 0 = static particle (pypbd)"}
    scene["tets"] = tets.tolist()
    scene["boundary"] = {"fixed": base.tolist(), "moved": top.tolist(), "displacement": dvec, "note": bnote}
    if constraints == "xpbd":
        if getattr(mesh, "lattice", None) is None:
            raise ExportError("constraints='xpbd' needs a structured block with a cube lattice (difftissue.mesh.block); "
                              "use constraints='fem' (approximate) for other meshes")
        model = SpringVolumeModel(mesh)
        try:
            k, _ = model.spring_constants(card.material().replace(pre_stretch=1.0, pre_stretch_y=None))  # pre-stretch is dropped (noted) for this target
        except ModelError as e:
            raise ExportError(f"pypbd: the scene is difftissue's spring lattice, which this mesh cannot carry: {e}") from None
        k = np.asarray(k, dtype=float)
        scene["distance_constraints"] = {"pairs": np.asarray(model.springs).tolist(), "stiffness": k.tolist(),
                                         "call": "addDistanceConstraint_XPBD(i, j, stiffness)", "unit": "N/m"}
        kv = (lam - mu) / (6.0 * vol)
        if lam - mu > mu * 1e-12:
            scene["volume_constraints"] = {"tets": tets.tolist(), "stiffness": kv.tolist(),
                                           "call": "addVolumeConstraint_XPBD(a, b, c, d, stiffness)",
                                           "unit": "N/m^5 (= (lambda - mu) / (6 V0))"}
        else:
            scene["notes"].append("nu = 1/4: lambda = mu, no volume constraints (pypbd stiffness 0 would mean rigid)")
    else:
        scene["fem_constraints"] = {"tets": tets.tolist(), "youngs_modulus": E, "poisson_ratio": nu,
                                    "call": "addFEMTetConstraint(a, b, c, d, youngs_modulus, poisson_ratio)"}
    if constraints == "xpbd":
        if load_fractions is None:
            load_fractions = _default_fractions(indentation)
        scene = _calibrate_budget(scene, card, mesh, base, top, np.asarray(dvec, dtype=float), load_fractions,
                                  pinned=pinned, approximate=approximate, calibrate=calibrate, field_tolerance=field_tolerance)
    elif field_tolerance is not None:
        raise ExportError("field_tolerance: a PBD FEM scene is not calibrated for its budget, so its field is not measured")
    return scene


def _default_fractions(indentation) -> list[float]:
    """Load fractions a scene is calibrated on: the indentation's depth steps (up to
    :data:`~difftissue.export.budget.BUDGET_STATES`), else 1/4, 1/2, 3/4, 1 of the displacement."""
    return load_fractions(indentation.steps if indentation is not None else 4)


def _calibrate_budget(scene, card, mesh, base, moved, dvec, fractions, *, pinned, approximate, calibrate, field_tolerance):
    """Recalibrate ``scene``'s stiffnesses at its budget on its specimen (:mod:`difftissue.export.budget`)."""
    st = scene["setting"]
    if not calibrate:
        if field_tolerance is not None:
            raise ExportError("field_tolerance needs the budget calibration (calibrate=True): the field is measured by it")
        scene["notes"].append(f"NOT calibrated for the budget (calibrate=False): the stiffnesses are the card's converged-limit "
                              f"values; at dt = {st['dt']:.6g} s, {st['iterations']} iterations pypbd's rest state differs from the "
                              "card's fitted response (run_pbd_budget measures it)")
        return scene
    n = len(scene["particles"]["positions"])
    fixed = np.zeros((n, 3), dtype=bool)
    fixed[np.asarray(base)] = True
    fixed[np.asarray(moved)] = True
    presc = np.zeros((n, 3))
    presc[np.asarray(moved)] = dvec
    observe = np.zeros((n, 3), dtype=bool)
    observe[np.asarray(moved)] = True
    try:
        ref = card_reference_reactions(card, mesh, fixed, presc, observe, fractions)
    except ExportError as e:
        if not approximate:
            raise ExportError(f"pypbd: {e}; pass approximate=True (--approximate) to write the card's converged-limit stiffnesses "
                              "(the error at the budget unmeasured)") from None
        scene["notes"].append(f"APPROXIMATION: not calibrated for the budget: {e}")
        return scene
    # the displacement field at the last load state: the card's model, the scene energy's exact minimum (what every budget
    # converges to; the pypbd lattice is not the card's model), and the card's model carrying the particles' weights
    u_card = card_reference_field(card, mesh, fixed, presc, fractions[-1])
    mat = card.material().replace(pre_stretch=1.0, pre_stretch_y=None, cubic_coefficient=0.0)  # what the scene holds (dropped terms noted)
    u_lattice = card_reference_field(card, mesh, fixed, presc, fractions[-1], model=pbd_reference_model(mesh), material=mat)
    weight = np.asarray(scene["particles"]["masses"], dtype=float)[:, None] * np.asarray(scene["gravity"], dtype=float)[None, :]
    u_weight = card_reference_field(card, mesh, fixed, presc, fractions[-1], force=weight)
    lattice_error, weight_share = field_error(u_lattice, u_card), field_error(u_weight, u_card)
    try:
        scene, rec = pbd_budget_calibration(scene, ref, fractions, pinned=pinned, approximate=approximate, reference_field=u_card,
                                            lattice_field_error=lattice_error, field_tolerance=field_tolerance)
    except ExportError as e:
        if approximate and "not installed" in str(e):
            scene["notes"].append("APPROXIMATION: not calibrated for the budget (pypbd not installed here): the stiffnesses are the "
                                  "card's converged-limit values and the error at the budget was not measured")
            return scene
        raise
    rec["reference_model"] = card.model
    st = scene["setting"]
    fmt = lambda a: ", ".join(f"{100 * v:+.3g} %" for v in a)  # noqa: E731
    scene["budget_calibration"] = rec
    scene["notes"].append(
        f"RECALIBRATED for the budget dt = {st['dt']:.6g} s, substeps = {st['substeps']}, iterations = {st['iterations']} "
        f"({rec['budget']}): every constraint stiffness = {rec['factor']:.6g} x the card's lattice value, so that pypbd's rest "
        f"state on this specimen (load fractions {[round(f, 4) for f in fractions]}) reproduces the card's {card.model} reactions "
        f"{fmt(rec['signed_error_after'])} (the card's values would give {fmt(rec['signed_error_before'])}); valid for this "
        "budget, mesh and loading only; gravity not included (pypbd applies it: the specimen's weight adds to the load)")
    rec["weight_field_share"] = weight_share
    target = ("no field target given" if rec["field_tolerance"] is None else
              f"field target {100 * rec['field_tolerance']:g} % " + ("met" if rec["field_within_tolerance"] else "NOT met"))
    scene["notes"].append(
        f"DISPLACEMENT FIELD at the last load state: max |u_pypbd - u_card| / max |u_card| = {100 * rec['field_error']:.3g} % at this "
        f"budget ({target}); {100 * lattice_error:.3g} % of it is the pypbd lattice itself (XPBD distance constraints and a volume "
        f"constraint per tet, not the card's {card.model}: the scene energy's exact minimum, which more substeps or iterations "
        f"approach, differs from the card's model by that much); the reactions, not the field, are what the budget was "
        f"recalibrated on. Gravity: pypbd applies (0, -9.81, 0) m/s^2 and cannot switch it off; the specimen's weight moves the "
        f"particles by up to {100 * weight_share:.3g} % of max |u_card| more (the card's model with the lumped weights)")
    if "field_note" in rec:
        scene["notes"].append("APPROXIMATION: " + rec["field_note"])
    return scene


def write_pbd(card, path, *, mesh=None, constraints: str = "xpbd", dt: float | None = None, substeps: int | None = None,
              iterations: int | None = None, approximate: bool = False, displacement: float | None = None, force: bool = False,
              indentation=None, calibrate: bool = True, load_fractions=None, field_tolerance: float | None = None) -> Path:
    """Write :func:`pbd_scene` as JSON (``"format": "difftissue-pbd/1"``); load it with
    :func:`read_pbd_scene` and :func:`pbd_simulation_from_scene`."""
    scene = pbd_scene(card, mesh, constraints=constraints, dt=dt, substeps=substeps, iterations=iterations,
                      approximate=approximate, displacement=displacement, indentation=indentation, calibrate=calibrate,
                      load_fractions=load_fractions, field_tolerance=field_tolerance)
    return write_text(path, json.dumps(scene, indent=1, allow_nan=False) + "\n", force)


_PBD_WHY = ("a pypbd scene holds fixed particles and one moved set (a particle is static, all components, or free), not per-node "
            "prescribed displacements, region materials or a pre-stretch")


def write_fitted_pbd(card, path, spec: FittedSpecimen, *, approximate: bool, force: bool, dt, iterations, substeps,
                     field_tolerance: float | None = None) -> Path:
    """pypbd scene of a fitted compression with bonded platens on a block (the only fitted experiment
    a pypbd scene can hold), recalibrated for its budget on the protocol's strains
    (:func:`difftissue.export.pypbd.pbd_scene`, :mod:`difftissue.export.budget`)."""
    if spec.experiment != "compression":
        raise ExportError(f"pypbd fitted specimen ({spec.experiment}): {_PBD_WHY}; export to febio, abaqus, xpbd or vtu "
                          "(pypbd takes a fitted compression with bonded platens, or --specimen indentation with a bonded flat punch)")
    if spec.protocol["platens"] != "bonded":
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: frictionless platens hold u_z only, and a pypbd particle is "
                          "either static (all components) or free, so the platens cannot be written; export to febio, abaqus, "
                          "xpbd or vtu")
    if spec.region_materials:
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: {_PBD_WHY}")
    try:
        mesh = recover_lattice(spec.mesh())
    except ModelError as e:
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: the pypbd scene is difftissue's spring lattice, which needs a "
                          f"structured block ({e}); a cylinder cannot be written; export to febio, abaqus, xpbd or vtu") from None
    base, top, _ = block_sets(mesh)
    want = np.zeros_like(spec.fixed)
    want[base] = True
    want[top] = True
    if not np.array_equal(want, spec.fixed) or not np.allclose(spec.prescribed[top], [0.0, 0.0, spec.protocol["top_displacement"]]):
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: the specimen's held components are not the bonded base and "
                          "top faces of the block; " + _PBD_WHY)
    fr = [float(v) for v in (np.asarray(spec.protocol["nominal_strains"], dtype=float) / spec.protocol["nominal_strains"][-1])]
    if len(fr) > 4:
        fr = recalibration_fractions(spec)
    scene = pbd_scene(card, mesh, dt=dt, iterations=iterations, substeps=substeps, approximate=approximate,
                      displacement=float(spec.protocol["top_displacement"]), load_fractions=fr, field_tolerance=field_tolerance)
    scene["header"] = scene["header"] + spec.describe()
    scene["fitted_specimen"] = {"scenario": spec.scenario, "experiment": spec.experiment, "protocol": dict(spec.protocol),
                                "note": "the protocol's strains are the load fractions of budget_calibration (nominal strain = "
                                        "fraction x the last); engineering stress = reaction / protocol.area"}
    return write_text(path, json.dumps(scene, indent=1, allow_nan=False) + "\n", force)
