"""What :mod:`telerig.export.view` (episodes) and :mod:`telerig.export.view_dataset` (datasets) share:
the summary of a written ``.rrd`` and the end effector's path by forward kinematics."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from telerig.errors import ExportError

__all__ = ["ViewSummary", "end_effector_path"]

Float64Array = npt.NDArray[np.float64]


@dataclass(slots=True)
class ViewSummary:
    """What :func:`view` wrote.

    Attributes:
        out: The ``.rrd`` file.
        source: Episode id, or the dataset directory.
        entities: Entity path → rows logged on the timeline (static entities count 1).
        video: ``asset`` (the MP4 referenced frame by frame), or ``none`` (no camera recorded).
        notes: What could not be shown, one line each (e.g. a robot without an arm model).
    """

    out: Path
    source: str
    entities: dict[str, int] = field(default_factory=dict)
    video: str = "none"
    notes: list[str] = field(default_factory=list)


def end_effector_path(model_name: str, joint_names: tuple[str, ...], positions: Float64Array) -> Float64Array:
    """End-effector (grasp site) positions [m, robot base frame], one per row of joint ``positions``.

    Args:
        model_name: Arm model, a key of :data:`telerig.robots.models.ARM_MODELS`.
        joint_names: Names of the columns of ``positions`` (bimanual arms prefix them).
        positions: Measured joint positions [rad], shape (T, len(joint_names)).

    Raises:
        ExportError: the model lacks one of its arm joints in ``joint_names``.
        ConfigError: no arm model of that name.
    """
    import mujoco

    from telerig.robots.models.arm import build_arm_kinematics

    kin = build_arm_kinematics(model_name)
    model = kin.model
    data = mujoco.MjData(model)
    columns: list[int] = []
    for joint in kin.arm_joints:
        match = [i for i, n in enumerate(joint_names) if n == joint or n.endswith(("_" + joint, "." + joint))]
        if not match:
            raise ExportError(f"arm model {model_name} has joint {joint}, which the joint states lack")
        columns.append(match[0])
    qpos_adr = [int(model.jnt_qposadr[model.joint(j).id]) for j in kin.arm_joints]
    site = model.site(kin.ee_site).id
    out = np.full((len(positions), 3), np.nan)
    for i, row in enumerate(positions):
        q = row[columns]
        if not np.all(np.isfinite(q)):
            continue
        data.qpos[qpos_adr] = q
        mujoco.mj_kinematics(model, data)
        out[i] = data.site_xpos[site]
    return out
