"""Registered devices: each its own MQTT login, enforced by the rig's Mosquitto through its files.

An admin registers a *teleoperating* device (an input device of the rig file: a glove, a headset,
a space mouse) or a *teleoperated* one (a robot of the rig file). The control center issues it its
own bus login: the username is the principal :mod:`telerig.bus.acl` gives it (``dev-<id>`` for a
device, ``robot-<robot>`` for a robot's process), the password is random (32 url-safe characters),
shown once to the admin and stored only as Mosquitto's PBKDF2-SHA512 hash (``$7$``, from
:func:`telerig.bus.acl.password_file_text`). What each principal may publish is the rig's ACL
(:meth:`telerig.bus.acl.AccessPolicy.acl_text`): a device its own streams, a robot's process its
robot's; neither the safety nor the coordinator command topics, nor another device's or robot's.

Registrations live in the control database (table ``devices``, beside the accounts). Every
register and revoke rewrites the rig's broker folder, the one ``telerig broker acl RIG --out DIR``
writes for an external Mosquitto (by default ``<data root>/broker/<rig>``):

* ``passwd``: the lines of principals the registry does not manage are kept as they are (the
  station's, ``cli``'s, ``web``'s from ``telerig broker acl``); a registered principal's line is its
  registration's hash (replacing one ``telerig broker acl`` wrote, whose login file
  ``logins/<principal>.json`` is removed: it no longer works); a revoked principal has no line;
* ``acl``: the rig's ACL;
* ``registered.json``: ``{"logins": {principal: hash}}``, the active registrations, for the
  embedded broker (``passwd`` alone does not say which lines the registry manages, and
  ``telerig broker acl`` rewrites them all);

all 0600, replaced atomically (a temporary file renamed over the old one). Mosquitto reads them at
start and again on ``SIGHUP``; on reload it also disconnects a client whose login is gone (measured
with Mosquitto 2.0.11). So the registry signals an external broker when it knows its process:
``reload_pid_file`` names the broker's ``pid_file`` (Mosquitto writes it when its config sets
``pid_file``); without one, the reply says to reload by hand (``kill -HUP <pid>`` or ``systemctl
reload mosquitto``).

The embedded broker of ``telerig run`` (same data root) reads the folder too
(:mod:`telerig.bus.registered`): at start it adds the logins of ``registered.json`` to its per-run
ones, and its watchdog applies a register or revoke within 0.25 s (rewrite, then ``SIGHUP`` of its
Mosquitto, which disconnects a revoked device). The registry does
not signal it: that broker's password file also holds the station's per-run logins, which only
the station knows, so the station rewrites it. A registered device or robot that runs in that
station itself is left out there with a warning
(:func:`telerig.runtime.broker_supervisor.station_logins`): the station's own node keeps its login.
Without a pid file, a registration of a rig whose file embeds its broker says this (reload status
``embedded``).

Passwords are never logged, stored in clear or returned after :meth:`DeviceRegistry.register`.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, get_args

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from telerig.bus.acl import (
    Principal,
    new_password,
    password_file_text,
    rig_access_policy,
    robot_process_principal,
    write_private,
)
from telerig.bus.registered import REGISTERED_FILE
from telerig.config.schema import EmbeddedBrokerConfig, RigConfig
from telerig.errors import TelerigError
from telerig.server.accounts import control_engine

__all__ = [
    "DEVICE_KINDS",
    "BrokerFiles",
    "DeviceError",
    "DeviceKind",
    "DeviceRegistry",
    "Issued",
    "Registration",
    "ReloadResult",
    "UnknownRegistrationError",
]

log = logging.getLogger(__name__)

#: A teleoperating device is one of the rig's input devices; a teleoperated one, one of its robots.
DeviceKind = Literal["teleoperating", "teleoperated"]
DEVICE_KINDS: tuple[DeviceKind, ...] = get_args(DeviceKind)
#: Broker folders of the rigs, under the data root: ``<data root>/broker/<rig>``.
BROKER_FOLDER = "broker"
_PASSWD_LINE = re.compile(r"^([^:\s#][^:]*):(\S+)$")

_meta = sa.MetaData()
_devices = sa.Table(
    "devices",
    _meta,
    sa.Column("rig", sa.String(64), primary_key=True),
    sa.Column("principal", sa.String(80), primary_key=True),
    sa.Column("kind", sa.String(16), nullable=False),
    sa.Column("device", sa.String(64), nullable=False),
    sa.Column("password_hash", sa.String(200), nullable=False),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("created_by", sa.String(32), nullable=False),
    sa.Column("revoked_ns", sa.BigInteger, nullable=True),
    sa.Column("revoked_by", sa.String(32), nullable=True),
)


class DeviceError(TelerigError):
    """A registration was refused (unknown rig or device, already registered); the message says why."""


class UnknownRegistrationError(DeviceError):
    """No registration of that principal on that rig."""


@dataclass(frozen=True, slots=True)
class Registration:
    """A device's registration: rig, principal (its MQTT username), kind, the rig's id of the device
    or robot, when and by whom it was created and (once revoked) revoked [ns, wall clock], and the
    topic filters the rig's ACL lets it publish on."""

    rig: str
    principal: str
    kind: DeviceKind
    device: str
    created_ns: int
    created_by: str
    revoked_ns: int | None
    revoked_by: str | None
    publishes: tuple[str, ...]

    @property
    def active(self) -> bool:
        return self.revoked_ns is None


