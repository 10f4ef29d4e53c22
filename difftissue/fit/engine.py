"""ONE optimiser engine and ONE step loop for :func:`~difftissue.fit.fit` and
:func:`~difftissue.fit.fit_batch`: the tolerance defaults, the vmapped single-start step of
each method (Levenberg--Marquardt / Gauss--Newton on optimistix's public extension points,
:mod:`difftissue.fit.gauss_newton`; optax Adam / L-BFGS), the
compiled-engine cache and the Python loop that calls the step.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._enumerations import result_code as _result_code
from .._enumerations import result_message as _result_message
from .gauss_newton import GaussNewton, GaussNewtonState
from .marquardt import ScaledLevenbergMarquardt
from .problem import FitProblem


#: Optimisers understood by :func:`~difftissue.fit.fit` and :func:`~difftissue.fit.fit_batch`.
METHODS = ("levenberg_marquardt", "gauss_newton", "adam", "lbfgs")

#: Default stopping tolerances ``(rtol, atol)`` by the precision of the starts: the ONE place
#: for :func:`~difftissue.fit.fit` and :func:`~difftissue.fit.fit_batch`.
TOLERANCES = {"float64": (1e-8, 1e-10), "float32": (1e-5, 1e-7)}


def tolerances(dtype, rtol: float | None = None, atol: float | None = None) -> tuple[float, float]:
    """``(rtol, atol)``: the given values, or the defaults of :data:`TOLERANCES` for starts of
    ``dtype`` (float64 when JAX's x64 mode is on and the starts are double, else float32)."""
    key = "float64" if np.dtype(dtype) == np.float64 else "float32"
    default_rtol, default_atol = TOLERANCES[key]
    return (default_rtol if rtol is None else float(rtol), default_atol if atol is None else float(atol))


# ============================================================================ optimisers
def _tree_where(cond, new, old):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(cond, a, b), new, old)


