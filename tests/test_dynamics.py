"""Damped dynamics (diffrax): modal decay and period, relaxation to the static equilibrium,
energy conservation, gradients against finite differences, recompilation and input errors.

One 1 x 1 x 2 cube column (12 nodes, springs_volume model), clamped at its base, its top
nodes guided in z (the pattern of a compression test). Compilation dominates the run time, so
the tests share compiled programs: every adaptive run uses this pattern of prescribed
components, passes ``beta_k`` (a number, so the stiffness-damping term is compiled in) and
``N_SAVE`` save times.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from difftissue.boundary import BoundaryConditions
from difftissue.errors import ConvergenceError, DifftissueError
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.solvers.dynamics import ramp, simulate_dynamics
from difftissue.solvers.static import solve_static

N_SAVE = 161  # every adaptive run uses this many save times: one compiled program per config
MATERIAL = Material(youngs_modulus=1.0e4, poisson_ratio=0.3, cubic_coefficient=5.0, density=1000.0)


@pytest.fixture(scope="module")
def column():
    mesh = block((0.01, 0.01, 0.02), (1, 1, 2))  # two 1 cm cubes
    model = make_model(mesh, "springs_volume")
    top = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.02))
    held = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, top, "z")
    return mesh, model, held, top


@pytest.fixture(scope="module")
def modes(column):
    """Generalised eigenpairs of the free DOFs at rest: K phi = omega^2 M phi (M-orthonormal)."""
    mesh, model, held, _ = column
    X = jnp.asarray(model.rest_points)
    K = np.asarray(jax.jit(jax.hessian(lambda u: model.energy(X + u, MATERIAL)))(jnp.zeros_like(X))).reshape(X.size, X.size)
    m = np.repeat(np.asarray(model.lumped_masses(MATERIAL)), 3)
    free = held.free_mask.reshape(-1)
    w2, phi = scipy.linalg.eigh(K[np.ix_(free, free)], np.diag(m[free]))
    return np.sqrt(w2), phi, m, free


def _peaks(t, q):
    """Times and values of the local maxima of |q| (parabolic refinement on the samples)."""
    a = np.abs(q)
    idx = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:])) + 1
    tp, vp = [], []
    for i in idx:
        y0, y1, y2 = a[i - 1], a[i], a[i + 1]
        d = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
        tp.append(t[i] + d * (t[1] - t[0]))
        vp.append(y1 - 0.25 * (y0 - y2) * d)
    return np.array(tp), np.array(vp)


def _free_vibration(column, modes, *, alpha_m, beta_k, n_periods):
    """Release the column from a small static lateral deformation; return the dominant mode's
    angular frequency and its modal coordinate history."""
    mesh, model, held, top = column
    omega, phi, m, free = modes
    load = held.add_force(mesh, top, (1e-4, 0.0, 0.0))  # small: linear regime
    u0 = np.asarray(solve_static(model, MATERIAL, load).displacement)
    part = phi.T @ (m[free] * u0.reshape(-1)[free])
    k = int(np.argmax(np.abs(part)))
    period = 2 * np.pi / omega[k]
    t_end = n_periods * period
    ts = np.linspace(0.0, t_end, N_SAVE)
    sol = simulate_dynamics(
        model, MATERIAL, held, t_end=t_end, t_ramp=period, save_times=ts, alpha_m=alpha_m, beta_k=beta_k,
        initial_displacement=u0, rtol=1e-7, atol=1e-12,
    )
    assert bool(sol.converged)
    q = np.asarray(sol.displacement).reshape(N_SAVE, -1)[:, free] @ (m[free] * phi[:, k])
    return omega[k], ts, q


def test_ramp_is_c2_and_holds():
    t_ramp = 0.3
    t = np.linspace(-0.1, 0.5, 13)
    r, dr, ddr = (np.asarray(v) for v in ramp(t, t_ramp))
    assert r[0] == 0 and np.allclose(r[t >= t_ramp], 1.0)
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(lambda s: ramp(s, t_ramp)[0]))(jnp.asarray(t))), dr, atol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(lambda s: ramp(s, t_ramp)[1]))(jnp.asarray(t))), ddr, atol=1e-10)
    for edge in (0.0, t_ramp):
        assert abs(float(ramp(edge, t_ramp)[1])) < 1e-14 and abs(float(ramp(edge, t_ramp)[2])) < 1e-12


def test_mass_damping_decay_and_period(column, modes):
    """Mass-proportional damping only: every mode decays as exp(-alpha_m t / 2) exactly (linear
    theory); the period is 2 pi / omega_d with omega_d = sqrt(omega^2 - alpha^2 / 4)."""
    alpha = 20.0  # damping ratio alpha / (2 omega) ~ 0.08 for the dominant mode (omega = 121 rad/s)
    omega, ts, q = _free_vibration(column, modes, alpha_m=alpha, beta_k=0.0, n_periods=5)  # beta_k=0.0: shared program
    tp, vp = _peaks(ts, q)
    assert len(tp) >= 8  # |q| peaks twice per period
    rate = np.log(vp[0] / vp[-1]) / (tp[-1] - tp[0])
    assert rate == pytest.approx(alpha / 2, rel=1e-3)  # measured: 2e-5
    period = 2 * (tp[-1] - tp[0]) / (len(tp) - 1)
    assert period == pytest.approx(2 * np.pi / omega, rel=0.01)  # undamped eigenproblem; measured 3.4e-3
    omega_d = np.sqrt(omega**2 - alpha**2 / 4)
    assert period == pytest.approx(2 * np.pi / omega_d, rel=1e-3)  # damped period; measured 1e-5


def test_stiffness_damping_decay(column, modes):
    """Stiffness-proportional damping only: mode decay rate beta_k omega^2 / 2."""
    beta = 2e-4
    omega, ts, q = _free_vibration(column, modes, alpha_m=0.0, beta_k=beta, n_periods=5)
    tp, vp = _peaks(ts, q)
    rate = np.log(vp[0] / vp[-1]) / (tp[-1] - tp[0])
    assert rate == pytest.approx(beta * omega**2 / 2, rel=1e-3)  # measured: 3e-5


def test_ramp_hold_relaxes_to_static(column, modes):
    """Strongly damped ramp-and-hold (large, nonlinear deformation) ends at solve_static's answer."""
    mesh, model, held, top = column
    bc = held.fix(mesh, top, "z", (0.0, 0.0, -2e-3))  # 10 % compression, cubic stiffening active
    bc = bc.add_force(mesh, top, (1e-2, 0.0, 0.0))  # plus a lateral load on the free components
    w1 = modes[0][0]
    t_ramp, t_end = 0.02, 0.3  # alpha_m = 2 w1: slowest decay rate ~ w1 = 117 /s; exp(-117 * 0.28) ~ 6e-15
    sol = simulate_dynamics(
        model, MATERIAL, bc, t_end=t_end, t_ramp=t_ramp, save_times=np.linspace(0.0, t_end, N_SAVE),
        alpha_m=2 * w1, beta_k=2e-4, rtol=1e-6, atol=1e-9,
    )
    st = solve_static(model, MATERIAL, bc)
    u, r = np.asarray(sol.displacement[-1]), np.asarray(sol.reaction[-1])
    assert np.abs(u - np.asarray(st.displacement)).max() <= 1e-6 * np.abs(np.asarray(st.displacement)).max()
    assert np.abs(r - np.asarray(st.reaction)).max() <= 1e-6 * np.abs(np.asarray(st.reaction)).max()
    assert np.all(np.asarray(sol.reaction)[:, bc.free_mask] == 0)


