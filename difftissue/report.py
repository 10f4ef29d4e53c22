"""Outputs of a fit: ``fit.json``, figures in human units, ``report.md``, the material card and
the specimen files.

:func:`write_fit_outputs` writes them from a :class:`~difftissue.fit.FitResult` (moved here from
``difftissue.fit``, which knows nothing of files or export: ``difftissue.fit.write_fit_outputs``
still works, with a DeprecationWarning, for one release). This module sits above both the fit
and export layers: it reads the fit's result and asks :mod:`difftissue.export` for the card and
the specimen files.

Units: every value in ``fit.json`` is SI (:data:`difftissue.fit.UNITS`); the figures use the
prefix that reads best (:func:`human_unit`).
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
import re
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._io import atomic_output, json_number, jsonable, sha256_file
from ._version import __version__
from .constitutive import UNIAXIAL_STRAIN_RANGE, cubic_coefficient_record, surface_tension_record
from .errors import DifftissueError, OutputError, OutputExistsError
from .export.card import card_from_fit, portable_path, scenario_record
from .export.fitted import fitted_specimen, specimen_file_name, specimen_record, write_specimen
from .fit.problem import UNITS, unit_text
from .fit.result import FitResult, ScenarioFit
from .incision import Incision
from .mesh import unique_edges
from .models import LATTICE_MODELS
from .fit.statistics import (
    AUTOCORRELATION_LIMIT,
    BOUND_FRACTION,
    PLAUSIBLE,
    RMS_LIMIT,
    RUNS_P_LIMIT,
    STRUCTURE_MIN_RMS,
    FitQuality,
)

__all__ = ["write_fit_outputs", "derived_quantities", "package_versions", "config_record", "human_unit", "OUTPUT_FILES"]

#: Files written by :func:`write_fit_outputs` (besides one ``specimen-<name>.vtu`` per simulated
#: fem_field, compression or incision scenario).
OUTPUT_FILES = ("fit.json", "material.json", "fit.png", "loss.png", "report.md")


# ============================================================================ outputs
def package_versions() -> dict[str, str | None]:
    """Installed versions of difftissue and the numerical stack (None where not installed)."""
    out: dict[str, str | None] = {"difftissue": __version__}
    for name in ("jax", "jaxlib", "numpy", "equinox", "optimistix", "optax", "lineax", "matplotlib"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _config_dir(config):
    """The folder of a config given as a path (data paths are stored relative to it), else None."""
    return Path(config).parent if isinstance(config, (str, os.PathLike)) else None


def config_record(config):
    """A config for a record: a mapping as strict-JSON data, or a config file as its name, sha256
    and (TOML) parsed content or text; None for None."""
    if config is None:
        return None
    if isinstance(config, (str, os.PathLike)):
        path = Path(config)
        if not path.is_file():
            raise OutputError(f"config file {path} does not exist")
        record: dict[str, Any] = {"path": path.name, "sha256": sha256_file(path)}
        if path.suffix.lower() == ".toml":
            import tomllib

            with open(path, "rb") as fh:
                record["content"] = jsonable(tomllib.load(fh))
        else:
            record["text"] = path.read_text(encoding="utf-8", errors="replace")
        return record
    if isinstance(config, Mapping):
        return jsonable(config)
    raise OutputError(f"config must be a mapping or a path, got {type(config).__name__}")


def _fit_json(result: FitResult, *, config, data_files, model, scenario_names) -> dict:
    fields = list(result.fields)
    params = {}
    for f in fields:
        se = result.standard_errors[f]
        v = result.values[f]
        params[f] = {
            "value": json_number(v),
            "unit": result.units[f],
            "standard_error": json_number(se),
            "relative_standard_error": json_number(se / abs(v)) if v != 0 and math.isfinite(se) else None,
        }
    model_name = None if model is None else (model if isinstance(model, str) else getattr(model, "name", None) or type(model).__name__)
    return {
        "schema": "difftissue-fit/1",
        "parameters": params,
        "fixed_parameters": {k: {"value": v, "unit": UNITS.get(k, "")} for k, v in result.material.to_dict().items() if k not in fields},
        "correlation": {"fields": fields, "matrix": jsonable(result.correlation)},
        "covariance": {"fields": fields, "matrix": jsonable(result.covariance), "absolute_sigma": result.absolute_sigma},
        "loss": json_number(result.loss),
        "loss_function": result.loss_function,
        "f_scale": result.f_scale,
        "converged": bool(result.converged),
        "reason": result.reason,
        "steps": result.steps,
        "method": result.method,
        "starts": {"count": int(result.start_losses.size), "best": result.best_start, "final_losses": jsonable(result.start_losses)},
        "residual_variance": json_number(result.residual_variance),
        "degrees_of_freedom": result.dof,
        "condition_number": json_number(result.condition_number),
        "identifiability_warnings": list(result.warnings),
        "quality": result.quality.to_json() if result.quality is not None else None,
        "effective_modulus": jsonable(result.effective_modulus),
        "discretisation": jsonable(result.discretisation),
        "unidentified": list(result.unidentified),
        "model": model_name,
        "scenarios": [
            {"name": s.name, "points": int(s.observed.size), "rms_scaled_residual": json_number(np.sqrt(np.mean(s.residual**2)))}
            for s in result.scenarios
        ]
        if scenario_names is None
        else [{"name": str(n)} for n in scenario_names],
        "data_files": [{"path": portable_path(p, _config_dir(config)), "sha256": sha256_file(Path(p))} for p in data_files],
        "versions": package_versions(),
        "config": config_record(config),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _not_computed(err: Exception) -> dict:
    return {"status": "not computed", "reason": f"{type(err).__name__}: {' '.join(str(err).split())[:300]}"}


def derived_quantities(result: FitResult, *, model=None, scenarios: Sequence | None = None) -> dict | None:
    """The fitted material's quantities that users transfer, from the models' own response
    (:mod:`difftissue.constitutive`), for ``fit.json``'s ``derived``, the report and the card:

    - ``surface_tension``: one record per :class:`~difftissue.incision.Incision` scenario whose
      fitted material is pre-stretched (:func:`~difftissue.constitutive.surface_tension_record`:
      the model's own tension [N/m] with its standard error, the layer, and the linearised value
      ``E (lambda0 - 1) t / (1 - nu)`` under its own name);
    - ``continuum_uniaxial_cubic_coefficient``: for fits of a lattice model (``springs_volume``,
      ``springs_volume_mesh_lattice``, ``springs_volume_matched_lattice``,
      :data:`~difftissue.models.LATTICE_MODELS`, named in its ``model``; the lattices are the same
      without pre-stretch), what the lattice's
      ``cubic_coefficient`` is as the continuum law ``sigma = E (eps + b_c eps^3)`` over the
      strain range :data:`~difftissue.constitutive.UNIAXIAL_STRAIN_RANGE`
      (:func:`~difftissue.constitutive.cubic_coefficient_record`, cube cells).

    A quantity the model cannot evaluate is recorded as ``{"status": "not computed", "reason"}``.
    Returns None when there is nothing to derive.
    """
    mat = result.material
    fields = tuple(result.fields)
    cov = np.asarray(result.covariance, dtype=float) if result.covariance is not None else None
    out: dict[str, Any] = {}
    tensions = []
    for s in scenarios or ():
        if not isinstance(s, Incision) or float(mat.pre_stretch) == 1.0 and mat.pre_stretch_y is None:
            continue
        try:
            rec = {"scenario": s.name, **surface_tension_record(s.kind, mat, s.fitted_layers(), fields=fields, covariance=cov)}
        except (DifftissueError, RuntimeError) as err:
            rec = {"scenario": s.name, "model": s.kind, **_not_computed(err)}
        tensions.append(rec)
    if tensions:
        out["surface_tension"] = tensions
    names = [m.strip() for m in str(model or "").split(";")] + [getattr(s, "kind", "") for s in scenarios or ()]
    lattice = next((m for m in names if m in LATTICE_MODELS), None)
    if lattice is not None:  # the variants' uniaxial response (no pre-stretch) is springs_volume's
        try:
            out["continuum_uniaxial_cubic_coefficient"] = {"model": lattice, **cubic_coefficient_record(
                mat, strain_range=UNIAXIAL_STRAIN_RANGE, fields=fields, covariance=cov)}
        except (DifftissueError, RuntimeError) as err:
            out["continuum_uniaxial_cubic_coefficient"] = _not_computed(err)
    return out or None


def _derived_md(derived: Mapping | None) -> list[str]:
    """report.md's "Derived quantities" section."""
    if not derived:
        return []
    lines = ["", "## Derived quantities"]
    for r in derived.get("surface_tension", ()):
        if r.get("status") == "not computed":
            lines += ["", f"**Surface tension** ({r['scenario']}, {r['model']}): not computed ({r['reason']})."]
            continue
        se = f" ± {r['standard_error']:.3g}" if r.get("standard_error") is not None else ""
        layers = ", ".join(f"{d['name']} {1e3 * d['thickness']:.4g} mm" for d in r["layers"])
        if "value_y" in r:  # anisotropic pre-stretch
            se_y = f" ± {r['standard_error_y']:.3g}" if r.get("standard_error_y") is not None else ""
            lines += ["", f"**Surface tensions** ({r['scenario']}, model {r['model']}, pre_stretch {r['pre_stretch']:.6g} along x, "
                      f"pre_stretch_y {r['pre_stretch_y']:.6g}, layer {layers}): **T_x = {r['value']:.4g}{se} N/m, "
                      f"T_y = {r['value_y']:.4g}{se_y} N/m**, the in-plane forces per unit in-vivo length across a line along y "
                      "(T_x) and along x (T_y), from the model's own biaxial stress with free top and bottom. The linear "
                      f"formulas give {r['linearised_surface_tension']:.4g} and {r['linearised_surface_tension_y']:.4g} N/m "
                      "(`linearised_surface_tension`, `_y` in fit.json)."]
            continue
        lines += ["", f"**Surface tension** ({r['scenario']}, model {r['model']}, pre_stretch {r['pre_stretch']:.6g}, layer {layers}): "
                  f"**T = {r['value']:.4g}{se} N/m**, the in-plane force per unit in-vivo length the model's layer carries "
                  "(its own equibiaxial stress with free top and bottom: Cauchy stress x current thickness). "
                  f"The linear formula E (lambda0 - 1) t / (1 - nu) gives {r['linearised_surface_tension']:.4g} N/m"
                  + (f" ({r['linearised_over_model']:.3f} x the model's)" if r.get("linearised_over_model") else "")
                  + " (`linearised_surface_tension` in fit.json)."]
    b = derived.get("continuum_uniaxial_cubic_coefficient")
    if b and b.get("status") == "not computed":
        lines += ["", f"**Continuum cubic coefficient**: not computed ({b['reason']})."]
    elif b:
        lo, hi = b["strain_range"]
        se = f" ± {b['standard_error']:.3g}" if b.get("standard_error") is not None else ""
        others = ", ".join(f"{d}: {v:.4g}" for d, v in b["by_direction"].items() if d != "[100]")
        ends = b["stress_over_E_at_range_ends"]
        lines += ["", f"**Continuum cubic coefficient**: {b.get('model', 'springs_volume')}'s cubic_coefficient b = {b['lattice_cubic_coefficient']:.6g} is the "
                  "lattice's spring coefficient (a = b k / L0^2), not the b of a continuum law. In homogeneous uniaxial stress "
                  f"(nominal stress, engineering strain in [{lo:g}, {hi:g}], lateral faces free) the lattice follows "
                  f"sigma = E (eps + b_c eps^3) best with **b_c = {b['value']:.4g}{se}** along a cell edge of a cube lattice"
                  + (f" ({others})" if others else "")
                  + f"; at b = 0 the lattice alone gives b_c = {b['at_lattice_b_zero']['[100]']:.4g}, and b_c changes by "
                  f"{b['continuum_b_per_lattice_b']['[100]']:.3g} per unit b. sigma/E at eps = {lo:g} / {hi:g}: lattice "
                  f"{ends['lattice'][0]:.4g} / {ends['lattice'][1]:.4g}, the law {ends['continuum_law'][0]:.4g} / {ends['continuum_law'][1]:.4g} "
                  "(neo-Hookean at nu = 0.45: 0.239 / -0.434 at eps = 0.3 / -0.3, docs/theory.md). "
                  "Give a continuum solver b_c for this strain range, never b (`continuum_uniaxial_cubic_coefficient` in fit.json)."]
    return lines


