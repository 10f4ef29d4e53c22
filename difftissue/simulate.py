"""Run the forward model of a fit config's experiments at one material, without fitting.

``difftissue simulate CONFIG.toml --out DIR`` is the "what does this material predict?"
half of ``difftissue fit``: the same experiments (scenarios, data, sigma) are evaluated at the
config's ``[material]`` -- or at values given on the command line -- and compared with the
measured data. Outputs, each written atomically and never over an existing file unless
``force``:

* ``DIR/simulation.json`` (schema ``difftissue-simulation/1``): the material (SI), and per
  experiment the abscissa, observed and predicted values, their units (axis labels), the
  RMS of the weighted residual ``(predicted - observed) / sigma`` [-], the relative RMS
  error ``rms(predicted - observed) / rms(observed)`` [-] and the wall time of the solve;
* ``DIR/<experiment>.csv``: ``abscissa, observed, predicted, sigma`` columns (SI units in the
  header);
* ``DIR/simulation.png``: data and prediction of every experiment.

A model evaluation that fails (a static solve that does not converge, an inverted element)
is raised as :class:`~difftissue.errors.SimulationError` with the experiment's name, never
written as a number.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ._io import atomic_output, jsonable
from .errors import DifftissueError, OutputError, OutputExistsError, SimulationError

__all__ = ["SimulatedExperiment", "SimulationError", "simulate_config", "write_simulation_outputs", "SIMULATION_FILES"]

#: Files written by :func:`write_simulation_outputs` besides one ``<experiment>.csv`` each.
SIMULATION_FILES = ("simulation.json", "simulation.png")


@dataclasses.dataclass(frozen=True)
class SimulatedExperiment:
    """One experiment's prediction at one material (all arrays SI, shape ``(n,)``).

    Attributes:
        name: the experiment (scenario) name.
        kind: the config's scenario kind (``"indentation"``, ``"compression"``, ...).
        model: the energy model name, or None for analytic scenarios.
        abscissa, observed, predicted, sigma: plot abscissa, data, model, measurement scale.
        x_label, y_label: axis labels with units.
        seconds: wall time of the evaluation, compilation included [s].
    """

    name: str
    kind: str
    model: str | None
    abscissa: np.ndarray
    observed: np.ndarray
    predicted: np.ndarray
    sigma: np.ndarray
    x_label: str
    y_label: str
    seconds: float

    @property
    def weighted_rms(self) -> float:
        """RMS of ``(predicted - observed) / sigma`` [-]."""
        return float(np.sqrt(np.mean(((self.predicted - self.observed) / self.sigma) ** 2)))

    @property
    def relative_rms(self) -> float:
        """``rms(predicted - observed) / rms(observed)`` [-] (inf when the data are all zero)."""
        den = float(np.sqrt(np.mean(self.observed**2)))
        num = float(np.sqrt(np.mean((self.predicted - self.observed) ** 2)))
        return num / den if den > 0 else math.inf


def _material_with(material, overrides: Mapping[str, float] | None):
    """``material`` with the given fields replaced; the Material constructor validates them."""
    if not overrides:
        return material
    from .materials import Material

    known = tuple(f.name for f in dataclasses.fields(Material))
    for k in overrides:
        if k not in known:
            raise SimulationError(f"unknown material field {k!r}; expected one of {', '.join(known)}")
    values = {k: getattr(material, k) for k in known}
    values.update({k: float(v) for k, v in overrides.items()})
    return Material(**values)


def simulate_config(cfg, material=None, *, overrides: Mapping[str, float] | None = None, on_experiment=None) -> tuple:
    """Evaluate every experiment of a loaded config (:func:`difftissue.config.load_config`).

    Args:
        cfg: a :class:`~difftissue.config.FitConfig`.
        material: the :class:`~difftissue.materials.Material` to evaluate (default: the
            config's ``[material]`` as written, :attr:`~difftissue.config.FitConfig.config_material`;
            a fit may start elsewhere, from the data).
        overrides: fields of the material to replace, in SI units, e.g.
            ``{"youngs_modulus": 12e3}``.
        on_experiment: called as ``on_experiment(i, n, name)`` before experiment ``i`` of ``n``
            is evaluated (progress).

    Returns:
        the material used and a tuple of :class:`SimulatedExperiment`, in config order.

    Raises:
        SimulationError: a model evaluation failed or predicted a non-finite value.
    """
    base = getattr(cfg, "config_material", cfg.material) if material is None else material
    mat = _material_with(base, overrides)
    out = []
    for i, e in enumerate(cfg.experiments):
        if on_experiment is not None:
            on_experiment(i, len(cfg.experiments), e.name)
        sc = e.scenario
        t0 = time.perf_counter()
        try:
            pred = np.asarray(sc.predict(mat), dtype=float)
        except DifftissueError:
            raise
        except Exception as err:  # JAX runtime errors carry the equinox message
            msg = " ".join(str(err).split())[:300]
            raise SimulationError(f"experiment {e.name!r}: the model evaluation failed: {msg}") from err
        seconds = time.perf_counter() - t0
        obs = np.asarray(sc.observed, dtype=float)
        if pred.shape != obs.shape:
            raise SimulationError(f"experiment {e.name!r}: prediction shape {pred.shape} != data shape {obs.shape}")
        if not np.all(np.isfinite(pred)):
            bad = int(np.sum(~np.isfinite(pred)))
            raise SimulationError(f"experiment {e.name!r}: {bad} of {pred.size} predictions are not finite "
                                  "(a solve failed at this material; change the material or the solver options)")
        out.append(SimulatedExperiment(name=e.name, kind=e.kind, model=e.model, abscissa=np.asarray(sc.abscissa, dtype=float),
                                       observed=obs, predicted=pred, sigma=np.asarray(sc.sigma, dtype=float),
                                       x_label=sc.x_label, y_label=sc.y_label, seconds=seconds))
    return mat, tuple(out)


def _safe_stem(name: str) -> str:
    stem = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in name).strip("._")
    return stem or "experiment"


def _output_paths(out: Path, sims: Sequence[SimulatedExperiment]) -> dict[str, Path]:
    paths = {n: out / n for n in SIMULATION_FILES}
    for s in sims:
        name = f"{_safe_stem(s.name)}.csv"
        if name in paths:
            raise OutputError(f"two experiments map to the same output file {name}; give them distinct names")
        paths[name] = out / name
    return paths


def _plot(sims: Sequence[SimulatedExperiment], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = len(sims)
    fig, axes = plt.subplots(1, n, figsize=(4.5 * n, 3.6), squeeze=False)
    for ax, s in zip(axes[0], sims):
        ax.plot(s.abscissa, s.observed, "o", ms=3, label="data")
        ax.plot(s.abscissa, s.predicted, "-", label="model")
        ax.set_xlabel(s.x_label)
        ax.set_ylabel(s.y_label)
        ax.set_title(f"{s.name} (rel. RMS {100 * s.relative_rms:.2g} %)", fontsize=9)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120, format="png")
    plt.close(fig)


def write_simulation_outputs(material, sims: Sequence[SimulatedExperiment], out_dir, *, config=None,
                             force: bool = False) -> dict[str, Path]:
    """Write ``simulation.json``, ``simulation.png`` and one CSV per experiment into ``out_dir``.

    Existing files are refused (:class:`~difftissue.errors.OutputExistsError`, naming the
    first one, before anything is written) unless ``force``. Returns ``{file name: path}``.
    """
    from .report import config_record, package_versions  # JAX and matplotlib: imported when writing, as the module's other heavy imports

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    paths = _output_paths(out, sims)
    if not force:
        for p in paths.values():
            if p.exists():
                raise OutputExistsError(f"{p} exists; refusing to overwrite it (choose another --out or pass --force)")
    from .materials import FIELD_UNITS, material_fields

    mat = {k: float(getattr(material, k)) for k in material_fields(material)}
    record = {
        "schema": "difftissue-simulation/1",
        "material": mat,
        "units": {k: FIELD_UNITS[k] for k in mat},
        "experiments": [
            {"name": s.name, "kind": s.kind, "model": s.model, "x_label": s.x_label, "y_label": s.y_label,
             "abscissa": s.abscissa, "observed": s.observed, "predicted": s.predicted, "sigma": s.sigma,
             "weighted_rms": s.weighted_rms, "relative_rms": s.relative_rms, "seconds": s.seconds,
             "csv": paths[f"{_safe_stem(s.name)}.csv"].name}
            for s in sims
        ],
        "config": config_record(config),
        "versions": package_versions(),
    }
    for s in sims:
        with atomic_output(paths[f"{_safe_stem(s.name)}.csv"], overwrite=force) as tmp:
            header = f"abscissa ({s.x_label}),observed ({s.y_label}),predicted ({s.y_label}),sigma ({s.y_label})"
            np.savetxt(tmp, np.column_stack([s.abscissa, s.observed, s.predicted, s.sigma]), delimiter=",",
                       header=header, comments="", fmt="%.10g")
    with atomic_output(paths["simulation.png"], overwrite=force) as tmp:
        _plot(sims, tmp)
    with atomic_output(paths["simulation.json"], overwrite=force) as tmp:
        tmp.write_text(json.dumps(jsonable(record), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return paths
