"""Budget-aware calibration: effective material parameters for a given XPBD budget.

Standard (real-time) XPBD with a fixed iteration budget does not converge each frame's
solve, and the state it settles to is softer than the model's static equilibrium (see
``docs/xpbd.md``). :func:`calibrate_for_budget` finds the *effective* material that makes
the budgeted XPBD solve reproduce a reference static response (the same model solved to
convergence with :func:`~difftissue.solvers.solve_static`, or a ``fem_linear`` model) at the
true material, by least squares on the relative observable mismatch with the Jacobian
taken through the unrolled XPBD loop (forward mode): the fit engine's Levenberg--Marquardt
(:func:`difftissue.fit.residuals.least_squares`, the engine of :func:`difftissue.fit.fit`),
which also gives the Gauss--Newton covariance of the calibrated fields. The result records
the setting (dt, substeps, iterations, method) it is valid for: an effective material is
only meaningful for that setting, that mesh resolution and similar loading.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import warnings
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._io import read_toml
from .boundary import BoundaryConditions
from .errors import (BudgetExtrapolationWarning, BudgetRangeError, BudgetSaturationError, ConfigError, ConvergenceError, DifftissueWarning,
                     ModelError)
from .fit.residuals import ResidualProblem, least_squares
from .materials import MATERIAL_FIELDS, Identity, Material, ScaledLogit
from .mesh import LENGTH_UNITS, signed_volumes
from .models import MESH_MODELS, ElasticModel, make_model
from .solvers.static import solve_static
from .solvers.xpbd import XPBDSettings, xpbd_quasi_static
from .structure_keys import hash_scenario_leaves

__all__ = ["BudgetCalibration", "calibrate_for_budget", "FITTABLE_FIELDS", "BudgetLoad", "indentation_load", "cell_size",
           "BudgetProposal", "propose_budget", "LoadSetCalibration", "calibrate_for_load_set", "MIN_SENSITIVITY", "SHAPES",
           "LoadSetSpec", "parse_load_set", "read_load_set", "LOAD_SET_KEYS", "LOAD_KEYS"]

#: fields that can be calibrated, with the transform to unconstrained space used for the steps
FITTABLE_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient")
_NU_LO, _NU_HI = 0.0, 0.4999


#: The variable of each field in the optimiser and its transform from the unconstrained one: E
#: as the ratio ``E / E_true`` [-] (so the transform does not depend on the true material, and
#: calls at other materials share the compiled programs), log-like; nu in (0, 0.4999) by a
#: scaled logit; the cubic coefficient as it is.
_TRANSFORMS = {
    # E within exp(+-reach) of the true value: log-like in between (a logit of E / E_true between
    # those bounds), so a saturated setting (a response insensitive to E) ends at a bound instead
    # of drifting to 1e34 x E.
    "youngs_modulus": lambda reach: ScaledLogit(math.exp(-reach), math.exp(reach)),
    "poisson_ratio": lambda reach: ScaledLogit(_NU_LO, _NU_HI),
    "cubic_coefficient": lambda reach: Identity(),
}


def _field_scales(material: Material, fields) -> np.ndarray:
    """``(p,)`` unit of each optimiser variable in its field's SI unit: the true E for
    ``youngs_modulus`` (the variable is ``E / E_true``), 1 for the others."""
    return np.array([float(material.youngs_modulus) if f == "youngs_modulus" else 1.0 for f in fields])


@dataclasses.dataclass(frozen=True)
class BudgetCalibration:
    """Result of :func:`calibrate_for_budget`.

    Attributes:
        material: the calibrated (effective) material for the budgeted XPBD setting.
        true_material: the material the reference was computed with.
        fit_fields: the calibrated fields.
        setting: ``{"dt", "substeps", "iterations", "method"}``: the XPBD setting the
            calibrated material is valid for (and only for).
        model_kind: the XPBD model kind.
        reference_kind: what the reference response came from (model kind).
        reference: the reference observable (array).
        naive: the observable of the budgeted XPBD solve at the true material.
        calibrated: the observable of the budgeted XPBD solve at the calibrated material.
        naive_error, calibrated_error: relative errors ``|obs - ref| / |ref|`` (2-norm).
        steps: optimiser steps taken (Levenberg--Marquardt trial steps after the start's
            evaluation; 0 when the naive error already met ``rtol``).
        converged: ``calibrated_error <= rtol``.
        jacobian: ``(n, p)`` derivative of the relative mismatch ``(obs - ref) / |ref|`` [-]
            with respect to the calibrated fields (SI) at the calibrated material.
        covariance: ``(p, p)`` Gauss--Newton covariance ``s^2 (J^T J)^-1`` of the calibrated
            fields (SI units squared), ``s^2 = |mismatch|^2 / (n - p)``: how well the
            observables pin the effective fields down given the mismatch left. NaN when there
            are no more observables than fields (``dof = 0``, e.g. the scalar ``"reaction"``
            with one field): the calibration then matches exactly and has no scatter to go by.
        standard_errors: ``{field: sqrt(covariance_ii)}`` (SI; NaN when ``dof = 0``).
        dof: observables minus calibrated fields.
    """

    material: Material
    true_material: Material
    fit_fields: tuple
    setting: dict
    model_kind: str
    reference_kind: str
    reference: np.ndarray
    naive: np.ndarray
    calibrated: np.ndarray
    naive_error: float
    calibrated_error: float
    steps: int
    converged: bool
    jacobian: np.ndarray | None = None
    covariance: np.ndarray | None = None
    standard_errors: dict = dataclasses.field(default_factory=dict)
    dof: int = 0

    def ratio(self, field: str = "youngs_modulus") -> float:
        """Calibrated / true value of ``field``."""
        return float(getattr(self.material, field)) / float(getattr(self.true_material, field))


def _moved_nodes(bc: BoundaryConditions):
    """``(idx, mask, direction)`` of the reaction observable: the nodes with a non-zero
    prescribed displacement, their prescribed components ``(k, 3)`` and the unit direction of
    their summed prescribed displacement ``(3,)``."""
    fixed = np.asarray(bc.fixed)
    disp = np.where(fixed, np.asarray(bc.displacement), 0.0)
    moved = np.any(np.abs(disp) > 0, axis=1)
    if not moved.any():
        raise ConfigError(
            "observable='reaction' needs nodes with a non-zero prescribed displacement "
            "(the total reaction on them is the observable); pass a function of the displacement instead"
        )
    idx = np.flatnonzero(moved)
    direction = disp[idx].sum(axis=0)
    if np.linalg.norm(direction) == 0.0:
        raise ConfigError("observable='reaction': the prescribed displacements sum to zero; pass a function instead")
    return idx, fixed[idx], direction / np.linalg.norm(direction)


def _reaction_weights(bc: BoundaryConditions) -> np.ndarray:
    """``(N, 3)`` weights ``w`` with the reaction observable ``= sum(w * reaction)`` [N] (the
    same quantity as :func:`_reaction_observable`, in a form that stacks over loads)."""
    idx, mask, direction = _moved_nodes(bc)
    w = np.zeros(np.shape(bc.fixed))
    w[idx] = np.where(mask, direction[None, :], 0.0)
    return w


def _reaction_observable(idx, mask, direction, reaction):
    """Total reaction force on the nodes ``idx`` with a non-zero prescribed displacement
    (:func:`_moved_nodes`), projected on the direction of their summed prescribed displacement
    (a ``(1,)`` array, N; with the solvers' reaction convention -- internal elastic force on the
    prescribed components -- it is positive when the tissue resists the prescribed motion)."""
    total = jnp.sum(jnp.where(mask, reaction[idx], 0.0), axis=0)
    return jnp.atleast_1d(jnp.dot(total, direction))


class _BudgetProgram:
    """The budgeted observable of one structure of :func:`calibrate_for_budget`, traced once and
    shared by every call of that structure (:func:`_budget_program`).

    Compiled in: the XPBD model (the mesh), which displacement components are prescribed, the
    settings' static configuration (substeps, iterations, method, ...), the observable (the
    reaction's nodes and direction, or the user's function) and the calibrated fields.
    Arguments (``args``): ``material`` (every field an array, SI), ``settings`` (the settings'
    arrays: dt [s], relaxation, damping [1/s]), the prescribed ``displacement`` [m] and
    ``force`` [N], ``tol`` [-], ``max_frames``, ``scale`` (:func:`_field_scales`) and, for the
    residuals, ``reference`` (the observable's unit) and ``norm`` (``|reference| rtol``)."""

    def __init__(self, key, model, bc: BoundaryConditions, settings: XPBDSettings, observable, fit_fields):
        self.key = key
        self.model = model
        self.bc = bc  # its prescribed components; its displacement and force are arguments
        self.settings = eqx.partition(settings, eqx.is_array)[1]
        self.observable = observable
        self.fit_fields = fit_fields
        self.observe = jax.jit(self._observe)

    def _observe(self, v, args):
        """Budgeted observable at the optimiser's variables ``v`` (``(p,)``, the fields' values
        over ``args["scale"]``) and whether XPBD came to rest."""
        m = _with_values(args["material"], self.fit_fields, v * args["scale"])
        settings = eqx.combine(args["settings"], self.settings)
        bc = eqx.tree_at(lambda b: (b.displacement, b.force), self.bc, (args["displacement"], args["force"]))
        sol = xpbd_quasi_static(self.model, m, bc, settings=settings, tol=args["tol"], max_steps=args["max_frames"], throw=False)
        if callable(self.observable):
            y = jnp.atleast_1d(jnp.asarray(self.observable(sol.displacement)))
        else:
            y = _reaction_observable(*self.observable[1:], sol.reaction)
        return y, sol.converged

    def residual_fn(self, v, data):
        """(y - y_ref) / (|y_ref| rtol): the relative mismatch in units of the target, so that
        the Jacobian dominates Levenberg--Marquardt's initial damping (unit in u) and the first
        steps are nearly Gauss--Newton steps (the minimiser and the covariance do not depend on
        this scale). A frame limit reached gives NaN, which the optimiser rejects."""
        y, ok = self._observe(v, data)
        r = (y - data["reference"]) / data["norm"]
        return jnp.where(ok, r, jnp.nan), y

    def arguments(self, material: Material, bc: BoundaryConditions, settings: XPBDSettings, tol, max_frames, scale) -> dict:
        """The ``args`` of a call (see the class docstring; no ``reference`` / ``norm``)."""
        return {
            "material": jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material),
            "settings": eqx.partition(settings, eqx.is_array)[0],
            "displacement": jnp.asarray(bc.displacement, dtype=float),
            "force": jnp.asarray(bc.force, dtype=float),
            "tol": jnp.asarray(tol, dtype=float),
            "max_frames": np.asarray(max_frames, dtype=np.int32),
            "scale": jnp.asarray(scale, dtype=float),
        }


