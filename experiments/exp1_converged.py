"""Experiment 1, converged: fit E, nu against a converged P2 reference of the flat punch.

Experiment 1 (``exp1_synthetic_punch.py``) compares each model with scikit-fem P1 tets on the
model's own nodes, so it measures P1's discretisation, not the continuum. This script builds
a reference that is itself converged and fits each model on its own lattice against it.

**Problem** (the quarter x, y >= 0 of experiment 1's 12 x 12 x 6 mm block, E = 12 kPa,
nu = 0.42): base z = 0 bonded, symmetry rollers on x = 0 (u_x = 0) and y = 0 (u_y = 0), a
frictionless flat punch prescribing u_z = -0.06 mm (1 % of the thickness) on the top face,
the rest of the top and the outer sides free. The punch is the **square** |x|, |y| <= 3 mm
(half-width 3 mm, the radius of experiment 1's punch): a node set of the top face that every
lattice with h dividing 3 mm holds exactly, so the continuum problem is the same at every h
and the differences between the models are discretisation alone (experiment 1's punch, the
top nodes within 3.05 mm of the axis, is a staircase that changes with h).

**Reference** (``reference``): scikit-fem quadratic tets (``ElementTetP2``) on tensor meshes
graded towards the punch edge (x = 3 mm, y = 3 mm, z = 6 mm: a power map of exponent
``GRADING``) with ``n`` intervals on each side of the edge, solved with PyAMG smoothed
aggregation + CG. The punch force of the levels is Richardson-extrapolated in 1/n. The
displacement of the finest level is sampled at the nodes of a uniform P2 mesh of 0.5 mm cubes
(``exp1_converged_reference.npz``); that field and the extrapolated force are the data.

**Fits** (``fit``): :class:`difftissue.scenarios.FEMField` with ``specimen=`` the model's own
``block`` of h-cubes (reference interpolated; prescribed: bottom xyz, punch z, rollers;
reaction: the punch z force = the extrapolated reference force); E and nu free, Gauss-Newton.

**Graded fits** (``fit --graded``): the FEM models on the graded tet mesh of level ``n``
(:func:`graded_specimen`: ``structured_grid`` of the reference's own axes ``punch_axes(n)``, a
node at the punch edge x = y = 3 mm, cells falling as ``t**GRADING`` towards it from both sides
and towards the top z = 6 mm; one parameter n, smallest cell 3 mm / n**GRADING), with the same
punch node set, rollers and bonded base.

Run:  python experiments/exp1_converged.py reference [--levels 4,6,8,12]
      python experiments/exp1_converged.py fit [--models springs_volume,fem_linear,stable_neo_hookean] [--cell-sizes 1,0.75,0.5,0.375,0.25]
      python experiments/exp1_converged.py fit --graded [--models fem_linear,stable_neo_hookean] [--levels 4,6,8,12,16]
      python experiments/exp1_converged.py report
Raw output: experiments/results/exp1_converged_*.json (one file per reference level and per fit;
graded fits: exp1_converged_fit_{model}_graded_n{n}.json).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
E_TRUE, NU_TRUE = 12.0e3, 0.42  # Pa, -
QUARTER = (6e-3, 6e-3, 6e-3)  # m: the quarter x, y >= 0 of the 12 x 12 x 6 mm block
HALF_WIDTH = 3e-3  # m: the square punch |x|, |y| <= 3 mm
DEPTH = 0.06e-3  # m
GRADING = 2.0  # power of the mesh grading towards the punch edge
SAMPLE_CUBE = 0.5e-3  # m: cube edge of the uniform P2 mesh the reference field is sampled on
INITIAL = (8e3, 0.33)


# ---------------------------------------------------------------- the P2 reference builder
def graded_axis(length: float, edge: float | None, n: int, power: float = GRADING) -> np.ndarray:
    """Node coordinates [m] on [0, length]: ``n`` intervals on each side of ``edge`` whose size
    falls as ``t**power`` towards it (``edge == length``: ``n`` intervals towards the end;
    ``edge is None``: ``n`` uniform intervals)."""
    t = np.linspace(0.0, 1.0, n + 1)
    if edge is None:
        return length * t
    left = edge - edge * (1.0 - t) ** power  # 0 .. edge, dense at edge
    if np.isclose(edge, length):
        return left
    right = edge + (length - edge) * t[1:] ** power  # edge .. length, dense at edge
    return np.concatenate([left, right])


def p2_solve(x, y, z, youngs_modulus: float, poisson_ratio: float, prescribe, direct_limit: int = 60_000):
    """Linear elasticity with scikit-fem P2 tets on the tensor mesh of the axes ``x, y, z`` [m].

    ``prescribe(points (n, 3), component (n,)) -> (fixed mask, values [m])`` over the DOFs
    (``points`` their locations: vertices and edge midpoints). Returns a dict: ``mesh``,
    ``basis``, ``u`` (DOF vector [m]), ``reaction`` ``K u`` on fixed DOFs [N] (0 on free ones),
    ``fixed``, ``component``, ``unknowns``, ``solver``, ``cg_iterations``, ``cpu_seconds``.
    Solver: SciPy's direct LU up to ``direct_limit`` unknowns, else PyAMG smoothed aggregation (rigid-body
    near-null space) + CG to a relative residual of 1e-12.
    """
    import pyamg
    import scipy.sparse.linalg as spla
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    t0 = time.process_time()
    m = skfem.MeshTet.init_tensor(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP2()))
    lam, mu = lame_parameters(youngs_modulus, poisson_ratio)
    K = skfem.asm(linear_elasticity(lam, mu), basis).tocsr()
    pts = basis.doflocs.T
    component = np.zeros(len(pts), dtype=int)
    for c in range(3):
        component[basis.nodal_dofs[c]] = c
        component[basis.edge_dofs[c]] = c
    fixed, values = prescribe(pts, component)
    u = np.where(fixed, values, 0.0).astype(float)
    free = ~fixed
    A = K[free][:, free].tocsr()
    b = -K[free][:, fixed] @ u[fixed]
    iterations = 0
    if A.shape[0] <= direct_limit:
        u[free] = spla.spsolve(A.tocsc(), b)
        solver = "direct"
    else:
        fp = pts[free]
        comp = component[free]
        B = np.zeros((A.shape[0], 6))
        for c in range(3):
            B[comp == c, c] = 1.0
        # rotations: e_c x r
        B[comp == 0, 3], B[comp == 1, 3] = -fp[comp == 0, 1], fp[comp == 1, 0]
        B[comp == 1, 4], B[comp == 2, 4] = -fp[comp == 1, 2], fp[comp == 2, 1]
        B[comp == 0, 5], B[comp == 2, 5] = fp[comp == 0, 2], -fp[comp == 2, 0]
        ml = pyamg.smoothed_aggregation_solver(A, B=B, max_coarse=500)
        res = []
        u[free] = ml.solve(b, tol=1e-12, accel="cg", maxiter=2000, residuals=res)
        iterations = len(res) - 1
        solver = "pyamg-sa+cg"
        rel = np.linalg.norm(b - A @ u[free]) / np.linalg.norm(b)
        if not rel < 1e-10:
            raise RuntimeError(f"PyAMG CG did not converge: relative residual {rel:.2e} after {iterations} iterations")
    reaction = K @ u
    reaction[free] = 0.0
    return {"mesh": m, "basis": basis, "u": u, "reaction": reaction, "fixed": fixed, "component": component, "unknowns": int(free.sum()), "solver": solver, "cg_iterations": iterations, "cpu_seconds": time.process_time() - t0}


def punch_prescribe(points, component):
    """The punch problem's prescribed DOFs (see the module docstring)."""
    tol = 1e-9
    X, Y, Z = points.T
    punch = np.isclose(Z, QUARTER[2], atol=tol) & (X <= HALF_WIDTH + tol) & (Y <= HALF_WIDTH + tol) & (component == 2)
    fixed = np.isclose(Z, 0.0, atol=tol) | punch
    fixed |= np.isclose(X, 0.0, atol=tol) & (component == 0)
    fixed |= np.isclose(Y, 0.0, atol=tol) & (component == 1)
    values = np.where(punch, -DEPTH, 0.0)
    return fixed, values


