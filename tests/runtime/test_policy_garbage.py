"""Garbage on the policy's streams and commands is counted and dropped, and the rig goes on (issue 16):
observation frames (short, forged sizes, oversized, wrong magic), the robot state the policy reads
(non-finite, forged source), the policy's own action stream (undecodable, non-finite)
and the control command topic (non-words, huge, binary; and from a device's login, which the
broker's ACL refuses). A valid ``operator`` / ``policy`` command hands control over and back."""

from __future__ import annotations

import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.ticks import TICK, picking
from telerig.devices.policy.device import PolicyDevice
from telerig.errors import DeviceError, WireError
from telerig.ir import wire
from telerig.ir.observation import MAX_SIDE, decode_observation, encode_observation
from telerig.ir.types import ControlSource, JointCommand, JointState, Stamp, now_ns
from telerig.runtime.rig import RigRuntime

if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))
from policy_rigs import UR5E, policy_rig, tiny_checkpoint

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

R = "telerig/v1/junk"


def _wait(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


_HEADER = struct.Struct("<4sqIHHI")
_GOOD = encode_observation(np.zeros((24, 32, 3), np.uint8), 1, 1)
#: Observation payloads that must be refused, each with why.
FRAMES: dict[str, bytes] = {
    "empty": b"",
    "short header": b"TOB1\x00\x01",
    "wrong magic": b"XXXX" + _GOOD[4:],
    "truncated pixels": _GOOD[:-1],
    "extra bytes": _GOOD + b"\x00",
    "zero width": _HEADER.pack(b"TOB1", 1, 1, 24, 0, 0),
    "too large side": _HEADER.pack(b"TOB1", 1, 1, MAX_SIDE + 1, 1, (MAX_SIDE + 1) * 3)
    + bytes((MAX_SIDE + 1) * 3),
    "count lies": _HEADER.pack(b"TOB1", 1, 1, 24, 32, 10) + bytes(24 * 32 * 3),
    "negative time": _HEADER.pack(b"TOB1", -5, 1, 24, 32, 24 * 32 * 3) + bytes(24 * 32 * 3),
    "oversized": _HEADER.pack(b"TOB1", 1, 1, 512, 512, 512 * 512 * 3) + bytes(512 * 512 * 3 + 400_000),
}


@pytest.mark.parametrize("name", sorted(FRAMES))
def test_an_observation_decoder_refuses_garbage(name: str) -> None:
    with pytest.raises(WireError):
        decode_observation(FRAMES[name])


def test_an_observation_round_trips() -> None:
    image = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    frame = decode_observation(encode_observation(image, 123, 7))
    assert (frame.capture_ns, frame.seq) == (123, 7)
    assert np.array_equal(frame.image, image)


def test_garbage_on_the_policys_streams_and_commands_is_counted_and_dropped(tmp_path: Path) -> None:
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    rig = policy_rig(checkpoint, operator=True, name="junk")
    with RigRuntime(rig, data_root=tmp_path / "data") as runtime:
        broker = runtime.broker.embedded
        assert broker is not None
        control = runtime.controls["arm0"]
        device = runtime.devices["pi0"].device
        assert isinstance(device, PolicyDevice)
        drivers: list[str | None] = []
        lock = threading.Lock()

        def on_control(message: Message) -> None:
            with lock:
                sample = wire.decode(message.payload)
                assert isinstance(sample, ControlSource)
                drivers.append(sample.source)

        def driver() -> str | None:
            with lock:
                return drivers[-1] if drivers else None

        with (
            MqttBus(broker.url_for("cli"), client_id="t-cli").connect() as cli,
            MqttBus(broker.url_for("cam-scene"), client_id="t-cam").connect() as cam,
            MqttBus(broker.url_for("ctl-arm0"), client_id="t-ctl").connect() as ctl,
            MqttBus(broker.url_for("dev-pi0"), client_id="t-pi0").connect() as pi0,
            MqttBus(broker.url_for("dev-vr0"), client_id="t-vr0").connect() as vr0,
        ):
            cli.subscribe(f"{R}/arm0/{TICK}", picking({"control_source"}, on_control))
            runtime.nodes.start_devices()
            try:
                _wait(lambda: device.stats["actions"] > 3, 60.0, "the policy to act")
                _wait(lambda: driver() == "pi0", 10.0, "the policy to drive")

                # Observation frames: each refused and counted; the policy goes on acting.
                for payload in FRAMES.values():
                    cam.publish(f"{R}/scene/observation", payload)
                _wait(lambda: device.stats["bad_frames"] >= len(FRAMES), 10.0, "bad frames counted")

                # The robot state the policy reads (in the robot's tick): non-finite, forged by another
                # node, an undecodable part, an undecodable tick.
                tick = f"{R}/arm0/{TICK}"
                nan = JointState(Stamp("arm0", 1, now_ns(), now_ns()), UR5E, np.full(6, np.nan), np.zeros(6))
                ctl.publish(tick, wire.encode_bundle([("joint_state", wire.encode(nan))]))
                _wait(lambda: device.stats["bad_state"] >= 1, 10.0, "a non-finite state counted")
                forged = JointState(Stamp("vr0", 1, now_ns(), now_ns()), UR5E, np.zeros(6), np.zeros(6))
                observed_before = runtime.devices["pi0"].observed_dropped
                ctl.publish(tick, wire.encode_bundle([("joint_state", wire.encode(forged))]))
                ctl.publish(tick, wire.encode_bundle([("joint_state", b"\x00garbage")]))
                ctl.publish(tick, b"\x00garbage")
                _wait(lambda: runtime.devices["pi0"].observed_dropped >= observed_before + 3, 10.0, "forged")

                # The policy's action stream: undecodable, non-finite.
                decode_before, nonfinite_before = (
                    control.stats.decode_errors,
                    control.stats.rejected["non_finite"],
                )
                pi0.publish(f"{R}/pi0/joints", b"\xff" * 64)
                bad = JointCommand(
                    Stamp("pi0/joints", 1, now_ns(), now_ns()), (*UR5E, "gripper"), np.full(7, np.inf)
                )
                pi0.publish(f"{R}/pi0/joints", wire.encode(bad))
                _wait(lambda: control.stats.decode_errors > decode_before, 10.0, "an undecodable action")
                _wait(
                    lambda: control.stats.rejected["non_finite"] > nonfinite_before,
                    10.0,
                    "a non-finite action",
                )
                q_before = runtime.robots["arm0"].read_state().positions
                assert np.all(np.isfinite(q_before))

                # Control commands: garbage counted and dropped; a device's login cannot send them.
                bad_before = control.stats.bad_commands
                junk = [b"", b"\xff\xfe", b"take over", b"operator; policy", b"o" * 5000, b"\x00operator"]
                for payload in junk:
                    cli.publish(f"{R}/arm0/control_command", payload, qos=1)
                _wait(
                    lambda: control.stats.bad_commands >= bad_before + len(junk), 10.0, "bad commands counted"
                )
                vr0.publish(f"{R}/arm0/control_command", b"operator", qos=1)  # refused by the ACL
                time.sleep(0.5)
                assert driver() == "pi0"
                assert control.stats.bad_commands == bad_before + len(junk)

                # A valid command hands over (without the clutch) and back.
                cli.publish(f"{R}/arm0/control_command", b"operator", qos=1)
                _wait(lambda: driver() == "vr0", 10.0, "the operator to drive")
                cli.publish(f"{R}/arm0/control_command", b"policy", qos=1)
                _wait(lambda: driver() == "pi0", 10.0, "the policy to drive again")
                acted = device.stats["actions"]
                _wait(lambda: device.stats["actions"] > acted + 3, 30.0, "the policy to go on acting")
                assert control.stats.tick_faults == 0

                # The inference process dies: no more actions, the chain's watchdog stops the arm,
                # and the policy refuses to start again with one line.
                stops = control.stats.safety_events.get("watchdog_stop", 0)
                assert device._process is not None
                pid = device._process.pid
                assert pid is not None
                os.kill(pid, signal.SIGKILL)
                process = device._process
                _wait(lambda: not process.alive, 10.0, "the inference process to end")  # a loaded host
                _wait(lambda: control.stats.safety_events.get("watchdog_stop", 0) > stops, 10.0, "a stop")
            finally:
                runtime.nodes.stop_devices()
            with pytest.raises(DeviceError, match="inference process ended"):
                device.start(lambda sample: None)
