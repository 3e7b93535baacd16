"""Task object sets for the simulated scenes: a cube to pick, a cup of balls to pour into a bowl."""

from __future__ import annotations

import mujoco

__all__ = ["add_balls", "add_bowl", "add_cube", "add_cup", "add_zone"]

_VISUAL_GROUP = 2  # the world's geom group (drawn by the cameras)
# Solid contacts for grasped objects: torsional friction (condim 4) so a pinched object does not spin.
_FRICTION = [1.5, 0.01, 0.001]


def add_cube(
    spec: mujoco.MjSpec,
    name: str,
    on: tuple[float, float, float],
    *,
    half: float = 0.02,
    mass: float = 0.05,
    rgba: tuple[float, float, float, float] = (0.85, 0.15, 0.15, 1.0),
) -> str:
    """Add a free cube standing on a surface; returns its body name.

    Args:
        spec: Scene to add to.
        name: Body name (the geom has the same name, the free joint ``<name>_free``).
        on: Point on the supporting surface under the cube's centre (x, y, z) [m], world frame.
        half: Half edge length [m].
        mass: Mass [kg].
        rgba: Colour.
    """
    body = spec.worldbody.add_body(name=name, pos=[on[0], on[1], on[2] + half])
    body.add_freejoint(name=f"{name}_free")
    body.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half] * 3,
        mass=mass,
        rgba=list(rgba),
        group=_VISUAL_GROUP,
        condim=4,
        friction=_FRICTION,
    )
    return name


def add_zone(
    spec: mujoco.MjSpec,
    name: str,
    on: tuple[float, float, float],
    *,
    half: float,
    rgba: tuple[float, float, float, float] = (0.2, 0.7, 0.3, 1.0),
) -> str:
    """Add a fixed square zone marked on a surface (a 1 mm plate without contacts); returns its body name.

    It is drawn by the cameras (where to place an object) and touches nothing.

    Args:
        spec: Scene to add to.
        name: Body name (the geom has the same name).
        on: Point on the surface under the zone's centre (x, y, z) [m], world frame.
        half: Half edge length [m].
        rgba: Colour.
    """
    body = spec.worldbody.add_body(name=name, pos=[on[0], on[1], on[2] + 0.0005])
    body.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half, half, 0.0005],
        rgba=list(rgba),
        group=_VISUAL_GROUP,
        contype=0,
        conaffinity=0,
    )
    return name


def _add_open_box(
    spec: mujoco.MjSpec,
    name: str,
    on: tuple[float, float, float],
    *,
    half_xy: float,
    height: float,
    wall: float,
    mass: float,
    rgba: tuple[float, float, float, float],
) -> str:
    """A free square container open at the top: a floor plate and four walls, origin at its floor centre."""
    body = spec.worldbody.add_body(name=name, pos=list(on))
    body.add_freejoint(name=f"{name}_free")
    # Mass spread over the parts by volume-free share: floor a fifth, each wall a fifth.
    part = mass / 5
    common = {"group": _VISUAL_GROUP, "rgba": list(rgba), "condim": 4, "friction": _FRICTION}
    body.add_geom(
        name=f"{name}_floor",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_xy, half_xy, wall / 2],
        pos=[0, 0, wall / 2],
        mass=part,
        **common,
    )
    inner = half_xy - wall / 2
    for i, (x, y, sx, sy) in enumerate(
        (
            (inner, 0, wall / 2, half_xy),
            (-inner, 0, wall / 2, half_xy),
            (0, inner, half_xy, wall / 2),
            (0, -inner, half_xy, wall / 2),
        )
    ):
        body.add_geom(
            name=f"{name}_wall{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[sx, sy, height / 2],
            pos=[x, y, height / 2],
            mass=part,
            **common,
        )
    return name


def add_cup(spec: mujoco.MjSpec, name: str, on: tuple[float, float, float]) -> str:
    """Add a free 6 x 6 x 9 cm cup (open square container, 60 g) standing on a surface; returns its body name.

    Args:
        spec: Scene to add to.
        name: Body name; geoms ``<name>_floor`` and ``<name>_wall0..3``.
        on: Point on the surface under the cup's floor centre (x, y, z) [m], world frame.
    """
    return _add_open_box(
        spec, name, on, half_xy=0.03, height=0.09, wall=0.004, mass=0.06, rgba=(0.2, 0.45, 0.8, 1.0)
    )


def add_bowl(spec: mujoco.MjSpec, name: str, on: tuple[float, float, float]) -> str:
    """Add a free 16 x 16 x 4 cm bowl (shallow open square tray, 150 g) on a surface; returns its body name.

    Args:
        spec: Scene to add to.
        name: Body name; geoms ``<name>_floor`` and ``<name>_wall0..3``.
        on: Point on the surface under the bowl's floor centre (x, y, z) [m], world frame.
    """
    return _add_open_box(
        spec, name, on, half_xy=0.08, height=0.04, wall=0.005, mass=0.15, rgba=(0.9, 0.9, 0.85, 1.0)
    )


def add_balls(
    spec: mujoco.MjSpec,
    prefix: str,
    cup_floor: tuple[float, float, float],
    *,
    count: int = 8,
    radius: float = 0.009,
) -> tuple[str, ...]:
    """Add free balls stacked in layers of four inside a cup; returns their body names.

    Args:
        spec: Scene to add to.
        prefix: Body names are ``<prefix>0``, ``<prefix>1``, ...
        cup_floor: Top of the cup's floor plate under its centre (x, y, z) [m], world frame.
        count: Number of balls.
        radius: Ball radius [m] (3 g each).
    """
    names = []
    offset = radius * 1.05
    for i in range(count):
        layer, k = divmod(i, 4)
        dx = offset if k in (0, 1) else -offset
        dy = offset if k in (0, 2) else -offset
        z = cup_floor[2] + radius * (1 + 2.1 * layer) + 1e-4
        name = f"{prefix}{i}"
        body = spec.worldbody.add_body(name=name, pos=[cup_floor[0] + dx, cup_floor[1] + dy, z])
        body.add_freejoint(name=f"{name}_free")
        # Rolling friction (condim 6) so a ball on a flat floor comes to rest instead of rolling on.
        body.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[radius, 0, 0],
            mass=0.003,
            rgba=[0.95, 0.75, 0.1, 1.0],
            group=_VISUAL_GROUP,
            condim=6,
            friction=[1.0, 0.005, 0.0005],
        )
        names.append(name)
    return tuple(names)
