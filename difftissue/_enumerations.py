"""Result codes and messages of equinox ``Enumeration`` results (optimistix, diffrax, lineax)
through public APIs only: an item's code is its one pytree leaf (public flattening, not the
private ``_value``), and the message of a code is looked up by the public
``enumeration[item]`` with the item rebuilt from a member's pytree structure (not the private
``_index_to_message``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

#: the most codes :func:`result_messages` looks for (diffrax 0.7 has 14)
MAX_CODES = 256


def result_code(result) -> jax.Array:
    """The integer code of an ``Enumeration`` item (0 = successful)."""
    return jnp.asarray(jax.tree_util.tree_leaves(result)[0])


def result_message(enumeration, code: int) -> str:
    """The message of code ``code`` of the ``Enumeration`` class ``enumeration`` (``""`` for
    success). Raises IndexError for a code the enumeration does not have."""
    member = enumeration.successful
    (leaf,), treedef = jax.tree_util.tree_flatten(member)
    return enumeration[jax.tree_util.tree_unflatten(treedef, [np.asarray(code, dtype=np.asarray(leaf).dtype)])]


def result_messages(enumeration) -> list[str]:
    """The messages of all codes of ``enumeration``, in code order."""
    out = []
    for code in range(MAX_CODES):
        try:
            out.append(result_message(enumeration, code))
        except (IndexError, KeyError, ValueError):
            break
    return out
