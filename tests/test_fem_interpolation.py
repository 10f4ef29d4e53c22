"""fem_field on any reference mesh (issue 19): the interpolation operator
(difftissue.interpolation), tetra10 / hexahedron references read with meshio, and FEMField with
a reference interpolated onto the model's own mesh (docs/dev/fem-field-interpolation.md).

Meshes are small (a few hundred nodes); the reference meshes come from gmsh (unstructured
linear and quadratic tetrahedra) and from a perturbed hexahedral grid."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

from difftissue import Material, errors
from difftissue.boundary import BoundaryConditions
from difftissue.config import SeparatelyCompiled, load_config
from difftissue.data import load_fem_result
from difftissue.fit import fit
from difftissue.fit.result import plot_layout
from difftissue.interpolation import interpolation_operator, shape_functions, shape_gradients
from difftissue.materials import MaterialParameterization, ScaledLogit
from difftissue.mesh import block, from_meshio, write_mesh
from difftissue.models import make_model
from difftissue.report import write_fit_outputs
from difftissue.scenarios import FEMField
from difftissue.solvers.static import solve_static

L, H = 0.01, 0.005  # the specimen: L x L x H [m]
TRUTH = Material(12e3, 0.42)
FACES = {f: {"face": f} for f in ("x-min", "y-min", "z-min", "z-max")}
ROLLERS = [{"set": FACES["z-min"], "components": "z"}, {"set": FACES["x-min"], "components": "x"},
           {"set": FACES["y-min"], "components": "y"}, {"set": FACES["z-max"], "components": "z"}]
P_E_NU = MaterialParameterization(("youngs_modulus", "poisson_ratio"), transforms={"poisson_ratio": ScaledLogit(0.0, 0.5)})


def _gmsh_box(size, h, order=1) -> meshio.Mesh:
    """An unstructured gmsh tet mesh of the box [0, size] (order 2: tetra10, straight edges)."""
    gmsh = pytest.importorskip("gmsh")
    import tempfile
    from pathlib import Path

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, *size)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 1)
        gmsh.option.setNumber("Mesh.MeshSizeMin", h)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.generate(3)
        if order == 2:
            gmsh.model.mesh.setOrder(2)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "box.msh"
            gmsh.write(str(path))
            return meshio.read(path)
    finally:
        gmsh.finalize()


def _hex_grid(size, n, *, perturb=0.0, seed=0):
    """``(points, hexahedra)`` of an n[0] x n[1] x n[2] grid of the box [0, size] (VTK order),
    interior nodes moved at random by up to ``perturb`` of a cell (distorted, non-planar faces)."""
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, n)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(P)).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    interior = np.ones(idx.shape, dtype=bool)
    interior[[0, -1]] = interior[:, [0, -1]] = interior[:, :, [0, -1]] = False
    rng = np.random.default_rng(seed)
    cell = np.array(size) / np.array(n)
    P[idx[interior]] += perturb * cell * rng.uniform(-1, 1, (int(interior.sum()), 3))
    i, j, k = (a.reshape(-1) for a in np.meshgrid(*[np.arange(m) for m in n], indexing="ij"))
    hexes = np.stack([idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
                      idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]], axis=1)
    return P, hexes


def _uniaxial(points, material=TRUTH, strain=0.01):
    """The exact homogeneous solution of the rollers + top-platen test (an affine field) and the
    top platen's reaction [N]: u = (nu e x, nu e y, -e z), F_z = -E e L^2."""
    nu = material.poisson_ratio
    u = np.stack([nu * strain * points[:, 0], nu * strain * points[:, 1], -strain * points[:, 2]], axis=1)
    return u, -material.youngs_modulus * strain * L * L