def punch_axes(n: int, power: float = GRADING):
    """The graded axes of reference level ``n`` (n intervals on each side of the edge)."""
    return (graded_axis(QUARTER[0], HALF_WIDTH, n, power), graded_axis(QUARTER[1], HALF_WIDTH, n, power), graded_axis(QUARTER[2], QUARTER[2], n, power))


def punch_force(sol) -> float:
    """Quarter punch force [N] (positive: pushing down)."""
    X, Y, Z = sol["basis"].doflocs
    on = sol["fixed"] & (sol["component"] == 2) & np.isclose(Z, QUARTER[2], atol=1e-9)
    return float(-sol["reaction"][on].sum())


def tetra10_cells(m):
    """Nodes and VTK-ordered ``tetra10`` cells of the skfem tet mesh ``m``: points are the
    vertices followed by the edge midpoints (in ``m.edges`` order, skfem's P2 DOF order)."""
    mids = 0.5 * (m.p[:, m.edges[0]] + m.p[:, m.edges[1]])
    points = np.concatenate([m.p.T, mids.T])
    nv = m.p.shape[1]
    key = lambda a, b: np.minimum(a, b) * nv + np.maximum(a, b)  # noqa: E731
    ekeys = key(m.edges[0], m.edges[1])
    order = np.argsort(ekeys)
    t = m.t
    pairs = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))  # VTK_QUADRATIC_TETRA edge order
    cells = np.empty((t.shape[1], 10), dtype=np.int64)
    cells[:, :4] = t.T
    for j, (a, b) in enumerate(pairs):
        k = key(t[a], t[b])
        pos = order[np.searchsorted(ekeys, k, sorter=order)]
        if not np.array_equal(ekeys[pos], k):
            raise RuntimeError("an element edge is missing from the mesh's edge list")
        cells[:, 4 + j] = nv + pos
    return points, cells


