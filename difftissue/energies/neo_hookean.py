"""Deformation gradient of a linear tet and the stable neo-Hookean constraints (DESIGN.md §3.2).

Macklin & Müller (2021), "A constraint-based formulation of stable neo-Hookean materials":
two XPBD constraints per tet,

    C_D = sqrt(tr(F^T F)),        alpha_D = 1 / (mu V0),
    C_H = det F - gamma,          alpha_H = 1 / (lam' V0),   gamma = 1 + mu / lam',

whose XPBD energy ``C_D^2 / (2 alpha_D) + C_H^2 / (2 alpha_H)`` is ``V0`` times the density
:func:`stable_neo_hookean_energy_density` up to a constant. Linearised at ``F = I`` the
stress is ``2 mu eps + (lam' - mu) tr(eps) I``: the effective Lamé constants are
``(lam' - mu, mu)``. **Use lam' = lambda + mu** to reproduce a linear material
``(lambda, mu)`` at small strain; with ``lam' = lambda`` the effective Poisson ratio is
``(4 nu - 1) / (4 nu)`` (1/6 at nu = 0.3, negative below nu = 1/4).

Shapes: a tet ``x`` is ``(..., 4, 3)`` [m], ``F`` and ``Dm_inv`` are ``(..., 3, 3)``; every
function broadcasts over the leading batch dimensions ``(...)`` and material parameters
broadcast against ``(...)``.
"""

from __future__ import annotations

import jax.numpy as jnp

from .springs import safe_norm
from .volume import array_namespace, cross, dot, tet_signed_volume

__all__ = [
    "det3",
    "det3_minus_one",
    "first_invariant_minus_three",
    "edge_matrix",
    "rest_shape",
    "deformation_gradient",
    "stable_neo_hookean_gamma",
    "stable_neo_hookean_constraints",
    "stable_neo_hookean_energy_density",
]


def det3(A):
    """Determinant of ``(..., 3, 3)`` matrices, ``a0 . (a1 x a2)`` over the rows ``a_i``.

    A polynomial written with elementwise products only: smooth everywhere (also at
    det = 0, unlike an LU-based determinant) and free of matrix-unit (TF32) rounding on
    accelerators in float32.
    """
    A = array_namespace(A).asarray(A)
    return dot(A[..., 0, :], cross(A[..., 1, :], A[..., 2, :]))


def det3_minus_one(H):
    """``det(I + H) - 1`` of ``(..., 3, 3)`` matrices ``H`` without cancellation for small ``H``.

    ``det(I + H) = 1 + tr H + (tr(H)^2 - tr(H H)) / 2 + det H``; use it with ``H = F - I``
    when ``F`` is close to a rotation-free identity (small strain), where ``det F - 1``
    would lose the leading digits.
    """
    tr = H[..., 0, 0] + H[..., 1, 1] + H[..., 2, 2]
    tr_hh = jnp.sum(H * jnp.swapaxes(H, -1, -2), axis=(-2, -1))
    return tr + 0.5 * (tr * tr - tr_hh) + det3(H)


def first_invariant_minus_three(H):
    """``tr(F^T F) - 3 = 2 tr H + |H|^2`` for ``F = I + H`` (no cancellation for small ``H``)."""
    return 2.0 * (H[..., 0, 0] + H[..., 1, 1] + H[..., 2, 2]) + jnp.sum(H * H, axis=(-2, -1))


def _adjugate3(A):
    """Adjugate ``adj A = det(A) A^-1`` of ``(..., 3, 3)`` matrices: its columns are the
    cross products ``a1 x a2, a2 x a0, a0 x a1`` of the rows ``a_i`` of ``A``."""
    a0, a1, a2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    return array_namespace(A).stack([cross(a1, a2), cross(a2, a0), cross(a0, a1)], axis=-1)


