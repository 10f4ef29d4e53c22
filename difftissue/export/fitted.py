"""Fitted specimens: the experiment of a ``fem_field``, ``compression`` or ``incision`` fit, written
with the fit outputs and exported as a complete model (docs/export.md, "Fitted specimens: fem_field,
compression and incision").

A :class:`~difftissue.scenarios.FEMField`, :class:`~difftissue.scenarios.Compression` or
:class:`~difftissue.incision.Incision` experiment is not rebuilt from a few numbers (the
reference mesh, node sets and per-node prescribed displacements; the model's block or cylinder
mesh with the fitted platen condition; the cut mesh with its duplicated nodes and per-region
materials), so
:func:`difftissue.fit.write_fit_outputs` writes it beside ``material.json`` as
``specimen-<scenario name>.vtu`` (:func:`specimen_file_name`, :func:`write_specimen`) and records
the file's name and sha256 in the card's scenario record (``provenance.scenario_records[i]
["specimen_file"]``). ``difftissue export CARD --specimen fitted [--scenario NAME]`` reads it back
(:func:`fitted_specimen_from_card`: a missing or altered file is refused) and writes the complete
model for the target (:func:`write_fitted`).

The specimen file (VTU, SI units, format :data:`SPECIMEN_FORMAT`) holds exactly the model's mesh
(points [m], tets, ``region_id`` with the region names) and:

* point data ``fixed`` ``(N, 3)`` (1 where a displacement component is prescribed),
  ``prescribed_displacement`` ``(N, 3)`` [m] (0 where free), ``reaction_set`` ``(N, 3)``
  (fem_field with a reaction, compression: 1 on the summed components), and for an incision
  ``cut_pair`` (index of the node's duplicated pair, -1 if none), ``cut_side`` (+1 the pair's
  original node, -1 its duplicate), ``cut_pair_s`` / ``cut_pair_depth`` [m] (arc length along
  the cut and depth of the node's pair, NaN if none), ``cut_surface_rank`` (rank of the pair
  in the surface profile, -1 if not on the surface);
* cell data ``fitted_material`` (1: the card's material; 0: a fixed material given by the cell
  fields ``youngs_modulus`` [Pa], ``poisson_ratio``, ``cubic_coefficient``, ``density``
  [kg/m^3], ``pre_stretch``, which are NaN on fitted cells).

A compression specimen is the model's mesh with the platens at the LAST (largest) strain of
the protocol: bonded platens hold all components of both faces (top ``u = (0, 0, -e H)``),
frictionless ones ``u_z`` of both faces plus the rigid-body pins of
:meth:`~difftissue.contact.Platens.apply`; the reaction set is the top face (z). The protocol
(platens, measure, strains, nominal strains, height ``H``, area ``A0``, top displacement) is in
the card's scenario record (:func:`compression_protocol`) and comes back as
:attr:`FittedSpecimen.protocol`. The file format is unchanged (``difftissue-specimen/1``): a
compression file has exactly the fields of a fem_field file.

What each target gets (:func:`write_fitted`): FEBio 4.0 (nodes, ``tet4`` elements per region,
node sets, ``zero displacement`` and ``prescribed displacement`` with per-node ``<NodeData>``
maps, ``prestrain elastic`` materials for pre-stretched regions, a static step), Abaqus
(``*NSET``, ``*BOUNDARY`` with per-node magnitudes in a ``*STATIC`` step; a pre-stretched
incision is refused), SOFA (one material, no pre-stretch: the fem_field, with the prescribed values
as initial positions held by projective constraints; the compression, with the top platen
ramped by a ``PartialLinearMovementProjectiveConstraint``), the XPBD JSON and VTU (our own formats:
everything). pypbd is refused with the reason. FEBio and Abaqus ramp the prescribed values
over the step; for a compression specimen the ramp is cut so that one increment is at most
:data:`MAX_STRAIN_INCREMENT` of nominal strain.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .._io import sha256_file
from ..errors import ExportError
from ..mesh import TetMesh, read_mesh, write_mesh
from ..models import stack_materials
from .card import MATERIAL_FIELDS, OPTIONAL_MATERIAL_FIELDS, MaterialCard, scenario_record

__all__ = [
    "SPECIMEN_FORMAT",
    "FITTED_EXPERIMENTS",
    "MAX_STRAIN_INCREMENT",
    "FittedSpecimen",
    "fitted_specimen",
    "compression_protocol",
    "specimen_file_name",
    "specimen_fields",
    "write_specimen",
    "read_specimen",
    "fitted_specimen_from_card",
    "specimen_record",
    "load_steps",
    "component_sets",
]


#: Format tag of the specimen file (recorded in the card next to its sha256).
SPECIMEN_FORMAT = "difftissue-specimen/1"


#: Experiments written as a specimen file by the fit outputs.
FITTED_EXPERIMENTS = ("fem_field", "compression", "incision")


#: Largest nominal-strain increment of one load step of an exported compression specimen.
MAX_STRAIN_INCREMENT = 0.02


@dataclasses.dataclass(frozen=True, eq=False)
class FittedSpecimen:
    """The experiment of a fitted ``fem_field``, ``compression`` or ``incision`` scenario (SI
    units, 0-based ids).

    Attributes:
        scenario: the scenario's name; experiment: ``"fem_field"``, ``"compression"`` or ``"incision"``;
        model: difftissue's elastic model of the scenario (``fem_linear``, ``stable_neo_hookean``, ...).
        points: ``(N, 3)`` reference (model) positions [m]; tets: ``(M, 4)``; region_ids: ``(M,)``;
        region_names: one name per region.
        fitted_regions: names of the regions that take the card's material.
        region_materials: ``{region name: {field: value}}`` of the other (fixed) regions.
        fixed: ``(N, 3)`` bool, prescribed components; prescribed: ``(N, 3)`` prescribed
            displacement [m] (0 where free).
        reaction: ``(N, 3)`` bool, the components whose reactions the fit summed, or None.
        pairs: ``(P, 2)`` duplicated node pairs ``(original, duplicate)`` of an incision, else None;
        pair_s, pair_depth: ``(P,)`` [m]; surface_pairs: indices into ``pairs`` of the top-surface
        pairs, in the order of the surface profile.
        protocol: a compression's protocol (:func:`compression_protocol`: platens, measure,
            strains, nominal strains, height [m], area [m^2], top displacement [m]), else None.
    """

    scenario: str
    experiment: str
    model: str
    points: np.ndarray
    tets: np.ndarray
    region_ids: np.ndarray
    region_names: tuple[str, ...]
    fitted_regions: tuple[str, ...]
    region_materials: Mapping[str, Mapping[str, float]]
    fixed: np.ndarray
    prescribed: np.ndarray
    reaction: np.ndarray | None = None
    pairs: np.ndarray | None = None
    pair_s: np.ndarray | None = None
    pair_depth: np.ndarray | None = None
    surface_pairs: np.ndarray | None = None
    protocol: Mapping[str, Any] | None = None

    def __post_init__(self):
        if self.experiment not in FITTED_EXPERIMENTS:
            raise ExportError(f"fitted specimen experiment {self.experiment!r}: expected one of {list(FITTED_EXPERIMENTS)}")
        n = len(self.points)
        if self.fixed.shape != (n, 3) or self.prescribed.shape != (n, 3):
            raise ExportError(f"fitted specimen {self.scenario!r}: fixed / prescribed must have shape ({n}, 3)")
        if not np.all(np.isfinite(self.prescribed)):
            raise ExportError(f"fitted specimen {self.scenario!r}: the prescribed displacement is not finite")
        unknown = set(self.fitted_regions) - set(self.region_names)
        if unknown:
            raise ExportError(f"fitted specimen {self.scenario!r}: fitted region(s) {sorted(unknown)} are not regions {list(self.region_names)}")
        for r in self.region_names:
            if r not in self.fitted_regions and r not in self.region_materials:
                raise ExportError(f"fitted specimen {self.scenario!r}: region {r!r} is neither fitted nor given a material")
        if self.experiment == "incision" and (self.pairs is None or self.surface_pairs is None):
            raise ExportError(f"fitted specimen {self.scenario!r}: an incision needs its duplicated node pairs")
        if self.experiment == "compression":
            _check_compression(self)

    # ------------------------------------------------------------------ materials
    def region_cards(self, card):
        """One :class:`~difftissue.export.MaterialCard` per region: ``card`` on the fitted
        regions, a card of the fixed values (named ``<card name>_<region>``) elsewhere."""
        out = []
        for r in self.region_names:
            if r in self.fitted_regions:
                out.append(card)
            else:
                vals = self.region_materials[r]
                out.append(MaterialCard(model=card.model, name=f"{card.name}_{r}", provenance={"fixed_region": r},
                                        parameters={k: {"value": float(vals[k])} for k in MATERIAL_FIELDS + OPTIONAL_MATERIAL_FIELDS if k in vals}))
        return out

    def material(self, card):
        """The per-region :class:`~difftissue.materials.Material` (fields ``(n_regions,)``) for
        difftissue's solvers, with ``card``'s values on the fitted regions."""
        return stack_materials([c.material() for c in self.region_cards(card)])

    def pre_stretches(self, card) -> np.ndarray:
        """``(n_regions,)`` pre-stretch ``lambda0`` of each region."""
        return np.array([c.pre_stretch for c in self.region_cards(card)])

    def pre_stretches_y(self, card) -> np.ndarray:
        """``(n_regions,)`` pre-stretch ``lambda_y`` of each region (``pre_stretch`` where a card has no ``pre_stretch_y``)."""
        return np.array([c.pre_stretch_y for c in self.region_cards(card)])

    def mesh(self):
        """The specimen as a :class:`~difftissue.mesh.TetMesh` (no fields)."""
        return TetMesh(self.points, self.tets, self.region_ids, self.region_names)

    def describe(self) -> list[str]:
        """Comment lines for the written models."""
        n_fix = int(self.fixed.sum())
        n_nz = int((self.fixed & (self.prescribed != 0.0)).sum())
        lines = [f"fitted specimen of scenario {self.scenario!r} ({self.experiment}, difftissue model {self.model}): "
                 f"{len(self.points)} nodes, {len(self.tets)} tets, regions {list(self.region_names)} "
                 f"(card material on {list(self.fitted_regions)})",
                 f"{n_fix} prescribed displacement components, {n_nz} of them nonzero "
                 + ("(the platens at the last strain of the protocol)" if self.experiment == "compression" else
                    "(per-node values from the fit's reference)")]
        if self.reaction is not None:
            comps = "".join(c for i, c in enumerate("xyz") if self.reaction[:, i].any())
            lines.append(f"the fit compared the summed reaction force ({comps}) over node set 'reaction' ({int(self.reaction.any(axis=1).sum())} nodes)")
        if self.protocol is not None:
            pr = self.protocol
            lines.append(f"compression between rigid {pr['platens']} platens: height H = {pr['height']:.10g} m, area A0 = "
                         f"{pr['area']:.10g} m^2 (volume / H), top platen moved by u_z = {pr['top_displacement']:.10g} m (nominal "
                         f"strain {pr['nominal_strains'][-1]:.10g}, the last of the {pr['measure']} protocol of {len(pr['strains'])} strains)")
            lines.append("engineering stress = F / A0 with F = -(sum of the z reactions over node set 'reaction'); true stress = "
                         "F h / V (current height h, current volume V); the load ramps linearly, so load fraction t is nominal strain "
                         f"t * {pr['nominal_strains'][-1]:.10g}")
        if self.pairs is not None:
            lines.append(f"incision: {len(self.pairs)} duplicated node pairs (cut faces, untied: the opened state), "
                         f"{len(self.surface_pairs)} on the top surface; node sets cut_plus / cut_minus list them pair by pair")
        return lines


def compression_protocol(scenario) -> dict:
    """The protocol of a :class:`~difftissue.scenarios.Compression` scenario, as recorded in the
    card's scenario record (:meth:`~difftissue.scenarios.Compression.protocol`): ``platens``
    (``"bonded"`` / ``"frictionless"``), ``measure`` (``"engineering"`` / ``"true"``), ``strains``
    (the fitted protocol in that measure, [-]), ``nominal_strains`` (``delta / H``), ``height``
    ``H`` [m], ``area`` ``A0`` [m^2] (volume / H, the area of the engineering stress),
    ``top_displacement`` [m] (``-e H`` at the last nominal strain ``e``: the specimen file's top
    platen) and ``reaction`` (``"z"``: the component summed over the top face)."""
    protocol = getattr(scenario, "protocol", None)
    if not callable(protocol):
        raise ExportError(f"{getattr(scenario, 'name', scenario)!r} is no compression scenario (it has no protocol())")
    return dict(protocol())


def _check_compression(spec: FittedSpecimen) -> None:
    """A compression specimen: a protocol, a top-face z reaction set whose nodes are prescribed
    u_z = the protocol's top displacement."""
    pr = spec.protocol
    need = ("platens", "measure", "strains", "nominal_strains", "height", "area", "top_displacement")
    if not isinstance(pr, Mapping) or any(k not in pr for k in need):
        raise ExportError(f"fitted specimen {spec.scenario!r}: a compression specimen needs its protocol {list(need)} "
                          "(the card's scenario record)")
    if pr["platens"] not in ("bonded", "frictionless") or pr["measure"] not in ("engineering", "true"):
        raise ExportError(f"fitted specimen {spec.scenario!r}: platens {pr['platens']!r} / measure {pr['measure']!r} are not "
                          "'bonded'/'frictionless' and 'engineering'/'true'")
    if not pr["strains"] or len(pr["strains"]) != len(pr["nominal_strains"]):
        raise ExportError(f"fitted specimen {spec.scenario!r}: the compression protocol needs one nominal strain per strain")
    if spec.reaction is None or spec.reaction[:, :2].any() or not spec.reaction[:, 2].any():
        raise ExportError(f"fitted specimen {spec.scenario!r}: a compression specimen sums the z reactions of its top face")
    top = np.flatnonzero(spec.reaction[:, 2])
    d = float(pr["top_displacement"])
    if not (np.all(spec.fixed[top, 2]) and np.all(spec.prescribed[top, 2] == d)):
        raise ExportError(f"fitted specimen {spec.scenario!r}: the file's top platen is not at the recorded top displacement "
                          f"{d:g} m (file and card record disagree)")
    z = spec.points[:, 2]
    H = float(np.ptp(z))
    if not (np.isclose(float(pr["height"]), H, rtol=1e-12, atol=0.0) and np.allclose(z[top], z.max(), rtol=0.0, atol=1e-9 * H)):
        raise ExportError(f"fitted specimen {spec.scenario!r}: the recorded height {pr['height']:g} m or top face does not match the mesh")