#: SI prefixes for plot axes, by unit: (factor, label).
_PREFIXES = {
    "m": ((1e-9, "nm"), (1e-6, "µm"), (1e-3, "mm"), (1.0, "m")),
    "N": ((1e-9, "nN"), (1e-6, "µN"), (1e-3, "mN"), (1.0, "N")),
    "Pa": ((1.0, "Pa"), (1e3, "kPa"), (1e6, "MPa"), (1e9, "GPa")),
}


def human_unit(values, unit: str) -> tuple[float, str]:
    """``(factor, label)`` such that ``values / factor`` reads well in ``label``: the largest
    prefix of ``unit`` (m, N, Pa; strain ``-``/``1`` as %) not above max|values|; other units as given."""
    v = np.asarray(values, dtype=float)
    peak = float(np.nanmax(np.abs(v))) if v.size and np.any(np.isfinite(v)) else 0.0
    if unit in ("-", "1"):
        return 0.01, "%"
    choices = _PREFIXES.get(unit)
    if not choices:
        return 1.0, unit
    best = choices[0]
    for f, label in choices:
        if peak >= f:
            best = (f, label)
    return best


def _split_label(label: str) -> tuple[str, str]:
    """``"depth [m]"`` -> ``("depth", "m")``; no unit -> ``(label, "")``."""
    m = re.match(r"^(.*?)\s*\[([^\]]*)\]\s*$", label)
    return (m.group(1), m.group(2)) if m else (label, "")


