"""The sparse direct linear solver of the static solve: same answers and gradients as dense."""

import logging
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.boundary import BoundaryConditions
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.solvers import solve_static
from difftissue.solvers.sparse import sparse_pattern


def _require_scikit_sparse():
    """Skip without scikit-sparse (the optional ``suitesparse`` extra, built only where
    SuiteSparse's headers are installed); under ``CI=true`` fail instead: ``.ci/run`` installs
    the headers, so the README's test command builds it there."""
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but scikit-sparse is not installed: .ci/run installs libsuitesparse-dev and the README's test command the suitesparse extra", pytrace=False)
        pytest.skip("scikit-sparse is not installed (the suitesparse extra)")


@pytest.fixture(scope="module")
def problem():
    mesh = block((0.01, 0.01, 0.01), (2, 2, 2))
    model = make_model(mesh, "fem_neo_hookean")
    top = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.01))
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "z", (0, 0, -2e-4))
    return mesh, model, top, bc


def _top_force(model, bc, top, solver, E, nu):
    sol = solve_static(model, Material(E, nu), bc, linear_solver=solver)
    return jnp.sum(sol.reaction[top, 2])


def test_pattern_is_csr_of_all_couplings(problem):
    mesh, model, _, _ = problem
    pat = sparse_pattern([t.nodes for t in model.terms(Material(1e4, 0.4))], mesh.n_nodes)
    # each row's columns sorted and unique; every edge couples its two nodes' 3x3 blocks
    for r in range(0, pat.n, 7):
        cols = pat.indices[pat.indptr[r] : pat.indptr[r + 1]]
        assert np.all(np.diff(cols) > 0)
    n_pairs = mesh.n_nodes + 2 * len(mesh.edges)
    assert pat.nnz == 9 * n_pairs
    assert sparse_pattern([t.nodes for t in model.terms(Material(2e4, 0.3))], mesh.n_nodes) is pat  # cached


@pytest.fixture(scope="module")
def sparse_derivatives(problem):
    """The top force through the sparse solver as a function of ``(E, nu)`` with its
    reverse-mode gradient and forward-mode Jacobian, compiled once for the module (one program
    instead of the solve's primal, JVP and transposed programs compiled one by one per test);
    the difference evaluations reuse it."""
    _, model, top, bc = problem

    def f(p):
        return _top_force(model, bc, top, "sparse", p[0], p[1])

    @jax.jit
    def value_reverse_forward(p):
        value, g = jax.value_and_grad(f)(p)
        return value, g, jax.jacfwd(f)(p)

    return value_reverse_forward


def test_sparse_matches_dense_solution_and_gradients(problem, sparse_derivatives):
    _, model, top, bc = problem
    dense = solve_static(model, Material(1e4, 0.45), bc, linear_solver="dense")
    sparse = solve_static(model, Material(1e4, 0.45), bc, linear_solver="sparse")
    assert bool(sparse.converged)
    np.testing.assert_allclose(sparse.displacement, dense.displacement, rtol=0, atol=1e-12 * 5e-4 * 1e3)
    value, g, t = sparse_derivatives(jnp.array([1e4, 0.45]))
    np.testing.assert_allclose(float(value), float(jnp.sum(sparse.reaction[top, 2])), rtol=1e-12)  # the program solves the same problem
    h = 1e-6
    force = lambda E, nu: sparse_derivatives(jnp.array([E, nu]))[0]  # noqa: E731
    fd_E = (force(1e4 * (1 + h), 0.45) - force(1e4 * (1 - h), 0.45)) / (2e4 * h)
    fd_nu = (force(1e4, 0.45 + h) - force(1e4, 0.45 - h)) / (2 * h)
    np.testing.assert_allclose([float(g[0]), float(g[1])], [float(fd_E), float(fd_nu)], rtol=1e-5)
    np.testing.assert_allclose(float(t[0]), float(g[0]), rtol=1e-9)  # forward mode (the tangent solve)


def test_sparse_vmaps_and_does_not_recompile(problem, caplog):
    _, model, top, bc = problem
    forces = jax.vmap(lambda E: _top_force(model, bc, top, "sparse", E, 0.4))(jnp.array([1e4, 2e4]))
    np.testing.assert_allclose(forces[1], 2 * forces[0], rtol=1e-9)  # homogeneous of degree 1 in E
    solve_static(model, Material(1e4, 0.3), bc, linear_solver="sparse")
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        caplog.clear()
        solve_static(model, Material(3e4, 0.35), bc, linear_solver="sparse")
    assert [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()] == []


def test_jacfwd_factorises_once_for_all_tangents_and_agrees_with_grad(sparse_derivatives):
    _, g, jf = sparse_derivatives(jnp.array([1e4, 0.45]))  # jacfwd: both tangents through one factorisation
    np.testing.assert_allclose(np.asarray(jf), np.asarray(g), rtol=1e-9)


