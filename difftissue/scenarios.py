"""Experiments as pure ``material -> predictions`` functions.

A scenario holds everything about one measurement except the material: the specimen and
its model, the boundary conditions, the loading protocol and the measured values. Its
:meth:`predict` maps a :class:`~difftissue.materials.Material` to predictions of the
measured quantity (SI units), jit-compatible and differentiable, so :func:`difftissue.fit.fit`
can fit any of them, alone or jointly. Every scenario has:

- ``name``; ``observed`` ``(n,)`` and ``sigma`` ``(n,)`` (the measurement scale used as
  the weight ``1/sigma``) in the unit of the prediction;
- ``abscissa`` ``(n,)`` with ``x_label`` / ``y_label`` (units included) for plots;
- ``predict(material) -> (n,)``;
- optionally ``prediction_rtol``: the relative precision [-] of the predictions (simulated
  scenarios: from their solver tolerances); a fit stops once its residuals are within it.

Scenarios:

- :class:`AnalyticIndentation`: Hertz, Sneddon punch or cone, Hayes punch on a layer, the
  exact bonded-layer sphere and the Dimitriadis series (the fast path AFM users expect).
- :class:`Indentation`: simulated indentation of a block, layered skin or imported mesh by a
  sphere, cone (frictionless penalty contact) or flat punch, with a bonded or sliding base,
  following a depth protocol (each depth starts from the previous equilibrium).
- :class:`Compression`: unconfined compression of a block or cylinder between frictionless
  or bonded platens, engineering or true stress-strain.
- :class:`FEMField`: a reference FEM displacement field (and optionally a reaction force)
  reproduced with the same boundary conditions.
"""

from __future__ import annotations

import collections
import contextvars
import dataclasses
import functools
import hashlib
import math
import warnings
import weakref
from typing import Any, ClassVar, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import analytic
from .boundary import BoundaryConditions, apply_rollers, check_rigid_modes, pin_free_rigid_modes
from .axisymmetric import (AXISYMMETRIC_MODELS, AxisymmetricContactModel, AxisymmetricMesh, AxisymmetricModel,
                           axisymmetric_boundary_conditions, axisymmetric_cylinder)
from .contact import (ConeIndenter, ContactModel, FlatPunch, Platens, SphereIndenter, _PenaltyEnergy, facing_surface_nodes, place_indenter,
                      top_surface_nodes)
from .energies.volume import tet_signed_volume
from .errors import BoundaryConditionError, ConfigError, ConvergenceError, DataError, ModelError, ReactionSignError, SelectorError, ThinSpecimenWarning, UnderResolvedContactWarning
from .materials import Linear, Material
from .mesh import TetMesh, graded_axis, graded_cells as _graded_cells, structured_grid
from .interpolation import interpolation_operator
from .models import LATTICE_MODELS, ElasticModel, make_model
from .selectors import select_nodes
from .solvers import solver_setup
from .solvers.condensed import CondensedContactModel, CondensedParameters, condensation_setup, linear_response_columns, solve_condensed_contact
from .solvers.spectral import SpectralDecomposition, spectral_decomposition, spectral_unsupported
from .solvers.host import HOST_MAX_NODES, HostStaticSolver
from .solvers.static import named_runtime_error, prediction_rtol, solve_static
from .structure_keys import data_leaf_indices, hash_scenario_leaves
from .xla_options import ProgramJit

__all__ = [
    "AnalyticIndentation",
    "Indentation",
    "AxisymmetricIndentation",
    "AxisymmetricSpecimen",
    "THIN_SPECIMEN_CONTACT_RADII",
    "thin_specimen_warning",
    "axisymmetric_specimen_for",
    "Compression",
    "FEMField",
    "graded_axis",
    "indentation_block",
    "IndentationSpecimen",
    "indentation_specimen_for",
    "indentation_contact_radius",
    "IndentationResolution",
    "MIN_CELLS_PER_CONTACT_RADIUS",
    "cylinder",
    "recover_lattice",
]


def _as_1d(name, v) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size == 0:
        raise DataError(f"{name} is empty")
    if not np.all(np.isfinite(a)):
        raise DataError(f"{name} contains NaN or infinite values")
    return a


def _sigma(observed: np.ndarray, sigma) -> np.ndarray:
    """Measurement scale: given (scalar or per point), else the RMS of the data (uniform)."""
    if sigma is None:
        s = float(np.sqrt(np.mean(observed**2)))
        return np.full_like(observed, s if s > 0 else 1.0)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), observed.shape).copy()
    if not np.all(np.isfinite(s) & (s > 0)):
        raise DataError("sigma must be positive and finite")
    return s


def _check_depths(depths: np.ndarray) -> None:
    if np.any(depths < 0):
        raise DataError(f"indentation depths must be >= 0 m (positive into the specimen); got min {depths.min():.3g} m")
    if np.any(np.diff(depths) < 0):
        raise DataError("the depth protocol must be non-decreasing (simulate the approach segment; each depth starts from the previous equilibrium)")


# =========================================================================== contact offset
#: The natural size of a fitted contact offset (the scale of its transform and the floor of its
#: relative standard error) as a fraction of the largest depth of the curve [-].
CONTACT_OFFSET_SCALE = 0.01


def contact_offset_parameter(depths) -> dict:
    """The ``fittable_parameters()`` entry of an indentation's contact offset [m]: added to
    every depth (the indenter at ``depth + contact_offset``: a contact point picked
    ``contact_offset`` too late), start 0, transform ``Linear`` with the scale
    :data:`CONTACT_OFFSET_SCALE` times the largest depth (1 um where the depths are all 0)."""
    d = np.asarray(depths, dtype=float)
    top = float(np.max(np.abs(d))) if d.size and np.all(np.isfinite(d)) else 0.0
    scale = CONTACT_OFFSET_SCALE * top if top > 0 else 1e-6
    return {"contact_offset": {"unit": "m", "transform": Linear(scale=scale), "start": 0.0, "scale": scale}}


# =========================================================================== analytic
class AnalyticIndentation(eqx.Module):
    """Force-depth curve of a closed-form (or exact layer) indentation solution.

    Args:
        depths, forces: the curve [m], [N] (depth from the contact point, force compressive).
        indenter: ``"sphere"`` (``radius``), ``"flat_punch"`` (``radius``) or ``"cone"``
            (``half_angle`` [rad]).
        thickness: layer thickness [m] for the finite-thickness solutions (``None``: half-space).
        solution: ``"half_space"`` (Hertz / Sneddon), ``"exact_layer"`` (sphere: the exact
            layer integral equation; punch: Hayes), ``"dimitriadis"`` (sphere on a layer).
        base: ``"bonded"`` or ``"lubricated"`` layer base.
        sigma: measurement scale [N] (default: RMS force, uniform weights).
    """

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    indenter: str = eqx.field(static=True)
    size: float = eqx.field(static=True)
    thickness: float | None = eqx.field(static=True)
    solution: str = eqx.field(static=True)
    base: str = eqx.field(static=True)
    x_label: str = eqx.field(static=True, default="depth [m]")
    y_label: str = eqx.field(static=True, default="force [N]")

    #: Attributes a fit passes to its compiled programs as arguments besides the measured
    #: forces and sigma (:meth:`difftissue.fit.FitProblem.data`): the depths [m], which
    #: :meth:`predict` reads through JAX operations only, so that a fit of another curve with
    #: as many points compiles nothing (their checks are made here, on the concrete values).
    fit_arguments: ClassVar[tuple[str, ...]] = ("abscissa",)

    def __init__(self, depths, forces, *, indenter="sphere", radius=None, half_angle=None, thickness=None, solution="half_space", base="bonded", sigma=None, name="indentation"):
        self.name = str(name)
        self.abscissa = _as_1d("depths", depths)
        self.observed = _as_1d("forces", forces)
        if self.abscissa.shape != self.observed.shape:
            raise DataError(f"{self.abscissa.size} depths but {self.observed.size} forces")
        if np.any(self.abscissa < 0):
            raise DataError("indentation depths must be >= 0 m")
        self.sigma = _sigma(self.observed, sigma)
        if indenter not in ("sphere", "flat_punch", "cone"):
            raise ConfigError(f"indenter must be 'sphere', 'flat_punch' or 'cone', got {indenter!r}")
        if indenter == "cone":
            if half_angle is None:
                raise ConfigError("a cone needs half_angle [rad]")
            size = float(half_angle)
        else:
            if radius is None:
                raise ConfigError(f"a {indenter} needs radius [m]")
            size = float(radius)
        solutions = {"sphere": ("half_space", "exact_layer", "dimitriadis"), "flat_punch": ("half_space", "exact_layer"), "cone": ("half_space",)}
        if solution not in solutions[indenter]:
            raise ConfigError(f"solution {solution!r} is not available for a {indenter}; choose one of {solutions[indenter]}")
        if solution != "half_space" and thickness is None:
            raise ConfigError(f"solution {solution!r} needs the layer thickness [m]")
        if base not in ("bonded", "lubricated"):
            raise ConfigError(f"base must be 'bonded' or 'lubricated', got {base!r}")
        self.indenter, self.size, self.solution, self.base = indenter, size, solution, base
        self.thickness = None if thickness is None else float(thickness)
        if indenter == "sphere" and solution == "exact_layer":  # the layer solution's range, checked on the depths here (traced in a fit)
            analytic._check_chi(np.sqrt(size * self.abscissa) / self.thickness)
        self.x_label, self.y_label = "depth [m]", "force [N]"

    def fittable_parameters(self) -> dict:
        """What :func:`~difftissue.fit.fit` can fit besides the material
        (``scenario_parameters``): the ``contact_offset`` [m] (:func:`contact_offset_parameter`)."""
        return contact_offset_parameter(self.abscissa)

    def predict(self, material: Material, contact_offset=0.0):
        """Force [N] at each depth; ``contact_offset`` [m] is added to every depth (the
        indenter at ``depth + contact_offset``), and a depth that becomes negative is out of
        contact (force 0, as the simulated sphere and cone: the closed forms hold no
        adhesion). Differentiable in ``contact_offset``."""
        d = jnp.maximum(jnp.asarray(self.abscissa) + contact_offset, 0.0)
        E, nu = material.youngs_modulus, material.poisson_ratio
        if self.indenter == "sphere":
            if self.solution == "half_space":
                return analytic.hertz_force(d, E, nu, self.size)
            if self.solution == "dimitriadis":
                return analytic.dimitriadis_force(d, E, nu, self.size, self.thickness, base=self.base)
            return analytic.layer_sphere_force(d, E, nu, self.size, self.thickness, base=self.base)
        if self.indenter == "flat_punch":
            if self.solution == "half_space":
                return analytic.flat_punch_force(d, E, nu, self.size)
            return analytic.layer_flat_punch_force(d, E, nu, self.size, self.thickness, base=self.base)
        return analytic.cone_force(d, E, nu, self.size)

    def record(self) -> dict:
        """The experiment as a material card's scenario record (``provenance.scenario_records``,
        :func:`difftissue.export.card.scenario_record`): ``name``, ``type``, ``experiment =
        "indentation"``, ``indenter``, ``radius`` [m] or ``half_angle`` [rad], the layer
        ``thickness`` [m] (None: half-space), ``base``, ``solution``, the largest depth
        ``max_depth`` [m] and the number of ``points``."""
        rec: dict[str, Any] = {"name": self.name, "type": type(self).__name__, "experiment": "indentation",
                               "indenter": self.indenter, ("half_angle" if self.indenter == "cone" else "radius"): float(self.size),
                               "thickness": None if self.thickness is None else float(self.thickness), "base": self.base,
                               "solution": self.solution}
        return _with_depths(rec, self.abscissa)


