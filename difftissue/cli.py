"""The ``difftissue`` command line.

Every command is a thin shell over public functions of the package. Errors print one
line ``error: ...`` on stderr and exit with status 1 (2 for usage errors); ``--debug``
shows the traceback instead. ``fit`` (and ``demo``) exit with status 3 when the fit finished
but its answer is unusable (a quality flag of severity "error": a parameter at a bound, an
implausible value, non-finite, not converged); the outputs are written all the same.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path

from ._version import __version__
from .errors import runtime_error_message

__all__ = ["main", "build_parser"]

_UNITS = ("m", "cm", "mm", "um")


class _UsageError(Exception):
    """Bad command-line usage (exit status 2)."""


def _length_factor(unit: str) -> float:
    from .mesh import LENGTH_UNITS

    return LENGTH_UNITS[unit]


def _parse_layer(spec: str, factor: float):
    """``name:thickness[:E[:nu[:cells]]]`` -> layer tuple (thickness in the CLI unit, E in Pa)."""
    from .materials import Material

    parts = spec.split(":")
    if len(parts) < 2 or len(parts) > 5 or not parts[0]:
        raise _UsageError(f"--layer {spec!r}: expected name:thickness[:E_Pa[:nu[:cells]]]")
    try:
        name, thickness = parts[0], float(parts[1]) * factor
        E = float(parts[2]) if len(parts) > 2 else 1.0e5
        nu = float(parts[3]) if len(parts) > 3 else 0.45
        layer = (name, thickness, Material(E, nu))
        if len(parts) > 4:
            layer = layer + (int(parts[4]),)
    except ValueError as e:
        raise _UsageError(f"--layer {spec!r}: {e}") from None
    return layer


# ----------------------------------------------------------------------------- commands
def _cmd_mesh(args) -> int:
    from .mesh import block, layered_skin, write_mesh

    f = _length_factor(args.unit)
    if any(not (v > 0) for v in args.size):
        raise _UsageError(f"--size must be positive lengths in {args.unit}, got {args.size}")
    if args.kind == "block":
        mesh = block(tuple(v * f for v in args.size), tuple(args.resolution))
        fields = {}
    else:
        layers = [_parse_layer(s, f) for s in args.layer] if args.layer else None
        specimen = layered_skin(layers, size=tuple(v * f for v in args.size), resolution=tuple(args.resolution),
                                cell_size=None if args.cell_size is None else args.cell_size * f)
        mesh, fields = specimen.mesh, specimen.cell_fields()
        if Path(args.out).suffix.lower() == ".mesh":
            print("note: Medit .mesh files cannot hold the layers' material fields; writing geometry and regions only")
            fields = {}
    path = write_mesh(args.out, mesh, cell_data=fields, overwrite=args.force)
    print(f"wrote {path}: {mesh.n_nodes} nodes, {mesh.n_tets} tets, regions {list(mesh.region_names)} (coordinates in metres)")
    return 0


def _mesh_summary(mesh) -> dict:
    import numpy as np

    vol = mesh.volumes()
    q = mesh.quality()
    lengths = np.linalg.norm(mesh.points[mesh.edges[:, 0]] - mesh.points[mesh.edges[:, 1]], axis=1)
    lo, hi = mesh.bounds()
    counts = np.bincount(mesh.region_ids, minlength=len(mesh.region_names))
    summary = {
        "nodes": mesh.n_nodes,
        "tets": mesh.n_tets,
        "edges": int(len(mesh.edges)),
        "boundary_faces": int(len(mesh.boundary_faces)),
        "volume_m3": float(vol.sum()),
        "bounds_m": {"lower": lo.tolist(), "upper": hi.tolist()},
        "edge_length_m": {"min": float(lengths.min()), "max": float(lengths.max())},
        "quality_mean_ratio": {"min": float(q.min()), "median": float(np.median(q)), "max": float(q.max())},
        "regions": [
            {"id": i, "name": n, "tets": int(counts[i]), "volume_m3": float(vol[mesh.region_ids == i].sum())}
            for i, n in enumerate(mesh.region_names)
        ],
        "point_fields": sorted(mesh.point_data),
        "cell_fields": sorted(mesh.cell_data),
    }
    if mesh.lattice is not None:
        summary["lattice_springs"] = mesh.lattice.n_springs
    return summary


def _print_summary(title: str, summary: dict, findings, notes) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console(highlight=False)
    console.print(f"[bold]{escape(title)}[/bold]")
    if summary:
        t = Table(show_header=False, box=None, pad_edge=False)
        t.add_row("nodes", str(summary["nodes"]))
        t.add_row("tetrahedra", str(summary["tets"]))
        t.add_row("edges", str(summary["edges"]))
        t.add_row("boundary faces", str(summary["boundary_faces"]))
        if "lattice_springs" in summary:
            t.add_row("lattice springs", str(summary["lattice_springs"]))
        t.add_row("volume", f"{summary['volume_m3']:.6g} m^3")
        lo, hi = summary["bounds_m"]["lower"], summary["bounds_m"]["upper"]
        t.add_row("bounds", escape(f"[{', '.join(f'{v:.4g}' for v in lo)}] .. [{', '.join(f'{v:.4g}' for v in hi)}] m"))
        el = summary["edge_length_m"]
        t.add_row("edge length", f"{el['min']:.4g} .. {el['max']:.4g} m")
        q = summary["quality_mean_ratio"]
        t.add_row("quality (mean ratio)", f"min {q['min']:.4f}  median {q['median']:.4f}  max {q['max']:.4f}")
        if summary["point_fields"]:
            t.add_row("point fields", escape(", ".join(summary["point_fields"])))
        if summary["cell_fields"]:
            t.add_row("cell fields", escape(", ".join(summary["cell_fields"])))
        console.print(t)
        r = Table(title="regions", title_justify="left")
        for col in ("id", "name", "tets", "volume [m^3]"):
            r.add_column(escape(col))
        for reg in summary["regions"]:
            r.add_row(str(reg["id"]), escape(reg["name"]), str(reg["tets"]), f"{reg['volume_m3']:.6g}")
        console.print(r)
    for n in notes:
        console.print(f"note: {n}", markup=False)
    if not findings:
        console.print("validation: no problems found")
    for f in findings:
        console.print(f"{f.severity}: {f.kind.__name__}: {cli_words(f.message, 'info')}", markup=False)


def _parse_specimen(spec: str, unit: str | None):
    """``block:LX,LY,LZ:NX,NY,NZ`` (lengths in --unit) or a tet mesh file (coordinates in
    --unit, which must then be given: a file's unit is not guessed) -> TetMesh."""
    from .mesh import block, read_mesh

    parts = spec.split(":")
    if parts[0] != "block":
        if not Path(spec).is_file():
            raise _UsageError(f"--specimen {spec!r}: expected block:LX,LY,LZ:NX,NY,NZ, indentation, fitted or a mesh file "
                              "(no such file)")
        if unit is None:
            raise _UsageError(f"--specimen {spec}: a mesh file needs --unit, the length unit of its coordinates (m, cm, mm or um)")
        return read_mesh(spec, length_unit=unit)
    factor = _length_factor(unit or "mm")
    if len(parts) != 3:
        raise _UsageError(f"--specimen {spec!r}: expected block:LX,LY,LZ:NX,NY,NZ")
    try:
        size = [float(v) for v in parts[1].split(",")]
        res = [int(v) for v in parts[2].split(",")]
    except ValueError as e:
        raise _UsageError(f"--specimen {spec!r}: {e}") from None
    if len(size) != 3 or len(res) != 3 or any(not (v > 0) for v in size) or any(n < 1 for n in res):
        raise _UsageError(f"--specimen {spec!r}: expected three positive lengths and three positive cell counts")
    return block(tuple(v * factor for v in size), tuple(res))


def _triple(opt: str, text: str, kind):
    try:
        vals = [kind(v) for v in text.split(",")]
    except ValueError:
        raise _UsageError(f"--{opt} {text!r}: expected three comma-separated numbers") from None
    if len(vals) != 3 or any(not (v > 0) for v in vals):
        raise _UsageError(f"--{opt} {text!r}: expected three positive numbers")
    return tuple(vals)


def _indentation_from_args(card, args, f: float):
    """``--specimen indentation`` + --indenter/--radius/--half-angle/--depth/--block/--cells/--base
    (lengths in --unit, the half-angle in degrees); missing values come from the card's scenario record."""
    import math

    from .export.specimens import indentation_specimen

    if args.displacement is not None:
        raise _UsageError("--displacement is the compression block's; an indentation specimen takes --depth")
    return indentation_specimen(
        card, indenter=args.indenter, radius=None if args.radius is None else args.radius * f,
        half_angle=None if args.half_angle is None else math.radians(args.half_angle),
        depth=None if args.depth is None else args.depth * f,
        size=None if args.block is None else tuple(v * f for v in _triple("block", args.block, float)),
        cells=None if args.cells is None else _triple("cells", args.cells, int), base=args.base,
        bonded_punch=True if args.bonded_punch else None, penalty=args.penalty, steps=args.steps, scenario=args.scenario)


_README_MARK = "<!-- difftissue export README: one section per exported file, rewritten by `difftissue export` -->"
_HOW_TO_RUN = {
    "febio": "`febio4 -i {f}` (FEBio 4); the reaction forces [N] are written per node to the logfile `reaction_<set>.txt` (sum the rows) "
             "and in the plot file",
    "sofa": "`runSofa {f}` (or `runSofa -g batch -n STEPS {f}`); positions [m] and forces [N] of every node go to `tissue_state.txt` "
            "(WriteState); run a few steps past t = 1",
    "abaqus": "`abaqus job={stem}` (Abaqus) or `ccx -i {stem}` (CalculiX: C3D4 / C3D10 only, it has no hybrid elements, analytical "
              "surfaces or ENCASTRE); summed reactions [N] are printed to `{stem}.dat`",
    "pbd": "in Python: `from difftissue.export.pypbd_runner import read_pbd_scene, run_pbd_scene; run_pbd_scene(read_pbd_scene('{f}'))` (pypbd)",
    "xpbd": "load the JSON into your XPBD engine: compliances for the stated dt and iteration count (docs/export.md)",
    "vtu": "open `{f}` in ParaView (cell fields: the material per cell)",
}


def _readme_budget(text: str) -> list[str]:
    """README lines about a real-time file's budget (pypbd scene, XPBD JSON): the budget written,
    whether the exporter chose it, the stiffness factor and the signed error per load state
    before and after the recalibration, the displacement field's error (pypbd: a fraction of
    the largest displacement, its converged limit, the target and whether it was met), or the
    check of a reaction-free specimen."""
    import json

    try:
        doc = json.loads(text)
    except ValueError:
        return []
    if not isinstance(doc, dict):
        return []
    st = doc.get("setting") or {}
    budget = (f"dt = {float(st['dt']):.6g} s, substeps = {st.get('substeps', 1)}, iterations = {st['iterations']}"
              if "dt" in st and "iterations" in st else None)
    fmt = lambda a: ", ".join(f"{100 * float(v):+.3g} %" for v in a)  # noqa: E731
    rec, chk = doc.get("budget_calibration"), doc.get("budget_check")
    if isinstance(rec, dict) and rec.get("method") == "load set":
        return _readme_load_set(rec, budget)
    if isinstance(rec, dict):
        how = rec.get("budget") or "as given (--dt, --iterations)"
        lines = [f"- budget: {budget} ({how})"]
        target = rec.get("field_tolerance")
        if rec.get("budgets_tried") and len(rec["budgets_tried"]) > 1:
            lines.append("- budgets tried before it (did not reach "
                         f"{100 * rec.get('tolerance', 0.02):g} % at every load state"
                         + (f" or the field target {100 * float(target):g} %" if target is not None and "field_note" not in rec
                            else "") + "): "
                         + "; ".join(f"dt = {float(b[0]):.6g} s, {b[1]} substep(s), {b[2]} iterations" for b in rec["budgets_tried"][:-1]))
        lines.append(f"- RECALIBRATED for this budget: stiffness x {float(rec['factor']):.6g} (nu kept) against the card's "
                     f"{rec.get('reference_model', 'model')} on the written specimen at load fractions "
                     f"{[round(float(f), 4) for f in rec.get('load_fractions', [])]}: signed reaction error "
                     f"{fmt(rec.get('signed_error_before', []))} with the card's values, {fmt(rec.get('signed_error_after', []))} "
                     + ("after (within tolerance)" if rec.get("within_tolerance") else "after: NOT within tolerance (--approximate)"))
        if rec.get("field_error") is not None:
            conv = rec.get("field_error_converged")
            lines.append(f"- displacement field at the last load state: max |u_pypbd - u_card| / max |u_card| = "
                         f"{100 * float(rec['field_error']):.3g} %"
                         + (f" (converged limit of every budget: {100 * float(conv):.3g} %)" if conv is not None else "")
                         + ("; no field target (--field-tolerance)" if target is None else
                            f"; field target {100 * float(target):g} % " + ("met" if rec.get("field_within_tolerance")
                                                                          else "NOT met (--approximate)")))
        return lines
    if isinstance(chk, dict):
        err = chk.get("relative_error")
        return [f"- budget: {budget} (as given)",
                f"- checked at this budget (no reaction to recalibrate on): {chk.get('observable')} "
                + (f"{100 * float(err):.3g} % of the largest" if err is not None else "did not come to rest")
                + (" (within tolerance)" if chk.get("within_tolerance") else ": NOT within tolerance (--approximate)")]
    if budget is not None:
        return [f"- budget: {budget} (NOT recalibrated: the card's converged-limit values; see the file's notes)"]
    return []


def _readme_load_set(rec: dict, budget) -> list[str]:
    """README lines of an XPBD file calibrated over a load set (``budget_calibration.method ==
    "load set"``): the budget, the effective modulus, the range the card holds over (shapes,
    depths, tissue moduli, cell size) and every load's residual force error."""
    card = rec.get("card") or {}
    v = card.get("validity") or {}
    (d0, d1), (e0, e1) = v.get("depth_range", [float("nan")] * 2), v.get("youngs_modulus_range", [float("nan")] * 2)
    lines = [f"- budget: {budget} (as given (--dt, --iterations, --substeps); standard XPBD, Gauss-Seidel, multipliers reset "
             "every substep)",
             f"- CALIBRATED OVER A LOAD SET (--load-set): E_eff = {float(rec['effective_youngs_modulus']):.6g} Pa "
             f"({float(rec['factor']):.6g} x the card's E), nu = {float(rec['poisson_ratio']):.6g}, against the "
             f"{rec.get('reference_model')} model",
             f"- valid for: indenter shapes {', '.join(v.get('shapes', []))}; depths {float(d0):.4g} ... {float(d1):.4g} m; tissue "
             f"moduli {float(e0):.4g} ... {float(e1):.4g} Pa; cells of {float((v.get('mesh') or {}).get('cell_size', float('nan'))):.4g} m "
             "(this mesh) and this budget only; nothing outside this range was measured",
             "- residual force error per load (budgeted XPBD with the card vs the reference): "
             + "; ".join(f"{ld['name']} {100 * float(ld['error']):+.3g} %" for ld in card.get("loads", []))
             + f" (largest {100 * float(rec['max_residual_error']):.3g} %; smallest d log F / d log E "
             f"{float(v.get('min_sensitivity', float('nan'))):.3g}, saturated below {float(v.get('sensitivity_threshold', 0.5)):g})"]
    if rec.get("extrapolated"):
        lines.append("- EXTRAPOLATED (--extrapolate): the card's E lies outside the calibrated moduli; the end factor is written, "
                     "its error is unmeasured")
    return lines


def _readme_section(path: Path, target: str, card, what: str) -> str:
    """The README section of one exported file: target, units, how to run it, the budget a
    real-time file was written and recalibrated for (pypbd, XPBD), what was recalibrated
    (the file's RECALIBRATED / VERIFIED lines) and what is approximated (APPROXIMATION lines)."""
    from .export import UNITS

    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):  # a binary VTU
        text = ""
    keys = ("APPROXIMATION", "RECALIBRATED", "VERIFIED for this budget", "NOT calibrated", "CALIBRATED OVER A LOAD SET")

    def clean(ln: str) -> str:  # the sentence from its keyword on (JSON: without the key), comment marks stripped
        i = min((ln.find(k) for k in keys if k in ln), default=0)
        return ln[i:].strip().strip("<!->*\"', ").strip()

    approx = sorted({clean(ln) for ln in text.splitlines() if "APPROXIMATION" in ln or "NOT calibrated" in ln})
    recal = sorted({clean(ln) for ln in text.splitlines() if ("RECALIBRATED" in ln or "VERIFIED for this budget" in ln
                                                                 or "CALIBRATED OVER A LOAD SET" in ln)
                    and "APPROXIMATION" not in ln})
    lines = [f"## {path.name}", "", f"- target: {target} ({what}), from a `{card.model}` card `{card.name}`",
             f"- units: {UNITS}", "- run: " + _HOW_TO_RUN[target].format(f=path.name, stem=path.stem)]
    if target in ("pbd", "xpbd"):
        lines += _readme_budget(text)
    lines += ["- recalibrated: " + (" / ".join(recal) if recal else "nothing (the card's values as written)")]
    lines += ["- approximated: " + (" / ".join(approx) if approx else "nothing (the file represents the card exactly)"), ""]
    return "\n".join(lines)


