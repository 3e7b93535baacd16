"""``telerig broker acl RIG``: the password, ACL and login files of a rig for an external Mosquitto.

Writes into ``--out`` (a new or empty folder, made 0700):

* ``passwd``: Mosquitto's ``password_file``, one PBKDF2-SHA512 hash per principal (0600);
* ``acl``: Mosquitto's ``acl_file``, the rig's ACL (see :mod:`telerig.bus.acl`) (0600);
* ``logins/<principal>.json``: each principal's bus login (0600), to hand to the host that runs
  it (``telerig safety --credentials logins/cli.json``, a station's ``--credentials``);
* ``mosquitto.conf.example``: the lines that use them.

Passwords are fresh on every run of the command; rerun it and restart Mosquitto to rotate them.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console

from telerig.errors import ConfigError

__all__ = ["add_arguments"]


def add_arguments(subparsers: Any) -> None:
    """Add ``telerig broker`` with its ``acl`` command to the CLI."""
    broker = subparsers.add_parser("broker", help="set up an external MQTT broker for a rig")
    commands = broker.add_subparsers(title="broker commands")
    acl = commands.add_parser(
        "acl", help="write the rig's Mosquitto password file, ACL file and one login file per principal"
    )
    acl.add_argument("rig", help="rig file path or shipped rig name")
    acl.add_argument("--out", type=Path, required=True, help="folder to write into (new or empty)")
    acl.add_argument(
        "--address",
        default=None,
        help="the broker's address written into the login files, e.g. mqtts://broker.lab:8883 "
        "(default: the rig's external broker URL)",
    )
    acl.set_defaults(handler=cmd_broker_acl)


def cmd_broker_acl(args: argparse.Namespace) -> int:
    from telerig.bus.acl import password_file_text, rig_access_policy, write_private
    from telerig.bus.login import BusLogin
    from telerig.bus.mqtt import MqttUrl
    from telerig.config import load_rig
    from telerig.config.schema import EmbeddedBrokerConfig

    rig = load_rig(args.rig)
    address = args.address
    if address is None:
        if isinstance(rig.broker, EmbeddedBrokerConfig):
            raise ConfigError(
                f"rig {rig.name!r} embeds its broker: pass --address with the external broker's URL, "
                "e.g. --address mqtts://broker.lab:8883"
            )
        address = rig.broker.url
    parsed = MqttUrl.parse(address)
    address = f"{'mqtts' if parsed.tls else 'mqtt'}://{parsed.host}:{parsed.port}"  # never a password
    out: Path = args.out
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"--out {out} exists and is not an empty folder; give a new one")
    (out / "logins").mkdir(parents=True, exist_ok=True, mode=0o700)
    out.chmod(0o700)
    policy = rig_access_policy(rig)
    passwd = write_private(out / "passwd", password_file_text(policy.passwords))
    acl = write_private(out / "acl", policy.acl_text())
    for name in policy.principals:
        BusLogin(address, name, policy.password(name), rig.name).write(out / "logins" / f"{name}.json")
    (out / "mosquitto.conf.example").write_text(
        f"# Mosquitto settings for rig {rig.name!r} (see mosquitto.conf(5)); copy passwd and acl where\n"
        "# the broker can read them and set these paths to them.\n"
        "allow_anonymous false\n"
        f"password_file {passwd.resolve()}\n"
        f"acl_file {acl.resolve()}\n"
        "message_size_limit 2097152\n"
    )
    console = Console(highlight=False)
    console.print(
        f"[green]ok[/] rig {rig.name!r}: {len(policy.principals)} principals → {passwd}, {acl}, "
        f"{out / 'logins'}/<principal>.json (address {address})"
    )
    return 0
