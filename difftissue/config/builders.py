"""Building one experiment from its ``[[experiment]]`` table: the data (through
:mod:`~difftissue.config.rows`), the specimen mesh (generated block, cylinder, layered skin, or
a mesh file), the indenter, platens, rollers, node sets, the cut, and the scenario
(:class:`~difftissue.scenarios.AnalyticIndentation`, :class:`~difftissue.scenarios.Indentation`,
:class:`~difftissue.scenarios.Compression`, :class:`~difftissue.scenarios.FEMField`,
:class:`~difftissue.incision.Incision`), with its builder on a coarser mesh for the
discretisation estimate. Each returns an :class:`~difftissue.config.Experiment`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..boundary import ROLLER_FACES, Roller
from ..cutting import ScalpelPath, cut_specimen
from ..errors import DifftissueError
from ..incision import Incision, IncisionOptions
from ..materials import Material
from ..mesh import Specimen, block, layer_node_heights, layered_skin, read_mesh
from ..models import LATTICE_MODELS, LATTICE_VARIANTS, MODELS, NODAL_FEM_MODELS
from ..axisymmetric import AXISYMMETRIC_MODELS
from ..scenarios import (AXISYMMETRIC_CELLS_PER_CONTACT_RADIUS, MIN_CELLS_PER_CONTACT_RADIUS, AnalyticIndentation, AxisymmetricIndentation, Compression, FEMField, Indentation, SolverOptions,
                         axisymmetric_specimen_for, cylinder, indentation_block, indentation_specimen_for, thin_specimen_warning)
from ..selectors import selector_from_dict
from .estimates import _compression_estimate, _compression_plausibility, _indentation_estimate, _plausibility
from .experiment import Experiment
from .rows import _force_depth, _load_data, _provenance_note, _stress_strain
from .schema import (
    _DATA_FORMATS,
    _MESH_UNITS,
    _SOLVER_KEYS,
    FIELDS,
    _bool,
    _choice,
    _counts,
    _fail,
    _integer,
    _is_number,
    _join,
    _length,
    _lengths,
    _material_values,
    _number,
    _positive,
    _reraise,
    _resolve,
    _show,
    _sigma,
    _string,
    _table,
    _unit_of,
)

def _solver_options(e: Mapping, path: str):
    if "solver" not in e:
        return SolverOptions()
    p = _join(path, "solver")
    t = _table(e["solver"], p, _SOLVER_KEYS)
    kw: dict[str, Any] = {}
    for k in ("rtol", "xtol"):
        if k in t:
            kw[k] = _positive(t[k], _join(p, k))
    if "max_steps" in t:
        kw["max_steps"] = _integer(t["max_steps"], _join(p, "max_steps"), minimum=1)
    if "linear_solver" in t:
        kw["linear_solver"] = _choice(t["linear_solver"], _join(p, "linear_solver"), ("auto", "multigrid", "sparse", "dense", "cg"))
    return SolverOptions(**kw)


def _model(e: Mapping, path: str, default: str) -> str:
    """The experiment's ``model``: one of :data:`~difftissue.models.MODELS`,
    :data:`~difftissue.models.NODAL_FEM_MODELS` or :data:`~difftissue.models.LATTICE_VARIANTS`
    (``springs_volume_mesh_lattice``, ``springs_volume_matched_lattice``: ``springs_volume`` bit
    for bit without pre-stretch, so they are accepted wherever ``springs_volume`` is)."""
    return _choice(e.get("model", default), _join(path, "model"), MODELS + NODAL_FEM_MODELS + LATTICE_VARIANTS)


def _build_experiment(e: Mapping, path: str, name: str, base_dir: Path, *, material=None, fitted: tuple[str, ...] = ()) -> Experiment:
    """One experiment; ``material`` is the config's [material] and ``fitted`` its fitted fields
    (an indentation's automatic specimen is axisymmetric only without pre-stretch)."""
    kind = e["scenario"]
    if "contact_offset" in e and e["contact_offset"] != "fit":
        _fail(_join(path, "contact_offset"), f"must be \"fit\" (fit the contact offset with the material), got {e['contact_offset']!r}")
    if kind == "incision":
        return _incision(e, path, name, base_dir, material)
    if kind == "indentation":
        exp = _indentation(e, path, name, base_dir, material=material, fitted=tuple(fitted))
    else:
        builder = {"analytic_indentation": _analytic, "indentation": _indentation, "compression": _compression, "fem_field": _fem_field}[kind]
        exp = builder(e, path, name, base_dir)
    return dataclasses.replace(exp, fit_contact_offset=True) if "contact_offset" in e else exp


def _indenter(e, path, curve, kind):
    p = _join(path, "indenter")
    if "indenter" not in e:
        _fail(p, "missing (required): e.g. { shape = \"sphere\", radius = 27.5e-6 }")
    placement = ("surface", "axis_point", "axis_direction", "contact_point") if kind == "indentation" else ()
    t = _table(e["indenter"], p, ("shape", "radius", "half_angle_deg", "bonded", "length_unit") + placement, ("shape",))
    shape = _choice(t["shape"], _join(p, "shape"), ("sphere", "flat_punch", "cone"))
    unit = _unit_of(t, p)
    kw: dict[str, Any] = {"indenter": shape}
    kw.update(_placement(t, p, unit, shape))
    if shape == "cone":
        for k in ("radius", "bonded"):
            if k in t:
                _fail(_join(p, k), "not used by a cone (give half_angle_deg)")
        if "half_angle_deg" not in t:
            _fail(_join(p, "half_angle_deg"), "missing (required for a cone): the half-angle in degrees")
        deg = _number(t["half_angle_deg"], _join(p, "half_angle_deg"), check=lambda v: 0 < v < 90, rule="an angle in degrees in (0, 90)")
        kw["half_angle"] = math.radians(deg)
    else:
        if "half_angle_deg" in t:
            _fail(_join(p, "half_angle_deg"), f"not used by a {shape} (give radius)")
        if "radius" not in t:
            _fail(_join(p, "radius"), f"missing (required for a {shape}): a length in {unit[0]}, or \"instrument\" for the tip radius in the data file")
        r = t["radius"]
        if r == "instrument":
            inst = getattr(curve, "metadata", {}).get("instrument", {}) or {}
            if not inst.get("tip_radius"):
                _fail(_join(p, "radius"), "\"instrument\": the data file records no tip radius; give the radius as a length")
            kw["radius"] = float(inst["tip_radius"])
        else:
            kw["radius"] = _length(r, _join(p, "radius"), unit)
        if "bonded" in t:
            if shape != "flat_punch" or kind != "indentation":
                _fail(_join(p, "bonded"), "only a simulated flat punch (scenario \"indentation\") can be bonded")
            kw["bonded_punch"] = _bool(t["bonded"], _join(p, "bonded"))
    return kw


def _vector(value, path: str, what: str, factor: float = 1.0) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        _fail(path, f"must be {what} (a list of 3 numbers), got {value!r}")
    return tuple(_number(v, _join(path, i)) * factor for i, v in enumerate(value))  # type: ignore[return-value]


def _placement(t, p, unit, shape) -> dict:
    """The indenter on a curved surface: ``surface = "boundary"`` with ``axis_point`` and
    ``contact_point`` (coordinates in the table's length unit) and ``axis_direction``."""
    kw: dict[str, Any] = {}
    if "surface" not in t:
        for k in ("axis_point", "axis_direction", "contact_point"):
            if k in t:
                _fail(_join(p, k), "places the indenter on a curved surface: needs surface = \"boundary\"")
        return kw
    kw["surface"] = _choice(t["surface"], _join(p, "surface"), ("top", "boundary"))
    if kw["surface"] == "boundary" and shape == "flat_punch":
        _fail(_join(p, "surface"), "a flat punch indents the flat top only (\"boundary\" takes a sphere or a cone)")
    for k in ("axis_point", "contact_point"):
        if k in t:
            kw[k] = _vector(t[k], _join(p, k), f"a point [x, y, z] in {unit[0]}", unit[1])
    if "axis_direction" in t:
        d = _vector(t["axis_direction"], _join(p, "axis_direction"), "a direction [dx, dy, dz]")
        if not any(d):
            _fail(_join(p, "axis_direction"), "must not be zero")
        kw["axis_direction"] = d
    if kw["surface"] == "top" and len(kw) > 1:
        _fail(p, "axis_point, axis_direction and contact_point need surface = \"boundary\"")
    return kw


def _analytic(e, path, name, base_dir) -> Experiment:
    curve, file, notes, depth, force, sigma, unit, prov = _force_depth(e, path, base_dir, "analytic_indentation")
    kw = _indenter(e, path, curve, "analytic_indentation")
    solution = _choice(e.get("solution", "half_space"), _join(path, "solution"), ("half_space", "exact_layer", "dimitriadis"))
    thickness = _length(e["thickness"], _join(path, "thickness"), unit) if "thickness" in e else None
    if solution != "half_space" and thickness is None:
        _fail(_join(path, "thickness"), f"missing (required by solution = {solution!r}): the layer thickness in {unit[0]}")
    if solution == "half_space" and thickness is not None:
        _fail(_join(path, "thickness"), "not used by solution = 'half_space'; choose 'exact_layer' or 'dimitriadis' for a layer")
    base = _choice(e.get("base", "bonded"), _join(path, "base"), ("bonded", "lubricated"))
    if kw["indenter"] == "cone" and solution != "half_space":
        _fail(_join(path, "solution"), "a cone has only the 'half_space' solution")
    if kw["indenter"] == "flat_punch" and solution == "dimitriadis":
        _fail(_join(path, "solution"), "'dimitriadis' is for a sphere; a flat punch on a layer uses 'exact_layer' (Hayes)")
    try:
        sc = AnalyticIndentation(depth, force, thickness=thickness, solution=solution, base=base, sigma=sigma, name=name, **kw)
    except DifftissueError as err:
        _reraise(path, err)
    model = {"sphere": "hertz", "flat_punch": "sneddon_flat_punch", "cone": "sneddon_cone"}[kw["indenter"]] if solution == "half_space" else f"{solution}_{kw['indenter']}"
    return Experiment(name, "analytic_indentation", model, sc, (file,), notes, prov, _plausibility(path, depth, force, kw, curve),
                      _indentation_estimate(depth, force, sigma, kw), coarsen_skip="a closed-form solution: no mesh, no discretisation error")


def _compression(e, path, name, base_dir) -> Experiment:
    curve, file, notes, x, y, prov = _stress_strain(e, path, base_dir)
    measure = _choice(e.get("measure", "engineering"), _join(path, "measure"), ("engineering", "true"))
    plausibility = _compression_plausibility(path, curve, x, y, measure)
    sigma = _sigma(e.get("sigma", "rms"), _join(path, "sigma"), y, "Pa")
    platens = _choice(e.get("platens", "frictionless"), _join(path, "platens"), ("frictionless", "bonded"))
    rollers = _rollers(e["rollers"], _join(path, "rollers")) if "rollers" in e else ()
    model = _model(e, path, "springs_volume")
    options = _solver_options(e, path)
    p = _join(path, "specimen")
    spec = _table(e.get("specimen", {}), p, ("shape", "size", "cells", "diameter", "height", "cells_radial", "cells_height", "mesh", "length_unit", "reorient"))
    files = [file]
    coarse_mesh, skip = None, _MESH_FILE_SKIP
    if "mesh" in spec:
        mesh, mfile = _mesh_file(spec, p, base_dir)
        files.append(mfile)
    else:
        shape = _choice(spec.get("shape", "block"), _join(p, "shape"), ("block", "cylinder"))
        unit = _unit_of(spec, p)
        h_data = curve.height or 0.01
        d_data = curve.diameter or h_data
        if shape == "block":
            for k in ("diameter", "height", "cells_radial", "cells_height"):
                if k in spec:
                    _fail(_join(p, k), "not used by shape = 'block' (give size and cells)")
            # default: a cube of the specimen's height (frictionless platens: any shape gives the same answer)
            size = _lengths(spec["size"], _join(p, "size"), unit) if "size" in spec else (h_data, h_data, h_data)
            cells = _counts(spec.get("cells", [2, 2, 2]), _join(p, "cells"))
            mesh = block(size, cells)
            coarse_mesh, skip = _coarse_block(size, cells)
        else:
            for k in ("size", "cells"):
                if k in spec:
                    _fail(_join(p, k), "not used by shape = 'cylinder' (give diameter, height, cells_radial, cells_height)")
            dia = _length(spec["diameter"], _join(p, "diameter"), unit) if "diameter" in spec else d_data
            hei = _length(spec["height"], _join(p, "height"), unit) if "height" in spec else h_data
            nr = _integer(spec.get("cells_radial", 4), _join(p, "cells_radial"), minimum=1)
            nh = _integer(spec.get("cells_height", 4), _join(p, "cells_height"), minimum=1)
            if model in LATTICE_MODELS:
                _fail(_join(path, "model"), f"a cylinder mesh has no cube lattice ({model} needs one): use 'stable_neo_hookean', 'fem_linear' or 'fem_neo_hookean' (or a block: with frictionless platens any shape gives the same answer)")
            mesh = cylinder(dia, hei, nr, nh)
            coarse_mesh, skip = _coarse_cylinder(dia, hei, nr, nh)
    try:
        sc = Compression(mesh, x, y, model=model, bonded=platens == "bonded", measure=measure, rollers=rollers, sigma=sigma, options=options, name=name)
    except DifftissueError as err:
        _reraise(path, err)
    coarsen = None
    if coarse_mesh is not None:
        def coarsen():
            m, info = coarse_mesh()
            return Compression(m, x, y, model=model, bonded=platens == "bonded", measure=measure, rollers=rollers, sigma=sigma, options=options, name=name), info
    return Experiment(name, "compression", model, sc, tuple(files), notes, prov, plausibility, _compression_estimate(x, y),
                      coarsen=coarsen, coarsen_skip=skip)


#: Why an experiment on a mesh file has no discretisation estimate.
_MESH_FILE_SKIP = "the specimen is a mesh file: difftissue cannot build a coarser version of it (give size and cells to get the estimate)"


def _halved(counts) -> tuple[tuple[int, ...], list[float]]:
    """Half the cells in each direction (at least 1) and each direction's fine / coarse ratio [-]."""
    coarse = tuple(max(1, int(n) // 2) for n in counts)
    return coarse, [n / c for n, c in zip(counts, coarse)]


def _size_ratio(ratios) -> float:
    """Coarse / fine cell size [-] from per-direction ratios: the geometric mean (h ~ cell volume^(1/3))."""
    return float(np.prod(ratios) ** (1.0 / len(ratios)))


def _coarse_block(size, cells, **kw):
    """``(builder, None)`` of a block of about half the cells (``builder() -> (mesh, info)``), or
    ``(None, reason)`` when every direction already has one cell."""
    coarse, ratios = _halved(cells)
    if coarse == tuple(cells):
        return None, f"the specimen has one cell in each direction ({list(cells)}): there is no coarser mesh"
    info = {"fine_cells": list(cells), "coarse_cells": list(coarse), "refinement_ratio": _size_ratio(ratios)}
    return (lambda: (block(size, coarse, **kw), info)), None


def _coarse_cylinder(dia, hei, nr, nh):
    """Like :func:`_coarse_block` for a cylinder of ``nr`` radial and ``nh`` axial cells."""
    (cr, ch), (rr, rh) = _halved((nr, nh))
    if (cr, ch) == (nr, nh):
        return None, "the cylinder has one radial and one axial cell: there is no coarser mesh"
    info = {"fine_cells": {"radial": nr, "height": nh}, "coarse_cells": {"radial": cr, "height": ch}, "refinement_ratio": _size_ratio((rr, rr, rh))}
    return (lambda: (cylinder(dia, hei, cr, ch), info)), None


def _mesh_file(spec: dict, p: str, base_dir: Path):
    for k in spec:
        if k not in ("mesh", "length_unit", "reorient"):
            _fail(_join(p, k), "not used with 'mesh' (a mesh file takes only length_unit and reorient)")
    unit = _unit_of(spec, p, _MESH_UNITS)
    file = _resolve(base_dir, spec["mesh"], _join(p, "mesh"))
    reorient = _bool(spec.get("reorient", False), _join(p, "reorient"))
    try:
        return read_mesh(file, length_unit=unit[0], reorient=reorient), file
    except DifftissueError as err:
        _reraise(_join(p, "mesh"), err)


#: ``specimen.geometry`` of a simulated indentation: the 2-D meridian model of a cylinder
#: (:class:`~difftissue.scenarios.AxisymmetricIndentation`) or a 3-D tetrahedral block.
SPECIMEN_GEOMETRIES = ("axisymmetric", "3d")
_AXISYMMETRIC_SPECIMEN_KEYS = ("geometry", "cells_per_contact_radius", "thickness", "length_unit")


def _axisymmetric_obstacles(kw: Mapping, model: str, rollers, material, fitted) -> list[str]:
    """Why this indentation cannot be simulated axisymmetrically (empty: it can)."""
    why = []
    if kw["indenter"] not in ("sphere", "cone"):
        why.append(f"a {kw['indenter']} indenter (axisymmetric: a sphere or a cone)")
    if model not in AXISYMMETRIC_MODELS:
        why.append(f"model {model!r} (axisymmetric: {' or '.join(AXISYMMETRIC_MODELS)}; a springs_volume lattice is 3-D only)")
    if rollers:
        why.append("rollers (boundary conditions of a 3-D block)")
    if kw.get("surface") == "boundary":
        why.append("an indenter placed on a curved surface (surface = \"boundary\")")
    stretch = [f for f in ("pre_stretch", "pre_stretch_y") if material is not None and getattr(material, f, None) not in (None, 1.0)]
    stretch += [f for f in ("pre_stretch", "pre_stretch_y") if f in fitted and f not in stretch]
    if stretch:
        why.append(f"a pre-stretch ({', '.join(stretch)} set or fitted; the axisymmetric model has no pre-tension)")
    return why


def _indentation(e, path, name, base_dir, *, material=None, fitted=()) -> Experiment:
    curve, file, notes, depth, force, sigma, unit, prov = _force_depth(e, path, base_dir, "indentation")
    kw = _indenter(e, path, curve, "indentation")
    model = _model(e, path, "springs_volume")
    base = _choice(e.get("base", "bonded"), _join(path, "base"), ("bonded", "sliding"))
    rollers = _rollers(e["rollers"], _join(path, "rollers")) if "rollers" in e else ()
    penalty = _positive(e["penalty"], _join(path, "penalty")) if "penalty" in e else 100.0
    if "penalty" in e and kw["indenter"] == "flat_punch":
        _fail(_join(path, "penalty"), "not used by a flat punch (its displacement is prescribed)")
    options = _solver_options(e, path)
    p = _join(path, "specimen")
    spec = _table(e["specimen"], p, ("geometry", "cells_per_contact_radius", "thickness", "shape", "size", "cells", "symmetry", "refine", "core",
                                      "mesh", "length_unit", "reorient")) if "specimen" in e else None
    files = [file]
    symmetry = "none"
    coarse_mesh, skip = None, _MESH_FILE_SKIP
    auto, thin = None, None
    # geometry: axisymmetric (explicit, or the default for an automatic specimen it can simulate) or 3-D
    geometry = _choice(spec["geometry"], _join(p, "geometry"), SPECIMEN_GEOMETRIES) if spec is not None and "geometry" in spec else None
    automatic = spec is None or set(spec) <= set(_AXISYMMETRIC_SPECIMEN_KEYS)
    obstacles = _axisymmetric_obstacles(kw, model, rollers, material, fitted)
    if geometry == "axisymmetric":
        for k in spec:
            if k not in _AXISYMMETRIC_SPECIMEN_KEYS:
                _fail(_join(p, k), "not used with geometry = \"axisymmetric\" (the cylinder's meridian mesh is chosen from the indenter and "
                      "the deepest point; cells_per_contact_radius sets its resolution, thickness its height)")
        if obstacles:
            _fail(_join(p, "geometry"), "\"axisymmetric\" cannot simulate this experiment: " + "; ".join(obstacles)
                  + ". Use geometry = \"3d\" (or leave the specimen out)")
    elif geometry is None and automatic and not obstacles:
        geometry = "axisymmetric"
    else:
        geometry = "3d"
    cells_per_a = None
    if spec is not None and "cells_per_contact_radius" in spec:
        if not automatic:
            _fail(_join(p, "cells_per_contact_radius"), "sets the automatic specimen's resolution: not used with size, cells or a mesh file")
        cells_per_a = _number(spec["cells_per_contact_radius"], _join(p, "cells_per_contact_radius"), check=lambda v: v >= 1,
                              rule="a number of cells >= 1")
    thickness = None
    if spec is not None and "thickness" in spec:
        if not automatic:
            _fail(_join(p, "thickness"), "sets the automatic specimen's height: not used with size, cells or a mesh file (the block's height is size[2])")
        thickness = _length(spec["thickness"], _join(p, "thickness"), _unit_of(spec, p))
    if geometry == "axisymmetric":
        return _axisymmetric_indentation(e, path, name, kw, model, base, penalty, options, cells_per_a, thickness, curve, file, notes, depth, force,
                                         sigma, prov)
    if automatic:
        # no specimen: the block the resolution rule chooses from the indenter and the deepest point
        if kw["indenter"] == "flat_punch":
            _fail(p, "missing (required for a flat punch): e.g. { size = [2e-3, 2e-3, 1e-3], cells = [6, 6, 4], symmetry = \"quarter\" } "
                  "or { mesh = \"specimen.vtu\", length_unit = \"mm\" } (a block is chosen automatically for a sphere or a cone only)")
        if model in LATTICE_MODELS:
            _fail(p, f"missing (required): with model {model} no block is chosen automatically (the automatic specimen grades its cells, which the lattice refuses); "
                  "set model = \"fem_linear\", \"fem_neo_hookean\" or \"stable_neo_hookean\", or give the specimen "
                  "(e.g. { size = [2e-3, 2e-3, 1e-3], cells = [6, 6, 4], symmetry = \"quarter\" })")
        try:
            auto = indentation_specimen_for(kw["indenter"], radius=kw.get("radius"), half_angle=kw.get("half_angle"),
                                            max_depth=float(depth.max()), model=model, thickness=thickness,
                                            **({} if cells_per_a is None else {"cells_per_contact_radius": cells_per_a}))
            mesh = auto.block()
        except DifftissueError as err:
            _reraise(_specimen_error_path(p, thickness, err), err)
        thin = thin_specimen_warning(auto, _join(p, "thickness"), stacklevel=4)
        symmetry = auto.symmetry
        coarse_mesh, skip = _coarse_auto_specimen(auto)
        notes = (*notes, _auto_specimen_note(auto) + (f" (3-D, not axisymmetric: {'; '.join(obstacles)})" if obstacles else ""))
    elif "mesh" in spec:
        mesh, mfile = _mesh_file({k: v for k, v in spec.items() if k != "geometry"}, p, base_dir)
        files.append(mfile)
    else:
        _choice(spec.get("shape", "block"), _join(p, "shape"), ("block",))
        sunit = _unit_of(spec, p)
        if "size" not in spec:
            _fail(_join(p, "size"), f"missing (required): [Lx, Ly, H] of the whole specimen in {sunit[0]}")
        size = _lengths(spec["size"], _join(p, "size"), sunit)
        cells = _counts(spec.get("cells", [6, 6, 4]), _join(p, "cells"))
        symmetry = _choice(spec.get("symmetry", "quarter"), _join(p, "symmetry"), ("quarter", "none"))
        refine = _length(spec["refine"], _join(p, "refine"), sunit) if "refine" in spec else None
        if refine is not None and model in LATTICE_MODELS:
            _fail(_join(p, "refine"), "graded cells are not cubes: use model 'fem_linear', 'fem_neo_hookean' or 'stable_neo_hookean' with refine")
        core = _length(spec["core"], _join(p, "core"), sunit) if "core" in spec else None
        if core is not None:
            if refine is None:
                _fail(_join(p, "core"), "needs refine (the size of the uniform cells kept within core of the axis and the surface)")
            reach = min(size[0] / 2, size[1] / 2, size[2])
            if not core < reach:
                _fail(_join(p, "core"), f"must be smaller than the half-width and the height of the specimen ({reach / sunit[1]:.6g} {sunit[0]}), got {spec['core']!r}")
            if core < refine:
                _fail(_join(p, "core"), f"must be at least one cell of refine ({refine / sunit[1]:.6g} {sunit[0]}), got {spec['core']!r}")
        try:
            mesh = indentation_block(size, cells, symmetry=symmetry, refine=refine, core=core)
        except DifftissueError as err:
            _reraise(p, err)
        coarse_mesh, skip = _coarse_indentation_block(size, cells, symmetry, refine, core)
        if depth.max() >= size[2]:
            _fail(_join(path, "max_depth"), f"the deepest point ({depth.max():.3g} m) reaches the specimen's height ({size[2]:.3g} m)")
    def make(depth, force, sigma, mesh=mesh):
        return Indentation(mesh, depth, force, model=model, base=base, symmetry=symmetry, rollers=rollers, penalty=penalty, sigma=sigma,
                           options=options, name=name, **kw)

    def make_coarse(depth, force, sigma):
        m, info = coarse_mesh()
        return make(depth, force, sigma, mesh=m), info

    return _resolved_indentation(e, path, name, model, kw, make, None if coarse_mesh is None else make_coarse, skip, curve, files, notes,
                                 depth, force, sigma, prov, extra_warnings=() if thin is None else (thin,))


def _specimen_error_path(p: str, thickness, err: Exception) -> str:
    """The key an automatic specimen's error belongs to: ``specimen.thickness`` for the
    thickness checks of :func:`~difftissue.scenarios.axisymmetric_specimen_for` and
    :func:`~difftissue.scenarios.indentation_specimen_for` (their messages start with
    "thickness"), else ``specimen``."""
    return _join(p, "thickness") if thickness is not None and str(err).startswith("thickness") else p


def _axisymmetric_indentation(e, path, name, kw, model, base, penalty, options, cells_per_a, thickness, curve, file, notes, depth, force, sigma,
                              prov) -> Experiment:
    """A sphere or cone indentation simulated in the meridian plane of a cylinder
    (:class:`~difftissue.scenarios.AxisymmetricIndentation`) on the automatic specimen
    (:func:`~difftissue.scenarios.axisymmetric_specimen_for`, ``thickness`` [m] or a
    half-space); its discretisation check evaluates the same rule on two coarser meshes, every
    cell times sqrt(2) and times 2 (``refined(1 / sqrt(2))``, ``refined(0.5)``), and takes the
    order of convergence they show, at most :data:`AXISYMMETRIC_MAX_ORDER`, or no estimate
    where they do not converge (:func:`~difftissue.fit.discretisation_estimate`)."""
    p = _join(path, "specimen")
    ind = {"indenter": kw["indenter"], "radius": kw.get("radius"), "half_angle": kw.get("half_angle")}
    try:
        auto = axisymmetric_specimen_for(kw["indenter"], radius=kw.get("radius"), half_angle=kw.get("half_angle"), max_depth=float(depth.max()),
                                         thickness=thickness, **({} if cells_per_a is None else {"cells_per_contact_radius": cells_per_a}))
    except DifftissueError as err:
        _reraise(_specimen_error_path(p, thickness, err), err)
    thin = thin_specimen_warning(auto, _join(p, "thickness"), stacklevel=4)
    notes = (*notes, _axisymmetric_note(auto))

    def make(depth, force, sigma, specimen=auto):
        return AxisymmetricIndentation(depth, force, model=model, specimen=specimen, base=base, penalty=penalty, sigma=sigma, options=options,
                                       name=name, **ind)

    def make_coarse(depth, force, sigma):
        coarse, coarser = auto.refined(1.0 / AXISYMMETRIC_CHECK_RATIO), auto.refined(0.5)

        def third():
            return make(depth, force, sigma, specimen=coarser), axisymmetric_resolution(coarser)

        info = {"fine_cells": axisymmetric_resolution(auto), "coarse_cells": axisymmetric_resolution(coarse),
                "refinement_ratio": coarse.first / auto.first, "coarser": third, "max_order": AXISYMMETRIC_MAX_ORDER, "specimen": auto.record()}
        return make(depth, force, sigma, specimen=coarse), info

    return _resolved_indentation(e, path, name, model, kw, make, make_coarse, None, curve, [file], notes, depth, force, sigma, prov, stacklevel=5,
                                 extra_warnings=() if thin is None else (thin,))


#: Cell size ratio between the levels of the axisymmetric discretisation check [-]: the fit's
#: mesh, every cell times sqrt(2), times 2 (three levels: the order is observed, not assumed).
AXISYMMETRIC_CHECK_RATIO = math.sqrt(2.0)
#: Largest order of convergence the axisymmetric check uses [-]: linear triangles converge in
#: force at second order at best (the sphere's observed 1.93 over 4 / 8 / 16 / 32 cells); a
#: faster order seen on the check's levels (3.2 for the sphere at 4 / 5.66 / 8) is capped.
AXISYMMETRIC_MAX_ORDER = 2.0


def axisymmetric_resolution(specimen) -> str:
    """``"axisymmetric, N cells per contact radius"`` of an :class:`~difftissue.scenarios.AxisymmetricSpecimen`."""
    return f"axisymmetric, {specimen.cells_per_contact_radius:g} cells per contact radius"


def _axisymmetric_note(auto) -> str:
    """The console note of the automatic axisymmetric specimen, with the convergence study's
    force error where it has one for this indenter and resolution."""
    m = auto.cells_per_contact_radius
    tabulated = m == AXISYMMETRIC_CELLS_PER_CONTACT_RADIUS  # the resolution of the convergence study's numbers below
    if auto.indenter == "sphere" and tabulated:
        err = ("estimated discretisation error of the force +0.6 %, of a fitted E about -0.6 % (sphere convergence study, against "
               "the Richardson-extrapolated force)")
    elif auto.indenter == "cone" and tabulated:
        err = ("estimated discretisation error of a fitted E about -0.9 % (70 deg cone convergence study: the force at 8 cells is +0.8 % "
               "above the mesh-converged model's, which is itself about 1.7 % below Sneddon's: finite deformation under the cone, not the mesh)")
    else:
        err = f"no tabulated discretisation error at {m:g} cells per contact radius"
    height = f"height {auto.height:.4g} m (the specimen's thickness)" if auto.thickness_given else f"height {auto.height:.4g} m"
    return (f"specimen chosen automatically (no 'specimen' given): axisymmetric, {m:g} cells per contact radius (the meridian plane of a "
            f"cylinder of radius {auto.radius:.4g} m and {height}; {auto.first:.4g} m cells within {auto.core:.4g} m of the axis and the "
            f"surface, contact radius {auto.contact_radius:.4g} m at the deepest point, growing by at most {auto.growth:g} beyond); "
            f"{err}; the discretisation check after the fit estimates it for this fit")


def _resolved_indentation(e, path, name, model, kw, make, make_coarse, skip, curve, files, notes, depth, force, sigma, prov, stacklevel=4,
                          extra_warnings: tuple[str, ...] = ()) -> Experiment:
    """The indentation scenario ``make(depth, force, sigma)`` with its resolution check
    (``min_cells_per_contact_radius``, ``under_resolved``: warn or drop the depths) and its
    coarser version ``make_coarse(depth, force, sigma) -> (scenario, info)`` (None: ``skip`` says why)."""
    min_cells = _positive(e["min_cells_per_contact_radius"], _join(path, "min_cells_per_contact_radius")) if "min_cells_per_contact_radius" in e \
        else MIN_CELLS_PER_CONTACT_RADIUS
    under = _choice(e.get("under_resolved", "warn"), _join(path, "under_resolved"), ("warn", "drop"))
    try:
        sc = make(depth, force, sigma)
        res = sc.resolution(min_cells)
    except DifftissueError as err:
        _reraise(path, err)
    resolution_warnings: tuple[str, ...] = ()
    res_record = {**res.record(), "under_resolved": under}
    for f in res_record["flagged"]:
        f["row"] = int(prov["used"][f["index"]])  # the data file's row (its name: provenance row_names)
    if res.flagged.size:
        if under == "warn":
            resolution_warnings = (res.warn(path, stacklevel=stacklevel),)
        else:
            depth, force, sigma, prov, notes = _drop_under_resolved(res, path, depth, force, sigma, prov, notes)
            try:
                sc = make(depth, force, sigma)
            except DifftissueError as err:
                _reraise(path, err)
    prov = {**prov, "resolution": res_record}
    coarsen = None
    if make_coarse is not None:
        def coarsen():
            return make_coarse(depth, force, sigma)
    return Experiment(name, "indentation", model, sc, tuple(files), notes, prov, _plausibility(path, depth, force, kw, curve) + extra_warnings + resolution_warnings,
                      _indentation_estimate(depth, force, sigma, kw), coarsen=coarsen, coarsen_skip=skip)


def _drop_under_resolved(res, path: str, depth, force, sigma, prov: dict, notes: tuple):
    """``under_resolved = "drop"``: the depths of ``res`` (:class:`~difftissue.scenarios.IndentationResolution`)
    below its threshold left out of ``depth``, ``force`` and ``sigma`` (an array per depth or
    one value), recorded as a "left out" step of the provenance and in its note. Returns
    ``depth, force, sigma, provenance, notes``."""
    keep = res.keep
    if not keep.any():
        _fail(_join(path, "under_resolved"), f"every depth has a contact radius of less than {res.min_cells_per_contact_radius:g} mesh cells "
              f"(at most {float(res.cells_per_contact_radius.max()):.3g}, cells of {res.cell_size:.4g} m under the indenter): "
              "nothing is left to fit; refine the specimen under the indenter")
    old_note = _provenance_note(path, prov)
    used = [prov["used"][i] for i in range(len(prov["used"])) if keep[i]]
    why = (f"a contact radius of less than {res.min_cells_per_contact_radius:g} mesh cells (cells of {res.cell_size:.4g} m under the indenter; "
           "under_resolved = \"drop\")")
    steps = [*prov["steps"], {"action": "left out", "rows": [int(prov["used"][i]) for i in res.flagged], "reason": why}]
    prov = {**prov, "rows_used": len(used), "used": used, "steps": steps}
    notes = tuple(_provenance_note(path, prov) if n == old_note else n for n in notes)
    sig = np.asarray(sigma)
    if sig.ndim and sig.size == keep.size:
        sigma = sig[keep]
    return depth[keep], force[keep], sigma, prov, notes


def _auto_specimen_note(auto) -> str:
    """The console note of a specimen chosen by :func:`~difftissue.scenarios.indentation_specimen_for`."""
    return (f"specimen chosen automatically (no 'specimen' given): a quarter of a {auto.size[0]:.4g} x {auto.size[1]:.4g} x {auto.size[2]:.4g} m "
            f"block, cells {list(auto.cells)}, {auto.refine:.4g} m cells ({auto.cells_per_contact_radius:g} per contact radius "
            f"{auto.contact_radius:.4g} m at the deepest point) within {auto.core:.4g} m of the axis and the surface; "
            + (f"estimated discretisation error of the force {100 * auto.force_error:+.2g} %, of a fitted E about "
               f"{-100 * auto.force_error / (1 + auto.force_error):+.2g} % (linear tetrahedra, from the convergence study)"
               if auto.force_error is not None else "no tabulated discretisation error for this indenter (see the discretisation check)"))


def _coarse_auto_specimen(auto):
    """``(builder, None)`` of the discretisation check's coarser block for an automatically
    chosen specimen: the same rule at half the cells per contact radius
    (:meth:`~difftissue.scenarios.IndentationSpecimen.coarser`: same size, core and grading
    rule, first cells doubled, so the cell size ratio is exactly 2), or ``(None, reason)``.
    Halving every cell count instead also coarsens the graded far field beyond the rule's
    growth, which made the first-order estimate over-correct a sphere fit's E by +2.4 %
    (docs/dev/indentation-resolution.md)."""
    try:
        c = auto.coarser(2.0)
    except DifftissueError as err:
        return None, f"no coarser automatic specimen: {err}"
    info = {"fine_cells": list(auto.cells), "coarse_cells": list(c.cells), "refinement_ratio": c.refine / auto.refine, "specimen": auto.record()}
    return (lambda: (c.block(), info)), None


def _coarse_indentation_block(size, cells, symmetry: str, refine, core=None):
    """Like :func:`_coarse_block` for :func:`~difftissue.scenarios.indentation_block`: half the
    cells, the same size and symmetry; a graded block doubles its first cell ``refine`` [m]
    (keeping the uniform ``core`` [m], which then holds half as many cells)."""
    coarse, ratios = _halved(cells)
    if coarse == tuple(cells):
        return None, f"the specimen has one cell in each direction ({list(cells)}): there is no coarser mesh"
    info = {"fine_cells": list(cells), "coarse_cells": list(coarse), "refinement_ratio": _size_ratio(ratios)}
    r2 = None if refine is None else 2.0 * refine
    if core is not None:
        try:
            indentation_block(size, coarse, symmetry=symmetry, refine=r2, core=core)
        except DifftissueError as err:
            return None, f"the coarser block (cells {list(coarse)}, refine {r2:.6g} m, core {core:.6g} m) cannot be built: {err}"
    return (lambda: (indentation_block(size, coarse, symmetry=symmetry, refine=r2, core=core), info)), None


def _node_set_spec(value, path: str):
    if isinstance(value, str):
        return _string(value, path)
    if isinstance(value, Mapping):
        try:
            selector_from_dict(dict(value))
        except DifftissueError as err:
            _reraise(path, err)
        except (TypeError, KeyError, ValueError) as err:
            _fail(path, f"not a valid selector: {err}")
        return dict(value)
    _fail(path, f"must be the name of a point-data node set or a selector table, got {_show(value)}")


def _components(value, path: str) -> str:
    if not isinstance(value, str) or not value or any(c not in "xyz" for c in value) or len(set(value)) != len(value):
        _fail(path, f"must be letters from 'xyz' (e.g. \"z\" or \"xyz\"), got {_show(value)}")
    return value


def _rollers(value, path: str) -> tuple:
    """``rollers``: a list of face names (``"x-min"``: the face's normal component held) or
    tables ``{ set = selector-or-mask-name, components = "x" }``; returns
    :class:`~difftissue.boundary.Roller` objects."""
    if not isinstance(value, list):
        _fail(path, f"must be a list of faces such as [\"x-min\", \"y-min\"] or tables {{ set = ..., components = \"x\" }}, got {_show(value)}")
    out = []
    for i, entry in enumerate(value):
        q = _join(path, i)
        if isinstance(entry, str):
            _choice(entry, q, tuple(ROLLER_FACES))
            out.append(Roller(entry))
            continue
        t = _table(entry, q, ("set", "components"), ("set", "components"))
        nodes = _node_set_spec(t["set"], _join(q, "set"))
        comps = _components(t["components"], _join(q, "components"))
        if len(comps) == 3:
            _fail(_join(q, "components"), "a roller holding x, y and z is a clamp: leave at least one component free")
        out.append(Roller(nodes, comps))
    return tuple(out)


def _fem_field(e, path, name, base_dir) -> Experiment:
    p = _join(path, "prescribed")
    if "prescribed" not in e:
        _fail(p, "missing (required): the node sets whose displacement the reference prescribed, e.g. [{ set = \"bottom\" }, { set = \"punch\", components = \"z\" }]")
    pres = e["prescribed"]
    if not isinstance(pres, list) or not pres:
        _fail(p, f"must be a non-empty list of tables {{ set = ..., components = \"xyz\" }}, got {_show(pres)}")
    prescribed = []
    for i, entry in enumerate(pres):
        q = _join(p, i)
        t = _table(entry, q, ("set", "components"), ("set",))
        prescribed.append({"set": _node_set_spec(t["set"], _join(q, "set")), "components": _components(t.get("components", "xyz"), _join(q, "components"))})
    observe = _node_set_spec(e["observe"], _join(path, "observe")) if "observe" in e else None
    reaction = None
    if "reaction" in e:
        q = _join(path, "reaction")
        t = _table(e["reaction"], q, ("set", "components", "force", "field"), ("set",))
        comps = _components(t.get("components", "z"), _join(q, "components"))
        reaction = {"set": _node_set_spec(t["set"], _join(q, "set")), "components": comps}
        if ("force" in t) == ("field" in t):
            _fail(q, "give exactly one of 'force' (total force in N, one value per component) or 'field' (a nodal reaction point field of the file)")
        if "force" in t:
            f = t["force"]
            f = [f] if _is_number(f) else f
            if not isinstance(f, list) or len(f) != len(comps):
                _fail(_join(q, "force"), f"must be {len(comps)} number(s) in N (one per component {comps!r}), got {_show(t['force'])}")
            reaction["force"] = [_number(v, _join(_join(q, "force"), j), what="a force in N") for j, v in enumerate(f)]
        else:
            reaction["field"] = _string(t["field"], _join(q, "field"))
    ds = _positive(e["displacement_sigma"], _join(path, "displacement_sigma"), "m") if "displacement_sigma" in e else None
    fs = _positive(e["force_sigma"], _join(path, "force_sigma"), "N") if "force_sigma" in e else None
    if fs is not None and reaction is None:
        _fail(_join(path, "force_sigma"), "needs a 'reaction' to compare")
    model = _model(e, path, "fem_linear")
    options = _solver_options(e, path)
    mode = _choice(e.get("reference_mesh", "interpolate" if "specimen" in e else "own"), _join(path, "reference_mesh"), ("own", "interpolate"))
    if mode == "interpolate" and "specimen" not in e:
        _fail(_join(path, "specimen"), "missing (required with reference_mesh = \"interpolate\"): the model's own mesh, e.g. { cells = [8, 8, 4] } "
              "(a block spanning the reference's bounding box) or { mesh = \"model.vtu\", length_unit = \"mm\" }")
    if mode == "own":
        for k in ("specimen", "tolerance"):
            if k in e:
                _fail(_join(path, k), "not used with reference_mesh = \"own\" (the model runs on the reference's mesh)")
    tolerance = _number(e["tolerance"], _join(path, "tolerance"), what="a distance >= 0 in m", check=lambda v: v >= 0) if "tolerance" in e else None
    result, file, notes = _load_data(e, path, "fem_field", base_dir)
    if mode == "own":
        if result.mesh is None:
            _fail(_join(path, "reference_mesh"), f"the reference holds {sorted(result.cells)} cells, not linear tetrahedra the model can run on: "
                  "give a 'specimen' (the model's own mesh) and the reference is interpolated onto it")
        try:
            sc = FEMField(result.mesh, result.displacement, prescribed=prescribed, model=model, observe=observe, reaction=reaction, displacement_sigma=ds, force_sigma=fs, options=options, name=name)
        except DifftissueError as err:
            _reraise(path, err)
        return Experiment(name, "fem_field", model, sc, (file,), notes,
                          coarsen_skip="the displacements are observed on the nodes of the given mesh: a coarser mesh has no such nodes")
    specimen, files, coarse_mesh, skip = _fem_field_specimen(e, path, base_dir, result)
    kw = dict(prescribed=prescribed, model=model, observe=observe, reaction=reaction, displacement_sigma=ds, force_sigma=fs, options=options, name=name, tolerance=tolerance)
    try:
        sc = FEMField(result, result.displacement, specimen=specimen, **kw)
    except DifftissueError as err:
        _reraise(path, err)
    coarsen = None
    if coarse_mesh is not None:
        def coarsen():
            m, info = coarse_mesh()
            return FEMField(result, result.displacement, specimen=m, **kw), info
    return Experiment(name, "fem_field", model, sc, (file, *files), notes, coarsen=coarsen, coarsen_skip=skip)


def _fem_field_specimen(e, path, base_dir, result):
    """The model's own mesh of an interpolated fem_field: ``(mesh, extra files, coarse builder,
    skip reason)``. A block defaults to the reference's bounding box."""
    p = _join(path, "specimen")
    spec = _table(e["specimen"], p, ("shape", "size", "origin", "cells", "mesh", "length_unit", "reorient"))
    if "mesh" in spec:
        mesh, mfile = _mesh_file(spec, p, base_dir)
        return mesh, (mfile,), None, _MESH_FILE_SKIP
    _choice(spec.get("shape", "block"), _join(p, "shape"), ("block",))
    unit = _unit_of(spec, p)
    if "cells" not in spec:
        _fail(_join(p, "cells"), "missing (required): the model's cells [nx, ny, nz] (the block spans the reference's bounding box unless size and origin are given)")
    cells = _counts(spec["cells"], _join(p, "cells"))
    lo, hi = result.points.min(axis=0), result.points.max(axis=0)
    size = _lengths(spec["size"], _join(p, "size"), unit) if "size" in spec else tuple(float(v) for v in hi - lo)
    if "origin" in spec:
        o = spec["origin"]
        if not isinstance(o, list) or len(o) != 3:
            _fail(_join(p, "origin"), f"must be 3 coordinates in {unit[0]} (a list), got {_show(o)}")
        origin = tuple(_number(v, _join(_join(p, "origin"), i), what=f"a coordinate in {unit[0]}") * unit[1] for i, v in enumerate(o))
    else:
        origin = tuple(float(v) for v in lo)
    if min(size) <= 0:
        _fail(_join(p, "size"), f"the reference is flat (bounding box {size} m): give size")
    try:
        mesh = block(size, cells, origin=origin)
    except DifftissueError as err:
        _reraise(p, err)
    coarse_mesh, skip = _coarse_block(size, cells, origin=origin)
    return mesh, (), coarse_mesh, skip


# ============================================================================ incision
_INCISION_QUANTITIES = ("surface_width", "max_width", "width_over_length")
_LAYER_KEYS = ("name", "thickness", "cells", "grading", "fitted") + tuple(FIELDS)


def _incision_data(e: Mapping, path: str, base_dir: Path, unit: tuple[str, float]):
    """``data`` of an incision: ``{ quantity, value }``, ``{ quantity = "surface_width",
    positions, widths }`` (inline, lengths in ``length_unit``) or ``{ format = "table", path }``
    (CSV with header ``position,width``)."""
    p = _join(path, "data")
    d = e["data"]
    if not isinstance(d, Mapping):
        _fail(p, f"must be a table such as {{ quantity = \"max_width\", value = 0.8 }}, got {_show(d)}")
    fmt = _choice(d.get("format", "inline"), _join(p, "format"), _DATA_FORMATS["incision"])
    files: tuple[Path, ...] = ()
    if fmt == "table":
        t = _table(d, p, ("format", "path", "quantity"), ("path",))
        q = _choice(t.get("quantity", "surface_width"), _join(p, "quantity"), ("surface_width",))
        file = _resolve(base_dir, t["path"], _join(p, "path"))
        try:
            arr = np.genfromtxt(file, delimiter=",", names=True)
        except (ValueError, OSError) as err:
            _fail(_join(p, "path"), f"cannot read {file.name} as CSV with a header line 'position,width': {err}")
        names = arr.dtype.names or ()
        if "position" not in names or "width" not in names:
            _fail(_join(p, "path"), f"{file.name} needs the columns 'position' and 'width' (in {unit[0]}), found {list(names)}")
        pos, w = np.atleast_1d(arr["position"]) * unit[1], np.atleast_1d(arr["width"]) * unit[1]
        if pos.size < 1 or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(w))):
            _fail(_join(p, "path"), f"{file.name}: positions and widths must be finite numbers")
        return q, pos, w, (file,)
    q = _choice(d.get("quantity"), _join(p, "quantity"), _INCISION_QUANTITIES) if "quantity" in d else _fail(_join(p, "quantity"), f"missing (required); one of {', '.join(_INCISION_QUANTITIES)}")
    if q == "surface_width":
        t = _table(d, p, ("format", "quantity", "positions", "widths"), ("positions", "widths"))
        pos, w = t["positions"], t["widths"]
        if not isinstance(pos, list) or not isinstance(w, list) or not pos or len(pos) != len(w):
            _fail(_join(p, "widths"), f"positions and widths must be two lists of the same non-zero length (in {unit[0]})")
        pos = np.array([_number(v, _join(_join(p, "positions"), i), what=f"a length in {unit[0]}") for i, v in enumerate(pos)]) * unit[1]
        w = np.array([_number(v, _join(_join(p, "widths"), i), what=f"a width in {unit[0]}", check=lambda x: x >= 0, rule=f"a width >= 0 in {unit[0]}") for i, v in enumerate(w)]) * unit[1]
        return q, pos, w, files
    t = _table(d, p, ("format", "quantity", "value"), ("value",))
    if q == "max_width":
        v = _length(t["value"], _join(p, "value"), unit)
    else:
        v = _number(t["value"], _join(p, "value"), what="a positive ratio w/l", check=lambda x: x > 0)
    return q, None, np.array([v]), files


def _incision(e, path, name, base_dir, material) -> Experiment:
    unit = _unit_of(e, path)
    model = _model(e, path, "stable_neo_hookean")
    quantity, positions, observed, files = _incision_data(e, path, base_dir, unit)
    unit_y = "1" if quantity == "width_over_length" else "m"
    sigma = _sigma(e.get("sigma", "rms"), _join(path, "sigma"), observed, unit_y)
    # specimen: layers (the fitted ones take [material]) or a mesh file (every region fitted)
    p = _join(path, "specimen")
    if "specimen" not in e:
        _fail(p, "missing (required): e.g. { size = [12, 12], cells = [12, 12], layers = [{ name = \"dermis\", thickness = 2, cells = 2, fitted = true }, ...] }")
    spec = _table(e["specimen"], p, ("size", "cells", "layers", "refine", "refine_at", "core", "mesh", "length_unit", "reorient"))
    files = list(files)
    fitted = None
    if "mesh" in spec:
        for k in ("size", "cells", "layers", "refine", "refine_at", "core"):
            if k in spec:
                _fail(_join(p, k), "not used with 'mesh' (every region of a mesh file takes [material])")
        mesh, mfile = _mesh_file(spec, p, base_dir)
        files.append(mfile)
        specimen = Specimen(mesh, (material,) * len(mesh.region_names))
    else:
        sunit = _unit_of(spec, p) if "length_unit" in spec else unit
        for k in ("size", "layers"):
            if k not in spec:
                _fail(_join(p, k), "missing (required)")
        size = _lengths(spec["size"], _join(p, "size"), sunit, n=2)
        cells = _counts(spec.get("cells", [12, 12]), _join(p, "cells"), n=2)
        lp = _join(p, "layers")
        if not isinstance(spec["layers"], list) or not spec["layers"]:
            _fail(lp, "must be a non-empty list of tables { name, thickness, cells, fitted | material fields }")
        layers, fitted, grading = [], [], {}
        for i, lay in enumerate(spec["layers"]):
            q = _join(lp, i)
            t = _table(lay, q, _LAYER_KEYS, ("name", "thickness"))
            lname = _string(t["name"], _join(q, "name"))
            thick = _length(t["thickness"], _join(q, "thickness"), sunit)
            nc = _integer(t.get("cells", 1), _join(q, "cells"), minimum=1)
            if "grading" in t:
                grading[lname] = _positive(t["grading"], _join(q, "grading"))
                if nc < 2:
                    _fail(_join(q, "grading"), f"needs at least two cells through the layer (cells = {nc})")
            is_fitted = _bool(t.get("fitted", False), _join(q, "fitted"))
            fields = {k: t[k] for k in FIELDS if k in t}
            if is_fitted:
                if fields:
                    _fail(_join(q, sorted(fields)[0]), "a fitted layer takes its material from [material]; remove the field or set fitted = false")
                mat = material
                fitted.append(lname)
            else:
                for k in ("youngs_modulus", "poisson_ratio"):
                    if k not in t:
                        _fail(_join(q, k), "missing (required for a layer that is not fitted)")
                mat = Material(**_material_values(fields, q))
            layers.append((lname, thick, mat, nc))
        if not fitted:
            _fail(lp, "no layer has fitted = true: the [material] must apply to at least one layer")
        lateral = {}
        if "refine" in spec:
            lateral["refine"] = _length(spec["refine"], _join(p, "refine"), sunit)
            if "refine_at" in spec:
                at = spec["refine_at"]
                if not isinstance(at, list) or len(at) != 2:
                    _fail(_join(p, "refine_at"), f"must be a point [x, y] on the top surface in {sunit[0]}, got {_show(at)}")
                lateral["refine_at"] = tuple(_number(v, _join(_join(p, "refine_at"), i), what=f"a coordinate in {sunit[0]}") * sunit[1] for i, v in enumerate(at))
                if not all(0 <= a <= s for a, s in zip(lateral["refine_at"], size)):
                    _fail(_join(p, "refine_at"), f"must lie on the top surface, within [0, {size[0] / sunit[1]:g}] x [0, {size[1] / sunit[1]:g}] {sunit[0]}")
            if "core" in spec:
                lateral["core"] = _lengths(spec["core"], _join(p, "core"), sunit, n=2)
        else:
            for k in ("refine_at", "core"):
                if k in spec:
                    _fail(_join(p, k), "needs refine (the lateral cell size at the refinement lines)")
        try:
            specimen = layered_skin(layers, size=size, resolution=cells, grading=grading or None, **lateral)
        except DifftissueError as err:
            _reraise(p, err)
        skin = {"size": size, "cells": cells, "layers": layers, "grading": grading, "refined": "refine" in spec}
    # the cut
    cp = _join(path, "cut")
    if "cut" not in e:
        _fail(cp, "missing (required): e.g. { path = [[3, 6], [9, 6]], depth = 2 } (lengths in length_unit)")
    c = _table(e["cut"], cp, ("path", "depth", "through", "tilt_deg", "method", "surface"), ("path",))
    pts = c["path"]
    if not isinstance(pts, list) or len(pts) < 2 or not all(isinstance(q, list) and len(q) in (2, 3) for q in pts):
        _fail(_join(cp, "path"), f"must be a list of >= 2 points [x, y] on the top surface in {unit[0]}, got {_show(pts)}")
    pts = [[_number(v, _join(_join(cp, "path"), i), what=f"a coordinate in {unit[0]}") * unit[1] for v in q] for i, q in enumerate(pts)]
    depth = _length(c["depth"], _join(cp, "depth"), unit) if "depth" in c else None
    through = _bool(c.get("through", False), _join(cp, "through"))
    tilt = math.radians(_number(c.get("tilt_deg", 0.0), _join(cp, "tilt_deg"), what="an angle in degrees"))
    method = _choice(c.get("method", "snap"), _join(cp, "method"), ("snap", "staircase", "remove"))
    surface = _choice(c.get("surface", "top"), _join(cp, "surface"), ("top", "boundary"))
    try:
        scalpel = ScalpelPath(pts, depth=depth, through=through, tilt=tilt, surface=surface)
    except DifftissueError as err:
        _reraise(cp, err)
    try:
        cut = cut_specimen(specimen, scalpel, method=method)
    except DifftissueError as err:
        _reraise(cp, err)
    bp = _join(path, "boundary")
    b = _table(e.get("boundary", {}), bp, ("lateral", "base", "rollers"))
    lateral = _choice(b.get("lateral", "held"), _join(bp, "lateral"), ("held", "roller", "free"))
    base = _choice(b.get("base", "clamped"), _join(bp, "base"), ("clamped", "sliding"))
    rollers = _rollers(b["rollers"], _join(bp, "rollers")) if "rollers" in b else ()
    steps = _integer(e.get("scalpel_steps", 4), _join(path, "scalpel_steps"), minimum=1)
    so = _solver_options(e, path)
    options = IncisionOptions(scalpel_steps=steps, rtol=so.rtol, xtol=so.xtol, max_steps=so.max_steps, linear_solver=so.linear_solver, failure=so.failure)
    if model in LATTICE_MODELS and getattr(cut.mesh, "lattice", None) is None:
        _fail(_join(path, "model"), f"an imported mesh has no cube lattice ({model} needs one): use 'stable_neo_hookean', 'fem_linear' or 'fem_neo_hookean'")
    try:
        sc = Incision(cut, model=model, quantity=quantity, positions=positions, observed=observed, sigma=sigma, fitted_regions=fitted, lateral=lateral, base=base, rollers=rollers, options=options, name=name)
    except DifftissueError as err:
        _reraise(path, err)
    notes = (f"{path}: {cut.quality}",)

    def make(level_cut):
        return Incision(level_cut, model=model, quantity=quantity, positions=positions, observed=observed, sigma=sigma, fitted_regions=fitted,
                        lateral=lateral, base=base, rollers=rollers, options=options, name=name)

    coarsen, skip = None, _MESH_FILE_SKIP
    if "mesh" not in spec:
        coarsen, skip = _coarse_incision(skin, scalpel, method, cut, make, unit)
    return Experiment(name, "incision", model, sc, tuple(files), notes, coarsen=coarsen, coarsen_skip=skip)


#: Tolerance of the coarse cut's realised geometry against the fine cut's [-]: the opened area
#: may differ by this fraction of the ideal cutting surface, a node may move (snap) or lie off
#: the ideal surface by this fraction of the coarser mesh's lateral cell. Tight: a coarser mesh
#: whose nodes do not carry the same cut makes a different cut, and the change in the opening
#: would not be the mesh's alone.
CUT_GEOMETRY_TOLERANCE = 1e-6


def _skin_level(skin: dict, k: int) -> tuple[tuple[int, int], list, dict]:
    """The layered specimen with its lateral cells and each layer's cells halved ``k`` times
    (at least one cell; a graded layer of ratio ``r`` gets ``r^2`` per halving, so its merged
    cells are the fine ones taken in pairs, and loses the grading at one cell)."""
    cells, layers, grading = tuple(skin["cells"]), list(skin["layers"]), dict(skin["grading"])
    for _ in range(k):
        cells = _halved(cells)[0]
        layers = [(n, t, m, max(1, nc // 2)) for n, t, m, nc in layers]
        grading = {n: r * r for n, r in grading.items() if dict((ln, nc) for ln, _, _, nc in layers)[n] >= 2}
    return cells, layers, grading


def _skin_cells(cells, layers) -> dict:
    return {"lateral": [int(c) for c in cells], "layers": [int(nc) for _, _, _, nc in layers]}


def _cut_geometry(cut) -> dict:
    """The realised geometry of a cut (compared between the discretisation check's levels): the
    nominal length and depth [m], the opened area and the ideal cutting surface's [m^2], the
    largest distance of an opened node from the ideal surface and the largest snap [m]."""
    q = cut.quality
    return {"cut_length": float(cut.length), "cut_depth": float(cut.depth), "cut_area": q.cut_area, "ideal_area": q.ideal_area,
            "max_normal_distance": q.max_normal_distance, "max_snap_distance": float(q.max_snap_distance), "n_snapped": int(q.n_snapped)}


def _same_cut(fine: dict, coarse: dict, cell: float) -> str | None:
    """Why the coarse cut's realised geometry differs from the fine cut's (None: the same cut
    within :data:`CUT_GEOMETRY_TOLERANCE`; ``cell``: the coarser mesh's smallest lateral cell [m])."""
    tol = CUT_GEOMETRY_TOLERANCE
    why = []
    for k in ("cut_length", "cut_depth"):
        if abs(coarse[k] - fine[k]) > tol * cell:
            why.append(f"its {k.replace('_', ' ')} is {coarse[k]:.4g} m, not {fine[k]:.4g} m")
    if coarse["max_snap_distance"] > tol * cell:
        why.append(f"{coarse['n_snapped']} node(s) had to be moved onto it, up to {coarse['max_snap_distance']:.3g} m")
    a_f, a_c, ideal = fine["cut_area"], coarse["cut_area"], fine["ideal_area"] or 0.0
    if a_f is not None and a_c is not None and abs(a_c - a_f) > tol * max(ideal, a_f):
        why.append(f"it opens {a_c:.4g} m^2, the fine cut {a_f:.4g} m^2")
    d_f, d_c = fine["max_normal_distance"], coarse["max_normal_distance"]
    if d_f is not None and d_c is not None and abs(d_c - d_f) > tol * cell:
        why.append(f"its opened faces lie up to {d_c:.3g} m off the ideal surface (the fine cut's {d_f:.3g} m)")
    return "; ".join(why) or None


def _off_nodes(scalpel, size, cells, layers, grading, cell: float, f: float) -> str | None:
    """Which of the cut's points inside the top surface (its ends and corners) and its depth do
    not lie on the nodes of the uniform layered mesh (``cells`` lateral, ``layers`` with their
    cell counts) within :data:`CUT_GEOMETRY_TOLERANCE` of ``cell`` [m] (None: all do). A cut
    ending between nodes is not snapped where the move would ruin a tet, so its opened faces
    end at a different place on each mesh. ``f``: metres per length unit, for the message."""
    tol = CUT_GEOMETRY_TOLERANCE * cell
    xs, ys = np.linspace(0.0, size[0], cells[0] + 1), np.linspace(0.0, size[1], cells[1] + 1)
    off = []
    for pt in np.asarray(scalpel.points, dtype=float):
        x, y = pt[0], pt[1]
        if not (-tol <= x <= size[0] + tol and -tol <= y <= size[1] + tol):
            continue  # outside the outline: the cut ends on the specimen's side, on nodes
        if np.min(np.abs(xs - x)) > tol or np.min(np.abs(ys - y)) > tol:
            off.append(f"[{x / f:.4g}, {y / f:.4g}]")
    why = [f"the point(s) {', '.join(off)} lie between its nodes"] if off else []
    if scalpel.depth is not None and not scalpel.through:
        if np.min(np.abs(np.asarray(_node_depths(layers, grading)) - float(scalpel.depth))) > tol:
            why.append(f"the depth {float(scalpel.depth) / f:.4g} lies between its node planes")
    return "; ".join(why) or None


def _node_depths(layers, grading) -> list[float]:
    """Depths [m] below the surface of the node planes of a layered specimen (surface first)."""
    z, out = 0.0, [0.0]
    for n, t, _, nc in layers:
        heights = layer_node_heights(t, nc, grading.get(n, 1.0))  # from the layer's base up
        out.extend(float(z + d) for d in (t - heights[::-1])[1:])
        z += t
    return out


def _coarse_incision(skin: dict, scalpel, method: str, cut, make, unit):
    """``(builder, None)`` of the discretisation check of an incision on a layered specimen, or
    ``(None, reason)``. The builder returns ``(scenario, info)`` on the specimen with every cell
    count halved (:func:`_skin_level`) and the same cut (the same :class:`ScalpelPath` and
    method), with a third level (halved again) where that mesh carries the same cut too, so the
    order is observed; or ``(None, reason)`` when the coarser mesh's cut is not the fine one
    (:func:`_same_cut`: its ends or depth do not fall on the coarser mesh's nodes)."""
    if method == "remove":
        return None, ("the cut removes a slab of elements one cell wide: a coarser mesh removes a wider slab, so the change would not be the "
                      "mesh's alone (use method = \"snap\" or \"staircase\" to get the estimate)")
    if skin["refined"]:
        return None, ("the specimen is refined laterally (refine): its graded cells do not halve onto the same cut; give uniform cells "
                      "(no refine) to get the estimate")
    c1, l1, g1 = _skin_level(skin, 1)
    if c1 == tuple(skin["cells"]) and all(a[3] == b[3] for a, b in zip(l1, skin["layers"])):
        return None, f"the specimen has one cell in each direction ({_skin_cells(c1, l1)}): there is no coarser mesh"
    fine_geo = _cut_geometry(cut)
    size = skin["size"]
    u, f = unit

    def level(k):
        cells, layers, grading = _skin_level(skin, k)
        cell = min(size[0] / cells[0], size[1] / cells[1])
        mesh = f"the cut on the coarser mesh (cells {_skin_cells(cells, layers)})"
        off = _off_nodes(scalpel, size, cells, layers, grading, cell, f)
        lcut = geo = None
        try:
            lcut = cut_specimen(layered_skin(layers, size=size, resolution=cells, grading=grading or None), scalpel, method=method)
        except DifftissueError as err:
            if off is None:  # on its nodes, but the coarser cells are too large for the cut
                return cells, layers, None, None, (f"{mesh} cannot be made: {err}: the fit's cells are too coarse for a coarser level "
                                                   "(refine them to get an estimate)")
            why = f"{mesh} cannot be made: {off}; {err}"
        else:
            geo = _cut_geometry(lcut)
            why = "; ".join(w for w in (off, _same_cut(fine_geo, geo, cell)) if w) or None
            if why is not None:
                why = f"{mesh} is not the fit's cut: {why}"
        if why is not None:
            depths = ", ".join(f"{d / f:.4g}" for d in _node_depths(layers, grading))
            why += (f" (its ends or depth do not fall on that mesh's nodes), so the change would not be the mesh's "
                    f"alone; give the cut's ends on multiples of the coarser cell size ({size[0] / cells[0] / f:.4g} {u} in x, "
                    f"{size[1] / cells[1] / f:.4g} {u} in y) and its depth on one of its node depths ({depths} {u}), or cells that halve onto the cut")
        return cells, layers, lcut, geo, why

    def ratio(a_cells, a_layers, b_cells, b_layers):
        return _size_ratio((a_cells[0] / b_cells[0], a_cells[1] / b_cells[1], sum(x[3] for x in a_layers) / sum(x[3] for x in b_layers)))

    def coarsen():
        cells1, layers1, cut1, geo1, why = level(1)
        if why is not None:
            return None, why
        fine = (tuple(skin["cells"]), skin["layers"])
        r = ratio(*fine, cells1, layers1)
        info = {"fine_cells": _skin_cells(*fine), "coarse_cells": _skin_cells(cells1, layers1), "refinement_ratio": r,
                "geometry": {"fine": fine_geo, "coarse": geo1}}
        c2, l2, _ = _skin_level(skin, 2)
        if c2 == cells1 and all(a[3] == b[3] for a, b in zip(l2, layers1)):
            info["geometry"]["third_level"] = "none: the coarse mesh has one cell in each direction"
        else:
            cells2, layers2, cut2, geo2, why2 = level(2)
            r2 = ratio(cells1, layers1, cells2, layers2)
            if why2 is not None:
                info["geometry"]["third_level"] = f"none (first order assumed): {why2}"
            elif abs(r2 - r) > 1e-9 * r:
                info["geometry"]["third_level"] = (f"none (first order assumed): its cell size ratio {r2:.4g} differs from the coarse mesh's "
                                                   f"{r:.4g} (a layer with one cell keeps it)")
            else:
                info["geometry"]["coarser"] = geo2
                info["coarser"] = lambda: (make(cut2), _skin_cells(cells2, layers2))
        return make(cut1), info

    return coarsen, None
