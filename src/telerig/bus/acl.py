"""Who may publish what on a rig's broker: principals, passwords, Mosquitto's ACL and password files.

Every bus client logs in as a *principal* (an MQTT username) and may publish only on the topics its
principal is granted; every principal may read the rig's topics. :func:`rig_access_policy` derives
the principals from a rig:

=================  ============================================================================
principal          may publish on (``R`` = ``telerig/v1/<rig>``)
=================  ============================================================================
``station``        ``R/#``: the first station (coordinator, recorder, safety supervisor)
``station-<id>``   ``R/#``: every other station (it follows the session and records its part)
``dev-<id>``       ``R/<id>/#``: a device node, its own streams only
``cam-<id>``       ``R/<id>/#``: a camera node
``ctl-<robot>``    ``R/<robot>/#``: a control node, its robot's state and command-sent streams
``robot-<robot>``  a robot process (``runtime.isolation: processes``): its robot, the devices and
                   cameras it hosts, its own safety alerts and ``R/safety/halt``
``cli``, ``web``   ``R/safety/command``, ``R/coordinator/command``, every device's ``command``
                   and every robot's ``<aid>_command`` (motion scale, fixture, whole-body mode,
                   control handover): operators' commands; and ``R/voice/#`` (what a voice or
                   text command heard and said back, the view it chose)
``web``            also every device's ``page_in``: the messages of an operator's page (the
                   WebXR page) that ``telerig serve`` relays after its login and role check;
                   and every robot's and camera's ``latency_view`` (the stages its pages report)
=================  ============================================================================

So a device cannot forge a robot's joint stream, an e-stop, a reset or a session command. The
passwords are generated per run (:meth:`AccessPolicy.generate`); :func:`password_file_text` hashes
them in Mosquitto's PBKDF2-SHA512 format (``$7$``, as ``mosquitto_passwd`` writes them).
"""

from __future__ import annotations

import base64
import hashlib
import os
import secrets
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from telerig.bus.catalogue import (
    COMMAND,
    CONTROL,
    COORDINATOR,
    FIXTURE,
    HALT,
    LATENCY_VIEW,
    MOTION_SCALE,
    PAGE_IN,
    PLAN,
    SAFETY,
    VOICE,
    WBC_MODE,
)
from telerig.bus.topics import Topic
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError

__all__ = [
    "AID_COMMANDS",
    "CLI",
    "OWNER",
    "STATION",
    "WEB",
    "AccessPolicy",
    "Principal",
    "new_password",
    "password_file_text",
    "principal_for_node",
    "rig_access_policy",
    "robot_process_principal",
    "station_principal",
    "write_private",
]

#: What a generated password is drawn from: letters and digits only, so that it never starts with
#: ``-`` (``--password -x...`` reads as a missing argument) and needs no quoting in a shell.
_PASSWORD_ALPHABET = string.ascii_letters + string.digits
#: 32 characters of 62: 190 bits.
_PASSWORD_LENGTH = 32

#: The principal of the first station (coordinator, recorder, supervisor).
STATION = "station"
#: The operator command line (``telerig safety``, ``telerig session``).
CLI = "cli"
#: The web UI's server.
WEB = "web"
#: The only principal of a broker started without a rig: it may publish anywhere.
OWNER = "owner"
#: Operators' commands to a robot's live aids, on ``R/<robot>/<stream>``.
AID_COMMANDS = tuple(f"{aid}_{COMMAND}" for aid in (MOTION_SCALE, FIXTURE, WBC_MODE, CONTROL, PLAN))
#: Mosquitto's PBKDF2 iterations for ``$7$`` hashes (its ``mosquitto_passwd`` default).
_PBKDF2_ITERATIONS = 101
_SALT_BYTES = 12


@dataclass(frozen=True, slots=True)
class Principal:
    """One MQTT user: its name and the topic filters it may publish on (it may read ``read``).

    Attributes:
        name: MQTT username.
        write: Topic filters (MQTT wildcards) it may publish on.
        read: Topic filters it may subscribe to.
    """

    name: str
    write: tuple[str, ...]
    read: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class AccessPolicy:
    """Principals with their passwords: what a broker enforces and what clients log in with.

    Attributes:
        principals: By name.
        passwords: Password of every principal, by name.
    """

    principals: Mapping[str, Principal]
    passwords: Mapping[str, str] = field(repr=False)

    @classmethod
    def generate(cls, principals: Iterable[Principal]) -> AccessPolicy:
        """A policy with a fresh random password (:func:`new_password`) per principal."""
        by_name = {p.name: p for p in principals}
        return cls(by_name, {name: new_password() for name in by_name})

    @classmethod
    def open_to_owner(cls) -> AccessPolicy:
        """One principal, :data:`OWNER`, allowed everything (a broker not bound to a rig)."""
        return cls.generate([Principal(OWNER, ("#",), ("#",))])

    def password(self, principal: str) -> str:
        """The password of ``principal``.

        Raises:
            ConfigError: No such principal; the message lists them.
        """
        try:
            return self.passwords[principal]
        except KeyError:
            raise ConfigError(
                f"no bus principal {principal!r}. Valid: {', '.join(sorted(self.principals))}"
            ) from None

    def acl_text(self) -> str:
        """Mosquitto ``acl_file`` text: one ``user`` block per principal (anything not listed is denied)."""
        lines = ["# telerig bus ACL: generated, one block per principal; anything not granted is denied"]
        for p in self.principals.values():
            lines += ["", f"user {p.name}"]
            lines += [f"topic read {t}" for t in p.read if t not in p.write]
            lines += [f"topic {'readwrite' if t in p.read else 'write'} {t}" for t in p.write]
        return "\n".join(lines) + "\n"


