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
import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import ExportError

__all__ = [
    "SPECIMEN_FORMAT",
    "FITTED_EXPERIMENTS",
    "FittedSpecimen",
    "fitted_specimen",
    "compression_protocol",
    "specimen_file_name",
    "write_specimen",
    "read_specimen",
    "fitted_specimen_from_card",
    "febio_fitted_model",
    "abaqus_fitted_model",
    "sofa_fitted_scene",
    "xpbd_fitted_parameters",
    "write_fitted",
    "specimen_reactions",
    "recalibrated_card",
    "recalibrated_from_reactions",
]

#: Format tag of the specimen file (recorded in the card next to its sha256).
SPECIMEN_FORMAT = "difftissue-specimen/1"
#: Experiments written as a specimen file by the fit outputs.
FITTED_EXPERIMENTS = ("fem_field", "compression", "incision")
#: Largest nominal-strain increment of one load step of an exported compression specimen.
MAX_STRAIN_INCREMENT = 0.02
_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")


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
        from .export import MaterialCard

        out = []
        for r in self.region_names:
            if r in self.fitted_regions:
                out.append(card)
            else:
                vals = self.region_materials[r]
                out.append(MaterialCard(model=card.model, name=f"{card.name}_{r}", provenance={"fixed_region": r},
                                        parameters={k: {"value": float(vals[k])} for k in _FIELDS}))
        return out

    def material(self, card):
        """The per-region :class:`~difftissue.materials.Material` (fields ``(n_regions,)``) for
        difftissue's solvers, with ``card``'s values on the fitted regions."""
        from .models import stack_materials

        return stack_materials([c.material() for c in self.region_cards(card)])

    def pre_stretches(self, card) -> np.ndarray:
        """``(n_regions,)`` pre-stretch ``lambda0`` of each region."""
        return np.array([c.pre_stretch for c in self.region_cards(card)])

    def mesh(self):
        """The specimen as a :class:`~difftissue.mesh.TetMesh` (no fields)."""
        from .mesh import TetMesh

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


