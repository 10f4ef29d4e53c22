"""Material cards and writers for other simulators (DESIGN.md §4, docs/export.md).

A :class:`MaterialCard` (JSON, ``"card_version": 1``) is the source of truth: the elastic model
that was fitted, the energy it refers to, every parameter with unit and standard error, and
provenance. Writers derive simulator inputs from it, each with its conversion spelled out:

* FEBio ``.feb`` (febio_spec 4.0): :func:`write_febio`
* SOFA ``.scn``: :func:`write_sofa`
* Abaqus ``.inp``: :func:`write_abaqus`
* XPBD compliances for a stated time step and iteration count (JSON): :func:`write_xpbd`
* a pypbd scene (JSON, XPBD distance + volume or PBD FEM constraints): :func:`difftissue.pbd.write_pbd`
* VTU with per-cell material fields: :func:`write_vtu`
* scikit-fem (in memory, no file): :func:`to_skfem`

All quantities are SI. Every file is written atomically and an existing file is refused
unless ``force=True``. The module imports only numpy and the standard library at import
time (meshes and meshio are loaded when a mesh is written).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Mapping, Sequence

import numpy as np

from ._io import atomic_output, sha256_file
from .errors import EffectiveModulusError, ExportError

__all__ = [
    "CARD_VERSION",
    "MODEL_ENERGIES",
    "PARAMETER_UNITS",
    "TARGETS",
    "MaterialCard",
    "card_from_fit",
    "card_from_fit_json",
    "resolve_effective_modulus",
    "read_card",
    "write_card",
    "abaqus_name",
    "abaqus_number",
    "abaqus_reaction_print",
    "abaqus_quadratic",
    "ABAQUS_ELEMENTS",
    "model_mismatch",
    "uniaxial_signed_errors",
    "portable_path",
    "febio_material",
    "febio_indenter_cap",
    "febio_prestrain_gradient",
    "pre_stretch_from_febio_gradient",
    "sofa_force_field",
    "sofa_polynomial_coefficients",
    "springs_from_sofa_polynomial",
    "sofa_springs_split",
    "abaqus_material",
    "xpbd_parameters",
    "write_febio",
    "write_sofa",
    "write_abaqus",
    "write_xpbd",
    "write_vtu",
    "to_skfem",
    "export",
]

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
    "fem_linear": "linear isotropic elasticity, W = lambda/2 tr(eps)^2 + mu eps:eps (small strain)",
    "fem_neo_hookean": "compressible neo-Hookean, W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2",
    "stable_neo_hookean": (
        "stable neo-Hookean (Smith et al. 2018), W = mu/2 (I1 - 3) + lambda'/2 (J - 1 - mu/lambda')^2 "
        "with lambda' = lambda + mu, so that its small-strain response is (E, nu)"
    ),
    "analytic": "small-strain linear isotropic elasticity (closed-form contact / compression solutions)",
}

#: The unit statement every written file carries (cards: the ``units`` field; files: a comment).
UNITS = "m, N, Pa, s (density kg/m^3)"
UNITS_LINE = "units: " + UNITS

#: SI unit of every parameter a card may hold.
PARAMETER_UNITS: dict[str, str] = {
    "youngs_modulus": "Pa",
    "poisson_ratio": "1",
    "cubic_coefficient": "1",
    "density": "kg/m^3",
    "pre_stretch": "1",
    "surface_tension": "N/m",
}

_DEFAULTS = {"cubic_coefficient": 0.0, "density": 1000.0, "pre_stretch": 1.0}
_REQUIRED = ("youngs_modulus", "poisson_ratio")
_RULES = {
    "youngs_modulus": (lambda v: v > 0, "must be > 0"),
    "poisson_ratio": (lambda v: -1.0 < v < 0.5, "must lie in (-1, 0.5) (0.5 is the incompressible limit)"),
    "density": (lambda v: v > 0, "must be > 0"),
    "pre_stretch": (lambda v: v > 0, "must be > 0"),
}

#: Export targets understood by :func:`export` and ``difftissue export --to``.
TARGETS = ("febio", "sofa", "abaqus", "pbd", "xpbd", "vtu")

#: Models whose energy is geometrically nonlinear: their cards export to neo-Hookean by default.
_FINITE_STRAIN_MODELS = ("springs_volume", "fem_neo_hookean", "stable_neo_hookean")


def _model_parts(model: str) -> list[str]:
    """``"hertz; springs_volume"`` (a joint fit) -> ``["hertz", "springs_volume"]``."""
    return [m.strip() for m in str(model).split(";") if m.strip()]


def _default_energy(model: str) -> str:
    """Energy in words; names outside :data:`MODEL_ENERGIES` (``hertz``, ``sneddon_cone``, ...)
    are difftissue's closed-form solutions, all small-strain linear elasticity."""
    out = []
    for m in _model_parts(model):
        out.append(f"{m}: {MODEL_ENERGIES[m]}" if m in MODEL_ENERGIES else f"{m}: {MODEL_ENERGIES['analytic']}")
    return out[0].split(": ", 1)[1] if len(out) == 1 else "; ".join(out)


