"""The indenter's contact offset as a fitted parameter (``fit(..., scenario_parameters=...)``):
joint recovery with E from exact closed-form and simulated curves, the bias of a fit without
it, its Jacobian column, multi-start, checkpoint/resume, fit_batch and the refusals."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

from difftissue import Material
from difftissue.analytic import cone_force, flat_punch_force, hertz_force
from difftissue.errors import FitError
from difftissue.fit import FitProblem, fit, fit_batch
from difftissue.materials import Linear, MaterialParameterization
from difftissue.scenarios import AnalyticIndentation, AxisymmetricIndentation, Compression, contact_offset_parameter

jax.config.update("jax_enable_x64", True)

E_TRUE, NU = 5e3, 0.45
RADIUS = 1e-3
OFFSET = 2e-5  # the contact point picked 20 um too late
DEPTHS = np.linspace(0.0, 3e-4, 31)
P_E = MaterialParameterization(("youngs_modulus",))
START = Material(2e3, NU)
ASK = {"indent": ("contact_offset",)}
FIELD = "indent.contact_offset"


def hertz_curve(offset=OFFSET, E=E_TRUE, name="indent"):
    forces = np.asarray(hertz_force(DEPTHS + offset, E, NU, RADIUS))
    return AnalyticIndentation(DEPTHS, forces, indenter="sphere", radius=RADIUS, name=name)


@pytest.mark.parametrize("indenter", ["sphere", "cone", "flat_punch"])
def test_joint_fit_recovers_modulus_and_offset_and_a_fit_without_it_is_biased(indenter):
    if indenter == "sphere":
        sc = hertz_curve()
    else:
        law, size = (cone_force, 1.2) if indenter == "cone" else (flat_punch_force, RADIUS)
        forces = np.asarray(law(DEPTHS + OFFSET, E_TRUE, NU, size))
        sc = AnalyticIndentation(DEPTHS, forces, indenter=indenter, half_angle=size if indenter == "cone" else None,
                                 radius=size if indenter == "flat_punch" else None, name="indent")
    res = fit(sc, P_E, START, scenario_parameters=ASK)
    assert res.converged
    assert res.fields == ("youngs_modulus", FIELD)
    assert res.values["youngs_modulus"] == pytest.approx(E_TRUE, rel=1e-6)
    assert abs(res.values[FIELD] - OFFSET) < 1e-9
    assert res.units == {"youngs_modulus": "Pa", FIELD: "m"}
    assert set(res.standard_errors) == set(res.fields) and all(np.isfinite(v) for v in res.standard_errors.values())
    assert res.covariance.shape == res.correlation.shape == (2, 2)
    # a later contact point and a stiffer material both raise the force: E and the offset are
    # negatively correlated, strongly but not degenerately on a curve from the contact point
    rho = res.correlation[0, 1]
    assert -0.999 < rho < -0.5 and res.correlation[1, 0] == pytest.approx(rho)
    assert isinstance(res.material, Material) and float(res.material.youngs_modulus) == pytest.approx(E_TRUE, rel=1e-6)
    assert res.quality.usable and not res.quality.flags
    # the same data without the offset: E absorbs it (sphere +13 %, flat punch +9.8 %)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the quality gates see the systematic residuals
        plain = fit(sc, P_E, START)
    assert plain.fields == ("youngs_modulus",)
    assert plain.values["youngs_modulus"] / E_TRUE - 1 > 0.05


def test_offset_jacobian_column_matches_central_differences():
    sc = hertz_curve()
    problem = FitProblem(sc, P_E, START, scenario_parameters=ASK)
    assert problem.fields == ("youngs_modulus", FIELD) and problem.n_parameters == 2
    v = np.array([4e3, 1.3e-5])
    _, J, _ = problem.evaluate_values(v)
    J = np.asarray(J)
    for k, h in ((0, 1e-2), (1, 1e-10)):
        e = np.zeros(2)
        e[k] = h
        fd = (np.asarray(problem.residuals_of_values(v + e)) - np.asarray(problem.residuals_of_values(v - e))) / (2 * h)
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-6, atol=1e-9 * np.max(np.abs(fd)))
    # the unconstrained vector: E through its Log, the offset through Linear(1 % of the largest depth)
    u = problem.parameterization.pack(Material(4e3, NU))
    assert u.shape == (2,) and u[1] == 0.0
    vals = problem.values(np.array([u[0], 1.3]))
    assert float(vals[FIELD]) == pytest.approx(1.3 * 0.01 * DEPTHS.max(), rel=1e-12)
    np.testing.assert_allclose(problem.residuals(np.array([u[0], 1.3e-5 / (0.01 * DEPTHS.max())])),
                               problem.residuals_of_values(v), rtol=1e-10, atol=1e-12)


def test_negative_offset_lifts_the_indenter_out_of_contact():
    """depth + offset < 0: no contact, force 0 (the closed forms hold no adhesion), with a
    finite derivative; a positive offset is the curve at depth + offset."""
    sc = hertz_curve()
    m = Material(E_TRUE, NU)
    f = np.asarray(sc.predict(m, -5e-5))
    assert np.all(f[DEPTHS < 5e-5] == 0) and np.all(f[DEPTHS > 5e-5] > 0)
    np.testing.assert_allclose(f[DEPTHS > 5e-5], np.asarray(hertz_force(DEPTHS[DEPTHS > 5e-5] - 5e-5, E_TRUE, NU, RADIUS)), rtol=1e-12)
    g = np.asarray(jax.jacfwd(lambda c: sc.predict(m, c))(-5e-5))
    assert np.all(np.isfinite(g)) and np.all(g[DEPTHS < 5e-5] == 0)
    np.testing.assert_allclose(sc.predict(m, 0.0), sc.predict(m), rtol=0)


def test_multistart_and_checkpoint_resume_carry_the_offset(tmp_path):
    sc = hertz_curve()
    full = fit(sc, P_E, START, scenario_parameters=ASK, starts=3)
    assert full.start_values.shape == (3, 2)
    assert abs(full.values[FIELD] - OFFSET) < 1e-9
    # an explicit start value of the offset
    res = fit(sc, P_E, START, scenario_parameters={"indent": {"contact_offset": 1.5e-5}}, starts=[START, Material(8e3, NU)])
    assert abs(res.values[FIELD] - OFFSET) < 1e-9
    # interrupted after 3 steps, resumed: the same answer as the uninterrupted fit
    ckpt = tmp_path / "ckpt.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # not converged after 3 steps
        fit(sc, P_E, START, scenario_parameters=ASK, max_steps=3, checkpoint=ckpt)
    resumed = fit(sc, P_E, START, scenario_parameters=ASK, checkpoint=ckpt, resume=True)
    once = fit(sc, P_E, START, scenario_parameters=ASK)
    assert resumed.resumed_from == 3
    assert resumed.values[FIELD] == pytest.approx(once.values[FIELD], rel=1e-10)
    assert resumed.values["youngs_modulus"] == pytest.approx(once.values["youngs_modulus"], rel=1e-10)
    # a checkpoint of the fit WITHOUT the offset is another problem
    from difftissue.errors import CheckpointMismatchError

    other = tmp_path / "plain.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # not converged
        fit(sc, P_E, START, max_steps=2, checkpoint=other)
    with pytest.raises(CheckpointMismatchError):
        fit(sc, P_E, START, scenario_parameters=ASK, checkpoint=other, resume=True)


def test_fit_batch_fits_each_specimens_offset():
    specimens = [hertz_curve(1e-5), hertz_curve(3e-5, E=7e3)]
    out = fit_batch(specimens, P_E, START, scenario_parameters=ASK)
    assert out.fields == ("youngs_modulus", FIELD)
    np.testing.assert_allclose(out.values[:, 0], [E_TRUE, 7e3], rtol=1e-6)
    np.testing.assert_allclose(out.values[:, 1], [1e-5, 3e-5], rtol=0, atol=1e-9)


def test_unknown_scenario_parameter_or_scenario_is_refused():
    sc = hertz_curve()
    with pytest.raises(FitError, match="no fittable parameter 'depth_scale'"):
        fit(sc, P_E, START, scenario_parameters={"indent": ("depth_scale",)})
    with pytest.raises(FitError, match="names scenario 'nope'"):
        fit(sc, P_E, START, scenario_parameters={"nope": ("contact_offset",)})
    with pytest.raises(FitError, match="must map scenario names"):
        fit(sc, P_E, START, scenario_parameters=("contact_offset",))
    with pytest.raises(FitError, match="finite number"):
        fit(sc, P_E, START, scenario_parameters={"indent": {"contact_offset": float("nan")}})
    comp = Compression.__new__(Compression)  # a scenario type that declares no fittable parameters
    object.__setattr__(comp, "name", "comp")
    from difftissue.fit.problem import scenario_parameterization

    with pytest.raises(FitError, match="Compression declares no fittable parameters"):
        scenario_parameterization((comp,), P_E, {"comp": ("contact_offset",)})


def test_contact_offset_scale_follows_the_depths():
    spec = contact_offset_parameter(DEPTHS)["contact_offset"]
    assert spec["unit"] == "m" and spec["start"] == 0.0
    assert isinstance(spec["transform"], Linear) and spec["transform"].scale == pytest.approx(3e-6)
    assert contact_offset_parameter(np.zeros(3))["contact_offset"]["scale"] == 1e-6


def test_simulated_axisymmetric_indentation_recovers_modulus_and_offset():
    """A small axisymmetric mesh (3 cells per contact radius): data simulated at depth + 10 um;
    the joint fit recovers both to the solver's precision, the fit without it is biased."""
    depths = np.linspace(2e-5, 1e-4, 5)
    truth = AxisymmetricIndentation(depths, indenter="sphere", radius=RADIUS, cells_per_contact_radius=3, name="indent")
    forces = np.asarray(truth.predict(Material(E_TRUE, NU), 1e-5))
    sc = AxisymmetricIndentation(depths, forces, indenter="sphere", radius=RADIUS, cells_per_contact_radius=3, name="indent")
    res = fit(sc, P_E, START, scenario_parameters=ASK)
    assert res.converged
    assert res.values["youngs_modulus"] == pytest.approx(E_TRUE, rel=1e-6)
    assert abs(res.values[FIELD] - 1e-5) < 1e-9
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = fit(sc, P_E, START)
    assert plain.values["youngs_modulus"] / E_TRUE - 1 > 0.1


