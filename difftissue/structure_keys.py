"""Structure keys: what a compiled program holds of a scenario (a pytree), hashed so that equal
scenarios share one program. The one formula behind the fit engine's compiled steps
(:meth:`difftissue.fit.FitProblem.structure_key`), the separately compiled scenarios of a fit
(``difftissue.config.compile``) and the scenarios' own compiled protocols
(``difftissue.scenarios``). Imports nothing of difftissue."""

from __future__ import annotations

import equinox as eqx
import numpy as np

__all__ = ["DATA_ATTRIBUTES", "data_leaf_indices", "hash_scenario_leaves"]

#: Attributes of a scenario that hold its measured data (SI, the unit of the observable):
#: compiled programs take them as arguments, so only their shapes and dtypes enter a
#: structure key (:func:`hash_scenario_leaves`).
DATA_ATTRIBUTES = ("observed", "sigma")


def data_leaf_indices(scenario, leaves, attributes: tuple[str, ...] = DATA_ATTRIBUTES) -> tuple[int, ...]:
    """Indices of the leaves (``leaves``: ``jax.tree_util.tree_flatten(scenario)[0]``) that ARE
    the scenario's measured data: the arrays of ``attributes`` (default :data:`DATA_ATTRIBUTES`),
    matched by identity."""
    attrs = [getattr(scenario, a, None) for a in attributes]
    return tuple(i for i, leaf in enumerate(leaves) if eqx.is_array(leaf) and any(leaf is a for a in attrs))


def hash_scenario_leaves(h, leaves, data, *, data_tag: str = "data") -> list[int]:
    """Feed what a compiled program holds of a scenario's pytree ``leaves`` into the hashlib
    object ``h``, leaf by leaf (each closed by ``|``), and return the ids of the leaves that are
    keyed by identity.

    - a leaf whose index is in ``data`` (an argument of the program, not compiled in): its shape
      and dtype only, after ``data_tag``;
    - an array (JAX or NumPy) or NumPy scalar: shape, dtype and bytes (its content);
    - None, bool, int, float, complex, str: type name and value;
    - any other object: not hashed; its ``id`` is returned (the caller keeps the object alive
      as long as the key is used).

    The one formula behind :meth:`FitProblem.structure_key` (the fit engine's compiled steps)
    and ``difftissue.config.compile.scenario_structure`` (the programs shared by equal
    scenarios); ``data_tag`` is ``"dyn"`` and ``"data"`` there."""
    objects = []
    for i, leaf in enumerate(leaves):
        if i in data:
            a = np.asarray(leaf)
            h.update(f"{data_tag}{a.shape}{a.dtype}".encode())
        elif eqx.is_array(leaf) or isinstance(leaf, np.generic):
            a = np.ascontiguousarray(leaf)
            h.update(f"{a.shape}{a.dtype}".encode())
            h.update(a.tobytes())
        elif leaf is None or isinstance(leaf, (bool, int, float, complex, str)):
            h.update(repr((type(leaf).__name__, leaf)).encode())
        else:  # an object that is not an array: by identity
            objects.append(id(leaf))
        h.update(b"|")
    return objects
