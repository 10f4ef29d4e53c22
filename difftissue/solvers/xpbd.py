"""Extended position-based dynamics (XPBD, Macklin et al. 2016), differentiable.

Constraint sets (equinox Modules; topology is data, parameters are differentiable leaves):

- :class:`DistanceConstraints` -- cubic springs as ``C = e sqrt(1 + a e^2 / (2 k))``,
  ``alpha = 1/k`` (``1/2 C^2 / alpha = k e^2/2 + a e^4/4``; ``a = 0`` is the standard XPBD
  distance constraint).
- :class:`VolumeConstraints` -- ``C = V - V0``, ``alpha = V0 / K`` on tets (explicit cross
  products) or trilinear hexahedral cells (:func:`difftissue.models.hexahedron_volume`).
- :class:`StableNeoHookeanConstraints` -- Macklin & Müller (2021), ``C_D = |F|``,
  ``C_H = det F - gamma`` with ``lambda' = lambda + mu``.

:func:`xpbd_constraints` builds them from a model; :func:`xpbd_simulate` runs frames of XPBD
(unrolled ``lax.scan`` with ``jax.checkpoint``: reverse-mode differentiable w.r.t. the
material, the prescribed displacements and the forces); :func:`xpbd_quasi_static` repeats
fully damped steps until the positions stop changing.

One substep of length ``h``:

    x~ = x + h v + h^2 W f_ext                      (W: per-DOF inverse masses, 0 where fixed)
    lambda = 0                                      (or the previous multipliers: warm_start)
    repeat `iterations` times, constraint by constraint (Gauss-Seidel, graph-coloured) or
    set by set (Jacobi):
        dlambda = (-C - alpha~ lambda) / (sum_i w_i |grad_i C|^2 + alpha~),  alpha~ = alpha / h^2
        lambda += dlambda;  x_i += w_i grad_i C dlambda
    v = (x_new - x) / h

Internally the update is written in the stiffness form ``beta = h^2 / alpha``:
``dlambda = -(beta C + lambda) / (beta sum w |grad C|^2 + 1)``, finite for zero stiffness
(``alpha = inf``: the constraint does nothing) and for rigid constraints (``alpha = 0``).
Inside the loops positions are ``(N, 4)`` rows (x, y, z and the node's inverse mass): one
gather and one scatter row per node of a constraint, the cheapest layout measured on
XLA:CPU (indirect rows dominate the cost). The Jacobi iteration is differentiated through an
arithmetically identical copy on x, y, z component arrays (``custom_jvp``): reverse mode
through it is about 2.5x faster on XLA:CPU than through the rows. See ``docs/xpbd.md`` and
``docs/performance.md``.
"""

from __future__ import annotations

import abc
import dataclasses
import hashlib
from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..boundary import BoundaryConditions, _validate_values
from ..errors import ConvergenceError, ModelError
from ..materials import Material, _is_concrete, lame_parameters
from ..models import ElasticModel, SpringVolumeModel, StableNeoHookeanModel, hexahedron_volume

__all__ = [
    "ConstraintSet",
    "DistanceConstraints",
    "VolumeConstraints",
    "StableNeoHookeanConstraints",
    "xpbd_constraints",
    "color_constraints",
    "XPBDSettings",
    "XPBDState",
    "XPBDQuasiStaticSolution",
    "xpbd_simulate",
    "xpbd_simulate_constraints",
    "xpbd_quasi_static",
    "xpbd_quasi_static_constraints",
    "constraint_energy",
]

METHODS = ("gauss_seidel", "jacobi")


# ----------------------------------------------------------------------- colouring
_COLOR_CACHE: dict = {}


def _greedy_colors(nodes: np.ndarray) -> np.ndarray:
    """Colour of each constraint: first fit, then rebalanced to equalise colour sizes."""
    S = nodes.shape[0]
    n_nodes = int(nodes.max()) + 1 if S else 0
    rows = nodes.tolist()
    used = [0] * n_nodes
    first = [0] * S
    for c, row in enumerate(rows):
        m = 0
        for v in row:
            m |= used[v]
        col = (~m & (m + 1)).bit_length() - 1
        first[c] = col
        b = 1 << col
        for v in row:
            used[v] |= b
    n_colors = max(first) + 1 if S else 0
    # Second pass: same number of colours, each constraint to the least-filled allowed colour
    # (fewer masked dummies when the colours are padded to one width).
    used = [0] * n_nodes
    counts = [0] * n_colors
    out = np.empty(S, dtype=np.int64)
    for c, row in enumerate(rows):
        m = 0
        for v in row:
            m |= used[v]
        best, best_n = -1, S + 1
        for col in range(n_colors):
            if not (m >> col) & 1 and counts[col] < best_n:
                best, best_n = col, counts[col]
        if best < 0:  # cannot happen for the first-fit count, kept for safety
            best = n_colors
            n_colors += 1
            counts.append(0)
        out[c] = best
        counts[best] += 1
        b = 1 << best
        for v in row:
            used[v] |= b
    return out


