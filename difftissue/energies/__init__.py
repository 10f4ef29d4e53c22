"""Pure per-element energy kernels (energy in J, forces by ``jax.grad``).

- :mod:`~difftissue.energies.springs` -- safe norm, cubic springs ``k e^2/2 + a e^4/4``.
- :mod:`~difftissue.energies.volume` -- tet volume constraint ``V - V0`` and its energy.
- :mod:`~difftissue.energies.neo_hookean` -- deformation gradient, stable neo-Hookean
  constraints and energy (Macklin & Müller 2021, with the ``lambda' = lambda + mu`` shift).
- :mod:`~difftissue.energies.fem` -- linear and compressible neo-Hookean tet FEM energies and
  their node-patch volumetric terms (nodal-averaged dilatation).

Every kernel is a pure function of arrays, differentiable to second order, and broadcasts
over leading batch dimensions (so it also works under ``jax.vmap``). Units are SI.
"""

from .fem import (
    ENERGY_DENSITIES,
    fem_energy,
    linear_elastic_energy_density,
    neo_hookean_energy_density,
    nodal_dilatation_energy,
    nodal_dilatation_hessian,
    nodal_volume_energy,
    nodal_volume_hessian,
    rest_shapes,
    tet_energy,
)
from .neo_hookean import (
    deformation_gradient,
    det3,
    det3_minus_one,
    edge_matrix,
    first_invariant_minus_three,
    rest_shape,
    stable_neo_hookean_constraints,
    stable_neo_hookean_energy_density,
    stable_neo_hookean_gamma,
)
from .springs import cubic_spring_energy, cubic_spring_hessian, safe_norm, spring_extension
from .volume import tet_signed_volume, volume_constraint, volume_energy

__all__ = [
    "safe_norm",
    "spring_extension",
    "cubic_spring_energy",
    "cubic_spring_hessian",
    "tet_signed_volume",
    "volume_constraint",
    "volume_energy",
    "det3",
    "det3_minus_one",
    "first_invariant_minus_three",
    "edge_matrix",
    "rest_shape",
    "deformation_gradient",
    "stable_neo_hookean_gamma",
    "stable_neo_hookean_constraints",
    "stable_neo_hookean_energy_density",
    "linear_elastic_energy_density",
    "neo_hookean_energy_density",
    "tet_energy",
    "rest_shapes",
    "fem_energy",
    "ENERGY_DENSITIES",
    "nodal_dilatation_energy",
    "nodal_volume_energy",
    "nodal_dilatation_hessian",
    "nodal_volume_hessian",
]
