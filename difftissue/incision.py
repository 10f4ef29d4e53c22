"""Incision: the opening of a cut in a pre-tensioned specimen, as a differentiable forward
model, a fit scenario, a progressive (seed 002) reference and pictures.

A specimen is cut once on the host (:func:`difftissue.cutting.cut_specimen`); the cut mesh is the
**in-vivo** state: a region with ``Material.pre_stretch = lambda0`` is stress-free only when
shrunk by ``1/lambda0`` in x and y, so it carries the pre-stress wherever the lateral faces
hold it. The incision is solved as

1. **before the cut**: every duplicated pair tied (closure penalty,
   :class:`~difftissue.cutting.CutClosureModel` at ``s = -inf``), boundary conditions of
   :func:`incision_boundary` (default: lateral faces held in x and y at the mesh, i.e. the
   stretched positions; base clamped) -> the pre-tensioned equilibrium (with lateral faces
   held, only the thickness changes);
2. **the scalpel advances** in ``scalpel_steps`` equal steps of arc length, each equilibrium
   starting from the previous one (pairs behind the blade released);
3. **after the cut**: all pairs released -> the opened equilibrium, from which
   :func:`~difftissue.cutting.opening_width` gives the width profile along the cut at the
   surface, across depth (every pair), the maximum width and ``w / l``.

Only the last equilibrium carries derivatives (implicit differentiation in
:func:`~difftissue.solvers.static.solve_static`); the earlier ones are its starting guess.
The cut topology is fixed, so the derivatives are those of the opening at fixed topology.

Lengths in metres, stresses in Pa. See ``docs/cutting.md`` ("Incision").
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._io import atomic_output
from .boundary import ROLLER_FACES, BoundaryConditions, Roller, apply_rollers, rigid_mode_rank
from .cutting import Cut, CutClosureModel, Opening, closed_mask, opening_width
from .errors import ConfigError, CutError, DataError
from .constitutive import surface_tension as _model_surface_tension
from .materials import Material, explicit_pre_stretch_y
from .mesh import Specimen, signed_volumes, write_mesh
from .models import make_model, stack_materials
from .scenarios import _SOLVE_SETUP, _jitted_solve
from .solvers.static import prediction_rtol, solve_static, solver_setup

__all__ = [
    "QUANTITIES",
    "LATTICE_OPENING_BIAS",
    "IncisionOptions",
    "IncisionResult",
    "Incision",
    "incision_boundary",
    "depth_profile",
    "plot_incision",
    "write_incision_series",
]

#: Observables an :class:`Incision` scenario can predict.
QUANTITIES = ("surface_width", "max_width", "width_over_length", "pair_width")
_UNITS = {"surface_width": "m", "max_width": "m", "width_over_length": "1", "pair_width": "m"}

#: The lattice models' own converged cut opening against the converged finite-strain continuum
#: (neo-Hookean, P2 reference) at in-plane pre-stretch ``lambda0``: ``{model: ((lambda0,
#: relative max-width bias), ...)}``, measured on the two-layer incision of docs/cutting.md at
#: nu = 0.45 ("Cell size for a given opening error": the h -> 0 limits of the aligned cut, the
#: 25 degree cut within a point of it). The linear limit (lambda0 -> 1) is taken as 0: there
#: the lattices' +3 to +5 % lies within the reference's own +-3.3 %. ``springs_volume_matched_lattice``
#: is within 5 % up to 1.15 and is not listed. Read by :meth:`Incision.lattice_opening_bias`.
LATTICE_OPENING_BIAS = {
    "springs_volume": ((1.0, 0.0), (1.05, -0.04), (1.10, -0.12), (1.15, -0.17)),
    "springs_volume_mesh_lattice": ((1.0, 0.0), (1.05, 0.008), (1.10, -0.040), (1.15, -0.06)),
}


@dataclasses.dataclass(frozen=True)
class IncisionOptions:
    """Solver options of an incision (see :func:`~difftissue.solvers.static.solve_static`).

    Attributes:
        scalpel_steps: equal steps of arc length in which the scalpel crosses the cut (a
            continuation: each equilibrium starts from the previous one), >= 1.
        penalty_factor: closure stiffness of the tied pairs relative to ``max(E) * h``.
        rtol, xtol, max_steps, linear_solver: as in ``solve_static``.
        atol: absolute residual floor [N]; None: ``1e-12 E h^2`` with ``E`` the largest Young's
            modulus of the specimen's materials (0 on a bare mesh) and ``h`` the median edge, so
            that an unloaded specimen (``lambda0 = 1``), whose residual is round-off from the
            start, counts as converged.
        failure: ``"raise"`` (a failed solve raises) or ``"nan"`` (its predictions become NaN,
            so an optimiser rejects the trial parameters).
    """

    scalpel_steps: int = 4
    penalty_factor: float = 1e4
    rtol: float = 1e-9
    xtol: float = 1e-8
    atol: float | None = None
    max_steps: int = 50
    linear_solver: str = "auto"
    failure: str = "raise"
    #: see :class:`~difftissue.scenarios.SolverOptions`
    preconditioner_material: Any = None

    def __post_init__(self):
        if not (isinstance(self.scalpel_steps, int) and self.scalpel_steps >= 1):
            raise ConfigError(f"scalpel_steps must be an integer >= 1, got {self.scalpel_steps!r}")
        if not self.penalty_factor > 0:
            raise ConfigError(f"penalty_factor must be > 0, got {self.penalty_factor!r}")
        if self.failure not in ("raise", "nan"):
            raise ConfigError(f"failure must be 'raise' or 'nan', got {self.failure!r}")
        if self.atol is not None and not self.atol >= 0:
            raise ConfigError(f"atol must be >= 0 N, got {self.atol!r}")

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of an opening width computed with these options
        (:func:`~difftissue.solvers.static.prediction_rtol`)."""
        return prediction_rtol(self.rtol, self.xtol)