# ============================================================================ meshes
def indentation_block(size, cells, *, symmetry: str = "quarter", refine: float | None = None, core: float | None = None) -> TetMesh:
    """A block for indentation along -z at the axis x = y = 0, top surface at ``z = size[2]``.

    Args:
        size: ``(Lx, Ly, H)`` [m] of the whole specimen.
        cells: ``(nx, ny, nz)`` cells of the modelled part.
        symmetry: ``"quarter"`` models ``[0, Lx/2] x [0, Ly/2] x [0, H]`` (the axis on the
            corner, symmetry planes x = 0 and y = 0); ``"none"`` models
            ``[-Lx/2, Lx/2] x [-Ly/2, Ly/2] x [0, H]``.
        refine: first cell size [m] at the axis and at the surface, growing geometrically
            (None: uniform cells). Graded cells are not cubes: use the FEM or stable
            neo-Hookean models with them (springs_volume refuses elongated cells).
        core: keep cells of size ``refine`` uniform within this distance [m] of the axis and
            of the surface (e.g. 1.5 x the largest contact radius), grading only outside.
    """
    Lx, Ly, H = (float(v) for v in np.broadcast_to(np.asarray(size, dtype=float), (3,)))
    nx, ny, nz = (int(v) for v in np.broadcast_to(np.asarray(cells), (3,)))
    if symmetry == "quarter":
        xs, ys = graded_axis(Lx / 2, nx, refine, core=core), graded_axis(Ly / 2, ny, refine, core=core)
    elif symmetry == "none":
        if refine is not None:
            hx, hy = graded_axis(Lx / 2, max(nx // 2, 1), refine, core=core), graded_axis(Ly / 2, max(ny // 2, 1), refine, core=core)
            xs, ys = np.concatenate([-hx[::-1], hx[1:]]), np.concatenate([-hy[::-1], hy[1:]])
        else:
            xs, ys = np.linspace(-Lx / 2, Lx / 2, nx + 1), np.linspace(-Ly / 2, Ly / 2, ny + 1)
    else:
        raise ConfigError(f"symmetry must be 'quarter' or 'none', got {symmetry!r}")
    zs = H - graded_axis(H, nz, refine, core=core)[::-1]
    return structured_grid(xs, ys, zs, region_names=("tissue",))


#: Cells of the automatic indentation specimen per contact radius at the largest depth
#: (``refine = a / CELLS_PER_CONTACT_RADIUS``), chosen from the convergence study
#: ``experiments/indentation_resolution.py`` (docs/experiments.md, "Indentation at resolution").
CELLS_PER_CONTACT_RADIUS = 4  # force error +7.3 %; within 1 % needs about 27 (order 1.05)
#: Half-width and thickness of the automatic specimen in contact radii: a half-space
#: approximation: the exact bonded-layer stiffening at ``chi = a / H = 1/200``
#: (:func:`~difftissue.analytic.layer_sphere_factor`) is +0.44 / +0.52 / +0.57 % at nu = 0.3 / 0.45 / 0.5
#: (lubricated base +0.37 % at nu = 0.45).
HALF_SPACE_EXTENT = 200.0
#: Radius of the uniform core of the automatic specimen in contact radii (axis and surface).
CONTACT_CORE = 1.5
#: Largest ratio of neighbouring cell sizes outside the core of the automatic specimen [-].
CELL_GROWTH = 1.3
#: Relative force error ``F_h / F_converged - 1`` [-] of fem_linear on the automatic specimen
#: as ``C * m**(-p)`` with ``m`` the cells per contact radius: ``{indenter: (C, p)}``, fitted to
#: the convergence study (``experiments/indentation_resolution.py``: sphere R = 1 mm to
#: d/R = 0.02, nu = 0.45, bonded base, m = 3, 4, 6 against the Richardson extrapolation; the
#: observed order is 1.05). The force is proportional to E, so a fitted E is off by about
#: ``-error / (1 + error)``. The cone (70 deg to 0.1 mm: +13.0 / +7.8 / +5.1 % against Sneddon at
#: m = 2, 3, 4) is not in the asymptotic range (apparent order 0.8, implausible extrapolation):
#: no entry, no estimate (docs/dev/indentation-resolution.md).
INDENTATION_FORCE_ERROR = {"sphere": (0.316, 1.054)}


@dataclasses.dataclass(frozen=True)
class IndentationSpecimen:
    """A block for simulated indentation chosen from the indenter and the depth
    (:func:`indentation_specimen_for`): the arguments of :func:`indentation_block` and why.

    Attributes:
        size: ``(Lx, Ly, H)`` [m] of the whole specimen.
        cells: ``(nx, ny, nz)`` cells of the modelled quarter.
        symmetry: ``"quarter"``.
        refine: first (and core) cell size [m].
        core: width [m] of the uniform core at the axis and the surface.
        contact_radius: contact radius ``a`` [m] at the largest depth (Hertz ``sqrt(R d)``,
            cone ``2 d tan(theta) / pi``).
        cells_per_contact_radius: ``a / refine`` [-].
        force_error: estimated relative force error ``F_h / F_converged - 1`` [-] of the linear
            tetrahedra at the largest depth (:data:`INDENTATION_FORCE_ERROR`; None where not
            measured: the cone); a fitted E is off by about ``-force_error / (1 + force_error)``.
        thickness_given: True when the thickness is the specimen's own (a layer), False for the
            half-space approximation.
        indenter: ``"sphere"`` or ``"cone"``.
    """

    size: tuple[float, float, float]
    cells: tuple[int, int, int]
    symmetry: str
    refine: float
    core: float
    contact_radius: float
    cells_per_contact_radius: float
    force_error: float | None
    thickness_given: bool
    indenter: str

    def block(self) -> TetMesh:
        """The mesh: :func:`indentation_block` with these arguments."""
        return indentation_block(self.size, self.cells, symmetry=self.symmetry, refine=self.refine, core=self.core)

    def record(self) -> dict:
        """The choice as plain numbers (SI) for reports and ``fit.json``."""
        return {"rule": "indentation_specimen_for", "size": list(self.size), "cells": list(self.cells), "symmetry": self.symmetry,
                "refine": self.refine, "core": self.core, "contact_radius": self.contact_radius,
                "cells_per_contact_radius": self.cells_per_contact_radius, "force_error": self.force_error,
                "thickness_given": self.thickness_given, "indenter": self.indenter}

    def coarser(self, factor: float = 2.0) -> "IndentationSpecimen":
        """The same rule at ``factor`` times fewer cells per contact radius: same size and core,
        first cells ``factor * refine``, the cells beyond the core graded as the rule grades
        them (so the two blocks differ in resolution only: the pair a Richardson estimate of
        the discretisation error needs, with cell size ratio exactly ``factor``).

        Raises:
            ConfigError: ``factor <= 1`` or fewer than one cell per contact radius left.
        """
        f = float(factor)
        if not (math.isfinite(f) and f > 1):
            raise ConfigError(f"factor must be > 1, got {factor!r}")
        m = self.cells_per_contact_radius / f
        if m < 1:
            raise ConfigError(f"{self.cells_per_contact_radius:g} cells per contact radius / {f:g} leaves fewer than one: no coarser specimen")
        h0 = f * self.refine
        n_xy = _graded_cells(self.size[0] / 2, h0, self.core, CELL_GROWTH)
        n_z = _graded_cells(self.size[2], h0, self.core, CELL_GROWTH)
        return dataclasses.replace(self, cells=(n_xy, n_xy, n_z), refine=h0, cells_per_contact_radius=m,
                                   force_error=_tabulated_force_error(self.indenter, m))


def indentation_specimen_for(indenter: str, *, radius: float | None = None, half_angle: float | None = None, max_depth: float,
                             model: str = "fem_linear", thickness: float | None = None,
                             cells_per_contact_radius: float = CELLS_PER_CONTACT_RADIUS, extent: float = HALF_SPACE_EXTENT) -> IndentationSpecimen:
    """The indentation block to simulate a sphere or cone indentation to ``max_depth``.

    The contact radius at the largest depth, ``a = sqrt(R d)`` (sphere, Hertz) or
    ``a = 2 d tan(theta) / pi`` (cone, Sneddon), sets the scale:

    - cells of ``refine = a / cells_per_contact_radius`` uniform within ``CONTACT_CORE a`` of the
      axis and of the surface (the contact zone), growing by at most :data:`CELL_GROWTH` beyond;
    - a quarter (``symmetry = "quarter"``) of half-width ``extent a`` (:data:`HALF_SPACE_EXTENT`); the thickness is
      ``thickness`` when given (the specimen's own: the model then includes its layer effect),
      else also ``extent a`` (a half-space: finite-size stiffening about +0.5 % for a sphere,
      :data:`HALF_SPACE_EXTENT`).

    Args:
        indenter: ``"sphere"`` or ``"cone"``.
        radius: sphere radius ``R`` [m].
        half_angle: cone half-angle ``theta`` [rad].
        max_depth: largest indentation depth ``d`` [m], > 0.
        model: elastic model; graded cells are boxes, not cubes, so the lattice models (:data:`~difftissue.models.LATTICE_MODELS`) are refused.
        thickness: specimen thickness [m] (None: a half-space).
        cells_per_contact_radius: ``a / refine`` [-] (default from the convergence study).
        extent: half-width (and thickness, without ``thickness``) in contact radii [-].

    Raises:
        ConfigError: a flat punch or unknown indenter, a missing or non-positive size, a
            springs_volume model, or a thickness that leaves no room below the contact core.
    """
    if indenter == "sphere":
        if radius is None or not float(radius) > 0:
            raise ConfigError(f"a sphere needs a positive radius [m], got {radius!r}")
    elif indenter == "cone":
        if half_angle is None or not 0 < float(half_angle) < math.pi / 2:
            raise ConfigError(f"a cone needs a half-angle in (0, pi/2) rad, got {half_angle!r}")
    else:
        raise ConfigError(f"an automatic indentation specimen is chosen for a sphere or a cone, got {indenter!r} "
                          "(a flat punch's contact radius is its own: give the specimen)")
    d = float(max_depth)
    if not (math.isfinite(d) and d > 0):
        raise ConfigError(f"max_depth must be a positive depth [m], got {max_depth!r}")
    if model in LATTICE_MODELS:
        raise ConfigError(f"the automatic indentation specimen grades its cells (boxes, not cubes), which {model} refuses: "
                          "use model 'fem_linear', 'fem_neo_hookean' or 'stable_neo_hookean', or give the specimen")
    m = float(cells_per_contact_radius)
    if not (math.isfinite(m) and m >= 1):
        raise ConfigError(f"cells_per_contact_radius must be >= 1, got {cells_per_contact_radius!r}")
    if indenter == "sphere":
        a = float(analytic.hertz_contact_radius(d, float(radius)))
    else:
        a = float(analytic.cone_contact_radius(d, float(half_angle)))
    h0, core = a / m, CONTACT_CORE * a
    if not (math.isfinite(float(extent)) and float(extent) > 2 * CONTACT_CORE):
        raise ConfigError(f"extent must exceed {2 * CONTACT_CORE:g} contact radii, got {extent!r}")
    half = float(extent) * a
    if thickness is None:
        H = half
    else:
        H = float(thickness)
        if not (math.isfinite(H) and H > core + h0 and H > d):
            raise ConfigError(f"thickness {thickness!r} m leaves no room below the contact core ({core + h0:.3g} m deep at "
                              f"max_depth {d:.3g} m): give the specimen explicitly")
    n_xy = _graded_cells(half, h0, core, CELL_GROWTH)
    n_z = _graded_cells(H, h0, core, CELL_GROWTH)
    return IndentationSpecimen(size=(2 * half, 2 * half, H), cells=(n_xy, n_xy, n_z), symmetry="quarter", refine=h0, core=core,
                               contact_radius=a, cells_per_contact_radius=m, force_error=_tabulated_force_error(indenter, m),
                               thickness_given=thickness is not None, indenter=indenter)


def _tabulated_force_error(indenter: str, m: float) -> float | None:
    """:data:`INDENTATION_FORCE_ERROR` at ``m`` cells per contact radius (None where not tabulated)."""
    C, p = INDENTATION_FORCE_ERROR.get(indenter, (None, None))
    return None if C is None else float(C * m ** (-p))


#: Fewest mesh cells per contact radius [-] at which a depth of a simulated indentation counts
#: as resolved (:meth:`Indentation.resolution`). Chosen from the per-depth force errors of
#: fem_linear on the automatic specimen against Hertz / Sneddon (``experiments/indentation_default_fit.py``,
#: docs/dev/indentation-resolution.md): from 1 to 2 cells per contact radius the force is
#: +13 to +27 % high (sphere and 70 deg cone, two meshes), below one cell it climbs steeply
#: (cone +49 / +93 / +199 / +497 % at 0.8 / 0.62 / 0.4 / 0.2 cells, sphere +39 / +92 % at 0.65 / 0.47).
MIN_CELLS_PER_CONTACT_RADIUS = 1.0
#: Surface nodes nearest the indenter axis over which the cell size under the indenter is taken.
_AXIS_NODES = 16


def indentation_contact_radius(indenter: str, depths, *, radius: float | None = None, half_angle: float | None = None) -> np.ndarray:
    """Contact radius [m] of a rigid indenter on a half-space at each depth [m]: sphere
    ``sqrt(R d)`` (:func:`~difftissue.analytic.hertz_contact_radius`), cone ``2 d tan(theta) / pi``
    (:func:`~difftissue.analytic.cone_contact_radius`), flat punch its ``radius``
    (:func:`~difftissue.analytic.flat_punch_contact_radius`).

    Args:
        indenter: ``"sphere"`` (``radius`` [m]), ``"cone"`` (``half_angle`` [rad]) or
            ``"flat_punch"`` (``radius`` [m]).
        depths: indentation depths [m], >= 0.

    Raises:
        ConfigError: an unknown indenter or a missing size.
    """
    d = np.asarray(depths, dtype=float)
    if indenter in ("sphere", "flat_punch"):
        if radius is None:
            raise ConfigError(f"a {indenter.replace('_', ' ')} needs radius [m]")
        f = analytic.hertz_contact_radius if indenter == "sphere" else analytic.flat_punch_contact_radius
        return np.asarray(f(d, float(radius)), dtype=float)
    if indenter == "cone":
        if half_angle is None:
            raise ConfigError("a cone needs half_angle [rad]")
        return np.asarray(analytic.cone_contact_radius(d, float(half_angle)), dtype=float)
    raise ConfigError(f"indenter must be 'sphere', 'cone' or 'flat_punch', got {indenter!r}")


def _cell_size_at_axis(points: np.ndarray, nodes: np.ndarray, distance: np.ndarray) -> float:
    """Cell size [m] under an indenter: the median distance from each of the
    :data:`_AXIS_NODES` surface ``nodes`` nearest the axis (``distance`` [m] from it) to its
    nearest other surface node (the spacing ``h`` of a structured grid, the first cell of a
    graded one). NaN with fewer than two surface nodes."""
    if nodes.size < 2:
        return float("nan")
    order = np.argsort(distance, kind="stable")
    near = points[nodes[order[: min(nodes.size, 16 * _AXIS_NODES)]]]
    k = min(near.shape[0], _AXIS_NODES)
    gap = np.linalg.norm(near[:k, None, :] - near[None, :, :], axis=-1)
    gap[np.arange(k), np.arange(k)] = np.inf
    return float(np.median(gap.min(axis=1)))


@dataclasses.dataclass(frozen=True)
class IndentationResolution:
    """How well a simulated indentation's mesh resolves the contact zone at each depth
    (:meth:`Indentation.resolution`).

    Attributes:
        name: the scenario's name.
        indenter: ``"sphere"``, ``"cone"`` or ``"flat_punch"``.
        depths: the protocol's depths [m].
        contact_radius: half-space contact radius [m] at each depth
            (:func:`indentation_contact_radius`).
        cell_size: mesh cell size [m] under the indenter (the median nearest-neighbour spacing
            of the surface nodes nearest the axis).
        cells_per_contact_radius: ``contact_radius / cell_size`` [-] at each depth.
        min_cells_per_contact_radius: the threshold [-] below which a depth is flagged.
    """

    name: str
    indenter: str
    depths: np.ndarray
    contact_radius: np.ndarray
    cell_size: float
    cells_per_contact_radius: np.ndarray
    min_cells_per_contact_radius: float

    @property
    def flagged(self) -> np.ndarray:
        """Indices of the depths below :attr:`min_cells_per_contact_radius` cells per contact radius."""
        # a relative 1e-6 below the threshold still counts (float32 meshes put a depth chosen at exactly the threshold a rounding below it)
        return np.flatnonzero(~(self.cells_per_contact_radius >= self.min_cells_per_contact_radius * (1.0 - 1e-6)))

    @property
    def keep(self) -> np.ndarray:
        """Boolean mask of the resolved depths (the complement of :attr:`flagged`)."""
        mask = np.ones(self.depths.shape, dtype=bool)
        mask[self.flagged] = False
        return mask

    def record(self) -> dict:
        """The check as plain numbers (SI) for ``fit.json``: threshold, cell size, and the
        flagged depths with their contact radius and cells per contact radius."""
        i = self.flagged
        return {"indenter": self.indenter, "min_cells_per_contact_radius": self.min_cells_per_contact_radius, "cell_size": self.cell_size,
                "cells_per_contact_radius_range": [float(np.min(self.cells_per_contact_radius)), float(np.max(self.cells_per_contact_radius))]
                if self.depths.size else [],
                "flagged": [{"index": int(k), "depth": float(self.depths[k]), "contact_radius": float(self.contact_radius[k]),
                             "cells_per_contact_radius": float(self.cells_per_contact_radius[k])} for k in i]}

    def message(self, where: str | None = None) -> str:
        """One line naming the flagged depths, their cells per contact radius and the options."""
        i = self.flagged
        shown = ", ".join(f"{self.depths[k]:.4g} m ({self.cells_per_contact_radius[k]:.2g})" for k in i[:8])
        more = f" and {i.size - 8} more" if i.size > 8 else ""
        return (f"{where or self.name}: {i.size} of {self.depths.size} depths have a contact radius of less than {self.min_cells_per_contact_radius:g} "
                f"mesh cells ({self.indenter}, cells of {self.cell_size:.4g} m under the indenter): depth (cells per contact radius) "
                f"{shown}{more}; the linear tetrahedra over-predict the force there by tens to hundreds of percent (docs/scenarios.md, "
                f"\"Resolution at each depth\"); refine the mesh under the indenter, or leave these depths out "
                f"(config: under_resolved = \"drop\"; Python: the scenario's depths[resolution.keep])")

    def warn(self, where: str | None = None, stacklevel: int = 2) -> str | None:
        """Emit :class:`~difftissue.errors.UnderResolvedContactWarning` when a depth is flagged;
        returns its message (None when every depth is resolved)."""
        if self.flagged.size == 0:
            return None
        msg = self.message(where)
        warnings.warn(msg, UnderResolvedContactWarning, stacklevel=stacklevel + 1)
        return msg


def cylinder(diameter: float, height: float, cells_radial: int = 4, cells_height: int = 4) -> TetMesh:
    """A cylinder along z (base at z = 0) meshed by mapping a structured square grid onto the
    disc (the elliptical grid map (u, v) -> (u sqrt(1 - v^2/2), v sqrt(1 - u^2/2))), so its tets are valid but not a cube lattice:
    use it with the FEM or stable neo-Hookean models."""
    r = float(diameter) / 2
    n = int(cells_radial)
    if not (r > 0 and float(height) > 0 and n >= 1 and int(cells_height) >= 1):
        raise ModelError("cylinder needs positive diameter, height and cell counts")
    s = np.linspace(-1.0, 1.0, 2 * n + 1)
    grid = structured_grid(s, s, np.linspace(0.0, float(height), int(cells_height) + 1))
    p = np.array(grid.points)
    u, v = p[:, 0].copy(), p[:, 1].copy()
    p[:, 0] = r * u * np.sqrt(1.0 - v**2 / 2.0)
    p[:, 1] = r * v * np.sqrt(1.0 - u**2 / 2.0)
    return TetMesh(p, grid.tets, grid.region_ids, grid.region_names)


def recover_lattice(mesh: TetMesh) -> TetMesh:
    """Re-attach the cube lattice to a mesh that is a Freudenthal-split rectilinear grid
    (e.g. written by :func:`~difftissue.mesh.block` and read back from a file, which loses it).

    Raises :class:`~difftissue.errors.ModelError` when the mesh is not such a grid.
    """
    p = np.asarray(mesh.points)
    size = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    tol = 1e-9 * size
    axes = []
    for a in range(3):
        c = np.sort(p[:, a])
        keep = np.concatenate([[True], np.diff(c) > tol])
        axes.append(c[keep])
    not_grid = ModelError("the mesh is not a rectilinear grid split into 6 tets per box, so it has no cube lattice; use the fem_* or stable_neo_hookean models")
    if np.prod([len(a) for a in axes]) != len(p):
        raise not_grid
    grid = structured_grid(*axes)
    idx = [np.clip(np.searchsorted(axes[a], p[:, a] - tol), 0, len(axes[a]) - 1) for a in range(3)]
    nx1, ny1 = len(axes[0]), len(axes[1])
    grid_id = idx[0] + nx1 * (idx[1] + ny1 * idx[2])  # grid node of each mesh node
    if len(np.unique(grid_id)) != len(p) or not np.allclose(np.asarray(grid.points)[grid_id], p, atol=10 * tol):
        raise not_grid
    to_mesh = np.empty(len(p), dtype=np.int64)
    to_mesh[grid_id] = np.arange(len(p))
    mine = {tuple(sorted(t)) for t in mesh.tets.tolist()}
    theirs = [tuple(sorted(t)) for t in to_mesh[grid.tets].tolist()]
    if len(mine) != len(theirs) or any(t not in mine for t in theirs):
        raise not_grid
    lat = grid.lattice
    # region of each cube = region of its tets (6 consecutive tets per cube in the grid)
    tet_index = {tuple(sorted(t)): i for i, t in enumerate(mesh.tets.tolist())}
    cube_regions = np.array([mesh.region_ids[tet_index[theirs[6 * c]]] for c in range(lat.n_cubes)], dtype=np.int32)
    lattice = eqx.tree_at(lambda l: (l.cubes, l.springs, l.cube_region_ids), lat, (to_mesh[lat.cubes].astype(lat.cubes.dtype), to_mesh[lat.springs].astype(lat.springs.dtype), cube_regions))
    return TetMesh(mesh.points, mesh.tets, mesh.region_ids, mesh.region_names, point_data=mesh.point_data, cell_data=mesh.cell_data, lattice=lattice, validate=False)


# ====================================================================== simulations
@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Options of the static solves inside a scenario (see :func:`solve_static`)."""

    rtol: float = 1e-9
    xtol: float = 1e-8
    max_steps: int = 50
    #: one of :func:`solve_static`'s (``"auto"``, ``"dense"``, ``"sparse"``, ``"multigrid"``,
    #: ``"cg"``), or ``"spectral"`` for the condensed indentation of a one-region ``fem_linear``
    #: body (:mod:`difftissue.solvers.spectral`: one eigendecomposition per mesh, no
    #: factorisation per material).
    linear_solver: str = "auto"
    #: ``"raise"``: a static solve that fails (no convergence, inverted elements) raises
    #: :class:`~difftissue.errors.ConvergenceError` (an equinox runtime error under jit);
    #: ``"nan"``: its predictions become NaN, so an optimiser rejects the trial parameters
    #: (what :mod:`difftissue.config` uses for fits; the fit refuses a NaN optimum).
    failure: str = "raise"
    #: the material the multigrid hierarchy is built for when the material is traced (a fit):
    #: only the CG iteration count depends on it (see :func:`solve_static`).
    preconditioner_material: Any = None

    def __post_init__(self):
        if self.failure not in ("raise", "nan"):
            raise ConfigError(f"solver failure must be 'raise' or 'nan', got {self.failure!r}")

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of a prediction computed with these options
        (:func:`~difftissue.solvers.static.prediction_rtol`)."""
        return prediction_rtol(self.rtol, self.xtol)


_JITTED: dict[tuple[int, str], tuple[Any, Any]] = {}

#: Most compiled protocols kept for sharing between equal scenarios (least recently used
#: dropped first); each keeps the scenario it was compiled for (and its mesh) alive.
SHARED_SOLVES_SIZE = 8

#: Only closed-over scenarios (see :func:`_jitted_solve`) whose
#: arrays hold at most this many bytes share their compiled protocol: a large mesh's program
#: embeds its arrays (GBs at 10^5 unknowns, docs/dev/solver-design.md), which must go with the
#: scenario, not stay in a cache. Programs taking the arrays as arguments share at any size.
SHARED_SOLVES_MAX_BYTES = 16 * 2**20

#: ``{structure key: (scenario, _SharedSolve)}`` (see :func:`_structure_key`), most recent last.
_SHARED: collections.OrderedDict = collections.OrderedDict()


def _structure_key(scenario):
    """What a scenario's compiled protocol depends on: its type, pytree structure (the static
    configuration) and every leaf (arrays by content, Python scalars by value, other objects by
    identity: the shared entry keeps them alive) but the measured data (``observed``,
    ``sigma``: shape and dtype only; a ``_solve_protocol`` never reads them), the formula of
    :func:`difftissue.structure_keys.hash_scenario_leaves`; None when the static configuration
    cannot be hashed, a leaf is traced or the arrays exceed :data:`SHARED_SOLVES_MAX_BYTES`
    (then the program is not shared)."""
    leaves, treedef = jax.tree_util.tree_flatten(scenario)
    if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
        return None  # a scenario traced by an outer transformation (the fit engine): inlined there
    if sum(int(getattr(leaf, "nbytes", 0)) for leaf in leaves if eqx.is_array(leaf)) > SHARED_SOLVES_MAX_BYTES:
        return None
    try:
        hash(treedef)
    except TypeError:
        return None
    h = hashlib.sha256()
    objects = hash_scenario_leaves(h, leaves, data_leaf_indices(scenario, leaves))
    return (type(scenario), treedef, h.hexdigest(), tuple(objects))


class _SharedSolve:
    """One jitted ``_solve_protocol`` for a set of equal scenarios. It holds them weakly and
    traces with any one still alive (they are equal: the same program), so the executable
    survives as long as one of them does, and none is kept alive by it."""

    def __init__(self, method: str = "_solve_protocol"):
        self._users: list = []
        self.method = method
        self.fn = ProgramJit(self._trace, "static")

    def _trace(self, material, *extra):
        token = _SOLVE_SETUP.set(None)  # the solves build their own setup (closed-over mesh)
        try:
            return getattr(self._live(), self.method)(material, *extra)
        finally:
            _SOLVE_SETUP.reset(token)

    def add(self, scenario) -> None:
        self._users = [r for r in self._users if r() is not None] + [weakref.ref(scenario)]

    def _live(self):
        for r in reversed(self._users):
            scenario = r()
            if scenario is not None:
                return scenario
        raise RuntimeError("a scenario's compiled solve outlived every scenario it was compiled for")


#: The :class:`~difftissue.solvers.static.SolverSetup` of the protocol being traced by an
#: :class:`_ArgumentSolve` (None otherwise), read by :func:`_solve`.
_SOLVE_SETUP: contextvars.ContextVar = contextvars.ContextVar("difftissue_scenario_solver_setup", default=None)


def _takes_arguments(scenario, leaves) -> bool:
    """Whether ``scenario``'s protocol is compiled with its arrays and solver setup as
    arguments (:class:`_ArgumentSolve`): every static solve of the protocol goes through
    :func:`_solve` with ``scenario.model`` (or it at another indenter depth) and
    ``scenario.bc.fixed`` (or, for the condensed indentation, the condensation's columns of
    its base model: :func:`~difftissue.solvers.condensed.condensation_setup`), or the scenario
    builds the setup of its solves itself (``_setup_builder``: the incision), and nothing is
    traced by an outer transformation."""
    if callable(getattr(scenario, "_setup_builder", None)):
        return not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)
    if not all(isinstance(getattr(scenario, a, None), t) for a, t in (("model", ElasticModel), ("bc", BoundaryConditions), ("options", SolverOptions))):
        return False
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)


