"""The material card: a fitted (or hand-written) material as versioned JSON, the source of truth
of every export (DESIGN.md §4, docs/export.md).

:class:`MaterialCard` (``"card_version": 1``) holds the elastic model that was fitted, the energy
it refers to, every parameter with unit and standard error, and provenance; :func:`card_from_fit`
and :func:`card_from_fit_json` build one from a fit, :func:`read_card` / :func:`write_card` read
and write it, :func:`resolve_effective_modulus` converts a card whose E rests on an assumed nu,
:func:`scenario_record` is the record of a fitted experiment the card keeps
(``provenance.scenario_records``: what a scenario's ``record()`` says about itself), and
:func:`header_lines` the comment lines every written file starts with.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from .._io import atomic_output, sha256_file
from ..errors import EffectiveModulusError, ExportError
from ..materials import FIELD_UNITS, Material
from ._common import UNITS, UNITS_LINE, difftissue_version, finite

__all__ = [
    "CARD_VERSION",
    "MODEL_ENERGIES",
    "PARAMETER_UNITS",
    "MATERIAL_FIELDS",
    "OPTIONAL_MATERIAL_FIELDS",
    "FINITE_STRAIN_MODELS",
    "MaterialCard",
    "model_parts",
    "portable_path",
    "card_from_fit",
    "card_from_fit_json",
    "resolve_effective_modulus",
    "read_card",
    "write_card",
    "scenario_record",
    "header_lines",
]

#: The material fields of a card and of :class:`~difftissue.materials.Material`, in order.
MATERIAL_FIELDS = ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")

#: Fields a card holds only when given: ``pre_stretch_y`` (anisotropic pre-stretch along y;
#: absent means equal to ``pre_stretch``).
OPTIONAL_MATERIAL_FIELDS = ("pre_stretch_y",)


#: Version of the card schema written by :meth:`MaterialCard.to_json`.
CARD_VERSION = 1


#: The energy each elastic model of difftissue refers to, in words.
MODEL_ENERGIES: dict[str, str] = {
    "springs_volume": (
        "cube lattice of central springs (edges and face diagonals, force k x + a x^3 with "
        "a = b k / L0^2) plus a per-cell volume term K (V - V0)^2 / (2 V0) over each hexahedral "
        "lattice cube (V: the cube's volume); under homogeneous strain its small-strain response "
        "equals isotropic linear elasticity (E, nu) with uniaxial stiffening sigma = E (eps + b eps^3); "
        "E and nu are lattice-effective values, not those of a continuum tet mesh under "
        "inhomogeneous strain"
    ),
    "springs_volume_mesh_lattice": (
        "springs_volume (cube lattice of central springs, force k x + a x^3 with a = b k / L0^2, plus a per-cell volume term "
        "K (V - V0)^2 / (2 V0)) whose pre-stretched regions keep the mesh cell's spring constants and shrink only the rest "
        "lengths and rest volumes by the pre-stretch (springs_volume builds them on the stress-free cell); equal to "
        "springs_volume without pre-stretch; E and nu are lattice-effective values"
    ),
    "springs_volume_matched_lattice": (
        "springs_volume (cube lattice of central springs, force k x + a x^3 with a = b k / L0^2, plus a per-cell volume term "
        "K (V - V0)^2 / (2 V0)) whose pre-stretched regions scale the mesh cell's spring constants per spring class and "
        "shrink the rest lengths and rest volumes by a lattice pre-stretch of their own, chosen so that the cell carries the "
        "neo-Hookean's tension and incremental moduli at the pre-stretch; equal to springs_volume without pre-stretch; "
        "E and nu are lattice-effective values"
    ),
    "fem_linear": "linear isotropic elasticity, W = lambda/2 tr(eps)^2 + mu eps:eps (small strain)",
    "fem_neo_hookean": "compressible neo-Hookean, W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2",
    "stable_neo_hookean": (
        "stable neo-Hookean (Smith et al. 2018), W = mu/2 (I1 - 3) + lambda'/2 (J - 1 - mu/lambda')^2 "
        "with lambda' = lambda + mu, so that its small-strain response is (E, nu)"
    ),
    "analytic": "small-strain linear isotropic elasticity (closed-form contact / compression solutions)",
}


#: SI unit of every parameter a card may hold.
PARAMETER_UNITS: dict[str, str] = FIELD_UNITS


_DEFAULTS = {"cubic_coefficient": 0.0, "density": 1000.0, "pre_stretch": 1.0}


_REQUIRED = ("youngs_modulus", "poisson_ratio")


_RULES = {
    "youngs_modulus": (lambda v: v > 0, "must be > 0"),
    "poisson_ratio": (lambda v: -1.0 < v < 0.5, "must lie in (-1, 0.5) (0.5 is the incompressible limit)"),
    "density": (lambda v: v > 0, "must be > 0"),
    "pre_stretch": (lambda v: v > 0, "must be > 0"),
    "pre_stretch_y": (lambda v: v > 0, "must be > 0"),
}


#: Models whose energy is geometrically nonlinear: their cards export to neo-Hookean by default.
FINITE_STRAIN_MODELS = ("springs_volume", "springs_volume_mesh_lattice", "springs_volume_matched_lattice", "fem_neo_hookean",
                        "stable_neo_hookean")


def model_parts(model: str) -> list[str]:
    """``"hertz; springs_volume"`` (a joint fit) -> ``["hertz", "springs_volume"]``."""
    return [m.strip() for m in str(model).split(";") if m.strip()]


def _default_energy(model: str) -> str:
    """Energy in words; names outside :data:`MODEL_ENERGIES` (``hertz``, ``sneddon_cone``, ...)
    are difftissue's closed-form solutions, all small-strain linear elasticity."""
    out = []
    for m in model_parts(model):
        out.append(f"{m}: {MODEL_ENERGIES[m]}" if m in MODEL_ENERGIES else f"{m}: {MODEL_ENERGIES['analytic']}")
    return out[0].split(": ", 1)[1] if len(out) == 1 else "; ".join(out)


