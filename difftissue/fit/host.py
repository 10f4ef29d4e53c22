"""The Levenberg--Marquardt step on the host (NumPy), for fits whose scenarios all solve on
the host.

A scenario that solves on the host (``scenario.solves_on_host``, e.g. a small compression
specimen wrapped by :class:`~difftissue.config.SeparatelyCompiled`) gives its prediction and
its tangents from NumPy (``scenario.predict_and_tangents_on_host(material, tangents)``). The
compiled fit engine (:mod:`difftissue.fit.engine`) would still trace and compile its step
(optimistix's machinery around a :func:`jax.pure_callback`) and its final evaluation: about
1.3 s of CPU for a fit whose arithmetic takes milliseconds. :class:`HostEngine` is the same
step in NumPy, with the interface of :class:`~difftissue.fit.engine.Engine` that
:func:`~difftissue.fit.fit` uses:

- the iteration of :class:`~difftissue.fit.gauss_newton.AbstractGaussNewtonFamily` with
  :class:`~difftissue.fit.marquardt.ScaledLevenbergMarquardt`: evaluate the residual and the
  Jacobian at the trial point; optimistix's classical trust region accepts or rejects it
  (ratio of the actual to the predicted reduction, cut-offs 0.01 / 0.99, step size times 0.25
  or 3.5); at an accepted point Marquardt's scale (running maximum of the Jacobian's column
  norms) and the Cauchy termination test; the next trial step from
  ``[J; sqrt(lambda) D] delta = -[r; 0]`` by QR, ``lambda = INITIAL_DAMPING / step size``;
- the engine's own stopping rules (:func:`~difftissue.fit.engine._stationary`, the rejected
  statistically small step, the precision floor), with the same formulas;
- the final evaluation from the state (the Jacobian taken to the physical values).

It is used by :func:`~difftissue.fit.fit` for ``method="levenberg_marquardt"``, ``loss="linear"``,
``jac="fwd"``, float64 starts, when every scenario solves on the host (:func:`host_capable`);
:data:`HOST_STEPS` ``= False`` goes back to the compiled engine. The iterates agree with the
compiled engine's to round-off (tests/test_fit_host.py: fitted values to 1e-10).
"""

from __future__ import annotations

import lineax as lx
import numpy as np
import optimistix as optx

from .._enumerations import result_code, result_message
from ..errors import FitError
from .engine import KINK_NEIGHBOURHOOD, STATIONARY_STEP
from .marquardt import INITIAL_DAMPING
from .problem import FitProblem

__all__ = ["HOST_STEPS", "HostEngine", "host_capable"]

#: Run the Levenberg--Marquardt steps on the host where every scenario solves there
#: (:func:`host_capable`). False: always the compiled engine.
HOST_STEPS = True

# optimistix.ClassicalTrustRegion's defaults (what ScaledLevenbergMarquardt uses)
_LOW_CUTOFF, _HIGH_CUTOFF, _LOW_CONSTANT, _HIGH_CONSTANT = 0.01, 0.99, 0.25, 3.5


def host_capable(problem: FitProblem, method: str, loss: str, jac: str, dtype) -> bool:
    """Whether :class:`HostEngine` runs this fit: :data:`HOST_STEPS`, Levenberg--Marquardt
    with the linear loss and forward Jacobians on float64 starts, and every scenario solving
    on the host (``solves_on_host`` and ``predict_and_tangents_on_host``), with no scenario
    parameters fitted (their tangents are the compiled engine's)."""
    return (HOST_STEPS and method == "levenberg_marquardt" and loss == "linear" and jac == "fwd"
            and np.dtype(dtype) == np.float64
            and not problem.has_scenario_parameters
            and all(getattr(sc, "solves_on_host", False) is True and callable(getattr(sc, "predict_and_tangents_on_host", None))
                    for sc in problem.scenarios))


def _max_norm(x) -> float:
    return float(np.max(np.abs(x))) if np.size(x) else 0.0


def _cauchy_small(diff, value, rtol, atol) -> bool:
    """``max |diff| / (atol + rtol |value|) < 1`` (optimistix's Cauchy criterion, one half)."""
    return bool(_max_norm(np.abs(diff) / (atol + rtol * np.abs(value))) < 1)