# ============================================================================ from a scenario
def compression_protocol(scenario) -> dict:
    """The protocol of a :class:`~difftissue.scenarios.Compression` scenario, as recorded in the
    card's scenario record: ``platens`` (``"bonded"`` / ``"frictionless"``), ``measure``
    (``"engineering"`` / ``"true"``), ``strains`` (the fitted protocol in that measure, [-]),
    ``nominal_strains`` (``delta / H``), ``height`` ``H`` [m], ``area`` ``A0`` [m^2] (volume /
    H, the area of the engineering stress), ``top_displacement`` [m] (``-e H`` at the last
    nominal strain ``e``: the specimen file's top platen) and ``reaction`` (``"z"``: the
    component summed over the top face)."""
    if type(scenario).__name__ == "SeparatelyCompiled":
        scenario = scenario.scenario
    eps = np.asarray(scenario.abscissa, dtype=float)
    if eps.size == 0:
        raise ExportError(f"compression scenario {scenario.name!r} has an empty strain protocol")
    nominal = eps if scenario.measure == "engineering" else -np.expm1(-eps)
    top = np.flatnonzero(np.asarray(scenario.top_mask))
    bonded = bool(np.all(np.asarray(scenario.bc.fixed)[top]))
    return {"platens": "bonded" if bonded else "frictionless", "measure": str(scenario.measure),
            "strains": eps.tolist(), "nominal_strains": nominal.tolist(), "height": float(scenario.height),
            "area": float(scenario.area), "top_displacement": float(-nominal[-1] * scenario.height), "reaction": "z"}


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
    (their experiments are rebuilt from the card's record or need no specimen file)."""
    if type(scenario).__name__ == "SeparatelyCompiled":  # difftissue.config's compiled wrapper
        scenario = scenario.scenario
    tname = type(scenario).__name__
    if tname not in ("FEMField", "Incision", "Compression"):
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
    if tname == "Compression":
        # the platens at the last strain, as Compression._solve_protocol prescribes them
        protocol = compression_protocol(scenario)
        top = np.asarray(scenario.top_mask, dtype=bool)
        presc[top, 2] = protocol["top_displacement"]
        reaction = np.zeros_like(fixed)
        reaction[top, 2] = True
        return FittedSpecimen(scenario=str(scenario.name), experiment="compression", model=str(m.kind), points=pts, tets=tets,
                              region_ids=regions, region_names=names, fitted_regions=names, region_materials={},
                              fixed=fixed, prescribed=presc, reaction=reaction, protocol=protocol)
    if tname == "FEMField":
        reaction = None if scenario.reaction_mask is None else np.asarray(scenario.reaction_mask, dtype=bool)
        return FittedSpecimen(scenario=str(scenario.name), experiment="fem_field", model=str(m.kind), points=pts, tets=tets,
                              region_ids=regions, region_names=names, fitted_regions=names, region_materials={},
                              fixed=fixed, prescribed=presc, reaction=reaction)
    cut = scenario.cut
    if scenario.fitted_regions is None:
        fitted, mats = names, {}
    else:
        fitted = tuple(names[i] for i in scenario.fitted_regions)
        base = scenario.base_materials
        mats = {names[i]: {f: float(np.asarray(getattr(base, f))[i]) for f in _FIELDS}
                for i in range(len(names)) if i not in scenario.fitted_regions}
    return FittedSpecimen(scenario=str(scenario.name), experiment="incision", model=str(m.base.kind), points=pts, tets=tets,
                          region_ids=regions, region_names=names, fitted_regions=fitted, region_materials=mats,
                          fixed=fixed, prescribed=presc, pairs=np.asarray(cut.pairs, dtype=np.int64),
                          pair_s=np.asarray(cut.pair_s, dtype=float), pair_depth=np.asarray(cut.pair_depth, dtype=float),
                          surface_pairs=np.asarray(cut.surface_pairs, dtype=np.int64))


_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def specimen_file_name(scenario_name: str) -> str:
    """``specimen-<name>.vtu`` with every character outside ``[A-Za-z0-9_.-]`` replaced by ``_``."""
    s = _SAFE.sub("_", str(scenario_name)).strip(".") or "scenario"
    return f"specimen-{s}.vtu"


# ============================================================================ the file
def _point_cell_fields(spec: FittedSpecimen, card=None) -> tuple[dict, dict]:
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
    for f in _FIELDS:
        v = np.full(m, np.nan)
        for i, r in enumerate(spec.region_names):
            sel = spec.region_ids == i
            if r in spec.region_materials:
                v[sel] = spec.region_materials[r][f]
            elif card is not None:
                v[sel] = card.value(f)
        cell[f] = v
    if card is not None:
        cards = spec.region_cards(card)
        for name in ("shear_modulus", "lame_lambda", "bulk_modulus"):
            cell[name] = np.array([getattr(cards[r], name) for r in spec.region_ids], dtype=float)
    return point, cell


def write_specimen(spec: FittedSpecimen, path, *, force: bool = False) -> Path:
    """Write the specimen file (VTU, see the module docstring) atomically; an existing file is
    refused unless ``force``."""
    from .mesh import write_mesh

    path = Path(path)
    if path.suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a specimen file must end in .vtu")
    point, cell = _point_cell_fields(spec)
    return write_mesh(path, spec.mesh(), point_data=point, cell_data=cell, overwrite=force)


def read_specimen(path, *, scenario: str, experiment: str, model: str, protocol: Mapping | None = None) -> FittedSpecimen:
    """Read a specimen file written by :func:`write_specimen` (the scalars, and a compression's
    ``protocol``, come from the card's record)."""
    from .mesh import read_mesh

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
        for f in _FIELDS:
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
    from ._io import sha256_file

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
    from ._io import sha256_file

    return {"path": Path(path).name, "sha256": sha256_file(path), "format": SPECIMEN_FORMAT,
            "nodes": int(len(spec.points)), "tets": int(len(spec.tets))}


# ============================================================================ writers
def load_steps(spec: FittedSpecimen, default: int = 10) -> int:
    """Load increments of the exported ramp: ``default`` (10), and for a compression specimen
    enough that one increment is at most :data:`MAX_STRAIN_INCREMENT` of nominal strain
    (40 % -> 20 increments)."""
    if spec.protocol is None:
        return int(default)
    e = abs(float(spec.protocol["nominal_strains"][-1]))
    return max(int(default), int(math.ceil(e / MAX_STRAIN_INCREMENT - 1e-9)))


def _component_sets(spec: FittedSpecimen, reaction_prescribed: bool = False):
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


def _refuse_pre_stretch(cards, target: str):
    lam = [c.pre_stretch for c in cards]
    if any(v != 1.0 for v in lam):
        # dropping the pre-stretch makes the incision stress-free: nothing would open
        raise ExportError(f"{target} fitted specimen: pre_stretch {sorted(set(lam))} cannot be represented by {target}, and without it "
                          "the cut specimen is stress-free and does not open (--approximate does not apply); export the incision "
                          "to febio, xpbd or vtu")


def febio_fitted_model(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False, steps: int | None = None) -> ET.Element:
    """FEBio 4.0 model of a fitted specimen.

    Nodes ``1..N`` (the specimen's order); ``tet4`` elements grouped by region (``<Elements
    name=<region>>``, numbered ``1..M`` region after region) in one ``SolidDomain`` per region;
    materials: the card's (:func:`~difftissue.export.febio_material`, a ``prestrain elastic``
    with ``F0 = diag(lambda0, lambda0, 1)`` where ``pre_stretch != 1``) on the fitted regions,
    one per fixed region otherwise. Per component ``c``: ``<NodeSet name="fixed_c">`` (held at
    zero: ``zero displacement`` with ``c_dof`` 1; the reaction set's components are instead
    prescribed 0, FEBio records reactions only there) and ``<NodeSet name="prescribed_c">`` with
    ``<MeshData><NodeData name="prescribed_uc" node_set="prescribed_c" data_type="scalar">``
    (``<node lid="k">``: the k-th node of the set, 1-based) and a ``prescribed displacement``
    BC (``<dof>c</dof>``, ``<value lc="1" type="map">prescribed_uc</value>``, ``relative`` 0),
    ramped by load controller 1 over ``steps`` static steps (default :func:`load_steps`: 10, a
    compression at most :data:`MAX_STRAIN_INCREMENT` nominal strain per step). fem_field and
    compression: ``<NodeSet name="reaction">`` (the reaction force is the sum of the ``reaction
    forces`` plot variable over it; a compression's top platen). Incision: ``cut_plus`` / ``cut_minus`` (pair k's original and duplicate, in pair
    order); the pairs are not tied, so the static solution is the opened state.
    """
    from .export import _febio_ramp_and_output, _febio_static_root, _fmt, _law, febio_material

    law = _law(card, law)
    cards = spec.region_cards(card)
    steps = load_steps(spec) if steps is None else int(steps)
    root = _febio_static_root(spec.describe(), steps)
    mats = ET.SubElement(root, "Material")
    names: dict[int, str] = {}
    mat_id = 0
    for c in cards:
        if id(c) in names:
            continue
        mat_id += 1
        el = febio_material(c, law=law, approximate=approximate, mat_id=mat_id)
        for child in list(el):
            mats.append(child)
        names[id(c)] = c.name
    if len(set(names.values())) != len(names):
        raise ExportError(f"FEBio fitted specimen: material names {sorted(names.values())} collide; rename the card")
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(spec.points, start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(_fmt(v) for v in p)
    eid = 0
    for r, rname in enumerate(spec.region_names):
        sel = np.flatnonzero(spec.region_ids == r)
        if sel.size == 0:
            continue
        elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": rname})
        for t in spec.tets[sel]:
            eid += 1
            ET.SubElement(elems, "elem", {"id": str(eid)}).text = ",".join(str(int(n) + 1) for n in t)
    ids = lambda a: ",".join(str(int(n) + 1) for n in np.atleast_1d(a))  # noqa: E731
    sets = _component_sets(spec, reaction_prescribed=True)
    for c, (zero, nz) in zip("xyz", sets):
        if zero.size:
            ET.SubElement(meshel, "NodeSet", {"name": f"fixed_{c}"}).text = ids(zero)
        if nz.size:
            ET.SubElement(meshel, "NodeSet", {"name": f"prescribed_{c}"}).text = ids(nz)
    if spec.reaction is not None:
        ET.SubElement(meshel, "NodeSet", {"name": "reaction"}).text = ids(np.flatnonzero(spec.reaction.any(axis=1)))
    if spec.pairs is not None:
        ET.SubElement(meshel, "NodeSet", {"name": "cut_plus"}).text = ids(spec.pairs[:, 0])
        ET.SubElement(meshel, "NodeSet", {"name": "cut_minus"}).text = ids(spec.pairs[:, 1])
    doms = ET.SubElement(root, "MeshDomains")
    for r, rname in enumerate(spec.region_names):
        if np.any(spec.region_ids == r):
            ET.SubElement(doms, "SolidDomain", {"name": rname, "mat": cards[r].name})
    if any(nz.size for _, nz in sets):
        md = ET.SubElement(root, "MeshData")
        for ci, (c, (_, nz)) in enumerate(zip("xyz", sets)):
            if nz.size:
                nd = ET.SubElement(md, "NodeData", {"name": f"prescribed_u{c}", "node_set": f"prescribed_{c}", "data_type": "scalar"})
                for k, n in enumerate(nz, start=1):
                    ET.SubElement(nd, "node", {"lid": str(k)}).text = _fmt(spec.prescribed[n, ci])
    bnd = ET.SubElement(root, "Boundary")
    for c, (zero, nz) in zip("xyz", sets):
        if zero.size:
            bc = ET.SubElement(bnd, "bc", {"name": f"fixed_{c}", "node_set": f"fixed_{c}", "type": "zero displacement"})
            for d in "xyz":
                ET.SubElement(bc, f"{d}_dof").text = "1" if d == c else "0"
        if nz.size:
            bc = ET.SubElement(bnd, "bc", {"name": f"prescribed_{c}", "node_set": f"prescribed_{c}", "type": "prescribed displacement"})
            ET.SubElement(bc, "dof").text = c
            ET.SubElement(bc, "value", {"lc": "1", "type": "map"}).text = f"prescribed_u{c}"
            ET.SubElement(bc, "relative").text = "0"
    _febio_ramp_and_output(root, {"reaction": ids(np.flatnonzero(spec.reaction.any(axis=1)))} if spec.reaction is not None else None)
    return root


def _quadratic_specimen(spec: FittedSpecimen):
    """``(spec with midside nodes, tets10)``: points of :func:`~difftissue.export.abaqus_quadratic`;
    a midside node is fixed / in the reaction set in a component when both edge ends are, with
    the mean of their prescribed values (the linear element's value there)."""
    from .export import abaqus_quadratic

    pts, t10, e = abaqus_quadratic(spec.points, spec.tets)
    both = lambda m: np.concatenate([m, m[e[:, 0]] & m[e[:, 1]]])  # noqa: E731
    fixed = both(spec.fixed)
    presc = np.where(fixed, np.concatenate([spec.prescribed, 0.5 * (spec.prescribed[e[:, 0]] + spec.prescribed[e[:, 1]])]), 0.0)
    reaction = None if spec.reaction is None else both(spec.reaction)
    return dataclasses.replace(spec, points=pts, fixed=fixed, prescribed=presc, reaction=reaction), t10


def abaqus_fitted_model(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False,
                        element: str = "C3D4") -> str:
    """Abaqus input of a fitted specimen: ``*NODE``, ``*ELEMENT, TYPE=<element>, ELSET=<region>`` (C3D4 default;
    C3D10 / C3D10H: midside nodes, a node set / prescribed value where both edge ends have one),
    one ``*SOLID SECTION`` and material per region, ``*NSET`` per held / prescribed component
    (``FIXED_X``, ``PRESCRIBED_X``, ...) and ``REACTION``, and one ``*STEP`` / ``*STATIC`` whose
    ``*BOUNDARY`` gives every prescribed component its own magnitude (data lines ``node, c, c,
    value``), ramped over the step (the default amplitude of a ``*STATIC`` step), with initial and
    largest increment ``1 /`` :func:`load_steps` of the step. An incision is refused: a pre-stretched one because Abaqus has no
    prestrain gradient here, and without it the cut does not open; one without pre-stretch because it carries no load."""
    from .export import (_abaqus_comment, _abaqus_element, _element_comment, _law, _wrap_ids, abaqus_material, abaqus_name,
                         abaqus_number, abaqus_reaction_print)

    law = _law(card, law)
    element = _abaqus_element(element)
    cards = spec.region_cards(card)
    _refuse_pre_stretch(cards, "Abaqus")
    if spec.experiment == "incision":
        raise ExportError(f"Abaqus fitted specimen {spec.scenario!r}: an incision is loaded only by its pre-stretch (its boundary holds "
                          "faces at zero displacement), and this one has none, so the deck would carry no load and the cut would not "
                          "open: it cannot reproduce the fitted widths; export the incision to febio, xpbd or vtu")
    lines = ["*HEADING", f"difftissue fitted specimen {spec.scenario} for material {abaqus_name(card.name)} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in spec.describe() + _element_comment(element)]
    tets = spec.tets
    if element.startswith("C3D10"):
        spec, tets = _quadratic_specimen(spec)
    lines.append("*NODE")
    for i, p in enumerate(spec.points, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(v) for v in p))
    eid = 0
    elsets = {}
    for r, rname in enumerate(spec.region_names):
        sel = np.flatnonzero(spec.region_ids == r)
        if sel.size == 0:
            continue
        es = abaqus_name(rname).upper()
        if es in elsets.values():
            raise ExportError(f"Abaqus fitted specimen: region names {list(spec.region_names)} collide once sanitised")
        elsets[r] = es
        lines.append(f"*ELEMENT, TYPE={element}, ELSET={es}")
        for t in tets[sel]:
            eid += 1
            lines.append(f"{eid}, " + ", ".join(str(int(n) + 1) for n in t))
    sets = _component_sets(spec)
    for c, (zero, nz) in zip("XYZ", sets):
        for name, arr in ((f"FIXED_{c}", zero), (f"PRESCRIBED_{c}", nz)):
            if arr.size:
                lines.append(f"*NSET, NSET={name}")
                lines += _wrap_ids(arr + 1)
    if spec.reaction is not None:
        lines.append("*NSET, NSET=REACTION")
        lines += _wrap_ids(np.flatnonzero(spec.reaction.any(axis=1)) + 1)
    done = set()
    for r, es in elsets.items():
        mname = abaqus_name(cards[r].name)
        lines += [f"*SOLID SECTION, ELSET={es}, MATERIAL={mname}", ","]
        if mname not in done:
            lines += abaqus_material(cards[r], law=law, approximate=approximate)
            done.add(mname)
    inc = abaqus_number(1.0 / load_steps(spec))
    lines += [f"*STEP, NLGEOM={'YES' if law == 'neo_hookean' else 'NO'}", "*STATIC", f"{inc}, 1.0, 1e-05, {inc}", "*BOUNDARY"]
    for c, (zero, nz) in zip("XYZ", sets):
        if zero.size:
            d = "XYZ".index(c) + 1
            lines.append(f"FIXED_{c}, {d}, {d}, 0.0")
    for ci, (zero, nz) in enumerate(sets):
        d = ci + 1
        for n in nz:
            lines.append(f"{int(n) + 1}, {d}, {d}, {abaqus_number(spec.prescribed[n, ci])}")
    lines += ["*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    if spec.reaction is not None:
        lines += abaqus_reaction_print("REACTION")
    lines.append("*END STEP")
    return "\n".join(lines) + "\n"


def xpbd_fitted_parameters(card, spec: FittedSpecimen, *, dt: float, iterations: int, substeps: int = 1, approximate: bool = False,
                           calibrate: bool = True) -> dict:
    """The XPBD JSON (``difftissue-xpbd/1``) of a fitted specimen: the header of
    :func:`~difftissue.export.xpbd_parameters` for the card, per-tet stable neo-Hookean
    compliances of each tet's region material, and a ``specimen`` block: positions [m], tets,
    regions (each with its material and whether it is the card's), lumped masses ``rho V / 4``,
    ``fixed`` node ids per component, ``prescribed_displacement`` ``[[node, component, value
    [m]], ...]``, the reaction set, and for an incision the duplicated pairs (with ``s``, depth,
    the surface order), for a compression the ``protocol`` and ``load_steps`` of the ramp, and per-tet ``pre_stretch``: a pre-stretched tet's stress-free shape is
    the mesh shrunk by ``1/lambda0`` in x and y (``Dm`` of that shape; rest volume ``V/lambda0^2``).

    ``calibrate`` (default): the written budget must reproduce the fitted experiment
    (:func:`xpbd_fitted_budget`): a specimen with a summed reaction and no pre-stretch (fem_field
    with reaction, compression) is **recalibrated** (one factor on ``mu`` and ``lambda'`` of the
    fitted regions, :func:`~difftissue.export_budget.xpbd_budget_calibration`); an incision or a
    fem_field without reaction is **checked** (opening widths / displacement field at the budget
    against the card's model, 2 % of the largest); a budget that does not reach 2 % is refused
    with the reason and a smaller ``dt`` that does (``approximate``: written, the measured error
    noted). ``calibrate=False`` writes the card's converged-limit compliances (conversion checks)."""
    from .export import _approximations, xpbd_parameters

    base = card
    if card.pre_stretch != 1.0:  # the header is the card's material; its pre-stretch is carried per tet below
        from .export import MaterialCard

        d = card.to_dict()
        d["parameters"] = {k: dict(v) for k, v in d["parameters"].items()}
        d["parameters"]["pre_stretch"] = {"value": 1.0, "unit": "1", "standard_error": None}
        base = MaterialCard.from_dict(d)
    doc = xpbd_parameters(base, dt=dt, iterations=iterations, substeps=substeps, approximate=approximate)
    doc["material"] = card.name
    cards = spec.region_cards(card)
    for c in cards:
        if c is not card:
            _approximations(c, "XPBD stable neo-Hookean", approximate=approximate, pre_stretch_ok=True)
    pts, t = spec.points, spec.tets
    v = np.abs(np.einsum("ij,ij->i", np.cross(pts[t[:, 1]] - pts[t[:, 0]], pts[t[:, 2]] - pts[t[:, 0]]), pts[t[:, 3]] - pts[t[:, 0]])) / 6.0
    lam0 = np.array([cards[r].pre_stretch for r in spec.region_ids])
    v0 = v / lam0**2  # stress-free volume
    mu = np.array([cards[r].shear_modulus for r in spec.region_ids])
    lam_s = np.array([cards[r].lame_lambda + cards[r].shear_modulus for r in spec.region_ids])
    rho = np.array([cards[r].density for r in spec.region_ids])
    h = dt / substeps
    doc["per_tet"] = {"region": spec.region_ids.tolist(), "pre_stretch": lam0.tolist(), "rest_volume": v0.tolist(),
                      "mu": mu.tolist(), "lambda_shifted": lam_s.tolist(),
                      "deviatoric_compliance": (1.0 / (mu * v0)).tolist(), "hydrostatic_compliance": (1.0 / (lam_s * v0)).tolist(),
                      "deviatoric_alpha_tilde": (1.0 / (mu * v0) / h**2).tolist(), "hydrostatic_alpha_tilde": (1.0 / (lam_s * v0) / h**2).tolist(),
                      "unit": "compliance 1/(Pa m^3); rest_volume m^3 of the stress-free tet (the mesh tet shrunk by 1/pre_stretch in x, y)"}
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(rho * v / 4.0, 4))
    presc = [[int(n), int(c), float(spec.prescribed[n, c])] for n, c in zip(*np.nonzero(spec.fixed))]
    regions = [{"name": r, "fitted": r in spec.fitted_regions, **{f: cards[i].value(f) for f in _FIELDS}}
               for i, r in enumerate(spec.region_names)]
    sp: dict[str, Any] = {"experiment": spec.experiment, "scenario": spec.scenario, "difftissue_model": spec.model,
                          "positions": pts.tolist(), "tets": t.tolist(), "regions": regions, "masses": m.tolist(),
                          "fixed": {c: np.flatnonzero(spec.fixed[:, i]).tolist() for i, c in enumerate("xyz")},
                          "prescribed_displacement": presc,
                          "rest_shape": "per tet: Dm from the positions shrunk by 1/pre_stretch in x and y (stress-free state)",
                          "assumptions": spec.describe(),
                          "note": "SI; fixed: node ids per held component; prescribed_displacement: [node, component (0 x, 1 y, 2 z), value m]"}
    if spec.reaction is not None:
        sp["reaction"] = {c: np.flatnonzero(spec.reaction[:, i]).tolist() for i, c in enumerate("xyz")}
    if spec.protocol is not None:
        sp["protocol"] = dict(spec.protocol)
        sp["load_steps"] = load_steps(spec)
        sp["load_note"] = ("compression: ramp the prescribed displacements linearly from 0 over load_steps quasi-static steps "
                           "(load fraction t <-> nominal strain t * protocol.nominal_strains[-1]); engineering stress = "
                           "-(sum of the z reactions over reaction.z) / protocol.area")
    if spec.pairs is not None:
        sp["cut"] = {"pairs": spec.pairs.tolist(), "pair_s": spec.pair_s.tolist(), "pair_depth": spec.pair_depth.tolist(),
                     "surface_pairs": spec.surface_pairs.tolist(),
                     "note": "pairs (original, duplicate) are separate, untied nodes: the opened cut; width = |x_a - x_b|"}
    doc["specimen"] = sp
    if calibrate:
        xpbd_fitted_budget(doc, card, spec, approximate=approximate)
    else:
        doc["notes"].append("NOT calibrated for the budget (calibrate=False): the compliances are the card's converged-limit values "
                            "(see validity)")
    return doc


def _budget_fractions(spec: FittedSpecimen) -> list[float]:
    """Load states of a budget recalibration: a compression's protocol strains (up to
    :data:`RECALIBRATION_STATES`), else 1 (the fem_field's one prescribed state)."""
    return _recalibration_fractions(spec)


def xpbd_fitted_budget(doc: dict, card, spec: FittedSpecimen, *, approximate: bool) -> dict:
    """Make the fitted XPBD document reproduce its fitted experiment at the written budget
    (issue 16), in place.

    * A summed reaction and no pre-stretch (fem_field with reaction, compression): the reference
      is the fit's model (``spec.model``) at the card's values on the specimen (per-region
      materials), solved by difftissue's static solver at the protocol's strains (a
      compression, up to 4) or the prescribed state (a fem_field): what the fit matched. The
      XPBD compliances of the fitted regions are recalibrated by one factor on ``mu`` and
      ``lambda'`` (nu kept) so that standard XPBD at the written budget is within 2 % per state
      (:func:`~difftissue.export_budget.xpbd_budget_calibration`); refused with a suggested
      ``dt`` when it cannot be.
    * No reaction or a pre-stretch (an incision, a fem_field without reaction): no force to
      scale (a common stiffness factor leaves a displacement-loaded or pre-stretch-loaded
      equilibrium unchanged), so the written budget is **checked** (:func:`xpbd_fitted_field_check`):
      the opening widths of the cut pairs (incision) or the displacement field (fem_field) of
      standard XPBD at the budget against the fit's model, within 2 % of the largest; refused
      with a smaller ``dt`` that reaches it, or with ``approximate`` written with the error noted.
    """
    from .export_budget import card_reference_reactions, xpbd_budget_calibration

    fitted_tets = np.array([spec.region_names[r] in spec.fitted_regions for r in spec.region_ids])
    pre = spec.pre_stretches(card)
    if spec.reaction is None or np.any(pre != 1.0):
        return xpbd_fitted_field_check(doc, card, spec, approximate=approximate)
    fr = _budget_fractions(spec)
    observe = spec.reaction & spec.fixed
    try:
        ref = card_reference_reactions(card, spec.mesh(), spec.fixed, spec.prescribed, observe, fr,
                                       material=spec.material(card), model=spec.model)
    except ExportError as e:
        if not approximate:
            raise ExportError(f"XPBD fitted specimen {spec.scenario!r}: {e}; pass approximate=True (--approximate) to write the "
                              "card's converged-limit compliances") from None
        doc["notes"].append(f"APPROXIMATION: not calibrated for the budget: {e}")
        return doc
    xpbd_budget_calibration(doc, ref, spec.fixed, spec.prescribed, observe, fr, approximate=approximate, fitted_tets=fitted_tets)
    rec = doc["budget_calibration"]
    rec["reference_model"] = spec.model
    rec["scenario"] = spec.scenario
    if spec.protocol is not None:
        rec["nominal_strains"] = [f * float(spec.protocol["nominal_strains"][-1]) for f in fr]
    doc["notes"].append(doc["validity"])
    return doc


def _xpbd_fitted_observable(spec: FittedSpecimen, u: np.ndarray) -> np.ndarray:
    """The checked observable of a reaction-free specimen: the cut pairs' opening widths [m]
    (incision) or the displacement field [m] (fem_field)."""
    if spec.pairs is not None:
        x = spec.points + u
        return np.linalg.norm(x[spec.pairs[:, 0]] - x[spec.pairs[:, 1]], axis=1)
    return np.asarray(u)


#: Halvings of dt tried when a reaction-free XPBD specimen misses 2 % at its budget (to suggest one).
FIELD_CHECK_HALVINGS = 3


def xpbd_fitted_field_check(doc: dict, card, spec: FittedSpecimen, *, approximate: bool, max_steps: int = 5_000) -> dict:
    """Check (in place) that standard XPBD at the document's budget reproduces a reaction-free
    fitted specimen: ``max |o_xpbd - o_ref| / max |o_ref|`` <= 2 % with ``o`` the opening widths
    (incision) or the displacement field (fem_field); ``o_ref`` of the fit's model at the card's
    values by difftissue's static solver, ``o_xpbd`` of the document's per-tet compliances and
    stress-free shapes run like a real-time engine (multipliers reset every substep, fully damped
    frames to rest). Refused with the reason and a smaller ``dt`` (halved up to
    :data:`FIELD_CHECK_HALVINGS` times) that
    reaches 2 %; ``approximate`` writes the file with the measured error noted. The result is
    recorded in ``doc["budget_check"]``."""
    import jax.numpy as jnp

    from .boundary import BoundaryConditions
    from .export_budget import MAX_BUDGET_ERROR, _snh_constraints
    from .models import make_model
    from .solvers.static import solve_static
    from .solvers.xpbd import XPBDSettings, xpbd_quasi_static_constraints

    what = "opening widths of the cut pairs" if spec.pairs is not None else "displacement field"
    mesh = spec.mesh()
    if spec.model == "springs_volume":
        from .scenarios import recover_lattice

        mesh = recover_lattice(mesh)
    bc = BoundaryConditions(spec.fixed, spec.prescribed, np.zeros_like(spec.prescribed))
    ref = _xpbd_fitted_observable(spec, np.asarray(solve_static(make_model(mesh, spec.model), spec.material(card), bc).displacement))
    scale = float(np.max(np.abs(ref)))
    if not scale > 0:
        raise ExportError(f"XPBD fitted specimen {spec.scenario!r}: the fit's model gives zero {what}: nothing to reproduce")
    cons, pts, masses = _snh_constraints(doc, 1.0, None)
    st = doc["setting"]
    bcj = BoundaryConditions(spec.fixed, jnp.asarray(spec.prescribed), jnp.zeros(spec.prescribed.shape))

    def error(dt):
        settings = XPBDSettings(dt=float(dt), substeps=int(st["substeps"]), iterations=int(st["iterations"]), damping=float("inf"),
                                warm_start=False)
        sol = xpbd_quasi_static_constraints((cons,), jnp.asarray(pts), jnp.asarray(masses), bcj, settings=settings, tol=1e-8,
                                            max_steps=max_steps, throw=False)
        u = np.asarray(sol.displacement)
        if not (bool(sol.converged) and np.all(np.isfinite(u))):
            return float("inf"), False
        return float(np.max(np.abs(_xpbd_fitted_observable(spec, u) - ref)) / scale), True

    err, rested = error(float(st["dt"]))
    ok = rested and err <= MAX_BUDGET_ERROR
    budget = f"dt = {float(st['dt']):.6g} s, substeps = {st['substeps']}, iterations = {st['iterations']}"
    doc["budget_check"] = {"target": "xpbd", "setting": dict(st), "observable": what, "reference_model": spec.model,
                           "relative_error": err if rested else None, "came_to_rest": rested, "within_tolerance": ok,
                           "tolerance": MAX_BUDGET_ERROR,
                           "note": f"max |XPBD - {spec.model}| / max |{spec.model}| of the {what}; standard XPBD (multipliers reset "
                                   "every substep, Gauss-Seidel), fully damped frames to rest; no stiffness factor (no reaction to "
                                   "scale, and a common factor leaves this equilibrium unchanged)"}
    doc["setting"]["multipliers"] = "reset every substep (standard XPBD); Gauss-Seidel iterations"
    if ok:
        doc["validity"] = (f"VERIFIED for this budget ({budget}, standard XPBD): difftissue's XPBD solver running these compliances "
                           f"reproduces the {what} of the card's {spec.model} model on the fitted experiment to {100 * err:.3g} % of "
                           "the largest; the card's values unchanged (no reaction to recalibrate on); valid for this budget, mesh and "
                           "loading only")
        doc["notes"].append(doc["validity"])
        return doc
    why = ("does not come to rest at this budget (diverges or creeps)" if not rested else
           f"gives the {what} {100 * err:.3g} % off (of the largest) against the card's {spec.model} model")
    msg = (f"XPBD fitted {spec.experiment} specimen {spec.scenario!r} at {budget}: standard XPBD {why}; it has no summed reaction, so "
           f"no stiffness factor can be recalibrated, and the written budget does not reproduce the fitted experiment within "
           f"{100 * MAX_BUDGET_ERROR:g} %")
    for k in range(1, FIELD_CHECK_HALVINGS + 1):
        dt = float(st["dt"]) / 2**k
        e2, r2 = error(dt)
        if r2 and e2 <= MAX_BUDGET_ERROR:
            msg += (f"; a budget that reaches it: dt = {dt:.6g} s with {st['iterations']} iterations and {st['substeps']} substep(s) "
                    f"(or keep dt and use {int(st['substeps']) * 2**k} substeps): {100 * e2:.3g} %")
            doc["budget_check"]["suggested_dt"] = dt
            break
    else:
        msg += (f"; no dt down to {float(st['dt']) / 2**FIELD_CHECK_HALVINGS:.3g} s reaches it with {st['iterations']} iterations: "
                "use more iterations or a smaller dt")
    if not approximate:
        raise ExportError(msg + "; pass approximate=True (--approximate) to write it with the measured error noted")
    doc["validity"] = "APPROXIMATION: " + msg
    doc["notes"].append(doc["validity"])
    return doc


def sofa_fitted_scene(card, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """SOFA scene of a fitted specimen with one material and no pre-stretch (a fem_field or
    compression fit).

    fem_field: the prescribed displacements are initial positions held by projective constraints: the
    ``MechanicalObject`` gets ``rest_position`` = the reference mesh and ``position`` = the
    reference moved by the prescribed values on the prescribed components (the free ones start
    at rest); ``FixedProjectiveConstraint`` (all three components prescribed) and
    ``PartialFixedProjectiveConstraint`` with ``fixedDirections`` (some) hold them: both zero
    the Newton correction of those components (``projectResponse``) and leave the positions
    alone (``projectPosition`` is empty), and SOFA's ``TetrahedronFEMForceField`` (``reinit``)
    and ``TetrahedronHyperelasticityFEMForceField`` (``init``) take their rest shape from the
    ``MechanicalObject``'s rest position (SOFA source, docs/export.md). ``StaticSolver`` +
    ``SparseLDLSolver``; ``MeshTopology`` of the reference mesh; ``MeshMatrixMass`` of the
    card's density. Several region materials or a pre-stretch (an incision) are refused.

    compression (finite strain: the platen displacement is ramped, not imposed at once, which
    would invert the top layer of tets): ``position`` = ``rest_position`` = the mesh; the nodes
    with a nonzero prescribed value (the top platen) are moved by one
    ``PartialLinearMovementProjectiveConstraint`` per (held components, value) group with
    ``movedDirections`` = the held components (bonded ``1 1 1``, frictionless ``0 0 1``),
    ``keyTimes="0 1 1000000"`` and ``movements`` ``0``, the prescribed value, the prescribed
    value: in SOFA's source it sets ``x = x0 + m(t)`` on the moved directions (``x0`` the
    positions when it first projects) and zeroes their Newton correction only while a later key
    time exists, so the value is held after ``t = 1`` (a key time of 1 alone would free the top
    at ``t = 1``). The root ``dt`` is ``1 /`` :func:`load_steps`, so the ramp takes that many
    steps; run a few more for the Newton iterations to settle. The held-at-zero components
    (bottom platen, rigid-body pins) are Fixed / PartialFixed as above. ``StaticSolver`` gets
    ``newton_iterations="25"`` and tight correction / residual thresholds (its defaults are 1
    iteration and 1e-5 absolute, too coarse for a millimetre specimen).
    """
    from .export import (_SOFA_SPECIMEN_PLUGINS, _approximations, _fmt, _header_lines, _law, _sofa_output, _sofa_static_solver,
                         _xml_comment, sofa_force_field)

    law = _law(card, law)
    cards = spec.region_cards(card)
    if any(c.pre_stretch != 1.0 for c in cards):
        raise ExportError("SOFA fitted specimen: a pre-stretch (an incision) cannot be written for SOFA (no prestrain in its tetrahedral "
                          "force fields), and without it the cut specimen does not open; export the incision to febio, xpbd or vtu")
    used = {id(cards[r]) for r in np.unique(spec.region_ids)}
    if len(used) > 1:
        raise ExportError(f"SOFA fitted specimen: {len(used)} region materials; this SOFA scene holds one force field with one "
                          "material; export to febio, abaqus, xpbd or vtu")
    notes = _approximations(card, "SOFA " + law, approximate=approximate)
    ramp = spec.experiment == "compression"
    steps = load_steps(spec)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": _fmt(1.0 / steps) if ramp else "1"})
    for line in _header_lines(card, "SOFA", law) + notes + spec.describe():
        root.append(_xml_comment(line))
    if ramp:
        root.append(_xml_comment(f"prescribed displacements: the top platen is moved by PartialLinearMovementProjectiveConstraint from 0 "
                                 f"at t = 0 to its prescribed value at t = 1 ({steps} steps of dt = 1/{steps}) and held there after; "
                                 "run a few more steps for the Newton iterations to settle; zero components held by "
                                 "(Partial)FixedProjectiveConstraint"))
    else:
        root.append(_xml_comment("prescribed displacements: MechanicalObject position = rest_position + prescribed value on the held "
                                 "components, held by (Partial)FixedProjectiveConstraint; each StaticSolver step is a Newton solve from "
                                 "the current positions: run a few steps until the positions stop changing"))
    plugins = ["Sofa.Component.SolidMechanics.FEM.Elastic" if law == "linear" else "Sofa.Component.SolidMechanics.FEM.HyperElastic",
               *_SOFA_SPECIMEN_PLUGINS]
    for p in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    rest = spec.points
    _sofa_static_solver(node, float(np.linalg.norm(np.ptp(rest, axis=0))))
    moving = (spec.fixed & (spec.prescribed != 0.0)).any(axis=1) if ramp else np.zeros(len(rest), dtype=bool)
    pos = rest + np.where(spec.fixed & ~moving[:, None], spec.prescribed, 0.0)
    flat = lambda a: " ".join(_fmt(v) for v in np.asarray(a, dtype=float).reshape(-1))  # noqa: E731
    ET.SubElement(node, "MeshTopology", {"name": "topology", "position": flat(rest),
                                         "tetrahedra": " ".join(str(int(n)) for n in spec.tets.reshape(-1))})
    ET.SubElement(node, "MechanicalObject", {"name": "dofs", "template": "Vec3d", "position": flat(pos), "rest_position": flat(rest)})
    ET.SubElement(node, "MeshMatrixMass", {"massDensity": _fmt(card.density)})
    _sofa_output(node, float(root.get("dt", "1")))
    node.append(sofa_force_field(card, law=law, approximate=True))
    patterns = {}
    for n in np.flatnonzero(spec.fixed.any(axis=1) & ~moving):
        patterns.setdefault(tuple(bool(v) for v in spec.fixed[n]), []).append(int(n))
    for pat, nodes in sorted(patterns.items(), reverse=True):
        tag = "".join(c for c, b in zip("xyz", pat) if b)
        idx = " ".join(str(n) for n in nodes)
        if all(pat):
            ET.SubElement(node, "FixedProjectiveConstraint", {"name": f"prescribed_{tag}", "indices": idx})
        else:
            ET.SubElement(node, "PartialFixedProjectiveConstraint", {"name": f"prescribed_{tag}", "template": "Vec3d", "indices": idx,
                                                                     "fixedDirections": " ".join("1" if b else "0" for b in pat)})
    groups: dict[tuple, list[int]] = {}
    for n in np.flatnonzero(moving):
        pat = tuple(bool(v) for v in spec.fixed[n])
        groups.setdefault((pat, tuple(float(v) if b else 0.0 for v, b in zip(spec.prescribed[n], pat))), []).append(int(n))
    for k, ((pat, value), nodes) in enumerate(sorted(groups.items())):
        m = " ".join(_fmt(v) for v in value)
        ET.SubElement(node, "PartialLinearMovementProjectiveConstraint", {
            "name": f"moved_{''.join(c for c, b in zip('xyz', pat) if b)}_{k}", "template": "Vec3d",
            "indices": " ".join(str(n) for n in nodes), "movedDirections": " ".join("1" if b else "0" for b in pat),
            "keyTimes": "0 1 1000000", "movements": f"0 0 0  {m}  {m}"})
    return root


# ============================================================================ recalibration
#: Largest number of protocol strains a compression recalibration solves (evenly picked, the last included).
RECALIBRATION_STATES = 4


def specimen_reactions(card, spec: FittedSpecimen, model: str, fractions=(1.0,)) -> np.ndarray:
    """Summed reaction forces [N] over ``spec.reaction`` (one per summed component) of
    difftissue's ``model`` with ``card``'s values on the fitted regions, the prescribed
    displacements scaled by each of ``fractions`` (shape ``(len(fractions), n_components)``).
    ``springs_volume`` gets the specimen's cube lattice back (``recover_lattice``; a mesh that
    is no structured grid is refused there). Solved by difftissue's static solver, ramped in
    increments of at most 5 % nominal strain for a compression."""
    from .boundary import BoundaryConditions
    from .models import make_model
    from .solvers.static import solve_static

    if spec.reaction is None:
        raise ExportError(f"fitted specimen {spec.scenario!r} has no reaction set")
    mesh = spec.mesh()
    if model == "springs_volume":
        from .scenarios import recover_lattice

        mesh = recover_lattice(mesh)
    m = make_model(mesh, model)
    mat = spec.material(card)
    comps = [c for c in range(3) if spec.reaction[:, c].any()]
    e_last = abs(float(spec.protocol["nominal_strains"][-1])) if spec.protocol is not None else 0.0
    out = []
    for f in fractions:
        bc = BoundaryConditions(spec.fixed, spec.prescribed * float(f), np.zeros_like(spec.prescribed))
        sol = solve_static(m, mat, bc, load_steps=max(1, int(math.ceil(abs(f) * e_last / 0.05 - 1e-9))))
        r = np.asarray(sol.reaction)
        out.append([float(np.sum(r[spec.reaction[:, c], c])) for c in comps])
    return np.asarray(out)


def _recalibration_fractions(spec: FittedSpecimen) -> list[float]:
    """Load fractions solved: 1 (fem_field), or up to :data:`RECALIBRATION_STATES` protocol
    strains of a compression as fractions of the last."""
    if spec.protocol is None:
        return [1.0]
    e = np.asarray(spec.protocol["nominal_strains"], dtype=float)
    idx = np.unique(np.round(np.linspace(0, len(e) - 1, min(RECALIBRATION_STATES, len(e)))).astype(int))
    return [float(e[i] / e[-1]) for i in idx]


def recalibrated_card(card, spec: FittedSpecimen, law: str, *, approximate: bool = False):
    """``card`` (a lattice model, :func:`~difftissue.export.model_mismatch`) recalibrated to the
    continuum ``law`` on its own fitted experiment ``spec``.

    The fitted experiment is rebuilt from the specimen file and solved twice with difftissue:
    the card's model at the card's values (what the fit matched to the data), and the
    continuum model of the law (:data:`~difftissue.export.LAW_MODELS`: ``fem_linear`` /
    ``fem_neo_hookean``, the same P1-tet energies the targets solve) at the same values. With
    displacements prescribed and nu fixed every energy here is proportional to E, so the
    reactions are too: the least-squares factor ``c = <R_card, R_law> / <R_law, R_law>`` over the
    solved load states gives ``E' = c E`` exactly (one state: the reaction is reproduced to the
    solver's precision). nu is kept (a summed reaction does not determine it), the cubic
    coefficient is dropped (its effect at these strains is absorbed into E'; the residual per
    state is recorded). Returns a new card (model ``fem_linear`` / ``fem_neo_hookean``) whose
    ``provenance["recalibration"]`` holds the factor, the reactions and ``notes`` for the file
    headers, including the signed error the card's own values would have had.
    Refused (one line) for an incision, a fem_field without reaction, fixed regions or a
    pre-stretch, and a cubic coefficient ``b != 0`` unless ``approximate`` (the law cannot
    follow the stiffening: E' is then a least-squares compromise, its residuals noted)."""
    from .export import LAW_MODELS, _model_parts, model_mismatch

    why = model_mismatch(card, law)
    own = next(m for m in _model_parts(card.model) if m in ("springs_volume",))
    if spec.experiment == "incision" or spec.reaction is None or card.pre_stretch != 1.0 or spec.region_materials:
        raise ExportError(f"{why}; the fitted {spec.experiment} specimen {spec.scenario!r} cannot be recalibrated (needs a summed "
                          "reaction, one material and no pre-stretch); pass approximate=True (--approximate) to write the card's values "
                          "with the measured error noted")
    if card.cubic_coefficient != 0.0 and not approximate:
        raise ExportError(f"cubic_coefficient b = {card.cubic_coefficient:g} cannot be represented by the continuum {law} law; pass "
                          "approximate=True (--approximate) to recalibrate E alone (b dropped, the residual per load state noted)")
    fr = _recalibration_fractions(spec)
    ref = specimen_reactions(card, spec, own, fr)
    tgt = specimen_reactions(card, spec, LAW_MODELS[law], fr)
    return recalibrated_from_reactions(card, law, own, why, ref, tgt, scenario=spec.scenario,
                                       states=f"load fraction(s) {[round(f, 6) for f in fr]}", record={"load_fractions": fr})


def recalibrated_from_reactions(card, law: str, own: str, why: str, ref, tgt, *, scenario: str, states: str,
                                record: Mapping | None = None, extra_notes=()):
    """The recalibrated card from the reactions [N] of the card's model ``own`` (``ref``: what
    the fit matched) and of the target's continuum model at the card's values (``tgt``), one per
    solved load state (same shapes): ``E' = c E`` with the least-squares ``c = <ref, tgt> /
    <tgt, tgt>`` (every energy here is proportional to E, so one state is reproduced exactly),
    nu kept, b dropped. ``provenance["recalibration"]`` records the factor, both reactions, the
    signed errors before and after, ``record`` and the ``notes`` the file headers print."""
    from .export import LAW_MODELS, MaterialCard

    ref, tgt = np.asarray(ref, dtype=float), np.asarray(tgt, dtype=float)
    c = float(np.vdot(ref, tgt) / np.vdot(tgt, tgt))
    if not (math.isfinite(c) and c > 0):
        raise ExportError(f"recalibration to the {law} law failed: factor {c!r} from reactions {ref.tolist()} / {tgt.tolist()} N")
    before = tgt / ref - 1.0
    after = c * tgt / ref - 1.0
    params = {k: dict(v) for k, v in card.parameters.items()}
    E = card.youngs_modulus
    params["youngs_modulus"].update(value=c * E, recalibrated_from=E)
    if params["youngs_modulus"].get("standard_error") is not None:
        params["youngs_modulus"]["standard_error"] *= c
    b = card.cubic_coefficient
    if "cubic_coefficient" in params:
        params["cubic_coefficient"].update(value=0.0, recalibrated_from=b)
    fmt = lambda a: ", ".join(f"{100 * v:+.3g} %" for v in np.ravel(a))  # noqa: E731
    notes = [f"RECALIBRATED for the continuum {law} law" + (" (APPROXIMATION: b dropped)" if b else "") + f": {why}",
             f"E = {c * E:.10g} Pa = {c:.6g} x the card's {E:.10g} Pa ({own}), nu = {card.poisson_ratio:.10g} kept"
             + (f", cubic_coefficient b = {b:g} dropped (absorbed into E at these strains)" if b else ""),
             f"the fitted experiment {scenario!r} solved in difftissue at {states}: "
             f"{LAW_MODELS[law]} at the card's values gives reaction error {fmt(before)} against {own} (what the fit matched); "
             f"after recalibration {fmt(after)}", *extra_notes]
    prov = dict(card.provenance or {})
    prov["recalibration"] = {"from_model": own, "to_model": LAW_MODELS[law], "law": law, "factor": c, "scenario": scenario,
                             **dict(record or {}), "reaction_card_model": ref.tolist(), "reaction_law_at_card_values": tgt.tolist(),
                             "signed_error_before": np.ravel(before).tolist(), "signed_error_after": np.ravel(after).tolist(),
                             "notes": notes}
    return MaterialCard(model=LAW_MODELS[law], parameters=params, name=card.name, provenance=prov)


_REFUSED: dict[str, str] = {}
_PBD_WHY = ("a pypbd scene holds fixed particles and one moved set (a particle is static, all components, or free), not per-node "
            "prescribed displacements, region materials or a pre-stretch")


def _write_fitted_pbd(card, path, spec: FittedSpecimen, *, approximate: bool, force: bool, dt, iterations, substeps) -> Path:
    """pypbd scene of a fitted compression with bonded platens on a block (the only fitted experiment
    a pypbd scene can hold), recalibrated for its budget on the protocol's strains
    (:func:`difftissue.pbd.pbd_scene`, :mod:`difftissue.export_budget`)."""
    from .errors import ModelError
    from .export import _specimen_sets, _write_text
    from .pbd import pbd_scene
    from .scenarios import recover_lattice

    if spec.experiment != "compression":
        raise ExportError(f"pypbd fitted specimen ({spec.experiment}): {_PBD_WHY}; export to febio, abaqus, xpbd or vtu "
                          "(pypbd takes a fitted compression with bonded platens, or --specimen indentation with a bonded flat punch)")
    if spec.protocol["platens"] != "bonded":
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: frictionless platens hold u_z only, and a pypbd particle is "
                          "either static (all components) or free, so the platens cannot be written; export to febio, abaqus, "
                          "xpbd or vtu")
    if spec.region_materials:
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: {_PBD_WHY}")
    try:
        mesh = recover_lattice(spec.mesh())
    except ModelError as e:
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: the pypbd scene is difftissue's spring lattice, which needs a "
                          f"structured block ({e}); a cylinder cannot be written; export to febio, abaqus, xpbd or vtu") from None
    base, top, _ = _specimen_sets(mesh)
    want = np.zeros_like(spec.fixed)
    want[base] = True
    want[top] = True
    if not np.array_equal(want, spec.fixed) or not np.allclose(spec.prescribed[top], [0.0, 0.0, spec.protocol["top_displacement"]]):
        raise ExportError(f"pypbd fitted compression {spec.scenario!r}: the specimen's held components are not the bonded base and "
                          "top faces of the block; " + _PBD_WHY)
    fr = [float(v) for v in (np.asarray(spec.protocol["nominal_strains"], dtype=float) / spec.protocol["nominal_strains"][-1])]
    if len(fr) > 4:
        fr = _recalibration_fractions(spec)
    scene = pbd_scene(card, mesh, dt=dt, iterations=iterations, substeps=substeps, approximate=approximate,
                      displacement=float(spec.protocol["top_displacement"]), load_fractions=fr)
    scene["header"] = scene["header"] + spec.describe()
    scene["fitted_specimen"] = {"scenario": spec.scenario, "experiment": spec.experiment, "protocol": dict(spec.protocol),
                                "note": "the protocol's strains are the load fractions of budget_calibration (nominal strain = "
                                        "fraction x the last); engineering stress = reaction / protocol.area"}
    return _write_text(path, json.dumps(scene, indent=1, allow_nan=False) + "\n", force)


def write_fitted(card, to: str, path, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False,
                 force: bool = False, dt: float | None = None, iterations: int | None = None, substeps: int | None = None,
                 element: str = "C3D4") -> Path:
    """Write the complete model of the fitted specimen ``spec`` for target ``to``.

    A lattice card (``springs_volume``) is recalibrated to the target's continuum law on this
    experiment before FEBio, SOFA and Abaqus are written (:func:`recalibrated_card`; the file
    header says so); where that is impossible (incision, no reaction) it is refused unless
    ``approximate``, which writes the card's values with the measured error noted."""
    from .export import TARGETS, _write_text, _xml_text

    if to == "pbd":
        return _write_fitted_pbd(card, path, spec, approximate=approximate, force=force, dt=dt, iterations=iterations,
                                 substeps=substeps)
    if to in _REFUSED:
        raise ExportError(_REFUSED[to])
    if law == "springs":
        raise ExportError("law='springs' is written for the SOFA compression block only, not for a fitted specimen")
    if to in ("febio", "sofa", "abaqus"):
        from .export import _law, model_mismatch

        lw = _law(card, law)
        if model_mismatch(card, lw) and not (approximate and (spec.experiment == "incision" or spec.reaction is None)):
            card = recalibrated_card(card, spec, lw, approximate=approximate)
    if to == "febio":
        return _write_text(path, _xml_text(febio_fitted_model(card, spec, law=law, approximate=approximate)), force)
    if to == "sofa":
        return _write_text(path, _xml_text(sofa_fitted_scene(card, spec, law=law, approximate=approximate)), force)
    if to == "abaqus":
        return _write_text(path, abaqus_fitted_model(card, spec, law=law, approximate=approximate, element=element), force)
    if to == "xpbd":
        if dt is None or iterations is None:
            raise ExportError("an XPBD export needs the time step dt and the iteration count (--dt, --iterations)")
        doc = xpbd_fitted_parameters(card, spec, dt=dt, iterations=iterations, substeps=1 if substeps is None else substeps,
                                     approximate=approximate)
        return _write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n", force)
    if to == "vtu":
        from .mesh import write_mesh

        if Path(path).suffix.lower() != ".vtu":
            raise ExportError(f"{path}: a VTU export must end in .vtu")
        point, cell = _point_cell_fields(spec, card)
        return write_mesh(path, spec.mesh(), point_data=point, cell_data=cell, overwrite=force)
    raise ExportError(f"unknown export target {to!r}; choose one of {list(TARGETS)}")
