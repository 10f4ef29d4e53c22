"""Levenberg--Marquardt with Marquardt's scaling, as an optimistix solver.

optimistix's :class:`optimistix.LevenbergMarquardt` damps the Gauss--Newton step with
``lambda I``: the damping is not invariant to the scale of the parameters. A fit's
unconstrained parameters (``log E``, ``logit nu``, ...) differ in sensitivity by orders of
magnitude, so the weakly determined direction is damped step after step and the fit crawls
(19 steps on the sphere-indentation benchmark where Gauss--Newton needs 5).

Marquardt (1963) and Moré (1978) damp with ``lambda D^2`` instead, ``D`` the column norms of
the Jacobian (their running maximum over the steps, as MINPACK's ``lmder``): the step

    min_delta |J delta + r|^2 + lambda |D delta|^2

is then the same whatever units the parameters are in. This module is that descent
(:class:`ScaledDampedNewtonDescent`, on optimistix's public ``AbstractDescent``) and the
solver built from it with optimistix's trust region (:class:`ScaledLevenbergMarquardt`, on
difftissue's :class:`~difftissue.fit.gauss_newton.AbstractGaussNewtonFamily`, whose state
the fit engine reads).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .gauss_newton import AbstractGaussNewtonFamily

__all__ = ["ScaledDampedNewtonDescent", "ScaledLevenbergMarquardt", "INITIAL_DAMPING"]

#: ``lambda`` of the first step relative to the scaled diagonal ``D^2`` (Nielsen's ``tau``,
#: Madsen, Nielsen & Tingleff 2004 use 1e-6..1e-3): the first step is nearly Gauss--Newton.
#: The trust region (:class:`optimistix.ClassicalTrustRegion`) then sets
#: ``lambda = INITIAL_DAMPING / step_size``.
INITIAL_DAMPING = 1e-3


class _ScaledDampedState(eqx.Module):
    f_info: optx.FunctionInfo.ResidualJac
    jacobian: jax.Array  # (n, p) at the current point
    scale: jax.Array  # (p,) Marquardt's D: running maximum of the Jacobian's column norms


def _zeros_like_struct(tree):
    return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype) if isinstance(s, jax.ShapeDtypeStruct) else s, tree)


class ScaledDampedNewtonDescent(optx.AbstractDescent):
    """The damped Gauss--Newton step with Marquardt's scaling (for a flat parameter vector).

    ``step(step_size)`` solves ``[J; sqrt(lambda) D] delta = -[r; 0]`` by QR with
    ``lambda = initial_damping / step_size`` and ``D`` the running maximum of ``J``'s column
    norms (a column that was never sensitive gets 1). The residual Jacobian is materialised
    once per accepted point (``p`` columns).

    Attributes:
        initial_damping: ``lambda`` at step size 1, relative to ``D^2``.
    """

    initial_damping: float = INITIAL_DAMPING

    def init(self, y, f_info_struct):
        if not (eqx.is_array(y) and y.ndim == 1):
            raise ValueError("ScaledDampedNewtonDescent needs a flat parameter vector y of shape (p,)")
        n = jax.tree_util.tree_leaves(f_info_struct.residual)[0].shape[0]
        p = y.shape[0]
        return _ScaledDampedState(_zeros_like_struct(f_info_struct), jnp.zeros((n, p), y.dtype), jnp.zeros((p,), y.dtype))

    def query(self, y, f_info, state):
        del y
        J = f_info.jac.as_matrix()
        columns = jnp.sqrt(jnp.sum(J * J, axis=0))
        return _ScaledDampedState(f_info, J, jnp.maximum(state.scale, columns))

    def step(self, step_size, state):
        J, D = state.jacobian, state.scale
        D = jnp.where(D > 0, D, 1.0)
        tiny = jnp.finfo(J.dtype).eps
        positive = step_size > tiny
        damping = jnp.where(positive, self.initial_damping / jnp.where(positive, step_size, 1.0), 1.0 / tiny)
        A = jnp.concatenate([J, jnp.sqrt(damping) * jnp.diag(D)], axis=0)
        b = jnp.concatenate([state.f_info.residual, jnp.zeros_like(D)])
        solution = lx.linear_solve(lx.MatrixLinearOperator(A), b, lx.QR(), throw=False)
        return -solution.value, optx.RESULTS.promote(solution.result)


class ScaledLevenbergMarquardt(AbstractGaussNewtonFamily):
    """Levenberg--Marquardt with Marquardt's scaling (see the module docstring): the
    Gauss--Newton machinery of :class:`~difftissue.fit.gauss_newton.AbstractGaussNewtonFamily`
    (optimistix's algorithm, with difftissue's state), optimistix's classical trust region and
    the Cauchy termination, with the :class:`ScaledDampedNewtonDescent` step.

    Attributes:
        rtol, atol: termination tolerances (as :class:`optimistix.LevenbergMarquardt`).
        norm: the norm of the termination test.
        descent: the scaled damped step.
        search: the trust region that sets ``lambda``.
    """

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: ScaledDampedNewtonDescent = ScaledDampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
