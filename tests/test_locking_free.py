"""The nodal-averaged FEM models (fem_linear_nodal, fem_neo_hookean_nodal): node patches,
patch test against the standard tets, derivatives against central differences, the solvers'
assembly of the 2-ring coupling, and that they do not lock at nu = 0.499."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue.boundary import BoundaryConditions
from difftissue.energies.fem import nodal_dilatation_energy, nodal_dilatation_hessian, nodal_volume_energy, nodal_volume_hessian
from difftissue.errors import ModelError
from difftissue.materials import Material
from difftissue.mesh import block, layered_skin, node_patches
from difftissue.models import FEMModel, make_model
from difftissue.solvers.multigrid import sparse_layout
from difftissue.solvers.static import _assemble_ell, _dense_hessian, solve_static


@pytest.fixture(scope="module")
def two_layers():
    m = Material(1e4, 0.49)
    return layered_skin([("top", 1e-3, m, 2), ("bottom", 1e-3, m.replace(youngs_modulus=3e4, poisson_ratio=0.45), 1)], size=(3e-3, 2e-3), resolution=(3, 2)).mesh


def test_node_patches_cover_every_node_and_region_once(two_layers):
    mesh = two_layers
    nodes, tet_ids, local, valid, regions = node_patches(mesh.tets, mesh.region_ids)
    pairs = {(int(n), int(r)) for t, r in zip(mesh.tets, mesh.region_ids) for n in t}
    assert sorted(zip(nodes[:, 0].tolist(), regions.tolist())) == sorted(pairs)
    # every real tet of a patch holds the patch's node, is of its region, and the local indices
    # give back its global nodes; every tet appears in exactly four patches
    for p in range(nodes.shape[0]):
        t = tet_ids[p, valid[p]]
        assert np.all(np.any(mesh.tets[t] == nodes[p, 0], axis=1))
        assert np.all(mesh.region_ids[t] == regions[p])
        np.testing.assert_array_equal(nodes[p][local[p, valid[p]]], mesh.tets[t])
    assert np.array_equal(np.bincount(tet_ids[valid], minlength=mesh.n_tets), np.full(mesh.n_tets, 4))


def test_unknown_volumetric_option_is_refused():
    with pytest.raises(ModelError, match="volumetric"):
        FEMModel(block(1.0, 1), "fem_linear", volumetric="patch")
    assert make_model(block(1.0, 1), "fem_neo_hookean_nodal").volumetric == "nodal"
    assert make_model(block(1.0, 1), "fem_neo_hookean").volumetric == "element"


@pytest.mark.parametrize("kind", ["fem_linear", "fem_neo_hookean"])
def test_patch_test_homogeneous_deformation_equals_standard_tets(two_layers, kind, pre_stretch=1.05):
    """An affine displacement: the same energy and nodal forces as the standard tets (to 1e-10
    relative; they are identical functions on affine fields, at any strain), on two layers of
    different materials and pre-stretch; on one material the interior nodes carry no residual
    (the stress is uniform)."""
    mesh = two_layers
    standard, nodal = make_model(mesh, kind), make_model(mesh, kind + "_nodal")
    mat = Material(np.array([1e4, 3e4]), np.array([0.499, 0.45]), pre_stretch=np.array([pre_stretch, 1.0]))
    A = jnp.array([[2.0, 0.5, -1.0], [0.3, -1.5, 0.7], [0.2, 0.4, 1.1]]) * 1e-3
    X = jnp.asarray(mesh.points)
    x = X + (X - X.mean(axis=0)) @ A.T
    # value_and_grad jitted: one program per model instead of the energies' operations
    # compiled one by one (~370 small programs)
    (e_s, g_s), (e_n, g_n) = (jax.jit(jax.value_and_grad(m.energy))(x, mat) for m in (standard, nodal))
    e_s, e_n = float(e_s), float(e_n)
    assert abs(e_n - e_s) <= 1e-10 * abs(e_s)
    scale = float(jnp.abs(g_s).max())
    assert float(jnp.abs(g_n - g_s).max()) <= 1e-10 * scale
    single = block((2e-3, 2e-3, 2e-3), 3)
    m1 = Material(1e4, 0.499, pre_stretch=pre_stretch)
    model = make_model(single, kind + "_nodal")
    Xs = jnp.asarray(single.points)
    xs = Xs + Xs @ A.T
    g = jax.jit(jax.grad(model.energy))(xs, m1)
    Ps = np.asarray(single.points)
    inner = np.all((Ps > 1e-9) & (Ps < 2e-3 - 1e-9), axis=1)
    assert inner.sum() == 8
    assert float(jnp.abs(g[inner]).max()) <= 1e-10 * float(jnp.abs(g).max())


def _patch_args(kind, seed):
    mesh = block((1e-3, 1.2e-3, 0.8e-3), 2)
    model = make_model(mesh, kind + "_nodal")
    mat = Material(2e4, 0.499, pre_stretch=1.03)
    term = model.terms(mat)[1]
    p = 13  # the centre node: a full 24-tet patch
    assert int(np.asarray(model.patch_valid[p]).sum()) == 24
    rng = np.random.default_rng(seed)
    x = jnp.asarray(mesh.points)[term.nodes[p]] * (1.0 + 0.03 * rng.standard_normal((term.nodes.shape[1], 3)))
    return x, [jnp.asarray(a)[p] for a in term.params]


@pytest.mark.parametrize("energy,kind", [(nodal_dilatation_energy, "fem_linear"), (nodal_volume_energy, "fem_neo_hookean")])
def test_nodal_energy_gradient_and_hessian_match_central_differences(energy, kind):
    x, params = _patch_args(kind, 0)
    f = jax.jit(lambda y: energy(y, *params))  # jitted: one program each for f, its gradient, its Hessian
    grad = jax.jit(jax.grad(f))
    g = grad(x)
    Hm = jax.jit(jax.hessian(f))(x).reshape(x.size, x.size)
    h = 1e-9
    rng = np.random.default_rng(1)
    for _ in range(3):
        d = jnp.asarray(rng.standard_normal(x.shape))
        fd = (f(x + h * d) - f(x - h * d)) / (2 * h)
        assert abs(float(fd - jnp.sum(g * d))) <= 1e-6 * float(jnp.linalg.norm(g) * jnp.linalg.norm(d))
        fd_h = (grad(x + h * d) - grad(x - h * d)).reshape(-1) / (2 * h)
        np.testing.assert_allclose(fd_h, Hm @ d.reshape(-1), rtol=0, atol=1e-6 * float(jnp.abs(Hm).max() * jnp.abs(d).max()))


@pytest.mark.parametrize("kind", ["fem_linear", "fem_neo_hookean"])
def test_closed_form_patch_hessian_equals_autodiff(two_layers, kind):
    """The closed-form patch Hessians the solvers use equal ``jax.hessian`` of the patch
    energies to 1e-10 (relative to the largest entry, per patch), on every patch of two layers
    with different materials and anisotropic pre-stretch, at a random finite deformation, and
    the model's term carries them."""
    mesh = two_layers
    model = make_model(mesh, kind + "_nodal")
    mat = Material(np.array([1e4, 3e4]), np.array([0.499, 0.45]), pre_stretch=np.array([1.1, 1.0]), pre_stretch_y=np.array([1.05, 1.0]))
    term = model.terms(mat)[1]
    assert term.hessian is (nodal_dilatation_hessian if kind == "fem_linear" else nodal_volume_hessian)
    rng = np.random.default_rng(3)
    x = jnp.asarray(mesh.points) * (1.0 + 0.05 * rng.standard_normal(mesh.points.shape))
    xe = x[term.nodes]
    P, k = term.nodes.shape
    auto = jax.jit(jax.vmap(jax.hessian(term.energy)))(xe, *term.params).reshape(P, 3 * k, 3 * k)  # jitted: one program each
    closed = jax.jit(jax.vmap(term.hessian))(xe, *term.params)
    scale = jnp.abs(auto).max(axis=(1, 2))
    assert float(scale.min()) > 0
    assert float((jnp.abs(closed - auto).max(axis=(1, 2)) / scale).max()) <= 1e-10