def _write_readme(out: Path, target: str, card, what: str) -> Path:
    """Add / replace the section of ``out`` in ``README.md`` beside it (a README.md that
    difftissue did not write is left alone: ``README-difftissue.md`` instead)."""
    from ._io import atomic_output

    readme = out.parent / "README.md"
    if readme.exists() and not readme.read_text(encoding="utf-8", errors="replace").startswith(_README_MARK):
        readme = out.parent / "README-difftissue.md"
    sections: dict[str, str] = {}
    if readme.exists():
        body = readme.read_text(encoding="utf-8").split("\n## ")[1:]
        sections = {b.split("\n", 1)[0].strip(): "## " + b.rstrip() + "\n" for b in body}
    sections[out.name] = _readme_section(out, target, card, what)
    text = _README_MARK + "\n\n# Exported simulator files\n\n" + "\n".join(sections[k] for k in sorted(sections))
    with atomic_output(readme, overwrite=True) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return readme


def _cmd_export(args) -> int:
    from .export import export, read_card

    _enable_float64()  # measuring an approximation or recalibrating solves in difftissue

    card = read_card(args.card)
    if args.load_set is not None or args.extrapolate:
        if args.load_set is None:
            raise _UsageError("--extrapolate applies to --load-set")
        if args.to != "xpbd":
            raise _UsageError(f"--load-set calibrates the XPBD JSON (--to xpbd), not --to {args.to}")
        if args.specimen == "fitted":
            raise _UsageError("--load-set needs the simulator's mesh as --specimen block:LX,LY,LZ:NX,NY,NZ, a mesh file or indentation, not fitted")
    f = _length_factor(args.unit or "mm")
    indentation = None
    ind_opts = {k: getattr(args, k) for k in ("indenter", "radius", "half_angle", "depth", "block", "cells", "base", "scenario")
                if getattr(args, k) is not None}
    fitted = None
    if args.specimen == "fitted":
        from .export.fitted import fitted_specimen_from_card

        extra = {k: v for k, v in ind_opts.items() if k != "scenario"}
        if extra or args.bonded_punch:
            raise _UsageError(f"--{sorted(extra)[0].replace('_', '-') if extra else 'bonded-punch'} belongs to --specimen indentation")
        if args.displacement is not None:
            raise _UsageError("--displacement is the compression block's; a fitted specimen carries its prescribed displacements")
        fitted = fitted_specimen_from_card(card, args.card, scenario=args.scenario)
        mesh = None
    elif args.specimen == "indentation":
        indentation = _indentation_from_args(card, args, f)
        mesh = None
    else:
        if ind_opts or args.bonded_punch:
            raise _UsageError(f"--{sorted(ind_opts)[0].replace('_', '-') if ind_opts else 'bonded-punch'} belongs to --specimen indentation")
        mesh = _parse_specimen(args.specimen, args.unit) if args.specimen else None
    if args.to == "vtu" and mesh is None and indentation is None and fitted is None:
        raise _UsageError("--to vtu needs --specimen block:LX,LY,LZ:NX,NY,NZ, a mesh file, indentation or fitted")
    if args.to == "xpbd" and (args.dt is None or args.iterations is None):
        raise _UsageError("--to xpbd needs --dt SECONDS and --iterations N")
    load_set = None
    if args.load_set is not None:
        lmesh = mesh if mesh is not None else indentation.mesh() if indentation is not None else None
        if lmesh is None:
            raise _UsageError("--load-set needs the simulator's mesh: --specimen block:LX,LY,LZ:NX,NY,NZ, a mesh file (or indentation); "
                              "the budget is calibrated on it")
        load_set = _load_set_calibration(card, args, lmesh)
    disp = None if args.displacement is None else args.displacement * f
    path = export(card, args.to, args.out, mesh=mesh, approximate=args.approximate, force=args.force, law=args.law,
                  dt=args.dt, iterations=args.iterations, substeps=args.substeps, displacement=disp,
                  constraints=args.constraints, indentation=indentation, fitted=fitted, nu=args.nu, element=args.element,
                  field_tolerance=args.field_tolerance, load_set=load_set, extrapolate=args.extrapolate)
    what = ("complete specimen model" if mesh is not None else
            f"fitted {fitted.experiment} specimen of scenario {fitted.scenario!r}" if fitted is not None else
            f"{indentation.indenter} indentation specimen, depth {indentation.depth:.6g} m" if indentation is not None else "material")
    readme = _write_readme(Path(path), args.to, card, what)
    extra = "" if load_set is None else (f"; calibrated over {len(load_set.loads)} loads (largest residual force error "
                                         f"{100 * load_set.max_error:.3g} %)")
    print(f"wrote {path}: {card.model} card as {args.to} ({what}){extra}; {readme.name} says how to run it")
    return 0