#: Programs of :func:`calibrate_for_budget` (:class:`_BudgetProgram`) and
#: :func:`calibrate_for_load_set` (:class:`_LoadSetProgram`) by structure key, most recently
#: used last (the fit engine keeps its own compiled steps, keyed by the same key).
_BUDGET_PROGRAMS: collections.OrderedDict = collections.OrderedDict()
_BUDGET_PROGRAMS_SIZE = 8


def _shared_program(build, compiled_in, settings: XPBDSettings, *tags):
    """``build(key)``, or the program already built for an equal key (most recently used kept).

    The key is what the program compiles in: ``tags`` (hashable: which calibration, the
    fields, ...), the settings' static configuration (substeps, iterations, method, ...) and the
    pytree ``compiled_in`` (the model, the prescribed components, the observable): its structure,
    its arrays by content, other objects (a user's function) by identity
    (:func:`hash_scenario_leaves`; the program keeps them alive). A static configuration that
    cannot be hashed gives ``build(None)``, shared with nothing."""
    leaves, treedef = jax.tree_util.tree_flatten(compiled_in)
    settings_def = jax.tree_util.tree_structure(eqx.partition(settings, eqx.is_array)[0])
    try:
        hash((treedef, settings_def, tags))
    except TypeError:  # a static field that cannot be hashed
        return build(None)
    h = hashlib.sha256()
    objects = hash_scenario_leaves(h, leaves, ())
    key = (tags, treedef, settings_def, h.hexdigest(), tuple(objects))
    program = _BUDGET_PROGRAMS.pop(key, None)
    if program is None:
        program = build(key)
    _BUDGET_PROGRAMS[key] = program  # most recent last
    while len(_BUDGET_PROGRAMS) > _BUDGET_PROGRAMS_SIZE:
        _BUDGET_PROGRAMS.popitem(last=False)
    return program


def calibrate_for_budget(
    mesh,
    model_kind: str,
    material: Material,
    bc: BoundaryConditions,
    settings: XPBDSettings,
    *,
    reference=None,
    fit_fields=("youngs_modulus",),
    observable="reaction",
    max_steps: int = 10,
    rtol: float = 1e-3,
    tol: float = 1e-10,
    max_frames: int = 5000,
    max_log_step: float = 1.0,
) -> BudgetCalibration:
    """Effective material parameters for a budgeted XPBD setting.

    Args:
        mesh: the :class:`~difftissue.mesh.TetMesh`.
        model_kind: XPBD model kind (``"springs_volume"`` or ``"stable_neo_hookean"``).
        material: the true :class:`~difftissue.materials.Material` (scalar fields).
        bc: prescribed displacements / forces (the same for the reference and XPBD).
        settings: the target :class:`~difftissue.solvers.xpbd.XPBDSettings` (dt, substeps,
            iterations, method). ``warm_start`` should be ``False`` (standard real-time XPBD);
            with ``True`` XPBD converges to the static answer and there is nothing to calibrate.
        reference: ``None`` (the static solve of the same model kind), a model kind string
            (e.g. ``"fem_linear"``) or an :class:`~difftissue.models.ElasticModel`.
        fit_fields: fields of ``material`` to calibrate (subset of :data:`FITTABLE_FIELDS`).
            Levenberg--Marquardt (damped Gauss--Newton) also when there are more fields than
            observables.
        observable: ``"reaction"`` (total reaction force on the nodes with a non-zero
            prescribed displacement, projected on the direction of their summed prescribed
            displacement: a scalar) or a function ``f(displacement) -> array``.
        max_steps: optimiser steps allowed (after the evaluation of the true material).
        rtol: stop when the relative error is at most this.
        tol, max_frames: convergence tolerance and frame limit of the quasi-static XPBD solve.
        max_log_step: the calibrated Young's modulus stays within
            ``exp(+-max_log_step * max_steps)`` of the true one (the reach of ``max_steps``
            steps of at most ``max_log_step`` in ``log E``): a saturated setting ends at that
            bound with ``converged=False``. Must be > 0.

    Raises:
        ConfigError: unknown field / observable, bad settings or step counts.
        ModelError: a model kind XPBD or the reference cannot use.
        ConvergenceError: the reference or the budgeted XPBD solve did not come to rest.

    Warns:
        DifftissueWarning: the error did not reach ``rtol`` (``converged`` is then False);
            typically the budgeted response is saturated and no material can fix it.
    """
    # ------------------------------------------------------------------ validation
    if not isinstance(settings, XPBDSettings):
        raise ConfigError(f"settings must be an XPBDSettings, got {type(settings).__name__}")
    if settings.warm_start:
        raise ConfigError(
            "settings.warm_start=True makes quasi-static XPBD converge to the static answer for any "
            "budget; calibrate the standard real-time setting (warm_start=False)"
        )
    if not isinstance(material, Material):
        raise ConfigError(f"material must be a Material, got {type(material).__name__}")
    if model_kind not in ("springs_volume", "stable_neo_hookean"):
        raise ModelError(
            f"model_kind must be an XPBD model ('springs_volume' or 'stable_neo_hookean'), got {model_kind!r}"
        )
    if isinstance(fit_fields, str):
        fit_fields = (fit_fields,)
    fit_fields = tuple(fit_fields)
    if not fit_fields:
        raise ConfigError("fit_fields is empty")
    for f in fit_fields:
        if f not in FITTABLE_FIELDS:
            raise ConfigError(f"fit_fields: {f!r} cannot be calibrated; choose from {FITTABLE_FIELDS}")
    if len(set(fit_fields)) != len(fit_fields):
        raise ConfigError(f"fit_fields has duplicates: {fit_fields}")
    for f in fit_fields:
        if np.ndim(getattr(material, f)) != 0:
            raise ConfigError(f"material.{f} must be a scalar to be calibrated (one value per region is not supported)")
    if "poisson_ratio" in fit_fields and not (_NU_LO < float(material.poisson_ratio) < _NU_HI):
        raise ConfigError(f"poisson_ratio must lie in ({_NU_LO}, {_NU_HI}) to be calibrated")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise ConfigError(f"max_steps must be an integer >= 0, got {max_steps!r}")
    if not rtol > 0:
        raise ConfigError(f"rtol must be > 0, got {rtol!r}")
    if not max_log_step > 0:
        raise ConfigError(f"max_log_step must be > 0, got {max_log_step!r}")

    model = make_model(mesh, model_kind)
    ref_model, ref_kind = _reference_model(mesh, model, model_kind, reference)

    if isinstance(observable, str) and observable == "reaction":
        observable = ("reaction", *_moved_nodes(bc))

        def obs(displacement, reaction):
            return _reaction_observable(*observable[1:], reaction)

    elif callable(observable):
        user: Callable = observable

        def obs(displacement, reaction):
            return jnp.atleast_1d(jnp.asarray(user(displacement)))

    else:
        raise ConfigError(f"observable must be 'reaction' or a function of the displacement, got {observable!r}")

    # ------------------------------------------------------------------ reference
    ref_sol = solve_static(ref_model, material, bc, throw=False)
    if not bool(ref_sol.converged):
        raise ConvergenceError(f"the reference static solve ({ref_kind}) did not converge")
    y_ref = obs(ref_sol.displacement, ref_sol.reaction)
    ref_norm = float(jnp.linalg.norm(y_ref))
    if not np.isfinite(ref_norm) or ref_norm == 0.0:
        raise ConfigError("the reference observable is zero or not finite: nothing to calibrate against")

    # ------------------------------------------------------------------ budgeted XPBD
    # One program per structure (model, prescribed components, static settings, observable,
    # fields); the numbers -- material, dt, prescribed displacements, reference -- are its
    # arguments, so calls that differ only in them compile nothing again.
    program = _shared_program(lambda key: _BudgetProgram(key, model, bc, settings, observable, fit_fields),
                              (model, np.asarray(bc.fixed), observable), settings, "calibrate_for_budget", type(model), fit_fields)
    scale = _field_scales(material, fit_fields)
    args = program.arguments(material, bc, settings, tol, max_frames, scale)

    def evaluate(v):
        """Observable and relative error at the optimiser's variables ``v`` (values / scale)."""
        y, ok = program.observe(jnp.asarray(v, dtype=float), args)
        if not bool(ok):
            raise ConvergenceError(
                f"the budgeted XPBD solve did not come to rest within {max_frames} frames "
                f"(model {model_kind}, iterations {settings.iterations}, method {settings.method}); "
                "raise max_frames or use another setting"
            )
        return y, float(jnp.linalg.norm((y - y_ref) / ref_norm))

    start = np.array([float(getattr(material, f)) for f in fit_fields]) / scale
    y_naive, naive_err = evaluate(start)
    reach = max_log_step * max(int(max_steps), 1)
    problem = ResidualProblem(program.residual_fn, fit_fields, [_TRANSFORMS[f](reach) for f in fit_fields], int(y_ref.shape[0]),
                              data={**args, "reference": np.asarray(y_ref), "norm": np.asarray(ref_norm * rtol)}, key=program.key)
    # The engine's first step evaluates the start (residual and Jacobian); max_steps optimiser
    # steps follow, until the relative error reaches rtol (the loss is (err / rtol)^2 / 2). With
    # max_steps = 0 or a naive error within rtol, the result holds the start's statistics.
    fit = least_squares(problem, start, method="levenberg_marquardt", max_steps=max_steps + 1,
                        stop=lambda loss: math.sqrt(2.0 * loss) <= 1.0)
    v = np.array([fit.values[f] for f in fit_fields])
    values = v * scale
    steps = max(fit.steps - 1, 0)
    y, err = evaluate(v)

    if err > rtol:
        warnings.warn(
            f"budget calibration stopped at relative error {err:.3g} after {steps} steps (naive {naive_err:.3g}): "
            "with this setting the budgeted response may be saturated (insensitive to the fitted fields; "
            "e.g. (dt c / h)^2 >> iterations); check .converged and consider a smaller dt or more substeps",
            DifftissueWarning,
            stacklevel=2,
        )
    return BudgetCalibration(
        material=_with_values(material, fit_fields, values),
        true_material=material,
        fit_fields=fit_fields,
        setting={
            "dt": float(settings.dt),
            "substeps": int(settings.substeps),
            "iterations": int(settings.iterations),
            "method": str(settings.method),
        },
        model_kind=model_kind,
        reference_kind=ref_kind,
        reference=np.asarray(y_ref),
        naive=np.asarray(y_naive),
        calibrated=np.asarray(y),
        naive_error=naive_err,
        calibrated_error=err,
        steps=steps,
        converged=err <= rtol,
        jacobian=np.asarray(fit.jacobian) / scale[None, :] * rtol,
        covariance=np.asarray(fit.covariance) * np.outer(scale, scale),
        standard_errors={f: float(fit.standard_errors[f] * scale[i]) for i, f in enumerate(fit_fields)},
        dof=fit.dof,
    )


