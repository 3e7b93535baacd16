"""CPU priorities of a station's threads and processes (``runtime.priorities`` in a rig file).

Data only; :mod:`telerig.priority` applies them (the control loops above everything else that
runs beside them: rendering, encoding, previews, health, uploads, the recorder's writer).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.priority import Priorities

__all__ = ["PriorityConfig"]


class PriorityConfig(BaseModel):
    """How the station's work is ordered on its CPUs.

    Attributes:
        enabled: Apply them (on by default); off leaves every thread at the station's priority.
        control_nice: Niceness of the control threads, -20..0. Below 0 needs root or
            CAP_SYS_NICE; where refused they keep the station's and one warning says so.
        control_realtime: Run the control threads under SCHED_RR at this priority (1..99)
            instead: above every ordinary thread of the host, a loaded one included. Same
            rights needed; where refused ``control_nice`` applies. Off by default.
        work_nice: Niceness of the station's other threads (video encoders, previews, health,
            uploads, the recorder's writer), 0..19.
        work_policy: Their Linux policy: ``batch`` (SCHED_BATCH: never preempts a running thread
            when it wakes) or ``other`` (the default policy). Not ``idle``: they share Python's
            lock with the control loop and must not be starved while holding it.
        render_nice: Niceness of the simulated cameras' render processes, 0..19.
        render_policy: Their policy; ``idle`` (SCHED_IDLE) gives them only CPU time nothing
            else wants (on a loaded host too little: the camera's rate drops).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = True
    control_nice: Annotated[int, Field(ge=-20, le=0)] = -10
    control_realtime: Annotated[int, Field(ge=1, le=99)] | None = None
    work_nice: Annotated[int, Field(ge=0, le=19)] = 10
    work_policy: Literal["other", "batch"] = "batch"
    render_nice: Annotated[int, Field(ge=0, le=19)] = 10
    render_policy: Literal["other", "batch", "idle"] = "batch"

    def priorities(self) -> Priorities:
        """The settings :func:`telerig.priority.configure` takes."""
        return Priorities(**self.model_dump())