def test_closed_form_volume_hessian_is_zero_for_an_inverted_patch():
    x, params = _patch_args("fem_neo_hookean", 0)
    assert float(jnp.abs(nodal_volume_hessian(x, *params)).max()) > 0
    assert float(jnp.abs(nodal_volume_hessian(x * jnp.array([1.0, 1.0, -1.0]), *params)).max()) == 0.0


@pytest.mark.parametrize("kind", ["fem_linear_nodal", "fem_neo_hookean_nodal"])
def test_implicit_gradient_through_the_closed_form_hessian_matches_finite_differences(kind):
    """The Newton steps and the implicit (tangent / adjoint) solves use the closed-form patch
    Hessian: the derivatives of a reaction and a displacement with respect to E, nu,
    pre-stretch and the prescribed displacement equal central differences (rtol 1e-5), forward
    equals reverse mode, with the sparse solver."""
    mesh = block(1.0, 2)
    model = make_model(mesh, kind)
    top = mesh.points[:, 2] == 1.0
    base_bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "z-max"}, "xy", (0.03, 0.0, 0.0))

    def output(p):
        E, nu, pre, depth = p
        bc = base_bc.fix(mesh, {"face": "z-max"}, "z", (0.0, 0.0, depth))
        sol = solve_static(model, Material(E, nu, pre_stretch=pre), bc, linear_solver="sparse", rtol=1e-12)
        return jnp.sum(sol.reaction[:, 2] * top) + 1e3 * jnp.sum(sol.displacement[:, 0] ** 2)

    # One compiled program gives the value (reverse mode's primal), the reverse-mode gradient
    # (adjoint solve) and the forward-mode Jacobian (tangent solves): the eight difference
    # evaluations reuse it (three separate programs cost ~60 % more compile time; the
    # executions are milliseconds on this 27-node mesh).
    @jax.jit
    def value_reverse_forward(p):
        value, vjp = jax.vjp(output, p)
        return value, vjp(jnp.ones_like(value))[0], jax.jacfwd(output)(p)

    p0 = jnp.array([1.0e3, 0.49, 1.05, -0.05])
    _, reverse, forward = (np.asarray(a) for a in value_reverse_forward(p0))
    for i in range(4):
        h = 1e-6 * abs(float(p0[i]))
        e = jnp.zeros(4).at[i].set(h)
        fd = float((value_reverse_forward(p0 + e)[0] - value_reverse_forward(p0 - e)[0]) / (2 * h))
        assert fd != 0.0
        assert reverse[i] == pytest.approx(fd, rel=1e-5), (i, reverse[i], fd)
        assert forward[i] == pytest.approx(reverse[i], rel=1e-9)


