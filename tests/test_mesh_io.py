"""meshio round trips, reading meshes written by other tools, selectors, atomic writes."""

import warnings

import meshio
import numpy as np
import pytest

from difftissue import errors
from difftissue.mesh import TetMesh, block, from_meshio, inspect_file, layered_skin, read_mesh, write_mesh
from difftissue.selectors import AnyOf, Ball, BoundingBoxFace, Box, select_nodes, selector_from_dict


@pytest.fixture
def skin():
    sp = layered_skin(size=(0.004, 0.003), resolution=(4, 3))
    rng = np.random.default_rng(0)
    mesh = sp.mesh
    fields_p = {"displacement": rng.normal(size=(mesh.n_nodes, 3)) * 1e-4, "temperature": rng.normal(size=mesh.n_nodes)}
    fields_c = {**sp.cell_fields(), "damage": rng.random(mesh.n_tets)}
    return mesh, fields_p, fields_c


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_round_trip_is_exact(tmp_path, skin, suffix):
    mesh, pd, cd = skin
    path = write_mesh(tmp_path / f"skin{suffix}", mesh, point_data=pd, cell_data=cd)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.points, mesh.points)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.region_ids, mesh.region_ids)
    assert back.region_names == mesh.region_names == ("epidermis", "dermis", "hypodermis")
    for k, v in pd.items():
        np.testing.assert_array_equal(back.point_data[k], v)
    for k, v in cd.items():
        np.testing.assert_array_equal(back.cell_data[k].reshape(v.shape), v)
    assert set(back.cell_data) == set(cd)


def test_xdmf_and_medit_round_trip(tmp_path, skin):
    mesh, pd, cd = skin
    back = read_mesh(write_mesh(tmp_path / "skin.xdmf", mesh, point_data=pd, cell_data=cd))
    np.testing.assert_allclose(back.points, mesh.points, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.region_ids, mesh.region_ids)
    np.testing.assert_allclose(back.point_data["displacement"], pd["displacement"], rtol=1e-12)
    medit = read_mesh(write_mesh(tmp_path / "skin.mesh", mesh))
    np.testing.assert_allclose(medit.points, mesh.points, rtol=1e-12)
    np.testing.assert_array_equal(medit.tets, mesh.tets)
    np.testing.assert_array_equal(medit.region_ids, mesh.region_ids)
    with pytest.raises(errors.MeshError, match="Medit"):
        write_mesh(tmp_path / "fields.mesh", mesh, point_data=pd)


def test_write_refuses_overwrite_and_is_atomic(tmp_path):
    mesh = block(1.0, 1)
    path = write_mesh(tmp_path / "m.vtu", mesh)
    before = path.read_bytes()
    with pytest.raises(errors.OutputExistsError, match="refusing to overwrite"):
        write_mesh(path, block(2.0, 1))
    assert path.read_bytes() == before
    write_mesh(path, block(2.0, 1), overwrite=True)
    np.testing.assert_allclose(read_mesh(path).bounds()[1], 2.0)
    # A failed write leaves neither a partial file nor a temporary one.
    with pytest.raises(errors.MeshError):
        write_mesh(tmp_path / "bad.vtu", mesh, point_data={"u": np.zeros(3)})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.vtu"]
    with pytest.raises(errors.MeshError, match="suffix"):
        write_mesh(tmp_path / "m.stl", mesh)


def test_length_unit_conversion(tmp_path):
    m = meshio.Mesh(np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]]), [("tetra", np.array([[0, 1, 2, 3]]))])
    meshio.write(tmp_path / "mm.vtu", m)
    mesh = read_mesh(tmp_path / "mm.vtu", length_unit="mm")
    np.testing.assert_allclose(mesh.volumes().sum(), (0.01) ** 3 / 6, rtol=1e-12)
    with pytest.raises(errors.MeshError, match="unknown length unit"):
        read_mesh(tmp_path / "mm.vtu", length_unit="furlong")


def test_unsupported_cells_are_refused(tmp_path):
    tri = meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))])
    meshio.write(tmp_path / "tri.vtu", tri)
    with pytest.raises(errors.UnsupportedMeshError, match="no tetrahedra"):
        read_mesh(tmp_path / "tri.vtu")
    t10 = meshio.Mesh(np.random.default_rng(1).random((10, 3)), [("tetra10", np.arange(10)[None])])
    with pytest.raises(errors.UnsupportedMeshError, match="linear 4-node"):
        from_meshio(t10)
    (tmp_path / "junk.vtu").write_text("not a mesh")
    with pytest.raises(errors.MeshError, match="cannot read"):
        read_mesh(tmp_path / "junk.vtu")


