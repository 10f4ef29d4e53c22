"""Fit configs: a TOML file -> scenarios, parameterization, initial material and fit options.

A config has three parts (the full schema, with every key, is in ``docs/configuration.md``)::

    [material]                 # initial values, SI
    youngs_modulus = 1e4
    poisson_ratio = 0.45

    [fit]
    parameters = ["youngs_modulus", "cubic_coefficient"]
    bounds = { cubic_coefficient = [-3.0, 5.0] }

    [[experiment]]
    name = "ecoflex"
    scenario = "compression"
    data = { format = "instron", path = "data/EF10_50T_A1.csv" }   # relative to this file

Every key is checked before anything heavy happens: an unknown key, a value of the wrong type
or outside its range raises :class:`~difftissue.errors.ConfigError` whose one-line message
starts with the key's path, e.g. ``experiment[0].indenter.radius: must be a positive length
in m, got -1``. Errors raised while loading the data or building a scenario are re-raised
with the experiment's path in front.

Lengths are in metres unless the table that holds them gives ``length_unit``.

:func:`load_config` reads a file, :func:`parse_config` a mapping; both return a
:class:`FitConfig`, whose :meth:`FitConfig.run` calls :func:`difftissue.fit.fit`.

The package follows the data flow (docs/dev/config-package.md): :mod:`.parser` reads and
checks the file and calls :mod:`.builders` for each experiment (data rows from :mod:`.rows`,
estimates and plausibility checks from :mod:`.estimates`); :mod:`.fitconfig` holds the built
:class:`FitConfig` and runs the fit under the compile policy of :mod:`.compile`
(:class:`SeparatelyCompiled`, programs shared by equal scenarios); :mod:`.schema` holds the
keys, defaults and validators every module uses. ``from difftissue.config import X`` keeps
working for every name the single module ``difftissue/config.py`` offered.
"""

from .builders import _build_experiment, _coarse_block
from .compile import SeparatelyCompiled, clear_compile_cache, compile_cache_info
from .estimates import (
    CUBIC_START_MAX_SE,
    PERCENT_SUSPECT_STRAIN,
    PLAUSIBLE_DEPTH_OVER_RADIUS,
    PLAUSIBLE_MAX_STRAIN,
    PLAUSIBLE_MODULUS,
    SMALL_STRAIN_FRACTION,
    _cubic_estimate,
)
from .experiment import Experiment
from .fitconfig import FitConfig, tissue_range_check
from .parser import load_config, parse_config
from .schema import FIELDS, SCENARIOS, TISSUE_RANGES

__all__ = [
    "FitConfig", "Experiment", "load_config", "parse_config", "SCENARIOS", "FIELDS", "TISSUE_RANGES", "tissue_range_check",
    "SeparatelyCompiled", "compile_cache_info", "clear_compile_cache", "PLAUSIBLE_MODULUS", "PLAUSIBLE_DEPTH_OVER_RADIUS",
    "PLAUSIBLE_MAX_STRAIN", "PERCENT_SUSPECT_STRAIN", "SMALL_STRAIN_FRACTION", "CUBIC_START_MAX_SE",
]
