"""Mesh generators, lattice topology, validation and surface extraction."""

import itertools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import errors
from difftissue.materials import Material
from difftissue.mesh import (
    TetMesh,
    block,
    boundary_faces,
    default_skin_layers,
    layered_skin,
    mean_ratio_quality,
    signed_volumes,
    structured_grid,
    validate_arrays,
)


@pytest.mark.parametrize(
    "size,res,origin",
    [((1.0, 1.0, 1.0), (1, 1, 1), (0, 0, 0)), ((0.02, 0.01, 0.005), (4, 3, 2), (0.1, -0.2, 0.3)), ((3.0, 2.0, 1.0), (5, 4, 3), (0, 0, 0))],
)
def test_block_volumes_sum_to_box_and_are_positive(size, res, origin):
    m = block(size, res, origin=origin)
    v = m.volumes()
    assert m.n_tets == 6 * np.prod(res)
    assert m.n_nodes == np.prod(np.asarray(res) + 1)
    assert np.all(v > 0)
    np.testing.assert_allclose(v.sum(), np.prod(size), rtol=1e-12)
    # The six tets of one cube have equal volume h^3/6.
    np.testing.assert_allclose(v, np.prod(np.asarray(size) / np.asarray(res)) / 6, rtol=1e-10)
    lo, hi = m.bounds()
    np.testing.assert_allclose(lo, origin, atol=1e-15)
    np.testing.assert_allclose(hi, np.asarray(origin) + np.asarray(size), rtol=1e-12)


def test_six_tet_split_is_conforming():
    m = block((1.0, 2.0, 3.0), (3, 4, 2))
    faces = np.sort(m.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(np.unique(counts)) == {1, 2}
    # Faces seen once are exactly the boundary: two triangles per boundary square.
    nx, ny, nz = 3, 4, 2
    assert np.sum(counts == 1) == 2 * 2 * (nx * ny + ny * nz + nx * nz) == len(m.boundary_faces)
    # Every interior face is shared by exactly two tets; none by more.
    n_faces_total = 4 * m.n_tets
    assert np.sum(counts == 2) * 2 + np.sum(counts == 1) == n_faces_total


def test_boundary_faces_lie_on_box_and_point_outwards():
    m = block((1.0, 1.0, 1.0), (2, 3, 2))
    p = m.points
    centroid_tet = p[m.tets[m.boundary_face_tets]].mean(axis=1)
    f = p[m.boundary_faces]
    normal = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, f.mean(axis=1) - centroid_tet) > 0)
    on_face = np.any(np.all(np.isclose(f, 0.0), axis=1) | np.all(np.isclose(f, 1.0), axis=1), axis=1)
    assert np.all(on_face)
    # Total boundary area = box surface area.
    area = 0.5 * np.linalg.norm(normal, axis=1).sum()
    np.testing.assert_allclose(area, 6.0, rtol=1e-12)


