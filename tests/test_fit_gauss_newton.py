"""difftissue.fit.gauss_newton: the Gauss--Newton family on optimistix's public extension
points, with difftissue's own state -- the same iterates as optimistix's own solvers -- and
the guard that difftissue reads no private attribute of its dependencies."""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from difftissue import Material
from difftissue.fit import FitProblem
from difftissue.fit.engine import Engine
from difftissue.fit.gauss_newton import GaussNewton, GaussNewtonState
from difftissue.fit.marquardt import ScaledDampedNewtonDescent, ScaledLevenbergMarquardt
from difftissue.materials import MaterialParameterization

jax.config.update("jax_enable_x64", True)

PACKAGE = Path(__file__).resolve().parents[1] / "difftissue"
T = jnp.linspace(0.0, 1.0, 25)


def _residuals(y, args):
    """``A exp(-k t) + c`` against noisy data, ``y = (log A, k, c)``; aux: the model curve."""
    data, scale = args
    log_amplitude, rate, offset = y * scale
    model = jnp.exp(log_amplitude - rate * T) + offset
    return 1e3 * (model - data), model


def _args(seed=0):
    rng = np.random.default_rng(seed)
    data = 2.0 * np.exp(-0.3 * np.asarray(T)) + 0.1 + 1e-3 * rng.normal(size=T.size)
    return jnp.asarray(data), jnp.array([1.0, 1.0, 1.0])