def sample_field(sol, points) -> np.ndarray:
    """The P2 displacement of ``sol`` at ``points`` (n, 3) [m], by its own shape functions
    (located and weighted by :func:`difftissue.interpolation.interpolation_operator`)."""
    from difftissue.interpolation import interpolation_operator

    nodes, cells = tetra10_cells(sol["mesh"])
    vb = sol["basis"]
    field = np.stack([np.concatenate([sol["u"][vb.nodal_dofs[c]], sol["u"][vb.edge_dofs[c]]]) for c in range(3)], 1)
    op = interpolation_operator(nodes, {"tetra10": cells}, np.asarray(points, float), what="sample points")
    return np.asarray(op.as_sparse() @ field)  # SciPy, float64


def tetra10_mesh(cube: float, size=QUARTER):
    """A uniform P2 mesh (VTK ``tetra10`` node order) of ``cube``-sided cubes: (points, cells)."""
    import skfem

    axes = [np.linspace(0.0, s, int(round(s / cube)) + 1) for s in size]
    return tetra10_cells(skfem.MeshTet.init_tensor(*axes))


def richardson(h, f):
    """Richardson extrapolation of ``f(h) = f0 + C h**p`` from the last three levels (any
    ratios): ``(p, f0, estimated error of the finest level relative to f0)``; ``p`` from the
    bisection of the three-level equation, ``None`` when the differences change sign."""
    h1, h2, h3 = (float(v) for v in h[-3:])
    f1, f2, f3 = (float(v) for v in f[-3:])
    d12, d23 = f1 - f2, f2 - f3
    if d12 * d23 <= 0:
        return None, None, None
    g = lambda p: (h1**p - h2**p) / (h2**p - h3**p) - d12 / d23  # noqa: E731
    lo, hi = 1e-3, 10.0
    if g(lo) * g(hi) > 0:
        return None, None, None
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(lo) * g(mid) > 0 else (lo, mid)
    p = 0.5 * (lo + hi)
    C = d23 / (h2**p - h3**p)
    f0 = f3 - C * h3**p
    return p, f0, (f3 - f0) / f0


# ---------------------------------------------------------------- reference levels
def run_reference(levels, power):
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    finest = None
    for n in levels:
        path = RESULTS / f"exp1_converged_reference_n{n}_q{power:g}.json"
        if path.exists() and n != levels[-1]:  # reuse a finished level; the finest is solved for its field
            rows.append(json.loads(path.read_text()))
            continue
        sol = p2_solve(*punch_axes(n, power), E_TRUE, NU_TRUE, punch_prescribe)
        row = {"n": n, "grading": power, "smallest_interval_m": float(HALF_WIDTH / n**power), "unknowns": sol["unknowns"], "force_N": punch_force(sol), "solver": sol["solver"], "cg_iterations": sol["cg_iterations"], "cpu_seconds": sol["cpu_seconds"]}
        rows.append(row)
        path.write_text(json.dumps(row, indent=2))
        print(json.dumps(row), flush=True)
        finest = sol
    pts, cells = tetra10_mesh(SAMPLE_CUBE)
    u = sample_field(finest, pts)
    np.savez_compressed(RESULTS / "exp1_converged_reference.npz", points=pts, cells=cells, displacement=u, level=levels[-1], grading=power)
    return rows


