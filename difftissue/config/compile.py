"""The compile policy of a fit: :class:`SeparatelyCompiled` compiles a simulated scenario's
``material -> prediction`` and its derivative once, on their own, and the fit calls them
through :func:`jax.pure_callback`; equal scenarios share those compiled programs
(:func:`compile_cache_info`, :func:`clear_compile_cache`).

A program is keyed by what is compiled into it: the scenario's type and pytree structure (its
static configuration: model, solver options, protocol settings), a hash of every array leaf
by content (mesh, lattice, boundary data, the protocol's abscissa, ...) with its shape and
dtype, objects that are not arrays by identity, the program's kind and argument shapes, and
the JAX settings it is compiled under (64-bit mode, backend, default device). The measured
data (``observed``, ``sigma``) are ARGUMENTS of the programs, not constants, so two
experiments of the same specimen and protocol with different measurements share one program.
Two scenarios that differ in anything compiled in get two programs.
"""

from __future__ import annotations

import collections
import hashlib
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, runtime_error_message
from ..fit.problem import data_leaf_indices, hash_scenario_leaves
from ..materials import Material
from ..scenarios import argument_setup, compiles_with_arguments, traced_arguments
from ..xla_options import LOW_OPTIMISATION, compiler_options

__all__ = ["SeparatelyCompiled", "compile_cache_info", "clear_compile_cache", "COMPILE_CACHE_SIZE", "HOST_SOLVES"]

#: Most compiled programs kept for sharing between equal scenarios (least recently used
#: dropped first). A dropped program stays with the :class:`SeparatelyCompiled` objects that
#: use it; only a new, equal scenario compiles it again.
COMPILE_CACHE_SIZE = 16

#: ``{key: compiled executable}``, most recently used last (see :func:`_program`).
_PROGRAMS: collections.OrderedDict = collections.OrderedDict()

#: A static scenario whose model has at most this many nodes has its programs compiled with
#: the ``"small_static"`` options of :mod:`difftissue.xla_options` (adding
#: :data:`SMALL_MODEL_COMPILER_OPTIONS`). Such a program runs in milliseconds and a fit calls it
#: tens of times, while compiling it takes seconds (the one-cube compression protocol with its
#: Newton solves and Jacobian tangents: 4.0 s CPU at XLA's default optimisation, 2.8 s at level
#: 0, which runs it in about twice the time, 3 -> 6 ms).
SMALL_MODEL_NODES = 64

#: XLA options added for the programs of small scenarios
#: (:data:`difftissue.xla_options.LOW_OPTIMISATION`). Results agree with the default options
#: to ~1e-12 relative.
SMALL_MODEL_COMPILER_OPTIONS = LOW_OPTIMISATION
_STATS = {"hits": 0, "compilations": 0, "unshared": 0}


def compile_cache_info() -> dict:
    """Counters of the programs :class:`SeparatelyCompiled` compiled or shared in this process:
    ``hits`` (a program taken from an equal scenario), ``compilations`` (programs compiled,
    shared or not), ``unshared`` (of those, the ones without a key: a scenario with static
    fields that cannot be hashed), ``size`` (programs kept now) and ``max_size``
    (:data:`COMPILE_CACHE_SIZE`)."""
    return {**_STATS, "size": len(_PROGRAMS), "max_size": COMPILE_CACHE_SIZE}


def clear_compile_cache() -> None:
    """Forget the shared programs and zero the counters of :func:`compile_cache_info` (the
    :class:`SeparatelyCompiled` objects keep the programs they already use)."""
    _PROGRAMS.clear()
    for k in _STATS:
        _STATS[k] = 0