class IncisionResult(NamedTuple):
    """An incision's equilibria.

    Attributes:
        displacement: ``(N', 3)`` displacement of the cut mesh after the cut [m].
        precut_displacement: ``(N', 3)`` pre-tensioned equilibrium before the cut [m].
        opening: :class:`~difftissue.cutting.Opening` after the cut (widths of every pair,
            surface profile, max width, ``w / l``).
    """

    displacement: jax.Array
    precut_displacement: jax.Array
    opening: Opening


def incision_boundary(mesh, *, lateral: str = "held", base: str = "clamped", rollers: Sequence = ()) -> BoundaryConditions:
    """Boundary conditions of an incision specimen.

    Args:
        mesh: the cut mesh (``cut.mesh``) or any :class:`~difftissue.mesh.TetMesh`.
        lateral: the side faces ``x-min, x-max, y-min, y-max`` (those not named in
            ``rollers``): ``"held"``: fixed in x and y at the mesh positions (the stretched,
            in-vivo state: the surrounding skin keeps its tension; z free); ``"roller"``: only
            the normal component held (``u_x = 0`` on the x faces, ``u_y = 0`` on the y faces:
            the faces keep their stretched positions but slide along themselves, frictionless);
            ``"free"``: nothing (an excised specimen, which shrinks to ``1/lambda0`` before it
            is cut).
        base: ``"clamped"``: the base ``z = min z`` fixed in x, y, z; ``"sliding"``: u_z = 0
            there.
        rollers: roller supports (:class:`~difftissue.boundary.Roller` or their data forms):
            a side face named here (``"x-min"``) is a roller (symmetry plane) instead of taking
            ``lateral``, e.g. the plane through the middle of a cut, normal to it, in a half
            model; a table ``{"set": selector, "components": "y"}`` holds those components of
            any node set at zero in addition.

    Raises:
        ConfigError: an unknown ``lateral`` or ``base``, or conditions that leave a rigid-body
            mode free (``lateral="free"`` with ``base="sliding"`` and no rollers that hold it).
        BoundaryConditionError: a roller that selects nothing or has no effect.
    """
    if lateral not in ("held", "roller", "free"):
        raise ConfigError(f"lateral must be 'held', 'roller' or 'free', got {lateral!r}")
    if base not in ("clamped", "sliding"):
        raise ConfigError(f"base must be 'clamped' or 'sliding', got {base!r}")
    if isinstance(rollers, (str, dict, Roller)):
        raise ConfigError(f"rollers must be a list, got {rollers!r}")
    named = {r for r in rollers if isinstance(r, str)} | {r.nodes for r in rollers if isinstance(r, Roller) and isinstance(r.nodes, str) and r.components == ROLLER_FACES.get(r.nodes)}
    bc = BoundaryConditions.free(mesh)
    for face in ("x-min", "x-max", "y-min", "y-max"):
        if face in named or lateral == "free":
            continue
        bc = bc.fix(mesh, {"face": face}, "xy" if lateral == "held" else face[0])
    bc = bc.fix(mesh, {"face": "z-min"}, "xyz" if base == "clamped" else "z")
    bc = apply_rollers(bc, mesh, rollers)
    if rigid_mode_rank(np.asarray(mesh.points), bc.fixed) < 6:
        raise ConfigError(f"lateral={lateral!r} with base={base!r}" + (f" and rollers {list(rollers)}" if len(rollers) else "")
                          + " leaves in-plane rigid motion free: clamp the base, hold the lateral faces or add rollers that hold them")
    return bc


