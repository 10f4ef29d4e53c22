"""Locating 2,000 random points in a distorted 8 x 8 x 4 hexahedron grid (interpolation_operator):
CPU time and a hash of the operator. Run with PYTHONPATH set to the tree to time (before /
after); results: benchmarks/results/interpolation-hex-locate-2026-12-05.json."""

import hashlib
import json
import time

import numpy as np

import difftissue
from difftissue.interpolation import interpolation_operator


def hex_grid(n, perturb, seed=0, size=(0.01, 0.01, 0.005)):
    """``(points, hexahedra)`` of an n[0] x n[1] x n[2] grid, interior nodes moved at random by up
    to ``perturb`` of a cell (VTK order)."""
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, n)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(P)).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    interior = np.ones(idx.shape, dtype=bool)
    interior[[0, -1]] = interior[:, [0, -1]] = interior[:, :, [0, -1]] = False
    cell = np.array(size) / np.array(n)
    P[idx[interior]] += perturb * cell * np.random.default_rng(seed).uniform(-1, 1, (int(interior.sum()), 3))
    i, j, k = (a.reshape(-1) for a in np.meshgrid(*[np.arange(m) for m in n], indexing="ij"))
    return P, np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                        idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]], axis=1)


if __name__ == "__main__":
    P, C = hex_grid((8, 8, 4), 0.25)
    q = np.random.default_rng(1).uniform(0, 1, (2000, 3)) * [0.01, 0.01, 0.005]
    t = time.process_time()
    op = interpolation_operator(P, {"hexahedron": C}, q)
    dt = time.process_time() - t
    sha = hashlib.sha256(op.indices.tobytes() + np.round(op.weights, 12).tobytes()).hexdigest()[:12]
    print(json.dumps({"tree": difftissue.__file__.split("/difftissue/")[0], "cpu_s": round(dt, 3), "sha_idx_w": sha}))
