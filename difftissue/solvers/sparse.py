"""Sparse direct solves of the static problem's (projected) Hessian.

The element Hessians of an :class:`~difftissue.models.ElasticModel` are assembled into a
CSR matrix whose sparsity pattern is computed once per mesh (in NumPy, outside the traced
code); the values are scattered inside the compiled solve. The linear solve itself is a
``jax.pure_callback`` to a sparse factorisation, wrapped as a :mod:`lineax` solver so that
implicit differentiation (forward and reverse) goes through it like through the dense
Cholesky. The matrix is symmetric, so the transposed solve (reverse mode) is the same solve.

Which factorisation (:func:`_factor_solve`): where scikit-sparse is installed, CHOLMOD's
supernodal Cholesky, and where that finds the matrix not positive definite (a Newton step at
an indefinite point), CHOLMOD's simplicial LDLᵀ, whose pivots ``D`` give the inertia without
a copy of the factor (:func:`_suitesparse_solve`); a failed factorisation is freed there.
Without scikit-sparse: CHOLMOD through cholespy, or SciPy's sparse LU (SuperLU with a
symmetric-mode ordering) where the matrix is not positive definite (and, since cholespy's
failed factorisation leaks memory, for every later matrix of a pattern that had
``CHOLMOD_FAILURES_MAX`` indefinite ones).

For the stiffness matrices here a sparse factorisation costs about ``O(n^1.5..2)`` instead
of the dense ``O(n^3)``, and unlike Jacobi-preconditioned CG it does not slow down on
bending-dominated or penalty-contact problems.
"""

from __future__ import annotations

import hashlib
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

__all__ = ["SparsePattern", "sparse_pattern", "SparseLU"]


class SparsePattern:
    """CSR pattern of ``P H P + (I - P)`` for a model's element terms.

    Attributes:
        n: matrix size (3 x nodes).
        indices, indptr: CSR column indices and row pointers (NumPy).
        scatter: ``(n_coo,)`` position in the CSR data of every element-Hessian entry
            (terms in order, each ``(E, 3k, 3k)`` row-major), then of the ``n`` diagonal entries.
        digest: content hash (equality and hashing use it, so a jit cache keyed on the pattern
            does not recompile for the same mesh).
    """

    def __init__(self, n: int, indices: np.ndarray, indptr: np.ndarray, scatter: np.ndarray, digest: str):
        self.n, self.indices, self.indptr, self.scatter, self.digest = n, indices, indptr, scatter, digest

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    def __hash__(self):
        return hash(self.digest)

    def __eq__(self, other):
        return isinstance(other, SparsePattern) and other.digest == self.digest

    def __repr__(self):
        return f"SparsePattern(n={self.n}, nnz={self.nnz})"


_CACHE: dict[str, SparsePattern] = {}


def cache_key(*parts) -> str:
    """A content hash of arrays and values (dtype, shape and bytes of each): the key of the
    sparse-pattern, block-layout and multigrid-hierarchy caches."""
    h = hashlib.sha256()
    for p in parts:
        a = np.asarray(p)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def sparse_pattern(node_arrays, n_nodes: int) -> SparsePattern:
    """The CSR pattern for element terms with node arrays ``[(E_t, k_t), ...]`` on ``n_nodes`` nodes."""
    arrays = [np.ascontiguousarray(np.asarray(a, dtype=np.int64)) for a in node_arrays]
    digest = cache_key(np.asarray(n_nodes), *arrays)
    if digest in _CACHE:
        return _CACHE[digest]
    n = 3 * int(n_nodes)
    keys = []
    for a in arrays:
        k = a.shape[1]
        dofs = (3 * a[:, :, None] + np.arange(3)).reshape(-1, 3 * k)
        keys.append((dofs[:, :, None] * n + dofs[:, None, :]).reshape(-1))
    diag = np.arange(n, dtype=np.int64)
    keys.append(diag * n + diag)
    allkeys = np.concatenate(keys)
    uniq, scatter = np.unique(allkeys, return_inverse=True)
    rows, cols = uniq // n, uniq % n
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(indptr, rows + 1, 1)
    indptr = np.cumsum(indptr)
    pattern = SparsePattern(n, cols.astype(np.int32), indptr.astype(np.int32), scatter.astype(np.int32), digest)
    if len(_CACHE) > 16:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[digest] = pattern
    return pattern