class _OptimistixScaledLM(optx.AbstractGaussNewton):
    """The Marquardt-scaled LM on optimistix's own Gauss--Newton machinery (what
    :class:`ScaledLevenbergMarquardt` was before it had its own state): the reference."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: ScaledDampedNewtonDescent = ScaledDampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
    verbose: Callable = lambda **kwargs: None  # noqa: E731


def _run(solver, y0, args, steps, jac):
    """``(y, aux, terminate, result)`` after each of ``steps`` steps, through the solvers'
    public ``init`` / ``step`` / ``terminate``."""
    f_struct = jax.ShapeDtypeStruct((T.size,), jnp.float64)
    aux_struct = jax.ShapeDtypeStruct((T.size,), jnp.float64)
    options = {"jac": jac}
    state = solver.init(_residuals, y0, args, options, f_struct, aux_struct, frozenset())
    step = eqx.filter_jit(lambda y, s: solver.step(_residuals, y, args, options, s, frozenset()))
    out, y = [], y0
    for _ in range(steps):
        y, state, aux = step(y, state)
        term, result = solver.terminate(_residuals, y, args, options, state, frozenset())
        out.append((np.asarray(y), np.asarray(aux), bool(term), int(jax.tree_util.tree_leaves(result)[0])))
    return out, state


@pytest.mark.parametrize("jac", ["fwd", "bwd"])
@pytest.mark.parametrize(
    "ours, reference",
    [
        (GaussNewton(rtol=1e-12, atol=1e-14), optx.GaussNewton(rtol=1e-12, atol=1e-14)),
        (ScaledLevenbergMarquardt(rtol=1e-12, atol=1e-14), _OptimistixScaledLM(rtol=1e-12, atol=1e-14)),
    ],
    ids=["gauss_newton", "levenberg_marquardt"],
)
def test_the_iterates_are_those_of_optimistix_to_the_last_bit(ours, reference, jac):
    """Same accepted points, aux and termination at every step (rejected trial steps included:
    the LM start is far enough away for the trust region to reject some)."""
    args = _args(1)
    y0 = jnp.array([-2.0, 5.0, 3.0])
    got, state = _run(ours, y0, args, 14, jac)
    expected, _ = _run(reference, y0, args, 14, jac)
    assert np.all(np.isfinite(got[-1][0]))
    for k, (a, b) in enumerate(zip(got, expected)):
        np.testing.assert_array_equal(a[0], b[0], err_msg=f"y, step {k}")
        np.testing.assert_array_equal(a[1], b[1], err_msg=f"aux, step {k}")
        assert a[2:] == b[2:], f"terminate / result, step {k}"
    assert isinstance(state, GaussNewtonState)
    # the state holds the residual and the aux at the last accepted point (a fresh evaluation
    # outside jit: equal to round-off)
    r, model = _residuals(got[-1][0], args)
    np.testing.assert_allclose(np.asarray(state.f_info.residual), np.asarray(r), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(state.aux), np.asarray(model), rtol=0, atol=1e-12)
    if isinstance(ours, ScaledLevenbergMarquardt):
        assert int(state.num_accepted_steps) < int(state.num_steps)  # some trial steps were rejected


@pytest.mark.parametrize(
    "ours, reference",
    [
        (GaussNewton(rtol=1e-10, atol=1e-12), optx.GaussNewton(rtol=1e-10, atol=1e-12)),
        (ScaledLevenbergMarquardt(rtol=1e-10, atol=1e-12), _OptimistixScaledLM(rtol=1e-10, atol=1e-12)),
    ],
    ids=["gauss_newton", "levenberg_marquardt"],
)
def test_optx_least_squares_gives_the_same_solution(ours, reference):
    args = _args(1)
    y0 = jnp.array([2.5, 4.0, -1.0])
    a = optx.least_squares(_residuals, ours, y0, args=args, has_aux=True, max_steps=256)
    b = optx.least_squares(_residuals, reference, y0, args=args, has_aux=True, max_steps=256)
    np.testing.assert_array_equal(np.asarray(a.value), np.asarray(b.value))
    np.testing.assert_array_equal(np.asarray(a.aux), np.asarray(b.aux))
    assert int(a.stats["num_steps"]) == int(b.stats["num_steps"])
    # and it is the least-squares minimum: the gradient J^T r vanishes there
    g = jax.grad(lambda y: 0.5 * jnp.sum(_residuals(y, args)[0] ** 2))(a.value)
    assert float(jnp.max(jnp.abs(g))) < 1e-6 * float(jnp.sum(_residuals(a.value, args)[0] ** 2))


def test_an_unknown_jac_option_fails_clearly():
    with pytest.raises(ValueError, match="jac must be 'fwd' or 'bwd'"):
        GaussNewton(rtol=1e-8, atol=1e-8).init(_residuals, jnp.zeros(3), _args(), {"jac": "central"},
                                                jax.ShapeDtypeStruct((T.size,), jnp.float64), None, frozenset())


# ---------------------------------------------------------------- no private dependency API
@pytest.mark.parametrize("method", ["levenberg_marquardt", "gauss_newton"])
def test_the_engine_steps_difftissue_solvers_whose_state_is_difftissue_s(method):
    """The engine reads the residual, Jacobian, aux and trial point from the solver state: that
    state must be difftissue's :class:`GaussNewtonState` (a documented class of this package),
    never an optimistix solver state (whose fields are not optimistix's public API)."""

    class Line:
        name, x_label, y_label = "line", "x [1]", "y [Pa]"
        abscissa = np.linspace(0.0, 1.0, 8)
        sigma = np.full(8, 10.0)
        observed = 5e3 * abscissa + 10.0 * np.random.default_rng(0).normal(size=8)

        def predict(self, material):
            return material.youngs_modulus * jnp.asarray(self.abscissa)

    problem = FitProblem(Line(), MaterialParameterization(("youngs_modulus",)), Material(2e3, 0.3))
    engine = Engine(problem, method, rtol=1e-8, atol=1e-10, learning_rate=0.05, jac="fwd")
    assert type(engine.solver).__module__.startswith("difftissue.")
    U = jnp.zeros((2, 1))
    dyn = engine.init(U, problem.data())
    state = eqx.combine(dyn, engine._static)
    assert type(state) is GaussNewtonState
    U, dyn, done, status, loss = engine.make_step()(U, dyn, jnp.zeros(2, bool), problem.data())
    assert type(eqx.combine(dyn, engine._static)) is GaussNewtonState
    assert np.all(np.isfinite(np.asarray(loss)))


#: Dependencies whose private names (a leading underscore, an ``internal`` module) difftissue
#: must not use.
DEPENDENCIES = ("jax", "jaxlib", "optimistix", "equinox", "lineax", "diffrax", "optax", "jaxtyping")

#: Fields of optimistix's solver-state classes (not public API). difftissue reads attributes
#: of these names only in modules that work on its own state classes, which declare them.
OPTIMISTIX_STATE_FIELDS = frozenset(
    {"f_info", "y_eval", "num_steps_since_acceptance", "num_accepted_steps", "search_state", "descent_state", "first_step"}
)


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _dependency_root(node, aliases) -> bool:
    """Whether the expression ``node`` is a dependency module or an attribute chain on one."""
    while isinstance(node, ast.Attribute):
        node = node.value
    return isinstance(node, ast.Name) and node.id in aliases


def _violations(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    aliases, bad = set(), []
    declared = {  # fields declared by classes of this module
        t.target.id for c in ast.walk(tree) if isinstance(c, ast.ClassDef) for t in c.body
        if isinstance(t, ast.AnnAssign) and isinstance(t.target, ast.Name)
    }
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] in DEPENDENCIES:
                    aliases.add(a.asname or parts[0])
                    if any(_private(p) or p == "internal" for p in parts[1:]):
                        bad.append(f"{path.name}:{node.lineno}: import {a.name}")
        elif isinstance(node, ast.ImportFrom) and node.module:
            parts = node.module.split(".")
            if node.level == 0 and parts[0] in DEPENDENCIES:
                if any(_private(p) or p == "internal" for p in parts[1:]):
                    bad.append(f"{path.name}:{node.lineno}: from {node.module} import ...")
                for a in node.names:
                    if _private(a.name) or a.name == "internal":
                        bad.append(f"{path.name}:{node.lineno}: from {node.module} import {a.name}")
            imported |= {a.asname or a.name for a in node.names}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            if (_private(node.attr) or node.attr == "internal") and _dependency_root(node.value, aliases):
                bad.append(f"{path.name}:{node.lineno}: {ast.unparse(node)}")
            if node.attr in OPTIMISTIX_STATE_FIELDS and node.attr not in declared and "GaussNewtonState" not in imported:
                bad.append(f"{path.name}:{node.lineno}: .{node.attr} read outside difftissue's solver-state modules")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr"):
            if len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str):
                name = node.args[1].value
                if (_private(name) and _dependency_root(node.args[0], aliases)) or (
                    name in OPTIMISTIX_STATE_FIELDS and name not in declared and "GaussNewtonState" not in imported
                ):
                    bad.append(f"{path.name}:{node.lineno}: {ast.unparse(node)}")
    return bad