def _argument_key(scenario, leaves, treedef, method: str = "_solve_protocol"):
    """The structure key of a protocol compiled with the scenario's arrays as arguments: its
    type, pytree structure (static configuration) and every leaf that is not an array
    (Python scalars by value, other objects by identity); arrays by shape and dtype only, so
    that scenarios of other values with the same shapes (another mesh of the same size, other
    depths) share the program. None when the static configuration cannot be hashed."""
    try:
        hash(treedef)
    except TypeError:
        return None
    h = hashlib.sha256()
    arrays = tuple(i for i, leaf in enumerate(leaves) if eqx.is_array(leaf))
    objects = hash_scenario_leaves(h, leaves, arrays, data_tag="arg")
    return ("arguments", method, type(scenario), treedef, h.hexdigest(), tuple(objects))


class _ArgumentSolve:
    """One jitted ``_solve_protocol`` that takes the scenario's arrays (the ``eqx.partition``
    of its array leaves) and the :class:`~difftissue.solvers.static.SolverSetup` of its
    static solves as arguments: the program holds no mesh-sized constant (a closed-over mesh
    and multigrid hierarchy are embedded in the executable, GBs at 10^5 unknowns), and
    scenarios of the same structure share it. It keeps only the non-array part of the
    scenario it was built for (``static``), which equal scenarios have in common."""

    def __init__(self, static, method: str = "_solve_protocol"):
        self.static = static
        self.method = method
        self.fn = ProgramJit(self._trace, "static")

    def _trace(self, dynamic, setup, material, *extra):
        token = _SOLVE_SETUP.set(setup)
        try:
            return getattr(eqx.combine(dynamic, self.static), self.method)(material, *extra)
        finally:
            _SOLVE_SETUP.reset(token)


class _ScenarioSolve:
    """``scenario.solve``'s compiled protocol for one scenario: the shared
    :class:`_ArgumentSolve` (``program``) called with this scenario's arrays and its solver
    setup, built on the first call per material structure (a concrete mesh; the multigrid
    hierarchy for a traced material, as inside the program: ``SolverOptions.preconditioner_material``
    or E = 1 Pa, nu = 0.45)."""

    def __init__(self, program: _ArgumentSolve, scenario, dynamic):
        self.program = program
        # Evaluated now, also when the first call is inside an outer jit (whose trace would
        # otherwise stage these operations and leave its tracers in this cached object).
        with jax.ensure_compile_time_eval():
            # converted once, not per call; jax.device_put, not jnp.asarray, which compiles a
            # small program per new shape of a NumPy array (same dtypes, weak types, placement)
            self._dynamic = jax.tree_util.tree_map(jax.device_put, dynamic)
            model = scenario.model
            # the reference state of a contact model: the indenter at depth 0 (the depth is traced in the protocol)
            self._model = model.with_depth(0.0) if isinstance(model, ContactModel) else model
        self._bc, self._options = scenario.bc, scenario.options
        self._condensation = getattr(scenario, "condensation", None)
        # a scenario that builds its own setup (the incision): a function of the material that
        # keeps what it needs, not the scenario (which this cache must not keep alive)
        builder = getattr(scenario, "_setup_builder", None)
        self._builder = builder() if callable(builder) else None
        self._setups: dict = {}

    def setup(self, material):
        leaves, treedef = jax.tree_util.tree_flatten(material)
        key = (treedef, tuple((jnp.shape(v), jnp.result_type(v)) for v in leaves))
        hit = self._setups.get(key)
        if hit is None and self._builder is not None:
            hit = self._setups[key] = self._builder(material)
        elif hit is None and self._condensation is not None:
            # the condensed indentation: the direct solver (and CSR pattern) of its base model's
            # columns; None for the spectral solver (its arrays are the decomposition's)
            hit = self._setups[key] = condensation_setup(self._condensation.base, material, linear_solver=self._options.linear_solver)
        elif hit is None:
            o = self._options
            built = []
            # Built while the material is traced (abstractly, nothing compiled or run but the
            # reference matrix): the same setup as a solve traced with the mesh closed over,
            # without evaluating the model's element terms eagerly (op by op).
            jax.eval_shape(lambda m: built.append(solver_setup(self._model, m, self._bc, linear_solver=o.linear_solver,
                                                               preconditioner_material=o.preconditioner_material)), material)
            hit = self._setups[key] = built[0]
        return hit

    def __call__(self, material, *extra):
        return _call_raising_named_errors(self.program.fn, self._dynamic, self.setup(material), material, *extra)


#: ``(scenario, setup, material key)`` while an outer program traces ``scenario``'s arrays as
#: its arguments (:func:`traced_arguments`), None otherwise: read by :func:`_jitted_solve`.
_TRACED_ARGUMENTS: contextvars.ContextVar = contextvars.ContextVar("difftissue_scenario_traced_arguments", default=None)


def _material_key(material):
    """The structure of a material that a solver setup is built for (pytree, leaf shapes and dtypes)."""
    leaves, treedef = jax.tree_util.tree_flatten(material)
    return (treedef, tuple((jnp.shape(v), jnp.result_type(v)) for v in leaves))


def compiles_with_arguments(scenario) -> bool:
    """Whether ``scenario`` (concrete) has :func:`argument_setup`: its protocol can be compiled
    with its arrays and a solver setup as arguments (the full and the condensed indentation,
    compression, FEM field, incision: :func:`_takes_arguments`). False for scenarios of other
    kinds and scenarios with traced leaves."""
    return _takes_arguments(scenario, jax.tree_util.tree_leaves(scenario))


def argument_setup(scenario, material):
    """The :class:`~difftissue.solvers.static.SolverSetup` of ``scenario``'s static solves for
    materials of ``material``'s structure (values unused), when its protocol can be compiled
    with its arrays as arguments (:func:`compiles_with_arguments`; for the condensed
    indentation the setup of its condensation's columns,
    :func:`~difftissue.solvers.condensed.condensation_setup`); None otherwise.
    ``scenario`` must be concrete (not traced). With it, an outer program can take the
    scenario's array leaves and the setup's as arguments (:func:`traced_arguments`)."""
    if not compiles_with_arguments(scenario):
        return None
    fn = _jitted_solve(scenario)
    if not isinstance(fn, _ScenarioSolve):
        return None
    return fn.setup(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material))


class traced_arguments:
    """Context manager: while it is active, the protocol of ``scenario`` (a scenario whose
    array leaves an outer transformation traces, e.g. the program of
    :class:`~difftissue.config.SeparatelyCompiled`) is traced inline with ``setup`` (from
    :func:`argument_setup` of the concrete scenario, its arrays possibly traced too) for its
    static solves, instead of building a setup from its (traced) mesh. Only for materials of
    the structure the setup was built for (``material``); another raises ConfigError."""

    def __init__(self, scenario, setup, material):
        self._value = (scenario, setup, _material_key(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)))
        self._token = None

    def __enter__(self):
        self._token = _TRACED_ARGUMENTS.set(self._value)
        return self

    def __exit__(self, *exc):
        _TRACED_ARGUMENTS.reset(self._token)
        return False


def _traced_solve(scenario, setup, material_key, method, material, *extra):
    """``getattr(scenario, method)`` (its protocol, or another compiled method) traced inline with
    ``setup`` (see :class:`traced_arguments`)."""
    if _material_key(material) != material_key:
        raise ConfigError(f"{getattr(scenario, 'name', type(scenario).__name__)}: solved with a material of another structure than the "
                          "solver setup passed to traced_arguments was built for")
    token = _SOLVE_SETUP.set(setup)
    try:
        return getattr(scenario, method)(material, *extra)
    finally:
        _SOLVE_SETUP.reset(token)


def _jitted_solve(scenario, method: str = "_solve_protocol"):
    """``getattr(scenario, method)`` (its ``_solve_protocol`` by default) compiled once per
    scenario, shared by equal scenarios.

    Scenarios of :func:`_takes_arguments` (the full and condensed indentation, compression,
    FEM field, incision) are compiled with their arrays and the solver setup
    (:func:`~difftissue.solvers.static.solver_setup`, the condensation's or the scenario's own
    ``_setup_builder``, built from the concrete mesh before the call) as arguments
    (:class:`_ScenarioSolve`): the executable holds no mesh-sized constant, and every scenario
    of the same structure (:func:`_argument_key`: method, type, static configuration,
    scalars, array shapes) shares it.
    The others (scenarios of other kinds, a scenario traced by an outer transformation) are
    closed over (their arrays stay concrete NumPy, which their protocol needs), shared by
    equal scenarios (:func:`_structure_key`: same mesh, protocol and settings) when small.
    Inside an outer ``jit`` (a fit) the call is simply inlined. A scenario traced by an outer
    program with its setup given (:class:`traced_arguments`) is traced inline with that setup.
    """
    traced = _TRACED_ARGUMENTS.get()
    if traced is not None and traced[0] is scenario:
        return functools.partial(_traced_solve, *traced, method)
    key = (id(scenario), method)
    hit = _JITTED.get(key)
    if hit is not None and hit[0]() is scenario:
        return hit[1]
    leaves, treedef = jax.tree_util.tree_flatten(scenario)
    if _takes_arguments(scenario, leaves):
        dynamic, static = eqx.partition(scenario, eqx.is_array)
        shared_key = _argument_key(scenario, leaves, treedef, method)
        entry = _SHARED.pop(shared_key, None) if shared_key is not None else None
        if entry is None:
            entry = (static, _ArgumentSolve(static, method))
        fn = _ScenarioSolve(entry[1], scenario, dynamic)
    else:
        shared_key = _structure_key(scenario)
        shared_key = None if shared_key is None else (method,) + shared_key
        entry = _SHARED.pop(shared_key, None) if shared_key is not None else None
        if entry is None:
            entry = (scenario, _SharedSolve(method))
        entry[1].add(scenario)
        fn = _raising_named_errors(entry[1].fn)
    if shared_key is not None:
        _SHARED[shared_key] = entry  # most recent last
        while len(_SHARED) > SHARED_SOLVES_SIZE:
            _SHARED.popitem(last=False)
    # Only a weak reference to the scenario in its own entry: dropped with the object.
    _JITTED[key] = (weakref.ref(scenario, lambda _, k=key, cache=_JITTED: cache.pop(k, None)), fn)
    return fn


