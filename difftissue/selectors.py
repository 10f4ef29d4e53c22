"""Node sets described as data: a face of the bounding box, a box, a ball, or a union.

Selectors are frozen dataclasses, so boundary conditions in a config file are plain data
(``{"face": "z-min"}``, ``{"box": {"lower": [...], "upper": [...]}}``), never code that is
evaluated. Coordinates are in metres, like the mesh.
"""

from __future__ import annotations

import dataclasses
from typing import Literal, Union

import numpy as np

from .errors import SelectorError

__all__ = ["BoundingBoxFace", "Box", "Ball", "AnyOf", "Selector", "select_nodes", "selector_from_dict"]

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclasses.dataclass(frozen=True)
class BoundingBoxFace:
    """Nodes on one face of the mesh's axis-aligned bounding box.

    Attributes:
        axis: ``"x"``, ``"y"`` or ``"z"``.
        side: ``"min"`` or ``"max"``.
        tolerance: distance from the face, relative to the bounding-box diagonal, within
            which a node counts as on it.
    """

    axis: Literal["x", "y", "z"]
    side: Literal["min", "max"]
    tolerance: float = 1e-6

    def __post_init__(self):
        if self.axis not in _AXES:
            raise SelectorError(f"face axis must be one of 'x', 'y', 'z', got {self.axis!r}")
        if self.side not in ("min", "max"):
            raise SelectorError(f"face side must be 'min' or 'max', got {self.side!r}")
        if not self.tolerance >= 0:
            raise SelectorError(f"face tolerance must be >= 0, got {self.tolerance!r}")

    def mask(self, points: np.ndarray) -> np.ndarray:
        a = _AXES[self.axis]
        lo, hi = points.min(axis=0), points.max(axis=0)
        tol = self.tolerance * float(np.linalg.norm(hi - lo))
        target = lo[a] if self.side == "min" else hi[a]
        return np.abs(points[:, a] - target) <= tol

    def to_dict(self) -> dict:
        return {"face": f"{self.axis}-{self.side}", "tolerance": self.tolerance}


@dataclasses.dataclass(frozen=True)
class Box:
    """Nodes inside the closed axis-aligned box ``lower <= x <= upper`` [m]."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self):
        lo, hi = _vec3(self.lower, "box lower"), _vec3(self.upper, "box upper")
        if np.any(hi < lo):
            raise SelectorError(f"box upper {tuple(hi)} is below lower {tuple(lo)} in some axis")
        object.__setattr__(self, "lower", tuple(float(v) for v in lo))
        object.__setattr__(self, "upper", tuple(float(v) for v in hi))

    def mask(self, points: np.ndarray) -> np.ndarray:
        return np.all((points >= np.asarray(self.lower)) & (points <= np.asarray(self.upper)), axis=1)

    def to_dict(self) -> dict:
        return {"box": {"lower": list(self.lower), "upper": list(self.upper)}}


@dataclasses.dataclass(frozen=True)
class Ball:
    """Nodes within ``radius`` [m] of ``center`` [m] (closed ball)."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self):
        c = _vec3(self.center, "ball center")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise SelectorError(f"ball radius must be a positive number of metres, got {self.radius!r}")
        object.__setattr__(self, "center", tuple(float(v) for v in c))
        object.__setattr__(self, "radius", float(self.radius))

    def mask(self, points: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - np.asarray(self.center), axis=1) <= self.radius

    def to_dict(self) -> dict:
        return {"ball": {"center": list(self.center), "radius": self.radius}}


@dataclasses.dataclass(frozen=True)
class AnyOf:
    """Nodes selected by any of ``parts`` (union)."""

    parts: tuple["Selector", ...]

    def __post_init__(self):
        if not self.parts:
            raise SelectorError("AnyOf needs at least one selector")
        object.__setattr__(self, "parts", tuple(self.parts))

    def mask(self, points: np.ndarray) -> np.ndarray:
        out = np.zeros(len(points), dtype=bool)
        for p in self.parts:
            out |= p.mask(points)
        return out

    def to_dict(self) -> dict:
        return {"any_of": [p.to_dict() for p in self.parts]}


Selector = Union[BoundingBoxFace, Box, Ball, AnyOf]


def _vec3(v, what: str) -> np.ndarray:
    try:
        arr = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise SelectorError(f"{what} must be three numbers (metres), got {v!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SelectorError(f"{what} must be three finite numbers (metres), got {v!r}")
    return arr


def select_nodes(mesh_or_points, selector: Selector, *, allow_empty: bool = False) -> np.ndarray:
    """Sorted indices of the nodes a selector picks.

    Args:
        mesh_or_points: a :class:`~difftissue.mesh.TetMesh` or an ``(N, 3)`` array [m].
        selector: a selector, or its dictionary form (see :func:`selector_from_dict`).
        allow_empty: return an empty array instead of raising when nothing is selected.
    """
    points = np.asarray(getattr(mesh_or_points, "points", mesh_or_points), dtype=float)
    if isinstance(selector, dict):
        selector = selector_from_dict(selector)
    if not hasattr(selector, "mask"):
        raise SelectorError(f"not a node selector: {selector!r}")
    idx = np.flatnonzero(selector.mask(points))
    if idx.size == 0 and not allow_empty:
        raise SelectorError(f"selector {selector.to_dict()} selects no node of the mesh")
    return idx


def selector_from_dict(data: dict) -> Selector:
    """Build a selector from its data form.

    Forms (lengths in metres)::

        {"face": "z-min"}                       # or {"face": "z-min", "tolerance": 1e-6}
        {"box": {"lower": [x, y, z], "upper": [x, y, z]}}
        {"ball": {"center": [x, y, z], "radius": r}}
        {"any_of": [selector, selector, ...]}
    """
    if not isinstance(data, dict) or not data:
        raise SelectorError(f"a selector must be a table such as {{face = 'z-min'}}, got {data!r}")
    kinds = [k for k in ("face", "box", "ball", "any_of") if k in data]
    if len(kinds) != 1:
        raise SelectorError(f"a selector needs exactly one of 'face', 'box', 'ball', 'any_of'; got keys {sorted(data)}")
    kind = kinds[0]
    extra = set(data) - {kind} - ({"tolerance"} if kind == "face" else set())
    if extra:
        raise SelectorError(f"unknown selector key(s) {sorted(extra)} in {data!r}")
    body = data[kind]
    if kind == "face":
        if not isinstance(body, str) or "-" not in body:
            raise SelectorError(f"face must be written like 'z-min' or 'x-max', got {body!r}")
        axis, side = body.split("-", 1)
        return BoundingBoxFace(axis, side, float(data.get("tolerance", 1e-6)))  # type: ignore[arg-type]
    if kind == "any_of":
        if not isinstance(body, (list, tuple)):
            raise SelectorError(f"any_of must be a list of selectors, got {body!r}")
        return AnyOf(tuple(selector_from_dict(b) for b in body))
    if not isinstance(body, dict):
        raise SelectorError(f"{kind} must be a table, got {body!r}")
    keys = {"box": ("lower", "upper"), "ball": ("center", "radius")}[kind]
    missing = [k for k in keys if k not in body]
    unknown = set(body) - set(keys)
    if missing or unknown:
        raise SelectorError(f"{kind} needs keys {list(keys)}; missing {missing}, unknown {sorted(unknown)}")
    return Box(body["lower"], body["upper"]) if kind == "box" else Ball(body["center"], body["radius"])