@dataclass(frozen=True, slots=True)
class ReloadResult:
    """What the broker was told: ``signalled`` (SIGHUP sent to the pid in the pid file),
    ``manual`` (no pid file configured: reload it yourself), ``embedded`` (no pid file, and the rig
    file embeds its broker, whose ``telerig run`` applies the folder itself) or ``failed``;
    ``detail`` says more."""

    status: Literal["signalled", "manual", "failed", "embedded"]
    detail: str


@dataclass(frozen=True, slots=True)
class Issued:
    """A new registration with its password (shown once; never stored in clear) and the reload."""

    registration: Registration
    password: str = field(repr=False)
    reload: ReloadResult


@dataclass(frozen=True, slots=True)
class BrokerFiles:
    """A rig's broker folder (``passwd``, ``acl``) and how to make its Mosquitto reload them.

    Attributes:
        folder: The folder Mosquitto's ``password_file`` and ``acl_file`` point into.
        reload_pid_file: The broker's ``pid_file``: after a change its pid gets ``SIGHUP``.
    """

    folder: Path
    reload_pid_file: Path | None = None

    @property
    def passwd(self) -> Path:
        return self.folder / "passwd"

    @property
    def acl(self) -> Path:
        return self.folder / "acl"

    def write(self, config: RigConfig, hashes: Mapping[str, str], managed: set[str]) -> None:
        """Rewrite ``passwd`` (unmanaged lines kept, ``hashes`` for the registered principals, none
        for the other ``managed`` ones) and ``acl`` (the rig's); remove stale login files."""
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        kept: list[str] = []
        if self.passwd.exists():
            for line in self.passwd.read_text(encoding="utf-8").splitlines():
                match = _PASSWD_LINE.match(line.strip())
                if match is not None and match.group(1) not in managed:
                    kept.append(line.strip())
        lines = kept + [f"{user}:{digest}" for user, digest in sorted(hashes.items())]
        _replace_private(self.passwd, "".join(f"{line}\n" for line in lines))
        _replace_private(self.acl, rig_access_policy(config).acl_text())
        listing = {"logins": dict(sorted(hashes.items()))}
        _replace_private(self.folder / REGISTERED_FILE, json.dumps(listing, indent=1) + "\n")
        for user in managed:  # a login file `telerig broker acl` wrote for it no longer works
            (self.folder / "logins" / f"{user}.json").unlink(missing_ok=True)
        example = self.folder / "mosquitto.conf.example"
        if not example.exists():
            example.write_text(
                f"# Mosquitto settings for rig {config.name!r} (see mosquitto.conf(5)). The control center\n"
                "# rewrites passwd and acl when a device is registered or revoked, and sends SIGHUP to the\n"
                "# pid in pid_file when `telerig serve --broker-pid-file` names it.\n"
                "allow_anonymous false\n"
                f"password_file {self.passwd.resolve()}\n"
                f"acl_file {self.acl.resolve()}\n"
                f"pid_file {(self.folder / 'mosquitto.pid').resolve()}\n"
                "message_size_limit 2097152\n"
            )

    def reload(self, config: RigConfig | None = None) -> ReloadResult:
        """Send ``SIGHUP`` to the broker of :attr:`reload_pid_file` (``config``: the rig, to say
        when its embedded broker would not see the files)."""
        if (
            self.reload_pid_file is None
            and config is not None
            and isinstance(config.broker, EmbeddedBrokerConfig)
        ):
            return ReloadResult(
                "embedded",
                f"files written in {self.folder}; rig {config.name!r} embeds its broker: `telerig run` "
                "with this data root applies them within 0.25 s (at its start when not running), "
                "except for the devices and robots that station runs itself; an external Mosquitto "
                "using this folder needs a reload",
            )
        if self.reload_pid_file is None:
            return ReloadResult(
                "manual",
                f"files rewritten in {self.folder}; reload the broker to apply them "
                "(kill -HUP <mosquitto pid>, or systemctl reload mosquitto)",
            )
        try:
            pid = int(self.reload_pid_file.read_text(encoding="ascii").strip())
            if pid <= 1:
                raise ValueError(pid)
            os.kill(pid, signal.SIGHUP)
        except (OSError, ValueError) as exc:
            log.warning("could not signal the broker of %s: %s", self.reload_pid_file, exc)
            return ReloadResult("failed", f"could not signal the broker ({exc}); reload it by hand")
        return ReloadResult("signalled", f"SIGHUP sent to mosquitto (pid {pid})")