def depth_profile(cut: Cut, width, *, s: float | None = None):
    """Widths across depth at one position along the cut.

    Args:
        cut: the :class:`~difftissue.cutting.Cut`.
        width: ``(P,)`` widths of every pair (``opening.width``) [m].
        s: arc length [m] of the column (default the cut centre); the pairs of the column of
            pairs nearest to it are taken.

    Returns:
        ``(depths (k,), widths (k,))`` sorted by depth [m] (``widths`` differentiable).
    """
    ps = np.asarray(cut.pair_s)
    target = 0.5 * cut.length if s is None else float(s)
    nearest = ps[np.argmin(np.abs(ps - target))]
    tol = 1e-6 * max(cut.length, 1e-12)
    idx = np.flatnonzero(np.abs(ps - nearest) <= tol)
    idx = idx[np.argsort(np.asarray(cut.pair_depth)[idx], kind="stable")]
    return np.asarray(cut.pair_depth)[idx], jnp.asarray(width)[idx]


# ============================================================================ the model
def _region_index(mesh, region) -> int:
    names = list(mesh.region_names)
    if isinstance(region, str):
        if region not in names:
            raise ConfigError(f"no region {region!r}; regions are {names}")
        return names.index(region)
    r = int(region)
    if not 0 <= r < len(names):
        raise ConfigError(f"region index {r} out of range; regions are {names}")
    return r


_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")


