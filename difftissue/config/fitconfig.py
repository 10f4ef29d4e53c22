"""A validated, built config ready to fit (:class:`FitConfig`): which scenarios the fit gets
(the compile policy: simulated scenarios wrapped in
:class:`~difftissue.config.compile.SeparatelyCompiled`), the data-driven start of the cubic
coefficient, the reaction-sign check, the fit itself, and the checks after it (tissue range,
a lattice model's pre-stretch bias in an incision, discretisation estimate).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, DifftissueError, FitQualityWarning
from ..fit import DISCRETISATION_METHOD, FitQuality, QualityFlag, discretisation_estimate, fit, with_discretisation
from ..materials import Material
from .compile import SeparatelyCompiled
from .estimates import _CUBIC_START_KINDS, _cubic_estimate, _inside
from .experiment import Experiment
from .schema import TISSUE_RANGES, _reraise

@dataclasses.dataclass(frozen=True)
class FitConfig:
    """A validated fit config, ready to run.

    Attributes:
        path: the config file (None when parsed from a mapping).
        raw: the parsed TOML (a dict).
        material: initial :class:`~difftissue.materials.Material` (SI): the config's
            [material], with E from the data unless ``fit.start = "material"`` (and, once
            :meth:`run` has chosen it, the cubic coefficient: :meth:`start_cubic_coefficient`).
        parameterization: fitted fields and their transforms.
        options: keyword arguments for :func:`difftissue.fit.fit` (method, loss, starts, ...).
        experiments: the built experiments, in file order.
        start: the data-driven start (see :func:`_data_start`), or None.
    """

    path: Path | None
    raw: dict
    material: Any
    parameterization: Any
    options: dict
    experiments: tuple[Experiment, ...]
    #: where the initial values came from when the data chose them (``fit.start = "data"``):
    #: ``{field: {"value", "config_value", "from"}}``; None when the config's [material] is the start.
    #: E is chosen when the config is read; the cubic coefficient b by :meth:`run` (it needs two
    #: model evaluations, see :meth:`start_cubic_coefficient`)
    start: dict | None = None
    #: ``fit.start``: ``"data"`` (E and b from the data unless ...) or ``"material"`` (the
    #: config's [material] is the start)
    start_mode: str = "data"

    @property
    def scenarios(self) -> tuple:
        return tuple(e.scenario for e in self.experiments)

    @property
    def config_material(self):
        """``[material]`` as written in the config (:attr:`material` is the fit's start, whose E
        may come from the data: :attr:`start`)."""
        if not self.start:
            return self.material
        return Material(**{**self.material.to_dict(), **{f: d["config_value"] for f, d in self.start.items()}})

    @property
    def data_files(self) -> tuple[Path, ...]:
        seen: dict[Path, None] = {}
        for e in self.experiments:
            for p in e.data_files:
                seen.setdefault(p, None)
        return tuple(seen)

    @property
    def data_provenance(self) -> list[dict]:
        """Per experiment with measured rows: ``{"experiment": name, **Experiment.provenance}``."""
        return [{"experiment": e.name, **e.provenance} for e in self.experiments if e.provenance is not None]

    @property
    def data_warnings(self) -> list[str]:
        """The plausibility warnings of every experiment's data (e.g. a likely unit mistake)."""
        return [w for e in self.experiments for w in e.warnings]

    @property
    def model_name(self) -> str:
        """The models used, e.g. ``"springs_volume"`` or ``"hertz; springs_volume"``."""
        names = dict.fromkeys(e.model or "analytic" for e in self.experiments)
        return "; ".join(names)

    @property
    def anisotropic_pre_stretch(self) -> bool:
        """True when the material has a ``pre_stretch_y`` or it is fitted."""
        return self.material.pre_stretch_y is not None or "pre_stretch_y" in self.parameterization.fields

    def fit_scenarios(self, separate_compilation: bool | None = None) -> tuple:
        """The scenarios handed to :func:`~difftissue.fit.fit`: the simulated ones wrapped in
        :class:`SeparatelyCompiled` unless ``separate_compilation`` (default: the config's
        ``fit.separate_compilation``, true) is false."""
        sep = self.options.get("separate_compilation", True) if separate_compilation is None else separate_compilation
        offset = [e.name for e in self.experiments if e.fit_contact_offset and e.kind != "analytic_indentation"]
        if sep and offset:
            raise ConfigError(f"experiment {offset[0]!r}: contact_offset = \"fit\" on a simulated indentation needs fit.separate_compilation = false "
                              "(the separately compiled programs take the material fields only); or fit it on an analytic_indentation experiment")
        if not sep:
            return self.scenarios
        mode = "reverse" if (self.options.get("method") in ("adam", "lbfgs") or self.options.get("jac") == "bwd") else "forward"
        fields = tuple(self.parameterization.fields)
        aniso = self.anisotropic_pre_stretch
        return tuple(SeparatelyCompiled(e.scenario, mode=mode, fields=fields, pre_stretch_y=aniso) if e.kind != "analytic_indentation" else e.scenario for e in self.experiments)

    def run(self, **overrides):
        """Fit: :func:`difftissue.fit.fit` with the config's options updated by ``overrides``
        (e.g. ``checkpoint=``, ``resume=``, ``progress=``, ``starts=``)."""
        opts = {**self.options, **overrides}
        check = opts.pop("discretisation_check", True)
        tissue = opts.pop("tissue", None)
        scenarios = self.fit_scenarios(opts.pop("separate_compilation", None))
        if any(isinstance(sc, SeparatelyCompiled) and sc.mode == "reverse" for sc in scenarios):
            # Reverse-mode scenarios (Adam, L-BFGS) have vector-Jacobian products only: the
            # fit's final Jacobian must be reverse mode too.
            if opts.get("jac", "bwd") != "bwd":
                raise ConfigError(
                    f"fit.method = {opts.get('method')!r} differentiates the separately compiled scenarios in reverse mode: "
                    "fit.jac must be 'bwd' (or leave it out), or set fit.separate_compilation = false"
                )
            opts["jac"] = "bwd"
        object.__setattr__(self, "last_scenarios", scenarios)  # for the failures of SeparatelyCompiled
        self.check_reaction_signs(scenarios)
        self.start_cubic_coefficient(scenarios)
        offsets = {e.name: ("contact_offset",) for e in self.experiments if e.fit_contact_offset}
        if offsets:
            opts["scenario_parameters"] = offsets
        result = fit(scenarios, self.parameterization, self.material, **opts)
        result = tissue_range_check(result, tissue)
        result = lattice_pre_stretch_check(result, self.experiments)
        return self.check_discretisation(result) if check else result

    def coarse_predictions(self, material) -> tuple[dict, dict]:
        """Each coarsenable experiment's prediction at ``material`` on its coarser mesh (one
        forward evaluation each, no refit), for :func:`~difftissue.fit.discretisation_estimate`.

        Returns ``(coarse, skipped)``: ``{name: {"prediction" (unit of the data), "fine_cells",
        "coarse_cells", "refinement_ratio"}}`` (plus ``"prediction_coarser"`` and
        ``"coarser_cells"`` where the experiment's coarsening gives a third level, ``info["coarser"]``:
        a callable returning ``(scenario, cells)``) and ``{name: reason}`` for the experiments
        without an estimate (no mesh, a mesh file, observed on given nodes, or a coarse
        evaluation that failed: its message is the reason). ``Experiment.coarsen`` may itself
        refuse, returning ``(None, reason)`` (an incision whose cut the coarser mesh cannot
        carry unchanged)."""
        coarse, skipped = {}, {}
        for e in self.experiments:
            if e.coarsen is None:
                skipped[e.name] = e.coarsen_skip or "this scenario cannot be coarsened"
                continue
            if e.fit_contact_offset:
                skipped[e.name] = "its contact offset is fitted (contact_offset = \"fit\"): the coarser mesh is not evaluated at the fitted offset"
                continue
            try:
                sc, info = e.coarsen()
                if sc is None:  # the experiment's own check refused the coarser mesh: info is the reason
                    skipped[e.name] = str(info)
                    continue
                info = dict(info)
                coarser = info.pop("coarser", None)
                levels = [(sc, info["coarse_cells"], "prediction")]
                if coarser is not None:  # a third level: the order is observed, not assumed
                    sc2, info["coarser_cells"] = coarser()
                    levels.append((sc2, info["coarser_cells"], "prediction_coarser"))
            except DifftissueError as err:
                skipped[e.name] = f"the coarser mesh could not be built: {err}"
                continue
            for sc_level, cells, key in levels:
                wrapped = SeparatelyCompiled(sc_level, pre_stretch_y=material.pre_stretch_y is not None)
                try:
                    pred = np.asarray(wrapped.evaluate(material), dtype=float)
                except DifftissueError as err:
                    pred, why = None, str(err)
                else:
                    why = None if np.all(np.isfinite(pred)) else (wrapped.failures[-1] if getattr(wrapped, "failures", None) else "non-finite prediction")
                if why is not None:
                    skipped[e.name] = f"the evaluation on the coarser mesh {cells} failed: {why}"
                    break
                info[key] = pred
            else:
                coarse[e.name] = info
        return coarse, skipped

    def check_discretisation(self, result):
        """``result`` with its discretisation estimate (``result.discretisation``, the
        ``discretisation_error`` quality flag and :class:`~difftissue.errors.DiscretisationWarning`
        where the estimate exceeds the standard error): one evaluation per experiment on a
        coarser mesh at the fitted material (:meth:`coarse_predictions`). A fit of closed-form
        scenarios only gets ``{"status": "not applicable", "reason"}`` (no mesh)."""
        if all(e.kind == "analytic_indentation" for e in self.experiments):
            rec = {"method": DISCRETISATION_METHOD, "status": "not applicable", "reason": "closed-form scenarios only: no mesh, no discretisation error"}
            return dataclasses.replace(result, discretisation=rec)
        coarse, skipped = self.coarse_predictions(result.material)
        return with_discretisation(result, discretisation_estimate(result, coarse, skipped), stacklevel=3)

    def start_cubic_coefficient(self, scenarios=None) -> dict | None:
        """Before a fit (``fit.start = "data"``, the default, and b in ``fit.parameters``): start
        the cubic coefficient b from the data. Each compression or simulated indentation
        experiment is evaluated at the start (E from the data) with the config's b and with b
        one unit away (two forward solves; with separate compilation through the function the
        fit then reuses) and :func:`_cubic_estimate` gives the b that matches the measured
        curve; several experiments give their mean. The start is kept inside
        ``fit.bounds.cubic_coefficient`` (:func:`_inside`). Updates :attr:`material` and
        :attr:`start` (``start["cubic_coefficient"]``: ``value``, ``config_value``, ``from``)
        and returns that record; None (and the config's b stays the start) when the start is
        pinned, b is not fitted, or no experiment determines it (the reason is then recorded
        with ``value`` = the config's b)."""
        field = "cubic_coefficient"
        if self.start_mode != "data" or field not in self.parameterization.fields or (self.start or {}).get(field):
            return None
        scenarios = self.fit_scenarios() if scenarios is None else scenarios
        b0 = float(self.material.cubic_coefficient)
        t = dict(zip(self.parameterization.fields, self.parameterization.transforms))[field]
        lo, hi = getattr(t, "lower", None), getattr(t, "upper", None)
        b1 = b0 + 1.0 if hi is None or b0 + 1.0 < hi else b0 - 1.0 if lo is None or b0 - 1.0 > lo else 0.5 * (b0 + hi)
        ests, why = [], []
        for e, sc in zip(self.experiments, scenarios):
            if e.kind not in _CUBIC_START_KINDS:
                continue
            at = []
            for b in (b0, b1):
                m = Material(**{**self.material.to_dict(), field: b})
                at.append(sc.evaluate(m) if isinstance(sc, SeparatelyCompiled) else np.asarray(sc.predict(m), dtype=float))
            est = _cubic_estimate(np.asarray(e.scenario.observed), np.asarray(e.scenario.sigma), at[0], at[1], b0, b1)
            if isinstance(est, str):
                why.append(f"{e.name}: {est}")
            else:
                ests.append((e.name, *est))
        if not ests:
            if why:
                rec = {"value": b0, "config_value": b0, "from": f"the config's material.{field}", "no_estimate": "; ".join(why)}
                object.__setattr__(self, "start", {**(self.start or {}), field: rec})
            return None
        b = float(np.mean([v for _, v, _ in ests]))
        inside = _inside(b, lo, hi)
        how = "; ".join(f"{name}: the model's curve at E = {float(self.material.youngs_modulus):.4g} Pa matched to the data's "
                        f"(linearised in b between b = {b0:g} and {b1:g}, scale {alpha:.3g}) gives b = {v:.4g}" for name, v, alpha in ests)
        if inside != b:
            how += f"; kept inside fit.bounds.cubic_coefficient = [{lo:g}, {hi:g}] (estimate {b:.4g})"
        rec = {"value": inside, "config_value": b0, "from": how}
        object.__setattr__(self, "material", Material(**{**self.material.to_dict(), field: inside}))
        object.__setattr__(self, "start", {**(self.start or {}), field: rec})
        return rec

    def check_reaction_signs(self, scenarios=None) -> None:
        """Before a fit: raise :class:`~difftissue.errors.ReactionSignError` for a ``fem_field``
        experiment whose measured reaction force has the opposite sign of the model's reaction
        at the initial material (one forward solve; with separate compilation it compiles the
        function the fit then reuses)."""
        scenarios = self.fit_scenarios() if scenarios is None else scenarios
        for i, (e, sc) in enumerate(zip(self.experiments, scenarios)):
            check = getattr(e.scenario, "check_reaction_sign", None)
            if e.kind != "fem_field" or check is None or getattr(e.scenario, "reaction_mask", None) is None:
                continue
            pred = sc.evaluate(self.material) if isinstance(sc, SeparatelyCompiled) else np.asarray(sc.predict(self.material))
            try:
                check(pred)
            except DifftissueError as err:
                _reraise(f"experiment[{i}]", err)