def _value_text(value: float, se: float, unit: str) -> str:
    """``"158.5 ± 0.96 Pa"`` in a human prefix of ``unit`` (SI value and standard error)."""
    f, u = human_unit([value], unit) if unit in _PREFIXES else (1.0, unit_text(unit))
    se_txt = f" ± {se / f:.2g}" if se is not None and math.isfinite(se) else " (se not determined)"
    return f"{value / f:.4g}{se_txt} {u}".rstrip()


def _fit_title(result: FitResult) -> str:
    """The figure's title: each fitted value with its standard error, E* where named, the quality verdict."""
    parts = [f"{f} = {_value_text(result.values[f], result.standard_errors[f], result.units[f])}" for f in result.fields]
    em = result.effective_modulus
    if em is not None:
        parts.append(f"E* = E/(1-ν²) = {_value_text(em['value'], em['standard_error'], 'Pa')} (ν = {em['poisson_ratio_assumed']:g} assumed)")
    if result.quality is not None:
        parts.append(f"quality: {result.quality.summary()}")
    return "\n".join(parts)


def _plot_curve(top, bottom, s: ScenarioFit) -> None:
    """Data with sigma bars and the model against the abscissa, in human units; residuals below."""
    xname, xunit = _split_label(s.x_label)
    yname, yunit = _split_label(s.y_label)
    fx, ux = human_unit(s.abscissa, xunit)
    fy, uy = human_unit(s.observed, yunit)
    x = np.asarray(s.abscissa) / fx
    top.errorbar(x, s.observed / fy, yerr=s.sigma / fy, fmt="o", ms=3, lw=0.8, color="0.3", label="data")
    # the model as lines along each increasing run of the abscissa (a scenario may concatenate
    # several outputs or loading segments); as markers when the points are not ordered
    runs = np.split(np.arange(x.size), np.nonzero(np.diff(x) < 0)[0] + 1)
    if min(len(r) for r in runs) >= 2:
        for i, run in enumerate(runs):
            top.plot(x[run], s.predicted[run] / fy, "-", color="C0", lw=1.6, label="model" if i == 0 else None)
    else:
        top.plot(x, s.predicted / fy, "x", color="C0", ms=5, label="model")
    top.set_ylabel(f"{yname} [{uy}]" if uy else yname)
    top.legend(frameon=False)
    bottom.plot(x, s.residual, "o", ms=3, color="C3")
    bottom.set_xlabel(f"{xname} [{ux}]" if ux else xname)