def reference_table(power=GRADING):
    rows = sorted((json.loads(p.read_text()) for p in RESULTS.glob(f"exp1_converged_reference_n*_q{power:g}.json")), key=lambda r: r["n"])
    table = []
    for i, r in enumerate(rows):
        hs = [1.0 / q["n"] for q in rows[: i + 1]]
        fs = [q["force_N"] for q in rows[: i + 1]]
        p, f0, err = richardson(hs, fs) if i >= 2 else (None, None, None)
        table.append({**r, "order": p, "extrapolated_N": f0, "estimated_error": err})
    return table


def converged_force(power=GRADING):
    t = reference_table(power)
    if not t or t[-1]["extrapolated_N"] is None:
        raise RuntimeError("run the reference first (three levels at least)")
    return t[-1]["extrapolated_N"]


# ---------------------------------------------------------------- fits
def graded_specimen(n: int, power: float = GRADING):
    """The graded model mesh of level ``n``: ``structured_grid`` of :func:`punch_axes` (x and y
    with a node at the punch edge 3 mm and ``n`` intervals on each side, z with ``n`` intervals
    towards the top; sizes falling as ``t**power`` towards the edge and the top), 6 tets per box."""
    from difftissue.mesh import structured_grid

    return structured_grid(*punch_axes(n, power))


def make_scenario(model: str, h: float | None, force: float, specimen=None):
    """The fit scenario on the uniform ``block`` of ``h``-cubes, or on ``specimen`` (``h`` None)."""
    from difftissue.data import FEMResult
    from difftissue.mesh import block
    from difftissue.scenarios import FEMField, SolverOptions

    d = np.load(RESULTS / "exp1_converged_reference.npz")
    ref = FEMResult(None, d["displacement"], points=d["points"], cells={"tetra10": d["cells"]})
    if specimen is None:
        cells = tuple(int(round(s / h)) for s in QUARTER)
        if not np.allclose(np.array(cells) * h, QUARTER) or abs(HALF_WIDTH / h - round(HALF_WIDTH / h)) > 1e-9:
            raise ValueError(f"cell size {h} m does not divide the quarter {QUARTER} m and the punch half-width {HALF_WIDTH} m")
        specimen = block(QUARTER, cells, origin=(0.0, 0.0, 0.0))
    eps = 1e-9
    punch = {"box": {"lower": [-eps, -eps, QUARTER[2] - eps], "upper": [HALF_WIDTH + eps, HALF_WIDTH + eps, QUARTER[2] + eps]}}
    prescribed = [
        {"set": {"face": "z-min"}, "components": "xyz"},
        {"set": punch, "components": "z"},
        {"set": {"face": "x-min"}, "components": "x"},
        {"set": {"face": "y-min"}, "components": "y"},
    ]
    return FEMField(ref, ref.displacement, specimen=specimen, prescribed=prescribed, reaction={"set": punch, "components": "z", "force": [-force]}, model=model, options=SolverOptions(), name=f"punch_{model}"), int(specimen.points.shape[0])


