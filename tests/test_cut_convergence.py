"""The P2 reference of experiments/cut_convergence.py: the pre-stretch convention against the
exact neo-Hookean plane-stress layer, and the quarter model (two mirror planes, the cut a
traction-free part of one) against the mirrored whole."""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("skfem")
pytest.importorskip("cholespy")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import cut_convergence as cc  # noqa: E402


def test_p2_prestretched_layer_is_the_exact_plane_stress_state():
    """Uncut, laterals held, base clamped: the pre-stretched dermis thins homogeneously to the
    neo-Hookean plane-stress stretch (mu (lz^2 - 1) + lam ln(l0^2 lz) = 0), the fat stays put."""
    from scipy.optimize import brentq

    p, t = cc.quarter_mesh(1)
    derm = p[t].mean(axis=1)[:, 2] > 4.0

    def fixed(X):
        f = np.zeros(X.shape, bool)
        side = (X[:, 0] < 1e-9) | (X[:, 1] < 1e-9) | (X[:, 0] > 6 - 1e-9) | (X[:, 1] > 6 - 1e-9)
        f[:, 0] |= side
        f[:, 1] |= side
        f[X[:, 2] < 1e-9] = True
        return f

    prob = cc.P2Problem(p, t, np.where(derm, 200.0, 5.0), derm, fixed)
    l0 = 1.1
    u, _ = prob.continuation(1.0, l0)
    nu = cc.NU
    lam, mu = nu / ((1 + nu) * (1 - 2 * nu)), 1 / (2 * (1 + nu))
    lz = brentq(lambda z: mu * (z * z - 1) + lam * np.log(l0 * l0 * z), 0.5, 1.0)
    X = prob.doflocs
    expected = np.where(X[:, 2] > 4.0, (lz - 1.0) * (X[:, 2] - 4.0), 0.0)
    assert lz < 0.95  # a real thinning, not the unloaded state
    np.testing.assert_allclose(u[:, 2], expected, rtol=0, atol=1e-9 * abs(lz - 1.0) * 2.0)
    np.testing.assert_allclose(u[:, :2], 0.0, atol=1e-12)


def _mirrored_whole(n):
    """The quarter mesh mirrored about x = 0 and y = 0; nodes on the open cut face (y = 0,
    |x| < 3, z > 4) kept apart per side, every other coincident node merged. The hexes are split
    with ``flip_x`` so that no tet edge joins two crack-front nodes across the open face (its P2
    midside node would glue the two sides there)."""
    p, t = cc.quarter_mesh(n, flip_x=True)
    pts, tets, keys = [], [], {}
    for sx in (1, -1):
        for sy in (1, -1):
            q = p * np.array([sx, sy, 1.0])
            ids = np.empty(len(q), int)
            for i, x in enumerate(q):
                open_face = abs(x[1]) < 1e-9 and abs(x[0]) < 3 - 1e-9 and x[2] > 4 + 1e-9
                key = (round(x[0], 9) + 0.0, round(x[1], 9) + 0.0, round(x[2], 9) + 0.0, sy if open_face else 0)
                if key not in keys:
                    keys[key] = len(pts)
                    pts.append(x)
                ids[i] = keys[key]
            tets.append(ids[t])
    return np.array(pts), np.concatenate(tets), keys


def test_quarter_model_equals_the_mirrored_whole():
    n, l0 = 2, 1.05
    quarter = cc.quarter_problem(n, flip_x=True)
    uq, _ = quarter.continuation(1.0, l0)
    wq, _ = cc.quarter_widths(quarter, uq)

    p, t, keys = _mirrored_whole(n)
    derm = p[t].mean(axis=1)[:, 2] > 4.0

    def fixed(X):
        f = np.zeros(X.shape, bool)
        side = (np.abs(X[:, 0]) > 6 - 1e-9) | (np.abs(X[:, 1]) > 6 - 1e-9)
        f[:, 0] |= side
        f[:, 1] |= side
        f[X[:, 2] < 1e-9] = True
        return f

    whole = cc.P2Problem(p, t, np.where(derm, cc.E_DERMIS * 1e-3, cc.E_FAT * 1e-3), derm, fixed)
    uw, _ = whole.continuation(1.0, l0)
    a, b = keys[(0.0, 0.0, 6.0, 1)], keys[(0.0, 0.0, 6.0, -1)]
    ww = np.linalg.norm(p[a] + uw[a] - p[b] - uw[b])
    assert wq > 0.5  # mm: the cut opens (about 0.7 mm at this pre-stretch)
    assert abs(ww / wq - 1.0) < 1e-7


