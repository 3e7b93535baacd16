"""Control-center accounts: users with roles, login sessions and the audit log, in one database.

Passwords are hashed with Argon2id (argon2-cffi's defaults, RFC 9106 low-memory profile); a
session is a random token whose SHA-256 is stored (a stolen database holds no usable cookie), with
its own CSRF token, an idle timeout and an absolute lifetime. Every state-changing action a person
takes (log in, start, stop, e-stop, add a user...) goes to the audit log with who, what and from
where.

The database is SQLite in the data root by default (``control.sqlite``), or any SQLAlchemy URL
(PostgreSQL when a lab runs the index there too). The constructor has no side effects;
:meth:`AccountStore.open` creates the tables.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import sqlalchemy as sa
from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy.engine import Connection, Engine

from telerig.errors import ConfigError, TelerigError

__all__ = [
    "DEFAULT_FILENAME",
    "ROLES",
    "AccountError",
    "AccountStore",
    "AuditEntry",
    "LoginSession",
    "Role",
    "User",
    "control_engine",
]

#: Database file in the data root when no URL is given.
DEFAULT_FILENAME = "control.sqlite"

#: Roles, weakest first: a viewer watches; an operator also runs sessions and e-stops; an admin
#: also manages users and devices.
Role = Literal["viewer", "operator", "admin"]
ROLES: tuple[Role, ...] = get_args(Role)

_NAME = re.compile(r"^[a-z][a-z0-9_.-]{1,31}$")
_MIN_PASSWORD = 12
_MAX_PASSWORD = 1024  # Argon2 hashes anything, but a megabyte "password" is an attack, not a login
_TOKEN_BYTES = 32
#: A session ends after this long without a request [s] ...
SESSION_IDLE_S = 8 * 3600
#: ... and after this long in any case [s] (one lab shift and a half).
SESSION_MAX_S = 12 * 3600
_AUDIT_TEXT = 500

_meta = sa.MetaData()
_users = sa.Table(
    "users",
    _meta,
    sa.Column("name", sa.String(32), primary_key=True),
    sa.Column("role", sa.String(16), nullable=False),
    sa.Column("password_hash", sa.String(200), nullable=False),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("disabled", sa.Boolean, nullable=False, default=False),
)
_sessions = sa.Table(
    "login_sessions",
    _meta,
    sa.Column("token_sha256", sa.String(64), primary_key=True),
    sa.Column("user", sa.String(32), sa.ForeignKey("users.name", ondelete="CASCADE"), nullable=False),
    sa.Column("csrf", sa.String(64), nullable=False),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("seen_ns", sa.BigInteger, nullable=False),
)
_audit = sa.Table(
    "audit",
    _meta,
    sa.Column("seq", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("t_ns", sa.BigInteger, nullable=False),
    sa.Column("user", sa.String(32), nullable=True),
    sa.Column("action", sa.String(64), nullable=False),
    sa.Column("target", sa.String(_AUDIT_TEXT), nullable=False, default=""),
    sa.Column("detail", sa.String(_AUDIT_TEXT), nullable=False, default=""),
    sa.Column("client", sa.String(64), nullable=False, default=""),
)
sa.Index("audit_time", _audit.c.t_ns)


class AccountError(TelerigError):
    """A user, password or session request was refused; the message says why and what to do."""


@dataclass(frozen=True, slots=True)
class User:
    """A control-center user: ``name``, ``role``, wall-clock creation time [ns], ``disabled``."""

    name: str
    role: Role
    created_ns: int
    disabled: bool = False

    def may(self, role: Role) -> bool:
        """Whether this user has at least ``role``."""
        return not self.disabled and ROLES.index(self.role) >= ROLES.index(role)


@dataclass(frozen=True, slots=True)
class LoginSession:
    """A logged-in browser: the cookie ``token`` (only when just created), its ``csrf`` token, the user."""

    user: User
    csrf: str
    created_ns: int
    token: str = ""


@dataclass(frozen=True, slots=True)
class AuditEntry:
    """One audited action: wall-clock time [ns], user (``None``: anonymous), action, target, detail,
    client address."""

    seq: int
    t_ns: int
    user: str | None
    action: str
    target: str
    detail: str
    client: str


def _sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _check_name(name: str) -> str:
    if not _NAME.match(name):
        raise AccountError(
            f"user name {name[:40]!r} is not allowed: 2-32 characters, lower-case letters, digits, "
            "'.', '_', '-', starting with a letter"
        )
    return name


def _check_password(password: str) -> str:
    if len(password) < _MIN_PASSWORD:
        raise AccountError(f"a password needs at least {_MIN_PASSWORD} characters")
    if len(password) > _MAX_PASSWORD:
        raise AccountError(f"a password has at most {_MAX_PASSWORD} characters")
    return password


def _check_role(role: str) -> Role:
    if role not in ROLES:
        raise AccountError(f"role {role[:20]!r} does not exist. Available: {', '.join(ROLES)}")
    return role


def _url(target: str | Path) -> sa.URL:
    text = str(target)
    if "://" not in text:
        path = Path(text).expanduser()
        if path.suffix not in (".sqlite", ".db"):
            path = path / DEFAULT_FILENAME
        path.parent.mkdir(parents=True, exist_ok=True)
        return sa.URL.create("sqlite+pysqlite", database=str(path.resolve()))
    try:
        url = sa.make_url(text)
    except sa.exc.ArgumentError:
        raise ConfigError(f"accounts URL {text!r} is malformed; use postgresql://user:pass@host/db") from None
    if url.get_backend_name() in ("postgresql", "postgres"):
        return url.set(drivername="postgresql+psycopg")
    if url.get_backend_name() == "sqlite":
        return url.set(drivername="sqlite+pysqlite")
    raise ConfigError(f"accounts URL {text!r}: only sqlite:// and postgresql:// are supported")


def control_engine(target: str | Path) -> Engine:
    """The engine of the control center's database (``control.sqlite`` in a data root, a file or a
    URL): accounts, device registrations and jobs share it.

    Raises:
        ConfigError: The URL is malformed or names an unsupported database.
    """
    url = _url(target)
    engine = sa.create_engine(url, pool_pre_ping=True)
    if url.get_backend_name() == "sqlite":
        sa.event.listen(engine, "connect", _sqlite_pragmas)
    return engine


class AccountStore:
    """Users, login sessions and the audit log.

    Args:
        engine: An SQLAlchemy engine (:meth:`open` builds one from a data root or URL).
        hasher: The Argon2 password hasher (tests pass cheaper parameters).
    """

    def __init__(self, engine: Engine, hasher: PasswordHasher | None = None) -> None:
        self._engine = engine
        self._hasher = hasher or PasswordHasher()

    @classmethod
    def open(cls, target: str | Path, *, hasher: PasswordHasher | None = None) -> AccountStore:
        """Open (and create the tables of) the account database of a data root, file or URL.

        Raises:
            ConfigError: The URL is malformed or names an unsupported database.
        """
        engine = control_engine(target)
        _meta.create_all(engine)
        return cls(engine, hasher)

    def close(self) -> None:
        self._engine.dispose()

    # -- users ----------------------------------------------------------------------------------

    def add_user(self, name: str, role: str, password: str) -> User:
        """Create a user.

        Raises:
            AccountError: Bad name, role or password, or the name is taken.
        """
        user = User(_check_name(name), _check_role(role), time.time_ns())
        digest = self._hasher.hash(_check_password(password))
        with self._write() as conn:
            if conn.execute(sa.select(_users.c.name).where(_users.c.name == name)).first():
                raise AccountError(f"user {name!r} exists; pick another name or set its password")
            conn.execute(
                sa.insert(_users).values(
                    name=user.name,
                    role=user.role,
                    password_hash=digest,
                    created_ns=user.created_ns,
                    disabled=False,
                )
            )
        return user

    def set_password(self, name: str, password: str) -> None:
        """Replace a user's password and end all of its sessions."""
        digest = self._hasher.hash(_check_password(password))
        with self._write() as conn:
            done = conn.execute(sa.update(_users).where(_users.c.name == name).values(password_hash=digest))
            if done.rowcount == 0:
                raise AccountError(f"user {name!r} does not exist")
            conn.execute(sa.delete(_sessions).where(_sessions.c.user == name))

    def set_role(self, name: str, role: str) -> User:
        """Change a user's role (its sessions see it on their next request)."""
        checked = _check_role(role)
        with self._write() as conn:
            if checked != "admin":
                self._keep_an_admin(conn, name)
            done = conn.execute(sa.update(_users).where(_users.c.name == name).values(role=checked))
            if done.rowcount == 0:
                raise AccountError(f"user {name!r} does not exist")
        return self.user(name)

    def disable(self, name: str) -> None:
        """Disable a user: its sessions end and it can no longer log in (the audit log keeps its name)."""
        with self._write() as conn:
            self._keep_an_admin(conn, name)
            done = conn.execute(sa.update(_users).where(_users.c.name == name).values(disabled=True))
            if done.rowcount == 0:
                raise AccountError(f"user {name!r} does not exist")
            conn.execute(sa.delete(_sessions).where(_sessions.c.user == name))

    def user(self, name: str) -> User:
        with self._engine.connect() as conn:
            row = conn.execute(sa.select(_users).where(_users.c.name == name)).mappings().first()
        if row is None:
            raise AccountError(f"user {name!r} does not exist")
        return _user(row)

    def users(self) -> list[User]:
        with self._engine.connect() as conn:
            rows = conn.execute(sa.select(_users).order_by(_users.c.name)).mappings().all()
        return [_user(r) for r in rows]

    def has_admin(self) -> bool:
        """Whether an enabled admin exists (the server refuses to start without one)."""
        with self._engine.connect() as conn:
            q = sa.select(_users.c.name).where(_users.c.role == "admin", _users.c.disabled.is_(False))
            return conn.execute(q).first() is not None

    # -- sessions ---------------------------------------------------------------------------------

    def login(self, name: str, password: str) -> LoginSession:
        """Check a password and open a session.

        Raises:
            AccountError: The same message for an unknown user, a wrong password and a disabled
                user (a login form must not tell which names exist).
        """
        refused = AccountError("wrong user name or password")
        if len(password) > _MAX_PASSWORD or not _NAME.match(name):
            raise refused
        with self._engine.connect() as conn:
            row = conn.execute(sa.select(_users).where(_users.c.name == name)).mappings().first()
        if row is None:
            self._hasher.hash(password)  # the same time as a real check: no user enumeration by timing
            raise refused
        try:
            self._hasher.verify(row["password_hash"], password)
        except (VerificationError, InvalidHashError):
            raise refused from None
        user = _user(row)
        if user.disabled:
            raise refused
        if self._hasher.check_needs_rehash(row["password_hash"]):
            with self._write() as conn:
                conn.execute(
                    sa.update(_users)
                    .where(_users.c.name == name)
                    .values(password_hash=self._hasher.hash(password))
                )
        token, csrf, now = (
            secrets.token_urlsafe(_TOKEN_BYTES),
            secrets.token_urlsafe(_TOKEN_BYTES),
            time.time_ns(),
        )
        with self._write() as conn:
            conn.execute(
                sa.insert(_sessions).values(
                    token_sha256=_sha(token), user=name, csrf=csrf, created_ns=now, seen_ns=now
                )
            )
        return LoginSession(user, csrf, now, token)

    def session(self, token: str) -> LoginSession | None:
        """The live session of a cookie token (and mark it seen); ``None`` when unknown or expired."""
        if not token or len(token) > 200:
            return None
        now = time.time_ns()
        with self._write() as conn:
            row = (
                conn.execute(
                    sa.select(_sessions, _users)
                    .join(_users, _users.c.name == _sessions.c.user)
                    .where(_sessions.c.token_sha256 == _sha(token))
                )
                .mappings()
                .first()
            )
            if row is None:
                return None
            expired = (
                now - row["seen_ns"] > SESSION_IDLE_S * 1e9 or now - row["created_ns"] > SESSION_MAX_S * 1e9
            )
            if expired or row["disabled"]:
                conn.execute(sa.delete(_sessions).where(_sessions.c.token_sha256 == _sha(token)))
                return None
            conn.execute(
                sa.update(_sessions).where(_sessions.c.token_sha256 == _sha(token)).values(seen_ns=now)
            )
        return LoginSession(_user(row), row["csrf"], row["created_ns"])

    def logout(self, token: str) -> None:
        with self._write() as conn:
            conn.execute(sa.delete(_sessions).where(_sessions.c.token_sha256 == _sha(token)))

    # -- audit ------------------------------------------------------------------------------------

    def audit(
        self, action: str, *, user: str | None, target: str = "", detail: str = "", client: str = ""
    ) -> None:
        """Append one entry to the audit log (texts cut to 500 characters)."""
        with self._write() as conn:
            conn.execute(
                sa.insert(_audit).values(
                    t_ns=time.time_ns(),
                    user=user,
                    action=action[:64],
                    target=target[:_AUDIT_TEXT],
                    detail=detail[:_AUDIT_TEXT],
                    client=client[:64],
                )
            )

    def audit_log(self, *, limit: int = 200, before_seq: int | None = None) -> list[AuditEntry]:
        """Newest entries first; ``before_seq`` pages back."""
        q = sa.select(_audit).order_by(_audit.c.seq.desc()).limit(max(1, min(limit, 1000)))
        if before_seq is not None:
            q = q.where(_audit.c.seq < before_seq)
        with self._engine.connect() as conn:
            rows = conn.execute(q).mappings().all()
        return [
            AuditEntry(r["seq"], r["t_ns"], r["user"], r["action"], r["target"], r["detail"], r["client"])
            for r in rows
        ]

    # -- internals --------------------------------------------------------------------------------

    @contextmanager
    def _write(self) -> Iterator[Connection]:
        with self._engine.connect() as conn, conn.begin():
            yield conn

    @staticmethod
    def _keep_an_admin(conn: Connection, name: str) -> None:
        q = sa.select(_users.c.name).where(
            _users.c.role == "admin", _users.c.disabled.is_(False), _users.c.name != name
        )
        if conn.execute(q).first() is None:
            row = conn.execute(sa.select(_users.c.role).where(_users.c.name == name)).first()
            if row is not None and row[0] == "admin":
                raise AccountError(f"{name!r} is the last admin; make another user admin first")


def _user(row: sa.RowMapping) -> User:
    return User(row["name"], _check_role(row["role"]), row["created_ns"], bool(row["disabled"]))


def _sqlite_pragmas(dbapi_connection: object, _record: object) -> None:
    cursor = dbapi_connection.cursor()  # type: ignore[attr-defined]
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()
