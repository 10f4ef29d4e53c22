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

Where one modulus cannot follow the fitted curve (a cubic term, or a one-modulus residual above
:data:`RECALIBRATION_TOLERANCE`) and the target takes a law with more terms (Abaqus / CalculiX),
a frictionless compression is recalibrated to a two-term Ogden law instead
(:func:`recalibrated_ogden_card`: :func:`ogden_energy`, :func:`fit_ogden`, :func:`drucker_unstable`).
"""

from __future__ import annotations

import functools
import math
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..boundary import BoundaryConditions
from ..errors import ExportError
from ..materials import Material
from ..models import LATTICE_MODELS, make_model
from ..scenarios import Indentation, indentation_block, recover_lattice
from ..solvers.static import solve_static
from .approximations import LAW_MODELS, lattice_model, model_mismatch, resolve_law
from .card import MaterialCard
from .fitted import FittedSpecimen
from .specimens import IndentationSpecimen, indentation_records

__all__ = ["RECALIBRATION_STATES", "RECALIBRATION_DEPTHS", "specimen_reactions", "recalibration_fractions", "recalibrated_card",
           "recalibrated_from_reactions", "recalibrated_indentation_card", "indentation_card", "RECALIBRATION_TOLERANCE", "OGDEN_STATES",
           "OGDEN_D2_FACTOR", "ogden_energy", "ogden_inverse_d", "ogden_uniaxial_stress", "drucker_unstable", "fit_ogden",
           "recalibrated_ogden_card"]


#: Largest number of protocol strains a compression recalibration solves (evenly picked, the last included).
RECALIBRATION_STATES = 4


def specimen_reactions(card, spec: FittedSpecimen, model: str, fractions=(1.0,)) -> np.ndarray:
    """Summed reaction forces [N] over ``spec.reaction`` (one per summed component) of
    difftissue's ``model`` with ``card``'s values on the fitted regions, the prescribed
    displacements scaled by each of ``fractions`` (shape ``(len(fractions), n_components)``).
    A lattice model (:data:`~difftissue.models.LATTICE_MODELS`) gets the specimen's cube lattice back (``recover_lattice``; a mesh that
    is no structured grid is refused there). Solved by difftissue's static solver, ramped in
    increments of at most 5 % nominal strain for a compression."""
    if spec.reaction is None:
        raise ExportError(f"fitted specimen {spec.scenario!r} has no reaction set")
    mesh = spec.mesh()
    if model in LATTICE_MODELS:
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


def recalibration_fractions(spec: FittedSpecimen, states: int = RECALIBRATION_STATES) -> list[float]:
    """Load fractions solved: 1 (fem_field), or up to ``states`` (:data:`RECALIBRATION_STATES`)
    protocol strains of a compression as fractions of the last."""
    if spec.protocol is None:
        return [1.0]
    e = np.asarray(spec.protocol["nominal_strains"], dtype=float)
    idx = np.unique(np.round(np.linspace(0, len(e) - 1, min(int(states), len(e)))).astype(int))
    return [float(e[i] / e[-1]) for i in idx]


def recalibrated_card(card, spec: FittedSpecimen, law: str, *, approximate: bool = False, hyperelastic: bool = False):
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
    follow the stiffening: E' is then a least-squares compromise, its residuals noted).

    ``hyperelastic`` (the target takes a law with more terms: Abaqus / CalculiX): for the
    ``neo_hookean`` law on a frictionless compression, a card with ``b != 0``, or one whose
    one-modulus residual exceeds :data:`RECALIBRATION_TOLERANCE` at a solved state, is
    recalibrated to a two-term Ogden law (:func:`recalibrated_ogden_card`). Where that law is
    Drucker-unstable or misses the tolerance: ``b != 0`` is refused with the reason unless
    ``approximate`` (then one modulus, the reason noted); ``b = 0`` keeps the one-modulus card
    with the reason noted."""
    why = model_mismatch(card, law)
    own = lattice_model(card)
    if spec.experiment == "incision" or spec.reaction is None or card.is_pre_stretched or spec.region_materials:
        raise ExportError(f"{why}; the fitted {spec.experiment} specimen {spec.scenario!r} cannot be recalibrated (needs a summed "
                          "reaction, one material and no pre-stretch); pass approximate=True (--approximate) to write the card's values "
                          "with the measured error noted")
    ogden = (hyperelastic and law == "neo_hookean" and spec.experiment == "compression" and spec.protocol is not None
             and spec.protocol.get("platens") == "frictionless")
    b = card.cubic_coefficient
    not_ogden = None
    if ogden and b != 0.0:
        out, not_ogden = recalibrated_ogden_card(card, spec, why=why)
        if out is not None:
            return out
        if not approximate:
            raise ExportError(f"cubic_coefficient b = {b:g}: {not_ogden}; pass approximate=True (--approximate) to recalibrate E "
                              "alone (b dropped, the residual per load state noted)")
    if b != 0.0 and not approximate:
        raise ExportError(f"cubic_coefficient b = {b:g} cannot be represented by the continuum {law} law; pass "
                          "approximate=True (--approximate) to recalibrate E alone (b dropped, the residual per load state noted)")
    fr = recalibration_fractions(spec)
    ref = specimen_reactions(card, spec, own, fr)
    tgt = specimen_reactions(card, spec, LAW_MODELS[law], fr)
    out = recalibrated_from_reactions(card, law, own, why, ref, tgt, scenario=spec.scenario,
                                      states=f"load fraction(s) {[round(f, 6) for f in fr]}", record={"load_fractions": fr})
    after = np.asarray(out.provenance["recalibration"]["signed_error_after"])
    if ogden and b == 0.0 and np.max(np.abs(after)) > RECALIBRATION_TOLERANCE:
        better, not_ogden = recalibrated_ogden_card(card, spec, why=why)
        if better is not None:
            return better
    if not_ogden:
        out.provenance["recalibration"]["notes"].append(f"NOT recalibrated to a two-term Ogden law (*HYPERELASTIC, OGDEN, N=2): "
                                                        f"{not_ogden}")
    return out


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
    when the card holds no matching simulated record or is pre-stretched."""
    why = model_mismatch(card, law)
    own = lattice_model(card)
    if card.is_pre_stretched:
        raise ExportError(f"{why}; the pre-stretched indentation card cannot be recalibrated (the target's continuum model is solved "
                          "without pre-stretch, so the factor would absorb the pre-tension); pass approximate=True (--approximate) "
                          "to write the card's values with the measured error noted")
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
    if approximate and (card.is_pre_stretched or _fit_record(card, spec, lattice_model(card))[0] is None):
        return card
    return recalibrated_indentation_card(card, spec, lw, approximate=approximate)


# ------------------------------------------------------------------ a law with more terms: Ogden N = 2
#: Largest relative stress error per fitted load state that a recalibration may leave without
#: ``approximate`` when it writes a law with more terms (:func:`recalibrated_ogden_card`).
RECALIBRATION_TOLERANCE = 0.02

#: Largest number of protocol strains the Ogden recalibration fits (evenly picked, the last included).
OGDEN_STATES = 20

#: ``D2 = OGDEN_D2_FACTOR * D1`` [1/Pa]: the second volumetric term ``(J - 1)^4 / D2`` is written
#: (CalculiX replaces a zero ``D2`` by ``(0.1 / mu0)^2``, a stiff term Abaqus does not have) and
#: is negligible (``1e-9 (J - 1)^2`` of the first); it is part of the energy fitted and checked.
OGDEN_D2_FACTOR = 1e9

#: Start values of the two-term fit, ``(mu1 / mu, alpha1, mu2 / mu, alpha2)`` with ``mu`` the card's shear modulus.
_OGDEN_STARTS = ((0.5, 5.0, 0.5, -2.0), (0.9, 2.5, 0.1, -2.0), (1.2, 8.0, -0.2, -4.0), (0.5, 1.5, 0.5, 6.0))

#: Homogeneous deformation modes of the Drucker check: principal log strains from the
#: prescribed one ``a`` and the free one ``x`` (traction-free direction), and which principal
#: stress the free one zeroes.
_MODES = {"uniaxial": (lambda a, x: jnp.stack([a, x, x]), 1), "equibiaxial": (lambda a, x: jnp.stack([a, a, x]), 2),
          "planar": (lambda a, x: jnp.stack([a, jnp.zeros_like(a), x]), 2)}


def ogden_energy(log_stretches, mu, alpha, inv_d):
    """Abaqus / CalculiX Ogden strain energy density [Pa], ``*HYPERELASTIC, OGDEN, N=n``:
    ``U = sum_i 2 mu_i / alpha_i^2 (l1b^alpha_i + l2b^alpha_i + l3b^alpha_i - 3) + sum_i (J - 1)^(2 i) / D_i``
    with ``lkb = J^(-1/3) lk`` the deviatoric principal stretches (CalculiX 2.20 manual,
    ``*HYPERELASTIC``; Abaqus strain energy potentials). ``log_stretches``: ``(3,)`` principal
    log strains ``ln lk``; ``mu`` [Pa], ``alpha`` [-]: ``(n,)``; ``inv_d``: ``(n,)`` ``1 / D_i``
    [Pa]. Initial shear modulus ``sum mu_i``, bulk modulus ``2 / D1``."""
    eps = jnp.asarray(log_stretches)
    lnj = jnp.sum(eps)
    dev = eps - lnj / 3.0
    w = jnp.sum(2.0 * mu / alpha ** 2 * (jnp.sum(jnp.exp(alpha[:, None] * dev[None, :]), axis=1) - 3.0))
    jm1 = jnp.expm1(lnj)
    return w + jnp.sum(inv_d * jm1 ** (2 * jnp.arange(1, inv_d.shape[0] + 1)))


_ogden_kirchhoff = jax.grad(ogden_energy)  # principal Kirchhoff stresses tau_k = dU/d(ln lk) [Pa]
_ogden_tangent = jax.hessian(ogden_energy)  # d tau_k / d(ln lm) [Pa]


def _free_strain(mode, a, mu, alpha, inv_d, nu):
    """The free principal log strain of ``mode`` at the prescribed ``a`` (its principal stress
    zero), by Newton from ``-nu a``; returns ``(log strains (3,), |free stress| / |stress|)``."""
    f, k = _MODES[mode]
    g = lambda x: _ogden_kirchhoff(f(a, x), mu, alpha, inv_d)[k]  # noqa: E731
    dg = jax.grad(g)
    x = jax.lax.fori_loop(0, 40, lambda i, x: x - g(x) / dg(x), -nu * a * (2.0 if mode != "uniaxial" else 1.0))
    tau = _ogden_kirchhoff(f(a, x), mu, alpha, inv_d)
    return f(a, x), jnp.abs(tau[k]) / jnp.maximum(jnp.max(jnp.abs(tau)), 1e-300)


@functools.partial(jax.jit, static_argnames="mode")
def _ogden_states(mode, a, mu, alpha, inv_d, nu):
    """Vectorised over ``a``: log strains ``(n, 3)``, relative free-stress residual ``(n,)``,
    principal Kirchhoff stresses ``(n, 3)`` and tangents ``(n, 3, 3)`` [Pa]."""
    eps, rel = jax.vmap(lambda s: _free_strain(mode, s, mu, alpha, inv_d, nu))(a)
    return (eps, rel, jax.vmap(lambda e: _ogden_kirchhoff(e, mu, alpha, inv_d))(eps),
            jax.vmap(lambda e: _ogden_tangent(e, mu, alpha, inv_d))(eps))


def ogden_inverse_d(mu, nu: float) -> np.ndarray:
    """``(1 / D1, 1 / D2)`` [Pa] of a two-term Ogden law with Poisson's ratio ``nu`` at small
    strain: ``K0 = 2 / D1 = 2 mu0 (1 + nu) / (3 (1 - 2 nu))``, ``mu0 = mu1 + mu2``, and
    ``D2 = OGDEN_D2_FACTOR D1``."""
    k0 = 2.0 * float(np.sum(mu)) * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))
    return np.array([k0 / 2.0, k0 / 2.0 / OGDEN_D2_FACTOR])


def ogden_uniaxial_stress(mu, alpha, nu: float, strains) -> np.ndarray:
    """Nominal (engineering) stress [Pa, compression positive] of the Abaqus / CalculiX Ogden
    law (:func:`ogden_energy`, ``D`` from ``nu``: :func:`ogden_inverse_d`) in homogeneous
    uniaxial compression (lateral faces traction free) at the nominal ``strains`` (compression
    positive, < 1): ``-tau_axial / l_axial``, the force per reference area of a frictionless
    compression. Needs float64 JAX."""
    if not jax.config.jax_enable_x64:
        raise ExportError("recalibrating a hyperelastic law needs float64 JAX (jax.config.update('jax_enable_x64', True))")
    mu, alpha = jnp.asarray(mu, dtype=float), jnp.asarray(alpha, dtype=float)
    a = jnp.log1p(-jnp.asarray(strains, dtype=float))
    _, rel, tau, _ = _ogden_states("uniaxial", a, mu, alpha, jnp.asarray(ogden_inverse_d(mu, nu)), nu)
    out = -np.asarray(tau)[:, 0] / np.exp(np.asarray(a))
    return np.where(np.asarray(rel) < 1e-9, out, np.nan)


def drucker_unstable(mu, alpha, nu: float, mode: str, strains) -> float | None:
    """The first nominal strain of ``strains`` (signed: positive = tension of the prescribed
    direction(s)) at which the Ogden law (:func:`ogden_energy`) violates Drucker's stability
    condition ``d tau : d eps > 0`` (Kirchhoff stress ``tau``, logarithmic strain ``eps``) in the
    homogeneous ``mode`` (``"uniaxial"``, ``"equibiaxial"``, ``"planar"``; the other directions
    traction free), or None when it holds at every one. For an isotropic law this is: the
    principal tangent ``d tau_k / d eps_m`` positive definite, and ``(tau_k - tau_m) / (eps_k -
    eps_m) > 0`` for the shears (the Abaqus check tests the principal tangent)."""
    mu, alpha = jnp.asarray(mu, dtype=float), jnp.asarray(alpha, dtype=float)
    e = np.asarray(strains, dtype=float)
    eps, rel, tau, tan = (np.asarray(v) for v in _ogden_states(mode, jnp.log1p(jnp.asarray(e)), mu, alpha,
                                                              jnp.asarray(ogden_inverse_d(mu, nu)), nu))
    for i in range(e.size):
        ok = rel[i] < 1e-9 and np.linalg.eigvalsh(0.5 * (tan[i] + tan[i].T))[0] > 0.0
        for k, m in ((0, 1), (1, 2), (0, 2)):
            d = eps[i, k] - eps[i, m]
            g = (tau[i, k] - tau[i, m]) / d if abs(d) > 1e-7 else tan[i, k, k] - tan[i, k, m]
            ok = ok and g > 0.0
        if not ok:
            return float(e[i])
    return None


def fit_ogden(strains, stresses, youngs_modulus: float, nu: float):
    """Least-squares two-term Ogden law (:func:`ogden_energy`, ``D`` from ``nu``) for the
    nominal compression stresses ``stresses`` [Pa] at the nominal ``strains``: minimises the
    relative errors ``ogden / stress - 1`` (every load state weighs the same, the smallest
    strains included) from a few start values (:data:`_OGDEN_STARTS`, scaled by the shear
    modulus of ``youngs_modulus`` [Pa] and ``nu``), keeping the best Drucker-stable one along
    the fitted compression. Returns ``(mu (2,) [Pa], alpha (2,), residuals)``, or None when no
    start gives a stable law."""
    e, s = np.asarray(strains, dtype=float), np.asarray(stresses, dtype=float)
    g = youngs_modulus / (2.0 * (1.0 + nu))
    path = np.linspace(0.0, float(e.max()), 81)[1:]
    best = None
    for x0 in _OGDEN_STARTS:
        res = lambda x: np.nan_to_num(ogden_uniaxial_stress(x[0::2] * g, x[1::2], nu, e) / s - 1.0, nan=1e3)  # noqa: E731
        try:
            from scipy.optimize import least_squares  # on first use (its import costs ~0.3 s)

            r = least_squares(res, np.asarray(x0), method="lm", max_nfev=2000, xtol=1e-12, ftol=1e-12)
        except (ValueError, FloatingPointError):
            continue
        mu, alpha = r.x[0::2] * g, r.x[1::2]
        if np.any(np.abs(alpha) < 1e-6) or np.sum(mu) <= 0.0 or drucker_unstable(mu, alpha, nu, "uniaxial", -path) is not None:
            continue
        err = res(r.x)
        if best is None or np.max(np.abs(err)) < np.max(np.abs(best[2])):
            best = (mu, alpha, err)
    return best


def _ogden_stability_note(mu, alpha, nu: float, e_max: float) -> str:
    """Where else the law is Drucker-stable within ``e_max`` nominal strain (information only)."""
    grid = np.linspace(0.0, e_max, 41)[1:]
    parts = []
    for mode in ("uniaxial", "equibiaxial", "planar"):
        for sign, word in ((1.0, "tension"), (-1.0, "compression")):
            if mode == "uniaxial" and sign < 0:
                continue
            bad = drucker_unstable(mu, alpha, nu, mode, sign * grid)
            parts.append(f"{mode} {word}: " + ("stable" if bad is None else f"NOT stable from {100 * abs(bad):.3g} %"))
    return f"other homogeneous modes to {100 * e_max:.3g} % nominal strain (not part of the fitted experiment): " + "; ".join(parts)


def recalibrated_ogden_card(card, spec: FittedSpecimen, *, why: str):
    """``card`` (a lattice model) as a two-term Ogden law (Abaqus / CalculiX ``*HYPERELASTIC,
    OGDEN, N=2``) fitted to its own frictionless compression ``spec``, or ``(None, reason)``.

    The frictionless compression is homogeneous uniaxial stress, so the target's answer is
    :func:`ogden_uniaxial_stress` (C3D4 tets represent a homogeneous deformation exactly). The
    card's model is solved in difftissue at up to :data:`OGDEN_STATES` protocol strains (what
    the fit matched to the data), the law is fitted to those nominal stresses (:func:`fit_ogden`:
    relative least squares; ``D1`` from the card's nu, ``D2`` negligible) and checked:
    Drucker-stable along the compression from 0 to the last protocol strain (81 states) and every
    state within :data:`RECALIBRATION_TOLERANCE`. Returns ``(card, None)`` with model ``ogden``,
    E and nu the law's small-strain values, and ``provenance["recalibration"]["hyperelastic"]``
    (law, keyword, coefficients [Pa], ``D`` [1/Pa], strain range, stresses, residuals, notes),
    or ``(None, reason)`` when the law is unstable or misses the tolerance."""
    own = lattice_model(card)
    pr = spec.protocol
    area = float(pr["area"])
    fr = recalibration_fractions(spec, OGDEN_STATES)
    e = np.asarray(fr) * abs(float(pr["nominal_strains"][-1]))
    ref = -specimen_reactions(card, spec, own, fr)[:, 0] / area
    nu = card.poisson_ratio
    fit = fit_ogden(e, ref, card.youngs_modulus, nu)
    if fit is None:
        return None, (f"no two-term Ogden law fitted to the {own} curve at {e.size} strains is Drucker-stable along the compression "
                      f"to {100 * e[-1]:.3g} %")
    mu, alpha, err = fit
    worst = float(np.max(np.abs(err)))
    if worst > RECALIBRATION_TOLERANCE:
        return None, (f"the best Drucker-stable two-term Ogden law misses the {own} curve by up to {100 * worst:.3g} % "
                      f"(> {100 * RECALIBRATION_TOLERANCE:g} %) at nominal strains {100 * e[0]:.3g} to {100 * e[-1]:.3g} %")
    inv_d = ogden_inverse_d(mu, nu)
    d = 1.0 / inv_d
    mu0 = float(np.sum(mu))
    E0 = 2.0 * mu0 * (1.0 + nu)
    keyword = "*HYPERELASTIC, OGDEN, N=2"
    fmt = lambda a: ", ".join(f"{100 * v:+.3g} %" for v in np.ravel(a))  # noqa: E731
    notes = [f"RECALIBRATED for Abaqus / CalculiX {keyword} (two-term Ogden; one modulus cannot follow the card's {own} curve"
             + (f" with cubic_coefficient b = {card.cubic_coefficient:g}" if card.cubic_coefficient else "") + "): "
             f"mu1 = {mu[0]:.10g} Pa, alpha1 = {alpha[0]:.10g}, mu2 = {mu[1]:.10g} Pa, alpha2 = {alpha[1]:.10g}, "
             f"D1 = {d[0]:.10g} 1/Pa, D2 = {d[1]:.10g} 1/Pa; valid for homogeneous uniaxial compression from 0 to {100 * e[-1]:.4g} % "
             f"nominal strain; residual against {own} at {e.size} fitted strains at most {100 * worst:.3g} %; Drucker-stable along "
             "the fitted compression",
             f"why: {why}",
             "energy: U = sum_i 2 mu_i / alpha_i^2 (l1b^alpha_i + l2b^alpha_i + l3b^alpha_i - 3) + (J - 1)^2 / D1 + (J - 1)^4 / D2, "
             "lkb = J^(-1/3) lk",
             f"small strain: mu0 = mu1 + mu2 = {mu0:.10g} Pa, K0 = 2 / D1 = {2 * inv_d[0]:.10g} Pa, i.e. E = {E0:.10g} Pa and the card's "
             f"nu = {nu:.10g} (the card's E = {card.youngs_modulus:.10g} Pa, {own}); D2 = {OGDEN_D2_FACTOR:g} D1: negligible, written "
             "because CalculiX replaces a zero D2 by a stiff default",
             f"range of validity: homogeneous uniaxial compression from 0 to {100 * e[-1]:.4g} % nominal strain (the fitted protocol of "
             f"{spec.scenario!r}); outside it the law is extrapolated",
             f"fitted by least squares of the relative nominal stress to {own} at the card's values at {e.size} protocol strains "
             f"({100 * e[0]:.3g} to {100 * e[-1]:.3g} %), solved in difftissue: residual {fmt(err)}",
             f"Drucker-stable (d tau : d eps > 0) along the fitted compression (81 states to {100 * e[-1]:.4g} %); "
             + _ogden_stability_note(mu, alpha, nu, float(e[-1]))]
    params = {k: dict(v) for k, v in card.parameters.items()}
    params["youngs_modulus"].update(value=E0, recalibrated_from=card.youngs_modulus, standard_error=None)
    if "cubic_coefficient" in params:
        params["cubic_coefficient"].update(value=0.0, recalibrated_from=card.cubic_coefficient, standard_error=None)
    hyper = {"law": "ogden", "keyword": keyword, "mu": mu.tolist(), "alpha": alpha.tolist(), "d": d.tolist(),
             "units": {"mu": "Pa", "alpha": "1", "d": "1/Pa"}, "nominal_strain_range": [0.0, float(e[-1])],
             "strains": e.tolist(), "stress_card_model": ref.tolist(),
             "stress_law": (ref * (1.0 + err)).tolist(), "residuals": np.asarray(err).tolist()}
    prov = dict(card.provenance or {})
    prov["recalibration"] = {"from_model": own, "to_model": "ogden", "law": "ogden", "scenario": spec.scenario,
                             "load_fractions": fr, "hyperelastic": hyper, "notes": notes}
    energy = ("Abaqus / CalculiX two-term Ogden (*HYPERELASTIC, OGDEN, N=2): U = sum_i 2 mu_i / alpha_i^2 (l1b^alpha_i + "
              "l2b^alpha_i + l3b^alpha_i - 3) + sum_i (J - 1)^(2 i) / D_i, coefficients in provenance.recalibration.hyperelastic")
    return MaterialCard(model="ogden", parameters=params, energy=energy, name=card.name, provenance=prov), None