@dataclasses.dataclass
class MaterialCard:
    """A fitted (or hand-written) material, versioned, with units, uncertainty and provenance.

    Attributes:
        model: the elastic model the parameters belong to (``springs_volume``, ``fem_linear``,
            ``fem_neo_hookean``, ``stable_neo_hookean``, ``analytic`` or another name).
        parameters: ``{field: {"value": float, "unit": str, "standard_error": float | None}}``;
            ``youngs_modulus`` and ``poisson_ratio`` are required, ``cubic_coefficient``,
            ``density`` and ``pre_stretch`` default to 0, 1000 kg/m^3 and 1. A ``standard_error``
            of ``None`` means "not fitted" (fixed) or "not determined by the data".
        energy: the energy the parameters refer to, in words (defaults from :data:`MODEL_ENERGIES`).
        name: a material name for the writers (escaped or sanitised per target).
        provenance: free-form record: ``data_files`` (path, sha256), ``scenarios``,
            ``difftissue_version``, ``created`` and whatever else the producer adds.
        card_version: schema version (:data:`CARD_VERSION`).
    """

    model: str
    parameters: dict[str, dict[str, Any]]
    energy: str = ""
    name: str = "tissue"
    provenance: dict[str, Any] = dataclasses.field(default_factory=dict)
    card_version: int = CARD_VERSION

    def __post_init__(self):
        if not self.energy:
            self.energy = _default_energy(self.model) if isinstance(self.model, str) else ""
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> "MaterialCard":
        """Check the card; raise :class:`~difftissue.errors.ExportError` naming the field."""
        if not isinstance(self.card_version, int) or isinstance(self.card_version, bool) or self.card_version != CARD_VERSION:
            raise ExportError(f"card_version = {self.card_version!r} is not supported (this difftissue reads card_version {CARD_VERSION})")
        if not isinstance(self.model, str) or not self.model.strip():
            raise ExportError(f"model = {self.model!r}: expected a non-empty model name such as {sorted(MODEL_ENERGIES)}")
        if not isinstance(self.name, str) or not self.name.strip():
            raise ExportError(f"name = {self.name!r}: expected a non-empty material name")
        if not isinstance(self.parameters, Mapping):
            raise ExportError("parameters: expected an object {field: {value, unit, standard_error}}")
        for req in _REQUIRED:
            if req not in self.parameters:
                raise ExportError(f"parameters.{req} is missing; a card needs {list(_REQUIRED)}")
        clean: dict[str, dict[str, Any]] = {}
        for key, entry in self.parameters.items():
            if not isinstance(entry, Mapping) or "value" not in entry:
                raise ExportError(f"parameters.{key}: expected an object with a 'value'")
            value = finite(entry["value"], f"parameters.{key}.value")
            if key in _RULES and not _RULES[key][0](value):
                raise ExportError(f"parameters.{key}.value = {value:g} {_RULES[key][1]}")
            unit = entry.get("unit", PARAMETER_UNITS.get(key, ""))
            if key in PARAMETER_UNITS and unit != PARAMETER_UNITS[key]:
                raise ExportError(f"parameters.{key}.unit = {unit!r}; cards are SI, expected {PARAMETER_UNITS[key]!r}")
            se = entry.get("standard_error")
            if se is not None:
                try:
                    se = float(se)
                except (TypeError, ValueError):
                    raise ExportError(f"parameters.{key}.standard_error = {se!r} is not a number") from None
                if math.isnan(se) or se < 0:
                    raise ExportError(f"parameters.{key}.standard_error = {se!r} must be >= 0 (or null)")
                if math.isinf(se):
                    se = None
            clean[str(key)] = {**{k: v for k, v in entry.items() if k not in ("value", "unit", "standard_error")},
                               "value": value, "unit": unit, "standard_error": se}
        self.parameters = clean
        return self

    # ------------------------------------------------------------------ values
    def value(self, field: str) -> float:
        """Value of ``field`` [SI], with the defaults for the optional fields."""
        if field in self.parameters:
            return float(self.parameters[field]["value"])
        if field in _DEFAULTS:
            return _DEFAULTS[field]
        raise ExportError(f"parameters.{field} is missing")

    @property
    def youngs_modulus(self) -> float:
        return self.value("youngs_modulus")

    @property
    def poisson_ratio(self) -> float:
        return self.value("poisson_ratio")

    @property
    def cubic_coefficient(self) -> float:
        return self.value("cubic_coefficient")

    @property
    def density(self) -> float:
        return self.value("density")

    @property
    def pre_stretch(self) -> float:
        return self.value("pre_stretch")

    @property
    def pre_stretch_y(self) -> float:
        """``lambda_y``: the card's ``pre_stretch_y``, else ``pre_stretch`` (equibiaxial)."""
        return self.value("pre_stretch_y") if "pre_stretch_y" in self.parameters else self.pre_stretch

    @property
    def is_pre_stretched(self) -> bool:
        """True when either in-plane pre-stretch differs from 1 (pre-tension)."""
        return self.pre_stretch != 1.0 or self.pre_stretch_y != 1.0

    @property
    def is_anisotropic_pre_stretch(self) -> bool:
        """True when ``pre_stretch_y`` is given and differs from ``pre_stretch``."""
        return self.pre_stretch_y != self.pre_stretch

    @property
    def shear_modulus(self) -> float:
        """``mu = E / (2 (1 + nu))`` [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda(self) -> float:
        """``lambda = E nu / ((1 + nu)(1 - 2 nu))`` [Pa]."""
        E, nu = self.youngs_modulus, self.poisson_ratio
        return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def bulk_modulus(self) -> float:
        """``K = E / (3 (1 - 2 nu))`` [Pa]."""
        return self.youngs_modulus / (3.0 * (1.0 - 2.0 * self.poisson_ratio))

    def material(self):
        """The card as a :class:`~difftissue.materials.Material` (the :data:`MATERIAL_FIELDS`)."""
        return Material(**{k: self.value(k) for k in MATERIAL_FIELDS + tuple(f for f in OPTIONAL_MATERIAL_FIELDS if f in self.parameters)})

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict:
        return {
            "card_version": self.card_version,
            "model": self.model,
            "energy": self.energy,
            "name": self.name,
            "parameters": {k: dict(v) for k, v in self.parameters.items()},
            "units": UNITS,
            "provenance": self.provenance,
        }

    def to_json(self) -> str:
        """Strict JSON (no NaN/Infinity), indented, ending in a newline."""
        return json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"

    @classmethod
    def from_dict(cls, doc: Mapping) -> "MaterialCard":
        if not isinstance(doc, Mapping):
            raise ExportError("a material card must be a JSON object")
        if "card_version" not in doc:
            raise ExportError("card_version is missing (not a difftissue material card?)")
        if "model" not in doc:
            raise ExportError("model is missing")
        if "parameters" not in doc:
            raise ExportError("parameters is missing")
        unknown = set(doc) - {"card_version", "model", "energy", "name", "parameters", "provenance", "units"}
        if unknown:
            raise ExportError(f"unknown card key(s) {sorted(unknown)}")
        if doc.get("units", UNITS) != UNITS:
            raise ExportError(f"units = {doc.get('units')!r}; cards are SI: {UNITS!r}")
        return cls(model=doc["model"], parameters=doc["parameters"], energy=doc.get("energy", ""),
                   name=doc.get("name", "tissue"), provenance=dict(doc.get("provenance") or {}), card_version=doc["card_version"])

    @classmethod
    def from_json(cls, text: str) -> "MaterialCard":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise ExportError(f"not valid JSON: {e}") from None
        if isinstance(doc, Mapping) and str(doc.get("schema", "")).startswith("difftissue-fit/"):
            return card_from_fit_json(doc)
        return cls.from_dict(doc)

    def __eq__(self, other):
        if not isinstance(other, MaterialCard):
            return NotImplemented
        return self.to_dict() == other.to_dict()


def portable_path(path, base=None) -> str:
    """A path for provenance without host directories: relative to ``base`` (the config's
    folder) when ``path`` lies below it, else the bare file name (the sha256 identifies it)."""
    p = Path(path)
    if base is not None:
        try:
            return Path(os.path.relpath(p.resolve(), Path(base).resolve())).as_posix() if p.resolve().is_relative_to(Path(base).resolve()) else p.name
        except (OSError, ValueError):
            return p.name
    return p.as_posix() if not p.is_absolute() and ".." not in p.parts else p.name


def card_from_fit(result, *, model: str, scenario_names: Sequence[str] | None = None,
                  data_files: Sequence[str | os.PathLike] = (), name: str = "tissue",
                  scenario_records: Sequence[Mapping] | None = None, base_dir=None) -> MaterialCard:
    """A card from a :class:`~difftissue.fit.FitResult`.

    ``scenario_records`` (e.g. ``[scenario_record(s) for s in scenarios]``,
    :func:`difftissue.export.card.scenario_record`) are stored as
    ``provenance.scenario_records``: the indenter geometry and depth protocol that
    ``export(..., indentation=indentation_specimen(card))`` rebuilds the specimen from.

    Every field of the fitted material is recorded; fitted fields carry their standard error
    (``None`` where the data do not determine it), fixed fields ``standard_error: None`` and
    ``"fitted": false``. Data file paths are stored without host directories
    (:func:`portable_path`: relative to ``base_dir``, the config's folder, else the file name).
    """
    if not isinstance(model, str):
        model = getattr(model, "name", None) or type(model).__name__
    values = result.material.to_dict()
    params = {}
    for k, v in values.items():
        fitted = k in result.fields
        se = result.standard_errors.get(k) if fitted else None
        params[k] = {"value": float(v), "unit": PARAMETER_UNITS.get(k, ""),
                     "standard_error": None if se is None or not math.isfinite(se) else float(se), "fitted": fitted}
    names = list(scenario_names) if scenario_names is not None else list(getattr(result, "scenario_names", ()))
    prov = {
        "scenarios": [str(n) for n in names],
        "data_files": [{"path": portable_path(p, base_dir), "sha256": sha256_file(Path(p))} for p in data_files],
        "difftissue_version": difftissue_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "fit": {"loss": float(result.loss), "converged": bool(result.converged), "method": result.method},
    }
    if scenario_records:
        prov["scenario_records"] = [dict(r) for r in scenario_records if r]
    em = getattr(result, "effective_modulus", None)
    if em is not None:  # a half-space indentation fit with nu fixed: E is E* (1 - nu^2) at an assumed nu
        prov["effective_modulus"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in em.items()}
    return MaterialCard(model=model, parameters=params, name=name, provenance=prov)


def card_from_fit_json(doc: Mapping) -> MaterialCard:
    """A card from the content of a ``fit.json`` written by :func:`~difftissue.fit.write_fit_outputs`."""
    params: dict[str, dict] = {}
    for k, v in (doc.get("fixed_parameters") or {}).items():
        params[k] = {"value": v.get("value"), "unit": v.get("unit", PARAMETER_UNITS.get(k, "")), "standard_error": None, "fitted": False}
    for k, v in (doc.get("parameters") or {}).items():
        params[k] = {"value": v.get("value"), "unit": v.get("unit", PARAMETER_UNITS.get(k, "")),
                     "standard_error": v.get("standard_error"), "fitted": True}
    model = doc.get("model")
    if not model:
        raise ExportError("model is missing in fit.json (write_fit_outputs was called without model=); write a card with card_from_fit(model=...)")
    prov = {
        "scenarios": [s.get("name") for s in doc.get("scenarios", [])],
        "data_files": list(doc.get("data_files", [])),
        "difftissue_version": (doc.get("versions") or {}).get("difftissue"),
        "created": doc.get("created"),
        "source": "fit.json",
    }
    if doc.get("effective_modulus"):
        prov["effective_modulus"] = dict(doc["effective_modulus"])
    return MaterialCard(model=str(model), parameters=params, provenance=prov)


def resolve_effective_modulus(card: MaterialCard, *, nu: float | None = None, approximate: bool = False) -> MaterialCard:
    """The card a simulator may be given, for a card whose E rests on an assumed nu.

    A half-space indentation fit with nu fixed determines only the effective modulus
    ``E* = E / (1 - nu^2)`` (``provenance.effective_modulus``). With ``nu`` stated the card is
    converted explicitly: ``E = E* (1 - nu^2)`` [Pa], poisson_ratio = ``nu`` (recorded in
    ``provenance.effective_modulus.converted``). Without it, a card fitted at the assumed
    ``nu = 0`` (the indentation-modulus convention, no tissue's nu) is refused with
    :class:`~difftissue.errors.EffectiveModulusError` unless ``approximate`` (exported as is,
    said in the file's header); a card fitted at another fixed nu is exported as is, its header
    saying that E rests on that nu.
    """
    em = (card.provenance or {}).get("effective_modulus")
    if not em:
        if nu is not None:
            raise ExportError(f"nu = {nu:g} was stated, but the card holds E and nu of its own (no effective modulus); leave nu out")
        return card
    e_star, nu0 = float(em["value"]), float(em["poisson_ratio_assumed"])
    if nu is not None:
        nu = finite(nu, "nu")
        if not -1.0 < nu < 0.5:
            raise ExportError(f"nu = {nu:g} must lie in (-1, 0.5) (0.5 is the incompressible limit; use e.g. 0.49)")
        k = 1.0 - nu**2
        params = {key: dict(v) for key, v in card.parameters.items()}
        se = em.get("standard_error")
        params["youngs_modulus"].update(value=e_star * k, standard_error=None if se is None else float(se) * k)
        params["poisson_ratio"].update(value=nu, standard_error=None, fitted=False)
        prov = {**card.provenance, "effective_modulus": {**em, "converted": {"poisson_ratio": nu, "youngs_modulus": e_star * k,
                "how": f"youngs_modulus = E* (1 - nu^2) = {e_star:.6g} Pa x {k:.6g} at the stated nu = {nu:g}"}}}
        return MaterialCard(model=card.model, parameters=params, energy=card.energy, name=card.name, provenance=prov)
    if nu0 == 0.0 and not approximate:
        raise EffectiveModulusError(
            f"the card's youngs_modulus = {card.youngs_modulus:.6g} Pa is the effective modulus E* = E/(1-nu^2) of a half-space "
            f"{em.get('law', 'indentation')} fit with nu fixed at 0 (the indentation-modulus convention): a simulator given E = E* and "
            f"nu = 0 is a different material. State the tissue's nu to convert (nu=0.45 / --nu 0.45: E = E* (1 - nu^2)), refit with "
            f"poisson_ratio fixed at the tissue's value, or pass approximate=True (--approximate) to export E* with nu = 0 as is")
    return card


def read_card(path) -> MaterialCard:
    """Read and validate a card (``material.json``) or a ``fit.json``; errors name the file and field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ExportError(f"cannot read {path}: {e.strerror or e}") from None
    try:
        return MaterialCard.from_json(text)
    except ExportError as e:
        raise ExportError(f"{path}: {e}") from None


def write_card(card: MaterialCard, path, *, force: bool = False) -> Path:
    """Write ``card`` as JSON, atomically; an existing file is refused unless ``force``."""
    card.validate()
    text = card.to_json()
    with atomic_output(path, overwrite=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def header_lines(card: MaterialCard, target: str, law: str | None = None) -> list[str]:
    """The comment lines every written file starts with: difftissue version and ``target``, the unit
    statement, the model and its energy, E, nu and density, the standard errors, the exported
    ``law``, data files and scenarios of the provenance, the effective-modulus conversion and the
    recalibration notes."""
    lines = [f"difftissue {difftissue_version()} material card export to {target}",
             UNITS_LINE,
             f"model: {card.model} ({card.energy})" if card.energy else f"model: {card.model}",
             f"E = {card.youngs_modulus:.10g} Pa, nu = {card.poisson_ratio:.10g}, density = {card.density:.10g} kg/m^3"]
    for k, v in card.parameters.items():
        if v.get("standard_error") is not None:
            lines.append(f"standard error of {k}: {v['standard_error']:.4g} {v['unit']}")
    if law:
        lines.append(f"exported law: {law}")
    prov = card.provenance or {}
    for f in prov.get("data_files", []) or []:
        if isinstance(f, Mapping):
            lines.append(f"data: {f.get('path')} sha256 {f.get('sha256')}")
    if prov.get("scenarios"):
        lines.append("scenarios: " + ", ".join(str(s) for s in prov["scenarios"]))
    em = prov.get("effective_modulus")
    if em:
        conv = em.get("converted")
        if conv:
            lines.append(f"E from the effective modulus E* = E/(1-nu^2) = {float(em['value']):.6g} Pa of a half-space indentation fit: {conv['how']}")
        elif float(em["poisson_ratio_assumed"]) == 0.0:
            lines.append(f"APPROXIMATION: E = {float(em['value']):.6g} Pa is the effective modulus E* = E/(1-nu^2) of a half-space indentation fit, "
                         "written with nu = 0 as is (no tissue's nu; the data do not determine nu)")
        else:
            lines.append(f"E rests on the assumed nu = {float(em['poisson_ratio_assumed']):g}: the data (half-space indentation) determine only "
                         f"E* = E/(1-nu^2) = {float(em['value']):.6g} Pa")
    rec = prov.get("recalibration")
    if isinstance(rec, Mapping):
        lines += [str(n) for n in rec.get("notes", [])]
    return lines


def scenario_record(scenario) -> dict | None:
    """JSON record of a scenario's experiment for a material card (``provenance.scenario_records``).

    The scenario describes itself: its ``record()`` (:meth:`difftissue.scenarios.AnalyticIndentation.record`,
    :meth:`difftissue.scenarios.Indentation.record`, :meth:`difftissue.scenarios.Compression.record`,
    :meth:`difftissue.scenarios.FEMField.record`, :meth:`difftissue.incision.Incision.record`):
    indentation scenarios record the indenter, its size, the largest depth and the number of
    points (the analytic ones also the layer thickness and base, the simulated one its block,
    cells, penalty and every depth); ``fem_field``, ``compression`` and ``incision`` record
    ``experiment``, difftissue's ``model`` and what their specimen file does not hold (the
    compression protocol, the incision's quantity and cut), their mesh and boundary conditions
    going into a specimen file (:mod:`difftissue.export.fitted`, written by
    :func:`difftissue.report.write_fit_outputs`). An object without ``record()`` is recorded by
    its name and type only; ``None`` for an object without a name.
    """
    name = getattr(scenario, "name", None)
    if name is None:
        return None
    record = getattr(scenario, "record", None)
    if callable(record):
        return dict(record())
    return {"name": str(name), "type": type(scenario).__name__}
