"""Registered device logins for the embedded broker: read from a rig's broker folder, checked.

The control center (:mod:`telerig.server.devices`) keeps a rig's registered devices in its broker
folder (``<data root>/broker/<rig>``): beside ``passwd`` and ``acl`` (for an external Mosquitto) it
writes ``registered.json``, ``{"logins": {principal: "$7$..."}}``, the active registrations with
their Mosquitto hashes. The embedded broker of ``telerig run`` adds exactly those: the plain
passwords are never known here, only the stored hashes, which Mosquitto checks itself. (Not the
``passwd`` lines: ``telerig broker acl`` rewrites every line there, registered principals' too, until
``telerig serve`` puts the registrations back.)

What is read is checked, because it decides who moves a robot: a file over
:data:`MAX_FILE_BYTES`, a ``registered.json`` that is not that shape, or a hash that is not a
``$7$`` PBKDF2 one is reported in one warning line and left out (never a login without a
password); a principal the rig does not have, or one the station's own nodes log in as, is left
out with one warning line too.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "MAX_FILE_BYTES",
    "REGISTERED_FILE",
    "RegisteredLogins",
    "folder_signature",
    "log_warnings",
    "read_registered_logins",
]

log = logging.getLogger(__name__)

#: The registry's list of its active principals, in the broker folder.
REGISTERED_FILE = "registered.json"
#: Largest ``registered.json`` read [bytes]: a login is ~140 bytes, so 1 MiB is ~7000 logins, far
#: more than a lab registers; a larger file is garbage and is not read at all.
MAX_FILE_BYTES = 1 << 20
#: Mosquitto's PBKDF2-SHA512 line, as :func:`telerig.bus.acl.password_file_text` writes it.
_HASH = re.compile(r"\$7\$[1-9][0-9]{0,6}\$[A-Za-z0-9+/]+={0,2}\$[A-Za-z0-9+/]+={0,2}")


@dataclass(frozen=True, slots=True)
class RegisteredLogins:
    """The registered logins to add: hash by principal, and the warnings about what was left out."""

    hashes: Mapping[str, str]
    warnings: tuple[str, ...]


def _read_capped(path: Path, warnings: list[str]) -> str | None:
    try:
        with path.open("rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        warnings.append(f"cannot read {path}: {exc}; no registered login is used")
        return None
    if len(data) > MAX_FILE_BYTES:
        warnings.append(f"{path} is over {MAX_FILE_BYTES} bytes; no registered login is used")
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        warnings.append(f"{path} is not UTF-8 text; no registered login is used")
        return None


def read_registered_logins(
    folder: Path, principals: Collection[str], reserved: Collection[str] = ()
) -> RegisteredLogins:
    """The registered logins of a broker folder that the embedded broker may add.

    Args:
        folder: The rig's broker folder (its ``registered.json``).
        principals: The rig's principals (:func:`telerig.bus.acl.rig_access_policy`): only those
            have ACL rights, so only those are added.
        reserved: Principals this station's own nodes log in as with their per-run passwords; a
            registration of one is left out (the station keeps working) with a warning.
    """
    warnings: list[str] = []
    listing = _read_capped(folder / REGISTERED_FILE, warnings)
    if listing is None:
        return RegisteredLogins({}, tuple(warnings))
    try:
        doc = json.loads(listing)
    except ValueError as exc:
        warnings.append(f"{folder / REGISTERED_FILE} is not JSON ({exc}); no registered login is used")
        return RegisteredLogins({}, tuple(warnings))
    logins = doc.get("logins") if isinstance(doc, dict) else None
    if not isinstance(logins, dict) or not all(isinstance(h, str) for h in logins.values()):
        warnings.append(
            f'{folder / REGISTERED_FILE} is not {{"logins": {{principal: hash}}}}; '
            "no registered login is used"
        )
        return RegisteredLogins({}, tuple(warnings))
    hashes: dict[str, str] = {}
    for name, digest in logins.items():
        if name not in principals:
            warnings.append(f"registered login {name[:80]!r} is no principal of the rig; left out")
        elif name in reserved:
            warnings.append(
                f"registered login {name!r} is the login of a node this station runs; left out (the "
                "station's own node keeps its per-run password). Register a device only where it does "
                "not run in `telerig run`'s station"
            )
        elif _HASH.fullmatch(digest) is None:
            warnings.append(f"registered login {name!r}: no Mosquitto $7$ hash; left out")
        else:
            hashes[name] = digest
    return RegisteredLogins(hashes, tuple(warnings))


def folder_signature(folder: Path) -> tuple[int, int, int]:
    """What changes when the registry rewrites ``registered.json`` (inode, size, mtime [ns])."""
    try:
        st = (folder / REGISTERED_FILE).stat()
    except OSError:
        return (0, 0, 0)
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def log_warnings(logins: RegisteredLogins) -> None:
    """Log each warning of ``logins`` as one line."""
    for warning in logins.warnings:
        log.warning("%s", warning)
