"""The seed 003 cut-opening surrogate: a closed-form width profile for real-time cutting.

Seed 003 (node snapping) opens a cut without solving for equilibrium: every snapped node
``i`` at depth ``h_i`` below the surface, on a cut of depth ``d``, gets the width

    w_i = min(c (d - h_i) / (1 - alpha), w_max)                     (seed 003, eqs. 2-3)

and is duplicated into two nodes moved apart perpendicular to the cut in the tangent plane,

    S_i1,2 = S_i +- (w_i / 2) (n_i x t_i) / |n_i x t_i|              (seed 003, eq. 4)

with ``n_i`` the surface normal at the node (mean of the neighbouring triangles' normals) and
``t_i`` the cut direction there (the paper's ``SS_i``, from the cut's start point ``S`` to
``S_i``). So ``w_i`` is the distance between the two copies. The paper's eq. 5, which should
just add eq. 4 to ``S_i``, prints ``w_i`` instead of ``w_i / 2`` (copies ``2 w_i`` apart); we
follow eq. 4 and the paper's own definition of ``w_i`` as the cut width. The paper leaves the
start and end points of the cut undivided.

Parameters: ``alpha`` in ``[0, 1)`` is the paper's "initial surface tension" (larger opens
wider), ``c > 0`` a dimensionless scale [m of width per m of depth], ``w_max`` [m] a cap
("slightly smaller than the average spring length"). DESIGN.md §3.6 reads ``alpha`` as a
pre-stretch: ``lambda0 = 1 / (1 - alpha)``, i.e. ``alpha = 1 - 1/lambda0``
(:func:`pre_stretch_from_alpha`, :func:`alpha_from_pre_stretch`), which turns the formula
into ``w = c lambda0 (d - h)``.

Two properties matter when fitting (docs/cutting.md):

- only ``q = c / (1 - alpha)`` enters the width, so ``alpha`` and ``c`` cannot both be
  fitted to widths: :func:`fit_surrogate` fits one of them with the other fixed, or one
  shared ``c`` over several profiles whose ``alpha`` are known (e.g. from their ``lambda0``);
- with ``alpha = 1 - 1/lambda0`` the surrogate opens by ``c d`` even without tension
  (``lambda0 = 1``) and grows like ``lambda0``, while linear elasticity opens like
  ``lambda0 - 1`` (``w0 = 4 sigma0 a / E'``, DESIGN.md §3.6). The fit's residual says how
  far that is from the physical model.

Everything is differentiable in ``alpha``, ``c``, ``d``, ``h`` (``jax.grad``); the hard
``min`` has a kink where ``c (d - h)/(1 - alpha) = w_max``: pass ``smoothing`` [m] for the
smooth minimum :func:`smooth_min`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import DifftissueError, FitError
from .fit.residuals import ResidualProblem, least_squares
from .materials import Log, ScaledLogit, _is_concrete

__all__ = [
    "SurrogateError",
    "smooth_min",
    "surrogate_width",
    "alpha_from_pre_stretch",
    "pre_stretch_from_alpha",
    "opening_directions",
    "open_duplicated_nodes",
    "SurrogateFit",
    "fit_surrogate",
]


class SurrogateError(DifftissueError):
    """Bad input to the seed 003 opening surrogate."""


def _concrete(name, value, ok, rule):
    """Raise :class:`SurrogateError` when a concrete ``value`` is non-finite or breaks ``ok``."""
    if not _is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if np.any(np.isnan(arr)):
        raise SurrogateError(f"{name} contains NaN: {value!r}")
    if not np.all(ok(arr)):
        raise SurrogateError(f"{name} {rule}, got {value!r}")


def smooth_min(a, b, smoothing):
    """Smooth minimum ``-s log(exp(-a/s) + exp(-b/s))`` [units of a, b].

    ``min(a, b) - s ln 2 <= smooth_min <= min(a, b)``: the error is largest (``s ln 2``) where
    ``a = b`` and falls off like ``s exp(-|a - b| / s)`` away from it. It is smooth (infinitely
    differentiable) everywhere; ``b = +inf`` gives ``a`` (to round-off).

    Args:
        a, b: arrays (broadcasting).
        smoothing: ``s`` > 0, same unit as ``a`` and ``b``.
    """
    _concrete("smoothing", smoothing, lambda v: v > 0, "must be > 0")
    s = jnp.asarray(smoothing, dtype=jnp.result_type(float))
    return -s * jnp.logaddexp(-jnp.asarray(a) / s, -jnp.asarray(b) / s)


def _check_alpha_c(alpha, c):
    _concrete("alpha", alpha, lambda v: (v >= 0) & (v < 1), "must lie in [0, 1) (seed 003's initial surface tension; 1 divides by zero)")
    _concrete("c", c, lambda v: (v > 0) & np.isfinite(v), "must be a finite number > 0 (width per unit depth)")


def surrogate_width(node_depth, cut_depth, alpha, c, w_max=math.inf, *, smoothing=None):
    """Seed 003 opening width ``w = min(c (d - h) / (1 - alpha), w_max)`` [m].

    Args:
        node_depth: ``h`` [m], depth of each node below the surface, in ``[0, d]``.
        cut_depth: ``d`` [m] > 0.
        alpha: initial surface tension in ``[0, 1)`` (``1 - 1/lambda0``).
        c: scale > 0 [-] (width per unit depth at ``alpha = 0``).
        w_max: cap [m] > 0 (``inf``: no cap).
        smoothing: ``None`` for the exact ``min``; ``s`` [m] > 0 for :func:`smooth_min`, whose
            width is below the exact one by at most ``s ln 2`` (at the cap's corner) and never
            below 0 (clipped at the cut bottom, where the smooth minimum dips below 0).

    Returns:
        Widths [m], the broadcast shape of the arguments. Concrete bad values raise
        :class:`SurrogateError`; traced ones are checked with ``equinox.error_if``.
    """
    _check_alpha_c(alpha, c)
    _concrete("cut_depth", cut_depth, lambda v: (v > 0) & np.isfinite(v), "must be a finite depth > 0 m")
    _concrete("w_max", w_max, lambda v: v > 0, "must be > 0 m (inf for no cap)")
    if _is_concrete(node_depth) and _is_concrete(cut_depth):
        h, d = np.asarray(node_depth, dtype=float), np.asarray(cut_depth, dtype=float)
        if not np.all(np.isfinite(h)):
            raise SurrogateError("node_depth contains NaN or infinite values")
        if np.any(h < 0) or np.any(h > d * (1 + 1e-12)):
            raise SurrogateError(f"node depths must lie in [0, cut_depth = {d}] m (surface to cut bottom), got range [{h.min()}, {h.max()}]")
    alpha = jnp.asarray(alpha, dtype=jnp.result_type(float))
    c = jnp.asarray(c, dtype=alpha.dtype)
    if not (_is_concrete(alpha) and _is_concrete(c)):
        alpha = eqx.error_if(alpha, jnp.any((alpha < 0) | (alpha >= 1) | ~jnp.isfinite(alpha)), "alpha must lie in [0, 1)")
        c = eqx.error_if(c, jnp.any(~(c > 0)), "c must be > 0")
    raw = c * (jnp.asarray(cut_depth) - jnp.asarray(node_depth)) / (1.0 - alpha)
    if smoothing is None:
        return jnp.minimum(raw, w_max)
    # At the cut bottom (raw = 0) the smooth minimum is -s log(1 + exp(-w_max / s)) < 0: a width
    # is never negative (open_duplicated_nodes refuses that), so it is clipped at 0 there.
    return jnp.maximum(smooth_min(raw, w_max, smoothing), 0.0)


def alpha_from_pre_stretch(pre_stretch):
    """``alpha = 1 - 1/lambda0`` (DESIGN.md §3.6): seed 003's tension from a pre-stretch >= 1."""
    _concrete("pre_stretch", pre_stretch, lambda v: (v >= 1) & np.isfinite(v), "must be a finite stretch >= 1 (alpha = 1 - 1/lambda0 lies in [0, 1) only then)")
    return 1.0 - 1.0 / jnp.asarray(pre_stretch, dtype=jnp.result_type(float))


def pre_stretch_from_alpha(alpha):
    """``lambda0 = 1 / (1 - alpha)`` (DESIGN.md §3.6), inverse of :func:`alpha_from_pre_stretch`."""
    _check_alpha_c(alpha, 1.0)
    return 1.0 / (1.0 - jnp.asarray(alpha, dtype=jnp.result_type(float)))


def _safe_unit(v):
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v * jax.lax.rsqrt(jnp.where(ok, n2, 1.0)), 0.0), jnp.sqrt(jnp.where(ok, n2, 0.0))[..., 0]