def fitted_specimen(scenario) -> FittedSpecimen | None:
    """The :class:`FittedSpecimen` of a :class:`~difftissue.scenarios.FEMField`,
    :class:`~difftissue.scenarios.Compression` (the platens at the last strain of the
    protocol) or :class:`~difftissue.incision.Incision` scenario; ``None`` for other scenarios
    (their experiments are rebuilt from the card's record or need no specimen file). Which one
    the scenario is comes from its own record (:func:`~difftissue.export.card.scenario_record`,
    ``experiment``); the mesh and boundary conditions from its ``model`` and ``bc``."""
    rec = scenario_record(scenario) or {}
    experiment = rec.get("experiment")
    if experiment not in FITTED_EXPERIMENTS:
        return None
    m = scenario.model
    pts = np.asarray(m.rest_points, dtype=float)
    tets = np.asarray(m.tets, dtype=np.int64)
    regions = np.asarray(m.tet_regions, dtype=np.int64)
    names = tuple(str(r) for r in m.region_names)
    fixed = np.asarray(scenario.bc.fixed, dtype=bool)
    presc = np.where(fixed, np.asarray(scenario.bc.displacement, dtype=float), 0.0)
    if np.any(np.asarray(scenario.bc.force) != 0.0):
        raise ExportError(f"scenario {scenario.name!r} has external nodal forces: the fitted-specimen file holds prescribed displacements only")
    name, model = str(rec["name"]), str(rec["model"])
    if experiment == "compression":
        # the platens at the last strain, as Compression._solve_protocol prescribes them
        protocol = compression_protocol(scenario)
        top = np.asarray(scenario.top_mask, dtype=bool)
        presc[top, 2] = protocol["top_displacement"]
        reaction = np.zeros_like(fixed)
        reaction[top, 2] = True
        return FittedSpecimen(scenario=name, experiment="compression", model=model, points=pts, tets=tets,
                              region_ids=regions, region_names=names, fitted_regions=names, region_materials={},
                              fixed=fixed, prescribed=presc, reaction=reaction, protocol=protocol)
    if experiment == "fem_field":
        reaction = None if scenario.reaction_mask is None else np.asarray(scenario.reaction_mask, dtype=bool)
        return FittedSpecimen(scenario=name, experiment="fem_field", model=model, points=pts, tets=tets,
                              region_ids=regions, region_names=names, fitted_regions=names, region_materials={},
                              fixed=fixed, prescribed=presc, reaction=reaction)
    cut = scenario.cut
    if scenario.fitted_regions is None:
        fitted, mats = names, {}
    else:
        fitted = tuple(names[i] for i in scenario.fitted_regions)
        base = scenario.base_materials
        fields = MATERIAL_FIELDS + (("pre_stretch_y",) if base.pre_stretch_y is not None else ())
        mats = {names[i]: {f: float(np.asarray(getattr(base, f))[i]) for f in fields}
                for i in range(len(names)) if i not in scenario.fitted_regions}
    return FittedSpecimen(scenario=name, experiment="incision", model=model, points=pts, tets=tets,
                          region_ids=regions, region_names=names, fitted_regions=fitted, region_materials=mats,
                          fixed=fixed, prescribed=presc, pairs=np.asarray(cut.pairs, dtype=np.int64),
                          pair_s=np.asarray(cut.pair_s, dtype=float), pair_depth=np.asarray(cut.pair_depth, dtype=float),
                          surface_pairs=np.asarray(cut.surface_pairs, dtype=np.int64))


