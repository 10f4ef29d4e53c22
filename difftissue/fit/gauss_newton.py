"""The Gauss--Newton family of least-squares solvers, with a state that is difftissue's own.

The fit engine (:mod:`difftissue.fit.engine`) needs, after every step, the residual and the
Jacobian at the accepted point (the loss, the stationarity test and the final evaluation:
no second compilation of the forward model), the predictions there (the ``aux``), the trial
point of the next step and whether the last trial was rejected. optimistix's own
Gauss--Newton solvers keep these in the fields of their state class, which is not part of
optimistix's public API. :class:`AbstractGaussNewtonFamily` is the same algorithm
(optimistix's ``AbstractGaussNewton``: evaluate at the trial point, let the search accept or
reject it, query the descent at an accepted point, Cauchy termination) written on
optimistix's public extension points only -- ``AbstractLeastSquaresSolver``,
``AbstractSearch``, ``AbstractDescent``, ``FunctionInfo.ResidualJac``, ``RESULTS`` -- with
its state, :class:`GaussNewtonState`, defined here: its fields are difftissue's API.

It takes the same operations in the same order as optimistix 0.1's ``AbstractGaussNewton``,
so a fit gives the same iterates to the last bit (tests/test_fit_gauss_newton.py compares
both on the same problems). :class:`GaussNewton` is optimistix's ``GaussNewton`` (Newton
descent, unit step); :class:`~difftissue.fit.marquardt.ScaledLevenbergMarquardt` is the
Marquardt-scaled Levenberg--Marquardt.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

__all__ = ["AbstractGaussNewtonFamily", "GaussNewtonState", "GaussNewton"]


class GaussNewtonState(eqx.Module):
    """The state of :class:`AbstractGaussNewtonFamily` between steps (difftissue's API).

    Attributes:
        first_step: True before the first step (nothing evaluated yet).
        y_eval: the trial point the next step evaluates.
        search_state: the search's state (step size / trust region).
        f_info: residual and Jacobian (a lineax operator) at the last ACCEPTED point
            (zeros before the first step).
        aux: the function's auxiliary output at the last accepted point (zeros before the
            first step).
        descent_state: the descent's state.
        terminate: whether the Cauchy test met the tolerances at the last accepted step.
        result: failure code of the search or the descent (``optx.RESULTS``).
        num_steps: steps taken (trial points evaluated).
        num_accepted_steps: trial points accepted.
        num_steps_since_acceptance: steps since the last accepted one (> 0: the last trial
            point was rejected).
    """

    first_step: jax.Array
    y_eval: Any
    search_state: Any
    f_info: optx.FunctionInfo.ResidualJac
    aux: Any
    descent_state: Any
    terminate: jax.Array
    result: optx.RESULTS
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    num_steps_since_acceptance: jax.Array


def _zeros_like(struct):
    """Zeros of the shapes and dtypes of the arrays / ``ShapeDtypeStruct`` leaves of
    ``struct``; other leaves (static parts) are kept."""
    return jax.tree_util.tree_map(
        lambda x: jnp.zeros(x.shape, x.dtype) if (eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)) else x,
        struct,
    )


def _tree_where(pred, true, false):
    return jax.tree_util.tree_map(lambda t, f: jnp.where(pred, t, f), true, false)


def _max_norm_ratio(norm, diff, value, rtol, atol) -> jax.Array:
    """``norm(|diff| / (atol + rtol |value|)) < 1`` (optimistix's Cauchy criterion, one half)."""
    scaled = jax.tree_util.tree_map(lambda d, v: jnp.abs(d) / (atol + rtol * jnp.abs(v)), diff, value)
    return norm(scaled) < 1


def cauchy_termination(rtol, atol, norm, y, y_diff, f, f_diff) -> jax.Array:
    """True when both the step ``y_diff`` and the change of the residuals ``f_diff`` are below
    ``atol + rtol |.|`` of ``y`` and ``f`` in ``norm`` (the test of optimistix's Gauss--Newton
    solvers)."""
    return _max_norm_ratio(norm, y_diff, y, rtol, atol) & _max_norm_ratio(norm, f_diff, f, rtol, atol)


class _Static(eqx.Module):
    """A non-array pytree carried through ``lax.cond`` as static metadata (compared by its
    flattened leaves)."""

    leaves: tuple = eqx.field(static=True)
    treedef: Any = eqx.field(static=True)

    @classmethod
    def wrap(cls, value):
        leaves, treedef = jax.tree_util.tree_flatten(value)
        return cls(tuple(leaves), treedef)

    @property
    def value(self):
        return jax.tree_util.tree_unflatten(self.treedef, list(self.leaves))


def _filter_cond(pred, true_fun, false_fun, *operands):
    """``lax.cond`` on pytrees with non-array leaves (equal in both branches)."""
    dynamic, static = eqx.partition(operands, eqx.is_array)

    def branch(fun):
        def run(dyn):
            out = fun(*eqx.combine(dyn, static))
            dyn_out, static_out = eqx.partition(out, eqx.is_array)
            return dyn_out, _Static.wrap(static_out)

        return run

    dyn_out, static_out = jax.lax.cond(pred, branch(true_fun), branch(false_fun), dynamic)
    return eqx.combine(dyn_out, static_out.value)


def _residual_jac(fn, y, args, tags, jac: str):
    """``(FunctionInfo.ResidualJac, aux)`` of ``fn`` at ``y``: the residual and its Jacobian,
    linearised (``jac="fwd"``: a :class:`lineax.FunctionLinearOperator`) or materialised by
    reverse mode (``jac="bwd"``: a :class:`lineax.PyTreeLinearOperator`)."""
    if jac == "fwd":
        f_eval, lin_fn, aux_eval = jax.linearize(lambda _y: fn(_y, args), y, has_aux=True)
        operator = lx.FunctionLinearOperator(lin_fn, jax.eval_shape(lambda: y), tags)
    elif jac == "bwd":

        def for_jacrev(_y):
            f_eval, aux_eval = fn(_y, args)
            return f_eval, (f_eval, aux_eval)

        jac_pytree, (f_eval, aux_eval) = jax.jacrev(for_jacrev, has_aux=True)(y)
        operator = lx.PyTreeLinearOperator(jac_pytree, jax.eval_shape(lambda: f_eval), tags)
    else:
        raise ValueError(f"jac must be 'fwd' or 'bwd', got {jac!r}")
    return optx.FunctionInfo.ResidualJac(f_eval, operator), aux_eval


class AbstractGaussNewtonFamily(optx.AbstractLeastSquaresSolver):
    """A Gauss--Newton-type least-squares solver: at each step the function (residual and
    Jacobian) is evaluated at the trial point ``y_eval``; the search accepts or rejects it
    and sets the step size; at an accepted point the descent is queried with the new
    residual and Jacobian; the next trial point is the accepted point plus the descent's step.

    Subclasses provide ``rtol``, ``atol`` (floats), ``norm`` (``PyTree -> Scalar``),
    ``descent`` (an :class:`optimistix.AbstractDescent` on ``FunctionInfo.ResidualJac``) and
    ``search`` (an :class:`optimistix.AbstractSearch`).

    Options: ``jac`` (``"fwd"``, default, or ``"bwd"``), as optimistix's Gauss--Newton solvers.
    The state is a :class:`GaussNewtonState`.
    """

    rtol: eqx.AbstractVar[float]
    atol: eqx.AbstractVar[float]
    norm: eqx.AbstractVar[Callable]
    descent: eqx.AbstractVar[optx.AbstractDescent]
    search: eqx.AbstractVar[optx.AbstractSearch]

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> GaussNewtonState:
        del f_struct
        jac = options.get("jac", "fwd")
        f_info_struct, _ = eqx.filter_eval_shape(_residual_jac, fn, y, args, tags, jac)
        return GaussNewtonState(
            first_step=jnp.array(True),
            y_eval=y,
            search_state=self.search.init(y, f_info_struct),
            f_info=_zeros_like(f_info_struct),
            aux=_zeros_like(aux_struct),
            descent_state=self.descent.init(y, f_info_struct),
            terminate=jnp.array(False),
            result=optx.RESULTS.successful,
            num_steps=jnp.array(0),
            num_accepted_steps=jnp.array(0),
            num_steps_since_acceptance=jnp.array(0),
        )

    def step(self, fn, y, args, options, state: GaussNewtonState, tags):
        jac = options.get("jac", "fwd")
        f_eval_info, aux_eval = _residual_jac(fn, state.y_eval, args, tags, jac)
        # The Jacobian operator's static part (for "fwd" a closure-converted jaxpr, compared
        # by identity) is the one the state already holds, so that both branches of the
        # accept/reject cond below have the same structure.
        operator = eqx.combine(eqx.filter(f_eval_info.jac, eqx.is_array), eqx.filter(state.f_info.jac, eqx.is_array, inverse=True))
        f_eval_info = eqx.tree_at(lambda f: f.jac, f_eval_info, operator)

        step_size, accept, search_result, search_state = self.search.step(
            state.first_step, y, state.y_eval, state.f_info, f_eval_info, state.search_state
        )
        num_steps = state.num_steps + 1
        num_accepted_steps = state.num_accepted_steps + jnp.where(accept, 1, 0)
        num_steps_since_acceptance = jnp.where(accept, 0, state.num_steps_since_acceptance + 1)

        def accepted(descent_state):
            descent_state = self.descent.query(state.y_eval, f_eval_info, descent_state)
            y_diff = jax.tree_util.tree_map(lambda a, b: a - b, state.y_eval, y)
            f_diff = jax.tree_util.tree_map(lambda a, b: a - b, f_eval_info.residual, state.f_info.residual)
            terminate = cauchy_termination(self.rtol, self.atol, self.norm, state.y_eval, y_diff, f_eval_info.residual, f_diff)
            return state.y_eval, f_eval_info, aux_eval, descent_state, terminate

        def rejected(descent_state):
            return y, state.f_info, state.aux, descent_state, jnp.array(False)

        y, f_info, aux, descent_state, terminate = _filter_cond(accept, accepted, rejected, state.descent_state)

        y_descent, descent_result = self.descent.step(step_size, descent_state)
        y_eval = jax.tree_util.tree_map(lambda a, b: a + b, y, y_descent)
        result = optx.RESULTS.where(search_result == optx.RESULTS.successful, descent_result, search_result)

        prev_aux = _tree_where(state.first_step, aux, state.aux)
        state = GaussNewtonState(
            first_step=jnp.array(False),
            y_eval=y_eval,
            search_state=search_state,
            f_info=f_info,
            aux=aux,
            descent_state=descent_state,
            terminate=terminate,
            result=result,
            num_steps=num_steps,
            num_accepted_steps=num_accepted_steps,
            num_steps_since_acceptance=num_steps_since_acceptance,
        )
        return y, state, prev_aux

    def terminate(self, fn, y, args, options, state: GaussNewtonState, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state: GaussNewtonState, tags, result):
        return y, aux, {}


class GaussNewton(AbstractGaussNewtonFamily):
    """Gauss--Newton: the Newton step ``-J^+ r`` (a least-squares solve, ``lineax``'s
    ``AutoLinearSolver(well_posed=None)``) with unit step size, as optimistix's
    :class:`optimistix.GaussNewton`.

    Attributes:
        rtol, atol: termination tolerances (Cauchy criterion on the step and the residuals).
        norm: the norm of the termination test.
        descent: the Newton descent.
        search: the unit learning rate.
    """

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: optx.NewtonDescent = optx.NewtonDescent(linear_solver=lx.AutoLinearSolver(well_posed=None))
    search: optx.LearningRate = optx.LearningRate(1.0)
