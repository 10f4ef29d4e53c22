"""The XPBD JSON (``difftissue-xpbd/1``): stable neo-Hookean compliances for a stated budget, with
the block, indentation or fitted specimen, recalibrated for that budget (docs/export.md, docs/xpbd.md).

:func:`xpbd_parameters` / :func:`write_xpbd` (material, block, indentation),
:func:`xpbd_fitted_parameters` (fitted specimen, recalibrated or checked at the budget:
:func:`xpbd_fitted_budget`, :func:`xpbd_fitted_field_check`), and
:func:`run_xpbd_indentation`, which runs a flat-punch file in difftissue's own XPBD solver.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import jax.numpy as jnp
import numpy as np

from ..boundary import BoundaryConditions
from ..errors import ConvergenceError, ExportError, ModelError
from ..mesh import signed_volumes
from ..models import LATTICE_MODELS, make_model
from ..scenarios import recover_lattice
from ..solvers.static import solve_static
from ..solvers.xpbd import StableNeoHookeanConstraints, XPBDSettings, xpbd_quasi_static_constraints
from ._common import UNITS, finite, write_text
from .approximations import approximation_notes
from .budget import (MAX_BUDGET_ERROR, card_reference_reactions, load_fractions, xpbd_budget_calibration, xpbd_document_constraints,
                     xpbd_load_set_calibration)
from .card import MATERIAL_FIELDS, MaterialCard
from .fitted import FittedSpecimen, load_steps
from .recalibration import recalibration_fractions
from .specimens import block_sets, default_displacement, indentation_sets, no_mesh_with_indentation

__all__ = ["xpbd_parameters", "write_xpbd", "run_xpbd_indentation", "xpbd_fitted_parameters", "xpbd_fitted_budget",
           "FIELD_CHECK_HALVINGS", "xpbd_fitted_field_check"]


def xpbd_parameters(card: MaterialCard, *, dt: float, iterations: int, substeps: int = 1, mesh=None,
                    approximate: bool = False, displacement: float | None = None, indentation=None, calibrate: bool = True,
                    load_set=None, extrapolate: bool = False) -> dict:
    """Stable neo-Hookean XPBD constraint data (Macklin & Müller 2021) for a stated time step.

    Per tetrahedron of rest volume ``V0``: deviatoric constraint ``C_D = sqrt(tr F^T F)`` with
    compliance ``alpha_D = 1 / (mu V0)``, hydrostatic ``C_H = det F - gamma`` with
    ``alpha_H = 1 / (lambda' V0)``, ``lambda' = lambda + mu`` and ``gamma = 1 + mu / lambda'``
    (the shift makes the small-strain response equal (E, nu)). The solver uses
    ``alpha_tilde = alpha / h^2`` with the substep ``h = dt / substeps``. Without ``mesh`` the
    values are given per unit volume (``alpha V0``, in 1/Pa); with ``mesh`` per tetrahedron,
    plus a ``"specimen"`` (positions, tets, lumped masses, base fixed, top moved by
    ``displacement`` [m] along z, default -10 % of the height).

    With a specimen (a block, or a flat-punch indentation) and ``calibrate`` (default), the
    compliances are **recalibrated for the written budget** (:mod:`difftissue.export.budget`):
    ``mu`` and ``lambda'`` times one factor so that standard XPBD (multipliers reset every
    substep) at ``dt`` / ``substeps`` / ``iterations``, run by difftissue's XPBD solver on the
    specimen, reproduces the card's own model's reactions within 2 % at up to 4 load states;
    a saturated budget is refused with a suggested one (``approximate``: written with the
    measured signed error). Without a specimen (or for sphere / cone specimens, which
    difftissue's solver cannot run) the values are the card's converged-limit ones: XPBD with
    a finite iteration count is softer than they imply (``validity`` says so).

    ``load_set``: a load-set calibration the caller computed, the object returned by
    :func:`difftissue.budget.calibrate_for_load_set` of ``"stable_neo_hookean"`` (the file's
    constraint pair) at this ``dt`` / ``substeps`` / ``iterations`` (``method="gauss_seidel"``,
    ``warm_start=False``) on ``mesh`` (or the indentation specimen's mesh) with the card's
    material. The export checks it against what it writes
    (:func:`~difftissue.export.budget.check_load_set_calibration`) and writes it
    (:func:`~difftissue.export.budget.xpbd_load_set_calibration`): the compliances are the
    card's ``E_eff = E f(E)`` and the file's ``budget_calibration.card`` holds the validity
    range (shapes, depths, stiffness range, cell size, setting) and every load's residual
    error. Raises :class:`~difftissue.errors.BudgetRangeError` when the calibration's setting or
    mesh is not the export's or the card's modulus lies outside its stiffness range
    (``extrapolate=True``: written with a :class:`~difftissue.errors.BudgetExtrapolationWarning`),
    :class:`~difftissue.errors.ExportError` for another model kind, Poisson ratio or density, no
    mesh, or an object that is no such calibration. ``approximate`` does not relax these. (A
    saturated budget is refused by ``calibrate_for_load_set`` itself, with the proposed budget.)
    """
    if load_set is not None and not calibrate:
        raise ExportError("load_set asks for a budget calibration over the loads; calibrate=False asks for none: give one of them")
    if extrapolate and load_set is None:
        raise ExportError("extrapolate applies to a load-set calibration (load_set=...); none was given")
    dt = finite(dt, "dt")
    if dt <= 0:
        raise ExportError(f"dt = {dt:g} s must be > 0")
    if int(iterations) != iterations or iterations < 1:
        raise ExportError(f"iterations = {iterations!r} must be a positive integer")
    if int(substeps) != substeps or substeps < 1:
        raise ExportError(f"substeps = {substeps!r} must be a positive integer")
    notes = approximation_notes(card, "XPBD stable neo-Hookean", approximate=approximate)
    mu, lam = card.shear_modulus, card.lame_lambda
    lam_s = lam + mu
    h = dt / substeps
    out = {
        "format": "difftissue-xpbd/1",
        "units": UNITS,
        "constraints": "stable neo-Hookean pair (Macklin & Mueller 2021): C_D = sqrt(tr F^T F), C_H = det F - gamma",
        "material": card.name,
        "model": card.model,
        "setting": {"dt": dt, "iterations": int(iterations), "substeps": int(substeps), "substep": h},
        "lame": {"mu": mu, "lambda": lam, "lambda_shifted": lam_s},
        "gamma": 1.0 + mu / lam_s,
        "per_unit_volume": {"deviatoric_compliance": 1.0 / mu, "hydrostatic_compliance": 1.0 / lam_s,
                            "unit": "1/Pa (divide by the tet rest volume V0 [m^3])"},
        "density": card.density,
        "validity": (f"compliances reproduce E = {card.youngs_modulus:.6g} Pa, nu = {card.poisson_ratio:.6g} only when "
                     f"the XPBD iterations converge; with {int(iterations)} iteration(s) the response is softer "
                     "(budget-aware calibration not applied)"),
        "notes": notes,
        "card_provenance": card.provenance,
    }
    if indentation is not None:
        no_mesh_with_indentation(mesh)
        mesh = indentation.mesh()
    if mesh is not None:
        pts = np.asarray(mesh.points, dtype=float)
        t = np.asarray(mesh.tets)
        v0 = np.abs(signed_volumes(pts, t))
        out["per_tet"] = {
            "rest_volume": v0.tolist(),
            "deviatoric_compliance": (1.0 / (mu * v0)).tolist(),
            "hydrostatic_compliance": (1.0 / (lam_s * v0)).tolist(),
            "deviatoric_alpha_tilde": (1.0 / (mu * v0) / h**2).tolist(),
            "hydrostatic_alpha_tilde": (1.0 / (lam_s * v0) / h**2).tolist(),
            "unit": "compliance 1/(Pa m^3); alpha_tilde = compliance / h^2",
        }
        out["specimen"] = _specimen_dict(card, mesh, displacement) if indentation is None else _xpbd_indentation_specimen(card, indentation, mesh)
    if load_set is not None:
        xpbd_load_set_calibration(out, card, load_set, mesh=mesh, extrapolate=extrapolate)
        out["notes"].append("calibrated over the load set (budget_calibration.card), not on the specimen: the specimen is "
                            "written for reference, its response at this budget was not measured")
        return out
    if mesh is not None:
        if calibrate and (indentation is None or indentation.indenter == "flat_punch"):
            _xpbd_calibrate_specimen(out, card, mesh, indentation, approximate)
        elif calibrate:
            out["notes"].append(f"NOT calibrated for the budget: difftissue's XPBD solver has no contact constraint, so the "
                                f"{indentation.indenter} specimen cannot be run at this budget here; the compliances are the card's "
                                "converged-limit values (see validity)")
    return out


def _xpbd_calibrate_specimen(doc: dict, card: MaterialCard, mesh, indentation, approximate: bool) -> None:
    """Recalibrate a block or flat-punch XPBD document for its budget (:mod:`difftissue.export.budget`)."""
    sp = doc["specimen"]
    n = len(sp["positions"])
    fixed = np.zeros((n, 3), dtype=bool)
    presc = np.zeros((n, 3))
    if indentation is None:
        fixed[sp["fixed"]] = True
        fixed[sp["moved"]] = True
        presc[sp["moved"]] = sp["displacement"]
        moved = np.asarray(sp["moved"])
        fr = load_fractions(4)
    else:
        fx = sp["fixed"]
        if "all_components" in fx:
            fixed[np.asarray(fx["all_components"], dtype=np.int64)] = True
        for c, axis in (("x", 0), ("y", 1), ("z", 2)):
            if c in fx:
                fixed[np.asarray(fx[c], dtype=np.int64), axis] = True
        ind = sp["indenter"]
        moved = np.asarray(ind["nodes"], dtype=np.int64)
        fixed[moved, 2] = True
        if ind.get("bonded"):
            fixed[moved, :2] = True
        presc[moved, 2] = -float(indentation.depth)
        fr = load_fractions(indentation.steps)
    observe = np.zeros((n, 3), dtype=bool)
    observe[moved] = fixed[moved]
    try:
        ref = card_reference_reactions(card, mesh, fixed, presc, observe, fr)
    except ExportError as e:
        if not approximate:
            raise ExportError(f"XPBD: {e}; pass approximate=True (--approximate) to write the card's converged-limit compliances") from None
        doc["notes"].append(f"APPROXIMATION: not calibrated for the budget: {e}")
        return
    xpbd_budget_calibration(doc, ref, fixed, presc, observe, fr, approximate=approximate)
    doc["budget_calibration"]["reference_model"] = card.model


def _xpbd_indentation_specimen(card: MaterialCard, spec, mesh) -> dict:
    s = indentation_sets(spec, mesh, card)
    pts = np.asarray(mesh.points, dtype=float)
    t = np.asarray(mesh.tets)
    v0 = np.abs(signed_volumes(pts, t))
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(card.density * v0 / 4.0, 4))
    if spec.base == "bonded":
        fixed = {"all_components": s["base"].tolist()}
    else:
        fixed = {"z": s["base"].tolist(), "x": [s["anchor"]], "y": [s["anchor"], s["other"]]}
    return {"experiment": "indentation", "positions": pts.tolist(), "tets": t.tolist(), "masses": m.tolist(),
            "fixed": fixed, "indenter": _xpbd_indenter(card, spec, mesh), "assumptions": spec.describe(),
            "note": "SI; fixed: node ids per held component (base z = 0); masses rho V/4 per tet node"}


def _xpbd_indenter(card: MaterialCard, spec, mesh) -> dict:
    """The ``indenter`` block of an XPBD indentation specimen (difftissue's contact energy)."""
    s = indentation_sets(spec, mesh, card)
    H = s["H"]
    out: dict[str, Any] = {"shape": spec.indenter, "axis": [0.0, 0.0], "surface_z": H, "depth": spec.depth,
                           "depth_steps": [spec.depth * (i + 1) / spec.steps for i in range(spec.steps)]}
    if spec.indenter == "flat_punch":
        out.update(radius=spec.radius, bonded=spec.bonded_punch, nodes=s["punch"].tolist(),
                   prescribed="u_z = -depth" + (", u_x = u_y = 0" if spec.bonded_punch else " (x, y free: frictionless)"))
        return out
    if spec.indenter == "sphere":
        out.update(radius=spec.radius, center_at_depth=[0.0, 0.0, H - spec.depth + spec.radius],
                   penetration="p_i = R - |x_i - c|, c = (0, 0, H - depth + R)")
    else:
        out.update(half_angle=spec.half_angle, tip_at_depth=[0.0, 0.0, H - spec.depth],
                   penetration="p_i = (z_i - z_tip) sin(theta) - r_i cos(theta), r_i = distance to the axis")
    out.update(contact_nodes=s["contact_nodes"].tolist(), penalty=s["kappa"].tolist(),
               energy="sum_i penalty_i / 2 max(p_i, 0)^2 (frictionless; penalty_i = p E sqrt(A_i) [N/m], "
                      f"p = {spec.penalty:g}, A_i the node's tributary boundary area)",
               force="indentation force = sum_i penalty_i max(p_i, 0) dp_i/d(depth) (positive compressive)")
    return out


def _specimen_dict(card: MaterialCard, mesh, displacement: float | None) -> dict:
    """Mesh, lumped masses and boundary conditions of the block specimen (JSON-ready)."""
    pts = np.asarray(mesh.points, dtype=float)
    t = np.asarray(mesh.tets)
    base, top, height = block_sets(mesh)
    d = default_displacement(height, displacement)
    v0 = np.abs(signed_volumes(pts, t))
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(card.density * v0 / 4.0, 4))
    return {"positions": pts.tolist(), "tets": t.tolist(), "masses": m.tolist(),
            "fixed": base.tolist(), "moved": top.tolist(), "displacement": [0.0, 0.0, d],
            "note": "SI; base (min z) fixed, top (max z) moved by 'displacement' (all components), masses rho V/4 per tet node"}


def write_xpbd(card: MaterialCard, path, *, dt: float, iterations: int, substeps: int = 1, mesh=None,
               approximate: bool = False, displacement: float | None = None, force: bool = False, indentation=None,
               calibrate: bool = True, load_set=None, extrapolate: bool = False) -> Path:
    """Write :func:`xpbd_parameters` as JSON."""
    doc = xpbd_parameters(card, dt=dt, iterations=iterations, substeps=substeps, mesh=mesh, approximate=approximate,
                          displacement=displacement, indentation=indentation, calibrate=calibrate, load_set=load_set,
                          extrapolate=extrapolate)
    return write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n", force)


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
            raise ConvergenceError(f"XPBD diverged (non-finite state) at depth {float(d):.6g} m with dt = {st['dt']:.6g} s, "
                                   f"{settings.iterations} iterations: warm-started XPBD needs a smaller time step on this mesh; "
                                   "export the file with a smaller --dt")
        out["depths"].append(float(d))
        out["forces"].append(force)
        out["converged"].append(bool(sol.converged))
        out["steps"].append(int(sol.steps))
    return out


def xpbd_fitted_parameters(card, spec: FittedSpecimen, *, dt: float, iterations: int, substeps: int = 1, approximate: bool = False,
                           calibrate: bool = True) -> dict:
    """The XPBD JSON (``difftissue-xpbd/1``) of a fitted specimen: the header of
    :func:`~difftissue.export.xpbd_parameters` for the card, per-tet stable neo-Hookean
    compliances of each tet's region material, and a ``specimen`` block: positions [m], tets,
    regions (each with its material and whether it is the card's), lumped masses ``rho V / 4``,
    ``fixed`` node ids per component, ``prescribed_displacement`` ``[[node, component, value
    [m]], ...]``, the reaction set, and for an incision the duplicated pairs (with ``s``, depth,
    the surface order), for a compression the ``protocol`` and ``load_steps`` of the ramp, and per-tet ``pre_stretch``: a pre-stretched tet's stress-free shape is
    the mesh shrunk by ``1/lambda0`` in x and y (``Dm`` of that shape; rest volume ``V/lambda0^2``).

    ``calibrate`` (default): the written budget must reproduce the fitted experiment
    (:func:`xpbd_fitted_budget`): a specimen with a summed reaction and no pre-stretch (fem_field
    with reaction, compression) is **recalibrated** (one factor on ``mu`` and ``lambda'`` of the
    fitted regions, :func:`~difftissue.export.budget.xpbd_budget_calibration`); an incision or a
    fem_field without reaction is **checked** (opening widths / displacement field at the budget
    against the card's model, 2 % of the largest); a budget that does not reach 2 % is refused
    with the reason and a smaller ``dt`` that does (``approximate``: written, the measured error
    noted). ``calibrate=False`` writes the card's converged-limit compliances (conversion checks)."""
    base = card
    if card.is_pre_stretched:  # the header is the card's material; its pre-stretch is carried per tet below
        d = card.to_dict()
        d["parameters"] = {k: dict(v) for k, v in d["parameters"].items() if k != "pre_stretch_y"}
        d["parameters"]["pre_stretch"] = {"value": 1.0, "unit": "1", "standard_error": None}
        base = MaterialCard.from_dict(d)
    doc = xpbd_parameters(base, dt=dt, iterations=iterations, substeps=substeps, approximate=approximate)
    doc["material"] = card.name
    cards = spec.region_cards(card)
    for c in cards:
        if c is not card:
            approximation_notes(c, "XPBD stable neo-Hookean", approximate=approximate, pre_stretch_ok=True)
    pts, t = spec.points, spec.tets
    v = np.abs(signed_volumes(pts, t))
    lam0 = np.array([cards[r].pre_stretch for r in spec.region_ids])
    aniso = any(c.is_anisotropic_pre_stretch for c in cards)
    lam_y = np.array([cards[r].pre_stretch_y for r in spec.region_ids])
    v0 = v / (lam0 * lam_y) if aniso else v / lam0**2  # stress-free volume
    mu = np.array([cards[r].shear_modulus for r in spec.region_ids])
    lam_s = np.array([cards[r].lame_lambda + cards[r].shear_modulus for r in spec.region_ids])
    rho = np.array([cards[r].density for r in spec.region_ids])
    h = dt / substeps
    doc["per_tet"] = {"region": spec.region_ids.tolist(), "pre_stretch": lam0.tolist(), "rest_volume": v0.tolist(),
                      "mu": mu.tolist(), "lambda_shifted": lam_s.tolist(),
                      "deviatoric_compliance": (1.0 / (mu * v0)).tolist(), "hydrostatic_compliance": (1.0 / (lam_s * v0)).tolist(),
                      "deviatoric_alpha_tilde": (1.0 / (mu * v0) / h**2).tolist(), "hydrostatic_alpha_tilde": (1.0 / (lam_s * v0) / h**2).tolist(),
                      "unit": "compliance 1/(Pa m^3); rest_volume m^3 of the stress-free tet (the mesh tet shrunk by 1/pre_stretch in x, y)"}
    if aniso:  # anisotropic pre-stretch: the tets shrink by 1/pre_stretch in x and 1/pre_stretch_y in y
        doc["per_tet"]["pre_stretch_y"] = lam_y.tolist()
        doc["per_tet"]["unit"] = ("compliance 1/(Pa m^3); rest_volume m^3 of the stress-free tet (the mesh tet shrunk by "
                                  "diag(1/pre_stretch, 1/pre_stretch_y, 1))")
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(rho * v / 4.0, 4))
    presc = [[int(n), int(c), float(spec.prescribed[n, c])] for n, c in zip(*np.nonzero(spec.fixed))]
    regions = [{"name": r, "fitted": r in spec.fitted_regions, **{f: cards[i].value(f) for f in MATERIAL_FIELDS},
                **({"pre_stretch_y": cards[i].pre_stretch_y} if aniso else {})}
               for i, r in enumerate(spec.region_names)]
    sp: dict[str, Any] = {"experiment": spec.experiment, "scenario": spec.scenario, "difftissue_model": spec.model,
                          "positions": pts.tolist(), "tets": t.tolist(), "regions": regions, "masses": m.tolist(),
                          "fixed": {c: np.flatnonzero(spec.fixed[:, i]).tolist() for i, c in enumerate("xyz")},
                          "prescribed_displacement": presc,
                          "rest_shape": ("per tet: Dm from the positions shrunk by 1/pre_stretch in x and 1/pre_stretch_y in y (stress-free state)"
                                         if aniso else "per tet: Dm from the positions shrunk by 1/pre_stretch in x and y (stress-free state)"),
                          "assumptions": spec.describe(),
                          "note": "SI; fixed: node ids per held component; prescribed_displacement: [node, component (0 x, 1 y, 2 z), value m]"}
    if spec.reaction is not None:
        sp["reaction"] = {c: np.flatnonzero(spec.reaction[:, i]).tolist() for i, c in enumerate("xyz")}
    if spec.protocol is not None:
        sp["protocol"] = dict(spec.protocol)
        sp["load_steps"] = load_steps(spec)
        sp["load_note"] = ("compression: ramp the prescribed displacements linearly from 0 over load_steps quasi-static steps "
                           "(load fraction t <-> nominal strain t * protocol.nominal_strains[-1]); engineering stress = "
                           "-(sum of the z reactions over reaction.z) / protocol.area")
    if spec.pairs is not None:
        sp["cut"] = {"pairs": spec.pairs.tolist(), "pair_s": spec.pair_s.tolist(), "pair_depth": spec.pair_depth.tolist(),
                     "surface_pairs": spec.surface_pairs.tolist(),
                     "note": "pairs (original, duplicate) are separate, untied nodes: the opened cut; width = |x_a - x_b|"}
    doc["specimen"] = sp
    if calibrate:
        xpbd_fitted_budget(doc, card, spec, approximate=approximate)
    else:
        doc["notes"].append("NOT calibrated for the budget (calibrate=False): the compliances are the card's converged-limit values "
                            "(see validity)")
    return doc


def _budget_fractions(spec: FittedSpecimen) -> list[float]:
    """Load states of a budget recalibration: a compression's protocol strains (up to
    :data:`RECALIBRATION_STATES`), else 1 (the fem_field's one prescribed state)."""
    return recalibration_fractions(spec)


def xpbd_fitted_budget(doc: dict, card, spec: FittedSpecimen, *, approximate: bool) -> dict:
    """Make the fitted XPBD document reproduce its fitted experiment at the written budget
    (issue 16), in place.

    * A summed reaction and no pre-stretch (fem_field with reaction, compression): the reference
      is the fit's model (``spec.model``) at the card's values on the specimen (per-region
      materials), solved by difftissue's static solver at the protocol's strains (a
      compression, up to 4) or the prescribed state (a fem_field): what the fit matched. The
      XPBD compliances of the fitted regions are recalibrated by one factor on ``mu`` and
      ``lambda'`` (nu kept) so that standard XPBD at the written budget is within 2 % per state
      (:func:`~difftissue.export.budget.xpbd_budget_calibration`); refused with a suggested
      ``dt`` when it cannot be.
    * No reaction or a pre-stretch (an incision, a fem_field without reaction): no force to
      scale (a common stiffness factor leaves a displacement-loaded or pre-stretch-loaded
      equilibrium unchanged), so the written budget is **checked** (:func:`xpbd_fitted_field_check`):
      the opening widths of the cut pairs (incision) or the displacement field (fem_field) of
      standard XPBD at the budget against the fit's model, within 2 % of the largest; refused
      with a smaller ``dt`` that reaches it, or with ``approximate`` written with the error noted.
    """
    fitted_tets = np.array([spec.region_names[r] in spec.fitted_regions for r in spec.region_ids])
    if spec.reaction is None or any(c.is_pre_stretched for c in spec.region_cards(card)):
        return xpbd_fitted_field_check(doc, card, spec, approximate=approximate)
    fr = _budget_fractions(spec)
    observe = spec.reaction & spec.fixed
    try:
        ref = card_reference_reactions(card, spec.mesh(), spec.fixed, spec.prescribed, observe, fr,
                                       material=spec.material(card), model=spec.model)
    except ExportError as e:
        if not approximate:
            raise ExportError(f"XPBD fitted specimen {spec.scenario!r}: {e}; pass approximate=True (--approximate) to write the "
                              "card's converged-limit compliances") from None
        doc["notes"].append(f"APPROXIMATION: not calibrated for the budget: {e}")
        return doc
    xpbd_budget_calibration(doc, ref, spec.fixed, spec.prescribed, observe, fr, approximate=approximate, fitted_tets=fitted_tets)
    rec = doc["budget_calibration"]
    rec["reference_model"] = spec.model
    rec["scenario"] = spec.scenario
    if spec.protocol is not None:
        rec["nominal_strains"] = [f * float(spec.protocol["nominal_strains"][-1]) for f in fr]
    doc["notes"].append(doc["validity"])
    return doc


def _xpbd_fitted_observable(spec: FittedSpecimen, u: np.ndarray) -> np.ndarray:
    """The checked observable of a reaction-free specimen: the cut pairs' opening widths [m]
    (incision) or the displacement field [m] (fem_field)."""
    if spec.pairs is not None:
        x = spec.points + u
        return np.linalg.norm(x[spec.pairs[:, 0]] - x[spec.pairs[:, 1]], axis=1)
    return np.asarray(u)


#: Halvings of dt tried when a reaction-free XPBD specimen misses 2 % at its budget (to suggest one).
FIELD_CHECK_HALVINGS = 3


def xpbd_fitted_field_check(doc: dict, card, spec: FittedSpecimen, *, approximate: bool, max_steps: int = 5_000) -> dict:
    """Check (in place) that standard XPBD at the document's budget reproduces a reaction-free
    fitted specimen: ``max |o_xpbd - o_ref| / max |o_ref|`` <= 2 % with ``o`` the opening widths
    (incision) or the displacement field (fem_field); ``o_ref`` of the fit's model at the card's
    values by difftissue's static solver, ``o_xpbd`` of the document's per-tet compliances and
    stress-free shapes run like a real-time engine (multipliers reset every substep, fully damped
    frames to rest). Refused with the reason and a smaller ``dt`` (halved up to
    :data:`FIELD_CHECK_HALVINGS` times) that
    reaches 2 %; ``approximate`` writes the file with the measured error noted. The result is
    recorded in ``doc["budget_check"]``."""
    what = "opening widths of the cut pairs" if spec.pairs is not None else "displacement field"
    mesh = spec.mesh()
    if spec.model in LATTICE_MODELS:
        try:
            mesh = recover_lattice(mesh)
        except ModelError as e:  # a cut mesh (duplicated nodes) is no rectilinear grid: its lattice is not in the specimen file
            msg = (f"XPBD fitted {spec.experiment} specimen {spec.scenario!r}: the fit's {spec.model} model cannot be solved on the "
                   f"specimen file's mesh ({e}), so the budget cannot be checked against it")
            if not approximate:
                raise ExportError(msg + "; pass approximate=True (--approximate) to write the file unchecked") from None
            doc["validity"] = "APPROXIMATION: NOT checked for this budget: " + msg
            doc["notes"].append(doc["validity"])
            return doc
    bc = BoundaryConditions(spec.fixed, spec.prescribed, np.zeros_like(spec.prescribed))
    ref = _xpbd_fitted_observable(spec, np.asarray(solve_static(make_model(mesh, spec.model), spec.material(card), bc).displacement))
    scale = float(np.max(np.abs(ref)))
    if not scale > 0:
        raise ExportError(f"XPBD fitted specimen {spec.scenario!r}: the fit's model gives zero {what}: nothing to reproduce")
    cons, pts, masses = xpbd_document_constraints(doc, 1.0, None)
    st = doc["setting"]
    bcj = BoundaryConditions(spec.fixed, jnp.asarray(spec.prescribed), jnp.zeros(spec.prescribed.shape))

    def error(dt):
        settings = XPBDSettings(dt=float(dt), substeps=int(st["substeps"]), iterations=int(st["iterations"]), damping=float("inf"),
                                warm_start=False)
        sol = xpbd_quasi_static_constraints((cons,), jnp.asarray(pts), jnp.asarray(masses), bcj, settings=settings, tol=1e-8,
                                            max_steps=max_steps, throw=False)
        u = np.asarray(sol.displacement)
        if not (bool(sol.converged) and np.all(np.isfinite(u))):
            return float("inf"), False
        return float(np.max(np.abs(_xpbd_fitted_observable(spec, u) - ref)) / scale), True

    err, rested = error(float(st["dt"]))
    ok = rested and err <= MAX_BUDGET_ERROR
    budget = f"dt = {float(st['dt']):.6g} s, substeps = {st['substeps']}, iterations = {st['iterations']}"
    doc["budget_check"] = {"target": "xpbd", "setting": dict(st), "observable": what, "reference_model": spec.model,
                           "relative_error": err if rested else None, "came_to_rest": rested, "within_tolerance": ok,
                           "tolerance": MAX_BUDGET_ERROR,
                           "note": f"max |XPBD - {spec.model}| / max |{spec.model}| of the {what}; standard XPBD (multipliers reset "
                                   "every substep, Gauss-Seidel), fully damped frames to rest; no stiffness factor (no reaction to "
                                   "scale, and a common factor leaves this equilibrium unchanged)"}
    doc["setting"]["multipliers"] = "reset every substep (standard XPBD); Gauss-Seidel iterations"
    if ok:
        doc["validity"] = (f"VERIFIED for this budget ({budget}, standard XPBD): difftissue's XPBD solver running these compliances "
                           f"reproduces the {what} of the card's {spec.model} model on the fitted experiment to {100 * err:.3g} % of "
                           "the largest; the card's values unchanged (no reaction to recalibrate on); valid for this budget, mesh and "
                           "loading only")
        doc["notes"].append(doc["validity"])
        return doc
    why = ("does not come to rest at this budget (diverges or creeps)" if not rested else
           f"gives the {what} {100 * err:.3g} % off (of the largest) against the card's {spec.model} model")
    msg = (f"XPBD fitted {spec.experiment} specimen {spec.scenario!r} at {budget}: standard XPBD {why}; it has no summed reaction, so "
           f"no stiffness factor can be recalibrated, and the written budget does not reproduce the fitted experiment within "
           f"{100 * MAX_BUDGET_ERROR:g} %")
    for k in range(1, FIELD_CHECK_HALVINGS + 1):
        dt = float(st["dt"]) / 2**k
        e2, r2 = error(dt)
        if r2 and e2 <= MAX_BUDGET_ERROR:
            msg += (f"; a budget that reaches it: dt = {dt:.6g} s with {st['iterations']} iterations and {st['substeps']} substep(s) "
                    f"(or keep dt and use {int(st['substeps']) * 2**k} substeps): {100 * e2:.3g} %")
            doc["budget_check"]["suggested_dt"] = dt
            break
    else:
        msg += (f"; no dt down to {float(st['dt']) / 2**FIELD_CHECK_HALVINGS:.3g} s reaches it with {st['iterations']} iterations: "
                "use more iterations or a smaller dt")
    if not approximate:
        raise ExportError(msg + "; pass approximate=True (--approximate) to write it with the measured error noted")
    doc["validity"] = "APPROXIMATION: " + msg
    doc["notes"].append(doc["validity"])
    return doc