# ======================================================================== the operator
def test_shape_functions_partition_unity_and_gradients():
    rng = np.random.default_rng(3)
    xi = rng.uniform(-0.2, 0.4, (7, 3))
    for t in ("tetra", "tetra10", "hexahedron"):
        N = shape_functions(t, xi)
        np.testing.assert_allclose(N.sum(axis=1), 1.0, rtol=0, atol=1e-14)
        e = 1e-6
        fd = np.stack([(shape_functions(t, xi + e * d) - shape_functions(t, xi - e * d)) / (2 * e) for d in np.eye(3)], axis=2)
        np.testing.assert_allclose(shape_gradients(t, xi), fd, rtol=0, atol=1e-8)
    # each shape function is 1 at its own node, 0 at the others
    hex_nodes = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float)
    np.testing.assert_allclose(shape_functions("hexahedron", hex_nodes), np.eye(8), atol=1e-15)
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    mids = np.array([(corners[a] + corners[b]) / 2 for a, b in ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))])
    np.testing.assert_allclose(shape_functions("tetra10", np.vstack([corners, mids])), np.eye(10), atol=1e-15)
    with pytest.raises(errors.UnsupportedMeshError, match="wedge"):
        shape_functions("wedge", xi)


def _affine(rng):
    A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
    return lambda x: x @ A.T + b


def test_operator_is_exact_for_affine_fields_on_tets_hexes_and_p2():
    rng = np.random.default_rng(0)
    f = _affine(rng)
    q = rng.uniform(0.0, 1.0, (300, 3)) * [L, L, H]
    tet = block((L, L, H), (3, 4, 2))
    hexP, hexes = _hex_grid((L, L, H), (3, 3, 2), perturb=0.25)
    p2 = _gmsh_box((L, L, H), 0.004, order=2)
    sources = {
        "tetra": (tet.points, {"tetra": tet.tets}),
        "hexahedron (distorted)": (hexP, {"hexahedron": hexes}),
        "tetra10": (p2.points, {"tetra10": p2.cells_dict["tetra10"]}),
    }
    for name, (P, cells) in sources.items():
        op = interpolation_operator(P, cells, q)
        assert op.distances.max() == 0.0, name
        np.testing.assert_allclose(np.asarray(op(f(P))), f(q), rtol=0, atol=1e-13 * np.abs(f(q)).max(), err_msg=name)
        np.testing.assert_allclose(op.weights.sum(axis=1), 1.0, atol=1e-13)
        np.testing.assert_allclose(op.as_sparse() @ f(P), f(q), atol=1e-13 * np.abs(f(q)).max())
    # P2 is exact for quadratic fields (straight-edged tetra10), the trilinear hexahedron for
    # trilinear fields on a parallelepiped grid
    Q = rng.normal(size=(3, 3, 3))
    quad = lambda x: np.einsum("ijk,nj,nk->ni", Q, x / L, x / L) + f(x)  # noqa: E731
    op = interpolation_operator(*sources["tetra10"], q)
    np.testing.assert_allclose(np.asarray(op(quad(p2.points))), quad(q), rtol=0, atol=1e-12 * np.abs(quad(q)).max())
    straight = _hex_grid((L, L, H), (3, 3, 2))
    tri = lambda x: np.stack([x[:, 0] * x[:, 1] * x[:, 2], x[:, 0] * x[:, 1], x[:, 1] * x[:, 2] + x[:, 0]], axis=1) / L**3  # noqa: E731
    op = interpolation_operator(straight[0], {"hexahedron": straight[1]}, q)
    np.testing.assert_allclose(np.asarray(op(tri(straight[0]))), tri(q), rtol=0, atol=1e-13 * np.abs(tri(q)).max())
    # ... and P1 is not exact for a quadratic field (the check can fail)
    op1 = interpolation_operator(tet.points, {"tetra": tet.tets}, q)
    assert np.abs(np.asarray(op1(quad(tet.points))) - quad(q)).max() > 1e-3 * np.abs(quad(q)).max()


@pytest.mark.parametrize("candidates", [1, 16])
def test_every_point_inside_is_found(monkeypatch, candidates):
    """2,000 random points in a 1,536-tet block: each is found in a tet that holds it, also when
    the nearest-centroid candidates are cut to one and most points go through the exhaustive
    search (a regression: several candidates of one point once overwrote each other)."""
    from difftissue import interpolation

    monkeypatch.setattr(interpolation, "_CANDIDATES", candidates)
    mesh = block((L, L, H), (8, 8, 4))
    q = np.random.default_rng(7).uniform(0.0, 1.0, (2000, 3)) * [L, L, H]
    op = interpolation_operator(mesh.points, {"tetra": mesh.tets}, q)
    assert op.distances.max() == 0.0 and op.weights.min() >= -1e-10
    f = _affine(np.random.default_rng(8))
    np.testing.assert_allclose(np.asarray(op(f(mesh.points))), f(q), rtol=0, atol=1e-13 * np.abs(f(q)).max())


