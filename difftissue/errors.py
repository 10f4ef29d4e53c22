"""Named errors and warnings raised by difftissue.

Every error a user can trigger with bad input derives from :class:`DifftissueError`
(and from :class:`ValueError`, so generic handlers still work). The command line
prints ``error: <message>`` for these and exits non-zero without a traceback.
"""

from __future__ import annotations

__all__ = [
    "DifftissueError",
    "DifftissueWarning",
    "MeshError",
    "NonFiniteCoordinatesError",
    "IndexOutOfRangeError",
    "InvertedElementError",
    "DegenerateElementError",
    "DuplicateElementError",
    "EmptyMeshError",
    "UnsupportedMeshError",
    "UnusedNodesWarning",
    "NonManifoldSurfaceWarning",
    "MaterialError",
    "ModelRangeError",
    "SelectorError",
    "OutputError",
    "OutputExistsError",
    "BoundaryConditionError",
    "RigidModeError",
    "ModelError",
    "ConvergenceError",
    "LinearSolverError",
]


def _cite(indices, limit: int = 8) -> str:
    """Format the first ``limit`` indices of a list, with the total count."""
    idx = [int(i) for i in indices]
    head = ", ".join(str(i) for i in idx[:limit])
    more = f", ... ({len(idx)} in all)" if len(idx) > limit else ""
    return f"[{head}{more}]"


class DifftissueError(ValueError):
    """Base class of all input errors raised by difftissue."""


class DifftissueWarning(UserWarning):
    """Base class of all warnings emitted by difftissue."""


# --------------------------------------------------------------------------- meshes
class MeshError(DifftissueError):
    """A mesh is unusable. ``indices`` holds the offending node or element indices."""

    def __init__(self, message: str, indices=()):
        super().__init__(message)
        self.indices = tuple(int(i) for i in indices)


class EmptyMeshError(MeshError):
    """The mesh has no nodes or no tetrahedra."""


class NonFiniteCoordinatesError(MeshError):
    """Some node coordinates are NaN or infinite (``indices`` are node indices)."""


class IndexOutOfRangeError(MeshError):
    """Some elements reference node indices outside ``[0, n_nodes)`` (``indices`` are element indices)."""


class InvertedElementError(MeshError):
    """Some tetrahedra have negative signed volume (``indices`` are element indices)."""


class DegenerateElementError(MeshError):
    """Some tetrahedra have (near-)zero volume or repeated nodes (``indices`` are element indices)."""


class DuplicateElementError(MeshError):
    """Some tetrahedra use the same four nodes as an earlier one (``indices`` are the later copies)."""


class UnsupportedMeshError(MeshError):
    """The file holds cells difftissue does not handle (e.g. quadratic tetrahedra)."""


class UnusedNodesWarning(DifftissueWarning):
    """Some nodes belong to no tetrahedron."""


class NonManifoldSurfaceWarning(DifftissueWarning):
    """Some boundary edges are shared by a number of boundary faces other than two."""


# ------------------------------------------------------------------------ materials
class MaterialError(DifftissueError):
    """A material parameter is outside its physical range (E <= 0, nu outside (-1, 1/2), NaN, ...)."""


class ModelRangeError(MaterialError):
    """A material is valid but the chosen discrete model cannot represent it (e.g. a pure spring lattice at nu > 1/3)."""


# ------------------------------------------------------------------------ selectors
class SelectorError(DifftissueError):
    """A node selector is malformed or selects no node."""


# --------------------------------------------------------------------------- output
class OutputError(DifftissueError):
    """An output cannot be written where it was asked for."""


class OutputExistsError(OutputError):
    """Refusing to overwrite an existing file or directory."""


# ------------------------------------------------------------------ boundary conditions
class BoundaryConditionError(DifftissueError):
    """Boundary conditions are malformed (wrong size, NaN values, unknown components)."""


class RigidModeError(BoundaryConditionError):
    """The prescribed displacements leave a rigid-body mode free: a static solve would be singular."""


