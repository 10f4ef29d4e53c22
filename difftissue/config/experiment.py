"""One built experiment of a config (:class:`Experiment`): its scenario, data files, notes,
rows used and data-driven estimates, as the builders return it and :class:`FitConfig` uses it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One built experiment: its scenario and where its data came from."""

    name: str
    kind: str
    model: str | None
    scenario: Any
    data_files: tuple[Path, ...]
    notes: tuple[str, ...] = ()
    #: rows of the data file used by the fit: ``file``, ``rows_loaded`` (by the loader),
    #: ``loaded`` (which rows the loader returned), ``rows_used``,
    #: ``row_names`` ("file lines" or "data rows"), ``used`` (their names, in fit order),
    #: ``steps`` (``{"action": "left out" | "reordered", "rows": [...], "reason": ...}``)
    provenance: dict | None = None
    #: plausibility warnings of the data (e.g. :class:`~difftissue.errors.ImplausibleUnitWarning`)
    warnings: tuple[str, ...] = ()
    #: the data's own modulus estimate for a data-driven start: ``(value [Pa], kind, how)`` with
    #: kind ``"effective"`` (E / (1 - nu^2), indentation) or ``"young"`` (E, compression)
    modulus_estimate: tuple[float, str, str] | None = None
    #: builds the same experiment on a coarser mesh (about half the cells in each direction,
    #: same geometry and protocol) for the discretisation estimate: a callable returning
    #: ``(scenario, info)``, info ``{"fine_cells", "coarse_cells", "refinement_ratio"}``
    #: (ratio: coarse / fine cell size [-]), or ``(None, reason)`` where the coarser mesh turns
    #: out unusable when built (an incision whose cut it cannot carry unchanged); None when it
    #: cannot be coarsened
    coarsen: Any = None
    #: why the experiment has no discretisation estimate (None when :attr:`coarsen` is given)
    coarsen_skip: str | None = None
    #: ``contact_offset = "fit"``: the indentation's contact offset [m] is fitted with the
    #: material (``fit(..., scenario_parameters={name: ("contact_offset",)})``)
    fit_contact_offset: bool = False