def _call_raising_named_errors(fn, *args):
    """``fn(*args)`` (a scenario's compiled protocol); called with concrete values it waits for
    the result and raises a failed check inside the program as the named error
    (:func:`~difftissue.solvers.static.named_runtime_error`: a static solve's failure as
    :class:`~difftissue.errors.ConvergenceError`, as ``SolverOptions.failure = "raise"``
    documents), not as JAX's runtime error with the host callback's traceback. Traced (inside
    an outer program) it is ``fn(*args)``."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(args)):
        return fn(*args)
    try:
        return jax.block_until_ready(fn(*args))
    except jax.errors.JaxRuntimeError as err:
        named = named_runtime_error(err)
        if named is None:
            raise
        raise named from None


def _raising_named_errors(fn):
    """``fn`` calling through :func:`_call_raising_named_errors`."""
    return functools.wraps(fn)(functools.partial(_call_raising_named_errors, fn))


def _shallowest_depth(abscissa, dtype):
    """The smallest positive depth of a protocol's ``abscissa`` [m] (a data leaf: traced in the
    compiled protocol), where a depth at or above the surface solves instead, discarding the
    result (the indentation protocols' ``step``)."""
    abscissa = jnp.asarray(abscissa, dtype=dtype)
    return jnp.min(jnp.where(abscissa > 0, abscissa, jnp.max(abscissa)))


def _force_where_touching(force_at, depth, start, rest, shallowest):
    """``force_at(depth, start) -> (force, u)`` of an indentation protocol's step where the
    indenter touches the specimen (``depth`` [m] > 0); where it does not (depth + contact_offset
    <= 0: a fitted offset that lifts the indenter), force 0 and the specimen at ``rest``. The
    solve there is replaced by one at the protocol's ``shallowest`` positive depth from rest
    (:func:`_shallowest_depth`), whose result is discarded: a branch-free select, so that
    forward-mode (vmapped) and reverse-mode derivatives get finite values from both sides (a
    solve with no load has nothing for its Newton loop to converge on).

    Returns:
        ``(touching, force, u)``.
    """
    touching = depth > 0
    f, u = force_at(jnp.where(touching, depth, shallowest), jnp.where(touching, start, rest))
    return touching, jnp.where(touching, f, jnp.zeros_like(f)), jnp.where(touching, u, rest)


def _history(u0):
    """The start of a protocol's equilibrium history for :func:`_extrapolate`: the zero state at
    load 0, twice (the unloaded specimen)."""
    zero = jnp.zeros((), dtype=u0.dtype)
    return (u0, u0, zero, zero)


def _advance(history, u, load):
    """``history`` after the equilibrium ``u`` at ``load``."""
    return (u, history[0], load, history[2])


def _extrapolate(history, load):
    """Starting guess for the next load of a protocol: the straight line through the last two
    equilibria (``history``: the last and the one before, with their loads), evaluated at
    ``load``. From the unloaded state this is the first equilibrium scaled by the load ratio
    (exact for a linear response); after that the secant follows a nonlinear response (contact
    growing with depth, stiffening) too: on the 20-depth springs_volume sphere indentation it
    takes 30 Newton steps in all against 69 for the scaled last equilibrium. Equal loads (a
    repeated point of the protocol) start from the last equilibrium."""
    u, u_before, load_before, load_before2 = history
    span = load_before - load_before2
    slope = (load - load_before) / jnp.where(span != 0, span, 1.0)
    return jnp.where(span != 0, u + slope * (u - u_before), u)


def _solve(model, material, bc, u0, opts: SolverOptions):
    # The warm start (the previous depth's equilibrium) does not change the solution; it
    # must not carry derivatives into the implicit-gradient solve.
    u0 = None if u0 is None else jax.lax.stop_gradient(u0)
    sol = solve_static(
        model, material, bc, rtol=opts.rtol, xtol=opts.xtol, max_steps=opts.max_steps, linear_solver=opts.linear_solver, initial_displacement=u0,
        throw=opts.failure == "raise", preconditioner_material=opts.preconditioner_material, setup=_SOLVE_SETUP.get(),
    )
    if opts.failure == "nan":
        # A multiplication by NaN, not a ``where``: the primal, its tangents (forward mode) and
        # its cotangents (reverse mode) all become NaN, where a ``where`` would give a zero
        # derivative (a finite gradient at a failed point). The solver's own tangents of a
        # failed solve are NaN as well (solve_static).
        nan = jnp.where(sol.converged, 1.0, jnp.nan).astype(sol.displacement.dtype)
        sol = eqx.tree_at(lambda s: (s.displacement, s.reaction), sol, (sol.displacement * nan, sol.reaction * nan))
    return sol


def _scales_with_youngs_modulus(model, bc: BoundaryConditions) -> bool:
    """Whether the static equilibria of ``model`` under ``bc`` are independent of Young's
    modulus and its reactions proportional to it: an energy linear in ``E`` and no applied
    force (prescribed displacements only). Needs a concrete ``bc.force``."""
    if not bool(getattr(model, "energy_linear_in_youngs_modulus", False)):
        return False
    force = bc.force
    if isinstance(force, jax.core.Tracer):
        return False
    return not bool(np.any(np.asarray(force) != 0.0))


class _Condensation(eqx.Module):
    """Penalty-contact indentation of a linear body solved on its candidate contact nodes.

    The candidates are the top-surface nodes the indenter could reach at 1.5 x the largest
    depth on the undeformed surface (the surface sinks around an indenter, so the true
    contact zone is smaller); after every depth the full field is recovered and any other
    top node that touches the indenter fails the solve (``SolverOptions.failure``).
    """

    base: ElasticModel
    free: np.ndarray
    nodes: np.ndarray
    dofs: np.ndarray
    contact: CondensedContactModel
    penalty_factors: np.ndarray
    contact_fixed: np.ndarray
    others: np.ndarray
    #: the free components among the candidates' ``3 k`` (``flatnonzero(~contact_fixed)``)
    rows: np.ndarray
    #: ``linear_solver="spectral"``: the body's eigendecomposition (arrays, shared by equal meshes).
    spectral: SpectralDecomposition | None

    def __init__(self, contact_model: ContactModel, bc: BoundaryConditions, max_depth: float, *, spectral: bool = False):
        X = np.asarray(contact_model.rest_points)
        top = np.asarray(contact_model.contact_nodes)
        reach = np.asarray(contact_model.indenter.penetration(jnp.asarray(X[top]), 1.5 * max_depth)) > 0
        if not np.any(reach):
            raise BoundaryConditionError("condensed indentation: no surface node within reach of the indenter")
        self.base = contact_model.base
        self.free = np.asarray(bc.free_mask)
        if np.any(np.asarray(bc.displacement)[~self.free] != 0.0) or np.any(np.asarray(bc.force) != 0.0):
            raise BoundaryConditionError("condensed indentation needs zero prescribed displacements and no other loads")
        self.nodes = top[reach]
        self.contact_fixed = ~self.free[self.nodes]
        flat = (3 * self.nodes[:, None] + np.arange(3)).reshape(-1)
        self.dofs = flat[self.free[self.nodes].reshape(-1)]
        self.penalty_factors = np.asarray(contact_model.penalty_factors)[reach]
        self.contact = CondensedContactModel(X[self.nodes], contact_model.indenter, _PenaltyEnergy(contact_model.indenter))
        self.others = top[~reach]
        self.rows = np.flatnonzero(~self.contact_fixed.reshape(-1))
        self.spectral = spectral_decomposition(self.base, self.free) if spectral else None

    def solve_protocol(self, material: Material, depths, options: SolverOptions):
        """Contact forces on the modelled part [N] and full displacement fields [m] at ``depths``."""
        if options.linear_solver == "spectral" and self.spectral is None:
            raise ConfigError("linear_solver='spectral': this condensation was built without its decomposition (build the scenario with these options)")
        # the setup of a protocol compiled with the arrays as arguments (_ScenarioSolve), else None: built here
        Z, G = linear_response_columns(self.base, material, self.free, self.dofs, linear_solver=options.linear_solver, decomposition=self.spectral,
                                       setup=_SOLVE_SETUP.get())
        S_free = jnp.linalg.inv(G)
        S_free = 0.5 * (S_free + S_free.T)
        k = self.nodes.size
        idx = jnp.asarray(self.rows)
        S = jnp.zeros((3 * k, 3 * k), dtype=G.dtype).at[idx[:, None], idx[None, :]].set(S_free)
        E = jnp.max(self.base.region_values(material)["youngs_modulus"])
        params = CondensedParameters(S, E * jnp.asarray(self.penalty_factors))
        free_c = ~self.contact_fixed
        X = jnp.asarray(self.base.rest_points)
        XC = jnp.asarray(self.contact.rest_points)
        indenter = self.contact.indenter

        def step(history, depth):
            model = self.contact.with_depth(depth)
            uc, converged = solve_condensed_contact(model, params, free_c, _extrapolate(history, depth), rtol=options.rtol, xtol=options.xtol, max_steps=options.max_steps)
            force = model.reaction_force(XC + uc, params)
            full = (Z.T @ (S @ uc.reshape(-1))[idx]).reshape(X.shape)
            outside = jnp.max(indenter.penetration(X[self.others] + full[self.others], depth)) if self.others.size else jnp.asarray(-1.0)
            bad = outside > 0
            if options.failure == "raise":
                force = eqx.error_if(force, ~converged, "condensed indentation: the contact solve on the candidate nodes did not converge")
                force = eqx.error_if(force, bad, "condensed indentation: a top-surface node outside the candidate set touches the indenter; use solver='full'")
            else:
                # Multiplications by NaN: NaN values, tangents and cotangents (see _solve).
                force = force * jnp.where(bad | ~converged, jnp.nan, 1.0)
                uc = uc * jnp.where(converged, 1.0, jnp.nan)
                full = full * jnp.where(converged, 1.0, jnp.nan)
            return _advance(history, uc, depth), (force, full)

        u0 = jnp.zeros((k, 3), dtype=G.dtype)
        _, (forces, us) = jax.lax.scan(step, _history(u0), jnp.asarray(depths, dtype=G.dtype))
        return forces, us


def _with_depths(rec: dict, depths, *, every: bool = False) -> dict:
    """``rec`` with the largest depth ``max_depth`` [m] and the number of ``points`` of a
    non-empty depth protocol (and, with ``every``, all ``depths`` [m])."""
    if depths is not None and np.size(depths):
        rec["max_depth"] = float(np.max(depths))
        rec["points"] = int(np.size(depths))
        if every:
            rec["depths"] = [float(v) for v in np.asarray(depths).reshape(-1)]
    return rec


def _uniform_block_cells(points, tets, size, symmetry: str) -> list[int] | None:
    """Full-block cell counts ``[nx, ny, nz]`` when the mesh ``(points [m], tets)`` is exactly
    :func:`indentation_block` ``(size, cells, symmetry)`` with uniform cells (its quarter with
    half the x and y cells for ``symmetry="quarter"``), else None."""
    p = np.asarray(points, dtype=float)
    t = np.asarray(tets)
    span = float(np.linalg.norm(np.ptp(p, axis=0)))
    counts = []
    for a in range(3):
        c = np.sort(p[:, a])
        counts.append(int(np.sum(np.diff(c) > 1e-9 * span)))
    if min(counts) < 1 or len(t) != 6 * counts[0] * counts[1] * counts[2]:
        return None
    try:
        ref = indentation_block(size, counts, symmetry=symmetry)
    except Exception:  # any size / count the generator refuses: not such a block
        return None
    if np.shape(ref.points) != p.shape or not np.allclose(ref.points, p, rtol=0, atol=1e-9 * span) or not np.array_equal(ref.tets, t):
        return None
    k = 2 if symmetry == "quarter" else 1
    return [k * counts[0], k * counts[1], counts[2]]


class Indentation(eqx.Module):
    """Simulated indentation of a specimen: force at each depth of a protocol.

    The specimen's top surface is indented along -z on the axis ``axis_xy``. Sphere and cone
    use frictionless penalty contact (:class:`~difftissue.contact.ContactModel`), the flat
    punch prescribed displacements (frictionless or bonded). The base ``z = min z`` is
    ``"bonded"`` (all components fixed) or ``"sliding"`` (``u_z = 0``; in-plane rigid modes
    removed by the symmetry planes or by pinning). With ``symmetry="quarter"`` the mesh is the
    quarter ``x >= 0, y >= 0`` with the axis on its corner: the planes x = 0 and y = 0 get
    ``u_x = 0`` / ``u_y = 0`` and the force is multiplied by 4.

    A top-surface node exactly on a cone's axis (under the apex) is held in x and y, as the
    quarter model's symmetry planes hold it: under a sharp frictionless tip it is in unstable
    equilibrium (its penetration is largest on the axis, so the penalty pushes it off in
    whichever direction round-off picks, by ``kappa p cos(theta)`` however close to the axis),
    and without the hold the full solve finds a symmetry-broken state (the node slid down the
    cone's flank, about 10 % less force on 0.5 mm cells under a 70 degree cone 0.25 mm deep)
    while the condensed solve stopped on the axis out of equilibrium (docs/dev/calculix-cone.md).

    The depths are solved in order, each starting from the previous equilibrium (a
    ``lax.scan``: one compilation for the whole protocol); the gradient with respect to the
    material is implicit at every depth.
    """

    #: the XLA option set of this scenario's compiled programs (a program kind of
    #: :data:`difftissue.xla_options.PROGRAMS`: static solves)
    xla_program = "static"

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    model: ElasticModel
    bc: BoundaryConditions
    punch_mask: np.ndarray | None
    punch: FlatPunch | None
    condensation: "_Condensation | None"
    symmetry: str = eqx.field(static=True)
    force_multiplier: float = eqx.field(static=True)
    options: SolverOptions = eqx.field(static=True)
    x_label: str = eqx.field(static=True, default="depth [m]")
    y_label: str = eqx.field(static=True, default="force [N]")

    def __init__(
        self,
        mesh: TetMesh,
        depths,
        forces=None,
        *,
        model: str = "springs_volume",
        indenter: str = "sphere",
        radius: float | None = None,
        half_angle: float | None = None,
        bonded_punch: bool = False,
        base: str = "bonded",
        symmetry: str = "none",
        axis_xy=None,
        surface: str = "top",
        axis_point=None,
        axis_direction=None,
        contact_point=None,
        rollers: Sequence = (),
        penalty: float = 100.0,
        sigma=None,
        options: SolverOptions = SolverOptions(),
        solver: str = "auto",
        name: str = "indentation",
    ):
        """
        Args:
            mesh: the specimen (e.g. :func:`indentation_block`, a layered skin, a file).
            depths: depth protocol [m], non-decreasing, from the contact point.
            forces: measured forces [N] (None: predictions only, ``observed`` is zeros).
            model: elastic model name (:func:`~difftissue.models.make_model`).
            indenter: ``"sphere"`` (``radius``), ``"cone"`` (``half_angle`` [rad]) or
                ``"flat_punch"`` (``radius``; ``bonded_punch`` for a no-slip face).
            base: ``"bonded"`` or ``"sliding"``.
            symmetry: ``"quarter"`` or ``"none"`` (see the class docstring).
            axis_xy: indenter axis [m]; default (0, 0) with quarter symmetry, else the centre of
                the top surface (with ``surface="boundary"``: of the nodes facing the indenter).
            surface: ``"top"`` (the plane ``z = max z``, indented along -z) or ``"boundary"``
                (any boundary: a dome, a cylinder, a mesh from file; sphere and cone only). With
                ``"boundary"`` the candidate contact nodes are the boundary nodes whose outward
                normal faces the indenter (:func:`~difftissue.contact.facing_surface_nodes`),
                and the depth is measured along the axis from the first contact
                (:func:`~difftissue.contact.place_indenter`).
            axis_point: a point [m] on the indenter axis (``surface="boundary"``; default
                ``(axis_xy, max z)``).
            axis_direction: the approach direction (``surface="boundary"``; default ``(0, 0, -1)``).
            contact_point: the tip's position [m] at depth 0 (``surface="boundary"``; default: the
                first contact along the axis).
            rollers: roller supports (:class:`~difftissue.boundary.Roller` or their data forms
                ``"x-max"`` / ``{"set": selector, "components": "x"}``): the listed displacement
                components held at zero, e.g. frictionless walls confining the sides. They add
                to ``base`` and ``symmetry`` (the force is not multiplied: a symmetry model is
                ``symmetry="quarter"``); a roller on the top surface's z (the contact surface)
                or the punch is refused, and with a sliding base no pin is added where the
                rollers already remove the in-plane rigid modes.
            penalty: contact penalty (see :class:`~difftissue.contact.ContactModel`).
            solver: ``"full"`` (a Newton solve of the whole specimen per depth),
                ``"condensed"`` (the linear body condensed onto the candidate contact nodes,
                :mod:`difftissue.solvers.condensed`: one factorisation per material, the
                same equilibrium; sphere or cone with ``model="fem_linear"`` only) or
                ``"auto"`` (condensed where it applies).
        """
        self.name = str(name)
        d = _as_1d("depths", depths)
        _check_depths(d)
        self.abscissa = d
        self.observed = np.zeros_like(d) if forces is None else _as_1d("forces", forces)
        if self.observed.shape != d.shape:
            raise DataError(f"{d.size} depths but {self.observed.size} forces")
        self.sigma = _sigma(self.observed, sigma) if forces is not None else np.ones_like(d)
        self.options = options
        self.x_label, self.y_label = "depth [m]", "force [N]"
        p = np.asarray(mesh.points)
        lo, hi = p.min(axis=0), p.max(axis=0)
        tol = 1e-9 * float(np.linalg.norm(hi - lo))
        if symmetry not in ("quarter", "none"):
            raise ConfigError(f"symmetry must be 'quarter' or 'none', got {symmetry!r}")
        if surface not in ("top", "boundary"):
            raise ConfigError(f"surface must be 'top' or 'boundary', got {surface!r}")
        curved = surface == "boundary"
        if not curved and not (axis_point is None and axis_direction is None and contact_point is None):
            raise ConfigError("axis_point, axis_direction and contact_point place an indenter on surface='boundary'; the flat top takes axis_xy")
        if curved and indenter not in ("sphere", "cone"):
            raise ConfigError(f"surface='boundary' supports the sphere and the cone (penalty contact), got indenter={indenter!r}")
        direction = (0.0, 0.0, -1.0) if axis_direction is None else tuple(float(v) for v in np.asarray(axis_direction, dtype=float).reshape(-1))
        mirror = ("x-min", "y-min") if symmetry == "quarter" else ()
        if symmetry == "quarter":
            if abs(lo[0]) > tol or abs(lo[1]) > tol:
                raise BoundaryConditionError("quarter symmetry needs the mesh's x >= 0, y >= 0 quarter with the axis at x = y = 0 (see indentation_block)")
            axis = (0.0, 0.0)
            if curved and (axis_point is not None or contact_point is not None or not np.allclose(direction, (0.0, 0.0, -1.0), rtol=0, atol=1e-12)):
                raise ConfigError("quarter symmetry indents along -z on the axis x = y = 0: leave axis_point, axis_direction and contact_point unset")
        elif curved:
            top = facing_surface_nodes(mesh, direction)
            if top.size == 0:
                raise BoundaryConditionError(f"no boundary node faces an indenter approaching along {list(direction)}")
            axis = tuple(float(v) for v in (0.5 * (p[top, :2].min(axis=0) + p[top, :2].max(axis=0)) if axis_xy is None else axis_xy))
        else:
            top = top_surface_nodes(mesh)
            axis = tuple(float(v) for v in (0.5 * (p[top, :2].min(axis=0) + p[top, :2].max(axis=0)) if axis_xy is None else axis_xy))
        candidates = facing_surface_nodes(mesh, direction, mirror_planes=mirror) if curved else None
        if curved and axis_point is None and contact_point is None:
            if not np.allclose(direction, (0.0, 0.0, -1.0), rtol=0, atol=1e-12):
                raise ConfigError("an indenter axis_direction other than (0, 0, -1) needs axis_point or contact_point [m]")
            axis_point = (axis[0], axis[1], float(hi[2]))
        self.symmetry = symmetry
        self.force_multiplier = 4.0 if symmetry == "quarter" else 1.0
        bc = BoundaryConditions.free(mesh)
        if base == "bonded":
            bc = bc.fix(mesh, {"face": "z-min"})
        elif base == "sliding":
            bc = bc.fix(mesh, {"face": "z-min"}, "z")
        else:
            raise ConfigError(f"base must be 'bonded' or 'sliding', got {base!r}")
        if symmetry == "quarter":
            bc = bc.fix(mesh, {"face": "x-min"}, "x").fix(mesh, {"face": "y-min"}, "y")
        if rollers:
            loaded = np.zeros((mesh.n_nodes, 3), dtype=bool)
            if indenter == "flat_punch" and radius is not None:
                loaded[FlatPunch(float(radius), axis_xy=axis, bonded=bonded_punch).nodes(mesh)] = True if bonded_punch else [False, False, True]
            elif curved:
                loaded[candidates] = np.abs(np.asarray(direction)) > 0  # the components the indenter's push has
            else:
                loaded[top_surface_nodes(mesh), 2] = True
            bc = apply_rollers(bc, mesh, rollers, loaded=loaded)
        if base == "sliding" and symmetry != "quarter":
            # pins for the in-plane rigid modes the rollers (if any) leave free: u_x, u_y of the
            # bottom node nearest the axis, u_y of the bottom node farthest from it along x
            bottom = np.flatnonzero(np.abs(p[:, 2] - lo[2]) <= tol)
            anchor = bottom[np.argmin(np.hypot(p[bottom, 0] - axis[0], p[bottom, 1] - axis[1]))]
            other = bottom[np.argmax(np.abs(p[bottom, 0] - p[anchor, 0]))]
            bc = pin_free_rigid_modes(mesh, bc, [(anchor, "x"), (anchor, "y"), (other, "y")])
        base_model = make_model(mesh, model)
        if indenter in ("sphere", "cone"):
            if indenter == "sphere":
                if radius is None:
                    raise ConfigError("a sphere indenter needs radius [m]")
                geom = SphereIndenter(float(radius), axis_xy=axis, surface_z=float(hi[2]))
            else:
                if half_angle is None:
                    raise ConfigError("a cone indenter needs half_angle [rad]")
                geom = ConeIndenter(float(half_angle), axis_xy=axis, surface_z=float(hi[2]))
            if curved:
                geom = place_indenter(geom, mesh, axis_point=axis_point, axis_direction=direction, contact_point=contact_point,
                                      nodes=candidates, mirror_planes=mirror)
            if indenter == "cone":
                # a top node exactly at the apex: held on the axis, the axisymmetric solution (class docstring)
                if curved:
                    t_touch = geom.touch_depth(p[candidates])
                    on_axis = np.asarray(geom.distance_from_axis(p[candidates])) <= tol
                    apex = candidates[on_axis & (np.abs(t_touch) <= tol)]
                    if apex.size:
                        n = np.asarray(geom.axis_direction)
                        along = np.flatnonzero(np.abs(n) > 1e-12)
                        if along.size != 1:
                            raise ConfigError("a node lies under the cone's apex on an axis that is not along x, y or z: it cannot be held on the axis; "
                                              "move the axis off the node or align it with a coordinate axis")
                        bc = bc.fix(mesh, apex, "".join(c for k, c in enumerate("xyz") if k != along[0]))
                else:
                    top = top_surface_nodes(mesh)
                    apex = top[np.hypot(p[top, 0] - axis[0], p[top, 1] - axis[1]) <= tol]
                    if apex.size:
                        bc = bc.fix(mesh, apex, "xy")
            self.model = ContactModel(base_model, geom, mesh, nodes=candidates, penalty=penalty, mirror_planes=mirror)
            self.punch_mask = None
            self.punch = None
        elif indenter == "flat_punch":
            if radius is None:
                raise ConfigError("a flat punch needs radius [m]")
            punch = FlatPunch(float(radius), axis_xy=axis, bonded=bonded_punch)
            nodes = punch.nodes(mesh)
            mask = np.zeros((mesh.n_nodes, 3), dtype=bool)
            mask[nodes, :] = [True, True, True] if bonded_punch else [False, False, True]
            bc = punch.apply(mesh, bc, 0.0)
            self.model = base_model
            self.punch_mask = mask
            self.punch = punch
        else:
            raise ConfigError(f"indenter must be 'sphere', 'cone' or 'flat_punch', got {indenter!r}")
        self.bc = bc
        if solver not in ("auto", "full", "condensed"):
            raise ConfigError(f"solver must be 'auto', 'full' or 'condensed', got {solver!r}")
        can_condense = model == "fem_linear" and indenter in ("sphere", "cone")
        if solver == "condensed" and not can_condense:
            raise ConfigError(
                "solver='condensed' needs a linear body (model='fem_linear') and penalty contact (indenter 'sphere' or 'cone'); "
                f"got model={model!r}, indenter={indenter!r}: use solver='full'"
            )
        spectral = options.linear_solver == "spectral"
        if spectral:
            if not can_condense or solver == "full":
                raise ConfigError(
                    "linear_solver='spectral' applies to the condensed indentation (model='fem_linear', indenter 'sphere' or 'cone', "
                    f"solver 'auto' or 'condensed'); got model={model!r}, indenter={indenter!r}, solver={solver!r}"
                )
            why = spectral_unsupported(base_model, bc.free_mask)
            if why is not None:
                raise ConfigError(f"linear_solver='spectral': {why}")
        self.condensation = _Condensation(self.model, bc, float(d.max()), spectral=spectral) if (can_condense and solver != "full") else None

    def spectral_variant(self, *, required: bool = False) -> "Indentation | None":
        """This scenario with ``options.linear_solver="spectral"`` (the same predictions to
        round-off, no factorisation per material: :mod:`difftissue.solvers.spectral`), or None
        where it does not apply: not a condensed indentation, another linear solver chosen
        explicitly, or a body out of the spectral solver's scope (not one-region
        ``fem_linear``, more than ``SPECTRAL_MAX_UNKNOWNS`` unknowns). The decomposition is
        computed on the host (about 1.2 s CPU at 2,187 unknowns) once per mesh and shared.

        Args:
            required: raise :class:`~difftissue.errors.ConfigError` with the reason instead of
                returning None (an explicitly chosen linear solver is then replaced).
        """
        if self.options.linear_solver == "spectral":
            return self
        if self.condensation is None:
            why = "not a condensed indentation (model 'fem_linear', sphere or cone, solver 'auto' or 'condensed')"
        elif self.options.linear_solver != "auto" and not required:
            why = f"linear_solver={self.options.linear_solver!r} was chosen explicitly"
        else:
            why = spectral_unsupported(self.condensation.base, self.condensation.free)
        if why is not None:
            if required:
                raise ConfigError(f"scenario {self.name!r}: the spectral solver does not apply: {why}")
            return None
        decomposition = spectral_decomposition(self.condensation.base, self.condensation.free)
        new = eqx.tree_at(lambda s: s.condensation.spectral, self, decomposition, is_leaf=lambda x: x is None)
        object.__setattr__(new, "options", dataclasses.replace(self.options, linear_solver="spectral"))  # a static field: a new structure
        return new

    def _force_at(self, material, depth, u0):
        if self.punch_mask is None:
            model = self.model.with_depth(depth)
            sol = _solve(model, material, self.bc, u0, self.options)
            force = model.reaction_force(jnp.asarray(model.rest_points) + sol.displacement, material)
        else:
            zmask = jnp.asarray(self.punch_mask[:, 2])
            disp = self.bc.displacement.at[:, 2].set(jnp.where(zmask, -depth, self.bc.displacement[:, 2]))
            bc = BoundaryConditions(self.bc.fixed, disp, self.bc.force)
            sol = _solve(self.model, material, bc, u0, self.options)
            force = -jnp.sum(jnp.where(zmask, sol.reaction[:, 2], 0.0))
        return self.force_multiplier * force, sol.displacement

    def solve(self, material: Material, contact_offset=0.0):
        """``(forces (n,) [N], displacements (n, N, 3) [m])`` along the protocol (compiled once
        per scenario).

        ``contact_offset`` [m] is added to every depth of the protocol (the indenter at
        ``depth + contact_offset``: a contact point found too late by ``contact_offset``).
        The forces are differentiable with respect to it (implicit function theorem: the
        indenter depth is a differentiated leaf of the contact model, or the punch's
        prescribed displacement), e.g. ``jax.grad(lambda c: sc.solve(m, c)[0].sum())``.
        :func:`~difftissue.fit.fit` fits it with the material fields where asked
        (``scenario_parameters={name: ("contact_offset",)}``, :meth:`fittable_parameters`);
        see docs/scenarios.md."""
        material = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)
        return _jitted_solve(self)(material, jnp.asarray(contact_offset, dtype=float))

    def _solve_protocol(self, material: Material, contact_offset=0.0):
        depths = jnp.asarray(self.abscissa) + contact_offset
        if self.condensation is not None:
            forces, us = self.condensation.solve_protocol(material, depths, self.options)
            return self.force_multiplier * forces, us
        u0 = jnp.zeros(self.bc.displacement.shape, dtype=jnp.result_type(float))
        shallowest = _shallowest_depth(self.abscissa, u0.dtype)

        # A depth at or above the surface has force 0 (_force_where_touching); the history
        # starts again from rest after it.
        def step(history, depth):
            touching, f, u_new = _force_where_touching(functools.partial(self._force_at, material), depth, _extrapolate(history, depth), u0, shallowest)
            history = jax.tree_util.tree_map(lambda a, b: jnp.where(touching, a, b), _advance(history, u_new, depth), _history(u0))
            return history, (f, u_new)

        _, (forces, us) = jax.lax.scan(step, _history(u0), jnp.asarray(depths, dtype=u0.dtype))
        return forces, us

    def resolution(self, min_cells_per_contact_radius: float = MIN_CELLS_PER_CONTACT_RADIUS) -> IndentationResolution:
        """Cells per contact radius at each depth: the half-space contact radius of the indenter
        (:func:`indentation_contact_radius`; on a curved surface an estimate) over the mesh's
        cell size under the indenter (the median nearest-neighbour spacing of the
        :data:`_AXIS_NODES` contact-surface nodes nearest the axis: the first cell of a graded
        block). Depths below ``min_cells_per_contact_radius`` are :attr:`~IndentationResolution.flagged`;
        :meth:`IndentationResolution.warn` emits :class:`~difftissue.errors.UnderResolvedContactWarning`.

        Raises:
            ConfigError: ``min_cells_per_contact_radius`` not a positive number.
        """
        m = float(min_cells_per_contact_radius)
        if not (math.isfinite(m) and m > 0):
            raise ConfigError(f"min_cells_per_contact_radius must be a positive number of cells, got {min_cells_per_contact_radius!r}")
        X = np.asarray(self.model.rest_points, dtype=float)
        if self.punch is None:
            geom = self.model.indenter
            nodes = np.asarray(self.model.contact_nodes)
            dist = np.asarray(geom.distance_from_axis(jnp.asarray(X[nodes])), dtype=float)
            kind = "sphere" if isinstance(geom, SphereIndenter) else "cone"
            a = indentation_contact_radius(kind, self.abscissa, radius=getattr(geom, "radius", None), half_angle=getattr(geom, "half_angle", None))
        else:
            kind = "flat_punch"
            zs = X[:, 2]
            nodes = np.flatnonzero(np.abs(zs - zs.max()) <= 1e-9 * max(float(np.ptp(X, axis=0).max()), 1e-300))
            dist = np.hypot(X[nodes, 0] - self.punch.axis_xy[0], X[nodes, 1] - self.punch.axis_xy[1])
            a = indentation_contact_radius(kind, self.abscissa, radius=self.punch.radius)
        h = _cell_size_at_axis(X, nodes, dist)
        return IndentationResolution(name=self.name, indenter=kind, depths=np.asarray(self.abscissa, dtype=float), contact_radius=a,
                                     cell_size=h, cells_per_contact_radius=a / h, min_cells_per_contact_radius=m)

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of the predictions (from the solver options)."""
        return self.options.prediction_rtol

    @property
    def prediction_scales_with_youngs_modulus(self) -> bool:
        """True when every predicted force is exactly proportional to Young's modulus at fixed
        other material fields: the model's energy, contact penalty included, is linear in
        ``E`` (:attr:`~difftissue.models.ElasticModel.energy_linear_in_youngs_modulus`) and the
        depths are prescribed with no applied force, so the equilibria do not depend on ``E``
        (``d u / d E = 0``) and ``d F / d E = F / E``. :class:`~difftissue.config.SeparatelyCompiled`
        then takes a Jacobian's ``E`` column in that closed form instead of an
        implicit-function-theorem solve per depth."""
        return _scales_with_youngs_modulus(self.model, self.bc)

    def fittable_parameters(self) -> dict:
        """What :func:`~difftissue.fit.fit` can fit besides the material
        (``scenario_parameters``): the ``contact_offset`` [m] of :meth:`solve`
        (:func:`contact_offset_parameter`)."""
        return contact_offset_parameter(self.abscissa)

    def predict(self, material: Material, contact_offset=0.0):
        """Indentation force [N] at each depth (positive compressive); ``contact_offset`` [m]
        shifts every depth (see :meth:`solve`)."""
        return self.solve(material, contact_offset)[0]

    def record(self) -> dict:
        """The experiment as a material card's scenario record (``provenance.scenario_records``,
        :func:`difftissue.export.card.scenario_record`), from which an export rebuilds the
        specimen and a lattice card is recalibrated (docs/export.md).

        ``name``, ``type``, ``experiment = "indentation"``; the indenter (the sphere's or cone's
        :meth:`~difftissue.contact.SphereIndenter.record`, or the punch's
        :meth:`~difftissue.contact.FlatPunch.record`: its effective radius [m], the outermost
        node ring under the punch, and ``bonded_punch``); ``base`` (``"bonded"`` / ``"sliding"``);
        ``block_size`` [m] (a quarter-symmetric block at full size), ``symmetry``, the fit's
        full-block ``cells`` when the mesh is a uniform :func:`indentation_block`; difftissue's
        ``model``; the contact ``penalty`` (sphere, cone); ``max_depth`` [m], ``points`` and
        every fitted depth ``depths`` [m]."""
        rec: dict[str, Any] = {"name": self.name, "type": type(self).__name__, "experiment": "indentation"}
        rest = np.asarray(self.model.rest_points)
        if self.punch is None:
            rec.update(self.model.indenter.record())
        else:
            rec.update(self.punch.record(rest, np.flatnonzero(self.punch_mask[:, 2])))
        fixed = np.asarray(self.bc.fixed)
        zr = rest[:, 2]
        bottom = np.flatnonzero(np.abs(zr - zr.min()) <= 1e-9 * max(float(np.ptp(zr)), 1e-300))
        rec["base"] = "bonded" if np.all(fixed[bottom]) else "sliding"
        span = rest.max(axis=0) - rest.min(axis=0)
        k = 2 if self.symmetry == "quarter" else 1
        rec["block_size"] = [float(span[0] * k), float(span[1] * k), float(span[2])]
        rec["symmetry"] = self.symmetry
        cells = _uniform_block_cells(rest, self.model.tets, rec["block_size"], self.symmetry)
        if cells is not None:
            rec["cells"] = cells
            rec["cells_note"] = ("the fit's mesh: indentation_block(block_size, cells, symmetry='none') of uniform cells"
                                 + (" (the fit modelled the x >= 0, y >= 0 quarter with half the x and y cells)" if k == 2 else ""))
        rec["model"] = str(self.model.model_name) or None
        if self.punch is None:
            rec["penalty"] = float(self.model.penalty)
            if not self.model.indenter.on_flat_top:
                rec["surface"] = "boundary"
        return _with_depths(rec, self.abscissa, every=True)


#: Cells per contact radius (at the largest depth) of the automatic axisymmetric specimen
#: (:func:`axisymmetric_specimen_for`), from ``experiments/axisymmetric_indentation.py``
#: (docs/experiments.md, "Axisymmetric indentation").
AXISYMMETRIC_CELLS_PER_CONTACT_RADIUS = 8
#: Largest ratio of neighbouring cell sizes outside the core of the automatic axisymmetric specimen [-].
AXISYMMETRIC_CELL_GROWTH = 1.15


@dataclasses.dataclass(frozen=True)
class AxisymmetricSpecimen:
    """A cylinder's meridian mesh for axisymmetric indentation chosen from the indenter and the
    depth (:func:`axisymmetric_specimen_for`): the arguments of
    :func:`~difftissue.axisymmetric.axisymmetric_cylinder` and why.

    Attributes:
        radius, height: the cylinder [m].
        first: cell size [m] at the contact (uniform within ``core`` of the axis and the top).
        core: width [m] of the uniform core.
        growth: largest ratio of neighbouring cell sizes beyond the core [-].
        contact_radius: half-space contact radius ``a`` [m] at the largest depth.
        cells_per_contact_radius: ``a / first`` [-].
        thickness_given: True when the height is the specimen's own (a layer), False for the
            half-space approximation (radius and height ``extent * a``).
        indenter: ``"sphere"`` or ``"cone"``.
    """

    radius: float
    height: float
    first: float
    core: float
    growth: float
    contact_radius: float
    cells_per_contact_radius: float
    thickness_given: bool
    indenter: str

    def mesh(self) -> AxisymmetricMesh:
        """The meridian mesh (:func:`~difftissue.axisymmetric.axisymmetric_cylinder`)."""
        return axisymmetric_cylinder(self.radius, self.height, first=self.first, core=self.core, growth=self.growth)

    def refined(self, factor: float) -> "AxisymmetricSpecimen":
        """Every cell divided by ``factor`` (> 0; < 1 coarsens): first cells ``first / factor``
        and growth ``growth ** (1 / factor)`` (the graded cells shrink alike), same size and
        core: the sequence of a convergence study with cell size ratio ``factor``."""
        f = float(factor)
        if not (math.isfinite(f) and f > 0):
            raise ConfigError(f"factor must be a positive number, got {factor!r}")
        return dataclasses.replace(self, first=self.first / f, growth=self.growth ** (1.0 / f),
                                   cells_per_contact_radius=self.cells_per_contact_radius * f)

    def record(self) -> dict:
        """The choice as plain numbers (SI) for reports and ``fit.json``."""
        return {"rule": "axisymmetric_specimen_for", "geometry": "axisymmetric", "radius": self.radius, "height": self.height,
                "first": self.first, "core": self.core, "growth": self.growth, "contact_radius": self.contact_radius,
                "cells_per_contact_radius": self.cells_per_contact_radius, "thickness_given": self.thickness_given,
                "indenter": self.indenter}


def axisymmetric_specimen_for(indenter: str, *, radius: float | None = None, half_angle: float | None = None, max_depth: float,
                              thickness: float | None = None, cells_per_contact_radius: float = AXISYMMETRIC_CELLS_PER_CONTACT_RADIUS,
                              growth: float = AXISYMMETRIC_CELL_GROWTH, extent: float = HALF_SPACE_EXTENT) -> AxisymmetricSpecimen:
    """The cylinder to simulate a sphere or cone indentation to ``max_depth`` [m] axisymmetrically.

    The half-space contact radius ``a`` at ``max_depth`` (:func:`indentation_contact_radius`)
    sets the scale: cells of ``a / cells_per_contact_radius`` within ``CONTACT_CORE * a`` of the
    axis and the surface, growing by at most ``growth`` beyond, out to a radius of
    ``extent * a`` and a height of ``extent * a`` (a half-space) or ``thickness`` [m] (a
    layer of that thickness on the scenario's base: its finite-thickness stiffening is then
    part of the model; :func:`thin_specimen_warning` says when it is large).

    Raises:
        ConfigError: an unknown indenter, a missing size, a non-positive depth, or a
            thickness that leaves no room below the contact core (``CONTACT_CORE * a`` plus
            one cell, and more than ``max_depth``), as :func:`indentation_specimen_for`.
    """
    if indenter not in ("sphere", "cone"):
        raise ConfigError(f"the axisymmetric specimen is for a sphere or a cone, got {indenter!r}")
    d = float(max_depth)
    if not (math.isfinite(d) and d > 0):
        raise ConfigError(f"max_depth must be > 0 m, got {max_depth!r}")
    m = float(cells_per_contact_radius)
    if not (math.isfinite(m) and m >= 1):
        raise ConfigError(f"cells_per_contact_radius must be >= 1, got {cells_per_contact_radius!r}")
    if not (math.isfinite(float(growth)) and float(growth) > 1):
        raise ConfigError(f"growth must be > 1, got {growth!r}")
    a = float(indentation_contact_radius(indenter, d, radius=radius, half_angle=half_angle))
    H = extent * a if thickness is None else float(thickness)
    if not (math.isfinite(H) and H > 0):
        raise ConfigError(f"thickness must be > 0 m, got {thickness!r}")
    if thickness is not None and not (H > CONTACT_CORE * a + a / m and H > d):
        raise ConfigError(f"thickness {H:.4g} m leaves no room below the contact core ({CONTACT_CORE * a + a / m:.4g} m deep: {CONTACT_CORE:g} contact "
                          f"radii of {a:.4g} m and one cell, at max_depth {d:.4g} m): a layer that thin is outside the automatic specimen; "
                          "give a mesh (AxisymmetricIndentation(mesh=axisymmetric_cylinder(...)))")
    return AxisymmetricSpecimen(radius=float(extent * a), height=H, first=a / m, core=CONTACT_CORE * a, growth=float(growth),
                                contact_radius=a, cells_per_contact_radius=m, thickness_given=thickness is not None, indenter=indenter)


#: Specimen thickness in contact radii (at the deepest point) below which
#: :func:`thin_specimen_warning` warns [-]: at 10 a a bonded layer raises a sphere's force by
#: 12 % over the half-space's at nu = 0.45 (``analytic.layer_sphere_factor(0.1, 0.45)``).
THIN_SPECIMEN_CONTACT_RADII = 10.0


def thin_specimen_warning(specimen, where: str | None = None, stacklevel: int = 2) -> str | None:
    """Emit :class:`~difftissue.errors.ThinSpecimenWarning` when an automatic specimen
    (:class:`AxisymmetricSpecimen` or :class:`IndentationSpecimen`) was given a thickness of
    less than :data:`THIN_SPECIMEN_CONTACT_RADII` contact radii; returns its message (None
    when the specimen is a half-space or thick enough)."""
    if not specimen.thickness_given:
        return None
    H = float(specimen.height if isinstance(specimen, AxisymmetricSpecimen) else specimen.size[2])
    a = float(specimen.contact_radius)
    if H >= THIN_SPECIMEN_CONTACT_RADII * a:
        return None
    msg = ((f"{where}: " if where else "") + f"the specimen is {H / a:.3g} contact radii thick ({H:.4g} m, contact radius {a:.4g} m at the deepest "
           f"point; < {THIN_SPECIMEN_CONTACT_RADII:g}): the base stiffens the force markedly (a sphere on a bonded layer 10 contact radii thick: "
           "+12 % over the half-space at nu = 0.45), so the fitted modulus is only as good as the thickness and base condition given")
    warnings.warn(msg, ThinSpecimenWarning, stacklevel=stacklevel + 1)
    return msg


class AxisymmetricIndentation(eqx.Module):
    """Simulated indentation of a cylinder by a sphere or cone on its axis, solved in the
    meridian plane (:mod:`difftissue.axisymmetric`): force at each depth of a protocol.

    The specimen is a cylinder with its base ``"bonded"`` or ``"sliding"``; its outer radius
    is free. It is solved translated so that its top surface lies at ``z = 0`` (``model``'s
    rest points; displacements and forces do not depend on it): the round-off of the small
    elements' strains under the indenter is then that of their own size. By default it is
    the half-space-like cylinder of
    :func:`axisymmetric_specimen_for` (``thickness`` makes it a layer), or give ``mesh`` (an
    :class:`~difftissue.axisymmetric.AxisymmetricMesh`). Frictionless penalty contact as in
    :class:`Indentation` (:class:`~difftissue.axisymmetric.AxisymmetricContactModel`); the
    depths are solved in order, each from the previous equilibrium, with a Newton solve of the
    whole meridian mesh and a sparse direct factorisation (``options.linear_solver="auto"``
    means ``"sparse"`` here); the gradient with respect to the material is implicit at every
    depth. Models: ``fem_linear``, ``fem_neo_hookean`` and ``stable_neo_hookean`` (the
    springs_volume lattices have no axisymmetric form: use :class:`Indentation`).
    """

    #: the XLA option set of this scenario's compiled programs (a program kind of
    #: :data:`difftissue.xla_options.PROGRAMS`: static solves)
    xla_program = "static"

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    model: AxisymmetricContactModel
    bc: BoundaryConditions
    specimen: AxisymmetricSpecimen | None = eqx.field(static=True)
    options: SolverOptions = eqx.field(static=True)
    x_label: str = eqx.field(static=True, default="depth [m]")
    y_label: str = eqx.field(static=True, default="force [N]")

    def __init__(self, depths, forces=None, *, indenter: str = "sphere", radius: float | None = None, half_angle: float | None = None,
                 model: str = "fem_linear", mesh: AxisymmetricMesh | None = None, thickness: float | None = None,
                 cells_per_contact_radius: float = AXISYMMETRIC_CELLS_PER_CONTACT_RADIUS, base: str = "bonded", penalty: float = 100.0,
                 sigma=None, options: SolverOptions = SolverOptions(), name: str = "indentation", specimen: AxisymmetricSpecimen | None = None):
        """
        Args:
            depths: depth protocol [m], non-decreasing, from the contact point.
            forces: measured forces [N] (None: predictions only, ``observed`` is zeros).
            indenter: ``"sphere"`` (``radius`` [m]) or ``"cone"`` (``half_angle`` [rad]).
            model: ``"fem_linear"``, ``"fem_neo_hookean"`` or ``"stable_neo_hookean"``
                (:data:`~difftissue.axisymmetric.AXISYMMETRIC_MODELS`).
            mesh: the cylinder's meridian mesh; default :func:`axisymmetric_specimen_for`
                at the largest depth with ``thickness`` and ``cells_per_contact_radius``.
            base: ``"bonded"`` or ``"sliding"``.
            penalty: contact penalty (see :class:`~difftissue.contact.ContactModel`).
            specimen: an :class:`AxisymmetricSpecimen` to mesh instead of the automatic one
                (e.g. ``axisymmetric_specimen_for(...).refined(0.5)``, or the specimen of a
                protocol whose depths were later thinned); recorded like the automatic one.
                Not with ``mesh`` or ``thickness``.
        """
        self.name = str(name)
        d = _as_1d("depths", depths)
        _check_depths(d)
        self.abscissa = d
        self.observed = np.zeros_like(d) if forces is None else _as_1d("forces", forces)
        if self.observed.shape != d.shape:
            raise DataError(f"{d.size} depths but {self.observed.size} forces")
        self.sigma = _sigma(self.observed, sigma) if forces is not None else np.ones_like(d)
        self.options = options if options.linear_solver != "auto" else dataclasses.replace(options, linear_solver="sparse")
        self.x_label, self.y_label = "depth [m]", "force [N]"
        if model not in AXISYMMETRIC_MODELS:
            raise ConfigError(f"the axisymmetric indentation supports the models {AXISYMMETRIC_MODELS}, got {model!r}"
                              + (": a lattice has no axisymmetric form, use Indentation (3-D)" if model in LATTICE_MODELS else ""))
        if indenter not in ("sphere", "cone"):
            raise ConfigError(f"the axisymmetric indentation takes indenter 'sphere' or 'cone', got {indenter!r}")
        if specimen is not None:
            if not isinstance(specimen, AxisymmetricSpecimen):
                raise ConfigError(f"specimen must be an AxisymmetricSpecimen, got {type(specimen).__name__}")
            if mesh is not None or thickness is not None:
                raise ConfigError("give the specimen, or a mesh (or thickness for the automatic specimen), not both")
            if specimen.indenter != indenter:
                raise ConfigError(f"the specimen was chosen for a {specimen.indenter}, the indenter is a {indenter}")
            self.specimen = specimen
            mesh = specimen.mesh()
        elif mesh is None:
            self.specimen = axisymmetric_specimen_for(indenter, radius=radius, half_angle=half_angle, max_depth=float(d.max()),
                                                      thickness=thickness, cells_per_contact_radius=cells_per_contact_radius)
            thin_specimen_warning(self.specimen, stacklevel=2)
            mesh = self.specimen.mesh()
        else:
            if not isinstance(mesh, AxisymmetricMesh):
                raise ConfigError(f"mesh must be an AxisymmetricMesh (difftissue.axisymmetric), got {type(mesh).__name__}")
            if thickness is not None:
                raise ConfigError("thickness sets the automatic specimen's height; with a mesh given, leave it unset")
            self.specimen = None
        # The mesh is solved translated so that its top surface is at z = 0 (the contact
        # point): an element's strain is computed from differences of positions, whose
        # round-off is eps times the coordinates' size. With the top at z = height (200
        # contact radii) that is ~1e-13 strain under the indenter and a residual floor above
        # the Newton tolerance (measured: 80 deg cone at 11.3 cells per contact radius, a
        # sphere at nu = 0.49); at z = 0 the coordinates near the contact are a few cells.
        top = float(mesh.points[:, 1].max())
        mesh = AxisymmetricMesh(mesh.points - np.array([0.0, top]), mesh.triangles)
        top = 0.0
        if indenter == "sphere":
            if radius is None:
                raise ConfigError("a sphere indenter needs radius [m]")
            geom = SphereIndenter(float(radius), surface_z=top)
        else:
            if half_angle is None:
                raise ConfigError("a cone indenter needs half_angle [rad]")
            geom = ConeIndenter(float(half_angle), surface_z=top)
        self.model = AxisymmetricContactModel(AxisymmetricModel(mesh, model), geom, mesh, penalty=penalty)
        self.bc = axisymmetric_boundary_conditions(mesh, base=base)

    def _force_at(self, material, depth, u0):
        model = self.model.with_depth(depth)
        sol = _solve(model, material, self.bc, u0, self.options)
        return model.reaction_force(jnp.asarray(model.rest_points) + sol.displacement, material), sol.displacement

    def solve(self, material: Material, contact_offset=0.0):
        """``(forces (n,) [N], displacements (n, N, 3) [m])`` along the protocol; the
        displacements are ``(u_r, 0, u_z)`` of the meridian nodes. ``contact_offset`` [m] is
        added to every depth (see :meth:`Indentation.solve`)."""
        material = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)
        return _jitted_solve(self)(material, jnp.asarray(contact_offset, dtype=float))

    def _solve_protocol(self, material: Material, contact_offset=0.0):
        depths = jnp.asarray(self.abscissa) + contact_offset
        u0 = jnp.zeros(self.bc.displacement.shape, dtype=jnp.result_type(float))

        # A depth at or above the surface has force 0 and leaves the specimen at rest
        # (_force_where_touching).
        shallowest = _shallowest_depth(self.abscissa, u0.dtype)

        # Each depth starts from the previous equilibrium, not from the secant extrapolation
        # of Indentation (_extrapolate): under a cone the extrapolated state made the line
        # search fail at the second depth (measured, 4 cells per contact radius, 70 deg).
        def step(u_prev, depth):
            _, f, u_new = _force_where_touching(functools.partial(self._force_at, material), depth, u_prev, u0, shallowest)
            return u_new, (f, u_new)

        _, (forces, us) = jax.lax.scan(step, u0, jnp.asarray(depths, dtype=u0.dtype))
        return forces, us

    def resolution(self, min_cells_per_contact_radius: float = MIN_CELLS_PER_CONTACT_RADIUS) -> IndentationResolution:
        """Cells per contact radius at each depth (as :meth:`Indentation.resolution`): the
        half-space contact radius over the median spacing of the top nodes nearest the axis."""
        m = float(min_cells_per_contact_radius)
        if not (math.isfinite(m) and m > 0):
            raise ConfigError(f"min_cells_per_contact_radius must be a positive number of cells, got {min_cells_per_contact_radius!r}")
        geom = self.model.indenter
        X, nodes = np.asarray(self.model.rest_points), np.asarray(self.model.contact_nodes)
        h = _cell_size_at_axis(X, nodes, X[nodes, 0])  # the meridian's r is the distance from the axis
        kind = "sphere" if isinstance(geom, SphereIndenter) else "cone"
        a = indentation_contact_radius(kind, self.abscissa, radius=getattr(geom, "radius", None), half_angle=getattr(geom, "half_angle", None))
        return IndentationResolution(name=self.name, indenter=kind, depths=np.asarray(self.abscissa, dtype=float), contact_radius=a,
                                     cell_size=h, cells_per_contact_radius=a / h, min_cells_per_contact_radius=m)

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of the predictions (from the solver options)."""
        return self.options.prediction_rtol

    @property
    def prediction_scales_with_youngs_modulus(self) -> bool:
        """True: both models' energies and the penalty are linear in ``E`` and the depths are
        prescribed (see :attr:`Indentation.prediction_scales_with_youngs_modulus`)."""
        return _scales_with_youngs_modulus(self.model, self.bc)

    def fittable_parameters(self) -> dict:
        """What :func:`~difftissue.fit.fit` can fit besides the material
        (``scenario_parameters``): the ``contact_offset`` [m] of :meth:`solve`
        (:func:`contact_offset_parameter`)."""
        return contact_offset_parameter(self.abscissa)

    def predict(self, material: Material, contact_offset=0.0):
        """Indentation force [N] at each depth (positive compressive); ``contact_offset`` [m]
        shifts every depth (see :meth:`Indentation.solve`)."""
        return self.solve(material, contact_offset)[0]

    def record(self) -> dict:
        """The experiment as a material card's scenario record: ``name``, ``type``,
        ``experiment = "indentation"``, ``geometry = "axisymmetric"``, the indenter, ``base``,
        the cylinder's ``radius_of_specimen`` and ``height`` [m], the mesh's
        ``cells_per_contact_radius`` and ``growth`` (the automatic specimen's), ``model``,
        ``penalty`` and the depths."""
        rec: dict[str, Any] = {"name": self.name, "type": type(self).__name__, "experiment": "indentation", "geometry": "axisymmetric"}
        rec.update(self.model.indenter.record())
        rest = np.asarray(self.model.rest_points)
        fixed = np.asarray(self.bc.fixed)
        bottom = np.flatnonzero(np.abs(rest[:, 2] - rest[:, 2].min()) <= 1e-9 * float(np.ptp(rest[:, 2])))
        rec["base"] = "bonded" if np.all(fixed[bottom][:, [0, 2]]) else "sliding"
        rec["radius_of_specimen"] = float(rest[:, 0].max())
        rec["height"] = float(np.ptp(rest[:, 2]))
        rec["nodes"] = int(rest.shape[0])
        if self.specimen is not None:
            rec["specimen"] = self.specimen.record()
        rec["model"] = str(self.model.kind)
        rec["penalty"] = float(self.model.penalty)
        return _with_depths(rec, self.abscissa, every=True)