def _definite_and_indefinite(n_cells):
    """A linear-elastic block's sparsity pattern with the CSR data of a random symmetric
    matrix on it that is positive definite (smallest eigenvalue 1) and of that matrix minus 2 I
    (indefinite)."""
    import scipy.sparse as sps

    mesh = block((1.0, 1.0, 1.0), (n_cells, 2, 2))
    model = make_model(mesh, "fem_linear")
    pat = sparse_pattern([t.nodes for t in model.terms(Material(1.0, 0.3))], mesh.n_nodes)
    rows = np.repeat(np.arange(pat.n), np.diff(pat.indptr))
    R = sps.csr_matrix((np.random.default_rng(1).standard_normal(pat.nnz), pat.indices, pat.indptr), shape=(pat.n, pat.n))
    S = (R + R.T).toarray()
    S += np.eye(pat.n) * (1.0 - np.linalg.eigvalsh(S).min())  # smallest eigenvalue 1
    return pat, S[rows, pat.indices], (S - 2.0 * np.eye(pat.n))[rows, pat.indices]


def test_cholmod_is_retried_until_a_pattern_had_the_maximum_of_indefinite_matrices(monkeypatch):
    """A failed CHOLMOD factorisation leaks its factor (cholespy), so after CHOLMOD_FAILURES_MAX
    indefinite matrices every later matrix of the same pattern goes to the symmetric LU (at
    most that many leaks per pattern); before that, a definite matrix after an indefinite one
    gets CHOLMOD again (a cut lattice's first tangent is indefinite, the later ones are not);
    the LU's pivots are read only where CHOLMOD did not already show the matrix indefinite;
    another pattern still gets CHOLMOD; every solve is exact. (Without scikit-sparse: cholespy.)"""
    import scipy.sparse as sps

    from difftissue.solvers import sparse

    calls, pivot_reads = [], []
    monkeypatch.setattr(sparse, "_suitesparse_cholmod", lambda: None)  # the path without scikit-sparse
    original, original_pivots = sparse._cholesky_solve, sparse._lu_is_definite
    monkeypatch.setattr(sparse, "_cholesky_solve", lambda p, d, b: calls.append(p.n) or original(p, d, b))
    monkeypatch.setattr(sparse, "_lu_is_definite", lambda lu: pivot_reads.append(lu.shape[0]) or original_pivots(lu))
    monkeypatch.setattr(sparse, "_CHOLMOD_FAILURES", {})
    assert sparse.CHOLMOD_FAILURES_MAX == 2
    pat, definite, indefinite = _definite_and_indefinite(2)
    other, other_definite, _ = _definite_and_indefinite(3)
    b = np.random.default_rng(2).standard_normal(pat.n)
    flags = []
    sequence = [(pat, definite), (pat, indefinite), (pat, definite), (pat, indefinite), (pat, indefinite), (pat, definite), (other, other_definite)]
    for k, (p, data) in enumerate(sequence):
        rhs = b if p is pat else np.ones(p.n)
        x, is_definite = sparse._factor_solve(p, data, rhs)
        flags.append(is_definite)
        A = sps.csr_matrix((data, p.indices, p.indptr), shape=(p.n, p.n))
        np.testing.assert_allclose(A @ x, rhs, rtol=0, atol=1e-9 * np.abs(rhs).max(), err_msg=f"solve {k}")
    # Definiteness as the factorisation shows it: CHOLMOD's success or failure, then (after the
    # second failure) the LU's pivots (Sylvester's inertia) for the 5th and 6th matrices.
    assert flags == [True, False, True, False, False, True, True]
    # CHOLMOD: 1st (definite), 2nd (fails), 3rd (definite, tried again), 4th (second failure);
    # LU for the rest of this pattern; the other pattern's definite matrix: CHOLMOD.
    assert calls == [pat.n] * 4 + [other.n]
    assert pivot_reads == [pat.n, pat.n]