def color_constraints(nodes) -> np.ndarray:
    """Greedy graph colouring of constraints on the host (NumPy): constraints of one colour
    share no node, so they can be projected in parallel (Gauss-Seidel between colours).

    Args:
        nodes: ``(S, k)`` node indices of the constraints (concrete, not traced).

    Returns:
        ``(n_colors, width)`` int32 constraint indices, one row per colour, padded with -1 to
        the size of the largest colour. Results are cached by content.
    """
    nodes = np.asarray(nodes)
    if nodes.ndim != 2 or nodes.shape[0] == 0:
        raise ModelError(f"constraint nodes must be a non-empty (S, k) integer array, got shape {nodes.shape}")
    if not np.issubdtype(nodes.dtype, np.integer):
        raise ModelError(f"constraint nodes must be integers, got {nodes.dtype}")
    if nodes.min() < 0:
        raise ModelError("constraint node indices must be >= 0")
    key = (nodes.shape, hashlib.sha1(np.ascontiguousarray(nodes, dtype=np.int64).tobytes()).hexdigest())
    hit = _COLOR_CACHE.get(key)
    if hit is not None:
        return hit
    col = _greedy_colors(nodes)
    n_colors = int(col.max()) + 1
    sizes = np.bincount(col, minlength=n_colors)
    width = int(sizes.max())
    table = np.full((n_colors, width), -1, dtype=np.int32)
    order = np.argsort(col, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    pos = np.arange(len(col)) - np.repeat(starts, sizes)
    table[col[order], pos] = order
    table.setflags(write=False)
    if len(_COLOR_CACHE) > 64:
        _COLOR_CACHE.clear()
    _COLOR_CACHE[key] = table
    return table


def _maybe_colors(nodes):
    return color_constraints(nodes) if _is_concrete(nodes) else None


# ------------------------------------------------------------------ small vector algebra
def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _neg(a):
    return (-a[0], -a[1], -a[2])


def _scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


# ---------------------------------------------------------------------- constraint rows
def _distance_linear(xs, params):
    (rest,) = params
    d = _sub(xs[1], xs[0])
    l2 = _dot(d, d)
    pos = l2 > 0
    inv = jnp.where(pos, jax.lax.rsqrt(jnp.where(pos, l2, 1.0)), 0.0)
    g = _scale(d, inv)
    return l2 * inv - rest, [_neg(g), g]


def _distance_cubic(xs, params):
    rest, q = params  # q = a / (2 k) [1/m^2]
    d = _sub(xs[1], xs[0])
    l2 = _dot(d, d)
    pos = l2 > 0
    inv = jnp.where(pos, jax.lax.rsqrt(jnp.where(pos, l2, 1.0)), 0.0)
    e = l2 * inv - rest
    s = jnp.maximum(1.0 + q * e * e, 1e-12)  # guard for softening (a < 0) springs far out
    r = jax.lax.rsqrt(s)
    C = e * s * r
    dCde = (1.0 + 2.0 * q * e * e) * r
    g = _scale(d, inv * dCde)
    return C, [_neg(g), g]


def _tet_volume(xs, params):
    (V0,) = params
    x0 = xs[0]
    e1, e2, e3 = _sub(xs[1], x0), _sub(xs[2], x0), _sub(xs[3], x0)
    g1 = _scale(_cross(e2, e3), 1.0 / 6.0)
    g2 = _scale(_cross(e3, e1), 1.0 / 6.0)
    g3 = _scale(_cross(e1, e2), 1.0 / 6.0)
    g0 = _neg(_add(_add(g1, g2), g3))
    return _dot(e1, g1) - V0, [g0, g1, g2, g3]


def _hex_volume(xs, params):
    (V0,) = params
    x = jnp.stack([jnp.stack(p, axis=-1) for p in xs], axis=-2)  # (..., 8, 3)
    lead = x.shape[:-2]
    V, g = jax.vmap(jax.value_and_grad(hexahedron_volume))(x.reshape(-1, 8, 3))
    V = V.reshape(lead)
    g = g.reshape(lead + (8, 3))
    return V - V0, [(g[..., k, 0], g[..., k, 1], g[..., k, 2]) for k in range(8)]


def _tet_columns(xs, Dm_inv):
    """Columns ``f_j`` of ``F = Ds Dm^-1`` as component triples, and the rows of ``Dm^-1``."""
    x0 = xs[0]
    e = [_sub(xs[k + 1], x0) for k in range(3)]
    B = [[Dm_inv[..., k, j] for j in range(3)] for k in range(3)]
    f = []
    for j in range(3):
        col = _scale(e[0], B[0][j])
        col = _add(col, _scale(e[1], B[1][j]))
        col = _add(col, _scale(e[2], B[2][j]))
        f.append(col)
    return f, B


def _node_gradients(dF_cols, B):
    """``dC/dx`` of the 4 tet nodes from ``dC/dF`` given by columns."""
    g = []
    for k in range(3):
        v = _scale(dF_cols[0], B[k][0])
        v = _add(v, _scale(dF_cols[1], B[k][1]))
        v = _add(v, _scale(dF_cols[2], B[k][2]))
        g.append(v)
    return [_neg(_add(_add(g[0], g[1]), g[2]))] + g


def _snh_deviatoric(xs, params):
    Dm_inv, _ = params
    f, B = _tet_columns(xs, Dm_inv)
    sq = _dot(f[0], f[0]) + _dot(f[1], f[1]) + _dot(f[2], f[2])
    pos = sq > 0
    inv = jnp.where(pos, jax.lax.rsqrt(jnp.where(pos, sq, 1.0)), 0.0)
    return sq * inv, _node_gradients([_scale(c, inv) for c in f], B)


def _snh_hydrostatic(xs, params):
    Dm_inv, gamma = params
    f, B = _tet_columns(xs, Dm_inv)
    c0, c1, c2 = _cross(f[1], f[2]), _cross(f[2], f[0]), _cross(f[0], f[1])
    return _dot(f[0], c0) - gamma, _node_gradients([c0, c1, c2], B)


class _Row(NamedTuple):
    """One kind of scalar constraint on the nodes of a set."""

    evaluate: Callable  # (xs: k component triples, params) -> (C, k gradient triples)
    params: tuple  # per-constraint parameters, leading dimension S
    stiffness: jax.Array  # 1 / alpha, (S,)


# ------------------------------------------------------------------- constraint sets
class ConstraintSet(eqx.Module):
    """A family of XPBD constraints on ``k`` nodes each (abstract).

    ``nodes`` (``(S, k)``) is topology, ``colors`` its host-computed graph colouring
    (:func:`color_constraints`, ``None`` when the set was built from traced indices: then
    only the Jacobi method can use it). The other fields are differentiable parameters.
    """

    @property
    @abc.abstractmethod
    def nodes(self):
        """``(S, k)`` node indices."""

    @property
    def n_constraints(self) -> int:
        return int(self.nodes.shape[0])

    @abc.abstractmethod
    def _rows(self) -> tuple[_Row, ...]:
        """The scalar constraint kinds of the set (projected one after the other)."""

    def values(self, x):
        """Constraint values ``(rows, S)`` at positions ``x`` ``(N, 3)`` [m]."""
        P = (x[:, 0], x[:, 1], x[:, 2])
        idx = jnp.asarray(self.nodes)
        xs = [tuple(p[idx[:, k]] for p in P) for k in range(idx.shape[1])]
        return jnp.stack([row.evaluate(xs, row.params)[0] for row in self._rows()])

    def energy(self, x):
        """XPBD energy ``1/2 sum C^2 / alpha`` [J] at positions ``x`` ``(N, 3)`` [m]."""
        C = self.values(x)
        k = jnp.stack([jnp.asarray(row.stiffness) for row in self._rows()])
        return 0.5 * jnp.sum(k * C * C)


class DistanceConstraints(ConstraintSet):
    """Cubic springs as XPBD distance constraints.

    ``C = e sqrt(1 + a e^2 / (2 k))`` with ``e = |xj - xi| - L0`` (safe norm) and compliance
    ``alpha = 1 / k``, so ``1/2 C^2 / alpha = k e^2 / 2 + a e^4 / 4``: exactly the cubic
    spring energy of :class:`~difftissue.models.SpringVolumeModel`. ``cubic=None`` (or 0)
    is the standard XPBD distance constraint ``C = e``. Softening springs (``a < 0``) are
    only valid while ``1 + a e^2 / (2 k) > 0``.

    Attributes:
        pairs: ``(S, 2)`` node indices.
        rest_length: ``(S,)`` [m].
        stiffness: ``(S,)`` ``k`` [N/m], > 0.
        cubic: ``(S,)`` ``a`` [N/m^3] or ``None`` (linear springs, a little faster).
        colors: graph colouring (computed from ``pairs`` when not given).
    """

    pairs: np.ndarray
    rest_length: jax.Array
    stiffness: jax.Array
    cubic: jax.Array | None
    colors: np.ndarray | None

    def __init__(self, pairs, rest_length, stiffness, cubic=None, *, colors=None):
        pairs = np.asarray(pairs, dtype=np.int32) if _is_concrete(pairs) else pairs
        if pairs.ndim != 2 or pairs.shape[1] != 2:
            raise ModelError(f"distance constraints need pairs of shape (S, 2), got {pairs.shape}")
        S = pairs.shape[0]
        self.pairs = pairs
        self.rest_length = _per_constraint(rest_length, S, "rest_length")
        self.stiffness = _per_constraint(stiffness, S, "stiffness")
        self.cubic = None if cubic is None else _per_constraint(cubic, S, "cubic")
        self.colors = _maybe_colors(pairs) if colors is None else colors

    @property
    def nodes(self):
        return self.pairs

    def _rows(self):
        if self.cubic is None:
            return (_Row(_distance_linear, (self.rest_length,), self.stiffness),)
        k = self.stiffness
        q = jnp.where(k > 0, self.cubic / (2.0 * jnp.where(k > 0, k, 1.0)), 0.0)
        return (_Row(_distance_cubic, (self.rest_length, q), k),)


class VolumeConstraints(ConstraintSet):
    """Volume constraints ``C = V - V0`` with compliance ``alpha = V0 / K``
    (energy ``K (V - V0)^2 / (2 V0)``).

    Attributes:
        elements: ``(E, 4)`` positively oriented tets (explicit cross/dot products) or
            ``(E, 8)`` trilinear hexahedral cells (local order ``v = bx + 2 by + 4 bz``;
            volume by :func:`~difftissue.models.hexahedron_volume`, gradient by ``jax.grad``).
        rest_volume: ``(E,)`` ``V0`` [m^3], > 0.
        bulk: ``(E,)`` ``K`` [Pa], >= 0 (0 switches a constraint off).
        colors: graph colouring (computed from ``elements`` when not given).
    """

    elements: np.ndarray
    rest_volume: jax.Array
    bulk: jax.Array
    colors: np.ndarray | None

    def __init__(self, elements, rest_volume, bulk, *, colors=None):
        elements = np.asarray(elements, dtype=np.int32) if _is_concrete(elements) else elements
        if elements.ndim != 2 or elements.shape[1] not in (4, 8):
            raise ModelError(f"volume constraints need (E, 4) tets or (E, 8) hexahedra, got shape {elements.shape}")
        E = elements.shape[0]
        self.elements = elements
        self.rest_volume = _per_constraint(rest_volume, E, "rest_volume")
        self.bulk = _per_constraint(bulk, E, "bulk")
        self.colors = _maybe_colors(elements) if colors is None else colors

    @property
    def nodes(self):
        return self.elements

    def _rows(self):
        fn = _tet_volume if self.elements.shape[1] == 4 else _hex_volume
        return (_Row(fn, (self.rest_volume,), self.bulk / self.rest_volume),)


class StableNeoHookeanConstraints(ConstraintSet):
    """Stable neo-Hookean tets (Macklin & Müller 2021): per tet

        C_D = sqrt(tr F^T F),  alpha_D = 1 / (mu V0);
        C_H = det F - gamma,   alpha_H = 1 / (lam' V0),  gamma = 1 + mu / lam'.

    ``1/2 sum C^2 / alpha`` is :class:`~difftissue.models.StableNeoHookeanModel`'s energy plus
    the constant ``V0 (3 mu / 2 + mu^2 / (2 lam'))`` per tet. The two constraints of a tet
    are projected one after the other (deviatoric first).

    Attributes:
        tets: ``(M, 4)``; Dm_inv ``(M, 3, 3)`` [1/m]; rest_volume ``(M,)`` [m^3];
        mu ``(M,)`` [Pa]; lam_shift ``(M,)`` ``lam' = lambda + mu`` [Pa].
    """

    tets: np.ndarray
    Dm_inv: jax.Array
    rest_volume: jax.Array
    mu: jax.Array
    lam_shift: jax.Array
    colors: np.ndarray | None

    def __init__(self, tets, Dm_inv, rest_volume, mu, lam_shift, *, colors=None):
        tets = np.asarray(tets, dtype=np.int32) if _is_concrete(tets) else tets
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ModelError(f"stable neo-Hookean constraints need (M, 4) tets, got shape {tets.shape}")
        M = tets.shape[0]
        self.tets = tets
        self.Dm_inv = jnp.asarray(Dm_inv, dtype=_float_dtype())
        if self.Dm_inv.shape != (M, 3, 3):
            raise ModelError(f"Dm_inv must have shape ({M}, 3, 3), got {self.Dm_inv.shape}")
        self.rest_volume = _per_constraint(rest_volume, M, "rest_volume")
        self.mu = _per_constraint(mu, M, "mu")
        self.lam_shift = _per_constraint(lam_shift, M, "lam_shift")
        self.colors = _maybe_colors(tets) if colors is None else colors

    @property
    def nodes(self):
        return self.tets

    def _rows(self):
        gamma = 1.0 + self.mu / self.lam_shift
        return (
            _Row(_snh_deviatoric, (self.Dm_inv, gamma), self.mu * self.rest_volume),
            _Row(_snh_hydrostatic, (self.Dm_inv, gamma), self.lam_shift * self.rest_volume),
        )


def _per_constraint(v, n, name):
    v = jnp.asarray(v, dtype=_float_dtype())
    if v.ndim == 0:
        v = jnp.broadcast_to(v, (n,))
    if v.shape != (n,):
        raise ModelError(f"{name} must be a scalar or have shape ({n},), got {v.shape}")
    return v


def constraint_energy(constraints, x):
    """Total XPBD energy ``1/2 sum C^2 / alpha`` [J] of constraint sets at positions ``x`` (N, 3)."""
    return sum(c.energy(x) for c in constraints)


def _unsupported(model) -> ModelError:
    kind = getattr(model, "kind", type(model).__name__)
    return ModelError(
        f"XPBD has no constraint form for the {kind!r} model; use 'springs_volume' or 'stable_neo_hookean' "
        "(the FEM models are solved with difftissue.solvers.solve_static)"
    )


def _model_colors(model):
    """Host colouring of the constraint sets :func:`xpbd_constraints` builds for ``model``."""
    if isinstance(model, SpringVolumeModel):
        return (color_constraints(model.springs), color_constraints(model.cells))
    if isinstance(model, StableNeoHookeanModel):
        return (color_constraints(model.tets),)
    raise _unsupported(model)


def xpbd_constraints(model: ElasticModel, material: Material, *, colors=None) -> tuple[ConstraintSet, ...]:
    """The XPBD constraint sets whose energy ``1/2 sum C^2 / alpha`` is the model's energy.

    - :class:`~difftissue.models.SpringVolumeModel`: a :class:`DistanceConstraints` with the
      model's spring constants ``(k, a)`` and a hexahedral :class:`VolumeConstraints` per
      cell with ``K = lambda - mu``.
    - :class:`~difftissue.models.StableNeoHookeanModel`: a :class:`StableNeoHookeanConstraints`
      (equal up to a constant).

    ``material.pre_stretch`` (and ``pre_stretch_y``, anisotropic) is honoured: the constraints get the stress-free state's rest
    lengths, spring constants, rest volumes and ``Dm_inv`` exactly as the model's energy does
    (:meth:`~difftissue.models.SpringVolumeModel.spring_parameters`,
    :meth:`~difftissue.models.ElasticModel.stress_free_tets`).

    ``material`` may be traced (``jax.grad`` flows through the parameters). The graph
    colouring is computed from the model's index arrays when they are concrete; under a
    trace of the model pass ``colors`` (one table per set, :func:`color_constraints`) or
    use the Jacobi method.
    """
    c = (None, None) if colors is None else tuple(colors)
    if isinstance(model, SpringVolumeModel):
        rest, k, a = model.spring_parameters(material)
        p = model.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        bulk = (lam - mu)[model.cell_regions]
        return (
            DistanceConstraints(model.springs, rest, k, a, colors=c[0]),
            VolumeConstraints(model.cells, model.cell_rest_volumes(material), bulk, colors=c[1]),
        )
    if isinstance(model, StableNeoHookeanModel):
        p = model.region_values(material)
        lam, mu = lame_parameters(p["youngs_modulus"], p["poisson_ratio"])
        r = model.tet_regions
        Dm_inv, V0 = model.stress_free_tets(p["pre_stretch"], p.get("pre_stretch_y"))
        return (StableNeoHookeanConstraints(model.tets, Dm_inv, V0, mu[r], (lam + mu)[r], colors=c[0]),)
    raise _unsupported(model)


# ------------------------------------------------------------------------- settings
def _float_dtype():
    return jnp.result_type(float)  # float64 with jax_enable_x64, else float32


def _as_float_array(v):
    return jnp.asarray(v, dtype=_float_dtype())


class XPBDSettings(eqx.Module):
    """Options of the XPBD loop.

    Attributes:
        dt: frame time step [s] (e.g. 1/60); each frame is ``substeps`` substeps of
            ``h = dt / substeps``.
        substeps: substeps per frame (static).
        iterations: constraint iterations per substep (static).
        method: ``"gauss_seidel"`` (graph-coloured, constraints of one colour in parallel) or
            ``"jacobi"`` (all constraints of a set at once, averaged by node valence).
        relaxation: Jacobi: ``omega_c = relaxation / max_i count_i`` (``count_i`` = number of
            constraints of the set on node ``i``); Gauss-Seidel: over-relaxation factor
            (1 = plain Gauss-Seidel).
        damping: velocity damping rate [1/s]: ``v <- v exp(-damping h)`` after each substep;
            ``inf`` zeroes the velocities (fully damped, quasi-static stepping).
        warm_start: keep the multipliers from one substep to the next (applying their
            impulses at the start of the substep, which keeps the XPBD invariant
            ``M (x - x~) = sum grad C^T lambda``). Standard XPBD (False) resets them at
            every substep; with True a quasi-static rest state is the exact energy minimum
            for any iteration budget (static).
        checkpoint: rematerialise each iteration and substep in reverse mode
            (``jax.checkpoint``): memory independent of the iteration count at the price of
            recomputation. False stores every iteration's intermediates (static).
    """

    dt: jax.Array = eqx.field(default=1.0 / 60.0, converter=_as_float_array)
    substeps: int = eqx.field(default=1, static=True)
    iterations: int = eqx.field(default=10, static=True)
    method: str = eqx.field(default="gauss_seidel", static=True)
    relaxation: jax.Array = eqx.field(default=1.0, converter=_as_float_array)
    damping: jax.Array = eqx.field(default=0.0, converter=_as_float_array)
    warm_start: bool = eqx.field(default=False, static=True)
    checkpoint: bool = eqx.field(default=True, static=True)
    # Test-only: the known bug of resetting the multipliers at every iteration.
    _reset_each_iteration: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ModelError(f"method must be one of {METHODS}, got {self.method!r}")
        if not isinstance(self.substeps, int) or self.substeps < 1:
            raise ModelError(f"substeps must be an integer >= 1, got {self.substeps!r}")
        if not isinstance(self.iterations, int) or self.iterations < 1:
            raise ModelError(f"iterations must be an integer >= 1, got {self.iterations!r}")
        if _is_concrete(self.dt) and not float(self.dt) > 0:
            raise ModelError(f"dt must be > 0 s, got {float(self.dt)}")
        if _is_concrete(self.relaxation) and not float(self.relaxation) > 0:
            raise ModelError(f"relaxation must be > 0, got {float(self.relaxation)}")
        if _is_concrete(self.damping) and not float(self.damping) >= 0:
            raise ModelError(f"damping must be >= 0 1/s, got {float(self.damping)}")


class XPBDState(eqx.Module):
    """State between frames.

    Attributes:
        positions: ``(N, 3)`` [m].
        velocities: ``(N, 3)`` [m/s].
        multipliers: per constraint set, per constraint kind, ``(S,)`` multipliers of the last
            substep [N s^2 units of C].
        reaction: ``(N, 3)`` [N] force the supports exert on the prescribed components:
            ``-sum grad C^T lambda / h^2 - f`` (0 on free components).
    """

    positions: jax.Array
    velocities: jax.Array
    multipliers: tuple
    reaction: jax.Array


class XPBDQuasiStaticSolution(eqx.Module):
    """Result of :func:`xpbd_quasi_static`.

    Attributes:
        displacement: ``(N, 3)`` [m]; positions = rest points + displacement.
        reaction: ``(N, 3)`` [N] support forces on prescribed components (see :class:`XPBDState`).
        multipliers: as in :class:`XPBDState`.
        steps: steps taken.
        max_change: largest position change [m] in the last step.
        converged: ``max_change <= tol * length_scale`` with finite values.
    """

    displacement: jax.Array
    reaction: jax.Array
    multipliers: tuple
    steps: jax.Array
    max_change: jax.Array
    converged: jax.Array


# ------------------------------------------------------------------- the XPBD loop
class _Block(NamedTuple):
    nodes: jax.Array  # (..., B, k) node indices
    params: list  # per row: params tuple, leading (..., B)
    stiffness: list  # per row: (..., B) 1/alpha
    w_dof: jax.Array | None  # (..., B, k, 4) per-DOF inverse masses (Gauss-Seidel with rollers only)
    mask: jax.Array | None  # (..., B) for padded colours
    omega: jax.Array | None  # (..., B) Jacobi scaling
    w_nodes: jax.Array  # (..., B, k) node inverse masses (the 4th lane of the rows), gathered once


def _prepare(cset: ConstraintSet, W4, w_node, n_nodes, method, relaxation, isotropic):
    """Per-solve data of one set: colour-major for Gauss-Seidel, flat for Jacobi."""
    nodes = jnp.asarray(cset.nodes)
    rows = cset._rows()
    if method == "gauss_seidel":
        if cset.colors is None:
            raise ModelError(
                f"{type(cset).__name__} has no graph colouring (built from traced indices): build the constraints "
                "outside jit (xpbd_constraints / the constructors with concrete index arrays) or use method='jacobi'"
            )
        table = jnp.asarray(cset.colors)
        mask = table >= 0
        sel = jnp.where(mask, table, 0)
        take = lambda a: a[sel]  # noqa: E731
        omega = None
    else:
        mask = None
        take = lambda a: a  # noqa: E731
        count = jnp.zeros(n_nodes, W4.dtype).at[nodes.reshape(-1)].add(1.0)
        omega = relaxation / jnp.max(count[nodes], axis=1)
    nb = take(nodes)
    w_dof = None if (isotropic or method == "jacobi") else W4[nb]
    params = [jax.tree_util.tree_map(take, row.params) for row in rows]
    stiffness = [take(row.stiffness) for row in rows]
    w_nodes = w_node[nb]
    return _Block(nb, params, stiffness, w_dof, mask, omega, w_nodes), [row.evaluate for row in rows]


def _split(xr):
    """Gathered rows ``(..., k, 4)`` -> k component triples."""
    return [(xr[..., j, 0], xr[..., j, 1], xr[..., j, 2]) for j in range(xr.shape[-2])]


def _rows_of(g, s, zero):
    """Per-node update rows ``(..., k, 4)`` from gradient triples ``g`` scaled by ``s``
    (a scalar array per constraint, or per node when a list)."""
    out = []
    for j, gj in enumerate(g):
        sj = s[j] if isinstance(s, list) else s
        out.append(jnp.stack([gj[0] * sj, gj[1] * sj, gj[2] * sj, zero], axis=-1))
    return jnp.stack(out, axis=-2)


def _project(P, lam, blk: _Block, evaluate, params, stiffness, h2, relaxation, W4, jacobi, reset):
    """Project one constraint kind of one block (a colour or a whole Jacobi set).

    ``P`` is ``(N, 4)``: positions and, in the last lane, the node's inverse mass (its
    largest per-DOF value; exact for nodes with all or no components prescribed, an
    under-relaxation for rollers -- the fixed point does not depend on it).
    """
    xr = P[blk.nodes]
    C, g = evaluate(_split(xr), params)
    denom = None
    for j, gj in enumerate(g):
        t = xr[..., j, 3] * _dot(gj, gj)
        denom = t if denom is None else denom + t
    beta = stiffness * h2
    if reset:
        lam = jnp.zeros_like(lam)
    dl = -(beta * C + lam) / (beta * denom + 1.0)
    if blk.omega is not None:
        dl = blk.omega * dl
    elif not jacobi:
        dl = relaxation * dl
    if blk.mask is not None:
        dl = jnp.where(blk.mask, dl, 0.0)
    lam = lam + dl
    zero = jnp.zeros_like(dl)
    if jacobi:  # one scatter, then the per-vertex inverse-mass scaling once
        acc = jnp.zeros_like(P).at[blk.nodes].add(_rows_of(g, dl, zero))
        return P + W4 * acc, lam
    if blk.w_dof is None:
        upd = _rows_of(g, [xr[..., j, 3] * dl for j in range(len(g))], zero)
    else:
        upd = _rows_of(g, dl, zero) * blk.w_dof
    return P.at[blk.nodes].add(upd), lam


def _iteration(P, lams, prepared, h2, relaxation, W4, method, reset):
    """One XPBD iteration over all sets. ``lams[s][r]`` in the set's layout."""
    new_lams = []
    for (blk, evals), lam_s in zip(prepared, lams):
        if method == "jacobi":
            ls = []
            for r, ev in enumerate(evals):
                P, lr = _project(P, lam_s[r], blk, ev, blk.params[r], blk.stiffness[r], h2, relaxation, W4, True, reset)
                ls.append(lr)
            new_lams.append(tuple(ls))
        else:

            def colour(P, xs, evals=evals):
                b, lam_c = xs
                ls = []
                for r, ev in enumerate(evals):
                    P, lr = _project(P, lam_c[r], b, ev, b.params[r], b.stiffness[r], h2, relaxation, W4, False, reset)
                    ls.append(lr)
                return P, tuple(ls)

            P, ls = jax.lax.scan(colour, P, (blk, tuple(lam_s)))
            new_lams.append(ls)
    return P, tuple(new_lams)


def _project_soa(S, lam, blk: _Block, evaluate, params, stiffness, h2, Wc, reset):
    """Jacobi :func:`_project` on component arrays ``S = (x, y, z)`` (each ``(N,)``): the same
    arithmetic, three gathers and three scatters per node instead of one row each. Used for
    the derivatives (see :func:`_make_iterate`)."""
    idx = blk.nodes
    k = idx.shape[-1]
    cols = [idx[..., j] for j in range(k)]
    xs = [tuple(p[c] for p in S) for c in cols]
    C, g = evaluate(xs, params)
    wn = blk.w_nodes
    denom = None
    for j, gj in enumerate(g):
        t = wn[..., j] * _dot(gj, gj)
        denom = t if denom is None else denom + t
    beta = stiffness * h2
    if reset:
        lam = jnp.zeros_like(lam)
    dl = -(beta * C + lam) / (beta * denom + 1.0)
    dl = blk.omega * dl
    lam = lam + dl
    # one scatter per component, then the per-vertex inverse-mass scaling once
    out = tuple(p + w * jnp.zeros_like(p).at[idx].add(jnp.stack([gj[c] * dl for gj in g], axis=-1)) for c, (p, w) in enumerate(zip(S, Wc)))
    return out, lam


def _iteration_soa(S, lams, prepared, h2, Wc, reset):
    """Jacobi :func:`_iteration` on component arrays."""
    new_lams = []
    for (blk, evals), lam_s in zip(prepared, lams):
        ls = []
        for r, ev in enumerate(evals):
            S, lr = _project_soa(S, lam_s[r], blk, ev, blk.params[r], blk.stiffness[r], h2, Wc, reset)
            ls.append(lr)
        new_lams.append(tuple(ls))
    return S, tuple(new_lams)


def _make_iterate(prepared, method, reset):
    """One XPBD iteration ``(P, lams, blocks, h2, relaxation, W4) -> (P, lams)``.

    Always evaluated on ``(N, 4)`` rows (one gather and one scatter row per node: the fastest
    forward pass on XLA:CPU). For the Jacobi method it is differentiated through the same
    iteration on component arrays (a ``custom_jvp`` whose rule is the JVP of
    :func:`_iteration_soa`, same arithmetic): transposing the row layout's component slices
    gives pad/concatenate fusions that XLA:CPU evaluates per output element, with all shared
    subexpressions recomputed (reverse mode 12-14x the forward time on the peerbench
    workload); the component form transposes into plain gathers and scatters (about 5x).
    The Gauss-Seidel method keeps the row form for derivatives too: its colour loop would
    turn the 12 component gathers per tet into full-size scatters per colour.
    """
    evals = [ev for _, ev in prepared]

    def rows(P, lams, blocks, h2, relaxation, W4):
        return _iteration(P, lams, list(zip(blocks, evals)), h2, relaxation, W4, method, reset)

    if method != "jacobi":
        return rows

    def components(P, lams, blocks, h2, relaxation, W4):
        S = (P[:, 0], P[:, 1], P[:, 2])
        Wc = (W4[:, 0], W4[:, 1], W4[:, 2])
        S, lams = _iteration_soa(S, lams, list(zip(blocks, evals)), h2, Wc, reset)
        return jnp.stack([S[0], S[1], S[2], P[:, 3]], axis=1), lams

    iterate = jax.custom_jvp(rows)
    iterate.defjvp(lambda primals, tangents: jax.jvp(components, primals, tangents))
    return iterate


def _impulses(P, lams, prepared):
    """``sum_c grad C_c(P)^T lambda_c``, ``(N, 4)`` (last lane 0)."""
    acc = jnp.zeros_like(P)
    for (blk, evals), lam_s in zip(prepared, lams):
        xs = _split(P[blk.nodes])
        for r, ev in enumerate(evals):
            _, g = ev(xs, blk.params[r])
            lam = lam_s[r] if blk.mask is None else jnp.where(blk.mask, lam_s[r], 0.0)
            acc = acc.at[blk.nodes].add(_rows_of(g, lam, jnp.zeros_like(lam)))
    return acc


class _Problem(NamedTuple):
    """Everything one solve needs, inside jit (rows of 4: x, y, z, inverse mass)."""

    prepared: list
    tables: list  # per set: colour table (Gauss-Seidel) or None
    sizes: list  # per set: S
    W4: jax.Array  # (N, 4) per-DOF inverse masses, last lane 0
    Xf4: jax.Array  # (N, 4) prescribed positions, last lane the node inverse mass
    fixed4: jax.Array  # (N, 4) bool, last lane True
    fW4: jax.Array  # (N, 4) W * force


def _setup(constraints, rest_points, masses, bc, settings, isotropic):
    X = jnp.asarray(rest_points)
    dtype = X.dtype
    m = jnp.asarray(masses, dtype=dtype)
    fixed = jnp.asarray(bc.fixed)
    winv = jnp.where(m > 0, 1.0 / jnp.where(m > 0, m, 1.0), 0.0)
    W = jnp.where(fixed, 0.0, winv[:, None])
    w_node = jnp.max(W, axis=1, keepdims=True)
    W4 = jnp.concatenate([W, jnp.zeros_like(w_node)], axis=1)
    n = X.shape[0]
    prepared, tables, sizes = [], [], []
    for c in constraints:
        prepared.append(_prepare(c, W4, w_node[:, 0], n, settings.method, settings.relaxation, isotropic))
        tables.append(None if settings.method == "jacobi" else jnp.asarray(c.colors))
        sizes.append(c.n_constraints)
    Xf4 = jnp.concatenate([X + jnp.where(fixed, bc.displacement, 0.0), w_node], axis=1)
    fixed4 = jnp.concatenate([fixed, jnp.ones((n, 1), bool)], axis=1)
    fW4 = jnp.concatenate([W * jnp.where(fixed, 0.0, bc.force), jnp.zeros_like(w_node)], axis=1)
    return _Problem(prepared, tables, sizes, W4, Xf4, fixed4, fW4)


def _lams_to_layout(prob: _Problem, multipliers):
    out = []
    for table, lam_s in zip(prob.tables, multipliers):
        if table is None:
            out.append(tuple(jnp.asarray(l) for l in lam_s))
        else:
            mask = table >= 0
            sel = jnp.where(mask, table, 0)
            out.append(tuple(jnp.where(mask, jnp.asarray(l)[sel], 0.0) for l in lam_s))
    return tuple(out)


def _lams_from_layout(prob: _Problem, lams):
    out = []
    for table, S, lam_s in zip(prob.tables, prob.sizes, lams):
        if table is None:
            out.append(tuple(lam_s))
        else:
            sel = jnp.where(table >= 0, table, S)  # dummies go to an extra slot, dropped below
            out.append(tuple(jnp.zeros(S + 1, l.dtype).at[sel].set(l)[:S] for l in lam_s))
    return tuple(out)


def _substep(prob: _Problem, settings: XPBDSettings, P, V, lams, h, zero_velocity, n_iter=None):
    """One XPBD substep on ``(N, 4)`` rows; ``lams`` in block layout."""
    h2 = h * h
    if zero_velocity:
        V = jnp.zeros_like(V)
    V = jnp.where(prob.fixed4, 0.0, V)
    start = jnp.where(prob.fixed4, prob.Xf4, P)
    pred = start + h * V + h2 * prob.fW4
    if settings.warm_start:
        pred = pred + prob.W4 * _impulses(start, lams, prob.prepared)
    else:
        lams = jax.tree_util.tree_map(jnp.zeros_like, lams)

    it = _make_iterate(prob.prepared, settings.method, settings._reset_each_iteration)
    blocks = [blk for blk, _ in prob.prepared]

    def iterate(carry):
        Pc, lc = carry
        return it(Pc, lc, blocks, h2, settings.relaxation, prob.W4)

    if n_iter is None:  # unrolled, reverse-mode differentiable
        body = lambda c, _: (iterate(c), None)  # noqa: E731
        if settings.checkpoint:
            body = jax.checkpoint(body)
        (Pn, lams), _ = jax.lax.scan(body, (pred, lams), None, length=settings.iterations)
    else:  # traced iteration count (quasi-static driver: no recompilation per budget)
        Pn, lams = jax.lax.fori_loop(0, n_iter, lambda i, c: iterate(c), (pred, lams))
    damp = settings.damping
    inf = jnp.isinf(damp)
    factor = jnp.where(inf, 0.0, jnp.exp(-jnp.where(inf, 0.0, damp) * h))
    Vn = jnp.where(prob.fixed4, 0.0, (Pn - start) * (factor / h))
    return Pn, Vn, lams


def _frame(prob, settings, P, V, lams, zero_velocity, n_iter=None):
    h = settings.dt / settings.substeps
    if settings.substeps == 1:
        return _substep(prob, settings, P, V, lams, h, zero_velocity, n_iter)

    def sub(carry, _):
        return _substep(prob, settings, *carry, h, zero_velocity, n_iter), None

    if settings.checkpoint:
        sub = jax.checkpoint(sub)

    (P, V, lams), _ = jax.lax.scan(sub, (P, V, lams), None, length=settings.substeps)
    return P, V, lams


def _reaction(prob, settings, P, lams, bc):
    h = settings.dt / settings.substeps
    imp = _impulses(P, lams, prob.prepared)[:, :3]
    fixed = jnp.asarray(bc.fixed)
    return jnp.where(fixed, -imp / (h * h) - bc.force, 0.0)


def _rows4(prob, x):
    return jnp.concatenate([x, prob.Xf4[:, 3:]], axis=1)


class _ConstraintProblem(eqx.Module):
    constraints: tuple
    rest_points: jax.Array
    masses: jax.Array

    def build(self):
        return self.constraints, self.rest_points, self.masses


class _ModelProblem(eqx.Module):
    model: ElasticModel
    material: Material
    colors: tuple | None

    def build(self):
        constraints = xpbd_constraints(self.model, self.material, colors=self.colors)
        X = jnp.asarray(self.model.rest_points, dtype=_float_dtype())
        return constraints, X, self.model.lumped_masses(self.material)


@eqx.filter_jit
def _simulate(problem, bc, state, settings, steps, isotropic):
    constraints, rest_points, masses = problem.build()
    state = _initial_state(constraints, rest_points, state, rest_points.dtype)
    prob = _setup(constraints, rest_points, masses, bc, settings, isotropic)
    P = _rows4(prob, state.positions)
    V = jnp.concatenate([state.velocities, jnp.zeros_like(state.velocities[:, :1])], axis=1)
    lams = _lams_to_layout(prob, state.multipliers)

    def frame(carry, _):  # substep and iteration bodies are checkpointed inside
        return _frame(prob, settings, *carry, False), None

    if steps == 1:
        P, V, lams = _frame(prob, settings, P, V, lams, False)
    else:
        (P, V, lams), _ = jax.lax.scan(frame, (P, V, lams), None, length=steps)
    reaction = _reaction(prob, settings, P, lams, bc)
    return XPBDState(P[:, :3], V[:, :3], _lams_from_layout(prob, lams), reaction)


@eqx.filter_jit
def _quasi_static(problem, bc, state, settings, tol, max_steps, n_iter, isotropic):
    constraints, rest_points, masses = problem.build()
    state = _initial_state(constraints, rest_points, state, rest_points.dtype)
    prob = _setup(constraints, rest_points, masses, bc, settings, isotropic)
    X = jnp.asarray(rest_points)
    scale = jnp.max(jnp.max(X, axis=0) - jnp.min(X, axis=0))
    P = _rows4(prob, state.positions)
    lams = _lams_to_layout(prob, state.multipliers)
    zeros = jnp.zeros_like(P)

    def cond(c):
        _, _, step, change = c
        return (step < max_steps) & ~(change <= tol * scale)

    def body(c):
        Pc, lc, step, _ = c
        Pn, _, ln = _frame(prob, settings, Pc, zeros, lc, True, n_iter)
        change = jnp.max(jnp.abs(Pn - Pc))
        change = jnp.where(jnp.isfinite(change), change, jnp.inf)
        return Pn, ln, step + 1, change

    init = (P, lams, jnp.asarray(0, jnp.int32), jnp.asarray(jnp.inf, X.dtype))
    P, lams, steps, change = jax.lax.while_loop(cond, body, init)
    x = P[:, :3]
    reaction = _reaction(prob, settings, P, lams, bc)
    converged = (change <= tol * scale) & jnp.all(jnp.isfinite(x))
    return XPBDQuasiStaticSolution(x - X, reaction, _lams_from_layout(prob, lams), steps, change, converged)


# ------------------------------------------------------------------------- entries
def _isotropic(bc) -> bool:
    """True when every node has all or none of its components prescribed (no rollers)."""
    fixed = bc.fixed
    if not _is_concrete(fixed):
        return False
    fixed = np.asarray(fixed, dtype=bool)
    return bool(np.all(fixed.all(axis=1) | ~fixed.any(axis=1)))


def _initial_state(constraints, rest_points, state, dtype):
    if state is not None:
        return state
    X = jnp.asarray(rest_points, dtype=dtype)
    mult = tuple(tuple(jnp.zeros(c.n_constraints, dtype) for _ in c._rows()) for c in constraints)
    return XPBDState(X, jnp.zeros_like(X), mult, jnp.zeros_like(X))


def _settings(settings, default):
    settings = default if settings is None else settings
    if not isinstance(settings, XPBDSettings):
        raise ModelError(f"settings must be an XPBDSettings, got {type(settings).__name__}")
    return settings


def _constraint_problem(constraints, rest_points, masses, bc):
    constraints = tuple(constraints)
    if not constraints or not all(isinstance(c, ConstraintSet) for c in constraints):
        raise ModelError("constraints must be a non-empty sequence of ConstraintSet")
    X = jnp.asarray(rest_points, dtype=_float_dtype())
    n = X.shape[0]
    _validate_values(bc, n)
    if np.shape(masses) != (n,):
        raise ModelError(f"masses must have shape ({n},), got {np.shape(masses)}")
    for c in constraints:
        if _is_concrete(c.nodes):
            nodes = np.asarray(c.nodes)
            if nodes.min() < 0 or nodes.max() >= n:
                raise ModelError(f"{type(c).__name__} references nodes outside [0, {n})")
    return _ConstraintProblem(constraints, X, jnp.asarray(masses, dtype=X.dtype))


def _model_problem(model, material, bc, settings):
    if not isinstance(model, ElasticModel):
        raise ModelError(f"model must be an ElasticModel (see difftissue.models.make_model), got {type(model).__name__}")
    if not isinstance(model, (SpringVolumeModel, StableNeoHookeanModel)):
        raise _unsupported(model)
    _validate_values(bc, model.n_nodes)
    if _is_concrete(material):
        model.region_values(material)  # range checks with clear errors now
    colors = _model_colors(model) if settings.method == "gauss_seidel" and _is_concrete(model) else None
    # Python floats would be static under jit (a recompile per value): make every leaf an array.
    material = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=_float_dtype()), material)
    return _ModelProblem(model, material, colors)