def _with_values(material: Material, fields, values) -> Material:
    """``material`` with ``fields`` set to ``values`` (physical, SI)."""
    kw = {name: getattr(material, name) for name in MATERIAL_FIELDS}
    for i, f in enumerate(fields):
        kw[f] = values[i]
    return Material(**kw)


# ============================================================================ load sets
#: Indenter shapes of :func:`indentation_load` (a :class:`BudgetLoad` may carry any label).
SHAPES = ("flat_punch", "sphere", "platen")

#: Smallest ``d log F / d log E`` of the budgeted response on every load of a set at which the
#: budget counts as carrying the load (1 for a converged linear response, -> 0 at the
#: hard-constraint limit). Below 0.5 more than half of a change of the effective modulus is
#: lost to the unconverged solve: a relative force error maps to more than twice that error in
#: E, and the factor a card needs rises steeply with the load and the stiffness
#: (docs/dev/budget-calibration.md, "Saturation threshold").
MIN_SENSITIVITY = 0.5


@dataclasses.dataclass(frozen=True)
class BudgetLoad:
    """One load of a set a simulator meets (:func:`calibrate_for_load_set`).

    Attributes:
        bc: prescribed displacements (and forces) on the set's mesh; the observable is the
            reaction on the nodes with a non-zero prescribed displacement along their summed
            displacement (as ``observable="reaction"`` of :func:`calibrate_for_budget`).
        shape: indenter shape label (``"flat_punch"``, ``"sphere"``, ``"platen"`` or another
            name): a card is valid only for the shapes of its set.
        depth: indenter travel [m] (> 0): a card is valid over the set's depth range.
        youngs_modulus: the true tissue modulus of this load [Pa]; None: the calibration's
            ``material``. Loads at several moduli give the card's stiffness range.
        name: a label for tables (default: shape and depth).
    """

    bc: BoundaryConditions
    shape: str
    depth: float
    youngs_modulus: float | None = None
    name: str = ""

    def label(self) -> str:
        return self.name or f"{self.shape} {1e3 * self.depth:g} mm"


def indentation_load(mesh, shape: str, depth: float, *, radius: float | None = None,
                     youngs_modulus: float | None = None, name: str = "") -> BudgetLoad:
    """A bonded indentation of the top face (largest z) of ``mesh`` with its base (smallest z)
    clamped: the load of a real-time simulator's tool on a block.

    ``shape``:

    - ``"flat_punch"``: the top nodes within ``radius`` [m] of the face's centre (x, y of the
      bounding box) move down by ``depth`` [m], bonded (all components prescribed);
    - ``"platen"``: every top node moves down by ``depth``, bonded;
    - ``"sphere"``: a sphere of ``radius`` [m] pushed ``depth`` into the face; the top nodes
      inside the geometric contact radius ``a = sqrt(2 radius depth)`` follow the sphere's
      surface (``u_z = -(depth - r^2 / (2 radius))``, paraboloid approximation, bonded).

    Raises:
        ConfigError: unknown shape, a non-positive depth or radius, a missing radius, or no
            top node under the indenter.
    """
    if shape not in SHAPES:
        raise ConfigError(f"indentation_load: shape must be one of {SHAPES}, got {shape!r}")
    if not (np.isfinite(depth) and depth > 0):
        raise ConfigError(f"indentation_load: depth must be > 0 m, got {depth!r}")
    if shape != "platen" and not (radius is not None and np.isfinite(radius) and radius > 0):
        raise ConfigError(f"indentation_load: a {shape} needs radius > 0 m, got {radius!r}")
    p = np.asarray(mesh.points)
    z_top = p[:, 2].max()
    top = np.abs(p[:, 2] - z_top) <= 1e-9 * max(float(np.ptp(p)), 1e-300)
    cx, cy = (p[:, 0].min() + p[:, 0].max()) / 2, (p[:, 1].min() + p[:, 1].max()) / 2
    r = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    if shape == "platen":
        nodes, uz = np.flatnonzero(top), np.full(int(top.sum()), -depth)
    elif shape == "flat_punch":
        nodes = np.flatnonzero(top & (r <= radius * (1 + 1e-9)))
        uz = np.full(nodes.size, -depth)
    else:
        a = math.sqrt(2.0 * radius * depth)
        nodes = np.flatnonzero(top & (r < a))
        uz = -(depth - r[nodes] ** 2 / (2.0 * radius))
    if nodes.size == 0:
        raise ConfigError(f"indentation_load: no top node under the {shape} (radius {radius!r} m, depth {depth} m); "
                          "use a larger radius or a finer mesh")
    disp = np.zeros((nodes.size, 3))
    disp[:, 2] = uz
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"}).fix(mesh, nodes, "xyz", disp)
    return BudgetLoad(bc, shape, float(depth), None if youngs_modulus is None else float(youngs_modulus), name)