def scenario_structure(scenario, *, arrays: bool = False) -> tuple[tuple | None, list, Any, tuple[int, ...]]:
    """``(key, leaves, treedef, data)`` of a scenario as a pytree: ``leaves`` and ``treedef``
    from :func:`jax.tree_util.tree_flatten`; ``data`` the indices of the leaves that are
    arguments of the compiled programs: its measured data
    (:data:`~difftissue.fit.problem.DATA_ATTRIBUTES`), or with ``arrays`` every array leaf
    (mesh, boundary data, protocol, measured data, ...); ``key`` what the traced program
    depends on besides those (see the module docstring; the leaves are hashed by
    :func:`difftissue.fit.problem.hash_scenario_leaves`, the formula of the fit engine's
    :meth:`~difftissue.fit.FitProblem.structure_key`: the arguments by shape and dtype), or None
    when the static configuration cannot be hashed (then the programs are not shared). A
    scenario that is not a pytree is one leaf, keyed by identity."""
    leaves, treedef = jax.tree_util.tree_flatten(scenario)
    if arrays:
        data = tuple(i for i, leaf in enumerate(leaves) if eqx.is_array(leaf))
    else:
        data = data_leaf_indices(scenario, leaves)
    try:
        hash(treedef)
    except TypeError:  # a static field that cannot be hashed
        return None, leaves, treedef, data
    h = hashlib.sha256()
    # objects by identity: the cached program keeps them alive; the tag tells the two kinds apart
    objects = hash_scenario_leaves(h, leaves, data, data_tag="arg" if arrays else "data")
    return (type(scenario), treedef, h.hexdigest(), tuple(objects)), leaves, treedef, data


def _settings() -> tuple:
    """The JAX settings a program is compiled under (part of its key): float64 or not, and the
    device it runs on. The device is resolved (``jax_default_device`` None means the first
    device of the default backend; JAX sets it to the CPU device inside a host callback, where
    a fit evaluates its scenarios), so that a program compiled before a fit is the fit's own
    program when both resolve to one device."""
    device = jax.config.jax_default_device
    if device is None:
        device = jax.devices()[0]
    elif isinstance(device, str):
        device = jax.devices(device)[0]
    return (bool(jax.config.jax_enable_x64), device.platform, device.id)


def _program(jitted, specs, key, options=None):
    """``jitted`` compiled ahead of time for the argument ``specs`` with the XLA ``options``
    (None: the defaults); shared through :data:`_PROGRAMS` under ``key`` (None: not shared)."""
    if key is None:
        _STATS["compilations"] += 1
        _STATS["unshared"] += 1
        return jitted.lower(*specs).compile(compiler_options=options)
    spec_leaves, spec_tree = jax.tree_util.tree_flatten(specs)
    key = (key, spec_tree, tuple((s.shape, str(s.dtype)) for s in spec_leaves), _settings(), tuple(sorted((options or {}).items())))
    program = _PROGRAMS.pop(key, None)
    if program is None:
        _STATS["compilations"] += 1
        program = jitted.lower(*specs).compile(compiler_options=options)
    else:
        _STATS["hits"] += 1
    _PROGRAMS[key] = program  # most recent last
    while len(_PROGRAMS) > COMPILE_CACHE_SIZE:
        _PROGRAMS.popitem(last=False)
    return program


def _compiled_per_shape(fn, key=None, data=(), options=None):
    """``fn(data, *args)`` compiled ahead of time for the shapes of the float64 ``args`` it is
    called with, once per shape; called as ``call(*args)``. ``data``: a pytree of arrays passed
    as the program's first argument, or a function returning it (called once, at the first
    call: e.g. a solver setup built only when needed). ``key``: what the program depends on
    besides its arguments (:func:`scenario_structure` and the program's kind), so that an
    equal scenario reuses the program; None: compiled for this function alone. ``options``:
    XLA compiler options (None: the defaults).

    A ``jax.jit`` function called both inside a callback (a fit's compiled step calls the
    scenario through :func:`jax.pure_callback`) and outside it is compiled twice: JAX keys its
    cache on that context. The ahead-of-time executable is one compilation for both."""
    jitted = jax.jit(fn)
    compiled: dict[tuple, Any] = {}
    state: dict[str, Any] = {}

    def arguments():
        if "data" not in state:
            # jax.device_put, not jnp.asarray (a small compiled program per new NumPy shape)
            d = jax.tree_util.tree_map(jax.device_put, data() if callable(data) else data)
            state["data"] = d
            state["specs"] = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), d)
        return state["data"], state["specs"]

    def call(*args):
        shapes = tuple(np.shape(a) for a in args)
        d, data_specs = arguments()
        if shapes not in compiled:
            specs = (data_specs, *(jax.ShapeDtypeStruct(sh, jnp.float64) for sh in shapes))
            compiled[shapes] = _program(jitted, specs, key, options)
        return compiled[shapes](d, *args)

    return call