def _check_steps(steps):
    if not isinstance(steps, int) or steps < 1:
        raise ModelError(f"steps must be an integer >= 1, got {steps!r}")


def xpbd_simulate_constraints(
    constraints,
    rest_points,
    masses,
    bc: BoundaryConditions,
    *,
    settings: XPBDSettings | None = None,
    steps: int = 1,
    state: XPBDState | None = None,
) -> XPBDState:
    """Run ``steps`` XPBD frames of arbitrary constraint sets (the engine of :func:`xpbd_simulate`).

    Args:
        constraints: a sequence of :class:`ConstraintSet`, projected in this order.
        rest_points: ``(N, 3)`` rest positions [m] (prescribed positions are
            ``rest_points + bc.displacement``).
        masses: ``(N,)`` nodal masses [kg] (0: the node does not move).
        bc: prescribed displacement components (inverse mass 0 per component) and forces [N].
        settings: :class:`XPBDSettings` (default ``XPBDSettings()``).
        steps: number of frames (static).
        state: state to continue from (default: at rest, positions = rest points).

    Returns:
        The :class:`XPBDState` after the last frame. Differentiable (reverse and forward mode)
        with respect to every inexact leaf of the constraints, masses, ``bc.displacement``,
        ``bc.force``, ``settings.dt`` and ``state``.
    """
    settings = _settings(settings, XPBDSettings())
    _check_steps(steps)
    problem = _constraint_problem(constraints, rest_points, masses, bc)
    return _simulate(problem, bc, state, settings, steps, _isotropic(bc))


