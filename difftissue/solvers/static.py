"""Static equilibrium: minimise the total potential energy by Newton-Krylov, differentiate
the minimiser implicitly.

The unknowns are the nodal displacements ``u`` (N, 3) [m]; prescribed components take the
boundary values; the potential energy is ``Pi(u) = U(X + u; material) - f . u``. Newton
steps use element Hessians (``jax.hessian`` of each element's energy, vmapped), assembled
into a dense matrix and factorised by Cholesky for small problems or applied matrix-free in
Jacobi-preconditioned conjugate gradients (lineax) for large ones, with a backtracking line
search that rejects steps which invert an element or raise the energy. The stopping rule is
residual-based: ``|grad Pi|_free <= max(atol, rtol * |grad Pi at the undeformed start|)``,
or a full Newton correction below ``xtol`` relative (round-off level) through a positive
definite matrix (a minimum: a tiny correction through an indefinite one is replaced by the
scaled gradient step), or a stall at the round-off floor (a step below the energy's round-off
whose full step does not lower the residual, a correction within ``ROUNDOFF_STALL_XTOL * xtol``
and a residual within ``ROUNDOFF_STALL_RESIDUAL`` times its tolerance).

Derivatives of the solution with respect to the material, the prescribed displacements and
the forces come from the implicit function theorem (a custom JVP with one linear solve with
the same Hessian), never from backpropagating through the Newton iterations; reverse mode
transposes that solve (one adjoint solve). See ``docs/theory.md``.
"""

from __future__ import annotations

import enum
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

from ..boundary import BoundaryConditions, _validate_values, check_rigid_modes
from ..errors import ConvergenceError, LinearSolverError, ModelError
from ..materials import Material, _is_concrete
from ..models import ElasticModel, material_error_type
from ..xla_options import ProgramJit
from .multigrid import BlockEllMatrix, JacobiPreconditioner, MultigridPreconditioner, PreconditionedCG, multigrid_cached, multigrid_setup, sparse_layout
from .sparse import SparseLU, assemble_csr_data, cache_key, sparse_pattern

__all__ = ["StaticSolution", "StaticResult", "SolverSetup", "solve_static", "solver_setup", "element_hessian_operator", "auto_linear_solver", "LINEAR_SOLVERS"]


class StaticResult(enum.IntEnum):
    """Why the Newton loop stopped."""

    successful = 0
    max_steps_reached = 1
    line_search_failed = 2
    inverted_elements = 3
    nonfinite = 4
    linear_solver_failed = 5


_MESSAGES = (
    "",
    "static solve did not converge within max_steps Newton steps (raise max_steps, or apply the load in increments)",
    "static solve: the line search found no step that lowers the energy without inverting an element (load too large for one step?)",
    "static solve: an element is inverted in the solution",
    "static solve produced NaN or infinite values",
    "static solve: the preconditioned conjugate gradients did not converge (the preconditioner no longer fits the operator: nu close to 0.5, or a material or deformation far from the one the multigrid hierarchy was built for); raise cg_max_steps or use linear_solver='sparse' (direct)",
)

#: A Newton direction whose CG relative residual is above this is unusable (solve stops with
#: ``linear_solver_failed``); below it but above ``cg_rtol`` it is an inexact Newton step.
NEWTON_CG_FAILURE = 1e-4
#: An implicit-gradient (tangent / adjoint) solve must reach this relative residual, else the
#: tangent is NaN (never a silently wrong gradient).
TANGENT_CG_FAILURE = 1e-7
#: Inexact Newton (iterative linear solvers): the CG tolerance of a Newton step is the forcing
#: term ``eta = min(NEWTON_FORCING_MAX, max(cg_rtol, |g| / |g_cold|, c tol / |g|))``, the
#: current residual relative to the residual scale of the Newton tolerance (Eisenstat & Walker
#: 1996): loose far from the solution, tightening with the residual, so the convergence stays
#: quadratic while the early steps cost a few CG iterations instead of a solve to ``cg_rtol``;
#: ``c tol / |g|`` (:data:`NEWTON_OVERSOLVE_SAFEGUARD`) keeps the last step from solving far
#: below the tolerance. The Dirichlet predictor (a starting guess that Newton corrects) is
#: solved to ``NEWTON_FORCING_MAX``.
NEWTON_FORCING_MAX = 1e-2
#: Kelley's safeguard against oversolving (Kelley 1995, sec. 6.3): the forcing term of a Newton
#: step is at least this fraction of the Newton tolerance over the current residual,
#: ``eta >= c tol / |g|``, so the last step is solved to about a tenth of the tolerance instead of
#: far below it (on the 105,903-unknown punch 5 CG iterations instead of 20; forces within
#: 2e-11 relative of the nearly exact last step, far inside ``prediction_rtol``). Such a
#: finishing step may reuse its predecessor's matrix (multigrid; ``_newton``).
NEWTON_OVERSOLVE_SAFEGUARD = 0.1
#: A Newton step whose predicted energy decrease ``|g.d| / 2`` is below this many machine
#: epsilons of the energy is below what the energy's evaluation resolves (a sum over every
#: element, each carrying its own round-off): where the Armijo line search then refuses the
#: full step, the step is taken if it lowers the residual norm instead (``_newton``).
ENERGY_ROUNDOFF = 1e4
#: A solve stalled at its round-off floor is converged: where a Newton step is below the
#: energy's round-off (``ENERGY_ROUNDOFF``), its full step does not lower the residual norm
#: (the residual is round-off noise), the correction is within this many ``xtol`` of ``|u|``
#: and the residual within ``ROUNDOFF_STALL_RESIDUAL`` times its tolerance, no further step can
#: improve the solution (``_newton``). Measured: the stable neo-Hookean sphere on the
#: axisymmetric check mesh (4 cells per contact radius) at 3 um stalled for 47 steps at
#: ``|d| = 1.25 xtol |u|``, residual 8.5e-13 N against a tolerance of 6.1e-13 N, and the
#: discretisation check failed on it (docs/dev/axisymmetric-indentation.md).
ROUNDOFF_STALL_XTOL = 4.0
#: See ``ROUNDOFF_STALL_XTOL``: the stall rule applies only within this factor of the residual tolerance.
ROUNDOFF_STALL_RESIDUAL = 100.0


class StaticSolution(eqx.Module):
    """Result of :func:`solve_static`.

    Attributes:
        displacement: ``(N, 3)`` nodal displacements [m] (prescribed values included).
        reaction: ``(N, 3)`` reaction forces [N] on prescribed components: internal elastic
            force minus applied force there (zero on free components).
        energy: total potential energy at the solution [J].
        residual_norm: 2-norm of the free-component residual [N].
        steps: Newton steps taken.
        result: a :class:`StaticResult` code (0 = successful).
        min_volume_ratio: smallest element volume ratio ``V / V0`` [-].
        linear_steps: largest number of conjugate-gradient iterations of one Newton step
            (0 for direct solvers).
        linear_residual: relative residual ``|b - A d| / |b|`` of the last Newton step's
            linear solve (0 for direct solvers).
    """

    displacement: jax.Array
    reaction: jax.Array
    energy: jax.Array
    residual_norm: jax.Array
    steps: jax.Array
    result: jax.Array
    min_volume_ratio: jax.Array
    linear_steps: jax.Array
    linear_residual: jax.Array

    @property
    def converged(self) -> jax.Array:
        """True when the residual reached its tolerance with no inverted element."""
        return self.result == StaticResult.successful


# ----------------------------------------------------------------- linear algebra
def _element_data(model: ElasticModel, x, material):
    """Per-term element Hessians ``(E, 3k, 3k)`` and DOF indices ``(E, 3k)``."""
    out = []
    for term in model.terms(material):
        k = term.nodes.shape[1]
        hess = _element_hessian(term, x[term.nodes], *term.params)
        dofs = (3 * jnp.asarray(term.nodes)[:, :, None] + jnp.arange(3)).reshape(-1, 3 * k)
        out.append((hess, dofs))
    return out