def test_undamped_energy_conservation(column):
    """No damping, force-controlled ramp: H = kinetic + elastic - work of the applied force.
    In the hold phase the load is constant and H = T + E - f.u is conserved to 1e-7 of the
    elastic energy (measured 1.4e-9 with Kvaerno5 at rtol 1e-10); over the ramp,
    H(t_ramp) = -int r' f.u dt (trapezoid) to 1e-4."""
    mesh, model, held, top = column
    bc = held.add_force(mesh, top, (0.02, 0.01, 0.0))  # large lateral deflection
    t_ramp, t_end = 0.02, 0.1
    ts = np.linspace(0.0, t_end, N_SAVE)
    sol = simulate_dynamics(model, MATERIAL, bc, t_end=t_end, t_ramp=t_ramp, save_times=ts, beta_k=0.0, rtol=1e-10, atol=1e-13)
    f = np.asarray(bc.force)
    fu = np.einsum("tnd,nd->t", np.asarray(sol.displacement), f)
    r, dr, _ = (np.asarray(v) for v in ramp(ts, t_ramp))
    H = np.asarray(sol.kinetic_energy) + np.asarray(sol.elastic_energy) - r * fu
    scale = float(np.max(np.asarray(sol.elastic_energy)))
    hold = ts >= t_ramp * (1 - 1e-12)
    assert np.ptp(H[hold]) <= 1e-7 * scale
    up = ts <= t_ramp * (1 + 1e-12)
    ramp_work = np.trapezoid(dr[up] * fu[up], ts[up])  # = int r' f.u over the ramp
    assert H[hold][0] == pytest.approx(-ramp_work, rel=1e-4)  # trapezoid on 33 samples; measured 6e-6


