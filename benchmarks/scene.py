"""The operator scene's cost on the server (issue 17's render budget): what a 500 Hz joint stream costs
the bus thread, what one feed tick costs, and how often a client is sent state.

The demo rig (UR5e) behind a real Mosquitto with its ACL, the control center's gateway as ``web``:

* bus thread, per joint_state message: the scene hub's handler (keep the newest payload, size
  checked) against the baseline of decoding it and running the forward kinematics per message
  (what relaying every message would cost), both on real protobuf bytes;
* one feed tick (``SceneHub.state``: decode the newest payloads, FK, aids) and its JSON size;
* the scene message (geometry, sent once) size;
* end to end: the control node's login publishes joint states at 500 Hz for ``--seconds`` while a
  WebSocket client (TestClient, with the login, Origin and CSRF subprotocol) counts the state
  messages it gets: bounded by SCENE_HZ whatever the control rate.

Usage: python benchmarks/scene.py [--seconds 3] [--out benchmarks/results/scene.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from rich.console import Console
from rich.table import Table

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.types import JointState, Stamp
from telerig.robots.models import arm_model
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway
from telerig.server.routes_scene import SCENE_SUBPROTOCOL
from telerig.server.scene import SCENE_HZ, SceneHub, robot_geometry

TOPIC = "telerig/v1/demo/arm0/joint_state"
UR5E = arm_model("ur5e_robotiq85")


def _per_call_us(fn: object, calls: int) -> float:
    assert callable(fn)
    start = time.perf_counter()
    for i in range(calls):
        fn(i)
    return (time.perf_counter() - start) / calls * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="end-to-end run at 500 Hz [s]")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/scene.json"))
    args = parser.parse_args()
    console = Console()
    config = load_rig("demo")
    robot = config.robots[0]
    rng = np.random.default_rng(0)
    payloads = [
        wire.encode(JointState(Stamp.now("arm0", i), UR5E.joints, rng.uniform(-3, 3, 6), np.zeros(6)))
        for i in range(1000)
    ]
    messages = [Message(TOPIC, p, time.time_ns()) for p in payloads]
    console.print("building the UR5e's scene geometry...")
    t0 = time.perf_counter()
    geometry = robot_geometry(robot)
    build_s = time.perf_counter() - t0

    with (
        tempfile.TemporaryDirectory() as tmp,
        MosquittoBroker(access=rig_access_policy(config), owner=STATION) as broker,
    ):
        gateway = RigGateway(config, broker.url_for(WEB)).start()
        try:
            hub = SceneHub(gateway)
            hub.start()
            handler_us = _per_call_us(lambda i: hub._on_message(messages[i % 1000]), 20_000)

            def baseline(i: int) -> None:
                state = wire.decode(payloads[i % 1000])
                assert isinstance(state, JointState)
                geometry.poses(dict(zip(state.names, state.positions.tolist(), strict=True)))

            baseline_us = _per_call_us(baseline, 2_000)

            def tick(i: int) -> None:
                hub._on_message(messages[i % 1000])  # a new payload every tick: nothing cached
                hub._state = None
                json.dumps(hub.state(), allow_nan=False)

            tick_us = _per_call_us(tick, 500)
            state_bytes = len(json.dumps(hub.state(), allow_nan=False))
            scene_bytes = len(json.dumps(hub.document(), allow_nan=False))

            accounts = AccountStore.open(
                Path(tmp), hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
            )
            accounts.add_user("vic", "viewer", "correct horse battery")
            client = TestClient(create_app(accounts, gateway=gateway))
            with client:
                csrf = client.post(
                    "/api/login", json={"user": "vic", "password": "correct horse battery"}
                ).json()["csrf"]
                publisher = MqttBus(broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
                stop = threading.Event()
                sent = [0]

                def publish() -> None:
                    period = 1 / 500
                    next_at = time.perf_counter()
                    while not stop.is_set():
                        publisher.publish(TOPIC, payloads[sent[0] % 1000])
                        sent[0] += 1
                        next_at += period
                        time.sleep(max(0.0, next_at - time.perf_counter()))

                with client.websocket_connect(
                    "/api/scene",
                    subprotocols=[SCENE_SUBPROTOCOL, f"csrf.{csrf}"],
                    headers={"origin": "http://testserver"},
                ) as ws:
                    ws.receive_text()  # the scene
                    thread = threading.Thread(target=publish, daemon=True)
                    thread.start()
                    start = time.perf_counter()
                    states = 0
                    while time.perf_counter() - start < args.seconds:
                        ws.receive_text()
                        states += 1
                    elapsed = time.perf_counter() - start
                    stop.set()
                    thread.join()
                publisher.close()
        finally:
            gateway.close()

    published_hz = sent[0] / elapsed
    state_hz = states / elapsed
    result = {
        "host": platform.node(),
        "python": platform.python_version(),
        "geometry_build_s": round(build_s, 3),
        "bus_handler_us_per_message": round(handler_us, 2),
        "baseline_decode_fk_us_per_message": round(baseline_us, 2),
        "handler_vs_baseline": round(handler_us / baseline_us, 4),
        "feed_tick_us": round(tick_us, 1),
        "feed_cpu_fraction_at_scene_hz": round(tick_us * 1e-6 * SCENE_HZ, 5),
        "state_message_bytes": state_bytes,
        "scene_message_bytes": scene_bytes,
        "published_hz": round(published_hz, 1),
        "states_received_hz": round(state_hz, 1),
        "scene_hz_bound": SCENE_HZ,
    }
    table = Table(title="operator scene: server cost (demo rig, UR5e)")
    table.add_column("what")
    table.add_column("value", justify="right")
    table.add_row("geometry build (once per model)", f"{build_s:.2f} s")
    table.add_row("bus thread per joint_state: scene hub", f"{handler_us:.1f} us")
    table.add_row("bus thread per joint_state: decode + FK (baseline)", f"{baseline_us:.1f} us")
    table.add_row("hub / baseline", f"{handler_us / baseline_us:.3f}")
    table.add_row("feed tick (decode newest, FK, aids, JSON)", f"{tick_us:.0f} us")
    table.add_row(f"feed CPU at {SCENE_HZ:g} Hz", f"{100 * tick_us * 1e-6 * SCENE_HZ:.2f} %")
    table.add_row("state message", f"{state_bytes} B")
    table.add_row("scene message (once)", f"{scene_bytes / 1024:.0f} KiB")
    table.add_row("joint states published", f"{published_hz:.0f} Hz")
    table.add_row("state messages a client got", f"{state_hz:.1f} Hz (bound {SCENE_HZ:g})")
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    console.print(f"wrote {args.out}")
    return 0 if state_hz <= SCENE_HZ * 1.1 else 1


if __name__ == "__main__":
    raise SystemExit(main())
