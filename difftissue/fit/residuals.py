"""Least squares of a residual function of named parameters through THE fit engine.

:func:`~difftissue.fit.fit` fits material fields to :class:`~difftissue.fit.Scenario` objects.
Some calibrations are least-squares problems of another shape: the effective material of a
budgeted XPBD setting (:func:`difftissue.budget.calibrate_for_budget`, residual: the budgeted
observable against a reference simulation), the seed 003 opening surrogate's ``alpha`` / ``c``
(:func:`difftissue.opening_surrogate.fit_surrogate`, parameters that are no material fields).
They state their residuals as a function of the PHYSICAL parameter values and run on the same
:class:`~difftissue.fit.engine.Engine`, step loop (:func:`~difftissue.fit.engine.run_steps`),
final evaluation and Gauss--Newton statistics
(:func:`~difftissue.fit.statistics.parameter_statistics`) as a material fit: one optimiser,
one covariance formula.

Units: the residuals are whatever the caller scales them to (dimensionless by convention:
``(prediction - target) / scale``); values, standard errors and covariance are in the
parameters' own units.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import FitError
from ..materials import Transform
from .engine import METHODS, Engine, LoopState, cached_engine, final_evaluation, run_steps, tolerances
from .statistics import parameter_statistics

__all__ = ["ResidualProblem", "LeastSquaresResult", "least_squares"]


class ResidualProblem:
    """A least-squares problem in named parameters, in the form the fit engine steps.

    Args:
        residual_fn: ``residual_fn(values, data) -> (residuals, predictions)``: ``values`` the
            ``(p,)`` physical parameter values, ``data`` the pytree of arrays given as ``data``;
            both outputs of shape ``(n,)`` (the predictions and residuals ride along as the
            solver's aux and come back in the result). Pure and differentiable in ``values`` (forward mode by
            default). A failed model evaluation should return non-finite residuals: the
            optimiser rejects such a trial point.
        fields: the parameter names, ``p`` of them.
        transforms: one :class:`~difftissue.materials.Transform` per field (unconstrained ``u``
            to the value: :class:`~difftissue.materials.Log`, ``ScaledLogit``, ``Identity``).
        n_residuals: ``n``.
        data: arrays passed to ``residual_fn`` as an argument (not compiled in), or None.
        key: a hashable naming the structure of ``residual_fn`` (what it computes, apart from
            ``data``); problems with equal keys, transforms and shapes share one compiled engine.
            None (default): keyed by the identity of ``residual_fn``.
    """

    def __init__(self, residual_fn: Callable, fields: Sequence[str], transforms: Sequence[Transform], n_residuals: int, *, data=None, key=None):
        fields = tuple(fields)
        transforms = tuple(transforms)
        if not callable(residual_fn):
            raise FitError("residual_fn must be a function residual_fn(values, data) -> (residuals, predictions)")
        if not fields or len(set(fields)) != len(fields):
            raise FitError(f"fields must be non-empty and unique, got {fields}")
        if len(transforms) != len(fields) or not all(isinstance(t, Transform) for t in transforms):
            raise FitError(f"need one Transform per field ({len(fields)}), got {transforms!r}")
        if not (isinstance(n_residuals, (int, np.integer)) and n_residuals >= 1):
            raise FitError(f"n_residuals must be an int >= 1, got {n_residuals!r}")
        self.residual_fn = residual_fn
        self.fields = fields
        self.transforms = transforms
        self.n_parameters = len(fields)
        self.n_residuals = int(n_residuals)
        self.sizes = (self.n_residuals, self.n_residuals)  # the aux: (predictions, residuals)
        self._data = {} if data is None else data
        self.key = key

    # -------------------------------------------------------------- what the engine calls
    def data(self):
        return self._data

    def with_data(self, data) -> "ResidualProblem":
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._data = data
        return new

    def precision_floor(self) -> jax.Array:
        """0: a residual function states no precision of its own (the engine's x tests and
        statistical stop end such fits; see :meth:`FitProblem.precision_floor`)."""
        return jnp.asarray(0.0)

    def structure_key(self) -> tuple:
        shapes = tuple((np.shape(a), np.dtype(a.dtype if hasattr(a, "dtype") else np.result_type(a)).str) for a in jax.tree_util.tree_leaves(self._data))
        own = ("key", self.key) if self.key is not None else ("function", id(self.residual_fn))
        return ("ResidualProblem", own, self.fields, self.transforms, self.n_residuals, jax.tree_util.tree_structure(self._data), shapes)

    def values(self, u) -> dict:
        """Physical values of the fields at unconstrained ``u``."""
        return {f: t.forward(u[i]) for i, (f, t) in enumerate(zip(self.fields, self.transforms))}

    def value_vector(self, u) -> jax.Array:
        vals = self.values(u)
        return jnp.stack([vals[f] for f in self.fields])

    def pack(self, values) -> jax.Array:
        """Unconstrained ``u`` of physical ``values`` (``(p,)``; strictly inside the bounds)."""
        return jnp.stack([jnp.asarray(t.inverse(values[i]), dtype=float) for i, t in enumerate(self.transforms)])

    def _checked(self, values):
        r, pred = self.residual_fn(values, self._data)
        r, pred = jnp.asarray(r), jnp.asarray(pred)
        if r.shape != (self.n_residuals,) or pred.shape != (self.n_residuals,):
            raise FitError(f"residual_fn returned shapes {r.shape} and {pred.shape}; expected ({self.n_residuals},) for both")
        return r, pred

    def residuals_and_predictions(self, u):
        r, pred = self._checked(self.value_vector(u))
        return r, (jnp.asarray(pred, dtype=r.dtype), r)

    def residuals(self, u) -> jax.Array:
        return self._checked(self.value_vector(u))[0]

    def loss(self, u) -> jax.Array:
        r = self.residuals(u)
        return 0.5 * jnp.sum(r * r)

    def evaluate_values(self, values, jac: str = "fwd"):
        """Loss, Jacobian ``(n, p)`` of the residuals w.r.t. the PHYSICAL values, predictions."""

        def res(v):
            r, pred = self._checked(v)
            return r, (r, pred)

        jac_fn = jax.jacfwd if jac == "fwd" else jax.jacrev
        J, (r, pred) = jac_fn(res, has_aux=True)(values)
        return 0.5 * jnp.sum(r * r), J, (jnp.asarray(pred, dtype=r.dtype), r)


@dataclasses.dataclass(frozen=True)
class LeastSquaresResult:
    """Result of :func:`least_squares`.

    Attributes:
        fields: parameter names.
        values: ``{field: value}`` at the optimum (the fields' units).
        unconstrained: ``(p,)`` ``u`` at the optimum.
        loss: ``0.5 * sum(residuals^2)`` [-].
        residuals, predictions: ``(n,)`` at the optimum.
        jacobian: ``(n, p)`` Jacobian of the residuals w.r.t. the physical values.
        covariance, correlation: ``(p, p)`` Gauss--Newton covariance ``s^2 (J^T J)^-1``
            (``(J^T J)^-1`` with ``absolute_sigma``) and correlation; NaN where undetermined.
        standard_errors: ``{field: sqrt(cov_ii)}`` (NaN when ``dof = 0`` without
            ``absolute_sigma``: no residual scatter to estimate ``s^2`` from; inf for a field
            the residuals do not depend on).
        residual_variance: ``s^2 = 2 loss / (n - p)``; dof: ``n - p``.
        condition_number: of ``J^T J`` in scaled parameters.
        converged: the engine's stopping test (step and residual change below rtol/atol) held.
        stopped: ``stop`` ended the loop.
        reason: why the loop ended.
        steps: engine steps taken (the first one evaluates the start).
        method: the optimiser.
    """

    fields: tuple
    values: dict
    unconstrained: np.ndarray
    loss: float
    residuals: np.ndarray
    predictions: np.ndarray
    jacobian: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    standard_errors: dict
    residual_variance: float
    dof: int
    condition_number: float
    converged: bool
    stopped: bool
    reason: str
    steps: int
    method: str


def least_squares(
    problem: ResidualProblem,
    initial,
    *,
    method: str = "levenberg_marquardt",
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    jac: str = "fwd",
    absolute_sigma: bool = False,
    stop: Callable[[float], bool] | None = None,
) -> LeastSquaresResult:
    """Minimise ``0.5 |r|^2`` of ``problem`` from the physical values ``initial`` (``(p,)``)
    with THE fit engine (:class:`~difftissue.fit.engine.Engine`: optimistix
    Levenberg--Marquardt / Gauss--Newton or optax, the compiled step, the step loop) and give
    the Gauss--Newton statistics of :func:`~difftissue.fit.statistics.parameter_statistics`.

    Args:
        problem: the :class:`ResidualProblem`.
        initial: starting physical values (strictly inside the transforms' bounds).
        method, max_steps, rtol, atol, jac, absolute_sigma: as for :func:`~difftissue.fit.fit`
            (``max_steps`` counts engine steps; the first evaluates the start).
        stop: ``stop(loss) -> bool`` called after every step with the loss at the current
            point; True ends the loop there (e.g. "relative error below a target").

    Raises:
        FitError: bad options, or a non-finite loss at the end.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}; choose one of {METHODS}")
    if jac not in ("fwd", "bwd"):
        raise FitError(f"jac must be 'fwd' or 'bwd', got {jac!r}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 1):
        raise FitError(f"max_steps must be an int >= 1, got {max_steps!r}")
    u0 = problem.pack(jnp.asarray(initial, dtype=float))
    U = u0[None, :]
    rtol, atol = tolerances(U.dtype, rtol, atol)
    engine: Engine = cached_engine(problem, method, rtol=rtol, atol=atol, learning_rate=0.05, jac=jac)
    data = problem.data()
    state = LoopState(U, engine.init(U, data), jnp.zeros(1, dtype=bool), np.zeros(1, dtype=np.int32))
    on_step = None if stop is None else (lambda st, losses: bool(stop(float(losses[0]))))
    stopped = run_steps(engine.make_step(), state, data, max_steps=max_steps, on_step=on_step)
    values, loss, J, preds = final_evaluation(engine.make_final(), engine.make_evaluate(), state.U, state.dyn, data)
    loss = float(np.asarray(loss)[0])
    if not math.isfinite(loss):
        raise FitError(f"least squares ended with a non-finite loss at {dict(zip(problem.fields, np.asarray(values)[0].tolist()))}")
    values = np.asarray(values)[0]
    J = np.asarray(J)[0]
    stats = parameter_statistics(J, values, problem.fields, loss=loss, absolute_sigma=absolute_sigma)
    status = int(state.status[0])
    converged = bool(np.asarray(state.done)[0]) and status == 0 and not stopped
    if stopped:
        reason = "stopped: target reached"
    elif converged:
        reason = "step and residual change below rtol/atol, the remaining or a rejected step below 1e-4 standard errors or rtol/atol, or residuals within the model's precision"
    elif status != 0:
        reason = f"failed: {engine.status_message(status)}"
    else:
        reason = f"max_steps ({max_steps}) reached"
    pred, res = (np.asarray(a)[0] for a in preds)
    return LeastSquaresResult(
        fields=problem.fields,
        values={f: float(values[i]) for i, f in enumerate(problem.fields)},
        unconstrained=np.asarray(state.U)[0],
        loss=loss,
        residuals=res,
        predictions=pred,
        jacobian=J,
        covariance=stats["covariance"],
        correlation=stats["correlation"],
        standard_errors={f: float(stats["standard_errors"][i]) for i, f in enumerate(problem.fields)},
        residual_variance=float(stats["residual_variance"]),
        dof=int(stats["dof"]),
        condition_number=float(stats["condition_number"]),
        converged=converged,
        stopped=bool(stopped),
        reason=reason,
        steps=int(state.step),
        method=method,
    )