class Compression(eqx.Module):
    """Unconfined compression between rigid platens: stress at each strain of a protocol.

    Predictions are nominal (engineering) stress ``F / A0`` [Pa] against nominal strain
    ``delta / H`` (``measure="engineering"``), or true stress ``F / A`` with the current mean
    cross-section ``A = V / h`` (volume over current height) against true strain
    ``-ln(1 - delta / H)`` (``measure="true"``); compression positive.

    With frictionless platens the deformation of a homogeneous specimen is homogeneous, so a
    small block gives the exact answer for any specimen shape; bonded platens (barrelling)
    need the real shape (:func:`cylinder`).
    """

    #: the XLA option set of this scenario's compiled programs (a program kind of
    #: :data:`difftissue.xla_options.PROGRAMS`: static solves)
    xla_program = "static"

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    model: ElasticModel
    bc: BoundaryConditions
    top_mask: np.ndarray
    height: float = eqx.field(static=True)
    area: float = eqx.field(static=True)
    measure: str = eqx.field(static=True)
    bonded: bool = eqx.field(static=True)
    options: SolverOptions = eqx.field(static=True)
    x_label: str = eqx.field(static=True, default="strain [-]")
    y_label: str = eqx.field(static=True, default="stress [Pa]")

    def __init__(
        self,
        mesh: TetMesh,
        strains,
        stresses=None,
        *,
        model: str = "springs_volume",
        bonded: bool = False,
        measure: str = "engineering",
        rollers: Sequence = (),
        sigma=None,
        options: SolverOptions = SolverOptions(),
        name: str = "compression",
    ):
        """
        Args:
            mesh: the specimen, compressed along z between ``z = min z`` and ``z = max z``.
            strains: strain protocol [-] (compression positive, increasing, < 1), in the
                ``measure`` given.
            stresses: measured stresses [Pa] in the same measure (None: predictions only).
            model: elastic model name.
            bonded: no-slip platens (default frictionless).
            measure: ``"engineering"`` or ``"true"``.
            rollers: roller supports on the sides (:class:`~difftissue.boundary.Roller` or their
                data forms ``"x-min"`` / ``{"set": selector, "components": "x"}``): symmetry
                planes of the specimen (the stress is that of the whole specimen: a half or
                quarter model needs no factor) or frictionless walls (``["x-min", "x-max",
                "y-min", "y-max"]``: confined compression). With frictionless platens the
                in-plane pins are added only for the rigid modes the rollers leave free; a
                roller on the top platen's z is refused.
        """
        self.name = str(name)
        eps = _as_1d("strains", strains)
        if measure not in ("engineering", "true"):
            raise ConfigError(f"measure must be 'engineering' or 'true', got {measure!r}")
        if np.any(eps < 0) or np.any(np.diff(eps) < 0):
            raise DataError("the strain protocol must be >= 0 (compression positive) and non-decreasing")
        nominal = eps if measure == "engineering" else -np.expm1(-eps)
        if np.any(nominal >= 1):
            raise DataError("a nominal compressive strain must be < 1")
        self.abscissa = eps
        self.observed = np.zeros_like(eps) if stresses is None else _as_1d("stresses", stresses)
        if self.observed.shape != eps.shape:
            raise DataError(f"{eps.size} strains but {self.observed.size} stresses")
        self.sigma = _sigma(self.observed, sigma) if stresses is not None else np.ones_like(eps)
        self.measure = measure
        self.options = options
        self.x_label = f"{measure} strain [-]"
        self.y_label = f"{measure} stress [Pa]"
        p = np.asarray(mesh.points)
        lo, hi = p.min(axis=0), p.max(axis=0)
        self.height = float(hi[2] - lo[2])
        self.area = float(np.sum(mesh.volumes()) / self.height)
        self.bonded = bool(bonded)
        platens = Platens(bonded=self.bonded)
        bottom, top = platens.faces(mesh)
        if not rollers:
            self.bc = platens.apply(mesh, BoundaryConditions.free(mesh), 0.0)
        else:
            # the platens without their in-plane pins (symmetry_planes x and y), the rollers, then
            # the pins Platens would add, each only where a rigid mode is still free
            bc = platens.apply(mesh, BoundaryConditions.free(mesh), 0.0, symmetry_planes=("x", "y"))
            loaded = np.zeros((mesh.n_nodes, 3), dtype=bool)
            loaded[top, :] = True if bonded else [False, False, True]
            bc = apply_rollers(bc, mesh, rollers, loaded=loaded)
            c = p[bottom, :2].mean(axis=0)
            anchor = bottom[np.argmin(np.linalg.norm(p[bottom, :2] - c, axis=1))]
            d = p[bottom, :2] - p[anchor, :2]
            other = bottom[np.argmax(np.abs(d[:, 0]) - 1e-3 * np.abs(d[:, 1]))]
            self.bc = pin_free_rigid_modes(mesh, bc, [(anchor, "x"), (anchor, "y"), (other, "y")])
            check_rigid_modes(p, self.bc.fixed)
        mask = np.zeros(mesh.n_nodes, dtype=bool)
        mask[top] = True
        self.top_mask = mask
        self.model = make_model(mesh, model)

    def solve(self, material: Material):
        """``(stress (n,) [Pa], displacements (n, N, 3) [m])`` along the protocol (compiled once
        per scenario)."""
        return _jitted_solve(self)(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material))

    def _solve_protocol(self, material: Material):
        # jnp: the strains are an argument of the compiled protocol (traced)
        nominal = jnp.asarray(self.abscissa) if self.measure == "engineering" else -jnp.expm1(-jnp.asarray(self.abscissa))
        top = jnp.asarray(self.top_mask)
        x0 = jnp.asarray(self.model.rest_points)

        def step(history, e):
            disp = self.bc.displacement.at[:, 2].set(jnp.where(top, -e * self.height, self.bc.displacement[:, 2]))
            sol = _solve(self.model, material, BoundaryConditions(self.bc.fixed, disp, self.bc.force), _extrapolate(history, e), self.options)
            force = -jnp.sum(jnp.where(top, sol.reaction[:, 2], 0.0))
            if self.measure == "engineering":
                stress = force / self.area
            else:
                x = x0 + sol.displacement
                volume = jnp.sum(jnp.abs(_tet_volumes(x, self.model.tets)))
                stress = force * (1.0 - e) * self.height / volume
            return _advance(history, sol.displacement, e), (stress, sol.displacement)

        u0 = jnp.zeros_like(self.bc.displacement)
        _, (stress, us) = jax.lax.scan(step, _history(u0), jnp.asarray(nominal, dtype=u0.dtype))
        return stress, us

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of the predictions (from the solver options)."""
        return self.options.prediction_rtol

    @property
    def prediction_scales_with_youngs_modulus(self) -> bool:
        """True when every predicted stress is exactly proportional to Young's modulus at fixed
        other material fields (the platen displacements are prescribed with no applied force
        and the model's energy is linear in ``E``): see
        :attr:`Indentation.prediction_scales_with_youngs_modulus`."""
        return _scales_with_youngs_modulus(self.model, self.bc)

    def predict(self, material: Material):
        """Stress [Pa] at each strain (compression positive)."""
        return self.solve(material)[0]

    @property
    def solves_on_host(self) -> bool:
        """Whether :meth:`solve_on_host` applies: a model of at most
        :data:`~difftissue.solvers.host.HOST_MAX_NODES` nodes, the dense linear solver
        (``"auto"`` picks it at that size) and engineering stress."""
        return (self.model.n_nodes <= HOST_MAX_NODES and self.options.linear_solver in ("auto", "dense")
                and self.measure == "engineering")

    def solve_on_host(self, material: Material, tangents: dict[str, np.ndarray] | None = None):
        """The protocol of :meth:`predict` solved on the host (NumPy; only the model's
        derivatives are compiled, :class:`~difftissue.solvers.host.HostStaticSolver`): the same
        load steps, starting guesses and Newton iteration, equal to :meth:`predict` to
        round-off, without tracing and compiling the protocol (seconds for a few milliseconds
        of arithmetic on a small specimen). Only where :attr:`solves_on_host`.

        Args:
            material: one concrete material (scalar fields).
            tangents: ``{field: (K,)}``: material tangents (fields left out: zero).

        Returns:
            ``(stress (n,) [Pa], stress tangents (K, n) [Pa per unit of the tangent])``. A
            static solve that fails raises :class:`~difftissue.errors.ConvergenceError`
            (``options.failure = "raise"``) or makes the stresses and tangents NaN from that
            strain on (``"nan"``).
        """
        if not self.solves_on_host:
            raise ModelError(f"compression scenario {self.name!r}: solve_on_host needs at most {HOST_MAX_NODES} nodes, "
                             f"linear_solver 'auto' or 'dense' and measure 'engineering' (use predict)")
        solver = HostStaticSolver(self.model, self.bc.fixed)
        checked = solver.checked(material)
        tangents = {} if tangents is None else {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in tangents.items()}
        K = len(next(iter(tangents.values()))) if tangents else 0
        eps = np.asarray(self.abscissa, dtype=float)
        nominal = eps  # engineering strain (solves_on_host)
        top = np.asarray(self.top_mask, dtype=bool)
        base = np.asarray(self.bc.displacement, dtype=float)
        force = np.asarray(self.bc.force, dtype=float)
        o = self.options
        stress, t_stress = np.full(nominal.size, np.nan), np.full((K, nominal.size), np.nan)
        u = u_before = np.zeros_like(base)
        load_before = load_before2 = 0.0
        for i, e in enumerate(nominal):
            span = load_before - load_before2  # _extrapolate's secant through the last two equilibria
            u0 = u + (e - load_before) / span * (u - u_before) if span != 0 else u
            disp = base.copy()
            disp[top, 2] = -e * self.height
            sol = solver.solve(checked, disp, u0, force=force, rtol=o.rtol, xtol=o.xtol, max_steps=o.max_steps)
            if not sol.converged:
                if o.failure == "raise":
                    raise ConvergenceError(f"compression scenario {self.name!r} at strain {float(eps[i]):g}: {sol.message} "
                                           f"(steps {sol.steps}, residual {sol.residual_norm:.3g} N)")
                break  # NaN from here on, as the compiled protocol (its next starting guesses are NaN)
            stress[i] = -np.sum(sol.reaction[top, 2]) / self.area
            if K:
                _, t_reaction = solver.tangents(sol, tangents)
                t_stress[:, i] = -np.sum(t_reaction[:, top, 2], axis=1) / self.area
            u, u_before, load_before, load_before2 = sol.displacement, u, float(e), load_before
        return stress, t_stress

    def protocol(self) -> dict:
        """The protocol as recorded in a material card's scenario record: ``platens``
        (``"bonded"`` / ``"frictionless"``), ``measure`` (``"engineering"`` / ``"true"``),
        ``strains`` (the protocol in that measure, [-]), ``nominal_strains`` (``delta / H``),
        ``height`` ``H`` [m], ``area`` ``A0`` [m^2] (volume / H, the area of the engineering
        stress), ``top_displacement`` [m] (``-e H`` at the last nominal strain ``e``: the top
        platen of the exported specimen) and ``reaction`` (``"z"``: the component summed over
        the top face)."""
        eps = np.asarray(self.abscissa, dtype=float)
        if eps.size == 0:
            raise DataError(f"compression scenario {self.name!r} has an empty strain protocol")
        nominal = eps if self.measure == "engineering" else -np.expm1(-eps)
        return {"platens": "bonded" if self.bonded else "frictionless", "measure": str(self.measure),
                "strains": eps.tolist(), "nominal_strains": nominal.tolist(), "height": float(self.height),
                "area": float(self.area), "top_displacement": float(-nominal[-1] * self.height), "reaction": "z"}

    def record(self) -> dict:
        """The experiment as a material card's scenario record (:func:`difftissue.export.card.scenario_record`):
        ``name``, ``type``, ``experiment = "compression"``, difftissue's ``model`` and the
        :meth:`protocol`; the mesh and boundary conditions go into a specimen file
        (:mod:`difftissue.export.fitted`)."""
        return {"name": self.name, "type": type(self).__name__, "experiment": "compression", "model": str(self.model.model_name),
                **self.protocol()}


def _tet_volumes(x, tets):
    """Signed volume of each tet [m^3] at positions ``x`` (traced: :func:`tet_signed_volume`)."""
    return tet_signed_volume(x[tets])


class FEMField(eqx.Module):
    """Reproduce a reference FEM solution: displacements of the unconstrained degrees of
    freedom, and optionally a reaction force, under the reference's boundary conditions.

    Two ways (``reference_mesh``):

    - ``"own"`` (no ``specimen``): the model mesh is the reference mesh (its lattice recovered
      for ``springs_volume`` when it is a structured grid); the model's free nodal components
      are compared with the reference's.
    - ``"interpolate"`` (a ``specimen``: the model's own mesh): the reference lives on the
      analyst's mesh (linear or quadratic tetrahedra, hexahedra). The model's displacement is
      observed at the reference's nodes by P1 interpolation in the model's tetrahedra (a
      precomputed sparse operator, :mod:`difftissue.interpolation`), so the data stay as
      given; the prescribed values of the model's boundary nodes are the reference's
      displacement interpolated there with the reference's own elements (P1, P2, trilinear).
      Reference nodes outside the model (or prescribed model nodes outside the reference) by
      more than ``tolerance`` are refused.

    Node sets are point-data masks (nonzero = member) or selectors
    (:mod:`difftissue.selectors`, SI coordinates). With ``"interpolate"`` a set is resolved on
    both meshes: a selector applies to each mesh's own nodes (a ``face`` is a face of each
    mesh's bounding box); a mask name must be a point field of the mesh it is resolved on (the
    reference's file for the observed and reaction-field nodes, the specimen for the model's
    prescribed and reaction nodes).

    Predictions: ``u`` of every free component of the nodes in ``observe`` (default all) [m],
    then, with ``reaction``, the summed reaction-force components [N]. ``sigma`` is
    ``displacement_sigma`` [m] for the displacements and ``force_sigma`` [N] for the force
    (defaults: 1e-3 of the largest value of each, i.e. equal relative precision).
    """

    #: the XLA option set of this scenario's compiled programs (a program kind of
    #: :data:`difftissue.xla_options.PROGRAMS`: static solves)
    xla_program = "static"

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    model: ElasticModel
    bc: BoundaryConditions
    observe_dofs: np.ndarray
    reaction_mask: np.ndarray | None
    x_label: str = eqx.field(static=True, default="observation index")
    y_label: str = eqx.field(static=True, default="displacement [m] / force [N]")
    options: SolverOptions = eqx.field(static=True, default=SolverOptions())
    #: ``"own"`` or ``"interpolate"`` (see the class docstring).
    reference_mesh: str = eqx.field(static=True, default="own")
    #: ``"interpolate"``: the model's displacement at the observed reference nodes.
    interpolation: Any = None
    #: ``"interpolate"``: ``(n, 3)`` coordinates [m] of the observed reference nodes
    #: (``observe_dofs // 3`` indexes them); ``"own"``: ``None`` (the model's nodes).
    observed_points: np.ndarray | None = None
    #: the axes (0, 1, 2: x, y, z) of the measured reaction components, in the order of the
    #: prediction (static: they set its length; ``predict`` must not read ``reaction_mask``'s
    #: values, which a compiled program may take as an argument)
    reaction_components: tuple[int, ...] = eqx.field(static=True, default=())

    def __init__(
        self,
        mesh,
        displacement,
        *,
        prescribed: Sequence[dict],
        model: str = "fem_linear",
        observe=None,
        reaction: dict | None = None,
        displacement_sigma: float | None = None,
        force_sigma: float | None = None,
        options: SolverOptions = SolverOptions(),
        name: str = "fem_field",
        specimen: TetMesh | None = None,
        tolerance: float | None = None,
    ):
        """
        Args:
            mesh: the reference mesh (with the node-set masks in ``point_data``): a
                :class:`~difftissue.mesh.TetMesh`, or a :class:`~difftissue.data.FEMResult`
                (any of its element types with ``specimen``).
            displacement: ``(N, 3)`` reference displacement [m].
            prescribed: ``[{"set": name-or-selector, "components": "xyz"}, ...]``: the
                reference displacement is prescribed on these components.
            model: elastic model name.
            observe: node set whose free components are compared (default all nodes).
            reaction: ``{"set": ..., "components": "z", "force": [..] (N) or "field": name}``:
                compare the sum of the model's reactions over the set with the given total
                force, or with the sum of a nodal reaction point field of the file.
            specimen: the model's own mesh; the reference is then interpolated (see the class
                docstring). ``None``: the model runs on the reference mesh.
            tolerance: ``specimen`` only: how far [m] a point may lie outside the mesh it is
                interpolated in (default 1e-6 x that mesh's bounding-box diagonal).
        """
        self.name = str(name)
        self.options = options
        if specimen is not None:
            fields = _interpolated_fem_field(mesh, displacement, specimen, prescribed, model, observe, reaction, displacement_sigma, force_sigma, tolerance)
            for k, v in fields.items():
                setattr(self, k, v)
            self.reaction_components = _reaction_components(self.reaction_mask)
            return
        if tolerance is not None:
            raise ConfigError("tolerance is used only when the reference is interpolated onto a specimen mesh")
        if not isinstance(mesh, TetMesh):
            if getattr(mesh, "mesh", None) is None:
                kinds = sorted(getattr(mesh, "cells", {}) or {})
                raise ConfigError(f"the reference has {kinds} cells, not a linear tet mesh the model can run on: give the model's own mesh "
                                  f"(specimen=...) and the reference is interpolated onto it")
            mesh = mesh.mesh
        self.reference_mesh = "own"
        self.interpolation = None
        self.observed_points = None
        u_ref = np.asarray(displacement, dtype=float)
        if u_ref.shape != (mesh.n_nodes, 3) or not np.all(np.isfinite(u_ref)):
            raise DataError(f"the reference displacement must be finite with shape ({mesh.n_nodes}, 3), got {u_ref.shape}")
        if model in LATTICE_MODELS and mesh.lattice is None:
            mesh = recover_lattice(mesh)
        if not prescribed:
            raise ConfigError("fem_field needs 'prescribed': the node sets whose displacement the reference prescribed")
        bc = BoundaryConditions.free(mesh)
        fixed = np.zeros((mesh.n_nodes, 3), dtype=bool)
        for i, entry in enumerate(prescribed):
            if not isinstance(entry, dict) or "set" not in entry:
                raise ConfigError(f"prescribed[{i}] must be a table with 'set' (and optionally 'components')")
            nodes = _node_set(mesh, entry["set"], f"prescribed[{i}].set")
            for c in str(entry.get("components", "xyz")):
                if c not in "xyz":
                    raise ConfigError(f"prescribed[{i}].components must be letters from 'xyz', got {entry.get('components')!r}")
                fixed[nodes, "xyz".index(c)] = True
        bc = BoundaryConditions(fixed, jnp.asarray(np.where(fixed, u_ref, 0.0)), jnp.zeros((mesh.n_nodes, 3)))
        from .boundary import check_rigid_modes

        check_rigid_modes(np.asarray(mesh.points), fixed)
        obs_nodes = np.arange(mesh.n_nodes) if observe is None else _node_set(mesh, observe, "observe")
        obs = np.zeros((mesh.n_nodes, 3), dtype=bool)
        obs[obs_nodes] = True
        obs &= ~fixed
        self.observe_dofs = np.flatnonzero(obs.reshape(-1))
        if self.observe_dofs.size == 0:
            raise ConfigError("no free displacement component to compare: every observed node is prescribed")
        observed = [u_ref.reshape(-1)[self.observe_dofs]]
        s_u = float(displacement_sigma) if displacement_sigma is not None else 1e-3 * max(float(np.abs(observed[0]).max()), 1e-300)
        sig = [np.full(observed[0].shape, s_u)]
        self.reaction_mask = None
        if reaction is not None:
            nodes = _node_set(mesh, reaction.get("set"), "reaction.set")
            comps = str(reaction.get("components", "z"))
            rmask = np.zeros((mesh.n_nodes, 3), dtype=bool)
            for c in comps:
                if c not in "xyz":
                    raise ConfigError(f"reaction.components must be letters from 'xyz', got {comps!r}")
                rmask[nodes, "xyz".index(c)] = True
            if not np.all(fixed[rmask]):
                raise ConfigError("reaction.set/components must be prescribed components (a reaction exists only where the displacement is prescribed)")
            if "force" in reaction:
                f = np.atleast_1d(np.asarray(reaction["force"], dtype=float))
            elif "field" in reaction:
                name_f = reaction["field"]
                if name_f not in mesh.point_data:
                    raise ConfigError(f"reaction.field {name_f!r} is not a point field of the reference (fields: {sorted(mesh.point_data)})")
                nodal = np.asarray(mesh.point_data[name_f], dtype=float).reshape(mesh.n_nodes, -1)
                f = np.array([nodal[nodes, "xyz".index(c)].sum() for c in comps])
            else:
                raise ConfigError("reaction needs 'force' (the total force in N, one value per component) or 'field' (a nodal reaction point field)")
            if f.shape != (len(comps),) or not np.all(np.isfinite(f)):
                raise ConfigError(f"reaction.force needs one finite value per component {comps!r}, got {f.tolist()}")
            self.reaction_mask = rmask
            observed.append(f)
            s_f = float(force_sigma) if force_sigma is not None else 1e-3 * max(float(np.abs(f).max()), 1e-300)
            sig.append(np.full(f.shape, s_f))
        self.observed = np.concatenate(observed)
        self.sigma = np.concatenate(sig)
        self.abscissa = np.arange(self.observed.size, dtype=float)
        self.x_label, self.y_label = "observation index", "displacement [m] / force [N]"
        self.bc = bc
        self.model = make_model(mesh, model)
        self.reaction_components = _reaction_components(self.reaction_mask)

    def solve(self, material: Material):
        """The static solution of the model under the reference's boundary conditions
        (compiled once per scenario)."""
        return _jitted_solve(self)(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material))

    def _solve_protocol(self, material: Material):
        return _solve(self.model, material, self.bc, None, self.options)

    def check_reaction_sign(self, predicted) -> None:
        """Raise :class:`~difftissue.errors.ReactionSignError` when a measured reaction component
        has the opposite sign of ``predicted`` (this scenario's prediction at the fit's initial
        material): no modulus can fit it, and a fit drives E to zero instead.

        The reaction is the force the supports exert on the prescribed nodes (internal elastic
        force, summed over ``reaction.set``): negative along an axis the nodes are pushed into
        the specimen (``-z`` for a punch pressed down), so its sign does not depend on the
        material. A NaN prediction (a failed solve) is not checked.
        """
        if self.reaction_mask is None:
            return
        comps = [c for i, c in enumerate("xyz") if self.reaction_mask[:, i].any()]
        pred = np.asarray(predicted, dtype=float)[-len(comps):]
        obs = np.asarray(self.observed, dtype=float)[-len(comps):]
        for c, p, o in zip(comps, pred, obs):
            if np.isfinite(p) and p != 0.0 and o != 0.0 and np.sign(p) != np.sign(o):
                raise ReactionSignError(
                    f"{self.name}: the measured reaction force {c} = {o:+.4g} N has the opposite sign of the model's reaction "
                    f"at the initial material ({p:+.4g} N); no modulus can fit it (a fit would drive E towards 0). difftissue's "
                    f"reaction is the force the supports exert on the prescribed nodes, summed over reaction.set: negative along "
                    f"an axis the nodes are pushed into the specimen (a punch pressed down in -{c} gives a negative {c} reaction). "
                    f"Give reaction.force = [{-o:.6g}] (N), or flip the sign of the reference's reaction field")

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of the predictions (from the solver options)."""
        return self.options.prediction_rtol

    def predict(self, material: Material):
        sol = self.solve(material)
        u = sol.displacement if self.interpolation is None else self.interpolation(sol.displacement)
        out = [u.reshape(-1)[self.observe_dofs]]
        if self.reaction_mask is not None:
            m = jnp.asarray(self.reaction_mask)
            out.append(jnp.stack([jnp.sum(jnp.where(m[:, c], sol.reaction[:, c], 0.0)) for c in self.reaction_components]))
        return jnp.concatenate(out)

    def record(self) -> dict:
        """The experiment as a material card's scenario record (:func:`difftissue.export.card.scenario_record`):
        ``name``, ``type``, ``experiment = "fem_field"`` and difftissue's ``model``; the mesh and
        boundary conditions go into a specimen file (:mod:`difftissue.export.fitted`)."""
        return {"name": self.name, "type": type(self).__name__, "experiment": "fem_field", "model": str(self.model.model_name)}


def _components_of(entry_components, key: str) -> list[int]:
    comps = str(entry_components)
    for c in comps:
        if c not in "xyz":
            raise ConfigError(f"{key} must be letters from 'xyz', got {entry_components!r}")
    return ["xyz".index(c) for c in comps]


def _reference_node_set(ref, spec: Any, key: str) -> np.ndarray:
    """A node set of the reference (``points`` and ``point_data``: a TetMesh or FEMResult)."""
    n = len(np.asarray(ref.points))
    if isinstance(spec, str):
        if spec not in ref.point_data:
            raise ConfigError(f"{key}: {spec!r} is not a point-data node set of the reference (point fields: {sorted(ref.point_data)})")
        nodes = np.flatnonzero(np.asarray(ref.point_data[spec]).reshape(n, -1)[:, 0] != 0)
        if nodes.size == 0:
            raise ConfigError(f"{key}: node set {spec!r} of the reference is empty")
        return nodes
    if isinstance(spec, dict):
        return select_nodes(np.asarray(ref.points), spec)
    raise ConfigError(f"{key} must be a point-data mask name or a selector table, got {spec!r}")


def _model_node_set(specimen: TetMesh, spec: Any, key: str) -> np.ndarray:
    """A node set of the model's own mesh (a reference's mask names mean nothing there)."""
    if isinstance(spec, str) and spec not in specimen.point_data:
        raise ConfigError(f"{key}: {spec!r} is a point-data node set of the reference; the model's own mesh (specimen) has no such point field: "
                          f"select the model's nodes with a selector in SI coordinates (e.g. {{face = \"z-min\"}}, {{box = {{lower = [...], "
                          f"upper = [...]}}}}), which applies to both meshes, or give the specimen file a mask of that name")
    try:
        return _node_set(specimen, spec, key)
    except SelectorError as err:
        raise ConfigError(f"{key} on the model's own mesh (specimen): {err}") from None


def _interpolated_fem_field(ref, displacement, specimen: TetMesh, prescribed, model, observe, reaction, displacement_sigma, force_sigma, tolerance) -> dict:
    """The fields of a :class:`FEMField` whose reference is interpolated onto ``specimen``."""
    if not isinstance(specimen, TetMesh):
        raise ConfigError(f"specimen must be the model's TetMesh, got {type(specimen).__name__}")
    ref_points = np.asarray(ref.points, dtype=float)
    ref_cells = getattr(ref, "cells", None) or {"tetra": np.asarray(ref.tets)}
    n_ref = len(ref_points)
    u_ref = np.asarray(displacement, dtype=float)
    if u_ref.shape != (n_ref, 3) or not np.all(np.isfinite(u_ref)):
        raise DataError(f"the reference displacement must be finite with shape ({n_ref}, 3), got {u_ref.shape}")
    if model in LATTICE_MODELS and specimen.lattice is None:
        specimen = recover_lattice(specimen)
    if not prescribed:
        raise ConfigError("fem_field needs 'prescribed': the node sets whose displacement the reference prescribed")
    fixed = np.zeros((specimen.n_nodes, 3), dtype=bool)  # model nodes
    ref_fixed = np.zeros((n_ref, 3), dtype=bool)  # reference nodes (not observed)
    for i, entry in enumerate(prescribed):
        if not isinstance(entry, dict) or "set" not in entry:
            raise ConfigError(f"prescribed[{i}] must be a table with 'set' (and optionally 'components')")
        comps = _components_of(entry.get("components", "xyz"), f"prescribed[{i}].components")
        nodes = _model_node_set(specimen, entry["set"], f"prescribed[{i}].set")
        ref_nodes = _reference_node_set(ref, entry["set"], f"prescribed[{i}].set")
        for c in comps:
            fixed[nodes, c] = True
            ref_fixed[ref_nodes, c] = True
    check_rigid_modes(np.asarray(specimen.points), fixed)
    # the prescribed values: the reference's displacement at the model's prescribed nodes,
    # interpolated with the reference's own elements
    presc_nodes = np.flatnonzero(fixed.any(axis=1))
    to_model = interpolation_operator(ref_points, ref_cells, np.asarray(specimen.points)[presc_nodes], tolerance=tolerance,
                                      what="prescribed nodes of the model (specimen)")
    values = np.zeros((specimen.n_nodes, 3))
    values[presc_nodes] = to_model.as_sparse() @ u_ref
    bc = BoundaryConditions(fixed, jnp.asarray(np.where(fixed, values, 0.0)), jnp.zeros((specimen.n_nodes, 3)))
    # the observations: the reference's free components at its nodes, the model's field
    # interpolated there (P1 in the model's tets)
    obs_nodes = np.arange(n_ref) if observe is None else _reference_node_set(ref, observe, "observe")
    obs = np.zeros((n_ref, 3), dtype=bool)
    obs[obs_nodes] = True
    obs &= ~ref_fixed
    rows = np.flatnonzero(obs.any(axis=1))
    if rows.size == 0:
        raise ConfigError("no free displacement component to compare: every observed reference node is prescribed")
    to_ref = interpolation_operator(np.asarray(specimen.points), {"tetra": np.asarray(specimen.tets)}, ref_points[rows], tolerance=tolerance,
                                    what="observed reference nodes")
    observe_dofs = np.flatnonzero(obs[rows].reshape(-1))
    observed = [u_ref[rows].reshape(-1)[observe_dofs]]
    s_u = float(displacement_sigma) if displacement_sigma is not None else 1e-3 * max(float(np.abs(observed[0]).max()), 1e-300)
    sig = [np.full(observed[0].shape, s_u)]
    reaction_mask = None
    if reaction is not None:
        comps = _components_of(reaction.get("components", "z"), "reaction.components")
        nodes = _model_node_set(specimen, reaction.get("set"), "reaction.set")
        rmask = np.zeros((specimen.n_nodes, 3), dtype=bool)
        for c in comps:
            rmask[nodes, c] = True
        if not np.all(fixed[rmask]):
            raise ConfigError("reaction.set/components must be prescribed components (a reaction exists only where the displacement is prescribed)")
        if "force" in reaction:
            f = np.atleast_1d(np.asarray(reaction["force"], dtype=float))
        elif "field" in reaction:
            name_f = reaction["field"]
            if name_f not in ref.point_data:
                raise ConfigError(f"reaction.field {name_f!r} is not a point field of the reference (fields: {sorted(ref.point_data)})")
            nodal = np.asarray(ref.point_data[name_f], dtype=float).reshape(n_ref, -1)
            ref_nodes = _reference_node_set(ref, reaction.get("set"), "reaction.set")
            f = np.array([nodal[ref_nodes, c].sum() for c in comps])
        else:
            raise ConfigError("reaction needs 'force' (the total force in N, one value per component) or 'field' (a nodal reaction point field)")
        if f.shape != (len(comps),) or not np.all(np.isfinite(f)):
            raise ConfigError(f"reaction.force needs one finite value per component {reaction.get('components', 'z')!r}, got {f.tolist()}")
        reaction_mask = rmask
        observed.append(f)
        s_f = float(force_sigma) if force_sigma is not None else 1e-3 * max(float(np.abs(f).max()), 1e-300)
        sig.append(np.full(f.shape, s_f))
    observed = np.concatenate(observed)
    return {
        "reference_mesh": "interpolate",
        "interpolation": to_ref,
        "observed_points": ref_points[rows],
        "observe_dofs": observe_dofs,
        "observed": observed,
        "sigma": np.concatenate(sig),
        "abscissa": np.arange(observed.size, dtype=float),
        "x_label": "observation index",
        "y_label": "displacement [m] / force [N]",
        "reaction_mask": reaction_mask,
        "bc": bc,
        "model": make_model(specimen, model),
    }


def _reaction_components(mask) -> tuple[int, ...]:
    """The axes with a measured reaction in a FEM field's ``(n, 3)`` reaction mask (None: none)."""
    return () if mask is None else tuple(int(c) for c in range(3) if np.asarray(mask)[:, c].any())


def _node_set(mesh: TetMesh, spec: Any, key: str) -> np.ndarray:
    if isinstance(spec, str):
        if spec not in mesh.point_data:
            raise ConfigError(f"{key}: {spec!r} is not a point-data node set of the mesh (point fields: {sorted(mesh.point_data)})")
        m = np.asarray(mesh.point_data[spec]).reshape(mesh.n_nodes, -1)[:, 0]
        nodes = np.flatnonzero(m != 0)
        if nodes.size == 0:
            raise ConfigError(f"{key}: node set {spec!r} is empty")
        return nodes
    if isinstance(spec, dict):
        return select_nodes(mesh, spec)
    raise ConfigError(f"{key} must be a point-data mask name or a selector table, got {spec!r}")
