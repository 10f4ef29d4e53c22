"""fit.json / report.md / material.json record the surface tension from the model's own stress
state and the continuum cubic coefficient of the springs_volume lattice (difftissue.report,
``derived``). Small: a toy fit supplies the FitResult; the Incision is built (cut, models) but
never solved."""

import json
import types

import numpy as np
import pytest

from difftissue.constitutive import continuum_cubic_coefficient, surface_tension
from difftissue.cutting import ScalpelPath, cut_specimen
from difftissue.export import read_card
from difftissue.fit import fit
from difftissue.incision import Incision
from difftissue.materials import Material, MaterialParameterization, surface_tension_from_pre_stretch
from difftissue.mesh import layered_skin
from difftissue.report import derived_quantities, write_fit_outputs

MM = 1e-3
SKIN, FAT = Material(2e5, 0.45, pre_stretch=1.06), Material(5e3, 0.45)


class Stretch:
    """Toy scenario: sigma = E (eps + b eps^3), fits E and b (no mesh)."""

    name = "toy"
    x_label, y_label = "strain [-]", "stress [Pa]"

    def __init__(self):
        self.abscissa = np.linspace(0.02, 0.3, 12)
        self.observed = 2e5 * (self.abscissa + 2.0 * self.abscissa**3)
        self.sigma = np.full(12, 50.0)

    def predict(self, material):
        return material.youngs_modulus * (self.abscissa + material.cubic_coefficient * self.abscissa**3)


@pytest.fixture(scope="module")
def toy_fit():
    return fit([Stretch()], MaterialParameterization(("youngs_modulus", "cubic_coefficient")), Material(1.5e5, 0.45, pre_stretch=1.06), method="gauss_newton")


@pytest.fixture(scope="module")
def incision():
    spec = layered_skin([("dermis", 1.5 * MM, SKIN, 2), ("fat", 2 * MM, FAT, 2)], size=(6 * MM, 6 * MM), resolution=(6, 6))
    cut = cut_specimen(spec, ScalpelPath([(2 * MM, 3 * MM), (4 * MM, 3 * MM)], depth=1.5 * MM))
    return Incision(cut, model="springs_volume", fitted_regions=("dermis",))


def test_incision_layers_and_its_surface_tension(incision):
    """The fitted dermis is one 1.5 mm layer of 1 x 1 x 0.75 mm cells; Incision.surface_tension
    is the model's own (constitutive.surface_tension on that cell), 1.19 x below the linear one."""
    (name, t, cell), = incision.fitted_layers()
    assert name == "dermis" and t == pytest.approx(1.5 * MM, rel=1e-12)
    np.testing.assert_allclose(cell, [MM, MM, 0.75 * MM], rtol=1e-12)
    T = float(incision.surface_tension(SKIN))
    assert T == pytest.approx(float(surface_tension("springs_volume", SKIN, 1.5 * MM, cell_size=cell)), rel=1e-14)
    assert float(incision.surface_tension(SKIN, 1.5 * MM)) == pytest.approx(T, rel=1e-14)
    assert 1.1 < float(surface_tension_from_pre_stretch(SKIN, 1.5 * MM)) / T < 1.35


def test_derived_quantities_of_an_incision_fit(toy_fit, incision):
    """The incision's surface tension (value, linearised value, layer, model) and the lattice's
    b mapping; the standard error of T from the fit covariance of E (T is linear in E)."""
    res = types.SimpleNamespace(material=SKIN.replace(cubic_coefficient=2.0), fields=("youngs_modulus",), covariance=np.array([[1e6]]))
    d = derived_quantities(res, model="springs_volume", scenarios=[incision])
    (st,) = d["surface_tension"]
    T = float(incision.surface_tension(res.material))
    assert st["scenario"] == "incision" and st["model"] == "springs_volume"
    assert st["value"] == pytest.approx(T, rel=1e-12)
    assert st["standard_error"] == pytest.approx(T / 2e5 * 1e3, rel=1e-6)
    assert st["linearised_surface_tension"] == pytest.approx(float(surface_tension_from_pre_stretch(res.material, 1.5 * MM)), rel=1e-12)
    b = d["continuum_uniaxial_cubic_coefficient"]
    assert b["value"] == pytest.approx(float(continuum_cubic_coefficient("springs_volume", res.material)), rel=1e-12)
    assert b["standard_error"] < 1e-12  # b not fitted here and b_c does not depend on E (an exact derivative: round-off)
    # not pre-stretched, not the lattice: nothing to derive
    plain = types.SimpleNamespace(material=Material(2e5, 0.45), fields=(), covariance=None)
    assert derived_quantities(plain, model="fem_neo_hookean", scenarios=()) is None
    # out of the model's range: said, not raised
    bad = types.SimpleNamespace(material=Material(2e5, 0.2, pre_stretch=1.05), fields=(), covariance=None)
    d = derived_quantities(bad, model="springs_volume", scenarios=[incision])
    assert d["surface_tension"][0]["status"] == "not computed" and "poisson_ratio" in d["surface_tension"][0]["reason"]
    assert d["continuum_uniaxial_cubic_coefficient"]["status"] == "not computed"


def test_fit_outputs_carry_the_derived_quantities(tmp_path, toy_fit, incision):
    paths = write_fit_outputs(toy_fit, tmp_path / "out", model="springs_volume", scenarios=[incision])
    doc = json.loads(paths["fit.json"].read_text())
    d = doc["derived"]
    assert d["surface_tension"][0]["value"] == pytest.approx(float(incision.surface_tension(toy_fit.material)), rel=1e-12)
    b = d["continuum_uniaxial_cubic_coefficient"]
    assert b["lattice_cubic_coefficient"] == pytest.approx(2.0, rel=1e-3)
    assert b["strain_range"] == [-0.3, 0.3] and b["standard_error"] > 0  # b was fitted
    report = paths["report.md"].read_text()
    assert "## Derived quantities" in report and "**Surface tension**" in report and "b_c =" in report
    assert "linearised_surface_tension" in report and "never b" in report
    card = read_card(paths["material.json"])
    assert card.provenance["derived"] == d
    assert card.cubic_coefficient == pytest.approx(2.0, rel=1e-3)  # the card's b stays the lattice's, named as such


def test_cubic_coefficient_record_standard_error_is_the_exact_linearisation():
    """The b_c record's standard error (the host Newton's solutions differentiated by the
    implicit function theorem) against the derivative of b_c by jax.grad through the jitted
    uniaxial solve, for a covariance of E and b with correlation."""
    import jax

    from difftissue.constitutive import cubic_coefficient_record

    E, nu, b = 1.58e4, 0.49, -1.64
    f = lambda m: continuum_cubic_coefficient("springs_volume", m)  # noqa: E731
    # the premise of leaving E out: b_c at 7 E is b_c at E (the lattice's energy is linear in E)
    assert float(f(Material(7 * E, nu, b))) == pytest.approx(float(f(Material(E, nu, b))), rel=1e-12, abs=1e-14)
    g = jax.jit(jax.grad(lambda e, bb: f(Material(e, nu, bb)), argnums=(0, 1)))(E, b)
    g = np.array([float(v) for v in g])
    assert abs(g[0]) < 1e-12 and abs(g[1]) > 0.1
    C = np.array([[2.6e3, -2.0], [-2.0, 1.8e-3]])
    rec = cubic_coefficient_record(Material(E, nu, b), fields=("youngs_modulus", "cubic_coefficient"), covariance=C)
    assert rec["standard_error"] == pytest.approx(float(np.sqrt(g @ C @ g)), rel=1e-10)  # central differences of step 1e-6: 7e-8 off
