"""Cuts on curved surfaces (``ScalpelPath(surface="boundary")``): the flat block cut through the
boundary path equals the flat cut, a rotated block gives the upright incision (rotation
invariance), the geometry of a cut on a dome (nodes on the surface, depth along the normal, no
tet inverted or dropped), an incision on a dome converging to the flat one as R grows, the
refusals and the config. ~1.5 min CPU (10 small incision solves)."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from difftissue.boundary import BoundaryConditions
from difftissue.cutting import ScalpelPath, _prepare, cut_specimen, opening_width
from difftissue.errors import ConfigError, CutError
from difftissue.incision import Incision, IncisionOptions, plot_incision
from difftissue.materials import Material
from difftissue.mesh import Specimen, TetMesh, block, curved_top, signed_volumes

jax.config.update("jax_enable_x64", True)

MM = 1e-3
M = Material(2e5, 0.45)


def _bare(mesh):
    """The mesh without its lattice (as a mesh from file)."""
    return TetMesh(mesh.points, mesh.tets, mesh.region_ids, mesh.region_names)


# ------------------------------------------------------------------ flat equivalence
@pytest.mark.parametrize(
    "points, kw, method",
    [
        ([(2.1 * MM, 4.2 * MM), (5.9 * MM, 3.7 * MM)], dict(depth=1.2 * MM), "snap"),
        ([(1.3 * MM, 1.5 * MM), (4.0 * MM, 2.5 * MM), (6.5 * MM, 2.0 * MM)], dict(depth=1 * MM), "snap"),  # polyline
        ([(0.0, 2 * MM), (6 * MM, 2 * MM)], dict(depth=1 * MM), "snap"),  # open start on the side face
        ([(2 * MM, 2.5 * MM), (6 * MM, 2.5 * MM)], dict(depth=2 * MM, tilt=0.3), "snap"),
        ([(1 * MM, 2 * MM), (5 * MM, 2 * MM)], dict(through=True), "snap"),
        ([(2.1 * MM, 4.2 * MM), (5.9 * MM, 3.7 * MM)], dict(depth=1.2 * MM), "remove"),
        ([(2.1 * MM, 4.2 * MM), (5.9 * MM, 3.7 * MM)], dict(depth=1.2 * MM), "staircase"),
    ],
)
def test_flat_block_cut_through_the_boundary_equals_the_top_cut(points, kw, method):
    """On a flat top the surface normal is +z exactly, each straight segment has one frame and
    the blade is the flat one: the same duplicated nodes, sides and pairs, points and pair
    coordinates to 1e-12 of the size."""
    mesh = block((8 * MM, 6 * MM, 3 * MM), (8, 6, 3))
    flat = cut_specimen(mesh, ScalpelPath(points, **kw), method=method)
    curved = cut_specimen(mesh, ScalpelPath(points, surface="boundary", **kw), method=method)
    tol = 1e-12 * 8 * MM
    assert np.array_equal(flat.pairs, curved.pairs) and np.array_equal(flat.tet_side, curved.tet_side)
    assert np.array_equal(flat.surface_pairs, curved.surface_pairs) and np.array_equal(flat.mesh.tets, curved.mesh.tets)
    np.testing.assert_allclose(np.asarray(curved.mesh.points), np.asarray(flat.mesh.points), rtol=0, atol=tol)
    np.testing.assert_allclose(curved.pair_s, flat.pair_s, rtol=0, atol=tol)
    np.testing.assert_allclose(curved.pair_depth, flat.pair_depth, rtol=0, atol=tol)
    np.testing.assert_allclose(curved.pair_normal, flat.pair_normal, rtol=0, atol=1e-12)
    assert curved.length == pytest.approx(flat.length, rel=1e-12) and curved.depth == pytest.approx(flat.depth, rel=1e-12)


# ------------------------------------------------------------------ rotation invariance
@pytest.mark.parametrize("tilt", [0.0, 0.3])
def test_rotated_block_gives_the_upright_incision(tilt):
    """A block rotated by a rigid rotation (0.7 rad about a tilted axis) and shifted, cut on its
    rotated top with surface="boundary", against the upright block cut on its flat top: the
    same pairs, rotated points and normals to 1e-12; the incision (lateral faces stretched 5 %
    in the specimen's plane, base clamped, every component held so that the conditions rotate
    with the block; stable neo-Hookean) opens the same widths to 1e-8 relative."""
    mesh = _bare(block((8 * MM, 4 * MM, 2 * MM), (8, 4, 2)))
    axis = np.array([0.3, -0.8, 0.5])
    Q = Rotation.from_rotvec(0.7 * axis / np.linalg.norm(axis)).as_matrix()
    shift = np.array([1e-3, -2e-3, 3e-3])
    rot = TetMesh(np.asarray(mesh.points) @ Q.T + shift, mesh.tets, mesh.region_ids, mesh.region_names)
    pts = np.array([(2.3 * MM, 1.8 * MM, 2 * MM), (5.9 * MM, 2.3 * MM, 2 * MM)])
    c0 = cut_specimen(Specimen(mesh, (M,)), ScalpelPath(pts[:, :2], depth=1 * MM, tilt=tilt))
    c1 = cut_specimen(Specimen(rot, (M,)), ScalpelPath(pts @ Q.T + shift, depth=1 * MM, tilt=tilt, surface="boundary"))
    assert np.array_equal(c0.pairs, c1.pairs) and np.array_equal(c0.surface_pairs, c1.surface_pairs) and c0.n_pairs > 0
    np.testing.assert_allclose(np.asarray(c1.mesh.points), np.asarray(c0.mesh.points) @ Q.T + shift, rtol=0, atol=1e-12 * 8 * MM)
    np.testing.assert_allclose(c1.pair_normal, c0.pair_normal @ Q.T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(c1.pair_s, c0.pair_s, rtol=0, atol=1e-12 * 8 * MM)
    orig = np.asarray(mesh.points)[c0.node_origin]
    lateral = np.isclose(orig[:, 0], 0) | np.isclose(orig[:, 0], 8 * MM) | np.isclose(orig[:, 1], 0) | np.isclose(orig[:, 1], 4 * MM)
    base = np.isclose(orig[:, 2], 0)
    u = np.zeros_like(orig)
    u[:, :2] = 0.05 * (orig[:, :2] - np.array([4 * MM, 2 * MM]))
    u[base] = 0.0
    idx = np.flatnonzero(lateral | base)
    opt = IncisionOptions(scalpel_steps=1, rtol=1e-12, atol=0.0)
    w = []
    for cut, uu in ((c0, u[idx]), (c1, u[idx] @ Q.T)):
        bc = BoundaryConditions.free(cut.mesh).fix(cut.mesh, idx, "xyz", uu)
        w.append(np.asarray(Incision(cut, model="stable_neo_hookean", bc=bc, options=opt).solve(M).opening.width))
    assert w[0].max() > 0.01 * MM  # the cut opens (by ~0.17 mm)
    np.testing.assert_allclose(w[1], w[0], rtol=0, atol=1e-8 * w[0].max())


# ------------------------------------------------------------------ a dome
R_DOME, H_DOME, DEPTH = 10 * MM, 3 * MM, 1 * MM
DOME_PATH = [(-2.3 * MM, 0.7 * MM), (2.1 * MM, -0.4 * MM)]


@pytest.fixture(scope="module")
def dome():
    return curved_top(block((8 * MM, 8 * MM, H_DOME), (16, 16, 6), origin=(-4 * MM, -4 * MM, 0.0)), R_DOME)


def test_cut_on_a_dome_follows_the_surface(dome, tmp_path):
    """A straight path in plan on a dome (R = 10 mm, 0.5 mm cells): the cut follows the sphere
    (its length is the arc's, to the faceting's 1e-3), the surface pairs' nodes lie on the
    sphere within the faceting's chord error e^2 / 8R (e the longest boundary edge), every
    pair's depth is its depth along the sphere's normal (radial) within the same, the nodes
    snapped to the bottom lie at the cut depth along the normal, the blade contains the normal
    (blade normal . radial < 0.05), and no tet is inverted or dropped."""
    path = ScalpelPath(DOME_PATH, depth=DEPTH, surface="boundary")
    cut = cut_specimen(dome, path)
    X = np.asarray(cut.mesh.points)
    centre = np.array([0.0, 0.0, H_DOME - R_DOME])
    P = np.asarray(dome.points)
    bf = dome.boundary_faces
    e_max = max(np.linalg.norm(P[bf[:, i]] - P[bf[:, (i + 1) % 3]], axis=1).max() for i in range(3))
    chord = e_max**2 / (8 * R_DOME)
    assert cut.mesh.n_tets == dome.n_tets and np.all(signed_volumes(X, cut.mesh.tets) > 0)
    assert cut.quality.n_snapped > 0 and cut.quality.n_off_surface == 0 and cut.quality.n_bridging_tets == 0
    # the length: the arc of the sphere over the straight plan path
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    xy = np.asarray(DOME_PATH[0]) + t * (np.asarray(DOME_PATH[1]) - np.asarray(DOME_PATH[0]))
    arc = np.column_stack([xy, centre[2] + np.sqrt(R_DOME**2 - np.sum(xy**2, axis=1))])
    assert cut.length == pytest.approx(np.sum(np.linalg.norm(np.diff(arc, axis=0), axis=1)), rel=1e-3)
    assert cut.length > np.linalg.norm(arc[-1] - arc[0]) * (1 + 1e-4)  # longer than the chord
    # surface pairs on the sphere, pair depths along the radial normal
    surf = cut.pairs[cut.surface_pairs]
    assert len(surf) >= 5
    r = np.linalg.norm(X[surf.reshape(-1)] - centre, axis=1)
    assert np.max(np.abs(r - R_DOME)) <= chord
    ra = np.linalg.norm(X[cut.pairs[:, 0]] - centre, axis=1)
    np.testing.assert_allclose(R_DOME - ra, cut.pair_depth, rtol=0, atol=chord)
    assert np.max(cut.pair_depth) < DEPTH
    # nodes snapped onto the bottom: at the cut depth along the normal
    g = _prepare(dome, path).geom
    s, n, h = g.coords(X[: dome.n_nodes])
    bottom = np.flatnonzero((np.abs(n) <= 1e-9 * MM) & (np.abs(h - DEPTH) <= 1e-12) & (s > 0) & (s < cut.length))
    assert bottom.size >= 3
    np.testing.assert_allclose(R_DOME - np.linalg.norm(X[bottom] - centre, axis=1), DEPTH, rtol=0, atol=chord)
    radial = (X[surf[:, 0]] - centre) / r[::2, None]
    assert np.max(np.abs(np.sum(cut.pair_normal[cut.surface_pairs] * radial, axis=1))) < 0.05
    # the opening is measured across the blade
    op = opening_width(cut, X)
    assert float(op.max_width) == pytest.approx(0.0, abs=1e-15)
    # the picture shows the curved top
    assert plot_incision(cut, np.zeros_like(X), tmp_path / "dome.png").stat().st_size > 0
    # element removal works on the dome as well
    removed = cut_specimen(dome, path, method="remove")
    assert removed.quality.n_removed > 0 and removed.surface_pairs.size > 0


def test_dome_incision_converges_to_the_flat_one():
    """The same straight plan cut (4 mm long, 1 mm deep, block 10 x 6 x 2 mm, 1 x 1 x 0.5 mm
    cells, lambda0 = 1.05, fem_linear) on domes of growing radius against the flat block: the
    surface widths' difference falls like 1/R (R x relative difference -2.44 mm at R = 100 mm,
    -2.40 mm at 200 mm, -2.38 mm at 10 m: halving within 10 %) and is 2.4e-4 of the width at
    R = 10 m."""
    mat = M.replace(pre_stretch=1.05)
    flat = _bare(block((10 * MM, 6 * MM, 2 * MM), (10, 6, 4), origin=(-5 * MM, -3 * MM, 0.0)))
    path = [(-2 * MM, 0.0), (2 * MM, 0.0)]
    opt = IncisionOptions(scalpel_steps=1, rtol=1e-10)

    def widths(mesh, surface):
        cut = cut_specimen(Specimen(mesh, (mat,)), ScalpelPath(path, depth=1 * MM, surface=surface))
        return np.asarray(Incision(cut, model="fem_linear", options=opt).solve(mat).opening.surface_width)

    w0 = widths(flat, "top")
    rel = {}
    for R in (100 * MM, 200 * MM, 10.0):
        w = widths(curved_top(flat, R), "boundary")
        assert w.shape == w0.shape
        rel[R] = np.max(np.abs(w - w0)) / np.max(w0)
    assert rel[100 * MM] / rel[200 * MM] == pytest.approx(2.0, rel=0.1)
    assert rel[10.0] < 5e-4


# ------------------------------------------------------------------ refusals and the config
def test_bad_paths_on_a_surface_are_refused(dome):
    with pytest.raises(CutError, match="surface must be 'top' or 'boundary'"):
        ScalpelPath(DOME_PATH, depth=DEPTH, surface="dome")
    above = [(-1 * MM, 0.0, H_DOME + 0.5 * MM), (1 * MM, 0.0, H_DOME + 0.5 * MM)]
    with pytest.raises(CutError, match="off the specimen's boundary surface"):
        cut_specimen(dome, ScalpelPath(above, depth=DEPTH, surface="boundary"))
    with pytest.raises(CutError, match="leaves the specimen's boundary surface"):
        cut_specimen(dome, ScalpelPath([(1 * MM, 0.0), (5 * MM, 0.0)], depth=DEPTH, surface="boundary"))
    with pytest.raises(CutError, match="tilted blade on surface='boundary'"):
        cut_specimen(dome, ScalpelPath(DOME_PATH, depth=DEPTH, tilt=0.2, surface="boundary"))
    with pytest.raises(CutError, match="reaches or exceeds the specimen thickness"):
        cut_specimen(dome, ScalpelPath(DOME_PATH, depth=2.9 * MM, surface="boundary"))
    cube = block((4 * MM, 4 * MM, 4 * MM), (4, 4, 4))
    over_the_edge = [(2 * MM, 2 * MM, 4 * MM), (4 * MM, 2 * MM, 4 * MM), (4 * MM, 2 * MM, 2 * MM)]
    with pytest.raises(CutError, match="crosses an edge of the specimen's surface"):
        cut_specimen(cube, ScalpelPath(over_the_edge, depth=1 * MM, surface="boundary"))


def test_config_cuts_a_curved_mesh_file(tmp_path):
    from difftissue.config import parse_config
    from difftissue.mesh import write_mesh

    write_mesh(tmp_path / "dome.vtu", curved_top(block((8 * MM, 6 * MM, 2 * MM), (8, 6, 4), origin=(-4 * MM, -3 * MM, 0.0)), 50 * MM))
    exp = {"name": "wound", "scenario": "incision", "length_unit": "mm", "model": "fem_linear",
           "data": {"quantity": "max_width", "value": 0.1},
           "specimen": {"mesh": "dome.vtu"},
           "cut": {"path": [[-2, 0], [2, 0]], "depth": 1, "surface": "boundary"}}
    cfg = {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": 1.05}, "fit": {"parameters": ["pre_stretch"]}, "experiment": [exp]}
    sc = parse_config(cfg, base_dir=tmp_path).experiments[0].scenario
    assert isinstance(sc, Incision) and sc.cut.length > 4 * MM and sc.cut.surface_pairs.size > 0
    with pytest.raises(CutError, match="no flat top surface"):
        parse_config({**cfg, "experiment": [{**exp, "cut": {"path": [[-2, 0], [2, 0]], "depth": 1}}]}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"cut\.surface"):
        parse_config({**cfg, "experiment": [{**exp, "cut": {**exp["cut"], "surface": "dome"}}]}, base_dir=tmp_path)