def strong(tree):
    """Every array leaf with its dtype made strong (not weak-typed), so the state that goes into
    the jitted step has the same avals as what comes out: no recompilation at the second step."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x)) if eqx.is_array(x) else x, tree)


def _with_forward_jacobian(f):
    """``f`` (``u (p,) -> pytree of arrays``) with a custom JVP that computes the whole Jacobian
    by forward mode (``jax.jacfwd``: p tangents in one pass) and applies it to the tangent.

    Same values and derivatives as ``f``. What changes is what a linearisation keeps: for
    ``jax.linearize`` (optimistix's Gauss--Newton family keeps the linearised function in its
    state, and carries it from step to step) the residuals are the Jacobian matrices, (n, p)
    per output, instead of every intermediate of the forward model -- 12 M floats (97 MB) per
    start on the 4,800-tet benchmark of ``benchmarks/fit.py``.
    """

    @jax.custom_jvp
    def g(u):
        return f(u)

    @g.defjvp
    def g_jvp(primals, tangents):
        (u,), (du,) = primals, tangents

        def both(v):
            out = f(v)
            return out, out

        J, out = jax.jacfwd(both, has_aux=True)(u)
        return out, jax.tree_util.tree_map(lambda Ji: Ji @ du, J)

    return g


class Engine:
    """One optimiser: ``init(U) -> dyn`` (batched state arrays) and a vmapped ``step``."""

    def __init__(self, problem: FitProblem, method: str, *, rtol: float, atol: float, learning_rate: float, jac: str):
        self.problem = problem
        self.method = method
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.jac = jac
        self.learning_rate = float(learning_rate)
        self.traces = 0
        if method in ("levenberg_marquardt", "gauss_newton"):
            import optimistix as optx

            self._optx = optx
            # Levenberg--Marquardt damps with Marquardt's scaling (lambda diag(J^T J), not
            # optimistix's lambda I): see :mod:`difftissue.fit.marquardt`. Both solvers are
            # difftissue's (:mod:`difftissue.fit.gauss_newton`: optimistix's Gauss--Newton
            # algorithm on its public extension points), so the state the engine reads below
            # -- residual, Jacobian and aux at the accepted point, the next trial point -- is
            # difftissue's :class:`GaussNewtonState`, not a private optimistix class.
            cls = ScaledLevenbergMarquardt if method == "levenberg_marquardt" else GaussNewton
            self.solver = cls(rtol=self.rtol, atol=self.atol)
            # The predictions ride along as the solver's aux: with the residual and Jacobian
            # the solver keeps at the accepted point, they give the fit's final evaluation
            # without compiling the forward model a second time (:meth:`make_final`).
            # With jac="fwd" the Jacobian is computed whole by forward mode inside a custom JVP
            # (:func:`_with_forward_jacobian`): the linearisation the solver keeps in its state
            # is then the (n, p) matrix, not every intermediate of the forward model.
            if jac == "fwd":
                self._fn = lambda y, data: _with_forward_jacobian(problem.with_data(data).residuals_and_predictions)(y)
            else:
                self._fn = lambda y, data: problem.with_data(data).residuals_and_predictions(y)
            self._options = {"jac": jac}
            self._tags = frozenset()
        else:
            import optax

            self._optax = optax
            if method == "adam":
                self.solver = optax.adam(self.learning_rate)
            else:
                self.solver = optax.lbfgs()

    # -- optimistix ------------------------------------------------------------------
    def _residual_struct(self, u) -> jax.ShapeDtypeStruct:
        """Shape and dtype of the residual vector, without tracing the forward model: the
        residuals ``(predict - observed) / sigma`` carry the promoted dtype of ``u`` and the
        float64 data (float32 when x64 is off)."""
        dtype = jax.dtypes.canonicalize_dtype(np.result_type(u.dtype, np.float64))
        return jax.ShapeDtypeStruct((self.problem.n_residuals,), dtype)

    def _optx_init_single(self, u, data):
        f_struct = self._residual_struct(u)
        aux_struct = tuple(jax.ShapeDtypeStruct((n,), f_struct.dtype) for n in self.problem.sizes)
        return self.solver.init(self._fn, u, data, self._options, f_struct, aux_struct, self._tags)

    def init(self, U, data):
        """Batched dynamic state for starts ``U`` (shape ``(S, p)``) of the problem with ``data``.

        One jitted program per engine (retraced only for a new number of starts): the optimiser's
        initial state is built from shapes (optimistix traces the model abstractly), so running
        it eagerly would dispatch and compile every small zero-filled array separately."""
        if getattr(self, "_init", None) is None:
            if hasattr(self, "_optx"):

                def batched(U, data):
                    def one(u):
                        dyn, static = eqx.partition(self._optx_init_single(u, data), eqx.is_array)
                        if not hasattr(self, "_static"):  # keep the first one: the compiled step closes over it
                            self._static = static
                        return dyn

                    return strong(jax.vmap(one)(U))

            else:

                def batched(U, data):
                    return strong(jax.vmap(self.solver.init)(U))

            self._init = jax.jit(batched)
        return self._init(U, data)

    def evaluate(self, U, data):
        """``(values (S, p), loss (S,), J (S, n, p), predictions)`` of every start ``U`` (S, p):
        the physical values, the loss, the Jacobian of the robustified scaled residuals w.r.t.
        the physical values and each scenario's predictions (not jitted; see :meth:`make_evaluate`)."""
        problem = self.problem.with_data(data)
        fields = problem.fields
        values = jax.vmap(lambda u: jnp.stack([problem.values(u)[f] for f in fields]))(U)
        loss, J, preds = jax.vmap(lambda v: problem.evaluate_values(v, self.jac))(values)
        return values, loss, J, preds

    def make_evaluate(self):
        """:meth:`evaluate` jitted once per engine (at the start and the end of every fit)."""
        if getattr(self, "_evaluate", None) is None:
            self._evaluate = jax.jit(self.evaluate)
        return self._evaluate

    def make_final(self):
        """Optimistix methods: ``(U, dyn, data) -> (values, loss, J, predictions, ok)`` from the
        solver state alone, jitted once per engine -- the residual, the Jacobian (materialised
        from the linearisation the solver keeps at the accepted point) and the predictions (the
        aux) of every start, the Jacobian taken to the PHYSICAL values by the chain rule through
        the transforms. ``ok`` is False for a start whose state holds no evaluation (no step
        taken) or whose transform derivative is singular (a parameter saturated at a bound):
        :func:`fit` then uses :meth:`make_evaluate`. ``None`` for optax methods."""
        if not hasattr(self, "_optx"):
            return None
        if getattr(self, "_final", None) is None:
            template, static = self.problem, self._static
            fields = template.fields

            def final(U, dyn, data):
                problem = template.with_data(data)

                def values_of(u):
                    vals = problem.values(u)
                    return jnp.stack([vals[f] for f in fields])

                def one(u, d):
                    state: GaussNewtonState = eqx.combine(d, static)
                    Ju = state.f_info.jac.as_matrix()
                    dvdu = jax.jacfwd(values_of)(u)
                    Jv = jnp.linalg.solve(dvdu.T, Ju.T).T  # Ju = Jv dv/du
                    r = state.f_info.residual
                    smallest = jnp.min(jnp.linalg.svd(dvdu, compute_uv=False))
                    ok = (state.num_steps > 0) & (smallest > 1e-100) & jnp.all(jnp.isfinite(Jv))
                    return values_of(u), 0.5 * jnp.sum(r * r), Jv, tuple(state.aux), ok

                return jax.vmap(one)(U, dyn)

            self._final = jax.jit(final)
        return self._final

    def make_step(self):
        """The ONE jitted step: ``(U, dyn, done, data) -> (U, dyn, done, status, loss)``,
        vmapped over starts (``data`` is shared by the starts: :meth:`FitProblem.data`).

        ``status``: 0 running or converged, >0 failure code (optimistix RESULTS index, or -1 for a
        non-finite loss in optax)."""
        if getattr(self, "_step", None) is None:
            one = self.single_step()

            def step(U, dyn, done, data):
                self.traces += 1  # Python side effect: runs once per trace (compilation)
                return strong(jax.vmap(one, in_axes=(0, 0, 0, None))(U, dyn, done, data))

            self._step = jax.jit(step)
        return self._step

    def single_step(self):
        """The step of ONE start, not jitted nor vmapped: ``(u, dyn, done, data) -> (u, dyn,
        done, status, loss)``; :meth:`make_step` and :func:`difftissue.fit.fit_batch` build
        their compiled programs from it."""
        template = self.problem
        rtol, atol = self.rtol, self.atol

        if hasattr(self, "_optx"):
            solver, fn, options, tags, static = self.solver, self._fn, self._options, self._tags, self._static

            def one(u, dyn, done, data):
                state: GaussNewtonState = eqx.combine(dyn, static)
                u_new, state_new, _ = solver.step(fn, u, data, options, state, tags)
                term, result = solver.terminate(fn, u_new, data, options, state_new, tags)
                dyn_new = eqx.partition(state_new, eqx.is_array)[0]
                status = _result_code(result)
                r = state_new.f_info.residual
                loss = 0.5 * jnp.sum(r * r)
                # Also stop when a trial step was rejected and the next one is below the x
                # tolerance (as SciPy's least_squares tests xtol on every trial step).
                # Optimistix tests only accepted steps: at the optimum the trial steps change
                # the loss at round-off, are rejected, and the trust region shrinks for another
                # 10-17 steps (each a forward + Jacobian) before one is accepted unchanged. The
                # result is the last accepted point, as before.
                trial = state_new.y_eval - u_new
                rejected = state_new.num_steps_since_acceptance > 0
                J = state_new.f_info.jac.as_matrix()
                # A rejected trial step below the x tolerance; or, within KINK_NEIGHBOURHOOD
                # standard errors of the Gauss--Newton optimum, a rejected trial step below
                # STATIONARY_STEP standard errors: no statistically meaningful step decreases
                # the loss. This is how a fit ends whose minimum sits on a kink of the residuals
                # (a contact-set change of a discretised contact: the one-sided Gauss--Newton
                # steps point at each other, and the trust region creeps towards the kink until
                # max_steps). Far from the optimum a small rejected step only means a strongly
                # nonlinear model (the trust region shrank): the fit goes on.
                near = _statistically_small(J, r, jnp.linalg.lstsq(J, r)[0], KINK_NEIGHBOURHOOD)
                negligible = rejected & ((jnp.linalg.norm(trial) <= atol + rtol * jnp.linalg.norm(u_new)) | (near & _statistically_small(J, r, trial)))
                # And stop when the accepted point is stationary to within a statistically
                # negligible step: the Gauss--Newton step that is left moves the parameters by
                # less than STATIONARY_STEP standard errors (Bates & Watts' relative-offset
                # criterion). On noisy data the x tolerance rtol |u| can sit below the
                # forward model's own precision, and the fit would crawl at a constant loss
                # until max_steps. Or when that Gauss--Newton step is below the x tolerance:
                # on exact (noise-free) data the point is then converged, and the damped steps
                # left would only move it below the tolerance (see :func:`_stationary`).
                # And when the residuals are within the forward models' own precision of the data
                # (FitProblem.precision_floor: simulated, noise-free data): the steps after that
                # fit round-off, whose Gauss--Newton step can stay above the x tolerance.
                at_floor = jnp.linalg.norm(r) <= template.with_data(data).precision_floor()
                finished = term | (status != 0) | negligible | at_floor | _stationary(J, r, u_new, rtol, atol)
                u_out = jnp.where(done, u, u_new)
                dyn_out = _tree_where(done, dyn, dyn_new)
                return u_out, dyn_out, done | finished, jnp.where(done, 0, status), loss

        else:
            optax = self._optax
            solver = self.solver
            lbfgs = self.method == "lbfgs"

            def one(u, state, done, data):
                loss_fn = template.with_data(data).loss
                if lbfgs:
                    value, grad = optax.value_and_grad_from_state(loss_fn)(u, state=state)
                    updates, state_new = solver.update(grad, state, u, value=value, grad=grad, value_fn=loss_fn)
                else:
                    value, grad = jax.value_and_grad(loss_fn)(u)
                    updates, state_new = solver.update(grad, state, u)
                u_new = optax.apply_updates(u, updates)
                if lbfgs:
                    # L-BFGS: optax's zoom line search treats a non-finite trial value (a
                    # failed static solve) as a failed decrease and shortens the step.
                    loss_new = optax.tree_utils.tree_get(state_new, "value")
                else:
                    loss_new = loss_fn(u_new)

                    # Adam: a trial point whose loss is not finite (a static solve that failed
                    # gives NaN predictions, SolverOptions(failure="nan")) is rejected and the
                    # step halved until the loss is finite (at most ADAM_MAX_HALVINGS times), as
                    # Levenberg--Marquardt shrinks its trust region; the moments keep the
                    # gradient at the accepted point u.
                    def shorter(c):
                        alpha, _, k = c
                        alpha = 0.5 * alpha
                        return alpha, loss_fn(u + alpha * updates), k + 1

                    def rejected(c):
                        return ~jnp.isfinite(c[1]) & (c[2] < ADAM_MAX_HALVINGS) & jnp.isfinite(value)

                    alpha, loss_new, _ = jax.lax.while_loop(rejected, shorter, (jnp.asarray(1.0, u.dtype), loss_new, jnp.asarray(0, jnp.int32)))
                    u_new = u + alpha * updates
                du = jnp.max(jnp.abs(u_new - u))
                small_u = du <= atol + rtol * jnp.max(jnp.abs(u_new))
                small_f = jnp.abs(loss_new - value) <= atol + rtol * jnp.abs(value)
                bad = ~jnp.isfinite(loss_new)
                finished = (small_u & small_f) | bad
                status = jnp.where(bad, -1, 0)
                u_out = jnp.where(done, u, u_new)
                state_out = _tree_where(done, state, state_new)
                loss_out = jnp.where(done, value, loss_new)  # a stopped start stays at u, whose loss is value
                return u_out, state_out, done | finished, jnp.where(done, 0, status), loss_out

        return one

    def status_message(self, code: int) -> str:
        if code == -1:
            return "non-finite loss"
        if hasattr(self, "_optx"):
            msg = _result_message(self._optx.RESULTS, code).strip().split("\n")[0]
            return f"optimistix: {msg}"
        return f"status {code}"


