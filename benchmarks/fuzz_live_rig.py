"""Fuzz a live demo rig through Mosquitto with well-formed IR messages of extreme values; measure what holds.

Runs the demo rig (scripted VR operator → embedded Mosquitto → control node: gate, IK, safety
chain → MuJoCo arm; camera off) and records an episode while a second MQTT client publishes, at
``--rate`` messages per second for ``--burst`` seconds, well-formed samples of every IR type on the
rig's device streams: NaN, inf, 1e300, zero and huge quaternions, out-of-range analog values,
capture times 1 h and 2^62 ns ahead or behind, negative, and sequence numbers that jump. The real
operator input keeps running. Then it e-stops and resets the arm over the bus, as
``telerig safety estop|reset`` does.

Measured: messages sent per topic and per type; rejected per reason at the control node's gate,
decode errors, wrong-type inputs, tick faults; whether the control loop is alive and its command
rate after the burst; whether the reset resumed control; the largest joint step between
consecutive sent commands against the per-tick speed limit, and position-limit violations.

Prints a table, writes ``benchmarks/results/fuzz_live_rig.json`` and exits 1 if a property failed.

Usage: python benchmarks/fuzz_live_rig.py [--burst 5] [--rate 400] [--seed 0] [--out PATH]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from rich.console import Console
from rich.table import Table

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.ticks import picking
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.types import (
    BaseVelocity,
    BodySkeleton,
    ControlKind,
    ControllerState,
    ControlMode,
    ControlSource,
    GripperCommand,
    HandPose,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Sample,
    Stamp,
    Twist,
    now_ns,
)
from telerig.runtime import streams
from telerig.runtime.rig import RigRuntime
from telerig.safety.commands import SafetyCommand, safety_command_topic

RESULTS = Path(__file__).parent / "results" / "fuzz_live_rig.json"
RIG = "demo"
PERIOD_S = 0.01  # the demo arm's control period [s]
EXTREMES = np.array([np.nan, np.inf, -np.inf, 1e300, -1e300, 1e154, 5e-324, 0.0, 2.0, -1.0])
QUATERNIONS = np.array([[0, 0, 0, 0], [1e300, 0, 0, 0], [np.nan, 0, 0, 1], [2.0, 0, 0, 0], [1, 0, 0, 0]])
INT64 = (-(2**63), 2**63 - 1)
#: A robot's record of who drove (published where a device streams, it is a wrong-type input).
CONTROL_SOURCES: tuple[tuple[str | None, ControlKind], ...] = (
    ("vr0", "operator"),
    ("pi0", "policy"),
    ("vr0", "paused"),
    ("home", "home"),
    (None, "none"),
)
CONTROL_MODES: tuple[ControlMode, ...] = ("auto", "operator", "policy")


class Fuzzer:
    """Well-formed IR samples with extreme values, from a seeded generator."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def value(self, n: int) -> np.ndarray:
        """``n`` floats: half plausible (normal, sd 1), half extremes."""
        plausible = self.rng.normal(0.0, 1.0, n)
        extreme = self.rng.choice(EXTREMES, n)
        values: np.ndarray = np.where(self.rng.random(n) < 0.5, plausible, extreme)
        return values

    def quaternion(self) -> np.ndarray:
        if self.rng.random() < 0.5:
            return np.array(QUATERNIONS[int(self.rng.integers(len(QUATERNIONS)))], dtype=np.float64)
        return self.value(4)

    def stamp(self, now: int) -> Stamp:
        r = self.rng
        choice = r.integers(6)
        capture = [
            now + 3600 * 10**9,
            now + 2**62,
            now - 3600 * 10**9,
            -int(r.integers(1, 2**62)),
            now + int(r.integers(-(10**9), 10**9)),
            int(r.integers(0, 2**62)),
        ][choice]
        capture = max(INT64[0], min(INT64[1], capture))
        seq = int(r.integers(INT64[0], INT64[1])) if r.random() < 0.5 else int(r.integers(0, 100))
        confidence = float(self.value(1)[0]) if r.random() < 0.3 else 1.0
        return Stamp("fuzz", seq, int(r.integers(INT64[0], INT64[1])), capture, 0, confidence)

    def sample(self, now: int) -> Sample:
        r, st = self.rng, self.stamp(now)
        kind = r.integers(9)
        p, q = self.value(3), self.quaternion()
        if kind <= 2:
            trig, grip = self.value(2)
            return ControllerState(st, "right", p, q, "operator", frozenset({"a"}), trig, grip, self.value(2))
        if kind == 3:
            return Pose(st, p, q, "operator")
        if kind == 4:
            return HandPose(st, "right", p, q, self.value(63).reshape(21, 3), self.value(21), "operator")
        if kind == 5:
            rot = np.array([self.quaternion() for _ in range(3)])
            return BodySkeleton(st, ("a", "b", "c"), self.value(9).reshape(3, 3), rot, "operator")
        if kind == 6:
            return Twist(st, p, self.value(3), "operator")
        if kind == 7:
            vx, vy, wz = self.value(3)
            return BaseVelocity(st, vx, vy, wz)
        names = tuple(f"joint{i}" for i in range(6))
        other = r.integers(5)
        if other == 0:
            return JointCommand(st, names, self.value(6))
        if other == 1:
            return JointState(st, names, self.value(6), self.value(6))
        if other == 2:
            driver, driven = CONTROL_SOURCES[int(r.integers(len(CONTROL_SOURCES)))]
            return ControlSource(st, driver, driven, CONTROL_MODES[int(r.integers(len(CONTROL_MODES)))])
        if other == 3:  # a robot's IK residual, where a device streams
            metrics = ("position_error_m", "orientation_error_rad")
            return RetargetResidual(st, bool(r.integers(2)), metrics, tuple(self.value(2).tolist()))
        return GripperCommand(st, float(self.value(1)[0]))


