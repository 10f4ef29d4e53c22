"""Deprecated: :mod:`difftissue.export_budget` moved to :mod:`difftissue.export.budget` (issue 18).

Kept for one release: it re-exports the former public names and warns (DeprecationWarning) on
import. Import them from :mod:`difftissue.export.budget` instead.
"""

import warnings

from .export.budget import (BUDGET_STATES, MAX_BUDGET_ERROR, MIN_SENSITIVITY, PBD_BUDGETS, calibrate_factor, card_reference_reactions,
                            load_fractions, pbd_budget_calibration, xpbd_budget_calibration, xpbd_budget_reactions)

warnings.warn("difftissue.export_budget moved to difftissue.export.budget (the old path goes in the next release)",
              DeprecationWarning, stacklevel=2)

__all__ = ["MAX_BUDGET_ERROR", "BUDGET_STATES", "MIN_SENSITIVITY", "PBD_BUDGETS", "load_fractions", "card_reference_reactions",
           "calibrate_factor", "pbd_budget_calibration", "xpbd_budget_reactions", "xpbd_budget_calibration"]
