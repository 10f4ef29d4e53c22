"""What a target cannot represent of a card, and the measured error of writing it anyway.

The continuum laws the simulators solve (:data:`LAW_MODELS`: ``linear`` -> ``fem_linear``,
``neo_hookean`` -> ``fem_neo_hookean``), the law a card exports to by default
(:func:`resolve_law`), the model mismatch of lattice-effective values in a continuum law
(:func:`model_mismatch`), the signed stress error of an approximation measured in difftissue
(:func:`uniaxial_signed_errors`) and the notes or refusals every writer states
(:func:`approximation_notes`).
"""

from __future__ import annotations

import math
from typing import Sequence

import jax
import numpy as np

from ..boundary import BoundaryConditions
from ..errors import ExportError
from ..materials import Material
from ..mesh import block
from ..models import LATTICE_MODELS, LATTICE_VARIANTS, MESH_MODELS, make_model
from ..solvers.static import solve_static
from .card import FINITE_STRAIN_MODELS, MaterialCard, model_parts

__all__ = ["LAW_MODELS", "UNIAXIAL_STRAINS", "resolve_law", "lattice_model", "model_mismatch", "uniaxial_signed_errors", "approximation_notes"]


def resolve_law(card: MaterialCard, law: str | None) -> str:
    """The continuum law a card is written with: ``law`` (``"linear"`` / ``"neo_hookean"``), or by
    default ``neo_hookean`` for a card of a finite-strain model (:data:`~difftissue.export.card.FINITE_STRAIN_MODELS`,
    also within a joint fit) and ``linear`` otherwise."""
    if law is None:
        return "neo_hookean" if any(m in FINITE_STRAIN_MODELS for m in model_parts(card.model)) else "linear"
    if law not in ("linear", "neo_hookean"):
        raise ExportError(f"law = {law!r}: expected 'linear' or 'neo_hookean'")
    return law


#: difftissue's model whose energy each exported continuum law is (FEBio, SOFA's tet force fields,
#: Abaqus / CalculiX on tets): the models a card is recalibrated to and its errors measured with.
LAW_MODELS = {"linear": "fem_linear", "neo_hookean": "fem_neo_hookean"}


def lattice_model(card: MaterialCard) -> str | None:
    """The card's lattice model (:data:`~difftissue.models.LATTICE_MODELS`: ``springs_volume`` or
    ``springs_volume_mesh_lattice``, also within a joint fit), whose (E, nu) are lattice-effective
    values, not a continuum's; None when it has none."""
    return next((m for m in model_parts(card.model) if m in LATTICE_MODELS), None)


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
    lattice = lattice_model(card)
    if lattice is None:
        return None
    return (f"model mismatch: the card's E = {card.youngs_modulus:.6g} Pa, nu = {card.poisson_ratio:.6g} are {lattice} "
            f"lattice-effective values (cube lattice of springs with a per-cell volume term), the target solves the continuum "
            f"{law} law ({LAW_MODELS[law]}) on tets, which under inhomogeneous strain (a punch, bonded platens) is tens of "
            f"percent stiffer at the same values")


def _uniaxial_cube_stress(model: str, values: tuple, strains: Sequence[float]) -> np.ndarray:
    """Engineering stress [Pa] of one 1 mm cube of difftissue's ``model`` (``values`` =
    E [Pa], nu, b) under frictionless uniaxial compression to the nominal ``strains``:
    bottom face held in z, top face moved by ``strain * 1 mm`` in z, the x = 0 / y = 0 faces
    held in x / y (symmetry), lateral faces free; solved by difftissue's static solver
    (float64 required). Stress = summed top z reaction / 1 mm^2."""
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
    own = next((m for m in model_parts(card.model) if m in MESH_MODELS), None)
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


def approximation_notes(card: MaterialCard, target: str, *, approximate: bool, cubic_ok: bool = False,
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
    if card.is_pre_stretched and not pre_stretch_ok:
        what = f"pre_stretch = {lam0:g}" + (f", pre_stretch_y = {card.pre_stretch_y:g}" if "pre_stretch_y" in card.parameters else "")
        msg = f"{what} (pre-tension) is not written for {target}"
        variant = lattice_model(card) if lattice_model(card) in LATTICE_VARIANTS else None
        if variant:  # the variant is springs_volume bit for bit without pre-stretch: dropping it drops the variant
            msg += (f" (the card's model {variant} differs from springs_volume only under pre-stretch, so without it the "
                    "written material is springs_volume's)")
        if not approximate:
            raise ExportError(msg + "; pass approximate=True (--approximate) to export the material without pre-tension")
        notes.append(f"APPROXIMATION: {what} dropped; the exported material starts stress-free"
                     + (f" ({variant} without pre-stretch is springs_volume)" if variant else ""))
    return notes
