"""One generalised eigendecomposition of a linear elastic body, shared by every material.

The stiffness of a homogeneous ``fem_linear`` body (energy density ``mu eps:eps + lambda/2
tr(eps)^2``, element or nodal dilatation) is linear in the Lamé parameters:
``K(mu, lambda) = mu K_mu + lambda K_lambda``. With the prescribed components eliminated
``K_mu`` is positive definite (Korn's inequality) and ``K_lambda`` positive semi-definite, so
one generalised symmetric eigendecomposition ``K_lambda v = theta K_mu v`` (``V^T K_mu V = I``,
``V^T K_lambda V = diag(theta)``, ``theta >= 0``), computed once on the host, gives

    K(mu, lambda)^{-1} = V diag(1 / (mu + lambda theta)) V^T

for EVERY material. The condensation's rows ``Z = C K^{-1}`` and compliance ``G = Z C^T``
(:func:`~difftissue.solvers.condensed.linear_response_columns`) then cost two matrix
products with ``V``'s rows instead of a factorisation, and their material derivatives are the
products' derivatives (forward and reverse mode by JAX, no solve). Specimens that share one
mesh share one decomposition: a batch of fits pays for it once.

Scope: an :class:`~difftissue.models.FEMModel` of kind ``fem_linear`` with ONE region, no
pre-stretch (``pre_stretch = 1``: a pre-stretch changes ``K_mu`` and ``K_lambda``), concrete
connectivity and boundary conditions, at most :data:`SPECTRAL_MAX_UNKNOWNS` unknowns (``V``
holds ``3N x n_free`` float64 numbers). Anything else raises :class:`~difftissue.errors.ModelError`.
"""

from __future__ import annotations

import collections
import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse

from ..errors import ModelError
from ..materials import Material, lame_parameters
from ..models import ElasticModel, FEMModel
from ..structure_keys import hash_scenario_leaves
from .static import AUTO_DENSE_MAX, _element_data

__all__ = ["SpectralDecomposition", "spectral_decomposition", "spectral_response_columns", "spectral_unsupported", "SPECTRAL_MAX_UNKNOWNS"]

#: Largest model (3 x nodes) a decomposition is built for: ``V`` takes ``3N x n_free x 8``
#: bytes (72 MB at 3,000) and the host ``eigh`` about 20 dense Cholesky factorisations' time
#: (1.2 s CPU at 1,800 free unknowns, one thread).
SPECTRAL_MAX_UNKNOWNS = AUTO_DENSE_MAX

#: Decompositions kept by :func:`spectral_decomposition` (keyed by the model's and the
#: boundary conditions' content), least recently used dropped first.
SPECTRAL_CACHE_SIZE = 4

_CACHE: collections.OrderedDict = collections.OrderedDict()


class SpectralDecomposition(eqx.Module):
    """``K_lambda v = theta K_mu v`` of a ``fem_linear`` body with its prescribed components
    eliminated (:func:`spectral_decomposition`).

    Attributes:
        vectors: ``(3N, n)`` the ``K_mu``-orthonormal eigenvectors ``V`` on every flat degree of
            freedom, rows of prescribed components zero [m^-1/2] (``V^T K_mu V = I``, ``K_mu``
            the stiffness per pascal of shear modulus [m]).
        theta: ``(n,)`` eigenvalues ``theta >= 0`` [-].
    """

    vectors: np.ndarray
    theta: np.ndarray


def spectral_unsupported(model: ElasticModel, free=None) -> str | None:
    """Why ``model`` (with the free mask ``free``) has no spectral decomposition, or None when it has one."""
    if not isinstance(model, FEMModel) or model.kind != "fem_linear":
        return f"the spectral solver needs the linear FEM (model 'fem_linear'), got {getattr(model, 'model_name', type(model).__name__)!r}"
    if model.n_regions != 1:
        return f"the spectral solver needs one homogeneous region, the mesh has {model.n_regions} ({list(model.region_names)})"
    if 3 * model.n_nodes > SPECTRAL_MAX_UNKNOWNS:
        return f"the spectral solver is limited to {SPECTRAL_MAX_UNKNOWNS:,} unknowns (V is 3N x n dense), the model has {3 * model.n_nodes:,}"
    for a in jax.tree_util.tree_leaves(model):
        if isinstance(a, jax.core.Tracer):
            return "the spectral solver needs a concrete mesh (it is decomposed on the host)"
    if free is not None and isinstance(free, jax.core.Tracer):
        return "the spectral solver needs concrete boundary conditions (it is decomposed on the host)"
    return None


def _key(model: ElasticModel, free: np.ndarray) -> tuple:
    """The cache key of a decomposition: the model's pytree structure and leaves (hashed by
    :func:`~difftissue.structure_keys.hash_scenario_leaves`, the project's one formula) and ``free``."""
    h = hashlib.sha256()
    leaves, treedef = jax.tree_util.tree_flatten(model)
    h.update(repr(treedef).encode())
    objects = hash_scenario_leaves(h, leaves, ())
    h.update(np.ascontiguousarray(free, dtype=bool).tobytes())
    return h.hexdigest(), tuple(objects)


@eqx.filter_jit
def _element_hessians(model, X, E, nu):
    """Element Hessians and their DOFs at rest for the materials ``(E[i], nu[i])`` (one program,
    the element kernels traced once and vmapped over the materials)."""
    data = jax.vmap(lambda e, n: _element_data(model, X, Material(e, n)))(E, nu)
    return [[(hess[i], dofs[i]) for hess, dofs in data] for i in range(E.shape[0])]