_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def specimen_file_name(scenario_name: str) -> str:
    """``specimen-<name>.vtu`` with every character outside ``[A-Za-z0-9_.-]`` replaced by ``_``."""
    s = _SAFE.sub("_", str(scenario_name)).strip(".") or "scenario"
    return f"specimen-{s}.vtu"


def specimen_fields(spec: FittedSpecimen, card=None) -> tuple[dict, dict]:
    """``(point_data, cell_data)`` of the specimen file (module docstring); with ``card`` the fitted
    cells get its values and every cell ``shear_modulus``, ``lame_lambda``, ``bulk_modulus`` (the
    VTU export), without it the fitted cells hold NaN (the specimen file)."""
    n, m = len(spec.points), len(spec.tets)
    point: dict[str, np.ndarray] = {"fixed": spec.fixed.astype(np.float64), "prescribed_displacement": spec.prescribed.astype(float)}
    if spec.reaction is not None:
        point["reaction_set"] = spec.reaction.astype(np.float64)
    if spec.pairs is not None:
        flat = spec.pairs.reshape(-1)
        if len(np.unique(flat)) != flat.size:
            raise ExportError(f"scenario {spec.scenario!r}: a node belongs to two duplicated pairs; the specimen file holds one pair per node")
        P = len(spec.pairs)
        pair = np.full(n, -1, dtype=np.int64)
        side = np.zeros(n, dtype=np.int64)
        s = np.full(n, np.nan)
        depth = np.full(n, np.nan)
        rank = np.full(n, -1, dtype=np.int64)
        for k in range(2):
            pair[spec.pairs[:, k]] = np.arange(P)
            side[spec.pairs[:, k]] = 1 - 2 * k
            s[spec.pairs[:, k]] = spec.pair_s
            depth[spec.pairs[:, k]] = spec.pair_depth
        for r, p in enumerate(spec.surface_pairs):
            rank[spec.pairs[p]] = r
        point.update(cut_pair=pair.astype(np.float64), cut_side=side.astype(np.float64), cut_pair_s=s, cut_pair_depth=depth,
                     cut_surface_rank=rank.astype(np.float64))
    fitted = np.array([spec.region_names[r] in spec.fitted_regions for r in spec.region_ids])
    cell: dict[str, np.ndarray] = {"fitted_material": fitted.astype(np.float64)}
    aniso = (card is not None and "pre_stretch_y" in card.parameters) or any("pre_stretch_y" in v for v in spec.region_materials.values())
    for f in MATERIAL_FIELDS + (("pre_stretch_y",) if aniso else ()):
        v = np.full(m, np.nan)
        for i, r in enumerate(spec.region_names):
            sel = spec.region_ids == i
            if r in spec.region_materials:
                v[sel] = spec.region_materials[r].get(f, spec.region_materials[r]["pre_stretch"]) if f == "pre_stretch_y" else spec.region_materials[r][f]
            elif card is not None:
                v[sel] = card.pre_stretch_y if f == "pre_stretch_y" else card.value(f)
        cell[f] = v
    if card is not None:
        cards = spec.region_cards(card)
        for name in ("shear_modulus", "lame_lambda", "bulk_modulus"):
            cell[name] = np.array([getattr(cards[r], name) for r in spec.region_ids], dtype=float)
    return point, cell