#: Element Hessians are computed and scattered into the block-ELL matrix in chunks of at most
#: this many elements per term (a ``fori_loop``), so the peak memory of an assembly is one
#: chunk's Hessians and their intermediates instead of the whole mesh's (1M unknowns: ~1.5M tets).
ASSEMBLY_CHUNK = 65_536


def _element_hessian(term, xe, *params):
    """``(E, 3k, 3k)`` Hessians of ``term``'s elements at positions ``xe (E, k, 3)``."""
    k = xe.shape[1]
    if term.hessian is not None:
        return jax.vmap(term.hessian)(xe, *params)
    hess = jax.vmap(jax.hessian(term.energy))(xe, *params)
    return hess.reshape(hess.shape[0], 3 * k, 3 * k)


def _assemble_ell(layout, model: ElasticModel, x, material, free_dofs, *, chunk: int | None = None) -> BlockEllMatrix:
    """The block-ELL matrix ``P H P + (I - P)`` at positions ``x`` (``free_dofs`` ``(3N,)``
    floats), the element Hessians computed and scattered ``chunk`` elements at a time
    (default :data:`ASSEMBLY_CHUNK`; a term with fewer elements in one go)."""
    chunk = ASSEMBLY_CHUNK if chunk is None else int(chunk)
    terms = model.terms(material)
    if all(t.nodes.shape[0] <= chunk for t in terms):
        return layout.assemble(_element_data(model, x, material), free_dofs)
    P = free_dofs
    n, w = layout.cols.shape
    flat = jnp.zeros((n * w, 3, 3), dtype=P.dtype)
    for term, slots in zip(terms, layout.term_slots):
        E, k = term.nodes.shape
        # A term with fewer elements than a chunk is one chunk of its own size: padding it to
        # the chunk size computed (and scattered) up to chunk / E times its Hessians.
        c = min(chunk, E)
        m = -(-E // c)
        pad = m * c - E
        # Padding elements repeat element 0 with zero weight. (Only shapes are used here: the
        # node arrays may be traced, e.g. in the reference assembly.)
        idx = jnp.asarray(np.concatenate([np.arange(E), np.zeros(pad, dtype=np.int64)]).reshape(m, c))
        weight = jnp.asarray((np.arange(m * c) < E).reshape(m, c), dtype=P.dtype)
        slot_rows = jnp.asarray(slots).reshape(E, k * k)[idx]
        node_rows = jnp.asarray(term.nodes)[idx]

        def body(i, flat, term=term, node_rows=node_rows, slot_rows=slot_rows, idx=idx, weight=weight, k=k, c=c):
            nd = node_rows[i]
            params = [jnp.asarray(p)[idx[i]] for p in term.params]
            hess = _element_hessian(term, x[nd], *params)
            dofs = (3 * nd[:, :, None] + jnp.arange(3)).reshape(c, 3 * k)
            Pd = P[dofs] * weight[i][:, None]
            masked = hess * Pd[:, :, None] * P[dofs][:, None, :]
            blocks = masked.reshape(c, k, 3, k, 3).transpose(0, 1, 3, 2, 4).reshape(c * k * k, 3, 3)
            return flat.at[slot_rows[i].reshape(-1)].add(blocks)

        flat = jax.lax.fori_loop(0, m, body, flat)
    fixed = (1.0 - P).reshape(n, 3)
    flat = flat.at[layout.diagonal_slots].add(fixed[:, :, None] * jnp.eye(3, dtype=P.dtype))
    return BlockEllMatrix.from_blocks(flat.reshape(n, w, 3, 3), layout.cols)


def element_hessian_operator(model: ElasticModel, x, material):
    """Matrix-free Hessian ``v -> H v`` of the elastic energy at ``x`` and its diagonal.

    Args:
        x: ``(N, 3)`` positions [m].

    Returns:
        ``(matvec, diagonal)``: ``matvec`` maps flat ``(3N,)`` vectors, ``diagonal`` is ``(3N,)``.
    """
    data = _element_data(model, x, material)
    n3 = 3 * model.n_nodes

    def matvec(v):
        y = jnp.zeros(n3, dtype=v.dtype)
        for hess, dofs in data:
            y = y.at[dofs].add(jnp.einsum("eij,ej->ei", hess, v[dofs]))
        return y

    diag = jnp.zeros(n3)
    for hess, dofs in data:
        diag = diag.at[dofs].add(jnp.diagonal(hess, axis1=1, axis2=2))
    return matvec, diag


def _dense_hessian(model, x, material):
    n3 = 3 * model.n_nodes
    H = jnp.zeros((n3, n3))
    for hess, dofs in _element_data(model, x, material):
        H = H.at[dofs[:, :, None], dofs[:, None, :]].add(hess)
    return H


class _Options(eqx.Module):
    rtol: float
    atol: float
    xtol: float
    max_steps: int
    linear_solver: str
    cg_rtol: float
    cg_max_steps: int
    #: CSR pattern for linear_solver="sparse" (hashable by content: no recompile per call).
    pattern: Any = eqx.field(static=True, default=None)
    #: linear_solver="multigrid": the ELL layout of the Hessian and the multigrid hierarchy
    #: (arrays, traced: a new mesh of the same size does not recompile).
    layout: Any = None
    hierarchy: Any = None


def _projected_operator(model, u, material, free, options: _Options, *, tangent: bool = False):
    """The SPD operator ``P H P + (I - P)`` on flat vectors, as a lineax operator + solver."""
    x = jnp.asarray(model.rest_points) + u
    P = free.reshape(-1)
    if options.linear_solver == "dense":
        H = _dense_hessian(model, x, material)
        A = H * P[:, None] * P[None, :] + jnp.diag(1.0 - P)
        return lx.MatrixLinearOperator(A, (lx.symmetric_tag, lx.positive_semidefinite_tag)), lx.Cholesky(), {}
    if options.linear_solver == "sparse":
        data = _element_data(model, x, material)
        csr = assemble_csr_data(options.pattern, data, P)
        struct = jax.ShapeDtypeStruct((3 * model.n_nodes,), u.dtype)

        def mv_sparse(v):
            y = (1.0 - P) * v
            for hess, dofs in data:
                pv = (P * v)[dofs]
                y = y.at[dofs].add(P[dofs] * jnp.einsum("eij,ej->ei", hess, pv))
            return y

        op = lx.FunctionLinearOperator(mv_sparse, struct, (lx.symmetric_tag, lx.positive_semidefinite_tag))
        return op, SparseLU(options.pattern), {"csr_data": csr}
    struct = jax.ShapeDtypeStruct((3 * model.n_nodes,), u.dtype)
    solver = PreconditionedCG(rtol=options.cg_rtol, max_steps=options.cg_max_steps, failure_rtol=TANGENT_CG_FAILURE if tangent else NEWTON_CG_FAILURE)
    if options.linear_solver == "multigrid":
        ell, pc = _multigrid_matrix(model, u, material, free, options)
        return _ell_operator(ell, struct), solver, {"preconditioner": pc}
    matvec, diag = element_hessian_operator(model, x, material)
    op = lx.FunctionLinearOperator(lambda v: P * matvec(P * v) + (1.0 - P) * v, struct, (lx.symmetric_tag, lx.positive_semidefinite_tag))
    d = P * diag + (1.0 - P)
    d = jnp.where(d > 0, d, 1.0)
    return op, solver, {"preconditioner": JacobiPreconditioner(1.0 / d)}


def _multigrid_matrix(model, u, material, free, options: _Options, power_start=None):
    """The block-ELL matrix ``P H P + (I - P)`` at displacement ``u`` and its multigrid V-cycle
    (``power_start``: warm start of its spectral estimate, see ``MultigridPreconditioner.build``)."""
    x = jnp.asarray(model.rest_points) + u
    Pf = free.reshape(-1).astype(x.dtype)
    ell = _assemble_ell(options.layout, model, x, material, Pf)
    return ell, MultigridPreconditioner.build(ell, options.hierarchy, Pf, power_start)


def _ell_operator(ell, struct):
    return lx.FunctionLinearOperator(ell.mv, struct, (lx.symmetric_tag, lx.positive_semidefinite_tag))


def _linear_stats(sol):
    """``(CG iterations, relative residual)`` of a lineax solution (zeros for direct solvers)."""
    steps = sol.stats.get("num_steps", 0)
    res = sol.stats.get("relative_residual", 0.0)
    return jnp.asarray(steps, jnp.int32), jnp.asarray(res, float)


def _potential(model, u, material, force):
    return model.energy(jnp.asarray(model.rest_points) + u, material) - jnp.sum(force * u)


def _full_gradient(model, u, material, force):
    return jax.grad(_potential, argnums=1)(model, u, material, force)


# ------------------------------------------------------------------------- Newton
def armijo_backtracking(potential, u, d, gd, *, max_tries: int = 40, c: float = 1e-4, e0=None, return_energy: bool = False, compare_only=False,
                        return_full_step: bool = False, e0_in_loop=False):
    """Backtracking line search along ``d`` from ``u`` (Armijo's sufficient decrease).

    Halves ``alpha`` from 1 until ``potential(u + alpha d) <= potential(u) + c alpha gd`` (with a
    round-off slack of 64 eps |e|, so that a converged point is not refused for rounding) and
    the energy is finite; ``potential`` returns ``inf`` where the step is inadmissible (an
    inverted element). ``gd`` is the directional derivative ``g . d`` (< 0 for a descent
    direction). ``e0``: ``potential(u)`` when the caller has it already (one energy evaluation
    less in the compiled program). Returns ``(alpha, accepted)``, or with
    ``return_energy=True`` ``(alpha, accepted, e)`` where ``e`` is the potential at the accepted
    point (``e0`` if no step was accepted). After ``max_tries`` halvings ``accepted`` is False.
    ``return_full_step=True`` appends the potential at ``u + d`` (its first try, ``alpha = 1``;
    ``inf`` when ``max_tries`` is 0), for a caller that considers the full step itself.
    ``e0_in_loop`` (a bool, may be traced): ``potential(u)`` is evaluated by the search's own
    loop, in a pass before the first try (``e0`` is then ignored): the program holds one copy
    of the energy where the caller would otherwise evaluate it beside the search.
    The Newton solvers of :func:`solve_static` and
    :func:`~difftissue.solvers.condensed.solve_condensed_contact` share it.

    ``compare_only`` (a bool, may be traced): instead, one try of ``alpha = 1``, accepted when
    ``u + d`` is finite and ``potential(u + d) <= potential(u)`` (the Dirichlet predictor's
    rule in :func:`solve_static`, whose Newton loop runs the predictor as its first pass).
    """
    in_loop = e0_in_loop is not False  # a Python False: e0 from the caller or evaluated here
    if e0 is None:
        e0 = jnp.zeros((), u.dtype) if in_loop else potential(u)  # (in_loop: a placeholder)
    plain = compare_only is False  # a Python False: the Armijo search alone in the program
    tries_allowed = max_tries if plain else jnp.where(compare_only, 1, max_tries)

    def body(s):
        alpha, _, tries, _, e_full, e0 = s
        if in_loop:
            first = tries < 0  # the pass that evaluates potential(u)
            trial = jnp.where(first, u, u + alpha * d)
        else:
            trial = u + alpha * d
        e1 = potential(trial)
        if in_loop:
            e0 = jnp.where(first, e1, e0)
        slack = 64 * jnp.finfo(u.dtype).eps * (jnp.abs(e0) + jnp.abs(e1))
        armijo = jnp.isfinite(e1) & (e1 <= e0 + c * alpha * gd + slack)
        ok = armijo if plain else jnp.where(compare_only, jnp.all(jnp.isfinite(trial)) & (e1 <= e0), armijo)
        halved = 0.5 * alpha
        if in_loop:
            ok = ok & ~first
            halved = jnp.where(first, alpha, halved)
        return jnp.where(ok, alpha, halved), ok, tries + 1, jnp.where(ok, e1, e0), jnp.where(tries == 0, e1, e_full), e0

    e0 = jnp.asarray(e0, u.dtype)
    tries0 = jnp.where(e0_in_loop, -1, 0) if in_loop else 0
    init = (jnp.asarray(1.0, u.dtype), jnp.asarray(False), tries0, e0, jnp.full_like(e0, jnp.inf), e0)
    alpha, accepted, _, e, e_full, _ = jax.lax.while_loop(lambda s: (~s[1]) & (s[2] < tries_allowed), body, init)
    out = (alpha, accepted, e) if return_energy else (alpha, accepted)
    return out + (e_full,) if return_full_step else out


def _newton(model: ElasticModel, material, displacement, force, free, u_init, options: _Options):
    Pf = free.astype(u_init.dtype)
    fixed_part = (1.0 - Pf) * displacement

    def residual(u):
        return Pf * _full_gradient(model, u, material, force)

    def potential(u):
        e = _potential(model, u, material, force)
        ok = model.min_volume_ratio(jnp.asarray(model.rest_points) + u) > 0
        return jnp.where(ok & jnp.isfinite(e), e, jnp.inf)

    # Dirichlet predictor: linearise at the starting guess (with its own prescribed values)
    # and solve for the free response to the jump in the prescribed values, as FE codes do.
    # Starting from the bare jump instead squeezes the boundary layer of elements, which
    # makes nearly incompressible or large-step problems crawl through line searches.
    # The predictor is the first pass of the Newton loop below (``predictor`` in its state):
    # it needs the same matrix assembly, V-cycle set-up and linear solve as a Newton step,
    # and one copy of them in the compiled program instead of two compiles ~1.5 s less at
    # 106k unknowns. Only the right-hand side, the CG tolerance, the start of the line search
    # and its acceptance rule differ (selected by values, so a vmapped solve runs no branch
    # it does not need).
    jump = (1.0 - Pf) * (displacement - u_init)
    naive = fixed_part + Pf * u_init
    g_init, h_jump = jax.jvp(lambda uu: _full_gradient(model, uu, material, force), (u_init,), (jump,))
    rhs = Pf * (g_init + h_jump)
    # Multigrid: the Newton matrix (block-ELL + V-cycle) is carried through the loop, so that
    # a finishing step can reuse its predecessor's (NEWTON_OVERSOLVE_SAFEGUARD, below).
    multigrid = options.linear_solver == "multigrid"
    struct = jax.ShapeDtypeStruct((u_init.size,), u_init.dtype)
    newton_cg = PreconditionedCG(rtol=options.cg_rtol, max_steps=options.cg_max_steps, failure_rtol=NEWTON_CG_FAILURE)

    def linear_system(u, matrix):
        if matrix is None:
            return _projected_operator(model, u, material, free, options)
        ell, pc = matrix
        return _ell_operator(ell, struct), newton_cg, {"preconditioner": pc}

    # The residual at the cold state (the prescribed values, free components zero) sets the
    # tolerance; it is evaluated in the predictor pass (carried as ``g_cold`` in the loop state:
    # one copy of the residual in the program, below).
    cold = fixed_part

    def cond(state):
        return ~state[4]

    def tolerance(g_cold):
        return jnp.maximum(options.atol, options.rtol * g_cold)

    # The predictor is a starting guess that Newton corrects: solved to the loosest forcing
    # term, not to cg_rtol (an exact predictor cost as many CG iterations as a tangent).
    predictor_rtol = max(NEWTON_FORCING_MAX, options.cg_rtol)

    def body(state):
        # In the predictor pass: u = u_init (the linearisation point), g = the predictor's
        # right-hand side, e a placeholder (its line search evaluates the potential at
        # ``naive``, where it starts, itself: e0_in_loop).
        u, g, step, code, _, cg_max, _, e, matrix, g_prev, fresh, predictor, g_cold = state
        tiny_g = jnp.finfo(u.dtype).tiny
        tol = tolerance(g_cold)
        g_scale = jnp.maximum(g_cold, tiny_g)
        gn = jnp.linalg.norm(g)
        # Inexact Newton: the forcing term (NEWTON_FORCING_MAX), at least the safeguard's
        # share of the tolerance (a finishing step need not go far below it).
        eta_ew = gn / g_scale
        eta_safe = NEWTON_OVERSOLVE_SAFEGUARD * tol / jnp.maximum(gn, tiny_g)
        eta = jnp.clip(jnp.maximum(eta_ew, eta_safe), options.cg_rtol, max(NEWTON_FORCING_MAX, options.cg_rtol))
        eta = jnp.where(predictor, predictor_rtol, eta)
        reused = jnp.asarray(False)
        if multigrid:
            # A finishing step (the safeguard sets its forcing term) reuses the matrix of the
            # step before, when that one was assembled fresh and the residual fell by at least
            # 2 / eta since: the lagged matrix adds a relative error of about 2 |g| / |g_prev|
            # to the step (the Hessian's change along the last step, bounded by its quadratic
            # model error, which is at most |g|), within the forcing term. The residual test
            # after the step decides convergence as always; a lagged step that falls short is
            # followed by one with a fresh matrix.
            reused = fresh & (eta_safe >= eta_ew) & (2.0 * gn <= eta * g_prev) & ~predictor
            # A fresh matrix's spectral estimate starts from the previous one's power iterate
            # (the predictor's from the hierarchy's start vector).
            start = jnp.where(predictor, power_start, matrix[1].power_vector)
            matrix = jax.lax.cond(reused, lambda: matrix, lambda: _multigrid_matrix(model, u, material, free, options, start))
        op, solver, opts = linear_system(u, matrix)
        if isinstance(solver, PreconditionedCG):
            opts = {**opts, "rtol": eta}
        sol = lx.linear_solve(op, -g.reshape(-1), solver, options=opts, throw=False)
        cg_steps, cg_res = _linear_stats(sol)
        # Negative curvature (an indefinite Hessian away from the solution) is not a failure:
        # the Newton loop falls back to a scaled gradient step as with a direct solver.
        negative_curvature = jnp.asarray(sol.stats.get("negative_curvature", False), dtype=bool)
        linear_failed = (cg_res > jnp.maximum(NEWTON_CG_FAILURE, opts.get("rtol", 0.0))) & ~negative_curvature
        d = sol.value.reshape(u.shape)
        gd = jnp.vdot(g, d)
        # Whether this step's matrix is positive definite (u is near a minimum, not a saddle):
        # the dense Cholesky fails (NaN direction) where it is not; CG met no negative
        # curvature; the sparse factorisation says so (CHOLMOD succeeded or the LU's pivots).
        definite = jnp.asarray(sol.stats.get("positive_definite", True), dtype=bool) & ~negative_curvature
        # A round-off-sized Newton correction through an indefinite matrix is no sign of
        # convergence: where the curvature is huge in one direction (a node under a sharp
        # indenter's tip) the correction is tiny while the residual is not, and an LU step heads
        # for the saddle. Such a step is replaced by the scaled gradient step below (as the
        # dense Cholesky's failure does), which moves off it.
        tiny = jnp.linalg.norm(d) <= options.xtol * jnp.linalg.norm(u + d)
        bad = (~jnp.all(jnp.isfinite(d)) | (gd >= 0) | (tiny & ~definite)) & ~predictor
        # Fall back to a Jacobi-scaled gradient step if the Newton direction is unusable.
        scale = jnp.linalg.norm(g) / jnp.maximum(jnp.linalg.norm(op.mv(g.reshape(-1))), 1e-300)
        d = jnp.where(bad, -g * scale, d)
        gd = jnp.vdot(g, d)
        # The predictor's step goes from ``naive`` (the prescribed values, free components
        # from u_init) along its free components, accepted when its energy is not higher.
        u_base = jnp.where(predictor, naive, u)
        d = jnp.where(predictor, Pf * d, d)
        # The potential at u is carried in the loop state (the line search's accepted value).
        # (e_full: the potential at u_base + d, the search's first try; the round-off rule below)
        alpha, accepted, e_new, e_full = armijo_backtracking(potential, u_base, d, gd, e0=e, return_energy=True, compare_only=predictor,
                                                             return_full_step=True, e0_in_loop=predictor)
        # Below the energy's round-off the Armijo test cannot see a Newton step's decrease
        # (|g.d| / 2, the quadratic model's): it refuses the full step or accepts a tiny one on
        # round-off noise, and the solve creeps until max_steps (measured: a sphere at 8 cells
        # per contact radius, nu = 0.45, depth 3 um: correction 1.5e-8 |u|, residual 1.2e-11 N
        # against a tolerance of 6.8e-13 N, 48 accepted steps of alpha = 7e-9). There the
        # residual norm decides instead: the full Newton step through a positive definite matrix
        # is taken when it lowers |g| (a local merit function the energy's round-off does not
        # hide; far from the solution the energy test alone decides, so the solve still heads
        # for a minimum, not a saddle).
        unresolved = ~bad & ~predictor & definite & (alpha < 1.0) & (0.5 * jnp.abs(gd) <= ENERGY_ROUNDOFF * jnp.finfo(u.dtype).eps * jnp.abs(e))
        # The full step's potential is the line search's first try (u_base = u outside the
        # predictor pass). The residual is evaluated in a loop of one or two passes, so that
        # the program holds one copy of it and a vmapped solve evaluates a second one only
        # while a specimen needs it (both branches of a ``lax.cond`` run under vmap): first
        # where the step ends (u + d for an unresolved step, else the line search's point);
        # then, for an unresolved step whose full step is not taken, at the line search's
        # point, and in the predictor pass at the cold state (the tolerance's scale).
        u_ls = jnp.where(accepted, u_base + alpha * d, u_base)
        u_full = u + d
        g_norm = jnp.linalg.norm(g)

        def full_step_taken(g_full):
            return jnp.isfinite(e_full) & (jnp.linalg.norm(g_full) < (1.0 - 1e-4) * g_norm)

        def residual_cond(s):
            i, g0, _ = s
            return (i == 0) | ((i == 1) & (predictor | (unresolved & ~full_step_taken(g0))))

        def residual_body(s):
            i, g0, g1 = s
            first = i == 0
            r = residual(jnp.where(first, jnp.where(unresolved, u_full, u_ls), jnp.where(predictor, cold, u_ls)))
            return i + 1, jnp.where(first, r, g0), jnp.where(first, g1, r)

        n_residuals, g0, g1 = jax.lax.while_loop(residual_cond, residual_body, (jnp.asarray(0, jnp.int32), jnp.zeros_like(g), jnp.zeros_like(g)))
        take_full = unresolved & (n_residuals == 1)
        alpha = jnp.where(take_full, jnp.asarray(1.0, alpha.dtype), alpha)
        accepted = accepted | take_full
        e_new = jnp.where(take_full, e_full, e_new)
        u_new = jnp.where(take_full, u_full, u_ls)
        g_new = jnp.where(unresolved & ~take_full, g1, g0)
        g_cold = jnp.where(predictor, jnp.linalg.norm(g1), g_cold)
        tol = tolerance(g_cold)
        rn = jnp.linalg.norm(g_new)
        step = jnp.where(predictor, step, step + 1)
        finite = jnp.all(jnp.isfinite(u_new)) & jnp.isfinite(rn)
        # Converged: residual below tolerance, or a full Newton step that no longer moves the
        # solution (a displacement correction at round-off level: the residual of an
        # ill-conditioned problem cannot drop further) through a positive definite matrix (a
        # minimum; ~bad excludes the indefinite ones). Such a correction converges whether or
        # not the line search accepted it: its energy decrease (about |g| |d| / 2) is then far
        # below the energy's own round-off, so the Armijo test cannot see it and may refuse
        # every trial step (measured: an 80 deg cone at 11.3 cells per contact radius, a
        # correction of 3e-16 m on |u| = 2e-5 m refused at its first depth, the residual
        # floor 3e-10 N set by thin far-field elements above the tolerance 1e-12 N).
        small_step = ~bad & definite & (jnp.linalg.norm(d) <= options.xtol * jnp.linalg.norm(u_new)) & ~predictor
        # At the round-off floor (ROUNDOFF_STALL_XTOL): a step the energy cannot resolve whose
        # full step does not lower the residual either, a correction of a few xtol and a
        # residual near its tolerance. Without this the solve crept at alpha ~ 1e-9 to max_steps.
        stalled = (unresolved & ~take_full & (jnp.linalg.norm(d) <= ROUNDOFF_STALL_XTOL * options.xtol * jnp.linalg.norm(u_new))
                   & (rn <= ROUNDOFF_STALL_RESIDUAL * tol))
        ok = (rn <= tol) | small_step | stalled
        code = jnp.where(
            ~finite,
            StaticResult.nonfinite,
            jnp.where(ok, StaticResult.successful, jnp.where(~accepted, StaticResult.line_search_failed, StaticResult.max_steps_reached)),
        )
        # A conjugate-gradient solve that did not converge is reported as such (with its
        # iteration count and residual), not taken as a Newton direction.
        code = jnp.where(linear_failed & ~ok, StaticResult.linear_solver_failed, code)
        # After the predictor: converged, or Newton steps to go (its own failures are not final).
        code = jnp.where(predictor, jnp.where(rn <= tol, StaticResult.successful, StaticResult.max_steps_reached), code).astype(jnp.int32)
        done = (code != StaticResult.max_steps_reached) | (step >= options.max_steps)
        # The predictor's matrix counts as fresh, its starting residual being that of the jump.
        return u_new, g_new, step, code, done, jnp.maximum(cg_max, cg_steps), cg_res, e_new, matrix, gn, ~reused, jnp.asarray(False), g_cold

    zero = jnp.asarray(0, jnp.int32)
    if multigrid:
        hierarchy = options.hierarchy
        # The predictor's V-cycle set-up starts its power iteration from the hierarchy's
        # start vector (a zero start is the generic vector alone, as without one).
        power_start = jnp.zeros(u_init.size, u_init.dtype) if hierarchy.power_start is None else jnp.asarray(hierarchy.power_start, u_init.dtype)
        # Placeholder matrix of the right structure for the predictor pass (always rebuilt
        # there): zeros for what depends on the state; the block columns and the hierarchy are
        # the setup's own arrays (zero copies of them cost ~0.2 GB of peak memory at 106k).
        shapes = jax.eval_shape(lambda: _multigrid_matrix(model, u_init, material, free, options, power_start))
        ell0, pc0 = jax.tree_util.tree_map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes)
        ell0 = eqx.tree_at(lambda m: m.cols, ell0, options.layout.cols)
        matrix0 = (ell0, eqx.tree_at(lambda p: (p.fine, p.hierarchy), pc0, (ell0, hierarchy)))
    else:
        matrix0 = None
    state = (u_init, rhs, zero, jnp.asarray(StaticResult.max_steps_reached, jnp.int32), jnp.asarray(False), zero, jnp.zeros((), u_init.dtype),
             jnp.zeros((), u_init.dtype), matrix0, jnp.zeros((), u_init.dtype), jnp.asarray(True), jnp.asarray(True), jnp.zeros((), u_init.dtype))
    u, g, step, code, _, cg_max, cg_res, _, _, _, _, _, _ = jax.lax.while_loop(cond, body, state)
    inverted = model.min_volume_ratio(jnp.asarray(model.rest_points) + u) <= 0
    code = jnp.where((code == StaticResult.successful) & inverted, StaticResult.inverted_elements, code)
    return u, jnp.linalg.norm(g), step, code, cg_max, cg_res


