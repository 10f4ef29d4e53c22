"""One entry point for every target: :func:`export` (block, indentation or fitted specimen, or the
material alone) and :func:`write_fitted` (a fitted specimen), as ``difftissue export`` calls them.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import ExportError
from ._common import write_text, xml_text
from .abaqus import abaqus_element, abaqus_fitted_model, write_abaqus
from .approximations import model_mismatch, resolve_law
from .card import MaterialCard, resolve_effective_modulus
from .febio import febio_fitted_model, write_febio
from .fitted import FittedSpecimen
from .pypbd import write_fitted_pbd, write_pbd
from .recalibration import recalibrated_card
from .sofa import sofa_fitted_scene, write_sofa
from .vtu import write_fitted_vtu, write_vtu
from .xpbd import write_xpbd, xpbd_fitted_parameters

__all__ = ["TARGETS", "export", "write_fitted"]


#: Export targets understood by :func:`export` and ``difftissue export --to``.
TARGETS = ("febio", "sofa", "abaqus", "pbd", "xpbd", "vtu")


def export(card: MaterialCard, to: str, path, *, mesh=None, approximate: bool = False, force: bool = False,
           law: str | None = None, dt: float | None = None, iterations: int | None = None, substeps: int | None = None,
           displacement: float | None = None, constraints: str = "xpbd", indentation=None, fitted=None,
           nu: float | None = None, element: str = "C3D4", field_tolerance: float | None = None, load_set=None,
           extrapolate: bool = False) -> Path:
    """Write ``card`` for target ``to`` (one of :data:`TARGETS`) to ``path``.

    ``to="pbd"``: a pypbd scene (:func:`difftissue.export.pypbd.write_pbd`; ``constraints`` ``"xpbd"`` or
    ``"fem"``, ``dt`` default 1/60 s, ``iterations`` default 10). ``field_tolerance`` (pypbd with a
    specimen only): the target for the displacement field pypbd comes to rest in at the last load
    state, a fraction max |u_pypbd - u_card| / max |u_card| [-] (e.g. 0.03); the budget must then
    meet it as well as the reactions' 2 %, and the export is refused when the pypbd lattice's
    converged limit already exceeds it (``approximate``: written with the miss stated). The
    target and the outcome are in the file's ``budget_calibration``. ``indentation``: an
    :class:`~difftissue.export.specimens.IndentationSpecimen` (instead of ``mesh``).
    ``fitted``: a :class:`~difftissue.export.fitted.FittedSpecimen` (the experiment of a
    fem_field / incision fit, :func:`~difftissue.export.fitted.fitted_specimen_from_card`),
    written by :func:`~difftissue.export.dispatch.write_fitted`. ``element``: the Abaqus element
    (:data:`ABAQUS_ELEMENTS`; other targets refuse anything but the default C3D4).

    A card whose E is an effective modulus (half-space indentation fit, nu fixed at 0) is
    refused unless ``nu`` converts it or ``approximate`` (:func:`resolve_effective_modulus`).

    ``load_set`` (XPBD only): the load-set calibration the caller computed with
    :func:`difftissue.budget.calibrate_for_load_set` at the export's budget and mesh, checked and
    written into the file (:func:`difftissue.export.xpbd.xpbd_parameters`); ``extrapolate``:
    write it although the card's modulus lies outside its stiffness range (with a warning)."""
    if load_set is not None and (to != "xpbd" or fitted is not None):
        raise ExportError(
            f"load_set: a load-set budget calibration is written for the XPBD JSON (to='xpbd', block or indentation "
            f"specimen or no specimen), not for {'a fitted specimen' if fitted is not None and to == 'xpbd' else repr(to)}"
            + ("; a pypbd scene's budget is calibrated by running pypbd itself (per-tet volume constraints, its own "
               "iteration order), and the load-set calibration runs difftissue's XPBD solver on difftissue's models: its "
               "factor would be unmeasured in pypbd, so it is not written there" if to == "pbd" else ""))
    if abaqus_element(element) != "C3D4" and to != "abaqus":
        raise ExportError(f"element = {element!r} is an Abaqus option; {to} is written with linear tets")
    _pbd_only_field_tolerance(to, field_tolerance)
    card = resolve_effective_modulus(card, nu=nu, approximate=approximate)
    if fitted is not None:
        if mesh is not None or indentation is not None or displacement is not None:
            raise ExportError("a fitted specimen carries its own mesh and prescribed displacements: give no mesh, indentation or displacement")
        return write_fitted(card, to, path, fitted, law=law, approximate=approximate, force=force, dt=dt,
                            iterations=iterations, substeps=substeps, element=element, field_tolerance=field_tolerance)
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
        return write_pbd(card, path, mesh=mesh, constraints=constraints, dt=dt, iterations=iterations, substeps=substeps,
                         approximate=approximate, displacement=displacement, force=force, indentation=indentation,
                         field_tolerance=field_tolerance)
    if to == "xpbd":
        if dt is None or iterations is None:
            raise ExportError("an XPBD export needs the time step dt and the iteration count (--dt, --iterations)")
        return write_xpbd(card, path, dt=dt, iterations=iterations, substeps=1 if substeps is None else substeps, mesh=mesh,
                          approximate=approximate,
                          displacement=displacement, force=force, indentation=indentation, load_set=load_set,
                          extrapolate=extrapolate)
    if to == "vtu":
        return write_vtu(card, mesh, path, displacement=displacement, force=force, indentation=indentation)
    raise ExportError(f"unknown export target {to!r}; choose one of {list(TARGETS)}")