#: A fit stops when the Gauss--Newton step left at the accepted point is smaller than this many
#: standard errors of the parameters (see :func:`_stationary`).
STATIONARY_STEP = 1e-4


#: A rejected trial step below :data:`STATIONARY_STEP` standard errors ends a fit only where
#: the Gauss--Newton step left is within this many standard errors (a minimum on a kink of the
#: residuals: the one-sided steps there are a fraction of a standard error).
KINK_NEIGHBOURHOOD = 1.0


def _statistically_small(J, r, delta, bound=STATIONARY_STEP):
    """Whether the parameter step ``delta`` (p,) moves the predictions of a fit with residuals
    ``r`` (n,) and Jacobian ``J`` (n, p) by at most ``bound`` standard errors,
    ``|J delta|^2 / s^2 <= bound^2`` with ``s^2 = |r|^2 / (n - p)`` (never where ``n <= p`` or
    the loss is 0: no residual variance to measure it by)."""
    n, p = J.shape
    if n <= p:
        return jnp.asarray(False)
    s2 = jnp.sum(r * r) / (n - p)
    moved = jnp.sum((J @ delta) ** 2)
    return jnp.all(jnp.isfinite(J)) & jnp.all(jnp.isfinite(r)) & (s2 > 0) & (moved <= bound**2 * s2)