class Incision(eqx.Module):
    """A cut in a (pre-tensioned) specimen: opening widths as a function of the material.

    Follows the :class:`difftissue.fit.Scenario` protocol: ``predict(material)`` returns the
    chosen ``quantity`` (``observed`` has its shape), so :func:`difftissue.fit.fit` fits it
    alone or jointly with other scenarios sharing the material.

    The fitted material is applied to ``fitted_regions`` (default: every region); the other
    regions keep their materials from ``materials`` (default: the specimen's, when a
    :class:`~difftissue.mesh.Specimen` was cut). E.g. a skin whose dermis is fitted on a fat
    layer of known stiffness: ``fitted_regions=("dermis",)``.

    Quantities (``quantity``):

    - ``"surface_width"``: the width at the top surface at arc lengths ``positions`` along the
      cut [m] (linear interpolation of the surface pair profile; the crack tips, where the
      width is zero, are added at ``s = 0`` and ``s = length`` unless a pair is there);
    - ``"max_width"``: the largest surface width [m] (one value);
    - ``"width_over_length"``: ``max_width / length`` [-] (one value);
    - ``"pair_width"``: the width of every duplicated pair [m] (``abscissa`` = pair depth).
    """

    #: the XLA option set of this scenario's compiled programs (a program kind of
    #: :data:`difftissue.xla_options.PROGRAMS`: static solves)
    xla_program = "static"

    name: str = eqx.field(static=True)
    abscissa: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    cut: Cut
    model: CutClosureModel
    bc: BoundaryConditions
    base_materials: Material | None
    fitted_regions: tuple[int, ...] | None = eqx.field(static=True)
    quantity: str = eqx.field(static=True)
    positions: np.ndarray | None
    kind: str = eqx.field(static=True)
    options: IncisionOptions = eqx.field(static=True)
    #: the absolute residual floor of the static solves [N] (a 0-d array: it comes from the
    #: mesh's edge length, a mesh value)
    atol: np.ndarray
    #: whether the surface profile starts / ends with a crack tip of zero width (no surface
    #: pair at ``s = 0`` / ``s = length``): the shape of the interpolated profile
    tip_start: bool = eqx.field(static=True)
    tip_end: bool = eqx.field(static=True)
    x_label: str = eqx.field(static=True, default="arc length along the cut [m]")
    y_label: str = eqx.field(static=True, default="opening width [m]")

    def __init__(
        self,
        cut: Cut,
        *,
        model: str = "stable_neo_hookean",
        quantity: str = "surface_width",
        positions=None,
        observed=None,
        sigma=None,
        materials: Sequence[Material] | Material | None = None,
        fitted_regions: Sequence[str | int] | None = None,
        lateral: str = "held",
        base: str = "clamped",
        rollers: Sequence = (),
        bc: BoundaryConditions | None = None,
        options: IncisionOptions = IncisionOptions(),
        name: str = "incision",
    ):
        """
        Args:
            cut: the cut specimen (:func:`~difftissue.cutting.cut_specimen`).
            model: elastic model name (:func:`~difftissue.models.make_model`).
            quantity: one of :data:`QUANTITIES`.
            positions: arc lengths along the cut [m] for ``"surface_width"`` (default: the
                surface pairs' own ``s``).
            observed: measured values in the quantity's unit (None: predictions only, zeros).
            sigma: measurement scale (scalar or per value; default the RMS of ``observed``).
            materials: one material per region for the regions that are not fitted (default
                the specimen's); required with ``fitted_regions`` on a bare mesh.
            fitted_regions: region names or indices the fitted material applies to (None: all).
            lateral, base, rollers: see :func:`incision_boundary` (not used when ``bc`` is given).
            bc: explicit boundary conditions on ``cut.mesh``.
            options: :class:`IncisionOptions`.
        """
        if not isinstance(cut, Cut):
            raise CutError(f"cut must be a Cut (difftissue.cutting.cut_specimen), got {type(cut).__name__}")
        if cut.n_pairs == 0 or cut.surface_pairs.size == 0:
            raise CutError("this cut has no duplicated pair on the top surface: no opening to measure")
        if quantity not in QUANTITIES:
            raise ConfigError(f"quantity must be one of {QUANTITIES}, got {quantity!r}")
        if not isinstance(options, IncisionOptions):
            raise ConfigError(f"options must be IncisionOptions, got {type(options).__name__}")
        self.name = str(name)
        # The cut without its quality report (mesh-value metadata, a static field that would
        # split the compiled programs of meshes of one structure; it stays on ``cut``), its
        # layer materials as arrays (Python floats would be compiled in by value: a specimen
        # with other layer materials would compile again).
        self.cut = eqx.tree_at(lambda c: c.pairs, cut, np.asarray(cut.pairs))
        object.__setattr__(self.cut, "quality", None)
        object.__setattr__(self.cut, "materials", _material_arrays(cut.materials))
        self.kind = str(model)
        self.options = options
        self.quantity = quantity
        mesh = cut.mesh
        self.model = CutClosureModel(make_model(mesh, model), cut, -jnp.inf, penalty_factor=options.penalty_factor)
        if bc is not None and (lateral, base, tuple(rollers)) != ("held", "clamped", ()):
            raise ConfigError("give either bc or lateral / base / rollers, not both")
        self.bc = incision_boundary(mesh, lateral=lateral, base=base, rollers=rollers) if bc is None else bc
        # materials of the regions that are not fitted
        if materials is None:
            materials = cut.materials
        if isinstance(materials, Material):
            materials = (materials,) * len(mesh.region_names)
        if fitted_regions is not None:
            idx = tuple(sorted({_region_index(mesh, r) for r in fitted_regions}))
            if not idx:
                raise ConfigError("fitted_regions is empty")
            if materials is None:
                raise ConfigError("fitted_regions needs the materials of the other regions: cut a Specimen or pass materials=")
            if len(materials) != len(mesh.region_names):
                raise ConfigError(f"{len(materials)} material(s) for {len(mesh.region_names)} region(s) {list(mesh.region_names)}")
            self.fitted_regions = idx
            self.base_materials = stack_materials(list(materials))
        else:
            self.fitted_regions = None
            self.base_materials = None
        if options.atol is not None:
            self.atol = np.asarray(float(options.atol))
        elif materials is not None:
            E_ref = max(float(np.max(np.asarray(m.youngs_modulus))) for m in materials)
            self.atol = np.asarray(1e-12 * E_ref * float(self.model.edge_length) ** 2)
        else:
            self.atol = np.asarray(0.0)
        # the observable
        surf_s = np.asarray(cut.pair_s)[cut.surface_pairs]
        self.tip_start = bool(surf_s.min() > 1e-9 * cut.length)
        self.tip_end = bool(surf_s.max() < cut.length - 1e-9 * cut.length)
        if quantity == "surface_width":
            pos = surf_s.copy() if positions is None else np.asarray(positions, dtype=float).reshape(-1)
            if pos.size == 0 or not np.all(np.isfinite(pos)):
                raise DataError("positions must be a non-empty array of finite arc lengths [m]")
            if np.any(pos < -1e-12 * cut.length) or np.any(pos > cut.length * (1 + 1e-12)):
                raise DataError(f"positions must lie on the cut, 0 <= s <= {cut.length:g} m; got {pos.min():g} .. {pos.max():g}")
            self.positions = pos
            self.abscissa = pos
            self.x_label, self.y_label = "arc length along the cut [m]", "surface opening width [m]"
        elif quantity == "pair_width":
            if positions is not None:
                raise ConfigError("positions apply to quantity 'surface_width' only")
            self.positions = None
            self.abscissa = np.asarray(cut.pair_depth, dtype=float)
            self.x_label, self.y_label = "pair depth [m]", "opening width [m]"
        else:
            if positions is not None:
                raise ConfigError("positions apply to quantity 'surface_width' only")
            self.positions = None
            self.abscissa = np.array([cut.length])
            self.x_label = "cut length [m]"
            self.y_label = "max surface width [m]" if quantity == "max_width" else "max width / cut length [-]"
        n = self.abscissa.size
        if observed is None:
            self.observed = np.zeros(n)
            self.sigma = np.ones(n)
        else:
            obs = np.asarray(observed, dtype=float).reshape(-1)
            if obs.shape != (n,):
                raise DataError(f"{n} predicted value(s) for quantity {quantity!r} but {obs.size} observed")
            if not np.all(np.isfinite(obs)):
                raise DataError("observed widths contain NaN or infinite values")
            self.observed = obs
            if sigma is None:
                s0 = float(np.sqrt(np.mean(obs**2)))
                self.sigma = np.full(n, s0 if s0 > 0 else 1.0)
            else:
                sg = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
                if not np.all(np.isfinite(sg) & (sg > 0)):
                    raise DataError("sigma must be positive and finite")
                self.sigma = sg

    # ----------------------------------------------------------------- materials
    def region_material(self, material: Material) -> Material:
        """The per-region material the model sees: ``material`` on the fitted regions, the
        fixed materials elsewhere (``material`` itself when every region is fitted)."""
        return _region_material(material, self.fitted_regions, self.base_materials)

    def fitted_layers(self) -> list[tuple[str, float, np.ndarray | None]]:
        """The regions the fitted material applies to, as layers: ``(name, thickness [m], cell)``.

        ``thickness`` is the region's volume over the area of its x-y bounding box (a flat layer's
        thickness in the mesh, i.e. its stress-free thickness: the models shrink only x and y);
        ``cell`` the median lattice cell ``(hx, hy, hz)`` [m] of the region for ``springs_volume``
        (whose finite-strain response depends on the cell shape), else None.
        """
        mesh = self.cut.mesh
        regions = self.fitted_regions if self.fitted_regions is not None else tuple(range(len(mesh.region_names)))
        p = np.asarray(mesh.points, dtype=float)
        tets = np.asarray(mesh.tets)
        ids = np.asarray(mesh.region_ids)
        vol = np.abs(signed_volumes(p, tets))
        lattice = getattr(mesh, "lattice", None)
        out = []
        for r in regions:
            sel = ids == r
            if not np.any(sel):
                continue
            q = p[np.unique(tets[sel])]
            area = np.ptp(q[:, 0]) * np.ptp(q[:, 1])
            cell = None
            if self.kind.startswith("springs_volume") and lattice is not None and np.any(np.asarray(lattice.cube_region_ids) == r):
                cell = np.median(np.asarray(lattice.cell_size)[np.asarray(lattice.cube_region_ids) == r], axis=0)
            out.append((mesh.region_names[r], float(np.sum(vol[sel]) / area), cell))
        return out

    def surface_tension(self, material: Material, thickness: float | None = None):
        """Surface tension ``T`` [N/m] the pre-stretched fitted layer carries in this scenario's
        model, from the model's own equibiaxial stress state
        (:func:`difftissue.constitutive.surface_tension`: in-plane force per unit in-vivo length,
        Cauchy stress x current thickness), not the linear ``E (lambda0 - 1) t / (1 - nu)``
        (:func:`~difftissue.materials.surface_tension_from_pre_stretch`, which overstates it by
        15-19 % at lambda0 = 1.05, nu = 0.45).

        Args:
            material: the fitted material (scalar fields; ``pre_stretch`` is ``lambda0``).
            thickness: layer thickness [m]; None: the fitted regions' own
                (:meth:`fitted_layers`, their tensions added). The lattice cell of the first
                fitted region is used with ``springs_volume``.

        Differentiable in ``material``.
        """
        layers = self.fitted_layers()
        if thickness is not None:
            return _model_surface_tension(self.kind, material, thickness, cell_size=layers[0][2] if layers else None)
        return sum(_model_surface_tension(self.kind, material, t, cell_size=c) for _, t, c in layers)

    def lattice_opening_bias(self, material: Material) -> dict | None:
        """The estimated bias of this scenario's opening widths from its model's own finite-strain
        response, at the pre-stretch of ``material`` (on the fitted regions) and of the fixed
        regions: refining the mesh does not remove it (:data:`LATTICE_OPENING_BIAS`).

        Returns None for a model without a listed bias (the continuum models,
        ``springs_volume_matched_lattice``). Otherwise ``{"model", "pre_stretch"`` (the
        ``lambda`` farthest from 1 over the regions and both in-plane directions) ``,
        "relative_bias"`` (interpolated linearly in ``lambda``; None outside the measured
        ``[1, 1.15]``) ``, "measured"`` (the table as lists) ``}``. Host arithmetic on concrete
        materials, not differentiable."""
        table = LATTICE_OPENING_BIAS.get(self.kind)
        if table is None:
            return None
        regional = self.region_material(material)
        lams = [np.ravel(np.asarray(regional.pre_stretch, dtype=float))]
        if regional.pre_stretch_y is not None:
            lams.append(np.ravel(np.asarray(regional.pre_stretch_y, dtype=float)))
        lams = np.concatenate(lams)
        lam = float(lams[np.argmax(np.abs(lams - 1.0))])
        knots, biases = np.array([k for k, _ in table]), np.array([b for _, b in table])
        inside = knots[0] <= lam <= knots[-1]
        return {"model": self.kind, "pre_stretch": lam,
                "relative_bias": float(np.interp(lam, knots, biases)) if inside else None,
                "measured": [list(kb) for kb in table]}

    # ----------------------------------------------------------------- solves
    def _closure(self, s):
        return eqx.tree_at(lambda m: m.closed, self.model, closed_mask(self.cut, s).astype(float))

    def _solve_at(self, material, s, u0):
        o = self.options
        # the setup of a program compiled with the arrays as arguments (None: built from the mesh)
        sol = solve_static(
            self._closure(s),
            material,
            self.bc,
            rtol=o.rtol,
            atol=self.atol,
            xtol=o.xtol,
            max_steps=o.max_steps,
            linear_solver=o.linear_solver,
            preconditioner_material=o.preconditioner_material,
            initial_displacement=jax.lax.stop_gradient(u0),
            throw=o.failure == "raise",
            setup=_SOLVE_SETUP.get(),
        )
        u = sol.displacement
        if o.failure == "nan":
            # A multiplication: NaN value, tangents and cotangents (a where would give zeros).
            u = u * jnp.where(sol.converged, 1.0, jnp.nan).astype(u.dtype)
        return u

    def _schedule(self):
        k = self.options.scalpel_steps
        return jnp.asarray(np.concatenate([[-np.inf], self.cut.length * np.arange(1, k) / k]))

    def _solve_cut(self, material):
        mat = self.region_material(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material))
        frozen = jax.lax.stop_gradient(mat)
        u0 = jnp.zeros((self.cut.mesh.n_nodes, 3))

        def step(u, s):
            u_new = self._solve_at(frozen, s, u)
            return u_new, u_new

        _, us = jax.lax.scan(step, u0, self._schedule())
        u = self._solve_at(mat, jnp.inf, us[-1])
        x = jnp.asarray(self.cut.mesh.points) + u
        return IncisionResult(u, us[0], opening_width(self.cut, x))

    def _progress(self, material, positions):
        mat = self.region_material(jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material))
        u0 = self._solve_at(jax.lax.stop_gradient(mat), -jnp.inf, jnp.zeros((self.cut.mesh.n_nodes, 3)))

        def step(u, s):
            u_new = self._solve_at(mat, s, u)
            op = opening_width(self.cut, jnp.asarray(self.cut.mesh.points) + u_new)
            return u_new, (u_new, op.width, op.max_width)

        _, (us, widths, mx) = jax.lax.scan(step, u0, jnp.asarray(positions, dtype=float))
        return us, widths, mx

    def solve(self, material: Material) -> IncisionResult:
        """Equilibria before and after the cut and the opening (compiled once per scenario)."""
        return _jitted_solve(self, "_solve_cut")(_as_arrays(material))

    def progress(self, material: Material, positions):
        """The opening as the scalpel advances (seed 002): for each arc length in
        ``positions`` [m] (increasing; pairs with ``pair_s > s`` still tied), the equilibrium.

        Returns:
            ``(displacements (K, N', 3) [m], pair widths (K, P) [m], max surface width (K,) [m])``.
        """
        pos = np.asarray(positions, dtype=float).reshape(-1)
        if pos.size == 0 or np.any(np.diff(pos) < 0):
            raise DataError("positions must be a non-empty, non-decreasing sequence of arc lengths [m]")
        return _jitted_solve(self, "_progress")(_as_arrays(material), pos)

    def _observable(self, op: Opening):
        if self.quantity == "max_width":
            return op.max_width[None]
        if self.quantity == "width_over_length":
            return op.width_over_length[None]
        if self.quantity == "pair_width":
            return op.width
        s, w = op.surface_s, op.surface_width
        L = self.cut.length
        if self.tip_start:  # the crack tip at the start: zero width
            s, w = jnp.concatenate([jnp.zeros(1), s]), jnp.concatenate([jnp.zeros(1), w])
        if self.tip_end:
            s, w = jnp.concatenate([s, jnp.full(1, L)]), jnp.concatenate([w, jnp.zeros(1)])
        return jnp.interp(jnp.asarray(self.positions), s, w)

    def _solve_protocol(self, material):
        """The observable (the protocol :func:`difftissue.scenarios._jitted_solve` compiles)."""
        return self._observable(self._solve_cut(material).opening)

    def _setup_builder(self):
        """``material -> SolverSetup`` of this incision's static solves (for a material of that
        structure, values unused), as a solve traced with the mesh closed over builds it: the
        closure weights and the material traced (the multigrid hierarchy for
        ``IncisionOptions.preconditioner_material`` or E = 1 Pa, nu = 0.45, at rest with every
        pair released). It keeps the model and the boundary conditions, not the scenario."""
        model, bc, o = self.model, self.bc, self.options
        fitted, base, pair_s = self.fitted_regions, self.base_materials, np.asarray(self.cut.pair_s)

        def build(material):
            built = []

            def trace(m, s):
                closure = eqx.tree_at(lambda c: c.closed, model, (jnp.asarray(pair_s) > s).astype(float))
                built.append(solver_setup(closure, _region_material(m, fitted, base), bc, linear_solver=o.linear_solver,
                                          preconditioner_material=o.preconditioner_material))

            jax.eval_shape(trace, material, jnp.zeros(()))
            return built[0]

        return build

    @property
    def prediction_rtol(self) -> float:
        """Relative precision [-] of the predictions (from the solver options)."""
        return self.options.prediction_rtol

    def predict(self, material: Material):
        """The ``quantity`` after the cut, shape ``observed.shape`` (its unit)."""
        return _jitted_solve(self)(_as_arrays(material))

    def record(self) -> dict:
        """The experiment as a material card's scenario record (:func:`difftissue.export.card.scenario_record`):
        ``name``, ``type``, ``experiment = "incision"``, difftissue's ``model``, the fitted
        ``quantity``, ``cut_length`` and ``cut_depth`` [m]; the cut mesh, its duplicated pairs
        and boundary conditions go into a specimen file (:mod:`difftissue.export.fitted`)."""
        return {"name": self.name, "type": type(self).__name__, "experiment": "incision", "model": str(self.model.base.model_name),
                "quantity": self.quantity, "cut_length": float(self.cut.length), "cut_depth": float(self.cut.depth)}