# ------------------------------------------------------------------------ models/solvers
class ModelError(DifftissueError):
    """A model cannot be built for this mesh or these options (e.g. springs need a cube lattice)."""


class ConvergenceError(DifftissueError):
    """A solver did not converge (raised only when the solver is asked to throw)."""


class LinearSolverError(ConvergenceError):
    """An iterative linear solve (preconditioned conjugate gradients) did not reach its
    tolerance: the message gives the iteration count and the relative residual."""


# =========================================================================== data
# (appended block: errors of difftissue.data -- loaders of measured data)
__all__ += [
    "DataError",
    "EmptyDataError",
    "MalformedDataError",
    "HeaderError",
    "MissingColumnError",
    "MissingFieldError",
    "NonFiniteDataError",
    "UnitError",
    "ImplausibleMagnitudeError",
    "NonMonotonicError",
    "InconsistentDataError",
    "InconsistentDataWarning",
    "ContactPointError",
]


class DataError(DifftissueError):
    """A measured-data file or dataset is unusable.

    ``rows`` holds the offending data-row indices (0-based, counted from the first data row)
    where that makes sense; ``lines`` the matching 1-based line numbers in the file.
    """

    def __init__(self, message: str, rows=(), lines=()):
        super().__init__(message)
        self.rows = tuple(int(i) for i in rows)
        self.lines = tuple(int(i) for i in lines)


class EmptyDataError(DataError):
    """The file is empty, or has a header but no data rows."""


class MalformedDataError(DataError):
    """A data row cannot be parsed (a token that is not a number, too few fields)."""


class HeaderError(DataError):
    """A metadata header is missing, truncated, or lacks a required entry (e.g. the tip radius)."""


class MissingColumnError(DataError):
    """A declared column is not in the file. ``column`` is its name, ``available`` the file's columns."""

    def __init__(self, message: str, column: str = "", available=()):
        super().__init__(message)
        self.column = column
        self.available = tuple(available)


class MissingFieldError(DataError):
    """A mesh result file lacks the expected point field (e.g. ``displacement``) or it has the wrong shape."""


class NonFiniteDataError(DataError):
    """Some values are NaN, infinite or empty (``rows`` and ``lines`` say where)."""


class UnitError(DataError):
    """A unit is unknown, of the wrong kind for the quantity, or contradicts the file's header."""


class ImplausibleMagnitudeError(UnitError):
    """Values are implausibly large or small for the declared unit (most often a wrong unit)."""


class NonMonotonicError(DataError):
    """Depth (or displacement) decreases inside a loading segment that was asked to be monotonic."""


class InconsistentDataError(DataError):
    """Redundant columns of a file disagree (e.g. stress != force / area with the header's diameter)."""


class InconsistentDataWarning(DifftissueWarning):
    """Redundant columns or header entries of a file disagree, within limits where it is only reported."""


class ContactPointError(DataError):
    """No contact point can be found in a force-depth curve (too few points, no force rise)."""


# =========================================================================== fitting
# (appended block: errors and warnings of difftissue.fit)
__all__ += [
    "FitError",
    "CheckpointError",
    "CheckpointMismatchError",
    "IdentifiabilityWarning",
    "SimulationError",
]


class SimulationError(DifftissueError):
    """A forward model evaluation (``difftissue simulate``) failed or predicted a non-finite value."""


class FitError(DifftissueError):
    """A fit cannot be set up or run (bad scenarios, unknown method or loss, inconsistent options)."""


class CheckpointError(FitError):
    """A fit checkpoint cannot be read or written (unreadable file, existing file without ``resume``)."""


class CheckpointMismatchError(CheckpointError):
    """A checkpoint belongs to a different fit problem (fields, transforms, data, method or starts differ)."""


class IdentifiabilityWarning(DifftissueWarning):
    """A fitted parameter is not determined by the data (singular or ill-conditioned J^T J,
    relative standard error above 100 %, or a correlation above 0.99 in magnitude)."""


# ====================================================================== configuration
# (appended block: errors of the scenarios and of fit configuration files)
__all__ += ["ConfigError"]