def _load_set_calibration(card, args, mesh):
    """``--load-set FILE``: the loads of the file's ``[budget]`` table on ``mesh``
    (:func:`difftissue.budget.read_load_set`) and their calibration at the export's budget
    (:func:`difftissue.budget.calibrate_for_load_set` of the XPBD file's stable neo-Hookean pair,
    standard XPBD, the card's material; reference ``budget.reference`` or the card's model).
    A saturated budget raises the calibration's :class:`~difftissue.errors.BudgetSaturationError`
    (with the proposed budget)."""
    from .budget import calibrate_for_load_set, read_load_set
    from .errors import ConfigError
    from .export import resolve_effective_modulus
    from .models import MESH_MODELS
    from .solvers.xpbd import XPBDSettings

    material = resolve_effective_modulus(card, nu=args.nu, approximate=args.approximate).material()
    spec = read_load_set(args.load_set, mesh, material)
    E = float(material.youngs_modulus)
    lo, hi = spec.youngs_modulus_range
    if not (lo * (1 - 1e-9) <= E <= hi * (1 + 1e-9)) and not args.extrapolate:
        raise ConfigError(f"{args.load_set}: the card's Young's modulus {E:.6g} Pa lies outside the load set's moduli {lo:.6g} ... "
                          f"{hi:.6g} Pa (budget.youngs_moduli, in Pa): the file is written at the card's modulus; include it in "
                          "the set, or pass --extrapolate to write the end factor with a warning")
    reference = spec.reference or card.model
    if reference not in MESH_MODELS:
        raise ConfigError(f"{args.load_set}: the card's model {card.model!r} is no mesh model to solve the loads' reference with; "
                          f"set budget.reference to one of {', '.join(MESH_MODELS)}")
    settings = XPBDSettings(dt=args.dt, substeps=1 if args.substeps is None else args.substeps, iterations=args.iterations,
                            method="gauss_seidel", damping=float("inf"), warm_start=False)
    print(f"calibrating the XPBD budget over {len(spec.loads)} loads of {args.load_set} (reference {reference}) ...",
          file=sys.stderr, flush=True)
    return calibrate_for_load_set(mesh, "stable_neo_hookean", material, spec.loads, settings, reference=reference, **spec.options)