def _statistically_small(J, r, delta, bound) -> bool:
    """:func:`difftissue.fit.engine._statistically_small` in NumPy."""
    n, p = J.shape
    if n <= p:
        return False
    s2 = np.sum(r * r) / (n - p)
    moved = np.sum((J @ delta) ** 2)
    return bool(np.all(np.isfinite(J)) and np.all(np.isfinite(r)) and s2 > 0 and moved <= bound**2 * s2)


def _lstsq(J, r):
    """The least-squares solution of ``J delta = r`` (NaN where ``J`` or ``r`` is not finite:
    every test that uses it is then False, as in the compiled engine)."""
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        return np.full(J.shape[1], np.nan)
    try:
        return np.linalg.lstsq(J, r, rcond=None)[0]
    except np.linalg.LinAlgError:  # LAPACK's SVD did not converge
        return np.full(J.shape[1], np.nan)


def _stationary(J, r, u, rtol, atol, bound) -> bool:
    """:func:`difftissue.fit.engine._stationary` in NumPy."""
    finite = bool(np.all(np.isfinite(J)) and np.all(np.isfinite(r)))
    delta = _lstsq(J, r)
    small = bool(np.all(np.abs(delta) < atol + rtol * np.abs(u)))
    return finite and (small or _statistically_small(J, r, delta, bound))


def _qr_least_squares(A, b):
    """The least-squares solution of ``A x = b`` (``A`` tall, full column rank) by Householder
    QR, as lineax's ``QR``; NaN where ``A`` is not finite."""
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return np.full(A.shape[1], np.nan)
    Q, R = np.linalg.qr(A)
    return _back_substitute(R, Q.T @ b)


def _back_substitute(R, y):
    """``R^{-1} y`` for upper-triangular ``R`` by back substitution (inf / NaN where a
    diagonal entry is 0, as a triangular solve gives)."""
    p = R.shape[0]
    x = np.zeros(p)
    with np.errstate(all="ignore"):
        for i in range(p - 1, -1, -1):
            x[i] = (y[i] - R[i, i + 1:] @ x[i + 1:]) / R[i, i]
    return x


