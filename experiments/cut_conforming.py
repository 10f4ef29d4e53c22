"""The 25 deg / 0 deg ratio of the incision's max surface width on tet meshes that FOLLOW the cut.

What: the whole-square P2 linear limit of the incision geometry of experiments/cut_convergence.py
(12 x 12 mm square, dermis 2 mm, E = 200 kPa, on fat 4 mm, E = 5 kPa, nu = 0.45; lateral faces held
in x and y, base clamped; a 6 mm cut through the dermis, z from 4 to 6 mm, centred, at angle theta to
x; loaded by the dermis' equibiaxial pre-stretch: the linear limit lambda0 = 1.001, or finite lambda0 with --lams), on an unstructured gmsh tet mesh
in which the cut rectangle is an internal surface (OCC boolean fragments), refined towards the cut
(Distance + Threshold size fields). Independent of the library's snapped cut meshes
(`cut_convergence.rotation`), whose 25 deg crack front is rough at 0.5 mm.

How: the nodes of the cut surface are duplicated except the crack front (bottom edge z = 4 mm and
the two vertical end edges; the top edge on the free surface is opened); the tets with an opened
node on the minus side of the cut plane (normal (-sin, cos, 0)) take the copies; midside nodes of
cut-face edges between two front nodes get a copy through `P2Problem`'s ``open_edges``. The solve
is `cut_convergence.P2Problem`'s (compressible neo-Hookean, Newton, CHOLMOD), continued in lambda0.
Width: the distance between the deformed paired top-surface points (vertices and the P2 midside
points of the top edge), reported per unit pre-strain [mm] (width / (lambda0 - 1)).

Run:  PYTHONPATH=. python experiments/cut_conforming.py --h 0.4 0.28 [--angles 0 25]
      [--far 1.5] [--lams 1.001 1.05 1.10 1.15]  -> rows appended to experiments/results/cut_conforming_p2.json
      (a (h_cut, h_far, angle) row given again is replaced);  --table prints the 25/0 table.
Units inside: mm, kPa.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from cut_convergence import E_DERMIS, E_FAT, LINEAR, P2Problem, RESULTS, _load, _write, rss_mb  # noqa: E402

# geometry [mm]
SIDE, Z_FAT, Z_TOP, CUT_LENGTH = 12.0, 4.0, 6.0, 6.0
CENTRE = np.array([6.0, 6.0])
OUT_NAME = "cut_conforming_p2.json"
EPS = 1e-7


def cut_axes(angle):
    """Unit direction along the cut and unit normal of the cut plane (in x, y) at ``angle`` [deg]."""
    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
    return np.array([c, s]), np.array([-s, c])


def conforming_mesh(angle, h_cut, h_far=1.5, dist_far=4.0):
    """gmsh tet mesh [mm] of the square with the layer interface z = 4 and the cut rectangle as
    internal faces. Element size h_cut within 0.5 h_cut of the cut surface, growing linearly to
    h_far at ``dist_far`` from it. Returns points (N, 3), tets (M, 4), dermis mask (M,), and the
    cut-face triangles (K, 3)."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("incision")
        occ = gmsh.model.occ
        fat = occ.addBox(0, 0, 0, SIDE, SIDE, Z_FAT)
        derm = occ.addBox(0, 0, Z_FAT, SIDE, SIDE, Z_TOP - Z_FAT)
        d, _ = cut_axes(angle)
        a, b = CENTRE - 0.5 * CUT_LENGTH * d, CENTRE + 0.5 * CUT_LENGTH * d
        pts = [occ.addPoint(a[0], a[1], Z_FAT), occ.addPoint(b[0], b[1], Z_FAT), occ.addPoint(b[0], b[1], Z_TOP), occ.addPoint(a[0], a[1], Z_TOP)]
        lines = [occ.addLine(pts[i], pts[(i + 1) % 4]) for i in range(4)]
        cut = occ.addPlaneSurface([occ.addCurveLoop(lines)])
        occ.fragment([(3, fat), (3, derm)], [(2, cut)])
        occ.synchronize()
        # the cut surface after fragmenting: the surface whose centre is the cut's centre
        cut_tags = []
        for dim, tag in gmsh.model.getEntities(2):
            cx, cy, cz = occ.getCenterOfMass(dim, tag)
            if abs(cx - CENTRE[0]) < 1e-6 and abs(cy - CENTRE[1]) < 1e-6 and abs(cz - 0.5 * (Z_FAT + Z_TOP)) < 1e-6:
                cut_tags.append(tag)
        assert len(cut_tags) == 1, cut_tags
        f_dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(f_dist, "SurfacesList", cut_tags)
        gmsh.model.mesh.field.setNumber(f_dist, "Sampling", 200)
        f_thr = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(f_thr, "InField", f_dist)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMin", h_cut)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMax", h_far)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMin", 0.5 * h_cut)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMax", dist_far)
        gmsh.model.mesh.field.setAsBackgroundMesh(f_thr)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        index = {int(t): i for i, t in enumerate(tags)}
        points = coords.reshape(-1, 3)
        tets = []
        for dim, tag in gmsh.model.getEntities(3):
            types, _, nodes = gmsh.model.mesh.getElements(dim, tag)
            for ty, nd in zip(types, nodes):
                assert ty == 4
                tets.append(np.array([index[int(n)] for n in nd]).reshape(-1, 4))
        tets = np.concatenate(tets)
        types, _, nodes = gmsh.model.mesh.getElements(2, cut_tags[0])
        tris = np.array([index[int(n)] for n in nodes[0]]).reshape(-1, 3)
    finally:
        gmsh.finalize()
    # drop unused nodes (geometry points), renumber
    used = np.unique(tets)
    new = -np.ones(len(points), int)
    new[used] = np.arange(len(used))
    points, tets, tris = points[used], new[tets], new[tris]
    assert (tris >= 0).all()
    # orient tets positively
    P = points[tets]
    vol = np.einsum("ij,ij->i", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0])
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    dermis = P.mean(axis=1)[:, 2] > Z_FAT
    return points, tets, dermis, tris


