"""VTU with per-cell material fields and the specimen's boundary conditions as point data: the
compression block, the indentation specimen and the fitted specimen (no conversion involved).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ExportError
from ..mesh import write_mesh
from .card import MATERIAL_FIELDS, MaterialCard
from .fitted import FittedSpecimen, specimen_fields
from .specimens import block_sets, default_displacement, indentation_sets, no_mesh_with_indentation

__all__ = ["write_vtu", "write_fitted_vtu"]


def _material_cells(card: MaterialCard, n: int) -> dict[str, np.ndarray]:
    """Cell fields of ``n`` cells of the card's material: the :data:`~difftissue.export.card.MATERIAL_FIELDS`
    and ``shear_modulus``, ``lame_lambda``, ``bulk_modulus`` (SI), constant over the cells."""
    vals = {k: card.value(k) for k in MATERIAL_FIELDS}
    if "pre_stretch_y" in card.parameters:  # anisotropic pre-stretch
        vals["pre_stretch_y"] = card.pre_stretch_y
    vals.update(shear_modulus=card.shear_modulus, lame_lambda=card.lame_lambda, bulk_modulus=card.bulk_modulus)
    return {k: np.full(n, float(v)) for k, v in vals.items()}


def write_vtu(card: MaterialCard, mesh, path, *, displacement: float | None = None, force: bool = False, indentation=None) -> Path:
    """Write ``mesh`` as VTU with per-cell material fields: ``youngs_modulus``, ``poisson_ratio``,
    ``cubic_coefficient``, ``density``, ``pre_stretch`` (and ``pre_stretch_y`` when the card has one), ``shear_modulus`` (mu), ``lame_lambda``,
    ``bulk_modulus`` (all SI), constant over the cells, and the specimen's boundary conditions as
    point data: ``boundary`` (0 free, 1 base fixed, 2 top moved) and ``prescribed_displacement``
    [m] (top: ``(0, 0, displacement)``, default -10 % of the height). No conversion is involved."""
    if indentation is not None:
        no_mesh_with_indentation(mesh)
        return _write_vtu_indentation(card, indentation, path, force)
    if mesh is None:
        raise ExportError("a VTU export needs a mesh (--specimen)")
    if Path(path).suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a VTU export must end in .vtu")
    n = int(np.asarray(mesh.tets).shape[0])
    cell = _material_cells(card, n)
    base, top, height = block_sets(mesh)
    d = default_displacement(height, displacement)
    boundary = np.zeros(len(np.asarray(mesh.points)))
    boundary[base] = 1.0
    boundary[top] = 2.0
    presc = np.zeros((len(boundary), 3))
    presc[top, 2] = d
    point = {"boundary": boundary, "prescribed_displacement": presc}
    return write_mesh(path, mesh, point_data=point, cell_data=cell, overwrite=force)


def _write_vtu_indentation(card: MaterialCard, spec, path, force: bool) -> Path:
    """VTU of an indentation specimen: material cell fields as for the block, point data
    ``boundary`` (0 free, 1 base bonded, 4 base sliding (u_z = 0), 2 punch, 3 contact
    candidate), ``prescribed_displacement`` [m] (punch: ``(0, 0, -depth)``) and
    ``contact_penalty`` [N/m] (difftissue's ``kappa_i`` of the candidate nodes)."""
    if Path(path).suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a VTU export must end in .vtu")
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    n = int(np.asarray(mesh.tets).shape[0])
    cell = _material_cells(card, n)
    npts = len(np.asarray(mesh.points))
    boundary = np.zeros(npts)
    presc = np.zeros((npts, 3))
    kappa = np.zeros(npts)
    if spec.indenter == "flat_punch":
        boundary[s["punch"]] = 2.0
        presc[s["punch"], 2] = -spec.depth
    else:
        boundary[s["contact_nodes"]] = 3.0
        kappa[s["contact_nodes"]] = s["kappa"]
    boundary[s["base"]] = 1.0 if spec.base == "bonded" else 4.0
    point = {"boundary": boundary, "prescribed_displacement": presc, "contact_penalty": kappa}
    return write_mesh(path, mesh, point_data=point, cell_data=cell, overwrite=force)


def write_fitted_vtu(card: MaterialCard, spec: FittedSpecimen, path, *, force: bool = False) -> Path:
    """Write the fitted specimen ``spec`` as VTU: the specimen file's fields
    (:func:`~difftissue.export.fitted.specimen_fields`) with ``card``'s values on the fitted
    regions and the derived ``shear_modulus``, ``lame_lambda``, ``bulk_modulus`` per cell (SI)."""
    if Path(path).suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a VTU export must end in .vtu")
    point, cell = specimen_fields(spec, card)
    return write_mesh(path, spec.mesh(), point_data=point, cell_data=cell, overwrite=force)
