"""``telerig serve`` (the control center's web server) and ``telerig users`` (its accounts)."""

from __future__ import annotations

import argparse
import errno
import getpass
import ipaddress
import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.table import Table

from telerig.errors import ConfigError, DependencyError
from telerig.server.accounts import ROLES, AccountError, AccountStore

if TYPE_CHECKING:
    import uvicorn

    from telerig.config.schema import RigConfig
    from telerig.server.devices import DeviceRegistry
    from telerig.server.gateway import RigGateway

__all__ = ["URL_LINE", "add_arguments", "wait_for_url"]

#: The line ``telerig serve`` prints once it serves; group 1 is its URL (with the port it took for
#: ``--port 0``). A program that starts the server as a child waits for it: :func:`wait_for_url`.
URL_LINE = re.compile(r"^telerig control center on (https?://\S+?)/$", re.MULTILINE)


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``serve`` and ``users`` commands."""
    serve = sub.add_parser(
        "serve",
        help="run the control center's web server (log in, users, audit log)",
        description="Run the control center over HTTPS. The first run needs an admin: create one with "
        "`telerig users add NAME --role admin`; there is no default password.",
    )
    serve.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    serve.add_argument(
        "--port", type=int, default=8443, help="port (default 8443; 0: any free port, printed with the URL)"
    )
    _data_root(serve)
    serve.add_argument(
        "--tls-cert", type=Path, default=None, help="certificate (PEM); default: a self-signed one"
    )
    serve.add_argument("--tls-key", type=Path, default=None, help="key of --tls-cert (PEM)")
    serve.add_argument(
        "--no-tls", action="store_true", help="plain HTTP (refused unless --host is a loopback address)"
    )
    rig = serve.add_argument_group(
        "running rig", "watch and command a running rig (live state, session, e-stop) over its broker"
    )
    rig.add_argument("--rig", default=None, help="the running rig's file or shipped name (default: none)")
    rig.add_argument(
        "--broker", default=None, help="the rig's broker URL (default: from the login file, or the rig's)"
    )
    rig.add_argument(
        "--credentials",
        type=Path,
        default=None,
        help="the web principal's bus login file (default: DATA_ROOT/.bus-RIG-web.json, written by "
        "`telerig run` while it runs, else the same file in the rig's data root, else "
        "BROKER_FOLDER/logins/web.json written by `telerig broker acl`)",
    )
    rig.add_argument("--ca-file", type=Path, default=None, help="CA of an mqtts:// broker's certificate")
    rig.add_argument("--cert-file", type=Path, default=None, help="client certificate for an mqtts:// broker")
    rig.add_argument("--key-file", type=Path, default=None, help="private key of --cert-file")
    rig.add_argument(
        "--broker-folder",
        type=Path,
        default=None,
        help="the rig's Mosquitto password and ACL files, rewritten when a device is registered or revoked "
        "(default: DATA_ROOT/broker/RIG; set it up with `telerig broker acl RIG --out` that folder)",
    )
    rig.add_argument(
        "--broker-pid-file",
        type=Path,
        default=None,
        help="the external Mosquitto's pid_file: it gets SIGHUP (reload) after each change "
        "(default: none, reload it yourself)",
    )
    serve.set_defaults(handler=_cmd_serve)

    users = sub.add_parser("users", help="control-center accounts: add, list, change role, password, disable")
    users_sub = users.add_subparsers(title="users commands")
    add = users_sub.add_parser("add", help="create a user (asks for its password twice)")
    add.add_argument("name")
    add.add_argument("--role", required=True, choices=ROLES)
    _password_stdin(add)
    _data_root(add)
    add.set_defaults(handler=_cmd_add)
    ls = users_sub.add_parser("list", help="list users")
    _data_root(ls)
    ls.set_defaults(handler=_cmd_list)
    pw = users_sub.add_parser("passwd", help="set a user's password (ends its sessions)")
    pw.add_argument("name")
    _password_stdin(pw)
    _data_root(pw)
    pw.set_defaults(handler=_cmd_passwd)
    role = users_sub.add_parser("role", help="change a user's role")
    role.add_argument("name")
    role.add_argument("role", choices=ROLES)
    _data_root(role)
    role.set_defaults(handler=_cmd_role)
    off = users_sub.add_parser("disable", help="disable a user (ends its sessions; the audit log keeps it)")
    off.add_argument("name")
    _data_root(off)
    off.set_defaults(handler=_cmd_disable)


def _data_root(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data-root",
        type=Path,
        default=Path("telerig-data"),
        help="data root holding the account database control.sqlite (default telerig-data)",
    )


def _password_stdin(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--password-stdin", action="store_true", help="read the password from the first line of stdin"
    )


def _read_password(from_stdin: bool) -> str:
    if from_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    if not sys.stdin.isatty():
        raise AccountError("no terminal to ask for the password; pass --password-stdin and pipe it in")
    first = getpass.getpass("password: ")
    if getpass.getpass("again: ") != first:
        raise AccountError("the two passwords differ; nothing changed")
    return first


def _cmd_add(args: argparse.Namespace) -> int:
    with _accounts(args.data_root) as accounts:
        user = accounts.add_user(args.name, args.role, _read_password(args.password_stdin))
        accounts.audit("user_added", user=None, target=user.name, detail=f"{user.role} (command line)")
    print(f"user {user.name} ({user.role}) added")
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    with _accounts(args.data_root) as accounts:
        table = Table("user", "role", "state")
        for u in accounts.users():
            table.add_row(u.name, u.role, "disabled" if u.disabled else "active")
    Console().print(table)
    return 0


def _cmd_passwd(args: argparse.Namespace) -> int:
    with _accounts(args.data_root) as accounts:
        accounts.set_password(args.name, _read_password(args.password_stdin))
        accounts.audit("password_set", user=None, target=args.name, detail="command line")
    print(f"password of {args.name} set; its sessions ended")
    return 0


def _cmd_role(args: argparse.Namespace) -> int:
    with _accounts(args.data_root) as accounts:
        user = accounts.set_role(args.name, args.role)
        accounts.audit("user_changed", user=None, target=user.name, detail=f"role {user.role} (command line)")
    print(f"{user.name} is now {user.role}")
    return 0


def _cmd_disable(args: argparse.Namespace) -> int:
    with _accounts(args.data_root) as accounts:
        accounts.disable(args.name)
        accounts.audit("user_changed", user=None, target=args.name, detail="disabled (command line)")
    print(f"{args.name} disabled")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from telerig.server.app import create_app

    cert, key = _tls(args)
    accounts = AccountStore.open(args.data_root)
    gateway = None
    devices = None
    try:
        if not accounts.has_admin():
            raise ConfigError(
                f"no admin account in {args.data_root}: create one with "
                f"`telerig users add NAME --role admin --data-root {args.data_root}` "
                "(there is no default password)"
            )
        _check_port(args.host, args.port)
        if args.rig is not None:
            gateway = _gateway(args)
            devices = _devices(args)
        scheme = "http" if cert is None else "https"

        def announce(port: int) -> None:
            print(f"telerig control center on {scheme}://{_url_host(args.host)}:{port}/", flush=True)
            if gateway is not None:
                _print_xr_page(gateway.rig, scheme, args.host, port)

        app = create_app(accounts, gateway=gateway, data_root=args.data_root)
        app.state.devices = devices  # device registration (server.routes_devices); 503 without --rig
        config = uvicorn.Config(
            app,
            host=args.host,
            port=args.port,
            ssl_certfile=None if cert is None else str(cert),
            ssl_keyfile=None if key is None else str(key),
            log_level="warning",
            server_header=False,
        )
        _run_announcing(config, announce)
    finally:
        if gateway is not None:
            gateway.close()
        if devices is not None:
            devices.close()
        accounts.close()
    return 0


def _devices(args: argparse.Namespace) -> DeviceRegistry:
    """The device registry of ``--rig`` (in the data root's control database); its broker folder
    is brought up to date with the registrations (and the broker reloaded) at start."""
    from telerig.config import load_rig
    from telerig.server.devices import DeviceRegistry

    rig = load_rig(args.rig)
    folders = None if args.broker_folder is None else {rig.name: args.broker_folder}
    registry = DeviceRegistry.open(
        args.data_root, [rig], broker_folders=folders, reload_pid_file=args.broker_pid_file
    )
    result = registry.sync(rig.name)
    if result is not None:
        print(f"device logins of rig {rig.name!r}: {result.detail}", flush=True)
    return registry


def _gateway(args: argparse.Namespace) -> RigGateway:
    """The running rig's gateway, logged in as its ``web`` principal the way ``telerig safety`` logs
    in as ``cli``: ``--credentials``, else the login file ``telerig run`` keeps in the data root.

    The login is read again whenever the gateway is not connected, so the server may start before
    the rig and follows it across runs (each run has new bus passwords).
    """
    from telerig.bus.acl import WEB
    from telerig.bus.login import login_path
    from telerig.bus.mqtt import TlsOptions
    from telerig.cli.bus_options import bus_connection
    from telerig.config import load_rig
    from telerig.server.gateway import RigGateway

    rig = load_rig(args.rig)

    def login() -> tuple[str, TlsOptions | None]:
        credentials = args.credentials
        if credentials is None:  # a running embedded broker's, else an external broker's folder's
            folder = args.broker_folder or Path(args.data_root) / "broker" / rig.name
            candidates = (
                login_path(args.data_root, rig.name, WEB),
                login_path(rig.recording.data_root, rig.name, WEB),
                folder / "logins" / f"{WEB}.json",
            )
            credentials = next((c for c in candidates if c.exists()), candidates[0])
        options = argparse.Namespace(
            broker=args.broker,
            credentials=credentials,
            username=None,
            password=None,
            data_root=None,
            ca_file=args.ca_file,
            cert_file=args.cert_file,
            key_file=args.key_file,
        )
        return bus_connection(options, rig)

    gateway = RigGateway(rig, login=login).start()
    if gateway.connected:
        print(f"watching rig {rig.name!r} as the {WEB} principal of its broker", flush=True)
    else:
        print(f"waiting for rig {rig.name!r}: {gateway.link_error}", flush=True)
    return gateway


def _tls(args: argparse.Namespace) -> tuple[Path | None, Path | None]:
    from telerig.devices.webxr.pairing import self_signed_pair

    if args.no_tls:
        if not _loopback(args.host):
            raise ConfigError(
                f"--no-tls on {args.host} would send passwords in clear; use TLS or --host 127.0.0.1"
            )
        return None, None
    if (args.tls_cert is None) != (args.tls_key is None):
        raise ConfigError("--tls-cert and --tls-key go together")
    if args.tls_cert is not None:
        return args.tls_cert, args.tls_key
    return self_signed_pair(args.data_root / ".tls-server", args.host)


def wait_for_url(log: Path, server: subprocess.Popen[Any], timeout_s: float = 60.0) -> str:
    """The URL a ``telerig serve`` child, whose output goes to the file ``log``, prints once it serves.

    Raises:
        RuntimeError: The server exited or printed no URL within ``timeout_s``; the message has the
            log's tail.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        found = URL_LINE.search(text)
        if found:
            return found[1]
        if server.poll() is not None or time.monotonic() > deadline:
            state = "exited" if server.poll() is not None else f"printed no URL in {timeout_s:.0f} s"
            raise RuntimeError(f"telerig serve {state}:\n{text[-3000:]}")
        time.sleep(0.1)


def _run_announcing(config: uvicorn.Config, announce: Callable[[int], None]) -> None:
    """Run uvicorn's server, calling ``announce(port)`` once it serves: after the app's startup (which
    may wait for the rig), with the port it listens on (the kernel's choice for ``--port 0``). A URL
    printed then answers; one printed before could name a port another program takes meanwhile."""
    import uvicorn

    class Server(uvicorn.Server):
        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            await super().startup(sockets)
            if self.started and self.servers and self.servers[0].sockets:
                announce(self.servers[0].sockets[0].getsockname()[1])

    Server(config).run()


def _check_port(host: str, port: int) -> None:
    """Say in one line, before anything starts, that ``port`` is no TCP port or is taken on ``host``.

    Raises:
        ConfigError: Not a port, an address that does not resolve or is not this machine's, or the
            port is taken.
    """
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port {port} is not a TCP port: give 1-65535, or 0 for any free one")
    if port == 0:
        return
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0][0]
        socket.create_server((host, port), family=family).close()
    except socket.gaierror as exc:
        raise ConfigError(f"--host {host!r} does not resolve ({exc.strerror}): give an address") from None
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(
                f"port {port} on {host} is in use: stop what listens there, or pass another --port "
                "(0: any free one)"
            ) from None
        raise ConfigError(
            f"cannot listen on {host} port {port} ({exc.strerror}): give an address of this machine "
            "with --host, and a port of 1024 or above unless running as root"
        ) from None


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _print_xr_page(rig: RigConfig, scheme: str, host: str, port: int) -> None:
    """The WebXR page's URL (and, bound beyond loopback, its QR code to scan with a headset)."""
    from telerig.devices.webxr.config import WebXRConfig
    from telerig.devices.webxr.pairing import lan_url_host, terminal_qr

    devices = [d.id for d in rig.devices if isinstance(d, WebXRConfig)]
    if not devices:
        return
    address = lan_url_host(host)
    url = f"{scheme}://{f'[{address}]' if ':' in address else address}:{port}/xr"
    print(f"WebXR page ({', '.join(devices)}; log in as an operator): {url}", flush=True)
    if not _loopback(host):
        try:
            print(terminal_qr(url), flush=True)
        except DependencyError as exc:  # the QR code is a convenience: the URL is printed above
            print(f"(no QR code: {exc})", flush=True)


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@contextmanager
def _accounts(data_root: Path) -> Iterator[AccountStore]:
    store = AccountStore.open(data_root)
    try:
        yield store
    finally:
        store.close()
