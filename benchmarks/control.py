"""Benchmark: control-loop compute per tick: arm IK + safety, whole-body QP, hand and humanoid retargeting.

Each row runs the real retargeter (and, where marked, the robot's safety chain) in a closed
kinematic loop: the command of one tick is the measured state of the next, as in the control
node. Timings are per call on one thread; p99 on a shared 2-core machine includes scheduler noise.
Targets (issue 4): arm tick <= 0.5 ms p50, WBC >= 1 kHz (p50 <= 1 ms), hand <= 0.5 ms per frame.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.devices.scripted import ScriptedVRController
from telerig.ir.types import ControllerState, JointCommand, JointState, Sample, Stamp
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.config import (
    ArmPoseConfig,
    FixtureConfig,
    FixturesConfig,
    MotionScaleConfig,
    PoseFilterConfig,
)
from telerig.robots.base import JointLimits
from telerig.robots.models.hands import HandModelName
from telerig.safety import SafetyChain

sys.path.insert(0, str(Path(__file__).parent))  # the hand motion generator of benchmarks/hand_retarget.py
from hand_retarget import human_sequence

DT = 0.01

#: (row, tick function, number of ticks) → p50/p99 [µs]
Tick = Callable[[int], object]


def _time(tick: Tick, n: int, warmup: int = 50) -> dict[str, float]:
    for k in range(warmup):
        tick(k)
    times = np.empty(n)
    for k in range(n):
        t0 = time.perf_counter()
        tick(warmup + k)
        times[k] = time.perf_counter() - t0
    return {"p50_us": float(np.median(times) * 1e6), "p99_us": float(np.percentile(times, 99) * 1e6)}


def _chain(limits: JointLimits) -> SafetyChain:
    return SafetyChain.default(limits, period_s=DT, ramp_duration_s=0.0)


def _limits(model: Any, names: tuple[str, ...], velocity: float, acceleration: float) -> JointLimits:
    """Joint limits from a MuJoCo model's joint ranges, with uniform speed/acceleration limits."""
    import mujoco

    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in names]
    n = len(names)
    return JointLimits(
        names,
        model.jnt_range[ids, 0],
        model.jnt_range[ids, 1],
        np.full(n, velocity),
        np.full(n, acceleration),
    )


def _state(names: tuple[str, ...], q: np.ndarray, t_ns: int) -> JointState:
    return JointState(Stamp("bench", 0, t_ns, t_ns), names, q, np.zeros(len(q)))


def _controller_samples(n: int, *, clutch: bool) -> Iterator[ControllerState]:
    device = ScriptedVRController(home=(0.40, 0.0, 1.10))
    for k in range(n):
        sample = device.sample_at(k * DT, seq=k)
        if clutch:
            sample = ControllerState(
                sample.stamp,
                sample.hand,
                sample.position,
                sample.orientation,
                sample.frame_id,
                buttons=frozenset({"grip"}),
                grip=1.0,
            )
        yield sample


def arm_tick(model: str, relative: bool, n: int) -> dict[str, Any]:
    """Retarget (IK) + safety chain for one arm; ``relative`` adds clutch, filter, scale and a fixture."""
    from telerig.robots.models.arm import build_arm_kinematics

    scene = build_arm_kinematics(model)
    home_p, _ = ArmIK(scene).forward(scene.home)
    if relative:
        config = ArmPoseConfig(
            mode="relative",
            clutch_button="grip",
            filter=PoseFilterConfig(),
            scale=MotionScaleConfig(initial=0.5),
            fixtures=FixturesConfig(options=[FixtureConfig(name="level", kind="orientation")]),
        )
    else:
        config = ArmPoseConfig.model_validate(
            {"alignment": {"operator_origin": (0.40, 0.0, 1.10), "robot_origin": tuple(home_p.tolist())}}
        )
    names = tuple(scene.arm_joints)
    # As the runtime binds it: one QP sub-step per tick (``ik_substeps``, benchmarks/arm_ik.py).
    ik = ArmIK(scene, iterations=config.ik_substeps, residual_threshold_m=config.residual_threshold_m)
    retargeter = config.build(ik, names)
    chain = _chain(_limits(scene.model, names, math.pi, 10.0))
    t0 = time.monotonic_ns()
    samples = [  # stamped as the control node sees them (decoded before the tick starts)
        ControllerState(
            Stamp("bench", k, t0 + k * 10_000_000, t0 + k * 10_000_000, t0 + k * 10_000_000),
            s.hand,
            s.position,
            s.orientation,
            s.frame_id,
            buttons=s.buttons,
            grip=s.grip,
        )
        for k, s in enumerate(_controller_samples(n + 100, clutch=relative))
    ]
    q = scene.home.copy()

    def tick(k: int) -> None:
        nonlocal q
        sample = samples[k]
        now = sample.stamp.capture_ns
        requested, _ = retargeter(sample, q, DT)
        out = chain.step(requested, now_ns=now, measured=_state(names, q, now))
        if out.command is not None:
            q = out.command.positions

    row = _time(tick, n)
    mode = "relative + filter + scale + fixture" if relative else "absolute"
    return {"row": f"arm tick {model} ({len(names)}-DoF), {mode}", "includes": "IK + safety", **row}