def _plot_fem_field(axes, s: ScenarioFit) -> None:
    """A fem_field scenario: displacement profile (each observed component against the node's
    distance from the most displaced node, data dots, model crosses), its residuals, and the
    reaction force in its own panel (magnitude, with the direction said in the label)."""
    top, bottom, side = axes
    lay = s.layout
    nd = len(lay["components"])
    pts = np.asarray(lay["points"], dtype=float)
    comp = np.asarray(lay["components"], dtype=int)
    obs_u, pred_u, res_u = s.observed[:nd], s.predicted[:nd], s.residual[:nd]
    centre = pts[int(np.argmax(np.abs(obs_u)))]
    r = np.linalg.norm((pts - centre)[:, :2], axis=1)
    fr, ur = human_unit(r, "m")
    fu, uu = human_unit(obs_u, "m")
    for c in np.unique(comp):
        k = comp == c
        top.plot(r[k] / fr, obs_u[k] / fu, "o", ms=3.5, color=f"C{c}", alpha=0.8, label=f"u{'xyz'[c]} data")
        top.plot(r[k] / fr, pred_u[k] / fu, "x", ms=5, mew=1.4, color=f"C{c}", label=f"u{'xyz'[c]} model")
        bottom.plot(r[k] / fr, res_u[k], "o", ms=3, color=f"C{c}")
    top.set_ylabel(f"displacement [{uu}]")
    top.set_title(f"{s.name}: displacement profile")
    top.legend(frameon=False, fontsize=8, ncol=2)
    bottom.set_xlabel(f"lateral distance from the most displaced node [{ur}]")
    forces = lay["force_components"]
    if side is None:
        return
    if not forces:
        side.set_axis_off()
        return
    F_obs, F_pred, F_sig = s.observed[nd:], s.predicted[nd:], s.sigma[nd:]
    ff, uf = human_unit(F_obs, "N")
    idx = np.arange(len(forces))
    side.bar(idx - 0.15, np.abs(F_obs) / ff, 0.3, yerr=F_sig / ff, color="0.6", label="measured")
    side.bar(idx + 0.15, np.abs(F_pred) / ff, 0.3, color="C0", label="model")
    side.set_xlim(-0.75, len(forces) - 0.25)
    side.set_xticks(idx, [f"{'-' if o < 0 else '+'}{c}" for c, o in zip(forces, F_obs)])
    side.set_ylabel(f"reaction force magnitude [{uf}]")
    side.set_xlabel("reaction direction (-z: pushed into the specimen)")
    side.set_title("reaction force")
    for i, (o, p) in enumerate(zip(F_obs, F_pred)):
        side.annotate(f"{abs(o) / ff:.4g} / {abs(p) / ff:.4g}", (i, max(abs(o), abs(p)) / ff), ha="center", va="bottom", fontsize=8)
    side.legend(frameon=True, fontsize=8, loc="lower center")


def _fixed_margins(width, height, *, left, right, bottom, top, wspace, hspace, rows, cols) -> dict:
    """``gridspec_kw`` of a fixed layout: margins and gaps in inches for a figure of
    ``width`` x ``height`` inches with a ``rows`` x ``cols`` grid of panels."""
    w = (width - left - right - wspace * (cols - 1)) / cols
    h = (height - top - bottom - hspace * (rows - 1)) / rows
    return {"left": left / width, "right": 1.0 - right / width, "bottom": bottom / height, "top": 1.0 - top / height,
            "wspace": wspace / w, "hspace": hspace / h}


def _plot_fit(result: FitResult, path: Path):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    k = len(result.scenarios)
    fem = [s.layout is not None and s.layout.get("kind") == "fem_field" for s in result.scenarios]
    cols = k + sum(fem)  # a fem_field scenario gets a second column for its force
    title = _fit_title(result)
    width, height = 5.0 * cols, 6.0
    fig = Figure(figsize=(width, height))
    # A fixed layout in inches (matplotlib's constrained layout measured every text's extent,
    # ~0.2 s CPU per report): room for the title's lines, the panel titles, the y labels of each
    # column and, between the rows, the top panels' tick labels (and a fem_field force panel's
    # x label).
    top_in = 0.1 + 9.0 / 72.0 * 1.25 * (title.count("\n") + 1) + 0.3
    axes = fig.subplots(2, cols, height_ratios=[3, 1], squeeze=False,
                        gridspec_kw=_fixed_margins(width, height, left=0.9, right=0.15, bottom=0.55, top=top_in,
                                                   wspace=1.0, hspace=0.85 if any(fem) else 0.35, rows=2, cols=cols))
    j = 0
    for s, is_fem in zip(result.scenarios, fem):
        top, bottom = axes[0, j], axes[1, j]
        bottom.sharex(top)
        if is_fem:
            side = axes[0, j + 1]
            axes[1, j + 1].set_axis_off()
            _plot_fem_field((top, bottom, side), s)
            j += 2
        else:
            _plot_curve(top, bottom, s)
            top.set_title(s.name)
            j += 1
        bottom.axhline(0.0, color="0.6", lw=0.8)
        bottom.set_ylabel("residual / sigma")
    fig.suptitle(title, fontsize=9, y=1.0 - 0.1 / height, va="top")
    fig.savefig(path, format="png", dpi=110)


