"""Geometry a real study needs: roller (symmetry) supports and graded meshes.

Rollers are checked against exact answers: a quarter model with rollers on its two symmetry
planes reproduces the mirrored whole specimen (force x 4 and displacements), a block on
rollers in frictionless compression is in homogeneous uniaxial stress, between four roller
walls in confined compression (P-wave modulus); the gradient of the platen stress through a
roller problem matches central differences. Graded layers: node positions, volumes and
validation. The configuration keys are parsed and refused key by key.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import errors
from difftissue.boundary import BoundaryConditions, Roller, apply_rollers, pin_free_rigid_modes, rigid_mode_rank
from difftissue.config import parse_config
from difftissue.incision import incision_boundary
from difftissue.materials import Material
from difftissue.mesh import TetMesh, block, layer_node_heights, layered_skin
from difftissue.scenarios import Compression, Indentation, indentation_block

MAT = Material(1.0e4, 0.4)


# ------------------------------------------------------------------ roller supports
def test_roller_forms_and_refusals():
    mesh = block((2e-3, 2e-3, 1e-3), (2, 2, 1))
    assert Roller.from_spec("x-max") == Roller("x-max", "x")
    assert Roller.from_spec({"set": {"box": {"lower": [0, 0, 0], "upper": [1e-3, 2e-3, 0]}}, "components": "yx"}).components == "xy"
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}, "z")
    bc = apply_rollers(bc, mesh, ["x-min", {"set": {"face": "y-max"}, "components": "y"}])
    p = np.asarray(mesh.points)
    np.testing.assert_array_equal(bc.fixed[:, 0], np.isclose(p[:, 0], 0.0))
    np.testing.assert_array_equal(bc.fixed[:, 1], np.isclose(p[:, 1], 2e-3))
    assert np.all(np.asarray(bc.displacement) == 0.0) and rigid_mode_rank(p, bc.fixed) == 6
    for spec, match in (("top", "face of the bounding box"), ({"set": {"face": "x-min"}}, "needs components"),
                        ({"set": {"face": "x-min"}, "components": "xyz"}, "clamp"), ({"set": {"face": "x-min"}, "components": "w"}, "letters"),
                        ({"set": {"ball": {"center": [1, 1, 1], "radius": 1e-4}}, "components": "x"}, "selects no node"),
                        ({"set": "symmetry", "components": "x"}, "not a point-data node set"), ("x-min", "no effect")):
        with pytest.raises(errors.BoundaryConditionError, match=match):
            apply_rollers(bc, mesh, [spec])
    loaded = np.zeros((mesh.n_nodes, 3), dtype=bool)
    loaded[np.isclose(p[:, 2], 1e-3), 2] = True
    with pytest.raises(errors.BoundaryConditionError, match="where the load is applied"):
        apply_rollers(BoundaryConditions.free(mesh), mesh, ["z-max"], loaded=loaded)
    with pytest.raises(errors.BoundaryConditionError, match="must be a list"):
        apply_rollers(bc, mesh, "x-min")
    # a mask of the mesh's own point data selects too
    masked = TetMesh(mesh.points, mesh.tets, point_data={"plane": np.isclose(p[:, 0], 2e-3).astype(float)})
    assert apply_rollers(BoundaryConditions.free(masked), masked, [{"set": "plane", "components": "x"}]).fixed[:, 0].sum() == 6


def test_pins_only_for_the_rigid_modes_the_rollers_leave():
    mesh = block((2e-3, 2e-3, 1e-3), (2, 2, 1))
    sliding = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}, "z")
    cand = [(0, "x"), (0, "y"), (2, "y")]
    assert pin_free_rigid_modes(mesh, sliding, cand).fixed.sum() - sliding.fixed.sum() == 3
    one = apply_rollers(sliding, mesh, ["x-max"])  # translation y is left
    pinned = pin_free_rigid_modes(mesh, one, cand)
    assert pinned.fixed.sum() - one.fixed.sum() == 1 and pinned.fixed[0, 1]
    both = apply_rollers(one, mesh, ["y-min"])
    assert pin_free_rigid_modes(mesh, both, cand).fixed.sum() == both.fixed.sum()


def _mirror(mesh: TetMesh, axis: int) -> TetMesh:
    """``mesh`` and its mirror image in the plane ``x_axis = 0`` (nodes on the plane shared)."""
    p = np.asarray(mesh.points)
    on = np.abs(p[:, axis]) <= 1e-12
    new = np.flatnonzero(~on)
    index = np.arange(len(p))
    index[new] = len(p) + np.arange(len(new))
    q = p[new].copy()
    q[:, axis] *= -1
    tets = np.concatenate([mesh.tets, index[mesh.tets][:, [0, 1, 3, 2]]])
    return TetMesh(np.concatenate([p, q]), tets, np.concatenate([mesh.region_ids] * 2), mesh.region_names)


def _with_lattice_of(mesh: TetMesh, grid: TetMesh) -> TetMesh:
    """``mesh`` carrying the cube lattice of ``grid`` (the same nodes in another order)."""
    key = {tuple(np.round(x / 1e-9).astype(int)): i for i, x in enumerate(np.asarray(mesh.points))}
    to_mesh = np.array([key[tuple(np.round(x / 1e-9).astype(int))] for x in np.asarray(grid.points)])
    lat = grid.lattice
    lat = eqx.tree_at(lambda l: (l.cubes, l.springs), lat, (to_mesh[lat.cubes].astype(np.int32), to_mesh[lat.springs].astype(np.int32)))
    return TetMesh(mesh.points, mesh.tets, mesh.region_ids, mesh.region_names, lattice=lat)


@pytest.mark.parametrize("model", ["fem_linear", "springs_volume"])
def test_quarter_model_on_rollers_reproduces_the_mirrored_whole(model):
    """Sphere indentation of a quarter (rollers u_x = 0 on x = 0, u_y = 0 on y = 0) against the
    whole specimen made of the quarter and its three mirror images: the same tets, so force x 4
    and every displacement agree to the solver's tolerance. (Before the contact penalty of the
    nodes on the planes was shared with their mirror images, quarter x 4 was 0.8 % stiffer.)"""
    quarter = indentation_block((4e-3, 4e-3, 2e-3), (4, 4, 4), symmetry="quarter")
    whole = _mirror(_mirror(quarter, 0), 1)
    if model == "springs_volume":
        whole = _with_lattice_of(whole, indentation_block((4e-3, 4e-3, 2e-3), (8, 8, 4), symmetry="none"))
    depths = [5e-5, 1e-4]
    kw = dict(model=model, indenter="sphere", radius=1e-3, solver="full")
    fq, uq = Indentation(quarter, depths, symmetry="quarter", **kw).solve(MAT)
    fw, uw = Indentation(whole, depths, symmetry="none", axis_xy=(0.0, 0.0), **kw).solve(MAT)
    np.testing.assert_allclose(np.asarray(fq), np.asarray(fw), rtol=1e-8)
    assert float(fq[-1]) > 0
    n = quarter.n_nodes  # the whole mesh's first nodes are the quarter's
    np.testing.assert_allclose(np.asarray(uw)[:, :n], np.asarray(uq), rtol=0, atol=1e-8 * float(np.abs(uq).max()))
    # the roller planes: u_x = 0 on x = 0 and u_y = 0 on y = 0 hold in the whole model by symmetry
    p = np.asarray(whole.points)
    assert float(np.abs(np.asarray(uw)[-1, np.abs(p[:, 0]) < 1e-12, 0]).max()) < 1e-8 * float(np.abs(uq).max())


def test_indentation_rollers_as_walls():
    """Side rollers on a sliding base: no pin is added (the rollers hold every in-plane rigid
    mode), the walls' normal displacement is zero and a roller on the contact surface or where
    the quarter symmetry already holds is refused."""
    mesh = indentation_block((4e-3, 4e-3, 2e-3), (4, 4, 2), symmetry="none")
    walls = ["x-min", "x-max", "y-min", "y-max"]
    sc = Indentation(mesh, [5e-5], model="fem_linear", indenter="sphere", radius=1e-3, base="sliding", rollers=walls)
    plain = Indentation(mesh, [5e-5], model="fem_linear", indenter="sphere", radius=1e-3, base="sliding")
    p = np.asarray(mesh.points)
    side = np.isclose(np.abs(p[:, 0]), 2e-3) | np.isclose(np.abs(p[:, 1]), 2e-3)
    bottom = np.isclose(p[:, 2], 0.0)
    assert not np.any(sc.bc.fixed[bottom & ~side, :2])  # no pin
    assert plain.bc.fixed[:, :2].sum() == 3  # the three pins of the unconfined sliding base
    assert float(sc.predict(MAT)[0]) > float(plain.predict(MAT)[0]) > 0  # the walls stiffen it
    with pytest.raises(errors.BoundaryConditionError, match="where the load is applied"):
        Indentation(mesh, [5e-5], model="fem_linear", indenter="sphere", radius=1e-3, rollers=["z-max"])
    q = indentation_block((4e-3, 4e-3, 2e-3), (2, 2, 2), symmetry="quarter")
    with pytest.raises(errors.BoundaryConditionError, match="no effect"):
        Indentation(q, [5e-5], model="fem_linear", indenter="sphere", radius=1e-3, symmetry="quarter", rollers=["x-min"])


def test_compression_on_rollers_is_exact_uniaxial_stress():
    """A block on rollers x = 0, y = 0 between frictionless platens: the homogeneous uniaxial
    stress state, sigma = E eps, u_z = -eps z, u_x = nu eps x, u_y = nu eps y (eps > 0 in
    compression; fem_linear, exact for linear
    tets), with no in-plane pin (the rollers hold every rigid mode)."""
    size = (2e-3, 3e-3, 4e-3)
    mesh = block(size, (2, 3, 2))
    eps = np.array([0.005, 0.01])
    sc = Compression(mesh, eps, model="fem_linear", rollers=["x-min", "y-min"])
    p = np.asarray(mesh.points)
    expected = np.isclose(p[:, 2], 0.0)[:, None] * [0, 0, 1] | np.isclose(p[:, 2], size[2])[:, None] * [0, 0, 1]
    expected = expected.astype(bool) | np.isclose(p[:, 0], 0.0)[:, None] * np.array([True, False, False]) | np.isclose(p[:, 1], 0.0)[:, None] * np.array([False, True, False])
    np.testing.assert_array_equal(sc.bc.fixed, expected)
    stress, u = sc.solve(MAT)
    np.testing.assert_allclose(np.asarray(stress), MAT.youngs_modulus * eps, rtol=1e-10)
    for k, e in enumerate(eps):
        np.testing.assert_allclose(np.asarray(u[k]), np.stack([0.4 * e * p[:, 0], 0.4 * e * p[:, 1], -e * p[:, 2]], axis=1), rtol=0, atol=1e-12 * size[2])
    # confined between four roller walls: the P-wave modulus, no lateral displacement
    confined = Compression(mesh, eps, model="fem_linear", rollers=["x-min", "x-max", "y-min", "y-max"])
    s, u = confined.solve(MAT)
    nu = 0.4
    M = MAT.youngs_modulus * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    np.testing.assert_allclose(np.asarray(s), M * eps, rtol=1e-10)
    assert float(jnp.abs(u[..., :2]).max()) < 1e-12 * size[2]
    # a single roller plane: only translation y is pinned, at one node (it carries no force)
    half = Compression(mesh, eps, model="fem_linear", rollers=["x-min"])
    assert half.bc.fixed[:, 1].sum() == 1
    np.testing.assert_allclose(np.asarray(half.predict(MAT)), MAT.youngs_modulus * eps, rtol=1e-10)
    with pytest.raises(errors.BoundaryConditionError, match="where the load is applied"):
        Compression(mesh, eps, model="fem_linear", rollers=["z-max"])
    with pytest.raises(errors.BoundaryConditionError, match="no effect"):
        Compression(mesh, eps, model="fem_linear", rollers=["z-min"])


def test_platens_with_one_symmetry_plane_pin_only_translation_y():
    """Platens.apply(symmetry_planes=("x",)) once pinned u_x of a node off the plane (a force
    in the homogeneous solution); now only u_y."""
    from difftissue.contact import Platens
    from difftissue.models import make_model
    from difftissue.solvers.static import solve_static

    mesh = block((2e-3, 2e-3, 2e-3), 2)
    bc = Platens().apply(mesh, apply_rollers(BoundaryConditions.free(mesh), mesh, ["x-min"]), 2e-5, symmetry_planes=("x",))
    assert bc.fixed[:, 1].sum() == 1
    sol = solve_static(make_model(mesh, "fem_linear"), MAT, bc)
    top = np.isclose(np.asarray(mesh.points)[:, 2], 2e-3)
    assert float(-jnp.sum(sol.reaction[top, 2])) / 4e-6 == pytest.approx(MAT.youngs_modulus * 0.01, rel=1e-10)


def test_stress_gradient_through_a_roller_problem():
    """d(platen stress)/d(E, nu) of confined compression (four roller walls) at 5 % strain with
    stable neo-Hookean: implicit forward and reverse mode against central differences (float64)."""
    mesh = block((2e-3, 2e-3, 2e-3), 2)
    sc = Compression(mesh, [0.05], model="stable_neo_hookean", rollers=["x-min", "x-max", "y-min", "y-max"])

    def output(v):
        return sc.predict(Material(v[0], v[1]))[0]

    # One compiled program gives the value (reverse mode's primal), the reverse-mode gradient
    # and the forward-mode Jacobian; the four difference evaluations reuse it.
    @jax.jit
    def value_reverse_forward(v):
        value, g = jax.value_and_grad(output)(v)
        return value, g, jax.jacfwd(output)(v)

    def stress(v):
        return value_reverse_forward(v)[0]

    v0 = jnp.array([1.0e4, 0.4])
    _, rev, fwd = (np.asarray(a) for a in value_reverse_forward(v0))
    for i, h in enumerate((1e-2, 1e-6)):
        e = jnp.zeros(2).at[i].set(h)
        fd = float((stress(v0 + e) - stress(v0 - e)) / (2 * h))
        assert rev[i] == pytest.approx(fd, rel=1e-5), (i, rev[i], fd)
        assert fwd[i] == pytest.approx(rev[i], rel=1e-9)
    assert abs(rev[1]) > 1e3  # nu matters in confined compression


def test_incision_lateral_roller_and_symmetry_plane():
    mesh = block((4e-3, 4e-3, 1e-3), (4, 4, 1))
    p = np.asarray(mesh.points)
    xface = np.isclose(p[:, 0], 0.0) | np.isclose(p[:, 0], 4e-3)
    yface = np.isclose(p[:, 1], 0.0) | np.isclose(p[:, 1], 4e-3)
    base = np.isclose(p[:, 2], 0.0)
    bc = incision_boundary(mesh, lateral="roller", base="sliding")
    np.testing.assert_array_equal(bc.fixed, np.stack([xface, yface, base], axis=1))
    # held sides, but x = 0 a symmetry plane: only u_x held there (corners keep the y faces' hold)
    bc = incision_boundary(mesh, lateral="held", rollers=["x-min"])
    x0 = np.isclose(p[:, 0], 0.0)
    held = np.isclose(p[:, 0], 4e-3) | yface
    np.testing.assert_array_equal(bc.fixed[:, 0], x0 | held | base)
    np.testing.assert_array_equal(bc.fixed[:, 1], held | base)
    with pytest.raises(errors.ConfigError, match="rigid"):
        incision_boundary(mesh, lateral="free", base="sliding")
    assert rigid_mode_rank(p, incision_boundary(mesh, lateral="free", base="sliding", rollers=["x-min", "y-min"]).fixed) == 6
    with pytest.raises(errors.ConfigError, match="lateral"):
        incision_boundary(mesh, lateral="slide")


# --------------------------------------------------------------------- graded layers
def test_layer_grading_positions_volumes_and_refusals():
    z = layer_node_heights(1e-3, 4, 2.0)
    np.testing.assert_allclose(np.diff(z)[::-1], 1e-3 * np.array([1, 2, 4, 8]) / 15, rtol=1e-14)  # top cell first
    assert z[0] == 0.0 and z[-1] == 1e-3
    np.testing.assert_array_equal(layer_node_heights(1e-3, 4, 1.0), 1e-3 * np.arange(5) / 4)
    layers = [("dermis", 2e-3, Material(1e5, 0.4), 4), ("fat", 3e-3, Material(1e4, 0.45), 3)]
    skin = layered_skin(layers, size=(4e-3, 6e-3), resolution=(2, 3), grading={"dermis": 1.5, "fat": 0.5})
    zs = np.unique(np.asarray(skin.mesh.points)[:, 2])
    h = np.diff(zs)[::-1]  # from the surface down
    np.testing.assert_allclose(h[1:4] / h[:3], 1.5, rtol=1e-12)
    np.testing.assert_allclose(h[5:] / h[4:6], 0.5, rtol=1e-12)
    np.testing.assert_allclose([h[:4].sum(), h[4:].sum()], [2e-3, 3e-3], rtol=1e-14)
    assert float(skin.mesh.volumes().sum()) == pytest.approx(4e-3 * 6e-3 * 5e-3, rel=1e-14)
    rv = skin.mesh.region_volumes()
    assert rv["dermis"] == pytest.approx(4e-3 * 6e-3 * 2e-3, rel=1e-14) and rv["fat"] == pytest.approx(4e-3 * 6e-3 * 3e-3, rel=1e-14)
    assert np.all(skin.mesh.volumes() > 0)
    for grading, match in (({"dermis": 0.0}, "positive finite"), ({"dermis": float("inf")}, "positive finite"), ({"dermis": "a"}, "positive number"),
                           ({"skin": 1.2}, "layers are"), ([1.2], "mapping")):
        with pytest.raises(errors.MeshError, match=match):
            layered_skin(layers, size=(4e-3, 6e-3), resolution=(2, 3), grading=grading)
    with pytest.raises(errors.MeshError, match="at least two cells"):
        layered_skin([("dermis", 2e-3, Material(1e5, 0.4), 1)], size=(4e-3, 4e-3), resolution=(2, 2), grading={"dermis": 1.3})
    with pytest.raises(errors.MeshError, match="grading ratio"):
        layer_node_heights(1e-3, 3, -1.0)


def test_graded_axis_with_one_cell_beyond_the_core():
    """One cell beyond a uniform core spans the rest (it used to fail in brentq, which made a
    coarsened graded indentation block unbuildable)."""
    from difftissue.scenarios import graded_axis

    np.testing.assert_array_equal(graded_axis(1.6e-3, 1, 2e-4), [0.0, 1.6e-3])
    np.testing.assert_allclose(graded_axis(2e-3, 2, 4e-4, core=4e-4), [0.0, 4e-4, 2e-3], rtol=1e-15)


@pytest.mark.parametrize("model", ["fem_linear", "stable_neo_hookean"])
def test_half_incision_on_a_symmetry_roller_reproduces_the_whole(model):
    """A cut across a pre-tensioned graded skin, modelled whole and as the half x >= 0 with a
    roller (u_x = 0) on the plane through the middle of the cut, normal to it: the same tets
    mirrored, so the surface widths agree to the solver's tolerance."""
    from difftissue.cutting import ScalpelPath, cut_specimen
    from difftissue.incision import Incision
    from difftissue.mesh import Specimen

    mm = 1e-3
    layers = [("dermis", 2 * mm, Material(2e5, 0.45, pre_stretch=1.05), 2), ("fat", 2 * mm, Material(5e3, 0.45), 2)]
    half = layered_skin(layers, size=(4 * mm, 6 * mm), resolution=(4, 6), grading={"dermis": 1.5})
    whole = Specimen(_mirror(half.mesh, 0), half.materials)
    cut_half = cut_specimen(half, ScalpelPath([[0, 3 * mm], [2 * mm, 3 * mm]], depth=1 * mm))
    cut_whole = cut_specimen(whole, ScalpelPath([[-2 * mm, 3 * mm], [2 * mm, 3 * mm]], depth=1 * mm))
    kw = dict(model=model, quantity="surface_width", fitted_regions=("dermis",))
    s = np.array([0.0, 0.5, 1.0, 1.5]) * mm
    w_half = np.asarray(Incision(cut_half, positions=s, rollers=["x-min"], **kw).predict(layers[0][2]))
    w_whole = np.asarray(Incision(cut_whole, positions=s + 2 * mm, **kw).predict(layers[0][2]))
    assert w_half.min() > 1e-5  # it opens
    np.testing.assert_allclose(w_half, w_whole, rtol=1e-8)


