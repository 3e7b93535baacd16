"""The minimal prototype of telerig's control path, the baseline that benchmarks/latency.py compares against.

device → Mosquitto → IK → Mosquitto → robot, nothing else: a device thread publishes a controller
pose (a 44-byte struct: capture stamp, position, orientation, trigger) at 100 Hz; an IK client
turns each pose into UR5e joint targets with the same mink IK telerig uses (``ArmIK``, same model,
same settings) and publishes them (capture stamp + 6 doubles); a robot client writes them into the
position servos of the same MuJoCo scene, stepped at 500 Hz in real time by a physics thread, and
notes the time it applied each one. No validation, safety chain, health, metrics or recording:
whatever telerig measures beyond this prototype is the price of those.

Both MQTT clients (paho-mqtt, MQTT 3.1.1, QoS 0) set TCP_NODELAY, and so does the broker, as
telerig's do. The latency is the device's capture stamp → the robot's apply stamp, both
``time.time_ns()`` in one process, like telerig's own figure.

Usage: python benchmarks/prototype_path.py [--duration 15] (prints p50/p99 and the interval std);
benchmarks/latency.py imports :func:`measure_prototype` to measure it in the same run.
"""

from __future__ import annotations

import argparse
import os
import socket
import struct
import threading
import time
from typing import Any
from urllib.parse import unquote, urlsplit

import numpy as np

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import paho.mqtt.client as mqtt

from telerig.bus.broker import MosquittoBroker
from telerig.retarget.arm_ik import ArmIK
from telerig.robots.sim.scene import build_arm_scene

_POSE = struct.Struct("<q3d4df")  # capture ns, position (3), orientation wxyz (4), trigger
_TARGET = struct.Struct("<q6d")  # capture ns, 6 joint targets [rad]
_RATE_HZ = 100.0
_PHYSICS_HZ = 500.0


def _client(broker: MosquittoBroker, name: str) -> mqtt.Client:
    """A connected paho client with Nagle off, its network loop on its own thread."""
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=name, protocol=mqtt.MQTTv311)
    url = urlsplit(broker.url)  # mqtt://user:password@127.0.0.1:port
    host, port = url.hostname or "127.0.0.1", url.port or 1883
    client.username_pw_set(unquote(url.username or ""), unquote(url.password or ""))
    connected = threading.Event()

    def on_connect(c: mqtt.Client, _u: Any, _f: Any, _rc: Any, _p: Any = None) -> None:
        sock = c.socket()
        if isinstance(sock, socket.socket):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        connected.set()

    client.on_connect = on_connect
    client.connect(host, port)
    client.loop_start()
    if not connected.wait(5.0):
        raise RuntimeError(f"prototype client {name} did not connect to {host}:{port}")
    return client


def measure_prototype(duration_s: float = 15.0) -> dict[str, Any]:
    """Run the prototype path for ``duration_s`` and return its latency and command-interval statistics."""
    ik = ArmIK()
    scene = build_arm_scene()
    model, data = scene.model, mujoco.MjData(scene.model)
    actuators = np.array([model.actuator(a).id for a in scene.arm_actuators])
    qadr = np.array([model.joint(j).qposadr[0] for j in scene.arm_joints])
    data.qpos[qadr] = scene.home
    data.ctrl[actuators] = scene.home
    mujoco.mj_forward(model, data)
    lock = threading.Lock()
    stop = threading.Event()
    # The operator's hand circles 5 cm around the gripper's home pose, pointing down.
    home_position, home_orientation = ik.forward(scene.home)
    latency_ns: list[int] = []
    applied_ns: list[int] = []

    def physics() -> None:
        period = 1.0 / _PHYSICS_HZ
        next_t = time.perf_counter()
        while not stop.is_set():
            with lock:
                mujoco.mj_step(model, data)
            next_t += period
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

    with MosquittoBroker() as broker:
        device = _client(broker, "proto-device")
        ik_node = _client(broker, "proto-ik")
        robot = _client(broker, "proto-robot")
        # The IK client solves the newest pose only (a backlog would only add latency), on its own
        # thread so its network loop keeps reading, as telerig's control node does.
        latest: list[bytes] = []
        pose_ready = threading.Event()

        def on_pose(_c: mqtt.Client, _u: Any, msg: mqtt.MQTTMessage) -> None:
            latest[:] = [msg.payload]
            pose_ready.set()

        def solve_loop() -> None:
            q_now = scene.home.copy()
            while not stop.is_set():
                if not pose_ready.wait(0.1):
                    continue
                pose_ready.clear()
                stamp, *values = _POSE.unpack(latest[0])
                result = ik.solve(values[0:3], values[3:7], q_now, 1.0 / _RATE_HZ)
                q_now = np.array(result.q)
                ik_node.publish("proto/target", _TARGET.pack(stamp, *q_now), qos=0)

        def on_target(_c: mqtt.Client, _u: Any, msg: mqtt.MQTTMessage) -> None:
            stamp, *q = _TARGET.unpack(msg.payload)
            with lock:
                data.ctrl[actuators] = q
            now = time.time_ns()
            latency_ns.append(now - stamp)
            applied_ns.append(now)

        ik_node.on_message = on_pose
        robot.on_message = on_target
        ik_node.subscribe("proto/pose", qos=0)
        robot.subscribe("proto/target", qos=0)
        time.sleep(0.5)  # both subscriptions acknowledged before the first sample
        threads = [
            threading.Thread(target=physics, name="proto-physics", daemon=True),
            threading.Thread(target=solve_loop, name="proto-ik", daemon=True),
        ]
        for thread in threads:
            thread.start()
        period = 1.0 / _RATE_HZ
        start = time.perf_counter()
        next_t = start
        k = 0
        while time.perf_counter() - start < duration_s:
            angle = 2.0 * np.pi * 0.2 * k * period
            position = home_position + 0.05 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
            payload = _POSE.pack(time.time_ns(), *position, *home_orientation, 0.0)
            device.publish("proto/pose", payload, qos=0)
            k += 1
            next_t += period
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        time.sleep(0.2)
        stop.set()
        for thread in threads:
            thread.join(2.0)
        for c in (device, ik_node, robot):
            c.loop_stop()
            c.disconnect()
    lat_ms = np.array(latency_ns, dtype=np.float64) / 1e6
    intervals_ms = np.diff(np.array(applied_ns, dtype=np.int64)) / 1e6
    return {
        "config": "minimal prototype (device → Mosquitto → IK → Mosquitto → robot)",
        "commands": int(lat_ms.size),
        "samples_sent": k,
        "latency_p50_ms": float(np.percentile(lat_ms, 50)),
        "latency_p99_ms": float(np.percentile(lat_ms, 99)),
        "latency_max_ms": float(lat_ms.max()),
        "interval_mean_ms": float(intervals_ms.mean()),
        "interval_std_ms": float(intervals_ms.std()),
        "jitter_p99_ms": float(np.percentile(np.abs(intervals_ms - 1e3 / _RATE_HZ), 99)),
        "camera_frames": 0,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=15.0, help="seconds to run [s]")
    args = parser.parse_args()
    r = measure_prototype(args.duration)
    print(
        f"{r['config']}: {r['commands']} of {r['samples_sent']} applied, p50 {r['latency_p50_ms']:.2f} ms, "
        f"p99 {r['latency_p99_ms']:.2f} ms, max {r['latency_max_ms']:.2f} ms, "
        f"interval {r['interval_mean_ms']:.2f} ± {r['interval_std_ms']:.2f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