@eqx.filter_custom_jvp
def _equilibrium(material, displacement, force, model, *, free, u_init, options):
    # ``model`` is a differentiated argument: its floating-point array leaves (a contact
    # model's indenter depth) may carry tangents, which the JVP rule takes into the
    # right-hand side of the implicit-function-theorem solve.
    u, rn, steps, code, cg_steps, cg_res = _newton(model, material, displacement, force, free, u_init, options)
    # Diagnostics as floats so they can carry (zero) tangents.
    return u, jnp.stack([rn, steps.astype(u.dtype), code.astype(u.dtype), cg_steps.astype(u.dtype), cg_res])


def _split_model_tangent(model, t_model):
    """``(dynamic, tangent, rebuild)``: the model's leaves that carry a tangent (a list), their
    tangents, and ``rebuild(dynamic) -> model`` with those leaves replaced. Leaves without a
    tangent (connectivity, rest geometry not differentiated) stay closed over, so the JVP
    costs nothing for them."""
    if t_model is None:
        return [], [], lambda _: model
    leaves, treedef = jax.tree_util.tree_flatten(model)
    t_leaves = treedef.flatten_up_to(t_model)
    idx = [i for i, t in enumerate(t_leaves) if t is not None]

    def rebuild(dynamic):
        new = list(leaves)
        for i, v in zip(idx, dynamic):
            new[i] = v
        return jax.tree_util.tree_unflatten(treedef, new)

    return [leaves[i] for i in idx], [t_leaves[i] for i in idx], rebuild


