"""Cyclone DDS set-up shared by the Unitree driver and its fake robot: one domain per process and id.

Unitree robots talk DDS on their own network (192.168.123.0/24) with multicast discovery; the
host joins through the interface on that network, as Unitree's SDK does
(``ChannelFactoryInitialize(0, "eth0")``). On the loopback interface, which has no multicast,
discovery goes unicast to 127.0.0.1 instead, so a dry run against
:class:`~telerig.robots.unitree.fake.FakeG1` needs no network at all.
"""

from __future__ import annotations

import threading
from xml.sax.saxutils import quoteattr

from cyclonedds.core import Entity
from cyclonedds.domain import Domain

from telerig.errors import RobotError

__all__ = ["cyclone_config", "delete_entities", "join_domain"]

_lock = threading.Lock()
_domains: dict[int, tuple[str, Domain]] = {}


def cyclone_config(network_interface: str) -> str:
    """Cyclone DDS XML for a domain on ``network_interface`` (unicast discovery on ``lo``)."""
    loopback = network_interface == "lo"
    discovery = (
        "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32"
        '</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>'
        if loopback
        else ""
    )
    return (
        '<CycloneDDS><Domain Id="any"><General><Interfaces>'
        f"<NetworkInterface name={quoteattr(network_interface)}/></Interfaces>"
        f"<AllowMulticast>{'false' if loopback else 'default'}</AllowMulticast></General>"
        f"{discovery}</Domain></CycloneDDS>"
    )


def join_domain(domain_id: int, network_interface: str) -> None:
    """Configure DDS domain ``domain_id`` of this process on ``network_interface`` (once).

    Raises:
        RobotError: the domain is already configured on another interface in this process, or
            Cyclone DDS refused the interface (the message names it).
    """
    config = cyclone_config(network_interface)
    with _lock:
        known = _domains.get(domain_id)
        if known is not None:
            if known[0] != config:
                raise RobotError(
                    f"DDS domain {domain_id} is already in use on another interface in this process; "
                    "give each Unitree robot on another network its own domain_id"
                )
            return
        try:
            _domains[domain_id] = (config, Domain(domain_id, config))
        except Exception as exc:  # Cyclone raises DDSException for a missing interface
            raise RobotError(
                f"DDS domain {domain_id} could not start on network interface {network_interface!r} "
                f"({exc}); set network_interface to the one on the robot's network (see `ip addr`)"
            ) from None


def delete_entities(entities: tuple[Entity, ...]) -> None:
    """Delete DDS entities children first (readers and writers, then topics, then the participant).

    Deleting only the participant deletes its children in Cyclone but leaves their Python objects
    holding stale handles that the garbage collector deletes again later, at any time; deleting
    each through its own ``__del__`` (idempotent) unregisters it, so nothing is deleted twice.
    """
    for entity in entities:
        entity.__del__()