def test_operator_in_jax_jit_vmap_and_gradient():
    mesh = block((L, L, H), (2, 2, 2))
    q = np.random.default_rng(1).uniform(0.0, 1.0, (20, 3)) * [L, L, H]
    op = interpolation_operator(mesh.points, {"tetra": mesh.tets}, q)
    u = jnp.asarray(np.random.default_rng(2).normal(size=(3, mesh.n_nodes, 3)))
    batched = jax.jit(jax.vmap(op))(u)
    np.testing.assert_allclose(np.asarray(batched[1]), op.as_sparse() @ np.asarray(u[1]), rtol=1e-13)
    # linear: the gradient of <w, P u> is P^T w
    w = np.random.default_rng(4).normal(size=(len(q), 3))
    g = jax.grad(lambda v: jnp.sum(jnp.asarray(w) * op(v)))(u[0])
    np.testing.assert_allclose(np.asarray(g), op.as_sparse().T @ w, rtol=1e-12)


def test_points_outside_the_mesh_are_refused_with_how_many_and_how_far():
    mesh = block((L, L, H), (2, 2, 2))
    inside = np.array([[0.5 * L, 0.5 * L, 0.5 * H], [0.1 * L, 0.2 * L, 0.3 * H]])
    out = np.array([[0.5 * L, 0.5 * L, H + 2e-4], [L + 5e-4, 0.5 * L, 0.5 * H]])  # 0.2 mm above, 0.5 mm beside
    with pytest.raises(errors.PointsOutsideMeshError, match=r"2 of the 4 reference nodes lie outside the mesh .* by 0\.0002 to 0\.0005 m") as info:
        interpolation_operator(mesh.points, {"tetra": mesh.tets}, np.vstack([inside, out]), what="reference nodes")
    assert info.value.indices == (2, 3)
    np.testing.assert_allclose(info.value.distances, [2e-4, 5e-4], rtol=1e-12)
    # within the tolerance: accepted, the nearest element extrapolated (exact for affine fields)
    f = _affine(np.random.default_rng(5))
    op = interpolation_operator(mesh.points, {"tetra": mesh.tets}, out, tolerance=1e-3)
    np.testing.assert_allclose(op.distances, [2e-4, 5e-4], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(op(f(mesh.points))), f(out), atol=1e-13 * np.abs(f(out)).max())
    # a hexahedral source: the same error
    P, hexes = _hex_grid((L, L, H), (2, 2, 1))
    with pytest.raises(errors.PointsOutsideMeshError, match=r"1 of the 1 points .* by 0\.0002 to 0\.0002 m"):
        interpolation_operator(P, {"hexahedron": hexes}, out[:1])
    with pytest.raises(errors.UnsupportedMeshError, match="pyramid"):
        interpolation_operator(P, {"pyramid": hexes[:, :5]}, out[:1])


# ======================================================================== reference files
@pytest.mark.parametrize("fmt", ["vtu", "xdmf", "vtk"])
def test_tetra10_and_hex_references_are_read(tmp_path, fmt):
    """VTU, XDMF and legacy VTK (what FEBio Studio exports) with quadratic tetrahedra or
    hexahedra: the elements are kept (``cells``), there is no TetMesh, lengths are converted."""
    p2 = _gmsh_box((L, L, H), 0.004, order=2)
    P, hexes = _hex_grid((L, L, H), (2, 2, 2), perturb=0.2)
    for cells, pts in (([("tetra10", p2.cells_dict["tetra10"])], p2.points), ([("hexahedron", hexes)], P)):
        u, _ = _uniaxial(pts)
        path = tmp_path / f"ref.{fmt}"
        meshio.write(path, meshio.Mesh(pts * 1e3, cells, point_data={"displacement": u * 1e3}), file_format=fmt)
        res = load_fem_result(path, length_unit="mm")
        assert res.mesh is None and list(res.cells) == [cells[0][0]] and res.metadata["cell_types"] == [cells[0][0]]
        np.testing.assert_allclose(res.points, pts, rtol=1e-12)
        np.testing.assert_allclose(res.displacement, u, rtol=1e-12, atol=1e-18)
    # linear tets still give a TetMesh (the own-mesh path), mixed meshes keep both element types
    tet = block((L, L, H), (1, 1, 1))
    write_mesh(tmp_path / "tet.vtu", tet, point_data={"displacement": np.zeros((tet.n_nodes, 3))})
    res = load_fem_result(tmp_path / "tet.vtu")
    assert res.mesh is not None and list(res.cells) == ["tetra"] and res.points is not None


