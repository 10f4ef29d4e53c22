"""The Young's modulus tangent in closed form: models whose energy is linear in E
(``ElasticModel.energy_linear_in_youngs_modulus``), scenarios whose predictions are then
proportional to E (``prediction_scales_with_youngs_modulus``), and the Jacobians of
:class:`difftissue.config.SeparatelyCompiled`, which take the E column as ``y / E`` instead of an
implicit solve per load step: checked against central differences and against the implicit
(IFT) Jacobian of the scenario itself."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import Material
from difftissue.boundary import BoundaryConditions
from difftissue.config import SeparatelyCompiled, compile_cache_info
from difftissue.config import compile as compile_module
from difftissue.contact import ContactModel, SphereIndenter
from difftissue.mesh import block
from difftissue.models import ElasticModel, make_model
from difftissue.scenarios import Compression, Indentation, SolverOptions, _scales_with_youngs_modulus, indentation_block

jax.config.update("jax_enable_x64", True)

MODELS = ["springs_volume", "fem_linear", "fem_neo_hookean", "stable_neo_hookean", "fem_linear_nodal", "fem_neo_hookean_nodal"]


@pytest.mark.parametrize("kind", MODELS)
def test_model_energies_that_say_so_are_linear_in_youngs_modulus(kind):
    mesh = block((2e-3, 2e-3, 1e-3), (2, 2, 1))
    model = make_model(mesh, kind)
    assert model.energy_linear_in_youngs_modulus
    rng = np.random.default_rng(3)
    x = jnp.asarray(mesh.points) * 1.02 + 2e-5 * rng.standard_normal(np.shape(mesh.points))
    m = Material(7e3, 0.41, cubic_coefficient=1.5, pre_stretch=1.05)
    for c in (0.3, 2.7):
        np.testing.assert_allclose(float(model.energy(x, m.replace(youngs_modulus=c * 7e3))), c * float(model.energy(x, m)), rtol=1e-13)
    # with penalty contact (the penalty is E times a constant) and a node in contact
    contact = ContactModel(model, SphereIndenter(1e-3, axis_xy=(1e-3, 1e-3), surface_z=1e-3), mesh, depth=5e-5)
    assert contact.energy_linear_in_youngs_modulus
    assert float(contact.contact_energy(x, m)) > 0
    np.testing.assert_allclose(float(contact.energy(x, m.replace(youngs_modulus=2.7 * 7e3))), 2.7 * float(contact.energy(x, m)), rtol=1e-13)


def test_no_claim_without_a_statement_or_with_applied_forces():
    assert ElasticModel.energy_linear_in_youngs_modulus is False
    mesh = block((1e-2, 1e-2, 1e-2), (1, 1, 1))
    model = make_model(mesh, "fem_linear")
    bc = BoundaryConditions.free(mesh).fix(mesh, {"face": "z-min"})
    assert _scales_with_youngs_modulus(model, bc)
    # a force-controlled problem: u ~ 1/E, no closed form
    loaded = BoundaryConditions(bc.fixed, bc.displacement, np.asarray(bc.force).copy() + np.array([0.0, 0.0, -1e-3]))
    assert not _scales_with_youngs_modulus(model, loaded)


def _fn(sc, fields):
    return lambda p: sc.predict(Material(12e3, 0.42, cubic_coefficient=0.5).replace(**dict(zip(fields, p))))


def _central(f, p, steps):
    cols = []
    for i, h in enumerate(steps):
        e = np.zeros(len(p))
        e[i] = h
        cols.append((np.asarray(f(p + e)) - np.asarray(f(p - e))) / (2 * h))
    return np.stack(cols, 1)


SCENARIOS = {
    # full Newton solves with multigrid-free (dense) linear algebra at this size, sphere penalty contact
    "indentation_springs_volume": lambda: Indentation(indentation_block((4e-3, 4e-3, 1.6e-3), (4, 4, 3), symmetry="quarter"), np.linspace(0.02, 0.2, 5) * 1e-3,
                                                      np.ones(5), model="springs_volume", radius=1e-3, symmetry="quarter", options=SolverOptions(failure="nan")),
    # the condensed contact path (linear body condensed onto the contact candidates)
    "indentation_condensed": lambda: Indentation(indentation_block((4e-3, 4e-3, 1.6e-3), (4, 4, 3), symmetry="quarter"), np.linspace(0.02, 0.2, 5) * 1e-3,
                                                 np.ones(5), model="fem_linear", radius=1e-3, symmetry="quarter", options=SolverOptions(failure="nan")),
    "compression_springs_volume": lambda: Compression(block((0.01, 0.01, 0.01), (2, 2, 2)), [0.05, 0.1, 0.2], [1.0, 2.0, 3.0], model="springs_volume",
                                                      options=SolverOptions(failure="nan")),
}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_separately_compiled_jacobian_with_the_closed_form_youngs_modulus_column(name):
    sc = SCENARIOS[name]()
    assert sc.prediction_scales_with_youngs_modulus
    fields = ("youngs_modulus", "poisson_ratio")
    w = SeparatelyCompiled(sc, fields=fields)
    assert w.scales_with_youngs_modulus
    p = jnp.array([12e3, 0.42])
    # one compiled protocol program, or none where a small compression specimen is solved on
    # the host (Compression.solve_on_host: only the model's derivatives are compiled)
    programs = 0 if (compile_module.HOST_SOLVES and getattr(sc, "solves_on_host", False)) else 1
    before = compile_cache_info()["compilations"]
    J = np.asarray(jax.jacfwd(_fn(w, fields))(p))
    assert compile_cache_info()["compilations"] - before == programs and w.calls["value_and_tangents"] == 1
    y = np.asarray(w.evaluate(Material(12e3, 0.42, cubic_coefficient=0.5)))  # the same program (one tangent lane, zero)
    assert compile_cache_info()["compilations"] - before == programs
    # The scenario's own implicit-function-theorem Jacobian and, as its auxiliary output, its
    # prediction from the same primal solve: one compiled program, which every evaluation of
    # the scenario below reuses (instead of a primal program and a JVP program).
    jac_and_value = jax.jit(jax.jacfwd(lambda q: (lambda y: (y, y))(_fn(sc, fields)(q)), has_aux=True))

    def scenario(q):
        return jac_and_value(jnp.asarray(q))[1]

    # the prediction really is proportional to E (what the closed form rests on)
    np.testing.assert_allclose(np.asarray(scenario(jnp.array([1.37 * 12e3, 0.42]))), 1.37 * y, rtol=1e-11)
    np.testing.assert_allclose(J[:, 0], y / 12e3, rtol=1e-14)
    # against central differences of the scenario (E: the function is linear in E, so the
    # difference is exact up to round-off and solver tolerance; nu: O(h^2) and solver noise)
    fd = _central(scenario, np.array([12e3, 0.42]), [12.0, 1e-5])
    np.testing.assert_allclose(J[:, 0], fd[:, 0], rtol=1e-8)
    np.testing.assert_allclose(J[:, 1], fd[:, 1], rtol=2e-6)
    # against the implicit-function-theorem Jacobian of the scenario itself: the nu column is
    # the same computation; the E column differs by the IFT solve of the Newton residual
    Ji = np.asarray(jac_and_value(p)[0])
    np.testing.assert_allclose(J[:, 1], Ji[:, 1], rtol=1e-10)  # one tangent lane vs two: summation order
    np.testing.assert_allclose(J[:, 0], Ji[:, 0], rtol=1e-8)


def test_other_tangents_than_the_compiled_ones_are_still_right():
    """A program compiled for the nu tangent only (E in closed form) answers a Jacobian in
    (nu, b) — two tangents to solve — by compiling a second program, with the same numbers as
    the scenario's own Jacobian; and a mixed tangent (E and nu together) splits into the closed
    form and a solve."""
    sc = SCENARIOS["compression_springs_volume"]()
    w = SeparatelyCompiled(sc, fields=("youngs_modulus", "poisson_ratio"))
    fields = ("poisson_ratio", "cubic_coefficient")
    p = jnp.array([0.42, 0.5])
    J = np.asarray(jax.jacfwd(_fn(w, fields))(p))
    Ji = np.asarray(jax.jacfwd(_fn(sc, fields))(p))
    np.testing.assert_allclose(J, Ji, rtol=1e-12)
    f2 = ("youngs_modulus", "poisson_ratio")
    t = jnp.array([3e3, 0.01])
    _, jt = jax.jvp(_fn(w, f2), (jnp.array([12e3, 0.42]),), (t,))
    _, jti = jax.jvp(_fn(sc, f2), (jnp.array([12e3, 0.42]),), (t,))
    np.testing.assert_allclose(jt, jti, rtol=1e-8)


def test_a_fit_of_youngs_modulus_alone_compiles_the_prediction_only():
    """With E the only fitted field and its tangent in closed form, a Jacobian needs no tangent
    solve: the one program compiled is the primal prediction (kind ``"value"``), not the
    prediction-and-tangents program run with a zero tangent (which still paid a linear solve
    per load step, with a sparse solver a factorisation each). A tangent along another field
    later compiles the tangent program and is still right."""
    sc = SCENARIOS["indentation_springs_volume"]()
    w = SeparatelyCompiled(sc, fields=("youngs_modulus",))
    assert w.scales_with_youngs_modulus
    before = compile_cache_info()["compilations"]
    J = np.asarray(jax.jacfwd(_fn(w, ("youngs_modulus",)))(jnp.array([12e3])))
    compiled = compile_cache_info()["compilations"] - before  # 0 where an equal scenario's program is shared
    assert compiled <= 1 and w.calls["value_and_tangents"] == 1
    kind = next(reversed(compile_module._PROGRAMS))[0][0]  # the program used last: (kind, structure key), ...
    assert kind == "value"
    y = np.asarray(w.evaluate(Material(12e3, 0.42, cubic_coefficient=0.5)))
    assert compile_cache_info()["compilations"] - before == compiled  # the same program
    np.testing.assert_allclose(J[:, 0], y / 12e3, rtol=1e-14)
    # the prediction equals the scenario's own
    np.testing.assert_allclose(y, np.asarray(_fn(sc, ("youngs_modulus",))(jnp.array([12e3]))), rtol=1e-12)
    # a nu tangent: the tangent program (compiled now, or shared), the scenario's implicit Jacobian's numbers
    jn = np.asarray(jax.jacfwd(_fn(w, ("poisson_ratio",)))(jnp.array([0.42])))
    assert next(reversed(compile_module._PROGRAMS))[0][0] == "value_and_tangents"
    jni = np.asarray(jax.jacfwd(_fn(sc, ("poisson_ratio",)))(jnp.array([0.42])))
    np.testing.assert_allclose(jn, jni, rtol=1e-10)
