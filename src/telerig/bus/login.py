"""A running rig's bus login for operator tools: written 0600 by ``telerig run``, read by the CLI.

``telerig run`` writes ``<data root>/.bus-<rig>.json`` (owner-only) while the rig runs and removes
it at exit: the broker's address and the ``cli`` principal's password. ``telerig safety`` and
``telerig session`` read it, so an operator on the station needs no password on the command line;
elsewhere they take ``--credentials FILE`` (a copy of it) or ``--username``/``--password``.
"""

from __future__ import annotations

import json
import stat
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from telerig.bus.acl import write_private
from telerig.bus.mqtt import MqttUrl
from telerig.errors import ConfigError

__all__ = ["BusLogin", "login_path"]


def login_path(data_root: Path, rig: str, principal: str | None = None) -> Path:
    """Where ``telerig run`` writes a bus login of rig ``rig``: ``<data_root>/.bus-<rig>.json`` for
    operators (the ``cli`` principal), ``<data_root>/.bus-<rig>-<principal>.json`` for another
    (a following station's, to copy to its host and pass as ``--credentials``)."""
    return Path(data_root) / (f".bus-{rig}.json" if principal is None else f".bus-{rig}-{principal}.json")


@dataclass(frozen=True, slots=True)
class BusLogin:
    """A broker address and who to log in as.

    Attributes:
        address: ``mqtt[s]://host:port``, without a login.
        username: MQTT username (a principal of the rig's ACL, e.g. ``cli``).
        password: Its password.
        rig: The rig it belongs to (a file of another rig is refused).
    """

    address: str
    username: str
    password: str
    rig: str

    @property
    def url(self) -> str:
        """``mqtt[s]://username:password@host:port`` (keep it out of logs)."""
        parsed = MqttUrl.parse(self.address)
        scheme = "mqtts" if parsed.tls else "mqtt"
        user, password = quote(self.username, safe=""), quote(self.password, safe="")
        return f"{scheme}://{user}:{password}@{parsed.host}:{parsed.port}"

    def write(self, path: Path) -> Path:
        """Write it as JSON readable by its owner only (0600)."""
        doc = {"rig": self.rig, "address": self.address, "username": self.username, "password": self.password}
        return write_private(Path(path), json.dumps(doc) + "\n")

    @classmethod
    def read(cls, path: Path, *, rig: str | None = None) -> BusLogin:
        """Read a login file.

        Raises:
            ConfigError: Missing, readable by others, not a login file, or of another rig than
                ``rig``; one line with the fix.
        """
        path = Path(path)
        try:
            mode = path.stat().st_mode
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError(
                f"no bus login at {path}: `telerig run` writes it there while the rig runs (same "
                "--data-root); or pass --credentials FILE, or --username and --password"
            ) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read the bus login {path}: {exc}") from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ConfigError(f"bus login {path} is readable by others: `chmod 600 {path}`")
        try:
            doc = json.loads(text)
            login = cls(str(doc["address"]), str(doc["username"]), str(doc["password"]), str(doc["rig"]))
            MqttUrl.parse(login.address)
        except (ValueError, KeyError, TypeError, ConfigError):
            raise ConfigError(
                f"{path} is not a telerig bus login (JSON with rig, address, username, password)"
            ) from None
        if rig is not None and login.rig != rig:
            raise ConfigError(f"bus login {path} is for rig {login.rig!r}, not {rig!r}")
        return login
