"""Material cards and writers for other simulators (DESIGN.md §4, docs/export.md).

A :class:`MaterialCard` (JSON, ``"card_version": 1``) is the source of truth: the elastic model
that was fitted, the energy it refers to, every parameter with unit and standard error, and
provenance. Writers derive simulator inputs from it, each with its conversion spelled out:

* FEBio ``.feb`` (febio_spec 4.0): :func:`write_febio` (:mod:`difftissue.export.febio`)
* SOFA ``.scn``: :func:`write_sofa` (:mod:`difftissue.export.sofa`)
* Abaqus ``.inp``: :func:`write_abaqus` (:mod:`difftissue.export.abaqus`)
* XPBD compliances for a stated time step and iteration count (JSON): :func:`write_xpbd`
  (:mod:`difftissue.export.xpbd`)
* a pypbd scene (JSON, XPBD distance + volume or PBD FEM constraints):
  :func:`difftissue.export.pypbd.write_pbd`, read and run by :mod:`difftissue.export.pypbd_runner`
* VTU with per-cell material fields: :func:`write_vtu` (:mod:`difftissue.export.vtu`)
* scikit-fem (in memory, no file): :func:`to_skfem` (:mod:`difftissue.export.scikit_fem`)

:func:`export` writes any of them for a block, indentation or fitted specimen. All quantities
are SI. Every file is written atomically and an existing file is refused unless ``force=True``.

The package follows the data flow, each module importing only those below it (checked by the
import-linter contracts of ``pyproject.toml``, docs/dev/export-package.md):

* :mod:`~difftissue.export.dispatch`: :func:`export`, :func:`~difftissue.export.dispatch.write_fitted`;
* one module per target: :mod:`~difftissue.export.febio`, :mod:`~difftissue.export.sofa`,
  :mod:`~difftissue.export.abaqus`, :mod:`~difftissue.export.xpbd`, :mod:`~difftissue.export.pypbd`,
  :mod:`~difftissue.export.vtu`, :mod:`~difftissue.export.scikit_fem`;
* :mod:`~difftissue.export.recalibration` (a lattice card for a continuum law) and
  :mod:`~difftissue.export.budget` (a real-time file for its budget), above the pypbd runner
  :mod:`~difftissue.export.pypbd_runner`;
* the specimens: :mod:`~difftissue.export.specimens` (block, indentation, indenter cap) and
  :mod:`~difftissue.export.fitted` (the fitted experiment and its specimen file);
* :mod:`~difftissue.export.approximations` (what a target cannot represent, measured errors),
  :mod:`~difftissue.export.card` (the card) and :mod:`~difftissue.export._common` (formatting).

This module re-exports the names ``difftissue.export`` has always offered.
"""

from ._common import UNITS, UNITS_LINE
from .abaqus import (ABAQUS_ELEMENTS, ABAQUS_FIELD_WIDTH, CONE_INCREMENTS_PER_CELL, abaqus_indentation_model, abaqus_indenter_mesh,
                     abaqus_material, abaqus_model, abaqus_name, abaqus_number, abaqus_quadratic, abaqus_reaction_print, write_abaqus)
from .approximations import LAW_MODELS, UNIAXIAL_STRAINS, model_mismatch, uniaxial_signed_errors
from .card import (CARD_VERSION, MODEL_ENERGIES, PARAMETER_UNITS, MaterialCard, card_from_fit, card_from_fit_json, portable_path,
                   read_card, resolve_effective_modulus, write_card)
from .dispatch import TARGETS, export
from .febio import (febio_indentation_model, febio_material, febio_model, febio_prestrain_gradient, pre_stretch_from_febio_gradient, pre_stretches_from_febio_gradient,
                    write_febio)
from .scikit_fem import to_skfem
from .sofa import (sofa_force_field, sofa_indentation_scene, sofa_polynomial_coefficients, sofa_scene, sofa_springs_split,
                   springs_from_sofa_polynomial, write_sofa)
from .specimens import FEBIO_INDENTER_MATERIAL, febio_indenter_cap
from .vtu import write_vtu
from .xpbd import write_xpbd, xpbd_parameters

__all__ = [
    "CARD_VERSION",
    "MODEL_ENERGIES",
    "PARAMETER_UNITS",
    "TARGETS",
    "MaterialCard",
    "card_from_fit",
    "card_from_fit_json",
    "resolve_effective_modulus",
    "read_card",
    "write_card",
    "abaqus_name",
    "abaqus_number",
    "abaqus_reaction_print",
    "abaqus_quadratic",
    "ABAQUS_ELEMENTS",
    "model_mismatch",
    "uniaxial_signed_errors",
    "portable_path",
    "febio_material",
    "febio_indenter_cap",
    "febio_prestrain_gradient",
    "pre_stretch_from_febio_gradient",
    "pre_stretches_from_febio_gradient",
    "sofa_force_field",
    "sofa_polynomial_coefficients",
    "springs_from_sofa_polynomial",
    "sofa_springs_split",
    "abaqus_material",
    "xpbd_parameters",
    "write_febio",
    "write_sofa",
    "write_abaqus",
    "write_xpbd",
    "write_vtu",
    "to_skfem",
    "export",
    # public before the split, outside __all__
    "UNITS",
    "UNITS_LINE",
    "LAW_MODELS",
    "UNIAXIAL_STRAINS",
    "febio_model",
    "sofa_scene",
    "ABAQUS_FIELD_WIDTH",
    "abaqus_model",
    "FEBIO_INDENTER_MATERIAL",
    "febio_indentation_model",
    "CONE_INCREMENTS_PER_CELL",
    "abaqus_indenter_mesh",
    "abaqus_indentation_model",
    "sofa_indentation_scene",
]