def _plot_loss(result: FitResult, path: Path):
    from matplotlib.figure import Figure

    width, height = 5.5, 3.8
    fig = Figure(figsize=(width, height))
    ax = fig.subplots(gridspec_kw=_fixed_margins(width, height, left=0.8, right=0.15, bottom=0.55, top=0.35, wspace=0.0, hspace=0.0, rows=1, cols=1))
    H = np.asarray(result.loss_history, dtype=float)
    steps = np.arange(H.shape[0])
    tiny = np.finfo(float).tiny
    for s in range(H.shape[1]):
        best = s == result.best_start
        ax.plot(steps, np.clip(H[:, s], tiny, None), color="C0" if best else "0.7", lw=1.8 if best else 0.8, label="best start" if best else None, zorder=3 if best else 2)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss [-]")
    ax.set_title(f"{result.method}, {H.shape[1]} start(s)")
    ax.legend(frameon=False)
    fig.savefig(path, format="png", dpi=110)


def _quality_md(quality: "FitQuality | None") -> list[str]:
    """The report's "Quality" section: verdict, flags, residual statistics per scenario."""
    if quality is None:
        return []
    verdict = {"ok": "**OK**: no quality flag raised.",
               "warnings": "**Usable, with warnings** (see below).",
               "unusable": "**UNUSABLE**: do not use these values (the CLI exits with status 3)."}[quality.verdict]
    lines = ["", "## Quality", "", verdict]
    if quality.flags:
        lines += ["", "| flag | severity | subject | finding |", "|---|---|---|---|"]
        lines += [f"| {f.name} | {f.severity} | {f.subject or '-'} | {f.message} |" for f in quality.flags]
    lines += ["", "| scenario | points | rms residual/sigma | lag-1 autocorrelation | sign runs (expected) | runs test p |", "|---|---|---|---|---|---|"]
    fmt = lambda x, spec: "-" if x is None or not np.isfinite(x) else format(x, spec)  # noqa: E731
    for name, st in quality.scenarios.items():
        lines.append(f"| {name} | {st['points']} | {fmt(st['rms'], '.3g')} | {fmt(st['lag1_autocorrelation'], '.2f')} | "
                     f"{st['runs']} ({fmt(st['runs_expected'], '.1f')}) | {fmt(st['runs_p'], '.2g')} |")
    lines += ["", f"Thresholds: errors for a parameter within {BOUND_FRACTION:g} of a transform bound, a value outside its plausible range "
              f"(E in [{PLAUSIBLE['youngs_modulus'][0]:g}, {PLAUSIBLE['youngs_modulus'][1]:g}] Pa unless fit.plausible says otherwise), "
              f"non-finite values, no convergence; warnings for rms residual/sigma > {RMS_LIMIT:g}, lag-1 autocorrelation > "
              f"{AUTOCORRELATION_LIMIT:g} or runs test p < {RUNS_P_LIMIT:g} (judged where rms >= {STRUCTURE_MIN_RMS:g}); "
              "a warning where the mesh's estimated share of a value's error exceeds its standard error (discretisation_error)."]
    return lines


def simulation_record(scenario) -> dict | None:
    """How a simulated experiment was modelled, for ``fit.json`` (``simulation``) and the
    report: the model and the resolution its fitted numbers belong to.

    - an indentation: ``{"name", "model", "geometry": "axisymmetric" | "3d",
      "cells_per_contact_radius"`` (at the deepest point) [-] ``, "resolution"}`` with
      ``resolution`` e.g. ``"axisymmetric, 8 cells per contact radius"``;
    - a compression, fem_field or incision: ``{"name", "model", "geometry": "3d", "nodes",
      "tets", "median_edge"`` [m] ``, "resolution"}``, e.g. ``"3-D mesh, 1183 nodes, 5400 tets,
      median edge 1.41 mm"`` (the mesh's tet edges, face diagonals of a cube lattice included);
    - None for the closed forms (no mesh)."""
    record = getattr(scenario, "record", None)
    if not callable(record):
        return None
    rec = record()
    if rec.get("experiment") in ("compression", "fem_field", "incision"):
        return _mesh_record(rec, getattr(scenario, "model", None))
    resolution = getattr(scenario, "resolution", None)
    if rec.get("experiment") != "indentation" or not callable(resolution):
        return None
    spec = rec.get("specimen") or {}
    geometry = rec.get("geometry", "3d")
    try:
        m = float(spec["cells_per_contact_radius"]) if geometry == "axisymmetric" and "cells_per_contact_radius" in spec \
            else float(np.max(resolution().cells_per_contact_radius))
    except DifftissueError:
        return None
    where = "axisymmetric" if geometry == "axisymmetric" else "3-D block"
    return {"name": rec.get("name"), "model": rec.get("model"), "geometry": geometry, "cells_per_contact_radius": m,
            "resolution": f"{where}, {m:.3g} cells per contact radius"}


