"""Static equilibrium of small models on the host: the Newton iteration of
:func:`~difftissue.solvers.static.solve_static` in NumPy, with the model's energy, gradient,
dense Hessian and mixed material derivative from ONE small compiled program.

For a model of a few nodes (the one-cube compression specimen: 8 nodes, 24 unknowns) the
arithmetic of a static solve takes microseconds, while tracing and compiling a protocol of such
solves into one XLA program (the Newton loop, its line search, the Dirichlet predictor and the
implicit-function-theorem tangents, inside a scan over the load steps) takes seconds. Here only
the model's derivatives are compiled (:func:`model_derivatives`, once per model structure and
batch size, shared by every model of the same structure and shapes); the iteration runs in
NumPy. It is the same algorithm as :func:`~difftissue.solvers.static.solve_static` with the
dense Cholesky solver (``linear_solver="dense"``, what ``"auto"`` picks at this size): the
Dirichlet predictor, Newton steps with Armijo backtracking on the energy (inadmissible where an
element inverts), the fallback to a scaled gradient step, and the same stopping rules; results
agree with it to round-off (tested to 1e-10 relative).

Derivatives with respect to the material come from the implicit function theorem, as in
:func:`~difftissue.solvers.static.solve_static`: one solve with the projected Hessian at the
equilibrium per tangent direction (:meth:`HostStaticSolver.tangents`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..errors import ModelError
from ..materials import Material
from ..models import CheckedMaterial, ElasticModel
from .static import _MESSAGES, StaticResult, _dense_hessian

__all__ = ["HOST_MAX_NODES", "HostStaticSolver", "HostSolution", "model_derivatives"]

#: Models with at most this many nodes may be solved on the host (:class:`HostStaticSolver`).
#: Above it the dense Hessian (``(3N)^2``) and the per-call cost of the compiled derivatives
#: make the compiled protocol the better choice.
HOST_MAX_NODES = 64

#: ``{structure key: compiled program}`` of :func:`model_derivatives`.
_PROGRAMS: dict = {}


def _derivatives(dynamic, static, material, x):
    model = eqx.combine(dynamic, static)

    def one(xc):
        e, g = jax.value_and_grad(model.energy)(xc, material)
        H = _dense_hessian(model, xc, material)
        dgdm = jax.jacfwd(lambda m: jax.grad(model.energy)(xc, m).reshape(-1))(material)
        return e, g.reshape(-1), H, dgdm, model.min_volume_ratio(xc)

    return jax.vmap(one)(x)


def _program(model: ElasticModel, material: CheckedMaterial, batch: int):
    """The compiled :func:`_derivatives` for ``model``'s structure and ``batch`` positions."""
    dynamic, static = eqx.partition(model, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    mleaves, mtree = jax.tree_util.tree_flatten(material)
    try:
        s_leaves, s_tree = jax.tree_util.tree_flatten(static)
        key = (s_tree, tuple(s_leaves), treedef, tuple((np.shape(v), np.result_type(v).str) for v in leaves), mtree,
               tuple(np.shape(v) for v in mleaves), int(batch), bool(jax.config.jax_enable_x64))
        hash(key)
    except TypeError:  # a static field that cannot be hashed: compiled for this model alone
        key = None
    hit = _PROGRAMS.get(key) if key is not None else None
    if hit is None:
        spec = lambda v: jax.ShapeDtypeStruct(np.shape(v), jnp.result_type(v))  # noqa: E731
        x = jax.ShapeDtypeStruct((int(batch), model.n_nodes, 3), jnp.float64)
        hit = jax.jit(_derivatives, static_argnums=1).lower(jax.tree_util.tree_map(spec, dynamic), static,
                                                           jax.tree_util.tree_map(spec, material), x).compile()
        if key is not None:
            _PROGRAMS[key] = hit
    return hit, dynamic


def model_derivatives(model: ElasticModel, material: CheckedMaterial, x):
    """The model's energy and its derivatives at a batch of node positions, from one compiled
    program per model structure and batch size (shared by models of the same structure and
    array shapes: the arrays are its arguments).

    Args:
        model: an :class:`~difftissue.models.ElasticModel`.
        material: ``model.checked(material)`` (concrete).
        x: ``(B, N, 3)`` node positions [m].

    Returns:
        NumPy arrays ``(energy (B,) [J], gradient (B, 3N) [N], Hessian (B, 3N, 3N) [N/m],
        dgrad_dmaterial, min_volume_ratio (B,))``; ``dgrad_dmaterial`` is a ``CheckedMaterial``
        whose fields are ``(B, 3N, n_regions)``: the derivative of the gradient with respect
        to each region's value of that field (None where the field is None).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (model.n_nodes, 3):
        raise ModelError(f"x must be (B, {model.n_nodes}, 3), got {x.shape}")
    program, dynamic = _program(model, material, x.shape[0])
    e, g, H, dgdm, mv = program(dynamic, material, x)
    return np.asarray(e), np.asarray(g), np.asarray(H), jax.tree_util.tree_map(np.asarray, dgdm), np.asarray(mv)


@dataclasses.dataclass
class HostSolution:
    """One static equilibrium from :meth:`HostStaticSolver.solve` (NumPy arrays).

    Attributes:
        displacement: ``(N, 3)`` [m].
        reaction: ``(N, 3)`` [N] on the prescribed components (zero elsewhere).
        result: a :class:`~difftissue.solvers.static.StaticResult` code (0 = successful).
        steps: Newton steps taken.
        residual_norm: 2-norm of the free-component residual [N].
        hessian: ``(3N, 3N)`` Hessian of the energy at the solution [N/m].
        dgrad_dmaterial: the mixed derivative at the solution (see :func:`model_derivatives`).
    """

    displacement: np.ndarray
    reaction: np.ndarray
    result: int
    steps: int
    residual_norm: float
    hessian: np.ndarray
    dgrad_dmaterial: Any

    @property
    def converged(self) -> bool:
        return self.result == StaticResult.successful

    @property
    def message(self) -> str:
        return _MESSAGES[self.result]


def _cholesky_solve(A, b):
    """``A^{-1} b`` by Cholesky; NaN where ``A`` is not positive definite (as lineax's
    Cholesky returns a non-finite solution there, which the Newton loop rejects)."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(A, lower=True, check_finite=False), b, check_finite=False)
    except (np.linalg.LinAlgError, ValueError):
        return np.full(np.shape(b), np.nan)


class HostStaticSolver:
    """Static equilibria of one small model with fixed prescribed DOFs, solved on the host.

    Args:
        model: an :class:`~difftissue.models.ElasticModel` with at most :data:`HOST_MAX_NODES` nodes.
        fixed: ``(N, 3)`` bool, the prescribed components (concrete).
    """

    def __init__(self, model: ElasticModel, fixed):
        if not isinstance(model, ElasticModel):
            raise ModelError(f"model must be an ElasticModel, got {type(model).__name__}")
        if model.n_nodes > HOST_MAX_NODES:
            raise ModelError(f"the host solver is for models of at most {HOST_MAX_NODES} nodes, this one has {model.n_nodes}")
        self.model = model
        self.fixed = np.asarray(fixed, dtype=bool).reshape(model.n_nodes, 3)
        self.P = (~self.fixed).astype(float).reshape(-1)
        self.rest = np.asarray(model.rest_points, dtype=float)

    def checked(self, material: Material) -> CheckedMaterial:
        """``material`` range-checked by the model (raises for values outside its range)."""
        return self.model.checked(material)

    def _eval(self, material, u):
        e, g, H, dgdm, mv = model_derivatives(self.model, material, (self.rest + u)[None])
        return e[0], g[0], H[0], jax.tree_util.tree_map(lambda a: a[0], dgdm), mv[0]

    def solve(self, material: CheckedMaterial, displacement, u_init, *, force=None, rtol: float = 1e-10, atol: float = 0.0,
              xtol: float = 1e-8, max_steps: int = 50, max_tries: int = 40, c: float = 1e-4) -> HostSolution:
        """The equilibrium under the prescribed ``displacement`` ``(N, 3)`` [m] (its free
        components ignored) and nodal ``force`` ``(N, 3)`` [N] (default none), from the
        starting guess ``u_init`` ``(N, 3)``; options as for
        :func:`~difftissue.solvers.static.solve_static`. A failed solve is reported in
        ``result``, never raised."""
        P = self.P
        n3 = P.size
        f = np.zeros(n3) if force is None else np.asarray(force, dtype=float).reshape(-1)
        disp = np.asarray(displacement, dtype=float).reshape(-1)
        u_init = np.asarray(u_init, dtype=float).reshape(-1)
        fixed_part = (1.0 - P) * disp
        cache: dict[bytes, tuple] = {}

        def ev(u):
            k = u.tobytes()
            if k not in cache:
                cache.clear() if len(cache) > 8 else None
                e, g, H, dgdm, mv = self._eval(material, u.reshape(-1, 3))
                cache[k] = (e - f @ u, g - f, H, dgdm, mv)
            return cache[k]

        def potential(u):
            e, _, _, _, mv = ev(u)
            return e if (mv > 0 and np.isfinite(e)) else np.inf

        def residual(u):
            return P * ev(u)[1]

        def project(H):
            return H * P[:, None] * P[None, :] + np.diag(1.0 - P)

        # Dirichlet predictor (solve_static's _newton): linearise at the starting guess.
        jump = (1.0 - P) * (disp - u_init)
        naive = fixed_part + P * u_init
        _, g_init, H_init, _, _ = ev(u_init)
        rhs = P * (g_init + H_init @ jump)
        delta = _cholesky_solve(project(H_init), -rhs)
        predicted = naive + P * delta
        e_predicted = potential(predicted) if np.all(np.isfinite(predicted)) else np.nan
        e_naive = potential(naive)
        use = bool(np.all(np.isfinite(predicted)) and e_predicted <= e_naive)
        u = predicted if use else naive
        e = e_predicted if use else e_naive
        g_cold = np.linalg.norm(residual(fixed_part))
        tol = max(atol, rtol * g_cold)
        g = residual(u)
        step = 0
        code = StaticResult.successful if np.linalg.norm(g) <= tol else StaticResult.max_steps_reached
        done = code == StaticResult.successful or max_steps <= 0
        eps = np.finfo(float).eps
        while not done:
            A = project(ev(u)[2])
            d = _cholesky_solve(A, -g)
            gd = float(g @ d)
            bad = not np.all(np.isfinite(d)) or not gd < 0
            if bad:
                scale = np.linalg.norm(g) / max(np.linalg.norm(A @ g), 1e-300)
                d = -g * scale
                gd = float(g @ d)
            alpha, accepted, e_new = 1.0, False, e
            for _ in range(max_tries):
                e1 = potential(u + alpha * d)
                slack = 64 * eps * (abs(e) + abs(e1))
                if np.isfinite(e1) and e1 <= e + c * alpha * gd + slack:
                    accepted, e_new = True, e1
                    break
                alpha *= 0.5
            u_new = u + alpha * d if accepted else u
            g_new = residual(u_new)
            rn = np.linalg.norm(g_new)
            step += 1
            finite = bool(np.all(np.isfinite(u_new)) and np.isfinite(rn))
            small_step = accepted and not bad and np.linalg.norm(d) <= xtol * np.linalg.norm(u_new)
            ok = rn <= tol or small_step
            if not finite:
                code = StaticResult.nonfinite
            elif not accepted:
                code = StaticResult.line_search_failed
            else:
                code = StaticResult.successful if ok else StaticResult.max_steps_reached
            done = code != StaticResult.max_steps_reached or step >= max_steps
            u, g, e = u_new, g_new, e_new
        _, grad, H, dgdm, mv = ev(u)
        if code == StaticResult.successful and not mv > 0:
            code = StaticResult.inverted_elements
        reaction = (1.0 - P) * grad
        return HostSolution(u.reshape(-1, 3), reaction.reshape(-1, 3), int(code), step, float(np.linalg.norm(g)), H, dgdm)

    def tangents(self, sol: HostSolution, t_material: dict[str, np.ndarray]):
        """Derivatives of the solution along ``K`` material tangents (implicit function
        theorem; prescribed displacements and forces held fixed).

        Args:
            sol: a converged :class:`HostSolution` of this solver.
            t_material: ``{field: (K,)}`` tangent of each (scalar) material field, applied to
                every region; fields left out have zero tangent.

        Returns:
            ``(t_displacement (K, N, 3), t_reaction (K, N, 3))``; NaN if ``sol`` did not converge.
        """
        P = self.P
        K = len(next(iter(t_material.values()))) if t_material else 0
        dg = np.zeros((K, P.size))
        for name, t in t_material.items():
            d = getattr(sol.dgrad_dmaterial, name, None)
            if d is None:
                raise ModelError(f"the model's material has no field {name!r}")
            dg += np.asarray(t, dtype=float)[:, None] * np.sum(d, axis=-1)[None, :]
        A = sol.hessian * P[:, None] * P[None, :] + np.diag(1.0 - P)
        w = _cholesky_solve(A, (-P * dg).T).T
        t_u = P * w
        t_reaction = (1.0 - P) * (t_u @ sol.hessian.T + dg)
        if not sol.converged:
            t_u, t_reaction = t_u * np.nan, t_reaction * np.nan
        n = self.model.n_nodes
        return t_u.reshape(K, n, 3), t_reaction.reshape(K, n, 3)