def opening_directions(normals, cut_directions):
    """Unit directions ``(n x t) / |n x t|`` in which seed 003 moves the first copy of a node.

    Args:
        normals: ``(n, 3)`` surface normals ``n_i`` (any length).
        cut_directions: ``(n, 3)`` directions ``t_i`` of the cut at the nodes (the paper's
            ``SS_i``: from the cut's start point to the node).

    Raises:
        SurrogateError: (concrete input) where ``n_i`` and ``t_i`` are parallel or zero, so no
            direction perpendicular to the cut in the tangent plane exists.
    """
    n = jnp.asarray(normals, dtype=jnp.result_type(float))
    t = jnp.asarray(cut_directions, dtype=n.dtype)
    if n.shape != t.shape or n.ndim != 2 or n.shape[1] != 3:
        raise SurrogateError(f"normals and cut_directions must both have shape (n, 3), got {n.shape} and {t.shape}")
    nu, _ = _safe_unit(n)
    tu, _ = _safe_unit(t)
    d, size = _safe_unit(jnp.cross(nu, tu))
    if _is_concrete(size):
        bad = np.flatnonzero(~(np.asarray(size) > 1e-9))
        if bad.size:
            raise SurrogateError(f"normal and cut direction are parallel or zero at node(s) {bad[:8].tolist()}: no opening direction")
    return d