@_equilibrium.def_jvp
def _equilibrium_jvp(primals, tangents, *, free, u_init, options):
    material, displacement, force, model = primals
    t_material, t_displacement, t_force, t_model = tangents
    u, info = _equilibrium(material, displacement, force, model, free=free, u_init=u_init, options=options)

    def fill(t, p):
        # a None field of the material (Material.pre_stretch_y of an equibiaxial one) stays None
        return jax.tree_util.tree_map(lambda tt, pp: None if pp is None else (jnp.zeros_like(jnp.asarray(pp, dtype=u.dtype)) if tt is None else tt),
                                      t, p, is_leaf=lambda z: z is None)

    P = free.astype(u.dtype)
    t_material = fill(t_material, material) if t_material is not None else jax.tree_util.tree_map(lambda p: jnp.zeros_like(jnp.asarray(p, dtype=u.dtype)), material)
    t_disp = jnp.zeros_like(u) if t_displacement is None else t_displacement
    t_f = jnp.zeros_like(u) if t_force is None else t_force
    material_f = jax.tree_util.tree_map(lambda p: jnp.asarray(p, dtype=u.dtype), material)
    model_dyn, t_model_dyn, rebuild = _split_model_tangent(model, t_model)
    t_u_fixed = (1.0 - P) * t_disp
    _, dgrad = jax.jvp(
        lambda uu, mm, ff, md: _full_gradient(rebuild(md), uu, mm, ff),
        (u, material_f, force, model_dyn),
        (t_u_fixed, t_material, t_f, t_model_dyn),
    )
    op, solver, opts = _projected_operator(model, u, material_f, free, options, tangent=True)
    # throw=False: a failed primal solve (NaN) gives NaN tangents instead of a crash, so an
    # optimiser can reject the step; the primal result code still reports the failure.
    # An iterative tangent (or, transposed, adjoint) solve that does not reach
    # TANGENT_CG_FAILURE returns NaN (PreconditionedCG.failure_rtol), never a wrong tangent.
    # jax.lax.custom_linear_solve (symmetric) carries the solve into reverse mode: lineax's
    # own transpose rule raises on a NaN cotangent whatever ``throw`` says, which would turn a
    # failed trial point of a fit into a crash instead of a NaN it can reject.
    def solve(_, b):
        return lx.linear_solve(op, b, solver, options=opts, throw=False).value

    w = jax.lax.custom_linear_solve(op.mv, (-P * dgrad).reshape(-1), solve, symmetric=True).reshape(u.shape)
    # A primal solve that did not succeed (max_steps reached, line search failed, inverted
    # element, non-finite, linear solver failed: result code != 0) is not an equilibrium: the
    # implicit-function-theorem tangent there would be a silently wrong derivative. Scaling by
    # NaN (a multiplication, so that it is linear in the tangents and transposes to a NaN
    # cotangent in reverse mode too; a ``where`` with a NaN constant would drop out of the
    # transpose) makes every tangent and every gradient of a failed solve NaN.
    failed = jnp.where(info[2] == StaticResult.successful, jnp.asarray(1.0, u.dtype), jnp.asarray(jnp.nan, u.dtype))
    t_u = (P * w + t_u_fixed) * failed
    return (u, info), (t_u, jnp.zeros_like(info))