def _cmd_info(args) -> int:
    from .mesh import inspect_file

    mesh, findings, notes = inspect_file(args.file, length_unit=args.unit, reorient=args.reorient)
    summary = _mesh_summary(mesh) if mesh is not None else None
    if args.json:
        print(json.dumps({"file": str(args.file), "summary": summary, "findings": [f.to_dict() for f in findings], "notes": notes}, indent=2))
    else:
        _print_summary(str(args.file), summary, findings, notes)
    return 1 if any(f.severity == "error" for f in findings) else 0


def _load_config(path):
    """:func:`difftissue.config.load_config`, its data-plausibility and resolution warnings kept for the
    command's own output (``warning:`` lines, fit.json, report.md) instead of Python's format."""
    from .config import load_config
    from .errors import ImplausibleUnitWarning, UnderResolvedContactWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ImplausibleUnitWarning)
        warnings.simplefilter("ignore", UnderResolvedContactWarning)
        return load_config(path)


def _enable_float64() -> None:
    """Fits run in float64 (the covariance and tight tolerances need it); must precede any jax array."""
    import jax

    jax.config.update("jax_enable_x64", True)


def _one_line(text) -> str:
    return " ".join(str(text).split())


_CHECKPOINT = Path("checkpoint") / "fit.npz"


class _quiet_callback_logs:
    """Silence JAX's own logging of exceptions raised inside callbacks (the error is re-raised
    and reported in one line by the CLI)."""

    def __enter__(self):
        import logging

        self._loggers = [logging.getLogger(n) for n in ("jax._src.callback", "jax._src.interpreters.pxla")]
        self._levels = [lg.level for lg in self._loggers]
        for lg in self._loggers:
            lg.setLevel(logging.CRITICAL)
        return self

    def __exit__(self, *exc):
        for lg, lvl in zip(self._loggers, self._levels):
            lg.setLevel(lvl)
        return False


def _interrupted(ckpt) -> KeyboardInterrupt:
    """The interruption of a fit, with how to carry on (``--resume`` when a checkpoint exists);
    a plain KeyboardInterrupt for fits without a checkpoint (``demo``: the command's own hint)."""
    if ckpt is None:
        return KeyboardInterrupt()
    if ckpt.exists():
        return _Interrupted(f"rerun the same command with --resume to continue from {ckpt}")
    return _Interrupted("rerun the same command to start again (no fit step was saved)")


def _is_runtime_error(e: BaseException) -> bool:
    """A JAX / XLA / equinox runtime error (an exception raised inside compiled code)."""
    return type(e).__name__ in ("JaxRuntimeError", "XlaRuntimeError", "EquinoxRuntimeError", "_EquinoxRuntimeError")


def _runtime_message(e: BaseException) -> str:
    """The useful line of a JAX runtime error (the equinox message, not the traceback)."""
    return runtime_error_message(e)


LOCK_NAME = ".difftissue.lock"


