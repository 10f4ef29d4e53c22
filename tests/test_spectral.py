"""The spectral linear solver of the condensation (difftissue.solvers.spectral): one generalised
eigendecomposition per mesh gives the condensed compliance of every material, equal to the
Cholesky path, with exact derivatives, and refuses what it cannot do."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import errors
from difftissue.boundary import BoundaryConditions
from difftissue.contact import top_surface_nodes
from difftissue.materials import Material
from difftissue.mesh import TetMesh
from difftissue.models import make_model
from difftissue.scenarios import Indentation, SolverOptions, indentation_block
from difftissue.solvers import spectral
from difftissue.solvers.condensed import linear_response_columns
from difftissue.solvers.spectral import spectral_decomposition

DEPTHS = np.linspace(0.02, 0.2, 5) * 1e-3
SPHERE = dict(model="fem_linear", indenter="sphere", radius=1e-3, symmetry="quarter")


@pytest.fixture(scope="module")
def quarter():
    return indentation_block((4e-3, 4e-3, 1.6e-3), (6, 6, 5), symmetry="quarter")


def _body(mesh, model="fem_linear"):
    m = make_model(mesh, model)
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, {"face": "x-min"}, "x").fix(mesh, {"face": "y-min"}, "y")
    free = np.asarray(bc.free_mask)
    top = top_surface_nodes(mesh)[[0, 4, 9, 17]]
    dofs = (3 * top[:, None] + np.arange(3)).reshape(-1)
    return m, free, dofs[free.reshape(-1)[dofs]]


@pytest.mark.parametrize("model", ["fem_linear", "fem_linear_nodal"])
def test_spectral_columns_equal_the_cholesky_path(quarter, model):
    body, free, dofs = _body(quarter, model)
    dec = spectral_decomposition(body, free)
    assert dec.vectors.shape == (3 * body.n_nodes, int(free.sum())) and np.all(dec.theta >= 0)
    assert np.all(dec.vectors[~free.reshape(-1)] == 0)
    dense = jax.jit(lambda E, nu: linear_response_columns(body, Material(E, nu), free, dofs, linear_solver="dense"))
    spec = jax.jit(lambda E, nu: linear_response_columns(body, Material(E, nu), free, dofs, linear_solver="spectral", decomposition=dec))
    for nu in (0.3, 0.45, 0.49):
        Zd, Gd = (np.asarray(a) for a in dense(1e4, nu))
        Zs, Gs = (np.asarray(a) for a in spec(1e4, nu))
        np.testing.assert_allclose(Gs, Gd, rtol=0, atol=1e-10 * np.abs(Gd).max())
        np.testing.assert_allclose(Zs, Zd, rtol=0, atol=1e-10 * np.abs(Zd).max())
    # without a decomposition it is computed (and cached: the same object again)
    Z2, G2 = linear_response_columns(body, Material(1e4, 0.49), free, dofs, linear_solver="spectral")
    np.testing.assert_allclose(np.asarray(G2), Gs, rtol=1e-12)
    assert spectral_decomposition(body, free) is dec


def test_spectral_derivatives_match_finite_differences_and_the_cholesky_path(quarter):
    body, free, dofs = _body(quarter)
    dec = spectral_decomposition(body, free)

    def columns(p, solver):
        Z, G = linear_response_columns(body, Material(p[0] * 1e4, p[1]), free, dofs, linear_solver=solver, decomposition=dec)
        return jnp.concatenate([G.reshape(-1), Z[:, ::17].reshape(-1)]) * 1e4  # [m/N] x 1e4: O(1e-2)

    p = jnp.array([1.2, 0.45])
    fs = jax.jit(lambda q: columns(q, "spectral"))
    jf = np.asarray(jax.jit(jax.jacfwd(fs))(p))
    jr = np.asarray(jax.jit(jax.jacrev(fs))(p))
    jd = np.asarray(jax.jit(jax.jacfwd(lambda q: columns(q, "dense")))(p))
    scale = np.abs(jd).max()
    np.testing.assert_allclose(jr, jf, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(jf, jd, rtol=0, atol=1e-8 * scale)
    h = 1e-5
    for k in range(2):
        e = jnp.zeros(2).at[k].set(h)
        fd = (np.asarray(fs(p + e)) - np.asarray(fs(p - e))) / (2 * h)
        np.testing.assert_allclose(jf[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
        assert np.abs(fd).max() > 0


def test_spectral_indentation_equals_the_default_and_is_shared_by_equal_meshes(quarter):
    default = Indentation(quarter, DEPTHS, **SPHERE)
    spec = Indentation(quarter, DEPTHS, options=SolverOptions(linear_solver="spectral"), **SPHERE)
    # an equal mesh built again: the same decomposition (cache keyed by content)
    again = Indentation(indentation_block((4e-3, 4e-3, 1.6e-3), (6, 6, 5), symmetry="quarter"), DEPTHS, **SPHERE).spectral_variant()
    assert again.options.linear_solver == "spectral" and again.condensation.spectral.vectors is spec.condensation.spectral.vectors
    assert spec.spectral_variant() is spec and default.condensation.spectral is None
    f = lambda sc: jax.jit(lambda p: sc.predict(Material(p[0], p[1])))  # noqa: E731
    p = jnp.array([12e3, 0.45])
    fd_, fs_ = np.asarray(f(default)(p)), np.asarray(f(spec)(p))
    assert np.all(fd_ > 0)
    np.testing.assert_allclose(fs_, fd_, rtol=1e-10)
    # derivatives (the default path's are tested in test_condensed.py, the columns' equality
    # with the Cholesky path above): forward = reverse, E dF/dE = F, dF/dnu = central differences
    js = np.asarray(jax.jit(jax.jacfwd(f(spec)))(p))
    jr = np.asarray(jax.jit(jax.jacrev(f(spec)))(p))
    np.testing.assert_allclose(jr, js, rtol=1e-10, atol=1e-14 * np.abs(js).max())
    np.testing.assert_allclose(js[:, 0] * p[0], fs_, rtol=1e-10)
    h = 1e-5
    fd_nu = (np.asarray(f(spec)(p + jnp.array([0.0, h]))) - np.asarray(f(spec)(p - jnp.array([0.0, h])))) / (2 * h)
    np.testing.assert_allclose(js[:, 1], fd_nu, rtol=1e-5, atol=1e-6 * np.abs(fd_nu).max())
    assert np.all(np.abs(fd_nu) > 0)
    # the displacement field too
    ud, us = np.asarray(default.solve(Material(12e3, 0.45))[1]), np.asarray(spec.solve(Material(12e3, 0.45))[1])
    np.testing.assert_allclose(us, ud, rtol=0, atol=1e-10 * np.abs(ud).max())


def test_spectral_refuses_what_it_cannot_do(quarter, monkeypatch):
    opts = SolverOptions(linear_solver="spectral")
    with pytest.raises(errors.ConfigError, match="condensed indentation"):
        Indentation(quarter, DEPTHS, options=opts, solver="full", **SPHERE)
    with pytest.raises(errors.ConfigError, match="condensed indentation"):
        Indentation(quarter, DEPTHS, model="fem_neo_hookean", indenter="sphere", radius=1e-3, symmetry="quarter", options=opts)
    punch = Indentation(quarter, DEPTHS, model="fem_linear", indenter="flat_punch", radius=5e-4, symmetry="quarter")
    assert punch.spectral_variant() is None
    with pytest.raises(errors.ConfigError, match="not a condensed indentation"):
        punch.spectral_variant(required=True)
    # an explicitly chosen solver is kept unless required
    dense = Indentation(quarter, DEPTHS, options=SolverOptions(linear_solver="dense"), **SPHERE)
    assert dense.spectral_variant() is None and dense.spectral_variant(required=True).options.linear_solver == "spectral"
    # two regions: the stiffness is no longer a two-matrix pencil
    z = quarter.points[quarter.tets].mean(axis=1)[:, 2]
    layered = TetMesh(quarter.points, quarter.tets, (z > 1.0e-3).astype(np.int32), ("deep", "skin"))
    with pytest.raises(errors.ConfigError, match="one homogeneous region"):
        Indentation(layered, DEPTHS, options=opts, **SPHERE)
    assert Indentation(layered, DEPTHS, **SPHERE).spectral_variant() is None
    # too large
    monkeypatch.setattr(spectral, "SPECTRAL_MAX_UNKNOWNS", 100)
    with pytest.raises(errors.ConfigError, match="limited to 100 unknowns"):
        Indentation(quarter, DEPTHS, options=opts, **SPHERE)
    monkeypatch.undo()
    # pre-stretch: concrete and traced
    body, free, dofs = _body(quarter)
    stretched = Material(1e4, 0.45, pre_stretch=1.1)
    with pytest.raises(errors.ModelError, match="pre-stretch"):
        linear_response_columns(body, stretched, free, dofs, linear_solver="spectral")
    with pytest.raises(Exception, match="pre-stretch"):
        jax.block_until_ready(jax.jit(lambda s: linear_response_columns(body, Material(1e4, 0.45, pre_stretch=s), free, dofs, linear_solver="spectral")[1])(1.1))
    # another mesh's decomposition
    other, ofree, _ = _body(indentation_block((4e-3, 4e-3, 1.6e-3), (4, 4, 4), symmetry="quarter"))
    with pytest.raises(errors.ModelError, match="another mesh"):
        linear_response_columns(body, Material(1e4, 0.45), free, dofs, linear_solver="spectral", decomposition=spectral_decomposition(other, ofree))
    # rigid modes left free: the shear stiffness is singular
    model = make_model(quarter, "fem_linear")
    with pytest.raises(errors.ModelError, match="not positive definite"):
        spectral_decomposition(model, np.ones((model.n_nodes, 3), dtype=bool))
