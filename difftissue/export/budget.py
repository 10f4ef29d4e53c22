"""Real-time exports (pypbd, XPBD JSON) that reproduce the fitted experiment at their written budget
(docs/export.md, "Budget recalibration").

A real-time engine runs a fixed budget: a time step ``dt``, ``substeps`` substeps and
``iterations`` constraint iterations, with the XPBD multipliers reset every (sub)step. The
state it settles to is not the energy minimum the card's values describe (docs/xpbd.md), and
the pypbd lattice (per-tet volume constraints) is not the card's model either. So the
exporter recalibrates the target's own stiffness on the fitted experiment:

1. the **reference**: the card's model (``springs_volume``, ``fem_linear``, ...) at the card's
   values on the written specimen, solved by difftissue's static solver at up to
   :data:`BUDGET_STATES` load fractions (the compression protocol's strains, the indentation's
   depth steps, or fractions of the block's displacement): what the fit matched;
2. the **target at its budget**: pypbd runs the written scene at its ``setting``
   (:func:`difftissue.export.pypbd_runner.run_pbd_budget`), or difftissue's XPBD solver runs the written
   stable neo-Hookean compliances with standard (multipliers reset) XPBD at the written
   ``dt`` / ``substeps`` / ``iterations`` (:func:`xpbd_budget_reactions`);
3. one stiffness factor ``c`` (all pypbd constraint stiffnesses, or ``mu`` and ``lambda'`` of the
   fitted regions: nu is kept) is found by secant steps in ``log c`` so that the least-squares
   projection of the target's reactions on the reference's is 1, and the residual per load
   state must be at most :data:`MAX_BUDGET_ERROR` (2 %).

When the response saturates (it hardly changes with ``c``: ``d log F / d log c`` below
:data:`MIN_SENSITIVITY`, the hard-constraint limit of too large a step for too few
iterations) or the budget does not come to rest, no factor exists: an
:class:`~difftissue.errors.ExportError` says so and suggests a budget that reaches 2 %
(searched over smaller substeps); when the user did not pin the budget (pypbd) the exporter
takes that budget and says so in the file. ``approximate=True`` writes the best factor found
with the measured signed error per state instead of refusing.

pypbd scenes also state the displacement field they come to rest in at the last load state
against the card's model (:func:`card_reference_field`, :func:`field_error`), and with a
``field_tolerance`` take it as a second target (docs/export.md, "Displacement column").
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..boundary import BoundaryConditions
from ..errors import ExportError
from ..materials import lame_parameters
from ..models import LATTICE_MODELS, MESH_MODELS, make_model
from ..scenarios import recover_lattice
from ..solvers.static import solve_static
from ..solvers.xpbd import StableNeoHookeanConstraints, XPBDSettings, xpbd_quasi_static_constraints
from .pypbd_runner import run_pbd_budget, scaled_scene

__all__ = ["MAX_BUDGET_ERROR", "BUDGET_STATES", "MIN_SENSITIVITY", "PBD_BUDGETS", "load_fractions", "card_reference_reactions",
           "card_reference_field", "field_error", "calibrate_factor", "pbd_budget_calibration", "xpbd_document_constraints", "xpbd_budget_reactions", "xpbd_budget_calibration",
           "LOAD_SET_CALIBRATION_API", "check_load_set_calibration", "xpbd_load_set_calibration"]


#: Largest |signed error| per load state a budget recalibration accepts.
MAX_BUDGET_ERROR = 0.02


#: Largest number of load states solved (evenly picked, the last included).
BUDGET_STATES = 4


#: Smallest ``d log F / d log c`` at which the budgeted response counts as not saturated.
MIN_SENSITIVITY = 0.2


def load_fractions(n: int, states: int = BUDGET_STATES) -> list[float]:
    """``min(states, n)`` fractions ``k / n`` evenly picked from ``1 .. n``, the last (1) included."""
    n = max(1, int(n))
    idx = np.unique(np.round(np.linspace(1, n, min(states, n))).astype(int))
    return [float(i) / n for i in idx]


def _card_solutions(card, mesh, fixed, prescribed, fractions, material, model, force):
    """``solve_static`` of the card's model (``model`` / ``material`` overrides) on ``mesh`` at each
    fraction of ``prescribed`` [m] on the ``fixed`` components, with the external nodal ``force``
    (N, 3) [N] (or none). Ramped in increments of at most 5 % of the height."""
    if model is not None and not isinstance(model, str):
        mdl = model  # an ElasticModel on ``mesh`` (e.g. pbd_reference_model: the scene's own energy)
    else:
        kind = (card.model if model is None else model).strip()
        if kind not in MESH_MODELS:
            raise ExportError(f"the card's model {kind!r} is no difftissue mesh model {list(MESH_MODELS)}: its fitted response "
                              "cannot be solved on the exported specimen, so the budget cannot be recalibrated")
        if kind in LATTICE_MODELS and getattr(mesh, "lattice", None) is None:
            mesh = recover_lattice(mesh)
        mdl = make_model(mesh, kind)
    mat = card.material() if material is None else material
    height = float(np.ptp(np.asarray(mesh.points)[:, 2])) or 1.0
    strain = float(np.max(np.abs(prescribed))) / height
    f_ext = np.zeros(np.shape(prescribed)) if force is None else np.asarray(force, dtype=float)
    for f in fractions:
        bc = BoundaryConditions(np.asarray(fixed, dtype=bool), jnp.asarray(np.asarray(prescribed) * float(f)), jnp.asarray(f_ext))
        yield solve_static(mdl, mat, bc, load_steps=max(1, int(math.ceil(abs(f) * strain / 0.05 - 1e-9))))


def card_reference_reactions(card, mesh, fixed: np.ndarray, prescribed: np.ndarray, observe: np.ndarray,
                             fractions: Sequence[float], material=None, model: str | None = None) -> np.ndarray:
    """Reactions [N] of the card's own model at the card's values (what the fit matched).

    ``model`` overrides ``card.model`` (a fitted specimen's record names the model the fit
    solved); ``material`` overrides ``card.material()`` (per-region materials of a specimen with
    fixed regions).

    ``mesh`` solved by :func:`~difftissue.solvers.static.solve_static` with the ``fixed``
    ``(N, 3)`` components held at ``fraction * prescribed`` [m]; the observable is the summed
    reaction (difftissue's convention, ``dU/dx`` on the held components) of the ``observe``
    ``(N, 3)`` components, projected on the direction of their summed prescribed displacement
    (positive when the specimen resists). Ramped in increments of at most 5 % of the height.
    """
    d = np.where(observe, prescribed, 0.0).sum(axis=0)
    if not np.any(d):
        raise ExportError("the observed nodes have no prescribed displacement: no reaction to calibrate on")
    direction = d / np.linalg.norm(d)
    out = []
    for sol in _card_solutions(card, mesh, fixed, prescribed, fractions, material, model, None):
        r = np.where(observe, np.asarray(sol.reaction), 0.0)
        out.append(float(np.sum(r @ direction)))
    return np.asarray(out)


def card_reference_field(card, mesh, fixed: np.ndarray, prescribed: np.ndarray, fraction: float = 1.0, *,
                         force: np.ndarray | None = None, material=None, model: str | None = None) -> np.ndarray:
    """Displacement field ``(N, 3)`` [m] of the card's own model at ``fraction * prescribed`` (the
    solve of :func:`card_reference_reactions`), with the external nodal ``force`` ``(N, 3)`` [N]
    (e.g. the particles' weights) when given: the field a budgeted run is compared with
    (:func:`field_error`). ``model`` may also be an elastic model built on ``mesh``."""
    sol = next(iter(_card_solutions(card, mesh, fixed, prescribed, [fraction], material, model, force)))
    return np.asarray(sol.displacement)


def field_error(u: np.ndarray, u_ref: np.ndarray) -> float:
    """``max |u - u_ref| / max |u_ref|`` over all nodes and components [-]: the displacement-field
    error of a run ``u`` [m] against a reference field ``u_ref`` [m] (the same node order)."""
    u, u_ref = np.asarray(u, dtype=float), np.asarray(u_ref, dtype=float)
    if u.shape != u_ref.shape:
        raise ExportError(f"field_error: fields of shapes {u.shape} and {u_ref.shape} (expected the same nodes)")
    scale = float(np.max(np.abs(u_ref)))
    if not scale > 0:
        raise ExportError("field_error: the reference field is zero (no displacement to compare with)")
    return float(np.max(np.abs(u - u_ref))) / scale


def _proj(run: np.ndarray, ref: np.ndarray) -> float:
    """Least-squares scale ``s`` with ``run ~ s ref``."""
    return float(np.vdot(run, ref) / np.vdot(ref, ref))


def calibrate_factor(response: Callable[[float], tuple[np.ndarray, bool]], reference: np.ndarray, *,
                     max_iter: int = 10, xtol: float = 1e-5) -> dict:
    """One stiffness factor ``c`` with ``proj(response(c), reference) = 1`` by secant steps in log c.

    ``response(c) -> (reactions, came_to_rest)``. Returns ``{"factor", "reactions", "errors"
    (signed, per state), "naive" (reactions at c = 1), "sensitivity" (d log F / d log c at the
    last step), "saturated", "rested", "evaluations"}``. Steps are capped at a factor 10.
    """
    ref = np.asarray(reference, dtype=float)
    lc, (R, rested) = 0.0, response(1.0)
    naive = np.asarray(R)
    hist = [(lc, math.log(max(_proj(R, ref), 1e-300)), R, rested)]
    sens, n = 1.0, 1
    if not rested or not np.all(np.isfinite(R)) or _proj(R, ref) <= 0:
        return {"factor": 1.0, "reactions": naive, "errors": naive / ref - 1.0, "naive": naive, "sensitivity": float("nan"),
                "saturated": False, "rested": False, "evaluations": 1}
    while n < max_iter:
        lc0, g0, R0, _ = hist[-1]
        if abs(g0) < 1e-7:
            break
        if len(hist) >= 2:
            lc1, g1 = hist[-2][0], hist[-2][1]
            sens = (g0 - g1) / (lc0 - lc1) if lc0 != lc1 else sens
        step = -g0 / sens if sens >= MIN_SENSITIVITY else -g0 / MIN_SENSITIVITY
        step = max(-math.log(10.0), min(math.log(10.0), step))
        if abs(step) < xtol:
            break
        lc = lc0 + step
        R, rested = response(math.exp(lc))
        n += 1
        if not rested or not np.all(np.isfinite(R)) or _proj(R, ref) <= 0:
            hist.append((lc, float("nan"), R, False))
            break
        hist.append((lc, math.log(_proj(R, ref)), R, True))
        if len(hist) >= 2:
            sens = (hist[-1][1] - hist[-2][1]) / (hist[-1][0] - hist[-2][0])
        if sens < MIN_SENSITIVITY and abs(hist[-1][1]) > math.log1p(MAX_BUDGET_ERROR):
            break
    if hist[-1][3] and len(ref) > 1 and n < max_iter + 1:
        # minimax polish: the factor that balances the largest and smallest per-state ratio (R ~ c r near the solution)
        q = np.asarray(hist[-1][2]) / ref
        lc = hist[-1][0] + math.log(2.0 / (float(q.max()) + float(q.min())))
        R, rested = response(math.exp(lc))
        n += 1
        if rested and np.all(np.isfinite(R)) and _proj(R, ref) > 0:
            hist.append((lc, math.log(_proj(R, ref)), R, True))
    good = [h for h in hist if h[3]]
    best = min(good, key=lambda h: float(np.max(np.abs(np.asarray(h[2]) / ref - 1.0))))
    errors = np.asarray(best[2]) / ref - 1.0
    return {"factor": math.exp(best[0]), "reactions": np.asarray(best[2]), "errors": errors, "naive": naive,
            "sensitivity": float(sens), "saturated": bool(sens < MIN_SENSITIVITY and np.max(np.abs(errors)) > MAX_BUDGET_ERROR),
            "rested": all(h[3] for h in hist), "evaluations": n}


def _fmt_errors(errors) -> str:
    return ", ".join(f"{100 * v:+.3g} %" for v in np.ravel(errors))


def _why(result: dict, where: str) -> str:
    if not result["rested"]:
        return f"{where} does not come to rest at this budget (diverges or creeps)"
    if result["saturated"]:
        return (f"{where} is saturated at this budget: the force hardly depends on the stiffness (d log F / d log c = "
                f"{result['sensitivity']:.3g}; the constraints act as hard constraints for this step and iteration count)")
    return (f"one stiffness factor cannot follow the fitted curve at this budget: best factor {result['factor']:.6g} leaves "
            f"{_fmt_errors(result['errors'])} per load state")


#: Budgets tried (in order) when the pypbd budget was not pinned, or to suggest one: (dt, substeps, iterations).
#: The last ones (32 and 64 substeps) bring pypbd's rest state within 1 % of the scene energy's minimum
#: on the measured specimens (docs/dev/pypbd-fields.md): what a field target needs.
PBD_BUDGETS = ((1.0 / 60.0, 1, 10), (1.0 / 60.0, 1, 20), (1.0 / 60.0, 2, 10), (1.0 / 60.0, 4, 10), (1.0 / 60.0, 8, 10),
               (1.0 / 60.0, 16, 10), (1.0 / 60.0, 32, 10), (1.0 / 60.0, 32, 20), (1.0 / 60.0, 64, 20))


def _budget_text(b) -> str:
    return f"dt = {b[0]:.6g} s, substeps = {b[1]}, iterations = {b[2]}"


def pbd_budget_calibration(scene: dict, reference: np.ndarray, fractions: Sequence[float], *, pinned: bool,
                           approximate: bool, reference_field: np.ndarray | None = None,
                           lattice_field_error: float | None = None, field_tolerance: float | None = None) -> tuple[dict, dict]:
    """Recalibrate the constraint stiffnesses of a pypbd ``scene`` (with a specimen) so that pypbd
    at the scene's budget reproduces ``reference`` (one reaction per load fraction, see
    :func:`card_reference_reactions`) within :data:`MAX_BUDGET_ERROR`, and measure the
    displacement field it comes to rest in.

    ``pinned``: the budget in ``scene["setting"]`` was given by the user (refuse, suggesting a
    budget, when it cannot be reached); otherwise :data:`PBD_BUDGETS` are tried in turn and the
    first that reaches the target is written.

    ``reference_field`` ``(N, 3)`` [m]: the card's model at the last load fraction
    (:func:`card_reference_field`); pypbd's rest state there is compared with it
    (:func:`field_error`, recorded as ``field_error``). ``lattice_field_error``: the same error of
    the scene energy's exact minimum (the converged limit of every budget), recorded as
    ``field_error_converged``: the part of the field error no budget removes.
    ``field_tolerance`` (needs both): the target for the field error too; a budget counts only
    when its reactions are within 2 % and its field error within ``field_tolerance``, and when the
    converged limit itself exceeds ``field_tolerance`` no budget is accepted (one that met it would
    do so by a load-dependent cancellation of the budget's bias against the lattice difference).
    Returns ``(scene, record)`` (the scaled scene with its setting, and the
    ``budget_calibration`` record). Needs pypbd.
    """
    try:
        import pypbd  # noqa: F401
    except ImportError:
        raise ExportError("recalibrating a pypbd scene for its budget runs pypbd, which is not installed (pip install pypbd); "
                          "pass approximate=True (--approximate) to write the card's converged-limit stiffnesses with the "
                          "budget error unmeasured") from None
    if field_tolerance is not None:
        field_tolerance = float(field_tolerance)
        if not (math.isfinite(field_tolerance) and field_tolerance > 0):
            raise ExportError(f"field_tolerance = {field_tolerance!r}: expected a fraction > 0 of the largest displacement (e.g. 0.02)")
        if reference_field is None or lattice_field_error is None:
            raise ExportError("field_tolerance needs the card's reference field and the converged limit's field error")
    requested_tolerance, field_msg = field_tolerance, ""
    if field_tolerance is not None and lattice_field_error > field_tolerance:
        field_msg = (f"the displacement field cannot be brought within {100 * field_tolerance:g} % of the card's model by any "
                     f"budget: even the scene energy's exact minimum (the converged limit of every budget) differs from it by "
                     f"{100 * lattice_field_error:.3g} % of the largest displacement (the pypbd lattice, XPBD distance constraints "
                     f"and a volume constraint per tet, is not the card's {scene.get('model', 'model')!r})")
        if not approximate:
            raise ExportError(f"pypbd: {field_msg}; export without a field target (the reactions are recalibrated and the field "
                              "error is stated in the file), or pass approximate=True (--approximate) to write it with the field "
                              "error stated")
        field_tolerance = None  # approximate: the reactions are recalibrated, the field target is reported as missed

    def attempt(sc):
        runs = {}

        def response(c):
            run = run_pbd_budget(scaled_scene(sc, c), fractions)
            runs[c] = run
            return run.reactions, bool(np.all(run.converged))
        res = calibrate_factor(response, reference)
        if reference_field is not None:
            run = runs.get(res["factor"]) or run_pbd_budget(scaled_scene(sc, res["factor"]), fractions)
            pts = np.asarray(sc["particles"]["positions"], dtype=float)
            x = run.positions[-1]
            res["field_error"] = field_error(x - pts, reference_field) if np.all(np.isfinite(x)) else float("inf")
        return res

    def force_ok(res):
        return res["rested"] and np.max(np.abs(res["errors"])) <= MAX_BUDGET_ERROR

    def ok(res):
        return force_ok(res) and (field_tolerance is None or res["field_error"] <= field_tolerance)

    st = scene["setting"]
    own = (float(st["dt"]), int(st["substeps"]), int(st["iterations"]))
    budgets = [own] + ([] if pinned else [b for b in PBD_BUDGETS if b != own])
    tried = []
    for b in budgets:
        res = attempt({**scene, "setting": {"dt": b[0], "substeps": b[1], "iterations": b[2]}})
        tried.append((b, res))
        if ok(res):
            break
    b, res = tried[-1]
    good = ok(res)
    if not good:
        def badness(t):
            r = t[1]
            if not r["rested"]:
                return (np.inf, np.inf)
            return (max(0.0, np.max(np.abs(r["errors"])) - MAX_BUDGET_ERROR), r.get("field_error", 0.0))
        best_b, best = min(tried, key=badness)
        suggestion = ""
        if pinned:
            for cand in PBD_BUDGETS:
                if cand == own:
                    continue
                r2 = attempt({**scene, "setting": {"dt": cand[0], "substeps": cand[1], "iterations": cand[2]}})
                if ok(r2):
                    suggestion = (f"; a budget that reaches it: {_budget_text(cand)} "
                                  f"(--dt {cand[0]:.6g} --substeps {cand[1]} --iterations {cand[2]})")
                    break
            else:
                suggestion = "; none of the budgets tried reaches it (" + ", ".join(f"{c}" for c in PBD_BUDGETS) + ")"
        if force_ok(res):
            why = (f"the displacement field at the last load state is {100 * res['field_error']:.3g} % off the card's model "
                   f"(largest |du| / largest |u|), over the field target {100 * field_tolerance:g} %")
        else:
            why = (_why(res, "the pypbd response on the fitted experiment")
                   + f"; it cannot reproduce the card's fitted reactions within {100 * MAX_BUDGET_ERROR:g} %")
        msg = f"pypbd at {_budget_text(b)}: " + why + suggestion
        if not approximate:
            raise ExportError(msg + "; pass approximate=True (--approximate) to write the best factor with its measured signed error")
        b, res = best_b, best
    sc = scaled_scene({**scene, "setting": {"dt": b[0], "substeps": b[1], "iterations": b[2]}}, res["factor"])
    chosen = "written as given" if b == own and pinned else ("the default budget" if b == own else
                                                            "CHOSEN by the exporter (the default did not reach the target)")
    record = {"target": "pypbd", "setting": sc["setting"], "budget": chosen, "factor": res["factor"],
              "load_fractions": list(map(float, fractions)), "reference_reactions": np.asarray(reference).tolist(),
              "reactions_before": np.asarray(res["naive"]).tolist(), "reactions_after": np.asarray(res["reactions"]).tolist(),
              "signed_error_before": (np.asarray(res["naive"]) / reference - 1.0).tolist(),
              "signed_error_after": np.asarray(res["errors"]).tolist(), "sensitivity": res["sensitivity"],
              "within_tolerance": bool(force_ok(res)), "tolerance": MAX_BUDGET_ERROR,  # the reactions
              "observable": "summed reaction on the moved particles along their displacement [N]: pypbd's rest state at the "
                            "budget (multipliers reset every step, velocities zeroed), force = the scene energy's gradient there",
              "budgets_tried": [list(t[0]) for t in tried]}
    if reference_field is not None:
        record.update({
            "field_error": float(res["field_error"]),
            "field_error_converged": None if lattice_field_error is None else float(lattice_field_error),
            "field_tolerance": requested_tolerance,
            "field_within_tolerance": None if requested_tolerance is None else bool(good and not field_msg),
            "field_observable": "max |u_pypbd - u_card| / max |u_card| over all particles and components at the last load "
                                "fraction (pypbd's rest state at the budget without gravity; u_card: the card's model solved "
                                "by difftissue's static solver); field_error_converged: the same for the scene energy's exact "
                                "minimum, which no budget goes below in general"})
        if field_msg:
            record["field_note"] = field_msg
    return sc, record


def xpbd_document_constraints(doc: dict, factor: float, fitted_tets: np.ndarray | None):
    """The stable neo-Hookean constraints of an XPBD document (``per_tet``: ``mu``, ``lambda'`` of the
    fitted tets times ``factor``, stress-free shapes of the pre-stretched tets) with its positions
    [m] and lumped masses [kg]: ``(constraints, positions (N, 3), masses (N,))``."""
    sp = doc["specimen"]
    pts = np.asarray(sp["positions"], dtype=float)
    tets = np.asarray(sp["tets"], dtype=np.int64)
    pt = doc["per_tet"]
    lam0 = np.asarray(pt.get("pre_stretch", np.ones(len(tets))), dtype=float)
    lam_y = np.asarray(pt["pre_stretch_y"], dtype=float) if "pre_stretch_y" in pt else lam0
    rest = pts[tets] * np.stack([1.0 / lam0, 1.0 / lam_y, np.ones_like(lam0)], axis=-1)[:, None, :]
    Ds = np.stack([rest[:, k + 1] - rest[:, 0] for k in range(3)], axis=-1)
    V0 = np.asarray(pt["rest_volume"], dtype=float)
    mu = np.asarray(pt["mu"], dtype=float) if "mu" in pt else 1.0 / (np.asarray(pt["deviatoric_compliance"]) * V0)
    ls = np.asarray(pt["lambda_shifted"], dtype=float) if "lambda_shifted" in pt else 1.0 / (np.asarray(pt["hydrostatic_compliance"]) * V0)
    scale = np.full(len(tets), float(factor)) if fitted_tets is None else np.where(fitted_tets, float(factor), 1.0)
    return StableNeoHookeanConstraints(tets, np.linalg.inv(Ds), V0, mu * scale, ls * scale), pts, np.asarray(sp["masses"], dtype=float)


def xpbd_budget_reactions(doc: dict, fixed: np.ndarray, prescribed: np.ndarray, observe: np.ndarray, fractions, *,
                          factor: float = 1.0, fitted_tets=None, dt: float | None = None, tol: float = 1e-8,
                          max_steps: int = 5_000) -> tuple[np.ndarray, bool]:
    """Reactions [N] of the XPBD document's stable neo-Hookean constraints (``mu``, ``lambda'`` of
    the fitted tets times ``factor``) run by difftissue's XPBD solver as a real-time engine
    with the written budget runs them: standard XPBD (multipliers reset every substep,
    Gauss-Seidel), the document's ``dt`` (or ``dt``), ``substeps`` and ``iterations``, fully
    damped frames until no node moves by more than ``tol`` times the specimen size
    (:func:`~difftissue.solvers.xpbd.xpbd_quasi_static_constraints`). The force is XPBD's own:
    the multipliers' impulses on the held components over ``h^2``. Same observable as
    :func:`card_reference_reactions`. Returns ``(reactions, all came to rest)``.
    """
    cons, pts, masses = xpbd_document_constraints(doc, factor, fitted_tets)
    st = doc["setting"]
    settings = XPBDSettings(dt=float(st["dt"] if dt is None else dt), substeps=int(st["substeps"]), iterations=int(st["iterations"]),
                            damping=float("inf"), warm_start=False)
    d = np.where(observe, prescribed, 0.0).sum(axis=0)
    direction = d / np.linalg.norm(d)
    held = np.asarray(fixed, dtype=bool)
    prescribed = np.asarray(prescribed, dtype=float)
    no_force = jnp.zeros(prescribed.shape)

    def one(displacement):
        bc = BoundaryConditions(held, displacement, no_force)
        sol = xpbd_quasi_static_constraints((cons,), jnp.asarray(pts), jnp.asarray(masses), bc, settings=settings, tol=tol,
                                            max_steps=max_steps, throw=False)
        return sol.reaction, sol.converged & jnp.all(jnp.isfinite(sol.displacement))

    # The load states run side by side (one vmapped loop: each state's frames stop counting once it rests, so
    # every state's rest state is the one it reaches alone), not one after the other.
    reactions, rested = jax.vmap(one)(jnp.asarray(np.stack([prescribed * float(f) for f in fractions])))
    r = np.where(observe[None], np.asarray(reactions), 0.0)
    return np.asarray([float(np.sum(ri @ direction)) for ri in r]), bool(np.all(np.asarray(rested)))


def xpbd_budget_calibration(doc: dict, reference: np.ndarray, fixed, prescribed, observe, fractions, *, approximate: bool,
                            fitted_tets=None) -> dict:
    """Recalibrate the XPBD document's compliances (``mu``, ``lambda'`` of the fitted tets times
    ``c``; nu kept) so that standard XPBD at the written budget reproduces ``reference`` within
    :data:`MAX_BUDGET_ERROR` (:func:`xpbd_budget_reactions`). The budget is the user's (the XPBD
    export needs ``--dt`` and ``--iterations``): when it cannot be reached the error suggests a
    smaller ``dt`` (or as many substeps) that does. Updates ``doc`` in place (``per_tet``,
    ``lame``, ``per_unit_volume``, ``validity``, ``budget_calibration``) and returns it."""
    def response(c, dt=None):
        return xpbd_budget_reactions(doc, fixed, prescribed, observe, fractions, factor=c, fitted_tets=fitted_tets, dt=dt)

    res = calibrate_factor(response, reference)
    st = doc["setting"]
    ok = res["rested"] and np.max(np.abs(res["errors"])) <= MAX_BUDGET_ERROR
    if not ok:
        msg = (f"XPBD at dt = {st['dt']:.6g} s, substeps = {st['substeps']}, iterations = {st['iterations']}: "
               + _why(res, "the XPBD response on the fitted experiment")
               + f"; the written compliances cannot reproduce the card's fitted reactions within {100 * MAX_BUDGET_ERROR:g} %")
        for k in range(1, 7):
            dt = float(st["dt"]) / 2**k
            r2 = calibrate_factor(lambda c, dt=dt: response(c, dt), reference)
            if r2["rested"] and np.max(np.abs(r2["errors"])) <= MAX_BUDGET_ERROR:
                msg += (f"; a budget that reaches it: dt = {dt:.6g} s with {st['iterations']} iterations and {st['substeps']} "
                        f"substep(s) (or keep dt and use {st['substeps'] * 2**k} substeps)")
                break
        else:
            msg += f"; no dt down to {float(st['dt']) / 2**6:.3g} s reaches it with {st['iterations']} iterations: use more iterations"
        if not approximate:
            raise ExportError(msg + "; pass approximate=True (--approximate) to write the best factor with its measured signed error")
        doc.setdefault("notes", []).append("APPROXIMATION: " + msg)
    c = res["factor"]
    pt = doc["per_tet"]
    V0 = np.asarray(pt["rest_volume"], dtype=float)
    scale = np.full(len(V0), c) if fitted_tets is None else np.where(fitted_tets, c, 1.0)
    h = float(st["dt"]) / int(st["substeps"])
    mu = (np.asarray(pt["mu"]) if "mu" in pt else 1.0 / (np.asarray(pt["deviatoric_compliance"]) * V0)) * scale
    ls = (np.asarray(pt["lambda_shifted"]) if "lambda_shifted" in pt else 1.0 / (np.asarray(pt["hydrostatic_compliance"]) * V0)) * scale
    pt.update({"mu": mu.tolist(), "lambda_shifted": ls.tolist(), "deviatoric_compliance": (1.0 / (mu * V0)).tolist(),
               "hydrostatic_compliance": (1.0 / (ls * V0)).tolist(), "deviatoric_alpha_tilde": (1.0 / (mu * V0) / h**2).tolist(),
               "hydrostatic_alpha_tilde": (1.0 / (ls * V0) / h**2).tolist()})
    card_lame = dict(doc["lame"])
    doc["lame"] = {k: v * c for k, v in card_lame.items()}
    doc["lame_card"] = card_lame
    doc["per_unit_volume"] = {**doc["per_unit_volume"], "deviatoric_compliance": 1.0 / doc["lame"]["mu"],
                              "hydrostatic_compliance": 1.0 / doc["lame"]["lambda_shifted"]}
    err = _fmt_errors(res["errors"])
    doc["validity"] = (f"RECALIBRATED for this budget (dt = {st['dt']:.6g} s, {st['substeps']} substep(s), {st['iterations']} "
                       f"iterations, standard XPBD: multipliers reset every substep, Gauss-Seidel): mu and lambda' = {c:.6g} x the "
                       f"card's; difftissue's XPBD solver running these compliances at this budget on the fitted experiment gives "
                       f"{err} against the card's model (before: {_fmt_errors(np.asarray(res['naive']) / reference - 1.0)}); "
                       "valid for this budget, mesh and loading only")
    doc["setting"]["multipliers"] = "reset every substep (standard XPBD); Gauss-Seidel iterations"
    doc["budget_calibration"] = {"target": "xpbd", "setting": dict(st), "factor": c, "load_fractions": list(map(float, fractions)),
                                 "reference_reactions": np.asarray(reference).tolist(),
                                 "reactions_before": np.asarray(res["naive"]).tolist(), "reactions_after": np.asarray(res["reactions"]).tolist(),
                                 "signed_error_before": (np.asarray(res["naive"]) / reference - 1.0).tolist(),
                                 "signed_error_after": np.asarray(res["errors"]).tolist(), "sensitivity": res["sensitivity"],
                                 "within_tolerance": bool(ok), "tolerance": MAX_BUDGET_ERROR,
                                 "observable": "summed reaction of the moved / reaction-set nodes along their prescribed displacement "
                                               "[N], XPBD's multiplier impulses / h^2, at the rest state of the budget"}
    return doc


# ============================================================================ load sets
#: What the export uses of a load-set calibration (:class:`difftissue.budget.LoadSetCalibration`, duck-typed:
#: the export layer knows nothing of the fit engine that computes it).
LOAD_SET_CALIBRATION_API = ("check", "card", "effective_youngs_modulus", "poisson_ratio", "validity", "setting", "model_kind",
                            "reference_kind", "mesh", "factors", "stiffness_nodes", "max_error")


def check_load_set_calibration(calibration, card, settings: XPBDSettings, model_kind: str, *, mesh, extrapolate: bool = False) -> None:
    """Check a load-set calibration the caller computed (the object returned by
    :func:`difftissue.budget.calibrate_for_load_set`) against what the export writes: ``card``
    (a :class:`~difftissue.export.card.MaterialCard`) with ``model_kind`` constraints at
    ``settings`` on ``mesh``.

    The calibration must be for the same XPBD setting (dt, substeps, iterations, method), the
    same model kind, the export's mesh (nodes, tets, cell size), the card's Poisson ratio and
    density, and the card's Young's modulus must lie in its stiffness range (the calibration's
    own ``check``; ``extrapolate``: a :class:`~difftissue.errors.BudgetExtrapolationWarning`
    instead of the refusal).

    Raises:
        ExportError: an object without the calibration's methods and attributes
            (:data:`LOAD_SET_CALIBRATION_API`), no mesh, another model kind, Poisson ratio or density.
        BudgetRangeError: another setting or mesh, or the card's modulus outside the stiffness range.
    """
    missing = [a for a in LOAD_SET_CALIBRATION_API if not hasattr(calibration, a)]
    if missing:
        raise ExportError(f"load_set must be the load-set calibration returned by difftissue.budget.calibrate_for_load_set(...) "
                          f"(computed by the caller at the export's budget, on its mesh); got a {type(calibration).__name__} "
                          f"without {', '.join(missing)}")
    if mesh is None:
        raise ExportError("a load-set calibration is valid on the mesh it was calibrated on: give the export that mesh "
                          "(mesh=..., or an indentation specimen on it); it is checked against the calibration's")
    if calibration.model_kind != model_kind:
        raise ExportError(f"the load-set calibration is for {calibration.model_kind!r} constraints; this file writes "
                          f"{model_kind!r} ones: calibrate_for_load_set(mesh, {model_kind!r}, ...) at the file's budget")
    cal_card = calibration.card()
    mat = card.material()
    for name, ours, theirs in (("Poisson ratio", float(mat.poisson_ratio), cal_card.get("true_poisson_ratio")),
                               ("density", float(mat.density), cal_card.get("density"))):
        if theirs is None or not math.isclose(ours, float(theirs), rel_tol=1e-9):
            raise ExportError(f"the load-set calibration was computed for a tissue of {name} {theirs!r}; the card's is {ours:.6g}: "
                              "calibrate with the card's material (calibrate_for_load_set(mesh, ..., card.material(), ...))")
    v = calibration.validity
    calibration.check(shape=v["shapes"][0], depth=v["depth_range"][0], youngs_modulus=float(mat.youngs_modulus),
                      settings=settings, mesh=mesh, extrapolate=extrapolate)


def xpbd_load_set_calibration(doc: dict, card, calibration, *, mesh, extrapolate: bool = False):
    """Write a load-set calibration the caller computed (``calibration``: the object returned by
    :func:`difftissue.budget.calibrate_for_load_set` with ``model_kind "stable_neo_hookean"`` at
    the document's budget, standard XPBD: multipliers reset every substep, Gauss-Seidel) into an
    XPBD document (``difftissue-xpbd/1``) in place, after :func:`check_load_set_calibration`
    (same setting, model kind, mesh, material; the card's ``E`` in its stiffness range):
    ``lame`` (and ``per_tet``, ``per_unit_volume``, ``gamma``) from the card's effective modulus
    ``E * f(E)`` at the card's ``E`` (and the calibration's Poisson ratio), ``lame_card`` (the
    card's own), ``validity`` and ``budget_calibration`` (``method "load set"``, the factor(s)
    and the calibration's ``card()``). Returns ``calibration``."""
    st = doc["setting"]
    settings = XPBDSettings(dt=float(st["dt"]), substeps=int(st["substeps"]), iterations=int(st["iterations"]),
                            method="gauss_seidel", damping=float("inf"), warm_start=False)
    check_load_set_calibration(calibration, card, settings, "stable_neo_hookean", mesh=mesh, extrapolate=extrapolate)
    cal = calibration
    E = float(card.material().youngs_modulus)
    E_eff, nu_eff = cal.effective_youngs_modulus(E), float(cal.poisson_ratio)
    lam, mu = (float(x) for x in lame_parameters(E_eff, nu_eff))
    lam_s = lam + mu
    h = float(st["dt"]) / int(st["substeps"])
    doc["lame_card"] = dict(doc["lame"])
    doc["lame"] = {"mu": mu, "lambda": lam, "lambda_shifted": lam_s}
    doc["gamma"] = 1.0 + mu / lam_s
    doc["per_unit_volume"] = {**doc["per_unit_volume"], "deviatoric_compliance": 1.0 / mu, "hydrostatic_compliance": 1.0 / lam_s}
    if "per_tet" in doc:
        V0 = np.asarray(doc["per_tet"]["rest_volume"], dtype=float)
        doc["per_tet"].update({"deviatoric_compliance": (1.0 / (mu * V0)).tolist(), "hydrostatic_compliance": (1.0 / (lam_s * V0)).tolist(),
                               "deviatoric_alpha_tilde": (1.0 / (mu * V0) / h**2).tolist(),
                               "hydrostatic_alpha_tilde": (1.0 / (lam_s * V0) / h**2).tolist()})
    v = cal.validity
    lo, hi = v["depth_range"]
    Elo, Ehi = v["youngs_modulus_range"]
    doc["validity"] = (f"CALIBRATED OVER A LOAD SET for this budget (dt = {float(st['dt']):.6g} s, {st['substeps']} substep(s), "
                       f"{st['iterations']} iterations, standard XPBD: multipliers reset every substep, Gauss-Seidel) on cells of "
                       f"{cal.mesh['cell_size']:.4g} m: E_eff = {E_eff:.6g} Pa ({E_eff / E:.6g} x the card's E), nu = {nu_eff:.6g}; "
                       f"shapes {', '.join(v['shapes'])}, depths {lo:.4g} ... {hi:.4g} m, tissue moduli {Elo:.4g} ... {Ehi:.4g} Pa; "
                       f"largest residual force error over the set {100 * cal.max_error:.3g} % against the {cal.reference_kind} "
                       "reference; valid for this budget, this cell size and these loads only (budget_calibration.card)")
    doc["setting"]["multipliers"] = "reset every substep (standard XPBD); Gauss-Seidel iterations"
    doc["budget_calibration"] = {"target": "xpbd", "method": "load set", "setting": dict(cal.setting), "factor": E_eff / E,
                                 "factors": list(cal.factors), "stiffness_nodes": list(cal.stiffness_nodes),
                                 "effective_youngs_modulus": E_eff, "poisson_ratio": nu_eff,
                                 "max_residual_error": cal.max_error, "reference_model": cal.reference_kind,
                                 "extrapolated": not (Elo * (1 - 1e-9) <= E <= Ehi * (1 + 1e-9)),
                                 "card": cal.card()}
    if cal.reference_kind != card.model:
        doc["notes"].append(f"the load-set calibration's reference is the {cal.reference_kind} model, not the card's {card.model}: "
                            f"the written compliances reproduce {cal.reference_kind} at the card's values, as the caller chose")
    if cal.max_error > MAX_BUDGET_ERROR:
        doc["notes"].append(f"the load-set card leaves up to {100 * cal.max_error:.3g} % on a load of its set (budget_calibration."
                            f"card.loads): one card for all its loads is a compromise, above the {100 * MAX_BUDGET_ERROR:g} % a "
                            "single-experiment recalibration accepts")
    return cal
