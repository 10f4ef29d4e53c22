"""Damped second-order dynamics (ramp-and-hold, relaxation, free vibration) with diffrax.

Equations of motion of the free displacement components (DESIGN.md §3.3)::

    M u'' = f_int(u) + r(t) f - C u',      f_int = -dE/dx (X + u),
    C = alpha_m M + beta_k K(x),           K(x) = d^2E/dx^2 (X + u)   (Rayleigh damping)

with lumped nodal masses ``M`` [kg] (:meth:`~difftissue.models.ElasticModel.lumped_masses`),
``alpha_m`` [1/s] and ``beta_k`` [s]. The stiffness-proportional part is applied matrix-free
as a Hessian-vector product (``jax.jvp`` of the energy gradient), with the velocity of *all*
components: ``beta_k K(x) u' = beta_k d/dt (dE/dx)``, so a moving support damps through it too.

Loading: the prescribed components follow ``u_p(t) = r(t) * bc.displacement`` and the
external nodal forces are ``r(t) * bc.force``, with the quintic (C2) ramp

    s = clip(t / t_ramp, 0, 1),    r(t) = 10 s^3 - 15 s^4 + 6 s^5

which rises from 0 to 1 over ``[0, t_ramp]`` with zero velocity and acceleration at both
ends, then holds. Prescribed components are not state: the ODE state is the vectors of free
displacement and velocity components (gathered by static indices), non-dimensionalised
by the specimen size ``L`` and the ramp time ``t_ramp`` (so ``rtol``,
``atol`` are relative: ``atol`` is in units of ``L`` for displacements and ``L / t_ramp``
for velocities).

Reaction (force the supports exert on the prescribed components, the dynamic counterpart of
:attr:`StaticSolution.reaction <difftissue.solvers.static.StaticSolution.reaction>`)::

    R = M u_p'' + dE/dx + C u' - r(t) f          (on prescribed components, 0 elsewhere)

The time integration uses diffrax; implicit solvers (Kvaerno 3/4/5, implicit Euler) solve
each stage by Newton's method with a dense Jacobian (``jax.jacfwd`` of the vector field, LU):
meant for small meshes (up to a few hundred nodes, i.e. ~10^3 unknowns). Gradients go through
diffrax's adjoints (``RecursiveCheckpointAdjoint`` discretise-then-optimise,
``BacksolveAdjoint`` optimise-then-discretise, ``DirectAdjoint`` also for forward mode).
See ``docs/dynamics.md``.
"""

from __future__ import annotations

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._enumerations import result_code, result_message, result_messages
from ..boundary import BoundaryConditions, _validate_values
from ..errors import ConvergenceError, ModelError
from ..materials import Material
from ..models import ElasticModel

__all__ = ["DynamicsSolution", "simulate_dynamics", "ramp", "SOLVERS", "ADJOINTS"]

#: Time integrators accepted by :func:`simulate_dynamics` (implicit ones first).
SOLVERS = ("kvaerno5", "kvaerno4", "kvaerno3", "implicit_euler", "tsit5", "dopri5")
_IMPLICIT = {
    "kvaerno5": diffrax.Kvaerno5,
    "kvaerno4": diffrax.Kvaerno4,
    "kvaerno3": diffrax.Kvaerno3,
    "implicit_euler": diffrax.ImplicitEuler,
}
_EXPLICIT = {"tsit5": diffrax.Tsit5, "dopri5": diffrax.Dopri5}
#: Adjoints accepted by :func:`simulate_dynamics`.
ADJOINTS = ("recursive_checkpoint", "backsolve", "direct")


def ramp(t, t_ramp):
    """The loading history ``r(t)`` and its first two time derivatives.

    ``s = clip(t / t_ramp, 0, 1)``, ``r = 10 s^3 - 15 s^4 + 6 s^5`` (quintic smoothstep: C2,
    ``r(0) = 0``, ``r(t >= t_ramp) = 1``, ``r' = r'' = 0`` at both ends).

    Returns:
        ``(r [-], dr/dt [1/s], d2r/dt2 [1/s^2])``.
    """
    t = jnp.asarray(t)
    s = jnp.clip(t / t_ramp, 0.0, 1.0)
    r = s**3 * (10.0 + s * (-15.0 + 6.0 * s))
    dr = 30.0 * s**2 * (1.0 - s) ** 2 / t_ramp
    ddr = 60.0 * s * (1.0 - s) * (1.0 - 2.0 * s) / t_ramp**2
    return r, dr, ddr