def cell_size(mesh) -> float:
    """``(6 V)^(1/3)`` of the mean tet volume ``V`` [m]: the edge of the cube six such tets fill
    (the cube size of a :func:`~difftissue.mesh.block` mesh)."""
    return float((6.0 * np.mean(np.abs(np.asarray(signed_volumes(mesh.points, mesh.tets))))) ** (1.0 / 3.0))


@dataclasses.dataclass(frozen=True)
class BudgetProposal:
    """A budget that carries every load of a set, found by a measured search
    (:func:`propose_budget`).

    Attributes:
        iterations: the smallest iteration count (at the given dt and substeps) whose
            sensitivity on every load is at least ``threshold``, or None (none up to the
            search's limit).
        iterations_sensitivity: the smallest per-load sensitivity measured there.
        substeps: the smallest substep count (at the given dt and iterations; the same rest
            state as a frame step ``dt * substeps_given / substeps``) that does, or None.
        substeps_sensitivity: the smallest per-load sensitivity measured there.
        threshold: the sensitivity required.
        measured: ``[(what, value, smallest sensitivity), ...]``: every budget evaluated.
    """

    iterations: int | None
    iterations_sensitivity: float
    substeps: int | None
    substeps_sensitivity: float
    threshold: float
    measured: tuple

    def settings(self, settings: XPBDSettings, which: str = "iterations") -> XPBDSettings:
        """``settings`` with the proposed iteration (``which="iterations"``) or substep count."""
        if which not in ("iterations", "substeps"):
            raise ConfigError(f"which must be 'iterations' or 'substeps', got {which!r}")
        value = getattr(self, which)
        if value is None:
            raise ConfigError(f"the search found no {which} count that carries the load set")
        return dataclasses.replace(settings, **{which: int(value)})

    def text(self, settings: XPBDSettings) -> str:
        parts = []
        if self.iterations is not None:
            parts.append(f"iterations = {self.iterations} (dt = {float(settings.dt):.6g} s, substeps = {settings.substeps}; "
                         f"sensitivity {self.iterations_sensitivity:.3g})")
        if self.substeps is not None:
            parts.append(f"substeps = {self.substeps} (dt = {float(settings.dt):.6g} s, iterations = {settings.iterations}; "
                         f"or a frame step of {float(settings.dt) * settings.substeps / self.substeps:.4g} s with "
                         f"{settings.substeps} substep(s); sensitivity {self.substeps_sensitivity:.3g})")
        if not parts:
            return (f"no budget up to the search's limit reaches sensitivity {self.threshold:g} "
                    f"(measured: {', '.join(f'{w} {v}: {s:.3g}' for w, v, s in self.measured)})")
        return "a budget that carries it (measured): " + " or ".join(parts)


class _LoadSet:
    """The loads of a set stacked for one vmapped budgeted solve (all on one mesh)."""

    def __init__(self, mesh, model, material: Material, loads, tol: float, max_frames: int):
        if isinstance(loads, BudgetLoad):
            loads = (loads,)
        loads = tuple(loads)
        if not loads:
            raise ConfigError("loads is empty: give at least one BudgetLoad")
        n = int(np.shape(mesh.points)[0])
        for i, ld in enumerate(loads):
            if not isinstance(ld, BudgetLoad):
                raise ConfigError(f"loads[{i}] must be a BudgetLoad (see indentation_load), got {type(ld).__name__}")
            if np.shape(ld.bc.fixed) != (n, 3):
                raise ConfigError(f"loads[{i}] ({ld.label()}): its boundary conditions are for {np.shape(ld.bc.fixed)[0]} nodes, "
                                  f"the mesh has {n}: all loads of a set must be on the set's mesh")
            if not (np.isfinite(ld.depth) and ld.depth > 0):
                raise ConfigError(f"loads[{i}] ({ld.label()}): depth must be > 0 m, got {ld.depth!r}")
            if ld.youngs_modulus is not None and not (np.isfinite(ld.youngs_modulus) and ld.youngs_modulus > 0):
                raise ConfigError(f"loads[{i}] ({ld.label()}): youngs_modulus must be > 0 Pa, got {ld.youngs_modulus!r}")
        self.loads = loads
        self.model = model
        self.material = material
        self.youngs = np.array([float(material.youngs_modulus) if ld.youngs_modulus is None else ld.youngs_modulus for ld in loads])
        self.weights = np.stack([_reaction_weights(ld.bc) for ld in loads])
        self.bc = jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *[ld.bc for ld in loads])
        self.tol, self.max_frames = float(tol), int(max_frames)

    def references(self, ref_model, ref_kind: str) -> np.ndarray:
        """Reference force [N] of every load: the static solve of ``ref_model`` at the load's
        true modulus (the same observable)."""
        F_ref = np.empty(len(self.loads))
        for i, ld in enumerate(self.loads):
            sol = solve_static(ref_model, _with_values(self.material, ("youngs_modulus",), [self.youngs[i]]), ld.bc, throw=False)
            if not bool(sol.converged):
                raise ConvergenceError(f"the reference static solve ({ref_kind}) of load {ld.label()!r} did not converge")
            F_ref[i] = float(np.sum(self.weights[i] * np.asarray(sol.reaction)))
            if not np.isfinite(F_ref[i]) or F_ref[i] == 0.0:
                raise ConfigError(f"the reference force of load {ld.label()!r} is zero or not finite: nothing to calibrate against")
        return F_ref

    def forces(self, youngs, settings, poisson_ratio=None):
        """Budgeted reaction observable [N] of every load at moduli ``youngs`` (n,) [Pa] (and
        ``poisson_ratio``, default the material's), and whether each came to rest (traceable;
        forward-mode differentiable)."""
        nu = self.material.poisson_ratio if poisson_ratio is None else poisson_ratio
        return _set_forces(self.model, self.material, self.bc, jnp.asarray(self.weights), settings, self.tol, self.max_frames, youngs, nu)

    def arguments(self, settings: XPBDSettings, reference, rtol: float) -> dict:
        """The arguments of the set's :class:`_LoadSetProgram`: the material (every field an
        array, SI), the loads' true moduli ``youngs`` [Pa], their logs and the logs of the
        distinct moduli ``log_nodes``, the stacked prescribed ``displacement`` [m] and ``force``
        [N], the reaction ``weights``, the settings' arrays, ``tol``, ``max_frames``, the
        ``reference`` forces [N] and ``norm`` (``|reference| rtol``)."""
        return {
            "material": jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), self.material),
            "youngs": jnp.asarray(self.youngs),
            "log_youngs": jnp.log(jnp.asarray(self.youngs)),
            "log_nodes": jnp.log(jnp.asarray(np.unique(self.youngs))),
            "displacement": self.bc.displacement,
            "force": self.bc.force,
            "weights": jnp.asarray(self.weights),
            "settings": eqx.partition(settings, eqx.is_array)[0],
            "tol": jnp.asarray(self.tol, dtype=float),
            "max_frames": np.asarray(self.max_frames, dtype=np.int32),
            "reference": np.asarray(reference),
            "norm": np.abs(reference) * rtol,
        }

    def response(self, youngs, settings, poisson_ratio=None):
        """``(F (n,) [N], d log F / d log E (n,), came to rest (n,))`` at moduli ``youngs``."""
        youngs = jnp.asarray(youngs, dtype=float)
        (F, ok), (dF, _) = jax.jvp(lambda t: self.forces(youngs * jnp.exp(t), settings, poisson_ratio),
                                   (jnp.zeros(len(self.loads)),),
                                   (jnp.ones(len(self.loads)),))
        F, dF, ok = np.asarray(F), np.asarray(dF), np.asarray(ok)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(ok & (F != 0), dF / F, np.nan)
        return F, s, ok


def _set_forces(model, material: Material, bc: BoundaryConditions, weights, settings: XPBDSettings, tol, max_frames, youngs, nu):
    """Budgeted reaction observable ``sum(weights * reaction)`` [N] of every load of a stacked
    set (``bc`` and ``weights`` stacked on a leading load axis) at moduli ``youngs`` (n,) [Pa] and
    Poisson ratio ``nu``, and whether each came to rest (traceable; forward-mode differentiable)."""

    def one(E, b, w):
        m = _with_values(material, ("youngs_modulus", "poisson_ratio"), [E, nu])
        sol = xpbd_quasi_static(model, m, b, settings=settings, tol=tol, max_steps=max_frames, throw=False)
        return jnp.sum(w * sol.reaction), sol.converged

    return jax.vmap(one)(jnp.asarray(youngs), bc, weights)