def xpbd_simulate(
    model: ElasticModel,
    material: Material,
    bc: BoundaryConditions,
    *,
    settings: XPBDSettings | None = None,
    steps: int = 1,
    state: XPBDState | None = None,
) -> XPBDState:
    """Run ``steps`` XPBD frames of a model (constraints from :func:`xpbd_constraints`, lumped
    masses from ``model.lumped_masses``).

    Reverse- and forward-mode differentiable with respect to ``material``,
    ``bc.displacement`` and ``bc.force`` (unrolled ``lax.scan`` with ``jax.checkpoint`` on
    each substep and iteration). Use ``settings.damping = inf`` for fully damped
    (quasi-static) stepping with a fixed budget. See :func:`xpbd_simulate_constraints`.
    """
    settings = _settings(settings, XPBDSettings())
    _check_steps(steps)
    problem = _model_problem(model, material, bc, settings)
    return _simulate(problem, bc, state, settings, steps, _isotropic(bc))


def _run_quasi_static(problem, bc, settings, tol, max_steps, state, throw):
    dtype = _float_dtype()
    n_iter = jnp.asarray(settings.iterations, jnp.int32)
    canonical = dataclasses.replace(settings, iterations=1)  # the budget is traced here
    sol = _quasi_static(problem, bc, state, canonical, jnp.asarray(tol, dtype), jnp.asarray(max_steps, jnp.int32), n_iter, _isotropic(bc))
    if throw:
        msg = "quasi-static XPBD did not converge within max_steps frames (raise max_steps or iterations, or loosen tol)"
        if isinstance(sol.converged, jax.core.Tracer):
            sol = eqx.tree_at(lambda s: s.displacement, sol, eqx.error_if(sol.displacement, ~sol.converged, msg))
        elif not bool(sol.converged):
            change = float(sol.max_change)
            if not np.isfinite(change):
                raise ConvergenceError(
                    f"quasi-static XPBD diverged after {int(sol.steps)} frames (non-finite positions): reduce settings.dt "
                    "(warm-started stable neo-Hookean constraints need roughly (dt * omega_max)^2 < 1) or the load"
                )
            raise ConvergenceError(f"{msg}: steps {int(sol.steps)}, last change {change:.3g} m")
    return sol