def open_cut(points, tets, tris, angle):
    """Duplicate the cut surface's nodes except the crack front (bottom edge z = 4, end edges).

    Returns new points, tets, the minus-side tet mask, the (plus, minus) node pairs, the open
    edges (pairs of front nodes whose edge lies inside the opened face) and the front node count."""
    d, n = cut_axes(angle)
    on = np.unique(tris)
    rel = points[on, :2] - CENTRE
    s = rel @ d
    front = (np.abs(points[on, 2] - Z_FAT) < EPS) | (np.abs(np.abs(s) - 0.5 * CUT_LENGTH) < EPS)
    assert np.all(np.abs(rel @ n) < 1e-6), "cut nodes off the cut plane"
    opened = on[~front]
    dist = (points[tets].mean(axis=1)[:, :2] - CENTRE) @ n
    touch = np.isin(tets, opened).any(axis=1)
    minus = touch & (dist < 0)
    copy = -np.ones(len(points), int)
    copy[opened] = len(points) + np.arange(len(opened))
    t2 = tets.copy()
    sub = t2[minus]
    sub = np.where(np.isin(sub, opened), copy[sub], sub)
    t2[minus] = sub
    new_points = np.vstack([points, points[opened]])
    pairs = np.stack([opened, copy[opened]], axis=1)
    # cut-face edges between two front nodes with their midpoint inside the opened face
    fset = set(on[front].tolist())
    edges = set()
    for tri in tris:
        for a, b in itertools.combinations(sorted(tri.tolist()), 2):
            if a in fset and b in fset:
                m = 0.5 * (points[a] + points[b])
                if m[2] > Z_FAT + EPS and abs((m[:2] - CENTRE) @ d) < 0.5 * CUT_LENGTH - EPS:
                    edges.add((a, b))
    return new_points, t2, minus, pairs, sorted(edges), int(front.sum())


