"""XLA compiler options per program (difftissue.xla_options): the static solves and the
scenarios' protocols are compiled with the ``"static"`` options when called on their own, the
same functions inside an outer program or under ``jax.grad`` take the outer program's, and the
XPBD programs never get them. An option XLA does not know is the witness that options reach the
compiler (it fails the compilation)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difftissue import xla_options
from difftissue.boundary import BoundaryConditions
from difftissue.materials import Material
from difftissue.mesh import block
from difftissue.models import make_model
from difftissue.scenarios import Compression
from difftissue.solvers.static import solve_static
from difftissue.solvers.xpbd import XPBDSettings, xpbd_simulate

BOGUS = {"xla_cpu_no_such_option_for_this_test": True}

MESH = block((0.01, 0.01, 0.01), (1, 1, 1))


def _problem():
    X = np.asarray(MESH.points)
    base, top = np.flatnonzero(np.isclose(X[:, 2], 0.0)), np.flatnonzero(np.isclose(X[:, 2], 0.01))
    bc = BoundaryConditions.free(MESH).fix(MESH, base).fix(MESH, top, "xyz", (0.0, 0.0, -1e-4))
    return make_model(MESH, "springs_volume"), bc, top


@pytest.fixture
def bogus(monkeypatch):
    """Every program kind with an option XLA does not know, passed through unfiltered."""
    for kind in xla_options.PROGRAMS:
        monkeypatch.setitem(xla_options.PROGRAMS, kind, BOGUS)
    monkeypatch.setattr(xla_options, "known_options", lambda options, backend="cpu": dict(options))


def test_the_option_sets_and_the_rule():
    assert xla_options.compiler_options("static") == xla_options.OLDER_FUSION
    assert xla_options.compiler_options("static", backend="gpu") is None  # CPU options only
    with pytest.raises(KeyError):
        xla_options.compiler_options("xpbd")
    # an option this jaxlib does not know is left out (it would fail the compilation)
    assert xla_options.known_options({**BOGUS, **xla_options.OLDER_FUSION}) == xla_options.OLDER_FUSION
    # the old names are the new module's values
    from difftissue.config import compile as cc
    from difftissue.fit import batch
    from difftissue.solvers import host

    assert host.HOST_COMPILER_OPTIONS == xla_options.PROGRAMS["host_derivatives"]
    assert cc.SMALL_MODEL_COMPILER_OPTIONS == xla_options.LOW_OPTIMISATION
    assert batch.CPU_COMPILER_OPTIONS == xla_options.PROGRAMS["batch"]
    assert batch.SPECTRAL_COMPILER_OPTIONS == {**xla_options.LOW_OPTIMISATION, **xla_options.OLDER_FUSION}
    assert {**batch.CPU_COMPILER_OPTIONS, **batch.SPECTRAL_COMPILER_OPTIONS} == xla_options.PROGRAMS["batch_spectral"]


def test_a_static_solve_on_its_own_is_compiled_with_the_static_options(bogus):
    model, bc, _ = _problem()
    with pytest.raises(Exception, match="xla_cpu_no_such_option_for_this_test"):
        solve_static(model, Material(1e4, 0.3), bc)


def test_inside_an_outer_program_or_a_gradient_it_takes_the_outer_options(bogus):
    """No ``compiler_options`` on a nested ``jax.jit`` (JAX refuses them): inside ``jax.jit``,
    ``lax.scan`` and under ``jax.grad`` the solve compiles (here: without the bogus option)."""
    model, bc, top = _problem()

    def force(E):
        return jnp.sum(solve_static(model, Material(E, 0.3), bc).reaction[top, 2])

    f = jax.jit(force)(1e4)
    g = jax.grad(force)(1e4)
    s = jax.lax.scan(lambda c, E: (c, force(E)), 0.0, jnp.array([1e4]))[1][0]
    assert np.isfinite(float(f)) and float(f) == pytest.approx(float(s), rel=1e-12)
    assert float(g) == pytest.approx(float(f) / 1e4, rel=1e-9)  # springs_volume: force linear in E


def test_a_scenario_protocol_on_its_own_is_compiled_with_the_static_options(bogus):
    sc = Compression(MESH, np.array([0.01, 0.02]), model="fem_linear", name="c")
    with pytest.raises(Exception, match="xla_cpu_no_such_option_for_this_test"):
        sc.predict(Material(1e4, 0.3))
    assert sc.xla_program == "static"  # the kind config.SeparatelyCompiled compiles it as
    # inside an outer jit: inlined, the outer program's options
    assert np.all(np.isfinite(np.asarray(jax.jit(lambda E: sc.predict(Material(E, 0.3)))(1e4))))


def test_xpbd_programs_keep_xla_defaults(bogus):
    """XPBD runs ~40 % slower with the older fusion: none of the option sets reaches it."""
    model, bc, top = _problem()
    state = xpbd_simulate(model, Material(1e4, 0.3), bc, settings=XPBDSettings(dt=1e-3, iterations=5), steps=2)
    assert np.all(np.isfinite(np.asarray(state.reaction[top])))