def test_no_order_reason_agrees_with_the_observed_order():
    """The table's label for a level triple without an observed order (the P2 levels 2, 3, 4 of
    lambda0 = 1.15 and 1.10) matches what `order3` finds; a triple with an order is refused."""
    h = [1 / 2, 1 / 3, 1 / 4]
    slow = [1.69241, 1.71190, 1.72598]  # increments 0.0195, 0.0141: ratio 1.38 < ln(3/2)/ln(4/3)
    grow = [1.26869, 1.27133, 1.27639]
    ordered = [0.73272, 0.72797, 0.72666]
    assert np.isnan(cc.order3(slow, h)[0]) and np.isnan(cc.order3(grow, h)[0])
    assert cc.no_order_reason(slow, h) == "increments shrink slower than any power of h"
    assert cc.no_order_reason(grow, h) == "increments grow"
    assert cc.no_order_reason([1.0, 1.1, 1.05], h) == "increments change sign"
    assert np.isfinite(cc.order3(ordered, h)[0])
    with pytest.raises(ValueError, match="give an observed order"):
        cc.no_order_reason(ordered, h)


def test_frozen_tangent_newton_reaches_the_full_newton_answer():
    """The frozen-tangent Newton (the default) converges to full Newton's solution, to the
    1e-9 step tolerance, with fewer tangent factorisations; full Newton factorises at every
    iteration."""
    rows = {}
    for frozen in (False, True):
        prob = cc.quarter_problem(2)
        prob.frozen_tangent = frozen
        u, widths, its = None, [], 0
        for start, stop in ((1.0, cc.LINEAR), (cc.LINEAR, 1.05)):
            u, k = prob.continuation(start, stop, u)
            its += k
            widths.append(cc.quarter_widths(prob, u))
        rows[frozen] = (np.array(widths), its, prob.factorisations)
    (w_full, its_full, fac_full), (w_frozen, _, fac_frozen) = rows[False], rows[True]
    assert w_full[1, 0] > 0.5  # mm: the cut opens at 1.05
    np.testing.assert_allclose(w_frozen, w_full, rtol=1e-8, atol=0)
    assert fac_full == its_full
    assert fac_frozen < 0.7 * fac_full


def test_corner_grading_refines_the_max_width_corner_with_the_same_nodes():
    """The "front+corner" grading keeps the node count and the grid of the segments away from
    the corner (x in [3, 6], y, z in [0, 4]); on x in [0, 3] and z in [4, 6] its cells at the
    corner end are as fine as at the front end, and less than half the front grading's there."""
    n = 4
    front, _ = cc.quarter_mesh(n)
    corner, _ = cc.quarter_mesh(n, grading="front+corner")
    assert front.shape == corner.shape
    xf, xc = np.unique(front[:, 0]), np.unique(corner[:, 0])
    zf, zc = np.unique(front[:, 2]), np.unique(corner[:, 2])
    np.testing.assert_allclose(xc[xc >= 3.0], xf[xf >= 3.0], atol=1e-12)
    np.testing.assert_allclose(np.unique(corner[:, 1]), np.unique(front[:, 1]), atol=1e-12)
    np.testing.assert_allclose(zc[zc <= 4.0], zf[zf <= 4.0], atol=1e-12)
    np.testing.assert_allclose(xc[1] - xc[0], xc[n] - xc[n - 1], rtol=1e-12)  # x = 0 and x = 3 ends
    np.testing.assert_allclose(zc[-1] - zc[-2], zc[n + 1] - zc[n], rtol=1e-12)  # z = 6 and z = 4 ends
    assert xc[1] - xc[0] < 0.5 * (xf[1] - xf[0])
    assert zc[-1] - zc[-2] < 0.5 * (zf[-1] - zf[-2])
    with pytest.raises(ValueError, match="grading"):
        cc.quarter_mesh(n, grading="corner")


def test_p2_files_keep_the_reference_apart_from_other_gradings():
    assert cc.p2_file() == "cut_convergence_p2.json"
    assert cc.p2_file("front+corner") == "cut_convergence_p2_corner.json"
    assert cc.p2_file("front", 2.5) == "cut_convergence_p2_q2.5.json"


def test_rotation_factor_takes_the_finest_ratio_unless_a_cell_is_named(monkeypatch):
    ratios = {(cc.LINEAR, "max_width_mm"): [(1e-3, 0.98), (5e-4, 0.99)]}
    monkeypatch.setattr(cc, "rotation_ratio", lambda: ratios)
    monkeypatch.setattr(cc, "ROTATION_SOURCE", "snapped")
    monkeypatch.setattr(cc, "ROTATION_CELL", None)
    assert cc.rotation_factor() == (5e-4, 0.99)
    monkeypatch.setattr(cc, "ROTATION_CELL", 1e-3)
    assert cc.rotation_factor() == (1e-3, 0.98)


