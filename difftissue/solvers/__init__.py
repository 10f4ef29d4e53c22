"""Solvers: static equilibrium (Newton-Krylov, implicit gradients), XPBD, damped dynamics."""

from .dynamics import ADJOINTS, SOLVERS, DynamicsSolution, ramp, simulate_dynamics
from .static import StaticResult, StaticSolution, solve_static
from .xpbd import XPBDQuasiStaticSolution, XPBDSettings, XPBDState, xpbd_constraints, xpbd_quasi_static, xpbd_simulate

__all__ = [
    "StaticResult",
    "StaticSolution",
    "solve_static",
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