def test_surface_is_closed_two_manifold():
    m = block((1.0, 1.0, 1.0), (3, 2, 2))
    nodes, tris = m.surface()
    edges = np.sort(tris[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)
    euler = len(nodes) - len(uniq) + len(tris)
    assert euler == 2
    assert len(m.edges) == len(np.unique(np.sort(m.tets[:, list(itertools.combinations(range(4), 2))].reshape(-1, 2), axis=1), axis=0))


def _expected_multiplicity(p0, p1, grid_lo, grid_hi):
    """Cubes sharing a spring, from geometry alone: for each axis the spring does not span,
    2 cubes if the spring lies strictly inside the grid along that axis, else 1."""
    m = 1
    spans = ~np.isclose(p0, p1)
    for a in range(3):
        if spans[a]:
            continue
        inside = grid_lo[a] + 1e-12 < p0[a] < grid_hi[a] - 1e-12
        m *= 2 if inside else 1
    return m


def test_lattice_multiplicities_match_design():
    m = block((3.0, 3.0, 3.0), (3, 3, 3))
    lat = m.lattice
    assert lat.n_cubes == 27
    assert lat.cube_springs.shape == (27, 24)
    p = m.points
    lo, hi = m.bounds()
    for s, (i, j) in enumerate(lat.springs):
        n_span = int(np.sum(~np.isclose(p[i], p[j])))
        assert n_span == (1 if lat.spring_kind[s] == 0 else 2)
        assert lat.multiplicity[s] == _expected_multiplicity(p[i], p[j], lo, hi)
    edge = lat.spring_kind == 0
    # DESIGN §3.1: an interior edge is shared by 4 cubes, a face diagonal by 2.
    assert lat.multiplicity[edge].max() == 4 and lat.multiplicity[~edge].max() == 2
    # Each cube holds 12 edges and 12 diagonals: multiplicities sum to 12 C each.
    assert lat.multiplicity[edge].sum() == 12 * 27
    assert lat.multiplicity[~edge].sum() == 12 * 27
    # Unique counts: edges 3 n (n+1)^2, face diagonals 2 * 3 n^2 (n+1) for an n^3 block.
    n = 3
    assert edge.sum() == 3 * n * (n + 1) ** 2
    assert (~edge).sum() == 2 * 3 * n * n * (n + 1)
    # Within a cube: springs 0..11 are the edges, 12..23 the diagonals, all distinct.
    for c in range(lat.n_cubes):
        assert len(set(lat.cube_springs[c])) == 24
        assert np.all(lat.spring_kind[lat.cube_springs[c, :12]] == 0)
        assert np.all(lat.spring_kind[lat.cube_springs[c, 12:]] == 1)


def test_lattice_spring_lengths_and_cell_size():
    m = block((0.3, 0.2, 0.1), (3, 2, 4))
    lat = m.lattice
    h = np.array([0.1, 0.1, 0.025])
    np.testing.assert_allclose(lat.cell_size, np.broadcast_to(h, (lat.n_cubes, 3)), rtol=1e-12)
    d = np.abs(m.points[lat.springs[:, 1]] - m.points[lat.springs[:, 0]])
    length = np.linalg.norm(d, axis=1)
    allowed = {0: set(np.round(h, 12)), 1: set(np.round([np.hypot(h[0], h[1]), np.hypot(h[0], h[2]), np.hypot(h[1], h[2])], 12))}
    for kind in (0, 1):
        assert set(np.round(length[lat.spring_kind == kind], 12)) <= allowed[kind]


def test_layered_skin_regions_volumes_and_surface():
    layers = [("epidermis", 1e-4, Material(1e6, 0.48)), ("dermis", 1.5e-3, Material(2e5, 0.48), 3), ("hypodermis", 4e-3, Material(5e3, 0.49))]
    sp = layered_skin(layers, size=(0.01, 0.008), resolution=(5, 4))
    m = sp.mesh
    assert m.region_names == ("epidermis", "dermis", "hypodermis")
    area = 0.01 * 0.008
    vols = m.region_volumes()
    for name, t, *_ in layers:
        np.testing.assert_allclose(vols[name], t * area, rtol=1e-12)
    lo, hi = m.bounds()
    np.testing.assert_allclose(hi[2], 1e-4 + 1.5e-3 + 4e-3, rtol=1e-12)
    np.testing.assert_allclose(lo[2], 0.0, atol=0)
    # Epidermis is the top: its tets lie above the dermis.
    zc = m.points[m.tets].mean(axis=1)[:, 2]
    assert zc[m.region_ids == 0].min() > zc[m.region_ids == 1].max() > zc[m.region_ids == 2].max() - 1e-12
    # Cell counts: 1 (0.1 mm / 2 mm cells rounds to 0 -> at least 1), 3 (given), 2 (4 mm / 2 mm).
    n_cubes = np.bincount(m.lattice.cube_region_ids)
    np.testing.assert_array_equal(n_cubes, np.array([1, 3, 2]) * 20)
    f = sp.cell_fields()
    np.testing.assert_array_equal(f["youngs_modulus"][m.region_ids == 1], 2e5)
    np.testing.assert_array_equal(f["poisson_ratio"][m.region_ids == 2], 0.49)
    assert sp.material("dermis").youngs_modulus == 2e5
    with pytest.raises(errors.MaterialError, match="no region"):
        sp.material("muscle")


def test_default_skin_layers_validate():
    sp = layered_skin(size=(0.004, 0.004), resolution=(4, 4))
    assert [n for n, *_ in default_skin_layers()] == list(sp.mesh.region_names)
    assert not [f for f in sp.mesh.validate() if f.severity != "note"]


def test_generator_input_errors():
    with pytest.raises(errors.MeshError, match="size"):
        block((1.0, -1.0, 1.0), 2)
    with pytest.raises(errors.MeshError, match="resolution"):
        block(1.0, (2, 0, 2))
    with pytest.raises(errors.MeshError, match="resolution"):
        block(1.0, 2.5)
    with pytest.raises(errors.MeshError, match="thickness"):
        layered_skin([("a", 0.0, Material(1e3, 0.4))])
    with pytest.raises(errors.MaterialError, match="material"):
        layered_skin([("a", 1e-3, "soft")])
    with pytest.raises(errors.MaterialError, match="poisson_ratio"):
        layered_skin([("a", 1e-3, {"youngs_modulus": 1e3, "poisson_ratio": 0.5})])
    with pytest.raises(errors.MeshError, match="increasing"):
        structured_grid([0, 1], [0, 1], [0, 0.5, 0.4])


# ------------------------------------------------------------------------ validation
def _unit_tet():
    return np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 1, 2, 3]])


def _two_tets():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    t = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    if signed_volumes(p, t[1:])[0] < 0:
        t[1] = t[1][[0, 1, 3, 2]]
    return p, t


def test_valid_tet_has_no_findings():
    p, t = _two_tets()
    assert validate_arrays(p, t) == []
    TetMesh(p, t)


