"""difftissue: differentiable calibration of soft-tissue material models.

The public API is organised by job:

- :mod:`difftissue.mesh` -- tet meshes, cube-lattice springs, generators, validation, I/O.
- :mod:`difftissue.materials` -- the :class:`Material` pytree, conversions, fitting transforms.
- :mod:`difftissue.selectors` -- node sets described as data.

Units are SI everywhere (m, N, Pa, s, kg).

The submodules that need JAX (``materials``, ``mesh``, ``selectors``) and the names taken from
them are imported on first use (PEP 562 ``__getattr__``), so ``import difftissue`` and the
command line's ``--help`` / ``--version`` do not start JAX.
"""

import importlib

from ._version import __version__
from . import errors  # (no JAX)

#: Names imported on first access: name -> (submodule, attribute or None for the module).
_LAZY = {
    "materials": ("materials", None),
    "mesh": ("mesh", None),
    "selectors": ("selectors", None),
    "Material": ("materials", "Material"),
    "Specimen": ("mesh", "Specimen"),
    "TetMesh": ("mesh", "TetMesh"),
    "block": ("mesh", "block"),
    "layered_skin": ("mesh", "layered_skin"),
    "read_mesh": ("mesh", "read_mesh"),
    "write_mesh": ("mesh", "write_mesh"),
}


def __getattr__(name: str):
    """Import a JAX-backed submodule (or a name from it) on first access."""
    if name not in _LAZY:
        raise AttributeError(f"module 'difftissue' has no attribute {name!r}")
    module, attr = _LAZY[name]
    mod = importlib.import_module(f".{module}", __name__)
    value = mod if attr is None else getattr(mod, attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


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
