"""Batched and sharded fits: many specimens of one structure in ONE compiled program.

:func:`fit_batch` fits the same material parameters to each of ``B`` specimens -- the same
scenarios (same mesh, model, indenter, protocol length) with their own measured data and
their own initial material -- as one ``jax.vmap`` over every start of every specimen of the
single-start step that :func:`difftissue.fit.fit` runs. The optimiser (the same
Levenberg--Marquardt / Gauss--Newton of optimistix, Adam or L-BFGS of optax, the same losses,
tolerances and stopping rule as :func:`~difftissue.fit.fit`) steps every specimen at once; a
specimen whose starts have all stopped is frozen while the others go on. The result holds one
:class:`~difftissue.fit.FitResult` per specimen (parameters, standard errors, covariance,
convergence), equal to what a serial loop of :func:`~difftissue.fit.fit` calls returns.

With ``devices=`` the specimen axis is split across devices (a ``jax.sharding.Mesh`` with one
axis ``"specimen"``): each device runs the SAME jitted batched step on its own share of the
specimens, dispatched to all devices before any result is waited for, with no communication
between devices; a batch that does not divide evenly is padded with copies of the first
specimen that are frozen from the start and dropped from the result.

What is batched: the measured data (``observed`` and ``sigma`` of every scenario), the
initial parameters of every start, and any other floating-point leaf of the scenarios that
differs between the specimens (e.g. a depth protocol). What must be equal: the scenario
types, names and static options, the number of points, every integer or boolean array
(mesh connectivity, node sets: the topology) and the non-fitted material fields. Anything
else raises :class:`~difftissue.errors.FitError` naming the specimen and the leaf.

Units: as in :mod:`difftissue.fit` (SI values and standard errors, dimensionless losses).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DifftissueError, FitError
from ..materials import Material, MaterialParameterization
from ..xla_options import LOW_OPTIMISATION, OLDER_FUSION, PROGRAMS
from .driver import build_result, initial_starts
from .engine import METHODS, LoopState, cached_engine, final_evaluation, progress_bar, run_steps, strong, tolerances
from .problem import FitProblem
from .result import FitResult

__all__ = ["BatchFitResult", "fit_batch", "specimen_mesh"]

#: Name of the mesh axis the specimens are split along.
AXIS = "specimen"

#: ``fit_batch(spectral=None)`` switches scenarios that offer it (``spectral_variant``: the
#: condensed ``fem_linear`` indentation of one region, up to 3,000 unknowns) to the spectral
#: solver from this many specimens on: one host eigendecomposition of the shared mesh (about
#: 20 dense factorisations' time) replaces a factorisation per specimen, step and tangent.
SPECTRAL_MIN_SPECIMENS = 2

#: XLA options the batched programs are compiled with on a CPU (``jax.jit``'s public
#: ``compiler_options``, for these programs only: nothing global, no ``XLA_FLAGS`` edit):
#: :data:`difftissue.xla_options.SERIAL_SCHEDULER`, the ``"batch"`` program kind. XLA's
#: concurrency-optimised CPU scheduler (the default of jaxlib 0.10) deadlocked batched
#: Levenberg--Marquardt steps of simulated compressions in earlier versions
#: (docs/dev/scale-investigation.md); with it off they ran. Passed as they are (an option this
#: jaxlib does not know fails the compilation).
CPU_COMPILER_OPTIONS = PROGRAMS["batch"]

#: XLA options added on a CPU for batches whose scenarios use the spectral solver
#: (:data:`difftissue.xla_options.LOW_OPTIMISATION` and
#: :data:`~difftissue.xla_options.OLDER_FUSION`; with :data:`CPU_COMPILER_OPTIONS` the
#: ``"batch_spectral"`` program kind): a batched step of such a batch runs in milliseconds
#: (0.07 s CPU for 16 specimens of 2,187 unknowns) while compiling it takes seconds; XLA's
#: backend optimisation level 0 compiles it in 4.0 s CPU instead of 6.3 s and runs it in
#: 0.087 s instead of 0.074 s (break-even after about 180 steps), and XLA's older element-wise
#: fusion then compiles it in about 1.6 s instead of 3.6 s CPU at the same run time,
#: bit-identical. Results agree with the default level to round-off (1e-12 relative in the
#: fits of ``benchmarks/batch.py``). Batches that factorise per specimen keep XLA's default
#: level and fusion.
SPECTRAL_COMPILER_OPTIONS = {**LOW_OPTIMISATION, **OLDER_FUSION}


# ============================================================================ result
@dataclasses.dataclass(frozen=True)
class BatchFitResult:
    """Outcome of :func:`fit_batch` (values SI, see :data:`difftissue.fit.UNITS`).

    Attributes:
        fits: one :class:`~difftissue.fit.FitResult` per specimen, in the order given.
        labels: the specimens' labels.
        fields: names of the fitted fields (the column order of ``values``, ``standard_errors``).
        values: ``(B, p)`` fitted values.
        standard_errors: ``(B, p)`` standard errors (``inf`` where the data do not determine it).
        loss: ``(B,)`` final loss of each specimen's best start [-].
        converged: ``(B,)`` whether each specimen's best start met the tolerances.
        steps: ``(B,)`` optimiser steps each specimen took (until all its starts stopped).
        batch_steps: steps of the batched loop (the largest of ``steps``).
        compilations: traces of the batched step (1 on a fresh structure, 0 when a batch of the
            same structure was compiled before in this session).
        devices: the devices the batch ran on (one entry when not sharded).
        padding: copies of the first specimen added to fill the devices evenly (not in ``fits``).
    """

    fits: tuple[FitResult, ...]
    labels: tuple[str, ...]
    fields: tuple[str, ...]
    values: np.ndarray
    standard_errors: np.ndarray
    loss: np.ndarray
    converged: np.ndarray
    steps: np.ndarray
    batch_steps: int
    compilations: int
    devices: tuple[str, ...]
    padding: int

    def __len__(self) -> int:
        return len(self.fits)

    def __getitem__(self, i) -> FitResult:
        return self.fits[i]

    def value(self, field: str) -> np.ndarray:
        """``(B,)`` fitted values of ``field`` (SI)."""
        return self.values[:, self.fields.index(field)]

    def table(self) -> str:
        """A Markdown table: one row per specimen with each value ± standard error, the loss,
        the steps and the convergence flag."""
        head = "| specimen | " + " | ".join(self.fields) + " | loss | steps | converged |"
        rows = [head, "|---" * (len(self.fields) + 4) + "|"]
        for b, label in enumerate(self.labels):
            cells = [f"{v:.6g} ± {se:.3g}" for v, se in zip(self.values[b], self.standard_errors[b])]
            rows.append(f"| {label} | " + " | ".join(cells) + f" | {self.loss[b]:.6g} | {int(self.steps[b])} | {'yes' if self.converged[b] else 'no'} |")
        return "\n".join(rows)


# ============================================================================ helpers
def _as_specimen(sp) -> tuple:
    if isinstance(sp, (str, bytes)) or not isinstance(sp, Sequence):
        return (sp,)
    return tuple(sp)


def _same(a, b) -> bool:
    if a is b:
        return True
    if eqx.is_array(a) or eqx.is_array(b) or isinstance(a, np.generic):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return False
        return bool(np.array_equal(a, b, equal_nan=np.issubdtype(a.dtype, np.inexact)))
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - objects without a usable ==: different
        return False


def _static_differences(a, b) -> list[str]:
    """Names of the static (compiled-in) fields of two equinox-Module scenarios that differ."""
    if type(a) is not type(b):
        return [f"type ({type(a).__name__} vs {type(b).__name__})"]
    out = []
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.metadata.get("static", False):
                try:
                    same = getattr(a, f.name) == getattr(b, f.name)
                    same = bool(same) if not isinstance(same, np.ndarray) else bool(np.all(same))
                except Exception:  # noqa: BLE001
                    same = False
                if not same:
                    out.append(f.name)
    return out


def specimen_mesh(devices=None) -> jax.sharding.Mesh:
    """A one-axis :class:`jax.sharding.Mesh` (axis ``"specimen"``) over ``devices``.

    Args:
        devices: ``None`` or ``"all"`` (every device of every process: ``jax.devices()``),
            an int ``n`` (the first ``n`` of them) or a sequence of :class:`jax.Device`.
    """
    if devices is None or (isinstance(devices, str) and devices == "all"):
        devs = list(jax.devices())
    elif isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        avail = jax.devices()
        if not 1 <= int(devices) <= len(avail):
            raise FitError(f"devices={int(devices)}: {len(avail)} device(s) are available ({avail[0].platform}); "
                           "for simulated CPU devices set XLA_FLAGS=--xla_force_host_platform_device_count=N before importing jax")
        devs = list(avail[: int(devices)])
    elif isinstance(devices, jax.sharding.Mesh):
        if devices.axis_names != (AXIS,):
            raise FitError(f"a mesh for fit_batch needs the single axis {AXIS!r}, got {devices.axis_names}")
        return devices
    elif isinstance(devices, Sequence) and devices and all(isinstance(d, jax.Device) for d in devices):
        devs = list(devices)
    else:
        raise FitError(f"devices must be None, 'all', an int or a sequence of jax devices, got {devices!r}")
    if len({d.id for d in devs}) != len(devs):
        raise FitError("devices: the same device is listed twice")
    return jax.sharding.Mesh(np.array(devs), (AXIS,))


class _Split:
    """A batched array split along its first (specimen) axis into one part per device
    (``fit_batch(devices=...)``): each device runs the unsharded batched program on its own
    part, with no communication between devices."""

    def __init__(self, parts):
        self.parts = list(parts)


def _is_split(x) -> bool:
    return isinstance(x, _Split)


def _to_host(x) -> np.ndarray:
    """A batched array (one device, or split across devices) as one NumPy array on this host."""
    if isinstance(x, _Split):
        return np.concatenate([np.asarray(p) for p in x.parts])
    return np.asarray(x)


def _place(tree, mesh):
    """Every leaf split along its first axis into equal parts, one per device of ``mesh``
    (a :class:`_Split`), each part placed on its device."""
    if mesh is None:
        return tree
    devs = list(mesh.devices.reshape(-1))
    if any(d.process_index != jax.process_index() for d in devs):
        raise FitError("fit_batch(devices=...) runs on this process's own devices; with several processes call fit_batch in each one on "
                       "its local devices (jax.local_devices()) and its share of the specimens")

    def split(x):
        per = x.shape[0] // len(devs)
        return _Split(jax.device_put(x[i * per : (i + 1) * per], d) for i, d in enumerate(devs))

    return jax.tree_util.tree_map(split, tree)


def _per_device(fn, n: int):
    """``fn`` (a jitted batched function) called on every device's part of :class:`_Split`
    arguments: dispatched to all devices before any result is waited for."""

    def call(*args):
        outs = [fn(*jax.tree_util.tree_map(lambda s: s.parts[i] if _is_split(s) else s, args, is_leaf=_is_split)) for i in range(n)]
        return jax.tree_util.tree_map(lambda *xs: _Split(xs), *outs)

    return call


# ============================================================================ fit
def fit_batch(
    specimens,
    parameterization: MaterialParameterization,
    initial,
    *,
    method: str = "levenberg_marquardt",
    loss: str = "linear",
    f_scale: float = 1.0,
    starts: int | Sequence[Material] = 1,
    seed: int = 0,
    start_spread: float = 1.0,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    learning_rate: float = 0.05,
    jac: str = "fwd",
    absolute_sigma: bool = False,
    devices=None,
    labels: Sequence[str] | None = None,
    progress: bool = False,
    spectral: bool | None = None,
    scenario_parameters=None,
) -> BatchFitResult:
    """Fit the fields of ``parameterization`` to each specimen separately, all in one program.

    Args:
        specimens: a sequence of ``B`` specimens; each is a scenario or a sequence of scenarios
            (a joint fit per specimen). All specimens must share the structure (see the module
            docstring): same scenario types, names and static options, same number of points,
            same topology; their measured data, sigma and other floating-point leaves may differ.
        parameterization: fitted fields and their bounded transforms (shared).
        initial: the starting material of every specimen, or one per specimen (sequence of
            ``B`` :class:`Material`); non-fitted fields must be equal across specimens.
        method, loss, f_scale, starts, seed, start_spread, max_steps, rtol, atol,
        learning_rate, jac, absolute_sigma: as in :func:`difftissue.fit.fit`, for every
            specimen (integer ``starts``: the same draws around each specimen's initial
            vector, as a serial loop of ``fit(..., seed=seed)`` calls would make).
        devices: ``None`` (default): one batch on the default device. ``"all"``, an int ``n``
            or a sequence of devices, or a :func:`specimen_mesh`: the specimens are split across
            these devices: each runs the same jitted batched step on its share (no
            communication between devices); the batch is padded to a multiple of the device
            count. The devices must belong to this process.
        labels: names of the specimens (default ``"0"``, ``"1"``, ...), used in messages.
        progress: show a rich progress bar (on stderr).
        spectral: the linear solver of scenarios that offer a shared eigendecomposition
            (``spectral_variant``: :meth:`~difftissue.scenarios.Indentation.spectral_variant`,
            :mod:`difftissue.solvers.spectral`). ``None`` (default): used from
            :data:`SPECTRAL_MIN_SPECIMENS` specimens on, for every scenario where it applies
            and whose ``linear_solver`` is ``"auto"`` (the predictions agree with the
            factorising solver to round-off); ``False``: never; ``True``: required for every
            scenario that offers it (an explicit ``linear_solver`` is replaced), a
            :class:`~difftissue.errors.FitError` where it does not apply or no scenario offers it.
        scenario_parameters: as in :func:`difftissue.fit.fit` (e.g. each specimen's contact
            offset, fitted per specimen), by the scenario names shared by the specimens.

    Returns:
        A :class:`BatchFitResult`. Identifiability problems are emitted as
        :class:`~difftissue.errors.IdentifiabilityWarning` prefixed by ``"specimen <label>: "``.

    Notes:
        Each batched step costs as much as the slowest specimen's: a batched ``while`` loop
        (the Newton iterations of a static solve) runs until all specimens converge, and a
        specimen that has stopped is still evaluated (its state is frozen). The sparse SciPy
        linear solver runs on the host and factorises the batch's matrices one after the
        other; the dense Cholesky and CG solvers are batched by XLA.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}; choose one of {METHODS}")
    if jac not in ("fwd", "bwd"):
        raise FitError(f"jac must be 'fwd' or 'bwd', got {jac!r}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise FitError(f"max_steps must be an int >= 0, got {max_steps!r}")
    if isinstance(specimens, (str, bytes)) or not isinstance(specimens, Sequence) or len(specimens) == 0:
        raise FitError("specimens must be a non-empty sequence (each a scenario or a sequence of scenarios)")
    specimens = [_as_specimen(sp) for sp in specimens]
    B = len(specimens)
    labels = tuple(str(i) for i in range(B)) if labels is None else tuple(str(x) for x in labels)
    if len(labels) != B or len(set(labels)) != B:
        raise FitError(f"labels must be {B} distinct names, got {len(labels)} ({len(set(labels))} distinct)")
    if spectral is not None and not isinstance(spectral, bool):
        raise FitError(f"spectral must be None (automatic), True or False, got {spectral!r}")
    uses_spectral = False
    if spectral or (spectral is None and B >= SPECTRAL_MIN_SPECIMENS):
        switched = [_spectral_specimen(sp, required=bool(spectral), label=label) for sp, label in zip(specimens, labels)]
        uses_spectral = any(a is not b for new, old in zip(switched, specimens) for a, b in zip(new, old))
        specimens = switched
    if isinstance(initial, Material):
        initials = [initial] * B
    elif isinstance(initial, Sequence) and all(isinstance(m, Material) for m in initial):
        initials = list(initial)
        if len(initials) != B:
            raise FitError(f"initial: {len(initials)} materials for {B} specimens; give one Material for all or one per specimen")
    else:
        raise FitError(f"initial must be a Material or a sequence of {B} Materials, got {type(initial).__name__}")

    problems = []
    for b, (sp, m0) in enumerate(zip(specimens, initials)):
        try:
            problems.append(FitProblem(sp, parameterization, m0, loss=loss, f_scale=f_scale, scenario_parameters=scenario_parameters))
        except FitError as exc:
            raise FitError(f"specimen {labels[b]}: {exc}") from exc
    problems = _shared_structure(problems, labels)
    template = problems[0]

    U = np.stack([np.asarray(initial_starts(pr.parameterization, m0, starts, seed, start_spread)) for pr, m0 in zip(problems, initials)])  # (B, S, p)
    n_starts = U.shape[1]
    rtol, atol = tolerances(U.dtype, rtol, atol)
    engine = cached_engine(template, method, rtol=rtol, atol=atol, learning_rate=learning_rate, jac=jac)
    data = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *[pb.data() for pb in problems])

    mesh = None if devices is None else specimen_mesh(devices)
    n_dev = 1 if mesh is None else mesh.devices.size
    padding = (-B) % n_dev
    if padding:
        pad = lambda x: np.concatenate([x, np.repeat(x[:1], padding, axis=0)])  # noqa: E731
        U = pad(U)
        data = jax.tree_util.tree_map(pad, data)
    done = np.zeros((B + padding, n_starts), dtype=bool)
    done[B:] = True  # padding: frozen from the start

    first = jax.tree_util.tree_map(lambda x: x[0], data)
    # fixes the optimiser state's static part, which the step closes over: traced, not compiled
    # (the batched init below reuses the trace and is the one program compiled)
    jax.eval_shape(engine.init, U[0], first)
    U = jnp.asarray(U)
    fns = _batched_functions(engine, mesh, fast_compile=uses_spectral)
    dyn = fns["init"](U, data) if mesh is None else strong(jax.vmap(engine.init)(U, data))
    traces_before = fns["traces"][0]
    U, dyn, done_d, data_d = _place((U, dyn, done, data), mesh)

    # Optimistix methods: the first step evaluates and accepts the starts, so its losses are the
    # initial ones and the evaluation program is compiled only as a fallback (as in fit).
    history = [] if "final" in fns else [_to_host(fns["evaluate"](U, data_d)[1])]
    state = LoopState(U, dyn, done_d, np.zeros((B + padding, n_starts), dtype=np.int32), history)
    finished = done.all(axis=1)
    spec_steps = np.zeros(B + padding, dtype=int)

    last_final = []  # optimistix methods: the final evaluation of the last step's state (computed by the step)

    def step_fn(U, dyn, done, data):
        out = fns["step"](U, dyn, done, data)
        if "final" not in fns:
            return out
        last_final[:] = [out[5]]
        return out[:5]

    bar = progress_bar(progress, max_steps)
    task = None

    def on_step(state: LoopState, losses: np.ndarray) -> None:
        nonlocal finished
        now = _to_host(state.done).all(axis=1)
        spec_steps[now & ~finished] = state.step
        finished = now
        if bar is not None:
            bar.update(task, completed=state.step, loss=f"{int(finished[:B].sum())}/{B} specimens done")

    if bar is not None:
        bar.start()
        task = bar.add_task("fit", total=max_steps, completed=0, loss=f"{np.nanmax(np.nanmin(history[-1][:B], axis=1)):.6g}" if history else "-")
    try:
        run_steps(step_fn, state, data_d, max_steps=max_steps, to_host=_to_host, on_step=on_step)
    finally:
        if bar is not None:
            bar.stop()
    spec_steps[~finished] = state.step
    # padding rows never step and are dropped: only the specimens' rows must hold an evaluation
    final_fn = fns.get("final")
    if last_final:
        final_fn = lambda U, dyn, data: last_final[0]  # noqa: E731 - the state after the last step: state.U, state.dyn
    result = final_evaluation(final_fn, fns["evaluate"], state.U, state.dyn, data_d, rows=slice(0, B), to_host=_to_host)
    all_values, final, all_J, all_preds = (jax.tree_util.tree_map(_to_host, x) for x in result)
    history = state.history
    if not history:  # no step taken
        history.append(final)
    U_h, done_h, status, step = _to_host(state.U), _to_host(state.done), state.status, state.step
    compilations = fns["traces"][0] - traces_before
    H = np.stack(history)  # (steps + 1, B, S)

    fits = []
    for b in range(B):
        n = int(spec_steps[b])
        fits.append(
            build_result(
                problems[b], engine, U_h[b], all_values[b], final[b], all_J[b], [p[b] for p in all_preds], done_h[b], status[b],
                list(H[: n + 1, b]), n, stop_reason=f"max_steps ({max_steps}) reached", absolute_sigma=absolute_sigma,
                method=method, loss=loss, f_scale=f_scale, compilations=compilations, warning_prefix=f"specimen {labels[b]}: ", stacklevel=3,
            )
        )
    fields = template.fields
    return BatchFitResult(
        fits=tuple(fits),
        labels=labels,
        fields=fields,
        values=np.array([[r.values[f] for f in fields] for r in fits]),
        standard_errors=np.array([[r.standard_errors[f] for f in fields] for r in fits]),
        loss=np.array([r.loss for r in fits]),
        converged=np.array([r.converged for r in fits]),
        steps=np.array([r.steps for r in fits]),
        batch_steps=int(step),
        compilations=int(compilations),
        devices=tuple(str(d) for d in (jax.devices()[:1] if mesh is None else mesh.devices.reshape(-1))),
        padding=int(padding),
    )


