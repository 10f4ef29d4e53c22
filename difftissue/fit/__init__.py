"""Fitting material parameters to measured curves: weighted (robust) least squares.

The fit works on a vector ``u`` of unconstrained reals; a
:class:`~difftissue.materials.MaterialParameterization` maps it through bounded transforms to
the fitted fields of a :class:`~difftissue.materials.Material`. Each scenario (one experiment:
an indentation curve, a compression curve, a displacement field, ...) predicts its observable
from the material; the residual vector is

    r(u) = concat_s (predict_s(material(u)) - observed_s) / sigma_s        [-]

and the loss is ``0.5 * f_scale^2 * sum(rho((r / f_scale)^2))`` with ``rho(z) = z`` (linear),
``2 (sqrt(1 + z) - 1)`` (soft_l1) or the Huber function (``z`` for ``z <= 1``, else
``2 sqrt(z) - 1``) -- the definitions of ``scipy.optimize.least_squares``.

Optimisers: optimistix Levenberg--Marquardt and Gauss--Newton on the (robustified) residual
vector, optax Adam and L-BFGS on the scalar loss. All starts of a multi-start fit run batched
with ``jax.vmap`` inside ONE jitted step function; a Python loop calls it once per step, so a
progress bar can be shown and checkpoints written, without recompiling.

After the fit, a Gauss--Newton covariance of the physical parameters, standard errors,
correlations and identifiability diagnostics are computed at the best start. See
``docs/fitting.md`` for the formulas and rules.

Batched and sharded fits of many specimens of one structure: :func:`fit_batch`
(:mod:`difftissue.fit.batch`), through the same engine and step loop.

Modules: :mod:`~difftissue.fit.problem` (:class:`Scenario`, :class:`FitProblem`),
:mod:`~difftissue.fit.result` (:class:`FitResult`), :mod:`~difftissue.fit.statistics`
(covariance, identifiability, quality gates, discretisation error, effective modulus),
:mod:`~difftissue.fit.engine` (the optimisers, tolerance defaults and THE step loop),
:mod:`~difftissue.fit.checkpoint`, :mod:`~difftissue.fit.driver` (:func:`fit`) and
:mod:`~difftissue.fit.batch` (:func:`fit_batch`). The package knows nothing of files beyond its
checkpoints, of scenarios beyond the :class:`Scenario` protocol, of export or of configs
(import-linter contracts in ``pyproject.toml``); the outputs of a fit (``fit.json``, figures,
``report.md``, the material card) are written by :mod:`difftissue.report`.

Units: the residuals and the loss are dimensionless (residuals are divided by ``sigma``, which
carries the unit of the observable); every parameter value and standard error is in SI
(:data:`UNITS`).
"""

import importlib as _importlib
import warnings as _warnings

from .problem import LOSSES, UNITS, FitProblem, Scenario
from .result import FitProgress, FitResult, ScenarioFit
from .statistics import (  # noqa: F401  (names importable from difftissue.fit, not all in __all__)
    AUTOCORRELATION_LIMIT,
    BOUND_FRACTION,
    CONDITION_LIMIT,
    CORRELATION_LIMIT,
    DISCRETISATION_METHOD,
    DISCRETISATION_ORDER,
    PLAUSIBLE,
    QUALITY_ERRORS,
    RELATIVE_SE_LIMIT,
    RMS_LIMIT,
    RUNS_P_LIMIT,
    STRUCTURE_MIN_POINTS,
    STRUCTURE_MIN_RMS,
    FitQuality,
    QualityFlag,
    assess_quality,
    discretisation_estimate,
    discretisation_line,
    effective_modulus,
    effective_modulus_line,
    identifiability_diagnostics,
    lag1_autocorrelation,
    parameter_statistics,
    runs_test,
    with_discretisation,
)
from .engine import ADAM_MAX_HALVINGS, METHODS, TOLERANCES
from .driver import fit
from .batch import BatchFitResult, fit_batch, specimen_mesh

__all__ = [
    "Scenario",
    "FitProblem",
    "FitProgress",
    "FitResult",
    "ScenarioFit",
    "fit",
    "fit_batch",
    "BatchFitResult",
    "specimen_mesh",
    "parameter_statistics",
    "identifiability_diagnostics",
    "assess_quality",
    "discretisation_estimate",
    "with_discretisation",
    "effective_modulus",
    "FitQuality",
    "QualityFlag",
    "PLAUSIBLE",
    "UNITS",
    "METHODS",
    "LOSSES",
    "TOLERANCES",
]

#: Output writers that lived in this module up to difftissue 0.1.0 and moved to :mod:`difftissue.report`
#: (fitting knows nothing of files): still importable from here, with a DeprecationWarning, for
#: one release. The import is by name at first access, so ``difftissue.fit`` itself does not
#: depend on the report (nor, through it, on export).
_MOVED_TO_REPORT = ("write_fit_outputs", "package_versions", "OUTPUT_FILES", "human_unit")


def __getattr__(name: str):
    if name in _MOVED_TO_REPORT:
        _warnings.warn(f"difftissue.fit.{name} moved to difftissue.report.{name}; import it from there "
                       "(the old path goes in the next release)", DeprecationWarning, stacklevel=2)
        return getattr(_importlib.import_module("difftissue.report"), name)
    raise AttributeError(f"module 'difftissue.fit' has no attribute {name!r}")
