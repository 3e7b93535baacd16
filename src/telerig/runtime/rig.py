"""Rig runtime: builds every node of a rig from its config and runs recorded episodes.

This slice runs all nodes of one station in one process, each with its own bus
client, talking through the broker exactly as separate processes would.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import JsonValue

from telerig.bus.base import Bus
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.cameras.config import MujocoCameraConfig
from telerig.config.schema import EmbeddedBrokerConfig, RigConfig
from telerig.devices.base import Device
from telerig.errors import ConfigError
from telerig.ir import wire
from telerig.ir.types import CameraFrame
from telerig.record.recorder import Recorder
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm import AbsolutePoseRetargeter
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.config import AbsolutePoseConfig, TriggerGripperConfig
from telerig.retarget.gripper import TriggerGripper
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime import streams
from telerig.runtime.control_node import ArmBinding, ControlNode, GripperBinding
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.metrics import LatencySummary, StreamSummary
from telerig.safety import SafetyChain
from telerig.store.episodes import EpisodeStore

__all__ = ["EpisodeResult", "RigRuntime"]

log = logging.getLogger(__name__)

#: Called with (seconds elapsed, seconds total) while an episode runs.
ProgressCallback = Callable[[float, float], None]


@dataclass(frozen=True, slots=True)
class EpisodeResult:
    """What one recorded episode produced."""

    episode_id: str
    status: str
    path: Path
    duration_s: float
    streams: list[StreamSummary]
    latency: LatencySummary
    camera_frames: dict[str, int] = field(default_factory=dict)


class RigRuntime:
    """Owns the broker, bus clients, robots, devices, cameras, control nodes and the recorder.

    Use as a context manager; ``close()`` is idempotent and always leaves robots
    stopped and no child process behind.
    """

    def __init__(self, config: RigConfig, *, data_root: Path | None = None) -> None:
        self.config = config
        self.data_root = data_root or config.recording.data_root
        self.store = EpisodeStore(self.data_root)
        self._broker: MosquittoBroker | None = None
        self._buses: list[MqttBus] = []
        self.robots: dict[str, MujocoArm] = {}
        self.devices: dict[str, DeviceNode] = {}
        self.controls: dict[str, ControlNode] = {}
        self.recorder: Recorder | None = None
        self._cameras: list[Any] = []
        self._closed = False

    # -- lifecycle -----------------------------------------------------------------------------

    def __enter__(self) -> RigRuntime:
        try:
            self.open()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Start the broker (if embedded), connect robots and start control nodes."""
        cfg = self.config
        url = self._start_broker()
        for robot_cfg in cfg.robots:
            robot = robot_cfg.build()
            robot.connect()
            self.robots[robot_cfg.id] = robot
        for device_cfg in cfg.devices:
            device: Device = device_cfg.build()
            self.devices[device_cfg.id] = DeviceNode(cfg.name, device, self._bus(url, f"dev-{device_cfg.id}"))
        for robot_cfg in cfg.robots:
            self.controls[robot_cfg.id] = self._build_control(robot_cfg.id, url)
        self.recorder = Recorder(cfg.name, self._bus(url, "recorder"), self._expected_rates())
        for node in self.controls.values():
            node.start()

    def close(self) -> None:
        """Stop devices, cameras and control; stop robots; disconnect; stop the broker. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for device in self.devices.values():
            _quietly(device.stop)
        for camera in self._cameras:
            _quietly(camera.stop)
        for node in self.controls.values():
            _quietly(node.stop)
        for robot in self.robots.values():
            _quietly(robot.close)
        if self.recorder is not None:
            _quietly(self.recorder.close)
        for bus in self._buses:
            _quietly(bus.close)
        if self._broker is not None:
            _quietly(self._broker.stop)

    # -- building ------------------------------------------------------------------------------

    def _start_broker(self) -> str:
        broker = self.config.broker
        if isinstance(broker, EmbeddedBrokerConfig):
            self._broker = MosquittoBroker(port=broker.port, max_queued_messages=broker.max_queued_messages)
            self._broker.start()
            return self._broker.url
        return broker.url

    def _bus(self, url: str, node: str) -> MqttBus:
        bus = MqttBus(url, client_id=f"{self.config.name}-{node}")
        bus.connect()
        self._buses.append(bus)
        return bus

    def _build_control(self, robot_id: str, url: str) -> ControlNode:
        cfg = self.config
        robot = self.robots[robot_id]
        robot_cfg = next(r for r in cfg.robots if r.id == robot_id)
        arm: ArmBinding | None = None
        gripper: GripperBinding | None = None
        for binding in cfg.bindings:
            if binding.robot != robot_id:
                continue
            topic = str(Topic(cfg.name, binding.device, binding.part))
            retargeter = binding.retargeter
            if binding.target == "arm" and isinstance(retargeter, AbsolutePoseConfig):
                ik = ArmIK(robot.scene, residual_threshold_m=retargeter.residual_threshold_m)
                arm = ArmBinding(
                    topic,
                    AbsolutePoseRetargeter(
                        Alignment.from_config(retargeter.alignment), ik, robot.joint_names
                    ),
                )
            elif binding.target == "gripper" and isinstance(retargeter, TriggerGripperConfig):
                gripper = GripperBinding(topic, TriggerGripper(retargeter.source))
            else:
                raise ConfigError(
                    f"binding {binding.device}.{binding.part} → {robot_id}.{binding.target}: retargeter "
                    f"{retargeter.type!r} cannot drive target {binding.target!r}. "
                    "Use absolute_pose for 'arm' and trigger_gripper for 'gripper'"
                )
        rate = float(getattr(robot_cfg, "control_rate_hz", 100.0))
        s = cfg.safety
        safety = SafetyChain.default(
            robot.limits,
            velocity_fraction=s.velocity_scale,
            ramp_initial_fraction=s.start_velocity_fraction,
            ramp_duration_s=s.start_ramp_s,
            hold_timeout_s=s.hold_timeout_ms / 1e3,
            stop_timeout_s=s.watchdog_timeout_ms / 1e3,
            period_s=1.0 / rate,
            source_id=f"{robot_id}/safety",
        )
        return ControlNode(
            cfg.name, robot, safety, self._bus(url, f"ctl-{robot_id}"), control_rate_hz=rate, arm=arm, gripper=gripper
        )

    def _expected_rates(self) -> dict[str, float]:
        cfg = self.config
        rates: dict[str, float] = {}
        for binding in cfg.bindings:
            device = next(d for d in cfg.devices if d.id == binding.device)
            rates[str(Topic(cfg.name, binding.device, binding.part))] = float(getattr(device, "rate_hz", 0.0))
        for robot_cfg in cfg.robots:
            rate = float(getattr(robot_cfg, "control_rate_hz", 100.0))
            for stream in (
                streams.JOINT_REQUESTED,
                streams.JOINT_SENT,
                streams.GRIPPER_REQUESTED,
                streams.GRIPPER_SENT,
                streams.JOINT_STATE,
            ):
                rates[str(Topic(cfg.name, robot_cfg.id, stream))] = rate
        for camera_cfg in cfg.cameras:
            rates[str(Topic(cfg.name, camera_cfg.id, streams.CAMERA_FRAMES))] = camera_cfg.fps
        return rates

    # -- episodes ------------------------------------------------------------------------------

    def run_episode(
        self, duration_s: float | None = None, *, progress: ProgressCallback | None = None
    ) -> EpisodeResult:
        """Record one episode: start devices and cameras, run for ``duration_s``, commit.

        On any exception (including Ctrl-C) the devices stop, the robots hold,
        and the episode is moved to the incomplete partition with the reason;
        earlier episodes are never touched.
        """
        assert self.recorder is not None, "open() the runtime first"
        cfg = self.config
        duration = duration_s if duration_s is not None else cfg.recording.episode_duration_s
        draft = self.store.begin(rig=cfg.name, task=cfg.recording.task, operator=cfg.recording.operator)
        for node in self.controls.values():
            node.latency.reset()
        for robot in self.robots.values():
            robot.reset_objects()
        self.recorder.start(draft.mcap_path)
        try:
            with self._cameras_running(draft.camera_path) as encoders:
                for device in self.devices.values():
                    device.start()
                try:
                    _wait(duration, progress)
                finally:
                    for device in self.devices.values():
                        device.stop()
            camera_frames = {name: enc.frames for name, enc in encoders.items()}
            stream_stats = self.recorder.stop()
        except BaseException as exc:
            _quietly(self.recorder.stop)
            reason = "interrupted by operator (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else repr(exc)
            draft.abandon(reason)
            raise
        latency = self._latency()
        extra: dict[str, JsonValue] = {
            "streams": [_json(s) for s in stream_stats],
            "cameras": {name: {"file": f"cameras/{name}.mp4", "frames": n} for name, n in camera_frames.items()},
            "latency_ms": _json(latency),
            "safety_events": {rid: dict(node.safety.counts) for rid, node in self.controls.items()},
            "malformed_messages": dict(self.recorder.malformed),
        }
        try:
            manifest = draft.commit(extra)
        except BaseException as exc:
            draft.abandon(f"commit failed: {exc!r}")
            raise
        return EpisodeResult(
            manifest.id,
            manifest.status,
            self.store.episode_dir(manifest.id),
            manifest.duration_s or 0.0,
            stream_stats,
            latency,
            camera_frames,
        )

    def _latency(self) -> LatencySummary:
        from telerig.runtime.metrics import LatencyTracker

        merged = LatencyTracker()
        for node in self.controls.values():
            for value in node.latency.values_ns():
                merged.add(int(value))
        return merged.summary()

    @contextlib.contextmanager
    def _cameras_running(self, camera_path: Callable[[str], Path]) -> Iterator[dict[str, Any]]:
        from telerig.cameras.encoder import VideoEncoder
        from telerig.cameras.mujoco_camera import MujocoCamera

        encoders: dict[str, Any] = {}
        results: dict[str, Any] = {}
        cameras: list[MujocoCamera] = []
        cfg = self.config
        try:
            for camera_cfg in cfg.cameras:
                if not isinstance(camera_cfg, MujocoCameraConfig):
                    raise ConfigError(f"cameras: type {camera_cfg.type!r} is not supported by this runtime yet")
                encoder = VideoEncoder(
                    camera_path(camera_cfg.id), width=camera_cfg.width, height=camera_cfg.height, fps=camera_cfg.fps
                )
                encoders[camera_cfg.id] = encoder
                bus = self.recorder_bus
                topic = str(Topic(cfg.name, camera_cfg.id, streams.CAMERA_FRAMES))

                def on_frame(image: Any, meta: CameraFrame, enc: Any = encoder, t: str = topic) -> None:
                    enc.submit(image, meta.stamp.capture_ns)
                    bus.publish(t, wire.encode(meta))

                camera = MujocoCamera(
                    camera_cfg.id,
                    camera_cfg.camera,
                    self.robots[camera_cfg.robot].locked,
                    width=camera_cfg.width,
                    height=camera_cfg.height,
                    fps=camera_cfg.fps,
                    on_frame=on_frame,
                )
                cameras.append(camera)
                self._cameras.append(camera)
            for camera in cameras:
                camera.start()
            yield results
        finally:
            for camera in cameras:
                camera.stop()
                self._cameras.remove(camera)
            for name, encoder in encoders.items():
                results[name] = encoder.finish()

    @property
    def recorder_bus(self) -> Bus:
        assert self.recorder is not None
        return self.recorder.bus


def _wait(duration_s: float, progress: ProgressCallback | None) -> None:
    start = time.monotonic()
    stop = threading.Event()
    while True:
        elapsed = time.monotonic() - start
        if progress is not None:
            progress(min(elapsed, duration_s), duration_s)
        if elapsed >= duration_s:
            return
        stop.wait(min(0.1, duration_s - elapsed))


def _json(obj: Any) -> dict[str, JsonValue]:
    """A slotted stats dataclass as JSON values (NaN becomes null)."""
    out: dict[str, JsonValue] = {}
    for name in obj.__slots__:
        value = getattr(obj, name)
        out[name] = None if isinstance(value, float) and math.isnan(value) else value
    return out


def _quietly(fn: Callable[[], object]) -> None:
    try:
        fn()
    except Exception:
        log.exception("error during shutdown in %s", getattr(fn, "__qualname__", fn))