class _Interrupted(KeyboardInterrupt):
    """Ctrl-C, with the one line that tells the user how to carry on."""

    def __init__(self, hint: str):
        super().__init__(hint)
        self.hint = hint


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (a permission error means it does)."""
    import os

    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class _OutputLock:
    """``DIR/.difftissue.lock``, created with O_CREAT|O_EXCL and holding ``pid host``, for the
    duration of one command that writes into DIR.

    A second run into the same DIR is refused at once (:class:`~difftissue.errors.OutputLockedError`).
    A lock whose process no longer exists on this host (a run that was killed) is taken over,
    and :attr:`note` says so. The lock is removed on exit, whatever happened.
    """

    def __init__(self, out: Path):
        self.out = Path(out)
        self.path = self.out / LOCK_NAME
        self.note: str | None = None
        self._held = False

    def _create(self) -> bool:
        import os
        import socket

        try:
            fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{os.getpid()} {socket.gethostname()}\n")
        self._held = True
        return True

    def _owner(self) -> tuple[int | None, str]:
        try:
            parts = self.path.read_text().split()
            return int(parts[0]), (parts[1] if len(parts) > 1 else "")
        except (OSError, ValueError, IndexError):
            return None, ""

    def __enter__(self) -> "_OutputLock":
        import socket

        from .errors import OutputError, OutputLockedError

        if self.out.exists() and not self.out.is_dir():
            raise OutputError(f"{self.out} exists and is not a directory")
        self.out.mkdir(parents=True, exist_ok=True)
        if self._create():
            return self
        pid, host = self._owner()
        stale = pid is not None and host in ("", socket.gethostname()) and not _pid_alive(pid)
        if not stale:
            who = f"pid {pid}" + (f" on {host}" if host else "") if pid is not None else "an unreadable lock"
            raise OutputLockedError(f"{self.out} is in use by another difftissue run ({who}, lock file {self.path}); "
                                    f"wait for it to finish or choose another --out (if no such run exists, delete {self.path})",
                                    pid=pid, lock=self.path)
        self.path.unlink(missing_ok=True)
        if not self._create():  # another run took it over first
            raise OutputLockedError(f"{self.out} is in use by another difftissue run (lock file {self.path}); choose another --out", lock=self.path)
        self.note = f"took over the lock {self.path} of an earlier run (pid {pid}) that no longer exists"
        return self

    def __exit__(self, *exc) -> bool:
        if self._held:
            self.path.unlink(missing_ok=True)
            self._held = False
        return False


def _prepare_out(out: Path, *, force: bool, resume: bool) -> Path:
    """Check DIR before fitting: refuse to overwrite outputs (or a checkpoint) without --force/--resume."""
    from .errors import OutputError, OutputExistsError
    from .report import OUTPUT_FILES

    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory")
    ckpt = out / _CHECKPOINT
    if not force and not resume:
        for name in (*OUTPUT_FILES, "config.toml"):
            if (out / name).exists():
                raise OutputExistsError(f"{out / name} exists; refusing to overwrite it (choose another --out, pass --force, or --resume to continue that fit)")
        old_specimens = sorted(out.glob("specimen-*.vtu")) if out.is_dir() else []
        if old_specimens:  # fitted specimen files of an earlier fit (difftissue.export.fitted)
            raise OutputExistsError(f"{old_specimens[0]} exists; refusing to overwrite it (choose another --out, pass --force, or --resume to continue that fit)")
        if ckpt.exists():
            raise OutputExistsError(f"{ckpt} exists (an interrupted fit); pass --resume to continue it or --force to start afresh")
    if force and not resume and ckpt.exists():
        ckpt.unlink()
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    return ckpt


def _run_config(cfg, out: Path, *, force: bool, resume: bool, progress: bool, starts, checkpoint: bool, console, extra_notes=(), phases=None):
    """Fit a loaded config and write DIR/{fit.json, fit.png, loss.png, report.md, config.toml}."""
    from ._io import atomic_output
    from .report import write_fit_outputs

    phases = phases or _Phases(enabled=False)
    ckpt = _prepare_out(out, force=force, resume=resume) if checkpoint else None
    if not checkpoint:
        out.mkdir(parents=True, exist_ok=True)
    overrides = {"progress": progress and phases.tty}
    if phases.enabled and not phases.tty:
        overrides["callback"] = phases.fit_callback(int(cfg.options.get("max_steps", 200)))
    phases.phase("compiling the model and taking the first fit step", live=False)
    if starts is not None:
        overrides["starts"] = starts
    if ckpt is not None:
        overrides.update(checkpoint=ckpt, resume=resume)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught, _quiet_callback_logs():
        warnings.simplefilter("always")
        try:
            result = cfg.run(**overrides)
        except KeyboardInterrupt as e:
            raise _interrupted(ckpt) from e
        except Exception as e:
            if not _is_runtime_error(e):
                raise
            if "KeyboardInterrupt" in str(e):  # Ctrl-C while a model callback was running
                raise _interrupted(ckpt) from e
            from .errors import FitError

            hint = f"; resume with --resume (checkpoint {ckpt})" if ckpt is not None and ckpt.exists() else ""
            raise FitError(f"the fit stopped: a model evaluation failed at trial parameters: {_runtime_message(e)} "
                           f"(narrow fit.bounds or change the initial material; --debug shows the traceback){hint}") from e
    elapsed = time.perf_counter() - t0
    phases.phase("writing fit.json, material.json, plots and report.md")
    from .export.card import scenario_record

    paths = write_fit_outputs(result, out, config=cfg.path if cfg.path is not None else cfg.raw, data_files=cfg.data_files, model=cfg.model_name,
                              force=force or resume, scenario_records=[scenario_record(s) for s in cfg.scenarios],
                              scenarios=cfg.scenarios, data=cfg.data_provenance, data_warnings=cfg.data_warnings,
                              start=getattr(cfg, "start", None))
    if cfg.path is not None:
        with atomic_output(out / "config.toml", overwrite=True) as tmp:
            tmp.write_bytes(Path(cfg.path).read_bytes())
    phases.phase("done", live=False)
    notes = [n for e in cfg.experiments for n in e.notes] + _start_notes(getattr(cfg, "start", None)) + list(extra_notes)
    notes += [f"{w.category.__name__}: {_one_line(w.message)}" for w in caught if w.category.__name__ not in ("IdentifiabilityWarning", "FitQualityWarning", "DiscretisationWarning")]
    for sc in getattr(cfg, "last_scenarios", ()):
        fails = getattr(sc, "failures", None)
        if fails:
            notes.append(f"{sc.name}: {len(fails)} model evaluation(s) failed at trial parameters and were rejected (last: {fails[-1]})")
    _print_fit(result, cfg, out, elapsed, console, notes)
    return result, paths


def _start_notes(start) -> list[str]:
    """One note per field whose start came from the data (``fit.start = "data"``)."""
    return [f"start: {f} = {d['value']:.4g} from the config's material.{f}: no estimate from the data ({d['no_estimate']})" if d.get("no_estimate") else
            f"start: {f} = {d['value']:.4g} from the data ({d['from']}); the config's material.{f} = {d['config_value']:.4g} "
            f"is not the start (fit.start = \"material\" pins it)" for f, d in (start or {}).items()]


def _print_fit(result, cfg, out: Path, elapsed: float, console, notes) -> None:
    import numpy as np
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=escape(f"{cfg.raw.get('title') or (cfg.path.name if cfg.path else 'fit')}"), title_justify="left")
    for col in ("parameter", "value", "standard error", "unit"):
        t.add_column(col, justify="left" if col in ("parameter", "unit") else "right")
    for f in result.fields:
        se = result.standard_errors[f]
        t.add_row(f, f"{result.values[f]:.6g}", f"{se:.3g}", result.units[f])
    console.print(t)
    if getattr(result, "effective_modulus", None) is not None:
        from .fit import effective_modulus_line

        console.print(effective_modulus_line(result.effective_modulus), markup=False, highlight=False)
    if getattr(result, "discretisation", None) is not None and result.discretisation.get("status") != "not applicable":
        from .fit import discretisation_line

        console.print(discretisation_line(result.discretisation), markup=False, highlight=False)
    fixed = {k: v for k, v in result.material.to_dict().items() if k not in result.fields}
    console.print("fixed: " + ", ".join(f"{k} = {v:g}" for k, v in fixed.items()), markup=False, highlight=False)
    state = "converged" if result.converged else "NOT converged"
    rms = ", ".join(f"{s.name} {np.sqrt(np.mean(s.residual ** 2)):.3g}" for s in result.scenarios)
    console.print(f"loss {result.loss:.6g}, {state} after {result.steps} steps ({result.reason}); rms residual/sigma: {rms}; {elapsed:.1f} s", markup=False, highlight=False)
    for w in [*cfg.data_warnings, *result.warnings]:
        console.print(f"warning: {_one_line(w)}", markup=False, highlight=False)
    _print_quality(result.quality, console)
    for n in notes:
        console.print(f"note: {cli_words(n, 'fit')}", markup=False, highlight=False)
    console.print(f"wrote {out}/: fit.json, fit.png, loss.png, report.md" + (", config.toml" if cfg.path else ""), markup=False, highlight=False)


#: Exit status of ``fit`` / ``demo`` when the fit's answer is unusable (quality error flags).
EXIT_UNUSABLE = 3


def _print_quality(quality, console) -> None:
    """``quality: ...`` then one ``error:`` / ``warning:`` line per quality flag."""
    if quality is None:
        return
    console.print(f"quality: {quality.summary()}", markup=False, highlight=False)
    for f in quality.flags:
        console.print(f"  {f.severity}: {_one_line(f.message)}", markup=False, highlight=False)


def _unusable_status(results) -> int:
    """0, or :data:`EXIT_UNUSABLE` (with a line on stderr) when a fit's answer is unusable."""
    bad = [r for r in results if r.quality is not None and not r.quality.usable]
    for r in bad:
        names = ", ".join(f.name + (f" ({f.subject})" if f.subject else "") for f in r.quality.errors)
        print(f"difftissue: error: the fit finished but its answer is unusable ({names}); the outputs are written "
              f"for inspection (report.md, section Quality); exit status {EXIT_UNUSABLE}", file=sys.stderr)
    return EXIT_UNUSABLE if bad else 0