def test_abaqus_inp_with_a_displacement_table(tmp_path):
    """An Abaqus input file holds the mesh only (the error says so); the displacement comes from
    a CSV keyed by the *NODE labels (here not 1..N and not in order)."""
    P, hexes = _hex_grid((L, L, H), (1, 1, 1))
    labels = np.array([108, 101, 107, 102, 106, 103, 105, 104])
    lines = ["*HEADING", "hand-written C3D8", "*NODE"] + [f"{k}, {float(x)!r}, {float(y)!r}, {float(z)!r}" for k, (x, y, z) in zip(labels, P * 1e3)]
    lines += ["** a comment", "*ELEMENT, TYPE=C3D8, ELSET=tissue", "1, " + ", ".join(str(labels[i]) for i in hexes[0]), "*END STEP"]
    (tmp_path / "ref.inp").write_text("\n".join(lines) + "\n")
    with pytest.raises(errors.MissingFieldError, match="no point field 'displacement'; its point fields are: none"):
        load_fem_result(tmp_path / "ref.inp", length_unit="mm")
    u, _ = _uniaxial(P)
    rows = np.random.default_rng(0).permutation(len(P))
    table = "node,ux,uy,uz\n" + "".join(f"{labels[i]},{float(u[i, 0]) * 1e3!r},{float(u[i, 1]) * 1e3!r},{float(u[i, 2]) * 1e3!r}\n" for i in rows)
    (tmp_path / "u.csv").write_text(table)
    res = load_fem_result(tmp_path / "ref.inp", length_unit="mm", displacement_table=tmp_path / "u.csv")
    assert res.mesh is None and list(res.cells) == ["hexahedron"] and res.metadata["field"] == "table:u.csv"
    np.testing.assert_allclose(res.points, P, rtol=1e-12)
    np.testing.assert_allclose(res.displacement, u, rtol=1e-12, atol=1e-18)
    (tmp_path / "short.csv").write_text("\n".join(table.splitlines()[:-1]) + "\n")
    with pytest.raises(errors.MissingFieldError, match=rf"no row for the nodes \[{labels[rows[-1]]}\]"):
        load_fem_result(tmp_path / "ref.inp", displacement_table=tmp_path / "short.csv")
    (tmp_path / "bad.csv").write_text(table.replace(f"\n{labels[rows[1]]},", "\n999,"))
    with pytest.raises(errors.MissingFieldError, match=r"node labels \[999\] are not nodes of ref.inp"):
        load_fem_result(tmp_path / "ref.inp", displacement_table=tmp_path / "bad.csv")


def test_abaqus_hybrid_tets_are_refused_with_the_fix(tmp_path):
    """meshio 5.3 cannot read Abaqus C3D4H cells (it maps them to "tetra4" and fails): the error
    says to write C3D4; with C3D4 the same file reads."""
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    lines = ["*NODE"] + [f"{k + 1}, {x}, {y}, {z}" for k, (x, y, z) in enumerate(P)] + ["*ELEMENT, TYPE=C3D4H", "1, 1, 2, 3, 4"]
    (tmp_path / "tet.inp").write_text("\n".join(lines) + "\n")
    (tmp_path / "u.csv").write_text("node,ux,uy,uz\n" + "".join(f"{k + 1},0,0,{-0.01 * z}\n" for k, z in enumerate(P[:, 2])))
    with pytest.raises(errors.UnsupportedMeshError, match="write them as C3D4"):
        load_fem_result(tmp_path / "tet.inp", length_unit="mm", displacement_table=tmp_path / "u.csv")
    (tmp_path / "tet.inp").write_text((tmp_path / "tet.inp").read_text().replace("C3D4H", "C3D4"))
    res = load_fem_result(tmp_path / "tet.inp", length_unit="mm", displacement_table=tmp_path / "u.csv")
    assert list(res.cells) == ["tetra"] and res.mesh is not None
    np.testing.assert_allclose(res.displacement[:, 2], -0.01e-3 * P[:, 2])