def open_duplicated_nodes(positions, normals, cut_directions, widths):
    """The two copies of each snapped node, ``S_i +- (w_i / 2) (n_i x t_i)/|n_i x t_i|`` [m]
    (seed 003 eq. 4; the copies end ``w_i`` apart).

    Args:
        positions: ``(n, 3)`` snapped node positions ``S_i`` [m].
        normals, cut_directions: see :func:`opening_directions`.
        widths: ``(n,)`` widths [m] (e.g. :func:`surrogate_width`).

    Returns:
        ``(first, second)``, each ``(n, 3)`` [m]; differentiable in every argument.
    """
    S = jnp.asarray(positions, dtype=jnp.result_type(float))
    w = jnp.asarray(widths, dtype=S.dtype)
    if S.ndim != 2 or S.shape[1] != 3 or w.shape != S.shape[:1]:
        raise SurrogateError(f"positions must be (n, 3) and widths (n,), got {S.shape} and {w.shape}")
    _concrete("widths", w, lambda v: v >= 0, "must be >= 0 m")
    d = opening_directions(normals, cut_directions)
    half = 0.5 * w[:, None] * d
    return S + half, S - half


# --------------------------------------------------------------------------- fitting
class SurrogateFit(NamedTuple):
    """Result of :func:`fit_surrogate`.

    Attributes:
        alpha: ``(n_profiles,)`` alpha per profile (fitted or as given).
        c: the shared scale [-].
        ratio: ``(n_profiles,)`` ``c / (1 - alpha)``, the identifiable combination.
        pre_stretch: ``(n_profiles,)`` ``1 / (1 - alpha)``.
        residuals: model minus data [m], all profiles concatenated.
        rms: root-mean-square residual [m]; relative_rms: ``rms / rms(widths)``.
        fitted: names of the fitted parameters.
        cost_evaluations: steps of the fit engine, each one evaluation of the widths and
            their Jacobian (the first at the start).
        message: why the fit stopped.
        standard_errors: ``{name: standard error}`` of the fitted parameters (names as in
            ``fitted``; dimensionless like ``c`` and ``alpha``): Gauss--Newton
            ``sqrt(diag(s^2 (J^T J)^-1))``, ``s^2`` the residual variance ``SSE / (n - p)``
            (NaN when there are no more widths than fitted parameters).
        covariance, correlation: ``(p, p)`` in the order of ``fitted``.
        dof: ``n - p`` (widths minus fitted parameters).
    """

    alpha: np.ndarray
    c: float
    ratio: np.ndarray
    pre_stretch: np.ndarray
    residuals: np.ndarray
    rms: float
    relative_rms: float
    fitted: tuple[str, ...]
    cost_evaluations: int
    message: str
    standard_errors: dict = {}
    covariance: np.ndarray | None = None
    correlation: np.ndarray | None = None
    dof: int = 0


