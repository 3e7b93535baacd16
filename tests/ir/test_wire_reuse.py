"""wire.encode reuses one Envelope per IR type and thread (issue 18: no protobuf message built per
control tick): the bytes are exactly a fresh message's, whatever came before, and memory stays flat."""

from __future__ import annotations

import threading

import numpy as np
import psutil
import pytest

from telerig.errors import WireError
from telerig.ir import wire
from telerig.ir._pb import ir_pb2
from telerig.ir.types import (
    CameraFrame,
    ControllerState,
    JointCommand,
    JointState,
    Pose,
    Sample,
    Stamp,
)

from .test_wire import SAMPLES, assert_same_sample


def _fresh(sample: Sample) -> bytes:
    """What a message built for this sample alone serializes to (a thread with no reused slots)."""
    out: list[bytes] = []
    thread = threading.Thread(target=lambda: out.append(wire.encode(sample)))
    thread.start()
    thread.join()
    return out[0]


def test_every_sample_after_every_other_encodes_as_a_fresh_message() -> None:
    """Each sample encoded right after each other one of its type (longer and shorter arrays, no
    buttons after buttons, no efforts after efforts, new names and frame ids) gives a fresh
    message's bytes: nothing of the previous sample is left in the reused message."""
    fresh = {name: _fresh(sample) for name, sample in SAMPLES.items()}
    for first_name, first in SAMPLES.items():
        for name, sample in SAMPLES.items():
            if type(sample) is not type(first):
                continue
            wire.encode(first)
            data = wire.encode(sample)
            assert data == fresh[name], f"{name} after {first_name}"
            assert_same_sample(wire.decode(data), sample)


def test_a_changed_names_list_is_written_again() -> None:
    names = ["a", "b"]
    st = Stamp("arm0", 1, 0, 1)
    wire.encode(JointCommand(st, tuple(names), (1.0, 2.0)))
    names[1] = "c"  # the same values in a new sample built from a changed list
    decoded = wire.decode(wire.encode(JointCommand(st, tuple(names), (1.0, 2.0))))
    assert isinstance(decoded, JointCommand)
    assert decoded.names == ("a", "c")


def test_a_refused_value_leaves_nothing_behind() -> None:
    st = Stamp("cam", 1, 0, 1)
    wire.encode(CameraFrame(st, "wrist", 5, 640, 480))
    with pytest.raises(WireError, match="CameraFrame"):
        wire.encode(CameraFrame(st, "scene", -1, 320, 240))  # half written when the index is refused
    decoded = wire.decode(wire.encode(CameraFrame(Stamp("cam", 2, 0, 2), "top", 7, 0, 0)))
    assert decoded == CameraFrame(Stamp("cam", 2, 0, 2), "top", 7, 0, 0)


def test_threads_encode_at_once_without_mixing_their_samples() -> None:
    errors: list[str] = []

    def run(k: int) -> None:
        names = tuple(f"t{k}_j{i}" for i in range(k + 1))
        for seq in range(2000):
            sample = JointState(
                Stamp(f"t{k}", seq, 0, seq), names, np.full(k + 1, float(seq)), np.zeros(k + 1)
            )
            decoded = wire.decode(wire.encode(sample))
            assert isinstance(decoded, JointState)
            if decoded.names != names or decoded.stamp.seq != seq or decoded.positions[0] != seq:
                errors.append(f"thread {k} seq {seq}: {decoded}")
                return

    threads = [threading.Thread(target=run, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors[:3]


def _rss_growth_mib(encode_one: object, n: int) -> float:
    proc = psutil.Process()
    for i in range(2000):  # warm: the slot, numpy's and Python's free lists
        encode_one(i)  # type: ignore[operator]
    before = proc.memory_info().rss
    for i in range(n):
        encode_one(i)  # type: ignore[operator]
    return (proc.memory_info().rss - before) / 2**20


def test_reused_messages_do_not_grow_memory() -> None:
    """A reused upb message keeps what is written into it until it is freed: clearing it would
    leak ~580 bytes per encode (+17 MiB over these 30 000), and texts that change every time are
    bounded by replacing the message."""
    names = tuple(f"joint_{i}" for i in range(6))
    q = np.arange(6.0)

    def state(i: int) -> None:
        wire.encode(JointState(Stamp("arm0", i, i, i), names, q, q, q))

    def renamed(i: int) -> None:  # a new frame id and button every time: text written each encode
        wire.encode(
            ControllerState(
                Stamp("vr0", i, i, i), "right", (0, 0, 0), (1, 0, 0, 0), f"frame-{i}", frozenset({f"b{i}"})
            )
        )

    assert _rss_growth_mib(state, 30_000) < 2.0
    assert _rss_growth_mib(renamed, 30_000) < 4.0


def test_clearing_a_reused_message_would_grow_memory() -> None:
    """The trap the comment in wire.py names, measured here so the bound above can fail."""
    env = ir_pb2.Envelope()
    values = [0.5] * 6

    def cleared(i: int) -> None:
        env.Clear()
        env.stamp.seq = i
        env.joint_state.positions.extend(values)
        env.joint_state.velocities.extend(values)
        env.joint_state.efforts.extend(values)
        env.SerializeToString()

    assert _rss_growth_mib(cleared, 30_000) > 4.0


def test_encode_without_reuse_gives_the_same_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    reused = {name: wire.encode(sample) for name, sample in SAMPLES.items()}
    monkeypatch.setattr(wire, "_reuse", False)
    assert {name: wire.encode(sample) for name, sample in SAMPLES.items()} == reused
    assert isinstance(wire.decode(reused["pose"]), Pose)