# ----------------------------------------------------------------------- the config
def _toml_blocks(marker: str) -> str:
    import re

    from docblocks import page_text

    return next(b for b in re.findall(r"```toml\n(.*?)```", page_text("configuration.md"), flags=re.S) if marker in b)


_HEAD = '[material]\nyoungs_modulus = 2e4\npoisson_ratio = 0.45\npre_stretch = 1.05\n[fit]\nparameters = ["youngs_modulus"]\n'


@pytest.fixture(scope="module")
def curve_dir(tmp_path_factory):
    from difftissue import analytic

    d = np.linspace(5e-6, 60e-6, 6)
    f = np.asarray(analytic.hertz_force(d, 2e4, 0.45, 1e-3))
    path = tmp_path_factory.mktemp("curve") / "curve.csv"
    path.write_text("depth (um),force (uN)\n" + "\n".join(f"{a * 1e6:.6f},{b * 1e6:.8f}" for a, b in zip(d, f)) + "\n")
    return path.parent


def test_the_graded_indentation_example_of_configuration_md_runs(curve_dir):
    from difftissue.config import load_config
    from difftissue.scenarios import graded_axis

    (curve_dir / "sphere.toml").write_text(_HEAD + _toml_blocks('rollers = ["x-max", "y-max"]'))
    cfg = load_config(curve_dir / "sphere.toml")
    exp = cfg.experiments[0]
    sc = getattr(exp.scenario, "scenario", exp.scenario)
    p = np.asarray(sc.model.rest_points)
    xs = np.unique(p[:, 0])
    np.testing.assert_allclose(xs, graded_axis(2e-3, 8, 1e-4, core=4e-4), rtol=1e-12)
    np.testing.assert_allclose(np.diff(xs)[:4], 1e-4, rtol=1e-9)  # the uniform core
    zs = np.unique(p[:, 2])
    np.testing.assert_allclose(np.diff(zs)[-4:], 1e-4, rtol=1e-9)  # under the surface
    walls = np.isclose(p[:, 0], 2e-3)
    inside = walls & (p[:, 1] > 1e-9) & (p[:, 1] < 2e-3 - 1e-9) & (p[:, 2] > 1e-9)  # off the other planes and the base
    assert np.all(sc.bc.fixed[walls, 0]) and inside.sum() == 7 * 8 and not np.any(sc.bc.fixed[inside, 1:])
    f = np.asarray(exp.scenario.predict(Material(2e4, 0.45)))
    assert np.all(np.isfinite(f)) and np.all(np.diff(f) > 0)
    coarse, info = exp.coarsen()
    assert info["coarse_cells"] == [4, 4, 4]
    np.testing.assert_allclose(np.unique(np.asarray(getattr(coarse, "scenario", coarse).model.rest_points)[:, 0])[:3], [0, 2e-4, 4e-4], atol=1e-15)


