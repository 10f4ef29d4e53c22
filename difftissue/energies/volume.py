"""Tetrahedral volume constraint and its energy (DESIGN.md §3.2, Macklin et al. 2016).

A tet ``x`` has shape ``(..., 4, 3)`` [m] with nodes ``x0..x3`` positively oriented:
``V = (x1 - x0) . ((x2 - x0) x (x3 - x0)) / 6 > 0``. All functions broadcast over the
leading batch dimensions ``(...)``; parameters broadcast against ``(...)``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["array_namespace", "cross", "dot", "tet_signed_volume", "volume_constraint", "volume_energy"]


def array_namespace(*arrays):
    """NumPy when every argument is NumPy (floats, ints, NumPy arrays and scalars: computed on
    the host, nothing dispatched to JAX, no one-operation program compiled), else ``jax.numpy``
    (JAX arrays, tracers). The geometry helpers here and in :mod:`.neo_hookean` take both."""
    if all(isinstance(a, (float, int, np.ndarray, np.generic)) for a in arrays):
        return np
    return jnp


def cross(a, b):
    """Cross product ``a x b`` of arrays of 3-vectors ``(..., 3)``, written out explicitly."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return array_namespace(a, b).stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def dot(a, b):
    """Dot product of arrays of 3-vectors ``(..., 3) -> (...)``."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def tet_signed_volume(x):
    """Signed volume ``V = (x1 - x0) . ((x2 - x0) x (x3 - x0)) / 6`` [m^3].

    Args:
        x: tet node positions [m], shape ``(..., 4, 3)``.

    Returns:
        Signed volume [m^3], shape ``(...)``; negative for an inverted tet.

    Host-side NumPy code (no tracing) uses :func:`difftissue.mesh.signed_volumes`, the same
    formula (equal to 3e-16 of the largest volume, tested).
    """
    x0 = x[..., 0, :]
    return dot(x[..., 1, :] - x0, cross(x[..., 2, :] - x0, x[..., 3, :] - x0)) / 6.0


def volume_constraint(x, rest_volume):
    """XPBD volume constraint ``C = V - V0`` [m^3].

    Args:
        x: tet node positions [m], shape ``(..., 4, 3)``.
        rest_volume: rest volume ``V0`` [m^3], broadcasting against ``(...)``.
    """
    return tet_signed_volume(x) - rest_volume


def volume_energy(x, rest_volume, bulk_stiffness):
    """Volume energy ``U = K (V - V0)^2 / (2 V0)`` [J].

    This is the XPBD volume constraint ``C = V - V0`` with compliance ``alpha = V0 / K``
    (``U = C^2 / (2 alpha)``, :func:`difftissue.materials.volume_compliance`). For a small
    uniform dilatation it is ``K V0 (tr eps)^2 / 2``: ``K`` [Pa] is the bulk stiffness the
    term adds. Inversion is not guarded: an inverted tet (``V < 0``) simply has a large
    energy. ``V0`` must be positive.

    Args:
        x: tet node positions [m], shape ``(..., 4, 3)``.
        rest_volume: rest volume ``V0`` [m^3] (> 0), broadcasting against ``(...)``.
        bulk_stiffness: bulk stiffness ``K`` [Pa].

    Returns:
        Energy [J], shape ``(...)``.
    """
    c = volume_constraint(x, rest_volume)
    return bulk_stiffness * c * c / (2.0 * rest_volume)
