"""Native VR stream over UDP: headset companion apps sending VrFrame protobuf datagrams."""

from telerig.devices.udp_vr.device import DEFAULT_PORT, UdpVrDevice
from telerig.devices.udp_vr.fake import FakeVrSender, typical_payload
from telerig.devices.udp_vr.protocol import (
    MAX_DATAGRAM_BYTES,
    OPENXR_TO_MEDIAPIPE,
    SequenceFilter,
    datagram_samples,
    decode_datagram,
)

__all__ = [
    "DEFAULT_PORT",
    "MAX_DATAGRAM_BYTES",
    "OPENXR_TO_MEDIAPIPE",
    "FakeVrSender",
    "SequenceFilter",
    "UdpVrDevice",
    "datagram_samples",
    "decode_datagram",
    "typical_payload",
]
