"""Broker supervision: start the rig's embedded broker (or use the given one) and restart it if it dies."""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Collection
from pathlib import Path

from telerig.bus.acl import (
    STATION,
    AccessPolicy,
    principal_for_node,
    robot_process_principal,
    station_principal,
)
from telerig.bus.base import Bus
from telerig.bus.broker import BROKER_DIR_PREFIX, MosquittoBroker, remove_stale_broker_dirs
from telerig.bus.catalogue import ALERTS, BROKER
from telerig.bus.registered import folder_signature, log_warnings, read_registered_logins
from telerig.bus.topics import Topic, qos_for
from telerig.config.schema import BrokerConfig, EmbeddedBrokerConfig, RigConfig
from telerig.errors import TelerigError
from telerig.ir.types import now_ns
from telerig.runtime.realtime import set_realtime_priority

__all__ = ["BROKER_DIR_PREFIX", "BrokerSupervisor", "remove_stale_broker_dirs", "station_logins"]

#: Where :class:`~telerig.bus.broker.MosquittoBroker` keeps its config, logins and ACL (``mkdtemp`` prefix).
#: A broker directory younger than this may belong to a broker still starting [s].

log = logging.getLogger(__name__)

#: How often the watchdog checks the broker process and the registered logins' files [s].
WATCH_PERIOD_S = 0.25


def station_logins(config: RigConfig, station: str) -> frozenset[str]:
    """The principals ``station`` of ``config`` logs in as, or whose streams it publishes itself:
    the station's, and every device's, camera's and robot's (``dev-``, ``cam-``, ``ctl-``,
    ``robot-``) that runs on it. A registered login of one of them is not added to the embedded
    broker: its password would replace the station's per-run one and lock out the station's own
    node, and an outside client would publish the same streams as that node. Registered logins are
    for devices and robots of the rig that no ``telerig run`` of this station runs."""
    names = {STATION, station_principal(config, station)}
    names |= {f"dev-{d.id}" for d in config.devices if d.station == station}
    names |= {f"cam-{c.id}" for c in config.cameras if c.station == station}
    for robot in config.robots:
        if robot.station == station:
            names |= {f"ctl-{robot.id}", robot_process_principal(robot.id)}
    return frozenset(names)


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
        registered_folder: The rig's broker folder (``<data root>/broker/<rig>``), where the control
            center keeps its registered devices' logins (:mod:`telerig.bus.registered`): the embedded
            broker adds them at start, and the watchdog applies a register or revoke within
            :data:`WATCH_PERIOD_S` (rewrite, then ``SIGHUP``: Mosquitto disconnects a revoked login).
            The control center does not signal this broker itself: its password file also holds
            the station's per-run logins, which only this process knows.
        reserved: Principals this station's own nodes log in as (per-run passwords); a registered
            login of one is left out with a warning, so a registration cannot lock out the station.
    """

    def __init__(
        self,
        rig: str,
        config: BrokerConfig,
        *,
        broker_url: str | None = None,
        access: AccessPolicy | None = None,
        realtime_priority: int | None = None,
        registered_folder: Path | None = None,
        reserved: Collection[str] = (),
    ) -> None:
        self._rig = rig
        self._registered_folder = registered_folder
        self._reserved = frozenset(reserved)
        self._registered_seen: object = None
        # The watchdog's reread and a node's own login both change the broker's registered logins.
        self._registered_lock = threading.Lock()
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
                registered=self._read_registered(),
            )
            if self._broker.registered:
                log.info("embedded broker: %d registered login(s) added", len(self._broker.registered))
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
        return self._own_login(principal_for_node(node))

    def host_url(self, url: str, robot: str) -> str:
        """The URL the process hosting ``robot`` logs in with (see :meth:`node_url`)."""
        if self._broker is None or self._access is None:
            return url
        return self._own_login(robot_process_principal(robot))

    def _own_login(self, principal: str) -> str:
        """The URL of a principal this station's node logs in as; a registered login of it (which
        :func:`station_logins` should have reserved) is dropped first, so the node's works."""
        assert self._broker is not None
        with self._registered_lock:
            if principal in self._reserved:
                return self._broker.url_for(principal)
            self._reserved |= {principal}
            registered = dict(self._broker.registered)
            if registered.pop(principal, None) is not None:
                log.warning("registered login %r left out: a node of this station logs in as it", principal)
                self._broker.set_registered(registered)
        return self._broker.url_for(principal)

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

    def _watch(self, period_s: float = WATCH_PERIOD_S) -> None:
        """Restart the embedded broker if it dies; the clients reconnect, the outage is recorded and alerted.

        Recording is local, so the episode goes on; the bus streams have a gap for the outage.
        """
        broker = self._broker
        while broker is not None and not self._stop.wait(period_s):
            if self._stop.is_set():
                continue
            if broker.running:
                self._apply_registered(broker)
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

    def _read_registered(self) -> dict[str, str]:
        """The registered logins of the folder (warnings logged); none without a folder or policy."""
        folder, access = self._registered_folder, self._access
        if folder is None or access is None:
            return {}
        self._registered_seen = folder_signature(folder)
        logins = read_registered_logins(folder, access.principals, self._reserved | {STATION})
        log_warnings(logins)
        return dict(logins.hashes)

    def _apply_registered(self, broker: MosquittoBroker) -> None:
        """Reread the folder when its files changed; reload the broker when its logins changed."""
        folder = self._registered_folder
        if folder is None or folder_signature(folder) == self._registered_seen:
            return
        with self._registered_lock:
            self._apply_registered_locked(broker)

    def _apply_registered_locked(self, broker: MosquittoBroker) -> None:
        hashes = self._read_registered()
        if hashes == dict(broker.registered):
            return
        added = sorted(set(hashes) - set(broker.registered))
        removed = sorted(set(broker.registered) - set(hashes))
        try:
            broker.set_registered(hashes)
        except (TelerigError, OSError) as exc:
            log.error("embedded broker: registered logins not applied: %s", exc)
            return
        log.info(
            "embedded broker reloaded its registered logins: %d (added %s, removed %s)",
            len(hashes),
            ", ".join(added) or "none",
            ", ".join(removed) or "none",
        )

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