def _as_profiles(depths, widths, cut_depth):
    single = not (isinstance(depths, (list, tuple)) and len(depths) > 0 and np.ndim(depths[0]) >= 1)
    if single:
        depths, widths = [depths], [widths]
    depths = [np.asarray(h, dtype=float).reshape(-1) for h in depths]
    widths = [np.asarray(w, dtype=float).reshape(-1) for w in widths]
    if len(depths) != len(widths) or not depths:
        raise SurrogateError(f"need as many width profiles as depth profiles (>= 1), got {len(depths)} and {len(widths)}")
    d = np.broadcast_to(np.asarray(cut_depth, dtype=float), (len(depths),)).copy()
    for k, (h, w) in enumerate(zip(depths, widths)):
        if h.shape != w.shape or h.size == 0:
            raise SurrogateError(f"profile {k}: depths {h.shape} and widths {w.shape} must be equal, non-empty")
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(w))):
            raise SurrogateError(f"profile {k}: depths and widths must be finite")
        if not (np.isfinite(d[k]) and d[k] > 0):
            raise SurrogateError(f"profile {k}: cut_depth must be > 0 m, got {d[k]}")
        if np.any(h < 0) or np.any(h > d[k] * (1 + 1e-12)):
            raise SurrogateError(f"profile {k}: node depths must lie in [0, cut_depth = {d[k]}] m")
    return depths, widths, d, single


def fit_surrogate(
    depths_of_nodes,
    widths,
    cut_depth,
    *,
    alpha=None,
    c=None,
    w_max=math.inf,
    smoothing=None,
    initial_alpha: float = 0.3,
    initial_c: float | None = None,
) -> SurrogateFit:
    """Least-squares fit of the seed 003 surrogate to width profiles (Gauss-Newton / LM).

    Only ``c / (1 - alpha)`` enters the width, so exactly one of ``alpha`` and ``c`` must be
    fixed:

    - ``alpha`` given (a number, or one per profile, e.g. :func:`alpha_from_pre_stretch` of
      each profile's ``lambda0``): one ``c`` shared by all profiles is fitted;
    - ``c`` given: one ``alpha`` per profile is fitted.

    Parameters are fitted through ``c = exp(u)`` and ``alpha = sigmoid(v)``, so they stay in
    range; the Jacobian is exact (``jax.jacfwd``); the solver is the fit engine's optimistix
    Levenberg-Marquardt (:func:`difftissue.fit.residuals.least_squares`, the engine of
    :func:`difftissue.fit.fit`), which also gives the Gauss-Newton standard errors and
    covariance of the fitted parameters (``s^2 (J^T J)^-1``).

    Args:
        depths_of_nodes: node depths ``h`` [m] of one profile, or a list of profiles.
        widths: the widths [m] to match (same layout), e.g. distances between duplicated
            nodes of the physical model or an FEM reference.
        cut_depth: ``d`` [m], one value or one per profile.
        alpha, c: the fixed parameter (see above).
        w_max, smoothing: as in :func:`surrogate_width`.
        initial_alpha, initial_c: starting values (``initial_c`` default: from the data).

    Raises:
        SurrogateError: bad profiles (shapes, NaN, depths outside ``[0, d]``), or both or none
            of ``alpha``, ``c`` fixed.
        FitError: the least-squares solver failed.
    """

    depths, ws, d, _ = _as_profiles(depths_of_nodes, widths, cut_depth)
    K = len(depths)
    if (alpha is None) == (c is None):
        raise SurrogateError(
            "fix exactly one of alpha and c: the surrogate width depends on them only through c / (1 - alpha), so they "
            "cannot both be fitted to widths (give alpha, e.g. alpha_from_pre_stretch(lambda0) per profile, and fit c; "
            "or give c and fit alpha)" if alpha is None else "both alpha and c are given: nothing to fit (call surrogate_width)"
        )
    if alpha is not None:
        alpha_fixed = np.broadcast_to(np.asarray(alpha, dtype=float), (K,)).copy()
        _check_alpha_c(alpha_fixed, 1.0)
    else:
        _check_alpha_c(0.0, c)
    _concrete("w_max", w_max, lambda v: v > 0, "must be > 0 m (inf for no cap)")
    if smoothing is not None:
        _concrete("smoothing", smoothing, lambda v: v > 0, "must be > 0")
    h_all = np.concatenate(depths)
    w_all = np.concatenate(ws)
    d_all = np.concatenate([np.full(h.size, dk) for h, dk in zip(depths, d)])
    prof = np.concatenate([np.full(h.size, k) for k, h in enumerate(depths)])
    scale = float(np.sqrt(np.mean(w_all**2))) or 1.0
    fit_c = alpha is not None
    fitted = ("c",) if fit_c else tuple(f"alpha[{k}]" for k in range(K))
    if fit_c:
        if initial_c is None:
            below = (d_all - h_all) > 0
            q = np.median(w_all[below] / (d_all - h_all)[below]) if np.any(below) else 1.0
            initial_c = float(q * np.mean(1.0 - alpha_fixed))
        if not initial_c > 0:
            raise FitError(f"initial c must be > 0, got {initial_c}")
        start = np.array([float(initial_c)])
        fixed = alpha_fixed
        transforms = (Log(),)  # c = exp(u) > 0
    else:
        a0 = min(max(float(initial_alpha), 1e-6), 1 - 1e-6)
        start = np.full(K, a0)
        fixed = np.asarray(float(c))
        transforms = tuple(ScaledLogit(0.0, 1.0) for _ in range(K))  # alpha = sigmoid(u) in (0, 1)
    data = {"h": h_all, "d": d_all, "w": w_all, "profile": prof, "fixed": fixed, "scale": np.asarray(scale),
            "w_max": np.asarray(float(w_max)), "smoothing": np.asarray(1.0 if smoothing is None else float(smoothing))}
    problem = ResidualProblem(_surrogate_residuals(fit_c, smoothing is not None), fitted, transforms, w_all.size,
                              data=data, key=("opening_surrogate", fit_c, smoothing is None))
    sol = least_squares(problem, start, method="levenberg_marquardt", max_steps=_FIT_MAX_STEPS, rtol=_FIT_RTOL, atol=_FIT_ATOL)
    if not sol.converged:
        raise FitError(f"surrogate fit failed: {sol.reason}")
    values = np.array([sol.values[f] for f in fitted])
    a, cc = (alpha_fixed, float(values[0])) if fit_c else (values, float(c))
    r = sol.predictions - w_all
    rms = float(np.sqrt(np.mean(r**2)))
    return SurrogateFit(
        alpha=np.asarray(a, dtype=float),
        c=cc,
        ratio=cc / (1.0 - a),
        pre_stretch=1.0 / (1.0 - a),
        residuals=r,
        rms=rms,
        relative_rms=rms / scale,
        fitted=fitted,
        cost_evaluations=int(sol.steps),
        message=sol.reason,
        standard_errors=dict(sol.standard_errors),
        covariance=sol.covariance,
        correlation=sol.correlation,
        dof=sol.dof,
    )


