"""Deprecated: :mod:`difftissue.batch` moved to :mod:`difftissue.fit.batch` (issue 18).

Kept for one release: it re-exports :func:`~difftissue.fit.fit_batch`,
:class:`~difftissue.fit.BatchFitResult`, :func:`~difftissue.fit.specimen_mesh` and ``AXIS`` and
warns (DeprecationWarning) on import. Import them from :mod:`difftissue.fit` instead.
"""

import warnings

from .fit.batch import AXIS, BatchFitResult, fit_batch, specimen_mesh

warnings.warn("difftissue.batch moved to difftissue.fit.batch; import fit_batch, BatchFitResult and specimen_mesh "
              "from difftissue.fit (the old path goes in the next release)", DeprecationWarning, stacklevel=2)

__all__ = ["BatchFitResult", "fit_batch", "specimen_mesh", "AXIS"]