def tissue_range_check(result, tissue: str | None):
    """``result`` with the quality warning ``outside_tissue_range`` added (and emitted as
    :class:`~difftissue.errors.FitQualityWarning`) when its fitted Young's modulus lies outside
    :data:`TISSUE_RANGES` of the stated ``tissue`` (config ``fit.tissue``); unchanged when no
    tissue is stated or E was not fitted."""
    if tissue is None or "youngs_modulus" not in result.values or result.quality is None:
        return result
    lo, hi = TISSUE_RANGES[tissue]
    E = float(result.values["youngs_modulus"])
    if not math.isfinite(E) or lo <= E <= hi:
        return result
    flag = QualityFlag(
        "outside_tissue_range", "warning", "youngs_modulus",
        f"youngs_modulus = {E:.4g} Pa lies outside [{lo:g}, {hi:g}] Pa, the range expected for fit.tissue = {tissue!r}: check the data's units, "
        "the contact point and the model (or state another tissue)",
        {"value": E, "range": [lo, hi], "tissue": tissue},
    )
    warnings.warn(f"warning: {flag.message}", FitQualityWarning, stacklevel=3)
    return dataclasses.replace(result, quality=FitQuality(result.quality.flags + (flag,), result.quality.scenarios))


#: The estimated opening bias (relative) from which :func:`lattice_pre_stretch_check` flags an
#: incision fit with a lattice model: 2 %, well inside the 5 % the lattice models are held to,
#: because the bias is systematic (refining does not remove it) and goes straight into the
#: fitted pre-stretch.
LATTICE_BIAS_FLAG = 0.02