def test_difftissue_uses_no_private_name_of_its_dependencies():
    """No ``jax._src``, ``equinox.internal``, ``optimistix._...`` import or attribute, and no read
    of an optimistix solver-state field outside the modules that declare or import difftissue's
    own :class:`GaussNewtonState`."""
    bad = [v for path in sorted(PACKAGE.rglob("*.py")) for v in _violations(path)]
    assert not bad, "private dependency API used:\n" + "\n".join(bad)


def test_the_private_name_guard_catches_what_it_is_for(tmp_path):
    """The guard above is not vacuous: each pattern it forbids is found in a sample module."""
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import jax\nimport optimistix as optx\nimport equinox.internal as eqxi\n"
        "from jax._src import core\n"
        "def f(state, sol):\n"
        "    a = state.f_info.residual\n"
        "    b = state.num_steps_since_acceptance\n"
        "    c = optx.RESULTS._index_to_message\n"
        "    d = getattr(jax, '_src')\n"
        "    return sol.value, sol.aux, sol.stats\n",
        encoding="utf-8",
    )
    found = "\n".join(_violations(sample))
    for pattern in ("import equinox.internal", "from jax._src", ".f_info", ".num_steps_since_acceptance",
                    "optx.RESULTS._index_to_message", "getattr(jax, '_src')"):
        assert pattern in found, (pattern, found)
    assert "sol.value" not in found and "aux" not in found
