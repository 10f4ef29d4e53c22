"""difftissue: differentiable calibration of soft-tissue material models.

The public API is organised by job:

- :mod:`difftissue.mesh` -- tet meshes, cube-lattice springs, generators, validation, I/O.
- :mod:`difftissue.materials` -- the :class:`Material` pytree, conversions, fitting transforms.
- :mod:`difftissue.selectors` -- node sets described as data.

Units are SI everywhere (m, N, Pa, s, kg).
"""

from ._version import __version__
from . import _xla

_xla.configure()  # before JAX's CPU backend starts (see difftissue/_xla.py)

from . import errors, materials, mesh, selectors
from .materials import Material
from .mesh import Specimen, TetMesh, block, layered_skin, read_mesh, write_mesh

__all__ = [
    "__version__",
    "errors",
    "materials",
    "mesh",
    "selectors",
    "Material",
    "Specimen",
    "TetMesh",
    "block",
    "layered_skin",
    "read_mesh",
    "write_mesh",
]
