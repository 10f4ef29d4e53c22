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

__all__ = [
    "linear_elastic_energy_density",
    "neo_hookean_energy_density",
    "tet_energy",
    "rest_shapes",
    "fem_energy",
    "ENERGY_DENSITIES",
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