def _matmul3(A, B):
    """``A @ B`` for ``(..., 3, 3)`` matrices by elementwise products and sums (no TF32 matmul)."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def edge_matrix(x):
    """Edge matrix ``D`` [m] with columns ``x1 - x0, x2 - x0, x3 - x0``: ``(..., 4, 3) -> (..., 3, 3)``."""
    return array_namespace(x).swapaxes(x[..., 1:, :] - x[..., :1, :], -1, -2)


def rest_shape(X):
    """Inverse rest edge matrix and rest volume of a tet.

    Args:
        X: rest node positions [m], shape ``(..., 4, 3)``, positively oriented.

    Returns:
        ``(Dm_inv, V0)``: ``Dm_inv`` [1/m] of shape ``(..., 3, 3)`` is the inverse of the
        matrix ``Dm`` whose columns are ``X1 - X0, X2 - X0, X3 - X0``; ``V0 = det(Dm) / 6``
        [m^3] of shape ``(...)`` is the signed rest volume
        (:func:`difftissue.energies.volume.tet_signed_volume`). A degenerate rest tet gives
        non-finite values: validate the mesh first (:class:`difftissue.mesh.TetMesh` does).
    """
    Dm = edge_matrix(X)
    return _adjugate3(Dm) / det3(Dm)[..., None, None], tet_signed_volume(X)


def deformation_gradient(x, Dm_inv):
    """Deformation gradient ``F = Ds Dm^-1`` [-] of a linear tet.

    Args:
        x: current node positions [m], shape ``(..., 4, 3)``.
        Dm_inv: inverse rest edge matrix [1/m], shape ``(..., 3, 3)`` (:func:`rest_shape`).

    Returns:
        ``F``, shape ``(..., 3, 3)``. The product is written elementwise, so float32 runs on
        GPUs keep full float32 precision (a default-precision matmul may use TF32).
    """
    return _matmul3(edge_matrix(x), Dm_inv)


def stable_neo_hookean_gamma(mu, lam_shift):
    """Rest-stability offset ``gamma = 1 + mu / lam'`` [-] of the hydrostatic constraint.

    It makes the stress vanish at ``F = I``. ``mu``, ``lam_shift`` in Pa.
    """
    return 1.0 + mu / lam_shift


def stable_neo_hookean_constraints(F, gamma):
    """The two stable neo-Hookean XPBD constraints ``(C_D, C_H)`` [-].

    ``C_D = sqrt(tr(F^T F))`` (the Frobenius norm of ``F``, with a finite gradient at
    ``F = 0``) and ``C_H = det F - gamma``. Their compliances are ``alpha_D = 1 / (mu V0)``
    and ``alpha_H = 1 / (lam' V0)`` with ``gamma = 1 + mu / lam'``
    (:func:`difftissue.materials.neo_hookean_xpbd_compliances`).

    Args:
        F: deformation gradients, shape ``(..., 3, 3)``.
        gamma: offset ``gamma`` [-] (:func:`stable_neo_hookean_gamma`), broadcasting against ``(...)``.

    Returns:
        ``(C_D, C_H)``, each of shape ``(...)``.
    """
    return safe_norm(F, axis=(-2, -1)), det3(F) - gamma


def stable_neo_hookean_energy_density(F, mu, lam_shift):
    """Stable neo-Hookean strain-energy density [J/m^3 = Pa].

        Psi = mu/2 (tr(F^T F) - 3) + lam'/2 (det F - gamma)^2 - mu^2 / (2 lam'),
        gamma = 1 + mu / lam'.

    ``Psi(I) = 0`` and the stress vanishes at ``F = I``. It is evaluated in the equivalent
    form ``mu/2 (I1 - 3) - mu (J - 1) + lam'/2 (J - 1)^2`` with ``I1 - 3`` and ``J - 1``
    expanded in ``H = F - I``, which keeps full relative precision at small strain. The density is smooth for every
    ``F`` (inverted elements included: no log, no guard needed). It differs from the XPBD
    energy of :func:`stable_neo_hookean_constraints` per unit rest volume only by the
    constant ``3 mu / 2 + mu^2 / (2 lam')``.

    Small-strain limit: Lamé constants ``(lam' - mu, mu)``. Pass
    ``lam_shift = lambda + mu`` for a material with Lamé constants ``(lambda, mu)``.
    Large-strain behaviour is not that of :func:`difftissue.energies.fem.neo_hookean_energy_density`
    (a different invariant form), only the small-strain response agrees.

    Args:
        F: deformation gradients, shape ``(..., 3, 3)``.
        mu: shear modulus [Pa].
        lam_shift: hydrostatic stiffness ``lam'`` [Pa], > 0 (normally ``lambda + mu``).

    Returns:
        Energy density [Pa], shape ``(...)``.
    """
    # Expanded about F = I so that small strains keep their digits:
    # lam'/2 (J - gamma)^2 - mu^2/(2 lam') = lam'/2 (J - 1)^2 - mu (J - 1).
    H = F - jnp.eye(3, dtype=F.dtype)
    jm1 = det3_minus_one(H)
    return 0.5 * mu * first_invariant_minus_three(H) - mu * jm1 + 0.5 * lam_shift * jm1 * jm1
