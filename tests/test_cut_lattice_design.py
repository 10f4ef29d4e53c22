"""The lattice-stretch tangent match of experiments/cut_lattice_tangent.py (`design`): the cell
through the library's kernels is the model's own one-cell energy, the match is exact (tension and
the four incremental moduli of the neo-Hookean), and its factors tend to the default lattice as
lambda0 -> 1 (docs/dev/cut-openings-finite-strain.md, section 7)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import cut_lattice_tangent as clt  # noqa: E402


def test_cell_kernel_is_the_models_one_cell_energy_at_another_lattice_stretch():
    """psi_lat(c, F, s) equals constitutive's one-cell springs_volume_mesh_lattice at pre-stretch s."""
    import jax.numpy as jnp

    psi_lat = clt._cell_kernels()[0]
    c = jnp.array([0.6, 1.4, 0.9, 1.05, 0.8])
    F = jnp.array([[1.02, 0.01, 0.0], [0.0, 0.99, 0.02], [0.01, 0.0, 0.9]])
    for s in (1.0, 1.0934):
        ref = float(clt.density("springs_volume_mesh_lattice", s)(c, F))
        assert abs(float(psi_lat(c, F, s)) - ref) <= 1e-10 * abs(ref)


def test_design_is_exact_and_tends_to_the_default_lattice():
    rows = [r for r in clt.design([1.0025, 1.005], step=0.0025, scan=False) if r["design"] == "S"]
    assert len(rows) == 2
    for r in rows:
        assert np.abs(r["residual"]).max() < 1e-10  # P_zz = 0, tension and moduli of the neo-Hookean / mu
        assert r["condition"] < 1e3  # regular near lambda0 = 1 (the 5-factor match's grows like (lambda0 - 1)^-2)
    (a, b) = rows
    ca, cb = np.asarray(a["factors"][:4]), np.asarray(b["factors"][:4])
    assert np.all(np.abs(cb - 1.0) > 4e-3)  # the factors do move with lambda0 (0.5-2.7 % at 1.005) ...
    # ... and their linear extrapolation to lambda0 = 1 is the default lattice (the five-factor
    # match's out-of-plane edges extrapolate to 1.21 there, section 6)
    np.testing.assert_allclose(2.0 * ca - cb, 1.0, atol=1e-3)
    assert abs(a["lattice_stretch"] / 1.0025 - 1.0) < 1e-5 and abs(b["lattice_stretch"] / 1.005 - 1.0) < 1e-4