def _mesh_record(rec: Mapping, model) -> dict | None:
    """:func:`simulation_record` of a scenario on a tet mesh (its model's ``rest_points`` and
    ``tets``); None when the model does not expose them."""
    points, tets = getattr(model, "rest_points", None), getattr(model, "tets", None)
    if points is None or tets is None:
        return None
    points, tets = np.asarray(points, dtype=float), np.asarray(tets, dtype=np.int64)
    edges = unique_edges(tets)
    h = float(np.median(np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)))
    n, m = int(points.shape[0]), int(tets.shape[0])
    return {"name": rec.get("name"), "model": rec.get("model"), "geometry": "3d", "nodes": n, "tets": m, "median_edge": h,
            "resolution": f"3-D mesh, {n} nodes, {m} tets, median edge {h * 1e3:.3g} mm"}


def _discretisation_md(rec: Mapping | None) -> list[str]:
    """The report's "Discretisation error" section (nothing when the check was off)."""
    if rec is None or rec.get("status") == "not applicable":
        return []
    lines = ["", "## Discretisation error", ""]
    if rec.get("status") == "estimated":
        lines += ["| parameter | estimate (fit - mesh-converged) | relative | standard error | estimate / SE | mesh-converged value |", "|---|---|---|---|---|---|"]
        for f, d in rec["estimate"].items():
            se, ratio = rec["standard_error"][f], rec["ratio_to_standard_error"][f]
            se_txt = "none (no residual degrees of freedom)" if math.isnan(se) else f"{se:.4g}"
            lines.append(f"| {f} | {d:+.4g} | {100 * rec['relative'][f]:+.3g} % | {se_txt} | "
                         f"{ratio:.3g} | {rec['corrected'][f]:.6g} |".replace("| nan |", "| - |"))
        lines.append("")
    lines.append("| scenario | status | cells (fit / coarse) | prediction change | order | reason |")
    lines.append("|---|---|---|---|---|---|")
    for k, v in rec["scenarios"].items():
        cells = f"{v.get('fine_cells')} / {v.get('coarse_cells')}" + (f" / {v['coarser_cells']}" if v.get("coarser_cells") is not None else "")
        if v["status"] == "estimated":
            order = f"{v['order']:.3g} ({v.get('order_source', 'assumed')})"
            lines.append(f"| {k} | estimated | {cells} | {100 * v['prediction_change_relative']:.3g} % | {order} | - |")
        elif "fine_cells" in v:  # evaluated on the coarser meshes, refused by the three-level check
            lines.append(f"| {k} | not estimated | {cells} | {100 * v['prediction_change_relative']:.3g} % | - | {v['reason']} |")
        else:
            lines.append(f"| {k} | not estimated | - | - | - | {v['reason']} |")
    for k, v in rec["scenarios"].items():
        a = v.get("specimen")
        if a and a.get("geometry") == "axisymmetric":
            lines += ["", f"{k}: specimen chosen automatically ({a['rule']}): axisymmetric, {a['cells_per_contact_radius']:g} cells per contact "
                      f"radius (first cells {a['first']:.4g} m = contact radius {a['contact_radius']:.4g} m / {a['cells_per_contact_radius']:g}; "
                      f"a cylinder of radius {a['radius']:.4g} m and height {a['height']:.4g} m"
                      + ("" if not a.get("thickness_given") else ", the specimen's thickness") + "); "
                      + ("the coarser meshes multiply every cell by sqrt(2) and 2; the order of convergence is the one these three levels show."
                         if v.get("coarser_cells") is not None else f"the coarser mesh doubles every cell; Richardson order {v.get('order', 2):g}.")]
        elif a:
            lines += ["", f"{k}: specimen chosen automatically ({a['rule']}): cells {a['cells']}, first cells {a['refine']:.4g} m = contact radius "
                      f"{a['contact_radius']:.4g} m / {a['cells_per_contact_radius']:g}; "
                      + (f"the convergence study's force error at this resolution is {100 * a['force_error']:+.2g} % (a fitted E about "
                         f"{-100 * a['force_error'] / (1 + a['force_error']):+.2g} %)." if a.get("force_error") is not None
                         else "no tabulated force error for this indenter.")]
    orders = sorted({float(v.get("order", 1.0)) for v in rec["scenarios"].values() if v["status"] == "estimated"})
    how = "first-order" if orders in ([], [1.0]) else "order-" + " / ".join(f"{q:.3g}" for q in orders)
    lines += ["", "One evaluation at the fitted values on a coarser mesh (about half the cells in each direction; two coarser meshes where "
              "the order is observed), no refit; "
              f"Richardson extrapolation with {how} convergence in the cell size gives the fit mesh's error in the "
              "predictions, converted to the parameters through the fit's Jacobian (linearised). An estimate, not a bound: "
              "see docs/fitting.md, \"Discretisation error\"."]
    return lines


def _start_md(start) -> list[str]:
    """report.md's "Starting values": each field whose start the data chose (or tried to)."""
    if not start:
        return []
    lines = ["", "## Starting values", "", "| parameter | start | config's [material] | from |", "|---|---|---|---|"]
    for f, d in start.items():
        how = f"{d['from']} (no estimate from the data: {d['no_estimate']})" if d.get("no_estimate") else d["from"]
        lines.append(f"| {f} | {d['value']:.6g} | {d['config_value']:.6g} | {how} |")
    return lines + ["", 'fit.start = "material" starts from the config\'s [material] instead.']