def test_scikit_fem_mesh_reads_with_reorientation(tmp_path):
    skfem = pytest.importorskip("skfem")
    sk = skfem.MeshTet.init_tensor(np.linspace(0, 0.02, 4), np.linspace(0, 0.01, 3), np.linspace(0, 0.005, 3))
    sk.save(str(tmp_path / "sk.vtu"))
    mesh, findings, _ = inspect_file(tmp_path / "sk.vtu")
    # scikit-fem does not orient its tets: strict reading reports the negative ones as inverted.
    inverted = [f for f in findings if f.kind is errors.InvertedElementError]
    assert mesh is None and inverted and inverted[0].severity == "error"
    with pytest.raises(errors.InvertedElementError, match="reorient=True"):
        read_mesh(tmp_path / "sk.vtu")
    mesh = read_mesh(tmp_path / "sk.vtu", reorient=True)
    assert mesh.n_tets == sk.t.shape[1] and mesh.n_nodes == sk.p.shape[1]
    assert np.all(mesh.volumes() > 0)
    np.testing.assert_allclose(mesh.volumes().sum(), 0.02 * 0.01 * 0.005, rtol=1e-12)


def test_gmsh_api_mesh_with_physical_groups(tmp_path):
    try:
        import gmsh
    except (ImportError, OSError) as e:  # the wheel needs system GL libraries
        pytest.skip(f"gmsh unavailable: {e}")
    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("two")
        a = gmsh.model.occ.addBox(0, 0, 0, 2, 1, 1)
        b = gmsh.model.occ.addBox(0, 0, 1, 2, 1, 0.5)
        gmsh.model.occ.fragment([(3, a)], [(3, b)])
        gmsh.model.occ.synchronize()
        vols = sorted(gmsh.model.getEntities(3), key=lambda e: gmsh.model.occ.getCenterOfMass(*e)[2])
        gmsh.model.addPhysicalGroup(3, [vols[0][1]], 7, name="muscle")
        gmsh.model.addPhysicalGroup(3, [vols[1][1]], 9, name="fat")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.4)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(tmp_path / "g.msh"))
    finally:
        gmsh.finalize()
    mesh = read_mesh(tmp_path / "g.msh", length_unit="mm")
    assert mesh.region_names == ("muscle", "fat")
    vols = mesh.region_volumes()
    np.testing.assert_allclose(vols["muscle"], 2e-9, rtol=1e-9)
    np.testing.assert_allclose(vols["fat"], 1e-9, rtol=1e-9)
    assert np.all(mesh.volumes() > 0)


# ------------------------------------------------------------------------- selectors
def test_selectors_pick_the_right_nodes():
    m = block((2.0, 1.0, 1.0), (4, 2, 2))
    p = m.points
    bottom = select_nodes(m, BoundingBoxFace("z", "min"))
    np.testing.assert_array_equal(bottom, np.flatnonzero(p[:, 2] == 0))
    assert len(bottom) == 5 * 3
    top = select_nodes(m, {"face": "z-max"})
    np.testing.assert_array_equal(top, np.flatnonzero(p[:, 2] == 1.0))
    box = select_nodes(m, Box((0.4, 0, 0), (1.1, 0.5, 1)))
    np.testing.assert_array_equal(box, np.flatnonzero((p[:, 0] >= 0.4) & (p[:, 0] <= 1.1) & (p[:, 1] <= 0.5)))
    ball = select_nodes(m, {"ball": {"center": [1.0, 0.5, 1.0], "radius": 0.51}})
    np.testing.assert_array_equal(ball, np.flatnonzero(np.linalg.norm(p - [1, 0.5, 1], axis=1) <= 0.51))
    both = select_nodes(m, {"any_of": [{"face": "x-min"}, {"face": "x-max"}]})
    assert len(both) == 2 * 9
    for sel in (BoundingBoxFace("x", "max"), Box((0, 0, 0), (1, 1, 1)), Ball((0, 0, 0), 1.0), AnyOf((Ball((0, 0, 0), 1.0),))):
        assert selector_from_dict(sel.to_dict()) == sel


@pytest.mark.parametrize(
    "data,match",
    [
        ({"face": "w-min"}, "axis"),
        ({"face": "z-middle"}, "side"),
        ({"face": "zmin"}, "like 'z-min'"),
        ({"box": {"lower": [0, 0, 0]}}, "missing \\['upper'\\]"),
        ({"box": {"lower": [0, 0, 1], "upper": [1, 1, 0]}}, "below"),
        ({"ball": {"center": [0, 0], "radius": 1}}, "three finite numbers"),
        ({"ball": {"center": [0, 0, 0], "radius": -1}}, "positive"),
        ({"face": "z-min", "box": {}}, "exactly one"),
        ({"fcae": "z-min"}, "exactly one"),
        ({"face": "z-min", "tol": 1}, "unknown selector key"),
        ("z-min", "table"),
    ],
)
def test_selector_errors_name_the_problem(data, match):
    with pytest.raises(errors.SelectorError, match=match):
        selector_from_dict(data)


def test_empty_selection_is_an_error_unless_allowed():
    m = block(1.0, 1)
    with pytest.raises(errors.SelectorError, match="selects no node"):
        select_nodes(m, Ball((5.0, 5, 5), 0.1))
    assert select_nodes(m, Ball((5.0, 5, 5), 0.1), allow_empty=True).size == 0


def test_written_files_get_normal_permissions(tmp_path):
    import os
    import stat

    umask = os.umask(0o022)
    try:
        path = write_mesh(tmp_path / "p.vtu", block(1.0, 1))
    finally:
        os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    with pytest.raises(errors.OutputError, match="does not exist"):
        write_mesh(tmp_path / "missing" / "p.vtu", block(1.0, 1))
