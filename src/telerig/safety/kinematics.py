"""Forward kinematics of one robot on a private MuJoCo model copy, for configuration checks (sim extra)."""

from __future__ import annotations

import copy
from collections.abc import Sequence

import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import ConfigError
from telerig.ir.types import FloatArray

__all__ = ["KinematicsModel"]

#: Integer index array.
IndexArray = npt.NDArray[np.intp]
_SCALAR_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class KinematicsModel:
    """A private copy of a MuJoCo model and data: set joint positions, read body/site positions.

    The copy is private so checks may tune it (e.g. collision margins) and so each robot's control
    thread owns its data; :meth:`update` runs ``mj_kinematics`` only when the joints changed, so
    several checks of one configuration share one forward-kinematics pass.

    Positions are reported in the frame of ``base_body`` (the robot base frame, where the
    workspace is defined), whatever the model's world frame.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        joints: Sequence[str],
        *,
        base_body: str,
        qpos: FloatArray | None = None,
    ) -> None:
        """Args:
        model: Compiled model of the robot (a kinematic model is enough); it is copied.
        joints: Commanded joints, in driver order (n); hinge or slide joints.
        base_body: Body whose frame the positions are expressed in.
        qpos: Positions of the model's other joints (e.g. fingers) [rad or m]. Shape (nq,);
            ``model.qpos0`` when ``None``.

        Raises:
            ConfigError: a joint or the base body does not exist, or ``qpos`` has the wrong shape.
        """
        self.model = copy.deepcopy(model)
        self.data = mujoco.MjData(self.model)
        m = self.model
        names = [m.joint(i).name for i in range(m.njnt)]
        adr = []
        for joint in joints:
            if joint not in names:
                raise ConfigError(f"joint '{joint}' does not exist. Available: {', '.join(names)}")
            jid = names.index(joint)
            if int(m.jnt_type[jid]) not in (
                int(mujoco.mjtJoint.mjJNT_HINGE),
                int(mujoco.mjtJoint.mjJNT_SLIDE),
            ):
                raise ConfigError(f"joint '{joint}' is not a hinge or slide joint")
            adr.append(int(m.jnt_qposadr[jid]))
        self.joints = tuple(joints)
        self._qadr = np.array(adr, dtype=np.intp)
        self.base_id = self.body_id(base_body)
        if qpos is not None:
            arr = np.asarray(qpos, dtype=np.float64)
            if arr.shape != (m.nq,):
                raise ConfigError(f"qpos must have shape ({m.nq},), got {arr.shape}")
            self.data.qpos[:] = arr
        else:
            self.data.qpos[:] = m.qpos0
        self._q = np.full(len(adr), np.nan)
        self._qkey = b""
        self.evaluations = 0
        mujoco.mj_kinematics(m, self.data)
        # A base welded to the world (no joint above it) has a constant pose: skip the transform
        # when it is the identity, as in kinematic models built at the world origin.
        moving, b = False, self.base_id
        while b > 0:
            moving = moving or int(m.body_jntnum[b]) > 0
            b = int(m.body_parentid[b])
        self._identity = (
            not moving
            and not self.data.xpos[self.base_id].any()
            and bool(np.array_equal(self.data.xmat[self.base_id], np.eye(3).ravel()))
        )

    def body_id(self, name: str) -> int:
        """Id of body ``name``; ``ConfigError`` naming the bodies that exist."""
        m = self.model
        bodies = [m.body(i).name for i in range(m.nbody)]
        if name not in bodies:
            raise ConfigError(f"body '{name}' does not exist. Available: {', '.join(b for b in bodies if b)}")
        return bodies.index(name)

    def point(self, name: str) -> tuple[str, int]:
        """``("site", id)`` or ``("body", id)`` of a site or body called ``name`` (sites first)."""
        m = self.model
        sites = [m.site(i).name for i in range(m.nsite)]
        if name in sites:
            return "site", sites.index(name)
        bodies = [m.body(i).name for i in range(m.nbody)]
        if name in bodies:
            return "body", bodies.index(name)
        raise ConfigError(
            f"site or body '{name}' does not exist. Available sites: {', '.join(s for s in sites if s)}; "
            f"bodies: {', '.join(b for b in bodies if b)}"
        )

    def subtree(self, root: int) -> frozenset[int]:
        """Ids of body ``root`` and all its descendants."""
        parent = self.model.body_parentid
        out = {root}
        for b in range(root + 1, self.model.nbody):  # MuJoCo orders children after parents
            if int(parent[b]) in out:
                out.add(b)
        return frozenset(out)

    def update(self, q: FloatArray) -> bool:
        """Set the commanded joints to ``q`` [rad] (shape (n,)) and run forward kinematics if they changed.

        Returns:
            Whether kinematics ran (False: ``q`` equals the last configuration).
        """
        key = q.tobytes()
        if key == self._qkey:
            return False
        self._qkey = key
        self._q[:] = q
        self.data.qpos[self._qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        self.evaluations += 1
        return True

    def positions(self, sites: IndexArray, bodies: IndexArray, out: FloatArray) -> FloatArray:
        """World positions of ``sites`` then ``bodies`` (id arrays) in the base frame [m]. Shape (k, 3).

        Call :meth:`update` first.
        """
        d = self.data
        ns = len(sites)
        out[:ns] = d.site_xpos[sites]
        out[ns:] = d.xpos[bodies]
        if self._identity:
            return out
        out -= d.xpos[self.base_id]
        # p_base = R^T (p_world - x_base); rows of out are points, so multiply by R on the right.
        np.matmul(out, d.xmat[self.base_id].reshape(3, 3), out=out)
        return out
