"""The WebXR page's ``receive`` latency stage (issue 17): ``telerig serve`` stamps each relayed frame
with the time it received it, and the device gives its samples that arrival time, so the stage from
the headset's capture to telerig ends at the server, not at the device node; a stamp from a server
whose clock is far off, or a short one, is not used."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from tests.server.test_xr import Lab, _frame, wait_for

from telerig.bus.acl import WEB
from telerig.devices.webxr.protocol import WebXRWireError
from telerig.devices.webxr.relay import (
    OPEN,
    STAMPED,
    decode_event,
    encode_event,
    open_body,
    parse_stamped,
    stamped_body,
)
from telerig.ir import wire

pytestmark = pytest.mark.broker


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    lab = Lab(tmp_path)
    try:
        yield lab
    finally:
        lab.close()


def test_the_stamped_envelope_round_trips_and_a_short_stamp_is_refused() -> None:
    envelope = encode_event(STAMPED, 7, stamped_body(123_456_789, b"frame"))
    event = decode_event(envelope)
    assert (event.event, event.conn) == (STAMPED, 7)
    assert parse_stamped(event.body) == (123_456_789, b"frame")
    with pytest.raises(WebXRWireError, match="8 bytes of stamp"):
        parse_stamped(b"\x01\x02")


def test_relayed_samples_arrive_when_the_server_received_the_frame(lab: Lab) -> None:
    csrf = lab.login("otto")
    with lab.page(csrf) as ws:
        before = time.time_ns()
        ws.send_bytes(_frame(0, trigger=0.25))
        assert wait_for(lambda: lab.samples), "the relayed frame never became a sample on the rig's bus"
        after = time.time_ns()
    sample = wire.decode(lab.samples[0].payload)
    # Stamped by the server on receipt: after the page sent it, before the device node published it.
    assert before <= sample.stamp.arrival_ns <= lab.samples[0].received_ns <= after


def test_a_stamp_from_a_far_off_clock_is_not_used(lab: Lab) -> None:
    # What a server whose clock is an hour off relays (as the web principal, on the device's page_in).
    web = lab.bus(WEB)
    topic = "telerig/v1/webxr/browser/page_in"
    web.publish(topic, encode_event(OPEN, 42, open_body("otto", "test")), qos=1)
    late = time.time_ns() - 3_600 * 10**9
    web.publish(topic, encode_event(STAMPED, 42, stamped_body(late, _frame(0))), qos=1)
    assert wait_for(lambda: lab.samples)
    arrival = wire.decode(lab.samples[0].payload).stamp.arrival_ns
    assert abs(arrival - time.time_ns()) < 10 * 10**9  # the device node's own stamp, not the hour-old one