def _report_md(result: FitResult, record: dict, names: Sequence[str]) -> str:
    lines = ["# Fit report", ""]
    lines.append(f"Model: {record['model'] or '(not given)'}; scenarios: {', '.join(names)}.")
    for sim in record.get("simulation") or ():
        lines.append(f"Simulation of {sim['name']}: {sim['model']}, {sim['resolution']}.")
    lines.append(
        f"Method {result.method}, loss {result.loss_function}"
        + (f" (f_scale {result.f_scale:g})" if result.loss_function != "linear" else "")
        + f", {int(result.start_losses.size)} start(s) (best: {result.best_start})."
    )
    lines.append(f"**{'Converged' if result.converged else 'Not converged'}** after {result.steps} steps: {result.reason}. Final loss {result.loss:.6g}."
                 + (f" Quality: {result.quality.summary()}." if result.quality is not None else ""))
    lines += ["", "## Parameters", "", "| parameter | value | standard error | relative | unit |", "|---|---|---|---|---|"]
    for f in result.fields:
        v, se = result.values[f], result.standard_errors[f]
        rel = f"{100 * se / abs(v):.3g} %" if v != 0 and math.isfinite(se) else "-"
        se_txt = f"{se:.4g}" if math.isfinite(se) else "not determined"
        lines.append(f"| {f} | {v:.6g} | {se_txt} | {rel} | {unit_text(result.units[f]) or '-'} |")
    if result.effective_modulus is not None:
        em = result.effective_modulus
        se = em["standard_error"]
        lines += ["", f"**Effective modulus E\\* = E/(1-nu^2) = {em['value']:.6g}"
                  + (f" ± {se:.4g}" if math.isfinite(se) else "") + f" Pa** ({em['law']}). {em['meaning']}."]
    cov_txt = "(J^T J)^-1 (absolute sigma)" if result.absolute_sigma else f"s^2 (J^T J)^-1 with s^2 = SSE/(n-p) = {result.residual_variance:.4g} (n-p = {result.dof})"
    lines += ["", f"Standard errors from the Gauss-Newton covariance {cov_txt}; condition number of J^T J (scaled) {result.condition_number:.3g}."]
    if record["fixed_parameters"]:
        lines += ["", "Fixed: " + ", ".join(f"{k} = {d['value']:g}{' ' + unit_text(d['unit']) if unit_text(d['unit']) else ''}" for k, d in record["fixed_parameters"].items()) + "."]
    lines += _start_md(record.get("start"))
    lines += _quality_md(result.quality)
    lines += _discretisation_md(result.discretisation)
    lines += _derived_md(record.get("derived"))
    if len(result.fields) > 1:
        lines += ["", "## Correlations", "", "| | " + " | ".join(result.fields) + " |", "|---" * (len(result.fields) + 1) + "|"]
        for i, f in enumerate(result.fields):
            cells = [f"{c:+.3f}" if np.isfinite(c) else "-" for c in result.correlation[i]]
            lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", "## Warnings", ""]
    data_warnings = [f"- data: {w}" for w in record.get("data_warnings", ())]
    lines += data_warnings + [f"- {w}" for w in result.warnings] or ["None from the data or identifiability checks (every parameter is determined by the data); the fit's quality flags are under Quality."]
    if record.get("data_rows"):
        lines += ["", "## Data rows", "", "| experiment | file | rows used | rows loaded | left out or reordered |", "|---|---|---|---|---|"]
        for d in record["data_rows"]:
            steps = "; ".join(f"{st['action']} {len(st['rows'])}: {st['reason']}" for st in d["steps"]) or "-"
            lines.append(f"| {d['experiment']} | `{Path(d['file']).name}` | {d['rows_used']} | {d['rows_loaded']} ({d['loaded']}) | {steps} |")
        lines += ["", "The row numbers are in `fit.json` (`data_rows`)."]
    lines += ["", "## Scenarios", "", "| scenario | points | rms residual / sigma |", "|---|---|---|"]
    for s in result.scenarios:
        lines.append(f"| {s.name} | {s.observed.size} | {np.sqrt(np.mean(s.residual ** 2)):.4g} |")
    lines += ["", "## Files", "", "- `fit.json`: parameters, uncertainty, versions", "- `material.json`: the material card for `difftissue export`", "- `fit.png`: data vs model with residuals", "- `loss.png`: loss history"]
    for d in record["data_files"]:
        lines.append(f"- data `{d['path']}` (sha256 `{d['sha256']}`)")
    lines += ["", "Versions: " + ", ".join(f"{k} {v}" for k, v in record["versions"].items() if v) + "."]
    return "\n".join(lines) + "\n"


