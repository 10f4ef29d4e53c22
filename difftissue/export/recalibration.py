"""Recalibration of a lattice card for a continuum target on the experiment it was fitted to
(docs/export.md, "Model mismatch").

A ``springs_volume`` card holds lattice-effective (E, nu); written into a continuum law
(FEBio, SOFA's tet force fields, Abaqus / CalculiX) it is tens of percent too stiff under
inhomogeneous strain. The fitted experiment is solved twice in difftissue, the card's model at
the card's values and the target's continuum model at the same values, and ``E' = c E`` with the
least-squares factor ``c`` (every energy here is proportional to E):
:func:`recalibrated_card` on a fitted specimen (fem_field with reaction, compression),
:func:`recalibrated_indentation_card` on the card's simulated indentation record, both through
:func:`recalibrated_from_reactions`; :func:`indentation_card` is what the indentation writers call.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from ..boundary import BoundaryConditions
from ..errors import ExportError
from ..materials import Material
from ..models import make_model
from ..scenarios import Indentation, indentation_block, recover_lattice
from ..solvers.static import solve_static
from .approximations import LAW_MODELS, model_mismatch, resolve_law
from .card import MaterialCard, model_parts
from .fitted import FittedSpecimen
from .specimens import IndentationSpecimen, indentation_records

__all__ = ["RECALIBRATION_STATES", "RECALIBRATION_DEPTHS", "specimen_reactions", "recalibration_fractions", "recalibrated_card",
           "recalibrated_from_reactions", "recalibrated_indentation_card", "indentation_card"]


#: Largest number of protocol strains a compression recalibration solves (evenly picked, the last included).
RECALIBRATION_STATES = 4


def specimen_reactions(card, spec: FittedSpecimen, model: str, fractions=(1.0,)) -> np.ndarray:
    """Summed reaction forces [N] over ``spec.reaction`` (one per summed component) of
    difftissue's ``model`` with ``card``'s values on the fitted regions, the prescribed
    displacements scaled by each of ``fractions`` (shape ``(len(fractions), n_components)``).
    ``springs_volume`` gets the specimen's cube lattice back (``recover_lattice``; a mesh that
    is no structured grid is refused there). Solved by difftissue's static solver, ramped in
    increments of at most 5 % nominal strain for a compression."""
    if spec.reaction is None:
        raise ExportError(f"fitted specimen {spec.scenario!r} has no reaction set")
    mesh = spec.mesh()
    if model == "springs_volume":
        mesh = recover_lattice(mesh)
    m = make_model(mesh, model)
    mat = spec.material(card)
    comps = [c for c in range(3) if spec.reaction[:, c].any()]
    e_last = abs(float(spec.protocol["nominal_strains"][-1])) if spec.protocol is not None else 0.0
    out = []
    for f in fractions:
        bc = BoundaryConditions(spec.fixed, spec.prescribed * float(f), np.zeros_like(spec.prescribed))
        sol = solve_static(m, mat, bc, load_steps=max(1, int(math.ceil(abs(f) * e_last / 0.05 - 1e-9))))
        r = np.asarray(sol.reaction)
        out.append([float(np.sum(r[spec.reaction[:, c], c])) for c in comps])
    return np.asarray(out)


def recalibration_fractions(spec: FittedSpecimen) -> list[float]:
    """Load fractions solved: 1 (fem_field), or up to :data:`RECALIBRATION_STATES` protocol
    strains of a compression as fractions of the last."""
    if spec.protocol is None:
        return [1.0]
    e = np.asarray(spec.protocol["nominal_strains"], dtype=float)
    idx = np.unique(np.round(np.linspace(0, len(e) - 1, min(RECALIBRATION_STATES, len(e)))).astype(int))
    return [float(e[i] / e[-1]) for i in idx]


def recalibrated_card(card, spec: FittedSpecimen, law: str, *, approximate: bool = False):
    """``card`` (a lattice model, :func:`~difftissue.export.model_mismatch`) recalibrated to the
    continuum ``law`` on its own fitted experiment ``spec``.

    The fitted experiment is rebuilt from the specimen file and solved twice with difftissue:
    the card's model at the card's values (what the fit matched to the data), and the
    continuum model of the law (:data:`~difftissue.export.LAW_MODELS`: ``fem_linear`` /
    ``fem_neo_hookean``, the same P1-tet energies the targets solve) at the same values. With
    displacements prescribed and nu fixed every energy here is proportional to E, so the
    reactions are too: the least-squares factor ``c = <R_card, R_law> / <R_law, R_law>`` over the
    solved load states gives ``E' = c E`` exactly (one state: the reaction is reproduced to the
    solver's precision). nu is kept (a summed reaction does not determine it), the cubic
    coefficient is dropped (its effect at these strains is absorbed into E'; the residual per
    state is recorded). Returns a new card (model ``fem_linear`` / ``fem_neo_hookean``) whose
    ``provenance["recalibration"]`` holds the factor, the reactions and ``notes`` for the file
    headers, including the signed error the card's own values would have had.
    Refused (one line) for an incision, a fem_field without reaction, fixed regions or a
    pre-stretch, and a cubic coefficient ``b != 0`` unless ``approximate`` (the law cannot
    follow the stiffening: E' is then a least-squares compromise, its residuals noted)."""
    why = model_mismatch(card, law)
    own = next(m for m in model_parts(card.model) if m in ("springs_volume",))
    if spec.experiment == "incision" or spec.reaction is None or card.pre_stretch != 1.0 or spec.region_materials:
        raise ExportError(f"{why}; the fitted {spec.experiment} specimen {spec.scenario!r} cannot be recalibrated (needs a summed "
                          "reaction, one material and no pre-stretch); pass approximate=True (--approximate) to write the card's values "
                          "with the measured error noted")
    if card.cubic_coefficient != 0.0 and not approximate:
        raise ExportError(f"cubic_coefficient b = {card.cubic_coefficient:g} cannot be represented by the continuum {law} law; pass "
                          "approximate=True (--approximate) to recalibrate E alone (b dropped, the residual per load state noted)")
    fr = recalibration_fractions(spec)
    ref = specimen_reactions(card, spec, own, fr)
    tgt = specimen_reactions(card, spec, LAW_MODELS[law], fr)
    return recalibrated_from_reactions(card, law, own, why, ref, tgt, scenario=spec.scenario,
                                       states=f"load fraction(s) {[round(f, 6) for f in fr]}", record={"load_fractions": fr})


def recalibrated_from_reactions(card, law: str, own: str, why: str, ref, tgt, *, scenario: str, states: str,
                                record: Mapping | None = None, extra_notes=()):
    """The recalibrated card from the reactions [N] of the card's model ``own`` (``ref``: what
    the fit matched) and of the target's continuum model at the card's values (``tgt``), one per
    solved load state (same shapes): ``E' = c E`` with the least-squares ``c = <ref, tgt> /
    <tgt, tgt>`` (every energy here is proportional to E, so one state is reproduced exactly),
    nu kept, b dropped. ``provenance["recalibration"]`` records the factor, both reactions, the
    signed errors before and after, ``record`` and the ``notes`` the file headers print."""
    ref, tgt = np.asarray(ref, dtype=float), np.asarray(tgt, dtype=float)
    c = float(np.vdot(ref, tgt) / np.vdot(tgt, tgt))
    if not (math.isfinite(c) and c > 0):
        raise ExportError(f"recalibration to the {law} law failed: factor {c!r} from reactions {ref.tolist()} / {tgt.tolist()} N")
    before = tgt / ref - 1.0
    after = c * tgt / ref - 1.0
    params = {k: dict(v) for k, v in card.parameters.items()}
    E = card.youngs_modulus
    params["youngs_modulus"].update(value=c * E, recalibrated_from=E)
    if params["youngs_modulus"].get("standard_error") is not None:
        params["youngs_modulus"]["standard_error"] *= c
    b = card.cubic_coefficient
    if "cubic_coefficient" in params:
        params["cubic_coefficient"].update(value=0.0, recalibrated_from=b)
    fmt = lambda a: ", ".join(f"{100 * v:+.3g} %" for v in np.ravel(a))  # noqa: E731
    notes = [f"RECALIBRATED for the continuum {law} law" + (" (APPROXIMATION: b dropped)" if b else "") + f": {why}",
             f"E = {c * E:.10g} Pa = {c:.6g} x the card's {E:.10g} Pa ({own}), nu = {card.poisson_ratio:.10g} kept"
             + (f", cubic_coefficient b = {b:g} dropped (absorbed into E at these strains)" if b else ""),
             f"the fitted experiment {scenario!r} solved in difftissue at {states}: "
             f"{LAW_MODELS[law]} at the card's values gives reaction error {fmt(before)} against {own} (what the fit matched); "
             f"after recalibration {fmt(after)}", *extra_notes]
    prov = dict(card.provenance or {})
    prov["recalibration"] = {"from_model": own, "to_model": LAW_MODELS[law], "law": law, "factor": c, "scenario": scenario,
                             **dict(record or {}), "reaction_card_model": ref.tolist(), "reaction_law_at_card_values": tgt.tolist(),
                             "signed_error_before": np.ravel(before).tolist(), "signed_error_after": np.ravel(after).tolist(),
                             "notes": notes}
    return MaterialCard(model=LAW_MODELS[law], parameters=params, name=card.name, provenance=prov)


#: Largest number of fitted depths an indentation recalibration solves (evenly picked, the last included).
RECALIBRATION_DEPTHS = 4


def _same(a, b) -> bool:
    return a is not None and b is not None and math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=0.0)


def _fit_record(card, spec: IndentationSpecimen, own: str) -> tuple[Mapping | None, list[str]]:
    """The card's simulated indentation record that ``spec`` is the experiment of (fitted with
    model ``own``), or None and the reasons each record does not fit."""
    why = []
    for r in indentation_records(card):
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
    headers (:func:`difftissue.export.recalibration.recalibrated_from_reactions`). Refused (one line)
    when the card holds no matching simulated record."""
    why = model_mismatch(card, law)
    own = next(m for m in model_parts(card.model) if m in ("springs_volume",))
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
    lw = resolve_law(card, law)
    if not model_mismatch(card, lw):
        return card
    if approximate and _fit_record(card, spec, "springs_volume")[0] is None:
        return card
    return recalibrated_indentation_card(card, spec, lw, approximate=approximate)