def lattice_pre_stretch_check(result, experiments):
    """``result`` with the quality warning ``lattice_pre_stretch_bias`` added (and emitted as
    :class:`~difftissue.errors.FitQualityWarning`) for each incision experiment whose lattice
    model (``springs_volume``, ``springs_volume_mesh_lattice``) opens the cut measurably narrower
    or wider than the finite-strain continuum at the fitted material's pre-stretch
    (:meth:`difftissue.incision.Incision.lattice_opening_bias`: an estimated bias of at least
    :data:`LATTICE_BIAS_FLAG`, or a pre-stretch outside the measured 1-1.15 by more than 0.02
    below or at all above). Unchanged otherwise."""
    if result.quality is None:
        return result
    flags = []
    for e in experiments:
        estimate = getattr(e.scenario, "lattice_opening_bias", None)
        info = estimate(result.material) if e.kind == "incision" and estimate is not None else None
        if info is None:
            continue
        lam, bias = info["pre_stretch"], info["relative_bias"]
        measured = ", ".join(f"{100 * b:+.0f} % at {k:g}" for k, b in info["measured"][1:])
        if bias is not None and abs(bias) < LATTICE_BIAS_FLAG:
            continue
        if bias is None and 0.98 <= lam <= 1.0:
            continue
        isotropic = result.material.pre_stretch_y is None
        remedy = ("use model = \"springs_volume_matched_lattice\" (within 5 % of the continuum up to 1.15) "
                  if isotropic and 0.95 <= lam <= 1.2 else "") + "or a finite-strain continuum model (stable_neo_hookean, fem_neo_hookean) on a converged mesh"
        if bias is None:
            what = (f"lies outside the measured range 1-1.15 of the {info['model']} lattice's opening bias "
                    f"(measured {measured} against the converged neo-Hookean opening): the widths carry an unmeasured model bias")
        else:
            what = (f"makes the {info['model']} lattice open the cut about {100 * abs(bias):.0f} % "
                    f"{'narrower' if bias < 0 else 'wider'} than the converged finite-strain continuum (measured {measured}); "
                    f"refining the mesh does not remove it, and the fitted pre_stretch - 1 is off by about as much the other way")
        flags.append(QualityFlag(
            "lattice_pre_stretch_bias", "warning", e.name,
            f"{e.name}: pre_stretch = {lam:.4g} {what}: {remedy}",
            {"pre_stretch": lam, "relative_bias": bias, "model": info["model"], "measured": info["measured"]},
        ))
    if not flags:
        return result
    for flag in flags:
        warnings.warn(f"warning: {flag.message}", FitQualityWarning, stacklevel=3)
    return dataclasses.replace(result, quality=FitQuality(result.quality.flags + tuple(flags), result.quality.scenarios))
