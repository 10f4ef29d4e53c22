"""Deprecated: :mod:`difftissue.pbd` moved into the :mod:`difftissue.export` package (issue 18).

Kept for one release: it re-exports the former public names and warns (DeprecationWarning) on
import. Import them instead from :mod:`difftissue.export.pypbd` (writing: ``pbd_scene``,
``write_pbd``, ``DEFAULT_BUDGET``) and :mod:`difftissue.export.pypbd_runner` (reading and running:
``read_pbd_scene``, ``pbd_simulation_from_scene``, ``run_pbd_scene``, ``PBDRun``, ``run_pbd_budget``,
``PBDBudgetRun``, ``scaled_scene``, ``scene_forces``, ``scene_energy``, ``pbd_reference_model``,
``SCENE_FORMAT``, ``PYPBD_GRAVITY``).
"""

import warnings

from .export.pypbd import DEFAULT_BUDGET, pbd_scene, write_pbd
from .export.pypbd_runner import (PYPBD_GRAVITY, SCENE_FORMAT, PBDBudgetRun, PBDRun, pbd_reference_model, pbd_simulation_from_scene,
                                  read_pbd_scene, run_pbd_budget, run_pbd_scene, scaled_scene, scene_energy, scene_forces)

warnings.warn("difftissue.pbd moved into the difftissue.export package: import from difftissue.export.pypbd (writing) or "
              "difftissue.export.pypbd_runner (reading, running) (the old path goes in the next release)",
              DeprecationWarning, stacklevel=2)

__all__ = [
    "SCENE_FORMAT",
    "PYPBD_GRAVITY",
    "DEFAULT_BUDGET",
    "pbd_scene",
    "write_pbd",
    "read_pbd_scene",
    "pbd_simulation_from_scene",
    "run_pbd_scene",
    "PBDRun",
    "scene_forces",
    "scene_energy",
    "pbd_reference_model",
    "scaled_scene",
    "run_pbd_budget",
    "PBDBudgetRun",
]
