"""``telerig device takeover confirm|deny``: the operator's answer to a page asking to take over a device.

A WebXR device with ``takeover: confirm`` holds a second page until the operator answers; this
publishes ``{"takeover": "confirm"}`` (or ``"deny"``) on ``telerig/v1/<rig>/<device>/command`` and
prints the device's reply from its ``events`` stream. Exit status 0 when the device confirmed the
answer, 1 when nothing was waiting or no reply came within ``--timeout``, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import queue
import secrets
from typing import Any

from telerig.cli.bus_options import add_bus_options, bus_connection
from telerig.errors import ConfigError

__all__ = ["add_arguments"]


def add_arguments(subparsers: Any) -> None:
    """Add ``telerig device takeover`` to the CLI."""
    device = subparsers.add_parser("device", help="answer a running rig's devices (a WebXR takeover)")
    commands = device.add_subparsers(title="device commands")
    p = commands.add_parser("takeover", help="confirm or deny the page waiting to take over a WebXR device")
    p.add_argument("answer", choices=("confirm", "deny"), help="let the waiting page drive, or refuse it")
    p.add_argument("--rig", required=True, help="the running rig's file path or shipped rig name")
    p.add_argument("--device", required=True, help="device id, e.g. browser")
    add_bus_options(p)
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the device's reply")
    p.set_defaults(handler=cmd_takeover)


def cmd_takeover(args: argparse.Namespace) -> int:
    from telerig.bus.base import Message
    from telerig.bus.mqtt import MqttBus
    from telerig.bus.topics import Topic
    from telerig.config import load_rig

    rig = load_rig(args.rig)
    devices = [d.id for d in rig.devices]
    if args.device not in devices:
        raise ConfigError(
            f"--device {args.device!r} is not a device of rig {rig.name!r}. Valid: {', '.join(devices)}"
        )
    url, tls = bus_connection(args, rig)
    replies: queue.Queue[str] = queue.Queue()

    def on_event(message: Message) -> None:
        try:
            event = json.loads(message.payload)
        except ValueError:
            return
        if isinstance(event, dict) and event.get("code") == "command_reply":
            replies.put(str(event.get("reason", "")))

    with MqttBus(url, client_id=f"cli-device-{secrets.token_hex(3)}", tls=tls) as bus:
        bus.subscribe(str(Topic(rig.name, args.device, "events")), on_event, qos=1)
        command = json.dumps({"takeover": args.answer}).encode()
        bus.publish(str(Topic(rig.name, args.device, "command")), command, qos=1)
        try:
            reply = replies.get(timeout=args.timeout)
        except queue.Empty:
            print(f"{args.device}: no reply within {args.timeout:g} s (is the rig running on this broker?)")
            return 1
    print(reply)
    return 0 if ("confirmed" in reply or "denied" in reply) else 1
