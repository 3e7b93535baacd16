"""Workspace bounds: listed bodies/sites stay inside a box and outside keep-out zones (robot base frame)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray
from telerig.safety.guard import Violation

if TYPE_CHECKING:
    from telerig.safety.kinematics import KinematicsModel

__all__ = ["Box", "Sphere", "WorkspaceBounds", "Zone"]


def _vec3(values: Sequence[float] | FloatArray, what: str) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ConfigError(f"{what} must be 3 finite values [m], got {values}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, slots=True, init=False)
class Box:
    """An axis-aligned box in the robot base frame.

    Attributes:
        lower: Minimum corner (x, y, z) [m]. Shape (3,).
        upper: Maximum corner [m]. Shape (3,).
        name: Name used in events.
    """

    lower: FloatArray
    upper: FloatArray
    name: str

    def __init__(
        self, lower: Sequence[float] | FloatArray, upper: Sequence[float] | FloatArray, name: str = "box"
    ) -> None:
        lo, hi = _vec3(lower, f"box '{name}' lower"), _vec3(upper, f"box '{name}' upper")
        if (lo >= hi).any():
            raise ConfigError(
                f"box '{name}': lower {lo.tolist()} must be below upper {hi.tolist()} on every axis"
            )
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "name", name)

    def outside(self, points: FloatArray) -> FloatArray:
        """Distance of each point outside the box [m] (0 inside). ``points`` shape (k, 3) → (k,)."""
        excess = np.maximum(self.lower - points, points - self.upper)
        np.maximum(excess, 0.0, out=excess)
        dist: FloatArray = np.sqrt((excess * excess).sum(axis=1))
        return dist

    def inside(self, points: FloatArray) -> FloatArray:
        """Depth of each point inside the box [m] (distance to the nearest face; 0 outside). (k,)."""
        depth: FloatArray = np.maximum(np.minimum(points - self.lower, self.upper - points).min(axis=1), 0.0)
        return depth


@dataclass(frozen=True, slots=True, init=False)
class Sphere:
    """A sphere in the robot base frame.

    Attributes:
        center: Center (x, y, z) [m]. Shape (3,).
        radius: Radius [m] (> 0).
        name: Name used in events.
    """

    center: FloatArray
    radius: float
    name: str

    def __init__(self, center: Sequence[float] | FloatArray, radius: float, name: str = "sphere") -> None:
        if not (math.isfinite(radius) and radius > 0.0):
            raise ConfigError(f"sphere '{name}': radius must be > 0 m, got {radius}")
        object.__setattr__(self, "center", _vec3(center, f"sphere '{name}' center"))
        object.__setattr__(self, "radius", float(radius))
        object.__setattr__(self, "name", name)

    def inside(self, points: FloatArray) -> FloatArray:
        """Depth of each point inside the sphere [m] (0 outside). ``points`` shape (k, 3) → (k,)."""
        d = points - self.center
        depth: FloatArray = np.maximum(self.radius - np.sqrt((d * d).sum(axis=1)), 0.0)
        return depth


#: A keep-out zone.
Zone = Box | Sphere


class WorkspaceBounds:
    """Forbids configurations that put a listed site/body outside ``box`` or inside a keep-out zone.

    Points are site or body origins (no geometry): list the tool point and, for a long tool or a
    wrist that could enter a zone, more sites or bodies, and use ``margin_m`` for their size.
    Evaluated by forward kinematics on the commanded joints; use it through a
    :class:`~telerig.safety.ConfigurationGuard`.
    """

    __slots__ = (
        "_body_ids",
        "_box_t",
        "_buf",
        "_cache_q",
        "_cache_v",
        "_inner",
        "_site_ids",
        "_zones",
        "_zones_t",
        "box",
        "keep_out",
        "kin",
        "margin_m",
        "names",
    )

    def __init__(
        self,
        kinematics: KinematicsModel,
        points: Sequence[str],
        *,
        box: Box | None = None,
        keep_out: Sequence[Zone] = (),
        margin_m: float = 0.0,
    ) -> None:
        """Args:
        kinematics: The robot's kinematics (may be shared with other checks).
        points: Names of sites or bodies to keep in bounds (e.g. the end-effector site).
        box: Allowed box; ``None`` for no box (keep-out zones only).
        keep_out: Forbidden boxes and spheres.
        margin_m: Clearance kept from every box face and zone surface [m] (>= 0): the box shrinks
            and the zones grow by it.

        Raises:
            ConfigError: no points or bounds, an unknown point, a bad margin, a box the margin empties.
        """
        if not points:
            raise ConfigError("workspace bounds need at least one site or body in points")
        if box is None and not keep_out:
            raise ConfigError("workspace bounds need a box or at least one keep-out zone")
        if not (math.isfinite(margin_m) and margin_m >= 0.0):
            raise ConfigError(f"workspace margin_m must be a finite value >= 0 m, got {margin_m}")
        if box is not None and (box.upper - box.lower <= 2 * margin_m).any():
            raise ConfigError(f"workspace box '{box.name}' is not larger than twice the margin {margin_m} m")
        self.kin = kinematics
        self.names = tuple(points)
        resolved = [kinematics.point(p) for p in points]
        self._site_ids = np.array([i for kind, i in resolved if kind == "site"], dtype=np.intp)
        self._body_ids = np.array([i for kind, i in resolved if kind == "body"], dtype=np.intp)
        # positions() returns sites first, then bodies: keep the names in that order.
        self.names = tuple(p for p, (k, _) in zip(points, resolved, strict=True) if k == "site") + tuple(
            p for p, (k, _) in zip(points, resolved, strict=True) if k == "body"
        )
        self.box = box
        self.keep_out = tuple(keep_out)
        self.margin_m = m = float(margin_m)
        self._inner = None if box is None else Box(box.lower + m, box.upper - m, box.name)
        self._zones = tuple(_grown(z, m) for z in self.keep_out)
        self._box_t = (
            ((0.0,) * 3, (0.0,) * 3)
            if self._inner is None
            else (tuple(self._inner.lower.tolist()), tuple(self._inner.upper.tolist()))
        )
        self._zones_t = tuple(
            (z, tuple(z.lower.tolist()), tuple(z.upper.tolist()))
            if isinstance(z, Box)
            else (z, tuple(z.center.tolist()), (z.radius, 0.0, 0.0))
            for z in self._zones
        )
        self._buf = np.zeros((len(points), 3))
        self._cache_q = b""
        self._cache_v: Violation | None = None

    def points(self, q: FloatArray) -> FloatArray:
        """Positions of the listed points at joints ``q`` [rad], base frame [m]. Shape (k, 3); a view."""
        self.kin.update(q)
        return self.kin.positions(self._site_ids, self._body_ids, self._buf)

    def violation(self, q: FloatArray) -> Violation | None:
        """The deepest breach at joints ``q`` [rad] (shape (n,)), or ``None``."""
        key = q.tobytes()
        if key == self._cache_q:
            return self._cache_v
        # Plain floats: with a few points this is several times faster than numpy on (k, 3) arrays.
        points = self.points(q).tolist()
        worst, what = 0.0, ""
        if self._inner is not None:
            lo, hi = self._box_t
            for i, p in enumerate(points):
                total = 0.0
                for a in range(3):
                    e = max(lo[a] - p[a], p[a] - hi[a])
                    if e > 0.0:
                        total += e * e
                if total > worst * worst:
                    worst = math.sqrt(total)
                    what = (
                        f"'{self.names[i]}' at {_fmt(p)} m is {worst * 100:.1f} cm outside the workspace "
                        f"box '{self._inner.name}'"
                    )
        for zone, a_, b_ in self._zones_t:
            for i, p in enumerate(points):
                if isinstance(zone, Box):
                    depth = min(min(p[a] - a_[a], b_[a] - p[a]) for a in range(3))
                else:
                    dx, dy, dz = p[0] - a_[0], p[1] - a_[1], p[2] - a_[2]
                    depth = b_[0] - math.sqrt(dx * dx + dy * dy + dz * dz)
                if depth > worst:
                    worst = depth
                    what = (
                        f"'{self.names[i]}' at {_fmt(p)} m is {worst * 100:.1f} cm inside keep-out zone "
                        f"'{zone.name}'"
                    )
        self._cache_q = key
        self._cache_v = (
            None
            if worst == 0.0
            else Violation(
                "workspace",
                worst,
                what,
                "move the operator's hand back towards the workspace; the robot holds its last safe pose",
            )
        )
        return self._cache_v


def _grown(zone: Zone, m: float) -> Zone:
    if isinstance(zone, Box):
        return Box(zone.lower - m, zone.upper + m, zone.name)
    return Sphere(zone.center, zone.radius + m, zone.name)


def _fmt(p: Sequence[float]) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in p) + ")"
