"""How operator commands (``telerig safety``, ``telerig session``) reach and log in to a rig's broker."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path

from telerig.bus.acl import CLI, WEB
from telerig.bus.broker import MosquittoBroker
from telerig.bus.login import BusLogin, login_path
from telerig.bus.mqtt import MqttUrl, TlsOptions, rig_tls
from telerig.config.schema import EmbeddedBrokerConfig, RigConfig
from telerig.errors import ConfigError

__all__ = [
    "add_bus_options",
    "bus_connection",
    "operator_login",
    "public_address",
    "run_broker_url",
    "session_arguments",
]


def add_bus_options(p: argparse.ArgumentParser) -> None:
    """Add ``--broker``, the login options (``--credentials``, ``--username``, ``--password``,
    ``--data-root``) and the TLS options (``--ca-file``, ``--cert-file``, ``--key-file``)."""
    p.add_argument(
        "--broker",
        default=None,
        help="the rig's broker URL, e.g. mqtt://127.0.0.1:1883 (default: from the running rig's login "
        "file, the rig's external broker, or its embedded broker's fixed port)",
    )
    p.add_argument(
        "--credentials",
        type=Path,
        default=None,
        help="bus login file (default: DATA_ROOT/.bus-RIG.json, written by `telerig run` while it runs)",
    )
    p.add_argument("--username", default=None, help="log in as this broker user (with --password)")
    p.add_argument("--password", default=None, help="password of --username")
    p.add_argument(
        "--data-root", type=Path, default=None, help="the running rig's data root (default: from the rig)"
    )
    p.add_argument("--ca-file", type=Path, default=None, help="CA of an mqtts:// broker's certificate (PEM)")
    p.add_argument("--cert-file", type=Path, default=None, help="client certificate for an mqtts:// broker")
    p.add_argument("--key-file", type=Path, default=None, help="private key of --cert-file")


def bus_connection(args: argparse.Namespace, rig: RigConfig) -> tuple[str, TlsOptions | None]:
    """The broker URL, with the login, and the TLS options the command connects with.

    The login is ``--username``/``--password``, else ``--credentials``, else the URL's own, else
    the running rig's login file in its data root.

    Raises:
        ConfigError: No broker address, no login for a broker that needs one, or a bad login
            file; one line with the fix.
    """
    if (args.username is None) != (args.password is None):
        raise ConfigError("--username and --password go together")
    login = None if args.credentials is None else BusLogin.read(args.credentials, rig=rig.name)
    address: str | None = args.broker or (None if login is None else login.address)
    has_login = address is not None and MqttUrl.parse(address).username is not None
    if login is None and args.username is None and not has_login:
        default = login_path(args.data_root or rig.recording.data_root, rig.name)
        if default.exists() or isinstance(rig.broker, EmbeddedBrokerConfig):
            login = BusLogin.read(default, rig=rig.name)  # one line naming the fix when missing
            address = address or login.address
    address = address or _rig_address(rig)
    if args.username is not None:
        login = BusLogin(address, args.username, args.password, rig.name)
    url = address if login is None else BusLogin(address, login.username, login.password, rig.name).url
    return url, _tls(args, rig)


def _rig_address(rig: RigConfig) -> str:
    broker = rig.broker
    if not isinstance(broker, EmbeddedBrokerConfig):
        return broker.url
    if not broker.port:
        raise ConfigError(
            f"rig {rig.name!r} runs its embedded broker on a free port: pass --broker with the URL "
            "`telerig run` printed, or --credentials with its login file"
        )
    return f"mqtt://127.0.0.1:{broker.port}"


def _tls(args: argparse.Namespace, rig: RigConfig) -> TlsOptions | None:
    if args.ca_file is not None or args.cert_file is not None:
        return TlsOptions(args.ca_file, args.cert_file, args.key_file)
    return rig_tls(rig.broker)


def session_arguments(argv: Sequence[str]) -> list[str]:
    """``telerig session`` arguments with the login resolved into the ``--url`` the session command takes.

    ``--url`` with no login options passes through as given; otherwise the rig (``--rig``, a file or
    shipped name) and :func:`bus_connection` decide the URL, and ``--rig`` becomes the rig's name.
    """
    parser = argparse.ArgumentParser(add_help=False)
    add_bus_options(parser)
    parser.add_argument("--rig", default="demo")
    parser.add_argument("--url", default=None)
    known, rest = parser.parse_known_args(list(argv))
    logins = (known.credentials, known.username, known.password, known.data_root, known.broker)
    if known.url is not None and all(v is None for v in logins):
        return list(argv)
    from telerig.config import load_rig

    rig = load_rig(known.rig)
    known.broker = known.broker or known.url
    url, tls = bus_connection(known, rig)
    if tls is not None and (tls.ca_file is not None or tls.cert_file is not None):
        raise ConfigError(
            "telerig session trusts the system's CAs only: add the broker's CA to them, or use "
            "telerig safety, which takes --ca-file"
        )
    return [*rest, "--url", url, "--rig", rig.name]


@contextlib.contextmanager
def operator_login(broker: MosquittoBroker | None, data_root: Path, rig: RigConfig) -> Iterator[Path | None]:
    """While the block runs, keep the bus logins of an embedded ``broker`` in ``data_root`` (0600):
    the ``cli`` principal's for operators, the ``web`` principal's for the control center
    (``telerig serve --rig``), and each following station's (``station-<id>``, to copy to its
    host); yields the operators' path (``None`` without an embedded broker). Removed at exit."""
    if broker is None:
        yield None
        return
    stations = ((p, p) for p in (f"station-{s.id}" for s in rig.stations[1:]))
    principals = [(None, CLI), (WEB, WEB), *stations]
    paths = []
    try:
        for name, principal in principals:
            login = BusLogin(broker.address, principal, broker.access.password(principal), rig.name)
            paths.append(login.write(login_path(data_root, rig.name, name)))
        yield paths[0]
    finally:
        for path in paths:
            path.unlink(missing_ok=True)


def public_address(url: str) -> str:
    """``url`` without its login: ``mqtt[s]://host:port``."""
    parsed = MqttUrl.parse(url)
    return f"{'mqtts' if parsed.tls else 'mqtt'}://{parsed.host}:{parsed.port}"


def run_broker_url(broker: str | None, credentials: Path | None, rig: RigConfig) -> str | None:
    """The broker URL ``telerig run`` gives the runtime: ``--broker``, logged in with ``--credentials``
    (a following station's login file, whose address serves when ``--broker`` is not given)."""
    if credentials is None:
        return broker
    login = BusLogin.read(credentials, rig=rig.name)
    return BusLogin(broker or login.address, login.username, login.password, rig.name).url
