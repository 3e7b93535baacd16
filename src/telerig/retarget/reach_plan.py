"""Plan, preview, execute: a mobile reach the operator designates, sees, and then confirms (issue 17).

:class:`ReachPlanAid` is a live :class:`~telerig.retarget.binding.Aid` of a whole-body robot
(stream ``plan``, retained JSON; text commands on ``plan_command``):

* ``target X Y Z [QW QX QY QZ]`` designates a target in text (world frame [m]);
* ``plan`` ("plan here") plans a reach to the designated target, else to the operator's **plan
  marker** (:class:`PlanMarker`: the latest pose of a device part, e.g. a VR controller, mapped
  into the robot's world frame by an :class:`~telerig.retarget.alignment.Alignment`) when one is
  configured; ``plan X Y Z [QW QX QY QZ]`` plans to the given one (orientation omitted: the
  hand's current one). With a marker, a text designation is used by the next ``plan`` only (the
  marker is the standing designation); a marker pose older than its ``max_age_s`` is refused.
  Planning runs on a worker thread, never on the control tick:
  :class:`~telerig.retarget.mobile_reach.MobileReachPlanner` (1-15 ms) plus a kinematic dry run of
  the execution (the same executor and controller) whose samples are the preview paths of the
  base and the grasp point. The plan is then ``staged``;
* ``execute ID`` runs the staged plan ``ID`` (what the voice dispatcher sends after ``robot please
  execute``); refused with a one-line reason when ``ID`` is not the staged plan, the plan is older
  than ``max_age_s``, or the robot moved from the configuration it was planned from;
* ``cancel`` drops a staged plan or stops an executing one (the controller brakes within its
  acceleration limits).

While a plan executes, :meth:`ReachPlanAid.action` gives the whole-body controller's action
instead of the operator's input (:class:`~telerig.retarget.whole_body.WholeBodyRetargeter` asks
it every tick), so the commands still pass the robot's safety chain like any other. A robot held
by the chain (e-stop, watchdog) does not move; an execution that makes no progress for
``stall_s`` or outlasts ``max_execute_s`` fails, so a released e-stop never resumes an old plan.
"""

from __future__ import annotations

import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np
from pydantic import JsonValue

from telerig.ir.frames import quat_normalize
from telerig.ir.types import ControllerState, FloatArray, Pose, Sample, now_ns
from telerig.retarget.alignment import Alignment
from telerig.retarget.mobile_reach import MobileReachExecutor, MobileReachPlan, MobileReachPlanner
from telerig.retarget.wbc import EE_MODE, WholeBodyController

__all__ = ["MAX_PREVIEW_POINTS", "PlanMarker", "PlanStatus", "ReachPlanAid"]

PlanStatus = Literal["none", "planning", "staged", "executing", "done", "cancelled", "failed"]
#: Most samples of each preview path sent to the scene.
MAX_PREVIEW_POINTS = 64
#: Largest target distance from the world origin accepted [m] (a lab, not a city).
MAX_TARGET_M = 50.0
#: Largest raw marker coordinate accepted [m] (operator frame; larger is a broken tracker).
MAX_MARKER_M = 1e3
_MAX_WORDS = 8
_NB = 3