def _as_arrays(material):
    return jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=float), material)


def _material_arrays(materials):
    """``materials`` (a material, a sequence of them or None) with every field a float64 NumPy
    array (0-d for a scalar) [the field's SI unit]: array leaves, not Python scalars, so that
    specimens with other layer materials share the compiled programs."""
    return jax.tree_util.tree_map(lambda v: np.asarray(v, dtype=float), materials)


def _region_material(material: Material, fitted_regions, base: Material | None) -> Material:
    """``material`` on the regions ``fitted_regions`` (indices; None: all, ``material`` itself),
    ``base`` (one material per region) elsewhere (see :meth:`Incision.region_material`)."""
    if fitted_regions is None:
        return material
    idx = jnp.asarray(fitted_regions)
    fields = _FIELDS
    if material.pre_stretch_y is not None or base.pre_stretch_y is not None:
        fields = _FIELDS + ("pre_stretch_y",)  # anisotropic: lambda_y = lambda_x where a material has none
        material, base = explicit_pre_stretch_y(material), explicit_pre_stretch_y(base)
    vals = []
    for f in fields:
        v = jnp.asarray(getattr(material, f), dtype=float)
        if v.ndim != 0:
            raise ConfigError(f"with fitted_regions the material's {f} must be a scalar, got shape {v.shape}")
        vals.append(jnp.asarray(getattr(base, f), dtype=float).at[idx].set(v))
    return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in fields), base, tuple(vals))


