"""The P2 reference builder of experiments/exp1_converged.py against analytic solutions."""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("skfem")
pytest.importorskip("pyamg")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import exp1_converged as X  # noqa: E402

E, NU, EPS = 12.0e3, 0.42, 0.01  # Pa, -, compressive strain
L, H = 4e-3, 3e-3  # m


def _uniaxial(points, component):
    """Free-slip (roller) base and sides x = 0, y = 0; the top pressed down by EPS * H."""
    tol = 1e-12
    X_, Y_, Z_ = points.T
    top = np.isclose(Z_, H, atol=tol) & (component == 2)
    fixed = (np.isclose(Z_, 0.0, atol=tol) & (component == 2)) | top
    fixed |= np.isclose(X_, 0.0, atol=tol) & (component == 0)
    fixed |= np.isclose(Y_, 0.0, atol=tol) & (component == 1)
    return fixed, np.where(top, -EPS * H, 0.0)


@pytest.fixture(scope="module", params=["direct", "pyamg"])
def graded_block(request):
    # graded axes (as the punch reference uses), so the grading cannot hide an error; both
    # solver paths (PyAMG forced on this small problem by direct_limit=0)
    axes = (X.graded_axis(L, L / 2, 2), X.graded_axis(L, None, 3), X.graded_axis(H, H, 3))
    sol = X.p2_solve(*axes, E, NU, _uniaxial, direct_limit=10**9 if request.param == "direct" else 0)
    assert sol["solver"] == ("direct" if request.param == "direct" else "pyamg-sa+cg")
    return sol


def test_uniaxial_force_is_E_A_eps(graded_block):
    sol = graded_block
    zc = sol["basis"].doflocs[2]
    top = sol["fixed"] & (sol["component"] == 2) & np.isclose(zc, H)
    force = -sol["reaction"][top].sum()
    assert force == pytest.approx(E * L * L * EPS, rel=1e-8)


def test_uniaxial_field_and_sampling(graded_block):
    """u = (nu eps x, nu eps y, -eps z) at every DOF and, through sample_field, at any point."""
    sol = graded_block
    pts = sol["basis"].doflocs.T
    exact = np.stack([NU * EPS * pts[:, 0], NU * EPS * pts[:, 1], -EPS * pts[:, 2]], 1)
    u = sol["u"]
    assert np.abs(u - exact[np.arange(len(pts)), sol["component"]]).max() < 1e-8 * EPS * H
    q = np.random.default_rng(3).uniform([0, 0, 0], [L, L, H], (50, 3))
    u_q = X.sample_field(sol, q)
    exact_q = np.stack([NU * EPS * q[:, 0], NU * EPS * q[:, 1], -EPS * q[:, 2]], 1)
    assert np.abs(u_q - exact_q).max() < 1e-8 * EPS * H


def test_tetra10_mesh_is_vtk_ordered():
    pts, cells = X.tetra10_mesh(1e-3, size=(2e-3, 1e-3, 1e-3))
    pairs = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
    for j, (a, b) in enumerate(pairs):
        np.testing.assert_allclose(pts[cells[:, 4 + j]], 0.5 * (pts[cells[:, a]] + pts[cells[:, b]]), atol=1e-15)


def test_richardson_recovers_a_known_limit():
    h = np.array([1.0, 0.5, 0.3])
    p, f0, err = X.richardson(h, 2.0 + 0.7 * h**1.3)
    assert p == pytest.approx(1.3, rel=1e-9) and f0 == pytest.approx(2.0, rel=1e-12)
    assert err == pytest.approx(0.35 * 0.3**1.3, rel=1e-9)
    assert X.richardson(h, [1.0, 2.0, 1.5]) == (None, None, None)  # not monotone: no order


@pytest.mark.parametrize("n", [2, 3, 5])
def test_graded_model_mesh(n):
    """The graded model mesh of the FEM fits: a node plane at the punch edge x = y = 3 mm, cells
    shrinking monotonically towards it (and towards the top), n intervals per side, 6 tets per box."""
    m = X.graded_specimen(n)
    xs, ys, zs = (np.unique(np.round(m.points[:, a], 12)) for a in range(3))
    assert len(xs) == len(ys) == 2 * n + 1 and len(zs) == n + 1
    assert m.points.shape[0] == (2 * n + 1) ** 2 * (n + 1) and m.tets.shape[0] == 6 * (2 * n) ** 2 * n
    for ax, full in ((xs, X.QUARTER[0]), (ys, X.QUARTER[1])):
        assert ax[0] == 0.0 and ax[-1] == pytest.approx(full, abs=1e-15)
        assert ax[n] == pytest.approx(X.HALF_WIDTH, abs=1e-15)  # the punch edge is a node
        d = np.diff(ax)
        assert np.all(np.diff(d[:n]) < 0) and np.all(np.diff(d[n:]) > 0)  # graded towards the edge from both sides
        assert d[n - 1] == pytest.approx(X.HALF_WIDTH / n**X.GRADING) and d[n] == pytest.approx((full - X.HALF_WIDTH) / n**X.GRADING)
    dz = np.diff(zs)
    assert zs[0] == 0.0 and zs[-1] == pytest.approx(X.QUARTER[2]) and np.all(np.diff(dz) < 0)  # graded towards the top
    # the square punch node set of make_scenario: (n + 1)^2 top nodes with x, y <= 3 mm
    top = np.isclose(m.points[:, 2], X.QUARTER[2]) & (m.points[:, 0] <= X.HALF_WIDTH + 1e-9) & (m.points[:, 1] <= X.HALF_WIDTH + 1e-9)
    assert top.sum() == (n + 1) ** 2
    assert np.isclose(m.points[top, 0].max(), X.HALF_WIDTH) and np.isclose(m.points[top, 1].max(), X.HALF_WIDTH)


def test_uniform_at_nodes_interpolates_log_log():
    rows = [{"nodes": 100, "E_error": -0.1}, {"nodes": 800, "E_error": -0.025}]
    assert X.uniform_at_nodes(rows, 100) == pytest.approx(-0.1)
    assert X.uniform_at_nodes(rows, 400) == pytest.approx(-0.1 * (400 / 100) ** (np.log(0.25) / np.log(8)))
    assert X.uniform_at_nodes(rows, 900) is None
    assert X.uniform_equivalent_h(7**3) == pytest.approx(1e-3)  # 6 mm / 1 mm cubes: 7 nodes per axis
