"""Experiment 1, discretisation check: the same punch problem solved by P1 and by P2 tets.

Experiment 1 fits springs_volume to a scikit-fem P1 field computed on the model's own nodes.
Its E error follows the punch force error of springs_volume against that P1 solution
(docs/experiments.md). This script asks how much of that error a *more accurate* FEM would
also have against the P1 data: it solves the quarter-symmetry punch of
``exp1_synthetic_punch.py --symmetry quarter`` (12 x 12 x 6 mm block, base fixed, flat punch on
the top nodes within 3.05 mm of the axis, u_z = -0.06 mm, E = 12 kPa, nu = 0.42) with
scikit-fem's quadratic tetrahedra (``ElementTetP2``) on the same mesh. The P2 punch is the
same polygon: its vertex nodes are the P1 punch nodes, an edge node is in it when both
vertices of its edge are. So the two FEM solutions share the nodes, the supports and the
punch; they differ only in the element.

For each cube edge ``h`` it prints the P1 and P2 punch forces, P2 / P1 - 1, and the
springs_volume force error against P1 read from ``experiments/results/exp1_probe_quarter_h*.json``
(``exp1_synthetic_punch.py --symmetry quarter --cell-size H --probe``) or, failing that, from the
fit's ``exp1_synthetic_punch_quarter_h*.json``, where present.

Run:  python experiments/exp1_p2_check.py [--cell-sizes 1,0.5] [--json OUT.json]
(P2 at 0.5 mm: 43,679 unknowns, 1-1.5 min with SciPy's SuperLU; at 1/3 mm, 152k unknowns, it had
not finished after 20 min and 7 GB.)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))

from exp1_synthetic_punch import DEPTH, E_TRUE, NU_TRUE, PUNCH_RADIUS, SIZE, make_mesh  # noqa: E402


def punch_force(h_mm: float, order: int) -> tuple[float, int, float]:
    """Quarter-model punch force [N] of scikit-fem P1 (``order=1``) or P2 (``order=2``) tets on
    the Freudenthal mesh of ``h_mm`` cubes; also the number of unknowns and the solve time [s]."""
    import scipy.sparse.linalg as spla
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    quarter = (SIZE[0] / 2, SIZE[1] / 2, SIZE[2])
    cells = tuple(int(round(L * 1e3 / h_mm)) for L in quarter)
    mesh = make_mesh(cells, "quarter", SIZE)
    m = skfem.MeshTet(np.asarray(mesh.points, dtype=float).T.copy(), np.asarray(mesh.tets).T.copy())
    element = skfem.ElementTetP1() if order == 1 else skfem.ElementTetP2()
    basis = skfem.Basis(m, skfem.ElementVector(element))
    lam, mu = lame_parameters(E_TRUE, NU_TRUE)
    K = skfem.asm(linear_elasticity(lam, mu), basis).tocsr()
    X, Y, Z = basis.doflocs
    n = X.size
    component = np.zeros(n, dtype=int)
    punch = np.zeros(n, dtype=bool)
    on_punch = np.isclose(m.p[2], SIZE[2]) & (np.hypot(m.p[0], m.p[1]) <= PUNCH_RADIUS)
    for c in range(3):
        component[basis.nodal_dofs[c]] = c
        punch[basis.nodal_dofs[c]] = on_punch
        if order == 2:
            component[basis.edge_dofs[c]] = c
            punch[basis.edge_dofs[c]] = on_punch[m.edges[0]] & on_punch[m.edges[1]]
    tol = 1e-12
    fixed = np.isclose(Z, 0.0, atol=tol) | (punch & (component == 2))
    fixed |= np.isclose(X, 0.0, atol=tol) & (component == 0)
    fixed |= np.isclose(Y, 0.0, atol=tol) & (component == 1)
    u = np.zeros(n)
    u[punch & (component == 2)] = -DEPTH
    free = ~fixed
    t0 = time.perf_counter()
    u[free] = spla.spsolve(K[free][:, free].tocsc(), -K[free][:, fixed] @ u[fixed])
    seconds = time.perf_counter() - t0
    return float(-(K @ u)[punch & (component == 2)].sum()), int(free.sum()), seconds


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell-sizes", default="1,0.5", help="cube edges [mm], comma-separated")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = ap.parse_args()
    rows = []
    print("| cube edge h [mm] | P1 force [mN] | P2 force [mN] | P2 / P1 - 1 | springs_volume / P1 - 1 | P1, P2 unknowns | P2 solve [s] |")
    print("|---|---|---|---|---|---|---|")
    for h in (float(v) for v in args.cell_sizes.split(",")):
        f1, n1, _ = punch_force(h, 1)
        f2, n2, t2 = punch_force(h, 2)
        springs = None
        for name, key in ((f"exp1_probe_quarter_h{h:g}mm.json", "probes"), (f"exp1_synthetic_punch_quarter_h{h:g}mm.json", "fits")):
            path = HERE / "results" / name
            if springs is None and path.exists():
                rows_h = json.loads(path.read_text())[key]
                springs = next((r["force_error_at_true_material"] for r in rows_h if r["model"] == "springs_volume"), None)
        rows.append({"cell_size_mm": h, "p1_force_N": f1, "p2_force_N": f2, "p2_vs_p1": f2 / f1 - 1.0, "springs_volume_vs_p1": springs, "p1_unknowns": n1, "p2_unknowns": n2, "p2_seconds": t2})
        s = "–" if springs is None else f"{100 * springs:+.2f} %"
        print(f"| {h:g} | {f1 * 1e3:.4f} | {f2 * 1e3:.4f} | {100 * (f2 / f1 - 1):+.2f} % | {s} | {n1:,}, {n2:,} | {t2:.1f} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"experiment": "exp1_p2_check", "truth": {"youngs_modulus": E_TRUE, "poisson_ratio": NU_TRUE}, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