def _top_faces(mesh):
    """The boundary faces facing up (outward normal with a positive z component): the flat top
    of a block, the whole curved top of a dome or a cylinder."""
    faces = np.asarray(mesh.boundary_faces)
    p = np.asarray(mesh.points)
    nrm = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    return faces[nrm[:, 2] > 1e-9 * np.linalg.norm(nrm, axis=1)]


def plot_incision(cut: Cut, displacement, path, *, s_section: float | None = None, title: str | None = None, overwrite: bool = False) -> Path:
    """PNG of an opened cut: the deformed top surface (left) and the cross-section through the
    cut at arc length ``s_section`` (default its centre; right), both sides of the cut shaded
    differently, the duplicated pairs marked. Written atomically; an existing file is refused
    unless ``overwrite``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    mesh = cut.mesh
    X = np.asarray(mesh.points)
    u = np.asarray(displacement, dtype=float)
    if u.shape != X.shape:
        raise CutError(f"displacement must have shape {X.shape}, got {u.shape}")
    x = X + u
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.8))
    tri = _top_faces(mesh)
    side = np.zeros(mesh.n_nodes)
    side[cut.pairs[:, 0]] = 1.0
    side[cut.pairs[:, 1]] = -1.0
    mag = np.linalg.norm(u[:, :2], axis=1)
    polys = PolyCollection(x[tri][:, :, :2] * 1e3, array=mag[tri].mean(axis=1) * 1e3, cmap="viridis", edgecolors="k", linewidths=0.2)
    ax1.add_collection(polys)
    fig.colorbar(polys, ax=ax1, label="in-plane displacement [mm]")
    sp = cut.surface_pairs
    pa, pb = cut.pairs[sp, 0], cut.pairs[sp, 1]
    ax1.plot(x[pa, 0] * 1e3, x[pa, 1] * 1e3, "r.-", ms=3, lw=0.8, label="cut face +")
    ax1.plot(x[pb, 0] * 1e3, x[pb, 1] * 1e3, "b.-", ms=3, lw=0.8, label="cut face -")
    ax1.set_aspect("equal")
    ax1.autoscale_view()
    ax1.set_xlabel("x [mm]")
    ax1.set_ylabel("y [mm]")
    ax1.set_title("top surface (deformed)")
    ax1.legend(loc="upper right", fontsize=7)
    # cross-section: tets whose rest centroid is within half a cell of the plane through the
    # point of the path at s_section, normal to the path there
    ps = np.asarray(cut.pair_s)
    target = 0.5 * cut.length if s_section is None else float(s_section)
    col = np.argmin(np.abs(ps - target))
    nrm = np.asarray(cut.pair_normal)[col]
    tangent = np.array([-nrm[1], nrm[0], 0.0])
    tangent /= np.linalg.norm(tangent) or 1.0
    origin = X[cut.pairs[col, 0]]
    cent = X[mesh.tets].mean(axis=1)
    e = mesh.edges
    h = float(np.median(np.linalg.norm(X[e[:, 1]] - X[e[:, 0]], axis=1)))
    near = np.abs((cent - origin) @ tangent) <= 0.5 * h
    segs, colours = [], []
    tside = np.asarray(cut.tet_side)
    for t in np.flatnonzero(near):
        nodes = mesh.tets[t]
        c = "r" if tside[t] > 0 else ("b" if tside[t] < 0 else "0.6")
        for i in range(4):
            for j in range(i + 1, 4):
                a, b = nodes[i], nodes[j]
                segs.append([[(x[a] - origin) @ nrm * 1e3, x[a, 2] * 1e3], [(x[b] - origin) @ nrm * 1e3, x[b, 2] * 1e3]])
                colours.append(c)
    ax2.add_collection(LineCollection(segs, colors=colours, linewidths=0.4))
    incol = np.flatnonzero(np.abs((X[cut.pairs[:, 0]] - origin) @ tangent) <= 0.5 * h)
    for k in incol:
        a, b = cut.pairs[k]
        ax2.plot([(x[a] - origin) @ nrm * 1e3, (x[b] - origin) @ nrm * 1e3], [x[a, 2] * 1e3, x[b, 2] * 1e3], "k.", ms=4)
    ax2.autoscale_view()
    ax2.set_aspect("equal")
    ax2.set_xlabel("distance across the cut [mm]")
    ax2.set_ylabel("z [mm]")
    ax2.set_title(f"cross-section at s = {ps[col] * 1e3:.2f} mm (red +, blue - side)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)
    return path


def write_incision_series(directory, cut: Cut, displacements, positions, *, stem: str = "incision", materials: Sequence[Material] | None = None, overwrite: bool = False) -> Path:
    """A VTU series for ParaView: one ``{stem}_{k:03d}.vtu`` per scalpel position and a
    ``{stem}.pvd`` collection whose timestep is the scalpel arc length [m].

    Point data: ``displacement`` [m], ``cut_side`` (+1 / -1 on duplicated nodes, 0 elsewhere),
    ``tied`` (1 on the nodes of pairs still tied at that position); cell data ``tet_side`` and
    region ids (and ``youngs_modulus``, ``pre_stretch`` per tet when ``materials`` are given).
    The mesh is the reference (in-vivo) configuration: use ParaView's *Warp By Vector* with
    ``displacement``. Files are written atomically; existing ones are refused unless ``overwrite``.

    Returns:
        The path of the ``.pvd`` file.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise CutError(f"directory {directory} does not exist; create it first")
    us = np.asarray(displacements, dtype=float)
    pos = np.asarray(positions, dtype=float).reshape(-1)
    mesh = cut.mesh
    if us.ndim != 3 or us.shape[1:] != (mesh.n_nodes, 3) or us.shape[0] != pos.size:
        raise CutError(f"displacements must have shape ({pos.size}, {mesh.n_nodes}, 3) for {pos.size} positions, got {us.shape}")
    side = np.zeros(mesh.n_nodes)
    side[cut.pairs[:, 0]] = 1.0
    side[cut.pairs[:, 1]] = -1.0
    cell = {"tet_side": np.asarray(cut.tet_side, dtype=float)}
    mats = materials if materials is not None else cut.materials
    if mats is not None:
        sp = Specimen(mesh, tuple(mats)).cell_fields()
        cell["youngs_modulus"] = sp["youngs_modulus"]
        cell["pre_stretch"] = sp["pre_stretch"]
        if "pre_stretch_y" in sp:
            cell["pre_stretch_y"] = sp["pre_stretch_y"]
    names = []
    for k, (u, s) in enumerate(zip(us, pos)):
        tied = np.zeros(mesh.n_nodes)
        closed = np.asarray(cut.pair_s) > s
        tied[cut.pairs[closed].reshape(-1)] = 1.0
        name = f"{stem}_{k:03d}.vtu"
        write_mesh(directory / name, mesh, point_data={"displacement": u, "cut_side": side, "tied": tied}, cell_data=cell, overwrite=overwrite)
        names.append((s, name))
    finite = [s for s, _ in names if np.isfinite(s)]
    big = (max(finite) if finite else cut.length) + cut.length
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "<Collection>"]
    for s, name in names:
        t = -cut.length if s == -np.inf else (big if s == np.inf else s)
        lines.append(f'<DataSet timestep="{t:.9g}" group="" part="0" file="{name}"/>')
    lines += ["</Collection>", "</VTKFile>", ""]
    pvd = directory / f"{stem}.pvd"
    with atomic_output(pvd, overwrite=overwrite) as tmp:
        Path(tmp).write_text("\n".join(lines))
    return pvd