class HostEngine:
    """The Levenberg--Marquardt engine on the host (see the module docstring): the interface
    of :class:`~difftissue.fit.engine.Engine` that :func:`~difftissue.fit.fit` uses
    (``init``, ``make_step``, ``make_evaluate``, ``make_final``, ``status_message``,
    ``traces``), with NumPy arrays for the starts and the state.

    Args:
        problem: the fit problem (every scenario solving on the host: :func:`host_capable`).
        rtol, atol: the stopping tolerances (as the compiled engine).
    """

    method = "levenberg_marquardt"

    def __init__(self, problem: FitProblem, *, rtol: float, atol: float):
        self.problem = problem
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.traces = 0  # nothing is traced or compiled

    # ------------------------------------------------------------------ the model
    def _transforms(self):
        return self.problem.parameterization.transforms

    def values(self, u) -> np.ndarray:
        """The physical values of the fitted fields at ``u`` (p,)."""
        return np.array([float(t.forward(float(x))) for t, x in zip(self._transforms(), u)])

    def _evaluate_tangents(self, problem: FitProblem, material, tangent_diagonal):
        """``(r (n,), J (n, p), predictions)`` at ``material``: the scaled residuals and their
        derivatives along the tangents ``tangent_diagonal[k] e_k`` of the fitted fields (NaN
        where an evaluation fails)."""
        fields = problem.fields
        p = len(fields)
        tangents = {f: np.where(np.arange(p) == k, tangent_diagonal[k], 0.0) for k, f in enumerate(fields)}
        rs, Js, preds = [], [], []
        for sc, obs, sig in zip(problem.scenarios, problem._observed, problem._sigma):
            y, JT = sc.predict_and_tangents_on_host(material, tangents)
            y = np.asarray(y, dtype=float)
            JT = np.asarray(JT, dtype=float).reshape(p, -1)
            if y.shape != obs.shape:
                raise FitError(f"scenario {sc.name!r}: predict returned shape {y.shape}, observed has {obs.shape}")
            obs, sig = np.asarray(obs, dtype=float), np.asarray(sig, dtype=float)
            rs.append((y - obs) / sig)
            Js.append(JT.T / sig[:, None])
            preds.append(y)
        return np.concatenate(rs), np.concatenate(Js, axis=0), tuple(preds)

    def _residual_jacobian(self, problem: FitProblem, u):
        """Residuals, their Jacobian with respect to ``u`` and the predictions at ``u``."""
        dvdu = np.array([float(t.derivative(float(x))) for t, x in zip(self._transforms(), u)])
        return self._evaluate_tangents(problem, problem.material(np.asarray(u, dtype=float)), dvdu)

    # ------------------------------------------------------------------ engine interface
    def init(self, U, data) -> dict:
        """The batched state of the starts ``U`` (S, p): nothing evaluated yet."""
        U = np.asarray(U, dtype=float)
        S, p = U.shape
        n = self.problem.n_residuals
        return {
            "first_step": np.ones(S, dtype=bool),
            "y_eval": U.copy(),
            "step_size": np.ones(S),
            "residual": np.zeros((S, n)),
            "jacobian": np.zeros((S, n, p)),
            "predictions": np.zeros((S, n)),
            "scale": np.zeros((S, p)),
            "terminate": np.zeros(S, dtype=bool),
            "result": np.zeros(S, dtype=np.int32),
            "num_steps": np.zeros(S, dtype=np.int64),
            "num_accepted_steps": np.zeros(S, dtype=np.int64),
            "num_steps_since_acceptance": np.zeros(S, dtype=np.int64),
        }

    def _one(self, problem: FitProblem, u, st: dict):
        """One step of one start: ``(u_new, state_new, finished, status, loss)``; ``st`` holds
        this start's rows of the state."""
        rtol, atol = self.rtol, self.atol
        y_eval = st["y_eval"]
        r_eval, J_eval, preds_eval = self._residual_jacobian(problem, y_eval)
        r, J = st["residual"], st["jacobian"]
        first = bool(st["first_step"])
        # optimistix's ClassicalTrustRegion
        y_diff = y_eval - u
        predicted = 0.5 * (np.sum((J @ y_diff + r) ** 2) - np.sum(r * r))
        f_min_diff = 0.5 * np.sum(r_eval * r_eval) - 0.5 * np.sum(r * r)
        accept = bool(f_min_diff <= _LOW_CUTOFF * predicted) or first
        good = bool(f_min_diff < _HIGH_CUTOFF * predicted) and bool(predicted < 0) and not first
        mul = (_HIGH_CONSTANT if good else 1.0) if accept else _LOW_CONSTANT
        step_size = mul * st["step_size"]
        new = dict(st)
        new["num_steps"] = st["num_steps"] + 1
        new["num_accepted_steps"] = st["num_accepted_steps"] + (1 if accept else 0)
        new["num_steps_since_acceptance"] = 0 if accept else st["num_steps_since_acceptance"] + 1
        if accept:
            columns = np.sqrt(np.sum(J_eval * J_eval, axis=0))
            new["scale"] = np.maximum(st["scale"], columns)
            terminate = _cauchy_small(y_diff, y_eval, rtol, atol) and _cauchy_small(r_eval - r, r_eval, rtol, atol)
            u_new, r, J = y_eval, r_eval, J_eval
            new["residual"], new["jacobian"] = r_eval, J_eval
            new["predictions"] = np.concatenate(preds_eval) if preds_eval else np.zeros(0)
        else:
            terminate = False
            u_new = u
        # ScaledDampedNewtonDescent.step
        D = np.where(new["scale"] > 0, new["scale"], 1.0)
        tiny = np.finfo(float).eps
        damping = INITIAL_DAMPING / step_size if step_size > tiny else 1.0 / tiny
        A = np.concatenate([J, np.sqrt(damping) * np.diag(D)], axis=0)
        b = np.concatenate([r, np.zeros_like(D)])
        delta = _qr_least_squares(A, b)
        new["y_eval"] = u_new + (-delta)
        new["step_size"] = step_size
        new["first_step"] = False
        new["terminate"] = terminate
        # lineax's result of the solve: singular where the solution is not finite,
        # nonfinite_input where the right-hand side is not either
        status = 0 if np.all(np.isfinite(delta)) else _result_codes()["nonfinite_input" if not np.all(np.isfinite(b)) else "singular"]
        new["result"] = status
        loss = 0.5 * np.sum(r * r)
        # the compiled engine's stopping rules (engine.Engine.single_step)
        trial = new["y_eval"] - u_new
        rejected = new["num_steps_since_acceptance"] > 0
        near = _statistically_small(J, r, _lstsq(J, r), KINK_NEIGHBOURHOOD)
        negligible = rejected and (np.linalg.norm(trial) <= atol + rtol * np.linalg.norm(u_new)
                                   or (near and _statistically_small(J, r, trial, STATIONARY_STEP)))
        at_floor = np.linalg.norm(r) <= problem.precision_floor()
        finished = terminate or status != 0 or negligible or at_floor or _stationary(J, r, u_new, rtol, atol, STATIONARY_STEP)
        return u_new, new, bool(finished), status, loss

    def make_step(self):
        """``(U, dyn, done, data) -> (U, dyn, done, status, loss)`` over the starts, as the
        compiled engine's step (a stopped start keeps its state)."""

        def step(U, dyn, done, data):
            problem = self.problem.with_data(data)
            U = np.array(U, dtype=float)
            done = np.array(done, dtype=bool)
            dyn = {k: np.array(v) for k, v in dyn.items()}
            S = U.shape[0]
            status = np.zeros(S, dtype=np.int32)
            losses = np.zeros(S)
            for i in range(S):
                st = {k: v[i] for k, v in dyn.items()}
                u_new, new, finished, code, loss = self._one(problem, U[i], st)
                # A stopped start keeps its state; its loss is the step's, as the compiled
                # engine reports it (which computes the step of every start and discards it).
                losses[i] = loss
                if done[i]:
                    continue
                U[i] = u_new
                for k, v in new.items():
                    dyn[k][i] = v
                done[i] = finished
                status[i] = code
                losses[i] = loss
            return U, dyn, done, status, losses

        return step

    def make_evaluate(self):
        """``(U, data) -> (values (S, p), loss (S,), J (S, n, p), predictions)``: the
        Jacobian with respect to the physical values (as the compiled engine's evaluate)."""

        def evaluate(U, data):
            problem = self.problem.with_data(data)
            U = np.asarray(U, dtype=float)
            p = U.shape[1]
            values, losses, Js, preds = [], [], [], []
            for u in U:
                v = self.values(u)
                r, J, pr = self._evaluate_tangents(problem, problem.material_from_values(v), np.ones(p))
                values.append(v)
                losses.append(0.5 * np.sum(r * r))
                Js.append(J)
                preds.append(pr)
            return np.stack(values), np.array(losses), np.stack(Js), tuple(np.stack(c) for c in zip(*preds))

        return evaluate

    def make_final(self):
        """``(U, dyn, data) -> (values, loss, J, predictions, ok)`` from the state alone (as the
        compiled engine's final evaluation): the Jacobian at the accepted point taken to the
        physical values; ``ok`` False where no step was taken or a transform's derivative is
        0 (a parameter saturated at a bound)."""

        def final(U, dyn, data):
            U = np.asarray(U, dtype=float)
            transforms = self._transforms()
            values, losses, Js, ok = [], [], [], []
            for i, u in enumerate(U):
                dvdu = np.array([float(t.derivative(float(x))) for t, x in zip(transforms, u)])
                with np.errstate(all="ignore"):
                    Jv = dyn["jacobian"][i] / dvdu[None, :]
                r = dyn["residual"][i]
                values.append(self.values(u))
                losses.append(0.5 * np.sum(r * r))
                Js.append(Jv)
                ok.append(bool(dyn["num_steps"][i] > 0 and np.min(np.abs(dvdu)) > 1e-100 and np.all(np.isfinite(Jv))))
            preds = np.asarray(dyn["predictions"])
            splits = np.cumsum(self.problem.sizes)[:-1]
            return np.stack(values), np.array(losses), np.stack(Js), tuple(np.split(preds, splits, axis=1)), np.array(ok)

        return final

    def status_message(self, code: int) -> str:
        msg = result_message(optx.RESULTS, code).strip().split("\n")[0]
        return f"optimistix: {msg}"


def _result_codes() -> dict[str, int]:
    """The codes of optimistix's results of a failed linear solve (lineax's, promoted)."""
    return {k: int(result_code(optx.RESULTS.promote(getattr(lx.RESULTS, k)))) for k in ("singular", "nonfinite_input")}
