"""``telerig session COMMAND``: episode commands to a running rig's session coordinator.

``stop`` and ``discard`` end only the running episode (``telerig run`` goes on with the next one);
``end`` ends the session.
"""

from __future__ import annotations

import argparse

from telerig.cli.bus_options import add_bus_options, bus_connection
from telerig.errors import ConfigError
from telerig.runtime.session import COMMANDS, EpisodeCommand, send_command

__all__ = ["add_arguments"]

_DESCRIPTION = (
    "Send an episode command to a running rig. `stop` ends the running episode and keeps it, "
    "`discard` throws it away; either way `telerig run` goes on with the next episode. "
    "`end` ends the session: `telerig run` keeps the running episode and exits."
)


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``telerig session`` and one sub-command per episode command."""
    session = sub.add_parser(
        "session",
        help="episode commands to a running rig: stop/discard end the running episode, end ends the session",
        description=_DESCRIPTION,
    )
    commands = session.add_subparsers(title="commands", metavar="COMMAND")
    for name, text in COMMANDS.items():
        p = commands.add_parser(name, help=text, description=text[0].upper() + text[1:] + ".")
        p.add_argument(
            "--url",
            default=None,
            help="the running rig's broker URL, as `telerig run` printed it (default: from its login file)",
        )
        p.add_argument("--rig", default="demo", help="rig name, file or shipped rig (default: demo)")
        if name in ("start", "restart", "mark"):
            p.add_argument("--task", default=None, help="task label (default: the previous one)")
            p.add_argument("--operator", default=None, help="operator id (default: the previous one)")
        if name == "mark":
            p.add_argument("--outcome", choices=["success", "failure"], required=True)
        if name in ("pause_device", "resume_device"):
            p.add_argument("--device", required=True, help="the input device's id in the rig")
        if name in ("start", "restart"):
            p.add_argument("--lead-s", type=float, default=None, help="start lead [s] (default: the rig's)")
        p.add_argument("--reason", default=None, help="free text kept in the session status")
        add_bus_options(p)
        p.set_defaults(handler=_cmd_session, command=name)
    session.set_defaults(handler=lambda args: _help(session))


def _help(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def _cmd_session(args: argparse.Namespace) -> int:
    fields = {
        "command": args.command,
        "task": getattr(args, "task", None),
        "operator": getattr(args, "operator", None),
        "outcome": getattr(args, "outcome", None),
        "reason": args.reason,
        "lead_s": getattr(args, "lead_s", None),
        "device": getattr(args, "device", None),
        "source": "cli",
    }
    try:
        command = EpisodeCommand.model_validate({k: v for k, v in fields.items() if v is not None})
    except ValueError as exc:
        raise ConfigError(f"telerig session {args.command}: {exc}") from None
    logins = (args.credentials, args.username, args.password, args.data_root, args.broker)
    if args.url is not None and all(v is None for v in logins):
        send_command(args.url, args.rig, command)
        return 0
    from telerig.config import load_rig

    rig = load_rig(args.rig)
    args.broker = args.broker or args.url
    url, tls = bus_connection(args, rig)
    send_command(url, rig.name, command, tls=tls)
    return 0