def midside_pairs(prob, tets, minus, angle):
    """P2 midside dofs of the top edge: for each tet edge on the top edge of the cut (both ends on
    z = 6 on the cut line, within the cut), the dof at its midpoint in a plus tet and in a minus
    tet. Returns a list of (plus dof, minus dof)."""
    d, n = cut_axes(angle)
    edofs = prob.gdofs[:, ::3] // 3
    X = prob.doflocs
    found = {}
    for k in range(len(tets)):
        P = X[edofs[k, :4]]
        for i, j in itertools.combinations(range(4), 2):
            a, b = P[i], P[j]
            if abs(a[2] - Z_TOP) > EPS or abs(b[2] - Z_TOP) > EPS:
                continue
            if abs((a[:2] - CENTRE) @ n) > 1e-6 or abs((b[:2] - CENTRE) @ n) > 1e-6:
                continue
            m = 0.5 * (a + b)
            if abs((m[:2] - CENTRE) @ d) > 0.5 * CUT_LENGTH:
                continue
            dof = edofs[k, 4:][np.argmin(np.linalg.norm(X[edofs[k, 4:]] - m, axis=1))]
            assert np.linalg.norm(X[dof] - m) < 1e-9
            key = tuple(np.round(m, 7))
            found.setdefault(key, {}).setdefault(bool(minus[k]), dof)
    return [(v[False], v[True]) for v in found.values() if len(v) == 2]


def run(angle, h_cut, h_far=1.5, lams=(LINEAR,)):
    """Rows (one per lambda0 of ``lams``, solved in order by continuation from the previous one)
    of the max / mean surface width of the cut at ``angle`` [deg] on the mesh of ``h_cut``,
    ``h_far`` [mm]; widths per unit pre-strain (width / (lambda0 - 1)) and, at finite lambda0,
    also in mm (``max_width_mm``)."""
    t0 = time.process_time()
    points, tets, dermis, tris = conforming_mesh(angle, h_cut, h_far)
    t_mesh = time.process_time() - t0
    X, T, minus, pairs, edges, n_front = open_cut(points, tets, tris, angle)

    def fixed(Y):
        f = np.zeros(Y.shape, bool)
        side = (np.abs(Y[:, 0]) < EPS) | (np.abs(Y[:, 0] - SIDE) < EPS) | (np.abs(Y[:, 1]) < EPS) | (np.abs(Y[:, 1] - SIDE) < EPS)
        f[:, 0] |= side
        f[:, 1] |= side
        f[np.abs(Y[:, 2]) < EPS] = True
        return f

    prob = P2Problem(X, T, np.where(dermis, E_DERMIS * 1e-3, E_FAT * 1e-3), dermis, fixed, open_edges=edges, minus=minus)
    rows, u, prev = [], None, 1.0
    for lam in lams:
        t1 = time.process_time()
        u, its = prob.continuation(prev, lam, u)
        prev = lam
        t_solve = time.process_time() - t1
        rows.append(_widths(prob, X, T, minus, pairs, points, tets, tris, edges, n_front, angle, h_cut, h_far, lam, u, its, t_mesh, t_solve))
    return rows