class DynamicsSolution(eqx.Module):
    """Result of :func:`simulate_dynamics`.

    Attributes:
        ts: ``(T,)`` save times [s].
        displacement: ``(T, N, 3)`` nodal displacements [m] (prescribed values included).
        velocity: ``(T, N, 3)`` nodal velocities [m/s] (prescribed ``r'(t) * bc.displacement``).
        reaction: ``(T, N, 3)`` force the supports exert on the prescribed components [N]:
            ``M u_p'' + dE/dx + C u' - r(t) f`` there, zero on free components. At rest it
            equals the static reaction of :func:`~difftissue.solvers.static.solve_static`.
        external_force: ``(T, N, 3)`` applied force ``r(t) * bc.force`` on free components [N].
        kinetic_energy: ``(T,)`` [J] (all components, prescribed ones included).
        elastic_energy: ``(T,)`` [J].
        result: diffrax's result code (``int32``; 0 = successful, see ``diffrax.RESULTS``).
        num_steps: accepted steps (``int``).
        num_rejected_steps: rejected steps (``int``; error too large or a Newton solve failed).
    """

    ts: jax.Array
    displacement: jax.Array
    velocity: jax.Array
    reaction: jax.Array
    external_force: jax.Array
    kinetic_energy: jax.Array
    elastic_energy: jax.Array
    result: jax.Array
    num_steps: jax.Array
    num_rejected_steps: jax.Array

    @property
    def converged(self) -> jax.Array:
        """True when diffrax reached ``t_end`` successfully."""
        return self.result == 0


class _Options(eqx.Module):
    solver: str = eqx.field(static=True)
    adaptive: bool = eqx.field(static=True)
    adjoint: str = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    root_max_steps: int = eqx.field(static=True)
    has_dt0: bool = eqx.field(static=True)
    stiffness_damping: bool = eqx.field(static=True)
    #: flat indices ``3 * node + component`` of the free components (the problem's structure).
    free_idx: tuple = eqx.field(static=True)


class _Args(eqx.Module):
    """Everything the vector field needs, passed through diffrax's ``args`` so that every
    adjoint (BacksolveAdjoint included) sees the differentiable leaves."""

    model: ElasticModel
    material: Material
    displacement: jax.Array
    force: jax.Array
    masses: jax.Array  # (N, 1) [kg]
    alpha_m: jax.Array
    beta_k: jax.Array
    t_ramp: jax.Array
    length: jax.Array
    prescribed: jax.Array  # (N, 3) 1.0 on prescribed components, 0.0 on free ones
    free_idx: tuple = eqx.field(static=True)  # flat indices of the free components (hashable)


def _scatter(a: "_Args", prescribed_part, free_values):
    """Full ``(N, 3)`` array: ``prescribed_part`` on prescribed components, ``free_values`` (n_free,) on free ones."""
    flat = (a.prescribed * prescribed_part).reshape(-1)
    return flat.at[np.asarray(a.free_idx)].set(free_values).reshape(prescribed_part.shape)


def _kinematics(t, q, w, a: _Args):
    """Full displacement [m], velocity [m/s] and prescribed acceleration [m/s^2] at time t [s]."""
    r, dr, ddr = ramp(t, a.t_ramp)
    u = _scatter(a, r * a.displacement, a.length * q)
    v = _scatter(a, dr * a.displacement, (a.length / a.t_ramp) * w)
    acc_p = a.prescribed * ddr * a.displacement
    return u, v, acc_p, r


def _forces(u, v, a: _Args, stiffness_damping: bool):
    """``(dE/dx, C v)`` at displacement ``u`` with velocity ``v`` [N]."""
    X = jnp.asarray(a.model.rest_points)

    def grad_energy(uu):
        return jax.grad(lambda z: a.model.energy(X + z, a.material))(uu)

    if not stiffness_damping:  # beta_k=None: skip the Hessian-vector product
        return grad_energy(u), a.alpha_m * a.masses * v
    g, Kv = jax.jvp(grad_energy, (u,), (v,))
    return g, a.alpha_m * a.masses * v + a.beta_k * Kv