#: Stopping tolerances of :func:`fit_surrogate` (optimistix Cauchy test on the step in ``u``
#: and the change of the scaled residuals): tight, the problem is tiny.
_FIT_RTOL, _FIT_ATOL = 1e-12, 1e-14
#: Engine steps allowed (each evaluates the widths and their Jacobian once).
_FIT_MAX_STEPS = 200


def _surrogate_model(c, alpha, data, smoothed: bool):
    """The surrogate widths [m] of all profiles' nodes, as in :func:`surrogate_width` without
    its checks (and without the clip at 0 of the smooth minimum: the fitted widths)."""
    raw = c * (data["d"] - data["h"]) / (1.0 - alpha[data["profile"]])
    if not smoothed:
        return jnp.minimum(raw, data["w_max"])
    s = data["smoothing"]
    return -s * jnp.logaddexp(-raw / s, -data["w_max"] / s)


def _surrogate_residuals(fit_c: bool, smoothed: bool):
    """``residual_fn(values, data) -> (residuals, widths)`` of :func:`fit_surrogate`: residuals
    ``(w - w_data) / rms(w_data)`` [-], widths ``w`` [m]; ``values = (c,)`` with the alphas
    fixed (``data["fixed"]``), or the alphas per profile with ``c`` fixed."""

    def residual_fn(values, data):
        if fit_c:
            w = _surrogate_model(values[0], data["fixed"], data, smoothed)
        else:
            w = _surrogate_model(data["fixed"], values, data, smoothed)
        return (w - data["w"]) / data["scale"], w

    return residual_fn