# --------------------------------------------------------------------------- entry
def _solve_program(model, material, bc, u_init, options: _Options):
    # One range check of the material here instead of one in every energy evaluation.
    material = model.checked(material)
    free = jnp.asarray(bc.free_mask)
    u, info = _equilibrium(material, bc.displacement, bc.force, model, free=free, u_init=u_init, options=options)
    code = info[2].astype(jnp.int32)
    x = jnp.asarray(model.rest_points) + u
    energy, grad = jax.value_and_grad(_potential, argnums=1)(model, u, material, bc.force)
    reaction = (1.0 - free.astype(u.dtype)) * grad
    return StaticSolution(
        displacement=u,
        reaction=reaction,
        energy=energy,
        residual_norm=info[0],
        steps=info[1].astype(jnp.int32),
        result=code,
        min_volume_ratio=model.min_volume_ratio(x),
        linear_steps=info[3].astype(jnp.int32),
        linear_residual=info[4],
    )


class _StaticPart:
    """The non-array part of ``_solve``'s arguments (``eqx.partition``'s second half), hashable
    as ``eqx.filter_jit`` holds it: by its pytree structure and static leaves, so that a
    static argument of ``jax.jit`` compiles one program per configuration."""

    def __init__(self, tree):
        self.tree = tree
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        self._key = (treedef, tuple(leaves))
        self._hash = hash(self._key)

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return isinstance(other, _StaticPart) and self._key == other._key