def new_password() -> str:
    """A fresh random bus password: 32 letters and digits (190 bits), safe on any command line."""
    return "".join(secrets.choice(_PASSWORD_ALPHABET) for _ in range(_PASSWORD_LENGTH))


def password_file_text(passwords: Mapping[str, str]) -> str:
    """Mosquitto ``password_file`` text: ``user:$7$iterations$salt$hash`` (PBKDF2-SHA512) per line."""
    lines = []
    for user, password in passwords.items():
        if ":" in user or "\n" in user or "\n" in password:
            raise ConfigError(f"bus principal {user!r}: names and passwords cannot hold ':' or newlines")
        salt = os.urandom(_SALT_BYTES)
        digest = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, _PBKDF2_ITERATIONS, dklen=64)
        salt64, hash64 = base64.b64encode(salt).decode(), base64.b64encode(digest).decode()
        lines.append(f"{user}:$7${_PBKDF2_ITERATIONS}${salt64}${hash64}")
    return "\n".join(lines) + "\n"


def write_private(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` readable by its owner only (0600 from creation, never wider).

    Atomic: the text goes to a new file beside ``path`` that is then renamed over it, so a reader
    (``telerig safety`` reading the login ``telerig run`` is writing) sees the old file or the whole
    new one, never a part; a link at ``path`` is replaced, not followed.
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def robot_process_principal(robot: str) -> str:
    """The principal of the process that hosts ``robot`` (``runtime.isolation: processes``)."""
    return f"robot-{robot}"


def station_principal(config: RigConfig, station: str) -> str:
    """The principal of station ``station`` of ``config``: :data:`STATION` for the first."""
    return STATION if station == config.stations[0].id else f"station-{station}"


def principal_for_node(node: str, station: str = STATION) -> str:
    """The principal a station's bus client named ``node`` logs in as (the runtime's node names).

    ``dev-<id>``, ``cam-<id>`` and ``ctl-<robot>`` have their own principals; the recorder's and
    the safety supervisor's clients (which also carry the session) are the station's, ``station``.
    """
    return node if node.startswith(("dev-", "cam-", "ctl-")) else station


def rig_access_policy(config: RigConfig) -> AccessPolicy:
    """The principals of ``config`` (see the module docs) with fresh passwords."""
    root = f"telerig/v1/{config.name}"
    every = (f"{root}/#",)

    def own(*nodes: str) -> tuple[str, ...]:
        return tuple(f"{root}/{Topic(config.name, n, 'x').node}/#" for n in nodes)

    commands = (
        f"{root}/{SAFETY}/{COMMAND}",
        f"{root}/{COORDINATOR}/{COMMAND}",
        *(f"{root}/{d.id}/{COMMAND}" for d in config.devices),  # e.g. a WebXR takeover's confirmation
        *(f"{root}/+/{stream}" for stream in AID_COMMANDS),
        f"{root}/{VOICE}/#",
    )
    principals = [Principal(STATION, every, every)]
    principals += [Principal(f"station-{s.id}", every, every) for s in config.stations[1:]]
    principals += [Principal(f"dev-{d.id}", own(d.id), every) for d in config.devices]
    principals += [Principal(f"cam-{c.id}", own(c.id), every) for c in config.cameras]
    principals += [Principal(f"ctl-{r.id}", own(r.id), every) for r in config.robots]
    for robot in config.robots:
        hosted = [robot.id, f"{SAFETY}-{robot.id}", *_hosted_by(config, robot.id, robot.station)]
        principals.append(
            Principal(robot_process_principal(robot.id), (*own(*hosted), f"{root}/{SAFETY}/{HALT}"), every)
        )
    # Only the web server relays operator pages (after its login); the command line has no page.
    pages = tuple(f"{root}/{d.id}/{PAGE_IN}" for d in config.devices)
    views = tuple(
        f"{root}/{n}/{LATENCY_VIEW}"
        for n in (*(r.id for r in config.robots), *(c.id for c in config.cameras))
    )
    principals += [Principal(CLI, commands, every), Principal(WEB, (*commands, *pages, *views), every)]
    return AccessPolicy.generate(principals)


def _hosted_by(config: RigConfig, robot: str, station: str) -> list[str]:
    """The devices and cameras a robot's process hosts: devices bound to it alone, cameras on it."""
    devices = [
        d.id
        for d in config.devices
        if d.station == station and {b.robot for b in config.bindings if b.device == d.id} == {robot}
    ]
    cameras = [c.id for c in config.cameras if c.station == station and getattr(c, "robot", None) == robot]
    return devices + cameras
