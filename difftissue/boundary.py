"""Boundary conditions: prescribed displacements (Dirichlet) and nodal forces.

A :class:`BoundaryConditions` is a pytree: the mask of prescribed components is fixed data
(it decides the problem's structure), the prescribed displacements [m] and the nodal forces
[N] are differentiable leaves (so a fit can differentiate with respect to an indentation
depth or a load).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import BoundaryConditionError, RigidModeError
from .selectors import select_nodes

__all__ = ["BoundaryConditions", "rigid_modes", "check_rigid_modes"]

_COMPONENTS = {"x": 0, "y": 1, "z": 2}


def _components(spec) -> list[int]:
    if isinstance(spec, str):
        if not spec or any(c not in _COMPONENTS for c in spec):
            raise BoundaryConditionError(f"components must be letters from 'xyz', got {spec!r}")
        return sorted({_COMPONENTS[c] for c in spec})
    comps = sorted({int(c) for c in spec})
    if not comps or any(c not in (0, 1, 2) for c in comps):
        raise BoundaryConditionError(f"components must be 0, 1, 2 or letters from 'xyz', got {spec!r}")
    return comps


def _concrete(*values) -> bool:
    """True when no value is a JAX tracer (they can be set up in NumPy)."""
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(values))


class BoundaryConditions(eqx.Module):
    """Prescribed displacement components and external nodal forces of a mesh.

    Attributes:
        fixed: ``(N, 3)`` bool, True where a displacement component is prescribed.
        displacement: ``(N, 3)`` prescribed displacement [m] (used where ``fixed``).
        force: ``(N, 3)`` external nodal force [N] (dead load; ignored where ``fixed``).

    Build with :meth:`free`, then chain :meth:`fix` and :meth:`add_force`::

        bc = (BoundaryConditions.free(mesh)
              .fix(mesh, {"face": "z-min"})                          # clamp the base
              .fix(mesh, {"face": "z-max"}, "z", (0, 0, -1e-4)))     # push the top 0.1 mm
    """

    fixed: np.ndarray
    displacement: jax.Array
    force: jax.Array

    @classmethod
    def free(cls, mesh) -> "BoundaryConditions":
        """No prescribed displacement and no force on any node."""
        n = int(np.shape(mesh.points)[0])
        zeros = jnp.asarray(np.zeros((n, 3)), dtype=jnp.result_type(float))
        return cls(np.zeros((n, 3), dtype=bool), zeros, zeros)

    def _nodes(self, mesh, nodes) -> np.ndarray:
        if isinstance(nodes, dict) or hasattr(nodes, "mask"):
            return select_nodes(mesh, nodes)
        idx = np.asarray(nodes, dtype=np.int64).reshape(-1)
        n = self.fixed.shape[0]
        if idx.size == 0:
            raise BoundaryConditionError("no node given")
        if idx.min() < 0 or idx.max() >= n:
            raise BoundaryConditionError(f"node indices must lie in [0, {n}), got min {idx.min()} max {idx.max()}")
        return idx

    def fix(self, mesh, nodes, components="xyz", displacement=(0.0, 0.0, 0.0)) -> "BoundaryConditions":
        """Prescribe ``displacement`` [m] on the given components of the selected nodes.

        Args:
            mesh: the mesh (for selectors).
            nodes: a selector (see :mod:`difftissue.selectors`), its dict form, or node indices.
            components: which components to prescribe: a string of ``"xyz"`` letters.
            displacement: the displacement vector [m] (only the listed components are used),
                or an ``(n_nodes_selected, 3)`` array.
        """
        idx = self._nodes(mesh, nodes)
        comps = _components(components)
        fixed = self.fixed.copy()
        mask = np.zeros((len(idx), 3), dtype=bool)
        mask[:, comps] = True
        fixed[idx[:, None], np.arange(3)[None, :]] |= mask
        if _concrete(self.displacement, displacement):
            # NumPy on concrete values: no per-operation compilation while a scenario is built.
            disp = np.array(self.displacement)
            d = np.broadcast_to(np.asarray(displacement, dtype=disp.dtype), (len(idx), 3))
            disp[idx] = np.where(mask, d, disp[idx])
            return BoundaryConditions(fixed, jnp.asarray(disp), self.force)
        d = jnp.broadcast_to(jnp.asarray(displacement, dtype=self.displacement.dtype), (len(idx), 3))
        disp = self.displacement.at[idx].set(jnp.where(mask, d, self.displacement[idx]))
        return BoundaryConditions(fixed, disp, self.force)

    def add_force(self, mesh, nodes, total_force, *, distribute: str = "equal") -> "BoundaryConditions":
        """Add a total force [N] spread over the selected nodes.

        Args:
            distribute: ``"equal"`` (same share per node) or ``"area"`` (by each node's share of
                the boundary faces whose three nodes are all selected: a uniform traction).
        """
        idx = self._nodes(mesh, nodes)
        total = jnp.asarray(total_force, dtype=self.force.dtype).reshape(3)
        if distribute == "equal":
            w = np.full(len(idx), 1.0 / len(idx))
        elif distribute == "area":
            sel = np.zeros(self.fixed.shape[0], dtype=bool)
            sel[idx] = True
            faces = mesh.boundary_faces[np.all(sel[mesh.boundary_faces], axis=1)]
            if len(faces) == 0:
                raise BoundaryConditionError("distribute='area' needs selected nodes that span boundary faces")
            p = np.asarray(mesh.points)[faces]
            area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
            node_area = np.zeros(self.fixed.shape[0])
            np.add.at(node_area, faces.reshape(-1), np.repeat(area / 3.0, 3))
            w = node_area[idx] / node_area[idx].sum()
        else:
            raise BoundaryConditionError(f"distribute must be 'equal' or 'area', got {distribute!r}")
        return BoundaryConditions(self.fixed, self.displacement, self.force.at[idx].add(jnp.asarray(w)[:, None] * total))

    @property
    def free_mask(self) -> np.ndarray:
        """``(N, 3)`` bool, True on unknown displacement components."""
        return ~self.fixed


def rigid_modes(points: np.ndarray) -> np.ndarray:
    """The six rigid-body modes ``(6, N, 3)``: translations x, y, z and rotations about x, y, z
    through the centroid (unit-scaled)."""
    p = np.asarray(points, dtype=float)
    c = p - p.mean(axis=0)
    scale = float(np.abs(c).max()) or 1.0
    modes = np.zeros((6, len(p), 3))
    for a in range(3):
        modes[a, :, a] = 1.0
        axis = np.zeros(3)
        axis[a] = 1.0
        modes[3 + a] = np.cross(axis, c) / scale
    return modes


_MODE_NAMES = ("translation x", "translation y", "translation z", "rotation about x", "rotation about y", "rotation about z")


def check_rigid_modes(points: np.ndarray, fixed: np.ndarray) -> None:
    """Raise :class:`RigidModeError` unless the prescribed components remove all rigid-body modes.

    A static problem with a free rigid mode has no unique solution (the stiffness matrix
    is singular). The check is geometric: the rigid modes restricted to the prescribed
    components must have full rank 6.
    """
    fixed = np.asarray(fixed, dtype=bool)
    modes = rigid_modes(points)[:, fixed]  # (6, n_fixed)
    if modes.shape[1] == 0:
        raise RigidModeError("no displacement is prescribed: all six rigid-body modes are free; fix some nodes (e.g. the base)")
    s = np.linalg.svd(modes.T, compute_uv=False) if modes.shape[1] >= 6 else np.concatenate([np.linalg.svd(modes.T, compute_uv=False), np.zeros(6 - modes.shape[1])])
    tol = 1e-10 * max(float(s.max()), 1.0)
    rank = int(np.sum(s > tol))
    if rank < 6:
        _, _, vt = np.linalg.svd(modes.T)
        free = vt[rank:]
        names = sorted({_MODE_NAMES[int(np.argmax(np.abs(v)))] for v in free})
        raise RigidModeError(
            f"the boundary conditions leave {6 - rank} rigid-body mode(s) free ({', '.join(names)}); "
            "prescribe more displacement components (a static solve would be singular)"
        )


def _validate_values(bc: BoundaryConditions, n_nodes: int) -> None:
    if bc.fixed.shape != (n_nodes, 3):
        raise BoundaryConditionError(f"boundary conditions are for {bc.fixed.shape[0]} nodes, the mesh has {n_nodes}")
    for name in ("displacement", "force"):
        v = getattr(bc, name)
        if not isinstance(v, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(v))):
            raise BoundaryConditionError(f"prescribed {name} contains NaN or infinite values")