def _solve_combined(dynamic, static: _StaticPart):
    return _solve_program(*eqx.combine(dynamic, static.tree))


#: ``_solve_combined`` compiled with the XLA options of the ``"static"`` program kind on its own
#: (:class:`difftissue.xla_options.ProgramJit`), inlined into an outer program.
_SOLVE_JIT = ProgramJit(_solve_combined, "static", static_argnums=1)

#: What ``equinox`` puts before the message of an ``eqx.error_if`` raised inside a program.
_EQX_ERROR_TAG = "_EquinoxRuntimeError: "


def _equinox_message(error: BaseException) -> str | None:
    """The message of an ``eqx.error_if`` that failed inside a program (the line after
    ``_EQX_ERROR_TAG`` in JAX's runtime error), None when ``error`` carries none."""
    text = str(error)
    if _EQX_ERROR_TAG not in text:
        return None
    return text.split(_EQX_ERROR_TAG, 1)[1].split("\n", 1)[0].strip()


def named_runtime_error(error: BaseException) -> Exception | None:
    """The named error for a runtime error raised by an ``equinox.error_if`` inside a
    library-compiled program called with concrete values: a static solve's failure
    :class:`~difftissue.errors.ConvergenceError`, a material check's
    :class:`~difftissue.errors.MaterialError` / :class:`~difftissue.errors.ModelRangeError`
    (:func:`~difftissue.models.material_error_type`), any other check
    ``equinox.EquinoxRuntimeError`` with its message alone (not the callback's traceback and
    equinox's advice to use ``filter_jit``); None when ``error`` carries no equinox message."""
    message = _equinox_message(error)
    if message is None:
        return None
    if message in _MESSAGES[1:]:
        return ConvergenceError(message)
    kind = material_error_type(message)
    return kind(message) if kind is not None else eqx.EquinoxRuntimeError(message)


def _solve(model, material, bc, u_init, options: _Options):
    """One static solve compiled as its own program (one per model structure, shapes and
    solver configuration: ``eqx.filter_jit``'s rule, array leaves traced, the rest static) with
    the XLA options of the ``"static"`` program kind on a CPU
    (:mod:`difftissue.xla_options`: ``eqx.filter_jit`` takes no compiler options). Inside an
    outer ``jit`` it is inlined there, with the outer program's options. A failed
    ``eqx.error_if`` (a traced material out of range) raises ``equinox.EquinoxRuntimeError``,
    as under ``eqx.filter_jit``."""
    dynamic, static = eqx.partition((model, material, bc, u_init, options), eqx.is_array)
    try:
        sol = _SOLVE_JIT(dynamic, _StaticPart(static))
        if isinstance(sol.result, jax.Array) and not isinstance(sol.result, jax.core.Tracer):
            sol.result.block_until_ready()  # a runtime error raised here, as eqx.filter_jit does
        return sol
    except jax.errors.JaxRuntimeError as err:
        message = _equinox_message(err)
        if message is None:
            raise
        raise eqx.EquinoxRuntimeError(message) from None


