"""Static condensation of a linear elastic body onto its candidate contact nodes.

A rigid indenter pressing on a *linear* elastic body touches only a few surface nodes. The
body's response at those nodes is its compliance ``G = C K^{-1} C^T`` (``K`` the stiffness
with the boundary conditions applied, ``C`` picks the candidate degrees of freedom), so the
contact problem can be solved on the candidates alone:

    minimise  1/2 u_C^T S u_C + sum_i kappa_i / 2 max(p_i(x_C), 0)^2,   S = G^{-1},

and the full displacement field is recovered as ``u = K^{-1} C^T S u_C``. This is exact for a
quadratic elastic energy (``fem_linear``): the same equilibrium as the full solve, to solver
tolerance. One sparse factorisation of ``K`` and ``m`` solves (``m`` = 3 x candidates) per
material replace a factorisation per Newton step per depth, which is what makes fitting a
simulated force-depth curve on a few-thousand-tet specimen take seconds.

Memory (the sparse solver): the rows ``Z`` (``m x 3N`` float64, dense: 0.56 GB for the
458 rows of a 152,000-unknown block) are solved in one host callback with one factorisation,
the unit right-hand sides formed and solved ``sparse.COLUMN_CHUNK`` at a time into the result
(no ``m x 3N`` one-hot matrix, no transposed copies), so a material's solve holds ``Z`` about
twice (the callback's result and JAX's copy of it) besides the factor. The derivative's
``dK Z^T`` is formed in blocks of rows (``ROW_BLOCK_BYTES``) and its solve (``dZ``) also in
chunks.

Derivatives with respect to the material come from ``dZ = -K^{-1} dK Z`` with
``Z = K^{-1} C^T`` (one more solve with the same factorisation per tangent, a custom JVP that
JAX transposes for reverse mode), the contact equilibrium on the candidates is differentiated
implicitly by :func:`~difftissue.solvers.static.solve_static`.

For a one-region ``fem_linear`` body without pre-stretch, ``linear_solver="spectral"`` takes
``Z`` and ``G`` from one generalised eigendecomposition of the mesh, shared by every material
(:mod:`difftissue.solvers.spectral`): two matrix products per material, no factorisation.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import lineax as lx
import numpy as np

from ..errors import ModelError
from ..models import ElasticModel, ElementTerm
from .sparse import _factor_solve, _Rows, sparse_pattern
from .spectral import spectral_decomposition, spectral_response_columns
from .static import AUTO_DENSE_MAX, SolverSetup, _element_data, _Options, _projected_operator, armijo_backtracking

__all__ = ["linear_response_columns", "condensation_setup", "CondensedParameters", "CondensedContactModel", "solve_condensed_contact"]


def _options_for(model: ElasticModel, material, linear_solver: str, setup: SolverSetup | None = None) -> _Options:
    n = model.n_nodes
    if setup is not None:
        if not isinstance(setup, SolverSetup) or setup.linear_solver not in ("dense", "sparse") or setup.n_nodes != n:
            raise ModelError("setup must be the condensation_setup of this model (a 'dense' or 'sparse' SolverSetup of its nodes)")
        if linear_solver not in ("auto", setup.linear_solver):
            raise ModelError(f"linear_solver={linear_solver!r} but the setup was built for {setup.linear_solver!r}")
        return _Options(0.0, 0.0, 0.0, 0, setup.linear_solver, 0.0, 0, setup.pattern)
    if linear_solver == "auto":
        linear_solver = "dense" if 3 * n <= AUTO_DENSE_MAX else "sparse"  # many columns, one factorisation
    if linear_solver not in ("dense", "sparse"):
        raise ModelError(f"condensation needs a direct linear solver ('dense', 'sparse' or 'spectral'), got {linear_solver!r}")
    pattern = sparse_pattern([t.nodes for t in model.terms(material)], n) if linear_solver == "sparse" else None
    return _Options(0.0, 0.0, 0.0, 0, linear_solver, 0.0, 0, pattern)


def condensation_setup(model: ElasticModel, material, *, linear_solver: str = "auto") -> SolverSetup:
    """What :func:`linear_response_columns` derives from ``model``'s mesh before it solves, as a
    :class:`~difftissue.solvers.static.SolverSetup` (every field static, no array): the
    direct solver (``"auto"``: dense up to ``AUTO_DENSE_MAX`` unknowns, sparse above) and, for
    ``"sparse"``, the CSR pattern (hashed by content); for ``"spectral"`` nothing but the name
    (its arrays are the decomposition's). Needs the connectivity concrete; ``material`` only
    for its structure (values unused). With it, ``linear_response_columns(..., setup=...)``
    runs with the mesh, the boundary mask and the degrees of freedom as traced arguments of a
    compiled program."""
    if linear_solver == "spectral":
        return SolverSetup("spectral", model.n_nodes)
    options = _options_for(model, material, linear_solver)
    return SolverSetup(options.linear_solver, model.n_nodes, options.pattern)


#: Bytes of the gathered rows of ``Z`` that the derivative's ``dK Z^T`` handles at a time
#: (:func:`_stiffness_derivative_rows`): ``Z[:, element dofs]`` is ``m x E x 12`` (8 bytes
#: each), about 12 GB for the m = 8 sphere block's 458 rows and 280,000 tets if formed whole.
ROW_BLOCK_BYTES = 2**28


def _host_columns(pattern, data, dofs):
    """Callback body: the rows ``Z[j] = K^{-1} e_{dofs[j]}`` ``(m, n)`` of the CSR matrix
    ``data``, one factorisation, the unit right-hand sides formed and solved
    ``sparse.COLUMN_CHUNK`` at a time into the result (:class:`~difftissue.solvers.sparse._Rows`)."""
    data = np.asarray(data)
    x, _ = _factor_solve(pattern, data, _Rows(pattern.n, dofs=np.asarray(dofs), dtype=data.dtype))
    return x.astype(data.dtype, copy=False)  # (NaN where the matrix is not finite)


def _solve_columns(material, model, free, dofs, options):
    op, solver, opts = _projected_operator(model, jnp.zeros((model.n_nodes, 3)), material, jnp.asarray(free), options)
    n3 = 3 * model.n_nodes
    if options.linear_solver == "sparse":
        # One host callback: no dense one-hot right-hand sides, no transposed copies; the
        # result (m, n) is about the only Z-sized array (plus JAX's copy of it).
        data = opts["csr_data"]
        shape = jax.ShapeDtypeStruct((dofs.size, n3), data.dtype)
        return jax.pure_callback(functools.partial(_host_columns, options.pattern), shape, data, jnp.asarray(dofs), vmap_method="sequential")
    rhs = jnp.zeros((dofs.size, n3)).at[jnp.arange(dofs.size), jnp.asarray(dofs)].set(1.0)
    return jax.vmap(lambda b: lx.linear_solve(op, b, solver, options=opts, throw=False).value)(rhs)


def _stiffness_derivative_rows(Z, d_hess, dofs_of, P):
    """``-(dK Z^T)^T`` projected on the free components (``(m, n)``): the rows of ``Z``
    times the element Hessians' derivative ``d_hess`` (``[(E, 12, 12)]``, gathers and
    scatters), in blocks of rows whose gather ``Z[rows, element dofs]`` stays within
    ``ROW_BLOCK_BYTES`` (a scan that writes each block into the result)."""
    m = Z.shape[0]

    def rows_of(Zb):
        Rb = jnp.zeros_like(Zb)
        for dh, d in zip(d_hess, dofs_of):
            Rb = Rb.at[:, d].add(jnp.einsum("eij,mej->mei", dh, Zb[:, d]))
        return Rb * (-P)[None, :]

    per_row = max(1, sum(int(np.prod(d.shape)) for d in dofs_of)) * Z.dtype.itemsize
    block = int(min(m, max(1, ROW_BLOCK_BYTES // per_row)))
    if block >= m:
        return rows_of(Z)
    count = -(-m // block)
    # the last block starts at m - block (it rewrites rows of the one before: the same values)
    starts = jnp.minimum(jnp.arange(count) * block, m - block)

    def body(R, start):
        Rb = rows_of(jax.lax.dynamic_slice_in_dim(Z, start, block, 0))
        return jax.lax.dynamic_update_slice_in_dim(R, Rb, start, 0), None

    R, _ = jax.lax.scan(body, jnp.zeros_like(Z), starts)
    return R


@eqx.filter_custom_jvp
def _columns(material, *, model, free, dofs, options):
    Z = _solve_columns(material, model, free, dofs, options)
    G = Z[:, jnp.asarray(dofs)]
    return Z, 0.5 * (G + G.T)


@_columns.def_jvp
def _columns_jvp(primals, tangents, *, model, free, dofs, options):
    (material,) = primals
    (t_material,) = tangents
    Z, G = _columns(material, model=model, free=free, dofs=dofs, options=options)
    material = jax.tree_util.tree_map(lambda p: jnp.asarray(p, dtype=Z.dtype), material)
    t_material = jax.tree_util.tree_map(
        lambda t, p: None if p is None else (jnp.zeros_like(p) if t is None else t), t_material, material, is_leaf=lambda z: z is None
    )
    P = jnp.asarray(free, dtype=Z.dtype).reshape(-1)
    x0 = jnp.asarray(model.rest_points, dtype=Z.dtype)
    N = model.n_nodes

    # dK: the derivative of the element Hessians at rest along the material tangent (one
    # forward pass over the elements), applied to every row of Z by gathers and scatters.
    # (Differentiating the Hessian-vector product H(x0; material) z once per row costs a
    # second-order pass over the whole mesh per row: several times slower.)
    dofs_of = [d for _, d in _element_data(model, x0, material)]
    _, d_hess = jax.jvp(lambda m: [h for h, _ in _element_data(model, x0, m)], (material,), (t_material,))
    R = _stiffness_derivative_rows(Z, d_hess, dofs_of, P)  # rows: -(dK Z^T)^T, in blocks of rows
    # dG = -C K^-1 dK K^-1 C^T = -Z dK Z^T: no solve. dZ needs one (a factorisation in one
    # host call for all rows, solved in chunks: sparse._Rows); when only G is used downstream
    # the solve is dead code and removed.
    dG = Z @ R.T
    op, solver, opts = _projected_operator(model, jnp.zeros((N, 3), Z.dtype), material, jnp.asarray(free), options)
    dZ = jax.vmap(lambda r: lx.linear_solve(op, r, solver, options=opts, throw=False).value)(R)
    return (Z, G), (dZ, 0.5 * (dG + dG.T))


def linear_response_columns(model: ElasticModel, material, free, dofs, *, linear_solver: str = "auto", decomposition=None, setup=None):
    """Rows ``Z = C K^{-1}`` (``(m, 3N)``; ``K`` symmetric, so ``Z^T = K^{-1} C^T``) of the inverse
    stiffness at rest for the degrees of freedom ``dofs``, and the compliance ``G = Z C^T``.

    ``K`` is the Hessian of ``model``'s energy at the rest state with the prescribed components
    (``free == False``) eliminated; for ``fem_linear`` it is the stiffness matrix, for the
    other models their small-strain linearisation. Column ``j`` of ``Z^T`` is the displacement
    field [m] produced by a unit force [N] on degree of freedom ``dofs[j]``.

    Args:
        model: an :class:`~difftissue.models.ElasticModel` with concrete connectivity.
        material: its material (differentiable: forward and reverse mode).
        free: ``(N, 3)`` bool, True on free components (``BoundaryConditions.free_mask``).
        dofs: ``(m,)`` flat degree-of-freedom indices ``3 node + component``; they must be free.
        linear_solver: ``"dense"``, ``"sparse"`` (sparse Cholesky, one factorisation for all
            columns), ``"auto"`` (dense up to ``AUTO_DENSE_MAX`` = 3,000 unknowns, sparse above)
            or ``"spectral"`` (no factorisation: products with the eigenvectors of
            ``decomposition``; a one-region ``fem_linear`` body without pre-stretch only, see
            :mod:`difftissue.solvers.spectral`).
        decomposition: for ``"spectral"``, the :class:`~difftissue.solvers.spectral.SpectralDecomposition`
            of ``model`` and ``free`` (:func:`~difftissue.solvers.spectral.spectral_decomposition`;
            None: computed here, cached per mesh). Ignored by the other solvers.
        setup: the :func:`condensation_setup` of ``model`` for ``linear_solver`` (None:
            built now, which needs the connectivity concrete). With it, ``model``, ``free`` and ``dofs`` may be traced
            arguments of a compiled program (their checks then run where they are concrete).

    Returns:
        ``(Z, G)``: ``Z`` ``(m, 3N)`` and ``G`` ``(m, m)`` (symmetric) [m/N]. The derivative of
        ``G`` needs no extra solve (``dG = -Z dK Z^T``); that of ``Z`` one per tangent (one
        more factorisation for all of them). ``Z`` is dense, ``8 m 3N`` bytes; with
        ``"sparse"`` the solve holds about twice that besides the factor (module docstring).
    """
    if isinstance(dofs, jax.core.Tracer) or isinstance(free, jax.core.Tracer):
        dofs = jnp.reshape(dofs, (-1,))  # traced (a compiled program's arguments): checked where they were built
    else:
        dofs = np.asarray(dofs, dtype=np.int64).reshape(-1)
        free = np.asarray(free, dtype=bool)
        if not np.all(free.reshape(-1)[dofs]):
            raise ModelError("condensation degrees of freedom must be free (not prescribed)")
    if dofs.size == 0:
        raise ModelError("no degrees of freedom to condense onto")
    material = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)
    model.region_values(material)
    if linear_solver == "spectral":
        if setup is not None and (not isinstance(setup, SolverSetup) or setup.linear_solver != "spectral"):
            raise ModelError("linear_solver='spectral' takes the condensation_setup built for 'spectral'")
        if decomposition is None:
            decomposition = spectral_decomposition(model, free)
        n = int(np.shape(decomposition.vectors)[0])
        if n != 3 * model.n_nodes:
            raise ModelError(f"the spectral decomposition has {n} rows, the model {3 * model.n_nodes} unknowns: it belongs to another mesh")
        return spectral_response_columns(decomposition, model, material, dofs)
    options = _options_for(model, material, linear_solver, setup)
    return _columns(material, model=model, free=free, dofs=dofs, options=options)


class CondensedParameters(eqx.Module):
    """The differentiable data of a :class:`CondensedContactModel`: the condensed stiffness
    ``S`` ``(3k, 3k)`` [N/m] and the penalty stiffnesses ``kappa`` ``(k,)`` [N/m]."""

    stiffness: jax.Array
    kappa: jax.Array


def _quadratic_energy(x_e, rest, stiffness):
    d = (x_e - rest).reshape(-1)
    return 0.5 * d @ (stiffness @ d)


class CondensedContactModel(ElasticModel):
    """Candidate contact nodes of a linear body (a superelement with stiffness ``S``) plus the
    frictionless penalty contact of :class:`~difftissue.contact.ContactModel`.

    Pass it to :func:`~difftissue.solvers.static.solve_static` with
    :class:`CondensedParameters` in place of the material and boundary conditions that leave
    every component free (``S`` already carries the body's supports).

    Attributes (besides :class:`ElasticModel`'s, which describe no tets):
        indenter: the rigid indenter (static).
        depth: indenter depth [m] (a leaf: :meth:`with_depth` does not recompile).
    """

    indenter: object = eqx.field(static=True)
    penalty_energy: object = eqx.field(static=True)
    depth: jax.Array
    #: The superelement's stiffness is positive definite: no rigid-mode check of the (empty)
    #: prescribed set (see :func:`~difftissue.solvers.static.solve_static`).
    stiffness_is_definite: ClassVar[bool] = True

    def __init__(self, rest_points, indenter, penalty_energy, *, depth=0.0):
        self.kind = "condensed_contact"
        self.rest_points = np.asarray(rest_points, dtype=float)
        self.tets = np.zeros((0, 4), dtype=np.int32)
        self.tet_regions = np.zeros((0,), dtype=np.int32)
        self.tet_Dm_inv = np.zeros((0, 3, 3))
        self.tet_volumes = np.zeros((0,))
        self.region_names = ("condensed",)
        self.nu_min = -1.0
        self.indenter = indenter
        self.penalty_energy = penalty_energy
        self.depth = jnp.asarray(depth, dtype=float)

    def with_depth(self, depth) -> "CondensedContactModel":
        return eqx.tree_at(lambda m: m.depth, self, jnp.asarray(depth, dtype=float))

    def region_values(self, material):
        if not isinstance(material, CondensedParameters):
            raise ModelError("a CondensedContactModel takes CondensedParameters, not a Material")
        return {}

    def terms(self, params: CondensedParameters):
        k = self.n_nodes
        X = jnp.asarray(self.rest_points)
        depth = jnp.broadcast_to(self.depth, (k,))
        return (
            ElementTerm("condensed", np.arange(k, dtype=np.int32)[None, :], _quadratic_energy, (X[None], params.stiffness[None])),
            ElementTerm("contact", np.arange(k, dtype=np.int32)[:, None], self.penalty_energy, (params.kappa, depth)),
        )

    def min_volume_ratio(self, x):
        return jnp.asarray(1.0, dtype=x.dtype)

    def contact_energy(self, x, params: CondensedParameters, depth=None):
        p = self.indenter.penetration(x, self.depth if depth is None else depth)
        return 0.5 * jnp.sum(params.kappa * jnp.maximum(p, 0.0) ** 2)

    def reaction_force(self, x, params: CondensedParameters):
        """Force [N] on the indenter along +z (positive compressive), as ContactModel's."""
        return jax.grad(lambda d: self.contact_energy(x, params, d))(self.depth)


# ------------------------------------------------------------ the small contact problem
def _condensed_energy(u, stiffness, kappa, depth, *, rest, indenter):
    """``1/2 u.S u + sum_i kappa_i/2 max(p_i, 0)^2`` [J] for flat candidate displacements ``u`` (3k,)."""
    p = indenter.penetration(rest + u.reshape(rest.shape), depth)
    return 0.5 * u @ (stiffness @ u) + 0.5 * jnp.sum(kappa * jnp.maximum(p, 0.0) ** 2)


def _condensed_newton(stiffness, kappa, depth, u_init, free, *, rest, indenter, rtol, atol, xtol, max_steps):
    P = free.astype(u_init.dtype)
    energy = lambda u: _condensed_energy(u, stiffness, kappa, depth, rest=rest, indenter=indenter)  # noqa: E731
    grad = jax.grad(energy)
    hess = jax.hessian(energy)

    def residual(u):
        return P * grad(u)

    g_start = jnp.linalg.norm(residual(jnp.zeros_like(u_init)))
    tol = jnp.maximum(atol, rtol * g_start)
    # A "small Newton step" exit is a round-off stall only if the residual is also within the
    # precision the solve claims (prediction_rtol = max(rtol, xtol)) of the force scale:
    # at a kink of the energy the Newton step is tiny because the curvature is huge, not
    # because the residual is at round-off (solve_condensed_contact's docstring).
    stall_tol = jnp.maximum(tol, xtol * g_start)

    def body(state):
        u, g, step, _, _ = state
        H = hess(u) * P[:, None] * P[None, :] + jnp.diag(1.0 - P)
        d = jnp.linalg.solve(H, -g)
        gd = jnp.vdot(g, d)
        bad = ~jnp.all(jnp.isfinite(d)) | (gd >= 0)
        # unusable Newton direction (indefinite Hessian): a diagonally scaled gradient step
        scale = 1.0 / jnp.maximum(jnp.max(jnp.abs(jnp.diagonal(H))), 1e-300)
        d = jnp.where(bad, -g * scale, d)
        gd = jnp.vdot(g, d)
        alpha, accepted = armijo_backtracking(energy, u, d, gd)
        u_new = jnp.where(accepted, u + alpha * d, u)
        g_new = residual(u_new)
        rn = jnp.linalg.norm(g_new)
        # (accepted or not: a round-off-sized correction's decrease is below the energy's
        # round-off, solve_static's rule)
        small_step = ~bad & (jnp.linalg.norm(d) <= xtol * jnp.linalg.norm(u_new)) & (rn <= stall_tol)
        ok = jnp.isfinite(rn) & ((rn <= tol) | small_step)
        step = step + 1
        done = ok | ~accepted | ~jnp.isfinite(rn) | (step >= max_steps)
        return u_new, g_new, step, ok, done

    u0 = P * u_init
    g0 = residual(u0)
    ok0 = jnp.linalg.norm(g0) <= tol
    state = (u0, g0, jnp.asarray(0, jnp.int32), ok0, ok0 | (max_steps <= 0))
    u, g, _, ok, _ = jax.lax.while_loop(lambda s: ~s[4], body, state)
    # One more full Newton step, kept if it lowers the residual: at a converged point it costs
    # one 3k x 3k solve and takes the solution from the tolerance to round-off (so that the
    # implicit derivative, exact at the exact equilibrium, matches the computed function).
    # The step is solved by Cholesky, which also checks the second-order condition: a stationary
    # point whose (projected) Hessian is not positive definite is not a minimum of the energy
    # (an unstable equilibrium, e.g. a node balanced on a cone's tip inside the 1e-77 m core
    # of the regularised distance to the axis) and is reported as not converged.
    # The same step also ends a round-off stall: where the iterations stopped with the residual
    # within the precision the solve claims (stall_tol) but above tol, a full Newton step
    # through a positive definite Hessian that takes the residual to tol converges (measured:
    # the m = 8 automatic sphere block's first depth with the depth traced, residual 3.2e-13 N
    # against tol 2.3e-13 N for 50 steps, 8e-17 N after this step; docs/dev/indentation-resolution.md).
    H = hess(u) * P[:, None] * P[None, :] + jnp.diag(1.0 - P)
    L = jnp.linalg.cholesky(H)
    stable = jnp.all(jnp.isfinite(L))
    u2 = u + jax.scipy.linalg.cho_solve((L, True), -g)
    g2 = residual(u2)
    finite2 = jnp.all(jnp.isfinite(u2)) & jnp.isfinite(jnp.linalg.norm(g2))
    polished = stable & finite2 & (jnp.linalg.norm(g) <= stall_tol) & (jnp.linalg.norm(g2) <= tol)
    ok = (ok & stable) | polished
    better = ok & finite2 & (jnp.linalg.norm(g2) <= jnp.linalg.norm(g))
    return jnp.where(better, u2, u), ok


@eqx.filter_custom_jvp
def _condensed_equilibrium(stiffness, kappa, depth, *, u_init, free, rest, indenter, rtol, atol, xtol, max_steps):
    u, ok = _condensed_newton(stiffness, kappa, depth, u_init, free, rest=rest, indenter=indenter, rtol=rtol, atol=atol, xtol=xtol, max_steps=max_steps)
    return u, ok.astype(u.dtype)


@_condensed_equilibrium.def_jvp
def _condensed_equilibrium_jvp(primals, tangents, *, u_init, free, rest, indenter, rtol, atol, xtol, max_steps):
    stiffness, kappa, depth = primals
    u, ok = _condensed_equilibrium(stiffness, kappa, depth, u_init=u_init, free=free, rest=rest, indenter=indenter, rtol=rtol, atol=atol, xtol=xtol, max_steps=max_steps)
    t = [jnp.zeros_like(jnp.asarray(p, dtype=u.dtype)) if tt is None else tt for tt, p in zip(tangents, primals)]
    P = free.astype(u.dtype)
    g = lambda uu, S, k, d: jax.grad(_condensed_energy)(uu, S, k, d, rest=rest, indenter=indenter)  # noqa: E731
    _, dg = jax.jvp(lambda S, k, d: g(u, S, k, d), (stiffness, kappa, depth), tuple(t))
    H = jax.hessian(lambda uu: _condensed_energy(uu, stiffness, kappa, depth, rest=rest, indenter=indenter))(u)
    H = H * P[:, None] * P[None, :] + jnp.diag(1.0 - P)
    # implicit function theorem: H du = -P dg (a failed primal gives NaN: the optimiser rejects it)
    # An unconverged primal is not an equilibrium: NaN tangents (a multiplication, so reverse
    # mode gets NaN cotangents too), never the implicit tangent of a wrong state.
    failed = jnp.where(ok > 0.5, jnp.asarray(1.0, u.dtype), jnp.asarray(jnp.nan, u.dtype))
    t_u = P * jnp.linalg.solve(H, -P * dg) * failed
    return (u, ok), (t_u, jnp.zeros_like(ok))


def solve_condensed_contact(model: "CondensedContactModel", params: "CondensedParameters", free, u_init, *, rtol: float = 1e-9, atol: float = 0.0, xtol: float = 1e-8, max_steps: int = 50):
    """Equilibrium of the candidate nodes of a :class:`CondensedContactModel` at its depth.

    The same problem and stopping rule as :func:`~difftissue.solvers.static.solve_static` on
    that model (Newton with the exact Hessian, dense LU of the ``3k x 3k`` system, Armijo
    backtracking; converged when ``|grad|_free <= max(atol, rtol |grad at u = 0|)`` or a full
    Newton step below ``xtol |u|``, then one more Newton step, kept if it lowers the residual),
    written for this small dense problem only: its compiled program is a fraction of the
    general solver's, which dominated the compile time of a condensed fit.

    Two checks keep it from reporting convergence where there is no stable equilibrium:

    * The small-step exit also needs ``|grad|_free <= max(tol, xtol |grad at u = 0|)``: the
      residual within the precision the solve claims (``prediction_rtol = max(rtol, xtol)``)
      of the force scale. A round-off stall of a smooth problem meets it (the Newton step
      ``H^-1 g`` is small because ``g`` is); at a kink of the energy the step is small because
      the curvature is huge (a node on a cone's axis: the curvature of the distance to the axis
      is ``1/r``, about ``1e77 /m`` inside the ``1e-77 m`` core of its regularisation) while the
      residual is not.
    * The returned state must have a positive definite Hessian (the last step is solved by
      Cholesky): a stationary point that is not a minimum is an unstable equilibrium, which
      the full solve leaves at round-off (a node balanced on a sharp frictionless tip: the
      residual there is at round-off by symmetry, but 1e-20 m off the axis the tip pushes the
      node out with its full contact force). ``converged`` is False there.

    Iterations that stop (``max_steps``) with the residual within that precision but above the
    tolerance (a round-off stall) converge when the last Newton step, through the positive
    definite Hessian, takes the residual to the tolerance. Derivatives with respect to ``params`` (and the depth) are implicit (one
    dense solve per tangent), never through the iterations.

    Args:
        free: ``(k, 3)`` bool, True on free components (the others stay 0).
        u_init: ``(k, 3)`` starting guess [m] (not differentiated).

    Returns:
        ``(u (k, 3) [m], converged (bool))``.
    """
    free = jnp.asarray(free).reshape(-1)
    rest = jnp.asarray(model.rest_points)
    u0 = jax.lax.stop_gradient(jnp.asarray(u_init, dtype=rest.dtype).reshape(-1))
    u, ok = _condensed_equilibrium(
        params.stiffness, params.kappa, model.depth, u_init=u0, free=free, rest=rest, indenter=model.indenter,
        rtol=float(rtol), atol=float(atol), xtol=float(xtol), max_steps=int(max_steps),
    )
    return u.reshape(rest.shape), ok > 0.5