def wbc_tick(n: int) -> dict[str, Any]:
    """The TIAGo whole-body QP, switching between EE and whole-body mode every 2 s at 1 kHz."""
    from telerig.retarget.wbc import WholeBodyController
    from telerig.robots.models.tiago import TIAGO_HOME

    wbc = WholeBodyController()
    dt = 0.001
    q = np.array(TIAGO_HOME, dtype=np.float64)

    def tick(k: int) -> None:
        nonlocal q
        t = k * dt
        w = 2 * math.pi * 0.5
        action = np.array(
            [-0.05 * math.sin(w * t), 0.05 * math.cos(w * t), 0.0, 0.0, 0.0, 0.2 * math.sin(w * t), 0.0,
             float(int(t / 2.0) % 2)]
        )  # fmt: skip
        q = wbc.step(action, q, dt).q

    row = _time(tick, n, warmup=200)
    return {"row": "WBC tick TIAGo (10-DoF QP, mode switch every 2 s)", "includes": "QP", **row}


def hand_frame(hand: HandModelName, n: int) -> dict[str, Any]:
    """Hand vector retargeting per frame, on the glove hand-motion sequence of benchmarks/hand_retarget.py."""
    from telerig.retarget.hand.optimizer import HandRetargeter
    from telerig.robots.models.hands import load_hand

    retargeter = HandRetargeter(load_hand(hand, "right"))
    samples: list[Sample] = human_sequence(n / 100.0 + 1.0)

    def tick(k: int) -> None:
        retargeter(samples[k])

    row = _time(tick, n)
    return {"row": f"hand frame {hand}", "includes": "vectors + solve + command", **row}


def humanoid_tick(n: int) -> dict[str, Any]:
    """G1 upper-body IK from the shipped BVH clip (looped) + safety chain."""
    from telerig.retarget.humanoid import HumanoidIK, HumanoidRetargeter
    from telerig.retarget.offline import load_skeletons
    from telerig.robots.models.g1 import build_humanoid_kinematics

    bvh = Path(__file__).parents[1] / "src/telerig/devices/mocap/data/reach.bvh"
    skeletons = load_skeletons(bvh)
    scene = build_humanoid_kinematics()
    retargeter = HumanoidRetargeter(HumanoidIK(scene))
    names = scene.joints
    chain = _chain(_limits(scene.model, names, 3.0, 15.0))
    q = scene.home.copy()
    t0 = time.monotonic_ns()

    def tick(k: int) -> None:
        nonlocal q
        now = t0 + k * 10_000_000
        skeleton = skeletons[k % len(skeletons)]
        requested, _ = retargeter(skeleton, q, DT)
        requested = JointCommand(Stamp("bench", k, now, now), requested.names, requested.positions)
        out = chain.step(requested, now_ns=now, measured=_state(names, q, now))
        if out.command is not None:
            q = out.command.positions

    row = _time(tick, n)
    return {"row": f"humanoid tick G1 upper body ({len(names)}-DoF)", "includes": "IK + safety", **row}


