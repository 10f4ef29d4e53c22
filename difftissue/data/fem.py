"""Reference FEM results (any meshio format) with a nodal displacement field.

Linear tetrahedra (``tetra``) give a :class:`~difftissue.mesh.TetMesh` (the model can run on
the reference's own mesh); quadratic tetrahedra (``tetra10``), trilinear hexahedra
(``hexahedron``) and quadratic hexahedra (``hexahedron20``, ``hexahedron27``) are kept as the
reference's own elements (``cells``), for interpolation onto a model mesh
(:mod:`difftissue.interpolation`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import equinox as eqx
import numpy as np

from ..errors import (DegenerateElementError, ImplausibleMagnitudeError, IndexOutOfRangeError, MeshError, MissingFieldError, NonFiniteDataError,
                      UnitError, UnsupportedMeshError, _cite)
from ..interpolation import node_coordinates, shape_gradients
from .units import normalize_unit


#: Volume cell types a reference may hold (meshio names; ``tetra4`` is meshio's name for
#: Abaqus C3D4H). Other volume cells are refused; surface, line and vertex cells are ignored.
REFERENCE_CELL_TYPES = ("tetra", "tetra10", "hexahedron", "hexahedron20", "hexahedron27")
_CELL_ALIASES = {"tetra4": "tetra", "hexahedron8": "hexahedron"}
_VOLUME_PREFIXES = ("tetra", "hexahedron", "wedge", "pyramid")


class FEMResult(eqx.Module):
    """A reference FEM solution: the undeformed mesh and its nodal displacements.

    Attributes:
        mesh: the reference configuration as a :class:`~difftissue.mesh.TetMesh` [m] when the
            file holds linear tetrahedra only, else ``None`` (quadratic tetrahedra,
            hexahedra of 8, 20 or 27 nodes: see ``cells``).
        displacement: ``(N, 3)`` nodal displacement [m].
        metadata: ``source``, ``sha256``, ``field`` (the point-data name read),
            ``length_unit``, ``displacement_unit``, ``max_displacement`` [m], ``cell_types``.
        points: ``(N, 3)`` node coordinates [m] (``mesh.points`` when there is a mesh).
        cells: ``{cell type: (M, k) node indices}`` of the volume elements (``"tetra"``,
            ``"tetra10"``, ``"hexahedron"``, ``"hexahedron20"``, ``"hexahedron27"``; VTK node
            order).
        point_data: the file's point fields (node-set masks, reaction fields, ...).
    """

    mesh: Any
    displacement: np.ndarray
    metadata: dict
    points: np.ndarray
    cells: dict
    point_data: dict

    def __init__(self, mesh, displacement, metadata: dict | None = None, *, points=None, cells: dict | None = None, point_data: dict | None = None):
        self.mesh = mesh
        self.displacement = np.asarray(displacement, dtype=float)
        self.metadata = dict(metadata or {})
        if mesh is not None:
            points = mesh.points if points is None else points
            cells = {"tetra": np.asarray(mesh.tets)} if cells is None else cells
            point_data = mesh.point_data if point_data is None else point_data
        if points is None or cells is None:
            raise MissingFieldError("a FEMResult needs a mesh, or points and cells")
        self.points = np.asarray(points, dtype=float)
        self.cells = {str(k): np.asarray(v) for k, v in cells.items()}
        self.point_data = dict(point_data or {})

    @property
    def n_nodes(self) -> int:
        return int(len(self.points))

    @property
    def deformed_points(self) -> np.ndarray:
        """``points + displacement`` [m]."""
        return self.points + self.displacement


# ============================================================================ FEM
def load_fem_result(
    path,
    *,
    field: str = "displacement",
    length_unit: str = "m",
    displacement_unit: str | None = None,
    reorient: bool = False,
    displacement_table=None,
) -> FEMResult:
    """A reference FEM result: a mesh (any meshio format) with a nodal displacement field.

    Linear tetrahedra give a :class:`~difftissue.mesh.TetMesh` (read and checked by
    :func:`~difftissue.mesh.read_mesh`, as a model mesh would be); a file with quadratic
    tetrahedra (``tetra10``, Abaqus C3D10, FEBio tet10) or hexahedra (``hexahedron``: Abaqus
    C3D8, FEBio hex8; ``hexahedron20``: Abaqus C3D20/C3D20R, FEBio hex20; ``hexahedron27``:
    FEBio hex27, in VTU/XDMF/VTK files: meshio does not read Abaqus C3D27), alone or mixed,
    keeps its elements in ``cells`` and has
    ``mesh = None``: such a reference is interpolated onto a model mesh
    (:class:`~difftissue.scenarios.FEMField` with ``specimen``).

    Args:
        field: the point-data name of the displacement.
        length_unit: unit of the coordinates in the file (converted to m).
        displacement_unit: unit of the displacement (default: ``length_unit``).
        reorient: passed to :func:`~difftissue.mesh.read_mesh`.
        displacement_table: an Abaqus input file (``.inp``) holds the mesh only: the nodal
            displacement then comes from this CSV file with the header ``node,ux,uy,uz``
            (``node``: the node labels of the ``*NODE`` block, one row per node, in
            ``displacement_unit``), e.g. written from the ``.odb`` by a report of ``U``.

    Raises:
        MissingFieldError: no such point field (the message lists those present) or it is
            not ``(N, 3)``.
        NonFiniteDataError: NaN or infinite displacements (``rows`` are node indices).
        ImplausibleMagnitudeError: displacements larger than 10 x the mesh's size (a unit
            mismatch between coordinates and displacements).
        MeshError: the file cannot be read as a valid tet mesh (linear tetrahedra), or its
            quadratic / hexahedral elements are degenerate (a quadratic hexahedron also when
            its Jacobian changes sign between its centre and nodes: misplaced or
            misordered mid-side nodes) or index missing nodes.
        UnsupportedMeshError: volume cells other than tetra, tetra10 and the 8-, 20- and
            27-node hexahedra (wedges, pyramids, hexahedron24), Abaqus C3D27 (meshio cannot
            read it), or no volume cells.
    """
    from ..mesh import LENGTH_UNITS, _read_meshio, read_mesh  # meshio and the mesh checks, only when a FEM result is read

    du = displacement_unit or length_unit
    if normalize_unit(du) not in LENGTH_UNITS and du not in LENGTH_UNITS:
        raise UnitError(f"unknown displacement unit {du!r}; choose one of {sorted(LENGTH_UNITS)}")
    try:
        raw = _read_meshio(path)
    except MeshError as err:
        if "'tetra4'" in str(err):  # meshio 5.3 maps C3D4H to a cell type it cannot store
            raise UnsupportedMeshError(f"{path}: meshio cannot read Abaqus C3D4H (hybrid linear tetrahedron) elements; write them as C3D4 "
                                       f"(same nodes and geometry) in the .inp") from None
        if "Element type not available: C3D27" in str(err):
            raise UnsupportedMeshError(f"{path}: meshio cannot read Abaqus C3D27 (27-node hexahedron) elements; export the result as VTU or "
                                       f"XDMF (hexahedron27 cells, VTK node order), or mesh with C3D20 / C3D20R") from None
        raise
    types = {c.type for c in raw.cells}
    if not types & (set(REFERENCE_CELL_TYPES) | set(_CELL_ALIASES)) - {"tetra"}:  # linear tets only (meshio's own name)
        mesh = read_mesh(path, length_unit=length_unit, reorient=reorient)
        points, cells, point_data = mesh.points, {"tetra": np.asarray(mesh.tets)}, mesh.point_data
    else:
        mesh = None
        points, cells, point_data = _higher_order_cells(raw, path, length_unit, LENGTH_UNITS)
    n_nodes = len(points)
    if displacement_table is not None:
        field = f"table:{Path(displacement_table).name}"
        point_data = {**point_data, field: _abaqus_displacement_table(path, displacement_table, n_nodes)}
    if field not in point_data:
        raise MissingFieldError(f"{path} has no point field {field!r}; its point fields are: {sorted(point_data) or 'none'}")
    u = np.asarray(point_data[field], dtype=float)
    if u.ndim != 2 or u.shape != (n_nodes, 3):
        raise MissingFieldError(f"point field {field!r} of {path} has shape {u.shape}; a displacement needs ({n_nodes}, 3)")
    bad = np.flatnonzero(~np.isfinite(u).all(axis=1))
    if bad.size:
        raise NonFiniteDataError(f"point field {field!r} of {path} has NaN or infinite values at nodes {_cite(bad)}", rows=bad)
    u = u * LENGTH_UNITS.get(du, LENGTH_UNITS.get(normalize_unit(du), 1.0))
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    umax = float(np.linalg.norm(u, axis=1).max()) if len(u) else 0.0
    if size > 0 and umax > 10 * size:
        raise ImplausibleMagnitudeError(
            f"the largest displacement in {path} is {umax:.4g} m, more than 10 x the mesh's diagonal ({size:.4g} m); "
            f"are the displacements in another unit than the coordinates? (displacement_unit={du!r})"
        )
    meta = {
        "source": str(path),
        "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
        **({"displacement_table": str(displacement_table), "displacement_table_sha256": hashlib.sha256(Path(displacement_table).read_bytes()).hexdigest()}
           if displacement_table is not None else {}),
        "format": "meshio",
        "field": field,
        "length_unit": length_unit,
        "displacement_unit": du,
        "max_displacement": umax,
        "cell_types": sorted(cells),
    }
    return FEMResult(mesh, u, meta, points=points, cells=cells, point_data=point_data)


def _abaqus_node_labels(path) -> np.ndarray:
    """The node labels of an Abaqus input file's ``*NODE`` block, in the order meshio numbers
    the nodes (meshio keeps the last ``*NODE`` block)."""
    labels: list[int] = []
    reading = False
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("**"):
                continue
            if line.startswith("*"):
                reading = line.partition(",")[0].strip().replace("*", "").upper() == "NODE"
                if reading:
                    labels = []
                continue
            if reading and line.strip():
                labels.append(int(line.split(",")[0]))
    return np.asarray(labels, dtype=np.int64)


def _abaqus_displacement_table(path, table, n_nodes: int) -> np.ndarray:
    """``(N, 3)`` displacement (in the file's unit) of an Abaqus mesh from a CSV table
    ``node,ux,uy,uz`` keyed by node label."""
    path, table = Path(path), Path(table)
    if path.suffix.lower() != ".inp":
        raise MissingFieldError(f"displacement_table is for Abaqus input files (.inp), which hold no results; {path.name} carries "
                                f"its displacement as a point field (field = ...)")
    if not table.is_file():
        raise MissingFieldError(f"no such displacement table: {table}")
    labels = _abaqus_node_labels(path)
    if len(labels) != n_nodes:
        raise MissingFieldError(f"{path.name}: found {len(labels)} node labels in its *NODE block but meshio read {n_nodes} nodes")
    try:
        arr = np.genfromtxt(table, delimiter=",", names=True, dtype=float, encoding="utf-8")
    except ValueError as err:
        raise MissingFieldError(f"cannot read {table.name} as CSV with the header node,ux,uy,uz: {err}") from None
    names = tuple(n.lower() for n in (arr.dtype.names or ()))
    need = ("node", "ux", "uy", "uz")
    if any(n not in names for n in need):
        raise MissingFieldError(f"{table.name} needs the columns {list(need)}, found {list(arr.dtype.names or ())}")
    arr = np.atleast_1d(arr)
    col = {n.lower(): n for n in arr.dtype.names}
    node = arr[col["node"]]
    u = np.stack([arr[col[c]] for c in ("ux", "uy", "uz")], axis=1)
    if not np.all(np.isfinite(node)) or np.any(node != np.round(node)):
        raise MissingFieldError(f"{table.name}: the node column must hold integer node labels")
    node = node.astype(np.int64)
    uniq, counts = np.unique(node, return_counts=True)
    if np.any(counts > 1):
        raise MissingFieldError(f"{table.name}: node labels {_cite(uniq[counts > 1])} appear more than once")
    unknown = np.setdiff1d(node, labels)
    if unknown.size:
        raise MissingFieldError(f"{table.name}: node labels {_cite(unknown)} are not nodes of {path.name}")
    missing = np.setdiff1d(labels, node)
    if missing.size:
        raise MissingFieldError(f"{table.name} has no row for the nodes {_cite(missing)} of {path.name}")
    order = {int(k): i for i, k in enumerate(node)}
    return u[[order[int(k)] for k in labels]]


def _higher_order_cells(raw, path, length_unit: str, units: dict):
    """``points [m], cells, point_data`` of a meshio mesh with quadratic tetrahedra or
    hexahedra (any mix with linear tetrahedra): every volume cell checked (indices in range,
    a non-degenerate Jacobian at the element's centre; quadratic hexahedra: the Jacobian of
    their own map at the centre and every node, non-degenerate and of one sign)."""
    if length_unit not in units:
        raise MeshError(f"unknown length unit {length_unit!r}; choose one of {sorted(units)}")
    points = np.asarray(raw.points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise UnsupportedMeshError(f"{path}: the file holds {points.shape[-1]}-D points; a reference needs 3-D coordinates")
    if not np.all(np.isfinite(points)):
        raise MeshError(f"{path}: node coordinates are NaN or infinite")
    points = points * units[length_unit]
    others = sorted({c.type for c in raw.cells if c.type.startswith(_VOLUME_PREFIXES)} - set(REFERENCE_CELL_TYPES) - set(_CELL_ALIASES))
    if others:
        raise UnsupportedMeshError(f"{path} holds {others} cells; a reference may hold tetra (4-node), tetra10, hexahedron (8-node), "
                                   f"hexahedron20 and hexahedron27 cells")
    cells: dict[str, list] = {}
    for c in raw.cells:
        t = _CELL_ALIASES.get(c.type, c.type)
        if t in REFERENCE_CELL_TYPES:
            cells.setdefault(t, []).append(np.asarray(c.data, dtype=np.int64))
    cells = {t: np.concatenate(v) for t, v in cells.items()}
    for t, conn in cells.items():
        bad = np.flatnonzero((conn < 0).any(axis=1) | (conn >= len(points)).any(axis=1))
        if bad.size:
            raise IndexOutOfRangeError(f"{path}: {t} cells {_cite(bad)} index nodes outside [0, {len(points)})", bad)
        X = points[conn]
        if t in ("hexahedron20", "hexahedron27"):
            _check_quadratic_hexahedra(path, t, X)
            continue
        if t == "hexahedron":  # edge vectors at the centre of the trilinear map
            J = np.stack([(X[:, [1, 2, 5, 6]] - X[:, [0, 3, 4, 7]]).mean(axis=1), (X[:, [3, 2, 7, 6]] - X[:, [0, 1, 4, 5]]).mean(axis=1),
                          (X[:, 4:] - X[:, :4]).mean(axis=1)], axis=2)
        else:
            J = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
        det = np.abs(np.linalg.det(J))
        h = np.linalg.norm(X.max(axis=1) - X.min(axis=1), axis=1)
        bad = np.flatnonzero(~(det > 1e-10 * h**3))
        if bad.size:
            raise DegenerateElementError(f"{path}: {t} cells {_cite(bad)} are degenerate (zero volume)", bad)
    point_data = {k: np.asarray(v) for k, v in raw.point_data.items() if k not in ("gmsh:dim_tags", "medit:ref")}
    return points, cells, point_data


def _check_quadratic_hexahedra(path, t: str, X: np.ndarray) -> None:
    """Refuse 20- or 27-node hexahedra ``X`` ``(M, k, 3)`` whose map (their own shape functions)
    has a (near-)zero Jacobian, or one that changes sign, at the centre or a node: flat
    elements, and mid-side nodes misplaced or given in another node order than VTK's."""
    at = np.vstack([[[0.0, 0.0, 0.0]], node_coordinates(t)])  # centre, nodes
    dN = shape_gradients(t, at)  # (1 + k, k, 3)
    det = np.linalg.det(np.einsum("mkd,pke->mpde", X, dN))  # (M, 1 + k)
    h = np.linalg.norm(X.max(axis=1) - X.min(axis=1), axis=1)
    tiny = 1e-10 * h[:, None] ** 3
    ok = np.all(det > tiny, axis=1) | np.all(det < -tiny, axis=1)
    bad = np.flatnonzero(~ok)
    if bad.size:
        raise DegenerateElementError(f"{path}: {t} cells {_cite(bad)} are degenerate or inverted (the Jacobian of the element's map is zero "
                                     f"or changes sign between its centre and nodes); check that the nodes are in VTK order (corners, "
                                     f"then mid-edge nodes{', face centres, body centre' if t == 'hexahedron27' else ''})", bad)