def _widths(prob, X, T, minus, pairs, points, tets, tris, edges, n_front, angle, h_cut, h_far, lam, u, its, t_mesh, t_solve):
    """One row: the widths of the solved displacement ``u`` (see `run`)."""
    x = prob.doflocs + u
    strain = lam - 1.0
    d, _ = cut_axes(angle)
    top = pairs[np.abs(X[pairs[:, 0], 2] - Z_TOP) < EPS]
    w_v = np.linalg.norm(x[top[:, 0]] - x[top[:, 1]], axis=1) / strain
    s_v = (X[top[:, 0], :2] - CENTRE) @ d
    mids = midside_pairs(prob, T, minus, angle)
    mids = np.array(mids, int).reshape(-1, 2)
    w_m = np.linalg.norm(x[mids[:, 0]] - x[mids[:, 1]], axis=1) / strain
    s_m = (prob.doflocs[mids[:, 0], :2] - CENTRE) @ d
    s_all = np.concatenate([s_v, s_m])
    w_all = np.concatenate([w_v, w_m])
    o = np.argsort(s_all)
    ss = np.concatenate([[-0.5 * CUT_LENGTH], s_all[o], [0.5 * CUT_LENGTH]])
    ww = np.concatenate([[0.0], w_all[o], [0.0]])
    mean = float(np.sum(0.5 * (ww[1:] + ww[:-1]) * np.diff(ss)) / CUT_LENGTH)
    row = dict(angle=angle, h_cut_mm=h_cut, h_far_mm=h_far, pre_stretch=lam, nodes=int(len(points)), tets=int(len(tets)), dofs=3 * int(prob.n),
               cut_triangles=int(len(tris)), opened_nodes=int(len(pairs)), front_nodes=n_front, open_edges=len(edges),
               top_vertex_pairs=int(len(top)), top_midside_pairs=int(len(mids)),
               max_width_vertices=float(w_v.max()), max_width=float(w_all.max()), s_at_max_mm=float(s_all[np.argmax(w_all)]),
               mean_width_trapezoid=mean, newton=its, cpu_mesh_s=t_mesh, cpu_solve_s=t_solve, rss_mb=rss_mb())
    if lam != LINEAR:
        row["max_width_mm"] = float(w_all.max()) * strain
    return row


def merge(rows, name=OUT_NAME):
    old = (_load(name) or {"rows": []})["rows"]
    key = lambda r: (r["h_cut_mm"], r["h_far_mm"], r["angle"], round(r["pre_stretch"], 9))  # noqa: E731
    keys = {key(r) for r in rows}
    out = [r for r in old if key(r) not in keys] + rows
    out.sort(key=lambda r: (r["pre_stretch"], -r["h_cut_mm"], r["h_far_mm"], r["angle"]))
    _write(name, {"units": "widths per unit pre-strain [mm]", "rows": out})


def table(name=OUT_NAME):
    """Markdown table of the 0 / 25 deg max widths and their ratio per (h_far, h_cut) from the JSON;
    90 deg rows (the 0 deg cut turned by the square's symmetry: mesh noise only) alongside."""
    rows = (_load(name) or {"rows": []})["rows"]
    by = {}
    for r in rows:
        by.setdefault((r["pre_stretch"], r["h_far_mm"], r["h_cut_mm"]), {})[r["angle"]] = r
    lines = ["| lambda0 | h_far | h_cut | DOFs (0 deg) | 0 deg max | 25 deg max | 25/0 (max) | 25/0 (mean) | 90/0 (max) |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for (lam, far, h), v in sorted(by.items(), key=lambda kv: (kv[0][0], kv[0][1], -kv[0][2])):
        if 0.0 not in v:
            continue
        z = v[0.0]
        f = lambda a, q="max_width": f"{v[a][q] / z[q]:.4f}" if a in v else "-"  # noqa: E731
        t = f"{v[25.0]['max_width']:.4f}" if 25.0 in v else "-"
        lines.append(f"| {'linear limit' if lam == LINEAR else f'{lam:g}'} | {far:g} | {h:g} | {z['dofs']} | {z['max_width']:.4f} | {t} | {f(25.0)} | {f(25.0, 'mean_width_trapezoid')} | {f(90.0)} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--h", type=float, nargs="+", default=[], help="element size at the cut [mm]")
    ap.add_argument("--table", action="store_true", help="print the markdown table of the JSON's rows")
    ap.add_argument("--far", type=float, default=1.5, help="element size far from the cut [mm]")
    ap.add_argument("--angles", type=float, nargs="+", default=[0.0, 25.0])
    ap.add_argument("--lams", type=float, nargs="+", default=[LINEAR], help="pre-stretches lambda0, solved in this order by continuation")
    a = ap.parse_args(argv)
    for h in a.h:
        for angle in a.angles:
            rows = run(angle, h, a.far, tuple(a.lams))
            for row in rows:
                print(json.dumps(row), flush=True)
            merge(rows)
    if a.table:
        print(table())


if __name__ == "__main__":
    main()