def _progress_default(args) -> bool:
    return sys.stderr.isatty() if args.progress is None else bool(args.progress)


#: Seconds between the plain progress lines of a run whose stderr is not a terminal.
PROGRESS_EVERY = 10.0


class _Phases:
    """What a long run is doing, on stderr: on a terminal a rich status line per phase (the
    fit's own bar shows step k/n and the loss); otherwise one plain line every ``every``
    seconds while a phase lasts (``difftissue: [40 s] fitting: step 12/200, loss 3.2``), so a
    log or CI job shows the run is alive. Nothing is printed for a phase shorter than ``every``
    off a terminal; ``enabled=False`` prints nothing at all."""

    def __init__(self, *, enabled: bool = True, tty: bool | None = None, every: float | None = None):
        import threading

        self.enabled = enabled
        self.tty = sys.stderr.isatty() if tty is None else tty
        self.every = float(PROGRESS_EVERY if every is None else every)
        self.text = "starting"
        self._t0 = time.perf_counter()
        self._stop = threading.Event()
        self._thread = None
        self._status = None

    def __enter__(self) -> "_Phases":
        import threading

        if self.enabled and not self.tty:
            self._thread = threading.Thread(target=self._beat, name="difftissue-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> bool:
        self._stop.set()
        self._end_status()
        return False

    def _beat(self) -> None:
        while not self._stop.wait(self.every):
            print(f"difftissue: [{time.perf_counter() - self._t0:.0f} s] {self.text}", file=sys.stderr, flush=True)

    def _end_status(self) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None

    def phase(self, text: str, *, live: bool = True) -> None:
        """Enter a phase (``loading``, ``compiling``, ``writing``, ...). ``live=False``: another
        display (the fit's bar) shows this phase on a terminal."""
        self.text = text
        if not (self.enabled and self.tty):
            return
        self._end_status()
        if live:
            from rich.console import Console

            self._status = Console(stderr=True).status(text)
            self._status.start()

    def fit_callback(self, total: int):
        """A :func:`difftissue.fit.fit` callback that keeps the phase text at ``fitting: step k/n, loss L``."""
        def cb(info) -> None:
            self.text = f"fitting: step {info.step}/{total}, loss {info.loss:.6g}"
        return cb


def _cmd_fit(args) -> int:
    """Fit a TOML config and write the outputs."""
    from rich.console import Console


    _enable_float64()
    if args.starts is not None and args.starts < 1:
        raise _UsageError(f"--starts must be >= 1, got {args.starts}")
    with _Phases(enabled=args.progress is not False) as phases:
        phases.phase(f"loading {args.config} and its data")
        cfg = _load_config(args.config)
        out = Path(args.out)
        with _OutputLock(out) as lock:
            try:
                result, _ = _run_config(cfg, out, force=args.force, resume=args.resume, progress=_progress_default(args), starts=args.starts,
                                        checkpoint=True, console=Console(highlight=False), extra_notes=[lock.note] if lock.note else (), phases=phases)
            finally:
                phases.phase("done", live=False)
                _remove_if_empty(out / _CHECKPOINT.parent)
    return _unusable_status([result])


def _remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` if it exists and is empty (a fit that stopped before its first checkpoint)."""
    try:
        folder.rmdir()
    except OSError:
        pass


def _parse_overrides(items) -> dict:
    """``--set FIELD=VALUE`` pairs (SI units) -> {field: float}."""
    out = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name:
            raise _UsageError(f"--set {item!r}: expected FIELD=VALUE, e.g. --set youngs_modulus=12e3")
        try:
            out[name] = float(value)
        except ValueError:
            raise _UsageError(f"--set {item!r}: {value!r} is not a number") from None
    return out


def _cmd_simulate(args) -> int:
    """Evaluate a config's experiments at its [material] (or --set values) without fitting."""
    from .simulate import simulate_config, write_simulation_outputs

    _enable_float64()
    overrides = _parse_overrides(args.set)
    with _Phases(enabled=args.progress is not False) as phases:
        phases.phase(f"loading {args.config} and its data")
        cfg = _load_config(args.config)
        out = Path(args.out)
        with _OutputLock(out) as lock:
            try:
                with _quiet_callback_logs():
                    material, sims = simulate_config(cfg, overrides=overrides, on_experiment=lambda i, n, name: phases.phase(
                        f"simulating experiment {i + 1}/{n} ({name}; compiles its model on first use)"))
            except Exception as e:
                if _is_runtime_error(e) and "KeyboardInterrupt" in str(e):  # Ctrl-C inside a model callback
                    raise KeyboardInterrupt from e
                raise
            finally:
                phases.phase("writing", live=False)
            phases.phase("writing simulation.json, simulation.png and the CSV files")
            paths = write_simulation_outputs(material, sims, out, config=cfg.path, force=args.force)
            phases.phase("done", live=False)
    if lock.note:
        print(f"note: {lock.note}")
    for w in cfg.data_warnings:
        print(f"warning: {_one_line(w)}")
    print(f"material: E = {float(material.youngs_modulus):.6g} Pa, nu = {float(material.poisson_ratio):.6g}, "
          f"b = {float(material.cubic_coefficient):.6g}, pre-stretch = {float(material.pre_stretch):.6g}"
          + (f", pre-stretch along y = {float(material.pre_stretch_y):.6g}" if material.pre_stretch_y is not None else ""))
    for s in sims:
        print(f"{s.name} ({s.kind}{', ' + s.model if s.model else ''}): {s.observed.size} points, relative RMS error "
              f"{100 * s.relative_rms:.3g} %, weighted RMS {s.weighted_rms:.3g}, {s.seconds:.1f} s")
    print(f"wrote {out}/: " + ", ".join(sorted(paths)))
    return 0


#: Demo configs shipped in difftissue/configs, with the output subfolder of each.
DEMO_CONFIGS = (("afm_hertz.toml", "afm_hertz"), ("ecoflex_compression.toml", "ecoflex_compression"))


def _cmd_demo(args) -> int:
    """Fit the bundled real data: the Chiaro AFM curve (Hertz) and the Ecoflex compression."""
    from .errors import OutputExistsError

    _enable_float64()
    t0 = time.perf_counter()
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out} exists and is not a directory")
    with _OutputLock(out) as lock:
        if any(p.name != LOCK_NAME for p in out.iterdir()) and not args.force:
            raise OutputExistsError(f"{out} exists and is not empty; choose another --out or pass --force")
        with _Phases() as phases:
            return _demo(args, out, t0, [lock.note] if lock.note else [], phases)


def _demo(args, out: Path, t0: float, notes, phases=None) -> int:
    """The demo's fits into ``out`` (locked by the caller)."""
    import numpy as np
    from rich.console import Console

    console = Console(highlight=False)
    here = Path(__file__).resolve().parent / "configs"
    chosen = DEMO_CONFIGS[:1] if args.quick else DEMO_CONFIGS
    summary = {}
    for name, sub in chosen:
        if phases is not None:
            phases.phase(f"loading {name} and its data")
        cfg = _load_config(here / name)
        result, _ = _run_config(cfg, out / sub, force=True, resume=False, progress=True, starts=None, checkpoint=False, console=console,
                                extra_notes=notes, phases=phases)
        notes = []
        summary[sub] = result
        console.print("")
    afm = summary.get("afm_hertz")
    if afm is not None:
        e_eff = afm.values["youngs_modulus"] / (1.0 - float(afm.material.poisson_ratio) ** 2)
        se = afm.standard_errors["youngs_modulus"]
        console.print(f"AFM (Hertz): E_eff = {e_eff:.1f} ± {se:.1f} Pa (instrument: 156.0 Pa, {100 * (e_eff / 156.0 - 1):+.1f} %); "
                      f"E at nu = 0.5: {0.75 * e_eff:.1f} Pa (instrument: 117.0 Pa)", markup=False)
    comp = summary.get("ecoflex_compression")
    if comp is not None:
        E = comp.values["youngs_modulus"]
        sc = comp.scenarios[0]
        dev = np.abs(sc.predicted - sc.observed).max() / np.abs(sc.observed).max()
        console.print(f"Ecoflex compression (springs_volume): E = {E / 1e3:.2f} ± {comp.standard_errors['youngs_modulus'] / 1e3:.2f} kPa "
                      f"(authors: 16.29 kPa, {100 * (E / 16290.0 - 1):+.1f} %), cubic coefficient b = {comp.values['cubic_coefficient']:.3f}; "
                      f"model within {100 * dev:.2f} % of the peak stress up to {sc.abscissa.max():.0%} strain", markup=False)
    console.print(f"demo finished in {time.perf_counter() - t0:.1f} s; outputs in {out}/ (fit.json, fit.png, loss.png, report.md, config.toml per fit)", markup=False)
    return _unusable_status(summary.values())


# ------------------------------------------------------------------------------ parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="difftissue",
        description="Calibrate soft-tissue material models with differentiable simulation. Units are SI unless --unit says otherwise.",
    )
    p.add_argument("--version", action="version", version=f"difftissue {__version__}")
    p.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser("demo", help="fit the bundled real data (AFM curve with Hertz, Ecoflex compression with springs_volume) and write the reports")
    d.add_argument("--out", default="demo-output", help="output directory (default: demo-output)")
    d.add_argument("--force", action="store_true", help="write into a non-empty --out, overwriting the demo's files")
    d.add_argument("--quick", action="store_true", help="only the AFM Hertz fit (a few seconds)")
    d.set_defaults(func=_cmd_demo)

    f = sub.add_parser("fit", help="fit material parameters to the experiments of a TOML config (see docs/configuration.md)")
    f.add_argument("config", help="the fit config (TOML); relative paths in it are taken from its folder")
    f.add_argument("--out", required=True, help="output directory: fit.json, fit.png, loss.png, report.md, config.toml, checkpoint/")
    f.add_argument("--force", action="store_true", help="overwrite the outputs in --out (and discard its checkpoint)")
    f.add_argument("--resume", action="store_true", help="continue the fit from --out/checkpoint/fit.npz (same config) and replace its outputs")
    f.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="show the phases and fit steps on stderr (default: a status line and progress bar on a terminal, else a line every 10 s)")
    f.add_argument("--starts", type=int, default=None, metavar="N", help="number of starts (overrides fit.starts)")
    f.set_defaults(func=_cmd_fit)

    sim = sub.add_parser("simulate", help="evaluate the experiments of a fit config at its [material] (or --set values) without fitting")
    sim.add_argument("config", help="the fit config (TOML), as for difftissue fit")
    sim.add_argument("--out", required=True, help="output directory: simulation.json, simulation.png, one CSV per experiment")
    sim.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                     help="replace a material field, SI units (youngs_modulus, poisson_ratio, cubic_coefficient, density, pre_stretch, pre_stretch_y); repeatable")
    sim.add_argument("--force", action="store_true", help="overwrite the outputs in --out")
    sim.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                     help="show the phases on stderr (default: a status line on a terminal, else a line every 10 s)")
    sim.set_defaults(func=_cmd_simulate)

    m = sub.add_parser("mesh", help="generate a specimen mesh")
    msub = m.add_subparsers(dest="kind", metavar="KIND", required=True)
    mb = msub.add_parser("block", help="rectangular block of cubes, 6 tets per cube")
    mb.add_argument("--size", type=float, nargs=3, required=True, metavar=("LX", "LY", "LZ"), help="edge lengths in --unit")
    mb.add_argument("--resolution", type=int, nargs=3, required=True, metavar=("NX", "NY", "NZ"), help="cells per axis")
    ms = msub.add_parser("skin", help="layered skin specimen (layers from the surface inwards)")
    ms.add_argument("--size", type=float, nargs=2, default=[20.0, 20.0], metavar=("LX", "LY"), help="lateral size in --unit (default 20 20, i.e. 20 mm with the default unit)")
    ms.add_argument("--resolution", type=int, nargs=2, default=[20, 20], metavar=("NX", "NY"), help="lateral cells (default 20 20)")
    ms.add_argument("--layer", action="append", metavar="NAME:T[:E[:NU[:CELLS]]]",
                    help="a layer, outermost first: thickness T in --unit, E in Pa; repeat per layer (default: epidermis/dermis/hypodermis)")
    ms.add_argument("--cell-size", type=float, default=None, help="target cell height in --unit (default: lateral cell size)")
    for sp in (mb, ms):
        sp.add_argument("--unit", choices=_UNITS, default="mm", help="length unit of --size (default mm); files are written in metres")
        sp.add_argument("--out", required=True, help="output file: .vtu, .msh, .xdmf or .mesh")
        sp.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    m.set_defaults(func=_cmd_mesh)

    i = sub.add_parser("info", help="summarise and validate a mesh file (any format meshio reads)")
    i.add_argument("file")
    i.add_argument("--unit", choices=_UNITS, default="m", help="length unit of the file's coordinates (default m)")
    i.add_argument("--reorient", action="store_true", help="accept negatively ordered tets (renumbered) instead of reporting them as inverted")
    i.add_argument("--json", action="store_true", help="print JSON instead of tables")
    i.set_defaults(func=_cmd_info)

    x = sub.add_parser("export", help="export a material card (material.json or fit.json) to FEBio, SOFA, Abaqus, pypbd, XPBD or VTU (see docs/export.md)")
    x.add_argument("card", help="material card (material.json written by fit) or a fit.json with a model")
    x.add_argument("--to", required=True, choices=("febio", "sofa", "abaqus", "pbd", "xpbd", "vtu"), help="target format")
    x.add_argument("--out", required=True, help="output file (.feb, .scn, .inp, .json, .vtu)")
    x.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    x.add_argument("--approximate", action="store_true",
                   help="drop what the target cannot represent (cubic stiffening, pre-stretch) and record the approximation in the file")
    x.add_argument("--nu", type=float, default=None, metavar="NU",
                   help="for a card holding an effective modulus E* = E/(1-nu^2) (a Hertz/Sneddon fit with nu fixed): the tissue's "
                        "Poisson ratio; exports E = E* (1 - nu^2) and this nu (without it a card fitted at nu = 0 is refused)")
    x.add_argument("--law", choices=("linear", "neo_hookean", "springs"), default=None,
                   help="constitutive law for febio/sofa/abaqus (default: neo_hookean for springs_volume and its lattice variants/fem_neo_hookean/stable_neo_hookean cards, linear otherwise); springs: SOFA only, PolynomialSpringsForceField + corotational FEM (needs --specimen)")
    x.add_argument("--specimen", default=None, metavar="block:LX,LY,LZ:NX,NY,NZ|FILE|indentation|fitted",
                   help="write a complete specimen model: a compression block (fixed base, prescribed top displacement), "
                        "a tet mesh FILE (VTU, XDMF, Gmsh, Medit, ...; coordinates in --unit, required then) held at its "
                        "flat base (smallest z) and loaded at its flat top (largest z) like the block, "
                        "'indentation' (the fitted indentation experiment from the card's scenario record, completed by the "
                        "options below), or 'fitted' (the fem_field / compression / incision experiment from the specimen file the fit wrote "
                        "beside the card); required for vtu")
    x.add_argument("--indenter", choices=("sphere", "cone", "flat_punch"), default=None, help="indentation: indenter (default: the card's record)")
    x.add_argument("--radius", type=float, default=None, help="indentation: sphere / punch radius in --unit (default: the card's record)")
    x.add_argument("--half-angle", type=float, default=None, help="indentation: cone half-angle in degrees (default: the card's record)")
    x.add_argument("--depth", type=float, default=None, help="indentation: final depth in --unit (default: the record's largest depth)")
    x.add_argument("--block", default=None, metavar="LX,LY,H", help="indentation: block size in --unit (default: from the record, see docs/export.md)")
    x.add_argument("--cells", default=None, metavar="NX,NY,NZ", help="indentation: uniform cells of the block (default: graded cells resolving the contact, see docs/export.md)")
    x.add_argument("--base", choices=("bonded", "sliding"), default=None, help="indentation: base condition (default: the record's, else bonded)")
    x.add_argument("--bonded-punch", action="store_true", help="indentation: flat punch face bonded (x, y held) instead of frictionless (default: the record's, else frictionless)")
    x.add_argument("--penalty", type=float, default=None,
                   help="indentation: difftissue's contact penalty factor (default: the card's record, else 100)")
    x.add_argument("--steps", type=int, default=10, help="indentation: load increments (default 10)")
    x.add_argument("--scenario", default=None, help="indentation / fitted: the card's scenario record to use (default: the first indentation record; fitted: the only specimen)")
    x.add_argument("--displacement", type=float, default=None, help="top displacement along z in --unit (default: -10%% of the height)")
    x.add_argument("--unit", choices=_UNITS, default=None, help="length unit of --specimen (a mesh file's coordinates too: required "
                   "then) and of --displacement and the indentation options (default mm); files are written in metres")
    x.add_argument("--dt", type=float, default=None, help="time step [s] (xpbd: required; pbd: default 1/60)")
    x.add_argument("--iterations", type=int, default=None, help="iterations per substep (xpbd: required, recorded with the compliances; pbd: default 10)")
    x.add_argument("--substeps", type=int, default=None, help="XPBD substeps per time step (default 1; pbd: chosen with dt and "
                   "iterations when none of the three is given)")
    x.add_argument("--field-tolerance", type=float, default=None, metavar="FRACTION",
                   help="pbd with a specimen only: target for the displacement field pypbd comes to rest in at the last load state, "
                        "as a fraction max|u_pypbd - u_card| / max|u_card| (dimensionless, e.g. 0.03 for 3 %%); the budget must meet "
                        "it and the reactions' 2 %% (searched unless --dt, --substeps or --iterations pin it); refused when the "
                        "pypbd lattice's converged limit exceeds it (--approximate: written with the miss stated). Default: no "
                        "field target (the field error is measured and stated)")
    x.add_argument("--load-set", default=None, metavar="FILE",
                   help="xpbd with --specimen only: a TOML file with a [budget] table of the loads the simulator meets "
                        "([[budget.loads]] shape flat_punch|platen|sphere, depth, radius; youngs_moduli in Pa; lengths in m unless "
                        "length_unit): the XPBD budget is calibrated over them on the specimen's mesh and the file states the range "
                        "it holds over (see docs/export.md)")
    x.add_argument("--extrapolate", action="store_true",
                   help="with --load-set: write the card although its Young's modulus lies outside the load set's moduli (the end "
                        "factor, with a warning) instead of refusing")
    x.add_argument("--constraints", choices=("xpbd", "fem"), default="xpbd",
                   help="pbd only: XPBD distance + volume constraints (default) or pypbd's PBD FEMTetConstraint (needs --approximate)")
    x.add_argument("--element", choices=("C3D4", "C3D4H", "C3D10", "C3D10H"), default="C3D4",
                   help="abaqus only: solid element (default C3D4; C3D10/C3D10H add midside nodes; H = hybrid, for near-incompressible "
                        "hyperelasticity; CalculiX has no hybrid elements)")
    x.set_defaults(func=_cmd_export)
    return p


#: OpenBLAS threads of a command-line run unless ``OPENBLAS_NUM_THREADS`` is set: the dense
#: Cholesky of small static solves runs in SciPy's OpenBLAS (jaxlib calls its LAPACK), whose
#: busy-waiting worker threads cost 2-100x the CPU of one thread on matrices up to 3,000 rows
#: when the cores are busy (docs/performance.md, "Small models on a CPU"). Larger systems use
#: the multigrid solver in XLA, which does not use OpenBLAS.
OPENBLAS_THREADS = "1"


def main(argv: list[str] | None = None) -> int:
    # Before anything loads NumPy: OpenBLAS reads it once, when it is loaded. The command line
    # is the one place that sets it (the library does not touch the environment).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", OPENBLAS_THREADS)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from .errors import DifftissueError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            return int(args.func(args))
    except _UsageError as e:
        if args.debug:
            raise
        print(f"difftissue: error: {cli_words(str(e), args.command)}", file=sys.stderr)
        return 2
    except (DifftissueError, OSError) as e:
        if args.debug:
            raise
        print(f"difftissue: error: {cli_words(str(e), args.command)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:
        if args.debug:
            raise
        print(f"difftissue: interrupted; {_interrupt_hint(e, args)}", file=sys.stderr)
        return 130


def _interrupt_hint(e: KeyboardInterrupt, args) -> str:
    """How to carry on after Ctrl-C: the fit's own hint (``--resume``), else rerun the command
    (with ``--force`` where the interrupted run may have left outputs in --out)."""
    if isinstance(e, _Interrupted):
        return e.hint
    out = getattr(args, "out", None)
    if args.command in ("fit", "simulate", "demo") and out is not None:
        return f"rerun the same command (add --force if {out} holds files of this run)"
    return "rerun the same command"


#: Library phrases (Python keyword arguments) and what a command-line user types instead.
_CLI_WORDS = (
    ("force=True / --force", "--force"),
    ("overwrite/--force", "--force"),
    ("pass resume=True", "pass --resume"),
    ("approximate=True (--approximate)", "--approximate"),
    ("nu=0.45 / --nu 0.45", "--nu 0.45"),
    ("bonded_punch=True (--bonded-punch)", "--bonded-punch"),
    ("field_tolerance", "--field-tolerance"),
    ("pass extrapolate=True", "pass --extrapolate"),
)


def cli_words(text: str, command: str | None = None) -> str:
    """``text`` (a library message) with keyword arguments replaced by the CLI's words:
    ``--force``, ``--resume``, ``--approximate``; ``reorient=True`` becomes ``--reorient``
    for ``info`` and the config key ``reorient = true`` for the commands that read a config."""
    for api, cli in _CLI_WORDS:
        text = text.replace(api, cli)
    reorient = "--reorient" if command == "info" else "reorient = true (in the mesh's specimen or data table of the config)"
    text = text.replace("reorient=True (CLI: --reorient)", reorient)
    # data.py: "pass plausible={'depth': (lo, hi)}" -> the config's data-table key
    return re.sub(r"pass plausible=\{'(\w+)': \(lo, hi\)\}", r"set plausible = { \1 = [lo, hi] } (SI) in the experiment's data table", text)