def test_bad_reference_files(tmp_path):
    """Wedges and degenerate hexahedra are refused."""
    P, hexes = _hex_grid((L, L, H), (1, 1, 1))
    wedge = meshio.Mesh(P[:6], [("wedge", np.arange(6)[None])], point_data={"displacement": np.zeros((6, 3))})
    meshio.write(tmp_path / "wedge.vtu", wedge)
    with pytest.raises(errors.UnsupportedMeshError, match="wedge"):
        load_fem_result(tmp_path / "wedge.vtu")
    flat = P.copy()
    flat[:, 2] = 0.0
    meshio.write(tmp_path / "flat.vtu", meshio.Mesh(flat, [("hexahedron", hexes)], point_data={"displacement": np.zeros((8, 3))}))
    with pytest.raises(errors.DegenerateElementError, match="degenerate"):
        load_fem_result(tmp_path / "flat.vtu")


# ================================================================ FEMField, interpolated
@pytest.fixture(scope="module")
def unstructured_reference():
    """A homogeneous block solved by difftissue's fem_linear on an unstructured gmsh tet mesh:
    rollers on x-min, y-min, z-min, the top pressed down 1 % (uniaxial stress: an affine field)."""
    mesh = from_meshio(_gmsh_box((L, L, H), 0.003), reorient=True)
    p = np.asarray(mesh.points)
    fixed, disp = np.zeros((mesh.n_nodes, 3), dtype=bool), np.zeros((mesh.n_nodes, 3))
    on = lambda a, v: np.abs(p[:, a] - v) <= 1e-9 * L  # noqa: E731
    fixed[on(0, 0.0), 0] = fixed[on(1, 0.0), 1] = fixed[on(2, 0.0), 2] = fixed[on(2, H), 2] = True
    disp[on(2, H), 2] = -0.01 * H
    sol = solve_static(make_model(mesh, "fem_linear"), TRUTH, BoundaryConditions(fixed, disp, np.zeros_like(disp)))
    u = np.asarray(sol.displacement)
    force = float(np.asarray(sol.reaction)[on(2, H), 2].sum())
    exact_u, exact_f = _uniaxial(p)
    assert np.abs(u - exact_u).max() <= 1e-9 * np.abs(exact_u).max() and force == pytest.approx(exact_f, rel=1e-9)
    return mesh, u, force


