"""Deprecated: :mod:`difftissue.export_indentation` moved into the :mod:`difftissue.export` package (issue 18).

Kept for one release: it re-exports the former public names from their new modules and warns
(DeprecationWarning) on import. Import them from there instead: ``IndentationSpecimen``,
``indentation_specimen``, ``indentation_sets``, ``INDENTERS`` from :mod:`difftissue.export.specimens`;
``scenario_record`` from :mod:`difftissue.export.card` (the scenarios describe themselves:
``scenario.record()``); ``run_xpbd_indentation`` from :mod:`difftissue.export.xpbd`;
``recalibrated_indentation_card``, ``indentation_card``, ``RECALIBRATION_DEPTHS`` from
:mod:`difftissue.export.recalibration`.
"""

import warnings

from .export.card import scenario_record
from .export.recalibration import RECALIBRATION_DEPTHS, indentation_card, recalibrated_indentation_card
from .export.specimens import INDENTERS, IndentationSpecimen, indentation_sets, indentation_specimen
from .export.xpbd import run_xpbd_indentation

warnings.warn("difftissue.export_indentation moved into the difftissue.export package: import from difftissue.export.specimens, "
              "difftissue.export.card (scenario_record), difftissue.export.xpbd (run_xpbd_indentation) or "
              "difftissue.export.recalibration (the old path goes in the next release)", DeprecationWarning, stacklevel=2)

__all__ = ["IndentationSpecimen", "indentation_specimen", "scenario_record", "indentation_sets", "run_xpbd_indentation", "INDENTERS",
           "recalibrated_indentation_card", "indentation_card", "RECALIBRATION_DEPTHS"]