def test_outputs_show_the_offset_and_the_material_card_does_not(tmp_path):
    import json

    from difftissue.report import write_fit_outputs

    res = fit(hertz_curve(), P_E, START, scenario_parameters=ASK)
    write_fit_outputs(res, tmp_path / "out")
    rec = json.loads((tmp_path / "out" / "fit.json").read_text())["parameters"][FIELD]
    assert rec["unit"] == "m" and abs(rec["value"] - OFFSET) < 1e-9 and np.isfinite(rec["standard_error"])
    assert "contact_offset" not in (tmp_path / "out" / "material.json").read_text()
    assert f"| {FIELD} |" in (tmp_path / "out" / "report.md").read_text()


@pytest.mark.parametrize("geometry", ["axisymmetric", "3d", "3d_condensed"])
def test_a_simulated_depth_lifted_above_the_surface_has_zero_force_and_finite_derivatives(geometry):
    """depth + offset <= 0 in a simulated indentation: force 0 there (no contact), the other
    depths the unshifted scenario's forces at depth + offset, and finite forward- and
    reverse-mode derivatives in the offset (0 at the lifted depth). Before, its solve at or
    above the surface did not converge, so a fit could not reach a negative offset past the
    first depth. One compiled program for the forces and both derivatives."""
    from difftissue.scenarios import Indentation, indentation_block

    depths = np.array([2e-5, 5e-5, 1e-4])
    if geometry == "axisymmetric":
        sc = AxisymmetricIndentation(depths, indenter="sphere", radius=RADIUS, cells_per_contact_radius=3)
    else:
        block = indentation_block((4e-3, 4e-3, 1.6e-3), (6, 6, 5), symmetry="quarter")
        solver = "condensed" if geometry == "3d_condensed" else "full"
        sc = Indentation(block, depths, model="fem_linear", indenter="sphere", radius=RADIUS, symmetry="quarter", solver=solver)
    m = Material(E_TRUE, NU)
    f = lambda c: sc.predict(m, c)  # noqa: E731
    program = jax.jit(lambda c: (f(c), jax.jacfwd(f)(c), jax.jacrev(f)(c)))
    lifted, dfwd, drev = (np.asarray(a) for a in program(-3e-5))
    unshifted = np.asarray(program(0.0)[0])
    assert lifted[0] == 0.0 and dfwd[0] == 0.0 and drev[0] == 0.0
    np.testing.assert_allclose(lifted[1], unshifted[0], rtol=1e-7)  # 5e-5 - 3e-5 = the first depth
    assert np.all(np.isfinite(dfwd)) and np.all(dfwd[1:] > 0)
    np.testing.assert_allclose(drev, dfwd, rtol=1e-8)