def write_specimen(spec: FittedSpecimen, path, *, force: bool = False) -> Path:
    """Write the specimen file (VTU, see the module docstring) atomically; an existing file is
    refused unless ``force``."""
    path = Path(path)
    if path.suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a specimen file must end in .vtu")
    point, cell = specimen_fields(spec)
    return write_mesh(path, spec.mesh(), point_data=point, cell_data=cell, overwrite=force)


def read_specimen(path, *, scenario: str, experiment: str, model: str, protocol: Mapping | None = None) -> FittedSpecimen:
    """Read a specimen file written by :func:`write_specimen` (the scalars, and a compression's
    ``protocol``, come from the card's record)."""
    try:
        mesh = read_mesh(path)
    except Exception as e:  # meshio raises many types; one line naming the file
        raise ExportError(f"cannot read the specimen file {path}: {' '.join(str(e).split())}") from None
    pd, cd = mesh.point_data, mesh.cell_data
    for k in ("fixed", "prescribed_displacement"):
        if k not in pd:
            raise ExportError(f"{path}: point field {k!r} is missing (not a {SPECIMEN_FORMAT} file)")
    if "fitted_material" not in cd:
        raise ExportError(f"{path}: cell field 'fitted_material' is missing (not a {SPECIMEN_FORMAT} file)")
    n = mesh.n_nodes
    fixed = np.asarray(pd["fixed"]).reshape(n, 3) != 0
    presc = np.asarray(pd["prescribed_displacement"], dtype=float).reshape(n, 3)
    reaction = None if "reaction_set" not in pd else np.asarray(pd["reaction_set"]).reshape(n, 3) != 0
    names = tuple(mesh.region_names)
    rid = np.asarray(mesh.region_ids)
    fitted_cell = np.asarray(cd["fitted_material"]).reshape(-1) != 0
    fitted, mats = [], {}
    for i, r in enumerate(names):
        sel = rid == i
        if not sel.any():
            continue
        flags = np.unique(fitted_cell[sel])
        if flags.size != 1:
            raise ExportError(f"{path}: region {r!r} mixes fitted and fixed cells")
        if flags[0]:
            fitted.append(r)
            continue
        vals = {}
        for f in MATERIAL_FIELDS + tuple(f for f in OPTIONAL_MATERIAL_FIELDS if f in cd):
            v = np.unique(np.asarray(cd[f], dtype=float).reshape(-1)[sel])
            if v.size != 1 or not np.isfinite(v[0]):
                raise ExportError(f"{path}: fixed region {r!r} has no single finite {f}")
            vals[f] = float(v[0])
        mats[r] = vals
    pairs = s = depth = surf = None
    if experiment == "incision":
        if "cut_pair" not in pd:
            raise ExportError(f"{path}: an incision specimen needs the point field 'cut_pair'")
        pair = np.asarray(pd["cut_pair"]).reshape(-1).astype(np.int64)
        side = np.asarray(pd["cut_side"]).reshape(-1).astype(np.int64)
        P = int(pair.max()) + 1
        pairs = np.full((P, 2), -1, dtype=np.int64)
        for node in np.flatnonzero(pair >= 0):
            pairs[pair[node], 0 if side[node] > 0 else 1] = node
        if np.any(pairs < 0):
            raise ExportError(f"{path}: a duplicated pair misses one of its nodes")
        s = np.asarray(pd["cut_pair_s"], dtype=float)[pairs[:, 0]]
        depth = np.asarray(pd["cut_pair_depth"], dtype=float)[pairs[:, 0]]
        rank = np.asarray(pd["cut_surface_rank"]).reshape(-1).astype(np.int64)[pairs[:, 0]]
        on = np.flatnonzero(rank >= 0)
        surf = on[np.argsort(rank[on], kind="stable")]
    return FittedSpecimen(scenario=scenario, experiment=experiment, model=model, points=np.asarray(mesh.points, dtype=float),
                          tets=np.asarray(mesh.tets, dtype=np.int64), region_ids=rid, region_names=names,
                          fitted_regions=tuple(fitted), region_materials=mats, fixed=fixed, prescribed=presc, reaction=reaction,
                          pairs=pairs, pair_s=s, pair_depth=depth, surface_pairs=surf,
                          protocol=dict(protocol) if experiment == "compression" and isinstance(protocol, Mapping) else None)


