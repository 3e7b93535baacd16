"""Self-collision check on the model's collision geometry by MuJoCo collision detection (sim extra)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray
from telerig.safety.guard import Violation
from telerig.safety.kinematics import KinematicsModel

__all__ = ["SelfCollision"]


class SelfCollision:
    """Forbids configurations where two bodies of the robot touch (or come closer than ``margin_m``).

    Uses the model's collision geoms (``contype``/``conaffinity``, ``<exclude>`` and MuJoCo's
    parent/child filtering apply), on the private model of ``kinematics``: geoms outside the
    robot's subtree are switched off there, so only robot-robot contacts are found (keep the
    environment out with workspace keep-out zones). Body pairs already in contact in any of the
    ``allowed`` configurations (e.g. home, where some links' meshes overlap by design) and the
    ``ignore`` pairs are never reported.
    """

    __slots__ = ("_allowed", "_body_of_geom", "_cache_q", "_cache_v", "kin", "margin_m", "pairs_allowed")

    def __init__(
        self,
        kinematics: KinematicsModel,
        *,
        allowed: Sequence[FloatArray] = (),
        ignore: Sequence[tuple[str, str]] = (),
        margin_m: float = 0.0,
        root_body: str | None = None,
    ) -> None:
        """Args:
        kinematics: The robot's kinematics (may be shared with other checks; its private model's
            geom margins and collision masks are changed here).
        allowed: Joint configurations [rad] (each shape (n,)) whose contacts are accepted, e.g.
            the home pose.
        ignore: Body name pairs never to report.
        margin_m: Report pairs closer than this [m] (>= 0), not only touching ones.
        root_body: Root of the robot's bodies; the kinematics' base body when ``None``.

        Raises:
            ConfigError: a bad margin, an unknown body, or an allowed configuration of the wrong shape.
        """
        if not (math.isfinite(margin_m) and margin_m >= 0.0):
            raise ConfigError(f"self-collision margin_m must be a finite value >= 0 m, got {margin_m}")
        self.kin = kinematics
        self.margin_m = float(margin_m)
        m = kinematics.model
        root = kinematics.base_id if root_body is None else kinematics.body_id(root_body)
        robot = kinematics.subtree(root)
        in_robot = np.array([int(b) in robot for b in m.geom_bodyid])
        m.geom_contype[~in_robot] = 0
        m.geom_conaffinity[~in_robot] = 0
        colliding = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        m.geom_margin[colliding] = self.margin_m
        self._body_of_geom = m.geom_bodyid.astype(np.intp)
        allowed_pairs = np.zeros((m.nbody, m.nbody), dtype=bool)
        for first, second in ignore:
            a, b = kinematics.body_id(first), kinematics.body_id(second)
            allowed_pairs[a, b] = allowed_pairs[b, a] = True
        n = len(kinematics.joints)
        for q in allowed:
            arr = np.asarray(q, dtype=np.float64)
            if arr.shape != (n,):
                raise ConfigError(f"allowed configurations must have shape ({n},), got {arr.shape}")
            for a, b, _ in self._contacts(arr):
                allowed_pairs[a, b] = allowed_pairs[b, a] = True
        self._allowed = allowed_pairs
        self._mask_allowed_pairs(colliding)
        self.pairs_allowed = tuple(
            (m.body(a).name, m.body(b).name) for a, b in zip(*np.nonzero(np.triu(allowed_pairs)), strict=True)
        )
        self._cache_q = b""
        self._cache_v: Violation | None = None

    def _mask_allowed_pairs(self, colliding: npt.NDArray[np.bool_]) -> None:
        """Switch the allowed body pairs off in MuJoCo itself, so its narrow phase skips them.

        Each body with collision geoms gets one bit: ``contype`` = its bit, ``conaffinity`` =
        the bits of the bodies it may still touch (pairs the original masks enabled, minus the
        allowed ones). Needs at most 32 such bodies; beyond that the allowed pairs are only
        filtered after detection, which is slower but equivalent.
        """
        m = self.kin.model
        bodies = sorted({int(b) for b in self._body_of_geom[colliding]})
        if len(bodies) > 32:
            return
        bit = {b: i for i, b in enumerate(bodies)}
        geoms = np.nonzero(colliding)[0]
        ctype, caff = m.geom_contype.copy(), m.geom_conaffinity.copy()
        enabled = np.zeros((m.nbody, m.nbody), dtype=bool)
        for g in geoms:
            for h in geoms:
                if (ctype[g] & caff[h]) or (ctype[h] & caff[g]):
                    enabled[self._body_of_geom[g], self._body_of_geom[h]] = True
        enabled &= ~self._allowed
        affinity = dict.fromkeys(bodies, 0)
        for a in bodies:
            for b in bodies:
                if a != b and enabled[a, b]:
                    affinity[a] |= 1 << bit[b]
        for g in geoms:
            b = int(self._body_of_geom[g])
            # Stored as int32 by MuJoCo: bit 31 must wrap to a negative value.
            m.geom_contype[g] = np.int32(np.uint32(1 << bit[b]).view(np.int32))
            m.geom_conaffinity[g] = np.int32(np.uint32(affinity[b]).view(np.int32))

    def _contacts(self, q: FloatArray) -> list[tuple[int, int, float]]:
        """(body1, body2, distance [m]) of every contact at joints ``q``."""
        kin = self.kin
        kin.update(q)
        mujoco.mj_collision(kin.model, kin.data)
        con = kin.data.contact
        g = self._body_of_geom
        return [
            (int(g[a]), int(g[b]), float(d)) for a, b, d in zip(con.geom1, con.geom2, con.dist, strict=True)
        ]

    def violation(self, q: FloatArray) -> Violation | None:
        """The deepest forbidden contact at joints ``q`` [rad] (shape (n,)), or ``None``."""
        key = q.tobytes()
        if key == self._cache_q:
            return self._cache_v
        kin = self.kin
        kin.update(q)
        mujoco.mj_collision(kin.model, kin.data)
        found: Violation | None = None
        if kin.data.ncon:
            con = kin.data.contact
            g = self._body_of_geom
            b1, b2 = g[con.geom1], g[con.geom2]
            bad = ~self._allowed[b1, b2]
            if bad.any():
                depth = self.margin_m - con.dist[bad]
                i = int(np.argmax(depth))
                a, b, dist = int(b1[bad][i]), int(b2[bad][i]), float(con.dist[bad][i])
                m = kin.model
                gap = f"penetrate by {-dist * 1000:.1f} mm" if dist < 0 else f"are {dist * 1000:.1f} mm apart"
                found = Violation(
                    "self_collision",
                    max(float(depth[i]), 1e-9),
                    f"links '{m.body(a).name}' and '{m.body(b).name}' {gap} "
                    f"(margin {self.margin_m * 1000:.0f} mm)",
                    "move the operator's arm so the robot does not fold onto itself",
                )
        self._cache_q = key
        self._cache_v = found
        return found