def _pencil(model, X, fi):
    """Dense ``K(E = 2 Pa, nu = 0)`` (``= K_mu``) and ``K(2.5 Pa, 1/4)`` (``= K_mu + K_lambda``)
    restricted to the free DOFs ``fi``: element Hessians in one compiled program, summed on the
    host (a sparse COO sum, then dense)."""
    n3 = 3 * model.n_nodes
    out = []
    for data in _element_hessians(model, X, jnp.asarray([2.0, 2.5]), jnp.asarray([0.0, 0.25])):
        rows, cols, vals = [], [], []
        for hess, dofs in data:
            dofs = np.asarray(dofs)
            rows.append(np.repeat(dofs, dofs.shape[1], axis=1).reshape(-1))
            cols.append(np.tile(dofs, (1, dofs.shape[1])).reshape(-1))
            vals.append(np.asarray(hess).reshape(-1))
        K = scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n3, n3)).tocsr()
        out.append(K[fi][:, fi].toarray())
    return out


def spectral_decomposition(model: ElasticModel, free) -> SpectralDecomposition:
    """The generalised eigendecomposition of ``model``'s stiffness pencil (module docstring),
    computed on the host with ``scipy.linalg.eigh`` (float64) and kept in a small cache keyed by
    the model's and ``free``'s content (equal meshes share one decomposition object).

    ``K_mu`` is the Hessian at rest at ``(mu, lambda) = (1, 0)`` Pa (E = 2 Pa, nu = 0) and
    ``K_lambda = K(1, 1) - K_mu`` (E = 2.5 Pa, nu = 1/4), both restricted to the free components.

    Args:
        model: a one-region ``fem_linear`` :class:`~difftissue.models.FEMModel`, concrete.
        free: ``(N, 3)`` bool, True on free components (``BoundaryConditions.free_mask``).

    Raises:
        ModelError: a model out of scope (:func:`spectral_unsupported`), or a ``K_mu`` that is
            not positive definite (rigid modes left free by the boundary conditions).
    """
    why = spectral_unsupported(model, free)
    if why is not None:
        raise ModelError(why)
    free = np.asarray(free, dtype=bool)
    if free.shape != (model.n_nodes, 3):
        raise ModelError(f"free has shape {free.shape}, expected ({model.n_nodes}, 3)")
    key = _key(model, free)
    hit = _CACHE.pop(key, None)
    if hit is None:
        fi = np.flatnonzero(free.reshape(-1))
        if not jax.config.jax_enable_x64:
            raise ModelError("the spectral decomposition needs float64 (jax.config.update('jax_enable_x64', True))")
        X = jnp.asarray(model.rest_points, dtype=jnp.float64)
        k1, k2 = _pencil(model, X, fi)
        k_mu = k1
        k_lam = k2 - k1
        try:
            theta, v = scipy.linalg.eigh(0.5 * (k_lam + k_lam.T), 0.5 * (k_mu + k_mu.T), check_finite=True)
        except np.linalg.LinAlgError as exc:
            raise ModelError(f"the shear stiffness is not positive definite (rigid modes left free by the boundary conditions?): {exc}") from exc
        vectors = np.zeros((3 * model.n_nodes, fi.size))
        vectors[fi] = v
        # K_lambda is positive semi-definite: the round-off-sized negative eigenvalues of its
        # null space (isochoric modes, about -1e-14) are zeros.
        hit = SpectralDecomposition(vectors, np.maximum(theta, 0.0))
    _CACHE[key] = hit
    while len(_CACHE) > SPECTRAL_CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))
    return hit


def spectral_response_columns(decomposition: SpectralDecomposition, model: ElasticModel, material, dofs):
    """``(Z, G)`` of :func:`~difftissue.solvers.condensed.linear_response_columns` from a
    decomposition: ``Z = V_C D V^T``, ``G = V_C D V_C^T`` with ``D = diag(1 / (mu + lambda
    theta))`` and ``V_C`` the rows of ``dofs``. Differentiable in ``material`` (forward and
    reverse, plain JAX). The material must be homogeneous and without pre-stretch (checked:
    :class:`ModelError` when concrete, an equinox runtime error under ``jit``)."""
    p = model.region_values(material)
    pre = p.get("pre_stretch")
    pre_y = p.get("pre_stretch_y")
    stretched = [a for a in (pre, pre_y) if a is not None]
    concrete = not any(isinstance(a, jax.core.Tracer) for a in stretched)
    if concrete and any(np.any(np.asarray(a) != 1.0) for a in stretched):
        raise ModelError("the spectral solver has no pre-stretch (pre_stretch must be 1): use linear_solver 'dense' or 'sparse'")
    lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
    lam, mu = lam[0], mu[0]
    if not concrete:
        bad = jnp.any(jnp.stack([jnp.any(a != 1.0) for a in stretched]))
        mu = eqx.error_if(mu, bad, "the spectral solver has no pre-stretch (pre_stretch must be 1): use linear_solver 'dense' or 'sparse'")
    V = jnp.asarray(decomposition.vectors)
    theta = jnp.asarray(decomposition.theta, dtype=V.dtype)
    d = 1.0 / (mu + lam * theta)
    VC = V[jnp.asarray(dofs)]  # (a NumPy or a traced index array)
    W = VC * d[None, :]
    Z = W @ V.T
    G = W @ VC.T
    return Z, 0.5 * (G + G.T)