def _vector_field(s, y, a: _Args, stiffness_damping: bool):
    """d/ds of the dimensionless state ``(q, w) = (u_free / L, t_ramp v_free / L)`` (vectors of
    the free components only), ``s = t / t_ramp``."""
    q, w = y
    t = s * a.t_ramp
    u, v, _, r = _kinematics(t, q, w, a)
    g, damp = _forces(u, v, a, stiffness_damping)
    acc = ((r * a.force - g - damp) / a.masses).reshape(-1)[np.asarray(a.free_idx)]
    return w, (a.t_ramp**2 / a.length) * acc


def _make_solver(options: _Options, rtol, atol):
    if options.solver in _EXPLICIT:
        return _EXPLICIT[options.solver]()
    # Newton with a dense Jacobian (jacfwd + LU). Its tolerances are tighter than the
    # step controller's so that the discrete solution is a smooth function of the
    # parameters to that level (finite-difference checks, gradient-based fits).
    root = optx.Newton(rtol=rtol, atol=atol, norm=optx.rms_norm)
    return _IMPLICIT[options.solver](root_finder=root, root_find_max_steps=options.root_max_steps)


def _make_adjoint(options: _Options, solver, rtol, atol):
    if options.adjoint == "recursive_checkpoint":
        return diffrax.RecursiveCheckpointAdjoint()
    if options.adjoint == "direct":
        return diffrax.DirectAdjoint()
    # Backward pass: the adjoint state has its own, unknown scale, so fixed root-finder
    # tolerances do not fit it. Use diffrax's standard setup instead: the same method with
    # its default chord root finder inheriting the tolerances of an adaptive PID controller
    # (rtol, atol), which rejects and shrinks a step whose stage solve fails, even when the
    # forward pass used constant steps. throw=True: a failed backward solve raises rather
    # than returning a silently wrong gradient.
    back_solver = _IMPLICIT[options.solver]() if options.solver in _IMPLICIT else solver
    back_controller = diffrax.PIDController(rtol=rtol, atol=atol)
    return diffrax.BacksolveAdjoint(solver=back_solver, stepsize_controller=back_controller, max_steps=max(options.max_steps, 16384), throw=True)


def _simulate_impl(
    model, material, bc_disp, bc_force, u0, v0, t_end, t_ramp, save_times, alpha_m, beta_k, dt0, rtol, atol, root_rtol, root_atol, length, options: _Options
):
    masses = model.lumped_masses(material)[:, None]
    idx = np.asarray(options.free_idx, dtype=np.int64)
    prescribed = np.ones(u0.size)
    prescribed[idx] = 0.0
    prescribed = jnp.asarray(prescribed.reshape(u0.shape), dtype=u0.dtype)
    P = 1.0 - prescribed
    # The mesh geometry is data, not a parameter: stop_gradient keeps it out of the adjoint
    # state of BacksolveAdjoint (which integrates a cotangent for every float leaf of args).
    model = jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, model)
    a = _Args(model, material, bc_disp, bc_force, masses, alpha_m, beta_k, t_ramp, length, prescribed, options.free_idx)
    # Dimensionless state: free components only.
    y0 = (u0.reshape(-1)[idx] / length, v0.reshape(-1)[idx] * t_ramp / length)
    solver = _make_solver(options, root_rtol, root_atol)
    if options.adaptive:
        controller = diffrax.PIDController(rtol=rtol, atol=atol)
    else:
        controller = diffrax.ConstantStepSize()
    adjoint = _make_adjoint(options, solver, rtol, atol)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(functools.partial(_vector_field, stiffness_damping=options.stiffness_damping)),
        solver,
        t0=jnp.zeros_like(t_end),
        t1=t_end / t_ramp,
        dt0=dt0 / t_ramp if options.has_dt0 else None,
        y0=y0,
        args=a,
        saveat=diffrax.SaveAt(ts=save_times / t_ramp),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=options.max_steps,
        throw=False,
    )
    qs, ws = sol.ys

    def outputs(t, q, w):
        u, v, acc_p, r = _kinematics(t, q, w, a)
        g, damp = _forces(u, v, a, options.stiffness_damping)
        reaction = (1.0 - P) * (masses * acc_p + g + damp - r * bc_force)
        f_ext = P * r * bc_force
        ke = 0.5 * jnp.sum(masses * v * v)
        ee = model.energy(jnp.asarray(model.rest_points) + u, material)
        return u, v, reaction, f_ext, ke, ee

    u, v, reaction, f_ext, ke, ee = jax.vmap(outputs)(save_times, qs, ws)
    return DynamicsSolution(
        ts=save_times,
        displacement=u,
        velocity=v,
        reaction=reaction,
        external_force=f_ext,
        kinetic_energy=ke,
        elastic_energy=ee,
        result=result_code(sol.result).astype(jnp.int32),
        num_steps=sol.stats["num_accepted_steps"],
        num_rejected_steps=sol.stats["num_rejected_steps"],
    )


