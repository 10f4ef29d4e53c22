"""Solvers: static equilibrium (Newton-Krylov, implicit gradients), XPBD, damped dynamics."""

from .static import SolverSetup, StaticResult, StaticSolution, solve_static, solver_setup
from .xpbd import XPBDQuasiStaticSolution, XPBDSettings, XPBDState, xpbd_constraints, xpbd_quasi_static, xpbd_simulate

#: Imported on first use (diffrax's import costs about a second that static fits do not need).
_DYNAMICS = ("ADJOINTS", "SOLVERS", "DynamicsSolution", "ramp", "simulate_dynamics")


def __getattr__(name):
    if name in _DYNAMICS:
        from . import dynamics

        return getattr(dynamics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "StaticResult",
    "StaticSolution",
    "solve_static",
    "SolverSetup",
    "solver_setup",
    "XPBDSettings",
    "XPBDState",
    "XPBDQuasiStaticSolution",
    "xpbd_constraints",
    "xpbd_simulate",
    "xpbd_quasi_static",
    "DynamicsSolution",
    "simulate_dynamics",
    "ramp",
    "SOLVERS",
    "ADJOINTS",
]