def _spectral_specimen(scenarios: tuple, *, required: bool, label: str) -> tuple:
    """The specimen's scenarios with the spectral solver where they offer it (``spectral_variant``)."""
    out, offered = [], False
    for sc in scenarios:
        variant = getattr(sc, "spectral_variant", None)
        if variant is None:
            out.append(sc)
            continue
        offered = True
        try:
            new = variant(required=required)
        except DifftissueError as exc:
            raise FitError(f"specimen {label}: spectral=True: {exc}") from exc
        out.append(sc if new is None else new)
    if required and not offered:
        raise FitError(f"specimen {label}: spectral=True, but none of its scenarios offers the spectral solver (the condensed fem_linear indentation does)")
    return tuple(out)


def _shared_structure(problems: list[FitProblem], labels) -> list[FitProblem]:
    """Check that the specimens share one structure; return the problems with every
    floating-point scenario leaf that differs between them passed as data (batched)."""
    p0 = problems[0]
    for b, pb in enumerate(problems[1:], 1):
        who = f"specimen {labels[b]}"
        if len(pb.scenarios) != len(p0.scenarios):
            raise FitError(f"{who} has {len(pb.scenarios)} scenario(s), specimen {labels[0]} {len(p0.scenarios)}: batched specimens need the same scenarios")
        if pb.names != p0.names:
            raise FitError(f"{who}: scenario names {pb.names} differ from {p0.names} of specimen {labels[0]}; the names are part of the compiled "
                           "structure: give every specimen's scenarios the same names (label the specimens with labels=)")
        for name, n0, n in zip(p0.names, p0.sizes, pb.sizes):
            if n != n0:
                raise FitError(f"{who}: scenario {name!r} has {n} points, specimen {labels[0]} has {n0}: batched specimens need the same number of "
                               "points per scenario (fit protocols of other lengths in a separate batch)")
        c0, cb = p0.fingerprint("", 0)[1], pb.fingerprint("", 0)[1]
        if c0["fixed material fields"] != cb["fixed material fields"]:
            raise FitError(f"{who}: the non-fitted fields of its initial material differ from specimen {labels[0]}'s; they are compiled in and must be equal (or fit them)")
        for s, name in enumerate(p0.names):
            if pb._treedefs[s] != p0._treedefs[s]:
                diff = _static_differences(p0.scenarios[s], pb.scenarios[s]) or ["the pytree structure"]
                raise FitError(f"{who}: scenario {name!r} differs from specimen {labels[0]}'s in {', '.join(diff)}; these are compiled in: "
                               "batched specimens must share them (fit the others in a separate batch)")
    dynamic = []
    for s, name in enumerate(p0.names):
        dyn = set(p0._dynamic[s])
        for pb in problems[1:]:
            dyn |= set(pb._dynamic[s])
        try:
            paths = [jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_flatten_with_path(p0.scenarios[s])[0]]
        except Exception:  # noqa: BLE001 - a leaf path is only for the message
            paths = [f"leaf {i}" for i in range(len(p0._leaves[s]))]
        for i, leaf0 in enumerate(p0._leaves[s]):
            if i in dyn:
                continue
            for b, pb in enumerate(problems[1:], 1):
                other = pb._leaves[s][i]
                if _same(leaf0, other):
                    continue
                a0, ab = np.asarray(leaf0) if eqx.is_array(leaf0) else None, np.asarray(other) if eqx.is_array(other) else None
                if a0 is not None and ab is not None and a0.shape == ab.shape and np.issubdtype(a0.dtype, np.floating) and a0.dtype == ab.dtype:
                    dyn.add(i)  # a floating-point leaf that differs (e.g. a depth protocol): batched
                    break
                if len(p0._leaves[s]) == 1 and leaf0 is p0.scenarios[s]:
                    raise FitError(
                        f"specimen {labels[b]}: scenario {name!r} ({type(leaf0).__name__}) is not a pytree, so it is compiled in as a whole and "
                        "batched specimens would have to be the same object; make the scenario class an equinox Module (its arrays become batchable leaves)"
                    )
                raise FitError(
                    f"specimen {labels[b]}: scenario {name!r}{paths[i]} differs from specimen {labels[0]}'s and is not a floating-point array of the same "
                    "shape; integer/boolean arrays (mesh connectivity, node sets: the topology) and other objects are compiled in, so batched specimens must share them"
                )
        dynamic.append(dyn)
    return [pb._with_dynamic(dynamic) for pb in problems]


