"""Boundary conditions: prescribed displacements (Dirichlet) and nodal forces.

A :class:`BoundaryConditions` is a pytree: the mask of prescribed components is fixed data
(it decides the problem's structure), the prescribed displacements [m] and the nodal forces
[N] are differentiable leaves (so a fit can differentiate with respect to an indentation
depth or a load).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import BoundaryConditionError, RigidModeError, SelectorError
from .selectors import select_nodes, selector_from_dict

__all__ = ["BoundaryConditions", "Roller", "ROLLER_FACES", "apply_rollers", "rigid_modes", "rigid_mode_rank", "pin_free_rigid_modes", "check_rigid_modes"]

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


#: The faces of the mesh's bounding box a roller can name, with the component normal to each.
ROLLER_FACES = {"x-min": "x", "x-max": "x", "y-min": "y", "y-max": "y", "z-min": "z", "z-max": "z"}


@dataclasses.dataclass(frozen=True)
class Roller:
    """A roller (frictionless symmetry) support: the ``components`` of the displacement of the
    selected nodes are held at zero (at their mesh positions); the other components are free
    and carry no force (zero tangential traction).

    On a symmetry plane of the specimen and its loads the roller holds the component normal to
    the plane, e.g. ``Roller("x-min")`` (``u_x = 0`` on the face ``x = min x``): the model is the
    part on one side of the plane and reproduces the whole specimen's solution there.

    Attributes:
        nodes: a bounding-box face name (``"x-min"``, ..., ``"z-max"``; the component defaults to
            the face's normal), a selector table (:mod:`difftissue.selectors`, SI coordinates)
            or the name of a point-data mask of the mesh (nonzero = member).
        components: the held components, letters from ``"xyz"`` (required unless ``nodes`` is a
            face name).
    """

    nodes: Any
    components: str = ""

    def __post_init__(self):
        nodes, comps = self.nodes, self.components
        if isinstance(nodes, str) and nodes in ROLLER_FACES:
            comps = comps or ROLLER_FACES[nodes]
        elif isinstance(nodes, dict):
            try:
                selector_from_dict(nodes)
            except SelectorError as err:
                raise BoundaryConditionError(f"roller nodes: {err}") from None
        elif not (isinstance(nodes, str) and nodes.strip()) and not hasattr(nodes, "mask"):
            raise BoundaryConditionError(f"roller nodes must be a face name ({', '.join(ROLLER_FACES)}), a selector table or a point-data mask name, got {nodes!r}")
        if not comps:
            raise BoundaryConditionError(f"a roller on {self.describe_nodes()} needs components (letters from 'xyz': the held displacement components)")
        if not isinstance(comps, str) or any(c not in _COMPONENTS for c in comps) or len(set(comps)) != len(comps):
            raise BoundaryConditionError(f"roller components must be distinct letters from 'xyz', got {comps!r}")
        if len(comps) == 3:
            raise BoundaryConditionError(f"a roller holding all of x, y, z on {self.describe_nodes()} is a clamp, not a roller: leave one component free")
        object.__setattr__(self, "components", "".join(sorted(comps)))

    @classmethod
    def from_spec(cls, spec) -> "Roller":
        """A roller from its data form: a face name ``"x-min"`` or a table
        ``{"set": selector-or-mask-name, "components": "x"}``."""
        if isinstance(spec, Roller):
            return spec
        if isinstance(spec, str):
            if spec not in ROLLER_FACES:
                raise BoundaryConditionError(f"a roller given by name must be a face of the bounding box ({', '.join(ROLLER_FACES)}), got {spec!r}")
            return cls(spec)
        if isinstance(spec, dict):
            unknown = set(spec) - {"set", "components"}
            if unknown or "set" not in spec:
                raise BoundaryConditionError(f"a roller table needs 'set' (a selector or mask name) and 'components'; got keys {sorted(spec)}")
            return cls(spec["set"], spec.get("components", ""))
        raise BoundaryConditionError(f"a roller must be a face name such as 'x-min' or a table {{set = ..., components = 'x'}}, got {spec!r}")

    def describe_nodes(self) -> str:
        n = self.nodes
        if isinstance(n, str):
            return f"face {n}" if n in ROLLER_FACES else f"node set {n!r}"
        return f"selector {n.to_dict() if hasattr(n, 'to_dict') else n}"

    def node_indices(self, mesh) -> np.ndarray:
        """The selected nodes of ``mesh`` (sorted indices)."""
        n = self.nodes
        if isinstance(n, str) and n in ROLLER_FACES:
            return select_nodes(mesh, {"face": n})
        if isinstance(n, str):
            data = getattr(mesh, "point_data", {}) or {}
            if n not in data:
                raise BoundaryConditionError(f"roller: {n!r} is not a point-data node set of the mesh (point fields: {sorted(data)})")
            idx = np.flatnonzero(np.asarray(data[n]).reshape(len(np.asarray(mesh.points)), -1)[:, 0] != 0)
            if idx.size == 0:
                raise BoundaryConditionError(f"roller: node set {n!r} is empty")
            return idx
        return select_nodes(mesh, n)

    def to_spec(self):
        """The data form (see :meth:`from_spec`)."""
        if isinstance(self.nodes, str) and self.nodes in ROLLER_FACES and self.components == ROLLER_FACES[self.nodes]:
            return self.nodes
        nodes = self.nodes.to_dict() if hasattr(self.nodes, "to_dict") else self.nodes
        return {"set": nodes, "components": self.components}


def apply_rollers(bc: BoundaryConditions, mesh, rollers: Sequence, *, loaded: np.ndarray | None = None, what: str = "rollers") -> BoundaryConditions:
    """``bc`` with roller supports added (see :class:`Roller`): the listed components held at zero.

    Args:
        bc: the other boundary conditions of ``mesh``.
        rollers: :class:`Roller` objects or their data forms (:meth:`Roller.from_spec`).
        loaded: ``(N, 3)`` bool, the components a load is prescribed on (a platen, a punch, the
            contact surface); a roller on any of them is refused.
        what: the name used in error messages (e.g. the config key).

    Raises:
        BoundaryConditionError: a roller that selects no node, touches a loaded component, or
            holds nothing new (every component it selects is already prescribed: it would have
            no effect).
    """
    if isinstance(rollers, (str, dict, Roller)):
        raise BoundaryConditionError(f"{what} must be a list of rollers, got {rollers!r}")
    for i, spec in enumerate(rollers):
        try:
            r = Roller.from_spec(spec)
            idx = r.node_indices(mesh)
        except (BoundaryConditionError, SelectorError) as err:
            raise BoundaryConditionError(f"{what}[{i}]: {err}") from None
        comps = _components(r.components)
        sel = np.zeros(bc.fixed.shape, dtype=bool)
        sel[idx[:, None], np.asarray(comps)[None, :]] = True
        if loaded is not None and np.any(sel & np.asarray(loaded, dtype=bool)):
            raise BoundaryConditionError(f"{what}[{i}]: the roller on {r.describe_nodes()} holds {r.components} where the load is applied (a platen, punch or contact surface); hold other faces")
        if not np.any(sel & ~bc.fixed):
            raise BoundaryConditionError(f"{what}[{i}]: the roller on {r.describe_nodes()} has no effect: the components {r.components} of its nodes are already prescribed by the other boundary conditions")
        bc = bc.fix(mesh, idx, r.components, (0.0, 0.0, 0.0))
    return bc


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


def rigid_mode_rank(points: np.ndarray, fixed: np.ndarray) -> int:
    """How many of the six rigid-body modes the prescribed components ``fixed`` ``(N, 3)``
    remove (6: none is left free)."""
    modes = rigid_modes(points)[:, np.asarray(fixed, dtype=bool)]
    if modes.shape[1] == 0:
        return 0
    s = np.linalg.svd(modes.T, compute_uv=False)
    return int(np.sum(s > 1e-10 * max(float(s.max()), 1.0)))


def pin_free_rigid_modes(mesh, bc: BoundaryConditions, candidates: Sequence[tuple[int, str]]) -> BoundaryConditions:
    """``bc`` with the rigid-body modes it leaves free removed by pinning single components.

    ``candidates`` are ``(node, component)`` pairs tried in order; each is prescribed (at zero
    displacement) only when it removes a mode still free. A pin that removes a free
    translation carries no force when the loads have no net component along it (a free
    rotation: no net moment), so the solution is that of the unpinned problem.
    """
    points = np.asarray(mesh.points)
    rank = rigid_mode_rank(points, bc.fixed)
    for node, comp in candidates:
        if rank == 6:
            break
        trial = bc.fixed.copy()
        trial[int(node), _COMPONENTS[comp]] = True
        r = rigid_mode_rank(points, trial)
        if r > rank:
            bc, rank = bc.fix(mesh, np.array([int(node)]), comp), r
    return bc


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

