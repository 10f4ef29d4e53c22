"""Static equilibrium of small models on the host: the Newton iteration of
:func:`~difftissue.solvers.static.solve_static` in NumPy, with the model's energy, gradient,
dense Hessian and mixed material derivative from ONE small compiled program.

For a model of a few nodes (the one-cube compression specimen: 8 nodes, 24 unknowns) the
arithmetic of a static solve takes microseconds, while tracing and compiling a protocol of such
solves into one XLA program (the Newton loop, its line search, the Dirichlet predictor and the
implicit-function-theorem tangents, inside a scan over the load steps) takes seconds. Here only
the model's derivatives are compiled (:class:`ModelDerivatives`, once per model structure,
shared by every model of the same structure and shapes); the iteration runs in
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

import collections
import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..materials import Material
from ..models import CheckedMaterial, ElasticModel
from ..xla_options import PROGRAMS, known_options
from .static import _MESSAGES, ENERGY_ROUNDOFF, StaticResult, _dense_hessian

__all__ = ["HOST_MAX_NODES", "HOST_BATCH", "HOST_COMPILER_OPTIONS", "HostStaticSolver", "HostSolution", "ModelDerivatives", "model_derivatives"]

#: Models with at most this many nodes may be solved on the host (:class:`HostStaticSolver`).
#: Above it the dense Hessian (``(3N)^2``) and the per-call cost of the compiled derivatives
#: make the compiled protocol the better choice.
HOST_MAX_NODES = 64

#: ``{structure key: compiled program}`` of :class:`ModelDerivatives`, most recently built
#: last; at most :data:`PROGRAMS_SIZE` kept (a dropped one stays with the objects using it).
_PROGRAMS: collections.OrderedDict = collections.OrderedDict()
PROGRAMS_SIZE = 16


def _derivatives(dynamic, static, material, x):
    model = eqx.combine(dynamic, static)
    leaves, treedef = jax.tree_util.tree_flatten(material)
    shapes = [np.shape(v) for v in leaves]
    ends = np.cumsum([int(np.prod(s)) for s in shapes])
    basis = np.eye(int(ends[-1]))  # one tangent per material value (field, region), as jax.jacfwd's

    def as_material(t):
        return jax.tree_util.tree_unflatten(treedef, [t[e - int(np.prod(s)):e].reshape(s) for e, s in zip(ends, shapes)])

    def one(xc):
        def value_and_grad(m):
            return jax.value_and_grad(model.energy)(xc, m)

        # The energy and gradient are the primal of the gradient's JVPs along the material
        # tangents: one trace of the energy serves both (jacfwd of the gradient traced it
        # again; the same values to the bit, ~0.2 s less to trace and compile).
        (e, g), (_, dg) = jax.vmap(lambda t: jax.jvp(value_and_grad, (material,), (as_material(t),)), out_axes=(None, 0))(basis)
        g = g.reshape(-1)
        dg = dg.reshape(basis.shape[0], -1).T  # (3N, material values)
        dgdm = jax.tree_util.tree_unflatten(treedef, [dg[:, e - int(np.prod(s)):e].reshape((-1, *s)) for e, s in zip(ends, shapes)])
        return e, g, _dense_hessian(model, xc, material), dgdm, model.min_volume_ratio(xc)

    return jax.vmap(one)(x)


#: XLA options the derivative program is compiled with on a CPU (this program only: nothing
#: global): :data:`difftissue.xla_options.OLDER_FUSION`, the set of the ``"host_derivatives"``
#: program kind (the module :mod:`difftissue.xla_options` says what it trades).
HOST_COMPILER_OPTIONS = PROGRAMS["host_derivatives"]


def _compile(lowered):
    """``lowered.compile()`` with :data:`HOST_COMPILER_OPTIONS` on a CPU backend (less the
    options this jaxlib does not know)."""
    options = known_options(HOST_COMPILER_OPTIONS) if HOST_COMPILER_OPTIONS and jax.default_backend() == "cpu" else None
    return lowered.compile(compiler_options=options) if options else lowered.compile()


#: Positions per call of the compiled derivatives (:class:`ModelDerivatives`): every call is
#: padded to this batch, so ONE program serves the Newton iteration here (a line search's trial
#: steps evaluated together) and the homogeneous-deformation solves of
#: :mod:`difftissue.constitutive` (16 quadrature strains) on a model of the same structure.
HOST_BATCH = 16


class ModelDerivatives:
    """The model's energy and its derivatives at node positions, from one compiled program per
    model structure (shared by models of the same structure and array shapes: the arrays are
    its arguments), evaluated :data:`HOST_BATCH` positions per call.

    Args:
        model: an :class:`~difftissue.models.ElasticModel`.
    """

    def __init__(self, model: ElasticModel):
        self.model = model
        self._dynamic, self._static = eqx.partition(model, eqx.is_array)
        self._programs: dict = {}

    def _program(self, material):
        mleaves, mtree = jax.tree_util.tree_flatten(material)
        mkey = (mtree, tuple(np.shape(v) for v in mleaves))
        hit = self._programs.get(mkey)
        if hit is not None:
            return hit
        leaves, treedef = jax.tree_util.tree_flatten(self._dynamic)
        try:
            s_leaves, s_tree = jax.tree_util.tree_flatten(self._static)
            key = (s_tree, tuple(s_leaves), treedef, tuple((np.shape(v), np.result_type(v).str) for v in leaves), mkey,
                   bool(jax.config.jax_enable_x64))
            hash(key)
        except TypeError:  # a static field that cannot be hashed: compiled for this model alone
            key = None
        hit = _PROGRAMS.get(key) if key is not None else None
        if hit is None:
            spec = lambda v: jax.ShapeDtypeStruct(np.shape(v), jnp.result_type(v))  # noqa: E731
            x = jax.ShapeDtypeStruct((HOST_BATCH, self.model.n_nodes, 3), jnp.float64)
            hit = _compile(jax.jit(_derivatives, static_argnums=1).lower(jax.tree_util.tree_map(spec, self._dynamic), self._static,
                                                                         jax.tree_util.tree_map(spec, material), x))
            if key is not None:
                _PROGRAMS[key] = hit
                while len(_PROGRAMS) > PROGRAMS_SIZE:
                    _PROGRAMS.popitem(last=False)
        self._programs[mkey] = hit
        return hit

    def __call__(self, material: CheckedMaterial, x):
        """At the positions ``x`` ``(B, N, 3)`` [m] (any ``B``; run :data:`HOST_BATCH` at a time).

        Args:
            material: ``model.checked(material)`` (concrete).

        Returns:
            NumPy arrays ``(energy (B,) [J], gradient (B, 3N) [N], Hessian (B, 3N, 3N) [N/m],
            dgrad_dmaterial, min_volume_ratio (B,))``; ``dgrad_dmaterial`` is a
            ``CheckedMaterial`` whose fields are ``(B, 3N, n_regions)``: the derivative of the
            gradient with respect to each region's value of that field (None where the field
            is None).
        """
        x = np.asarray(x, dtype=np.float64)
        n = self.model.n_nodes
        if x.ndim != 3 or x.shape[1:] != (n, 3):
            raise ModelError(f"x must be (B, {n}, 3), got {x.shape}")
        program = self._program(material)
        B = x.shape[0]
        pad = -B % HOST_BATCH
        if pad or B == 0:
            x = np.concatenate([x, np.broadcast_to(np.asarray(self.model.rest_points, dtype=np.float64), (pad or HOST_BATCH, n, 3))])
        parts = [program(self._dynamic, material, x[i:i + HOST_BATCH]) for i in range(0, x.shape[0], HOST_BATCH)]
        out = jax.tree_util.tree_map(lambda *a: np.concatenate([np.asarray(v) for v in a])[:B], *parts)
        return tuple(out)


def model_derivatives(model: ElasticModel, material: CheckedMaterial, x):
    """:class:`ModelDerivatives` of ``model`` at ``x`` ``(B, N, 3)`` [m] (see its ``__call__``)."""
    return ModelDerivatives(model)(material, x)


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
    """``A^{-1} b`` by Cholesky ``A = L L^T`` (NumPy); NaN where ``A`` is not positive definite
    (as lineax's Cholesky returns a non-finite solution there, which the Newton loop rejects)."""
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return np.full(np.shape(b), np.nan)
    return np.linalg.solve(L.T, np.linalg.solve(L, b))


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
        self.derivatives = ModelDerivatives(model)

    def checked(self, material: Material) -> CheckedMaterial:
        """``material`` range-checked by the model (raises for values outside its range)."""
        return self.model.checked(material)

    def solve(self, material: CheckedMaterial, displacement, u_init, *, force=None, rtol: float = 1e-10, atol: float = 0.0,
              xtol: float = 1e-8, max_steps: int = 50, max_tries: int = 40, c: float = 1e-4) -> HostSolution:
        """The equilibrium under the prescribed ``displacement`` ``(N, 3)`` [m] (its free
        components ignored) and nodal ``force`` ``(N, 3)`` [N] (default none), from the
        starting guess ``u_init`` ``(N, 3)``; options as for
        :func:`~difftissue.solvers.static.solve_static` (``max_tries``, ``c``: its line
        search's). A failed solve is reported in ``result``, never raised."""
        P = self.P
        n = self.model.n_nodes
        f = np.zeros(P.size) if force is None else np.asarray(force, dtype=float).reshape(-1)
        disp = np.asarray(displacement, dtype=float).reshape(-1)
        u_init = np.asarray(u_init, dtype=float).reshape(-1)
        fixed_part = (1.0 - P) * disp

        def ev(us):
            """Potential (inf where an element inverts or it is not finite), full gradient,
            Hessian, mixed material derivative at the rows of ``us`` (B, 3N)."""
            e, g, H, dgdm, mv = self.derivatives(material, self.rest[None] + us.reshape(-1, n, 3))
            e = e - us @ f
            e = np.where((mv > 0) & np.isfinite(e), e, np.inf)
            return e, g - f, H, dgdm

        def project(H):
            return H * P[:, None] * P[None, :] + np.diag(1.0 - P)

        # Dirichlet predictor (solve_static's _newton): linearise at the starting guess and
        # solve for the free response to the jump in the prescribed values.
        jump = (1.0 - P) * (disp - u_init)
        naive = fixed_part + P * u_init
        e3, g3, H3, _ = ev(np.stack([u_init, naive, fixed_part]))
        rhs = P * (g3[0] + H3[0] @ jump)
        predicted = naive + P * _cholesky_solve(project(H3[0]), -rhs)
        g_cold = np.linalg.norm(P * g3[2])
        tol = max(atol, rtol * g_cold)
        use = bool(np.all(np.isfinite(predicted)))
        if use:
            e1, g1, H1, dgdm1 = ev(predicted[None])
            use = bool(e1[0] <= e3[1])
        if use:
            u, e, grad, H, dgdm = predicted, e1[0], g1[0], H1[0], jax.tree_util.tree_map(lambda a: a[0], dgdm1)
        else:
            u, e, grad, H, dgdm = naive, e3[1], g3[1], H3[1], None
        g = P * grad
        step = 0
        code = StaticResult.successful if np.linalg.norm(g) <= tol else StaticResult.max_steps_reached
        done = code == StaticResult.successful or max_steps <= 0
        eps = np.finfo(float).eps
        while not done:
            A = project(H)
            d = _cholesky_solve(A, -g)
            gd = float(g @ d)
            bad = not np.all(np.isfinite(d)) or not gd < 0
            if bad:  # a Jacobi-scaled gradient step instead of an unusable Newton direction
                d = -g * (np.linalg.norm(g) / max(np.linalg.norm(A @ g), 1e-300))
                gd = float(g @ d)
            # Armijo backtracking (armijo_backtracking): alpha = 1, 1/2, 1/4, ... up to max_tries,
            # the trial steps evaluated HOST_BATCH at a time; the first acceptable one is taken.
            accepted = False
            e_before, alpha, full = e, 0.0, None
            for start in range(0, max_tries, HOST_BATCH):
                alphas = 0.5 ** np.arange(start, min(start + HOST_BATCH, max_tries))
                trial = u[None] + alphas[:, None] * d[None]
                et, gt, Ht, dt = ev(trial)
                if start == 0:  # the full step (alpha = 1), for the round-off rule below
                    full = (trial[0], et[0], gt[0], Ht[0], jax.tree_util.tree_map(lambda a: a[0], dt))
                slack = 64 * eps * (abs(e) + np.abs(et))
                ok = np.isfinite(et) & (et <= e + c * alphas * gd + slack)
                if np.any(ok):
                    j = int(np.argmax(ok))
                    accepted = True
                    alpha, u_new, e, grad, H = alphas[j], trial[j], et[j], gt[j], Ht[j]
                    dgdm = jax.tree_util.tree_map(lambda a: a[j], dt)
                    break
            # A Newton step below the energy's round-off (solve_static's rule, ENERGY_ROUNDOFF):
            # where the Armijo test refused the full step, it is taken if it lowers |g|.
            if (not bad and alpha < 1.0 and full is not None and 0.5 * abs(gd) <= ENERGY_ROUNDOFF * eps * abs(e_before)
                    and np.isfinite(full[1]) and np.linalg.norm(P * full[2]) < (1.0 - 1e-4) * np.linalg.norm(g)):
                accepted, alpha = True, 1.0
                u_new, e, grad, H, dgdm = full
            if not accepted:
                u_new = u
            g_new = P * grad
            rn = np.linalg.norm(g_new)
            step += 1
            finite = bool(np.all(np.isfinite(u_new)) and np.isfinite(rn))
            # A round-off-sized Newton correction (Cholesky: a positive definite matrix) is
            # convergence also when the line search refused it (solve_static's rule).
            small_step = not bad and np.linalg.norm(d) <= xtol * np.linalg.norm(u_new)
            ok = rn <= tol or small_step
            if not finite:
                code = StaticResult.nonfinite
            elif ok:
                code = StaticResult.successful
            elif not accepted:
                code = StaticResult.line_search_failed
            else:
                code = StaticResult.max_steps_reached
            done = code != StaticResult.max_steps_reached or step >= max_steps
            u, g = u_new, g_new
        if dgdm is None:  # the naive start accepted as the solution at once: its derivatives
            _, grad, H, dgdm_b = ev(u[None])
            grad, H, dgdm = grad[0], H[0], jax.tree_util.tree_map(lambda a: a[0], dgdm_b)
        if code == StaticResult.successful and not np.isfinite(e):
            code = StaticResult.inverted_elements  # e is inf exactly where an element is inverted (or not finite)
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