def _batched_functions(engine, mesh, *, fast_compile: bool = False) -> dict[str, Any]:
    """The compiled batched init, step and evaluation of ``engine`` (kept with it, per mesh and
    ``fast_compile``: :data:`SPECTRAL_COMPILER_OPTIONS`), from the same single-start step as
    :func:`difftissue.fit.fit`: one ``vmap`` over every start of every specimen; the step of an
    optimistix method also returns the final evaluation of its new state. With a mesh, called
    on each device's part of the batch."""
    cache = engine.__dict__.setdefault("_batch_functions", {})
    key = (fast_compile, None if mesh is None else (tuple(d.id for d in mesh.devices.reshape(-1)), mesh.axis_names))
    hit = cache.get(key)
    if hit is not None:
        return hit
    one = engine.single_step()
    traces = [0]

    def step(U, dyn, done, data):
        traces[0] += 1  # Python side effect: once per trace (compilation)
        # ONE vmap over the specimens' starts, (B, S) flattened to B S rows with each
        # specimen's data repeated for its starts, rather than a vmap over the starts inside a
        # vmap over the specimens: tracing the step under one batching level instead of two
        # (the trace is about a third of the program's cold cost).
        B, S = U.shape[:2]
        rows = lambda x: x.reshape((B * S,) + x.shape[2:])  # noqa: E731
        out = jax.vmap(one)(rows(U), jax.tree_util.tree_map(rows, dyn), rows(done), jax.tree_util.tree_map(lambda x: jnp.repeat(x, S, axis=0), data))
        out = strong(jax.tree_util.tree_map(lambda x: x.reshape((B, S) + x.shape[1:]), out))
        if single_final is None:
            return out
        # Optimistix methods: the final evaluation of the new state (values, loss, Jacobian,
        # predictions from the solver state: a few 2 x 2 solves) in the same program, so that
        # no separate final program is compiled (fit_batch keeps the last step's).
        return (*out, final(out[0], out[1], data))

    def evaluate(U, data):
        return jax.vmap(engine.evaluate)(U, data)

    single_final = engine.make_final()  # None for optax methods

    def final(U, dyn, data):
        return jax.vmap(single_final)(U, dyn, data)

    def init(U, data):
        # in one program: vmapped outside a jit, the init's unbatched outputs would each be
        # broadcast by a separately compiled eager operation
        return strong(jax.vmap(engine.init)(U, data))

    options = None
    if jax.default_backend() == "cpu":
        options = {**CPU_COMPILER_OPTIONS, **(SPECTRAL_COMPILER_OPTIONS if fast_compile else {})}
    fns = {"step": jax.jit(step, compiler_options=options), "evaluate": jax.jit(evaluate, compiler_options=options), "traces": traces,
           "init": jax.jit(init, compiler_options=options)}
    if single_final is not None:
        fns["final"] = jax.jit(final, compiler_options=options)
    if mesh is not None:
        # One program per device on its own specimens, no cross-device communication. (A
        # GSPMD-partitioned program, inputs placed with NamedSharding, turned the batched
        # while-loop predicates and error checks into 36 cross-device all-reduces per LM step,
        # which hung XLA's CPU collectives with more than one specimen per simulated device;
        # jax.shard_map / pmap are refused by lineax 0.1.1 (issue #185).)
        n = mesh.devices.size
        fns = {**{k: _per_device(f, n) for k, f in fns.items() if k != "traces"}, "traces": traces}
    cache[key] = fns
    return fns