def assemble_csr_data(pattern: SparsePattern, element_hessians, free_dofs):
    """CSR data of ``P H P + (I - P)`` from ``[(hess (E, 3k, 3k), dofs (E, 3k)), ...]`` and the
    free-DOF indicator ``free_dofs`` (``(n,)``, 1 free / 0 prescribed)."""
    P = free_dofs
    vals = []
    for hess, dofs in element_hessians:
        mask = P[dofs][:, :, None] * P[dofs][:, None, :]
        vals.append((hess * mask).reshape(-1))
    vals.append(1.0 - P)
    v = jnp.concatenate(vals)
    return jnp.zeros(pattern.nnz, dtype=v.dtype).at[jnp.asarray(pattern.scatter)].add(v)


#: How many failed CHOLMOD factorisations (indefinite matrices) one sparsity pattern may have:
#: after that many its matrices go to the symmetric LU for good (see _factor_solve).
CHOLMOD_FAILURES_MAX = 2

#: Failed CHOLMOD factorisations per sparsity pattern (digest: 64 characters), kept for the
#: process, so that each pattern leaks at most CHOLMOD_FAILURES_MAX failed CHOLMOD factors.
_CHOLMOD_FAILURES: dict[str, int] = {}


#: How many right-hand sides a many-column solve (:class:`_Rows`: the condensation's response
#: rows, a batch of tangents or adjoints) passes to the factorisation at a time: each chunk's
#: right-hand sides and solution are ``n x COLUMN_CHUNK`` (float64: 8 n x 64 bytes, 78 MB at
#: 152,000 unknowns), written into one preallocated ``(B, n)`` result.
COLUMN_CHUNK = 64


class _Rows:
    """Right-hand sides of a many-column solve given as rows, solved chunk by chunk.

    ``x[j] = A^{-1} b[j]`` for the rows ``b[j]`` of a ``(B, n)`` array (``rows``) or, with
    ``dofs`` (``(B,)`` indices), of the identity (``b[j] = e_{dofs[j]}``, never formed whole).
    The factorisation paths (:func:`_factor_solve`) take it in place of a ``(n, k)`` array and
    pass it to :func:`_solve_each`, which solves ``chunk`` columns at a time into one ``(B, n)``
    result of ``dtype`` (the layout JAX wants: no transposed copy of all the right-hand sides or
    solutions, no ``astype`` copy). ``shape`` is the result's."""

    def __init__(self, n: int, *, rows=None, dofs=None, dtype=np.float64, chunk: int | None = None):
        self.n, self.rows, self.dofs, self.dtype = int(n), rows, None if dofs is None else np.asarray(dofs, dtype=np.int64).reshape(-1), np.dtype(dtype)
        self.shape = (int(rows.shape[0]) if rows is not None else int(self.dofs.size), self.n)
        self.chunk = max(1, int(COLUMN_CHUNK if chunk is None else chunk))

    def finite(self) -> bool:
        return True if self.rows is None else bool(np.all(np.isfinite(self.rows)))

    def rhs(self, j0: int, j1: int) -> np.ndarray:
        """Right-hand sides ``j0:j1`` as an ``(n, j1 - j0)`` Fortran-ordered float64 array."""
        if self.rows is None:
            b = np.zeros((self.n, j1 - j0), dtype=np.float64, order="F")
            b[self.dofs[j0:j1], np.arange(j1 - j0)] = 1.0
            return b
        return np.asfortranarray(self.rows[j0:j1].T, dtype=np.float64)


def _solve_each(b, solve):
    """``solve(b)`` for an array ``b``; for a :class:`_Rows` request, ``solve`` of each chunk
    of its right-hand sides (``(n, c)``) written into one ``(B, n)`` result."""
    if not isinstance(b, _Rows):
        return solve(b)
    out = np.empty(b.shape, dtype=b.dtype)
    for j0 in range(0, b.shape[0], b.chunk):
        j1 = min(b.shape[0], j0 + b.chunk)
        out[j0:j1] = np.asarray(solve(b.rhs(j0, j1))).reshape(b.n, j1 - j0).T
    return out


def _finite(b) -> bool:
    return b.finite() if isinstance(b, _Rows) else bool(np.all(np.isfinite(b)))