class ConfigError(DifftissueError):
    """A scenario or fit configuration is invalid: a missing or unknown key, a value of the
    wrong type or out of range. The message names the key (e.g. ``experiment[0].radius``)."""


# ============================================================================ export
# (appended block: errors of difftissue.export -- material cards and simulator writers)
__all__ += ["ExportError"]


class ExportError(DifftissueError):
    """A material card is invalid (missing or out-of-range parameter, unknown card_version), or
    cannot be exported to the asked target without an approximation that was not allowed.
    The message names the field (e.g. ``parameters.poisson_ratio``)."""


# =========================================================================== cutting
# (appended block: errors of difftissue.cutting -- scalpel paths and cut topology)
__all__ += ["CutError", "DisconnectedCutError"]


class CutError(DifftissueError):
    """A cut is refused: a bad scalpel path (outside the specimen, fewer than 2 points, zero
    length, self-intersecting), a depth <= 0 or beyond the thickness without ``through=True``,
    or degenerate / inverted elements after snapping. ``indices`` holds the offending element
    (or cube) indices where that makes sense."""

    def __init__(self, message: str, indices=()):
        super().__init__(message)
        self.indices = tuple(int(i) for i in indices)


class DisconnectedCutError(CutError):
    """The cut splits a part off the specimen and ``allow_disconnect`` was not given; the message
    names the part (node count and bounding box)."""


# ====================================================================== trustworthy fits
# (appended block: issue 17 -- no silent wrong answers)
__all__ += ["OutputLockedError", "ImplausibleUnitWarning", "ReactionSignError"]


class OutputLockedError(OutputError):
    """Another difftissue run holds the output directory's lock file (``DIR/.difftissue.lock``,
    with its process id); ``pid`` is that process, ``lock`` the lock file."""

    def __init__(self, message: str, pid: int | None = None, lock=None):
        super().__init__(message)
        self.pid = pid
        self.lock = lock


class ImplausibleUnitWarning(DifftissueWarning):
    """Measured values are implausible for the experiment's geometry (e.g. indentation depths
    larger than the indenter radius, or a thousand times smaller): most often a unit mistake
    (depths in m declared as mm). The message names the likely mistake and its factor."""


class ReactionSignError(DataError):
    """A measured reaction force has the opposite sign of the model's reaction at the initial
    material: the data follow another sign convention. difftissue's reaction is the force the
    supports exert on the prescribed nodes (internal elastic force minus applied force there),
    negative along an axis the nodes are pushed into the specimen (e.g. ``-z`` for a punch
    pressed down)."""


# ====================================================================== fit quality gates
# (appended block: issue 17 -- a fit's answer checked before anyone uses it)
__all__ += ["FitQualityWarning", "UnusableFitError", "EffectiveModulusError"]


class FitQualityWarning(DifftissueWarning):
    """A quality gate of a fit (:func:`difftissue.fit.assess_quality`) raised a flag: the
    message starts with ``error:`` (the answer is unusable: a parameter at a bound, an
    implausible value, non-finite, not converged) or ``warning:`` (poor or systematic residuals)."""


class UnusableFitError(FitError):
    """A fit finished but its answer is unusable (a quality flag of severity "error"); the
    CLI writes the outputs and exits with status 3. ``quality`` is the
    :class:`~difftissue.fit.FitQuality`."""

    def __init__(self, message: str, quality=None):
        super().__init__(message)
        self.quality = quality


class EffectiveModulusError(DifftissueError):
    """A material card holds an effective modulus ``E / (1 - nu^2)`` (a Hertz/Sneddon fit with
    nu fixed as a placeholder) and a simulator needs E and nu separately: state nu
    (``--nu``), pass ``--approximate``, or refit with nu fixed at the tissue's value."""


# ====================================================================== discretisation error
# (appended block: issue 17 -- the mesh's share of a fitted parameter's error)
__all__ += ["DiscretisationWarning"]


class DiscretisationWarning(FitQualityWarning):
    """The estimated discretisation error of a fitted parameter (one evaluation on a coarser
    mesh at the optimum, Richardson first order: :func:`difftissue.fit.discretisation_estimate`)
    exceeds its statistical standard error: the mesh, not the noise, limits the answer. Refine
    the specimen's cells; the message names the parameter, both numbers and the relative bias."""