class _LoadSetProgram:
    """The residuals of :func:`calibrate_for_load_set`'s joint fit for one structure, shared by
    every call of that structure (:func:`_shared_program`: the fit engine compiles its step once
    per key). Compiled in: the XPBD model, the loads' prescribed components, the settings'
    static configuration, the number of stiffness nodes and whether a Poisson ratio is fitted;
    the numbers are arguments (:meth:`_LoadSet.arguments`)."""

    def __init__(self, key, model, bc: BoundaryConditions, settings: XPBDSettings, n_nodes: int, effective_poisson: bool):
        self.key = key
        self.model = model
        self.bc = bc  # stacked; its prescribed components (displacement and force are arguments)
        self.settings = eqx.partition(settings, eqx.is_array)[1]
        self.n_nodes = int(n_nodes)
        self.effective_poisson = bool(effective_poisson)

    def card(self, v, args):
        """The card's moduli of the loads [Pa] and Poisson ratio at the fit's variables ``v``
        (one factor per stiffness node, then nu when fitted)."""
        n_f = self.n_nodes
        E = args["youngs"] * _nodal_factor(args["log_nodes"], jnp.log(v[:n_f]), args["log_youngs"])
        return E, (v[n_f] if self.effective_poisson else args["material"].poisson_ratio)

    def residual_fn(self, v, data):
        """Per-load relative force error in units of ``rtol``; NaN where XPBD did not come to rest."""
        E, nu = self.card(v, data)
        settings = eqx.combine(data["settings"], self.settings)
        bc = eqx.tree_at(lambda b: (b.displacement, b.force), self.bc, (data["displacement"], data["force"]))
        y, ok = _set_forces(self.model, data["material"], bc, data["weights"], settings, data["tol"], data["max_frames"], E, nu)
        r = (y - data["reference"]) / data["norm"]
        return jnp.where(ok, r, jnp.nan), y


def _reference_model(mesh, model, model_kind: str, reference):
    """``(model, kind)`` of the reference: None (the XPBD model itself), a model kind or an
    :class:`~difftissue.models.ElasticModel`."""
    if reference is None:
        return model, model_kind
    if isinstance(reference, str):
        if reference not in MESH_MODELS:
            raise ModelError(f"reference must be one of {MESH_MODELS} or an ElasticModel, got {reference!r}")
        return make_model(mesh, reference), reference
    if isinstance(reference, ElasticModel):
        return reference, type(reference).__name__
    raise ConfigError(f"reference must be None, a model kind or an ElasticModel, got {type(reference).__name__}")


def _nodal_factor(log_nodes, log_factors, log_e):
    """``f(E)`` with ``log f`` piecewise linear in ``log E`` through ``(log_nodes, log_factors)``
    (constant beyond the ends; one node: that factor). Traceable."""
    if np.size(log_nodes) == 1:
        return jnp.exp(jnp.asarray(log_factors)[0]) * jnp.ones_like(jnp.asarray(log_e, dtype=float))
    return jnp.exp(jnp.interp(log_e, log_nodes, log_factors))


def _scaled_settings(settings: XPBDSettings, what: str, value: int) -> XPBDSettings:
    """The settings a search evaluates: ``iterations = value``, or ``value`` substeps per frame
    as frames of ``dt * substeps / value`` (the same fully damped rest state; dt is traced, so no
    recompilation)."""
    if what == "iterations":
        return dataclasses.replace(settings, iterations=int(value))
    return dataclasses.replace(settings, dt=float(settings.dt) * settings.substeps / int(value))


def _smallest_passing(measure, start: int, max_factor: int):
    """Smallest integer ``v`` in ``(start, start * max_factor]`` with ``measure(v) >= 0`` (the
    margin over the threshold), by doubling then bisection (assumes the margin grows with v).
    Returns ``(v or None, margin at v)``."""
    lo, hi, hi_m = start, None, -np.inf
    v = start
    while v < start * max_factor:
        v = min(2 * v, start * max_factor)
        m = measure(v)
        if m >= 0:
            hi, hi_m = v, m
            break
        lo = v
    if hi is None:
        return None, hi_m
    while hi - lo > 1:
        mid = (lo + hi) // 2
        m = measure(mid)
        if m >= 0:
            hi, hi_m = mid, m
        else:
            lo = mid
    return hi, hi_m


def propose_budget(mesh, model_kind: str, material: Material, loads, settings: XPBDSettings, *, reference=None,
                   threshold: float = MIN_SENSITIVITY, max_factor: int = 64, search=("iterations", "substeps"),
                   tol: float = 1e-10, max_frames: int = 5000, _set: _LoadSet | None = None,
                   _reference: np.ndarray | None = None) -> BudgetProposal:
    """The smallest budget that carries every load of the set: a measured search (doubling from
    the given count, then bisection) over the iteration count at the given dt and substeps, and
    over the substep count at the given dt and iterations, for a sensitivity
    ``d log F / d log E >= threshold`` on every load both at its true modulus and at the
    modulus a card would need there (one Newton step in ``log E`` from the true modulus to the
    load's reference force: the card is usually stiffer, where the budget saturates sooner),
    with budgeted solves that come to rest.

    Args:
        mesh, model_kind, material, loads, settings, reference: as for
            :func:`calibrate_for_load_set`.
        threshold: the sensitivity required (default :data:`MIN_SENSITIVITY`).
        max_factor: search up to ``max_factor`` times the given count.
        search: which counts to search (``"iterations"``, ``"substeps"``).
        tol, max_frames: of the quasi-static XPBD solves.

    Returns:
        A :class:`BudgetProposal` with every budget measured.
    """
    if not (0 < threshold < 1):
        raise ConfigError(f"threshold must lie in (0, 1), got {threshold!r}")
    if not (isinstance(max_factor, (int, np.integer)) and max_factor >= 2):
        raise ConfigError(f"max_factor must be an integer >= 2, got {max_factor!r}")
    search = (search,) if isinstance(search, str) else tuple(search)
    for w in search:
        if w not in ("iterations", "substeps"):
            raise ConfigError(f"search: {w!r} is no budget count; choose from ('iterations', 'substeps')")
    if _set is None:
        model = make_model(mesh, model_kind)
        ls = _LoadSet(mesh, model, material, loads, tol, max_frames)
        F_ref = ls.references(*_reference_model(mesh, model, model_kind, reference))
    else:
        ls, F_ref = _set, _reference
    measured = []

    def smallest(s, ok):
        return float(np.min(s)) if np.all(ok) and np.all(np.isfinite(s)) else -np.inf

    def margin(what):
        def m(value):
            st = _scaled_settings(settings, what, value)
            F, s, ok = ls.response(ls.youngs, st)
            smin = smallest(s, ok)
            if smin >= threshold:
                # the modulus each load's own card would need (one Newton step in log E), within e^+-5
                step = np.clip(np.log(F_ref / F) / s, -5.0, 5.0)
                _, s_card, ok_card = ls.response(ls.youngs * np.exp(step), st)
                smin = min(smin, smallest(s_card, ok_card))
            measured.append((what, int(value), smin))
            return smin - threshold
        return m

    found = {}
    for what in ("iterations", "substeps"):
        if what in search:
            v, m = _smallest_passing(margin(what), int(getattr(settings, what)), int(max_factor))
            found[what] = (v, m + threshold if v is not None else float("nan"))
        else:
            found[what] = (None, float("nan"))
    return BudgetProposal(found["iterations"][0], found["iterations"][1], found["substeps"][0], found["substeps"][1],
                          float(threshold), tuple(measured))


