"""Per-element energy kernels: gradient checks, analytic values, invariances, small-strain limits."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from difftissue.energies import (
    ENERGY_DENSITIES,
    cubic_spring_energy,
    deformation_gradient,
    det3,
    det3_minus_one,
    first_invariant_minus_three,
    fem_energy,
    linear_elastic_energy_density,
    neo_hookean_energy_density,
    rest_shape,
    rest_shapes,
    safe_norm,
    spring_extension,
    stable_neo_hookean_constraints,
    stable_neo_hookean_energy_density,
    stable_neo_hookean_gamma,
    tet_energy,
    tet_signed_volume,
    volume_constraint,
    volume_energy,
)
from difftissue.errors import DifftissueError
from difftissue.materials import lame_parameters, youngs_poisson_from_lame
from difftissue.mesh import block

UNIT_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
LAM, MU = 2.3, 0.7  # generic Lamé constants [Pa] (O(1) so that finite differences are well scaled)


def _rng(seed=0):
    return np.random.default_rng(seed)


def _perturbed_tet(rng, scale=0.15):
    X = UNIT_TET + scale * rng.standard_normal((4, 3))
    assert float(tet_signed_volume(X)) > 0.05
    return X


def _rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@pytest.fixture(scope="module")
def generic():
    """A seeded, non-degenerate configuration: rest tet X, deformed tet x, F, spring ends."""
    rng = _rng(1)
    X = _perturbed_tet(rng)
    x = X + 0.1 * rng.standard_normal((4, 3))
    assert float(tet_signed_volume(x)) > 0.05
    Dm_inv, V0 = rest_shape(X)
    F = deformation_gradient(x, Dm_inv)
    return {
        "X": jnp.asarray(X),
        "x": jnp.asarray(x),
        "Dm_inv": Dm_inv,
        "V0": V0,
        "F": F,
        "xi": jnp.asarray(rng.standard_normal(3)),
        "xj": jnp.asarray(rng.standard_normal(3) + 1.0),
        "v": jnp.asarray(rng.standard_normal(3)),
    }


@pytest.fixture(scope="module")
def batch():
    """The same inputs as ``generic`` for the 6 tets of a perturbed one-cube mesh (batched kernels).

    The gradient checks run on these: batches are checked too, and the primitives compiled
    for these shapes are shared with the mesh-level check (a large saving on a slow CPU).
    """
    pts, tets = _small_mesh()
    rng = _rng(11)
    xdef = pts + 0.05 * rng.standard_normal(pts.shape)
    X, x = pts[tets], xdef[tets]
    assert np.all(np.asarray(tet_signed_volume(x)) > 0)
    Dm_inv, V0 = rest_shape(X)
    return {
        "X": X,
        "x": x,
        "Dm_inv": Dm_inv,
        "V0": V0,
        "F": deformation_gradient(x, Dm_inv),
        "xi": x[:, 0],
        "xj": x[:, 1],
        "v": jnp.asarray(rng.standard_normal((6, 3))),
    }


def _small_mesh():
    m = block((1.0, 0.8, 0.6), (1, 1, 1))
    rng = _rng(2)
    pts = m.points + 0.03 * rng.standard_normal(m.points.shape)
    assert np.all(np.asarray(tet_signed_volume(pts[m.tets])) > 0)
    return jnp.asarray(pts), jnp.asarray(m.tets)


# ------------------------------------------------------------------------------ gradients
GRAD_CASES = {
    "safe_norm": lambda g: (safe_norm, (g["v"],)),
    "safe_norm_eps_inside": lambda g: (lambda v: safe_norm(v, eps=10.0), (g["v"],)),
    "safe_norm_eps_outside": lambda g: (lambda v: safe_norm(v, eps=0.1), (g["v"],)),
    "spring_extension": lambda g: (spring_extension, (g["xi"], g["xj"], 0.7)),
    "cubic_spring_energy": lambda g: (cubic_spring_energy, (g["xi"], g["xj"], 0.7, 3.0, 5.0)),
    "tet_signed_volume": lambda g: (tet_signed_volume, (g["x"],)),
    "volume_constraint": lambda g: (volume_constraint, (g["x"], g["V0"])),
    "volume_energy": lambda g: (volume_energy, (g["x"], g["V0"], 4.0)),
    "det3": lambda g: (det3, (g["F"],)),
    "rest_shape": lambda g: (rest_shape, (g["X"],)),
    "deformation_gradient": lambda g: (deformation_gradient, (g["x"], g["Dm_inv"])),
    "stable_nh_constraints": lambda g: (stable_neo_hookean_constraints, (g["F"], 1.2)),
    "stable_nh_density": lambda g: (stable_neo_hookean_energy_density, (g["F"], MU, LAM + MU)),
    "linear_density": lambda g: (linear_elastic_energy_density, (g["F"], LAM, MU)),
    "neo_hookean_density": lambda g: (neo_hookean_energy_density, (g["F"], LAM, MU)),
    "tet_energy_linear": lambda g: (
        lambda x, Dm_inv, V0, lam, mu: tet_energy(x, Dm_inv, V0, linear_elastic_energy_density, lam, mu),
        (g["x"], g["Dm_inv"], g["V0"], LAM, MU),
    ),
    "tet_energy_neo_hookean": lambda g: (
        lambda x, Dm_inv, V0, lam, mu: tet_energy(x, Dm_inv, V0, neo_hookean_energy_density, lam, mu),
        (g["x"], g["Dm_inv"], g["V0"], LAM, MU),
    ),
    "tet_energy_stable_nh": lambda g: (
        lambda x, Dm_inv, V0, mu, ls: tet_energy(x, Dm_inv, V0, stable_neo_hookean_energy_density, mu, ls),
        (g["x"], g["Dm_inv"], g["V0"], MU, LAM + MU),
    ),
}


@pytest.mark.parametrize("name", sorted(GRAD_CASES))
def test_check_grads_order2(batch, name):
    f, args = GRAD_CASES[name](batch)
    # not jitted on purpose: op by op, the primitives' small programs are shared by all the
    # cases; jitted, each case compiled ~13 derivative programs of its own (measured: 25 s ->
    # 89 s CPU for these tests, docs/dev/test-suite.md)
    check_grads(f, args, order=2, modes=("fwd", "rev"), eps=1e-5)


def test_check_grads_mesh_level():
    pts, tets = _small_mesh()
    rng = _rng(3)
    x = pts + 0.05 * rng.standard_normal(pts.shape)
    lam = LAM * (1 + 0.2 * rng.random(tets.shape[0]))
    mu = MU * (1 + 0.2 * rng.random(tets.shape[0]))

    def mesh_kernels(p, x, la, m):
        Dm_inv, V0 = rest_shapes(p, tets)
        return {
            "rest_shapes": (Dm_inv, V0),
            **{kind: fem_energy(x, tets, Dm_inv, V0, la, m, kind=kind) for kind in ENERGY_DENSITIES},
        }

    check_grads(mesh_kernels, (pts, x, lam, mu), order=2, modes=("fwd", "rev"))


# ------------------------------------------------------------------------------ batching
def _all_kernels(a):
    """Every element kernel evaluated on one (possibly batched) set of inputs ``a``."""
    x, F, V0 = a["x"], a["F"], a["V0"]
    lam = LAM * (1 + 0.1 * V0)  # an input-dependent parameter, batched with the tets
    return {
        "safe_norm": safe_norm(a["v"]),
        "spring_extension": spring_extension(a["xi"], a["xj"], 0.9),
        "cubic_spring_energy": cubic_spring_energy(a["xi"], a["xj"], 0.9, 2.0, 4.0),
        "tet_signed_volume": tet_signed_volume(x),
        "volume_energy": volume_energy(x, V0, 3.0),
        "rest_shape": rest_shape(a["X"]),
        "deformation_gradient": deformation_gradient(x, a["Dm_inv"]),
        "stable_nh_constraints": stable_neo_hookean_constraints(F, 1.1),
        **{d.__name__: d(F, lam, MU) for d in (linear_elastic_energy_density, neo_hookean_energy_density, stable_neo_hookean_energy_density)},
        "tet_energy": tet_energy(x, a["Dm_inv"], V0, neo_hookean_energy_density, lam, MU),
    }


def test_kernels_broadcast_over_leading_dims(batch):
    batched = _all_kernels(batch)
    for leaf in jax.tree.leaves(batched):
        assert leaf.shape[:1] == (6,)
    for i in range(6):
        single = _all_kernels({k: v[i] for k, v in batch.items()})
        jax.tree.map(lambda b, s: np.testing.assert_allclose(b[i], s, rtol=1e-13, atol=1e-15), batched, single)


def test_kernels_under_vmap(batch):
    vmapped = jax.jit(jax.vmap(_all_kernels))(batch)
    jax.tree.map(lambda v, b: np.testing.assert_allclose(v, b, rtol=1e-13, atol=1e-15), vmapped, _all_kernels(batch))


# ------------------------------------------------------------------------------ springs
def test_safe_norm_value_and_gradient():
    rng = _rng(5)
    v = rng.standard_normal((7, 3))
    np.testing.assert_allclose(safe_norm(v), np.linalg.norm(v, axis=-1), rtol=1e-15)
    grad = jax.jit(jax.grad(safe_norm))
    g = grad(jnp.asarray(v[0]))
    np.testing.assert_allclose(g, v[0] / np.linalg.norm(v[0]), rtol=1e-14)
    zero = jnp.zeros(3)
    assert float(safe_norm(zero)) == 0.0
    g0 = grad(zero)
    h0 = jax.jit(jax.hessian(safe_norm))(zero)
    assert np.all(np.isfinite(g0)) and np.all(np.isfinite(h0))
    np.testing.assert_array_equal(g0, 0.0)
    # The naive norm really is NaN there (what the guard is for).
    assert np.all(np.isnan(jax.jit(jax.grad(jnp.linalg.norm))(zero)))
    # Tiny but non-zero vectors keep their exact value and unit gradient.
    tiny = jnp.array([3e-150, 4e-150, 0.0])
    np.testing.assert_allclose(safe_norm(tiny), 5e-150, rtol=1e-15)
    np.testing.assert_allclose(grad(tiny), [0.6, 0.8, 0.0], rtol=1e-14)


def test_safe_norm_eps_blend_is_c1():
    eps = 0.5
    d = jnp.array([0.6, 0.0, 0.8])
    f = lambda r: safe_norm(r * d, eps=eps)  # noqa: E731
    for r in (eps * (1 - 1e-9), eps * (1 + 1e-9)):
        np.testing.assert_allclose(f(r), eps, rtol=1e-8)
        np.testing.assert_allclose(jax.grad(f)(r), 1.0, rtol=1e-8)
    np.testing.assert_allclose(f(0.0), eps / 2, rtol=1e-15)
    np.testing.assert_allclose(f(2.0), 2.0, rtol=1e-15)  # exact outside eps
    assert float(jax.grad(f)(0.0)) == 0.0


def test_cubic_spring_energy_known_value():
    xi = jnp.array([1.0, 2.0, 3.0])
    xj = xi + jnp.array([3.0, 4.0, 0.0])  # length 5
    e = 0.5
    k, a = 2.0, 8.0
    np.testing.assert_allclose(spring_extension(xi, xj, 5.0 - e), e, rtol=1e-15)
    np.testing.assert_allclose(cubic_spring_energy(xi, xj, 5.0 - e, k, a), k * e**2 / 2 + a * e**4 / 4, rtol=1e-15)
    np.testing.assert_allclose(cubic_spring_energy(xi, xj, 5.0 - e, k, a), 0.375, rtol=1e-15)


@pytest.mark.parametrize("extension", [-0.8, -0.1, 0.0, 0.3, 1.7])
def test_cubic_spring_force(extension):
    rng = _rng(6)
    xi = jnp.asarray(rng.standard_normal(3))
    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    L0 = 1.3
    xj = xi + (L0 + extension) * n
    k, a = 2.5, 7.0
    gi, gj = jax.grad(cubic_spring_energy, argnums=(0, 1))(xi, xj, L0, k, a)
    tension = k * extension + a * extension**3
    np.testing.assert_allclose(gj, tension * n, atol=1e-13)
    np.testing.assert_allclose(gi, -tension * n, atol=1e-13)


def test_cubic_spring_gradient_finite_at_zero_length():
    x = jnp.array([0.2, -0.1, 0.4])
    g = jax.grad(cubic_spring_energy, argnums=(0, 1))(x, x, 0.5, 3.0, 1.0)
    assert all(np.all(np.isfinite(gi)) for gi in g)
    np.testing.assert_allclose(cubic_spring_energy(x, x, 0.5, 3.0, 1.0), 3.0 * 0.25 / 2 + 0.0625 / 4, rtol=1e-15)


# ------------------------------------------------------------------------------ volume
def test_unit_tet_volume_and_orientation():
    np.testing.assert_allclose(tet_signed_volume(UNIT_TET), 1.0 / 6.0, rtol=1e-15)
    np.testing.assert_allclose(tet_signed_volume(UNIT_TET[[0, 2, 1, 3]]), -1.0 / 6.0, rtol=1e-15)
    X = np.array([[0.0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 5]]) + 7.0
    np.testing.assert_allclose(tet_signed_volume(X), 5.0, rtol=1e-14)


def test_numpy_tet_volume_is_the_jax_formula():
    """The host (NumPy) signed volume :func:`difftissue.mesh.signed_volumes` and the JAX one:
    +1/6 exactly for the unit right tet, -1/6 with two nodes swapped, agreement to 1e-15 of the
    largest volume on random tets (<= 3e-16 measured: the products are rounded in another
    order); the host copies of the formula (pypbd runner) are that function."""
    from difftissue.export.pypbd_runner import signed_tet_volumes
    from difftissue.mesh import signed_volumes
    from difftissue.scenarios import _tet_volumes

    def tet_signed_volume_np(x):  # (..., 4, 3) -> (...)
        return signed_volumes(x.reshape(-1, 3), np.arange(x.size // 3).reshape(-1, 4)).reshape(x.shape[:-2])

    assert tet_signed_volume_np(UNIT_TET) == 1.0 / 6.0
    assert float(tet_signed_volume(jnp.asarray(UNIT_TET))) == 1.0 / 6.0
    assert tet_signed_volume_np(UNIT_TET[[0, 2, 1, 3]]) == -1.0 / 6.0
    rng = _rng(3)
    points = rng.normal(size=(300, 3)) * 1e-3
    tets = rng.integers(0, 300, size=(2000, 4))
    v_np = tet_signed_volume_np(points[tets])
    v_jax = np.asarray(tet_signed_volume(jnp.asarray(points[tets])))
    assert v_np.shape == (2000,) and np.any(v_np < 0) and np.any(v_np > 0)
    assert np.max(np.abs(v_np - v_jax)) <= 1e-15 * np.max(np.abs(v_np))
    np.testing.assert_array_equal(signed_volumes(points, tets), v_np)
    np.testing.assert_array_equal(signed_tet_volumes(points, tets), v_np)
    np.testing.assert_array_equal(np.asarray(_tet_volumes(jnp.asarray(points), jnp.asarray(tets))), v_jax)


@pytest.mark.parametrize("s", [0.7, 1.0, 1.2])
def test_volume_energy_uniform_scaling(generic, s):
    X = np.asarray(generic["X"])
    V0 = float(tet_signed_volume(X))
    c = np.array([0.3, -1.0, 2.0])
    x = c + s * (X - c)
    K = 3.7
    np.testing.assert_allclose(volume_constraint(x, V0), (s**3 - 1) * V0, atol=1e-15)
    np.testing.assert_allclose(volume_energy(x, V0, K), K * V0 * (s**3 - 1) ** 2 / 2, rtol=1e-12, atol=1e-300)


def test_volume_gradient_matches_xpbd_formula(generic):
    x = np.asarray(generic["x"])
    g = jax.grad(tet_signed_volume)(jnp.asarray(x))
    g1 = np.cross(x[2] - x[0], x[3] - x[0]) / 6
    g2 = np.cross(x[3] - x[0], x[1] - x[0]) / 6
    g3 = np.cross(x[1] - x[0], x[2] - x[0]) / 6
    np.testing.assert_allclose(g, np.stack([-(g1 + g2 + g3), g1, g2, g3]), rtol=1e-13, atol=1e-15)


# ------------------------------------------------------------------------------ F and rest shape
def test_rest_shape_and_affine_deformation_gradient(generic):
    X = np.asarray(generic["X"])
    Dm_inv, V0 = rest_shape(X)
    Dm = (X[1:] - X[0]).T
    np.testing.assert_allclose(Dm_inv @ Dm, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(V0, np.linalg.det(Dm) / 6, rtol=1e-14)
    A = np.array([[1.1, 0.2, -0.1], [0.05, 0.9, 0.3], [-0.2, 0.1, 1.3]])
    x = X @ A.T + np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(deformation_gradient(x, Dm_inv), A, atol=1e-13)
    np.testing.assert_allclose(det3(A), np.linalg.det(A), rtol=1e-14)


# ------------------------------------------------------------------------------ rigid motions
def _tet_energies(X):
    """Every element energy of the package as a function of the tet nodes x (rest X)."""
    Dm_inv, V0 = rest_shape(X)
    edges = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    L0 = np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=-1)
    return {
        "springs": lambda x: jnp.sum(cubic_spring_energy(x[edges[:, 0]], x[edges[:, 1]], L0, 3.0, 11.0)),
        "volume": lambda x: volume_energy(x, V0, 4.0),
        "stable_neo_hookean": lambda x: tet_energy(x, Dm_inv, V0, stable_neo_hookean_energy_density, MU, LAM + MU),
        "neo_hookean": lambda x: tet_energy(x, Dm_inv, V0, neo_hookean_energy_density, LAM, MU),
        "linear": lambda x: tet_energy(x, Dm_inv, V0, linear_elastic_energy_density, LAM, MU),
    }


@pytest.mark.parametrize("name", ["springs", "volume", "stable_neo_hookean", "neo_hookean"])
def test_rigid_motion_zero_energy_and_gradient(generic, name):
    X = np.asarray(generic["X"])
    U = _tet_energies(X)[name]
    R = _rotation(_rng(7))
    assert np.linalg.norm(R - np.eye(3)) > 0.5  # a finite rotation
    x = jnp.asarray(X @ R.T + np.array([0.4, -1.2, 2.0]))
    assert abs(float(U(x))) < 1e-13
    grad = jax.jit(jax.grad(U))
    np.testing.assert_allclose(grad(x), 0.0, atol=1e-13)
    # ... and a real deformation is not free (the check can fail).
    y = x[0] + 1.05 * (x - x[0])  # a 5 % dilatation
    assert float(U(y)) > 1e-6
    assert float(jnp.max(jnp.abs(grad(y)))) > 1e-4


def test_linear_energy_rigid_only_infinitesimally(generic):
    """Linear elasticity is invariant under translations and infinitesimal rotations only."""
    X = np.asarray(generic["X"])
    U = _tet_energies(X)["linear"]
    t = np.array([0.4, -1.2, 2.0])
    W = np.array([[0.0, -0.3, 0.2], [0.3, 0.0, -0.5], [-0.2, 0.5, 0.0]])  # skew: linearised rotation
    x = jnp.asarray(X + X @ W.T + t)
    assert abs(float(U(x))) < 1e-14
    np.testing.assert_allclose(jax.grad(U)(x), 0.0, atol=1e-13)

    # A finite rotation by theta costs O(theta^4): the known caveat of small-strain energy.
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])

    U = jax.jit(U)

    def rotated(theta):
        Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx
        return float(U(jnp.asarray(X @ R.T + t)))

    assert rotated(0.2) > 1e-5
    np.testing.assert_allclose(rotated(0.02) / rotated(0.01), 16.0, rtol=1e-3)


# ------------------------------------------------------------------------------ densities
@pytest.mark.parametrize("density,params", [
    (linear_elastic_energy_density, (LAM, MU)),
    (neo_hookean_energy_density, (LAM, MU)),
    (stable_neo_hookean_energy_density, (MU, LAM + MU)),
])
def test_zero_energy_and_stress_at_identity(density, params):
    eye = jnp.eye(3)
    assert abs(float(density(eye, *params))) < 1e-15
    np.testing.assert_allclose(jax.grad(density)(eye, *params), 0.0, atol=1e-14)


def _isotropic_tensor(lam, mu):
    d = np.eye(3)
    return lam * np.einsum("ij,kl->ijkl", d, d) + mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))


def _linearised_tangent(density, *params):
    """dP/dF at F = I (P = dPsi/dF, the first Piola stress), shape (3, 3, 3, 3)."""
    return np.asarray(_tangent_at_identity(density, *params))


@functools.partial(jax.jit, static_argnums=0)
def _tangent_at_identity(density, *params):
    return jax.jacfwd(jax.grad(density))(jnp.eye(3), *params)


@pytest.mark.parametrize("density,params", [
    (linear_elastic_energy_density, (LAM, MU)),
    (neo_hookean_energy_density, (LAM, MU)),
    (stable_neo_hookean_energy_density, (MU, LAM + MU)),  # the lambda' = lambda + mu shift
])
def test_linearised_stress_is_linear_elasticity(density, params):
    C = _linearised_tangent(density, *params)
    np.testing.assert_allclose(C, _isotropic_tensor(LAM, MU), atol=1e-13)
    # Stress of an arbitrary small displacement gradient H: lam tr(eps) I + 2 mu eps.
    H = _rng(8).standard_normal((3, 3))
    eps = 0.5 * (H + H.T)
    np.testing.assert_allclose(np.einsum("ijkl,kl->ij", C, H), LAM * np.trace(eps) * np.eye(3) + 2 * MU * eps, atol=1e-13)


def test_stable_neo_hookean_without_shift_has_wrong_poisson_ratio():
    E, nu = 1.0e4, 0.3
    lam, mu = lame_parameters(E, nu)

    def effective(lam_shift):
        C = _linearised_tangent(stable_neo_hookean_energy_density, mu, lam_shift)
        lam_eff, mu_eff = C[0, 0, 1, 1], C[0, 1, 0, 1]
        np.testing.assert_allclose(C, _isotropic_tensor(lam_eff, mu_eff), atol=1e-10 * E)  # really isotropic
        return youngs_poisson_from_lame(lam_eff, mu_eff)

    E_ok, nu_ok = effective(lam + mu)
    np.testing.assert_allclose([E_ok, nu_ok], [E, nu], rtol=1e-12)
    E_bad, nu_bad = effective(lam)
    np.testing.assert_allclose(nu_bad, (4 * nu - 1) / (4 * nu), rtol=1e-12)
    np.testing.assert_allclose(nu_bad, 1.0 / 6.0, rtol=1e-12)  # about 0.167
    assert E_bad < 0.9 * E


def test_stable_neo_hookean_constraints_match_energy(generic):
    F = generic["F"]
    lam_shift = LAM + MU
    gamma = stable_neo_hookean_gamma(MU, lam_shift)
    np.testing.assert_allclose(gamma, 1 + MU / lam_shift, rtol=1e-15)
    c_d, c_h = stable_neo_hookean_constraints(F, gamma)
    np.testing.assert_allclose(c_d, np.sqrt(np.trace(np.asarray(F).T @ np.asarray(F))), rtol=1e-14)
    np.testing.assert_allclose(c_h, np.linalg.det(np.asarray(F)) - gamma, rtol=1e-13)
    # XPBD energy C_D^2 / (2 alpha_D) + C_H^2 / (2 alpha_H) per unit volume, alpha_D = 1/mu, alpha_H = 1/lam'.
    xpbd = 0.5 * MU * c_d**2 + 0.5 * lam_shift * c_h**2
    np.testing.assert_allclose(xpbd - 1.5 * MU - MU**2 / (2 * lam_shift), stable_neo_hookean_energy_density(F, MU, lam_shift), rtol=1e-13)
    # C_D has a finite gradient at F = 0.
    assert np.all(np.isfinite(jax.grad(lambda f: stable_neo_hookean_constraints(f, gamma)[0])(jnp.zeros((3, 3)))))


def test_stable_neo_hookean_smooth_through_inversion():
    F = jnp.diag(jnp.array([-0.5, 1.0, 1.0]))
    psi = stable_neo_hookean_energy_density(F, MU, LAM + MU)
    assert np.isfinite(psi) and psi > 0
    assert np.all(np.isfinite(jax.jit(jax.hessian(stable_neo_hookean_energy_density))(F, MU, LAM + MU)))


@pytest.mark.parametrize("F", [
    np.diag([-1.0, 1.0, 1.0]),
    np.diag([1.2, 0.9, -0.01]),
    np.diag([1.0, 1.0, 0.0]),  # flat: J = 0
])
def test_neo_hookean_inf_for_inverted(F):
    F = jnp.asarray(F)
    assert float(neo_hookean_energy_density(F, LAM, MU)) == np.inf
    g = jax.grad(neo_hookean_energy_density)(F, LAM, MU)
    assert np.all(np.isfinite(g))  # no NaN leaks from the unused log branch


def test_neo_hookean_tet_energy_inf_for_inverted_tet(generic):
    X = np.asarray(generic["X"])
    Dm_inv, V0 = rest_shape(X)
    x = X.copy()
    x[3] = X[0] - (X[3] - X[0])  # push node 3 through the opposite face
    assert float(tet_signed_volume(x)) < 0
    assert float(tet_energy(jnp.asarray(x), Dm_inv, V0, neo_hookean_energy_density, LAM, MU)) == np.inf
    # Close to inversion the energy is finite, with finite gradient and Hessian.
    y = X.copy()
    y[3] = X[0] + 1e-3 * (X[3] - X[0])
    U = lambda z: tet_energy(z, Dm_inv, V0, neo_hookean_energy_density, LAM, MU)  # noqa: E731
    assert np.isfinite(U(jnp.asarray(y)))
    assert np.all(np.isfinite(jax.jit(jax.hessian(U))(jnp.asarray(y))))


def _relative_difference(density, params, strain, seed=9):
    H = _rng(seed).standard_normal((3, 3))
    H /= np.linalg.norm(H)
    F = jnp.eye(3) + strain * H
    lin = float(linear_elastic_energy_density(F, LAM, MU))
    other = float(density(F, *params))
    assert lin > 0
    return abs(other - lin) / lin


@pytest.mark.parametrize("density,params", [
    (neo_hookean_energy_density, (LAM, MU)),
    (stable_neo_hookean_energy_density, (MU, LAM + MU)),
])
def test_matches_linear_to_second_order(density, params):
    r3, r4 = (_relative_difference(density, params, s) for s in (1e-3, 1e-4))
    assert r4 < 1e-3
    assert r4 > 1e-7  # the cubic term is there: the two are not the same function
    np.testing.assert_allclose(r3 / r4, 10.0, rtol=0.05)  # relative difference O(strain)


@pytest.mark.parametrize("density,params", [
    (neo_hookean_energy_density, (LAM, MU)),
    (stable_neo_hookean_energy_density, (MU, LAM + MU)),
])
def test_small_strain_energy_keeps_its_digits(density, params):
    """At strain 1e-7 the energy is ~1e-14 Pa; computed naively (I1 - 3 - 2 ln det F) it
    would carry absolute round-off ~1e-16, i.e. ~1 % relative error."""
    assert _relative_difference(density, params, 1e-7) < 1e-5


def test_det3_minus_one():
    H = _rng(10).standard_normal((4, 3, 3))
    np.testing.assert_allclose(det3_minus_one(H), np.linalg.det(np.eye(3) + H) - 1, rtol=1e-12)
    h = 1e-9 * H[0]
    np.testing.assert_allclose(det3_minus_one(h), np.trace(h), rtol=1e-8)  # no cancellation
    np.testing.assert_allclose(first_invariant_minus_three(H), np.einsum("nij,nij->n", np.eye(3) + H, np.eye(3) + H) - 3, rtol=1e-12)


def test_stable_and_classic_neo_hookean_differ_at_large_strain():
    F = jnp.diag(jnp.array([1.5, 0.9, 0.8]))
    a = float(neo_hookean_energy_density(F, LAM, MU))
    b = float(stable_neo_hookean_energy_density(F, MU, LAM + MU))
    assert abs(a - b) > 1e-3 * abs(a)


# ------------------------------------------------------------------------------ mesh assembly
def test_fem_energy_affine_deformation_and_per_tet_parameters():
    pts, tets = _small_mesh()
    Dm_inv, V0 = rest_shapes(pts, tets)
    assert Dm_inv.shape == (tets.shape[0], 3, 3) and V0.shape == (tets.shape[0],)
    np.testing.assert_allclose(V0, tet_signed_volume(pts[tets]), rtol=1e-13)
    A = jnp.array([[1.05, 0.02, 0.0], [-0.01, 0.97, 0.03], [0.0, 0.01, 1.02]])
    x = pts @ A.T + 0.3
    for kind, density in ENERGY_DENSITIES.items():
        total = fem_energy(x, tets, Dm_inv, V0, LAM, MU, kind=kind)
        np.testing.assert_allclose(total, jnp.sum(V0) * density(A, LAM, MU), rtol=1e-12)
        per_tet = fem_energy(x, tets, Dm_inv, V0, jnp.full(tets.shape[0], LAM), jnp.full(tets.shape[0], MU), kind=kind)
        np.testing.assert_allclose(per_tet, total, rtol=1e-14)
    # Per-tet values are really used per tet: doubling mu in one tet adds that tet's mu-part.
    mu = jnp.full(tets.shape[0], MU).at[2].set(2 * MU)
    diff = fem_energy(x, tets, Dm_inv, V0, LAM, mu) - fem_energy(x, tets, Dm_inv, V0, LAM, MU)
    np.testing.assert_allclose(diff, V0[2] * linear_elastic_energy_density(A, 0.0, MU), rtol=1e-10)


def test_fem_energy_unknown_kind():
    pts, tets = _small_mesh()
    Dm_inv, V0 = rest_shapes(pts, tets)
    with pytest.raises(DifftissueError, match="neo_hookean"):
        fem_energy(pts, tets, Dm_inv, V0, LAM, MU, kind="neohookean")


def test_fem_energy_jits():
    pts, tets = _small_mesh()
    Dm_inv, V0 = rest_shapes(pts, tets)
    f = jax.jit(lambda p: fem_energy(p, tets, Dm_inv, V0, LAM, MU, kind="neo_hookean"))
    x = pts * 1.01
    np.testing.assert_allclose(f(x), fem_energy(x, tets, Dm_inv, V0, LAM, MU, kind="neo_hookean"), rtol=1e-14)


def test_cell_volume_hessian_is_the_exact_hessian_of_its_energy():
    """The springs_volume cell term's closed-form Hessian (cubic volume form, used by the
    Newton solver) equals ``jax.hessian`` of the energy on distorted cells, and the cubic form
    reproduces the trilinear-hexahedron volume."""
    from difftissue.models import _HEX_VOLUME_T, _cell_volume_energy, _cell_volume_hessian, hexahedron_volume

    corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float) * [1e-3, 1.2e-3, 0.9e-3]
    rng = np.random.default_rng(3)
    # both Hessians jitted (one program each, shared by the three cells) instead of op by op
    closed, hessian = jax.jit(_cell_volume_hessian), jax.jit(jax.hessian(_cell_volume_energy))
    for scale in (0.0, 1e-5, 2e-4):
        x = jnp.asarray(corners + scale * rng.standard_normal((8, 3)))
        xf = x.reshape(-1)
        np.testing.assert_allclose(float(np.einsum("abc,a,b,c->", _HEX_VOLUME_T, xf, xf, xf) / 6.0), float(hexahedron_volume(x)), rtol=1e-12)
        params = (jnp.asarray(0.8e-9), jnp.asarray(3.0e4))
        H = closed(x, *params)
        ref = hessian(x, *params).reshape(24, 24)
        np.testing.assert_allclose(H, ref, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(ref))))


def test_cubic_spring_hessian_is_the_exact_hessian_of_its_energy():
    """The closed-form spring Hessian (used by the Newton solver for springs_volume) equals
    ``jax.hessian`` of :func:`cubic_spring_energy` in tension, compression, with and without
    the cubic term, for a spring in a general direction, and is 0 at zero length."""
    from difftissue.energies.springs import cubic_spring_energy, cubic_spring_hessian

    def energy(x, L0, k, a):
        return cubic_spring_energy(x[0], x[1], L0, k, a)

    rng = np.random.default_rng(7)
    L0, k = 1.3e-3, 4.0
    # both Hessians jitted (L0, k, a are arguments: one program each for the nine springs, one
    # more for the batch) instead of op by op
    closed, hessian = jax.jit(cubic_spring_hessian), jax.jit(jax.hessian(energy))
    for stretch in (0.7, 1.0, 1.25):
        for a in (0.0, 3.0e6, -1.5e6):
            d = rng.standard_normal(3)
            d *= stretch * L0 / np.linalg.norm(d)
            x0 = rng.standard_normal(3) * 1e-3
            x = jnp.asarray(np.stack([x0, x0 + d]))
            H = closed(x[0], x[1], L0, k, a)
            ref = hessian(x, L0, k, a).reshape(6, 6)
            np.testing.assert_allclose(H, ref, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(ref))))
    # batched (leading dimensions) and the zero-length spring
    xs = jnp.asarray(rng.standard_normal((5, 2, 3)) * 1e-3)
    Hb = closed(xs[:, 0], xs[:, 1], L0, k, 2.0e6)
    for i in range(5):
        np.testing.assert_allclose(Hb[i], hessian(xs[i], L0, k, 2.0e6).reshape(6, 6), rtol=1e-12, atol=1e-9)
    same = jnp.zeros((2, 3))
    np.testing.assert_array_equal(closed(same[0], same[1], L0, k, 2.0e6), hessian(same, L0, k, 2.0e6).reshape(6, 6))
