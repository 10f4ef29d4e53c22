"""The seed 003 opening surrogate: formula, limits, smooth minimum, gradients, fit, errors."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from difftissue.opening_surrogate import (
    SurrogateError,
    alpha_from_pre_stretch,
    fit_surrogate,
    open_duplicated_nodes,
    opening_directions,
    pre_stretch_from_alpha,
    smooth_min,
    surrogate_width,
)

D = 2e-3  # cut depth [m]
H = np.linspace(0.0, D, 9)


def test_formula_values_and_limits():
    w = np.asarray(surrogate_width(H, D, 0.2, 0.5))
    np.testing.assert_allclose(w, 0.5 * (D - H) / 0.8, rtol=1e-15)
    assert w[0] == pytest.approx(0.5 * D / 0.8) and w[-1] == 0.0  # surface: largest; cut bottom: closed
    np.testing.assert_allclose(np.asarray(surrogate_width(H, D, 0.0, 0.5)), 0.5 * (D - H), rtol=1e-15)  # alpha -> 0
    np.testing.assert_allclose(np.asarray(surrogate_width(H, D, 1e-12, 0.5)), 0.5 * (D - H), rtol=1e-11)
    capped = np.asarray(surrogate_width(H, D, 0.5, 1.0, w_max=1e-3))
    np.testing.assert_allclose(capped, np.minimum(2.0 * (D - H), 1e-3), rtol=1e-15)
    assert np.sum(capped == 1e-3) == 7  # 2 (d - h) >= w_max for h <= 3 d / 4: capped
    # wider with more tension
    assert np.all(np.diff([float(surrogate_width(0.0, D, a, 0.5)) for a in (0.0, 0.3, 0.6, 0.9)]) > 0)


def test_pre_stretch_alpha_relation():
    lam0 = np.array([1.0, 1.05, 1.15, 2.0])
    a = np.asarray(alpha_from_pre_stretch(lam0))
    np.testing.assert_allclose(a, [0.0, 1 - 1 / 1.05, 1 - 1 / 1.15, 0.5], rtol=1e-15, atol=0)
    np.testing.assert_allclose(np.asarray(pre_stretch_from_alpha(a)), lam0, rtol=1e-14)
    # the formula in terms of lambda0 is c lambda0 (d - h)
    np.testing.assert_allclose(np.asarray(surrogate_width(H, D, alpha_from_pre_stretch(1.15), 0.4)), 0.4 * 1.15 * (D - H), rtol=1e-14)
    with pytest.raises(SurrogateError, match="pre_stretch"):
        alpha_from_pre_stretch(0.95)
    with pytest.raises(SurrogateError, match="alpha"):
        pre_stretch_from_alpha(1.0)


def test_smooth_min_error_bound_and_convergence():
    a = jnp.linspace(0.0, 2e-3, 2001)
    b = 1e-3
    errs = []
    for s in (1e-4, 1e-5, 1e-6):
        sm = np.asarray(smooth_min(a, b, s))
        exact = np.minimum(np.asarray(a), b)
        err = exact - sm
        assert np.all(err >= -1e-18) and np.max(err) <= s * math.log(2) * (1 + 1e-12)
        assert float(smooth_min(b, b, s)) == pytest.approx(b - s * math.log(2), rel=1e-14)
        errs.append(np.max(err))
    assert errs[0] / errs[2] == pytest.approx(100.0, rel=1e-6)  # error proportional to s
    # no cap: the smooth width is the raw formula (to round-off)
    np.testing.assert_allclose(np.asarray(surrogate_width(H, D, 0.3, 0.5, smoothing=1e-5)), np.asarray(surrogate_width(H, D, 0.3, 0.5)), rtol=1e-15, atol=1e-20)
    sw = np.asarray(surrogate_width(H, D, 0.5, 1.0, w_max=1e-3, smoothing=1e-5))
    hw = np.asarray(surrogate_width(H, D, 0.5, 1.0, w_max=1e-3))
    assert np.all(hw - sw >= 0) and np.max(hw - sw) <= 1e-5 * math.log(2) * (1 + 1e-9)


def test_gradients_check_grads():
    h = jnp.asarray(H[1:-1])

    def smooth(alpha, c, d):
        return surrogate_width(h, d, alpha, c, w_max=1.2e-3, smoothing=1e-4) / 1e-3

    def hard(alpha, c, d):  # away from the cap's kink
        return surrogate_width(h, d, alpha, c, w_max=5e-3) / 1e-3

    args = (jnp.asarray(0.3), jnp.asarray(0.7), jnp.asarray(D))
    check_grads(jax.jit(smooth), args, order=2, modes=("fwd", "rev"), eps=1e-7)
    check_grads(jax.jit(hard), args, order=1, modes=("fwd", "rev"), eps=1e-7)
    # analytic derivatives of the uncapped width
    g = jax.grad(lambda a, c, d: surrogate_width(0.5e-3, d, a, c), argnums=(0, 1, 2))(0.3, 0.7, D)
    q = 0.7 / 0.7
    np.testing.assert_allclose([float(v) for v in g], [q * (D - 0.5e-3) / 0.7, (D - 0.5e-3) / 0.7, 0.7 / 0.7], rtol=1e-14)
    rng = np.random.default_rng(0)
    S = jnp.asarray(rng.standard_normal((4, 3)))
    n = jnp.asarray(rng.standard_normal((4, 3)))
    t = jnp.asarray(rng.standard_normal((4, 3)))
    w = jnp.asarray(rng.uniform(0.1, 1.0, 4))
    check_grads(jax.jit(lambda *a: jnp.concatenate(open_duplicated_nodes(*a))), (S, n, t, w), order=1, modes=("fwd", "rev"))


def test_duplicated_nodes_open_perpendicular_to_the_cut():
    S = jnp.array([[0.0, 0.0, 3e-3], [1e-3, 0.0, 2e-3], [2e-3, 0.0, 1e-3]])
    normals = jnp.tile(jnp.array([0.0, 0.0, 2.0]), (3, 1))  # surface normal +z (any length)
    along = jnp.tile(jnp.array([5.0, 0.0, 0.0]), (3, 1))  # cut along +x
    w = surrogate_width(jnp.array([0.0, 1e-3, 2e-3]), 2e-3, 0.25, 0.6)
    first, second = open_duplicated_nodes(S, normals, along, w)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(first - second), axis=1), np.asarray(w), rtol=1e-15)  # eq. 4: copies w apart
    np.testing.assert_allclose(np.asarray(first - S), np.asarray(0.5 * w)[:, None] * [0.0, 1.0, 0.0], atol=1e-18)  # z x x = +y
    np.testing.assert_allclose(np.asarray(first + second) / 2, np.asarray(S), atol=1e-18)
    np.testing.assert_allclose(np.asarray(opening_directions(normals, along)), np.tile([0.0, 1.0, 0.0], (3, 1)))


def test_bad_input_raises():
    with pytest.raises(SurrogateError, match="alpha"):
        surrogate_width(H, D, 1.0, 0.5)
    with pytest.raises(SurrogateError, match="alpha"):
        surrogate_width(H, D, -0.1, 0.5)
    with pytest.raises(SurrogateError, match="alpha"):
        surrogate_width(H, D, float("nan"), 0.5)
    with pytest.raises(SurrogateError, match="c "):
        surrogate_width(H, D, 0.2, 0.0)
    with pytest.raises(SurrogateError, match="node depths"):
        surrogate_width(H + 1e-4, D, 0.2, 0.5)
    with pytest.raises(SurrogateError, match="node depths"):
        surrogate_width(-H, D, 0.2, 0.5)
    with pytest.raises(SurrogateError, match="cut_depth"):
        surrogate_width(0.0, 0.0, 0.2, 0.5)
    with pytest.raises(SurrogateError, match="w_max"):
        surrogate_width(H, D, 0.2, 0.5, w_max=0.0)
    with pytest.raises(SurrogateError, match="smoothing"):
        surrogate_width(H, D, 0.2, 0.5, smoothing=-1e-5)
    with pytest.raises(Exception, match="alpha must lie in"):
        jax.jit(lambda a: surrogate_width(H, D, a, 0.5))(1.0).block_until_ready()
    with pytest.raises(SurrogateError, match="parallel"):
        opening_directions(jnp.array([[0.0, 0.0, 1.0]]), jnp.array([[0.0, 0.0, -2.0]]))
    with pytest.raises(SurrogateError, match="widths \\(n,\\)"):
        open_duplicated_nodes(jnp.zeros((2, 3)), jnp.zeros((2, 3)), jnp.zeros((2, 3)), jnp.zeros(3))
    with pytest.raises(SurrogateError, match=">= 0"):
        open_duplicated_nodes(jnp.zeros((1, 3)), jnp.array([[0.0, 0, 1]]), jnp.array([[1.0, 0, 0]]), jnp.array([-1e-3]))


def test_fit_recovers_c_or_alpha_from_noisy_surrogate_data():
    rng = np.random.default_rng(3)
    h = np.linspace(0.0, D, 21)
    w_max = 1.5e-3
    # alpha known from the pre-stretch of each profile, c shared and fitted
    lam = (1.05, 1.15)
    alphas = [float(alpha_from_pre_stretch(x)) for x in lam]
    c_true = 0.6
    data = [np.asarray(surrogate_width(h, D, a, c_true, w_max=w_max)) for a in alphas]
    noisy = [w * (1 + 0.01 * rng.standard_normal(w.size)) for w in data]
    fit = fit_surrogate([h, h], noisy, D, alpha=alphas, w_max=w_max)
    assert fit.fitted == ("c",)
    assert fit.c == pytest.approx(c_true, rel=0.01)
    np.testing.assert_allclose(fit.pre_stretch, lam, rtol=1e-14)
    assert 0.001 < fit.relative_rms < 0.02  # the 1 % noise, not a misfit
    # c known, one alpha per profile fitted
    fit = fit_surrogate([h, h], noisy, D, c=c_true, w_max=w_max, smoothing=1e-6)
    np.testing.assert_allclose(fit.alpha, alphas, atol=0.01)
    # exact data: exact recovery
    fit = fit_surrogate(h, data[1], D, c=c_true, w_max=w_max)
    assert fit.alpha[0] == pytest.approx(alphas[1], abs=1e-10) and fit.rms < 1e-15


def test_fit_standard_errors_equal_the_finite_difference_covariance():
    """The fit's standard errors (fit engine, Gauss--Newton) equal ``sqrt(diag(s^2 (J^T J)^-1))``
    with a central-difference Jacobian of the scaled residuals ``(w - w_data) / rms(w_data)``
    w.r.t. (c) and w.r.t. (alpha_0, alpha_1), ``s^2 = SSE / (n - p)``; and the truth lies within
    a few standard errors."""
    rng = np.random.default_rng(11)
    h = np.linspace(0.0, D, 15)
    w_max = 1.5e-3
    alphas, c_true = [0.1, 0.25], 0.5
    noisy = [np.asarray(surrogate_width(h, D, a, c_true, w_max=w_max)) + 2e-6 * rng.standard_normal(h.size) for a in alphas]
    w_all = np.concatenate(noisy)
    scale = float(np.sqrt(np.mean(w_all**2)))

    def fd_standard_errors(residual, v):
        J = np.empty((w_all.size, v.size))
        for j in range(v.size):
            e = np.zeros(v.size)
            e[j] = 1e-6 * abs(v[j])
            J[:, j] = (residual(v + e) - residual(v - e)) / (2 * e[j])
        s2 = float(np.sum(residual(v) ** 2)) / (w_all.size - v.size)
        return np.sqrt(np.diag(s2 * np.linalg.inv(J.T @ J)))

    fit = fit_surrogate([h, h], noisy, D, alpha=alphas, w_max=w_max)
    se = fd_standard_errors(lambda v: np.concatenate([np.asarray(surrogate_width(h, D, a, v[0], w_max=w_max)) for a in alphas]) / scale - w_all / scale,
                            np.array([fit.c]))
    assert fit.dof == w_all.size - 1
    assert fit.standard_errors["c"] == pytest.approx(se[0], rel=1e-6)
    assert abs(fit.c - c_true) < 4 * se[0]
    fit = fit_surrogate([h, h], noisy, D, c=c_true, w_max=w_max)
    se = fd_standard_errors(lambda v: np.concatenate([np.asarray(surrogate_width(h, D, a, c_true, w_max=w_max)) for a in v]) / scale - w_all / scale,
                            np.asarray(fit.alpha))
    np.testing.assert_allclose([fit.standard_errors["alpha[0]"], fit.standard_errors["alpha[1]"]], se, rtol=1e-6)
    assert np.all(np.abs(fit.alpha - alphas) < 4 * se)
    assert fit.covariance.shape == (2, 2) and abs(fit.correlation[0, 1]) < 1e-6  # the profiles share no parameter


def test_fit_refuses_unidentifiable_or_bad_input():
    h = np.linspace(0.0, D, 5)
    w = np.asarray(surrogate_width(h, D, 0.3, 0.5))
    with pytest.raises(SurrogateError, match="c / \\(1 - alpha\\)"):
        fit_surrogate(h, w, D)
    with pytest.raises(SurrogateError, match="nothing to fit"):
        fit_surrogate(h, w, D, alpha=0.3, c=0.5)
    with pytest.raises(SurrogateError, match="equal"):
        fit_surrogate(h, w[:-1], D, alpha=0.3)
    with pytest.raises(SurrogateError, match="finite"):
        fit_surrogate(h, np.where(h > 0, w, np.nan), D, alpha=0.3)
    with pytest.raises(SurrogateError, match="node depths"):
        fit_surrogate(h + D, w, D, alpha=0.3)
    with pytest.raises(SurrogateError, match="alpha"):
        fit_surrogate(h, w, D, alpha=1.2)


def test_smooth_width_is_never_negative_at_the_cut_bottom():
    """At the cut bottom the smooth minimum dips below 0 (-s log(1 + exp(-w_max/s))); the width
    is clipped at 0 so that open_duplicated_nodes takes it (it refuses negative widths)."""
    import numpy as np

    from difftissue.opening_surrogate import open_duplicated_nodes, smooth_min, surrogate_width

    d, s, w_max = 2e-3, 1e-4, 5e-4
    assert float(smooth_min(0.0, w_max, s)) < 0.0  # what the clip guards against
    h = np.array([0.0, 0.5 * d, d])
    w = np.asarray(surrogate_width(h, d, 0.2, 0.3, w_max, smoothing=s))
    assert np.all(w >= 0.0) and w[-1] == 0.0
    pos = np.zeros((3, 3))
    normals = np.tile([0.0, 1.0, 0.0], (3, 1))
    dirs = np.tile([1.0, 0.0, 0.0], (3, 1))
    opened = np.asarray(open_duplicated_nodes(pos, normals, dirs, w))
    assert np.all(np.isfinite(opened))
