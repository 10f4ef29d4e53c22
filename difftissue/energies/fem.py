"""Linear-tetrahedron FEM energies: linear elasticity and compressible neo-Hookean (DESIGN.md §3.4).

Energy densities are functions of the deformation gradient ``F`` (``(..., 3, 3)``) and the
Lamé constants ``lam``, ``mu`` [Pa] (broadcasting against ``(...)``); they return
``(...)``-shaped densities [J/m^3]. A linear tet has a constant ``F``, so its energy is
``V0 * Psi(F)`` [J]; the mesh energy is the sum over tets. Nodal forces are
``-jax.grad(fem_energy)`` and the stiffness matrix is its Hessian.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..errors import DifftissueError
from .neo_hookean import deformation_gradient, det3_minus_one, first_invariant_minus_three, rest_shape
from .volume import cross

__all__ = [
    "linear_elastic_energy_density",
    "neo_hookean_energy_density",
    "tet_energy",
    "rest_shapes",
    "fem_energy",
    "ENERGY_DENSITIES",
    "nodal_dilatation_energy",
    "nodal_volume_energy",
    "nodal_dilatation_hessian",
    "nodal_volume_hessian",
]


def _trace(A):
    return A[..., 0, 0] + A[..., 1, 1] + A[..., 2, 2]


def linear_elastic_energy_density(F, lam, mu):
    """Small-strain (Hookean) energy density ``Psi = mu eps:eps + lam/2 (tr eps)^2`` [Pa].

    ``eps = sym(F - I)`` is the *linearised* strain: the density is zero under
    translations and infinitesimal rotations, but **not** under finite rotations (a
    rotation by ``theta`` gives ``eps ~ -theta^2/2`` in the rotation plane, so
    ``Psi = O(theta^4)``). Use it for small displacements only.

    Args:
        F: deformation gradients, shape ``(..., 3, 3)``.
        lam, mu: Lamé constants [Pa], broadcasting against ``(...)``.

    Returns:
        Energy density [Pa], shape ``(...)``.
    """
    H = F - jnp.eye(3, dtype=F.dtype)
    eps = 0.5 * (H + jnp.swapaxes(H, -1, -2))
    tr = _trace(eps)
    return mu * jnp.sum(eps * eps, axis=(-2, -1)) + 0.5 * lam * tr * tr


def neo_hookean_energy_density(F, lam, mu):
    """Compressible neo-Hookean density ``Psi = mu/2 (I1 - 3 - 2 ln J) + lam/2 (ln J)^2`` [Pa].

    ``I1 = tr(F^T F)``, ``J = det F``. Its small-strain limit is
    :func:`linear_elastic_energy_density` with the same ``(lam, mu)``.

    Inverted or flat elements (``J <= 0``) have ``Psi = +inf`` (the energy barrier that
    keeps a line search out of them); the log is evaluated on a guarded ``J`` so that the
    value and all derivatives are finite wherever ``J > 0`` (the gradient reported at
    ``J <= 0`` is 0, meaningless there: check the energy value). ``I1 - 3`` and
    ``ln J = log1p(J - 1)`` are expanded in ``H = F - I`` so that the density keeps its
    relative precision at small strain (the naive form loses ``~1e-16 / strain^2``).

    Args:
        F: deformation gradients, shape ``(..., 3, 3)``.
        lam, mu: Lamé constants [Pa], broadcasting against ``(...)``.

    Returns:
        Energy density [Pa], shape ``(...)``.
    """
    H = F - jnp.eye(3, dtype=F.dtype)
    jm1 = det3_minus_one(H)  # J - 1, accurate at small strain
    ok = jm1 > -1.0  # J > 0
    log_j = jnp.log1p(jnp.where(ok, jm1, 0.0))
    psi = 0.5 * mu * (first_invariant_minus_three(H) - 2.0 * log_j) + 0.5 * lam * log_j * log_j
    return jnp.where(ok, psi, jnp.inf)


#: Energy densities understood by :func:`fem_energy`, by ``kind``.
ENERGY_DENSITIES = {
    "linear": linear_elastic_energy_density,
    "neo_hookean": neo_hookean_energy_density,
}


def tet_energy(x, Dm_inv, V0, density, *params):
    """Energy ``V0 * density(F, *params)`` [J] of linear tets.

    Args:
        x: current node positions [m], shape ``(..., 4, 3)``.
        Dm_inv: inverse rest edge matrices [1/m], shape ``(..., 3, 3)`` (:func:`rest_shapes`).
        V0: rest volumes [m^3], shape ``(...)``.
        density: an energy density ``density(F, *params) -> Psi`` [Pa], e.g.
            :func:`neo_hookean_energy_density` or
            :func:`~difftissue.energies.neo_hookean.stable_neo_hookean_energy_density`.
        *params: its material parameters (e.g. ``lam, mu`` [Pa]).

    Returns:
        Energy [J], shape ``(...)``.
    """
    return V0 * density(deformation_gradient(x, Dm_inv), *params)


def rest_shapes(points, tets):
    """Inverse rest edge matrices and rest volumes of every tet of a mesh.

    Args:
        points: rest node positions [m], shape ``(N, 3)``.
        tets: node indices, integer array of shape ``(M, 4)`` (positively oriented).

    Returns:
        ``(Dm_inv, V0)`` of shapes ``(M, 3, 3)`` [1/m] and ``(M,)`` [m^3]
        (see :func:`~difftissue.energies.neo_hookean.rest_shape`).
    """
    return rest_shape(jnp.asarray(points)[jnp.asarray(tets)])


def fem_energy(points, tets, Dm_inv, V0, lam, mu, *, kind="linear"):
    """Total elastic energy [J] of a tet mesh: ``sum_e V0_e Psi(F_e; lam_e, mu_e)``.

    Args:
        points: current node positions [m], shape ``(N, 3)``.
        tets: node indices, integer array ``(M, 4)``.
        Dm_inv, V0: rest shapes from :func:`rest_shapes`, ``(M, 3, 3)`` and ``(M,)``.
        lam, mu: Lamé constants [Pa], scalars or per-tet arrays of shape ``(M,)``.
        kind: ``"linear"`` (:func:`linear_elastic_energy_density`) or ``"neo_hookean"``
            (:func:`neo_hookean_energy_density`; ``+inf`` when a tet is inverted).

    Returns:
        Scalar energy [J]. ``-jax.grad`` w.r.t. ``points`` gives the nodal forces [N].
    """
    try:
        density = ENERGY_DENSITIES[kind]
    except (KeyError, TypeError):
        raise DifftissueError(f"unknown FEM energy kind {kind!r}; choose one of {sorted(ENERGY_DENSITIES)}") from None
    x = jnp.asarray(points)[jnp.asarray(tets)]
    return jnp.sum(tet_energy(x, Dm_inv, V0, density, lam, mu))


def _patch_strains(x, local_tets, Dm_inv):
    """``H = F - I`` of the tets of a node patch: ``x (k, 3)`` patch nodes [m], ``local_tets
    (T, 4)`` patch-local node indices, ``Dm_inv (T, 3, 3)`` [1/m] -> ``(T, 3, 3)``."""
    return deformation_gradient(x[local_tets], Dm_inv) - jnp.eye(3, dtype=x.dtype)


def nodal_dilatation_energy(x, local_tets, Dm_inv, weights, lam):
    """Small-strain volumetric energy of a node patch, ``V_n lam/2 theta_n^2`` [J].

    ``theta_n = sum_e w_e tr(eps_e) / V_n`` is the patch's volume-averaged dilatation
    (``w_e = V0_e / 4``: each tet gives a quarter of its rest volume to each of its nodes;
    ``V_n = sum_e w_e``). With ``V0_e mu eps:eps`` per tet (:func:`linear_elastic_energy_density` with ``lam = 0``) it is ``fem_linear`` with
    the ``lambda`` term moved from the tets to the nodes.

    Args:
        x: ``(k, 3)`` positions of the patch's nodes [m] (padding repeats a node).
        local_tets: ``(T, 4)`` the patch's tets as indices into ``x`` (padding: any).
        Dm_inv: ``(T, 3, 3)`` their stress-free inverse edge matrices [1/m].
        weights: ``(T,)`` ``V0_e / 4`` [m^3], 0 for padding tets.
        lam: Lamé's first constant of the patch [Pa].
    """
    H = _patch_strains(x, local_tets, Dm_inv)
    volume = jnp.sum(weights)
    theta = jnp.sum(weights * (H[:, 0, 0] + H[:, 1, 1] + H[:, 2, 2])) / volume
    return 0.5 * lam * volume * theta * theta


def nodal_volume_energy(x, local_tets, Dm_inv, weights, lam):
    """Finite-strain volumetric energy of a node patch, ``V_n lam/2 (ln J_n)^2`` [J].

    ``J_n = sum_e w_e J_e / V_n`` is the patch's current volume over its rest volume (each tet
    gives a quarter of its volume to each of its nodes, ``w_e = V0_e / 4``, ``V_n = sum_e w_e``;
    Bonet & Burton 1998). With ``V0_e mu/2 (I1 - 3 - 2 ln J_e)`` per tet (:func:`neo_hookean_energy_density` with ``lam = 0``) it is
    ``fem_neo_hookean`` with the ``lambda (ln J)^2 / 2`` term moved from the tets to the nodes.
    ``+inf`` when ``J_n <= 0``. Arguments as :func:`nodal_dilatation_energy`.
    """
    H = _patch_strains(x, local_tets, Dm_inv)
    volume = jnp.sum(weights)
    jm1 = jnp.sum(weights * det3_minus_one(H)) / volume  # J_n - 1, accurate at small strain
    ok = jm1 > -1.0
    log_j = jnp.log1p(jnp.where(ok, jm1, 0.0))
    return jnp.where(ok, 0.5 * lam * volume * log_j * log_j, jnp.inf)


# ----------------------------------------------------------------- closed-form patch Hessians
def _shape_gradients(Dm_inv):
    """Reference gradients ``b_a`` of the 4 linear shape functions of tets, ``(..., 4, 3)``
    [1/m]: ``F = sum_a x_a b_a^T`` (``b_1..b_3`` are the rows of ``Dm_inv``, ``b_0`` minus their sum)."""
    return jnp.concatenate([-jnp.sum(Dm_inv, axis=-2, keepdims=True), Dm_inv], axis=-2)


def _scatter_patch_vector(local_tets, v, k):
    """``sum_e v_e`` scattered from tet nodes to patch nodes: ``v (T, 4, 3)`` -> ``(k, 3)``."""
    return jnp.zeros((k, 3), dtype=v.dtype).at[local_tets].add(v)


def _patch_outer(g):
    """``vec(g) vec(g)^T`` in the node-major layout of an element Hessian: ``(k, 3) -> (3k, 3k)``."""
    f = g.reshape(-1)
    return f[:, None] * f[None, :]


def nodal_dilatation_hessian(x, local_tets, Dm_inv, weights, lam):
    """Hessian ``(3k, 3k)`` [J/m^2] of :func:`nodal_dilatation_energy` (node-major rows).

    ``theta_n`` is linear in ``x`` with gradient ``sum_e (w_e / V_n) b_{e,a}`` at patch node
    ``a`` of tet ``e`` (``b`` the shape-function gradients), so the Hessian is the rank-one,
    constant ``lam V_n grad(theta_n) grad(theta_n)^T``. Arguments as
    :func:`nodal_dilatation_energy`.
    """
    k = x.shape[0]
    volume = jnp.sum(weights)
    b = _shape_gradients(Dm_inv) * (weights / volume)[:, None, None]
    grad_theta = _scatter_patch_vector(local_tets, b.astype(x.dtype), k)
    return lam * volume * _patch_outer(grad_theta)


def nodal_volume_hessian(x, local_tets, Dm_inv, weights, lam):
    """Hessian ``(3k, 3k)`` [J/m^2] of :func:`nodal_volume_energy` (node-major rows), in closed form.

    With ``g(J) = (ln J)^2 / 2`` the energy is ``lam V_n g(J_n)``, ``J_n = sum_e (w_e / V_n) J_e``, so

        H = lam V_n [g''(J_n) grad J_n grad J_n^T + g'(J_n) sum_e (w_e / V_n) hess J_e],
        g' = ln J / J,  g'' = (1 - ln J) / J^2,

    with, for tet ``e`` (``F = sum_a x_a b_a^T``), ``dJ_e/dx_a = cof(F) b_a`` and the 3x3 block
    ``d^2 J_e / dx_a dx_b = [i, j] -> eps_ijk (F (b_a x b_b))_k``. This is the exact Hessian of the
    patch energy (not a Gauss-Newton approximation) at a fraction of the memory and time of
    ``jax.hessian`` (one scatter of ``T`` 12x12 tet blocks instead of ``3k`` reverse passes over
    the patch). Zero where ``J_n <= 0`` (the energy is ``+inf`` there). Arguments as
    :func:`nodal_dilatation_energy`.
    """
    k = x.shape[0]
    dtype = x.dtype
    volume = jnp.sum(weights)
    c = (weights / volume).astype(dtype)  # (T,)
    Dm_inv = Dm_inv.astype(dtype)
    b = _shape_gradients(Dm_inv)  # (T, 4, 3)
    H = _patch_strains(x, local_tets, Dm_inv)
    F = H + jnp.eye(3, dtype=dtype)
    jm1 = jnp.sum(c * det3_minus_one(H))  # J_n - 1
    # cofactor rows cof[i] = F[i+1] x F[i+2]; dJ/dx_a = cof(F) b_a
    cof = jnp.stack([cross(F[:, 1], F[:, 2]), cross(F[:, 2], F[:, 0]), cross(F[:, 0], F[:, 1])], axis=-2)  # (T, 3, 3)
    grad_e = jnp.sum(cof[:, None, :, :] * b[:, :, None, :], axis=-1)  # (T, 4, 3)
    grad_j = _scatter_patch_vector(local_tets, c[:, None, None] * grad_e, k)  # (k, 3)
    # hess J_e: v_ab = F (b_a x b_b), block_ab = eps_ijk v_ab,k
    ab = cross(b[:, :, None, :], b[:, None, :, :])  # (T, 4, 4, 3)
    v = jnp.sum(F[:, None, None, :, :] * ab[:, :, :, None, :], axis=-1) * c[:, None, None, None]  # (T, 4, 4, 3)
    zero = jnp.zeros_like(v[..., 0])
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    blocks = jnp.stack([jnp.stack([zero, v2, -v1], -1), jnp.stack([-v2, zero, v0], -1), jnp.stack([v1, -v0, zero], -1)], -2)  # (T, 4, 4, 3, 3)
    hess_j = jnp.zeros((k, k, 3, 3), dtype=dtype).at[local_tets[:, :, None], local_tets[:, None, :]].add(blocks)
    hess_j = hess_j.transpose(0, 2, 1, 3).reshape(3 * k, 3 * k)
    ok = jm1 > -1.0
    log_j = jnp.log1p(jnp.where(ok, jm1, 0.0))
    j = 1.0 + jnp.where(ok, jm1, 0.0)
    d1 = log_j / j
    d2 = (1.0 - log_j) / (j * j)
    hess = lam * volume * (d2 * _patch_outer(grad_j) + d1 * hess_j)
    return jnp.where(ok, hess, 0.0)