def solve_static(
    model: ElasticModel,
    material: Material,
    bc: BoundaryConditions,
    *,
    rtol: float = 1e-10,
    atol: float = 0.0,
    xtol: float = 1e-8,
    max_steps: int = 50,
    linear_solver: str = "auto",
    cg_rtol: float = 1e-10,
    cg_max_steps: int | None = None,
    initial_displacement=None,
    load_steps: int = 1,
    throw: bool = True,
    preconditioner_material: Material | None = None,
    setup: "SolverSetup | None" = None,
) -> StaticSolution:
    """Static equilibrium of ``model`` under ``bc``, differentiable in ``material`` and ``bc``.

    Args:
        model: an :class:`~difftissue.models.ElasticModel` (see :func:`~difftissue.models.make_model`).
        material: a :class:`~difftissue.materials.Material` (scalars or one value per region).
        bc: prescribed displacements [m] and nodal forces [N]; they must remove every
            rigid-body mode (checked when values are concrete: :class:`RigidModeError`).
        rtol, atol: residual tolerance ``|grad Pi|_free <= max(atol [N], rtol * |grad Pi|_start)``
            (``atol`` may be a 0-d array, also a traced one).
        xtol: also converged when a full Newton correction is below ``xtol * |u|`` (2-norms)
            and that step's matrix was positive definite (Cholesky succeeded, CG met no
            negative curvature, the sparse factorisation's pivots were positive): the residual
            of an ill-conditioned problem stalls at round-off level, and with Newton's
            quadratic convergence the remaining error is far below that correction. This holds
            also when the line search refuses the correction (its energy decrease is below the
            energy's round-off there). A tiny
            correction through an indefinite matrix (a node balanced on a sharp indenter's
            tip: the correction is small because the curvature is huge, not because the
            residual is at round-off) is replaced by a scaled gradient step, never accepted.
            A solve stalled at its round-off floor also converges: a step below the energy's
            round-off whose full step does not lower the residual, with a correction within
            ``ROUNDOFF_STALL_XTOL`` (4) ``* xtol * |u|`` and a residual within
            ``ROUNDOFF_STALL_RESIDUAL`` (100) times the tolerance.
        max_steps: Newton steps allowed.
        linear_solver: ``"multigrid"`` (conjugate gradients preconditioned by a
            smoothed-aggregation multigrid V-cycle, applied in JAX: jit, vmap, GPU; see
            :mod:`~difftissue.solvers.multigrid`), ``"sparse"`` (sparse direct: Cholesky of
            the assembled CSR Hessian on the host via ``pure_callback``, LU where it is not
            positive definite), ``"dense"`` (Cholesky of the assembled Hessian), ``"cg"``
            (matrix-free Jacobi-preconditioned CG) or ``"auto"``: :func:`auto_linear_solver`.
        cg_rtol, cg_max_steps: CG tolerance on the relative 2-norm of the true residual and
            step limit (default 500 for multigrid, 10 x unknowns for Jacobi).
        preconditioner_material: the material the multigrid hierarchy is built for when
            ``material`` is traced (a fit): the start values are a good choice. Default:
            ``material`` when concrete, else E = 1 Pa, nu = 0.45 (only the convergence speed
            depends on it, never the answer).
        setup: a :class:`SolverSetup` from :func:`solver_setup` (the linear solver, sparsity
            pattern, block layout and multigrid hierarchy of this model and these fixed DOFs).
            Default: built now, which needs the connectivity and ``bc.fixed`` concrete. Pass
            one built beforehand to call ``solve_static`` inside ``jit`` with the model and
            the boundary conditions as traced arguments: the compiled program then holds no
            mesh-sized constants. ``linear_solver`` must then be ``"auto"`` or the setup's;
            ``preconditioner_material`` is ignored (the setup's hierarchy is used).
        initial_displacement: ``(N, 3)`` starting guess [m] for the free components.
        load_steps: apply the prescribed displacements and forces in this many equal
            increments, each solve starting from the previous one (for large deformations
            whose first guess would invert elements). Only the last equilibrium is
            differentiated; the intermediate ones just provide its starting guess.
        throw: raise :class:`~difftissue.errors.ConvergenceError` (outside jit) or an
            ``equinox`` runtime error (inside jit) when the solve fails; with
            ``throw=False`` inspect ``result`` / ``converged`` instead.

    Returns:
        A :class:`StaticSolution`. ``jax.grad`` / ``jax.jvp`` through ``displacement``,
        ``reaction`` and ``energy`` use one extra linear solve (implicit differentiation).
    """
    if setup is None:
        setup = solver_setup(model, material, bc, linear_solver=linear_solver, preconditioner_material=preconditioner_material)
    else:
        if not isinstance(setup, SolverSetup):
            raise ModelError(f"setup must be a SolverSetup (see solver_setup), got {type(setup).__name__}")
        if not isinstance(model, ElasticModel):
            raise ModelError(f"model must be an ElasticModel (see difftissue.models.make_model), got {type(model).__name__}")
        if setup.n_nodes != model.n_nodes:
            raise ModelError(f"setup was built for {setup.n_nodes} nodes, the model has {model.n_nodes}")
        if linear_solver not in ("auto", setup.linear_solver):
            raise ModelError(f"linear_solver={linear_solver!r} but the setup was built for {setup.linear_solver!r}")
        _validate_values(bc, model.n_nodes)
        model.region_values(material)  # range checks (raise now when concrete)
    n = model.n_nodes
    linear_solver, pattern, layout, hierarchy = setup.linear_solver, setup.pattern, setup.layout, setup.hierarchy
    default_steps = 500 if linear_solver == "multigrid" else 10 * 3 * n
    # atol may be an array (a mesh-derived floor passed as an argument of a compiled program)
    atol = jnp.asarray(atol, dtype=float) if eqx.is_array(atol) else float(atol)
    options = _Options(float(rtol), atol, float(xtol), int(max_steps), linear_solver, float(cg_rtol), int(cg_max_steps or default_steps), pattern, layout, hierarchy)
    # Python floats would be static under jit (a recompile per value): make every leaf an array.
    material = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)
    if _is_concrete(material):
        # Range-checked here, on the host (MaterialError / ModelRangeError), so that the compiled
        # solve carries no ``equinox.error_if`` callback for it: JAX never writes a program with
        # a host callback to its persistent compilation cache. Traced values keep the checks.
        material = model.checked(material)
    u_init = jnp.zeros((n, 3)) if initial_displacement is None else jnp.asarray(initial_displacement, dtype=float)
    if int(load_steps) < 1:
        raise ModelError(f"load_steps must be >= 1, got {load_steps}")
    for k in range(1, int(load_steps)):
        frac = k / int(load_steps)
        partial = BoundaryConditions(bc.fixed, bc.displacement * frac, bc.force * frac)
        step = _solve(model, material, jax.lax.stop_gradient(partial), u_init, options)
        if throw and not isinstance(step.result, jax.core.Tracer) and int(step.result) != 0:
            raise ConvergenceError(f"load increment {k}/{load_steps}: {_MESSAGES[int(step.result)]}")
        u_init = jax.lax.stop_gradient(step.displacement)
    sol = _solve(model, material, bc, u_init, options)
    if throw:
        code = sol.result
        if isinstance(code, jax.core.Tracer):
            sol = eqx.tree_at(lambda s: s.displacement, sol, eqx.branched_error_if(sol.displacement, code != 0, code, _MESSAGES))
        elif int(code) == StaticResult.linear_solver_failed:
            raise LinearSolverError(
                f"{_MESSAGES[int(code)]} (Newton step {int(sol.steps)}: {int(sol.linear_steps)} CG iterations, "
                f"relative residual {float(sol.linear_residual):.3g} > {NEWTON_CG_FAILURE:g})"
            )
        elif int(code) != 0:
            raise ConvergenceError(f"{_MESSAGES[int(code)]} (steps {int(sol.steps)}, residual {float(sol.residual_norm):.3g} N, min V/V0 {float(sol.min_volume_ratio):.3g})")
    return sol


class SolverSetup(eqx.Module):
    """What :func:`solve_static` derives from a mesh before it solves (:func:`solver_setup`):
    the linear solver chosen, the CSR pattern (``"sparse"``), the block-ELL layout and the
    multigrid hierarchy (``"multigrid"``). A pytree of arrays (the pattern is static): passed
    to a jitted function as an argument it stays an argument, not a constant of the program.

    Attributes:
        linear_solver: one of :data:`LINEAR_SOLVERS`.
        n_nodes: nodes of the model it was built for.
        pattern: the CSR pattern (``"sparse"``; static, hashed by content), else None.
        layout: the :class:`~difftissue.solvers.multigrid.SparseLayout` (``"multigrid"``), else None.
        hierarchy: the :class:`~difftissue.solvers.multigrid.MultigridHierarchy` (``"multigrid"``), else None.
    """

    linear_solver: str = eqx.field(static=True)
    n_nodes: int = eqx.field(static=True)
    pattern: Any = eqx.field(static=True, default=None)
    layout: Any = None
    hierarchy: Any = None