def test_the_half_incision_example_of_configuration_md_runs(tmp_path):
    from difftissue.config import load_config

    (tmp_path / "cut.toml").write_text(_HEAD.replace('"youngs_modulus"]', '"pre_stretch"]') + _toml_blocks('name = "half_cut"'))
    sc = load_config(tmp_path / "cut.toml").experiments[0].scenario
    p = np.asarray(sc.cut.mesh.points)
    x0 = np.isclose(p[:, 0], 0.0) & (p[:, 1] > 1e-3) & (p[:, 1] < 7e-3) & (p[:, 2] > 0)
    assert np.all(sc.bc.fixed[x0, 0]) and not np.any(sc.bc.fixed[x0, 1:])
    column = np.isclose(p[:, 0], 8e-3) & np.isclose(p[:, 1], 0.0)  # far from the cut (snapping moves nodes near it)
    np.testing.assert_allclose(np.unique(p[:, 0])[:8], np.arange(8) * 5e-4, rtol=1e-12, atol=1e-15)  # 0.5 mm cells to x = 3.5 mm
    heights = np.diff(np.sort(p[column, 2]))[::-1]  # from the surface down
    np.testing.assert_allclose(heights[1:4] / heights[:3], 1.5, rtol=1e-9)
    np.testing.assert_allclose(heights[:4].sum(), 2e-3, rtol=1e-12)
    w = np.asarray(sc.predict(Material(2e4, 0.45, pre_stretch=1.05)))
    assert w.shape == (1,) and w[0] > 0