def _stationary(J, r, u, rtol, atol):
    """Whether the accepted point ``u`` (p,) with residuals ``r`` (n,) and Jacobian ``J`` (n, p)
    is converged by the Gauss--Newton step left there, ``delta = -J^+ r``:

    - statistically: ``delta`` is below :data:`STATIONARY_STEP` standard errors,
      ``delta^T J^T J delta / s^2 <= STATIONARY_STEP^2`` with ``s^2 = |r|^2 / (n - p)``, i.e. the
      predicted loss decrease ``|J delta|^2 / 2`` is at most ``STATIONARY_STEP^2 loss / (n - p)``
      (never where ``n <= p``: no residual variance; or where the loss is 0);
    - or numerically: every component of ``delta`` is below the x tolerance,
      ``|delta_i| < atol + rtol |u_i|`` (the test optimistix applies to an accepted step, here
      applied to the step still to go). On exact, noise-free data the first test cannot hold
      (the loss left is the forward model's round-off, which a step can still halve), and the
      damped steps after a converged point would only move it below this tolerance.
    """
    finite = jnp.all(jnp.isfinite(J)) & jnp.all(jnp.isfinite(r))
    delta = jnp.linalg.lstsq(J, r)[0]
    small = jnp.all(jnp.abs(delta) < atol + rtol * jnp.abs(u))
    return finite & (small | _statistically_small(J, r, delta))


