"""Dataset export defaults of a rig file (``export:``): the rate and resampling its episodes export with.

Data only; :mod:`telerig.export` resamples with them. ``telerig export --rig RIG`` reads them and
its own options override them (``--fps``, ``--resample STREAM=POLICY``, ``--normalize``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

__all__ = ["ExportDefaults", "ResamplePolicy"]

#: How a stream's value at a dataset frame is chosen (see :mod:`telerig.record.align`).
ResamplePolicy = Literal["nearest", "linear", "zoh"]
_StreamName = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_]{0,63}$")]


class ExportDefaults(BaseModel):
    """How this rig's episodes become dataset frames.

    Attributes:
        fps: Dataset rate [Hz]; ``None`` takes the anchor camera's configured rate (30 Hz without a
            camera).
        resample: Stream name (``joint_state``, ``gripper_command_sent``...) → policy, over the
            built-in defaults (measured streams ``linear``, sent commands ``zoh``).
        normalize: Map state and action to [-1, 1] from the robots' limits.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    fps: int | None = Field(default=None, gt=0, le=1000)
    resample: dict[_StreamName, ResamplePolicy] = Field(default_factory=dict, max_length=64)
    normalize: bool = False