def _replace_private(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    write_private(tmp, text)
    os.replace(tmp, path)


class DeviceRegistry:
    """Registered devices of the control center's rigs, and their broker files.

    Args:
        engine: SQLAlchemy engine of the control database (:meth:`open` builds one).
        rigs: The rigs whose devices may be registered, by name.
        broker_files: The broker folder of each rig, by name.
    """

    def __init__(
        self, engine: Engine, rigs: Mapping[str, RigConfig], broker_files: Mapping[str, BrokerFiles]
    ) -> None:
        missing = set(rigs) - set(broker_files)
        if missing:
            raise DeviceError(f"no broker folder for rig(s) {', '.join(sorted(missing))}")
        self._engine = engine
        self._rigs = dict(rigs)
        self._files = dict(broker_files)
        self._principals = {name: rig_access_policy(cfg).principals for name, cfg in rigs.items()}
        self._lock = threading.Lock()

    @classmethod
    def open(
        cls,
        target: str | Path,
        rigs: Mapping[str, RigConfig] | list[RigConfig],
        *,
        broker_folders: Mapping[str, Path] | None = None,
        reload_pid_file: Path | None = None,
    ) -> DeviceRegistry:
        """The registry in the control database of a data root, file or URL (tables created).

        Args:
            target: Data root (``control.sqlite`` in it), database file or URL.
            rigs: The rigs, by name or as a list.
            broker_folders: The broker folder of each rig, by name; a rig not named gets
                ``<data root>/broker/<rig>`` (which needs ``target`` to be a data root).
            reload_pid_file: The broker's pid file, for ``SIGHUP`` after a change (one broker).
        """
        by_name = {r.name: r for r in rigs} if isinstance(rigs, list) else dict(rigs)
        folders = dict(broker_folders or {})
        for name in by_name:
            if name not in folders:
                if "://" in str(target) or Path(target).suffix in (".sqlite", ".db"):
                    raise DeviceError(
                        f"give the broker folder of rig {name!r}: the database is not a data root"
                    )
                folders[name] = Path(target) / BROKER_FOLDER / name
        engine = control_engine(target)
        _meta.create_all(engine)
        files = {name: BrokerFiles(Path(folders[name]), reload_pid_file) for name in by_name}
        return cls(engine, by_name, files)

    def close(self) -> None:
        self._engine.dispose()

    @property
    def rigs(self) -> tuple[str, ...]:
        return tuple(self._rigs)

    def rig_config(self, rig: str) -> RigConfig:
        """The configuration of a served rig.

        Raises:
            DeviceError: Not served here; the message lists those that are.
        """
        return self._rig(rig)

    def broker_files(self, rig: str) -> BrokerFiles:
        return self._files[self._rig(rig).name]

    # -- queries ----------------------------------------------------------------------------------

    def registrations(self, rig: str | None = None, *, include_revoked: bool = True) -> list[Registration]:
        """Registrations (of ``rig``, or of every rig), by rig and principal."""
        q = sa.select(_devices).order_by(_devices.c.rig, _devices.c.principal)
        if rig is not None:
            q = q.where(_devices.c.rig == rig)
        if not include_revoked:
            q = q.where(_devices.c.revoked_ns.is_(None))
        with self._engine.connect() as conn:
            rows = conn.execute(q).mappings().all()
        return [self._registration(r) for r in rows]

    def get(self, rig: str, principal: str) -> Registration:
        """One registration.

        Raises:
            UnknownRegistrationError: None of that principal on that rig.
        """
        with self._engine.connect() as conn:
            row = self._row(conn, rig, principal)
        if row is None:
            raise UnknownRegistrationError(f"no device {principal!r} is registered on rig {rig!r}")
        return self._registration(row)

    def principal(self, rig: str, kind: DeviceKind, device: str) -> str:
        """The MQTT username of ``device`` (an input device or robot id of ``rig``).

        Raises:
            DeviceError: Unknown rig, kind or id; the message lists the valid ids.
        """
        config = self._rig(rig)
        if kind == "teleoperating":
            ids = [d.id for d in config.devices]
            name = f"dev-{device}"
        elif kind == "teleoperated":
            ids = [r.id for r in config.robots]
            name = robot_process_principal(device)
        else:
            raise DeviceError(
                f"device kind {str(kind)[:20]!r} does not exist. Valid: {', '.join(DEVICE_KINDS)}"
            )
        if device not in ids:
            what = "input device" if kind == "teleoperating" else "robot"
            valid = ", ".join(ids) or "(none)"
            raise DeviceError(f"{device[:64]!r} is not an {what} of rig {config.name!r}. Valid: {valid}")
        if name not in self._principals[config.name]:  # pragma: no cover - acl.py names every one
            raise DeviceError(f"rig {config.name!r} has no bus principal {name!r}")
        return name

    # -- changes ----------------------------------------------------------------------------------

    def register(self, rig: str, kind: DeviceKind, device: str, *, by: str) -> Issued:
        """Register a device, issue its login and rewrite the broker files (then reload the broker).

        Raises:
            DeviceError: Unknown rig or device, or registered already (revoke it first).
        """
        config = self._rig(rig)
        principal = self.principal(rig, kind, device)
        password = new_password()
        digest = password_file_text({principal: password}).strip().split(":", 1)[1]
        now = time.time_ns()
        with self._lock, self._write() as conn:
            row = self._row(conn, config.name, principal)
            if row is not None and row["revoked_ns"] is None:
                raise DeviceError(
                    f"{principal!r} is registered on rig {config.name!r} already; revoke it first to issue "
                    "a new password"
                )
            values = {
                "kind": kind,
                "device": device,
                "password_hash": digest,
                "created_ns": now,
                "created_by": by,
                "revoked_ns": None,
                "revoked_by": None,
            }
            if row is None:
                conn.execute(sa.insert(_devices).values(rig=config.name, principal=principal, **values))
            else:
                conn.execute(self._where(sa.update(_devices), config.name, principal).values(**values))
            self._write_files(conn, config)
            registration = self._registration(self._row(conn, config.name, principal))
        log.info("registered %s on rig %s (%s) by %s", principal, config.name, kind, by)
        return Issued(registration, password, self._files[config.name].reload(config))

    def revoke(self, rig: str, principal: str, *, by: str) -> tuple[Registration, ReloadResult]:
        """Revoke a registration: its login leaves the broker files, then the broker reloads
        (Mosquitto disconnects a client whose login is gone).

        Raises:
            UnknownRegistrationError: None active of that principal on that rig.
        """
        config = self._rig(rig, unknown=UnknownRegistrationError)
        now = time.time_ns()
        with self._lock, self._write() as conn:
            row = self._row(conn, config.name, principal)
            if row is None or row["revoked_ns"] is not None:
                raise UnknownRegistrationError(
                    f"no device {principal!r} is registered on rig {config.name!r}"
                )
            conn.execute(
                self._where(sa.update(_devices), config.name, principal).values(revoked_ns=now, revoked_by=by)
            )
            self._write_files(conn, config)
            registration = self._registration(self._row(conn, config.name, principal))
        log.info("revoked %s on rig %s by %s", principal, config.name, by)
        return registration, self._files[config.name].reload(config)

    def sync(self, rig: str) -> ReloadResult | None:
        """Rewrite a rig's broker files from the database and reload the broker when they changed
        (``telerig serve`` at start: after ``telerig broker acl`` rotated the folder's passwords, the
        registered logins are put back and the revoked ones left out). ``None``: nothing to do (no
        registration ever, or the files were current).
        """
        config = self._rig(rig)
        files = self._files[config.name]
        with self._lock, self._write() as conn:
            if (
                conn.execute(sa.select(_devices.c.principal).where(_devices.c.rig == config.name)).first()
                is None
            ):
                return None
            before = files.passwd.read_bytes() if files.passwd.exists() else None
            self._write_files(conn, config)
        return None if files.passwd.read_bytes() == before else files.reload(config)

    # -- internals --------------------------------------------------------------------------------

    def _rig(self, rig: str, *, unknown: type[DeviceError] = DeviceError) -> RigConfig:
        try:
            return self._rigs[rig]
        except KeyError:
            raise unknown(
                f"rig {rig[:64]!r} is not served here. Valid: {', '.join(self._rigs) or '(none)'}"
            ) from None

    def _write_files(self, conn: Connection, config: RigConfig) -> None:
        rows = conn.execute(sa.select(_devices).where(_devices.c.rig == config.name)).mappings().all()
        hashes = {r["principal"]: r["password_hash"] for r in rows if r["revoked_ns"] is None}
        self._files[config.name].write(config, hashes, {r["principal"] for r in rows})

    @staticmethod
    def _where(stmt: sa.Update, rig: str, principal: str) -> sa.Update:
        return stmt.where(_devices.c.rig == rig, _devices.c.principal == principal)

    @staticmethod
    def _row(conn: Connection, rig: str, principal: str) -> sa.RowMapping | None:
        q = sa.select(_devices).where(_devices.c.rig == rig, _devices.c.principal == principal)
        return conn.execute(q).mappings().first()

    def _registration(self, row: sa.RowMapping | None) -> Registration:
        assert row is not None
        principal: Principal | None = self._principals.get(row["rig"], {}).get(row["principal"])
        kind: DeviceKind = "teleoperated" if row["kind"] == "teleoperated" else "teleoperating"
        return Registration(
            rig=row["rig"],
            principal=row["principal"],
            kind=kind,
            device=row["device"],
            created_ns=row["created_ns"],
            created_by=row["created_by"],
            revoked_ns=row["revoked_ns"],
            revoked_by=row["revoked_by"],
            publishes=() if principal is None else principal.write,
        )

    @contextmanager
    def _write(self) -> Iterator[Connection]:
        with self._engine.connect() as conn, conn.begin():
            yield conn