def _suitesparse_cholmod():
    """scikit-sparse's CHOLMOD module (``sksparse.cholmod``), or None where scikit-sparse is
    not installed (then :func:`_factor_solve` uses cholespy and SuperLU)."""
    try:
        from sksparse import cholmod  # host-side only; optional (needs SuiteSparse's headers to build)
    except ImportError:
        return None
    return cholmod


def _ldlt_pivots_definite(pivots: np.ndarray) -> bool | None:
    """Whether a symmetric matrix ``P A P^T = L D L^T`` (unit lower ``L``) with the pivots
    ``D`` (``(n,)``) is positive definite: by Sylvester's law of inertia ``A`` has as many
    negative eigenvalues as ``D`` has negative entries, so it is definite exactly when every
    pivot is positive. None where a pivot is zero or not finite (the factorisation is singular
    or broke down: its solve is not usable)."""
    if not np.all(np.isfinite(pivots)) or np.any(pivots == 0.0):
        return None
    return bool(np.all(pivots > 0.0))


def _suitesparse_solve(cholmod, pattern: SparsePattern, data: np.ndarray, b: np.ndarray):
    """``(x, definite)`` from CHOLMOD through scikit-sparse (``cholmod``: the module), or None
    where the matrix is singular (a zero LDLᵀ pivot: SuperLU then decides).

    First CHOLMOD's supernodal Cholesky ``L L^T`` (its default fill-reducing ordering, METIS
    where CHOLMOD was built with it); where that finds the matrix not positive definite, the
    simplicial ``L D L^T`` without pivoting, whose pivots give the inertia
    (:func:`_ldlt_pivots_definite`; ``Factor.D()`` reads them from CHOLMOD's factor without
    copying it). A failed factorisation is freed with its Python object: no leak, so unlike
    cholespy's path no pattern is ever moved off CHOLMOD."""
    import scipy.sparse as sps

    A = sps.csc_matrix((data, pattern.indices, pattern.indptr), shape=(pattern.n, pattern.n))  # CSR of a symmetric matrix read as CSC: the same matrix
    try:
        factor = cholmod.cholesky(A, mode="supernodal")
        return _solve_each(b, factor), True
    except cholmod.CholmodNotPositiveDefiniteError:
        pass
    try:
        factor = cholmod.cholesky(A, mode="simplicial")  # LDL^T (CHOLMOD keeps a simplicial factor as LDL^T)
    except cholmod.CholmodError:  # a zero pivot
        return None
    definite = _ldlt_pivots_definite(factor.D())
    if definite is None:
        return None
    return _solve_each(b, factor), definite


def _cholesky_solve(pattern: SparsePattern, data: np.ndarray, b: np.ndarray):
    """Sparse Cholesky (CHOLMOD through cholespy) of the symmetric CSR matrix, or None when it
    is not positive definite (then the LU below decides).

    A failed factorisation is not free: cholespy (2.2) raises from its constructor without
    releasing CHOLMOD's factor, so every indefinite matrix passed here leaks about the size of
    its Cholesky factor (measured: ~175 MB per attempt at 17,500 unknowns). ``_factor_solve``
    therefore calls it at most ``CHOLMOD_FAILURES_MAX`` times per pattern with an indefinite matrix."""
    import cholespy  # host-side only

    try:
        factor = cholespy.CholeskySolverD(pattern.n, pattern.indptr, pattern.indices, np.array(data, dtype=np.float64), cholespy.MatrixType.CSR)  # a writable copy: the binding refuses read-only arrays
    except ValueError:  # "Matrix is not positive definite!"
        return None

    def solve(rhs):
        x = np.zeros(rhs.shape, dtype=np.float64)
        factor.solve(np.array(rhs, dtype=np.float64, order="C"), x)
        return x

    return _solve_each(b, solve)


