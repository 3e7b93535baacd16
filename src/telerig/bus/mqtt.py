"""The MQTT bus: :class:`~telerig.bus.base.Bus` on paho-mqtt 2.x (MQTT 3.1.1), plain or over TLS."""

from __future__ import annotations

import logging
import os
import socket
import ssl
import threading
from dataclasses import dataclass
from types import TracebackType
from typing import Any
from urllib.parse import unquote, urlsplit

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode

from telerig.bus.base import DEFAULT_QUEUE_SIZE, BusStats, Message, MessageHandler, topic_matches
from telerig.bus.broker import MosquittoBroker
from telerig.config.schema import BrokerConfig, EmbeddedBrokerConfig
from telerig.errors import BusError, ConfigError
from telerig.ir.types import now_ns

__all__ = ["MqttBus", "MqttUrl", "TlsOptions", "connect_bus", "rig_tls"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 1883
DEFAULT_TLS_PORT = 8883
_URL_FORM = "mqtt://[user:password@]host[:port] or mqtts://... (TLS)"
_FIX = (
    "check the host and port (`telerig run` prints the URL of the broker it runs) "
    "or start a broker there (e.g. `mosquitto -p PORT`)"
)


class _TlsContext(ssl.SSLContext):
    """Remembers the socket it wrapped last: paho leaves it open when the handshake fails."""

    last: ssl.SSLSocket | None = None

    def wrap_socket(self, *args: Any, **kwargs: Any) -> ssl.SSLSocket:
        self.last = super().wrap_socket(*args, **kwargs)
        return self.last


@dataclass(frozen=True, slots=True)
class TlsOptions:
    """How a client checks the broker (and proves itself) over TLS: PEM files.

    Attributes:
        ca_file: CA certificate(s) the broker's certificate must chain to; ``None``: the
            system's trusted CAs.
        cert_file: Client certificate, for brokers that require one (``require_certificate``).
        key_file: Private key of ``cert_file``.
    """

    ca_file: str | os.PathLike[str] | None = None
    cert_file: str | os.PathLike[str] | None = None
    key_file: str | os.PathLike[str] | None = None

    def __post_init__(self) -> None:
        if self.key_file is not None and self.cert_file is None:
            raise ConfigError("a TLS key_file needs its cert_file")
        for name in ("ca_file", "cert_file", "key_file"):
            path = getattr(self, name)
            if path is not None and not os.path.isfile(path):
                raise ConfigError(f"TLS {name} {str(path)!r} does not exist or is not a file")

    def context(self) -> ssl.SSLContext:
        """A client context that verifies the broker's certificate and host name."""
        context = _TlsContext(ssl.PROTOCOL_TLS_CLIENT)  # verifies the certificate and host name
        if self.ca_file is None:
            context.load_default_certs()
        else:
            context.load_verify_locations(cafile=os.fspath(self.ca_file))
        if self.cert_file is not None:
            key = None if self.key_file is None else os.fspath(self.key_file)
            context.load_cert_chain(os.fspath(self.cert_file), key)
        return context


def rig_tls(broker: BrokerConfig) -> TlsOptions | None:
    """The TLS options of a rig's broker section: its external broker's ``tls``, if any."""
    if isinstance(broker, EmbeddedBrokerConfig) or broker.tls is None:
        return None
    return TlsOptions(broker.tls.ca_file, broker.tls.cert_file, broker.tls.key_file)


@dataclass(frozen=True, slots=True)
class MqttUrl:
    """A parsed ``mqtt[s]://[user:password@]host[:port]`` broker address."""

    host: str
    port: int = DEFAULT_PORT
    username: str | None = None
    password: str | None = None
    tls: bool = False

    @classmethod
    def parse(cls, url: str) -> MqttUrl:
        """Parse a broker URL; the default port is 1883 (``mqtt``) or 8883 (``mqtts``, TLS).

        Raises:
            ConfigError: Another scheme, no host, a bad port, or a path; the message shows the valid form.
        """
        try:
            parts = urlsplit(url)
            port = parts.port
        except ValueError as exc:
            raise ConfigError(f"invalid bus URL {url!r} ({exc}); use {_URL_FORM}") from None
        if parts.scheme not in ("mqtt", "mqtts"):
            raise ConfigError(f"unsupported bus URL {url!r}: use {_URL_FORM}")
        if not parts.hostname:
            raise ConfigError(f"bus URL {url!r} has no host: use {_URL_FORM}")
        if parts.path not in ("", "/") or parts.query or parts.fragment:
            raise ConfigError(f"bus URL {url!r} must not have a path or query: use {_URL_FORM}")
        tls = parts.scheme == "mqtts"
        return cls(
            host=parts.hostname,
            port=(DEFAULT_TLS_PORT if tls else DEFAULT_PORT) if port is None else port,
            tls=tls,
            username=None if parts.username is None else unquote(parts.username),
            password=None if parts.password is None else unquote(parts.password),
        )

    def __str__(self) -> str:
        """The URL with the password masked, safe for logs and error messages."""
        auth = "" if self.username is None else f"{self.username}{':***' if self.password else ''}@"
        return f"{'mqtts' if self.tls else 'mqtt'}://{auth}{self.host}:{self.port}"


def _valid_pattern(pattern: str) -> bool:
    levels = pattern.split("/")
    for i, level in enumerate(levels):
        if ("#" in level and (level != "#" or i != len(levels) - 1)) or ("+" in level and level != "+"):
            return False
    return bool(pattern)


@dataclass(eq=False, slots=True)
class _MqttSubscription:
    bus: MqttBus
    pattern: str
    handler: MessageHandler
    qos: int

    def cancel(self) -> None:
        self.bus._remove(self)


class MqttBus:
    """A :class:`~telerig.bus.base.Bus` client of an MQTT broker.

    The network loop runs on paho's thread, which also runs the handlers: they must
    not block (hand messages to an :class:`~telerig.bus.base.Inbox`). A handler that
    raises is counted in ``stats.handler_errors`` and logged; delivery goes on.

    ``publish`` never blocks. QoS 1/2 messages wait in a bounded outgoing queue while
    unacknowledged or disconnected; when it is full, the message is dropped and counted
    in ``stats.publish_overflow``. A QoS 0 message published while disconnected is also
    dropped and counted there. After a lost connection the client reconnects with
    exponential backoff, subscribes again (the broker resends retained state) and counts
    ``stats.reconnects``.

    Overlapping subscriptions: each matching handler gets a message once (Mosquitto sends
    MQTT 3.1.1 clients one copy). Subscribing a second handler to a pattern already
    subscribed asks the broker again, so the new handler gets the retained state; the
    handlers already there may see it again.

    Example::

        with MqttBus("mqtt://127.0.0.1:1883", client_id="vr0") as bus:
            bus.subscribe("telerig/v1/demo/+/session", inbox, qos=1)
            bus.publish("telerig/v1/demo/vr0/controller_right", payload)
    """

    def __init__(
        self,
        url: str,
        *,
        client_id: str,
        max_queued_messages: int = DEFAULT_QUEUE_SIZE,
        tcp_nodelay: bool = True,
        keepalive_s: int = 10,
        connect_timeout_s: float = 5.0,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 2.0,
        broker: MosquittoBroker | None = None,
        username: str | None = None,
        password: str | None = None,
        tls: TlsOptions | None = None,
    ) -> None:
        """Configure the client; nothing touches the network until :meth:`connect`.

        Args:
            url: ``mqtt://[user:password@]host[:port]``.
            client_id: MQTT client id, unique per broker (the node name).
            max_queued_messages: Bound of the outgoing QoS 1/2 queue [messages].
            tcp_nodelay: Disable Nagle's algorithm on the socket (lower latency for small messages).
            keepalive_s: MQTT keepalive; a dead connection is noticed within 1.5x this [s].
            connect_timeout_s: How long :meth:`connect` waits for the broker's CONNACK [s].
            reconnect_min_s: First delay before reconnecting, doubled per failed try [s].
            reconnect_max_s: Cap of the reconnect delay [s].
            broker: An embedded broker this bus owns: :meth:`close` stops it.
            username: Log in as this user (overrides the URL's).
            password: Its password.
            tls: CA and client certificate for an ``mqtts://`` URL; ``None`` trusts the system's CAs.

        Raises:
            ConfigError: A malformed URL or option; ``tls`` with an ``mqtt://`` URL.
        """
        self._url = MqttUrl.parse(url)
        if username is not None:
            self._url = MqttUrl(self._url.host, self._url.port, username, password, self._url.tls)
        if tls is not None and not self._url.tls:
            raise ConfigError(f"TLS options given for {self._url}: use an mqtts:// URL")
        if not client_id:
            raise ConfigError("client_id must be non-empty (use the node name)")
        if max_queued_messages < 1:
            raise ConfigError(f"max_queued_messages must be >= 1, got {max_queued_messages}")
        if connect_timeout_s <= 0 or keepalive_s < 1:
            raise ConfigError("connect_timeout_s must be > 0 and keepalive_s >= 1")
        if not 0 < reconnect_min_s <= reconnect_max_s:
            raise ConfigError(
                f"need 0 < reconnect_min_s <= reconnect_max_s, got {reconnect_min_s} and {reconnect_max_s}"
            )
        self._client_id = client_id
        self._tcp_nodelay = tcp_nodelay
        self._keepalive_s = keepalive_s
        self._connect_timeout_s = connect_timeout_s
        self._broker = broker
        self._stats = BusStats()
        self._stats_lock = threading.Lock()
        self._lock = threading.Lock()
        # Copy-on-write: the delivery thread reads the tuple without taking the lock.
        self._subs: tuple[_MqttSubscription, ...] = ()
        self._connack = threading.Event()
        self._connack_reason: str | None = None
        self._connected = False
        self._ever_connected = False
        self._closed = False
        self._stopping = False  # set while we disconnect on purpose: no "lost the broker" warning

        client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=paho.MQTTv311,
            clean_session=True,
        )
        if self._url.username is not None:
            client.username_pw_set(self._url.username, self._url.password)
        self._tls_context: ssl.SSLContext | None = None
        if self._url.tls:
            self._tls_context = (tls or TlsOptions()).context()
            client.tls_set_context(self._tls_context)
        client.max_queued_messages_set(max_queued_messages)
        client.reconnect_delay_set(reconnect_min_s, reconnect_max_s)  # paho accepts float seconds
        client.connect_timeout = connect_timeout_s
        client.on_socket_open = self._on_socket_open
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        self._client = client

    @property
    def stats(self) -> BusStats:
        """Counters of this client."""
        return self._stats

    @property
    def url(self) -> str:
        """The broker URL with the password masked."""
        return str(self._url)

    @property
    def client_id(self) -> str:
        """The MQTT client id."""
        return self._client_id

    @property
    def connected(self) -> bool:
        """Whether the broker has acknowledged the current connection."""
        return self._connected

    @property
    def broker(self) -> MosquittoBroker | None:
        """The embedded broker this bus owns, if any (share ``broker.url`` with other clients)."""
        return self._broker

    def connect(self) -> MqttBus:
        """Connect and wait for the broker's CONNACK; then start the network thread. Returns ``self``.

        Raises:
            BusError: The broker is unreachable, silent or refuses the client; the message
                names the URL and the fix.
        """
        if self._closed:
            raise BusError(f"bus {self._client_id!r} is closed; create a new MqttBus")
        if self._connected:
            return self
        self._connack.clear()
        self._connack_reason = None
        self._stopping = False
        try:
            self._client.connect(self._url.host, self._url.port, keepalive=self._keepalive_s)
        except ssl.SSLError as exc:
            if isinstance(self._tls_context, _TlsContext) and self._tls_context.last is not None:
                self._tls_context.last.close()
            if isinstance(exc, ssl.SSLCertVerificationError):
                reason = f"certificate verify failed: {exc.verify_message}"
            else:
                reason = exc.reason or str(exc)
            raise BusError(
                f"TLS handshake with the MQTT broker at {self._url} failed ({reason}); give the CA that "
                "signed its certificate (the rig's broker.tls.ca_file or --ca-file), or check the "
                "host name in the URL"
            ) from None
        except OSError as exc:
            reason = exc.strerror or str(exc) or type(exc).__name__
            raise BusError(f"cannot reach the MQTT broker at {self._url} ({reason}); {_FIX}") from None
        self._client.loop_start()
        if not self._connack.wait(self._connect_timeout_s):
            self._shutdown_client()
            raise BusError(
                f"the MQTT broker at {self._url} did not answer within {self._connect_timeout_s} s; "
                f"check that it is an MQTT broker, or {_FIX}"
            )
        if self._connack_reason is not None:
            self._shutdown_client()
            raise BusError(
                f"the MQTT broker at {self._url} refused client {self._client_id!r}: "
                f"{self._connack_reason}; check the user and password in the URL"
            )
        return self

    def publish(self, topic: str, payload: bytes, *, qos: int = 0, retain: bool = False) -> None:
        """Send ``payload`` on ``topic`` with ``qos`` 0, 1 or 2. Never blocks; drops and counts when full."""
        if self._closed:
            return
        rc = self._client.publish(topic, payload, qos=qos, retain=retain).rc
        with self._stats_lock:
            if rc == MQTTErrorCode.MQTT_ERR_SUCCESS or (rc == MQTTErrorCode.MQTT_ERR_NO_CONN and qos > 0):
                # A QoS 1/2 message published while disconnected waits in paho's queue.
                self._stats.published += 1
            else:
                self._stats.publish_overflow += 1

    def subscribe(self, pattern: str, handler: MessageHandler, *, qos: int = 0) -> _MqttSubscription:
        """Call ``handler`` on the network thread for every message matching ``pattern`` (``+``, ``#``)."""
        if qos not in (0, 1, 2):
            raise ValueError(f"qos must be 0, 1 or 2, got {qos}")
        if not _valid_pattern(pattern):
            raise ValueError(f"invalid MQTT subscription pattern {pattern!r}")
        if self._closed:
            raise BusError(f"bus {self._client_id!r} is closed")
        sub = _MqttSubscription(self, pattern, handler, qos)
        with self._lock:
            self._subs = (*self._subs, sub)
            server_qos = max(s.qos for s in self._subs if s.pattern == pattern)
        # While disconnected this is a no-op; _on_connect subscribes everything again.
        self._client.subscribe(pattern, server_qos)
        return sub

    def close(self) -> None:
        """Disconnect, stop the network thread and, if owned, the embedded broker. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._subs = ()
        self._shutdown_client()
        if self._broker is not None:
            self._broker.stop()

    def __enter__(self) -> MqttBus:
        return self.connect()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _shutdown_client(self) -> None:
        self._stopping = True
        self._client.disconnect()
        self._client.loop_stop()
        # paho 2.2 leaves the wake-up socket pair of loop_start() open (ResourceWarning).
        reset = getattr(self._client, "_reset_sockets", None)
        if reset is not None:
            reset()
        self._connected = False

    def _remove(self, sub: _MqttSubscription) -> None:
        with self._lock:
            if sub not in self._subs:
                return
            self._subs = tuple(s for s in self._subs if s is not sub)
            still_used = any(s.pattern == sub.pattern for s in self._subs)
        if not still_used and not self._closed:
            self._client.unsubscribe(sub.pattern)

    # paho callbacks, run on the network thread.

    def _on_socket_open(self, client: paho.Client, userdata: Any, sock: Any) -> None:
        # An SSLSocket is a socket: the option reaches the TCP socket under the TLS layer.
        if self._tcp_nodelay:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except (AttributeError, OSError) as exc:  # e.g. a websocket wrapper
                log.warning("%s: cannot set TCP_NODELAY: %s", self._client_id, exc)

    def _on_connect(
        self, client: paho.Client, userdata: Any, flags: Any, reason_code: Any, properties: Any
    ) -> None:
        if reason_code.is_failure:
            self._connack_reason = str(reason_code)
            # During connect() the BusError says it; later (a reconnect) only the log can.
            level = logging.WARNING if self._ever_connected else logging.DEBUG
            log.log(level, "%s: broker %s refused us: %s", self._client_id, self._url, reason_code)
            self._connack.set()
            return
        # Subscribe again before flagging the connection up, so a caller that waits for
        # ``connected`` and then subscribes cannot overtake the old subscriptions.
        topics: dict[str, int] = {}
        for sub in self._subs:
            topics[sub.pattern] = max(topics.get(sub.pattern, 0), sub.qos)
        if topics:
            client.subscribe(list(topics.items()))
        if self._ever_connected:
            with self._stats_lock:
                self._stats.reconnects += 1
            log.info("%s: reconnected to %s", self._client_id, self._url)
        self._ever_connected = True
        self._connected = True
        self._connack.set()

    def _on_disconnect(
        self, client: paho.Client, userdata: Any, flags: Any, reason_code: Any, properties: Any
    ) -> None:
        self._connected = False
        if not self._stopping:
            log.warning("%s: lost the broker %s (%s); reconnecting", self._client_id, self._url, reason_code)

    def _on_message(self, client: paho.Client, userdata: Any, msg: paho.MQTTMessage) -> None:
        received_ns = now_ns()
        topic: str = msg.topic
        message = Message(topic, bytes(msg.payload), received_ns)
        for sub in self._subs:
            if not topic_matches(sub.pattern, topic):
                continue
            try:
                sub.handler(message)
            except Exception:
                with self._stats_lock:
                    self._stats.handler_errors += 1
                log.exception("%s: handler for %s failed on %s", self._client_id, sub.pattern, topic)
            else:
                self._stats.delivered += 1


def connect_bus(url: str | None = None, *, client_id: str, **options: Any) -> MqttBus:
    """Connect to the broker at ``url``, or start an embedded Mosquitto when ``url`` is ``None``.

    The returned bus is connected. With no URL it owns the embedded broker: ``bus.broker.url``
    is the address for other clients, and ``bus.close()`` stops the broker after disconnecting.

    Args:
        url: ``mqtt://[user:password@]host[:port]`` or ``None`` for the embedded broker.
        client_id: MQTT client id (the node name).
        options: Passed to :class:`MqttBus`.

    Raises:
        ConfigError: The URL is malformed.
        DependencyError: No URL and Mosquitto is not installed.
        BusError: The broker could not be started or reached.
    """
    if url is not None:
        return MqttBus(url, client_id=client_id, **options).connect()
    broker = MosquittoBroker().start()
    try:
        return MqttBus(broker.url, client_id=client_id, broker=broker, **options).connect()
    except BaseException:
        broker.stop()
        raise
