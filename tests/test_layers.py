"""The package's import layers (issue 18): the import-linter contracts of ``pyproject.toml``
hold, no module outside ``difftissue.fit`` reaches into its private names, and the moved
modules keep their old import paths for one release (with a DeprecationWarning)."""

import ast
import os
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "difftissue"


def test_import_contracts_are_kept():
    """``lint-imports`` on the contracts of pyproject.toml: physics layers, energies importing
    only errors, fit independent of scenarios/export/config/report, data free of physics, no
    cycle inside the fit, data and export packages, the export package's layers (dispatch ->
    targets -> recalibration / budget -> specimens -> card), export below the CLI / config /
    report and the physics below export. Function-level imports count."""
    pytest.importorskip("importlinter", reason="import-linter not installed (pip install '.[test]')")
    code = ("import sys\nfrom importlinter.cli import lint_imports\n"
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH", "")]))}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-3000:]
    assert "0 broken" in out.stdout, out.stdout[-3000:]


def _contracts() -> dict[str, dict]:
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return {c["id"]: c for c in tomllib.load(fh)["tool"]["importlinter"]["contracts"]}


def _top_level_modules() -> set[str]:
    names = {p.stem for p in PACKAGE.glob("*.py") if p.stem not in ("__init__", "__main__", "_version")}
    names |= {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    return {f"difftissue.{n}" for n in names}


def test_the_energies_contract_names_every_other_module():
    """``energies`` may import only ``errors``: its forbidden list must name every other
    top-level module, so that a new module is forbidden too."""
    forbidden = set(_contracts()["energies-pure"]["forbidden_modules"])
    missing = _top_level_modules() - forbidden - {"difftissue.errors", "difftissue.energies"}
    assert not missing, f"add {sorted(missing)} to the energies-pure contract in pyproject.toml"


def _private_fit_imports(path: Path) -> list[str]:
    """``from <difftissue.fit...> import _name`` statements of one module (relative or absolute)."""
    rel = path.relative_to(ROOT).with_suffix("")
    package = list(rel.parts[:-1])  # a module's package (an __init__'s is its own folder)
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = package[: len(package) - node.level + 1]
            module = ".".join(base + ([node.module] if node.module else []))
        else:
            module = node.module or ""
        if module == "difftissue.fit" or module.startswith("difftissue.fit."):
            found += [f"{rel}:{node.lineno} from {module} import {a.name}" for a in node.names if a.name.startswith("_")]
    return found


def test_no_module_outside_fit_imports_its_private_names():
    """batch (now ``difftissue.fit.batch``), simulate, report, config and the CLI use fit's
    public names only: what they share with fit lives under a public name."""
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if (PACKAGE / "fit") in path.parents:
            continue
        bad += _private_fit_imports(path)
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------ moved modules and names
def test_difftissue_batch_is_a_deprecated_shim(monkeypatch):
    from difftissue.fit import BatchFitResult, fit_batch, specimen_mesh

    monkeypatch.delitem(sys.modules, "difftissue.batch", raising=False)
    with pytest.warns(DeprecationWarning, match=r"difftissue\.batch moved to difftissue\.fit\.batch"):
        import difftissue.batch as old
    assert (old.fit_batch, old.BatchFitResult, old.specimen_mesh) == (fit_batch, BatchFitResult, specimen_mesh)


@pytest.mark.parametrize("name", ["write_fit_outputs", "package_versions", "OUTPUT_FILES", "human_unit"])
def test_output_writers_moved_to_report_still_import_from_fit(name):
    import difftissue.fit
    import difftissue.report

    with pytest.warns(DeprecationWarning, match=f"difftissue.fit.{name} moved to difftissue.report.{name}"):
        value = getattr(difftissue.fit, name)
    assert value is getattr(difftissue.report, name)


#: Every public name of difftissue/fit.py before the split (issue 18).
FIT_NAMES = [
    "UNITS", "METHODS", "LOSSES", "CONDITION_LIMIT", "RELATIVE_SE_LIMIT", "CORRELATION_LIMIT", "Scenario", "FitProblem",
    "ScenarioFit", "FitResult", "FitProgress", "parameter_statistics", "identifiability_diagnostics", "PLAUSIBLE", "RMS_LIMIT",
    "AUTOCORRELATION_LIMIT", "RUNS_P_LIMIT", "BOUND_FRACTION", "STRUCTURE_MIN_RMS", "STRUCTURE_MIN_POINTS", "QUALITY_ERRORS",
    "QualityFlag", "FitQuality", "lag1_autocorrelation", "runs_test", "assess_quality", "DISCRETISATION_METHOD",
    "DISCRETISATION_ORDER", "discretisation_estimate", "with_discretisation", "discretisation_line", "effective_modulus",
    "effective_modulus_line", "fit",
]

#: ``__all__`` of difftissue/data.py before the split.
DATA_NAMES = [
    "ForceDepthCurve", "CompressionCurve", "FEMResult", "Table", "ContactPoint", "UNITS", "QUANTITY_DIMENSIONS",
    "PLAUSIBLE_RANGES", "normalize_unit", "unit_factor", "parse_quantity", "read_text", "TextFile", "load_table",
    "load_force_depth", "load_compression", "load_instron_compression", "load_chiaro", "load_fem_result", "load_dataset",
    "find_contact", "shift_to_contact", "check_monotonic", "CONTACT_METHODS",
]


def test_every_public_name_keeps_its_import_path():
    import difftissue.data
    import difftissue.fit

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # these did not move: no warning
        missing = [f"difftissue.fit.{n}" for n in FIT_NAMES if not hasattr(difftissue.fit, n)]
        missing += [f"difftissue.data.{n}" for n in DATA_NAMES if not hasattr(difftissue.data, n)]
    assert not missing, missing
    assert set(DATA_NAMES) <= set(difftissue.data.__all__)
    assert all(hasattr(difftissue.fit, n) for n in difftissue.fit.__all__)


# ------------------------------------------------------------------ the export package (issue 18)
#: Every public name of difftissue/export.py before it became a package.
EXPORT_NAMES = [
    "CARD_VERSION", "MODEL_ENERGIES", "PARAMETER_UNITS", "TARGETS", "MaterialCard", "card_from_fit", "card_from_fit_json",
    "resolve_effective_modulus", "read_card", "write_card", "abaqus_name", "abaqus_number", "abaqus_reaction_print",
    "abaqus_quadratic", "ABAQUS_ELEMENTS", "model_mismatch", "uniaxial_signed_errors", "portable_path", "febio_material",
    "febio_indenter_cap", "febio_prestrain_gradient", "pre_stretch_from_febio_gradient", "pre_stretches_from_febio_gradient", "sofa_force_field",
    "sofa_polynomial_coefficients", "springs_from_sofa_polynomial", "sofa_springs_split", "abaqus_material", "xpbd_parameters",
    "write_febio", "write_sofa", "write_abaqus", "write_xpbd", "write_vtu", "to_skfem", "export", "UNITS", "UNITS_LINE",
    "LAW_MODELS", "UNIAXIAL_STRAINS", "febio_model", "sofa_scene", "ABAQUS_FIELD_WIDTH", "abaqus_model", "FEBIO_INDENTER_MATERIAL",
    "febio_indentation_model", "CONE_INCREMENTS_PER_CELL", "abaqus_indenter_mesh", "abaqus_indentation_model",
    "sofa_indentation_scene",
]

#: The former modules, their public names and where they live now.
MOVED_EXPORT_MODULES = {
    "difftissue.export_fitted": {
        "difftissue.export.fitted": ["SPECIMEN_FORMAT", "FITTED_EXPERIMENTS", "MAX_STRAIN_INCREMENT", "FittedSpecimen", "fitted_specimen",
                                     "compression_protocol", "specimen_file_name", "write_specimen", "read_specimen",
                                     "fitted_specimen_from_card", "specimen_record", "load_steps"],
        "difftissue.export.recalibration": ["specimen_reactions", "recalibrated_card", "recalibrated_from_reactions",
                                            "RECALIBRATION_STATES"],
        "difftissue.export.febio": ["febio_fitted_model"],
        "difftissue.export.abaqus": ["abaqus_fitted_model"],
        "difftissue.export.sofa": ["sofa_fitted_scene"],
        "difftissue.export.xpbd": ["xpbd_fitted_parameters", "xpbd_fitted_budget", "xpbd_fitted_field_check", "FIELD_CHECK_HALVINGS"],
        "difftissue.export.dispatch": ["write_fitted"],
    },
    "difftissue.export_indentation": {
        "difftissue.export.specimens": ["IndentationSpecimen", "indentation_specimen", "indentation_sets", "INDENTERS"],
        "difftissue.export.card": ["scenario_record"],
        "difftissue.export.xpbd": ["run_xpbd_indentation"],
        "difftissue.export.recalibration": ["recalibrated_indentation_card", "indentation_card", "RECALIBRATION_DEPTHS"],
    },
    "difftissue.export_budget": {
        "difftissue.export.budget": ["MAX_BUDGET_ERROR", "BUDGET_STATES", "MIN_SENSITIVITY", "PBD_BUDGETS", "load_fractions",
                                     "card_reference_reactions", "calibrate_factor", "pbd_budget_calibration",
                                     "xpbd_budget_reactions", "xpbd_budget_calibration"],
    },
    "difftissue.pbd": {
        "difftissue.export.pypbd": ["DEFAULT_BUDGET", "pbd_scene", "write_pbd"],
        "difftissue.export.pypbd_runner": ["SCENE_FORMAT", "PYPBD_GRAVITY", "read_pbd_scene", "pbd_simulation_from_scene",
                                           "run_pbd_scene", "PBDRun", "scene_forces", "scene_energy", "pbd_reference_model",
                                           "scaled_scene", "run_pbd_budget", "PBDBudgetRun"],
    },
}


def test_difftissue_export_keeps_every_public_name():
    import difftissue.export

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        missing = [n for n in EXPORT_NAMES if not hasattr(difftissue.export, n)]
    assert not missing, missing
    assert set(difftissue.export.__all__) == set(EXPORT_NAMES)


@pytest.mark.parametrize("old", sorted(MOVED_EXPORT_MODULES))
def test_moved_export_modules_are_deprecated_shims(monkeypatch, old):
    import importlib

    monkeypatch.delitem(sys.modules, old, raising=False)
    with pytest.warns(DeprecationWarning, match=rf"{old.replace('.', chr(92) + '.')} moved"):
        shim = importlib.import_module(old)
    for new, names in MOVED_EXPORT_MODULES[old].items():
        mod = importlib.import_module(new)
        for n in names:
            assert getattr(shim, n) is getattr(mod, n), f"{old}.{n} is not {new}.{n}"
    assert sorted(shim.__all__) == sorted(n for names in MOVED_EXPORT_MODULES[old].values() for n in names)


def test_no_export_module_imports_another_ones_private_names():
    """The export modules share helpers under public names (a private module, ``_common``, may
    hold them): no ``from .x import _name`` inside the package."""
    bad = []
    for path in sorted((PACKAGE / "export").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level:
                bad += [f"{path.name}:{node.lineno} from {'.' * node.level}{node.module or ''} import {a.name}"
                        for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------ the config package (issue 18)
#: Every public name of difftissue/config.py before it became a package, and the private ones
#: the tests and docs use (``_build_experiment``, ``_coarse_block``, ``_cubic_estimate``).
CONFIG_NAMES = [
    "SCENARIOS", "FIELDS", "TISSUE_RANGES", "Experiment", "FitConfig", "tissue_range_check", "SeparatelyCompiled", "load_config",
    "parse_config", "PLAUSIBLE_MODULUS", "PLAUSIBLE_DEPTH_OVER_RADIUS", "SMALL_STRAIN_FRACTION", "CUBIC_START_MAX_SE",
    "PLAUSIBLE_MAX_STRAIN", "PERCENT_SUSPECT_STRAIN", "_build_experiment", "_coarse_block", "_cubic_estimate",
]


def test_difftissue_config_keeps_every_public_name():
    import difftissue.config

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # the package path is the module path: no shim
        missing = [n for n in CONFIG_NAMES if not hasattr(difftissue.config, n)]
    assert not missing, missing
    assert {"FitConfig", "Experiment", "load_config", "parse_config", "SCENARIOS", "FIELDS"} <= set(difftissue.config.__all__)
    assert all(hasattr(difftissue.config, n) for n in difftissue.config.__all__)
    # the CLI and tests patch these where the CLI looks them up
    assert difftissue.config.load_config.__module__ == "difftissue.config.parser"
    assert difftissue.config.FitConfig.__module__ == "difftissue.config.fitconfig"


def test_the_config_layers_contract_places_every_module():
    """The ``config-layers`` contract is exhaustive and names the package's modules."""
    contract = _contracts()["config-layers"]
    named = {m.strip() for layer in contract["layers"] for m in layer.split("|")}
    modules = {p.stem for p in (PACKAGE / "config").glob("*.py") if p.stem != "__init__"}
    assert contract["exhaustive"] and named == modules, (named, modules)


def test_no_config_module_imports_a_function_level_difftissue_module():
    """Imports of difftissue modules sit at the top of the config modules (none inside a
    function, where they could hide a cycle or an upward import from a reader)."""
    bad = []
    for path in sorted((PACKAGE / "config").glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top = set(map(id, tree.body))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level and id(node) not in top:
                bad.append(f"{path.name}:{node.lineno}")
    assert not bad, bad