@dataclasses.dataclass(frozen=True)
class LoadSetCalibration:
    """Result of :func:`calibrate_for_load_set`: one budget card for a set of loads.

    The card's effective modulus for a tissue of modulus ``E`` is ``E_eff = E * f(E)``
    (:meth:`effective_youngs_modulus`): ``log f`` piecewise linear in ``log E`` through the
    fitted ``factors`` at the set's distinct moduli ``stiffness_nodes`` (one factor when the set
    has one modulus); with ``effective_poisson`` the card also holds an effective Poisson
    ratio; the other material fields are the true ones.

    Attributes:
        factors: ``f`` at each node [-]; factor: the first (the only one for one modulus).
        stiffness_nodes: the set's distinct moduli [Pa], ascending.
        poisson_ratio: the card's Poisson ratio [-] (the true one unless fitted).
        material: the true material of the calibration (the loads' moduli replace its E).
        setting: ``{"dt", "substeps", "iterations", "method"}`` the card is valid for.
        model_kind, reference_kind: the XPBD model and the reference's model.
        mesh: ``{"n_nodes", "n_tets", "cell_size"}`` of the mesh calibrated on (the card is
            valid at that resolution only; cell size by :func:`cell_size`) [m].
        loads: one dict per load: ``name``, ``shape``, ``depth`` [m], ``youngs_modulus`` [Pa],
            ``reference``, ``naive``, ``calibrated`` (forces [N]), ``naive_error``, ``error``
            (signed relative force errors), ``sensitivity_naive``, ``sensitivity``
            (``d log F / d log E`` at the true and at the card's modulus).
        max_error: largest ``|error|`` over the set: the card's residual error.
        threshold: the saturation threshold the sensitivities were checked against.
        steps, jacobian, covariance, standard_errors, dof: the fit engine's statistics of the
            card's parameters (Jacobian of the relative force mismatch).
    """

    factors: tuple
    stiffness_nodes: tuple
    poisson_ratio: float
    material: Material
    setting: dict
    model_kind: str
    reference_kind: str
    mesh: dict
    loads: tuple
    max_error: float
    threshold: float
    steps: int
    jacobian: np.ndarray
    covariance: np.ndarray
    standard_errors: dict
    dof: int

    @property
    def factor(self) -> float:
        return float(self.factors[0])

    def effective_youngs_modulus(self, youngs_modulus) -> float:
        """The card's effective modulus [Pa] for a tissue of modulus ``youngs_modulus`` [Pa]
        (no range check; :meth:`effective_material` checks; outside the nodes the end factor)."""
        E = float(youngs_modulus)
        return float(E * _nodal_factor(np.log(self.stiffness_nodes), np.log(self.factors), np.log(E)))

    @property
    def validity(self) -> dict:
        """What the card was calibrated over: the setting, the mesh, the shapes, the depth and
        modulus ranges, and the residual error of every load of the set."""
        depths = [ld["depth"] for ld in self.loads]
        youngs = [ld["youngs_modulus"] for ld in self.loads]
        return {
            "setting": dict(self.setting), "mesh": dict(self.mesh), "model_kind": self.model_kind,
            "shapes": sorted({ld["shape"] for ld in self.loads}),
            "depth_range": [min(depths), max(depths)], "youngs_modulus_range": [min(youngs), max(youngs)],
            "residual_error": {ld["name"]: ld["error"] for ld in self.loads}, "max_residual_error": self.max_error,
            "min_sensitivity": min(ld["sensitivity"] for ld in self.loads), "sensitivity_threshold": self.threshold,
        }

    def check(self, *, shape: str, depth: float, youngs_modulus: float | None = None, settings: XPBDSettings | None = None,
              mesh=None, extrapolate: bool = False) -> None:
        """Refuse a use outside the calibrated range.

        Raises:
            BudgetRangeError: another setting or mesh, a shape not in the set (always), or a
                depth or modulus outside the set's range (unless ``extrapolate``).

        Warns:
            BudgetExtrapolationWarning: depth or modulus outside the range with ``extrapolate=True``.
        """

        v = self.validity
        if settings is not None:
            got = {"dt": float(settings.dt), "substeps": int(settings.substeps), "iterations": int(settings.iterations),
                   "method": str(settings.method)}
            diff = [k for k in got if (not math.isclose(got[k], self.setting[k], rel_tol=1e-9) if k == "dt" else got[k] != self.setting[k])]
            if diff:
                raise BudgetRangeError(f"budget card calibrated for {self.setting}, used with {got}: an effective modulus is "
                                       f"valid only for its own XPBD setting ({', '.join(diff)} differ); recalibrate")
        if mesh is not None:
            n_nodes, n_tets, h = int(np.shape(mesh.points)[0]), int(np.shape(mesh.tets)[0]), cell_size(mesh)
            if (n_nodes, n_tets) != (self.mesh["n_nodes"], self.mesh["n_tets"]) or not math.isclose(h, self.mesh["cell_size"], rel_tol=1e-6):
                raise BudgetRangeError(f"budget card calibrated on a mesh of {self.mesh['n_nodes']} nodes, {self.mesh['n_tets']} tets, "
                                       f"cell size {self.mesh['cell_size']:.4g} m; used on {n_nodes} nodes, {n_tets} tets, cell size "
                                       f"{h:.4g} m: the budget's bias depends on the cell size; recalibrate on this mesh")
        if shape not in v["shapes"]:
            raise BudgetRangeError(f"budget card calibrated for the indenter shapes {v['shapes']}, used with {shape!r}: "
                                   "add loads of that shape to the calibration set")
        out = []
        lo, hi = v["depth_range"]
        if not (lo * (1 - 1e-9) <= depth <= hi * (1 + 1e-9)):
            out.append(f"depth {depth:.4g} m outside the calibrated {lo:.4g} ... {hi:.4g} m")
        if youngs_modulus is not None:
            lo, hi = v["youngs_modulus_range"]
            if not (lo * (1 - 1e-9) <= youngs_modulus <= hi * (1 + 1e-9)):
                out.append(f"Young's modulus {youngs_modulus:.4g} Pa outside the calibrated {lo:.4g} ... {hi:.4g} Pa")
        if out:
            msg = ("budget card used outside its calibrated range: " + "; ".join(out)
                   + f" (residual error inside the range at most {100 * self.max_error:.3g} %; outside it is unmeasured)")
            if not extrapolate:
                raise BudgetRangeError(msg + "; add such loads to the calibration set, or pass extrapolate=True to use it anyway")
            warnings.warn(msg, BudgetExtrapolationWarning, stacklevel=3)

    def effective_material(self, *, shape: str, depth: float, youngs_modulus: float | None = None,
                           settings: XPBDSettings | None = None, mesh=None, extrapolate: bool = False) -> Material:
        """The material to give the budgeted simulator for a tissue of modulus ``youngs_modulus``
        [Pa] (default: the calibration's) under an indenter ``shape`` pushed ``depth`` [m],
        after :meth:`check` (which refuses a use outside the calibrated range)."""
        E = float(self.material.youngs_modulus) if youngs_modulus is None else float(youngs_modulus)
        self.check(shape=shape, depth=depth, youngs_modulus=E, settings=settings, mesh=mesh, extrapolate=extrapolate)
        return _with_values(self.material, ("youngs_modulus", "poisson_ratio"), [self.effective_youngs_modulus(E), self.poisson_ratio])

    def card(self) -> dict:
        """The budget card as a JSON-serialisable dict: the effective-modulus law, the setting and
        the validity range with the residual error of every load."""
        return {
            "kind": "difftissue budget card",
            "effective_youngs_modulus": "E * f(E), log f piecewise linear in log E through (stiffness_nodes, factors)",
            "stiffness_nodes": list(self.stiffness_nodes), "factors": list(self.factors),
            "poisson_ratio": self.poisson_ratio, "true_poisson_ratio": float(self.material.poisson_ratio),
            "density": float(self.material.density),
            "model_kind": self.model_kind, "reference_kind": self.reference_kind,
            "validity": self.validity,
            "loads": [{k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in ld.items()} for ld in self.loads],
            "observable": "reaction on the moved nodes along their summed prescribed displacement [N], at the rest state of "
                          "standard XPBD (multipliers reset every substep, fully damped frames)",
        }