def test_neo_hookean_nodal_energy_is_infinite_for_an_inverted_patch():
    x, params = _patch_args("fem_neo_hookean", 0)
    assert np.isfinite(float(nodal_volume_energy(x, *params)))
    assert float(nodal_volume_energy(x * jnp.array([1.0, 1.0, -1.0]), *params)) == np.inf


def _bonded_block(m, nu, kind):
    W, H = 0.5, 0.25
    mesh = block((W, W, H), (2 * m, 2 * m, m))
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}, "xyz").fix(mesh, {"face": "z-max"}, "xyz", (0.0, 0.0, -0.01 * H))
    bc = bc.fix(mesh, {"face": "x-min"}, "x").fix(mesh, {"face": "y-min"}, "y")
    return mesh, make_model(mesh, kind), bc, np.asarray(mesh.points)[:, 2] > H - 1e-12


def test_sparse_multigrid_and_chunked_assembly_agree_with_dense_for_the_patch_coupling():
    """The node patches couple 2-rings: the block-ELL layout of the multigrid solver (also
    assembled in chunks) equals the dense Hessian, and the dense and sparse (CSR) solves give
    the same reaction."""
    mesh, model, bc, top = _bonded_block(1, 0.49, "fem_neo_hookean_nodal")
    mat = Material(1.0, 0.49)
    x = jnp.asarray(mesh.points) * 1.01
    free = jnp.ones(3 * mesh.n_nodes)
    # the assemblies jitted: one program each instead of ~400 operations compiled one by one
    dense = np.asarray(jax.jit(lambda y: _dense_hessian(model, y, mat))(x))
    layout = sparse_layout([t.nodes for t in model.terms(mat)], mesh.n_nodes)
    for chunk in (None, 7):
        ell = jax.jit(lambda y, chunk=chunk: _assemble_ell(layout, model, y, mat, free, chunk=chunk))(x)  # jitted, as in the solver
        np.testing.assert_allclose(ell.to_scipy().toarray(), dense, rtol=0, atol=1e-12 * np.abs(dense).max())
    sols = {ls: solve_static(model, mat, bc, linear_solver=ls, rtol=1e-11) for ls in ("dense", "sparse")}
    ref = float(jnp.sum(sols["dense"].reaction[top, 2]))
    for s in sols.values():
        assert abs(float(jnp.sum(s.reaction[top, 2])) - ref) <= 1e-8 * abs(ref)