class SentCommands:
    """Joint commands the rig reports sent to the arm, with their arrival times."""

    def __init__(self) -> None:
        self.items: list[tuple[float, np.ndarray]] = []
        self.lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        command = wire.decode(message.payload)
        if isinstance(command, JointCommand):
            with self.lock:
                self.items.append((time.monotonic(), np.array(command.positions)))

    def since(self, t: float) -> int:
        with self.lock:
            return sum(1 for at, _ in self.items if at >= t)


def wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def run(burst_s: float, rate_hz: float, seed: int) -> dict[str, Any]:
    # The robot in this process (the demo rig runs it in one of its own), so the control node's gate
    # counters, safety counts and limits are read directly; the gate and chain are the same code.
    config = load_rig(RIG).with_isolation("threads").model_copy(update={"cameras": []})
    topics = [str(Topic(RIG, "vr0", part)) for part in ("right_controller", "left_controller", "right_hand")]
    weights = np.array([0.8, 0.1, 0.1])
    fuzzer = Fuzzer(seed)
    sent = SentCommands()
    per_topic: Counter[str] = Counter()
    per_type: Counter[str] = Counter()
    with tempfile.TemporaryDirectory() as tmp, RigRuntime(config, data_root=Path(tmp)) as runtime:
        assert runtime.broker_url is not None
        client = MqttBus(runtime.broker_url, client_id="fuzz").connect()
        client.subscribe(str(Topic(RIG, "arm0", streams.TICK)), picking({streams.JOINT_SENT}, sent))
        control = runtime.controls["arm0"]
        limits = runtime.robots["arm0"].limits
        outcome: list[Any] = []
        episode = threading.Thread(target=lambda: outcome.append(runtime.run_episode(burst_s + 8.0)))
        episode.start()
        try:
            started = wait_until(lambda: sent.since(0.0) > 50, 15.0)
            t0 = time.monotonic()
            n = 0
            while time.monotonic() - t0 < burst_s:
                topic = topics[int(fuzzer.rng.choice(len(topics), p=weights))]
                sample = fuzzer.sample(now_ns())
                client.publish(topic, wire.encode(sample))
                per_topic[topic] += 1
                per_type[type(sample).__name__] += 1
                n += 1
                time.sleep(max(0.0, t0 + n / rate_hz - time.monotonic()))
            after = time.monotonic()
            time.sleep(1.0)
            rate_after = sent.since(after) / 1.0
            alive = control.alive
            command_topic = safety_command_topic(RIG)
            estop = SafetyCommand(command="estop", source="fuzz_live_rig").model_dump_json().encode()
            client.publish(command_topic, estop, qos=1)
            estopped = wait_until(lambda: control.stats.safety_status == "estopped", 3.0)
            reset = SafetyCommand(command="reset", source="fuzz_live_rig").model_dump_json().encode()
            client.publish(command_topic, reset, qos=1)
            reset_at = time.monotonic()
            resumed = estopped and wait_until(lambda: sent.since(reset_at) > 30, 4.0)
        finally:
            episode.join(60.0)
            client.close()
        stats = control.stats
        safety = dict(control.safety.counts)
    items = sent.items
    q = np.array([p for _, p in items])
    beyond = int(np.sum((q < limits.lower - 1e-9) | (q > limits.upper + 1e-9)))
    per_tick = limits.velocity * 2 * PERIOD_S  # the chain bounds a tick's dt to two periods
    steps = [np.abs(b - a) for (ta, a), (tb, b) in itertools.pairwise(items) if tb - ta < 0.05]
    step = np.max(np.array(steps), axis=0) if steps else np.zeros(len(limits.names))
    return {
        "started": started,
        "burst_s": burst_s,
        "published_per_topic": dict(per_topic),
        "published_per_type": dict(per_type),
        "published": int(sum(per_topic.values())),
        "rejected_per_reason": dict(stats.rejected),
        "decode_errors": stats.decode_errors,
        "wrong_type": stats.wrong_type,
        "tick_faults": stats.tick_faults,
        "safety_events": {k: v for k, v in safety.items() if v},
        "control_loops_alive": int(alive),
        "control_loops": 1,
        "commands_per_s_after_burst": rate_after,
        "reset_resumed_control": bool(resumed),
        "commands_sent": len(items),
        "max_joint_step_rad": float(step.max()),
        "max_joint_step_fraction_of_tick_limit": float(np.max(step / per_tick)),
        "joint_limit_violations": beyond,
        "episode_status": outcome[0].status if outcome else None,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--burst", type=float, default=5.0, help="seconds of fuzzing")
    parser.add_argument("--rate", type=float, default=400.0, help="fuzz messages per second")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    console = Console(width=120)
    console.print(
        f"fuzzing the live demo rig for {args.burst:g} s at {args.rate:g} msg/s (seed {args.seed}) ..."
    )
    r = run(args.burst, args.rate, args.seed)
    table = Table(title=f"fuzz into a live demo rig through Mosquitto ({os.cpu_count()} cores)")
    table.add_column("measure")
    table.add_column("value", justify="right")
    for topic, n in sorted(r["published_per_topic"].items()):
        table.add_row(f"sent on {topic}", str(n))
    for kind, n in sorted(r["published_per_type"].items()):
        table.add_row(f"sent {kind}", str(n))
    for reason, n in r["rejected_per_reason"].items():
        table.add_row(f"rejected: {reason}", str(n))
    for key in ("decode_errors", "wrong_type", "tick_faults"):
        table.add_row(key.replace("_", " "), str(r[key]))
    table.add_row("control loops alive", f"{r['control_loops_alive']}/{r['control_loops']}")
    table.add_row("commands/s after the burst", f"{r['commands_per_s_after_burst']:.0f}")
    table.add_row("reset resumed control", str(r["reset_resumed_control"]))
    table.add_row("max joint step (rad)", f"{r['max_joint_step_rad']:.4f}")
    table.add_row("max joint step / per-tick limit", f"{r['max_joint_step_fraction_of_tick_limit']:.2f}")
    table.add_row("joint limit violations", str(r["joint_limit_violations"]))
    table.add_row("safety events", ", ".join(f"{k} {v}" for k, v in r["safety_events"].items()) or "none")
    table.add_row("episode", str(r["episode_status"]))
    console.print(table)
    ok = (
        r["started"]
        and r["control_loops_alive"] == r["control_loops"]
        and r["tick_faults"] == 0
        and r["reset_resumed_control"]
        and r["joint_limit_violations"] == 0
        and r["max_joint_step_fraction_of_tick_limit"] <= 1.0 + 1e-6
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    machine = {"cpus": os.cpu_count(), "python": platform.python_version(), "load1": os.getloadavg()[0]}
    args.out.write_text(
        json.dumps({"benchmark": "fuzz_live_rig", "machine": machine, "ok": ok, **r}, indent=2)
    )
    console.print(f"{'all properties held' if ok else 'A PROPERTY FAILED'}; wrote {args.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