def write_fitted(card: MaterialCard, to: str, path, spec: FittedSpecimen, *, law: str | None = None, approximate: bool = False,
                 force: bool = False, dt: float | None = None, iterations: int | None = None, substeps: int | None = None,
                 element: str = "C3D4", field_tolerance: float | None = None) -> Path:
    """Write the complete model of the fitted specimen ``spec`` for target ``to``.

    A lattice card (``springs_volume``) is recalibrated to the target's continuum law on this
    experiment before FEBio, SOFA and Abaqus are written (:func:`recalibrated_card`; the file
    header says so); where that is impossible (incision, no reaction) it is refused unless
    ``approximate``, which writes the card's values with the measured error noted."""
    if to == "pbd":
        return write_fitted_pbd(card, path, spec, approximate=approximate, force=force, dt=dt, iterations=iterations,
                                 substeps=substeps)
    if law == "springs":
        raise ExportError("law='springs' is written for the SOFA compression block only, not for a fitted specimen")
    if to in ("febio", "sofa", "abaqus"):
        lw = resolve_law(card, law)
        if model_mismatch(card, lw) and not (approximate and (spec.experiment == "incision" or spec.reaction is None)):
            card = recalibrated_card(card, spec, lw, approximate=approximate, hyperelastic=to == "abaqus")
    if to == "febio":
        return write_text(path, xml_text(febio_fitted_model(card, spec, law=law, approximate=approximate)), force)
    if to == "sofa":
        return write_text(path, xml_text(sofa_fitted_scene(card, spec, law=law, approximate=approximate)), force)
    if to == "abaqus":
        return write_text(path, abaqus_fitted_model(card, spec, law=law, approximate=approximate, element=element), force)
    if to == "xpbd":
        if dt is None or iterations is None:
            raise ExportError("an XPBD export needs the time step dt and the iteration count (--dt, --iterations)")
        doc = xpbd_fitted_parameters(card, spec, dt=dt, iterations=iterations, substeps=1 if substeps is None else substeps,
                                     approximate=approximate)
        return write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n", force)
    if to == "vtu":
        return write_fitted_vtu(card, spec, path, force=force)
    raise ExportError(f"unknown export target {to!r}; choose one of {list(TARGETS)}")


def _pbd_only_field_tolerance(to: str, field_tolerance) -> None:
    """Refuse ``field_tolerance`` for a target that does not measure its displacement field."""
    if field_tolerance is not None and to != "pbd":
        raise ExportError(f"field_tolerance applies to the pbd target only (a pypbd scene measures its displacement field at its "
                          f"budget); the {to} export does not measure a displacement field against the card's model")