@pytest.mark.parametrize(
    "mutate,error,cited",
    [
        (lambda p, t: (np.where(np.arange(5)[:, None] == 4, np.nan, p), t), errors.NonFiniteCoordinatesError, 4),
        (lambda p, t: (p, np.array([[0, 1, 2, 3], [1, 2, 3, 7]])), errors.IndexOutOfRangeError, 1),
        (lambda p, t: (p, np.array([[0, 1, 2, 3], [1, 2, 4, 3]]) if signed_volumes(p, np.array([[1, 2, 3, 4]]))[0] > 0 else np.array([[0, 1, 2, 3], [1, 2, 3, 4]])), errors.InvertedElementError, 1),
        (lambda p, t: (np.vstack([p[:4], [0.5, 0.5, 0.0]]), t), errors.DegenerateElementError, 1),
        (lambda p, t: (p, np.array([[0, 1, 2, 3], [1, 2, 3, 3]])), errors.DegenerateElementError, 1),
        (lambda p, t: (p, np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 1, 3][::-1]])), errors.DuplicateElementError, 2),
        (lambda p, t: (p[:0], t), errors.EmptyMeshError, None),
        (lambda p, t: (p, t[:0]), errors.EmptyMeshError, None),
    ],
    ids=["nan", "out_of_range", "inverted", "flat", "repeated_node", "duplicate", "no_points", "no_tets"],
)
def test_each_validation_error_is_raised_and_cites_indices(mutate, error, cited):
    p, t = mutate(*_two_tets())
    with pytest.raises(error) as info:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            TetMesh(p, t)
    if cited is not None:
        assert cited in info.value.indices
        assert str(cited) in str(info.value)


def test_degenerate_tolerance_is_relative_to_mesh_scale():
    p, t = _unit_tet()
    for scale in (1e-6, 1.0, 1e3):
        TetMesh(p * scale, t)  # a good tet at any scale
        flat = p.copy()
        flat[3, 2] = 1e-10
        with pytest.raises(errors.DegenerateElementError):
            TetMesh(flat * scale, t)


def test_unused_nodes_and_non_manifold_surface_warn():
    p, t = _unit_tet()
    with pytest.warns(errors.UnusedNodesWarning, match="nodes \\[4\\]"):
        TetMesh(np.vstack([p, [5.0, 5, 5]]), t)
    # Two tets touching along one edge only: the surface is non-manifold at that edge.
    q = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 5]])
    vol = signed_volumes(q, tets)
    tets[vol < 0] = tets[vol < 0][:, [0, 1, 3, 2]]
    with pytest.warns(errors.NonManifoldSurfaceWarning, match="non-manifold"):
        TetMesh(q, tets)


def test_quality_metric():
    p, t = _unit_tet()
    reg = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
    reg_t = t if signed_volumes(reg, t)[0] > 0 else t[:, [0, 1, 3, 2]]
    np.testing.assert_allclose(mean_ratio_quality(reg, reg_t), 1.0, rtol=1e-12)
    q = mean_ratio_quality(p, t)[0]
    assert 0 < q < 1
    assert mean_ratio_quality(p, t[:, [0, 1, 3, 2]])[0] == pytest.approx(-q)


def test_boundary_faces_function_matches_mesh():
    m = block(1.0, 2)
    f, owner = boundary_faces(m.tets)
    np.testing.assert_array_equal(f, m.boundary_faces)
    np.testing.assert_array_equal(owner, m.boundary_face_tets)


def test_tetmesh_is_a_pytree_with_points_as_the_differentiable_leaf():
    m = block(1.0, 2)

    @jax.jit
    def total_volume(mesh):
        x = mesh.points[mesh.tets]
        a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        return jnp.sum(jnp.einsum("ij,ij->i", a, jnp.cross(b, c))) / 6

    np.testing.assert_allclose(total_volume(m), 1.0, rtol=1e-12)
    g = jax.grad(lambda pts: total_volume(m.with_points(pts)))(jnp.asarray(m.points))
    # d(volume)/d(x) is zero for interior nodes and non-zero on the boundary.
    interior = np.all((m.points > 1e-9) & (m.points < 1 - 1e-9), axis=1)
    np.testing.assert_allclose(np.asarray(g)[interior], 0.0, atol=1e-12)
    assert np.abs(np.asarray(g)[~interior]).sum() > 0
    leaves = jax.tree_util.tree_leaves(eqx.filter(m, eqx.is_inexact_array))
    assert any(leaf.shape == m.points.shape for leaf in leaves)


def test_mesh_field_shape_errors():
    p, t = _two_tets()
    with pytest.raises(errors.MeshError, match="point field 'u'"):
        TetMesh(p, t, point_data={"u": np.zeros((3, 3))})
    with pytest.raises(errors.MeshError, match="cell field 'E'"):
        TetMesh(p, t, cell_data={"E": np.zeros(3)})
    with pytest.raises(errors.MeshError, match="region name"):
        TetMesh(p, t, region_ids=[0, 1], region_names=["only"])