def node_tick(n: int) -> list[dict[str, Any]]:
    """One whole control-node tick on a stepped simulated UR5e + Robotiq: decode the operator's
    sample, IK, safety chain, driver reads and sends, and every stream it publishes (in-memory bus,
    so the MQTT client's own cost is not in it). The physics steps between ticks, untimed."""
    from telerig.bus.base import Message
    from telerig.bus.memory import InMemoryBus
    from telerig.bus.topics import Topic
    from telerig.config.schema import AlignmentConfig
    from telerig.ir import wire
    from telerig.retarget.alignment import Alignment
    from telerig.retarget.arm import AbsolutePoseRetargeter
    from telerig.retarget.gripper import TriggerGripper
    from telerig.robots.sim.arm import MujocoArm
    from telerig.runtime.control_node import ControlNode, GripperBinding, JointsBinding

    arm = MujocoArm(name="arm0", realtime=False)
    arm.connect()
    ik = ArmIK(arm.scene)
    home_p, _ = ik.forward(arm.scene.home)
    alignment = Alignment.from_config(
        AlignmentConfig(operator_origin=(0.40, 0.0, 1.10), robot_origin=tuple(home_p.tolist()))
    )
    topic = str(Topic("bench", "vr0", "right_controller"))
    node = ControlNode(
        "bench",
        arm,
        _chain(arm.limits),
        InMemoryBus(),
        control_rate_hz=100.0,
        joints=JointsBinding(topic, AbsolutePoseRetargeter(alignment, ik, arm.joint_names)),
        gripper=GripperBinding(topic, TriggerGripper()),
    )
    samples = list(_controller_samples(n + 100, clutch=False))
    times = np.empty(n)
    cpu = np.empty(n)  # the tick's own CPU time [s]: what a loaded host cannot inflate
    # Even ticks encode into the thread's reused Envelopes, odd ones into fresh ones (the code before
    # issue 18): both halves see the same trajectory and the same host load.
    try:
        for k in range(n + 100):
            wire._reuse = k % 2 == 0
            arm.step(5)  # 500 Hz physics, 100 Hz control
            t = time.time_ns()
            s = samples[k]
            sample = ControllerState(
                Stamp("bench", k, t, t), s.hand, s.position, s.orientation, s.frame_id, trigger=0.5
            )
            message = Message(topic, wire.encode(sample), t)
            t0, c0 = time.perf_counter(), time.thread_time()
            node._tick([message])  # the loop's own step, timed without its thread
            if k >= 100:
                times[k - 100] = time.perf_counter() - t0
                cpu[k - 100] = time.thread_time() - c0
    finally:
        wire._reuse = True
        node.stop()
        arm.close()
    includes = "IK + safety + driver + publish"
    rows = []
    for label, part, part_cpu in (
        ("reused messages", times[0::2], cpu[0::2]),
        ("fresh messages (before)", times[1::2], cpu[1::2]),
    ):
        stats = {
            "p50_us": float(np.median(part) * 1e6),
            "p99_us": float(np.percentile(part, 99) * 1e6),
            "cpu_p50_us": float(np.median(part_cpu) * 1e6),
            "cpu_mean_us": float(np.mean(part_cpu) * 1e6),
        }
        rows.append(
            {"row": f"node tick UR5e sim (stepped), in-memory bus, {label}", "includes": includes, **stats}
        )
    return rows


TARGETS_US = {"arm tick": 500.0, "WBC tick": 1000.0, "hand frame": 500.0}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/control.json"))
    parser.add_argument(
        "--only",
        nargs="+",
        choices=("arm", "wbc", "hand", "humanoid", "node"),
        help="rows to run (default all)",
    )
    args = parser.parse_args()
    n = args.ticks
    console = Console(width=130)
    named: list[tuple[str, Callable[[], dict[str, Any] | list[dict[str, Any]]]]] = [
        ("arm", lambda: arm_tick("ur5e_robotiq85", False, n)),
        ("arm", lambda: arm_tick("ur5e_robotiq85", True, n)),
        ("arm", lambda: arm_tick("panda", False, n)),
        ("wbc", lambda: wbc_tick(5 * n)),
        ("hand", lambda: hand_frame("inspire", n)),
        ("hand", lambda: hand_frame("ability", n)),
        ("hand", lambda: hand_frame("allegro", n)),
        ("humanoid", lambda: humanoid_tick(n)),
        ("node", lambda: node_tick(n)),
    ]
    jobs = [job for key, job in named if args.only is None or key in args.only]
    rows = []
    with console.status("timing") as status:
        for i, job in enumerate(jobs, 1):
            status.update(f"timing row {i}/{len(jobs)}")
            result = job()
            rows.extend(result if isinstance(result, list) else [result])
    table = Table(title="Control-loop compute per call (closed kinematic loop, one thread)")
    for col in ("row", "includes", "p50 µs", "p99 µs", "CPU p50 µs", "target p50", "met"):
        table.add_column(col, justify="left" if col in ("row", "includes") else "right")
    for r in rows:
        target = next((v for k, v in TARGETS_US.items() if r["row"].startswith(k)), None)
        r["target_p50_us"] = target
        r["met"] = None if target is None else r["p50_us"] <= target
        table.add_row(
            r["row"],
            r["includes"],
            f"{r['p50_us']:.0f}",
            f"{r['p99_us']:.0f}",
            f"{r['cpu_p50_us']:.0f}" if "cpu_p50_us" in r else "-",
            "-" if target is None else f"{target:.0f}",
            "-" if r["met"] is None else ("yes" if r["met"] else "NO"),
        )
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "control", "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
