"""Cubic springs between two nodes (DESIGN.md §3.1).

A spring of rest length ``L0`` [m] between nodes ``xi`` and ``xj`` [m] with extension
``e = |xj - xi| - L0`` [m] stores ``U = k e^2 / 2 + a e^4 / 4`` [J]; its tension is
``dU/de = k e + a e^3`` [N] (``k`` in N/m, ``a`` in N/m^3). Forces on the nodes are
``-jax.grad(U)``.

All functions are pure and broadcast over leading batch dimensions: ``xi``, ``xj`` have
shape ``(..., 3)``; rest lengths and coefficients broadcast against ``(...)``.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["safe_norm", "spring_extension", "cubic_spring_energy", "cubic_spring_hessian"]


def safe_norm(v, axis=-1, eps=0.0):
    """Euclidean norm ``|v|`` along ``axis`` whose gradient is finite at ``v = 0``.

    ``jnp.linalg.norm`` has gradient ``v / |v|`` = NaN at zero (e.g. coincident nodes).
    Here the zero (or small) vectors take a separate branch selected with the "double
    ``where``" trick, so neither the value nor any derivative of the unused branch leaks.

    Args:
        v: array of vectors (any units), reduced along ``axis``.
        axis: axis (or tuple of axes) holding the vector components.
        eps: radius (same units as ``v``) below which the norm is replaced by the smooth
            ``(|v|^2 + eps^2) / (2 eps)`` (value and gradient continuous at ``|v| = eps``,
            gradient 0 at ``v = 0``). The default 0 keeps the exact norm for every
            non-zero ``v`` and returns 0 with gradient 0 at ``v = 0`` exactly.

    Returns:
        ``|v|`` with ``axis`` removed.
    """
    sq = jnp.sum(v * v, axis=axis)
    eps = jnp.asarray(eps, dtype=sq.dtype)
    eps2 = eps * eps
    outside = sq > eps2
    norm = jnp.sqrt(jnp.where(outside, sq, 1.0))
    has_eps = eps > 0
    inner = jnp.where(has_eps, (sq + eps2) / (2.0 * jnp.where(has_eps, eps, 1.0)), 0.0)
    return jnp.where(outside, norm, inner)


def spring_extension(xi, xj, rest_length):
    """Extension ``e = |xj - xi| - L0`` [m] of a spring (gradient finite at zero length).

    Args:
        xi, xj: end positions [m], shape ``(..., 3)``.
        rest_length: rest length ``L0`` [m], broadcasting against ``(...)``.

    Returns:
        Extension [m], shape ``(...)``; negative in compression.
    """
    return safe_norm(xj - xi) - rest_length


def cubic_spring_energy(xi, xj, rest_length, stiffness, cubic):
    """Energy ``U = k e^2 / 2 + a e^4 / 4`` [J] of a cubic spring, ``e = |xj - xi| - L0``.

    The tension is ``k e + a e^3`` [N]; the force on ``xj`` is ``-(k e + a e^3) n`` with
    ``n = (xj - xi) / |xj - xi|`` (``-jax.grad`` of this function). At zero length the
    direction is undefined and the gradient is 0 (finite).

    Args:
        xi, xj: end positions [m], shape ``(..., 3)``.
        rest_length: rest length ``L0`` [m].
        stiffness: linear stiffness ``k`` [N/m].
        cubic: cubic coefficient ``a`` [N/m^3] (see
            :func:`difftissue.materials.cubic_spring_coefficient`).

    Returns:
        Energy [J], shape ``(...)`` (broadcast of the arguments).
    """
    e = spring_extension(xi, xj, rest_length)
    e2 = e * e
    return 0.5 * stiffness * e2 + 0.25 * cubic * e2 * e2


def cubic_spring_hessian(xi, xj, rest_length, stiffness, cubic):
    """Hessian ``(..., 6, 6)`` [J/m^2] of :func:`cubic_spring_energy` with respect to
    ``(xi, xj)`` (node-major: rows 0-2 are ``xi``, 3-5 are ``xj``), in closed form.

    With ``d = xj - xi``, ``l = |d|``, ``n = d / l``, tension ``t = k e + a e^3`` and tangent
    stiffness ``s = k + 3 a e^2`` (``e = l - L0``), the Hessian with respect to ``d`` is
    ``K = s n n^T + (t / l) (I - n n^T)`` and with respect to the two nodes
    ``[[K, -K], [-K, K]]``: the exact second derivative, a few dozen operations instead of the
    reverse-over-forward passes of ``jax.hessian`` (which the tests compare it with). At zero
    length it is 0, as ``jax.hessian`` of the energy (its :func:`safe_norm` branch) gives.

    Args:
        xi, xj: end positions [m], shape ``(..., 3)``.
        rest_length: rest length ``L0`` [m].
        stiffness: linear stiffness ``k`` [N/m].
        cubic: cubic coefficient ``a`` [N/m^3].

    Returns:
        ``(..., 6, 6)`` [J/m^2].
    """
    d = xj - xi
    sq = jnp.sum(d * d, axis=-1)
    positive = sq > 0.0
    length = jnp.sqrt(jnp.where(positive, sq, 1.0))
    e = length - rest_length
    tension = stiffness * e + cubic * e * e * e
    tangent = stiffness + 3.0 * cubic * e * e
    n = d / length[..., None]
    nn = n[..., :, None] * n[..., None, :]
    eye = jnp.eye(3, dtype=d.dtype)
    K = tangent[..., None, None] * nn + (tension / length)[..., None, None] * (eye - nn)
    K = jnp.where(positive[..., None, None], K, 0.0)
    top = jnp.concatenate([K, -K], axis=-1)
    return jnp.concatenate([top, -top], axis=-2)