# ------------------------------------------------------------------------------ gradients
T_RAMP, N_STEPS = 0.01, 10


def _loaded(column, params):
    """Material and boundary conditions from ``params = (E / 10 kPa, nu, b, s)``: the top is pushed
    down by ``s * 2 mm`` (10 % strain, where the cubic term matters) and pulled sideways by 10 mN."""
    mesh, model, held, top = column
    E, nu, b, s = params
    bc = held.fix(mesh, top, "z", (0.0, 0.0, -2e-3)).add_force(mesh, top, (1e-2, 0.0, 0.0))
    bc = BoundaryConditions(bc.fixed, bc.displacement * s, bc.force)
    return Material(E * 1e4, nu, b, 1000.0), bc


def _end_of_ramp_output(column, params, adjoint):
    """Top reaction (z) [per 0.1 N] plus lateral top displacement [per mm] at the end of the
    ramp, on N_STEPS constant Kvaerno5 steps (so the discrete solution is smooth in params)."""
    mesh, model, held, top = column
    material, bc = _loaded(column, params)
    sol = simulate_dynamics(
        model, material, bc, t_end=T_RAMP, t_ramp=T_RAMP, save_times=jnp.array([T_RAMP]), alpha_m=100.0, beta_k=1e-4,
        solver="kvaerno5", adaptive=False, dt0=T_RAMP / N_STEPS, max_steps=N_STEPS + 1, adjoint=adjoint,
        root_rtol=1e-12, root_atol=1e-12,
    )
    return sol.reaction[-1, top, 2].sum() / 0.1 + sol.displacement[-1, top[0], 0] / 1e-3


P0 = np.array([1.0, 0.3, 5.0, 1.0])  # E = 10 kPa, nu = 0.3, b = 5, full amplitude


@pytest.fixture(scope="module")
def reverse_gradient(column):
    """(value_and_grad program, gradient at P0) with RecursiveCheckpointAdjoint, compiled once
    (the finite differences evaluate the same program)."""
    vg = jax.jit(jax.value_and_grad(lambda p: _end_of_ramp_output(column, p, "recursive_checkpoint")))
    return vg, np.asarray(vg(jnp.asarray(P0))[1])


def test_gradient_recursive_checkpoint_matches_finite_differences(reverse_gradient):
    """d(output)/d(E, nu, b, amplitude) by reverse mode through diffrax vs central differences
    (step 1e-5 relative; the same compiled program gives the values)."""
    vg, grad = reverse_gradient
    fd = np.empty(4)
    for i in range(4):
        h = 1e-5 * max(abs(P0[i]), 1.0)
        e = np.zeros(4)
        e[i] = h
        fd[i] = (float(vg(jnp.asarray(P0 + e))[0]) - float(vg(jnp.asarray(P0 - e))[0])) / (2 * h)
    assert np.all(np.abs(fd) > 1e-4)  # every parameter matters
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


