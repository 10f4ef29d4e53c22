"""Solvers: static equilibrium (Newton-Krylov, implicit gradients), XPBD, damped dynamics."""

from .dynamics import ADJOINTS, SOLVERS, DynamicsSolution, ramp, simulate_dynamics  # noqa: F401
from .static import StaticResult, StaticSolution, solve_static
from .xpbd import XPBDSettings, XPBDState, XPBDQuasiStaticSolution, xpbd_constraints, xpbd_quasi_static, xpbd_simulate  # noqa: F401

__all__ = ["StaticResult", "StaticSolution", "solve_static"]