def _factor_solve(pattern: SparsePattern, data: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve with one factorisation for ``b`` of shape ``(n,)`` or ``(n, k)``, or for the rows
    of a :class:`_Rows` request (then ``x`` is ``(B, n)``, solved ``COLUMN_CHUNK`` columns at a
    time: the memory of ``x`` and one chunk besides the factor). Returns ``(x, definite)``: ``definite`` is True when the factorisation shows the matrix positive
    definite (a Cholesky succeeded, or the pivots of an LDLᵀ or symmetric LU are all
    positive), False when it is indefinite, singular, not finite or its inertia is not known.
    (A Newton step at an indefinite point: the Newton loop then checks the direction.)

    Where scikit-sparse is installed: CHOLMOD's supernodal Cholesky, else its LDLᵀ with the
    inertia from the pivots (:func:`_suitesparse_solve`; no failed factor is kept), and
    SuperLU with its pivots read only where that LDLᵀ meets a zero pivot.

    Without it (cholespy and SuperLU): CHOLMOD is tried first while the pattern has had fewer
    than :data:`CHOLMOD_FAILURES_MAX` indefinite matrices. Its failure shows the matrix not
    positive definite, so the LU that then solves the step returns ``definite=False`` without
    reading its pivots (reading them, ``lu.U``, copies both SuperLU factors into SciPy
    matrices: about double the factor's memory, 0.30 GiB more on a 0.33 GiB factor at 24,507
    unknowns). A failed Cholesky leaks its factor (``_cholesky_solve``), and along a Newton
    path of a nearly incompressible, pre-stretched membrane the Hessian is indefinite at one
    step out of three (at 16,560 unknowns 0.12-0.24 GB per step, 8 GB and a MemoryError over
    one solve without a bound); so after the pattern's ``CHOLMOD_FAILURES_MAX``-th failure its
    matrices go to the symmetric LU for good, whose pivots then say whether each is definite.
    Where only the first tangent of a solve is indefinite (a cut, pre-stretched lattice), the
    later, definite tangents keep CHOLMOD: about half the LU's factor memory. Linear-elastic
    stiffness matrices (condensation, fits of linear models: many right-hand sides, where
    CHOLMOD wins) are never indefinite and keep CHOLMOD. Which factorisation solved a definite
    matrix changes the result at round-off level only."""
    if not (np.all(np.isfinite(data)) and _finite(b)):
        return np.full(b.shape, np.nan), False
    cholmod = _suitesparse_cholmod()
    if cholmod is not None:
        solved = _suitesparse_solve(cholmod, pattern, data, b)
        return solved if solved is not None else _superlu_solve(pattern, data, b, read_pivots=True)
    failures = _CHOLMOD_FAILURES.get(pattern.digest, 0)
    if failures < CHOLMOD_FAILURES_MAX:
        x = _cholesky_solve(pattern, data, b)
        if x is not None:
            return x, True
        _CHOLMOD_FAILURES[pattern.digest] = failures + 1
    # CHOLMOD failed on this very matrix: not positive definite, no need for the pivots.
    return _superlu_solve(pattern, data, b, read_pivots=failures >= CHOLMOD_FAILURES_MAX)


def _superlu_solve(pattern: SparsePattern, data: np.ndarray, b: np.ndarray, read_pivots: bool) -> tuple[np.ndarray, bool]:
    """``(x, definite)`` from SciPy's SuperLU in symmetric mode (diagonal pivots): NaN where
    the matrix is exactly singular; ``definite`` from the pivots (:func:`_lu_is_definite`)
    where ``read_pivots``, else False (the caller knows the matrix is not positive definite)."""
    import scipy.sparse as sps  # imported on first use: a fit that never factorises need not load SciPy
    import scipy.sparse.linalg as spla

    A = sps.csc_matrix(sps.csr_matrix((data, pattern.indices, pattern.indptr), shape=(pattern.n, pattern.n)))
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:  # exactly singular: NaN, the Newton loop falls back / flags it
        return np.full(b.shape, np.nan), False
    del A
    definite = _lu_is_definite(lu) if read_pivots else False
    factors = []  # the triangular factors as CSR, converted once for all chunks of a _Rows request

    def solve(rhs):
        if rhs.ndim == 1 or rhs.shape[1] < 4:
            return lu.solve(rhs)
        return _solve_many(lu, rhs, factors)

    return _solve_each(b, solve), definite


def _lu_is_definite(lu) -> bool:
    """Whether the symmetric matrix ``A`` factorised by SuperLU as ``Pr A Pc = L U`` is
    positive definite. With a symmetric permutation (``perm_r == perm_c``, which the
    symmetric mode with diagonal pivoting keeps unless a diagonal pivot is exactly zero)
    ``U = D L^T`` with ``Pc^T A Pc = L D L^T``, so the pivots ``U_ii`` decide
    (:func:`_ldlt_pivots_definite`). Any other permutation: False (not known to be definite)."""
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return False
    return _ldlt_pivots_definite(lu.U.diagonal()) is True


def _solve_many(lu, b: np.ndarray, factors: list | None = None) -> np.ndarray:
    """``A^{-1} b`` for many right-hand sides ``b (n, k)`` with SuperLU's factors ``Pr A Pc = L U``.

    SciPy's ``SuperLU.solve`` with a matrix right-hand side is several times slower than the
    two sparse triangular solves done here (measured: 31 columns of a 3,267-unknown stiffness,
    0.76 s against 0.13 s), which dominated a condensed indentation's forward solve.
    """
    import scipy.sparse.linalg as spla

    if factors is None:
        factors = []
    if not factors:  # (``factors``: a cache of ``(L, U)`` for solves of several chunks)
        factors.extend((lu.L.tocsr(), lu.U.tocsr()))
    L, U = factors
    pb = np.empty_like(b)
    pb[lu.perm_r] = b
    y = spla.spsolve_triangular(L, pb, lower=True, unit_diagonal=True)
    w = spla.spsolve_triangular(U, y, lower=False)
    return w[lu.perm_c]


def _host_solve(pattern: SparsePattern, data, b):
    """Callback body: ``(x, definite)`` (see :func:`_factor_solve`). Under ``vmap``
    (``vmap_method="expand_dims"``) ``data`` is ``(B or 1, ..., nnz)`` and ``b``
    ``(B or 1, ..., n)``, ``definite`` then has the batch shape: an unbatched matrix (the
    common case: several tangents or adjoints of one solve) is factorised once for all
    right-hand sides, solved in chunks of ``COLUMN_CHUNK`` into the ``(B, n)`` result
    (:class:`_Rows`: besides the input and the result, the factor and one chunk)."""
    data, b = np.asarray(data), np.asarray(b)
    dtype = b.dtype
    if data.ndim == 1:
        x, definite = _factor_solve(pattern, data, b)
        return x.astype(dtype, copy=False), np.asarray(definite)
    batch = np.broadcast_shapes(data.shape[:-1], b.shape[:-1])
    d2 = data.reshape(-1, data.shape[-1])
    b2 = np.broadcast_to(b, batch + b.shape[-1:]).reshape(-1, b.shape[-1])
    if d2.shape[0] == 1:
        # one factorisation, the right-hand sides solved in chunks into the (B, n) result
        # (_Rows): no transposed copy of them all, no astype copy of the solution
        x, definite = _factor_solve(pattern, d2[0], _Rows(pattern.n, rows=b2, dtype=dtype))
        flags = np.full(b2.shape[0], definite)
    else:
        d2 = np.broadcast_to(data, batch + data.shape[-1:]).reshape(-1, data.shape[-1])
        solved = [_factor_solve(pattern, d2[i], b2[i]) for i in range(b2.shape[0])]
        x, flags = np.stack([s[0] for s in solved]), np.array([s[1] for s in solved])
    return x.reshape(batch + b.shape[-1:]).astype(dtype, copy=False), flags.reshape(batch)


class SparseLU(lx.AbstractLinearSolver):
    """:mod:`lineax` solver: sparse Cholesky (LDLᵀ or LU where not positive definite:
    :func:`_factor_solve`) of the CSR matrix passed as ``options["csr_data"]``.

    The matrix must be symmetric (transposed solves reuse it). Runs on the host through
    ``jax.pure_callback``; under ``vmap`` one matrix with many right-hand sides (``jacfwd``
    tangents) is factorised once. Stats: ``positive_definite`` (bool: a Cholesky succeeded, or
    the LDLᵀ's or LU's pivots show the matrix positive definite).
    """

    pattern: SparsePattern = eqx.field(static=True)

    def init(self, operator, options: dict[str, Any]):
        return options["csr_data"]

    def compute(self, state, vector, options):
        data = state
        shapes = (jax.ShapeDtypeStruct(vector.shape, vector.dtype), jax.ShapeDtypeStruct(vector.shape[:-1], jnp.bool_))
        x, definite = jax.pure_callback(lambda d, b: _host_solve(self.pattern, d, b), shapes, data, vector, vmap_method="expand_dims")
        # A singular matrix gives NaN values (the Newton loop and fits check for them); the
        # result code stays successful, since lineax raises on any other code of a transposed
        # solve in reverse mode. ``positive_definite``: the factorisation showed the matrix
        # positive definite (the Newton loop accepts a round-off-sized step only then).
        return x, lx.RESULTS.successful, {"positive_definite": definite}

    def transpose(self, state, options):
        return state, options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True