#: Adam: the most halvings of a step whose trial point has a non-finite loss (a failed static
#: solve) before the start stops with a non-finite loss (a 2^-12 shorter step still failing).
ADAM_MAX_HALVINGS = 12


#: Recently used engines (compiled step and evaluation), so that fitting the same problem
#: again in a session -- a resume, a re-run with more steps, or ANOTHER SPECIMEN of the same
#: structure with its own data -- does not compile again. The key is
#: :meth:`FitProblem.structure_key` (fields, transforms, fixed fields, loss, scenario types and
#: pytree structures, a hash of the compiled-in scenario leaves; objects that are not arrays by
#: identity) and the solver options; the measured data are arguments, not part of the key. The
#: entry keeps its problem alive, so the ids in a key cannot be reused while cached. The
#: evaluation program (:meth:`Engine.make_evaluate`) is shared by the cached engines of one
#: structure and ``jac`` whatever their method and options (it depends on neither).
_ENGINE_CACHE: dict = {}
_ENGINE_CACHE_SIZE = 8


def cached_engine(problem: FitProblem, method: str, **options) -> Engine:
    structure = problem.structure_key()
    key = (structure, method, tuple(sorted(options.items())))
    engine = _ENGINE_CACHE.pop(key, None)
    if engine is None:
        engine = Engine(problem, method, **options)
        # The evaluation program depends on the problem's structure and ``jac`` only, not on the
        # method or its tolerances / learning rate: an engine of the same structure and ``jac``
        # already cached lends its (possibly compiled) program, so a refit with another method
        # does not compile the forward model's evaluation again.
        for (other_structure, _, other_options), other in _ENGINE_CACHE.items():
            if other_structure == structure and dict(other_options).get("jac") == options.get("jac"):
                engine._evaluate = other.make_evaluate()
                break
    _ENGINE_CACHE[key] = engine  # most recent last
    while len(_ENGINE_CACHE) > _ENGINE_CACHE_SIZE:
        _ENGINE_CACHE.pop(next(iter(_ENGINE_CACHE)))
    return engine