def calibrate_for_load_set(
    mesh,
    model_kind: str,
    material: Material,
    loads,
    settings: XPBDSettings,
    *,
    reference=None,
    effective_poisson: bool = False,
    threshold: float = MIN_SENSITIVITY,
    propose: bool = True,
    max_steps: int = 20,
    rtol: float = 1e-3,
    tol: float = 1e-10,
    max_frames: int = 5000,
    max_log_step: float = 1.0,
) -> LoadSetCalibration:
    """One budget card for the set of loads a simulator meets (depths, indenter shapes, a
    stiffness range) at its cell size and budget.

    Every load's reference is the static solve of ``reference`` at the load's true modulus; the
    card ``E_eff = E * f(E)`` (``log f`` piecewise linear in ``log E`` through one factor per
    distinct modulus of the set; optionally an effective Poisson ratio) is fitted jointly by the fit
    engine (Levenberg--Marquardt on the per-load relative force errors, Jacobian through the
    unrolled XPBD loop) so that the budgeted XPBD force of every load at its card modulus
    matches its reference; the per-load residual errors are the card's validity
    (:attr:`LoadSetCalibration.validity`). With one load (and one modulus) this is
    :func:`calibrate_for_budget` with the reaction observable (the same modulus).

    Before the fit and at the card, the sensitivity ``d log F / d log E`` of every load is
    measured (forward mode); below ``threshold`` the budget is saturated: the force hardly
    follows the modulus and no card exists, so a :class:`~difftissue.errors.BudgetSaturationError`
    is raised with the budget that carries the set (:func:`propose_budget`, when ``propose``).

    Args:
        mesh: the simulator's mesh (all loads on it).
        model_kind: ``"springs_volume"`` or ``"stable_neo_hookean"``.
        material: the true material (its E for loads without their own modulus).
        loads: :class:`BudgetLoad` objects (e.g. from :func:`indentation_load`).
        settings: the simulator's :class:`~difftissue.solvers.xpbd.XPBDSettings` (standard XPBD,
            ``warm_start=False``).
        reference: as for :func:`calibrate_for_budget`.
        effective_poisson: also fit one effective Poisson ratio for the whole set (it can
            balance shapes that load the volume term differently, e.g. a platen and a punch).
        threshold: the saturation threshold (default :data:`MIN_SENSITIVITY` = 0.5).
        propose: search a budget when saturated (costs several budgeted solves of the set):
            True (iteration and substep counts), False, or which counts to search (see
            :func:`propose_budget`).
        max_steps: optimiser steps after the start's evaluation.
        rtol: stop early when the 2-norm of the per-load relative errors is at most this.
        tol, max_frames, max_log_step: as for :func:`calibrate_for_budget` (the factor stays
            within ``exp(+-max_log_step * max_steps)``).

    Raises:
        ConfigError: bad loads or options; ModelError: as for :func:`calibrate_for_budget`.
        BudgetSaturationError: the budget cannot carry a load of the set (``.proposal``).
        ConvergenceError: a reference or budgeted solve did not come to rest.
    """

    if not isinstance(settings, XPBDSettings):
        raise ConfigError(f"settings must be an XPBDSettings, got {type(settings).__name__}")
    if settings.warm_start:
        raise ConfigError("settings.warm_start=True makes quasi-static XPBD converge to the static answer for any "
                          "budget; calibrate the standard real-time setting (warm_start=False)")
    if not isinstance(material, Material):
        raise ConfigError(f"material must be a Material, got {type(material).__name__}")
    if model_kind not in ("springs_volume", "stable_neo_hookean"):
        raise ModelError(f"model_kind must be an XPBD model ('springs_volume' or 'stable_neo_hookean'), got {model_kind!r}")
    if np.ndim(material.youngs_modulus) != 0:
        raise ConfigError("material.youngs_modulus must be a scalar (one value per region is not supported)")
    if not (0 < threshold < 1):
        raise ConfigError(f"threshold must lie in (0, 1), got {threshold!r}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 0):
        raise ConfigError(f"max_steps must be an integer >= 0, got {max_steps!r}")
    if not rtol > 0 or not max_log_step > 0:
        raise ConfigError(f"rtol and max_log_step must be > 0, got {rtol!r}, {max_log_step!r}")
    model = make_model(mesh, model_kind)
    ref_model, ref_kind = _reference_model(mesh, model, model_kind, reference)
    ls = _LoadSet(mesh, model, material, loads, tol, max_frames)
    n = len(ls.loads)

    F_ref = ls.references(ref_model, ref_kind)

    def saturated(s, ok, where):
        bad = [i for i in range(n) if not (ok[i] and np.isfinite(s[i]) and s[i] >= threshold)]
        if not bad:
            return
        if not all(ok):
            why = "does not come to rest on " + ", ".join(ls.loads[i].label() for i in range(n) if not ok[i])
        else:
            why = ("is saturated: d log F / d log E = " + ", ".join(f"{s[i]:.3g} ({ls.loads[i].label()})" for i in bad)
                   + f" below {threshold:g} (1 when converged): the iteration budget cannot carry the load at this step, "
                   "the force hardly follows the modulus and no effective modulus exists")
        msg = (f"XPBD at dt = {float(settings.dt):.6g} s, substeps = {settings.substeps}, iterations = {settings.iterations} "
               f"({settings.method}) on cells of {cell_size(mesh):.4g} m {why} [{where}]")
        proposal = None
        if propose:
            search = ("iterations", "substeps") if propose is True else propose
            proposal = propose_budget(mesh, model_kind, material, ls.loads, settings, threshold=threshold, search=search,
                                      _set=ls, _reference=F_ref)
            msg += "; " + proposal.text(settings)
        raise BudgetSaturationError(msg, sensitivity=s, proposal=proposal)

    F_naive, s_naive, ok = ls.response(ls.youngs, settings)
    saturated(s_naive, ok, "at the true modulus")

    # ------------------------------------------------------------------ the joint fit
    nodes = np.unique(ls.youngs)
    labels = ("factor",) if nodes.size == 1 else tuple(f"factor at E = {E:.6g} Pa" for E in nodes)
    reach = max_log_step * max(int(max_steps), 1)
    transforms = [ScaledLogit(math.exp(-reach), math.exp(reach)) for _ in labels]
    if effective_poisson:
        if not (_NU_LO < float(material.poisson_ratio) < _NU_HI):
            raise ConfigError(f"poisson_ratio must lie in ({_NU_LO}, {_NU_HI}) to be calibrated")
        labels += ("poisson_ratio",)
        transforms.append(ScaledLogit(_NU_LO, _NU_HI))
    n_f = nodes.size
    # The fit's fields by position (the labels name the moduli, which are arguments): sets of
    # one structure at other moduli share the compiled step.
    fields = tuple(f"factor {i}" for i in range(n_f)) + (("poisson_ratio",) if effective_poisson else ())
    program = _shared_program(lambda key: _LoadSetProgram(key, model, ls.bc, settings, n_f, effective_poisson),
                              (model, ls.bc.fixed), settings, "calibrate_for_load_set", type(model), n_f, bool(effective_poisson))
    data = ls.arguments(settings, F_ref, rtol)
    problem = ResidualProblem(program.residual_fn, fields, transforms, n, data=data, key=program.key)
    start = np.array([1.0] * n_f + ([float(material.poisson_ratio)] if effective_poisson else []))
    fit = least_squares(problem, start, method="levenberg_marquardt", max_steps=max_steps + 1,
                        stop=lambda loss: math.sqrt(2.0 * loss) <= 1.0)
    values = np.array([fit.values[f] for f in fields])
    E_card, nu_card = program.card(jnp.asarray(values), data)
    E_card = np.asarray(E_card)
    nu_card = float(nu_card)
    # The forces and sensitivities at the card from the fit's own evaluation there (its
    # predictions are the budgeted forces, its Jacobian d r / d factor = d F / d factor / norm;
    # every load's modulus is a stiffness node, so d log E_i / d log factor_k is 1 for its own
    # node and 0 for the others): no second budgeted solve of the set. A load that did not come
    # to rest has a NaN residual there.
    F_cal = np.asarray(fit.predictions, dtype=float)
    dF = np.asarray(fit.jacobian, dtype=float)[:, :n_f] * np.asarray(data["norm"])[:, None] * values[None, :n_f]
    ok = np.isfinite(np.asarray(fit.residuals))
    with np.errstate(divide="ignore", invalid="ignore"):
        s_cal = np.where(ok & (F_cal != 0), np.sum(dF, axis=1) / F_cal, np.nan)
    if not all(ok):
        raise ConvergenceError("the budgeted XPBD solve at the card's moduli did not come to rest on "
                               + ", ".join(ls.loads[i].label() for i in range(n) if not ok[i]) + "; raise max_frames")
    saturated(s_cal, ok, "at the card's modulus")
    err = F_cal / F_ref - 1.0
    rows = tuple({
        "name": ld.label(), "shape": ld.shape, "depth": float(ld.depth), "youngs_modulus": float(ls.youngs[i]),
        "card_youngs_modulus": float(E_card[i]), "reference": float(F_ref[i]), "naive": float(F_naive[i]),
        "calibrated": float(F_cal[i]), "naive_error": float(F_naive[i] / F_ref[i] - 1.0), "error": float(err[i]),
        "sensitivity_naive": float(s_naive[i]), "sensitivity": float(s_cal[i]),
    } for i, ld in enumerate(ls.loads))
    return LoadSetCalibration(
        factors=tuple(float(v) for v in values[:n_f]), stiffness_nodes=tuple(float(E) for E in nodes), poisson_ratio=nu_card,
        material=material,
        setting={"dt": float(settings.dt), "substeps": int(settings.substeps), "iterations": int(settings.iterations),
                 "method": str(settings.method)},
        model_kind=model_kind, reference_kind=ref_kind,
        mesh={"n_nodes": int(np.shape(mesh.points)[0]), "n_tets": int(np.shape(mesh.tets)[0]), "cell_size": cell_size(mesh)},
        loads=rows, max_error=float(np.max(np.abs(err))), threshold=float(threshold), steps=max(fit.steps - 1, 0),
        jacobian=np.asarray(fit.jacobian) * rtol, covariance=np.asarray(fit.covariance),
        standard_errors={label: fit.standard_errors[f] for label, f in zip(labels, fields)}, dof=fit.dof,
    )


# ============================================================================ load sets from TOML
#: Keys of a load-set file's ``[budget]`` table and of each ``[[budget.loads]]`` entry.
LOAD_SET_KEYS = ("length_unit", "youngs_moduli", "reference", "effective_poisson", "propose", "max_steps", "loads")
LOAD_KEYS = ("shape", "depth", "radius", "youngs_moduli", "length_unit", "name")


@dataclasses.dataclass(frozen=True)
class LoadSetSpec:
    """A load set read from a TOML ``[budget]`` table (:func:`parse_load_set`).

    Attributes:
        loads: the :class:`BudgetLoad` objects on the given mesh (one per load and modulus).
        options: keyword arguments for :func:`calibrate_for_load_set` given in the table
            (``effective_poisson``, ``propose``, ``max_steps``).
        reference: the reference model kind given (``budget.reference``), or None (the caller's
            default).
        youngs_modulus_range: ``(lo, hi)`` [Pa] of the loads' moduli.
    """

    loads: tuple
    options: dict
    reference: str | None
    youngs_modulus_range: tuple


def _ls_fail(where: str, msg: str):
    raise ConfigError(f"{where}: {msg}")


def _ls_number(value, where: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _ls_fail(where, f"must be a number in {unit}, got {value!r}")
    if not value > 0:
        _ls_fail(where, f"must be > 0 {unit}, got {value!r}")
    return float(value)


def _ls_unit(value, where: str) -> float:
    if not isinstance(value, str) or value not in LENGTH_UNITS:
        _ls_fail(where, f"must be one of {', '.join(repr(u) for u in LENGTH_UNITS)}, got {value!r}")
    return LENGTH_UNITS[value]


def _ls_moduli(value, where: str) -> list:
    if not isinstance(value, list) or not value:
        _ls_fail(where, f"must be a non-empty list of Young's moduli in Pa, got {value!r}")
    return sorted({_ls_number(v, f"{where}[{i}]", "Pa") for i, v in enumerate(value)})


def _ls_keys(table, where: str, allowed) -> None:
    unknown = [k for k in table if k not in allowed]
    if unknown:
        _ls_fail(where, f"unknown key {unknown[0]!r}; allowed: {', '.join(allowed)}")


def parse_load_set(raw, mesh, material: Material, *, where: str = "budget") -> LoadSetSpec:
    """The load set of a TOML ``[budget]`` table (``raw``: the table as a mapping) on ``mesh``,
    for the tissue ``material``, checked before anything is solved.

    The table (lengths in metres unless ``length_unit`` says otherwise, moduli in Pa)::

        [budget]
        length_unit = "mm"             # of depth and radius below ("m", "cm", "mm", "um"; default "m")
        youngs_moduli = [5e3, 10e3]    # tissue moduli [Pa] the card covers (default: the material's E)
        reference = "fem_neo_hookean"  # reference model (default: the caller's choice)
        effective_poisson = false      # also fit one effective Poisson ratio
        propose = true                 # when saturated, search a budget (or ["substeps"], ["iterations"], false)
        max_steps = 20                 # optimiser steps

        [[budget.loads]]
        shape = "flat_punch"           # "flat_punch", "platen" or "sphere" (indentation_load)
        depth = 0.1                    # indenter travel (length_unit)
        radius = 3                     # punch / sphere radius (length_unit); not for a platen
        # youngs_moduli = [10e3]       # this load's moduli [Pa] (default: the table's)
        # length_unit, name            # this load's own unit and label

    Every load is built by :func:`indentation_load` on ``mesh`` (top face indented, base
    clamped) once per modulus of its ``youngs_moduli``.

    Raises:
        ConfigError: unknown or missing keys, values of the wrong type, a unit that is not a
            length unit, a non-positive depth, radius or modulus, a radius given to a platen
            or missing for a punch or sphere, a depth not less than the mesh's height or an
            indenter that covers the whole top face (both usually lengths in the wrong unit),
            no top node under an indenter. The message starts with the key's path
            (``budget.loads[1].depth: ...``).
    """
    from collections.abc import Mapping

    if not isinstance(raw, Mapping):
        _ls_fail(where, f"must be a table, got {raw!r}")
    _ls_keys(raw, where, LOAD_SET_KEYS)
    if "loads" not in raw:
        _ls_fail(where, "missing key 'loads': one or more [[budget.loads]] tables (shape, depth, radius)")
    unit = _ls_unit(raw["length_unit"], f"{where}.length_unit") if "length_unit" in raw else 1.0
    E0 = float(material.youngs_modulus)
    moduli = _ls_moduli(raw["youngs_moduli"], f"{where}.youngs_moduli") if "youngs_moduli" in raw else None
    options = {}
    if "effective_poisson" in raw:
        if not isinstance(raw["effective_poisson"], bool):
            _ls_fail(f"{where}.effective_poisson", f"must be true or false, got {raw['effective_poisson']!r}")
        options["effective_poisson"] = raw["effective_poisson"]
    if "propose" in raw:
        p = raw["propose"]
        if isinstance(p, list):
            if not p or any(w not in ("iterations", "substeps") for w in p) or len(set(p)) != len(p):
                _ls_fail(f"{where}.propose", f"must be true, false or a list of 'iterations' and/or 'substeps', got {p!r}")
            options["propose"] = tuple(p)
        elif isinstance(p, bool):
            options["propose"] = p
        else:
            _ls_fail(f"{where}.propose", f"must be true, false or a list of 'iterations' and/or 'substeps', got {p!r}")
    if "max_steps" in raw:
        m = raw["max_steps"]
        if isinstance(m, bool) or not isinstance(m, int) or m < 0:
            _ls_fail(f"{where}.max_steps", f"must be an integer >= 0, got {m!r}")
        options["max_steps"] = int(m)
    reference = None
    if "reference" in raw:
        if raw["reference"] not in MESH_MODELS:
            _ls_fail(f"{where}.reference", f"must be one of {', '.join(MESH_MODELS)}, got {raw['reference']!r}")
        reference = raw["reference"]
    entries = raw["loads"]
    if not isinstance(entries, list) or not entries:
        _ls_fail(f"{where}.loads", "must be one or more [[budget.loads]] tables (shape, depth, radius)")
    p = np.asarray(mesh.points)
    height = float(np.ptp(p[:, 2]))
    half = 0.5 * math.hypot(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1])))  # centre to the top face's corners
    loads = []
    for i, e in enumerate(entries):
        w = f"{where}.loads[{i}]"
        if not isinstance(e, Mapping):
            _ls_fail(w, f"must be a table (shape, depth, radius), got {e!r}")
        _ls_keys(e, w, LOAD_KEYS)
        for k in ("shape", "depth"):
            if k not in e:
                _ls_fail(w, f"missing key {k!r}" + (f" (one of {', '.join(SHAPES)})" if k == "shape" else " (indenter travel)"))
        shape = e["shape"]
        if shape not in SHAPES:
            _ls_fail(f"{w}.shape", f"must be one of {', '.join(SHAPES)}, got {shape!r}")
        f = _ls_unit(e["length_unit"], f"{w}.length_unit") if "length_unit" in e else unit
        uname = e.get("length_unit", raw.get("length_unit", "m"))
        depth = _ls_number(e["depth"], f"{w}.depth", uname) * f
        if depth >= height:
            _ls_fail(f"{w}.depth", f"{depth:.4g} m is not less than the mesh's height {height:.4g} m (lengths are in "
                                   f"{uname!r}; set length_unit, e.g. length_unit = \"mm\", if they are not)")
        radius = None
        if shape == "platen":
            if "radius" in e:
                _ls_fail(f"{w}.radius", "a platen moves the whole top face: it has no radius (use shape = \"flat_punch\")")
        else:
            if "radius" not in e:
                _ls_fail(w, f"missing key 'radius' (the {shape}'s radius)")
            radius = _ls_number(e["radius"], f"{w}.radius", uname) * f
            reach = radius if shape == "flat_punch" else math.sqrt(2.0 * radius * depth)
            if reach >= half * (1 - 1e-9):
                what = f"radius {reach:.4g} m" if shape == "flat_punch" else f"contact radius sqrt(2 radius depth) = {reach:.4g} m"
                _ls_fail(f"{w}.radius", f"the {shape}'s {what} covers the "
                                        f"whole top face (half-diagonal {half:.4g} m): lengths are in {uname!r}; set length_unit if "
                                        "they are not, or use shape = \"platen\"")
        name = ""
        if "name" in e:
            if not isinstance(e["name"], str) or not e["name"]:
                _ls_fail(f"{w}.name", f"must be a non-empty string, got {e['name']!r}")
            name = e["name"]
        own = _ls_moduli(e["youngs_moduli"], f"{w}.youngs_moduli") if "youngs_moduli" in e else moduli
        for E in (own or [None]):
            label = (name or f"{shape} {1e3 * depth:g} mm") + ("" if E is None or (name and len(own) == 1) else f" E {E:.4g} Pa")
            try:
                loads.append(indentation_load(mesh, shape, depth, radius=radius, youngs_modulus=E, name=label))
            except ConfigError as err:
                raise ConfigError(f"{w}: {err}") from None
    youngs = [E0 if ld.youngs_modulus is None else ld.youngs_modulus for ld in loads]
    return LoadSetSpec(tuple(loads), options, reference, (min(youngs), max(youngs)))


def read_load_set(path, mesh, material: Material) -> LoadSetSpec:
    """:func:`parse_load_set` of the ``[budget]`` table of the TOML file ``path`` (no other
    top-level key)."""
    path = Path(path)
    raw = read_toml(path, "load-set")
    _ls_keys(raw, str(path), ("budget",))
    if "budget" not in raw:
        _ls_fail(str(path), "missing the [budget] table (with one or more [[budget.loads]])")
    try:
        return parse_load_set(raw["budget"], mesh, material)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
