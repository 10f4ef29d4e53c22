"""Loaders that turn measured-data files into typed datasets (no physics in here).

Datasets
    :class:`ForceDepthCurve` (indentation: depth [m], force [N]),
    :class:`CompressionCurve` (unconfined compression: strain [-], stress [Pa], force [N],
    displacement [m], specimen size [m]) and :class:`FEMResult` (a reference mesh with a
    ``displacement`` point field [m]).

Sign convention (every dataset, whatever the file does)
    depth, displacement and strain are **positive into the specimen** (compression
    positive); force and stress are **positive compressive** (the indenter or platen pushes
    on the specimen). Loaders flip the file's signs where needed and record the flips in
    ``metadata["signs"]``.

Units
    SI inside (m, N, Pa, s). Files declare their units (in the column names, or in a
    loader config); :data:`UNITS` lists those understood. After conversion every quantity
    is checked against a plausibility range (:data:`PLAUSIBLE_RANGES`), which catches most
    wrong units (nanometres declared as metres, newtons for an AFM curve, ...).

Loaders
    :func:`load_table` / :func:`load_force_depth` / :func:`load_compression` (generic
    CSV/TSV with declared columns), :func:`load_instron_compression` (the Instron export of
    the Tissue Phantom Material Database), :func:`load_chiaro` (Optics11 Chiaro
    nano-indenter text export), :func:`load_fem_result` (meshio), and
    :func:`load_dataset` (any of these from a config mapping).

Contact point
    :func:`find_contact` (default: a piecewise fit, linear baseline + power law with a free
    exponent, on the approach segment) and :func:`shift_to_contact` (approach segment,
    depth and force measured from the contact point).

Modules
    :mod:`~difftissue.data.units` (units, SI factors, plausibility ranges),
    :mod:`~difftissue.data.table` (text decoding, declared-column tables),
    :mod:`~difftissue.data.curves` (the curve datasets and their generic loaders),
    :mod:`~difftissue.data.instruments` (Instron, Chiaro),
    :mod:`~difftissue.data.contact_point` (contact-point detection),
    :mod:`~difftissue.data.fem` (meshio FEM results) and
    :mod:`~difftissue.data.dataset` (:func:`load_dataset`). Every public name is importable
    from :mod:`difftissue.data` itself.

See ``docs/data.md``.
"""

from .units import normalize_unit, parse_quantity, PLAUSIBLE_RANGES, QUANTITY_DIMENSIONS, unit_factor, UNITS
from .table import load_table, read_text, Table, TextFile
from .curves import check_monotonic, CompressionCurve, ForceDepthCurve, load_compression, load_force_depth
from .fem import FEMResult, load_fem_result
from .instruments import load_chiaro, load_instron_compression
from .contact_point import CONTACT_METHODS, ContactPoint, find_contact, shift_to_contact
from .dataset import load_dataset

__all__ = [
    "ForceDepthCurve",
    "CompressionCurve",
    "FEMResult",
    "Table",
    "ContactPoint",
    "UNITS",
    "QUANTITY_DIMENSIONS",
    "PLAUSIBLE_RANGES",
    "normalize_unit",
    "unit_factor",
    "parse_quantity",
    "read_text",
    "TextFile",
    "load_table",
    "load_force_depth",
    "load_compression",
    "load_instron_compression",
    "load_chiaro",
    "load_fem_result",
    "load_dataset",
    "find_contact",
    "shift_to_contact",
    "check_monotonic",
    "CONTACT_METHODS",
]