_simulate = eqx.filter_jit(_simulate_impl)


def _result_message(code: int) -> str:
    try:
        msg = result_message(diffrax.RESULTS, code)
    except (IndexError, KeyError, ValueError):
        msg = ""
    return msg or f"diffrax result code {code}"


def _is_traced(*xs) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(xs))


def simulate_dynamics(
    model: ElasticModel,
    material: Material,
    bc: BoundaryConditions,
    *,
    t_end,
    t_ramp,
    save_times,
    alpha_m=0.0,
    beta_k=None,
    solver: str = "kvaerno5",
    adaptive: bool = True,
    dt0=None,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    root_rtol=None,
    root_atol=None,
    root_max_steps: int = 10,
    adjoint: str = "recursive_checkpoint",
    max_steps: int = 16384,
    initial_displacement=None,
    initial_velocity=None,
    throw: bool = True,
) -> DynamicsSolution:
    """Damped dynamics of ``model`` under ramp-and-hold loading ``bc``, differentiable.

    Solves ``M u'' = f_int(u) + r(t) f - (alpha_m M + beta_k K(u)) u'`` for the free
    components while the prescribed ones follow ``r(t) * bc.displacement`` (see the module
    docstring and ``docs/dynamics.md`` for the ramp ``r`` and the reaction).

    Args:
        model, material: the elastic model and its material (as for ``solve_static``).
        bc: prescribed displacement amplitudes [m] and force amplitudes [N], reached at ``t_ramp``.
        t_end: end time [s] (> 0).
        t_ramp: ramp duration [s] (> 0); also the time scale of the non-dimensional state.
        save_times: ``(T,)`` non-decreasing times in ``[0, t_end]`` [s] where outputs are saved.
        alpha_m: mass-proportional damping [1/s] (>= 0): every mode decays at least as
            ``exp(-alpha_m t / 2)``.
        beta_k: stiffness-proportional damping [s] (>= 0): modal damping ratio ``beta_k omega / 2``.
            ``None`` (default) leaves the term out of the compiled program (it costs a
            Hessian-vector product per evaluation and about doubles compile time); any number,
            0 included, keeps it, so changing its value never recompiles.
        solver: one of :data:`SOLVERS`. ``"kvaerno5"`` (default), ``"kvaerno4"``, ``"kvaerno3"``
            and ``"implicit_euler"`` are implicit (Newton, dense Jacobian), for stiff problems;
            ``"tsit5"``/``"dopri5"`` are explicit (only for very small, lightly damped cases).
        adaptive: adaptive steps (PID controller with ``rtol``/``atol``) or constant steps ``dt0``.
        dt0: initial (adaptive; ``None`` = automatic) or constant (required) step [s].
        rtol, atol: step-control tolerances on the dimensionless state; ``atol`` is relative to
            the specimen size ``L`` (displacements) and to ``L / t_ramp`` (velocities).
        root_rtol, root_atol: Newton tolerances of the implicit stages (default ``1e-3 * rtol``
            and ``max(1e-3 * atol, 1e-12)``; tighter than the step control). ``root_atol`` bounds
            the stage residual absolutely: too small a value is defeated by round-off and shows
            as many ``num_rejected_steps`` and a slow solve.
        root_max_steps: Newton iterations per stage.
        adjoint: ``"recursive_checkpoint"`` (exact gradient of the discrete solution, reverse
            mode; the default), ``"direct"`` (exact too, and supports forward mode ``jax.jvp``)
            or ``"backsolve"`` (continuous adjoint: O(1) memory, gradient accurate to
            ``rtol``/``atol`` only, backward pass always adaptive; on the 12-node test column
            ~100x slower than ``"recursive_checkpoint"`` -- see ``docs/dynamics.md``).
        max_steps: maximum number of time steps (static: changing it recompiles).
        initial_displacement, initial_velocity: ``(N, 3)`` initial state [m], [m/s] of the free
            components (default rest); prescribed components start at ``r(0) = 0``.
        throw: raise :class:`~difftissue.errors.ConvergenceError` (outside jit; an ``equinox``
            runtime error inside jit) when diffrax fails; with ``throw=False`` inspect
            ``result`` / ``converged``.

    Returns:
        A :class:`DynamicsSolution` (SI units).

    Cost and size: each Newton iteration of an implicit stage assembles the dense
    ``2 n_free x 2 n_free`` Jacobian of the vector field by forward-mode AD and factorises it
    (LU), so this is meant for small meshes (up to a few hundred nodes, ~10^3 unknowns).
    A new program is compiled for each mesh, pattern of prescribed components (``bc.fixed``),
    ``solver``, ``adaptive``, ``adjoint``, ``max_steps``, ``root_max_steps``, number of save
    times, ``beta_k is None`` and ``dt0 is None``; new values of the material, of
    ``bc.displacement`` / ``bc.force``, of the times, damping and tolerances reuse it.
    The mesh geometry is treated as data: no gradient flows to ``model``.
    """
    if not isinstance(model, ElasticModel):
        raise ModelError(f"model must be an ElasticModel (see difftissue.models.make_model), got {type(model).__name__}")
    if solver not in SOLVERS:
        raise ModelError(f"unknown solver {solver!r}; choose one of {SOLVERS}")
    if adjoint not in ADJOINTS:
        raise ModelError(f"unknown adjoint {adjoint!r}; choose one of {ADJOINTS}")
    if not isinstance(adaptive, bool):
        raise ModelError(f"adaptive must be True or False, got {adaptive!r}")
    if not adaptive and dt0 is None:
        raise ModelError("constant steps (adaptive=False) need dt0 [s]")
    max_steps = int(max_steps)
    if max_steps < 1:
        raise ModelError(f"max_steps must be >= 1, got {max_steps}")
    n = model.n_nodes
    _validate_values(bc, n)
    model.region_values(material)  # range checks (raise now when concrete)

    f = lambda v: jnp.asarray(v, dtype=float)  # noqa: E731  (arrays, never Python floats: no recompiles)
    stiffness_damping = beta_k is not None
    t_end, t_ramp, alpha_m, beta_k = f(t_end), f(t_ramp), f(alpha_m), f(0.0 if beta_k is None else beta_k)
    save_times = f(save_times)
    for name, val in (("t_end", t_end), ("t_ramp", t_ramp), ("alpha_m", alpha_m), ("beta_k", beta_k)):
        if val.ndim != 0:
            raise ModelError(f"{name} must be a scalar, got shape {val.shape}")
    if save_times.ndim != 1 or save_times.shape[0] == 0:
        raise ModelError(f"save_times must be a non-empty 1-D array of times [s], got shape {save_times.shape}")
    rtol, atol = f(rtol), f(atol)
    root_rtol = 1e-3 * rtol if root_rtol is None else f(root_rtol)
    # The Newton residual test |F| <= root_atol is absolute: below ~1e-12 (dimensionless)
    # round-off makes it unreachable, stages fail and steps get rejected. Hence the floor.
    root_atol = jnp.maximum(1e-3 * atol, 1e-12) if root_atol is None else f(root_atol)
    dt0_arr = f(0.0 if dt0 is None else dt0)

    scalars = {"t_end": t_end, "t_ramp": t_ramp, "alpha_m": alpha_m, "beta_k": beta_k, "rtol": rtol, "atol": atol, "dt0": dt0_arr}
    rules = {
        "t_end": (lambda x: x > 0, "t_end must be > 0 s"),
        "t_ramp": (lambda x: x > 0, "t_ramp must be > 0 s (use a short ramp, e.g. 1e-3 * t_end, for a step load)"),
        "alpha_m": (lambda x: x >= 0, "alpha_m (mass-proportional damping) must be >= 0 1/s"),
        "beta_k": (lambda x: x >= 0, "beta_k (stiffness-proportional damping) must be >= 0 s"),
        "rtol": (lambda x: x >= 0, "rtol must be >= 0"),
        "atol": (lambda x: x >= 0, "atol must be >= 0"),
        "dt0": (lambda x: x > 0, "dt0 must be > 0 s"),
    }
    if dt0 is None:
        del scalars["dt0"]
    if not _is_traced(scalars, save_times):
        for name, val in scalars.items():
            ok, msg = rules[name]
            if not (np.isfinite(float(val)) and ok(float(val))):
                raise ModelError(f"{msg}, got {float(val)!r}")
        st = np.asarray(save_times)
        if not np.all(np.isfinite(st)) or st.min() < 0 or st.max() > float(t_end):
            raise ModelError(f"save_times must lie in [0, t_end = {float(t_end):g}] s, got min {st.min():g} max {st.max():g}")
        if np.any(np.diff(st) < 0):
            raise ModelError("save_times must be non-decreasing")
    else:
        for name, val in scalars.items():
            ok, msg = rules[name]
            scalars[name] = eqx.error_if(val, ~(jnp.isfinite(val) & ok(val)), msg)
        t_end, t_ramp, alpha_m, beta_k, rtol, atol = (scalars[k] for k in ("t_end", "t_ramp", "alpha_m", "beta_k", "rtol", "atol"))
        dt0_arr = scalars.get("dt0", dt0_arr)
        bad = (save_times.min() < 0) | (save_times.max() > t_end) | jnp.any(jnp.diff(save_times) < 0)
        save_times = eqx.error_if(save_times, bad, "save_times must be non-decreasing and lie in [0, t_end]")

    if not _is_traced(material):
        m = np.asarray(model.lumped_masses(material))
        if not np.all(m > 0):
            raise ModelError(f"{int(np.sum(~(m > 0)))} node(s) have no mass (nodes in no tetrahedron?); remove unused nodes")

    q0 = jnp.zeros((n, 3)) if initial_displacement is None else f(initial_displacement)
    v0 = jnp.zeros((n, 3)) if initial_velocity is None else f(initial_velocity)
    for name, val in (("initial_displacement", q0), ("initial_velocity", v0)):
        if val.shape != (n, 3):
            raise ModelError(f"{name} must have shape ({n}, 3), got {val.shape}")
    pts = np.asarray(model.rest_points)
    length = f(float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0)
    material = jax.tree_util.tree_map(f, material)
    # beta_k=None: the stiffness-damping term is left out of the compiled program.
    free_idx = tuple(int(i) for i in np.flatnonzero(np.asarray(bc.free_mask).reshape(-1)))
    if not free_idx:
        raise ModelError("every displacement component is prescribed: there is no dynamics to solve")
    options = _Options(solver, adaptive, adjoint, max_steps, int(root_max_steps), dt0 is not None, stiffness_damping, free_idx)
    sol = _simulate(
        model, material, f(bc.displacement), f(bc.force), q0, v0, t_end, t_ramp, save_times, alpha_m, beta_k, dt0_arr, rtol, atol, root_rtol, root_atol, length, options
    )
    if throw:
        code = sol.result
        if isinstance(code, jax.core.Tracer):
            msgs = [_result_message(i) for i in range(len(result_messages(diffrax.RESULTS)))]
            msgs = ["dynamics: " + m if m else "" for m in msgs]
            sol = eqx.tree_at(lambda s: s.displacement, sol, eqx.branched_error_if(sol.displacement, code != 0, code, msgs))
        elif int(code) != 0:
            raise ConvergenceError(f"dynamics: diffrax failed after {int(sol.num_steps)} steps: {_result_message(int(code))}")
    return sol