@pytest.mark.skipif(
    not os.environ.get("DIFFTISSUE_SLOW_TESTS"),
    reason="compiles a second gradient program (~20 s); set DIFFTISSUE_SLOW_TESTS=1 to run",
)
def test_gradient_direct_adjoint_forward_mode(column, reverse_gradient):
    """DirectAdjoint supports forward mode: a JVP along a generic direction equals grad . dir."""
    _, grad = reverse_gradient
    direction = np.array([0.7, -0.2, 0.05, 0.4])
    _, tangent = jax.jvp(lambda p: _end_of_ramp_output(column, p, "direct"), (jnp.asarray(P0),), (jnp.asarray(direction),))
    assert float(tangent) == pytest.approx(float(grad @ direction), rel=1e-9)


# ------------------------------------------------------------------- compilation, errors
def test_no_recompile_for_new_values(column):
    mesh, model, held, top = column
    compiles = []

    def listener(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":  # jax.monitoring's XLA compilation event
            compiles.append(duration)

    def run(material, bc, t_end, t_ramp, alpha, beta):
        sol = simulate_dynamics(
            model, material, bc, t_end=t_end, t_ramp=t_ramp, save_times=np.linspace(0.0, t_end, N_SAVE), alpha_m=alpha, beta_k=beta,
        )
        return np.asarray(sol.displacement)

    m1, bc1 = _loaded(column, (1.0, 0.3, 5.0, 0.1))
    m2, bc2 = _loaded(column, (1.2, 0.35, 2.0, 0.12))
    u1 = run(m1, bc1, 0.01, 0.005, 50.0, 1e-4)  # the adaptive program is compiled by now
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        u2 = run(m2, bc2, 0.012, 0.004, 80.0, 3e-4)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiles == []
    assert not np.allclose(u1, u2)


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(t_ramp=0.0), "t_ramp must be > 0"),
        (dict(t_ramp=-1.0), "t_ramp must be > 0"),
        (dict(t_end=-1.0, save_times=[0.0]), "t_end must be > 0"),
        (dict(save_times=[0.0, 0.2]), r"save_times must lie in \[0, t_end"),
        (dict(save_times=[-0.01, 0.05]), r"save_times must lie in \[0, t_end"),
        (dict(save_times=[0.05, 0.01]), "non-decreasing"),
        (dict(alpha_m=-1.0), "alpha_m .* must be >= 0"),
        (dict(beta_k=-1e-4), "beta_k .* must be >= 0"),
        (dict(solver="rk4"), "unknown solver"),
        (dict(adjoint="adjoint"), "unknown adjoint"),
        (dict(adaptive=False), "need dt0"),
        (dict(initial_displacement=np.zeros((3, 3))), "initial_displacement must have shape"),
    ],
)
def test_bad_input(column, changes, match):
    mesh, model, held, top = column
    kwargs = dict(t_end=0.1, t_ramp=0.01, save_times=[0.0, 0.1])
    kwargs.update(changes)
    with pytest.raises(DifftissueError, match=match):
        simulate_dynamics(model, MATERIAL, held.add_force(mesh, top, (1e-3, 0.0, 0.0)), **kwargs)


def test_failure_raises_convergence_error(column):
    mesh, model, held, top = column
    bc = held.add_force(mesh, top, (1e-3, 0.0, 0.0))
    kwargs = dict(t_end=0.1, t_ramp=0.01, save_times=[0.1], solver="tsit5", max_steps=3)
    with pytest.raises(ConvergenceError, match="maximum number of solver steps"):
        simulate_dynamics(model, MATERIAL, bc, **kwargs)
    sol = simulate_dynamics(model, MATERIAL, bc, throw=False, **kwargs)
    assert not bool(sol.converged) and int(sol.result) != 0