def _compiler_options(scenario) -> dict | None:
    """The XLA options of a scenario's programs (:func:`difftissue.xla_options.compiler_options`,
    on a CPU only): for a static scenario (``scenario.xla_program == "static"``: the simulated
    indentations, compression, FEM field, incision) the ``"static"`` set, ``"small_static"``
    when its model (``scenario.model``) has at most :data:`SMALL_MODEL_NODES` nodes; None
    (XLA's defaults) for other scenarios."""
    if getattr(scenario, "xla_program", None) != "static":
        return None
    n = getattr(getattr(scenario, "model", None), "n_nodes", None)
    small = isinstance(n, (int, np.integer)) and n <= SMALL_MODEL_NODES
    return compiler_options("small_static" if small else "static")


#: Forward-mode scenarios that can solve on the host (``scenario.solves_on_host``: a small
#: compression specimen, :meth:`difftissue.scenarios.Compression.solve_on_host`) do so instead
#: of compiling their protocol: the same numbers to round-off, without the seconds of tracing
#: and compiling it (the one-cube Ecoflex fit). False: always the compiled protocol.
HOST_SOLVES = True

#: Scenarios whose protocol can take its arrays as arguments
#: (:func:`difftissue.scenarios.compiles_with_arguments`) are compiled with every array and
#: the solver setup as arguments (:attr:`SeparatelyCompiled.arrays_as_arguments`). False:
#: only the measured data are arguments, the mesh and the solver setup constants.
ARRAYS_AS_ARGUMENTS = True

_MATERIAL_LEAVES = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")