def solver_setup(model: ElasticModel, material: Material, bc: BoundaryConditions, *, linear_solver: str = "auto",
                 preconditioner_material: Material | None = None, material_is_traced: bool = False) -> SolverSetup:
    """The :class:`SolverSetup` :func:`solve_static` builds for ``model``, ``material`` and
    ``bc`` (same arguments), for reuse: ``solve_static(..., setup=solver_setup(...))``.

    The connectivity and ``bc.fixed`` must be concrete for ``"sparse"`` and ``"multigrid"``
    (:class:`~difftissue.errors.ModelError` otherwise); the rigid-mode check runs here when
    ``bc.fixed`` is concrete. ``material_is_traced``: build the multigrid hierarchy as
    ``solve_static`` does for a traced ``material`` (for ``preconditioner_material``, or
    E = 1 Pa, nu = 0.45 in ``material``'s shape), so that a setup built before a ``jit`` gives
    the same iterations as one built while tracing it."""
    if not isinstance(model, ElasticModel):
        raise ModelError(f"model must be an ElasticModel (see difftissue.models.make_model), got {type(model).__name__}")
    n = model.n_nodes
    _validate_values(bc, n)
    if not isinstance(bc.fixed, jax.core.Tracer) and not getattr(model, "stiffness_is_definite", False):
        check_rigid_modes(model.rest_points, bc.fixed)
    if material_is_traced:  # its values are not those of the solves: only its structure is used
        material = _reference_material(material, preconditioner_material, True)
    model.region_values(material)  # range checks (raise now when concrete)
    node_arrays = _term_nodes(model, material)
    concrete_nodes = not any(isinstance(a, jax.core.Tracer) for a in node_arrays)
    concrete_fixed = not isinstance(bc.fixed, jax.core.Tracer)
    if linear_solver == "auto":
        linear_solver = auto_linear_solver(3 * n, concrete=concrete_nodes and concrete_fixed)
    if linear_solver not in LINEAR_SOLVERS:
        raise ModelError(f"linear_solver must be 'auto' or one of {LINEAR_SOLVERS}, got {linear_solver!r}")
    pattern = layout = hierarchy = None
    if linear_solver in ("sparse", "multigrid"):
        if not concrete_nodes or (linear_solver == "multigrid" and not concrete_fixed):
            raise ModelError(
                f"linear_solver={linear_solver!r} needs the model's element connectivity and the fixed DOFs as concrete arrays "
                "(close over the model and boundary mask instead of passing them as traced arguments, or pass a setup "
                "built beforehand: solver_setup), or use 'cg'"
            )
    if linear_solver == "sparse":
        pattern = sparse_pattern(node_arrays, n)
    if linear_solver == "multigrid":
        layout, hierarchy = _multigrid_for(model, material, bc.fixed, node_arrays, preconditioner_material, material_is_traced)
    return SolverSetup(linear_solver, n, pattern, layout, hierarchy)


def _term_nodes(model: ElasticModel, material):
    """The node arrays ``[(E_t, k_t), ...]`` of ``model.terms(material)``, the terms traced
    abstractly (``jax.eval_shape``): their parameters are not needed here, and evaluated
    eagerly they cost one compiled program per operation (~30 at 106k unknowns, ~1 s CPU).
    Where a node array is itself computed in ``terms`` (it is then a tracer of that
    abstract trace), or where ``terms`` needs the material's values, the terms are evaluated
    as they are called."""
    nodes = []

    def collect(m):
        nodes.extend(t.nodes for t in model.terms(m))

    try:
        jax.eval_shape(collect, material)
    except jax.errors.ConcretizationTypeError:
        nodes = [None]
    if any(a is None or isinstance(a, jax.core.Tracer) for a in nodes):
        nodes = [t.nodes for t in model.terms(material)]
    return nodes


#: The linear solvers of :func:`solve_static`.
LINEAR_SOLVERS = ("multigrid", "sparse", "dense", "cg")
#: ``"auto"`` picks the dense Cholesky up to this many unknowns (3 x nodes), multigrid above.
AUTO_DENSE_MAX = 3_000


def prediction_rtol(rtol: float, xtol: float) -> float:
    """Relative precision [-] claimed for a quantity (a force, a displacement, an opening width)
    computed from static solves converged to the residual tolerance ``rtol`` and the Newton
    correction tolerance ``xtol`` of :func:`solve_static`: ``max(rtol, xtol)``. A fit treats
    residuals within this precision of the data as the forward model's round-off (it stops
    there: :meth:`difftissue.fit.problem.FitProblem.precision_floor`)."""
    return max(float(rtol), float(xtol))


def auto_linear_solver(n_unknowns: int, *, concrete: bool = True) -> str:
    """The linear solver ``linear_solver="auto"`` uses for ``n_unknowns`` (3 x nodes).

    Rule (measured with ``benchmarks/static.py``, tables in docs/performance.md): dense
    Cholesky up to :data:`AUTO_DENSE_MAX` unknowns, multigrid-preconditioned CG above (faster
    from a few thousand unknowns on, and the only solver whose cost grows about linearly);
    Jacobi CG above that size when the connectivity or the fixed DOFs are traced (no pattern
    can be built). Both are XLA programs: they batch under ``vmap``, shard and run on a GPU.

    The sparse direct Cholesky (``"sparse"``) is faster than the dense one from a few hundred
    unknowns on (5-10x at 600-1,200 unknowns, measured) but it is a host callback: under
    ``vmap`` it factorises one specimen after the other, and inside a sharded program it
    deadlocks XLA's CPU collectives. So it is never chosen automatically; pass it for single
    CPU fits of a few hundred to a few thousand unknowns.
    """
    if n_unknowns <= AUTO_DENSE_MAX:
        return "dense"
    return "multigrid" if concrete else "cg"


def _reference_material(material, preconditioner_material, material_is_traced=False):
    """The material the multigrid hierarchy is built for, with E normalised to a largest value
    of 1 Pa (the preconditioner rescales to the current stiffness): a new E, the usual change
    in a loop or a fit, then reuses the cached hierarchy."""
    if material_is_traced or any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(material)):
        if preconditioner_material is None:
            shape = jnp.shape(material.youngs_modulus)
            return Material(np.ones(shape), np.full(shape, 0.45), np.zeros(shape), np.full(shape, 1000.0), np.ones(shape))
        material = preconditioner_material
    E = np.asarray(material.youngs_modulus, dtype=float)
    return eqx.tree_at(lambda m: m.youngs_modulus, material, E / np.max(E))


def _multigrid_for(model, material, fixed, node_arrays, preconditioner_material, material_is_traced=False):
    """The block-ELL layout (cached per mesh) and the multigrid hierarchy (cached per mesh,
    fixed DOFs and reference material) of ``model``'s projected Hessian."""
    # One hash of the connectivity for both caches (a direct-call loop on a big mesh hashes it per call).
    arrays = [np.asarray(a) for a in node_arrays]
    mesh_key = cache_key(np.asarray(model.n_nodes), *arrays)
    layout = sparse_layout(arrays, model.n_nodes, key=mesh_key)
    ref = jax.tree_util.tree_map(lambda v: np.asarray(v, dtype=float), _reference_material(material, preconditioner_material, material_is_traced))
    free = 1.0 - np.asarray(fixed, dtype=float).reshape(-1)
    rest = np.asarray(model.rest_points, dtype=float)
    key = cache_key(np.frombuffer(mesh_key.encode(), np.uint8), free, rest, *jax.tree_util.tree_leaves(ref))
    hierarchy = multigrid_cached(key)
    if hierarchy is None:
        A = _reference_matrix(model, jax.tree_util.tree_map(np.asarray, ref), layout, np.asarray(free)).to_scipy()
        hierarchy = multigrid_setup(A, rest, free, key=key)
    return layout, hierarchy


def _reference_matrix(model, material, layout, free):
    """The block-ELL matrix ``P H P + (I - P)`` at rest, computed now (host arrays), also when
    called while ``solve_static`` is being traced: the program is lowered and compiled on its
    own and its executable called with concrete arrays."""
    # The (concrete) material is closed over: its range checks then run now, in Python,
    # instead of as equinox runtime checks, which misfire in a program executed while an
    # outer program is being traced.
    # A model field traced in the caller (an indenter depth inside a fit's protocol) is taken
    # as zero for the reference: the undeformed, contact-free state.
    model = jax.tree_util.tree_map(lambda v: np.zeros(v.shape, v.dtype) if isinstance(v, jax.core.Tracer) else v, model)
    dynamic, static = eqx.partition((model, layout, free), eqx.is_array)

    def assemble(dynamic):
        model, layout, free = eqx.combine(dynamic, static)
        x = jnp.asarray(model.rest_points, dtype=free.dtype)
        return _assemble_ell(layout, model, x, material, free).data

    data = np.asarray(jax.jit(assemble).lower(dynamic).compile()(dynamic))
    if not np.all(np.isfinite(data)):
        raise ModelError("linear_solver='multigrid': the reference stiffness at rest is not finite (a traced model field taken as zero?); use linear_solver='sparse'")
    return BlockEllMatrix(data, np.asarray(layout.cols))
