"""Reading a config: :func:`load_config` (a TOML file) and :func:`parse_config` (a mapping)
check every key of ``[material]`` and ``[fit]`` and the structure of the ``[[experiment]]``
tables before anything heavy happens, build the experiments
(:mod:`~difftissue.config.builders`), choose the data-driven start of Young's modulus and
return a :class:`~difftissue.config.FitConfig`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .._io import read_toml
from ..errors import ConfigError
from ..fit import LOSSES, METHODS
from ..materials import Identity, Log, Material, MaterialParameterization, ScaledLogit
from ..models import LATTICE_MODELS
from .builders import _build_experiment
from .estimates import _data_start
from .fitconfig import FitConfig
from .schema import (
    _EXPERIMENT_KEYS,
    _FIT_KEYS,
    _POSITIVE_FIELDS,
    _TOP_KEYS,
    FIELDS,
    SCENARIOS,
    TISSUE_RANGES,
    _bool,
    _choice,
    _fail,
    _integer,
    _is_number,
    _join,
    _material_values,
    _positive,
    _show,
    _string,
    _table,
)

def load_config(path) -> FitConfig:
    """Read, validate and build a TOML fit config; relative paths are taken from its folder."""
    path = Path(path)
    return parse_config(read_toml(path, "config"), base_dir=path.parent, path=path)


def parse_config(raw: Mapping, *, base_dir=".", path=None) -> FitConfig:
    """Validate and build a config given as a mapping (the parsed TOML)."""
    base_dir = Path(base_dir)
    top = _table(raw, "", _TOP_KEYS, ("material", "fit", "experiment"))
    for k in ("title", "description"):
        if k in top:
            _string(top[k], k)
    material = _parse_material(top["material"])
    param, options = _parse_fit(top["fit"], material)
    exps = top["experiment"]
    if not isinstance(exps, list) or not exps:
        _fail("experiment", "must be one or more [[experiment]] tables")
    # Structure first (cheap), then the data and the models.
    names = []
    for i, e in enumerate(exps):
        p = f"experiment[{i}]"
        if not isinstance(e, Mapping):
            _fail(p, f"must be a table, got {_show(e)}")
        if "scenario" not in e:
            _fail(_join(p, "scenario"), f"missing (required); one of {', '.join(SCENARIOS)}")
        kind = _choice(e["scenario"], _join(p, "scenario"), SCENARIOS)
        _table(e, p, _EXPERIMENT_KEYS[kind], ("data",))
        name = _string(e["name"], _join(p, "name")) if "name" in e else f"{kind}_{i}"
        if name in names:
            _fail(_join(p, "name"), f"{name!r} is used by experiment[{names.index(name)}] too; names must be unique")
        names.append(name)
    built = tuple(_build_experiment(e, f"experiment[{i}]", names[i], base_dir, material=material, fitted=param.fields) for i, e in enumerate(exps))
    _check_model_ranges(built, material, param)
    start = None
    start_mode = options.pop("start", "data")
    if start_mode == "data" and "youngs_modulus" in param.fields:
        material, start = _data_start(built, material, options)
        if start is not None:  # the transforms are scaled at the start (u = 0 there)
            param, _ = _parse_fit(top["fit"], material)
    options.pop("_bounds", None)
    return FitConfig(
        path=None if path is None else Path(path),
        raw=dict(raw),
        material=material,
        parameterization=param,
        options=options,
        experiments=built,
        start=start,
        start_mode=start_mode,
    )


def _check_model_ranges(experiments, material, param) -> None:
    """The springs_volume lattice (and its variants, :data:`~difftissue.models.LATTICE_MODELS`)
    represents nu in [0.25, 0.5) only: the fit must stay there."""
    springs = [i for i, e in enumerate(experiments) if e.model in LATTICE_MODELS]
    if not springs:
        return
    who = f"the {experiments[springs[0]].model} model (experiment[{springs[0]}])"
    nu = float(material.poisson_ratio)
    if nu < 0.25:
        _fail("material.poisson_ratio", f"{who} needs nu in [0.25, 0.5), got {nu:g}; use stable_neo_hookean or fem_* below 0.25")
    if "poisson_ratio" in param.fields:
        t = dict(zip(param.fields, param.transforms))["poisson_ratio"]
        lo = getattr(t, "lower", None)
        if lo is None or lo < 0.25:
            _fail("fit.bounds.poisson_ratio", f"{who} needs nu in [0.25, 0.5): give bounds such as [0.25, 0.499] (got {'none' if lo is None else f'lower bound {lo:g}'})")


def _parse_material(value):
    t = _table(value, "material", tuple(FIELDS), ("youngs_modulus", "poisson_ratio"))
    return Material(**_material_values(t, "material"))


def _parse_fit(value, material):
    t = _table(value, "fit", _FIT_KEYS, ("parameters",))
    params = t["parameters"]
    if isinstance(params, str):
        params = [params]
    if not isinstance(params, list) or not params:
        _fail("fit.parameters", f"must be a non-empty list of material fields ({', '.join(FIELDS)}), got {_show(params)}")
    for i, f in enumerate(params):
        if not isinstance(f, str) or f not in FIELDS:
            _fail(f"fit.parameters[{i}]", f"unknown material field {_show(f)}; choose from {', '.join(FIELDS)}")
        if params.index(f) != i:
            _fail(f"fit.parameters[{i}]", f"{f!r} is listed twice")
    bounds = _table(t.get("bounds", {}), "fit.bounds", tuple(FIELDS))
    transforms = {}
    for f in params:
        x0 = float(getattr(material, f))
        if f in bounds:
            p = f"fit.bounds.{f}"
            b = bounds[f]
            if not isinstance(b, list) or len(b) != 2 or not all(_is_number(v) for v in b):
                _fail(p, f"must be [lower, upper] (numbers; inf allowed), got {_show(b)}")
            lo, hi = float(b[0]), float(b[1])
            if math.isnan(lo) or math.isnan(hi) or not lo < hi:
                _fail(p, f"needs lower < upper, got [{lo:g}, {hi:g}]")
            if f in _POSITIVE_FIELDS and lo < 0:
                _fail(p, f"the lower bound of {f} must be >= 0 (it must stay positive), got {lo:g}")
            if f == "poisson_ratio" and (lo < -1 or hi > 0.5):
                _fail(p, f"bounds of poisson_ratio must lie within [-1, 0.5], got [{lo:g}, {hi:g}]")
            if not lo < x0 < hi:
                _fail(p, f"the initial value material.{f} = {x0:g} must lie strictly inside [{lo:g}, {hi:g}]")
            if math.isfinite(lo) and math.isfinite(hi):
                transforms[f] = ScaledLogit(lo, hi)
            elif math.isfinite(lo):
                transforms[f] = Log(lower=lo, scale=x0 - lo)
            elif math.isfinite(hi):
                _fail(p, "an upper bound alone is not supported; give a finite lower bound too")
            else:
                if f in _POSITIVE_FIELDS or f == "poisson_ratio":
                    _fail(p, f"{f} needs a finite lower bound")
                transforms[f] = Identity()
        elif f in _POSITIVE_FIELDS:
            transforms[f] = Log(scale=x0)  # u = 0 at the initial value
    for f in bounds:
        if f not in params:
            _fail(f"fit.bounds.{f}", f"{f!r} is not fitted (not in fit.parameters)")
    param = MaterialParameterization(tuple(params), transforms)

    opts: dict[str, Any] = {}
    if "method" in t:
        opts["method"] = _choice(t["method"], "fit.method", METHODS)
    if "loss" in t:
        opts["loss"] = _choice(t["loss"], "fit.loss", LOSSES)
    if "f_scale" in t:
        opts["f_scale"] = _positive(t["f_scale"], "fit.f_scale")
    if "starts" in t:
        opts["starts"] = _integer(t["starts"], "fit.starts", minimum=1)
    if "seed" in t:
        opts["seed"] = _integer(t["seed"], "fit.seed")
    if "start_spread" in t:
        opts["start_spread"] = _positive(t["start_spread"], "fit.start_spread")
    if "max_steps" in t:
        opts["max_steps"] = _integer(t["max_steps"], "fit.max_steps")
    for k in ("rtol", "atol", "learning_rate"):
        if k in t:
            opts[k] = _positive(t[k], f"fit.{k}")
    if "jac" in t:
        opts["jac"] = _choice(t["jac"], "fit.jac", ("fwd", "bwd"))
    if "absolute_sigma" in t:
        opts["absolute_sigma"] = _bool(t["absolute_sigma"], "fit.absolute_sigma")
    if "checkpoint_every" in t:
        opts["checkpoint_every"] = _integer(t["checkpoint_every"], "fit.checkpoint_every", minimum=1)
    if "separate_compilation" in t:
        opts["separate_compilation"] = _bool(t["separate_compilation"], "fit.separate_compilation")
    if "plausible" in t:
        opts["plausible"] = _plausible_ranges(t["plausible"], params)
    if "tissue" in t:
        opts["tissue"] = _choice(t["tissue"], "fit.tissue", tuple(TISSUE_RANGES))
    opts["start"] = _choice(t.get("start", "data"), "fit.start", ("data", "material"))
    if "discretisation_check" in t:
        opts["discretisation_check"] = _bool(t["discretisation_check"], "fit.discretisation_check")
    opts["_bounds"] = {f: (float(b[0]), float(b[1])) for f, b in bounds.items()}
    return param, opts


def _plausible_ranges(value, params) -> dict:
    """``fit.plausible = { youngs_modulus = [lo, hi] }`` (SI): the range outside which a fitted
    value is flagged ``implausible_value`` (default E in [1 Pa, 1 GPa])."""
    t = _table(value, "fit.plausible", tuple(FIELDS))
    out = {}
    for f, b in t.items():
        p = f"fit.plausible.{f}"
        if not isinstance(b, list) or len(b) != 2 or not all(_is_number(v) for v in b) or not float(b[0]) < float(b[1]):
            _fail(p, f"must be [lower, upper] with lower < upper ({FIELDS[f] if FIELDS[f] != '1' else 'dimensionless'}), got {_show(b)}")
        out[f] = (float(b[0]), float(b[1]))
    return out