def fitted_specimen_from_card(card, card_path, *, scenario: str | None = None) -> FittedSpecimen:
    """The fitted specimen recorded in ``card`` (read from ``card_path``): its scenario record's
    ``specimen_file`` (the one named ``scenario``, or the only one), resolved beside the card,
    checked against the recorded sha256 and read. Every failure is one :class:`ExportError` line."""
    recs = [r for r in ((card.provenance or {}).get("scenario_records") or []) if isinstance(r, Mapping)]
    with_file = [r for r in recs if isinstance(r.get("specimen_file"), Mapping)]
    if not with_file:
        raise ExportError(f"{card_path}: the card records no fitted specimen file (only fits of simulated fem_field / compression / incision "
                          "scenarios write one, with the fit outputs); use --specimen block:... or --specimen indentation")
    if scenario is not None:
        named = [r for r in with_file if r.get("name") == scenario]
        if not named:
            raise ExportError(f"{card_path}: no fitted specimen for scenario {scenario!r} (recorded: {[r.get('name') for r in with_file]})")
        rec = named[0]
    elif len(with_file) > 1:
        raise ExportError(f"{card_path}: the card records {len(with_file)} fitted specimens {[r.get('name') for r in with_file]}: "
                          "choose one with --scenario NAME")
    else:
        rec = with_file[0]
    info = rec["specimen_file"]
    if info.get("format") != SPECIMEN_FORMAT:
        raise ExportError(f"{card_path}: specimen file format {info.get('format')!r} is not {SPECIMEN_FORMAT!r}")
    name = str(info.get("path", ""))
    if not name or Path(name).name != name:
        raise ExportError(f"{card_path}: specimen file name {name!r} must be a plain file name beside the card")
    path = Path(card_path).parent / name
    if not path.is_file():
        raise ExportError(f"fitted specimen file {path} (scenario {rec.get('name')!r}) is missing: it is written beside "
                          "material.json by the fit and must stay there")
    digest = sha256_file(path)
    if digest != info.get("sha256"):
        raise ExportError(f"fitted specimen file {path} has sha256 {digest[:12]}..., the card records "
                          f"{str(info.get('sha256'))[:12]}...: the file was altered or replaced; refusing to export from it")
    protocol = None
    if rec.get("experiment") == "compression":
        protocol = {k: rec.get(k) for k in ("platens", "measure", "strains", "nominal_strains", "height", "area", "top_displacement", "reaction")
                    if k in rec}
    return read_specimen(path, scenario=str(rec.get("name")), experiment=str(rec.get("experiment")), model=str(rec.get("model")),
                         protocol=protocol)


