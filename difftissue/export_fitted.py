"""Deprecated: :mod:`difftissue.export_fitted` moved into the :mod:`difftissue.export` package (issue 18).

Kept for one release: it re-exports the former public names from their new modules and warns
(DeprecationWarning) on import. Import them from there instead:

* :mod:`difftissue.export.fitted`: ``FittedSpecimen``, ``fitted_specimen``, ``compression_protocol``,
  ``specimen_file_name``, ``write_specimen``, ``read_specimen``, ``fitted_specimen_from_card``,
  ``specimen_record``, ``load_steps``, ``SPECIMEN_FORMAT``, ``FITTED_EXPERIMENTS``, ``MAX_STRAIN_INCREMENT``;
* :mod:`difftissue.export.recalibration`: ``specimen_reactions``, ``recalibrated_card``,
  ``recalibrated_from_reactions``, ``RECALIBRATION_STATES``;
* the target modules: ``febio_fitted_model`` (:mod:`~difftissue.export.febio`), ``abaqus_fitted_model``
  (:mod:`~difftissue.export.abaqus`), ``sofa_fitted_scene`` (:mod:`~difftissue.export.sofa`),
  ``xpbd_fitted_parameters``, ``xpbd_fitted_budget``, ``xpbd_fitted_field_check``, ``FIELD_CHECK_HALVINGS``
  (:mod:`~difftissue.export.xpbd`);
* :mod:`difftissue.export.dispatch`: ``write_fitted``.
"""

import warnings

from .export.abaqus import abaqus_fitted_model
from .export.dispatch import write_fitted
from .export.febio import febio_fitted_model
from .export.fitted import (FITTED_EXPERIMENTS, MAX_STRAIN_INCREMENT, SPECIMEN_FORMAT, FittedSpecimen, compression_protocol,
                            fitted_specimen, fitted_specimen_from_card, load_steps, read_specimen, specimen_file_name, specimen_record,
                            write_specimen)
from .export.recalibration import RECALIBRATION_STATES, recalibrated_card, recalibrated_from_reactions, specimen_reactions
from .export.sofa import sofa_fitted_scene
from .export.xpbd import FIELD_CHECK_HALVINGS, xpbd_fitted_budget, xpbd_fitted_field_check, xpbd_fitted_parameters

warnings.warn("difftissue.export_fitted moved into the difftissue.export package: import from difftissue.export.fitted, "
              "difftissue.export.recalibration, difftissue.export.dispatch (write_fitted) or the target modules "
              "(the old path goes in the next release)", DeprecationWarning, stacklevel=2)

__all__ = [
    "SPECIMEN_FORMAT",
    "FITTED_EXPERIMENTS",
    "MAX_STRAIN_INCREMENT",
    "FittedSpecimen",
    "fitted_specimen",
    "compression_protocol",
    "specimen_file_name",
    "write_specimen",
    "read_specimen",
    "fitted_specimen_from_card",
    "specimen_record",
    "load_steps",
    "febio_fitted_model",
    "abaqus_fitted_model",
    "sofa_fitted_scene",
    "xpbd_fitted_parameters",
    "xpbd_fitted_budget",
    "xpbd_fitted_field_check",
    "FIELD_CHECK_HALVINGS",
    "write_fitted",
    "specimen_reactions",
    "recalibrated_card",
    "recalibrated_from_reactions",
    "RECALIBRATION_STATES",
]
