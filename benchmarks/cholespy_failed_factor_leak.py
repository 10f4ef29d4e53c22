"""Resident memory after repeated sparse factorisations: cholespy (CHOLMOD) on a definite
matrix, cholespy on an indefinite one (raises "not positive definite"), SciPy's SuperLU.

A 3-D, 3-dof-per-node matrix with 2-ring rows (the square of a 7-point Laplacian on an
18^3 grid, 17,496 unknowns, like the nodal-volumetric FEM Hessian). Prints the RSS after each
of ``repeats`` factorisations per mode; a growing RSS is a leak. Run:

    python benchmarks/cholespy_failed_factor_leak.py [repeats]
"""

import gc
import sys
import time

import cholespy
import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla


def rss_gb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1e6


def matrix(m=18):
    i, d = sps.identity(m), sps.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(m, m))
    lap = sps.kron(sps.kron(d, i), i) + sps.kron(sps.kron(i, d), i) + sps.kron(sps.kron(i, i), d)
    a = sps.kron(lap @ lap + sps.identity(m**3), np.ones((3, 3)) + 3 * np.eye(3)).tocsr()
    a.sort_indices()
    return a


def main(repeats=5):
    a = matrix()
    n = a.shape[0]
    bad = (a - 30.0 * sps.identity(n)).tocsr()
    bad.sort_indices()
    print(f"n = {n}, nnz = {a.nnz}, RSS {rss_gb():.3f} GB")
    for mode in ("cholmod definite", "cholmod indefinite", "superlu definite"):
        for k in range(repeats):
            t = time.process_time()
            if mode == "cholmod definite":
                f = cholespy.CholeskySolverD(n, a.indptr.astype(np.int32), a.indices.astype(np.int32), a.data.copy(), cholespy.MatrixType.CSR)
                x = np.zeros(n)
                f.solve(np.ones(n), x)
                del f
            elif mode == "cholmod indefinite":
                try:
                    cholespy.CholeskySolverD(n, bad.indptr.astype(np.int32), bad.indices.astype(np.int32), bad.data.copy(), cholespy.MatrixType.CSR)
                except ValueError:
                    pass
            else:
                lu = spla.splu(sps.csc_matrix(a), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
                lu.solve(np.ones(n))
                del lu
            gc.collect()
            print(f"{mode}: {k + 1}, CPU {time.process_time() - t:.2f} s, RSS {rss_gb():.3f} GB", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
