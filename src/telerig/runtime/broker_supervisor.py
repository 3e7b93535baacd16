"""Broker supervision: start the rig's embedded broker (or use the given one) and restart it if it dies."""

from __future__ import annotations

import json
import logging
import threading

from telerig.bus.acl import STATION, AccessPolicy, principal_for_node, robot_process_principal
from telerig.bus.base import Bus
from telerig.bus.broker import BROKER_DIR_PREFIX, MosquittoBroker, remove_stale_broker_dirs
from telerig.bus.catalogue import ALERTS, BROKER
from telerig.bus.topics import Topic, qos_for
from telerig.config.schema import BrokerConfig, EmbeddedBrokerConfig
from telerig.errors import TelerigError
from telerig.ir.types import now_ns
from telerig.runtime.realtime import set_realtime_priority

__all__ = ["BROKER_DIR_PREFIX", "BrokerSupervisor", "remove_stale_broker_dirs"]

#: Where :class:`~telerig.bus.broker.MosquittoBroker` keeps its config, logins and ACL (``mkdtemp`` prefix).
#: A broker directory younger than this may belong to a broker still starting [s].

log = logging.getLogger(__name__)


class BrokerSupervisor:
    """Owns the embedded broker of a station: starts it, watches it, restarts it, records outages.

    With an external broker (the rig's ``broker.url``, or ``broker_url`` given by a following
    station) it only hands out that address.

    Args:
        rig: Rig name (alerts go on ``telerig/v1/<rig>/broker/alerts``).
        config: The rig's broker section.
        broker_url: Broker to use instead of the rig's.
        access: Who may log in to the embedded broker and publish where (the rig's principals,
            :func:`telerig.bus.acl.rig_access_policy`); ``None``: one owner allowed everything.
        realtime_priority: ``SCHED_RR`` priority of the embedded broker (the rig's robot processes'
            one): every sample a robot process consumes passes through the broker, so a broker at
            normal priority is starved by the robots it serves once they fill the CPUs (measured on
            the fleet rig, 2 cores: 15 of 400 commands applied in 4 s; 408 with the broker at theirs).
    """

    def __init__(
        self,
        rig: str,
        config: BrokerConfig,
        *,
        broker_url: str | None = None,
        access: AccessPolicy | None = None,
        realtime_priority: int | None = None,
    ) -> None:
        self._rig = rig
        self._realtime_priority = realtime_priority
        self._access = access
        self._config = config
        self._given_url = broker_url
        self._broker: MosquittoBroker | None = None
        self._stop = threading.Event()
        self._alerts: Bus | None = None
        #: ``(down_ns, up_ns)`` of every restart of the embedded broker, common clock [ns].
        self.outages: list[tuple[int, int]] = []
        #: The broker's address once :meth:`start` returned.
        self.url: str | None = None

    @property
    def embedded(self) -> MosquittoBroker | None:
        """The embedded broker process, if this station runs one."""
        return self._broker

    def start(self) -> str:
        """Start the embedded broker and its watchdog (or take the external one); returns the URL."""
        config = self._config
        if self._given_url is not None:
            self.url = self._given_url
        elif isinstance(config, EmbeddedBrokerConfig):
            remove_stale_broker_dirs()
            self._broker = MosquittoBroker(
                port=config.port,
                max_queued_messages=config.max_queued_messages,
                message_size_limit=config.message_size_limit,
                access=self._access,
                owner=None if self._access is None else STATION,
            )
            self._broker.start()
            self._prioritize()
            threading.Thread(target=self._watch, name="broker-watchdog", daemon=True).start()
            self.url = self._broker.url
        else:
            self.url = config.url
        return self.url

    def node_url(self, url: str, node: str) -> str:
        """The URL a bus client named ``node`` of this station logs in with: its principal's on the
        embedded broker with the rig's access policy, else ``url`` as given."""
        if self._broker is None or self._access is None:
            return url
        return self._broker.url_for(principal_for_node(node))

    def host_url(self, url: str, robot: str) -> str:
        """The URL the process hosting ``robot`` logs in with (see :meth:`node_url`)."""
        if self._broker is None or self._access is None:
            return url
        return self._broker.url_for(robot_process_principal(robot))

    def publish_alerts_on(self, bus: Bus) -> None:
        """Publish restart alerts on ``bus`` (a client that reconnects after the restart)."""
        self._alerts = bus

    def outages_since(self, start_ns: int) -> list[tuple[int, int]]:
        """The outages that began at or after ``start_ns`` [ns]."""
        return [(down, up) for down, up in self.outages if down >= start_ns]

    def close(self) -> None:
        """Stop the watchdog, then the embedded broker. Idempotent."""
        self._stop.set()
        if self._broker is not None:
            self._broker.stop()

    def _watch(self, period_s: float = 0.25) -> None:
        """Restart the embedded broker if it dies; the clients reconnect, the outage is recorded and alerted.

        Recording is local, so the episode goes on; the bus streams have a gap for the outage.
        """
        broker = self._broker
        while broker is not None and not self._stop.wait(period_s):
            if broker.running or self._stop.is_set():
                continue
            down_ns = now_ns()
            log.warning("embedded broker died; restarting it on the same port")
            try:
                broker.restart()
            except TelerigError as exc:
                log.error("embedded broker could not be restarted: %s", exc)
                continue
            # When it first accepted a connection: the watchdog may get the CPU back later than the
            # clients that reconnected at once.
            up_ns = broker.listening_since_ns
            self._prioritize()
            self.outages.append((down_ns, up_ns))
            self._alert(down_ns, up_ns)

    def _prioritize(self) -> None:
        broker, priority = self._broker, self._realtime_priority
        if broker is not None and priority is not None and broker.pid is not None:
            set_realtime_priority(priority, "the embedded broker", pid=broker.pid)

    def _alert(self, down_ns: int, up_ns: int) -> None:
        if self._alerts is None:
            return
        alert = {
            "code": "broker_restarted",
            "severity": "warning",
            "reason": "the embedded MQTT broker process died and was restarted",
            "suggested_action": "check the broker log and the machine's memory; bus streams have a gap",
            "active": False,
            "down_ns": down_ns,
            "up_ns": up_ns,
        }
        qos, retain = qos_for(ALERTS)
        topic = str(Topic(self._rig, BROKER, ALERTS))
        self._alerts.publish(topic, json.dumps(alert).encode(), qos=qos, retain=retain)