class SeparatelyCompiled:
    """A scenario whose prediction and derivative are compiled once each, on their own.

    :func:`difftissue.fit.fit` traces the scenario's ``predict`` into several jitted functions
    (the batched loss, the optimiser step with its Jacobian, the final Jacobian, the final
    prediction). For a simulated scenario (a scan of static solves with implicit gradients)
    each of these XLA compilations takes seconds to tens of seconds, which dominates a small
    fit. This wrapper compiles ``material -> prediction`` and its Jacobian-vector product
    (``mode="forward"``: Levenberg--Marquardt / Gauss--Newton with forward Jacobians) or
    vector-Jacobian product (``mode="reverse"``: Adam, L-BFGS, ``jac = "bwd"``) once, and the
    fit's compiled code calls them through :func:`jax.pure_callback` (batched calls run one
    after the other). The numbers are the same; only the compilation is shared. The material
    must have scalar fields.

    In forward mode one call gives the prediction and all the tangents of a Jacobian (one
    model solve per ``jax.jacfwd``), so it supports ``jax.jvp`` and ``jax.jacfwd`` (what the
    fit's forward Jacobians use) but not ``jax.linearize`` or reverse mode: use
    ``mode="reverse"`` for those.

    A scenario that solves on the host (:data:`HOST_SOLVES`, ``scenario.solves_on_host``)
    compiles no protocol: forward mode calls its ``solve_on_host`` (prediction and tangents) instead.

    An evaluation at an invalid material (E <= 0, nu outside (-1, 0.5), non-finite values) or
    one whose static solve fails returns NaN instead of raising, so that Levenberg--Marquardt
    rejects that trial point (shrinking its trust region) rather than the fit aborting; the
    failures' messages are kept in :attr:`failures`.
    """

    def __init__(self, scenario, *, mode: str = "forward", n_tangents: int = 1, pre_stretch_y: bool = False, fields=None):
        """
        Args:
            scenario: a scenario with ``predict(material)`` and the data attributes.
            mode: ``"forward"`` or ``"reverse"`` (see the class docstring).
            n_tangents: forward mode: the number of tangents a Jacobian call pushes through
                (the number of fitted parameters); primal-only calls run the same program with
                that many zero tangents, so one program serves both.
            pre_stretch_y: compile for materials with an anisotropic pre-stretch
                (``Material.pre_stretch_y``, then a sixth leaf; a material without one passes
                ``pre_stretch`` for it). Without it a material with a ``pre_stretch_y`` is refused.
            fields: the material fields the Jacobians are taken in (the fitted ones), in
                place of ``n_tangents`` (which is then ``len(fields)``). With a scenario whose
                predictions are proportional to Young's modulus
                (``scenario.prediction_scales_with_youngs_modulus``), the tangent along
                ``youngs_modulus`` is the prediction over ``E`` (no model solve) and the
                program is compiled for the other tangents only when ``fields`` names
                ``youngs_modulus`` (with ``n_tangents`` alone, for ``n_tangents`` tangents);
                where ``fields`` is ``youngs_modulus`` alone, the one program is the
                prediction's (no tangent, not even a zero one, is solved).
                Any tangent is answered correctly either way; a call with more tangents to
                solve than the program was compiled for compiles another.
        """
        if mode not in ("forward", "reverse"):
            raise ConfigError(f"mode must be 'forward' or 'reverse', got {mode!r}")
        if fields is not None:
            fields = tuple(fields)
            unknown = [f for f in fields if f not in _MATERIAL_LEAVES + ("pre_stretch_y",)]
            if unknown:
                raise ConfigError(f"fields: {unknown} are not material fields (choose from {list(_MATERIAL_LEAVES) + ['pre_stretch_y']})")
            n_tangents = len(fields)
        self.inner = scenario
        self.mode = mode
        #: messages of the model evaluations that failed (returned NaN) during fits
        self.failures: list[str] = []
        #: model solves run so far: ``"value"`` (prediction only) and ``"value_and_tangents"``
        #: (prediction and the tangents of a Jacobian, forward mode)
        self.calls = {"value": 0, "value_and_tangents": 0}
        for k in ("name", "observed", "sigma", "abscissa", "x_label", "y_label"):
            setattr(self, k, getattr(scenario, k))
        #: relative precision [-] of the inner scenario's predictions (0: none stated)
        self.prediction_rtol = float(getattr(scenario, "prediction_rtol", 0.0))
        n = int(np.asarray(scenario.observed).size)
        self._leaves = _MATERIAL_LEAVES + (("pre_stretch_y",) if pre_stretch_y else ())
        n_leaves = len(self._leaves)

        options = _compiler_options(scenario)
        #: whether the compiled programs take every array of the scenario (mesh, boundary
        #: data, protocol, measured data) and the solver setup of its static solves as
        #: arguments (:func:`difftissue.scenarios.compiles_with_arguments`); otherwise only the
        #: measured data, the rest compiled in as constants
        host = mode == "forward" and HOST_SOLVES and bool(getattr(scenario, "solves_on_host", False))  # no program compiled
        self.arrays_as_arguments = bool(ARRAYS_AS_ARGUMENTS and not host and compiles_with_arguments(scenario))
        if self.arrays_as_arguments:
            # Every array is an argument, keyed by shape and dtype: the program holds no
            # mesh-sized constant, and scenarios of one structure with other mesh values,
            # depths or data share it. The setup (block layout, multigrid hierarchy) is built
            # from the concrete scenario at the first compilation, for the material structure
            # of the program (the values of ``probe`` are not used).
            key, leaves, treedef, data_leaves = scenario_structure(scenario, arrays=True)
            probe = Material(*(jnp.asarray(x, dtype=jnp.float64) for x in (1.0, 0.25, 0.0, 1000.0, 1.0, 1.0)[:n_leaves]))

            built: list = []

            def data():  # once for all the programs of this scenario (value, tangents, VJP)
                if not built:
                    arrays = tuple(jnp.asarray(leaves[i]) for i in data_leaves)
                    built.append((arrays, argument_setup(scenario, probe)))
                return built[0]
        else:
            # The measured data are arguments of the compiled programs (``data``), everything
            # else of the scenario is compiled in and keys the programs shared with equal scenarios.
            key, leaves, treedef, data_leaves = scenario_structure(scenario)
            data = (tuple(leaves[i] for i in data_leaves), None)

        def f(data, v):
            arrays, setup = data
            if data_leaves:
                rebuilt = list(leaves)
                for i, d in zip(data_leaves, arrays):
                    rebuilt[i] = d
                sc = jax.tree_util.tree_unflatten(treedef, rebuilt)
            else:
                sc = scenario
            material = Material(*(v[i] for i in range(n_leaves)))
            if setup is None:
                return sc.predict(material)
            with traced_arguments(sc, setup, material):
                return sc.predict(material)

        def program_key(kind):
            return None if key is None else (kind, key)

        out = jax.ShapeDtypeStruct((n,), jnp.float64)
        vec = jax.ShapeDtypeStruct((n_leaves,), jnp.float64)

        def valid(v) -> bool:
            v = np.asarray(v, dtype=float)
            return bool(np.all(np.isfinite(v)) and v[0] > 0 and -1.0 < v[1] < 0.5 and np.all(v[3:] > 0))

        def guarded(fn, v, *args, shape=(n,)):
            # An invalid material (optimistix evaluates the Jacobian of a discarded branch at an
            # all-zero placeholder) or a failed solve gives NaN instead of an exception, so the
            # optimiser rejects that trial point instead of the whole fit aborting.
            if not valid(v):
                return None if shape is None else np.full(shape, np.nan)
            # host solves take NumPy arrays (nothing dispatched to JAX), compiled programs JAX arrays
            asarray = np.asarray if self.solves_on_host else jnp.asarray
            try:
                return fn(asarray(v, dtype=np.float64), *(asarray(a, dtype=np.float64) for a in args))
            except jax.errors.JAXTypeError:
                raise  # a tracing error (a value read on the host while traced): a defect, not a failed solve
            except Exception as e:  # a static solve that failed to converge, an inverted element, ...
                # the message itself (an equinox runtime error carries the callback's
                # traceback and a closing paragraph on filter_jit)
                self.failures.append(runtime_error_message(e))
                return None if shape is None else np.full(shape, np.nan)

        if mode == "forward":
            # ONE compiled program gives the prediction and its derivatives along a batch of
            # tangents: the model is solved once, the tangents (one implicit linear solve each
            # per load step) are batched. A primal-only call runs it with zero tangents, so
            # nothing is compiled twice (except E alone in closed form: see ``primal_only``).
            # Compiled ahead of time per tangent count (_compiled_per_shape).
            #: whether the predictions and their tangents are solved on the host (NumPy, no
            #: compiled protocol): :meth:`predict_and_tangents_on_host` is then available, and
            #: a Levenberg--Marquardt fit runs its steps on the host too (:mod:`difftissue.fit.host`)
            self.solves_on_host = bool(HOST_SOLVES and getattr(scenario, "solves_on_host", False))
            if self.solves_on_host:
                # A small specimen (solve_on_host: the same numbers to round-off): the protocol's
                # Newton iterations in NumPy, only the model's derivatives compiled.
                leaf_names = self._leaves

                def both(v, T):
                    v, T = np.asarray(v, dtype=float), np.asarray(T, dtype=float)
                    return scenario.solve_on_host(Material(*(float(x) for x in v)), {k: T[:, i] for i, k in enumerate(leaf_names)})
            else:
                both = _compiled_per_shape(jax.vmap(lambda d, v, t: jax.jvp(lambda vv: f(d, vv), (v,), (t,)), in_axes=(None, None, 0), out_axes=(None, 0)),
                                          program_key("value_and_tangents"), data, options)
            # A prediction proportional to Young's modulus (leaf 0) has the E tangent
            # t_E y / E in closed form: the equilibria do not depend on E (displacement
            # control, an energy linear in E), so the implicit solve of that tangent at every
            # load step would only return d u / d E = 0 up to the solver's tolerance. The
            # program is then compiled for the other tangents only (the vmapped tangent solves
            # cost about one solve per tangent, batched or not).
            #: whether Jacobian calls take the Young's modulus tangent in closed form
            self.scales_with_youngs_modulus = bool(getattr(scenario, "prediction_scales_with_youngs_modulus", False))
            n_solved = int(n_tangents)
            if self.scales_with_youngs_modulus and fields is not None and "youngs_modulus" in fields:
                n_solved -= 1
            n_zero = max(n_solved, 1)

            # Where every tangent a fit asks for is the closed-form E one (E the only fitted
            # field), the prediction needs no tangent solve at all: a primal-only program,
            # compiled only then (a zero tangent would still cost its linear solves: with the
            # sparse solver a factorisation per load step, with the condensation dK Z^T).
            primal_only = n_solved == 0 and self.scales_with_youngs_modulus and not self.solves_on_host
            value = _compiled_per_shape(f, program_key("value"), data, options) if primal_only else None

            def solve_tangents(v, T):
                y, JT = both(v, T)
                return np.asarray(y, dtype=np.float64), np.asarray(JT, dtype=np.float64)

            def run(v, T):
                if not self.scales_with_youngs_modulus:
                    return solve_tangents(v, T)
                T = np.array(T, dtype=np.float64)
                along_E = T[:, 0] / float(v[0])  # v[0] > 0 (guarded)
                T[:, 0] = 0.0
                rows = np.flatnonzero(np.any(T != 0.0, axis=1))
                if rows.size == 0 and value is not None:
                    y = np.asarray(value(v), dtype=np.float64)
                    return y, along_E[:, None] * y[None, :]
                solved = np.zeros((max(n_zero, rows.size), n_leaves))
                solved[: rows.size] = T[rows]
                y, JS = solve_tangents(v, solved)
                JT = along_E[:, None] * y[None, :]
                JT[rows] += JS[: rows.size]
                return y, JT

            def host_f(v):
                self.calls["value"] += 1
                return guarded(lambda vv: run(vv, np.zeros((n_zero, n_leaves)))[0], v)

            def host_tangents(v, T):
                # One model solve, all the tangents of a Jacobian.
                self.calls["value_and_tangents"] += 1
                v, T = np.asarray(v, dtype=float), np.asarray(T, dtype=float)
                res = guarded(lambda vv, tt: run(vv, tt), v, T, shape=None)
                return res if res is not None else (np.full(n, np.nan), np.full((T.shape[0], n), np.nan))

            def host_rows(V, T):
                # Several materials (the starts of a multi-start fit): one call per material.
                V, T = np.asarray(V, dtype=float), np.asarray(T, dtype=float)
                ys, jts = np.empty((V.shape[0], n)), np.empty((V.shape[0], n))
                groups: dict[bytes, list[int]] = {}
                for i, row in enumerate(V):
                    groups.setdefault(row.tobytes(), []).append(i)
                for rows in groups.values():
                    y, jt = host_tangents(V[rows[0]], T[rows])
                    ys[rows], jts[rows] = y, jt
                return ys, jts

            @jax.custom_batching.custom_vmap
            def value_and_tangent(v, t):
                y, jt = jax.pure_callback(host_tangents, (out, jax.ShapeDtypeStruct((1, n), jnp.float64)), v, t[None], vmap_method="sequential")
                return y, jt[0]

            @value_and_tangent.def_vmap
            def _value_and_tangents(axis_size, in_batched, v, t):
                v_batched, t_batched = in_batched
                T = t if t_batched else jnp.broadcast_to(t, (axis_size, n_leaves))
                if not v_batched:  # the Jacobian's tangents at one material: the prediction is not batched
                    y, JT = jax.pure_callback(host_tangents, (out, jax.ShapeDtypeStruct((axis_size, n), jnp.float64)), v, T, vmap_method="sequential")
                    return (y, JT), (False, True)
                rows = jax.ShapeDtypeStruct((axis_size, n), jnp.float64)
                Y, JT = jax.pure_callback(host_rows, (rows, rows), v, T, vmap_method="sequential")
                return (Y, JT), (True, True)

            self._host_f = host_f
            self._host_tangents = host_tangents

            def call_f(v):
                return jax.pure_callback(host_f, out, v, vmap_method="sequential")

            @jax.custom_jvp
            def call(v):
                return call_f(v)

            @call.defjvp
            def _call_jvp(primals, tangents):
                # The prediction comes with its tangents from the same call (one model solve per
                # Jacobian: jax.jacfwd's tangents arrive batched, see _value_and_tangents).
                (v,), (t,) = primals, tangents
                return value_and_tangent(v, t)

        else:
            self.scales_with_youngs_modulus = False
            self.solves_on_host = False
            fwd = _compiled_per_shape(f, program_key("value"), data, options)
            vjp = _compiled_per_shape(lambda d, v, ct: jax.vjp(lambda vv: f(d, vv), v)[1](ct)[0], program_key("vector_jacobian"), data, options)

            def host_f(v):
                return np.asarray(guarded(fwd, v), dtype=np.float64)

            self._host_f = host_f

            def call_f(v):
                return jax.pure_callback(host_f, out, v, vmap_method="sequential")

            def host_vjp(v, ct):
                out = np.asarray(guarded(vjp, v, ct), dtype=np.float64)
                return out if out.shape == (n_leaves,) else np.full(n_leaves, np.nan)

            @jax.custom_vjp
            def call(v):
                return call_f(v)

            def _fwd(v):
                return call_f(v), v

            def _bwd(v, ct):
                return (jax.pure_callback(host_vjp, vec, v, ct, vmap_method="sequential"),)

            call.defvjp(_fwd, _bwd)
        self._call = call

    def evaluate(self, material) -> np.ndarray:
        """The prediction at ``material`` on the host, through the same compiled function the
        fit calls (no extra compilation); NaN where the evaluation fails."""
        return self._host_f(np.array([float(v) for v in self._values(material)]))

    def predict_and_tangents_on_host(self, material, tangents: dict) -> tuple[np.ndarray, np.ndarray]:
        """The prediction at ``material`` and its derivatives along ``K`` material tangents,
        solved on the host by the same function the fit's compiled code calls (one model solve;
        only where :attr:`solves_on_host`). NaN where the evaluation fails.

        Args:
            material: the material (scalar fields).
            tangents: ``{field: (K,)}``, the tangent of each material field (fields left out:
                zero).

        Returns:
            ``(prediction (n,), tangents (K, n))`` (NumPy, float64).
        """
        if not self.solves_on_host:
            raise ConfigError(f"{self.name}: this scenario does not solve on the host (solves_on_host is False)")
        unknown = [f for f in tangents if f not in self._leaves and f != "pre_stretch_y"]
        if unknown:
            raise ConfigError(f"{self.name}: tangents of unknown material fields {unknown} (choose from {list(self._leaves)})")
        K = len(next(iter(tangents.values()))) if tangents else 0
        T = np.zeros((K, len(self._leaves)))
        for i, k in enumerate(self._leaves):
            # the leaf's value is _values' (pre_stretch_y without one: pre_stretch), so is its tangent
            source = "pre_stretch" if (k == "pre_stretch_y" and material.pre_stretch_y is None) else k
            if source in tangents:
                T[:, i] = np.asarray(tangents[source], dtype=float)
        v = np.array([float(x) for x in self._values(material)])
        return self._host_tangents(v, T)

    def _values(self, material):
        """The material's leaves in the compiled order (``pre_stretch_y``: see ``__init__``)."""
        if material.pre_stretch_y is not None and "pre_stretch_y" not in self._leaves:
            raise ConfigError(f"{self.name}: the material has a pre_stretch_y (anisotropic pre-stretch) but this scenario was compiled "
                              "without one; build SeparatelyCompiled(..., pre_stretch_y=True)")
        return [material.pre_stretch if (k == "pre_stretch_y" and material.pre_stretch_y is None) else getattr(material, k) for k in self._leaves]

    def predict(self, material):
        v = jnp.stack([jnp.asarray(x, dtype=jnp.float64).reshape(()) for x in self._values(material)])
        return self._call(v)
