"""The fit problem: the :class:`Scenario` protocol and :class:`FitProblem` (residuals and loss
as pure functions of the unconstrained vector ``u``).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from typing import Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import FitError
from ..materials import FIELD_UNITS, Material, MaterialParameterization, Transform, material_fields
# the structure-key formula (shared with the scenarios' compiled protocols, which must not
# import fit); its names stay importable from here
from ..structure_keys import DATA_ATTRIBUTES, data_leaf_indices, hash_scenario_leaves  # noqa: F401


#: SI unit of every material field ("1" for dimensionless).
UNITS: dict[str, str] = FIELD_UNITS


def unit_text(unit: str) -> str:
    """Unit for prose: empty for dimensionless ("1")."""
    return "" if unit == "1" else unit


#: Loss functions understood by :func:`fit` (scipy.optimize.least_squares names).
LOSSES = ("linear", "soft_l1", "huber")


# ============================================================================ protocol
@runtime_checkable
class Scenario(Protocol):
    """One experiment to fit: what it measured and how the model predicts it.

    Attributes:
        name: unique name of the scenario (used in outputs and plots).
        observed: measured values, shape ``(n,)``, SI units (N, m, Pa, ...).
        sigma: measurement scale, shape ``(n,)``, same unit as ``observed``; residuals are
            divided by it (weight ``1 / sigma``). Use the noise standard deviation when known.
        abscissa: x values for plots, shape ``(n,)``, SI units (e.g. depth in m).
        x_label: axis label of ``abscissa`` including its unit, e.g. ``"depth [m]"``.
        y_label: axis label of ``observed`` including its unit, e.g. ``"force [N]"``.

    Methods:
        predict(material): model prediction, shape ``(n,)``, same unit as ``observed``. Must be
            pure, jittable and differentiable in the material's fields.

    Optional: a scenario with parameters of its own that a fit can fit alongside the material
    (e.g. an indentation's ``contact_offset``) names them in ``fittable_parameters()``:
    ``{name: {"unit": str, "transform": Transform, "start": float, "scale": float}}`` (SI;
    ``scale`` [unit] is the natural size of the parameter, the floor of its relative standard
    error), and its ``predict(material, **{name: value})`` takes them as keyword arguments
    (differentiable in them). :func:`~difftissue.fit.fit` fits them where its
    ``scenario_parameters`` asks for them (:class:`FitParameterization`).
    """

    name: str
    observed: np.ndarray
    sigma: np.ndarray
    abscissa: np.ndarray
    x_label: str
    y_label: str

    def predict(self, material: Material) -> jax.Array: ...


# ============================================================================ parameters
class FitParameterization(eqx.Module):
    """The fitted parameters of a problem with scenario parameters: the material's fields
    (through their transforms, as :class:`~difftissue.materials.MaterialParameterization`)
    followed by parameters of the scenarios themselves (e.g. ``"indent.contact_offset"``).

    The unconstrained vector ``u`` holds the material fields first (in the order of the
    material parameterization), then the scenario parameters in the order they were asked for.
    ``fields``, ``transforms``, :meth:`pack`, :meth:`values` and :meth:`unpack` follow
    :class:`~difftissue.materials.MaterialParameterization` (``unpack`` gives the material
    only); :meth:`scenario_values` the scenario parameters' values.
    """

    fields: tuple[str, ...] = eqx.field(static=True)
    transforms: tuple[Transform, ...]
    material_fields: tuple[str, ...] = eqx.field(static=True)
    #: per scenario parameter: (scenario index, scenario name, parameter name)
    scenario_keys: tuple[tuple[int, str, str], ...] = eqx.field(static=True)
    starts: tuple[float, ...] = eqx.field(static=True)
    units: tuple[str, ...] = eqx.field(static=True)
    floors: tuple[float, ...] = eqx.field(static=True)

    @property
    def n_material(self) -> int:
        return len(self.material_fields)

    def material_parameterization(self) -> MaterialParameterization:
        """The material part (with the current transforms)."""
        return MaterialParameterization(self.material_fields, dict(zip(self.material_fields, self.transforms[: self.n_material])))

    def pack(self, material: Material):
        """``u`` of ``material``'s fitted fields followed by the scenario parameters' starts."""
        u_m = self.material_parameterization().pack(material)
        extra = [t.inverse(np.asarray(v, dtype=float)) for t, v in zip(self.transforms[self.n_material:], self.starts)]
        if isinstance(u_m, np.ndarray) and all(_concrete(e) for e in extra):
            return np.concatenate([u_m, np.asarray([float(e) for e in extra], dtype=u_m.dtype)])
        return jnp.concatenate([jnp.asarray(u_m), jnp.stack([jnp.asarray(e, dtype=jnp.asarray(u_m).dtype) for e in extra])])

    def values(self, u) -> dict:
        """Physical values of every fitted parameter from ``u`` (SI)."""
        return {f: t.forward(u[i]) for i, (f, t) in enumerate(zip(self.fields, self.transforms))}

    def unpack(self, u, base: Material) -> Material:
        """``base`` with the fitted MATERIAL fields replaced by their values at ``u``."""
        return self.material_parameterization().unpack(u[: self.n_material], base)

    def scenario_values(self, vector, n_scenarios: int) -> tuple[dict, ...]:
        """Per scenario, ``{parameter name: value}`` from the physical value ``vector`` (p,)."""
        out: list[dict] = [dict() for _ in range(n_scenarios)]
        for k, (i, _, pname) in enumerate(self.scenario_keys):
            out[i][pname] = vector[self.n_material + k]
        return tuple(out)


def _concrete(x) -> bool:
    return isinstance(x, (float, int, np.ndarray, np.generic)) or (isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer))


def scenario_parameterization(scenarios, parameterization: MaterialParameterization, requested) -> FitParameterization:
    """The :class:`FitParameterization` of ``parameterization`` plus the scenario parameters
    ``requested``: ``{scenario name: names}`` (each starting at the scenario's start value) or
    ``{scenario name: {name: start value (SI)}}``.

    Raises:
        FitError: an unknown scenario name, a scenario that declares no fittable parameters,
            a parameter it does not declare, a repeated one or a start value that is not a
            finite number.
    """
    if not isinstance(requested, Mapping):
        raise FitError(f"scenario_parameters must map scenario names to parameter names, e.g. {{'indentation': ('contact_offset',)}}; got {requested!r}")
    by_name = {getattr(sc, "name", None): i for i, sc in enumerate(scenarios)}
    keys, transforms, starts, units, floors, names = [], [], [], [], [], []
    for sname, wanted in requested.items():
        if sname not in by_name:
            raise FitError(f"scenario_parameters names scenario {sname!r}, which is not fitted; scenarios: {sorted(n for n in by_name if isinstance(n, str))}")
        i = by_name[sname]
        sc = scenarios[i]
        declare = getattr(sc, "fittable_parameters", None)
        declared = declare() if callable(declare) else {}
        if isinstance(wanted, str):
            wanted = (wanted,)
        if isinstance(wanted, Mapping):
            items = list(wanted.items())
        elif isinstance(wanted, Sequence):
            items = [(w, None) for w in wanted]
        else:
            raise FitError(f"scenario_parameters[{sname!r}] must be parameter names or {{name: start value}}, got {wanted!r}")
        for pname, start in items:
            if pname not in declared:
                have = f"it declares {sorted(declared)}" if declared else f"{type(sc).__name__} declares no fittable parameters"
                raise FitError(f"scenario {sname!r} has no fittable parameter {pname!r} ({have})")
            spec = declared[pname]
            start = spec.get("start", 0.0) if start is None else start
            if not (isinstance(start, (int, float, np.floating)) and not isinstance(start, bool) and math.isfinite(start)):
                raise FitError(f"start value of {sname}.{pname} must be a finite number (SI), got {start!r}")
            field = f"{sname}.{pname}"
            if field in names:
                raise FitError(f"scenario parameter {field!r} is asked for twice")
            names.append(field)
            keys.append((i, sname, pname))
            transforms.append(spec["transform"])
            starts.append(float(start))
            units.append(str(spec.get("unit", "")))
            floors.append(float(spec.get("scale", 0.0)))
    material_floors = tuple(0.0 for _ in parameterization.fields)
    return FitParameterization(fields=tuple(parameterization.fields) + tuple(names), transforms=tuple(parameterization.transforms) + tuple(transforms),
                               material_fields=tuple(parameterization.fields), scenario_keys=tuple(keys), starts=tuple(starts),
                               units=tuple(UNITS.get(f, "") for f in parameterization.fields) + tuple(units), floors=material_floors + tuple(floors))


# ============================================================================ problem
def _robust_weight(z, loss: str):
    """``sqrt(rho(z) / z)`` for the robust loss ``rho``: smooth, positive, 1 at ``z = 0``."""
    if loss == "linear":
        return jnp.ones_like(z)
    if loss == "soft_l1":
        return jnp.sqrt(2.0 / (1.0 + jnp.sqrt(1.0 + z)))
    if loss == "huber":
        z_big = jnp.where(z <= 1.0, 1.0, z)
        return jnp.where(z <= 1.0, 1.0, jnp.sqrt((2.0 * jnp.sqrt(z_big) - 1.0) / z_big))
    raise FitError(f"unknown loss {loss!r}; choose one of {LOSSES}")


class FitProblem:
    """The residuals and loss of a fit, as pure functions of the unconstrained vector ``u``.

    Args:
        scenarios: one or more objects following :class:`Scenario` (names must be unique).
        parameterization: which material fields are fitted and through which transforms.
        base: the material whose non-fitted fields (e.g. density) are kept.
        loss: ``"linear"``, ``"soft_l1"`` or ``"huber"``.
        f_scale: residual scale of the robust loss [-] (residuals are already divided by sigma,
            so ``f_scale = 3`` down-weights points more than 3 sigma off).
        scenario_parameters: scenario parameters fitted with the material fields,
            ``{scenario name: (parameter name, ...)}`` or ``{scenario name: {parameter name:
            start value (SI)}}`` (see :func:`scenario_parameterization`); their fields are named
            ``"<scenario>.<parameter>"`` and follow the material fields in ``u``.
    """

    def __init__(self, scenarios, parameterization: MaterialParameterization, base: Material, *, loss: str = "linear", f_scale: float = 1.0,
                 scenario_parameters=None):
        if not isinstance(parameterization, (MaterialParameterization, FitParameterization)):
            raise FitError(f"parameterization must be a MaterialParameterization, got {type(parameterization).__name__}")
        if not isinstance(base, Material):
            raise FitError(f"the initial material must be a Material, got {type(base).__name__}")
        if loss not in LOSSES:
            raise FitError(f"unknown loss {loss!r}; choose one of {LOSSES}")
        if not (isinstance(f_scale, (int, float)) and math.isfinite(f_scale) and f_scale > 0):
            raise FitError(f"f_scale must be a finite number > 0, got {f_scale!r}")
        if isinstance(scenarios, (str, bytes)) or not isinstance(scenarios, Sequence):
            scenarios = (scenarios,)
        scenarios = tuple(scenarios)
        if not scenarios:
            raise FitError("no scenario to fit")
        names = []
        observed, sigma, precision = [], [], []
        for i, sc in enumerate(scenarios):
            name = getattr(sc, "name", None)
            if not isinstance(name, str) or not name:
                raise FitError(f"scenario {i} has no name (a non-empty str attribute 'name')")
            if name in names:
                raise FitError(f"two scenarios are named {name!r}; scenario names must be unique")
            if not callable(getattr(sc, "predict", None)):
                raise FitError(f"scenario {name!r} has no predict(material) method")
            obs = np.asarray(getattr(sc, "observed", None), dtype=float)
            sig = np.asarray(getattr(sc, "sigma", None), dtype=float)
            if obs.ndim != 1 or obs.size == 0:
                raise FitError(f"scenario {name!r}: observed must be a non-empty 1-D array, got shape {obs.shape}")
            if sig.shape != obs.shape:
                raise FitError(f"scenario {name!r}: sigma has shape {sig.shape}, observed has {obs.shape}; they must match")
            if not np.all(np.isfinite(obs)):
                raise FitError(f"scenario {name!r}: observed holds {int(np.sum(~np.isfinite(obs)))} non-finite value(s)")
            if not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
                raise FitError(f"scenario {name!r}: every sigma must be finite and > 0 (same unit as observed)")
            eps = getattr(sc, "prediction_rtol", 0.0)
            if not (isinstance(eps, (int, float, np.floating)) and math.isfinite(eps) and 0.0 <= eps < 1.0):
                raise FitError(f"scenario {name!r}: prediction_rtol must be a number in [0, 1), got {eps!r}")
            names.append(name)
            observed.append(obs)
            sigma.append(sig)
            precision.append(float(eps))
        self.scenarios = scenarios
        self.names = tuple(names)
        if scenario_parameters:
            if isinstance(parameterization, FitParameterization):
                raise FitError("give scenario_parameters with a MaterialParameterization, not with a FitParameterization that already holds them")
            parameterization = scenario_parameterization(scenarios, parameterization, scenario_parameters)
        self.parameterization = parameterization
        self.fields = tuple(parameterization.fields)
        if isinstance(parameterization, FitParameterization):
            self.material_fields = parameterization.material_fields
            self.units = dict(zip(parameterization.fields, parameterization.units))
            self.scale_floors = {f: v for f, v in zip(parameterization.fields, parameterization.floors) if v > 0}
        else:
            self.material_fields = self.fields
            self.units = {f: UNITS.get(f, "") for f in self.fields}
            self.scale_floors = {}
        self.n_material = len(self.material_fields)
        self.base = base
        self.loss_name = loss
        self.f_scale = float(f_scale)
        self._observed = tuple(observed)
        self._sigma = tuple(sigma)
        self.prediction_rtol = tuple(precision)
        self.sizes = tuple(o.size for o in observed)
        self.n_residuals = int(sum(self.sizes))
        self.n_parameters = len(self.fields)
        # Each scenario as a pytree: its measured-data leaves (``observed``, ``sigma`` of an
        # equinox-Module scenario, and the attributes its class names in ``fit_arguments``,
        # e.g. the depths of a closed-form indentation) are passed to the compiled functions as
        # ARGUMENTS, with the problem's observed and sigma, so that one compilation serves every
        # specimen of the same structure (see :meth:`data`, :meth:`with_data`, :meth:`structure_key`).
        self._treedefs, self._leaves, dynamic = [], [], []
        for sc in scenarios:
            leaves, treedef = jax.tree_util.tree_flatten(sc)
            self._treedefs.append(treedef)
            self._leaves.append(leaves)
            dynamic.append(data_leaf_indices(sc, leaves, DATA_ATTRIBUTES + tuple(getattr(type(sc), "fit_arguments", ()))))
        self._dynamic = tuple(dynamic)
        # The transforms' numbers (a ``Log``'s ``scale``: the start value of a data-driven
        # start; bounds) are arguments too, not compiled in: a fit of the same structure from
        # another start compiles nothing (the transform types stay in the key).
        transform_leaves, self._transform_treedef = jax.tree_util.tree_flatten(parameterization.transforms)
        self._transform_leaves = tuple(transform_leaves)

    # -------------------------------------------------------------- data as arguments
    def data(self) -> dict:
        """The problem's measured data as a pytree of arrays: ``observed`` and ``sigma`` per
        scenario (SI), each scenario's dynamic leaves and the numbers of the parameterization's
        transforms (``transforms``: e.g. a ``Log``'s ``lower`` and ``scale``, unit of the
        parameter). The compiled step and evaluation take it as an argument (:meth:`with_data`
        rebuilds the problem from it inside the trace)."""
        dtype = jax.dtypes.canonicalize_dtype(float)
        return {
            "observed": tuple(np.asarray(o) for o in self._observed),
            "sigma": tuple(np.asarray(s) for s in self._sigma),
            "leaves": tuple(tuple(np.asarray(leaves[i]) for i in dyn) for leaves, dyn in zip(self._leaves, self._dynamic)),
            "transforms": tuple(np.asarray(t, dtype=dtype) for t in self._transform_leaves),
        }

    def with_data(self, data) -> "FitProblem":
        """A shallow copy whose observed data, sigma and scenario data leaves are ``data``
        (arrays or tracers with the structure of :meth:`data`)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._observed = tuple(data["observed"])
        new._sigma = tuple(data["sigma"])
        scenarios = []
        for sc, treedef, leaves, dyn, values in zip(self.scenarios, self._treedefs, self._leaves, self._dynamic, data["leaves"]):
            if not dyn:
                scenarios.append(sc)
                continue
            leaves = list(leaves)
            for i, v in zip(dyn, values):
                leaves[i] = v
            scenarios.append(jax.tree_util.tree_unflatten(treedef, leaves))
        new.scenarios = tuple(scenarios)
        transforms = jax.tree_util.tree_unflatten(self._transform_treedef, data["transforms"])
        new.parameterization = eqx.tree_at(lambda p: p.transforms, self.parameterization, transforms)
        return new

    def _with_dynamic(self, dynamic) -> "FitProblem":
        """A shallow copy passing the scenario leaves ``dynamic`` (per scenario, leaf indices
        of ``jax.tree_util.tree_flatten(scenario)``) as data instead of compiling them in."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._dynamic = tuple(tuple(sorted(d)) for d in dynamic)
        return new

    def structure_key(self) -> tuple:
        """What the compiled step depends on besides :meth:`data`: fields, the transforms'
        types (their numbers are data), fixed material fields, loss, scenario names, types and
        pytree structures, data shapes, and a hash of every scenario leaf that is compiled in
        (arrays by content; other objects, e.g. a scenario that is not a pytree, by identity:
        :func:`hash_scenario_leaves`). Two problems with equal keys can share one compiled step
        with their own data."""
        digest, comps = self.fingerprint("", 0)
        parts = [comps[k] for k in ("fields", "fixed material fields", "scenarios", "loss")]
        parts.append(self._transform_treedef)
        parts.append(self.sizes)
        h = hashlib.sha256()
        objects = []
        for treedef, leaves, dyn in zip(self._treedefs, self._leaves, self._dynamic):
            try:
                hash(treedef)
                parts.append(treedef)
            except TypeError:  # a static field that cannot be hashed: key by the scenario itself
                objects.append(id(leaves))
            parts.append(dyn)
            objects += hash_scenario_leaves(h, leaves, dyn, data_tag="dyn")
        parts.append(h.hexdigest())
        parts.append(tuple(objects))
        return tuple(parts)

    # -------------------------------------------------------------- pure functions
    def material(self, u) -> Material:
        """The material at unconstrained ``u`` (shape ``(p,)``)."""
        return self.parameterization.unpack(u, self.base)

    def material_from_values(self, values) -> Material:
        """The material with the fitted fields set to physical ``values`` (shape ``(p,)``, SI)."""
        return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in self.material_fields), self.base, tuple(values[i] for i in range(self.n_material)))

    @property
    def has_scenario_parameters(self) -> bool:
        """Whether scenario parameters (e.g. a contact offset) are fitted with the material."""
        return isinstance(self.parameterization, FitParameterization) and bool(self.parameterization.scenario_keys)

    def scenario_values_of(self, values) -> tuple[dict, ...] | None:
        """Per scenario, its fitted parameters ``{name: value}`` from the physical ``values``
        (p,) (None when none are fitted)."""
        if not self.has_scenario_parameters:
            return None
        return self.parameterization.scenario_values(values, len(self.scenarios))

    def _scenario_values_at(self, u) -> tuple[dict, ...] | None:
        """:meth:`scenario_values_of` at the unconstrained ``u`` (None when none are fitted)."""
        if not self.has_scenario_parameters:
            return None
        vals = self.values(u)
        return self.scenario_values_of(jnp.stack([jnp.asarray(vals[f]) for f in self.fields]))

    def predictions_of(self, material: Material, scenario_values=None) -> list[jax.Array]:
        """Each scenario's predictions (its unit), checked against the observed shapes;
        ``scenario_values`` (:meth:`scenario_values_of`) the fitted scenario parameters."""
        preds = []
        for k, (sc, obs) in enumerate(zip(self.scenarios, self._observed)):
            extra = scenario_values[k] if scenario_values is not None else {}
            pred = jnp.asarray(sc.predict(material, **extra) if extra else sc.predict(material))
            if pred.shape != obs.shape:
                raise FitError(f"scenario {sc.name!r}: predict returned shape {pred.shape}, observed has {obs.shape}")
            preds.append(pred)
        return preds

    def _scaled(self, preds) -> jax.Array:
        return jnp.concatenate([(p - obs) / sig for p, obs, sig in zip(preds, self._observed, self._sigma)])

    def precision_floor(self) -> jax.Array:
        """The 2-norm of the scaled residuals [-] within which the predictions reproduce the data
        to the forward models' own precision: ``|eps_k observed_k / sigma_k|_2`` over all rows,
        ``eps_k`` the ``prediction_rtol`` of row k's scenario (0 where a scenario states none,
        e.g. closed forms). Below it the steps fit the models' round-off (noise-free,
        simulated data), and the fit engine stops (see :mod:`difftissue.fit.engine`)."""
        arrays = (*self._observed, *self._sigma)
        xp = np if all(isinstance(a, np.ndarray) for a in arrays) else jnp  # NumPy data: nothing dispatched to JAX
        return xp.sqrt(sum(xp.sum((eps * obs / sig) ** 2) for eps, obs, sig in zip(self.prediction_rtol, self._observed, self._sigma)))

    def scaled_residuals_of(self, material: Material) -> jax.Array:
        """``(predict - observed) / sigma`` of all scenarios, concatenated, shape ``(n,)`` [-]."""
        return self._scaled(self.predictions_of(material))

    def evaluate_values(self, values, jac: str = "fwd"):
        """Loss, Jacobian of the robustified scaled residuals with respect to the PHYSICAL
        values ``(n, p)``, and each scenario's predictions, at ``values`` (one pass: what a
        fit needs at its start and end, compiled once)."""

        def res(v):
            preds = self.predictions_of(self.material_from_values(v), self.scenario_values_of(v))
            r = self.robust(self._scaled(preds))
            return r, (r, preds)

        jac_fn = jax.jacfwd if jac == "fwd" else jax.jacrev
        J, (r, preds) = jac_fn(res, has_aux=True)(values)
        return 0.5 * jnp.sum(r * r), J, preds

    def robust(self, r) -> jax.Array:
        """Robustified residuals ``r sqrt(rho(z)/z)``, ``z = (r/f_scale)^2``: their half sum of
        squares is the loss, so Gauss--Newton methods minimise the robust loss."""
        if self.loss_name == "linear":
            return r
        z = (r / self.f_scale) ** 2
        return r * _robust_weight(z, self.loss_name)

    def residuals_and_predictions(self, u) -> tuple[jax.Array, tuple[jax.Array, ...]]:
        """``(residuals(u), predictions)``: the robustified scaled residuals and each
        scenario's predictions (in the residuals' dtype) from one forward evaluation."""
        preds = self.predictions_of(self.material(u), self._scenario_values_at(u))
        r = self.robust(self._scaled(preds))
        return r, tuple(jnp.asarray(p, dtype=r.dtype) for p in preds)

    def residuals(self, u) -> jax.Array:
        """Robustified scaled residuals at ``u``, shape ``(n,)`` [-] (plain ones for ``linear``)."""
        return self.robust(self._scaled(self.predictions_of(self.material(u), self._scenario_values_at(u))))

    def residuals_of_values(self, values) -> jax.Array:
        """Robustified scaled residuals as a function of the PHYSICAL fitted values (SI)."""
        return self.robust(self._scaled(self.predictions_of(self.material_from_values(values), self.scenario_values_of(values))))

    def loss(self, u) -> jax.Array:
        """Loss ``0.5 f_scale^2 sum rho((r/f_scale)^2)`` [-] at ``u``."""
        r = self.residuals(u)
        return 0.5 * jnp.sum(r * r)

    def values(self, u) -> dict[str, jax.Array]:
        """Physical values of the fitted fields at ``u`` (SI)."""
        return self.parameterization.values(u)

    # -------------------------------------------------------------- fingerprint
    def fingerprint(self, method: str, n_starts: int) -> tuple[str, dict[str, str]]:
        """sha256 of the problem: fields, transforms, fixed fields of the base material,
        scenario names and types, observed data and sigma, loss, method and number of starts.

        Returns ``(hexdigest, components)``; ``components`` maps each part to its own short hash
        so a mismatch can be named. The predict functions themselves cannot be hashed: a change
        of the model code with the same data and names is not detected.
        """

        def h(b: bytes) -> str:
            return hashlib.sha256(b).hexdigest()[:16]

        fixed = {f: np.asarray(getattr(self.base, f), dtype=float).tolist() for f in material_fields(self.base) if f not in self.fields}
        data = hashlib.sha256()
        for obs, sig in zip(self._observed, self._sigma):
            data.update(np.ascontiguousarray(obs, dtype="<f8").tobytes())
            data.update(b"|")
            data.update(np.ascontiguousarray(sig, dtype="<f8").tobytes())
            data.update(b"||")
        comps = {
            "fields": h(repr(self.fields).encode()),
            "transforms": h(repr(tuple(repr(t) for t in self.parameterization.transforms)).encode()),
            "fixed material fields": h(json.dumps(fixed, sort_keys=True).encode()),
            "scenarios": h(repr(tuple((n, type(s).__qualname__) for n, s in zip(self.names, self.scenarios))).encode()),
            "observed data and sigma": data.hexdigest()[:16],
            "loss": h(f"{self.loss_name}:{self.f_scale!r}".encode()),
            "method": h(method.encode()),
            "number of starts": h(str(int(n_starts)).encode()),
        }
        total = hashlib.sha256(json.dumps(comps, sort_keys=True).encode()).hexdigest()
        return total, comps