# ===================================================================== interpolation
__all__ += ["PointsOutsideMeshError"]


class PointsOutsideMeshError(MeshError):
    """Points to interpolate at lie outside the mesh they are interpolated in, farther than the
    tolerance (``indices``: the points' indices; ``distances``: their distances to the mesh [m])."""

    def __init__(self, message: str, indices=(), distances=()):
        super().__init__(message, indices)
        self.distances = tuple(float(d) for d in distances)


# ===================================================================== budget calibration
# (appended block: calibration of a real-time XPBD budget over a set of loads)
__all__ += ["BudgetSaturationError", "BudgetRangeError", "BudgetExtrapolationWarning"]


class BudgetSaturationError(ConvergenceError):
    """The budgeted XPBD response is saturated: the iteration budget at this time step cannot
    carry the load, the force hardly depends on the stiffness (``d log F / d log E`` below the
    threshold) and no effective material exists. ``sensitivity``: the measured
    ``d log F / d log E`` per load; ``proposal``: the :class:`~difftissue.budget.BudgetProposal`
    of the measured search for a budget that carries the load (None when not searched)."""

    def __init__(self, message: str, sensitivity=(), proposal=None):
        super().__init__(message)
        self.sensitivity = tuple(float(s) for s in sensitivity)
        self.proposal = proposal


class BudgetRangeError(ConfigError):
    """A budget card is used outside the range it was calibrated over (another setting or
    mesh, an indenter shape, depth or stiffness outside the calibrated set). The message names
    the quantity, the value and the calibrated range."""


class BudgetExtrapolationWarning(DifftissueWarning):
    """A budget card is used outside its calibrated depth or stiffness range because the caller
    asked for it (``extrapolate=True``): the effective material's error there is unmeasured."""


# ===================================================================== indentation resolution
# (appended block: depths whose contact zone the mesh does not resolve)
__all__ += ["UnderResolvedContactWarning"]


class UnderResolvedContactWarning(DifftissueWarning):
    """Some depths of a simulated indentation have a contact radius smaller than the stated
    number of mesh cells (:meth:`difftissue.scenarios.Indentation.resolution`): the linear
    tetrahedra over-predict the force there by tens to hundreds of percent, and those depths
    enter the fit as if they were as good as the others. The message names the depths, their
    cells per contact radius, and the options: refine the mesh under the indenter, or leave the
    depths out (config ``under_resolved = "drop"``)."""


# ===================================================================== thin automatic specimen
__all__ += ["ThinSpecimenWarning"]


class ThinSpecimenWarning(DifftissueWarning):
    """An automatically chosen indentation specimen was given a thickness of only a few contact
    radii (:func:`difftissue.scenarios.thin_specimen_warning`): the simulated layer is then
    markedly stiffer than a half-space, which the model includes, so the fitted modulus depends
    on the thickness and the base condition given as much as on the data."""


# ===================================================================== runtime error messages
__all__ += ["runtime_error_message"]


def runtime_error_message(error: BaseException, limit: int = 300) -> str:
    """The one useful line of an exception raised inside compiled code (a JAX / XLA runtime
    error carrying an ``equinox.error_if`` message, or a named error raised in a host
    callback): the message after ``EquinoxRuntimeError:`` or ``ConvergenceError:``, not the
    traceback of the callback nor equinox's closing paragraph on ``filter_jit``; otherwise the
    first line that is not a traceback line. At most ``limit`` characters, on one line."""
    lines = [ln.strip() for ln in str(error).splitlines() if ln.strip()]
    for ln in reversed(lines):
        for tag in ("EquinoxRuntimeError:", "ConvergenceError:"):
            if tag in ln:
                return " ".join(ln.split(tag, 1)[1].split())[:limit]
    text = next((ln for ln in lines if not ln.startswith(("File ", "Traceback", "---"))), "")
    return " ".join(text.split())[:limit]