def _indentation(curve_dir, **change):
    e = {"name": "s", "scenario": "indentation", "model": "fem_linear", "length_unit": "um",
         "data": {"format": "table", "path": "curve.csv", "columns": {"depth": "depth (um)", "force": "force (uN)"}},
         "indenter": {"shape": "sphere", "radius": 1.0, "length_unit": "mm"},
         "specimen": {"size": [4, 4, 2], "cells": [4, 4, 4], "refine": 0.2, "core": 0.4, "length_unit": "mm"}}
    e.update(change)
    return {"material": {"youngs_modulus": 2e4, "poisson_ratio": 0.45}, "fit": {"parameters": ["youngs_modulus"]}, "experiment": [e]}


@pytest.mark.parametrize("change, match", [
    ({"rollers": "x-max"}, r"^experiment\[0\]\.rollers: must be a list"),
    ({"rollers": ["top"]}, r"^experiment\[0\]\.rollers\[0\]: must be one of 'x-min'"),
    ({"rollers": [{"set": {"face": "x-max"}}]}, r"^experiment\[0\]\.rollers\[0\]\.components: missing"),
    ({"rollers": [{"set": {"face": "x-max"}, "components": "xyz"}]}, r"^experiment\[0\]\.rollers\[0\]\.components: a roller holding x, y and z"),
    ({"rollers": [{"set": {"face": "x-max"}, "components": "q"}]}, r"^experiment\[0\]\.rollers\[0\]\.components: must be letters"),
    ({"rollers": [{"set": {"cube": 1}, "components": "x"}]}, r"^experiment\[0\]\.rollers\[0\]\.set: "),
    ({"rollers": [{"face": "x-max"}]}, r"^experiment\[0\]\.rollers\[0\]: unknown key 'face'"),
    ({"rollers": ["x-min"]}, r"^experiment\[0\]: rollers\[0\]: the roller on face x-min has no effect"),
    ({"rollers": ["z-max"]}, r"^experiment\[0\]: rollers\[0\]: .*where the load is applied"),
    ({"specimen": {"size": [4, 4, 2], "cells": 4, "core": 0.4, "length_unit": "mm"}}, r"^experiment\[0\]\.specimen\.core: needs refine"),
    ({"specimen": {"size": [4, 4, 2], "cells": 4, "refine": 0.2, "core": 2, "length_unit": "mm"}}, r"^experiment\[0\]\.specimen\.core: must be smaller"),
    ({"specimen": {"size": [4, 4, 2], "cells": 4, "refine": 0.2, "core": 0.1, "length_unit": "mm"}}, r"^experiment\[0\]\.specimen\.core: must be at least one cell"),
    ({"specimen": {"size": [4, 4, 2], "cells": 4, "refine": 0.2, "core": -1, "length_unit": "mm"}}, r"^experiment\[0\]\.specimen\.core: must be a positive length"),
    ({"specimen": {"size": [4, 4, 2], "cells": 4, "refine": 0.1, "core": 0.5, "length_unit": "mm"}}, r"^experiment\[0\]\.specimen: a uniform core .* needs 5 cells"),
])
def test_indentation_config_errors_name_the_key(curve_dir, change, match):
    with pytest.raises(errors.DifftissueError, match=match):
        parse_config(_indentation(curve_dir, **change), base_dir=curve_dir)