def fit_one(model: str, h: float | None, force: float, graded_n: int | None = None, power: float = GRADING):
    """One fit on the uniform lattice of ``h``-cubes, or (``graded_n``) on :func:`graded_specimen`."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from difftissue.errors import FitQualityWarning
    from difftissue.fit import fit
    from difftissue.materials import Material, MaterialParameterization, ScaledLogit

    t0 = time.process_time()
    specimen = None if graded_n is None else graded_specimen(graded_n, power)
    sc, n_nodes = make_scenario(model, h, force, specimen)
    lower = 0.25 if model == "springs_volume" else 0.0
    param = MaterialParameterization(("youngs_modulus", "poisson_ratio"), {"poisson_ratio": ScaledLogit(lower, 0.499)})
    with warnings.catch_warnings():  # the lattice misses the data near the punch edge by far more than sigma: expected
        warnings.simplefilter("ignore", FitQualityWarning)
        res = fit(sc, param, Material(*INITIAL), method="gauss_newton", max_steps=40)
    f_true = float(np.asarray(sc.predict(Material(E_TRUE, NU_TRUE)))[-1])
    if graded_n is None:
        mesh = {"cell_size_m": h, "cells_per_half_width": HALF_WIDTH / h}
    else:
        d = [np.diff(a) for a in punch_axes(graded_n, power)]
        mesh = {"mesh": "graded", "n": graded_n, "grading": power, "smallest_cell_m": float(min(v.min() for v in d)), "largest_cell_m": float(max(v.max() for v in d)), "tets": int(specimen.tets.shape[0])}
    return {
        "model": model, **mesh, "nodes": n_nodes,
        "E": res.values["youngs_modulus"], "nu": res.values["poisson_ratio"],
        "E_error": res.values["youngs_modulus"] / E_TRUE - 1.0, "nu_error": res.values["poisson_ratio"] - NU_TRUE,
        "force_error_at_true_material": f_true / sc.observed[-1] - 1.0,
        "reference_force_N": force, "converged": bool(res.converged), "steps": int(res.steps), "loss": float(res.loss),
        "cpu_seconds": time.process_time() - t0, "n_observations": int(sc.observed.size),
    }


def graded_fit_path(model: str, n: int, power: float = GRADING) -> Path:
    q = "" if power == GRADING else f"_q{power:g}"
    return RESULTS / f"exp1_converged_fit_{model}_graded_n{n}{q}.json"


def run_fits(models, cell_sizes, graded_levels=None, power=GRADING):
    """Uniform fits at ``cell_sizes`` [m], or (``graded_levels``) graded fits at those levels n."""
    force = converged_force()
    levels = cell_sizes if graded_levels is None else graded_levels
    for level in levels:
        for model in models:
            if graded_levels is None:
                out = RESULTS / f"exp1_converged_fit_{model}_h{level * 1e3:g}mm.json"
            else:
                out = graded_fit_path(model, level, power)
            claim = out.with_suffix(".running")  # another process fits this level: skip it
            if out.exists() or claim.exists():
                continue
            claim.write_text("")
            try:
                if graded_levels is None:
                    row = fit_one(model, level, force)
                else:
                    row = fit_one(model, None, force, graded_n=level, power=power)
                out.write_text(json.dumps(row, indent=2))
            finally:
                claim.unlink()
            print(json.dumps(row), flush=True)


# ---------------------------------------------------------------- report
def uniform_equivalent_h(nodes: int) -> float:
    """The cube edge [m] of the uniform lattice of the quarter with ``nodes`` nodes: (6 mm / h + 1)**3 = nodes."""
    return QUARTER[0] / (nodes ** (1.0 / 3.0) - 1.0)


def uniform_at_nodes(uniform_rows, nodes: int, key: str = "E_error"):
    """The uniform lattice's error ``key`` at ``nodes`` nodes: log-log interpolation in the
    node count between the two uniform levels around it (None outside their range or on a sign change)."""
    rows = sorted(uniform_rows, key=lambda f: f["nodes"])
    for a, b in zip(rows, rows[1:]):
        if a["nodes"] <= nodes <= b["nodes"] and a[key] * b[key] > 0:
            w = np.log(nodes / a["nodes"]) / np.log(b["nodes"] / a["nodes"])
            return float(np.sign(a[key]) * np.exp((1 - w) * np.log(abs(a[key])) + w * np.log(abs(b[key]))))
    return None


def local_order(error_a, error_b, h_a, h_b) -> float:
    """Log-log slope of |error| between two levels of size ``h_a`` and ``h_b`` (NaN on a sign change)."""
    if error_a * error_b <= 0:
        return float("nan")
    return float(np.log(abs(error_a) / abs(error_b)) / np.log(h_a / h_b))


def graded_report(graded, uniform):
    """Print the graded-mesh tables; returns the Richardson extrapolation per model."""
    if not graded:
        return {}
    print("\n| model | n | smallest / largest cell [mm] | nodes | E error | local order (E) vs smallest cell | vs nodes^(-1/3) | nu error | force at truth | uniform E error at equal nodes | CPU [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    summary = {}
    for model in ("fem_linear", "stable_neo_hookean"):
        rows = sorted((f for f in graded if f["model"] == model), key=lambda f: f["n"])
        uni = [f for f in uniform if f["model"] == model]
        for i, f in enumerate(rows):
            oh = oN = "–"
            if i:
                g = rows[i - 1]
                oh = f"{local_order(g['E_error'], f['E_error'], g['smallest_cell_m'], f['smallest_cell_m']):.2f}"
                oN = f"{local_order(g['E_error'], f['E_error'], g['nodes'] ** (-1 / 3), f['nodes'] ** (-1 / 3)):.2f}"
            u = uniform_at_nodes(uni, f["nodes"])
            us = "–" if u is None else f"{100 * u:+.2f} %"
            print(f"| {model} | {f['n']} | {f['smallest_cell_m'] * 1e3:.4f} / {f['largest_cell_m'] * 1e3:.3f} | {f['nodes']:,} | {100 * f['E_error']:+.2f} % | {oh} | {oN} | {f['nu_error']:+.4f} | {100 * f['force_error_at_true_material']:+.2f} % | {us} | {f['cpu_seconds']:.0f} |")
        if len(rows) >= 3:
            h = [f["smallest_cell_m"] for f in rows]
            pE, E0, _ = richardson(h, [f["E"] for f in rows])
            pN, E0N, _ = richardson([f["nodes"] ** (-1 / 3) for f in rows], [f["E"] for f in rows])
            pF, F0, _ = richardson(h, [f["force_error_at_true_material"] for f in rows])
            summary[model] = {"levels": [f["n"] for f in rows[-3:]], "E_order_smallest_cell": pE, "E_limit": E0, "E_order_nodes": pN, "E_limit_nodes": E0N, "force_error_limit": F0}
    if not summary:
        return summary
    print("\n| model | levels n | Richardson order in E (smallest cell) | extrapolated E [kPa] | order vs nodes^(-1/3) | extrapolated E [kPa] | force at truth, extrapolated |")
    print("|---|---|---|---|---|---|---|")
    fmt = lambda v, spec, scale=1.0: "–" if v is None else format(v * scale, spec)  # noqa: E731
    for model, s in summary.items():
        print(f"| {model} | {', '.join(map(str, s['levels']))} | {fmt(s['E_order_smallest_cell'], '.2f')} | {fmt(s['E_limit'], '.4f', 1e-3)} | {fmt(s['E_order_nodes'], '.2f')} | {fmt(s['E_limit_nodes'], '.4f', 1e-3)} | {fmt(s['force_error_limit'], '+.2%')} |")
    return summary


def report():
    print("| level n | smallest interval [mm] | unknowns | force [mN] | observed order | extrapolated [mN] | estimated error of this level | CPU [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for r in reference_table():
        o = "–" if r["order"] is None else f"{r['order']:.2f}"
        x = "–" if r["extrapolated_N"] is None else f"{r['extrapolated_N'] * 1e3:.5f}"
        e = "–" if r["estimated_error"] is None else f"{100 * r['estimated_error']:+.3f} %"
        print(f"| {r['n']} | {r['smallest_interval_m'] * 1e3:.4f} | {r['unknowns']:,} | {r['force_N'] * 1e3:.5f} | {o} | {x} | {e} | {r['cpu_seconds']:.0f} |")
    fits = [json.loads(p.read_text()) for p in RESULTS.glob("exp1_converged_fit_*_h*mm.json")]
    graded = [json.loads(p.read_text()) for p in RESULTS.glob("exp1_converged_fit_*_graded_n*.json")]
    graded = [g for g in graded if g["grading"] == GRADING]
    if not fits:
        return
    summary = {}
    print("\n| model | h [mm] | cells per half-width | nodes | E error | order (E) | nu error | order (nu) | force error at truth | steps | CPU [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for model in ("springs_volume", "fem_linear", "stable_neo_hookean"):
        rows = sorted((f for f in fits if f["model"] == model), key=lambda f: -f["cell_size_m"])
        for i, f in enumerate(rows):
            # local order: log-log slope of |error| against h from the previous (coarser) level
            oE = on = "–"
            if i:
                g = rows[i - 1]
                oE = f"{local_order(g['E_error'], f['E_error'], g['cell_size_m'], f['cell_size_m']):.2f}"
                on = f"{local_order(g['nu_error'], f['nu_error'], g['cell_size_m'], f['cell_size_m']):.2f}"
            print(f"| {model} | {f['cell_size_m'] * 1e3:g} | {f['cells_per_half_width']:g} | {f['nodes']:,} | {100 * f['E_error']:+.2f} % | {oE} | {f['nu_error']:+.4f} | {on} | {100 * f['force_error_at_true_material']:+.2f} % | {f['steps']} | {f['cpu_seconds']:.0f} |")
        if len(rows) >= 3:
            hs = [f["cell_size_m"] for f in rows]
            pE, E0, _ = richardson(hs, [f["E"] for f in rows])
            pn, n0, _ = richardson(hs, [f["nu"] for f in rows])
            summary[model] = {"E_order": pE, "E_limit": E0, "nu_order": pn, "nu_limit": n0}
    print("\n| model | Richardson order in E (3 finest) | extrapolated E [kPa] | Richardson order in nu | extrapolated nu |")
    print("|---|---|---|---|---|")
    for model, s in summary.items():
        fmt = lambda v, spec: "–" if v is None else format(v, spec)  # noqa: E731
        print(f"| {model} | {fmt(s['E_order'], '.2f')} | {fmt(None if s['E_limit'] is None else s['E_limit'] / 1e3, '.4f')} | {fmt(s['nu_order'], '.2f')} | {fmt(s['nu_limit'], '.4f')} |")
    graded_summary = graded_report(graded, fits)
    (RESULTS / "exp1_converged_summary.json").write_text(json.dumps({"reference": reference_table(), "fits": fits, "extrapolation": summary, "graded_fits": graded, "graded_extrapolation": graded_summary}, indent=2))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(10, 4))
    for model, mk in (("springs_volume", "o"), ("fem_linear", "s"), ("stable_neo_hookean", "^")):
        rows = sorted((f for f in fits if f["model"] == model), key=lambda f: -f["cell_size_m"])
        if not rows:
            continue
        h = np.array([f["cell_size_m"] * 1e3 for f in rows])
        (line,) = axs[0].loglog(h, [100 * abs(f["E_error"]) for f in rows], mk + "-", label=model)
        axs[1].loglog(h, [abs(f["nu_error"]) for f in rows], mk + "-", color=line.get_color(), label=model)
        g = sorted((f for f in graded if f["model"] == model), key=lambda f: f["n"])
        if g:  # the graded meshes at the cube size of the uniform lattice with as many nodes
            hg = np.array([uniform_equivalent_h(f["nodes"]) * 1e3 for f in g])
            label = f"{model}, graded (at the h of equal nodes)"
            axs[0].loglog(hg, [100 * abs(f["E_error"]) for f in g], mk + "--", mfc="none", color=line.get_color(), label=label)
            axs[1].loglog(hg, [abs(f["nu_error"]) for f in g], mk + "--", mfc="none", color=line.get_color(), label=label)
    axs[0].axhline(2.0, color="k", lw=0.8, ls="--")
    axs[1].axhline(0.02, color="k", lw=0.8, ls="--")
    axs[0].set_ylabel("|E error| [%]")
    axs[1].set_ylabel("|nu error|")
    for ax, loc in zip(axs, ("lower right", "upper left")):
        ax.set_xlabel("cell size h [mm] (punch half-width 3 mm)")
        ax.legend(fontsize=7, loc=loc)
        ax.grid(True, which="both", lw=0.3)
    fig.suptitle("Exp 1 converged: fits against a Richardson-extrapolated P2 reference (E = 12 kPa, nu = 0.42)")
    fig.tight_layout()
    fig.savefig(RESULTS / "exp1_converged.png", dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=("reference", "fit", "report"))
    ap.add_argument("--levels", default="4,6,8,12", help="reference levels n (intervals on each side of the punch edge)")
    ap.add_argument("--grading", type=float, default=GRADING)
    ap.add_argument("--models", default=None, help="default: springs_volume,fem_linear,stable_neo_hookean (with --graded: the FEM models)")
    ap.add_argument("--cell-sizes", default="1,0.75,0.5,0.375,0.25", help="model cube edges [mm]")
    ap.add_argument("--graded", action="store_true", help="fit: the graded model meshes of levels --levels (graded_specimen) instead of uniform cubes")
    args = ap.parse_args()
    if args.command == "reference":
        run_reference([int(v) for v in args.levels.split(",")], args.grading)
    elif args.command == "fit":
        levels = [int(v) for v in args.levels.split(",")] if args.graded else None
        models = args.models or ("fem_linear,stable_neo_hookean" if args.graded else "springs_volume,fem_linear,stable_neo_hookean")
        run_fits(models.split(","), [float(v) * 1e-3 for v in args.cell_sizes.split(",")], levels, args.grading)
    report()


if __name__ == "__main__":
    main()