def _floats(words: list[str], what: str) -> FloatArray:
    if len(words) not in (3, 7):
        raise ValueError(f"{what} needs X Y Z [m] and optionally QW QX QY QZ, got {len(words)} numbers")
    try:
        values = np.array([float(w) for w in words], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{what} takes numbers, got {' '.join(words)[:80]!r}") from None
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{what} must be finite, got {' '.join(words)[:80]!r}")
    if float(np.max(np.abs(values[:3]))) > MAX_TARGET_M:
        raise ValueError(f"{what} is more than {MAX_TARGET_M:g} m from the origin")
    if len(values) == 7 and not 1e-6 < float(np.max(np.abs(values[3:]))) < 1e6:
        raise ValueError(f"{what} orientation must be a non-zero quaternion (w, x, y, z)")
    return values


def _r(values: FloatArray, digits: int = 4) -> list[JsonValue]:
    return [round(float(v), digits) for v in values]


class PlanMarker:
    """The operator's plan marker: the latest pose of one device part, as a target in the robot's world.

    The control node hands it each fresh sample of the marker's stream (:meth:`take`: a type and
    finiteness check and one attribute store on the control tick, nothing else); the alignment is
    applied only when a plan is asked for (:meth:`target`). Dropped samples are counted by reason
    in :attr:`counts`: ``wrong_type`` (not a ``ControllerState`` or ``Pose``), ``non_finite``,
    ``out_of_range`` (a coordinate beyond :data:`MAX_MARKER_M`, or a zero quaternion).

    Args:
        name: The marker's device part, ``device.part`` (for messages).
        alignment: Operator frame → robot world frame (the same class the arm retargeters use).
        max_age_s: A marker pose older than this (capture time, rig clock) is stale [s], > 0.
        orientation: Plan the marker's orientation too; False: the hand keeps its current one
            (a pointing device rarely holds the grasp orientation the operator wants).
        clock_ns: The rig's common clock [ns] (tests inject one).
    """

    __slots__ = ("_clock_ns", "_latest", "alignment", "counts", "max_age_s", "name", "orientation")

    def __init__(
        self,
        name: str,
        alignment: Alignment,
        *,
        max_age_s: float = 0.5,
        orientation: bool = False,
        clock_ns: Callable[[], int] = now_ns,
    ) -> None:
        if not (math.isfinite(max_age_s) and max_age_s > 0):
            raise ValueError(f"max_age_s must be > 0, got {max_age_s}")
        self.name = name
        self.alignment = alignment
        self.max_age_s = float(max_age_s)
        self.orientation = orientation
        self._clock_ns = clock_ns
        self._latest: ControllerState | Pose | None = None
        #: Samples kept, and dropped by reason.
        self.counts: dict[str, int] = {"taken": 0, "wrong_type": 0, "non_finite": 0, "out_of_range": 0}

    def take(self, sample: Sample) -> None:
        """Keep ``sample`` as the marker's latest pose, or count why it was dropped."""
        if not isinstance(sample, ControllerState | Pose):
            self.counts["wrong_type"] += 1
            return
        p, q = sample.position, sample.orientation
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            self.counts["non_finite"] += 1
            return
        if float(np.max(np.abs(p))) > MAX_MARKER_M or not 1e-6 < float(np.max(np.abs(q))) < 1e6:
            self.counts["out_of_range"] += 1
            return
        self._latest = sample
        self.counts["taken"] += 1

    def target(self) -> FloatArray:
        """The plan target: aligned position [m] (shape (3,)), or position and orientation (7,).

        Raises:
            ValueError: No pose yet, the latest is stale, or it maps too far from the origin.
        """
        sample = self._latest
        if sample is None:
            raise ValueError(
                f"no pose from the plan marker {self.name} yet: start its device, or send target X Y Z"
            )
        age = (self._clock_ns() - sample.stamp.capture_ns) / 1e9
        if age > self.max_age_s:
            raise ValueError(
                f"the plan marker {self.name} is stale (last pose {age:.1f} s old, at most "
                f"{self.max_age_s:g} s): check its device, or send target X Y Z"
            )
        position, orientation = self.alignment.apply(sample.position, sample.orientation)
        if float(np.max(np.abs(position))) > MAX_TARGET_M:
            raise ValueError(f"the plan marker {self.name} is more than {MAX_TARGET_M:g} m from the origin")
        if self.orientation:
            return np.concatenate([position, quat_normalize(orientation)])
        return np.asarray(position, dtype=np.float64)


@dataclass(slots=True)
class _Staged:
    id: str
    plan: MobileReachPlan
    base_path: FloatArray  # (n, 3): x, y [m], yaw [rad]
    ee_path: FloatArray  # (n, 3) [m], world
    made: float  # monotonic [s]
    made_ns: int  # wall clock [ns]
    planned_ms: float


class ReachPlanAid:
    """Plan-preview-execute of mobile reaches on a whole-body controller (see the module docs).

    Args:
        controller: The live controller the executor drives (the retargeter's).
        planner: Planner on the same robot model; one on ``controller.scene`` when None.
        max_age_s: A staged plan older than this is refused [s].
        max_start_error: Largest difference between the robot's configuration and the plan's start
            [m for base x/y, rad for the rest] for the plan to run.
        max_execute_s: An execution not done after this fails [s].
        stall_s: An execution during which the commanded configuration stays still this long fails
            (the safety chain is holding the robot) [s].
        dt: Period of the preview's dry run [s].
        clock: Monotonic clock [s] (tests inject one).
        marker: The operator's plan marker that ``plan`` without coordinates plans to; None: the
            ``target`` command designates.
    """

    #: Stream the node publishes :meth:`state` on (retained JSON).
    stream = "plan"

    def __init__(
        self,
        controller: WholeBodyController,
        planner: MobileReachPlanner | None = None,
        *,
        max_age_s: float = 30.0,
        max_start_error: float = 0.05,
        max_execute_s: float = 40.0,
        stall_s: float = 0.5,
        dt: float = 0.01,
        clock: Callable[[], float] = time.monotonic,
        marker: PlanMarker | None = None,
    ) -> None:
        for name, value in (
            ("max_age_s", max_age_s),
            ("max_start_error", max_start_error),
            ("max_execute_s", max_execute_s),
            ("stall_s", stall_s),
            ("dt", dt),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        self._live = controller
        scene = controller.scene
        self._planner = planner if planner is not None else MobileReachPlanner(scene)
        # The dry run gets a controller of its own: the live one belongs to the control thread.
        self._dry = WholeBodyController(scene)
        self._executor = MobileReachExecutor(controller, self._planner)
        self._max_age = max_age_s
        self._max_start = max_start_error
        self._max_exec = max_execute_s
        self._stall = stall_s
        self._dt = dt
        self._clock = clock
        self.marker = marker
        self._fk = mujoco.MjData(scene.model)
        self._ee = scene.model.site(scene.ee_site).id
        self._lock = threading.Lock()
        self._status: PlanStatus = "none"
        self._reason = ""
        self._staged: _Staged | None = None
        self._designated: FloatArray | None = None
        self._q: FloatArray | None = None  # the configuration the retargeter last started from
        self._worker: threading.Thread | None = None
        self._seq = 0
        self._dirty = False
        self._exec_start = 0.0
        self._still_since = 0.0
        self._q_prev: FloatArray | None = None
        #: Plans made, executions started and finished, commands refused.
        self.counts: dict[str, int] = {"planned": 0, "executed": 0, "done": 0, "refused": 0}
        self.last_refusal = ""
        #: Instructions the executed reaches took (1 each) and would have taken without the planner.
        self.instructions = 0
        self.manual_instructions = 0

    # --- Aid ----------------------------------------------------------------------------------------

    def update(self, sample: Sample) -> bool:
        """Publish what the worker or the execution changed since the last tick (samples carry nothing)."""
        with self._lock:
            dirty, self._dirty = self._dirty, False
        return dirty

    def command(self, text: str) -> bool:
        """Apply one ``plan_command`` (see the module docs); ``ValueError`` with the reason when refused."""
        try:
            return self._command(text)
        except ValueError as exc:
            with self._lock:
                self.counts["refused"] += 1
                self.last_refusal = str(exc)[:200]
                self._dirty = True
            raise

    def _command(self, text: str) -> bool:
        words = text.split()
        if not words or len(words) > _MAX_WORDS:
            raise ValueError(f"plan command must be plan, target, execute ID or cancel, got {text[:80]!r}")
        verb, args = words[0].lower(), words[1:]
        if verb == "target":
            target = _floats(args, "target")
            with self._lock:
                self._designated = target
            return True
        if verb == "plan":
            target = self._plan_target(args)
            started = self._start_planning(target)
            with self._lock:
                if self.marker is not None and self._designated is target:
                    self._designated = None  # the marker is the standing designation; text is one-shot
            return started
        if verb == "execute":
            if len(args) != 1:
                raise ValueError("execute needs the staged plan's id: execute ID")
            return self._execute(args[0])
        if verb == "cancel" and not args:
            return self.cancel("cancelled by the operator")
        raise ValueError(f"plan command must be plan, target, execute ID or cancel, got {text[:80]!r}")

    def state(self) -> dict[str, JsonValue]:
        """The plan the scene draws: id, status, reason, target, base/arm goals and preview paths."""
        with self._lock:
            staged, status, reason = self._staged, self._status, self._reason
            designated = self._designated
            doc: dict[str, JsonValue] = {
                "status": status,
                "reason": reason,
                "designated": None if designated is None else _r(designated),
                "refused": self.counts["refused"],
                "last_refusal": self.last_refusal,
                "instructions": self.instructions,
                "manual_instructions": self.manual_instructions,
            }
        marker = self.marker
        doc["marker"] = None if marker is None else marker.name
        doc["marker_dropped"] = 0 if marker is None else sum(marker.counts.values()) - marker.counts["taken"]
        if staged is None:
            doc["id"] = None
            return doc
        plan = staged.plan
        doc.update(
            id=staged.id,
            made_ns=staged.made_ns,
            planned_ms=round(staged.planned_ms, 2),
            max_age_s=self._max_age,
            target={"position": _r(plan.target_position), "orientation": _r(plan.target_orientation)},
            base_start=_r(plan.q_start[:_NB]),
            base_goal=_r(plan.base_goal),
            arm_goal=_r(plan.arm_goal),
            base_moves=plan.base_moves,
            reachable=plan.reachable,
            position_error=round(plan.position_error, 5),
            manual=plan.manual_instructions,
            base_path=[_r(p) for p in staged.base_path],
            ee_path=[_r(p) for p in staged.ee_path],
        )
        return doc

    # --- what the retargeter asks -------------------------------------------------------------------

    @property
    def status(self) -> PlanStatus:
        """``none``, ``planning``, ``staged``, ``executing``, ``done``, ``cancelled`` or ``failed``."""
        return self._status

    @property
    def executing(self) -> bool:
        """Whether :meth:`action` drives the robot now."""
        return self._status == "executing"

    def observe(self, q: FloatArray) -> None:
        """The configuration the retargeter starts this tick from (the last command sent)."""
        self._q = np.array(q, dtype=np.float64)

    def action(self, q: FloatArray, gripper: float) -> FloatArray | None:
        """The controller's action this tick while executing (shape (8,)); None otherwise."""
        if self._status != "executing":
            return None
        now = self._clock()
        if self._q_prev is not None and np.array_equal(q, self._q_prev):
            if now - self._still_since > self._stall:
                self._finish("failed", "the robot did not move: held or stopped by the safety chain")
                return None
        else:
            self._still_since = now
        self._q_prev = np.array(q, dtype=np.float64)
        if now - self._exec_start > self._max_exec:
            self._finish("failed", f"not done within {self._max_exec:g} s")
            return None
        out = self._executor.action(q)
        out[6] = gripper
        if self._executor.phase == "done":
            self._finish("done", "reached the target")
            out[:6] = 0.0
            out[7] = EE_MODE
        return out

    def cancel(self, reason: str) -> bool:
        """Drop a staged plan or stop an executing one; returns whether there was one."""
        with self._lock:
            if self._status not in ("staged", "executing", "planning"):
                return False
            self._status, self._reason, self._dirty = "cancelled", reason, True
        self._live.posture = self._live.scene.home[_NB:]
        return True

    def join(self, timeout: float = 5.0) -> None:
        """Wait for a planning worker to finish (tests, shutdown)."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)

    # --- internals ----------------------------------------------------------------------------------

    def _finish(self, status: PlanStatus, reason: str) -> None:
        with self._lock:
            self._status, self._reason, self._dirty = status, reason, True
            if status == "done":
                self.counts["done"] += 1

    def _plan_target(self, args: list[str]) -> FloatArray:
        """Given coordinates, else the designated target, else the marker's pose (see the module docs)."""
        if args:
            return _floats(args, "plan target")
        designated = self._designated
        if designated is not None:
            return designated
        if self.marker is not None:
            return self.marker.target()
        raise ValueError(
            "no target designated: configure a plan marker (plan_marker in the wbc retargeter) "
            "or send target X Y Z"
        )

    def _start_planning(self, target: FloatArray) -> bool:
        q = self._q
        if q is None:
            raise ValueError("no robot configuration yet: plan once the robot is being driven")
        with self._lock:
            if self._status in ("planning", "executing"):
                raise ValueError(f"a plan is {self._status}: cancel it first")
            self._status, self._reason, self._dirty = "planning", "", True
            self._seq += 1
            seq = self._seq
        worker = threading.Thread(
            target=self._plan, args=(seq, target, q.copy()), name="reach-plan", daemon=True
        )
        self._worker = worker
        worker.start()
        return True

    def _plan(self, seq: int, target: FloatArray, q: FloatArray) -> None:
        """Worker: plan, dry-run the execution for the preview, then stage (or fail with the reason)."""
        t0 = time.perf_counter()
        try:
            orientation = target[3:] if len(target) == 7 else self._hand_orientation(q)
            plan = self._planner.plan(target[:3], orientation, q)
            if not plan.reachable:
                reason = f"target out of reach (off by {plan.position_error * 100:.1f} cm)"
                self._set(seq, None, "failed", reason)
                return
            base_path, ee_path, reached = self._preview(plan)
        except Exception as exc:  # the worker must always leave a status the operator sees
            self._set(seq, None, "failed", f"planning failed: {str(exc)[:160]}")
            return
        planned_ms = (time.perf_counter() - t0) * 1e3
        if not reached:
            self._set(seq, None, "failed", "the dry run did not reach the target")
            return
        staged = _Staged(
            id=f"{seq}-{secrets.token_hex(4)}",
            plan=plan,
            base_path=base_path,
            ee_path=ee_path,
            made=self._clock(),
            made_ns=time.time_ns(),
            planned_ms=planned_ms,
        )
        moves = "base then arm" if plan.base_moves else "arm only"
        self._set(seq, staged, "staged", f"{moves}; say 'robot please execute' to run it")

    def _set(self, seq: int, staged: _Staged | None, status: PlanStatus, reason: str) -> None:
        with self._lock:
            if seq != self._seq or self._status != "planning":
                return  # cancelled (or superseded) while planning
            self._staged = staged
            self._status, self._reason, self._dirty = status, reason, True
            if staged is not None:
                self.counts["planned"] += 1

    def _hand_orientation(self, q: FloatArray) -> FloatArray:
        data = self._fk
        data.qpos[:] = q
        mujoco.mj_kinematics(self._live.scene.model, data)
        out = np.empty(4)
        mujoco.mju_mat2Quat(out, data.site_xmat[self._ee])
        return out

    def _preview(self, plan: MobileReachPlan) -> tuple[FloatArray, FloatArray, bool]:
        """Dry run of the execution on the worker's controller: sampled base and grasp-point paths."""
        dry = self._dry
        dry.reset()
        dry.posture = self._live.scene.home[_NB:]
        executor = MobileReachExecutor(dry, self._planner)
        executor.execute(plan)
        q = plan.q_start.copy()
        qs = [q]
        steps = int(self._max_exec / self._dt)
        for _ in range(steps):
            if executor.phase == "done":
                break
            q = np.array(dry.step(executor.action(q), q, self._dt).q)
            qs.append(q)
        every = max(1, math.ceil(len(qs) / (MAX_PREVIEW_POINTS - 1)))
        picked = [*qs[::every], qs[-1]][:MAX_PREVIEW_POINTS]
        base = np.array([p[:_NB] for p in picked])
        ee = np.empty((len(picked), 3))
        data = self._fk
        for i, p in enumerate(picked):
            data.qpos[:] = p
            mujoco.mj_kinematics(self._live.scene.model, data)
            ee[i] = data.site_xpos[self._ee]
        return base, ee, executor.phase == "done"

    def _execute(self, plan_id: str) -> bool:
        with self._lock:
            staged, status = self._staged, self._status
            if staged is None or status != "staged":
                raise ValueError(f"no plan is staged (status {status}): say 'plan reach' first")
            if plan_id != staged.id:
                raise ValueError(f"plan {plan_id[:40]!r} is not the staged plan: re-plan and confirm it")
            age = self._clock() - staged.made
            if age > self._max_age:
                self._status, self._reason, self._dirty = "failed", f"stale: planned {age:.0f} s ago", True
                raise ValueError(f"plan {plan_id} is {age:.0f} s old (at most {self._max_age:g}): re-plan")
            q = self._q
            off = math.inf if q is None else float(np.max(np.abs(q - staged.plan.q_start)))
            if off > self._max_start:
                self._status, self._dirty = "failed", True
                self._reason = f"the robot moved {off:.3f} since planning"
                raise ValueError(
                    f"the robot moved since plan {plan_id} was made (by {off:.3f} m/rad, at most "
                    f"{self._max_start:g}): re-plan"
                )
            self._status, self._reason, self._dirty = "executing", "executing", True
            self.counts["executed"] += 1
            self.instructions += 1
            self.manual_instructions += staged.plan.manual_instructions
        self._executor.execute(staged.plan)
        self._exec_start = self._still_since = self._clock()
        self._q_prev = None
        return True