def test_the_25_degree_reference_takes_the_conforming_ratio_of_the_finest_mesh(monkeypatch):
    """The default source of the 25/0 ratio is the conforming whole-square P2: its finest h_cut
    with the 1.5 mm far field, linear limit, both angles present; other far fields, lambda0 and
    a mesh with one angle only are not taken."""
    def row(h, far, angle, width, lam=cc.LINEAR):
        return {"h_cut_mm": h, "h_far_mm": far, "angle": angle, "pre_stretch": lam, "max_width": width, "mean_width_trapezoid": width / 2}

    rows = [row(0.4, 1.5, 0.0, 10.0), row(0.4, 1.5, 25.0, 10.1), row(0.2, 1.5, 0.0, 10.0), row(0.2, 1.5, 25.0, 10.02),
            row(0.1, 1.5, 0.0, 10.0), row(0.1, 0.75, 0.0, 10.0), row(0.1, 0.75, 25.0, 9.0), row(0.2, 1.5, 25.0, 12.0, lam=1.05),
            row(0.2, 1.5, 0.0, 10.0, lam=1.05)]
    monkeypatch.setattr(cc, "_load", lambda name: {"rows": rows} if name == "cut_conforming_p2.json" else None)
    monkeypatch.setattr(cc, "ROTATION_SOURCE", "conforming")
    monkeypatch.setattr(cc, "CONFORMING_H", None)
    h, x = cc.rotation_factor()
    assert h == pytest.approx(2e-4) and x == pytest.approx(1.002)
    assert cc.rotation_factor("mean_width_mm")[1] == pytest.approx(1.002)
    monkeypatch.setattr(cc, "CONFORMING_H", 4e-4)
    assert cc.rotation_factor()[1] == pytest.approx(1.01)
    assert cc.conforming_ratio()[(round(1.05, 9), "max_width_mm")] == [(pytest.approx(2e-4), pytest.approx(1.2))]


def test_supernodal_and_cholespy_factorisations_give_the_same_widths(monkeypatch):
    """`P2Problem._factorise` through scikit-sparse's supernodal CHOLMOD and through cholespy:
    the same linear-limit and lambda0 = 1.05 widths to the Newton tolerance."""
    pytest.importorskip("sksparse")
    widths = []
    for backend in ("sksparse", "cholespy"):
        if backend == "cholespy":
            monkeypatch.setattr(cc, "_suitesparse_cholmod", lambda: None)
        prob = cc.quarter_problem(2)
        u, w = None, []
        for start, stop in ((1.0, cc.LINEAR), (cc.LINEAR, 1.05)):
            u, _ = prob.continuation(start, stop, u)
            w.append(cc.quarter_widths(prob, u))
        widths.append(np.array(w))
    assert widths[0][1, 0] > 0.5  # mm
    np.testing.assert_allclose(widths[0], widths[1], rtol=1e-8, atol=0)


def test_conforming_cut_mesh_opens_the_face_and_keeps_the_front():
    """experiments/cut_conforming.py at 25 deg: every cut triangle lies between one plus and one
    minus tet; the opened nodes are the cut's nodes off the front (bottom edge z = 4, end edges),
    top edge included; after opening no cut triangle is shared by two tets, the front nodes are."""
    pytest.importorskip("gmsh")
    import cut_conforming as cf

    angle = 25.0
    p, t, derm, tris = cf.conforming_mesh(angle, 0.6, 1.5)
    X, t2, minus, pairs, edges, n_front = cf.open_cut(p, t, tris, angle)
    d, n = cf.cut_axes(angle)
    on = np.unique(tris)
    s = (p[on, :2] - cf.CENTRE) @ d
    assert np.allclose((p[on, :2] - cf.CENTRE) @ n, 0.0, atol=1e-9)
    assert np.isclose(s.min(), -3.0) and np.isclose(s.max(), 3.0)
    front = (np.abs(p[on, 2] - 4.0) < 1e-7) | (np.abs(np.abs(s) - 3.0) < 1e-7)
    assert n_front == front.sum() and len(pairs) == len(on) - front.sum()
    assert np.array_equal(np.sort(pairs[:, 0]), np.sort(on[~front]))
    assert np.allclose(X[pairs[:, 0]], X[pairs[:, 1]])
    top = np.abs(p[pairs[:, 0], 2] - 6.0) < 1e-7
    assert top.sum() >= 5  # the top edge is opened
    faces = {}
    for k, tet in enumerate(t):
        for f in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
            faces.setdefault(tuple(sorted(tet[list(f)])), []).append(k)
    for tri in tris:
        ks = faces[tuple(sorted(tri))]
        assert len(ks) == 2 and minus[ks].sum() == 1
    faces2 = {}
    for tet in t2:
        for f in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
            key = tuple(sorted(tet[list(f)]))
            faces2[key] = faces2.get(key, 0) + 1
    copy = dict(map(tuple, pairs))
    for tri in tris:
        assert faces2.get(tuple(sorted(tri)), 0) == 1
        assert faces2.get(tuple(sorted(copy.get(v, v) for v in tri)), 0) == 1
    # minus tets use only copies of opened nodes, plus tets only originals
    assert not np.isin(t2[minus], pairs[:, 0]).any() and not np.isin(t2[~minus], pairs[:, 1]).any()