def xpbd_quasi_static_constraints(
    constraints,
    rest_points,
    masses,
    bc: BoundaryConditions,
    *,
    settings: XPBDSettings | None = None,
    tol: float = 1e-6,
    max_steps: int = 10_000,
    state: XPBDState | None = None,
    throw: bool = True,
) -> XPBDQuasiStaticSolution:
    """Quasi-static XPBD: fully damped frames (velocities zeroed at every substep) until the
    largest position change in a frame is at most ``tol * L`` (``L`` = largest extent of the
    rest mesh).

    With ``settings.warm_start=True`` (the default here) the rest state is the minimum of
    ``1/2 sum C^2/alpha - f . x`` -- what :func:`~difftissue.solvers.solve_static` computes --
    for any iteration budget. With standard XPBD (``warm_start=False``) it is the state a
    real-time simulator with that budget settles to (see ``docs/xpbd.md``: softer when the
    substep's solve is not converged, and off by ``O((h omega)^2)`` otherwise).

    ``settings.iterations``, ``dt``, ``tol`` and ``max_steps`` are traced here (changing them
    does not recompile). The loop is a ``lax.while_loop``: forward-mode differentiable only;
    for reverse mode use :func:`xpbd_simulate` with a fixed number of steps, or ``solve_static``.

    Raises:
        ConvergenceError: not converged (or non-finite) and ``throw`` (an ``equinox``
            runtime error when called under a trace).
    """
    settings = _settings(settings, XPBDSettings(warm_start=True))
    problem = _constraint_problem(constraints, rest_points, masses, bc)
    return _run_quasi_static(problem, bc, settings, tol, max_steps, state, throw)


def xpbd_quasi_static(
    model: ElasticModel,
    material: Material,
    bc: BoundaryConditions,
    *,
    settings: XPBDSettings | None = None,
    tol: float = 1e-6,
    max_steps: int = 10_000,
    state: XPBDState | None = None,
    throw: bool = True,
) -> XPBDQuasiStaticSolution:
    """Quasi-static XPBD of a model; see :func:`xpbd_quasi_static_constraints`.

    The default settings (``XPBDSettings(warm_start=True)``) give the model's static
    equilibrium; pass ``XPBDSettings(warm_start=False, ...)`` for the rest state of
    standard (real-time) XPBD with a given budget.
    """
    settings = _settings(settings, XPBDSettings(warm_start=True))
    problem = _model_problem(model, material, bc, settings)
    return _run_quasi_static(problem, bc, settings, tol, max_steps, state, throw)
