"""Test configuration: float64 everywhere (gradient checks need it), headless plots."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