def test_unstructured_reference_recovers_E_and_nu_on_the_models_own_grid(unstructured_reference, tmp_path):
    """The check of issue 19: a reference on an unstructured gmsh mesh (not the model's nodes),
    fitted by fem_linear on its own 2 x 2 x 2 structured grid with ``difftissue.fit``. The field
    is affine, which P1 on any mesh represents exactly, so the discretisation adds nothing:
    E and nu are recovered to round-off (measured 3e-14 relative), tested at 1e-6."""
    ref, u, force = unstructured_reference
    spec = block((L, L, H), (2, 2, 2))
    assert not np.isin(np.round(ref.points / 1e-9), np.round(spec.points / 1e-9)).all(axis=1).all()  # other nodes
    sc = FEMField(ref, u, prescribed=ROLLERS, specimen=spec, model="fem_linear", reaction={"set": FACES["z-max"], "components": "z", "force": [force]})
    # observed: every free component of the reference's nodes (rollers and platen excluded)
    p = ref.points
    free = np.ones((ref.n_nodes, 3), dtype=bool)
    free[np.abs(p[:, 0]) < 1e-12, 0] = free[np.abs(p[:, 1]) < 1e-12, 1] = free[np.abs(p[:, 2]) < 1e-12, 2] = free[np.abs(p[:, 2] - H) < 1e-12, 2] = False
    assert sc.reference_mesh == "interpolate" and sc.observe_dofs.size == free.sum()
    # fitted as a fit config fits it: the scenario's prediction and its tangents compiled once
    # (SeparatelyCompiled), not inlined in each of the fit's programs
    res = fit([SeparatelyCompiled(sc, fields=P_E_NU.fields)], P_E_NU, Material(8e3, 0.3))
    assert res.converged
    assert res.values["youngs_modulus"] == pytest.approx(TRUTH.youngs_modulus, rel=1e-6)
    assert res.values["poisson_ratio"] == pytest.approx(TRUTH.poisson_ratio, rel=1e-6)
    # the outputs: the displacement profile is plotted at the reference's nodes, the fitted
    # specimen is the model's grid with the transferred boundary values
    paths = write_fit_outputs(res, tmp_path / "out", model="fem_linear", scenarios=[sc])
    assert {"fit.png", "report.md", "specimen-fem_field.vtu"} <= set(paths)
    np.testing.assert_array_equal(plot_layout(sc)["points"], sc.observed_points[sc.observe_dofs // 3])
    assert meshio.read(paths["specimen-fem_field.vtu"]).points.shape == (spec.n_nodes, 3)


@pytest.mark.parametrize("kind", ["tetra10", "hexahedron"])
def test_p2_and_hex_references_recover_E_and_nu(tmp_path, kind):
    """The exact homogeneous solution written on a quadratic-tet (gmsh) or distorted-hex
    reference file, read back and fitted by fem_linear on a 2 x 2 x 1 grid: E, nu to 1e-6."""
    if kind == "tetra10":
        m = _gmsh_box((L, L, H), 0.004, order=2)
        pts, cells = m.points, [("tetra10", m.cells_dict["tetra10"])]
    else:
        pts, hexes = _hex_grid((L, L, H), (3, 2, 3), perturb=0.25)
        cells = [("hexahedron", hexes)]
    u, force = _uniaxial(pts)
    meshio.write(tmp_path / "ref.vtu", meshio.Mesh(pts, cells, point_data={"displacement": u}))
    ref = load_fem_result(tmp_path / "ref.vtu")
    sc = FEMField(ref, ref.displacement, prescribed=ROLLERS, specimen=block((L, L, H), (2, 2, 1)), model="fem_linear",
                  reaction={"set": FACES["z-max"], "components": "z", "force": [force]})
    # the scenario's prediction compiled once (with its tangents, SeparatelyCompiled, as a fit
    # config does): the check at the truth and the fit run the same program
    compiled = SeparatelyCompiled(sc, fields=P_E_NU.fields)
    np.testing.assert_allclose(np.asarray(compiled.predict(TRUTH)), sc.observed, rtol=1e-9, atol=1e-9 * np.abs(sc.observed).max())
    res = fit([compiled], P_E_NU, Material(8e3, 0.3))
    assert res.values["youngs_modulus"] == pytest.approx(TRUTH.youngs_modulus, rel=1e-6)
    assert res.values["poisson_ratio"] == pytest.approx(TRUTH.poisson_ratio, rel=1e-6)


@pytest.fixture(scope="module")
def punch_reference():
    """A non-affine field: a punch pressed into a block (gmsh mesh, base clamped), fem_linear."""
    mesh = from_meshio(_gmsh_box((L, L, H), 0.0025), reorient=True)
    p = np.asarray(mesh.points)
    bottom = np.abs(p[:, 2]) <= 1e-9 * L
    punch = (np.abs(p[:, 2] - H) <= 1e-9 * L) & (np.hypot(p[:, 0] - L / 2, p[:, 1] - L / 2) <= 0.3 * L)
    bc = BoundaryConditions.free(mesh).fix(mesh, np.flatnonzero(bottom)).fix(mesh, np.flatnonzero(punch), "z", (0, 0, -1e-4))
    sol = solve_static(make_model(mesh, "fem_linear"), TRUTH, bc)
    return mesh, np.asarray(sol.displacement), float(np.asarray(sol.reaction)[punch, 2].sum())


PUNCH = {"ball": {"center": [L / 2, L / 2, H], "radius": 0.3 * L}}


def test_interpolated_on_the_same_mesh_equals_the_own_mesh_path(punch_reference):
    """With the reference's own mesh as the specimen the operators are the identity: the
    interpolated scenario predicts what the own-mesh one does (a non-affine punch field)."""
    mesh, u, force = punch_reference
    kw = dict(prescribed=[{"set": FACES["z-min"]}, {"set": PUNCH, "components": "z"}], model="fem_linear",
              reaction={"set": PUNCH, "components": "z", "force": [force]})
    own = FEMField(mesh, u, **kw)
    interp = FEMField(mesh, u, specimen=mesh, **kw)
    np.testing.assert_allclose(interp.observed, own.observed, rtol=0, atol=0)
    np.testing.assert_allclose(np.asarray(interp.predict(TRUTH)), interp.observed, rtol=1e-8, atol=1e-10 * np.abs(own.observed).max())
    other = Material(9e3, 0.3)
    np.testing.assert_allclose(np.asarray(interp.predict(other)), np.asarray(own.predict(other)), rtol=1e-10, atol=1e-12 * np.abs(own.observed).max())


def test_gradient_of_an_interpolated_fem_field_loss(punch_reference):
    """d loss / d(E, nu) through the solve and the observation operator (model block 3 x 3 x 2,
    reference on the gmsh mesh) against central differences, float64, rtol 1e-5."""
    mesh, u, force = punch_reference
    sc = FEMField(mesh, u, prescribed=[{"set": FACES["z-min"]}, {"set": PUNCH, "components": "z"}], specimen=block((L, L, H), (3, 3, 2)),
                  model="fem_linear", reaction={"set": PUNCH, "components": "z", "force": [force]})

    @jax.jit  # one program for the four difference evaluations
    def loss(E, nu):
        r = (sc.predict(Material(E, nu)) - sc.observed) / sc.sigma
        return 0.5 * jnp.sum(r**2)

    E0, nu0 = 10e3, 0.35
    gE, gnu = jax.jit(jax.grad(loss, argnums=(0, 1)))(E0, nu0)
    hE, hnu = 1e-4 * E0, 1e-5
    fdE = (loss(E0 + hE, nu0) - loss(E0 - hE, nu0)) / (2 * hE)
    fdnu = (loss(E0, nu0 + hnu) - loss(E0, nu0 - hnu)) / (2 * hnu)
    assert float(gE) == pytest.approx(float(fdE), rel=1e-5)
    assert float(gnu) == pytest.approx(float(fdnu), rel=1e-5)
    assert abs(float(gE)) > 0 and abs(float(gnu)) > 0


def test_interpolated_fem_field_errors(punch_reference):
    mesh, u, force = punch_reference
    spec = block((L, L, H), (2, 2, 1))
    with pytest.raises(errors.ConfigError, match="'bottom' is a point-data node set of the reference; the model's own mesh"):
        FEMField(mesh.__class__(mesh.points, mesh.tets, point_data={"bottom": (mesh.points[:, 2] == 0).astype(int)}), u,
                 prescribed=[{"set": "bottom"}], specimen=spec)
    # a specimen larger than the reference: its prescribed top nodes lie outside the reference
    with pytest.raises(errors.PointsOutsideMeshError, match=r"prescribed nodes of the model \(specimen\)"):
        FEMField(mesh, u, prescribed=[{"set": FACES["z-min"]}, {"set": FACES["z-max"], "components": "z"}], specimen=block((L, L, 2 * H), (2, 2, 2)))
    # a specimen smaller than the reference: the reference's nodes lie outside the model
    with pytest.raises(errors.PointsOutsideMeshError, match=r"of the \d+ observed reference nodes lie outside"):
        FEMField(mesh, u, prescribed=[{"set": FACES["z-min"]}], specimen=block((L, L, 0.8 * H), (2, 2, 1)))
    with pytest.raises(errors.ConfigError, match="tolerance is used only"):
        FEMField(mesh, u, prescribed=[{"set": FACES["z-min"]}], tolerance=1e-6)


# ================================================================================ config
def test_config_fem_field_with_a_specimen(tmp_path, unstructured_reference):
    ref, u, force = unstructured_reference
    write_mesh(tmp_path / "ref.vtu", ref, point_data={"displacement": u * 1e3}, overwrite=True)
    base = f"""
[material]
youngs_modulus = 8e3
poisson_ratio = 0.3
[fit]
parameters = ["youngs_modulus", "poisson_ratio"]
[[experiment]]
name = "rollers"
scenario = "fem_field"
data = {{ format = "fem", path = "ref.vtu", displacement_unit = "mm" }}
prescribed = [{{ set = {{ face = "z-min" }}, components = "z" }}, {{ set = {{ face = "x-min" }}, components = "x" }},
              {{ set = {{ face = "y-min" }}, components = "y" }}, {{ set = {{ face = "z-max" }}, components = "z" }}]
reaction = {{ set = {{ face = "z-max" }}, components = "z", force = [{force!r}] }}
"""
    (tmp_path / "a.toml").write_text(base + "specimen = { cells = [2, 2, 1] }\n")
    cfg = load_config(tmp_path / "a.toml")
    sc = cfg.experiments[0].scenario
    sc = getattr(sc, "scenario", sc)
    assert sc.reference_mesh == "interpolate" and sc.model.rest_points.shape == (18, 3)
    np.testing.assert_allclose(np.asarray(sc.predict(TRUTH)), sc.observed, rtol=1e-9, atol=1e-9 * np.abs(sc.observed).max())
    # a block specimen can be coarsened (the fit's discretisation check): the same observations
    coarse, info = cfg.experiments[0].coarsen()
    assert info["coarse_cells"] == [1, 1, 1] and coarse.model.rest_points.shape == (8, 3)
    np.testing.assert_array_equal(coarse.observed, sc.observed)
    (tmp_path / "own.toml").write_text(base)
    own = load_config(tmp_path / "own.toml").experiments[0].scenario
    assert getattr(own, "scenario", own).reference_mesh == "own"
    for extra, message in (('reference_mesh = "interpolate"\n', r"specimen: missing \(required with reference_mesh"),
                           ('reference_mesh = "own"\nspecimen = { cells = 2 }\n', r"specimen: not used with reference_mesh = \"own\""),
                           ("specimen = { size = [1, 1, 1] }\n", r"specimen.cells: missing"),
                           ("specimen = { cells = 2, origin = [0, 0, 0.001] }\ntolerance = 1e-9\n", r"lie outside")):
        (tmp_path / "b.toml").write_text(base + extra)
        with pytest.raises(errors.DifftissueError, match=message):
            load_config(tmp_path / "b.toml")
    # the example of docs/configuration.md, on a hexahedral reference in mm
    import re
    import tomllib

    from docblocks import page_text

    example = next(b for b in re.findall(r"```toml\n(.*?)```", page_text("configuration.md"), flags=re.S) if "febio_result.vtu" in b)
    P, hexes = _hex_grid((10.0, 10.0, 5.0), (4, 4, 2), perturb=0.2)
    meshio.write(tmp_path / "febio_result.vtu", meshio.Mesh(P, [("hexahedron", hexes)], point_data={"displacement": _uniaxial(P)[0]}))
    head = '[material]\nyoungs_modulus = 8e3\npoisson_ratio = 0.3\n[fit]\nparameters = ["youngs_modulus"]\n'
    (tmp_path / "doc.toml").write_text(head + example)
    assert tomllib.loads(head + example)["experiment"][0]["model"] == "springs_volume"
    sc = load_config(tmp_path / "doc.toml").experiments[0].scenario
    sc = getattr(sc, "scenario", sc)
    assert sc.reference_mesh == "interpolate" and sc.model.rest_points.shape == (9 * 9 * 5, 3)


def test_the_code_blocks_of_scenarios_md_run():
    """Every python block of docs/scenarios.md (the indentation example and the interpolated
    reference, whose block asserts its own misfit) runs."""
    from docblocks import exec_blocks, python_blocks

    blocks = python_blocks("scenarios.md")
    assert any("FEMField" in b and "specimen=" in b for b in blocks)
    exec_blocks("scenarios.md", blocks)
