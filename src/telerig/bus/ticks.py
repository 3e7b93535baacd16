"""A robot's control tick on the bus: its IR samples travel together in one ``tick`` message.

A control node publishes what one tick made (the joint command requested and sent, the joint
state, the gripper, the residual, the sensors) as one ``telerig.v1.Bundle`` on
``telerig/v1/<rig>/<robot>/tick`` instead of one message per stream: an MQTT message costs its
publisher, the broker and every reader per message, and six robots at 100 Hz with six streams each
were more messages than one station's recorder could read on 2 cores (benchmarks/fleet.py).

A reader wants streams, not bundles: :func:`unbundle` turns a tick message into the messages its
parts would have been on their own (topic ``telerig/v1/<rig>/<robot>/<stream>``, the part's
Envelope, the tick's receive time), and :func:`picking` makes a handler of tick messages that
passes on the parts of the streams it names. The recorder files each part under its stream's
topic, so an episode log has the same channels and bytes as before bundles.
"""

from __future__ import annotations

from collections.abc import Collection

from telerig.bus.base import Message, MessageHandler
from telerig.bus.catalogue import CATALOGUE, TICK
from telerig.errors import WireError
from telerig.ir import wire

__all__ = ["TICK", "picking", "unbundle"]

_SUFFIX = "/" + TICK
#: Largest tick accepted [bytes] (the catalogue's): a reader parses nothing bigger.
_MAX_BYTES = next(spec.max_bytes for spec in CATALOGUE if spec.name == TICK)


def unbundle(message: Message) -> list[Message]:
    """The messages a tick message's parts would have been on their own, in order.

    Raises:
        WireError: the payload is larger than the catalogue allows a tick, or not a Bundle (see
            :func:`telerig.ir.wire.decode_bundle`).
        ValueError: the topic is not a tick topic.
    """
    prefix, _, stream = message.topic.rpartition("/")
    if stream != TICK or not prefix:
        raise ValueError(f"not a tick topic: {message.topic[:200]!r}")
    if len(message.payload) > _MAX_BYTES:
        raise WireError(f"a tick of {len(message.payload)} bytes, limit {_MAX_BYTES}")
    received = message.received_ns
    return [
        Message(f"{prefix}/{name}", envelope, received)
        for name, envelope in wire.decode_bundle(message.payload)
    ]


def picking(streams: Collection[str], handler: MessageHandler) -> MessageHandler:
    """A handler of tick messages that calls ``handler`` with the parts of ``streams``, each as the
    message its stream would have carried on its own. A malformed bundle raises
    :class:`~telerig.errors.WireError` to the caller's bus guard; the rest of the tick is skipped."""
    wanted = frozenset(streams)

    def pick(message: Message) -> None:
        if not message.topic.endswith(_SUFFIX):
            return
        for part in unbundle(message):
            if part.topic.rpartition("/")[2] in wanted:
                handler(part)

    return pick