@pytest.fixture(scope="module")
def bonded_moduli():
    """Apparent modulus F / (A eps E) of a bonded block (quarter model, 1 x 1 x 0.25, 4 cells
    through the height) at nu = 0.49 and 0.499, standard and nodal linear tets."""
    out = {}
    for kind in ("fem_linear", "fem_linear_nodal"):
        mesh, model, bc, top = _bonded_block(4, 0.49, kind)
        for nu in (0.49, 0.499):
            sol = solve_static(model, Material(1.0, nu), bc, linear_solver="sparse", rtol=1e-10)
            out[kind, nu] = -float(jnp.sum(sol.reaction[top, 2])) / (0.25 * 0.01)
    return out


@pytest.mark.parametrize("kind,locks", [("fem_linear", True), ("fem_linear_nodal", False)])
def test_bonded_block_does_not_lock_at_nu_0_499(bonded_moduli, kind, locks):
    """From nu = 0.49 to 0.499 (lambda/mu 49 -> 499) the continuum's apparent modulus grows by
    a bounded factor (the incompressible limit is finite); locking tets grow with lambda.
    Measured on this coarse mesh: standard 4.29 -> 15.98 (x 3.7), nodal 3.30 -> 4.04 (x 1.22);
    the mesh-converged ratio (Richardson, experiments/locking_free.py) is 3.51 / 2.97 = 1.18."""
    ratio = bonded_moduli[kind, 0.499] / bonded_moduli[kind, 0.49]
    assert (ratio > 2.5) if locks else (ratio < 1.5)


def _locking_free_experiment():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    import locking_free

    return locking_free


def test_indentation_study_coarsest_level_locks_with_standard_tets_only():
    """Part (c) of experiments/locking_free.py at its coarsest level (2 cells per contact
    radius, nu = 0.499): the automatic quarter specimen, and the force at d/R = 0.1 against
    Hertz. The finite block (half-width = thickness = 6 a) is stiffer than the half-space
    (bonded-layer factor 1.24 at chi = 1/6): measured 1.18 x Hertz for the nodal model, 2.78 x
    for the standard tets (locking)."""
    lf = _locking_free_experiment()
    spec = lf.indentation_specimen(2)
    assert spec.symmetry == "quarter" and spec.cells == (8, 8, 8)
    assert spec.size[0] == pytest.approx(2 * 6 * np.sqrt(1e-3 * 1e-4))
    ratio = {kind: lf.indentation_force(kind, 2, 0.499)[0] / lf.hertz(lf.DEPTHS_C[-1], 0.499) for kind in ("fem_linear", "fem_linear_nodal")}
    assert ratio["fem_linear"] > 2.0
    assert 1.0 < ratio["fem_linear_nodal"] < 1.35


def test_indentation_study_merges_single_level_runs(tmp_path):
    """Single-level result files (one process per level) join into one row per model and nu,
    in level order, with the observed order and Richardson value of the joined values."""
    import json

    lf = _locking_free_experiment()
    files = []
    for m, v in ((8, 1.125), (2, 2.0), (4, 1.25)):
        f = tmp_path / f"c_{m}.json"
        f.write_text(json.dumps({"sphere_indentation": {"observable": "force", "levels": "cells per contact radius", "rows": [
            {"model": "fem_linear_nodal", "poisson_ratio": 0.499, "levels": [m], "values": [v], "cpu_seconds": 1.0,
             "curves": [{"depths": [1.0], "forces": [v]}]}]}}))
        files.append(f)
    lf.merge(tmp_path / "c.json", files)
    (row,) = json.loads((tmp_path / "c.json").read_text())["sphere_indentation"]["rows"]
    assert row["levels"] == [2, 4, 8] and row["values"] == [2.0, 1.25, 1.125]
    assert row["observed_order"] == pytest.approx(np.log2(0.75 / 0.125))
    assert row["richardson"] == pytest.approx(1.125 - 0.125 / (2 ** row["observed_order"] - 1))
    assert [c["forces"][0] for c in row["curves"]] == [2.0, 1.25, 1.125]
