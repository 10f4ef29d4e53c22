"""Fit checkpoints: the optimiser state of every start saved to ``.npz`` atomically and read
back with a fingerprint check (a checkpoint of another problem is refused).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._io import atomic_output
from ..errors import CheckpointError, CheckpointMismatchError


# ============================================================================ checkpoints
def save_checkpoint(path: Path, *, U, dyn, done, status, history, step, fingerprint, components, method):
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(dyn)]
    arrays = {f"state_{i}": a for i, a in enumerate(leaves)}
    meta = {
        "format": "difftissue-fit-checkpoint/1",
        "fingerprint": fingerprint,
        "components": components,
        "method": method,
        "step": int(step),
        "n_state_leaves": len(leaves),
    }
    with atomic_output(path, overwrite=True) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                meta=np.array(json.dumps(meta)),
                unconstrained=np.asarray(U),
                done=np.asarray(done),
                status=np.asarray(status),
                loss_history=np.asarray(history),
                **arrays,
            )


def load_checkpoint(path: Path, *, fingerprint, components, dyn_template):
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            data = {k: np.array(z[k]) for k in z.files if k != "meta"}
    except Exception as exc:  # noqa: BLE001 - report any unreadable file as one clear error
        raise CheckpointError(f"cannot read fit checkpoint {path}: {exc}") from exc
    if meta.get("fingerprint") != fingerprint:
        saved = meta.get("components", {})
        differ = [k for k in components if saved.get(k) != components[k]] or ["unknown"]
        raise CheckpointMismatchError(
            f"checkpoint {path} was written by a different fit problem (differs in: {', '.join(differ)}); "
            "refusing to resume from it. Delete it or choose another checkpoint path to start afresh."
        )
    leaves, treedef = jax.tree_util.tree_flatten(dyn_template)
    if meta.get("n_state_leaves") != len(leaves):
        raise CheckpointMismatchError(f"checkpoint {path} holds an optimiser state of another layout (library version changed?); delete it to start afresh")
    new_leaves = []
    for i, ref in enumerate(leaves):
        a = data[f"state_{i}"]
        if a.shape != ref.shape:
            raise CheckpointMismatchError(f"checkpoint {path}: optimiser state leaf {i} has shape {a.shape}, expected {ref.shape}; delete it to start afresh")
        new_leaves.append(jnp.asarray(a, dtype=ref.dtype))
    dyn = jax.tree_util.tree_unflatten(treedef, new_leaves)
    return (
        jnp.asarray(data["unconstrained"]),
        dyn,
        jnp.asarray(data["done"]),
        jnp.asarray(data["status"]),
        [row for row in np.asarray(data["loss_history"])],
        int(meta["step"]),
    )
