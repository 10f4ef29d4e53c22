"""An incision fit with a lattice model at a pre-stretch where the lattice's own finite-strain
response biases the opening gets a named quality warning (``lattice_pre_stretch_bias``).

The plain ``springs_volume`` lattice's converged opening is 4 / 12 / 17 % narrower than the
converged neo-Hookean continuum's at lambda0 = 1.05 / 1.10 / 1.15 (docs/cutting.md): refining
does not remove it and it goes straight into a fitted pre-stretch. No compiled solve here: the
estimate is host arithmetic on the materials, and the check reads only the result's material
and quality."""

from __future__ import annotations

import dataclasses
import warnings

import pytest

from difftissue.config import parse_config
from difftissue.config.fitconfig import LATTICE_BIAS_FLAG, lattice_pre_stretch_check
from difftissue.errors import FitQualityWarning
from difftissue.fit import FitQuality
from difftissue.incision import LATTICE_OPENING_BIAS
from difftissue.materials import Material
from lattice_incision_config import incision_config


@dataclasses.dataclass(frozen=True)
class _Result:
    """The two fields of a FitResult the check reads."""

    material: Material
    quality: FitQuality


def _experiments(model):
    return parse_config(incision_config(model)).experiments


def _check(model, material):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = lattice_pre_stretch_check(_Result(material, FitQuality((), {})), _experiments(model))
    flags = [f for f in out.quality.flags if f.name == "lattice_pre_stretch_bias"]
    emitted = [w for w in caught if issubclass(w.category, FitQualityWarning)]
    assert len(emitted) == len(flags)
    return flags, [str(w.message) for w in emitted]


@pytest.mark.parametrize(("lam0", "bias"), [(1.0, 0.0), (1.05, -0.04), (1.075, -0.08), (1.10, -0.12), (1.15, -0.17)])
def test_the_plain_lattice_bias_is_the_measured_table(lam0, bias):
    (e,) = _experiments("springs_volume")
    info = e.scenario.lattice_opening_bias(Material(2e5, 0.45, pre_stretch=lam0))
    assert info["model"] == "springs_volume" and info["pre_stretch"] == pytest.approx(lam0)
    assert info["relative_bias"] == pytest.approx(bias, abs=1e-12)
    assert info["measured"] == [list(kb) for kb in LATTICE_OPENING_BIAS["springs_volume"]]


def test_continuum_and_matched_lattice_have_no_listed_bias():
    for model in ("springs_volume_matched_lattice", "stable_neo_hookean"):
        (e,) = _experiments(model)
        assert e.scenario.lattice_opening_bias(Material(2e5, 0.45, pre_stretch=1.15)) is None
        flags, _ = _check(model, Material(2e5, 0.45, pre_stretch=1.15))
        assert flags == []


def test_the_fixed_layer_s_pre_stretch_counts_too():
    """The fat layer is not fitted; a pre-stretch given to it is the one farthest from 1."""
    cfg = incision_config("springs_volume")
    cfg["experiment"][0]["specimen"]["layers"][1]["pre_stretch"] = 1.12
    (e,) = parse_config(cfg).experiments
    info = e.scenario.lattice_opening_bias(Material(2e5, 0.45, pre_stretch=1.02))
    assert info["pre_stretch"] == pytest.approx(1.12)
    assert info["relative_bias"] == pytest.approx(-0.12 - 0.4 * 0.05)


@pytest.mark.parametrize(("model", "lam0", "flagged"), [
    ("springs_volume", 1.0, False),
    ("springs_volume", 1.02, False),   # -1.6 %: below the 2 % flag
    ("springs_volume", 1.03, True),    # -2.4 %
    ("springs_volume", 1.10, True),
    ("springs_volume_mesh_lattice", 1.05, False),  # +0.8 %
    ("springs_volume_mesh_lattice", 1.10, True),   # -4.0 %
    ("springs_volume", 1.2, True),     # beyond the measured range
    ("springs_volume", 0.99, False),   # within 0.02 below 1: the linear limit
    ("springs_volume", 0.95, True),    # compressive pre-stretch: unmeasured
    ("springs_volume", 0.9, True),     # and outside the matched lattice's range: not proposed
])
def test_the_check_flags_a_measured_or_unmeasured_bias_and_names_the_remedy(model, lam0, flagged):
    flags, messages = _check(model, Material(2e5, 0.45, pre_stretch=lam0))
    assert bool(flags) == flagged
    if not flagged:
        return
    (flag,) = flags
    assert flag.severity == "warning" and flag.subject == "wound" and flag.numbers["model"] == model
    assert flag.message.startswith(f"wound: pre_stretch = {lam0:.4g} ")
    assert ('use model = "springs_volume_matched_lattice"' in flag.message) == (0.95 <= lam0 <= 1.2)
    assert messages == [f"warning: {flag.message}"]
    if 1.0 <= lam0 <= 1.15:
        assert abs(flag.numbers["relative_bias"]) >= LATTICE_BIAS_FLAG
        assert ("narrower" in flag.message) == (flag.numbers["relative_bias"] < 0)
    else:
        assert flag.numbers["relative_bias"] is None and "unmeasured model bias" in flag.message


def test_an_anisotropic_pre_stretch_is_not_sent_to_the_equibiaxial_matched_lattice():
    flags, _ = _check("springs_volume", Material(2e5, 0.45, pre_stretch=1.0, pre_stretch_y=1.10))
    (flag,) = flags
    assert flag.numbers["pre_stretch"] == pytest.approx(1.10) and flag.numbers["relative_bias"] == pytest.approx(-0.12)
    assert "matched_lattice" not in flag.message and "finite-strain continuum model" in flag.message
