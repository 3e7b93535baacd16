"""Wire format of a camera's low-resolution observation frames (the ``observation`` stream).

A policy needs the pixels the camera sees now, small and often: 96x96 RGB at 10-30 Hz is
27 kB per frame, well under the broker's message limit, so frames go raw (no JPEG: a lossy
second encoding would differ from the MP4 the policy was trained on, and decoding costs more
than the copy). One message is a fixed 24-byte little-endian header then the pixels:

==========  =======  ================================================
bytes       type     field
==========  =======  ================================================
0-3         4s       magic ``b"TOB1"`` (format version 1)
4-11        int64    capture time, common clock [ns]
12-15       uint32   sequence number of the frame at the camera
16-17       uint16   height [px]
18-19       uint16   width [px]
20-23       uint32   pixel byte count (= height * width * 3)
24-         uint8    RGB pixels, row-major, shape (height, width, 3)
==========  =======  ================================================
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from telerig.errors import WireError

__all__ = ["MAX_SIDE", "ObservationFrame", "decode_observation", "encode_observation"]

_MAGIC = b"TOB1"
_HEADER = struct.Struct("<4sqIHHI")
#: Largest side of an observation frame [px]: a policy's input, never a full camera image.
MAX_SIDE = 512


@dataclass(frozen=True, slots=True)
class ObservationFrame:
    """One observation frame.

    Attributes:
        capture_ns: When the camera captured it, common clock [ns].
        seq: The camera's frame sequence number.
        image: RGB pixels, uint8 of shape (H, W, 3), read-only.
    """

    capture_ns: int
    seq: int
    image: npt.NDArray[np.uint8]


def encode_observation(image: npt.NDArray[np.uint8], capture_ns: int, seq: int) -> bytes:
    """Header and pixels of an RGB uint8 image of shape (H, W, 3) with 1 <= H, W <= :data:`MAX_SIDE`.

    Raises:
        ValueError: the image is not uint8 RGB or too large.
    """
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"observation must be uint8 of shape (H, W, 3), got {image.dtype} {image.shape}")
    height, width = int(image.shape[0]), int(image.shape[1])
    if not (1 <= height <= MAX_SIDE and 1 <= width <= MAX_SIDE):
        raise ValueError(f"observation size {width}x{height} is outside 1..{MAX_SIDE} px")
    pixels = np.ascontiguousarray(image).tobytes()
    return _HEADER.pack(_MAGIC, capture_ns, seq & 0xFFFFFFFF, height, width, len(pixels)) + pixels


def decode_observation(payload: bytes) -> ObservationFrame:
    """The frame in ``payload``.

    Raises:
        WireError: a short, oversized or inconsistent message (one line saying what is wrong).
    """
    if len(payload) < _HEADER.size:
        raise WireError(f"observation message of {len(payload)} bytes is shorter than its header")
    magic, capture_ns, seq, height, width, count = _HEADER.unpack_from(payload)
    if magic != _MAGIC:
        raise WireError(f"observation message starts with {magic!r}, not {_MAGIC!r}")
    if not (1 <= height <= MAX_SIDE and 1 <= width <= MAX_SIDE):
        raise WireError(f"observation size {width}x{height} is outside 1..{MAX_SIDE} px")
    if count != height * width * 3 or len(payload) - _HEADER.size != count:
        raise WireError(
            f"observation of {width}x{height} px needs {height * width * 3} pixel bytes; the header says "
            f"{count} and the message has {len(payload) - _HEADER.size}"
        )
    if capture_ns <= 0:
        raise WireError(f"observation capture time {capture_ns} ns is not positive")
    image = np.frombuffer(payload, dtype=np.uint8, offset=_HEADER.size).reshape(height, width, 3)
    return ObservationFrame(int(capture_ns), int(seq), image)