# =============================================================================== card
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
            value = _finite(entry["value"], f"parameters.{key}.value")
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
        """The card as a :class:`~difftissue.materials.Material` (imports JAX)."""
        from .materials import Material

        return Material(**{k: self.value(k) for k in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")})

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


def _finite(v, where: str) -> float:
    if isinstance(v, bool) or v is None:
        raise ExportError(f"{where} = {v!r} is not a number")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ExportError(f"{where} = {v!r} is not a number") from None
    if not math.isfinite(f):
        raise ExportError(f"{where} = {v!r} is not finite")
    return f


def _sha256(path: Path) -> str:
    return sha256_file(path)


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


def _version() -> str:
    from ._version import __version__

    return __version__


def card_from_fit(result, *, model: str, scenario_names: Sequence[str] | None = None,
                  data_files: Sequence[str | os.PathLike] = (), name: str = "tissue",
                  scenario_records: Sequence[Mapping] | None = None, base_dir=None) -> MaterialCard:
    """A card from a :class:`~difftissue.fit.FitResult`.

    ``scenario_records`` (e.g. ``[scenario_record(s) for s in scenarios]``,
    :func:`difftissue.export_indentation.scenario_record`) are stored as
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
        "data_files": [{"path": portable_path(p, base_dir), "sha256": _sha256(Path(p))} for p in data_files],
        "difftissue_version": _version(),
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
        nu = _finite(nu, "nu")
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


# ======================================================================= approximations
def _law(card: MaterialCard, law: str | None) -> str:
    if law is None:
        return "neo_hookean" if any(m in _FINITE_STRAIN_MODELS for m in _model_parts(card.model)) else "linear"
    if law not in ("linear", "neo_hookean"):
        raise ExportError(f"law = {law!r}: expected 'linear' or 'neo_hookean'")
    return law


#: difftissue's model whose energy each exported continuum law is (FEBio, SOFA's tet force fields,
#: Abaqus / CalculiX on tets): the models a card is recalibrated to and its errors measured with.
LAW_MODELS = {"linear": "fem_linear", "neo_hookean": "fem_neo_hookean"}
#: Card models whose (E, nu) are lattice-effective values, not a continuum's.
_LATTICE_MODELS = ("springs_volume",)
#: Nominal strains (compression) at which an --approximate note quotes the signed stress error.
UNIAXIAL_STRAINS = (-0.1, -0.2, -0.4)


def model_mismatch(card: MaterialCard, law: str) -> str | None:
    """Why the card's (E, nu) are not values of the continuum ``law`` (``"linear"`` /
    ``"neo_hookean"``), or None when they are.

    A ``springs_volume`` card (alone or in a joint fit) holds lattice-effective values: the
    cube lattice of springs with a per-cell volume term equals (E, nu) only under homogeneous
    strain; under a punch or bonded platens its cubes change volume far more freely than
    tets do, so the same (E, nu) on a continuum tet mesh is much stiffer (measured: +40 %
    punch force, docs/export.md "Model mismatch")."""
    lattice = [m for m in _model_parts(card.model) if m in _LATTICE_MODELS]
    if not lattice:
        return None
    return (f"model mismatch: the card's E = {card.youngs_modulus:.6g} Pa, nu = {card.poisson_ratio:.6g} are {lattice[0]} "
            f"lattice-effective values (cube lattice of springs with a per-cell volume term), the target solves the continuum "
            f"{law} law ({LAW_MODELS[law]}) on tets, which under inhomogeneous strain (a punch, bonded platens) is tens of "
            f"percent stiffer at the same values")


def _uniaxial_cube_stress(model: str, values: tuple, strains: Sequence[float]) -> np.ndarray:
    """Engineering stress [Pa] of one 1 mm cube of difftissue's ``model`` (``values`` =
    E [Pa], nu, b) under frictionless uniaxial compression to the nominal ``strains``:
    bottom face held in z, top face moved by ``strain * 1 mm`` in z, the x = 0 / y = 0 faces
    held in x / y (symmetry), lateral faces free; solved by difftissue's static solver
    (float64 required). Stress = summed top z reaction / 1 mm^2."""
    import jax

    from .boundary import BoundaryConditions
    from .materials import Material
    from .mesh import block
    from .models import make_model
    from .solvers.static import solve_static

    if not jax.config.jax_enable_x64:
        raise ExportError("measuring an approximation needs float64 JAX (jax.config.update('jax_enable_x64', True))")
    L = 1e-3
    mesh = block(L, 1)
    p = np.asarray(mesh.points)
    low, top = np.isclose(p[:, 2], 0.0), np.isclose(p[:, 2], L)
    fixed = np.zeros((len(p), 3), dtype=bool)
    fixed[low | top, 2] = True
    fixed[np.isclose(p[:, 0], 0.0), 0] = True
    fixed[np.isclose(p[:, 1], 0.0), 1] = True
    m = make_model(mesh, model)
    mat = Material(youngs_modulus=values[0], poisson_ratio=values[1], cubic_coefficient=values[2])
    out = []
    for e in strains:
        u = np.zeros((len(p), 3))
        u[top, 2] = e * L
        sol = solve_static(m, mat, BoundaryConditions(fixed, u, np.zeros_like(u)), load_steps=max(1, int(math.ceil(abs(e) / 0.05))))
        out.append(float(np.sum(np.asarray(sol.reaction)[top, 2])) / L**2)
    return np.asarray(out)


_ERROR_CACHE: dict = {}


def uniaxial_signed_errors(card: MaterialCard, law: str, strains: Sequence[float] = UNIAXIAL_STRAINS) -> np.ndarray:
    """Signed relative error ``(|exported| - |card|) / |card|`` of the engineering stress under
    homogeneous frictionless uniaxial compression at the nominal ``strains`` (default
    -10, -20, -40 %): the exported ``law`` at the card's (E, nu) with ``b`` dropped
    (:data:`LAW_MODELS`: ``fem_linear`` / ``fem_neo_hookean``, FEBio's and SOFA's energies)
    against the card's own model with ``b`` (difftissue's ``springs_volume``,
    ``stable_neo_hookean``, ... solved the same way, :func:`_uniaxial_cube_stress`; a closed-form
    card, e.g. ``hertz``, against its stated law ``E (eps + b eps^3)``). Positive: the export is
    stiffer. Pre-stretch is left out of both (it is noted separately)."""
    from .models import MODELS

    own = next((m for m in _model_parts(card.model) if m in MODELS), None)
    E, nu, b = card.youngs_modulus, card.poisson_ratio, card.cubic_coefficient
    key = (own, E, nu, b, law, tuple(strains))
    if key not in _ERROR_CACHE:
        eps = np.asarray(strains, dtype=float)
        ref = _uniaxial_cube_stress(own, (E, nu, b), eps) if own else E * (eps + b * eps**3)
        exp = _uniaxial_cube_stress(LAW_MODELS[law], (E, nu, 0.0), eps)
        _ERROR_CACHE[key] = (np.abs(exp) - np.abs(ref)) / np.abs(ref)
    return _ERROR_CACHE[key]


def _signed_error_text(card: MaterialCard, law: str) -> str:
    """``+8.5 % at 10 %, ... compression`` for :func:`uniaxial_signed_errors` (a solve that
    fails, e.g. outside the card model's range, is reported in the note instead)."""
    try:
        err = uniaxial_signed_errors(card, law)
    except ExportError:
        raise
    except Exception as e:  # difftissue's solver / model errors: one line in the note, the export goes on
        return f"signed stress error NOT measured ({type(e).__name__}: {' '.join(str(e).split())[:200]})"
    parts = ", ".join(f"{100 * e:+.3g} % at {100 * abs(s):g} %" for e, s in zip(err, UNIAXIAL_STRAINS))
    return (f"measured signed stress error of the exported {law} law ({LAW_MODELS[law]}) against the card's model "
            f"{card.model}, homogeneous uniaxial compression of one cube in difftissue: {parts} nominal strain "
            "(positive: the export is stiffer)")


def _target_law(target: str) -> str | None:
    """``"FEBio neo_hookean"`` -> ``"neo_hookean"``; None for a target that is no continuum law."""
    law = target.rsplit(" ", 1)[-1]
    return law if law in LAW_MODELS else None


def _approximations(card: MaterialCard, target: str, *, approximate: bool, cubic_ok: bool = False,
                    pre_stretch_ok: bool = False) -> list[str]:
    """Notes on what ``target`` cannot represent; raise unless ``approximate``.

    ``target`` ending in a continuum law (``"... linear"`` / ``"... neo_hookean"``) is also
    checked for a model mismatch (:func:`model_mismatch`). With ``approximate`` the notes state
    the measured signed error (:func:`uniaxial_signed_errors`) of dropping the cubic term
    and / or of writing lattice-effective values into a continuum law."""
    notes = []
    law = _target_law(target)
    mismatch = model_mismatch(card, law) if law else None
    if mismatch:
        if not approximate:
            raise ExportError(f"{mismatch}; export the fitted experiment (--specimen fitted), which recalibrates E for {target}, "
                              "or pass approximate=True (--approximate) to write the card's values anyway with the measured error noted")
        notes.append(f"APPROXIMATION: {mismatch}; the values are written unchanged")
    b = card.cubic_coefficient
    if b != 0.0 and not cubic_ok:
        msg = (f"cubic_coefficient b = {b:g} (strain stiffening sigma = E (eps + b eps^3)) cannot be represented by {target}")
        if not approximate:
            raise ExportError(msg + "; pass approximate=True (--approximate) to drop it (the file then states the measured signed "
                              "stress error)")
        notes.append(f"APPROXIMATION: cubic_coefficient b = {b:g} dropped (target {target} has no cubic strain stiffening)")
    if law and approximate and (mismatch or b != 0.0):
        notes.append("APPROXIMATION ERROR: " + _signed_error_text(card, law)
                     + ("; under inhomogeneous strain the lattice/continuum difference is larger" if mismatch else ""))
    lam0 = card.pre_stretch
    if lam0 != 1.0 and not pre_stretch_ok:
        msg = f"pre_stretch = {lam0:g} (pre-tension) is not written for {target}"
        if not approximate:
            raise ExportError(msg + "; pass approximate=True (--approximate) to export the material without pre-tension")
        notes.append(f"APPROXIMATION: pre_stretch = {lam0:g} dropped; the exported material starts stress-free")
    return notes


def _header_lines(card: MaterialCard, target: str, law: str | None = None) -> list[str]:
    lines = [f"difftissue {_version()} material card export to {target}",
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


# ============================================================================ FEBio
def _fmt(x: float) -> str:
    return repr(float(x))


def _xml_comment(text: str) -> ET.Element:
    # '--' is not allowed inside an XML comment, and a trailing '-' would close it badly
    return ET.Comment(" " + text.replace("--", "- -").rstrip("-") + " ")


def febio_material(card: MaterialCard, *, law: str | None = None, approximate: bool = False, mat_id: int = 1) -> ET.Element:
    """The FEBio ``<Material>`` element for ``card``.

    Conversion: none needed, FEBio takes Young's modulus and Poisson's ratio directly.

    * ``law="neo_hookean"`` -> ``<material type="neo-Hookean"><E>E</E><v>nu</v>`` whose energy is
      ``W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2`` with ``mu, lambda`` the Lamé parameters
      of ``(E, nu)``: identical to difftissue's ``fem_neo_hookean`` and to the small-strain
      response of every model.
    * ``law="linear"`` -> ``type="isotropic elastic"`` (same ``E``, ``v``).
    * ``<density>`` is the card's density [kg/m^3].

    The default law is ``neo_hookean`` for cards of a finite-strain model (``springs_volume``,
    ``fem_neo_hookean``, ``stable_neo_hookean``, also within a joint ``"hertz; springs_volume"``)
    and ``linear`` otherwise (``fem_linear`` and the analytic solutions: ``hertz``, ...). A nonzero
    ``cubic_coefficient`` is refused unless ``approximate``, which drops it and records the error
    in a comment. A ``pre_stretch`` other than 1 wraps the material in FEBio's
    ``<material type="prestrain elastic">`` with ``<elastic type=...>`` (the law above) and
    ``<prestrain type="prestrain gradient"><ramp>1.0</ramp><F0>l,0,0,0,l,0,0,0,1</F0>``
    (:func:`febio_prestrain_gradient`).
    """
    law = _law(card, law)
    notes = _approximations(card, "FEBio " + law, approximate=approximate, pre_stretch_ok=True)
    lam0 = card.pre_stretch
    mats = ET.Element("Material")
    for line in _header_lines(card, "FEBio", law) + notes:
        mats.append(_xml_comment(line))
    etype = "neo-Hookean" if law == "neo_hookean" else "isotropic elastic"
    if lam0 == 1.0:
        m = ET.SubElement(mats, "material", {"id": str(mat_id), "name": card.name, "type": etype})
        ET.SubElement(m, "density").text = _fmt(card.density)
        ET.SubElement(m, "E").text = _fmt(card.youngs_modulus)
        ET.SubElement(m, "v").text = _fmt(card.poisson_ratio)
        return mats
    sigma0 = card.youngs_modulus * (lam0 - 1.0) / (1.0 - card.poisson_ratio)
    mats.append(_xml_comment(
        f"pre-tension: pre_stretch lambda0 = {lam0:.10g} in x and y (the stress-free state is the mesh shrunk by 1/lambda0 "
        f"in x and y): prestrain gradient F0 = diag(lambda0, lambda0, 1); small-strain equibiaxial pre-stress "
        f"E (lambda0 - 1) / (1 - nu) = {sigma0:.6g} Pa"))
    m = ET.SubElement(mats, "material", {"id": str(mat_id), "name": card.name, "type": "prestrain elastic"})
    ET.SubElement(m, "density").text = _fmt(card.density)
    el = ET.SubElement(m, "elastic", {"type": etype})
    ET.SubElement(el, "density").text = _fmt(card.density)
    ET.SubElement(el, "E").text = _fmt(card.youngs_modulus)
    ET.SubElement(el, "v").text = _fmt(card.poisson_ratio)
    pre = ET.SubElement(m, "prestrain", {"type": "prestrain gradient"})
    ET.SubElement(pre, "ramp").text = "1.0"
    ET.SubElement(pre, "F0").text = febio_prestrain_gradient(lam0)
    return mats


def febio_prestrain_gradient(pre_stretch: float) -> str:
    """FEBio ``<F0>`` text of difftissue's pre-stretch: ``diag(lambda0, lambda0, 1)`` row by row.

    FEBio's ``prestrain elastic`` evaluates its ``elastic`` material at ``F Fp`` with ``Fp`` the
    prestrain gradient (map from the stress-free to the reference configuration, Maas et al.
    2016); difftissue's pre-stretch makes the stress-free state the mesh shrunk by
    ``1/lambda0`` in x and y, so ``Fp = diag(lambda0, lambda0, 1)``. Inverse:
    :func:`pre_stretch_from_febio_gradient`.
    """
    lam0 = _finite(pre_stretch, "pre_stretch")
    if lam0 <= 0:
        raise ExportError(f"pre_stretch = {lam0:g} must be > 0")
    return ",".join(_fmt(v) for v in (lam0, 0.0, 0.0, 0.0, lam0, 0.0, 0.0, 0.0, 1.0))


def pre_stretch_from_febio_gradient(text: str) -> float:
    """``lambda0`` from an FEBio ``<F0>`` of the form ``diag(lambda0, lambda0, 1)`` (others refused)."""
    try:
        F = np.array([float(v) for v in str(text).split(",")]).reshape(3, 3)
    except ValueError:
        raise ExportError(f"F0 = {text!r}: expected 9 comma-separated numbers") from None
    if not (np.allclose(F, np.diag(np.diag(F)), rtol=0, atol=0) and F[0, 0] == F[1, 1] and F[2, 2] == 1.0):
        raise ExportError(f"F0 = {text!r} is not an in-plane equibiaxial pre-stretch diag(l, l, 1)")
    return float(F[0, 0])


def _specimen_sets(mesh, axis: int = 2, tol: float = 1e-9):
    pts = np.asarray(mesh.points, dtype=float)
    lo, hi = pts[:, axis].min(), pts[:, axis].max()
    t = tol * max(hi - lo, 1e-300)
    base = np.flatnonzero(pts[:, axis] <= lo + t)
    top = np.flatnonzero(pts[:, axis] >= hi - t)
    if base.size == 0 or top.size == 0 or hi <= lo:
        raise ExportError("the specimen mesh has no distinct base and top faces along z")
    return base, top, hi - lo


def _default_displacement(height: float, displacement: float | None) -> float:
    d = -0.1 * height if displacement is None else float(displacement)
    if not math.isfinite(d):
        raise ExportError(f"displacement = {displacement!r} is not finite")
    return d


def febio_model(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
                displacement: float | None = None, steps: int = 10) -> ET.Element:
    """A complete ``<febio_spec version="4.0">`` tree (material only when ``mesh`` is None).

    With a mesh: nodes, ``tet4`` elements, a ``SolidDomain``, the base (min z) fixed with
    ``zero displacement`` and the top (max z) moved by ``displacement`` [m] along z
    (``prescribed displacement`` ramped by a linear load curve over ``steps`` static steps).
    Default displacement: -10 % of the height (compression).
    """
    root = ET.Element("febio_spec", {"version": "4.0"})
    ET.SubElement(root, "Module", {"type": "solid"})
    mats = febio_material(card, law=law, approximate=approximate)
    if mesh is None:
        root.append(mats)
        return root
    base, top, height = _specimen_sets(mesh)
    d = _default_displacement(height, displacement)
    ctrl = ET.SubElement(root, "Control")
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(int(steps))
    ET.SubElement(ctrl, "step_size").text = _fmt(1.0 / steps)
    root.append(mats)
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(np.asarray(mesh.points, dtype=float), start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(_fmt(c) for c in p)
    elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": "tissue"})
    for i, t in enumerate(np.asarray(mesh.tets), start=1):
        ET.SubElement(elems, "elem", {"id": str(i)}).text = ",".join(str(int(n) + 1) for n in t)
    ET.SubElement(meshel, "NodeSet", {"name": "base"}).text = ",".join(str(int(n) + 1) for n in base)
    ET.SubElement(meshel, "NodeSet", {"name": "top"}).text = ",".join(str(int(n) + 1) for n in top)
    doms = ET.SubElement(root, "MeshDomains")
    ET.SubElement(doms, "SolidDomain", {"name": "tissue", "mat": card.name})
    bnd = ET.SubElement(root, "Boundary")
    fix = ET.SubElement(bnd, "bc", {"name": "fixed_base", "node_set": "base", "type": "zero displacement"})
    for dof in ("x_dof", "y_dof", "z_dof"):
        ET.SubElement(fix, dof).text = "1"
    pre = ET.SubElement(bnd, "bc", {"name": "top_displacement", "node_set": "top", "type": "prescribed displacement"})
    ET.SubElement(pre, "dof").text = "z"
    ET.SubElement(pre, "value", {"lc": "1"}).text = _fmt(d)
    ET.SubElement(pre, "relative").text = "0"
    _febio_ramp_and_output(root, {"top": ",".join(str(int(n) + 1) for n in top)})
    return root


def _febio_static_root(comments, steps: int) -> ET.Element:
    """``<febio_spec version="4.0">`` with ``comments``, the solid ``Module`` and a STATIC
    ``Control`` of ``steps`` time steps of ``1/steps`` (the specimen models' common head)."""
    root = ET.Element("febio_spec", {"version": "4.0"})
    for line in comments:
        root.append(_xml_comment(line))
    ET.SubElement(root, "Module", {"type": "solid"})
    ctrl = ET.SubElement(root, "Control")
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(int(steps))
    ET.SubElement(ctrl, "step_size").text = _fmt(1.0 / steps)
    return root


def _febio_ramp_and_output(root: ET.Element, reactions: Mapping[str, str] | None = None, rigid: Sequence[int] = ()) -> None:
    """FEBio ``LoadData`` (load controller 1: a linear ramp 0 -> 1 over the step) and ``Output``:
    the plot file (displacement, stress, reaction forces) and a ``<logfile>`` that writes the
    reaction force [N] of each node set in ``reactions`` (``{set name: "1,2,..."}``, 1-based
    ids: ``<node_data data="Rx;Ry;Rz" file="reaction_<set>.txt" delim=",">ids</node_data>``,
    one line per node and step; sum them) and of each rigid material id in ``rigid``
    (``<rigid_body_data data="Fx;Fy;Fz">id</rigid_body_data>``). FEBio reports reactions only
    on prescribed degrees of freedom, so the writers prescribe 0 (``prescribed displacement``)
    rather than ``zero displacement`` on every set listed here."""
    ld = ET.SubElement(root, "LoadData")
    lc = ET.SubElement(ld, "load_controller", {"id": "1", "name": "ramp", "type": "loadcurve"})
    ET.SubElement(lc, "interpolate").text = "LINEAR"
    pts = ET.SubElement(lc, "points")
    ET.SubElement(pts, "pt").text = "0,0"
    ET.SubElement(pts, "pt").text = "1,1"
    out = ET.SubElement(root, "Output")
    plot = ET.SubElement(out, "plotfile", {"type": "febio"})
    for var in ("displacement", "stress", "reaction forces"):
        ET.SubElement(plot, "var", {"type": var})
    if reactions or rigid:
        log = ET.SubElement(out, "logfile")
        for name, ids in (reactions or {}).items():
            ET.SubElement(log, "node_data", {"data": "Rx;Ry;Rz", "name": f"reaction_{name}", "file": f"reaction_{name}.txt",
                                             "delim": ","}).text = ids
        for rid in rigid:
            ET.SubElement(log, "rigid_body_data", {"data": "Fx;Fy;Fz", "name": f"rigid_{rid}_force", "file": f"rigid_{rid}_force.txt",
                                                   "delim": ","}).text = str(int(rid))


def _febio_zero_prescribed(bnd: ET.Element, name: str, nset: str, dofs: str) -> None:
    """Hold ``dofs`` (e.g. ``"xyz"``) of node set ``nset`` at 0 by ``prescribed displacement``
    (value 0, one BC per dof) instead of ``zero displacement``: FEBio records reaction forces
    only for prescribed degrees of freedom, and this set's reaction is reported."""
    for d in dofs:
        bc = ET.SubElement(bnd, "bc", {"name": f"{name}_{d}", "node_set": nset, "type": "prescribed displacement"})
        ET.SubElement(bc, "dof").text = d
        ET.SubElement(bc, "value", {"lc": "1"}).text = "0.0"
        ET.SubElement(bc, "relative").text = "0"


def _xml_text(root: ET.Element) -> str:
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_febio(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
                displacement: float | None = None, force: bool = False, indentation=None) -> Path:
    """Write an FEBio ``.feb`` file (febio_spec 4.0): the material alone, with ``mesh`` a
    complete compression specimen (see :func:`febio_model`), or with ``indentation`` (an
    :class:`~difftissue.export_indentation.IndentationSpecimen`) an indentation specimen
    (:func:`febio_indentation_model`). Conversion: :func:`febio_material`."""
    if indentation is not None:
        _no_mesh_with_indentation(mesh)
        text = _xml_text(febio_indentation_model(card, indentation, law=law, approximate=approximate))
        return _write_text(path, text, force)
    text = _xml_text(febio_model(card, mesh, law=law, approximate=approximate, displacement=displacement))
    return _write_text(path, text, force)


# ============================================================================= SOFA
def sofa_force_field(card: MaterialCard, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """The SOFA force field for ``card``.

    * ``law="linear"`` -> ``<TetrahedronFEMForceField youngModulus="E" poissonRatio="nu" method="large"/>``
      (corotational linear elasticity; ``method="small"`` would be strictly linear).
    * ``law="neo_hookean"`` -> ``<TetrahedronHyperelasticityFEMForceField materialName="NeoHookean"
      ParameterSet="mu lambda"/>`` with ``mu = E / (2 (1 + nu))`` and
      ``lambda = E nu / ((1 + nu)(1 - 2 nu))``. SOFA's ``NeoHookean.h`` reads
      ``parameterArray[0]`` as mu and ``parameterArray[1]`` as lambda, energy
      ``mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2`` (Bonet & Wood), the same energy as FEBio's
      neo-Hookean. Older SOFA documentation listed ``[mu, k]``; check the SOFA version in use.

    Inverse (tested): ``E = mu (3 lambda + 2 mu) / (lambda + mu)``, ``nu = lambda / (2 (lambda + mu))``.
    """
    law = _law(card, law)
    _approximations(card, "SOFA " + law, approximate=approximate)
    if law == "linear":
        return ET.Element("TetrahedronFEMForceField", {"name": card.name, "youngModulus": _fmt(card.youngs_modulus),
                                                       "poissonRatio": _fmt(card.poisson_ratio), "method": "large"})
    return ET.Element("TetrahedronHyperelasticityFEMForceField", {
        "name": card.name, "materialName": "NeoHookean",
        "ParameterSet": f"{_fmt(card.shear_modulus)} {_fmt(card.lame_lambda)}"})


def sofa_polynomial_coefficients(stiffness, cubic, rest_length) -> np.ndarray:
    """difftissue spring constants -> ``PolynomialSpringsForceField`` strain coefficients.

    SOFA's spring force is ``sigma(L) = a1 L + a2 L^2 + ... + an L^n`` of the strain
    ``L = (l - l0) / l0`` (cross section 1), so difftissue's tension ``k e + a e^3`` with
    ``e = L l0`` gives ``a1 = k l0`` [N], ``a2 = 0``, ``a3 = a l0^3`` [N].

    Args:
        stiffness: ``k`` [N/m] per spring; cubic: ``a`` [N/m^3]; rest_length: ``l0`` [m].

    Returns:
        ``(S, 3)`` coefficients ``[a1, a2, a3]`` [N] per spring (degree 3).
    """
    k, a, L0 = (np.asarray(v, dtype=float) for v in (stiffness, cubic, rest_length))
    k, a, L0 = np.broadcast_arrays(k, a, L0)
    return np.stack([k * L0, np.zeros_like(k), a * L0**3], axis=-1)


def springs_from_sofa_polynomial(coefficients, rest_length):
    """Inverse of :func:`sofa_polynomial_coefficients`: ``k = a1 / l0``, ``a = a3 / l0^3``
    (a nonzero ``a2`` has no difftissue counterpart and is refused)."""
    c = np.asarray(coefficients, dtype=float)
    L0 = np.asarray(rest_length, dtype=float)
    if c.shape[-1] != 3:
        raise ExportError(f"expected degree-3 coefficients [a1, a2, a3], got shape {c.shape}")
    if np.any(c[..., 1] != 0.0):
        raise ExportError("a2 != 0: a quadratic strain term (tension/compression asymmetric) has no difftissue counterpart")
    return c[..., 0] / L0, c[..., 2] / L0**3


def sofa_springs_split(card: MaterialCard, spring_fraction: float = 0.5) -> dict:
    """How a ``springs_volume`` card is split between SOFA's springs and a corotational FEM.

    SOFA has no per-cell volume-penalty force field, so the bulk term of ``springs_volume`` is
    carried by a ``TetrahedronFEMForceField`` (``method="large"``). A cube lattice with spring
    constants ``c mu g`` has Lamé parameters ``(c mu, c mu)``; the FEM adds
    ``lambda_f = lambda - c mu``, ``mu_f = (1 - c) mu`` so the sum is exactly (lambda, mu) at
    small strain for any ``0 <= c < 1`` (``c = spring_fraction``). The cubic coefficients of the
    springs are kept whole, so the cubic stiffening is difftissue's. Returns ``c``, ``lambda_f``,
    ``mu_f`` and the FEM's ``youngs_modulus`` / ``poisson_ratio``
    (``E_f = mu_f (3 lambda_f + 2 mu_f) / (lambda_f + mu_f)``, ``nu_f = lambda_f / (2 (lambda_f + mu_f))``).
    Inverse: ``lambda = c mu + lambda_f``, ``mu = c mu + mu_f`` (tested).
    """
    c = _finite(spring_fraction, "spring_fraction")
    if not 0.0 <= c < 1.0:
        raise ExportError(f"spring_fraction = {c:g} must lie in [0, 1) (the FEM needs a positive shear modulus)")
    mu, lam = card.shear_modulus, card.lame_lambda
    lam_f, mu_f = lam - c * mu, (1.0 - c) * mu
    if lam_f < 0:
        raise ExportError(f"spring_fraction = {c:g} leaves the FEM a negative lambda ({lam_f:.6g} Pa) at nu = {card.poisson_ratio:g}; "
                          f"use spring_fraction <= {lam / mu:.4g}")
    return {"spring_fraction": c, "lambda_f": lam_f, "mu_f": mu_f,
            "youngs_modulus": mu_f * (3 * lam_f + 2 * mu_f) / (lam_f + mu_f), "poisson_ratio": lam_f / (2 * (lam_f + mu_f))}


def _sofa_law(card: MaterialCard, law: str | None) -> str:
    return "springs" if law == "springs" else _law(card, law)


def sofa_scene(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
               displacement: float | None = None, spring_fraction: float = 0.5, steps: int = 10) -> ET.Element:
    """A SOFA scene: the force field in a ``Node`` (material alone), or with ``mesh`` a static
    specimen: ``MeshTopology`` (points, tetrahedra), ``MechanicalObject``, ``MeshMatrixMass``
    (``massDensity``), ``StaticSolver`` + ``SparseLDLSolver``, the force field(s), a
    ``FixedProjectiveConstraint`` on the base (min z) and a ``LinearMovementProjectiveConstraint``
    moving the top (max z) by ``displacement`` [m] along z over ``steps`` steps of ``dt = 1/steps``
    (:func:`_sofa_ramp`: ``keyTimes="0 1 1000000"``, held after t = 1; it prescribes all three
    components of the top nodes).

    ``law="springs"`` (needs ``mesh``, a structured block): difftissue's spring lattice as one
    ``PolynomialSpringsForceField`` (``object1 = object2 = @dofs``, degree-3 strain polynomials
    from :func:`sofa_polynomial_coefficients` with the springs scaled by ``spring_fraction``,
    ``compressible="1"``) plus the corotational ``TetrahedronFEMForceField`` of
    :func:`sofa_springs_split` for the rest of the stiffness.
    """
    law = _sofa_law(card, law)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": _fmt(1.0 / steps)})
    if law == "springs":
        if mesh is None:
            raise ExportError("law='springs' writes one SOFA spring per lattice edge: it needs a specimen mesh (--specimen)")
        if getattr(mesh, "lattice", None) is None:
            raise ExportError("law='springs' needs a structured block with a cube lattice (difftissue.mesh.block)")
        notes = _approximations(card, "SOFA springs", approximate=approximate, cubic_ok=True)
        split = sofa_springs_split(card, spring_fraction)
        notes = notes + [
            f"springs_volume split: springs carry {split['spring_fraction']:g} of mu (PolynomialSpringsForceField, full cubic "
            f"coefficients), a corotational TetrahedronFEMForceField carries lambda_f = {split['lambda_f']:.10g} Pa, "
            f"mu_f = {split['mu_f']:.10g} Pa; exact at small strain, finite-strain stress within about 1 % of springs_volume "
            "at 10 % strain (docs/export.md)"]
    else:
        notes = _approximations(card, "SOFA " + law, approximate=approximate)
    for line in _header_lines(card, "SOFA", law) + notes:
        root.append(_xml_comment(line))
    plugins = {"linear": ["Sofa.Component.SolidMechanics.FEM.Elastic"], "neo_hookean": ["Sofa.Component.SolidMechanics.FEM.HyperElastic"],
               "springs": ["Sofa.Component.SolidMechanics.Spring", "Sofa.Component.SolidMechanics.FEM.Elastic"]}[law]
    for plugin in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": plugin})
    if mesh is None:
        node = ET.SubElement(root, "Node", {"name": "tissue"})
        node.append(_xml_comment("add a tetrahedral topology and a MechanicalObject here"))
        node.append(sofa_force_field(card, law=law, approximate=True))
        return root
    for p in _SOFA_SPECIMEN_PLUGINS:  # every RequiredPlugin before the first Node that uses it
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    base, top, height = _specimen_sets(mesh)
    d = _default_displacement(height, displacement)
    _sofa_specimen_node(node, card, mesh, dt=1.0 / steps)
    if law == "springs":
        from .models import SpringVolumeModel

        model = SpringVolumeModel(mesh)
        # pre-stretch is dropped (and noted) for this target: springs of the unstretched lattice
        k, a = (np.asarray(v, dtype=float) for v in model.spring_constants(card.material().replace(pre_stretch=1.0)))
        split = sofa_springs_split(card, spring_fraction)
        coeffs = sofa_polynomial_coefficients(split["spring_fraction"] * k, a, model.rest_lengths)
        springs = np.asarray(model.springs)
        ET.SubElement(node, "PolynomialSpringsForceField", {
            "name": card.name + "_springs", "object1": "@dofs", "object2": "@dofs",
            "firstObjectPoints": " ".join(str(int(i)) for i in springs[:, 0]),
            "secondObjectPoints": " ".join(str(int(i)) for i in springs[:, 1]),
            "polynomialDegree": " ".join("3" for _ in range(len(springs))),
            "polynomialStiffness": " ".join(_fmt(c) for c in coeffs.reshape(-1)),
            "computeZeroLength": "1", "compressible": "1"})
        ET.SubElement(node, "TetrahedronFEMForceField", {"name": card.name + "_bulk", "youngModulus": _fmt(split["youngs_modulus"]),
                                                         "poissonRatio": _fmt(split["poisson_ratio"]), "method": "large"})
    else:
        node.append(sofa_force_field(card, law=law, approximate=True))
    ET.SubElement(node, "FixedProjectiveConstraint", {"name": "fixed_base", "indices": " ".join(str(int(i)) for i in base)})
    ET.SubElement(node, "LinearMovementProjectiveConstraint", {
        "name": "top_displacement", "template": "Vec3d", "indices": " ".join(str(int(i)) for i in top),
        **_sofa_ramp(d)})
    return root


#: SOFA plugins of a static specimen scene (solver, direct linear solver, mass, state, topology, projective
#: constraints, WriteState output).
_SOFA_SPECIMEN_PLUGINS = ("Sofa.Component.ODESolver.Backward", "Sofa.Component.LinearSolver.Direct", "Sofa.Component.Mass",
                          "Sofa.Component.StateContainer", "Sofa.Component.Topology.Container.Constant",
                          "Sofa.Component.Constraint.Projective", "Sofa.Component.Playback")


def _sofa_static_solver(node: ET.Element, size: float) -> None:
    """``StaticSolver`` with explicit Newton settings and a direct linear solver: at most 25
    Newton iterations per step, converged when the correction is below ``1e-12 size`` [m]
    (``size``: the specimen's diagonal) or 1e-10 of the displacement, or the residual below
    1e-10 of the first one (absolute residual test off: -1); ``SparseLDLSolver`` on 3x3
    blocks. SOFA's own defaults differ between releases, hence explicit."""
    ET.SubElement(node, "StaticSolver", {"newton_iterations": "25", "absolute_correction_tolerance_threshold": _fmt(1e-12 * size),
                                         "relative_correction_tolerance_threshold": "1e-10",
                                         "absolute_residual_tolerance_threshold": "-1",
                                         "relative_residual_tolerance_threshold": "1e-10"})
    ET.SubElement(node, "SparseLDLSolver", {"template": "CompressedRowSparseMatrixMat3x3d"})


def _sofa_output(node: ET.Element, dt: float, name: str = "tissue") -> None:
    """A ``WriteState`` (Sofa.Component.Playback) writing positions [m] and forces [N] of every
    node each step ``dt`` [s] to ``<name>_state.txt`` (after the ``MechanicalObject``). The
    reaction at a held node is minus its force entry; NOT run in SOFA here."""
    ET.SubElement(node, "WriteState", {"name": f"{name}_output", "filename": f"{name}_state.txt", "period": _fmt(dt),
                                       "time": "0", "writeX": "1", "writeV": "0", "writeF": "1"})


def _sofa_ramp(dz: float) -> dict:
    """Attributes of a ``LinearMovementProjectiveConstraint`` moving its nodes by ``(0, 0, dz)``
    [m] from t = 0 to t = 1 and HOLDING them there: SOFA's constraint acts only while a later
    key time exists (``findKeyTimes`` in LinearMovementProjectiveConstraint.inl sets
    ``finished`` only for ``t <`` a key time), so with ``keyTimes="0 1"`` alone the nodes would be
    free at t = 1, the last step; a third key time far later with the same movement holds them."""
    m = f"0 0 {_fmt(dz)}"
    return {"keyTimes": "0 1 1000000", "movements": f"0 0 0  {m}  {m}", "relativeMovements": "1"}


def _sofa_specimen_node(node: ET.Element, card: MaterialCard, mesh, *, dt: float) -> None:
    """The static solver and sparse LDL solver (:func:`_sofa_static_solver`), tet topology of
    ``mesh`` [m], its ``MechanicalObject``, a ``MeshMatrixMass`` of the card's density [kg/m^3]
    and the ``WriteState`` output (:func:`_sofa_output`, every ``dt`` [s]) inside the tissue node."""
    pts = np.asarray(mesh.points, dtype=float)
    _sofa_static_solver(node, float(np.linalg.norm(np.ptp(pts, axis=0))))
    ET.SubElement(node, "MeshTopology", {"name": "topology", "position": " ".join(_fmt(c) for c in pts.reshape(-1)),
                                         "tetrahedra": " ".join(str(int(n)) for n in np.asarray(mesh.tets).reshape(-1))})
    ET.SubElement(node, "MechanicalObject", {"name": "dofs", "template": "Vec3d", "src": "@topology"})
    ET.SubElement(node, "MeshMatrixMass", {"massDensity": _fmt(card.density)})
    _sofa_output(node, dt)


def write_sofa(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
               displacement: float | None = None, spring_fraction: float = 0.5, force: bool = False, indentation=None) -> Path:
    """Write a SOFA ``.scn`` scene (see :func:`sofa_scene`; conversions in :func:`sofa_force_field`,
    :func:`sofa_polynomial_coefficients`, :func:`sofa_springs_split`; indentation specimens:
    :func:`sofa_indentation_scene`)."""
    if indentation is not None:
        _no_mesh_with_indentation(mesh)
        if law == "springs":
            raise ExportError("law='springs' is written for the compression block only, not for an indentation specimen")
        return _write_text(path, _xml_text(sofa_indentation_scene(card, indentation, law=law, approximate=approximate)), force)
    return _write_text(path, _xml_text(sofa_scene(card, mesh, law=law, approximate=approximate, displacement=displacement,
                                                  spring_fraction=spring_fraction)), force)


# =========================================================================== Abaqus
_ABAQUS_BAD = re.compile(r"[^A-Za-z0-9_-]")
ABAQUS_FIELD_WIDTH = 20  # characters of a numeric data field that CalculiX reads (Abaqus reads more)


def _strip_zero(s: str) -> str:
    """``0.0035`` -> ``.0035`` (one character less; Fortran and Python read both)."""
    return s[1:] if s.startswith("0.") and len(s) > 2 else s


def _number_forms(x: float, digits: int | None) -> list[str]:
    """Decimal spellings of ``x``: shortest round-trip (``digits=None``) or ``digits``
    significant digits, positional and scientific with a one-digit minimum exponent."""
    unique = digits is None
    prec = None if unique else digits - 1
    sci = np.format_float_scientific(x, precision=prec, unique=unique, trim="-", exp_digits=1)
    pos = np.format_float_positional(x, precision=None if unique else digits, unique=unique, fractional=False, trim="-")
    sign = "-" if pos.startswith("-") else ""
    return [sci, sign + _strip_zero(pos.lstrip("-"))]


def abaqus_number(x: float, width: int = ABAQUS_FIELD_WIDTH) -> str:
    """One number as an Abaqus / CalculiX data field of at most ``width`` (20) characters.

    CalculiX reads only the first 20 characters of a numeric field (``7.575610012003474e-06``,
    21 characters, was read as 7.58), so every number in an ``.inp`` deck goes through here.
    The spelling is exact when the shortest round-trip spelling fits (Python ``repr``, or the
    same digits positional without the leading ``0`` or scientific with a one-digit exponent:
    ``float(abaqus_number(x)) == x``); otherwise it keeps the most significant digits that fit,
    correctly rounded. For a finite double at least 13 significant digits always fit
    (``-d.dddddddddddde-308``), so the relative error is at most ``5e-13``; at most ``5e-15``
    for ``1e-9 <= |x| < 1e10`` (15 digits fit). Units are those of the caller (SI here).
    Raises ExportError for non-finite values.
    """
    x = float(x)
    if not math.isfinite(x):
        raise ExportError(f"cannot write the non-finite number {x!r} into an Abaqus deck")
    text = repr(x)  # the shortest round-trip spelling, most often short enough
    if len(text) <= width:
        return text
    fits = sorted((s for s in _number_forms(x, None) if len(s) <= width), key=len)
    if fits:
        return fits[0]
    for digits in range(17, 0, -1):
        fits = sorted((s for s in _number_forms(x, digits) if len(s) <= width), key=len)
        if fits:
            return fits[0]
    raise ExportError(f"{x!r} does not fit in {width} characters")  # unreachable for width >= 7


def abaqus_name(name: str) -> str:
    """A safe Abaqus label: only ``[A-Za-z0-9_-]`` (others become ``_``), starting with a
    letter (``M_`` is prefixed otherwise), at most 80 characters."""
    s = _ABAQUS_BAD.sub("_", str(name))
    if not s or not s[0].isalpha():
        s = "M_" + s
    return s[:80]


def _abaqus_comment(text: str) -> str:
    return "** " + " ".join(str(text).split())


def abaqus_material(card: MaterialCard, *, law: str | None = None, approximate: bool = False) -> list[str]:
    """Abaqus keyword lines of the material.

    * ``law="linear"``: ``*ELASTIC`` with the data line ``E, nu``.
    * ``law="neo_hookean"``: ``*HYPERELASTIC, NEO HOOKE`` with the data line ``C10, D1`` where
      ``C10 = mu / 2`` and ``D1 = 2 / K`` (Abaqus: initial shear modulus ``mu0 = 2 C10``, bulk
      modulus ``K0 = 2 / D1``), ``mu = E / (2 (1 + nu))``, ``K = E / (3 (1 - 2 nu))``. Abaqus's
      energy ``C10 (I1bar - 3) + (J - 1)^2 / D1`` differs from FEBio's at finite strain but has
      the same small-strain response (E, nu).
    * ``*DENSITY`` with the density.

    Inverse (tested): ``mu = 2 C10``, ``K = 2 / D1``, ``E = 9 K mu / (3 K + mu)``,
    ``nu = (3 K - 2 mu) / (2 (3 K + mu))``.
    """
    law = _law(card, law)
    notes = _approximations(card, "Abaqus " + law, approximate=approximate)
    lines = [_abaqus_comment(s) for s in _header_lines(card, "Abaqus", law) + notes]
    if card.name != abaqus_name(card.name):
        lines.append(_abaqus_comment(f"material name sanitised from {card.name!r}"))
    lines.append(f"*MATERIAL, NAME={abaqus_name(card.name)}")
    if law == "linear":
        lines += ["*ELASTIC", f"{abaqus_number(card.youngs_modulus)}, {abaqus_number(card.poisson_ratio)}"]
    else:
        c10 = card.shear_modulus / 2.0
        d1 = 2.0 / card.bulk_modulus
        lines += ["*HYPERELASTIC, NEO HOOKE", f"{abaqus_number(c10)}, {abaqus_number(d1)}"]
    lines += ["*DENSITY", abaqus_number(card.density)]
    return lines


def _wrap_ids(ids, per_line: int = 16) -> list[str]:
    ids = [str(int(i)) for i in ids]
    return [", ".join(ids[i:i + per_line]) for i in range(0, len(ids), per_line)]


def abaqus_reaction_print(nset: str) -> list[str]:
    """Keyword lines that print the summed reaction force [N] of node set ``nset`` to the
    ``.dat`` file: ``*NODE PRINT, NSET=<nset>, TOTALS=ONLY`` with ``RF``. Accepted by Abaqus and
    CalculiX (CalculiX writes ``total force (fx,fy,fz) for set <NSET> and time ...`` followed by
    the three sums); CalculiX ignores history output (``*OUTPUT, HISTORY`` with ``RF1, ...``)."""
    return [f"*NODE PRINT, NSET={nset}, TOTALS=ONLY", "RF"]


#: Abaqus solid elements the specimen writers can use (``element=``, ``--element``): linear
#: tets, hybrid linear tets (near-incompressible hyperelasticity), quadratic tets (midside nodes
#: added by :func:`abaqus_quadratic`) and hybrid quadratic tets. CalculiX has C3D4 and C3D10 but
#: no hybrid elements (docs/export.md, tests/test_export_calculix.py).
ABAQUS_ELEMENTS = ("C3D4", "C3D4H", "C3D10", "C3D10H")
#: Local corner pairs of the midside nodes 5..10 of an Abaqus C3D10 (1-2, 2-3, 3-1, 1-4, 2-4, 3-4).
_C3D10_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))


def _abaqus_element(element: str) -> str:
    e = str(element).upper()
    if e not in ABAQUS_ELEMENTS:
        raise ExportError(f"element = {element!r}: expected one of {list(ABAQUS_ELEMENTS)}")
    return e


def abaqus_quadratic(points, tets):
    """Quadratic tets from linear ones: one midside node per edge at its midpoint [m].

    Returns ``(points (N + E, 3), tets (M, 10), edges (E, 2))``: the first N points are the
    input's, point ``N + k`` is the midpoint of ``edges[k]``; each row of ``tets`` is in Abaqus
    C3D10 order (corners 1-4, then midside 1-2, 2-3, 3-1, 1-4, 2-4, 3-4). Straight edges, so
    the geometry is the linear mesh's."""
    pts = np.asarray(points, dtype=float)
    t = np.asarray(tets, dtype=np.int64)
    pairs = np.sort(t[:, np.array(_C3D10_EDGES)].reshape(-1, 2), axis=1)
    edges, inv = np.unique(pairs, axis=0, return_inverse=True)
    mid = 0.5 * (pts[edges[:, 0]] + pts[edges[:, 1]])
    return np.vstack([pts, mid]), np.hstack([t, len(pts) + inv.reshape(len(t), 6)]), edges


def _abaqus_elements(points, tets, element: str):
    """``(points, connectivity)`` for ``element``: the mesh as is (C3D4, C3D4H) or with midside
    nodes (C3D10, C3D10H: :func:`abaqus_quadratic`)."""
    if element.startswith("C3D10"):
        p, t, _ = abaqus_quadratic(points, tets)
        return p, t
    return np.asarray(points, dtype=float), np.asarray(tets, dtype=np.int64)


def _element_comment(element: str) -> list[str]:
    """Header lines on the element choice (what CalculiX lacks)."""
    out = [f"element: {element}" + {"C3D4": " (linear tet)", "C3D4H": " (hybrid linear tet, for near-incompressible hyperelasticity)",
                                     "C3D10": " (quadratic tet, midside nodes at the edge midpoints)",
                                     "C3D10H": " (hybrid quadratic tet)"}[element]]
    if element.endswith("H"):
        out.append("CalculiX has no hybrid (H) elements: this deck is for Abaqus; use C3D4 or C3D10 in CalculiX (docs/export.md)")
    return out


def abaqus_model(card: MaterialCard, mesh=None, *, law: str | None = None, approximate: bool = False,
                 displacement: float | None = None, element: str = "C3D4") -> str:
    """Abaqus input: the material alone, or with ``mesh`` a complete specimen: ``*NODE``,
    ``*ELEMENT, TYPE=<element>`` (:data:`ABAQUS_ELEMENTS`, default C3D4; C3D10 / C3D10H get
    midside nodes, :func:`abaqus_quadratic`), node sets ``BASE`` (min z, clamped: ``BASE, 1, 3``, not
    ``ENCASTRE``, which CalculiX rejects) and ``TOP`` (max z, moved by ``displacement`` [m] in
    direction 3, free in x and y), ``*SOLID SECTION`` and one ``*STATIC`` step (``NLGEOM=YES``
    for the neo-Hookean law) that prints the summed ``TOP`` reaction [N] to the ``.dat``
    (:func:`abaqus_reaction_print`). Runs in CalculiX 2.20 with C3D4 and C3D10
    (tests/test_export_calculix.py); CalculiX has no hybrid elements."""
    law = _law(card, law)
    element = _abaqus_element(element)
    mat = abaqus_material(card, law=law, approximate=approximate)
    if mesh is None:
        return "\n".join(mat) + "\n"
    pts, conn = _abaqus_elements(mesh.points, mesh.tets, element)
    base, top, height = _specimen_sets(SimpleNamespace(points=pts))
    d = _default_displacement(height, displacement)
    mname = abaqus_name(card.name)
    lines = ["*HEADING", f"difftissue specimen for material {mname} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in _element_comment(element)] + ["*NODE"]
    for i, p in enumerate(pts, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    lines.append(f"*ELEMENT, TYPE={element}, ELSET=TISSUE")
    for i, t in enumerate(conn, start=1):
        lines.append(f"{i}, " + ", ".join(str(int(n) + 1) for n in t))
    lines.append("*NSET, NSET=BASE")
    lines += _wrap_ids(base + 1)
    lines.append("*NSET, NSET=TOP")
    lines += _wrap_ids(top + 1)
    lines += [f"*SOLID SECTION, ELSET=TISSUE, MATERIAL={mname}", ","]
    lines += mat
    lines += [f"*STEP, NLGEOM={'YES' if law == 'neo_hookean' else 'NO'}", "*STATIC", "0.1, 1.0, 1e-05, 0.1",
              "*BOUNDARY", "BASE, 1, 3", "*BOUNDARY", f"TOP, 3, 3, {abaqus_number(d)}",
              "*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    lines += abaqus_reaction_print("TOP") + ["*END STEP"]
    return "\n".join(lines) + "\n"


def write_abaqus(card: MaterialCard, path, *, mesh=None, law: str | None = None, approximate: bool = False,
                 displacement: float | None = None, force: bool = False, indentation=None, element: str = "C3D4") -> Path:
    """Write an Abaqus ``.inp`` (see :func:`abaqus_model`; conversion in :func:`abaqus_material`;
    indentation specimens: :func:`abaqus_indentation_model`, C3D4 only)."""
    if indentation is not None:
        _no_mesh_with_indentation(mesh)
        if _abaqus_element(element) != "C3D4":
            raise ExportError(f"element = {element!r}: the Abaqus indentation specimen is written with C3D4 only")
        return _write_text(path, abaqus_indentation_model(card, indentation, law=law, approximate=approximate), force)
    return _write_text(path, abaqus_model(card, mesh, law=law, approximate=approximate, displacement=displacement,
                                          element=element), force)


# ============================================================================= XPBD
def xpbd_parameters(card: MaterialCard, *, dt: float, iterations: int, substeps: int = 1, mesh=None,
                    approximate: bool = False, displacement: float | None = None, indentation=None, calibrate: bool = True) -> dict:
    """Stable neo-Hookean XPBD constraint data (Macklin & Müller 2021) for a stated time step.

    Per tetrahedron of rest volume ``V0``: deviatoric constraint ``C_D = sqrt(tr F^T F)`` with
    compliance ``alpha_D = 1 / (mu V0)``, hydrostatic ``C_H = det F - gamma`` with
    ``alpha_H = 1 / (lambda' V0)``, ``lambda' = lambda + mu`` and ``gamma = 1 + mu / lambda'``
    (the shift makes the small-strain response equal (E, nu)). The solver uses
    ``alpha_tilde = alpha / h^2`` with the substep ``h = dt / substeps``. Without ``mesh`` the
    values are given per unit volume (``alpha V0``, in 1/Pa); with ``mesh`` per tetrahedron,
    plus a ``"specimen"`` (positions, tets, lumped masses, base fixed, top moved by
    ``displacement`` [m] along z, default -10 % of the height).

    With a specimen (a block, or a flat-punch indentation) and ``calibrate`` (default), the
    compliances are **recalibrated for the written budget** (:mod:`difftissue.export_budget`):
    ``mu`` and ``lambda'`` times one factor so that standard XPBD (multipliers reset every
    substep) at ``dt`` / ``substeps`` / ``iterations``, run by difftissue's XPBD solver on the
    specimen, reproduces the card's own model's reactions within 2 % at up to 4 load states;
    a saturated budget is refused with a suggested one (``approximate``: written with the
    measured signed error). Without a specimen (or for sphere / cone specimens, which
    difftissue's solver cannot run) the values are the card's converged-limit ones: XPBD with
    a finite iteration count is softer than they imply (``validity`` says so).
    """
    dt = _finite(dt, "dt")
    if dt <= 0:
        raise ExportError(f"dt = {dt:g} s must be > 0")
    if int(iterations) != iterations or iterations < 1:
        raise ExportError(f"iterations = {iterations!r} must be a positive integer")
    if int(substeps) != substeps or substeps < 1:
        raise ExportError(f"substeps = {substeps!r} must be a positive integer")
    notes = _approximations(card, "XPBD stable neo-Hookean", approximate=approximate)
    mu, lam = card.shear_modulus, card.lame_lambda
    lam_s = lam + mu
    h = dt / substeps
    out = {
        "format": "difftissue-xpbd/1",
        "units": UNITS,
        "constraints": "stable neo-Hookean pair (Macklin & Mueller 2021): C_D = sqrt(tr F^T F), C_H = det F - gamma",
        "material": card.name,
        "model": card.model,
        "setting": {"dt": dt, "iterations": int(iterations), "substeps": int(substeps), "substep": h},
        "lame": {"mu": mu, "lambda": lam, "lambda_shifted": lam_s},
        "gamma": 1.0 + mu / lam_s,
        "per_unit_volume": {"deviatoric_compliance": 1.0 / mu, "hydrostatic_compliance": 1.0 / lam_s,
                            "unit": "1/Pa (divide by the tet rest volume V0 [m^3])"},
        "density": card.density,
        "validity": (f"compliances reproduce E = {card.youngs_modulus:.6g} Pa, nu = {card.poisson_ratio:.6g} only when "
                     f"the XPBD iterations converge; with {int(iterations)} iteration(s) the response is softer "
                     "(budget-aware calibration not applied)"),
        "notes": notes,
        "card_provenance": card.provenance,
    }
    if indentation is not None:
        _no_mesh_with_indentation(mesh)
        mesh = indentation.mesh()
    if mesh is not None:
        pts = np.asarray(mesh.points, dtype=float)
        t = np.asarray(mesh.tets)
        v0 = np.abs(np.einsum("ij,ij->i", np.cross(pts[t[:, 1]] - pts[t[:, 0]], pts[t[:, 2]] - pts[t[:, 0]]), pts[t[:, 3]] - pts[t[:, 0]])) / 6.0
        out["per_tet"] = {
            "rest_volume": v0.tolist(),
            "deviatoric_compliance": (1.0 / (mu * v0)).tolist(),
            "hydrostatic_compliance": (1.0 / (lam_s * v0)).tolist(),
            "deviatoric_alpha_tilde": (1.0 / (mu * v0) / h**2).tolist(),
            "hydrostatic_alpha_tilde": (1.0 / (lam_s * v0) / h**2).tolist(),
            "unit": "compliance 1/(Pa m^3); alpha_tilde = compliance / h^2",
        }
        out["specimen"] = _specimen_dict(card, mesh, displacement) if indentation is None else _xpbd_indentation_specimen(card, indentation, mesh)
        if calibrate and (indentation is None or indentation.indenter == "flat_punch"):
            _xpbd_calibrate_specimen(out, card, mesh, indentation, approximate)
        elif calibrate:
            out["notes"].append(f"NOT calibrated for the budget: difftissue's XPBD solver has no contact constraint, so the "
                                f"{indentation.indenter} specimen cannot be run at this budget here; the compliances are the card's "
                                "converged-limit values (see validity)")
    return out


def _xpbd_calibrate_specimen(doc: dict, card: MaterialCard, mesh, indentation, approximate: bool) -> None:
    """Recalibrate a block or flat-punch XPBD document for its budget (:mod:`difftissue.export_budget`)."""
    from .export_budget import card_reference_reactions, load_fractions, xpbd_budget_calibration

    sp = doc["specimen"]
    n = len(sp["positions"])
    fixed = np.zeros((n, 3), dtype=bool)
    presc = np.zeros((n, 3))
    if indentation is None:
        fixed[sp["fixed"]] = True
        fixed[sp["moved"]] = True
        presc[sp["moved"]] = sp["displacement"]
        moved = np.asarray(sp["moved"])
        fr = load_fractions(4)
    else:
        fx = sp["fixed"]
        if "all_components" in fx:
            fixed[np.asarray(fx["all_components"], dtype=np.int64)] = True
        for c, axis in (("x", 0), ("y", 1), ("z", 2)):
            if c in fx:
                fixed[np.asarray(fx[c], dtype=np.int64), axis] = True
        ind = sp["indenter"]
        moved = np.asarray(ind["nodes"], dtype=np.int64)
        fixed[moved, 2] = True
        if ind.get("bonded"):
            fixed[moved, :2] = True
        presc[moved, 2] = -float(indentation.depth)
        fr = load_fractions(indentation.steps)
    observe = np.zeros((n, 3), dtype=bool)
    observe[moved] = fixed[moved]
    try:
        ref = card_reference_reactions(card, mesh, fixed, presc, observe, fr)
    except ExportError as e:
        if not approximate:
            raise ExportError(f"XPBD: {e}; pass approximate=True (--approximate) to write the card's converged-limit compliances") from None
        doc["notes"].append(f"APPROXIMATION: not calibrated for the budget: {e}")
        return
    xpbd_budget_calibration(doc, ref, fixed, presc, observe, fr, approximate=approximate)
    doc["budget_calibration"]["reference_model"] = card.model


def _xpbd_indentation_specimen(card: MaterialCard, spec, mesh) -> dict:
    from .export_indentation import indentation_sets

    s = indentation_sets(spec, mesh, card)
    pts = np.asarray(mesh.points, dtype=float)
    t = np.asarray(mesh.tets)
    v0 = np.abs(np.einsum("ij,ij->i", np.cross(pts[t[:, 1]] - pts[t[:, 0]], pts[t[:, 2]] - pts[t[:, 0]]), pts[t[:, 3]] - pts[t[:, 0]])) / 6.0
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(card.density * v0 / 4.0, 4))
    if spec.base == "bonded":
        fixed = {"all_components": s["base"].tolist()}
    else:
        fixed = {"z": s["base"].tolist(), "x": [s["anchor"]], "y": [s["anchor"], s["other"]]}
    return {"experiment": "indentation", "positions": pts.tolist(), "tets": t.tolist(), "masses": m.tolist(),
            "fixed": fixed, "indenter": _xpbd_indenter(card, spec, mesh), "assumptions": spec.describe(),
            "note": "SI; fixed: node ids per held component (base z = 0); masses rho V/4 per tet node"}


def _specimen_dict(card: MaterialCard, mesh, displacement: float | None) -> dict:
    """Mesh, lumped masses and boundary conditions of the block specimen (JSON-ready)."""
    pts = np.asarray(mesh.points, dtype=float)
    t = np.asarray(mesh.tets)
    base, top, height = _specimen_sets(mesh)
    d = _default_displacement(height, displacement)
    v0 = np.abs(np.einsum("ij,ij->i", np.cross(pts[t[:, 1]] - pts[t[:, 0]], pts[t[:, 2]] - pts[t[:, 0]]), pts[t[:, 3]] - pts[t[:, 0]])) / 6.0
    m = np.zeros(len(pts))
    np.add.at(m, t.reshape(-1), np.repeat(card.density * v0 / 4.0, 4))
    return {"positions": pts.tolist(), "tets": t.tolist(), "masses": m.tolist(),
            "fixed": base.tolist(), "moved": top.tolist(), "displacement": [0.0, 0.0, d],
            "note": "SI; base (min z) fixed, top (max z) moved by 'displacement' (all components), masses rho V/4 per tet node"}


def write_xpbd(card: MaterialCard, path, *, dt: float, iterations: int, substeps: int = 1, mesh=None,
               approximate: bool = False, displacement: float | None = None, force: bool = False, indentation=None,
               calibrate: bool = True) -> Path:
    """Write :func:`xpbd_parameters` as JSON."""
    doc = xpbd_parameters(card, dt=dt, iterations=iterations, substeps=substeps, mesh=mesh, approximate=approximate,
                          displacement=displacement, indentation=indentation, calibrate=calibrate)
    return _write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n", force)


# ============================================================================== VTU
def write_vtu(card: MaterialCard, mesh, path, *, displacement: float | None = None, force: bool = False, indentation=None) -> Path:
    """Write ``mesh`` as VTU with per-cell material fields: ``youngs_modulus``, ``poisson_ratio``,
    ``cubic_coefficient``, ``density``, ``pre_stretch``, ``shear_modulus`` (mu), ``lame_lambda``,
    ``bulk_modulus`` (all SI), constant over the cells, and the specimen's boundary conditions as
    point data: ``boundary`` (0 free, 1 base fixed, 2 top moved) and ``prescribed_displacement``
    [m] (top: ``(0, 0, displacement)``, default -10 % of the height). No conversion is involved."""
    from .mesh import write_mesh

    if indentation is not None:
        _no_mesh_with_indentation(mesh)
        return _write_vtu_indentation(card, indentation, path, force)
    if mesh is None:
        raise ExportError("a VTU export needs a mesh (--specimen)")
    if Path(path).suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a VTU export must end in .vtu")
    n = int(np.asarray(mesh.tets).shape[0])
    vals = {k: card.value(k) for k in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")}
    vals.update(shear_modulus=card.shear_modulus, lame_lambda=card.lame_lambda, bulk_modulus=card.bulk_modulus)
    cell = {k: np.full(n, float(v)) for k, v in vals.items()}
    base, top, height = _specimen_sets(mesh)
    d = _default_displacement(height, displacement)
    boundary = np.zeros(len(np.asarray(mesh.points)))
    boundary[base] = 1.0
    boundary[top] = 2.0
    presc = np.zeros((len(boundary), 3))
    presc[top, 2] = d
    point = {"boundary": boundary, "prescribed_displacement": presc}
    return write_mesh(path, mesh, point_data=point, cell_data=cell, overwrite=force)



# ======================================================================== scikit-fem
def to_skfem(card: MaterialCard, mesh=None, *, approximate: bool = False) -> dict:
    """The card as a scikit-fem linear-elasticity model (in memory; imports ``skfem``).

    Conversion: scikit-fem's ``skfem.models.elasticity.linear_elasticity(Lambda, Mu)`` takes the
    Lamé parameters, ``lam = E nu / ((1 + nu)(1 - 2 nu))`` and ``mu = E / (2 (1 + nu))``; its
    energy ``W = lam/2 tr(eps)^2 + mu eps:eps`` is difftissue's ``fem_linear`` and the
    small-strain response of every model. A nonzero ``cubic_coefficient`` or a ``pre_stretch``
    other than 1 is refused unless ``approximate`` (then listed in ``"notes"``).

    Returns ``{"lam", "mu", "form", "notes"}`` (``form``: the bilinear form for ``skfem.asm``);
    with ``mesh`` also ``"mesh"`` (``skfem.MeshTet``, same node and tet order), ``"basis"``
    (vector P1), ``"stiffness"`` (assembled CSR matrix [N/m]) and ``"dofs"``: an ``(N, 3)``
    integer array, ``dofs[a, c]`` is scikit-fem's DOF of component ``c`` of node ``a``.
    """
    try:
        import skfem
        from skfem.models.elasticity import linear_elasticity
    except ImportError:
        raise ExportError("the scikit-fem export needs scikit-fem (pip install scikit-fem)") from None
    notes = _approximations(card, "scikit-fem linear elasticity", approximate=approximate)
    lam, mu = card.lame_lambda, card.shear_modulus
    out = {"lam": lam, "mu": mu, "form": linear_elasticity(lam, mu), "notes": notes}
    if mesh is not None:
        pts = np.asarray(mesh.points, dtype=float)
        tets = np.asarray(mesh.tets, dtype=np.int64)
        m = skfem.MeshTet(pts.T.copy(), tets.T.copy())
        basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
        out.update(mesh=m, basis=basis, stiffness=skfem.asm(out["form"], basis).tocsr(),
                   dofs=np.asarray(basis.nodal_dofs).T.copy())
    return out

def _write_vtu_indentation(card: MaterialCard, spec, path, force: bool) -> Path:
    """VTU of an indentation specimen: material cell fields as for the block, point data
    ``boundary`` (0 free, 1 base bonded, 4 base sliding (u_z = 0), 2 punch, 3 contact
    candidate), ``prescribed_displacement`` [m] (punch: ``(0, 0, -depth)``) and
    ``contact_penalty`` [N/m] (difftissue's ``kappa_i`` of the candidate nodes)."""
    from .export_indentation import indentation_sets
    from .mesh import write_mesh

    if Path(path).suffix.lower() != ".vtu":
        raise ExportError(f"{path}: a VTU export must end in .vtu")
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    n = int(np.asarray(mesh.tets).shape[0])
    vals = {k: card.value(k) for k in ("youngs_modulus", "poisson_ratio", "cubic_coefficient", "density", "pre_stretch")}
    vals.update(shear_modulus=card.shear_modulus, lame_lambda=card.lame_lambda, bulk_modulus=card.bulk_modulus)
    cell = {k: np.full(n, float(v)) for k, v in vals.items()}
    npts = len(np.asarray(mesh.points))
    boundary = np.zeros(npts)
    presc = np.zeros((npts, 3))
    kappa = np.zeros(npts)
    if spec.indenter == "flat_punch":
        boundary[s["punch"]] = 2.0
        presc[s["punch"], 2] = -spec.depth
    else:
        boundary[s["contact_nodes"]] = 3.0
        kappa[s["contact_nodes"]] = s["kappa"]
    boundary[s["base"]] = 1.0 if spec.base == "bonded" else 4.0
    point = {"boundary": boundary, "prescribed_displacement": presc, "contact_penalty": kappa}
    return write_mesh(path, mesh, point_data=point, cell_data=cell, overwrite=force)


def _no_mesh_with_indentation(mesh) -> None:
    if mesh is not None:
        raise ExportError("give either a block specimen (mesh) or an indentation specimen, not both")


# =========================================================================== common
def _write_text(path, text: str, force: bool) -> Path:
    with atomic_output(path, overwrite=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def export(card: MaterialCard, to: str, path, *, mesh=None, approximate: bool = False, force: bool = False,
           law: str | None = None, dt: float | None = None, iterations: int | None = None, substeps: int | None = None,
           displacement: float | None = None, constraints: str = "xpbd", indentation=None, fitted=None,
           nu: float | None = None, element: str = "C3D4") -> Path:
    """Write ``card`` for target ``to`` (one of :data:`TARGETS`) to ``path``.

    ``to="pbd"``: a pypbd scene (:func:`difftissue.pbd.write_pbd`; ``constraints`` ``"xpbd"`` or
    ``"fem"``, ``dt`` default 1/60 s, ``iterations`` default 10). ``indentation``: an
    :class:`~difftissue.export_indentation.IndentationSpecimen` (instead of ``mesh``).
    ``fitted``: a :class:`~difftissue.export_fitted.FittedSpecimen` (the experiment of a
    fem_field / incision fit, :func:`~difftissue.export_fitted.fitted_specimen_from_card`),
    written by :func:`~difftissue.export_fitted.write_fitted`. ``element``: the Abaqus element
    (:data:`ABAQUS_ELEMENTS`; other targets refuse anything but the default C3D4).

    A card whose E is an effective modulus (half-space indentation fit, nu fixed at 0) is
    refused unless ``nu`` converts it or ``approximate`` (:func:`resolve_effective_modulus`)."""
    if _abaqus_element(element) != "C3D4" and to != "abaqus":
        raise ExportError(f"element = {element!r} is an Abaqus option; {to} is written with linear tets")
    card = resolve_effective_modulus(card, nu=nu, approximate=approximate)
    if fitted is not None:
        if mesh is not None or indentation is not None or displacement is not None:
            raise ExportError("a fitted specimen carries its own mesh and prescribed displacements: give no mesh, indentation or displacement")
        from .export_fitted import write_fitted

        return write_fitted(card, to, path, fitted, law=law, approximate=approximate, force=force, dt=dt,
                            iterations=iterations, substeps=substeps, element=element)
    if indentation is not None and displacement is not None:
        raise ExportError("displacement is the compression block's top displacement; an indentation specimen takes its depth")
    if to == "febio":
        return write_febio(card, path, mesh=mesh, law=law, approximate=approximate, displacement=displacement, force=force,
                           indentation=indentation)
    if to == "sofa":
        return write_sofa(card, path, mesh=mesh, law=law, approximate=approximate, displacement=displacement, force=force,
                          indentation=indentation)
    if to == "abaqus":
        return write_abaqus(card, path, mesh=mesh, law=law, approximate=approximate, displacement=displacement, force=force,
                            indentation=indentation, element=element)
    if to == "pbd":
        from .pbd import write_pbd

        return write_pbd(card, path, mesh=mesh, constraints=constraints, dt=dt, iterations=iterations, substeps=substeps,
                         approximate=approximate, displacement=displacement, force=force, indentation=indentation)
    if to == "xpbd":
        if dt is None or iterations is None:
            raise ExportError("an XPBD export needs the time step dt and the iteration count (--dt, --iterations)")
        return write_xpbd(card, path, dt=dt, iterations=iterations, substeps=1 if substeps is None else substeps, mesh=mesh,
                          approximate=approximate,
                          displacement=displacement, force=force, indentation=indentation)
    if to == "vtu":
        return write_vtu(card, mesh, path, displacement=displacement, force=force, indentation=indentation)
    raise ExportError(f"unknown export target {to!r}; choose one of {list(TARGETS)}")


# ===================================================================== indentation
_WHY = {
    ("SOFA", "cone"): ("the SOFA scene has no cone: SOFA's ConicalForceField (Sofa.Component.MechanicalLoad) was not "
                       "checked against difftissue's cone penetration; export the cone to Abaqus or the XPBD JSON"),
}


def _ind_check(spec, target: str, *, cone: bool = True, sphere: bool = True, sliding: bool = True,
               frictionless_punch: bool = True) -> None:
    """Refuse (one ExportError line) what ``target`` cannot represent of the indentation ``spec``."""
    for shape, ok in (("cone", cone), ("sphere", sphere)):
        if spec.indenter == shape and not ok:
            raise ExportError(f"{target} indentation specimen: a {shape} indenter cannot be written: " + _WHY[(target, shape)])
    if spec.base == "sliding" and not sliding:
        raise ExportError(f"{target} indentation specimen: base='sliding' (u_z = 0, x and y free) cannot be written: "
                          f"{target}'s moved/fixed nodes hold all three components; use base='bonded' (--base bonded)")
    if spec.indenter == "flat_punch" and not spec.bonded_punch and not frictionless_punch:
        raise ExportError(f"{target} indentation specimen: a frictionless flat punch (u_z prescribed, x and y free) cannot be "
                          f"written: {target} prescribes all three components of moved nodes; use bonded_punch=True (--bonded-punch)")


def _indentation_card(card: MaterialCard, spec, law: str | None, approximate: bool) -> MaterialCard:
    """A lattice card recalibrated on its fitted indentation for a continuum target
    (:func:`~difftissue.export_indentation.indentation_card`)."""
    from .export_indentation import indentation_card

    return indentation_card(card, spec, law, approximate=approximate)


FEBIO_INDENTER_MATERIAL = "rigid_indenter"


def febio_indenter_cap(spec, height: float, spacing: float, *, max_rings: int = 48):
    """Triangulated cap of a sphere or cone indenter for the FEBio specimen (SI units).

    The indenter's tip touches the top face ``z = height`` on the axis ``x = y = 0``; the
    sphere's centre is ``(0, 0, height + R)``, the cone's tip ``(0, 0, height)``. The cap
    extends to the horizontal radius ``r_cap``: sphere ``min(3 sqrt(R d), R)`` (3x the
    small-strain contact radius, at most the hemisphere), cone ``3 d tan(theta)`` (3x the
    radius where the cone crosses the undeformed surface at the final depth ``d``, which
    exceeds the contact radius ``2 d tan(theta) / pi``). Rings ``k = 0..n`` (ring ``k`` has
    ``6 k`` nodes, the tip is ring 0) at equal polar angles (sphere) or equal radii (cone),
    ``n = ceil(arc length / (spacing / 2))`` clipped to ``[4, max_rings]`` (``spacing`` [m]: the
    tissue's top cell size; the rings are then at most ``spacing / 2`` apart unless clipped),
    zipped into ``tri3`` facets whose normal ``(x1 - x0) x (x2 - x0)`` points away from the
    indenter's interior (towards the tissue).

    Returns ``(points (N, 3), tris (M, 3) 0-based, r_cap)``.
    """
    if not (math.isfinite(spacing) and spacing > 0):
        raise ExportError(f"indenter cap spacing = {spacing!r} must be a positive length [m]")
    d = spec.depth
    if spec.indenter == "sphere":
        R = spec.radius
        r_cap = min(3.0 * math.sqrt(R * d), R)
        theta_max = math.asin(r_cap / R) if r_cap < R else 0.5 * math.pi
        arc = R * theta_max
    elif spec.indenter == "cone":
        r_cap = 3.0 * d * math.tan(spec.half_angle)
        arc = r_cap / math.sin(spec.half_angle)
    else:
        raise ExportError(f"no indenter cap for a {spec.indenter!r} indenter (sphere and cone only)")
    n = int(min(max(4, math.ceil(arc / (0.5 * spacing))), max_rings))
    pts = [(0.0, 0.0, float(height))]
    rings = [[0]]
    for k in range(1, n + 1):
        if spec.indenter == "sphere":
            th = theta_max * k / n
            r, z = R * math.sin(th), height + R - R * math.cos(th)
        else:
            r = r_cap * k / n
            z = height + r / math.tan(spec.half_angle)
        ids = []
        for m in range(6 * k):
            phi = 2.0 * math.pi * m / (6 * k)
            ids.append(len(pts))
            pts.append((r * math.cos(phi), r * math.sin(phi), z))
        rings.append(ids)
    tris = []
    for k in range(1, n + 1):
        inner, outer = rings[k - 1], rings[k]
        ni, no = len(inner), len(outer)
        if ni == 1:
            tris += [(inner[0], outer[j], outer[(j + 1) % no]) for j in range(no)]
            continue
        i = j = 0
        while i < ni or j < no:  # zip the two rings by angle: ni + no triangles
            if j < no and (i >= ni or (j + 1) / no <= (i + 1) / ni):
                tris.append((inner[i % ni], outer[j], outer[(j + 1) % no]))
                j += 1
            else:
                tris.append((inner[i], outer[j % no], inner[(i + 1) % ni]))
                i += 1
    P = np.asarray(pts, dtype=float)
    T = np.asarray(tris, dtype=np.int64)
    # orient every facet away from the indenter's interior (sphere: from the centre; cone: outward and down)
    nrm = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    c = P[T].mean(axis=1)
    if spec.indenter == "sphere":
        out = c - np.array([0.0, 0.0, height + spec.radius])
    else:
        rho = np.hypot(c[:, 0], c[:, 1])
        out = np.stack([c[:, 0] * math.cos(spec.half_angle) / np.maximum(rho, 1e-300),
                        c[:, 1] * math.cos(spec.half_angle) / np.maximum(rho, 1e-300),
                        -np.full(len(c), math.sin(spec.half_angle))], axis=1)
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    T[flip] = T[flip][:, [0, 2, 1]]
    return P, T, float(r_cap)


def febio_indentation_model(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """FEBio 4.0 model of an indentation specimen (:mod:`difftissue.export_indentation`).

    Tissue (all indenters): nodes ``1..N`` (``<Nodes name="specimen">``), ``tet4`` elements
    ``1..Nt`` (``tissue``), node sets ``base``, ``top`` (and ``base_anchor``, ``base_other``
    for a sliding base); the base ``z = 0`` is ``zero displacement`` x, y, z (bonded) or z only
    plus ``base_anchor`` (x, y) and ``base_other`` (y) (sliding).

    Flat punch: the ``prescribed displacement`` (``dof`` z, ``-depth`` ramped by load
    controller 1 over ``spec.steps`` static steps) of the node set ``punch`` (top nodes within
    the radius), plus ``zero displacement`` x, y of the same set for a bonded punch. The punch
    force is the sum of the ``reaction forces`` (plot variable) over ``punch``.

    Sphere and cone: a meshed rigid indenter, as FEBio users model one (FEBio 4.0 has no
    analytical sphere or cone): the cap of :func:`febio_indenter_cap` (``tri3`` shells, nodes
    ``N+1..``, elements ``Nt+1..``) in a ``ShellDomain`` of a ``<material type="rigid body">``
    (``center_of_mass`` at the sphere centre / cone tip), ``rigid_fixed`` x, y and the three
    rotations, ``rigid_displacement`` z = ``-depth`` (load controller 1); frictionless
    ``sliding-elastic`` contact (``fric_coeff`` 0) on the ``SurfacePair`` with the tissue's top
    face as ``primary`` and the indenter cap as ``secondary``, penalty method (``laugon`` 0,
    ``auto_penalty`` 0) with ``penalty = p E / h`` [Pa/m], difftissue's per-node penalty
    ``kappa_i = p E sqrt(A_i)`` per tributary area (``h = sqrt(A)`` of the top node on the
    axis). The indentation force is minus the sum of the base's ``reaction forces`` along z
    (static equilibrium, no other loads). Keyword sources: docs/export.md.
    """
    from .export_indentation import indentation_sets

    _ind_check(spec, "FEBio")
    card = _indentation_card(card, spec, law, approximate)
    contact = spec.indenter in ("sphere", "cone")
    if contact and card.name == FEBIO_INDENTER_MATERIAL:
        raise ExportError(f"FEBio indentation specimen: the card's name {card.name!r} is the indenter's rigid material name; "
                          "rename the card (its 'name')")
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    pts_t = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    H = s["H"]
    root = _febio_static_root(spec.describe(), spec.steps)
    mats = febio_material(card, law=law, approximate=approximate)
    root.append(mats)
    if contact:
        cap_pts, cap_tris, r_cap = febio_indenter_cap(spec, H, spacing=s["h"])
        centre = (0.0, 0.0, H + spec.radius) if spec.indenter == "sphere" else (0.0, 0.0, H)
        mats.append(_xml_comment(
            "the indenter: a rigid body (FEBio 'rigid body' material; E and v are used only by FEBio's auto-penalty, "
            "which this file does not use); center_of_mass = " + ("the sphere centre (0, 0, H + R)" if spec.indenter == "sphere"
                                                                  else "the cone tip (0, 0, H)")))
        rig = ET.SubElement(mats, "material", {"id": "2", "name": FEBIO_INDENTER_MATERIAL, "type": "rigid body"})
        ET.SubElement(rig, "density").text = _fmt(card.density)
        ET.SubElement(rig, "E").text = _fmt(card.youngs_modulus)
        ET.SubElement(rig, "v").text = _fmt(card.poisson_ratio)
        ET.SubElement(rig, "center_of_mass").text = ",".join(_fmt(c) for c in centre)
    meshel = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(meshel, "Nodes", {"name": "specimen"})
    for i, p in enumerate(pts_t, start=1):
        ET.SubElement(nodes, "node", {"id": str(i)}).text = ",".join(_fmt(c) for c in p)
    n_t = len(pts_t)
    if contact:
        meshel.append(_xml_comment(
            f"indenter cap: {len(cap_pts)} nodes on the {spec.indenter} (tip at (0, 0, H)), {len(cap_tris)} tri3 facets, "
            f"horizontal radius {r_cap:.6g} m (contact radius at the final depth {spec.contact_radius():.6g} m); "
            "facet normals point away from the indenter, towards the tissue"))
        cnodes = ET.SubElement(meshel, "Nodes", {"name": "indenter"})
        for i, p in enumerate(cap_pts, start=n_t + 1):
            ET.SubElement(cnodes, "node", {"id": str(i)}).text = ",".join(_fmt(c) for c in p)
    elems = ET.SubElement(meshel, "Elements", {"type": "tet4", "name": "tissue"})
    for i, t in enumerate(tets, start=1):
        ET.SubElement(elems, "elem", {"id": str(i)}).text = ",".join(str(int(n) + 1) for n in t)
    if contact:
        shells = ET.SubElement(meshel, "Elements", {"type": "tri3", "name": "indenter_shell"})
        for i, t in enumerate(cap_tris, start=len(tets) + 1):
            ET.SubElement(shells, "elem", {"id": str(i)}).text = ",".join(str(int(n) + n_t + 1) for n in t)
    ids = lambda a: ",".join(str(int(n) + 1) for n in np.atleast_1d(a))  # noqa: E731
    ET.SubElement(meshel, "NodeSet", {"name": "base"}).text = ids(s["base"])
    ET.SubElement(meshel, "NodeSet", {"name": "top"}).text = ids(s["top"])
    if spec.base == "sliding":
        ET.SubElement(meshel, "NodeSet", {"name": "base_anchor"}).text = ids(s["anchor"])
        ET.SubElement(meshel, "NodeSet", {"name": "base_other"}).text = ids(s["other"])
    if not contact:
        ET.SubElement(meshel, "NodeSet", {"name": "punch"}).text = ids(s["punch"])
    else:
        surf = ET.SubElement(meshel, "Surface", {"name": "tissue_top"})
        for i, f in enumerate(s["top_faces"], start=1):
            ET.SubElement(surf, "tri3", {"id": str(i)}).text = ids(f)
        csurf = ET.SubElement(meshel, "Surface", {"name": "indenter_surface"})
        for i, f in enumerate(cap_tris, start=1):
            ET.SubElement(csurf, "tri3", {"id": str(i)}).text = ",".join(str(int(n) + n_t + 1) for n in f)
        pair = ET.SubElement(meshel, "SurfacePair", {"name": "indentation_contact"})
        ET.SubElement(pair, "primary").text = "tissue_top"
        ET.SubElement(pair, "secondary").text = "indenter_surface"
    doms = ET.SubElement(root, "MeshDomains")
    ET.SubElement(doms, "SolidDomain", {"name": "tissue", "mat": card.name})
    if contact:
        sd = ET.SubElement(doms, "ShellDomain", {"name": "indenter_shell", "mat": FEBIO_INDENTER_MATERIAL})
        # FERigidShellDomain parameter; a rigid body's thickness only sets its mass (irrelevant here: static, all dofs prescribed)
        ET.SubElement(sd, "shell_thickness").text = _fmt(0.01 * (spec.radius if spec.indenter == "sphere" else r_cap))
    bnd = ET.SubElement(root, "Boundary")

    def zero(name, nset, dofs):
        bc = ET.SubElement(bnd, "bc", {"name": name, "node_set": nset, "type": "zero displacement"})
        for dof in ("x_dof", "y_dof", "z_dof"):
            ET.SubElement(bc, dof).text = "1" if dof[0] in dofs else "0"

    if contact and spec.base == "bonded":  # the indentation force is read from the base: prescribed 0
        _febio_zero_prescribed(bnd, "fixed_base", "base", "xyz")
    elif contact:
        _febio_zero_prescribed(bnd, "sliding_base", "base", "z")
    elif spec.base == "bonded":
        zero("fixed_base", "base", "xyz")
    else:
        zero("sliding_base", "base", "z")
    if spec.base == "sliding":
        zero("base_anchor", "base_anchor", "xy")
        zero("base_other", "base_other", "y")
    if not contact:
        pre = ET.SubElement(bnd, "bc", {"name": "punch_displacement", "node_set": "punch", "type": "prescribed displacement"})
        ET.SubElement(pre, "dof").text = "z"
        ET.SubElement(pre, "value", {"lc": "1"}).text = _fmt(-spec.depth)
        ET.SubElement(pre, "relative").text = "0"
        if spec.bonded_punch:
            zero("punch_bonded", "punch", "xy")
    else:
        rigid = ET.SubElement(root, "Rigid")
        rigid.append(_xml_comment("rb: the rigid material's name, as in the FEBio 4 documentation (rigid_fixed, rigid_displacement); "
                                  "NOT VERIFIED for every FEBio 4 release: GIBBON's febio_spec 4.0 demos give the material id (2) "
                                  "instead; use 2 if this FEBio rejects the name"))
        fx = ET.SubElement(rigid, "rigid_bc", {"name": "indenter_fixed", "type": "rigid_fixed"})
        ET.SubElement(fx, "rb").text = FEBIO_INDENTER_MATERIAL
        for dof, v in (("Rx_dof", "1"), ("Ry_dof", "1"), ("Rz_dof", "0"), ("Ru_dof", "1"), ("Rv_dof", "1"), ("Rw_dof", "1")):
            ET.SubElement(fx, dof).text = v
        mv = ET.SubElement(rigid, "rigid_bc", {"name": "indenter_depth", "type": "rigid_displacement"})
        ET.SubElement(mv, "rb").text = FEBIO_INDENTER_MATERIAL
        ET.SubElement(mv, "dof").text = "z"
        ET.SubElement(mv, "value", {"lc": "1"}).text = _fmt(-spec.depth)
        ET.SubElement(mv, "relative").text = "0"
        eps = spec.penalty * card.youngs_modulus / s["h"]
        cont = ET.SubElement(root, "Contact")
        cont.append(_xml_comment(
            f"frictionless penalty contact: traction = penalty x penetration, penalty = p E / h = {spec.penalty:g} x "
            f"{card.youngs_modulus:.6g} Pa / {s['h']:.6g} m = {eps:.6g} Pa/m, difftissue's per-node kappa_i = p E sqrt(A_i) "
            "per tributary area A_i (h = sqrt(A) of the top node on the axis); set auto_penalty 1 (penalty then a scale "
            "factor) or laugon 1 (augmented Lagrangian) for FEBio's own choices"))
        c = ET.SubElement(cont, "contact", {"name": "indentation", "type": "sliding-elastic", "surface_pair": "indentation_contact"})
        for tag, val in (("laugon", "0"), ("penalty", _fmt(eps)), ("auto_penalty", "0"), ("two_pass", "0"),
                         ("fric_coeff", "0.0"), ("tension", "0"), ("search_radius", _fmt(max(spec.depth, r_cap)))):
            ET.SubElement(c, tag).text = val
    logs = {"base": ids(s["base"])} if contact else {"punch": ids(s["punch"])}
    _febio_ramp_and_output(root, logs, rigid=(len(mats.findall("material")),) if contact else ())
    return root


#: Increments per top cell size of the cone's depth in the Abaqus / CalculiX deck (the tip moves
#: at most h / this per increment; measured: h / 20 loses the node under the tip, h / 40 does not).
CONE_INCREMENTS_PER_CELL = 50.0
#: Local nodes of the faces S1..S4 of an Abaqus / CalculiX C3D4 (1-based face number = index + 1).
_C3D4_FACES = ((0, 1, 2), (0, 3, 1), (1, 3, 2), (2, 3, 0))


def abaqus_indenter_mesh(spec, height: float, spacing: float):
    """The meshed rigid indenter of the Abaqus / CalculiX sphere and cone specimens (SI units).

    The cap of :func:`febio_indenter_cap` (rings at most ``spacing / 2`` apart, up to 96
    rings; called with ``spacing`` = half the tissue's top cell size, so the facets are at
    most a quarter of a cell) closed into a fan of C3D4 tets towards one apex node on the axis
    inside the indenter (sphere: its centre ``(0, 0, height + R)``; cone: ``(0, 0, height + 2
    r_cap / tan(theta))``, above the cap's top ring). Each tet is ``(a, c, b, apex)`` for a cap
    facet ``(a, b, c)`` whose normal faces the tissue, so its volume is positive and its face
    S1 (local nodes 1-2-3) is the facet: the contact surface is ``INDENTER, S1``.

    Returns ``(points (N, 3), tets (M, 4) 0-based, r_cap)``; the last point is the apex.
    """
    P, T, r_cap = febio_indenter_cap(spec, height, spacing, max_rings=96)
    if spec.indenter == "sphere":
        apex = np.array([0.0, 0.0, height + spec.radius])
    else:
        apex = np.array([0.0, 0.0, height + 2.0 * r_cap / math.tan(spec.half_angle)])
    pts = np.vstack([P, apex])
    tets = np.column_stack([T[:, 0], T[:, 2], T[:, 1], np.full(len(T), len(P))])
    a, b, c, d = (pts[tets[:, k]] for k in range(4))
    vol = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0
    if not np.all(vol > 0):
        raise ExportError(f"the meshed {spec.indenter} indenter has {int(np.sum(vol <= 0))} inverted tets (a bug)")
    return pts, tets, r_cap


def _tet_faces_on(tets, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(element index (F,), face number 1..4 (F,))`` of the C3D4 face of ``tets`` that each
    boundary triangle of ``faces`` (F, 3) is (each boundary face belongs to one tet)."""
    key = {}
    for e, t in enumerate(np.asarray(tets)):
        for k, loc in enumerate(_C3D4_FACES):
            key.setdefault(tuple(sorted(int(t[i]) for i in loc)), []).append((e, k + 1))
    out = []
    for f in np.asarray(faces):
        hit = key.get(tuple(sorted(int(v) for v in f)), [])
        if len(hit) != 1:
            raise ExportError(f"top face {f.tolist()} is not the face of exactly one tet ({len(hit)})")
        out.append(hit[0])
    arr = np.asarray(out, dtype=np.int64).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def abaqus_indentation_model(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> str:
    """Abaqus input of an indentation specimen, in the dialect that CalculiX 2.20 also runs.

    Sphere and cone: a **meshed rigid indenter** (CalculiX has no analytical rigid surface):
    the cap of :func:`abaqus_indenter_mesh` as C3D4 tets (``ELSET=INDENTER``, a dummy linear
    material ``RIGID_INDENTER``; every node of the indenter is prescribed, ``INDENTER, 1, 2``
    zero and ``INDENTER, 3, 3, -depth``, so it only translates, rigidly, and its material
    never enters), ``*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF`` (the facets ``INDENTER, S1``,
    the master), ``*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF`` (the tissue's top faces, the slave),
    ``*SURFACE INTERACTION`` with ``*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR`` and the
    slope ``K = p E / h`` [Pa/m] (difftissue's per-node penalty ``kappa_i = p E sqrt(A_i)``
    per tributary area ``A_i = h^2``, ``h`` of the top node on the axis: CalculiX's spring force
    is ``K A_i`` times the overclosure, ``A_i`` a third of the slave faces at the node), no
    ``*FRICTION`` (frictionless in both codes), ``*CONTACT PAIR, INTERACTION=INDENTER_CONTACT,
    TYPE=NODE TO SURFACE`` with ``TOP_SURF, INDENTER_SURF``. The indentation force is minus the
    summed z reaction of node set ``INDENTER``. Flat punch: ``*BOUNDARY`` ``PUNCH, 3, 3,
    -depth`` (plus ``PUNCH, 1, 2`` for a bonded punch). A bonded base is ``BASE, 1, 3``. The
    summed reaction [N] of ``PUNCH`` or ``INDENTER`` is printed to the ``.dat``
    (:func:`abaqus_reaction_print`). ``NLGEOM=YES`` for the neo-Hookean law only (the linear
    law is difftissue's small-strain ``fem_linear``; the contact is found in the deformed
    configuration either way).

    All decks run in CalculiX 2.20 (tests/test_export_calculix.py). For Abaqus the same deck is
    valid; an Abaqus user who wants a reference node (force control) may replace the indenter's
    ``*BOUNDARY`` lines by ``*RIGID BODY, ELSET=INDENTER, REF NODE=...`` (CalculiX puts the
    rotations on a separate ``ROT NODE``, which Abaqus does not know: not one dialect).
    """
    from .export_indentation import indentation_sets

    _ind_check(spec, "Abaqus")
    card = _indentation_card(card, spec, law, approximate)
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    law = _law(card, law)
    mat = abaqus_material(card, law=law, approximate=approximate)
    mname = abaqus_name(card.name)
    pts = np.asarray(mesh.points, dtype=float)
    tets = np.asarray(mesh.tets)
    H = s["H"]
    lines = ["*HEADING", f"difftissue indentation specimen for material {mname} (SI units: m, N, Pa, kg)"]
    lines += [_abaqus_comment(t) for t in spec.describe()]
    contact = spec.indenter in ("sphere", "cone")
    if contact:
        ipts, itets, r_cap = abaqus_indenter_mesh(spec, H, 0.5 * s["h"])
        n0, e0 = len(pts), len(tets)
        K = spec.penalty * card.youngs_modulus / s["h"]
        lines += [_abaqus_comment(t) for t in (
            f"meshed rigid {spec.indenter}: {len(itets)} facets out to r = {r_cap:.6g} m (the cap's C3D4 fan to one apex node, "
            "face S1 of each tet is a facet); every indenter node is moved by (0, 0, -depth): a rigid translation",
            f"frictionless penalty contact (node to surface): K = p E / h = {spec.penalty:g} x {card.youngs_modulus:.10g} Pa / "
            f"{s['h']:.10g} m = {K:.10g} Pa/m; spring force K A_i x overclosure at the top node with tributary area A_i, "
            "difftissue's kappa_i = p E sqrt(A_i) where A_i = h^2 (uniform top cells)",
            "Abaqus: valid as written; for force control replace the INDENTER boundary lines by *RIGID BODY, ELSET=INDENTER, "
            "REF NODE=<a new node> and load that node")]
    lines.append("*NODE")
    for i, p in enumerate(pts, start=1):
        lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    if contact:
        for i, p in enumerate(ipts, start=n0 + 1):
            lines.append(f"{i}, " + ", ".join(abaqus_number(c) for c in p))
    lines.append("*ELEMENT, TYPE=C3D4, ELSET=TISSUE")
    for i, t in enumerate(tets, start=1):
        lines.append(f"{i}, " + ", ".join(str(int(n) + 1) for n in t))
    if contact:
        lines.append("*ELEMENT, TYPE=C3D4, ELSET=INDENTER")
        for i, t in enumerate(itets, start=e0 + 1):
            lines.append(f"{i}, " + ", ".join(str(int(n) + n0 + 1) for n in t))
    for name, arr in (("BASE", s["base"]), ("TOP", s["top"])):
        lines.append(f"*NSET, NSET={name}")
        lines += _wrap_ids(np.atleast_1d(arr) + 1)
    if spec.base == "sliding":
        lines += ["*NSET, NSET=BASE_ANCHOR", str(s["anchor"] + 1), "*NSET, NSET=BASE_OTHER", str(s["other"] + 1)]
    if spec.indenter == "flat_punch":
        lines.append("*NSET, NSET=PUNCH")
        lines += _wrap_ids(s["punch"] + 1)
    lines += [f"*SOLID SECTION, ELSET=TISSUE, MATERIAL={mname}", ","]
    lines += mat
    if contact:
        el, face = _tet_faces_on(tets, s["top_faces"])
        lines += ["*NSET, NSET=INDENTER, GENERATE", f"{n0 + 1}, {n0 + len(ipts)}, 1"]
        for k in range(1, 5):
            if np.any(face == k):
                lines.append(f"*ELSET, ELSET=TOP_S{k}")
                lines += _wrap_ids(np.sort(el[face == k]) + 1)
        lines.append("*SURFACE, TYPE=ELEMENT, NAME=TOP_SURF")
        lines += [f"TOP_S{k}, S{k}" for k in range(1, 5) if np.any(face == k)]
        lines += ["*SURFACE, TYPE=ELEMENT, NAME=INDENTER_SURF", "INDENTER, S1",
                  _abaqus_comment("the indenter's material: every indenter node is prescribed, so these constants never enter"),
                  "*SOLID SECTION, ELSET=INDENTER, MATERIAL=RIGID_INDENTER", ",",
                  "*MATERIAL, NAME=RIGID_INDENTER", "*ELASTIC", f"{abaqus_number(1e3 * card.youngs_modulus)}, 0.3",
                  "*SURFACE INTERACTION, NAME=INDENTER_CONTACT", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", abaqus_number(K),
                  "*CONTACT PAIR, INTERACTION=INDENTER_CONTACT, TYPE=NODE TO SURFACE", "TOP_SURF, INDENTER_SURF"]
    n_inc = spec.steps
    axis_top = np.flatnonzero(np.hypot(pts[s["top"], 0], pts[s["top"], 1]) <= 1e-9 * H) if spec.indenter == "cone" else []
    if spec.indenter == "cone":
        # the node-to-surface pairing loses the node under the sharp tip when the tip moves more than ~h/40 per increment
        n_inc = max(n_inc, int(math.ceil(CONE_INCREMENTS_PER_CELL * spec.depth / s["h"])))
        lines.append(_abaqus_comment(
            f"cone: {n_inc} increments (the tip moves at most h / {CONE_INCREMENTS_PER_CELL:g} per increment: with larger ones CalculiX's "
            "node-to-surface search loses the node under the sharp tip)" + ("; the top node on the axis is held in x and y (the "
            "axisymmetric solution: under a frictionless sharp tip it is in unstable equilibrium, and a faceted tip pushes it off "
            "the axis)" if len(axis_top) else "")))
        if len(axis_top):
            lines += ["*NSET, NSET=AXIS_TOP", str(int(s["top"][axis_top[0]]) + 1)]
    inc = abaqus_number(1.0 / n_inc)
    lines += [f"*STEP, NLGEOM={'YES' if law == 'neo_hookean' else 'NO'}, INC={max(1000, 4 * n_inc)}", "*STATIC",
              f"{inc}, 1.0, 1e-05, {inc}", "*BOUNDARY"]
    if spec.base == "bonded":
        lines.append("BASE, 1, 3")
    else:
        lines += ["BASE, 3, 3, 0.0", "BASE_ANCHOR, 1, 2, 0.0", "BASE_OTHER, 2, 2, 0.0"]
    if contact:
        lines += ["INDENTER, 1, 2, 0.0", f"INDENTER, 3, 3, {abaqus_number(-spec.depth)}"]
        if len(axis_top):
            lines.append("AXIS_TOP, 1, 2, 0.0")
    else:
        lines.append(f"PUNCH, 3, 3, {abaqus_number(-spec.depth)}")
        if spec.bonded_punch:
            lines.append("PUNCH, 1, 2, 0.0")
    lines += ["*OUTPUT, FIELD", "*NODE OUTPUT", "U, RF", "*ELEMENT OUTPUT", "S, E"]
    lines += abaqus_reaction_print("INDENTER" if contact else "PUNCH")
    lines.append("*END STEP")
    return "\n".join(lines) + "\n"


def sofa_indentation_scene(card: MaterialCard, spec, *, law: str | None = None, approximate: bool = False) -> ET.Element:
    """SOFA scene of an indentation specimen (base bonded only).

    Sphere: ``SphereForceField`` (``Sofa.Component.MechanicalLoad``; force on every point inside
    the sphere ``stiffness * (R - |x - c|)`` along the outward normal, i.e. difftissue's
    per-node penalty force with one ``stiffness`` = ``p E h`` for all nodes), fixed at the
    centre ``(0, 0, H + R)``, with ``damping="0"``; the indentation is the base moved up by
    ``depth`` (``LinearMovementProjectiveConstraint`` on the base, all components, over
    ``steps`` steps): the same relative motion, and a static equilibrium does not depend on
    the frame. Flat punch: base fixed, punch nodes moved by ``(0, 0, -depth)`` (bonded punch
    only: the constraint prescribes all components). Cone: refused (``ConicalForceField``'s
    angle and inside/outside conventions were not verified).
    """
    from .export_indentation import indentation_sets

    _ind_check(spec, "SOFA", cone=False, sliding=False, frictionless_punch=False)
    card = _indentation_card(card, spec, law, approximate)
    mesh = spec.mesh()
    s = indentation_sets(spec, mesh, card)
    law = _law(card, law)
    notes = _approximations(card, "SOFA " + law, approximate=approximate)
    root = ET.Element("Node", {"name": "root", "gravity": "0 0 0", "dt": _fmt(1.0 / spec.steps)})
    for line in _header_lines(card, "SOFA", law) + notes + spec.describe():
        root.append(_xml_comment(line))
    plugins = ["Sofa.Component.SolidMechanics.FEM.Elastic" if law == "linear" else "Sofa.Component.SolidMechanics.FEM.HyperElastic",
               *_SOFA_SPECIMEN_PLUGINS]
    if spec.indenter == "sphere":
        plugins.append("Sofa.Component.MechanicalLoad")
    for p in plugins:
        ET.SubElement(root, "RequiredPlugin", {"name": p})
    node = ET.SubElement(root, "Node", {"name": "tissue"})
    _sofa_specimen_node(node, card, mesh, dt=1.0 / spec.steps)
    node.append(sofa_force_field(card, law=law, approximate=True))
    join = lambda a: " ".join(str(int(i)) for i in np.atleast_1d(a))  # noqa: E731
    if spec.indenter == "sphere":
        k = spec.penalty * card.youngs_modulus * s["h"]
        node.append(_xml_comment(
            f"SphereForceField stiffness = p E h = {spec.penalty:g} * {card.youngs_modulus:.10g} Pa * {s['h']:.10g} m = {k:.10g} N/m "
            "(difftissue's kappa_i of an interior top node; edge nodes differ, docs/export.md); the sphere is fixed and the "
            f"base moves up by the depth {spec.depth:.10g} m"))
        ET.SubElement(node, "SphereForceField", {"name": "indenter", "template": "Vec3d",
                                                 "center": f"0 0 {_fmt(s['H'] + spec.radius)}", "radius": _fmt(spec.radius),
                                                 "stiffness": _fmt(k), "damping": "0"})
        ET.SubElement(node, "LinearMovementProjectiveConstraint", {
            "name": "base_displacement", "template": "Vec3d", "indices": join(s["base"]),
            **_sofa_ramp(spec.depth)})
    else:
        ET.SubElement(node, "FixedProjectiveConstraint", {"name": "fixed_base", "indices": join(s["base"])})
        ET.SubElement(node, "LinearMovementProjectiveConstraint", {
            "name": "punch_displacement", "template": "Vec3d", "indices": join(s["punch"]),
            **_sofa_ramp(-spec.depth)})
    return root


def _xpbd_indenter(card: MaterialCard, spec, mesh) -> dict:
    """The ``indenter`` block of an XPBD indentation specimen (difftissue's contact energy)."""
    from .export_indentation import indentation_sets

    s = indentation_sets(spec, mesh, card)
    H = s["H"]
    out: dict[str, Any] = {"shape": spec.indenter, "axis": [0.0, 0.0], "surface_z": H, "depth": spec.depth,
                           "depth_steps": [spec.depth * (i + 1) / spec.steps for i in range(spec.steps)]}
    if spec.indenter == "flat_punch":
        out.update(radius=spec.radius, bonded=spec.bonded_punch, nodes=s["punch"].tolist(),
                   prescribed="u_z = -depth" + (", u_x = u_y = 0" if spec.bonded_punch else " (x, y free: frictionless)"))
        return out
    if spec.indenter == "sphere":
        out.update(radius=spec.radius, center_at_depth=[0.0, 0.0, H - spec.depth + spec.radius],
                   penetration="p_i = R - |x_i - c|, c = (0, 0, H - depth + R)")
    else:
        out.update(half_angle=spec.half_angle, tip_at_depth=[0.0, 0.0, H - spec.depth],
                   penetration="p_i = (z_i - z_tip) sin(theta) - r_i cos(theta), r_i = distance to the axis")
    out.update(contact_nodes=s["contact_nodes"].tolist(), penalty=s["kappa"].tolist(),
               energy="sum_i penalty_i / 2 max(p_i, 0)^2 (frictionless; penalty_i = p E sqrt(A_i) [N/m], "
                      f"p = {spec.penalty:g}, A_i the node's tributary boundary area)",
               force="indentation force = sum_i penalty_i max(p_i, 0) dp_i/d(depth) (positive compressive)")
    return out
