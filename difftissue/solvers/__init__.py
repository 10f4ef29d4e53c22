"""Solvers: static equilibrium (Newton-Krylov, implicit gradients), XPBD, damped dynamics."""

from .static import StaticResult, StaticSolution, solve_static

__all__ = ["StaticResult", "StaticSolution", "solve_static"]