@pytest.mark.parametrize("scikit_sparse", [True, False], ids=["scikit-sparse", "cholespy"])
def test_the_solver_reports_positive_definiteness_per_matrix_under_vmap(monkeypatch, scikit_sparse):
    """``SparseLU`` passes out of its host callback whether each matrix was positive definite
    (the static solve accepts a round-off-sized Newton step only then): one flag per batch
    member, from CHOLMOD's success, its LDLᵀ pivots or, on a pattern that went to the LU (the
    path without scikit-sparse), from the LU's pivots."""
    import lineax as lx

    from difftissue.solvers import sparse

    if scikit_sparse:
        _require_scikit_sparse()
    else:
        monkeypatch.setattr(sparse, "_suitesparse_cholmod", lambda: None)
    monkeypatch.setattr(sparse, "_CHOLMOD_FAILURES", {})
    mesh = block((1.0, 1.0, 1.0), (2, 2, 2))
    model = make_model(mesh, "fem_linear")
    pat = sparse_pattern([t.nodes for t in model.terms(Material(1.0, 0.3))], mesh.n_nodes)
    rows = np.repeat(np.arange(pat.n), np.diff(pat.indptr))
    diagonal = rows == pat.indices
    base = np.where(diagonal, 4.0, 0.0) + np.where(rows == pat.indices + 3, 1.0, 0.0) + np.where(rows + 3 == pat.indices, 1.0, 0.0)
    indefinite = base - 5.0 * (diagonal & (rows == 7))  # e_7 . A e_7 = -1
    dense = lambda d: np.asarray(sps_dense(pat, d))  # noqa: E731
    assert np.linalg.eigvalsh(dense(base)).min() > 0 and np.linalg.eigvalsh(dense(indefinite)).min() < 0

    def solve(data, b):
        op = lx.FunctionLinearOperator(lambda v: v, jax.ShapeDtypeStruct((pat.n,), jnp.float64))  # unused by SparseLU
        sol = lx.linear_solve(op, b, sparse.SparseLU(pat), options={"csr_data": data}, throw=False)
        return sol.value, sol.stats["positive_definite"]

    b = jnp.ones(pat.n)
    for order in ([base, indefinite], [indefinite, base]):  # CHOLMOD (fails once, then twice: LU and its pivots for the last)
        x, flags = jax.vmap(solve, in_axes=(0, None))(jnp.asarray(np.stack(order)), b)
        assert np.asarray(flags).tolist() == [d is base for d in order]
        for data, xi in zip(order, np.asarray(x)):
            np.testing.assert_allclose(dense(data) @ xi, np.ones(pat.n), atol=1e-10)
    x, flag = jax.jit(solve)(jnp.asarray(base), b)
    assert bool(flag) and np.asarray(flag).shape == ()


def sps_dense(pat, data):
    import scipy.sparse as sps

    return sps.csr_matrix((data, pat.indices, pat.indptr), shape=(pat.n, pat.n)).toarray()


def test_scikit_sparse_gives_the_inertia_of_indefinite_matrices_without_superlu_or_cholespy(monkeypatch):
    """With scikit-sparse, every matrix is factorised by CHOLMOD there: a Cholesky where it is
    positive definite, else an LDLᵀ whose pivots show it indefinite (Sylvester's inertia), so
    no matrix goes to SuperLU (no pivot copy), none to cholespy (no leaked factor) and no
    pattern is moved off CHOLMOD however many indefinite matrices it has; every solve exact."""
    _require_scikit_sparse()
    import scipy.sparse as sps

    from difftissue.solvers import sparse

    other_paths = []
    monkeypatch.setattr(sparse, "_cholesky_solve", lambda *a: other_paths.append("cholespy"))
    monkeypatch.setattr(sparse, "_superlu_solve", lambda *a, **k: other_paths.append("superlu"))
    monkeypatch.setattr(sparse, "_CHOLMOD_FAILURES", {})
    pat, definite, indefinite = _definite_and_indefinite(2)
    b = np.random.default_rng(2).standard_normal(pat.n)
    flags = []
    for data in [indefinite, definite, indefinite, indefinite, indefinite, definite]:
        for rhs in (b, np.stack([b, 2.0 * b, -b, b + 1.0, b - 1.0], axis=1)):  # one and many right-hand sides
            x, is_definite = sparse._factor_solve(pat, data, rhs)
            A = sps.csr_matrix((data, pat.indices, pat.indptr), shape=(pat.n, pat.n))
            np.testing.assert_allclose(A @ x, rhs, rtol=0, atol=1e-9 * np.abs(rhs).max())
            flags.append(bool(is_definite))
    assert flags == [False, False, True, True] + [False] * 6 + [True, True]
    assert other_paths == [] and sparse._CHOLMOD_FAILURES == {}


def test_a_zero_ldlt_pivot_goes_to_superlu_with_its_pivots_read(monkeypatch):
    """A nonsingular symmetric matrix whose LDLᵀ without pivoting meets an exactly zero pivot
    (here 3x3 blocks [[0, 1, 0], [1, 0, 0], [0, 0, 1]] on every node: eigenvalues +-1) is
    solved by SuperLU, which pivots off the diagonal there and so reports it not definite."""
    _require_scikit_sparse()
    from difftissue.solvers import sparse

    mesh = block((1.0, 1.0, 1.0), (2, 2, 2))
    model = make_model(mesh, "fem_linear")
    pat = sparse_pattern([t.nodes for t in model.terms(Material(1.0, 0.3))], mesh.n_nodes)
    rows = np.repeat(np.arange(pat.n), np.diff(pat.indptr))
    swap = (rows // 3 == pat.indices // 3) & (rows % 3 < 2) & (pat.indices % 3 < 2) & (rows != pat.indices)
    data = np.where(swap | ((rows == pat.indices) & (rows % 3 == 2)), 1.0, 0.0)
    calls = []
    original = sparse._superlu_solve
    monkeypatch.setattr(sparse, "_superlu_solve", lambda *a, **k: calls.append(k) or original(*a, **k))
    b = np.arange(pat.n, dtype=float)
    x, is_definite = sparse._factor_solve(pat, data, b)
    np.testing.assert_allclose(sps_dense(pat, data) @ x, b, atol=1e-12)
    assert not is_definite and calls == [{"read_pivots": True}]