def write_fit_outputs(
    result: FitResult,
    out_dir,
    *,
    config=None,
    data_files: Sequence[str | os.PathLike] = (),
    model=None,
    scenario_names: Sequence[str] | None = None,
    force: bool = False,
    scenario_records: Sequence[dict] | None = None,
    scenarios: Sequence | None = None,
    data: Sequence[Mapping] = (),
    data_warnings: Sequence[str] = (),
    start: Mapping | None = None,
) -> dict[str, Path]:
    """Write ``fit.json``, ``material.json``, ``fit.png``, ``loss.png`` and ``report.md`` into
    ``out_dir``, and ``specimen-<name>.vtu`` for each simulated ``fem_field``, ``compression``
    or ``incision`` scenario among ``scenarios``.

    ``material.json`` is the versioned material card (:class:`~difftissue.export.MaterialCard`)
    that ``difftissue export`` reads: model, energy, parameters with units and standard
    errors, provenance.

    Args:
        result: a :class:`FitResult`.
        out_dir: output directory (created if missing).
        config: the run's configuration: a mapping (stored as is) or a config file path
            (stored with its sha256 and, for TOML, its parsed content).
        data_files: measured-data files used by the fit; each is recorded with its sha256.
        model: model name (str) or object (its ``name`` or type name is recorded).
        scenario_names: names to record instead of the result's scenarios.
        scenario_records: per-scenario experiment records for the card
            (:func:`difftissue.export.card.scenario_record`: indenter, radius, depths, ...),
            used by ``difftissue export --specimen indentation``; default (with ``scenarios``)
            ``scenario_record(s)`` of each scenario.
        scenarios: the fitted scenarios: each :class:`~difftissue.scenarios.FEMField`,
            :class:`~difftissue.scenarios.Compression` and :class:`~difftissue.incision.Incision`
            gets its specimen file
            (:func:`difftissue.export.fitted.write_specimen`: mesh, fixed masks, prescribed
            displacements, regions, cut pairs), recorded with its sha256 in its scenario record
            (``specimen_file``), which ``difftissue export --specimen fitted`` reads.
        data: the rows of each data file the fit used and those it reordered or left out, with
            why (:attr:`difftissue.config.FitConfig.data_provenance`); recorded as ``data_rows``
            in ``fit.json`` and in the report's "Data rows" section.
        data_warnings: plausibility warnings of the data (a likely unit mistake, ...); recorded
            as ``data_warnings`` in ``fit.json`` and first under the report's "Warnings".
        start: where the initial values came from when the data chose them
            (:attr:`difftissue.config.FitConfig.start`); recorded as ``start`` in ``fit.json``.
        force: overwrite existing output files. Without it, an existing file among the five
            (or a specimen file to be written) raises :class:`~difftissue.errors.OutputExistsError`
            naming it, before anything is written.

    Every file is written atomically (temporary file beside it, then ``os.replace``).

    Returns:
        ``{file name: path}`` of the written files.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory")
    paths = {name: out / name for name in OUTPUT_FILES}
    specimens = {}
    if scenarios is not None:
        if scenario_records is None:
            scenario_records = [scenario_record(s) for s in scenarios]
        for s in scenarios:
            sp = fitted_specimen(s)
            if sp is None:
                continue
            fname = specimen_file_name(sp.scenario)
            if fname in specimens:
                raise OutputError(f"scenarios {specimens[fname].scenario!r} and {sp.scenario!r} would share the specimen file {fname}: give them distinct names")
            specimens[fname] = sp
        paths.update({fname: out / fname for fname in specimens})
    if not force:
        for p in paths.values():
            if p.exists():
                raise OutputExistsError(f"{p} exists; refusing to overwrite it (choose another output directory or pass force=True / --force)")
    for p in data_files:
        if not Path(p).is_file():
            raise OutputError(f"data file {p} does not exist")
    names = list(scenario_names) if scenario_names is not None else list(result.scenario_names)
    model_name = None if model is None else (model if isinstance(model, str) else getattr(model, "name", None) or type(model).__name__)
    record = _fit_json(result, config=config, data_files=data_files, model=model, scenario_names=scenario_names)
    record["data_warnings"] = [str(w) for w in data_warnings]
    record["data_rows"] = [dict(d) for d in data]
    record["start"] = jsonable(start) if start else None
    record["derived"] = jsonable(derived_quantities(result, model=model_name, scenarios=scenarios))
    record["simulation"] = [r for r in (simulation_record(s) for s in scenarios or ()) if r is not None]
    out.mkdir(parents=True, exist_ok=True)
    with atomic_output(paths["fit.json"], overwrite=force) as tmp:
        tmp.write_text(json.dumps(record, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    if specimens:
        scenario_records = [dict(r) if r else r for r in scenario_records]
        for fname, sp in specimens.items():
            write_specimen(sp, paths[fname], force=force)
            matched = [r for r in scenario_records if r and r.get("name") == sp.scenario]
            if not matched:
                scenario_records.append({"name": sp.scenario, "experiment": sp.experiment, "model": sp.model})
                matched = scenario_records[-1:]
            for r in matched:
                r["specimen_file"] = specimen_record(sp, paths[fname])
    card = card_from_fit(result, model=model_name or "unspecified", scenario_names=names, data_files=data_files,
                         scenario_records=scenario_records, base_dir=_config_dir(config))
    if record["derived"]:
        card.provenance["derived"] = record["derived"]
    with atomic_output(paths["material.json"], overwrite=force) as tmp:
        tmp.write_text(card.to_json(), encoding="utf-8")
    with atomic_output(paths["fit.png"], overwrite=force) as tmp:
        _plot_fit(result, tmp)
    with atomic_output(paths["loss.png"], overwrite=force) as tmp:
        _plot_loss(result, tmp)
    with atomic_output(paths["report.md"], overwrite=force) as tmp:
        tmp.write_text(_report_md(result, record, names), encoding="utf-8")
    if force:
        _remove_stale_specimens(out, keep=set(specimens))
    return paths


def _remove_stale_specimens(out: Path, keep: set) -> list[Path]:
    """Remove the ``specimen-*.vtu`` files of an earlier fit in ``out`` that this fit did not
    write (``--force``: the folder then holds one fit's outputs, not a mix of two)."""
    removed = []
    for p in sorted(out.glob("specimen-*.vtu")):
        if p.name not in keep:
            p.unlink()
            removed.append(p)
    return removed
