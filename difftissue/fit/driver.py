"""The driver of a fit: :func:`fit` (starts, checkpoints, progress, callback, the step loop) and
the :class:`FitResult` built from the final state (shared with :func:`~difftissue.fit.fit_batch`).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, FitError, FitQualityWarning, IdentifiabilityWarning
from ..materials import Material, MaterialParameterization
from .checkpoint import load_checkpoint, save_checkpoint
from .host import HostEngine, host_capable
from .engine import Engine, LoopState, METHODS, cached_engine, final_evaluation, progress_bar, run_steps, tolerances
from .problem import FitProblem
from .result import plot_layout, FitProgress, FitResult, ScenarioFit
from .statistics import assess_quality, effective_modulus, identifiability_diagnostics, parameter_statistics


# ============================================================================ fit
def initial_starts(parameterization, initial: Material, starts, seed: int, spread: float):
    """The unconstrained starts ``(S, p)``: NumPy where the materials are concrete (nothing
    dispatched to JAX), JAX arrays otherwise."""
    u0 = parameterization.pack(initial)
    xp = np if isinstance(u0, np.ndarray) else jnp
    if isinstance(starts, Material):
        starts = [starts]
    if isinstance(starts, (int, np.integer)) and not isinstance(starts, bool):
        if starts < 1:
            raise FitError(f"starts must be >= 1, got {starts}")
        if starts == 1:
            return u0[None, :]
        rng = np.random.default_rng(seed)
        extra = rng.normal(0.0, spread, size=(int(starts) - 1, u0.shape[0]))
        return xp.concatenate([u0[None, :], u0[None, :] + xp.asarray(extra, dtype=u0.dtype)])
    if isinstance(starts, Sequence) and starts and all(isinstance(m, Material) for m in starts):
        packed = [parameterization.pack(m) for m in starts]
        if all(isinstance(u, np.ndarray) for u in packed):
            return np.stack([np.asarray(u, dtype=u0.dtype) for u in packed])
        return jnp.stack([jnp.asarray(u, dtype=u0.dtype) for u in packed])
    raise FitError(f"starts must be an int >= 1 or a non-empty sequence of Material, got {starts!r}")


def fit(
    scenarios,
    parameterization: MaterialParameterization,
    initial: Material,
    *,
    method: str = "levenberg_marquardt",
    loss: str = "linear",
    f_scale: float = 1.0,
    starts: int | Sequence[Material] = 1,
    seed: int = 0,
    start_spread: float = 1.0,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    learning_rate: float = 0.05,
    jac: str = "fwd",
    absolute_sigma: bool = False,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 10,
    resume: bool = False,
    progress: bool = False,
    callback: Callable[[FitProgress], bool | None] | None = None,
    plausible: Mapping[str, Sequence[float]] | None = None,
    scenario_parameters: Mapping[str, Sequence[str] | Mapping[str, float]] | None = None,
) -> FitResult:
    """Fit the fields of ``parameterization`` to one or more scenarios (weighted least squares).

    Args:
        scenarios: a :class:`Scenario` or a sequence of them; a joint fit shares the parameters.
        parameterization: fitted fields and their bounded transforms.
        initial: starting material (SI); its non-fitted fields are kept fixed.
        method: ``"levenberg_marquardt"`` (default), ``"gauss_newton"`` (optimistix, on the
            residual vector), ``"adam"`` or ``"lbfgs"`` (optax, on the scalar loss).
        loss: ``"linear"``, ``"soft_l1"`` or ``"huber"``; robust losses use ``f_scale`` [-] (in
            units of sigma).
        starts: number of starts (the first is ``initial``; the others are drawn from
            ``N(u0, start_spread^2)`` in the unconstrained space with ``numpy`` generator ``seed``),
            or a sequence of starting materials. All starts run batched (``jax.vmap``) in one
            jitted step; the result reports the start with the lowest final loss.
        max_steps: total optimiser steps (a resumed fit counts the steps already taken).
        rtol, atol: stop a start when both the step in ``u`` and the change of the residuals
            (optimistix Cauchy criterion; for optax the loss) are below ``atol + rtol * |.|``.
            Default ``1e-8, 1e-10`` in float64 and ``1e-5, 1e-7`` in float32 (the dtype of ``u``).
        learning_rate: Adam step size in ``u`` (ignored by the other methods).
        jac: ``"fwd"`` or ``"bwd"``: forward- or reverse-mode Jacobian (use ``"bwd"`` for
            scenarios whose derivatives are ``custom_vjp`` only).
        absolute_sigma: covariance ``(J^T J)^-1`` (sigma is the true noise level) instead of the
            default ``s^2 (J^T J)^-1``, ``s^2 = SSE / (n - p)``.
        checkpoint: file (``.npz``) to save the unconstrained parameters of every start, the
            optimiser state, step count, loss history and a fingerprint of the problem every
            ``checkpoint_every`` steps, at the end and on interruption (written atomically:
            temporary file in the same directory, then ``os.replace``).
        resume: continue from ``checkpoint`` if it exists (else start afresh). The optimiser's
            internal state (Levenberg--Marquardt damping / trust region, Adam moments, L-BFGS
            memory) is restored, so a resumed fit takes the same steps as an uninterrupted one. A
            checkpoint of a different problem raises :class:`CheckpointMismatchError`; an
            existing checkpoint without ``resume`` raises :class:`CheckpointError`.
        progress: show a rich progress bar (on stderr) with the best loss.
        callback: called with a :class:`FitProgress` after every step; returning ``True``
            stops the fit (reason "stopped by callback"). An exception (e.g. KeyboardInterrupt)
            propagates after the checkpoint is written.
        plausible: ``{field: (lo, hi)}`` (SI) widening or narrowing :data:`PLAUSIBLE` (default
            E in [1 Pa, 1 GPa]) for the ``implausible_value`` quality gate.
        scenario_parameters: parameters of the scenarios fitted jointly with the material
            fields: ``{scenario name: ("contact_offset",)}`` (starting at the scenario's start
            value, 0 for a contact offset) or ``{scenario name: {"contact_offset": start [m]}}``.
            A scenario declares what it can fit in ``fittable_parameters()`` (the indentation
            scenarios: ``contact_offset`` [m], added to every depth). The result names them
            ``"<scenario>.<parameter>"`` after the material fields in ``fields``, ``values``,
            ``units``, ``standard_errors``, ``covariance`` and ``correlation``;
            ``result.material`` holds the material fields only. Random starts spread them by
            ``start_spread`` times their transform's scale; a sequence of starting materials
            starts them all at their start value. An unknown scenario or parameter raises
            :class:`~difftissue.errors.FitError`.

    Returns:
        A :class:`FitResult`. Identifiability problems are also emitted as
        :class:`~difftissue.errors.IdentifiabilityWarning`, quality flags (:func:`assess_quality`)
        as :class:`~difftissue.errors.FitQualityWarning`.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}; choose one of {METHODS}")
    if jac not in ("fwd", "bwd"):
        raise FitError(f"jac must be 'fwd' or 'bwd', got {jac!r}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise FitError(f"max_steps must be an int >= 0, got {max_steps!r}")
    if not (isinstance(checkpoint_every, (int, np.integer)) and checkpoint_every >= 1):
        raise FitError(f"checkpoint_every must be an int >= 1, got {checkpoint_every!r}")
    if resume and checkpoint is None:
        raise FitError("resume=True needs a checkpoint path")
    problem = FitProblem(scenarios, parameterization, initial, loss=loss, f_scale=f_scale, scenario_parameters=scenario_parameters)
    U = initial_starts(problem.parameterization, initial, starts, seed, start_spread)
    n_starts = int(U.shape[0])
    rtol, atol = tolerances(U.dtype, rtol, atol)
    fingerprint, components = problem.fingerprint(method, n_starts)

    if host_capable(problem, method, loss, jac, U.dtype):
        # every scenario solves on the host: the same Levenberg--Marquardt steps in NumPy,
        # nothing compiled (difftissue.fit.host)
        engine = HostEngine(problem, rtol=rtol, atol=atol)
        U = np.asarray(U)
        done0 = np.zeros(n_starts, dtype=bool)
    else:
        engine = cached_engine(problem, method, rtol=rtol, atol=atol, learning_rate=learning_rate, jac=jac)
        done0 = jnp.zeros(n_starts, dtype=bool)
    traces_before = engine.traces
    data = problem.data()
    state = LoopState(U, engine.init(U, data), done0, np.zeros(n_starts, dtype=np.int32))
    step_fn = engine.make_step()
    resumed_from = 0
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if ckpt is not None:
        if ckpt.exists() and ckpt.is_dir():
            raise CheckpointError(f"checkpoint {ckpt} is a directory; give a file path such as {ckpt / 'fit-checkpoint.npz'}")
        if not ckpt.parent.is_dir():
            raise CheckpointError(f"directory {ckpt.parent} of checkpoint {ckpt.name} does not exist; create it first")
        if ckpt.exists():
            if not resume:
                raise CheckpointError(f"checkpoint {ckpt} exists; pass resume=True to continue that fit, or delete it to start afresh")
            U, dyn, done, status, history, step = load_checkpoint(ckpt, fingerprint=fingerprint, components=components, dyn_template=state.dyn)
            state = LoopState(U, dyn, done, status, history, step)
            resumed_from = step
    # Values, loss, Jacobian and predictions of every start in ONE compiled program (kept with
    # the engine), used at the start (the initial losses) and at the end (covariance,
    # predictions): fewer compilations than separate loss / Jacobian / predict programs (each
    # one compiles the whole forward model).
    evaluate = engine.make_evaluate()  # compiled on its first call only
    final_from_state = engine.make_final()
    if not state.history and final_from_state is None:
        state.history.append(np.asarray(evaluate(state.U, data)[1]))
    # Optimistix: the first step evaluates the starts and accepts them (its loss is the initial
    # loss, recorded as history[0] by run_steps), so no separate program is compiled for the start.

    def save():
        if ckpt is not None and state.history:
            save_checkpoint(ckpt, U=state.U, dyn=state.dyn, done=state.done, status=state.status, history=np.stack(state.history), step=state.step,
                            fingerprint=fingerprint, components=components, method=method)

    bar = progress_bar(progress, max_steps)
    task = None

    def on_step(state: LoopState, losses: np.ndarray) -> bool | None:
        if bar is not None:
            bar.update(task, completed=state.step, loss=f"{np.nanmin(losses):.6g}", description="fitting")
        if ckpt is not None and state.step % checkpoint_every == 0:
            save()
        if callback is not None:
            vals = {k: np.asarray(v) for k, v in jax.vmap(problem.values)(state.U).items()}
            return callback(FitProgress(state.step, float(np.nanmin(losses)), losses, vals, np.asarray(state.done))) is True
        return None

    if bar is not None:
        bar.start()
        task = bar.add_task("compiling + first step", total=max_steps, completed=state.step,
                            loss=f"{np.nanmin(state.history[-1]):.6g}" if state.history else "-")
    try:
        stopped_by_callback = run_steps(step_fn, state, data, max_steps=max_steps, on_step=on_step)
    except BaseException:
        if state.step > resumed_from:  # nothing new to save before the first step (a rerun must not find a stale checkpoint)
            save()
        raise
    finally:
        if bar is not None:
            bar.stop()
    if state.history:
        save()

    all_values, final, all_J, all_preds = final_evaluation(final_from_state, evaluate, state.U, state.dyn, data)
    if not state.history:  # no step taken: the loss at the start is the final one
        state.history.append(np.asarray(final))
        save()
    stop_reason = "stopped by callback" if stopped_by_callback else f"max_steps ({max_steps}) reached"
    return build_result(
        problem, engine, state.U, all_values, final, all_J, all_preds, state.done, state.status, state.history, state.step,
        stop_reason=stop_reason, absolute_sigma=absolute_sigma, method=method, loss=loss, f_scale=f_scale,
        compilations=engine.traces - traces_before, resumed_from=resumed_from, stacklevel=3, plausible=plausible,
    )


def build_result(problem: FitProblem, engine: Engine, U, all_values, final, all_J, all_preds, done, status, history, step, *,
                stop_reason: str, absolute_sigma: bool, method: str, loss: str, f_scale: float, compilations: int,
                resumed_from: int = 0, warning_prefix: str = "", stacklevel: int = 2, plausible=None) -> FitResult:
    """The :class:`FitResult` of one problem from the final state of its starts: best start,
    covariance, identifiability diagnostics (emitted as warnings, prefixed by
    ``warning_prefix``) and per-scenario outputs. ``history`` is a list of ``(S,)`` loss rows."""
    fields = problem.fields
    U = U if isinstance(U, np.ndarray) else jnp.asarray(U)  # NumPy (the host engine): no JAX dispatch
    history = list(history)
    final = np.asarray(final)
    history[-1] = final
    finite = np.where(np.isfinite(final), final, np.inf)
    best = int(np.argmin(finite))
    if not np.isfinite(finite[best]):
        vals = np.asarray(all_values)
        shown = "; ".join(", ".join(f"{f} = {v:.6g}" for f, v in zip(fields, row)) for row in vals.reshape(len(vals), -1)[:4])
        initial = np.asarray(history[0], dtype=float) if len(history) > 1 else final
        if not np.any(np.isfinite(initial)):
            # Infeasible starts: the optimiser accepts its start unconditionally (there is no
            # accepted point to fall back to), so no step can be taken from a start whose
            # predictions are not finite. Say so, with the scenarios' own failure messages
            # (e.g. a static solve that did not converge there, SolverOptions(failure="nan")).
            why = [f"{getattr(sc, 'name', '?')}: {sc.failures[-1]}" for sc in problem.scenarios if getattr(sc, "failures", None)]
            raise FitError(f"{warning_prefix}every start is infeasible: the loss at the starting point is not finite (at {shown}), so the fit "
                           "could take no step. A scenario's prediction failed there (a static solve that did not converge gives NaN "
                           "with SolverOptions(failure='nan'); a value far outside the tissue range, e.g. youngs_modulus = 1e308, gives "
                           "non-finite predictions): start from another material, or check the transforms and the scenarios' predictions"
                           + (f". Last failure: {why[0]}" if why else ""))
        raise FitError(f"{warning_prefix}every start ended with a non-finite loss (at {shown}); check the initial material "
                       "(a value far outside the tissue range, e.g. youngs_modulus = 1e308, gives non-finite predictions), the transforms and the scenarios' predictions")
    done_np = np.asarray(done)
    status_np = np.asarray(status)
    start_converged = done_np & (status_np == 0)
    if start_converged[best]:
        reason = "step and residual change below rtol/atol, the remaining or a rejected step below 1e-4 standard errors or rtol/atol, or residuals within the model's precision"
    elif status_np[best] != 0:
        reason = f"failed: {engine.status_message(int(status_np[best]))}"
    else:
        reason = stop_reason
    u_best = U[best]
    material = problem.material(u_best)
    values_vec = np.asarray(all_values[best])
    J = np.asarray(all_J[best])
    stats = parameter_statistics(J, np.asarray(values_vec), problem.fields, loss=float(final[best]), absolute_sigma=absolute_sigma,
                                 floors=problem.scale_floors)
    diag = identifiability_diagnostics(stats, np.asarray(values_vec), problem.fields, floors=problem.scale_floors,
                                       units=problem.units)
    if not start_converged[best]:
        diag = [(f, f"{msg} (evaluated where the fit stopped without converging: {reason})") for f, msg in diag]
    for _, msg in diag:
        warnings.warn(warning_prefix + msg, IdentifiabilityWarning, stacklevel=stacklevel)

    # ------------------------------------------------------------ per-scenario outputs
    scen_fits = []
    predictions, residuals = {}, {}
    for sc, obs, sig, pred_all in zip(problem.scenarios, problem._observed, problem._sigma, all_preds):
        pred = np.asarray(pred_all[best], dtype=float)
        res = (pred - obs) / sig
        absc = getattr(sc, "abscissa", None)
        absc = np.arange(obs.size, dtype=float) if absc is None else np.asarray(absc, dtype=float)
        predictions[sc.name] = pred
        residuals[sc.name] = res
        scen_fits.append(ScenarioFit(sc.name, absc, obs, sig, pred, res, str(getattr(sc, "x_label", "index")), str(getattr(sc, "y_label", "observed")),
                                     plot_layout(sc)))
    start_vals = np.asarray(all_values)
    result = FitResult(
        material=material,
        fields=fields,
        values={f: float(values_vec[i]) for i, f in enumerate(fields)},
        units={f: problem.units.get(f, "") for f in fields},
        standard_errors={f: float(stats["standard_errors"][i]) for i, f in enumerate(fields)},
        covariance=stats["covariance"],
        correlation=stats["correlation"],
        jacobian=J,
        loss=float(final[best]),
        converged=bool(start_converged[best]),
        reason=reason,
        steps=int(step),
        best_start=best,
        start_losses=final,
        start_values=start_vals,
        start_converged=start_converged,
        loss_history=np.stack(history),
        predictions=predictions,
        residuals=residuals,
        scenarios=tuple(scen_fits),
        warnings=tuple(msg for _, msg in diag),
        unidentified=tuple(dict.fromkeys(f for f, _ in diag)),
        condition_number=float(stats["condition_number"]),
        residual_variance=float(stats["residual_variance"]),
        dof=int(stats["dof"]),
        absolute_sigma=bool(absolute_sigma),
        method=method,
        loss_function=loss,
        f_scale=float(f_scale),
        unconstrained=np.asarray(u_best),
        compilations=int(compilations),
        resumed_from=resumed_from,
    )
    result = dataclasses.replace(result, effective_modulus=effective_modulus(result, problem.scenarios))
    quality = assess_quality(result, problem.parameterization, plausible=plausible)
    for flag in quality.flags:
        warnings.warn(f"{warning_prefix}{flag.severity}: {flag.message}", FitQualityWarning, stacklevel=stacklevel)
    return dataclasses.replace(result, quality=quality)
