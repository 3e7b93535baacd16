"""``telerig safety estop|reset``: an operator's e-stop or reset of a running rig's robots, over the bus.

Publishes a :class:`~telerig.safety.commands.SafetyCommand`, then watches each named robot's
retained control status until it confirms (``estopped`` after an e-stop, anything else after a
reset) and prints one line per robot. Exit status 0 when every robot confirmed, 1 when one did
not within ``--timeout``, 2 for bad arguments (unknown robot, no broker URL or login).

It logs in as the rig's ``cli`` principal from the login file ``telerig run`` keeps in the data
root while the rig runs, or as given (``--credentials``, ``--username``/``--password``).
"""

from __future__ import annotations

import argparse
import secrets
import sys
import threading
import time
from typing import Any

from rich.console import Console

from telerig.cli.bus_options import add_bus_options, bus_connection
from telerig.errors import ConfigError

__all__ = ["add_arguments"]


def add_arguments(subparsers: Any) -> None:
    """Add ``telerig safety`` with its ``estop`` and ``reset`` commands to the CLI."""
    safety = subparsers.add_parser("safety", help="e-stop or reset robots of a running rig")
    commands = safety.add_subparsers(title="safety commands")
    for name, help_text in (
        ("estop", "latch the e-stop of one robot (--robot) or of every robot, and stop its driver"),
        ("reset", "release the e-stop of one robot (--robot) or of every robot after a fault or e-stop"),
    ):
        p = commands.add_parser(name, help=help_text)
        p.add_argument("--rig", required=True, help="the running rig's file path or shipped rig name")
        p.add_argument("--robot", default=None, help="robot id (default: every robot of the rig)")
        add_bus_options(p)
        p.add_argument("--operator", default=None, help="who sends it (logged)")
        p.add_argument("--reason", default=None, help="why (shown in the e-stop's alert)")
        p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for confirmation")
        p.set_defaults(handler=cmd_safety, command=name)


def cmd_safety(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from telerig.bus.mqtt import MqttBus
    from telerig.bus.topics import Topic
    from telerig.config import load_rig
    from telerig.runtime import streams
    from telerig.safety.commands import SafetyCommand, safety_command_topic

    rig = load_rig(args.rig)
    robot_ids = [r.id for r in rig.robots]
    if args.robot is not None and args.robot not in robot_ids:
        raise ConfigError(
            f"--robot {args.robot!r} is not a robot of rig {rig.name!r}. Valid: {', '.join(robot_ids)}"
        )
    url, tls = bus_connection(args, rig)
    try:
        command = SafetyCommand(
            command=args.command, robot=args.robot, reason=args.reason, operator=args.operator, source="cli"
        )
    except ValidationError as exc:
        raise ConfigError(f"--{exc.errors()[0]['loc'][0]}: {exc.errors()[0]['msg']}") from None

    targets = robot_ids if args.robot is None else [args.robot]
    status: dict[str, str] = {}
    changed = threading.Condition()

    def on_status(message: Any) -> None:
        robot = Topic.parse(message.topic).node
        with changed:
            status[robot] = message.payload.decode(errors="replace")
            changed.notify_all()

    def confirmed(states: dict[str, str], robot: str) -> bool:
        state = states.get(robot)
        return state == "estopped" if args.command == "estop" else state not in (None, "estopped")

    with MqttBus(url, client_id=f"cli-safety-{secrets.token_hex(3)}", tls=tls) as bus:
        for robot in targets:
            bus.subscribe(str(Topic(rig.name, robot, streams.STATUS)), on_status, qos=1)
        bus.publish(safety_command_topic(rig.name), command.model_dump_json().encode(), qos=1)
        deadline = time.monotonic() + args.timeout
        with changed:
            while not all(confirmed(status, r) for r in targets) and time.monotonic() < deadline:
                changed.wait(max(0.0, deadline - time.monotonic()))
            final = dict(status)
    console = Console(width=None if sys.stdout.isatty() else 130)
    failed = [r for r in targets if not confirmed(final, r)]
    for robot in targets:
        line = f"{robot}: {final.get(robot, 'no status (is the rig running on this broker?)')}"
        if robot in failed:
            console.print(f"[bold red]{line}[/] (not confirmed within {args.timeout:g} s)", highlight=False)
        else:
            console.print(f"[green]{line}[/]", highlight=False)
    return 1 if failed else 0