def test_compression_config_rollers():
    from pathlib import Path

    data = str(Path(__file__).resolve().parents[1] / "data/compression/EF10_50T_A1.csv")
    e = {"name": "c", "scenario": "compression", "model": "fem_linear", "data": {"format": "instron", "path": data}, "max_strain": 0.1, "points": 4,
         "specimen": {"size": [10, 10, 10], "cells": [1, 1, 1], "length_unit": "mm"}, "rollers": ["x-min", "x-max", "y-min", "y-max"]}
    cfg = parse_config({"material": {"youngs_modulus": 2e4, "poisson_ratio": 0.45}, "fit": {"parameters": ["youngs_modulus"]}, "experiment": [e]})
    sc = getattr(cfg.experiments[0].scenario, "scenario", cfg.experiments[0].scenario)
    assert sc.bc.fixed[:, :2].all()  # every node of the one-cell block is on two walls
    e["rollers"] = ["z-min"]
    with pytest.raises(errors.DifftissueError, match=r"^experiment\[0\]: rollers\[0\]: the roller on face z-min has no effect"):
        parse_config({"material": {"youngs_modulus": 2e4, "poisson_ratio": 0.45}, "fit": {"parameters": ["youngs_modulus"]}, "experiment": [e]})


def _incision(**change):
    e = {"name": "wound", "scenario": "incision", "length_unit": "mm", "data": {"quantity": "max_width", "value": 0.3},
         "specimen": {"size": [8, 8], "cells": [8, 8], "layers": [{"name": "dermis", "thickness": 1, "cells": 2, "fitted": True},
                                                                 {"name": "fat", "thickness": 2, "cells": 2, "youngs_modulus": 5e3, "poisson_ratio": 0.45}]},
         "cut": {"path": [[2, 4], [6, 4]], "depth": 1}}
    for k, v in change.items():
        if k == "dermis":
            e["specimen"]["layers"][0].update(v)
        else:
            e[k] = v
    return {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": 1.05}, "fit": {"parameters": ["pre_stretch"]}, "experiment": [e]}


def test_incision_config_boundary_and_grading():
    sc = parse_config(_incision(boundary={"lateral": "roller", "base": "sliding"}, dermis={"grading": 2.0})).experiments[0].scenario
    p = np.asarray(sc.cut.mesh.points)
    xface = np.isclose(p[:, 0], 0.0) | np.isclose(p[:, 0], 8e-3)
    assert np.all(sc.bc.fixed[xface, 0]) and not np.any(sc.bc.fixed[xface & ~np.isclose(p[:, 1], 0.0) & ~np.isclose(p[:, 1], 8e-3), 1])
    np.testing.assert_allclose(np.unique(p[:, 2])[-3:], [2e-3, 2e-3 + 2e-3 / 3, 3e-3], rtol=1e-12)  # dermis cells 1/3, 2/3 mm from the top
    for change, match in (({"boundary": {"lateral": "sliding"}}, r"^experiment\[0\]\.boundary\.lateral: must be one of 'held', 'roller', 'free'"),
                          ({"boundary": {"rollers": ["x-min"], "lateral": "held", "walls": 1}}, r"^experiment\[0\]\.boundary: unknown key 'walls'"),
                          ({"boundary": {"rollers": [{"set": {"face": "x-min"}, "components": "x"}]}}, r"^experiment\[0\]: rollers\[0\]: .*no effect"),
                          ({"boundary": {"lateral": "free", "base": "sliding", "rollers": ["x-min"]}}, r"^experiment\[0\]: .*rigid motion free"),
                          ({"dermis": {"grading": 0}}, r"^experiment\[0\]\.specimen\.layers\[0\]\.grading: must be a positive number"),
                          ({"dermis": {"grading": 1.5, "cells": 1}}, r"^experiment\[0\]\.specimen\.layers\[0\]\.grading: needs at least two cells")):
        with pytest.raises(errors.DifftissueError, match=match):
            parse_config(_incision(**change))


def test_lateral_refinement_of_a_layered_skin():
    from difftissue.mesh import refined_axis

    x = refined_axis(8e-3, 8, 4e-3, 2e-4, core=6e-4)
    np.testing.assert_allclose(x, [0, 3.4e-3, 3.6e-3, 3.8e-3, 4e-3, 4.2e-3, 4.4e-3, 4.6e-3, 8e-3], rtol=1e-12, atol=1e-15)
    x = refined_axis(8e-3, 8, 2e-3, 2e-4)  # off-centre: 2 cells left, 6 right, growing geometrically
    h = np.diff(x)
    assert x[0] == 0 and x[-1] == 8e-3 and np.all(h > 0) and h[1] == pytest.approx(2e-4) and h[2] == pytest.approx(2e-4)
    np.testing.assert_allclose(h[3:] / h[2:-1], h[3] / h[2], rtol=1e-9)  # one ratio on the right
    one_sided = refined_axis(8e-3, 8, 0.0, 2e-4)
    np.testing.assert_allclose(refined_axis(8e-3, 8, 8e-3, 2e-4), 8e-3 - one_sided[::-1], rtol=1e-12)
    layers = [("dermis", 2e-3, Material(2e5, 0.45), 2), ("fat", 3e-3, Material(5e3, 0.45), 2)]
    skin = layered_skin(layers, size=(8e-3, 6e-3), resolution=(12, 10), refine=2.5e-4, refine_at=(4e-3, 3e-3), core=(1e-3, 5e-4), grading={"fat": 0.5})
    p = np.asarray(skin.mesh.points)
    xs, ys = np.unique(p[:, 0]), np.unique(p[:, 1])
    assert len(xs) == 13 and len(ys) == 11
    np.testing.assert_allclose(np.diff(xs)[2:10], 2.5e-4, rtol=1e-9)  # 4 core cells each side of x = 4 mm
    np.testing.assert_allclose(np.diff(ys)[3:7], 2.5e-4, rtol=1e-9)
    assert float(skin.mesh.volumes().sum()) == pytest.approx(8e-3 * 6e-3 * 5e-3, rel=1e-14) and np.all(skin.mesh.volumes() > 0)
    for kw, match in ((dict(core=1e-3), "need refine"), (dict(refine=-1.0), "positive lateral cell size"), (dict(refine=2.5e-4, refine_at=(9e-3, 1e-3)), "must lie in"),
                      (dict(refine=2.5e-4, refine_at=(1.0,)), "point"), (dict(refine=2.5e-4, core=0.0), "positive lengths")):
        with pytest.raises(errors.MeshError, match=match):
            layered_skin(layers, size=(8e-3, 6e-3), resolution=(12, 10), **kw)
    with pytest.raises(errors.ModelError, match="needs 8 cells"):
        layered_skin(layers, size=(8e-3, 6e-3), resolution=(12, 10), refine=2.5e-4, core=2e-3)
    for change, match in (({"refine_at": [0, 4]}, r"specimen\.refine_at: needs refine"), ({"refine": 0.5, "refine_at": [9, 4]}, r"specimen\.refine_at: must lie on the top surface"),
                          ({"refine": 0.5, "core": [1, 1, 1]}, r"specimen\.core: must be 2 positive lengths"), ({"refine": 0.5, "core": 3}, r"^experiment\[0\]\.specimen: .*needs 6 cells"),
                          ({"refine": 0.5, "core": 5}, r"^experiment\[0\]\.specimen: core 0.005 m reaches past a side")):
        cfg = _incision()
        cfg["experiment"][0]["specimen"].update(change)
        with pytest.raises(errors.DifftissueError, match=match):
            parse_config(cfg)


def test_incision_config_staircase_cut():
    """``cut.method = "staircase"`` reaches cut_specimen: an oblique cut keeps every lattice cube
    (no node moved: the cut mesh's points are the specimen's plus the duplicated ones), and an
    unknown method is refused with its key."""
    oblique = {"path": [[2, 3], [6, 5]], "depth": 1}
    stair = parse_config(_incision(cut={**oblique, "method": "staircase"})).experiments[0].scenario.cut
    snap = parse_config(_incision(cut=oblique)).experiments[0].scenario.cut
    assert stair.method == "staircase" and snap.method == "snap"
    grid = np.unique(np.round(np.asarray(stair.mesh.points)[:, :2] / 1e-3, 9))
    assert np.allclose(grid, np.round(grid))  # every node still on the 1 mm lattice
    assert not np.allclose(np.unique(np.round(np.asarray(snap.mesh.points)[:, :2] / 1e-3, 9)), np.round(np.unique(np.round(np.asarray(snap.mesh.points)[:, :2] / 1e-3, 9))))
    with pytest.raises(errors.DifftissueError, match=r"^experiment\[0\]\.cut\.method: must be one of 'snap', 'staircase', 'remove'"):
        parse_config(_incision(cut={**oblique, "method": "zigzag"}))
