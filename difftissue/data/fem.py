"""Reference FEM results (any meshio format) with a nodal displacement field."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import equinox as eqx
import numpy as np

from ..errors import ImplausibleMagnitudeError, MissingFieldError, NonFiniteDataError, UnitError, _cite
from .units import normalize_unit


class FEMResult(eqx.Module):
    """A reference FEM solution: the undeformed mesh and its nodal displacements.

    Attributes:
        mesh: the reference configuration (:class:`~difftissue.mesh.TetMesh`), in m.
        displacement: ``(N, 3)`` nodal displacement [m].
        metadata: ``source``, ``sha256``, ``field`` (the point-data name read),
            ``length_unit``, ``displacement_unit``, ``max_displacement`` [m].
    """

    mesh: Any
    displacement: np.ndarray
    metadata: dict = eqx.field(default_factory=dict)

    @property
    def deformed_points(self) -> np.ndarray:
        """``mesh.points + displacement`` [m]."""
        return np.asarray(self.mesh.points) + self.displacement


# ============================================================================ FEM
def load_fem_result(
    path,
    *,
    field: str = "displacement",
    length_unit: str = "m",
    displacement_unit: str | None = None,
    reorient: bool = False,
) -> FEMResult:
    """A reference FEM result: a tet mesh (any meshio format) with a nodal displacement field.

    Args:
        field: the point-data name of the displacement.
        length_unit: unit of the coordinates in the file (converted to m).
        displacement_unit: unit of the displacement (default: ``length_unit``).
        reorient: passed to :func:`~difftissue.mesh.read_mesh`.

    Raises:
        MissingFieldError: no such point field (the message lists those present) or it is
            not ``(N, 3)``.
        NonFiniteDataError: NaN or infinite displacements (``rows`` are node indices).
        ImplausibleMagnitudeError: displacements larger than 10 x the mesh's size (a unit
            mismatch between coordinates and displacements).
        MeshError: the file cannot be read as a valid tet mesh.
    """
    from ..mesh import LENGTH_UNITS, read_mesh  # meshio and the mesh checks, only when a FEM result is read

    du = displacement_unit or length_unit
    if normalize_unit(du) not in LENGTH_UNITS and du not in LENGTH_UNITS:
        raise UnitError(f"unknown displacement unit {du!r}; choose one of {sorted(LENGTH_UNITS)}")
    mesh = read_mesh(path, length_unit=length_unit, reorient=reorient)
    if field not in mesh.point_data:
        raise MissingFieldError(f"{path} has no point field {field!r}; its point fields are: {sorted(mesh.point_data) or 'none'}")
    u = np.asarray(mesh.point_data[field], dtype=float)
    if u.ndim != 2 or u.shape != (mesh.n_nodes, 3):
        raise MissingFieldError(f"point field {field!r} of {path} has shape {u.shape}; a displacement needs ({mesh.n_nodes}, 3)")
    bad = np.flatnonzero(~np.isfinite(u).all(axis=1))
    if bad.size:
        raise NonFiniteDataError(f"point field {field!r} of {path} has NaN or infinite values at nodes {_cite(bad)}", rows=bad)
    u = u * LENGTH_UNITS.get(du, LENGTH_UNITS.get(normalize_unit(du), 1.0))
    lo, hi = mesh.bounds()
    size = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    umax = float(np.linalg.norm(u, axis=1).max()) if len(u) else 0.0
    if size > 0 and umax > 10 * size:
        raise ImplausibleMagnitudeError(
            f"the largest displacement in {path} is {umax:.4g} m, more than 10 x the mesh's diagonal ({size:.4g} m); "
            f"are the displacements in another unit than the coordinates? (displacement_unit={du!r})"
        )
    meta = {
        "source": str(path),
        "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
        "format": "meshio",
        "field": field,
        "length_unit": length_unit,
        "displacement_unit": du,
        "max_displacement": umax,
    }
    return FEMResult(mesh, u, meta)