def specimen_record(spec: FittedSpecimen, path) -> dict:
    """The ``specimen_file`` entry of the card's scenario record."""
    return {"path": Path(path).name, "sha256": sha256_file(path), "format": SPECIMEN_FORMAT,
            "nodes": int(len(spec.points)), "tets": int(len(spec.tets))}


def load_steps(spec: FittedSpecimen, default: int = 10) -> int:
    """Load increments of the exported ramp: ``default`` (10), and for a compression specimen
    enough that one increment is at most :data:`MAX_STRAIN_INCREMENT` of nominal strain
    (40 % -> 20 increments)."""
    if spec.protocol is None:
        return int(default)
    e = abs(float(spec.protocol["nominal_strains"][-1]))
    return max(int(default), int(math.ceil(e / MAX_STRAIN_INCREMENT - 1e-9)))


def component_sets(spec: FittedSpecimen, reaction_prescribed: bool = False):
    """Per component c: nodes held at zero, nodes with a nonzero prescribed value (0-based).
    ``reaction_prescribed`` (FEBio): the reaction set's held components go with the prescribed
    ones (value 0), since FEBio records reactions only on prescribed displacements."""
    out = []
    for c in range(3):
        held = spec.fixed[:, c]
        nz = held & (spec.prescribed[:, c] != 0.0)
        if reaction_prescribed and spec.reaction is not None:
            nz |= held & spec.reaction[:, c]
        out.append((np.flatnonzero(held & ~nz), np.flatnonzero(nz)))
    return out
