"""The card as a scikit-fem linear-elasticity model, in memory (imports scikit-fem when called)."""

from __future__ import annotations

import numpy as np

from ..errors import ExportError
from .approximations import approximation_notes
from .card import MaterialCard

__all__ = ["to_skfem"]


def to_skfem(card: MaterialCard, mesh=None, *, approximate: bool = False) -> dict:
    """The card as a scikit-fem linear-elasticity model (in memory; imports ``skfem``).

    Conversion: scikit-fem's ``skfem.models.elasticity.linear_elasticity(Lambda, Mu)`` takes the
    Lamé parameters, ``lam = E nu / ((1 + nu)(1 - 2 nu))`` and ``mu = E / (2 (1 + nu))``; its
    energy ``W = lam/2 tr(eps)^2 + mu eps:eps`` is difftissue's ``fem_linear`` and the
    small-strain response of every model. A nonzero ``cubic_coefficient`` or a ``pre_stretch``
    other than 1 is refused unless ``approximate`` (then listed in ``"notes"``).

    Returns ``{"lam", "mu", "form", "notes"}`` (``form``: the bilinear form for ``skfem.asm``);
    with ``mesh`` also ``"mesh"`` (``skfem.MeshTet``, same node and tet order), ``"basis"``
    (vector P1), ``"stiffness"`` (assembled CSR matrix [N/m]) and ``"dofs"``: an ``(N, 3)``
    integer array, ``dofs[a, c]`` is scikit-fem's DOF of component ``c`` of node ``a``.
    """
    try:
        import skfem
        from skfem.models.elasticity import linear_elasticity
    except ImportError:
        raise ExportError("the scikit-fem export needs scikit-fem (pip install scikit-fem)") from None
    notes = approximation_notes(card, "scikit-fem linear elasticity", approximate=approximate)
    lam, mu = card.lame_lambda, card.shear_modulus
    out = {"lam": lam, "mu": mu, "form": linear_elasticity(lam, mu), "notes": notes}
    if mesh is not None:
        pts = np.asarray(mesh.points, dtype=float)
        tets = np.asarray(mesh.tets, dtype=np.int64)
        m = skfem.MeshTet(pts.T.copy(), tets.T.copy())
        basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
        out.update(mesh=m, basis=basis, stiffness=skfem.asm(out["form"], basis).tocsr(),
                   dofs=np.asarray(basis.nodal_dofs).T.copy())
    return out