# ============================================================================ step loop
class LoopState:
    """The state of a fit between steps, held by the caller so that an interruption still sees
    the last completed step (a checkpoint is written from it).

    Attributes:
        U: unconstrained parameters of every start (``(S, p)``, or ``(B, S, p)`` batched).
        dyn: the optimiser's batched dynamic state.
        done: which starts have stopped (the shape of ``U`` without its last axis).
        status: failure code of every start (0: running or converged), NumPy int32.
        history: loss rows, one per step, row 0 the initial losses.
        step: steps taken (counted over resumes).
    """

    def __init__(self, U, dyn, done, status, history=(), step: int = 0):
        self.U, self.dyn, self.done = U, dyn, done
        self.status = np.asarray(status, dtype=np.int32)
        self.history = list(history)
        self.step = int(step)


def run_steps(step_fn, state: LoopState, data, *, max_steps: int, to_host: Callable = np.asarray,
              on_step: Callable[[LoopState, np.ndarray], bool | None] | None = None) -> bool:
    """THE step loop of every fit: call the compiled ``step_fn(U, dyn, done, data)`` until every
    start has stopped or ``state.step`` reaches ``max_steps``, updating ``state`` in place.

    After each step the new failure codes are merged into ``state.status``, the losses appended
    to ``state.history`` (the first step's losses twice when the history is empty: an optimistix
    method evaluates and accepts the starts in its first step, so those are the initial losses),
    and ``on_step(state, losses)`` is called; it returning ``True`` stops the loop. ``to_host``
    brings a (possibly sharded) device array to one NumPy array.

    Returns:
        True when ``on_step`` stopped the loop, else False.
    """
    while state.step < max_steps and not bool(np.all(to_host(state.done))):
        state.U, state.dyn, state.done, new_status, losses = step_fn(state.U, state.dyn, state.done, data)
        new_status = to_host(new_status)
        state.status = np.where(new_status != 0, new_status, state.status).astype(np.int32)
        state.step += 1
        losses = to_host(losses)
        if not state.history:
            state.history.append(losses)
        state.history.append(losses)
        if on_step is not None and on_step(state, losses) is True:
            return True
    return False


def final_evaluation(final_fn, evaluate_fn, U, dyn, data, *, rows=slice(None), to_host: Callable = np.asarray):
    """``(values, loss, J, predictions)`` of every start at the end of a fit: from the solver
    state (``final_fn``, optimistix methods: no second compilation of the forward model) when
    every start in ``rows`` holds a usable evaluation there, else a fresh ``evaluate_fn``."""
    if final_fn is not None:
        *result, ok = final_fn(U, dyn, data)
        if bool(np.all(to_host(ok)[rows])):
            return tuple(result)
    return evaluate_fn(U, data)


def progress_bar(enabled: bool, total: int):
    """A rich progress bar on stderr for ``total`` steps, or None when not ``enabled``."""
    if not enabled:
        return None
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=False,
    )
