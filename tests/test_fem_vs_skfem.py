"""Our linear-tet FEM energy against an independent assembler (scikit-fem) on the same mesh."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from difftissue.energies import fem_energy, rest_shapes, tet_signed_volume
from difftissue.materials import lame_parameters
from difftissue.mesh import block

skfem = pytest.importorskip("skfem")
from skfem.models.elasticity import linear_elasticity  # noqa: E402

E, NU = 5.0e3, 0.45  # Pa, -
LAM, MU = lame_parameters(E, NU)


@pytest.fixture(scope="module")
def problem():
    mesh = block((1.0, 0.8, 0.6), (3, 2, 2))
    rest = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    # Perturb every node a little (seeded) to break the symmetries of the structured grid.
    rng = np.random.default_rng(12)
    points = rest + rng.uniform(-0.04, 0.04, rest.shape)
    assert np.all(np.asarray(tet_signed_volume(points[tets])) > 1e-4)
    n = points.shape[0]
    tets_j = jnp.asarray(tets)
    Dm_inv, V0 = rest_shapes(jnp.asarray(points), tets_j)

    def hessian(kind):
        energy = lambda u: fem_energy(u.reshape(n, 3), tets_j, Dm_inv, V0, LAM, MU, kind=kind)  # noqa: E731
        return np.asarray(jax.jit(jax.hessian(energy))(jnp.asarray(points.reshape(-1))))

    K_ours = hessian("linear")
    K_nh = hessian("neo_hookean")

    m = skfem.MeshTet(points.T.copy(), tets.T.copy())
    np.testing.assert_array_equal(m.p.T, points)  # skfem kept our node numbering
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
    K_sk = skfem.asm(linear_elasticity(LAM, MU), basis).toarray()
    # Our DOF 3 a + c (node a, component c) is skfem's nodal_dofs[c, a].
    perm = np.asarray(basis.nodal_dofs).T.reshape(-1)
    assert sorted(perm.tolist()) == list(range(3 * n))
    np.testing.assert_allclose(basis.doflocs[:, perm].T, np.repeat(points, 3, axis=0), atol=1e-14)  # DOF 3 a + c sits at node a
    K_sk = K_sk[np.ix_(perm, perm)]
    z = rest[:, 2]
    return {
        "points": points, "K_ours": K_ours, "K_nh": K_nh, "K_sk": K_sk,
        "bottom": np.flatnonzero(np.isclose(z, z.min())), "top": np.flatnonzero(np.isclose(z, z.max())),
    }


def test_stiffness_matches_skfem(problem):
    K, K_sk = problem["K_ours"], problem["K_sk"]
    assert K.shape == K_sk.shape == (3 * len(problem["points"]),) * 2
    scale = np.abs(K_sk).max()
    assert scale > 0
    np.testing.assert_allclose(K, K.T, atol=1e-12 * scale)
    assert np.abs(K - K_sk).max() <= 1e-10 * scale


def _solve_dirichlet(K, bottom, top, u_top):
    n = K.shape[0] // 3
    u = np.zeros((n, 3))
    fixed = np.zeros((n, 3), dtype=bool)
    fixed[bottom] = True
    fixed[top] = True
    u[top] = u_top
    fixed, u = fixed.reshape(-1), u.reshape(-1)
    free = ~fixed
    u[free] = scipy.linalg.solve(K[np.ix_(free, free)], -K[np.ix_(free, fixed)] @ u[fixed], assume_a="sym")
    return u.reshape(n, 3), free


def test_dirichlet_solution_matches_skfem(problem):
    u_top = np.array([0.01, -0.005, -0.02])  # m
    u, free = _solve_dirichlet(problem["K_ours"], problem["bottom"], problem["top"], u_top)
    u_sk, _ = _solve_dirichlet(problem["K_sk"], problem["bottom"], problem["top"], u_top)
    assert free.sum() > 0
    interior = u.reshape(-1)[free]
    assert np.abs(interior).max() > 1e-4  # a non-trivial field
    np.testing.assert_allclose(u, u_sk, rtol=0, atol=1e-8 * np.abs(u_sk).max())
    # Equilibrium of the free DOFs with our stiffness.
    r = (problem["K_ours"] @ u.reshape(-1))[free]
    assert np.abs(r).max() <= 1e-9 * np.abs(problem["K_ours"]).max() * np.abs(u).max()


def test_neo_hookean_hessian_at_rest_is_linear_stiffness(problem):
    K, K_nh = problem["K_ours"], problem["K_nh"]
    assert np.abs(K_nh - K).max() <= 1e-8 * np.abs(K).max()
