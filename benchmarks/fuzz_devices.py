"""Long mutation fuzz of every device parser: only WireError may escape, no bad value may reach the IR.

For every family's ``protocol.FUZZ_TARGET`` (the glove's ``kinematics.FUZZ_TARGET``, and
``mocap.bvh.BVH_FUZZ_TARGET``) this feeds ``--n`` inputs (default 10^5) mutated from the family's
``fake.typical_payload()`` (plus a few other messages its fake speaks) with a fixed seed: bit flips,
byte and integer overwrites, byte insertion and deletion, truncation, splicing, random bytes, and
float perturbations (NaN, inf, huge, subnormal and just-out-of-range values) at the float fields of
binary payloads or at the number tokens of text payloads. Inputs a parser accepts join a small pool
that later inputs are mutated from too, and formats with a checksum or length field get it re-sealed
on half the inputs so mutations reach past it.

A finding is an exception other than :class:`telerig.errors.WireError`, or an IR sample in the
result with a NaN/inf value or a value the validator's range check rejects (positions beyond the
family's own documented limit, non-unit quaternions, analog values or confidences outside their
range, twists faster than the family's full scale). Each finding is shrunk to a small reproducer.

Prints a table, writes ``benchmarks/results/fuzz_devices.json`` and exits 1 on any finding.

Usage: python benchmarks/fuzz_devices.py [--n 100000] [--seed 0] [--targets udp_vr,glove] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import platform
import random
import re
import struct
import sys
import time
import traceback
import warnings
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from telerig.devices.validate import RangeCheck, Track
from telerig.errors import WireError
from telerig.ir.types import BaseVelocity, BodySkeleton, ControllerState, HandPose, Pose, Twist

RESULTS = Path(__file__).parent / "results" / "fuzz_devices.json"
SQRT3 = math.sqrt(3.0)
_IR_TYPES = (Pose, ControllerState, HandPose, BodySkeleton, Twist, BaseVelocity)
#: Findings kept (with a reproducer) per target and signature; the rest are only counted.
_MAX_FINDINGS = 20


# ---------------------------------------------------------------------------------------------
# Targets


@dataclass(frozen=True)
class Target:
    """One parser under fuzz.

    Attributes:
        name: Family (and parser) name.
        fn: The fuzz target: bytes in, parsed object out; may raise only ``WireError``.
        seeds: Valid inputs to mutate from; the first is the family's ``typical_payload()``.
        kind: ``"binary"`` (float fields found by scanning) or ``"text"`` (number tokens).
        radius_m: Largest distance of an IR position from its frame origin the family documents [m].
        max_linear_m_s: Largest linear speed of an IR twist the family can produce [m/s].
        max_angular_rad_s: Largest angular speed of an IR twist the family can produce [rad/s].
        reseal: Re-seals checksum and length fields of a mutated input, or None.
        words: Format keywords inserted by the text mutator.
    """

    name: str
    fn: Callable[[bytes], object]
    seeds: tuple[bytes, ...]
    kind: Literal["binary", "text"]
    radius_m: float = 5.0
    max_linear_m_s: float = 10.0
    max_angular_rad_s: float = 20.0
    reseal: Callable[[bytes], bytes] | None = None
    words: tuple[bytes, ...] = ()


def _glove_reseal(data: bytes) -> bytes:
    from telerig.devices.glove.protocol import HEADER

    if len(data) < HEADER.size + 4:
        return data
    out = bytearray(data)
    struct.pack_into("<H", out, 6, len(out) & 0xFFFF)  # length field after magic, version, flags
    struct.pack_into("<I", out, len(out) - 4, zlib.crc32(out[:-4]))
    return bytes(out)


def _natnet_reseal(data: bytes) -> bytes:
    if len(data) < 4:
        return data
    return data[:2] + struct.pack("<H", min(len(data) - 4, 0xFFFF)) + data[4:]


def targets() -> list[Target]:
    """Every fuzz target of the built-in device families, with their seeds and limits."""
    from telerig.devices.gamepad import fake as gamepad_fake
    from telerig.devices.gamepad import protocol as gamepad
    from telerig.devices.glove import fake as glove_fake
    from telerig.devices.glove import kinematics as glove_kinematics
    from telerig.devices.glove import protocol as glove
    from telerig.devices.keyboard import fake as keyboard_fake
    from telerig.devices.keyboard import protocol as keyboard
    from telerig.devices.leap import fake as leap_fake
    from telerig.devices.leap import protocol as leap
    from telerig.devices.markerless import fake as markerless_fake
    from telerig.devices.markerless import protocol as markerless
    from telerig.devices.markerless import tracker
    from telerig.devices.mocap import bvh
    from telerig.devices.mocap import fake as mocap_fake
    from telerig.devices.mocap import protocol as natnet
    from telerig.devices.spacemouse import fake as spacemouse_fake
    from telerig.devices.spacemouse import protocol as spacemouse
    from telerig.devices.udp_vr import fake as udp_vr_fake
    from telerig.devices.udp_vr import protocol as udp_vr
    from telerig.devices.webxr import fake as webxr_fake
    from telerig.devices.webxr import protocol as webxr

    bridge = glove_fake.FakeGloveBridge(wrist=True)
    glove_wrist = glove.encode_frame(bridge.frame_at(2.1, seq=7, device_ns=5_000))
    glove_bare = glove.encode_frame(glove_fake.FakeGloveBridge(fingertips=False).frame_at(0.4, seq=8))
    server = mocap_fake.FakeNatNetServer()
    v31, v41 = natnet.NatNetVersion(3, 1), natnet.NatNetVersion(4, 1)
    with markerless_fake.FakeTracker(("127.0.0.1", 9)) as fake:
        capture = 1_700_000_000_000_000_000
        pose = fake.pose_bytes(1, capture_ns=capture)
        summary = tracker.encode_frame(fake.header(tracker.KIND_FRAME, 1, capture), 1, 1, 12.5)
    # Twists of the normalizers' default full scale: each component up to the max.
    sm = spacemouse.SpaceMouseNormalizer("x")
    gp = gamepad.GamepadNormalizer("x")
    kb = keyboard.KeyboardNormalizer("x")
    return [
        Target(
            "udp_vr",
            udp_vr.FUZZ_TARGET,
            (udp_vr_fake.typical_payload(),),
            "binary",
            radius_m=SQRT3 * udp_vr.MAX_POSITION_M,
        ),
        Target(
            "webxr",
            webxr.FUZZ_TARGET,
            (webxr_fake.typical_payload(), webxr_fake.encode_pong(3, 1.7e12 + 0.25)),
            "binary",
            radius_m=SQRT3 * webxr.MAX_POSITION_M,
        ),
        Target(
            "glove",
            glove_kinematics.FUZZ_TARGET,
            (glove_fake.typical_payload(), glove_wrist, glove_bare),
            "binary",
            # Hand frame: model keypoints are within a hand's reach, measured tips within MAX_TIP_MM.
            radius_m=SQRT3 * glove.MAX_TIP_MM / 1000.0,
            reseal=_glove_reseal,
        ),
        Target(
            "leap",
            leap.FUZZ_TARGET,
            (leap_fake.typical_payload(), b'{"serviceVersion": "2.3.1+33747", "version": 6}'),
            "text",
            # Leap coordinates within MAX_COORD_MM, rotated and shifted by the desk mount.
            radius_m=SQRT3 * leap.MAX_COORD_MM / 1000.0 + float(np.linalg.norm(leap.DESK_MOUNT.position_m)),
            words=(b"null", b"[]", b"{}", b'"', b"true", b'"left"', b'"right"', b'"hands"', b'"pointables"'),
        ),
        Target(
            "natnet",
            natnet.FUZZ_TARGET,
            (
                mocap_fake.typical_payload(),
                natnet.encode_frame(server.frame_at(7), v31),
                natnet.encode_model_definitions(server.models, v41),
                natnet.encode_server_info(server.server_info()),
            ),
            "binary",
            radius_m=SQRT3 * 100.0,  # FrameNormalizer's default max_range_m per coordinate
            reseal=_natnet_reseal,
        ),
        Target(
            "markerless",
            markerless.FUZZ_TARGET,
            (markerless_fake.typical_payload(), pose, summary),
            "binary",
            radius_m=SQRT3 * markerless.POSE_LIMIT_M,
        ),
        Target(
            "spacemouse",
            spacemouse.FUZZ_TARGET,
            (spacemouse_fake.typical_payload(), spacemouse_fake.button_report(0b11)),
            "binary",
            max_linear_m_s=SQRT3 * sm.max_linear,
            max_angular_rad_s=SQRT3 * sm.max_angular,
        ),
        Target(
            "gamepad",
            gamepad.FUZZ_TARGET,
            (
                gamepad_fake.typical_payload(),
                gamepad_fake.report(1_700_000_000_000_000_000, buttons={"a": 1, "lb": 1}),
            ),
            "binary",
            max_linear_m_s=SQRT3 * gp.max_linear,
            max_angular_rad_s=SQRT3 * gp.max_angular,
        ),
        Target(
            "keyboard",
            keyboard.FUZZ_TARGET,
            (keyboard_fake.typical_payload(), b"wwwa d\x1b[5~3\x1b[6~qe r\x1b[D\x1b[1;5A"),
            "text",
            max_linear_m_s=SQRT3 * kb.max_linear,
            max_angular_rad_s=SQRT3 * kb.max_angular,
            words=(b"\x1b", b"\x1b[", b"\x1bO", b"~", b";", b"\x1b[1;2C", b"\x1b[200~", b"\x1b[M"),
        ),
        Target(
            "bvh",
            bvh.BVH_FUZZ_TARGET,
            (mocap_fake.reaching_bvh(60.0, 4 / 60).encode(),),
            "text",
            radius_m=SQRT3 * bvh.MAX_RANGE_M,
            words=(
                b"{",
                b"}",
                b"JOINT j",
                b"End Site",
                b"OFFSET 0 0 0",
                b"CHANNELS 3 Xrotation Yrotation Zrotation",
                b"CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
                b"MOTION",
                b"Frames: 1000000",
                b"Frame Time:",
            ),
        ),
    ]


# ---------------------------------------------------------------------------------------------
# Mutation

_F32_SPECIALS = (
    math.nan,
    math.inf,
    -math.inf,
    3.4028235e38,
    -3.4028235e38,
    1e30,
    -1e30,
    1e-45,
    -0.0,
    0.0,
    1.0,
    -1.0,
    1.0000001,
    1.01,
    -1.01,
    50.001,
    2000.1,
    400.1,
    3.0001,
)
_F64_SPECIALS = (
    math.nan,
    math.inf,
    -math.inf,
    1.7976931348623157e308,
    -1e300,
    5e-324,
    -0.0,
    0.0,
    1e13,
    9.9e11,
)
_RAW_NANS = (b"\x01\x00\x80\x7f", b"\x00\x00\xc0\xff", b"\xff\xff\xff\x7f")  # signalling, negative, payload
_INTS = (0, 1, -1, 2, 127, 128, 255, 256, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 10**6)
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_TEXT_NUMBERS = (
    b"NaN",
    b"nan",
    b"Infinity",
    b"-Infinity",
    b"inf",
    b"-inf",
    b"1e400",
    b"-1e400",
    b"1e308",
    b"1e-400",
    b"3.5e38",
    b"123456789012345678901234567890",
    b"9223372036854775808",
    b"-9223372036854775809",
    b"2147483648",
    b"-0",
    b"0",
    b"1",
    b"-1",
    b"0.5",
    b"1.0000001",
    b"2000.0001",
    b"1e7",
    b"1e-7",
    b"0x10",
    b"1_000",
    b"",
)


def _float_offsets(seed: bytes) -> tuple[list[int], list[int]]:
    """Offsets of plausible little-endian float32 and float64 values in ``seed`` (a heuristic)."""
    f32, f64 = [], []
    for off in range(len(seed) - 3):
        (v,) = struct.unpack_from("<f", seed, off)
        if math.isfinite(v) and 1e-4 <= abs(v) <= 1e5:
            f32.append(off)
        if off + 8 <= len(seed):
            (d,) = struct.unpack_from("<d", seed, off)
            if math.isfinite(d) and 1e-3 <= abs(d) <= 1e15:
                f64.append(off)
    return f32, f64


class Mutator:
    """Deterministic mutations of a target's seeds (and of accepted inputs, kept in a small pool)."""

    def __init__(self, target: Target, rng: random.Random, pool_size: int = 256) -> None:
        self.target = target
        self.rng = rng
        self.seeds = list(target.seeds)
        self.pool: list[bytes] = []
        self.pool_size = pool_size
        self.offsets = [_float_offsets(s) for s in self.seeds] if target.kind == "binary" else []
        self.numbers = [[m.span() for m in _NUMBER.finditer(s)] for s in self.seeds]
        self.float_sites = sum(len(a) + len(b) for a, b in self.offsets) + sum(map(len, self.numbers))

    def keep(self, data: bytes) -> None:
        """Remember an accepted input for later mutation."""
        if len(self.pool) < self.pool_size:
            self.pool.append(data)
        else:
            self.pool[self.rng.randrange(self.pool_size)] = data

    def __call__(self) -> bytes:
        rng = self.rng
        if rng.random() < 0.02:
            return rng.randbytes(rng.randrange(0, 2 * len(self.seeds[0]) + 2))
        k = rng.randrange(len(self.seeds))
        rounds = 1 + min(int(rng.expovariate(1.0)), 5)
        if self.pool and rng.random() < 0.3:
            data = bytearray(rng.choice(self.pool))
        else:
            data = bytearray(self.seeds[k])
            if self.float_sites and rng.random() < 0.4:
                data = self._float(data, k)
                if rng.random() < 0.5:
                    rounds = 0  # a bad number in an otherwise valid message gets past the framing
        for _ in range(rounds):
            data = self._once(data)
        if self.target.reseal is not None and rng.random() < 0.5:
            return self.target.reseal(bytes(data))
        return bytes(data)

    def _float(self, data: bytearray, k: int) -> bytearray:
        rng = self.rng
        if self.target.kind == "text":
            spans = self.numbers[k]
            if not spans:
                return data
            for _ in range(1 + int(rng.expovariate(1.5))):
                a, b = rng.choice(spans)
                token = rng.choice(_TEXT_NUMBERS)
                data[a:b] = token
                if len(token) != b - a:
                    break  # the spans after this one moved
            return data
        f32, f64 = self.offsets[k]
        for _ in range(1 + int(rng.expovariate(1.5))):
            if f64 and (not f32 or rng.random() < 0.15):
                off = rng.choice(f64)
                (old,) = struct.unpack_from("<d", data, off)
                value = rng.choice((*_F64_SPECIALS, old * 1e6, -old, old + rng.gauss(0.0, 1.0)))
                struct.pack_into("<d", data, off, value)
            elif f32:
                off = rng.choice(f32)
                if rng.random() < 0.1:
                    data[off : off + 4] = rng.choice(_RAW_NANS)
                    continue
                (old,) = struct.unpack_from("<f", data, off)
                value = rng.choice((*_F32_SPECIALS, old * 1e6, -old, old * 1.02, old + rng.gauss(0.0, 0.01)))
                try:
                    struct.pack_into("<f", data, off, value)
                except OverflowError:
                    struct.pack_into("<f", data, off, math.copysign(math.inf, value))
        return data

    def _once(self, data: bytearray) -> bytearray:
        rng = self.rng
        n = len(data)
        op = rng.randrange(10 if self.target.words else 9)
        if n == 0 or op == 0:  # insert bytes (random, or a copy of a chunk)
            at = rng.randrange(n + 1)
            if n and rng.random() < 0.5:
                a = rng.randrange(n)
                chunk = data[a : a + rng.randrange(1, 33)]
            else:
                chunk = bytearray(rng.randbytes(rng.randrange(1, 33)))
            data[at:at] = chunk
        elif op in (1, 2):  # bit flips
            for _ in range(rng.randrange(1, 5)):
                i = rng.randrange(n)
                data[i] ^= 1 << rng.randrange(8)
        elif op == 3:  # byte overwrite
            i = rng.randrange(n)
            data[i] = rng.choice((0, 1, 0x7F, 0x80, 0xFF, rng.randrange(256)))
        elif op == 4:  # integer overwrite
            size = rng.choice((1, 2, 4, 8))
            if n >= size:
                i = rng.randrange(n - size + 1)
                value = rng.choice(_INTS) & ((1 << (8 * size)) - 1)
                data[i : i + size] = value.to_bytes(size, rng.choice(("little", "big")))
        elif op == 5:  # delete a range
            a = rng.randrange(n)
            del data[a : a + rng.randrange(1, 33)]
        elif op == 6:  # truncate
            del data[rng.randrange(n) :]
        elif op == 7:  # splice with another seed or accepted input
            other = rng.choice(self.seeds + self.pool[:16])
            data = data[: rng.randrange(n + 1)] + other[rng.randrange(len(other) + 1) :]
        elif op == 8:  # duplicate the tail, or repeat the whole input
            data = data + data[rng.randrange(n) :] if rng.random() < 0.7 else data * rng.randrange(2, 5)
        else:  # insert a format keyword
            at = rng.randrange(n + 1)
            data[at:at] = rng.choice(self.target.words)
        return data


# ---------------------------------------------------------------------------------------------
# Checking what a parser returned


def _samples(result: object, depth: int = 0) -> Iterable[object]:
    if isinstance(result, _IR_TYPES):
        yield result
    elif isinstance(result, list | tuple) and depth < 3:
        for item in result:
            yield from _samples(item, depth + 1)


def _non_finite(obj: object, path: str = "") -> str | None:
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        value = getattr(obj, f.name)
        where = f"{path}{f.name}"
        if dataclasses.is_dataclass(value):
            found = _non_finite(value, where + ".")
            if found:
                return found
        elif isinstance(value, np.ndarray) and value.dtype.kind in "fc":
            if not np.all(np.isfinite(value)):
                return where
        elif isinstance(value, float) and not math.isfinite(value):
            return where
    return None


class IrCheck:
    """Why an IR sample a parser returned is bad (non-finite, or rejected as out of range), if it is."""

    def __init__(self, target: Target) -> None:
        self.range = RangeCheck(
            target.radius_m,
            quaternion_tolerance=1e-6,
            max_linear_m_s=target.max_linear_m_s * (1 + 1e-9),
            max_angular_rad_s=target.max_angular_rad_s * (1 + 1e-9),
        )
        self.track = Track(("fuzz", "fuzz"))

    def __call__(self, result: object) -> str | None:
        for sample in _samples(result):
            name = type(sample).__name__
            where = _non_finite(sample)
            if where:
                return f"non-finite {name}.{where}"
            stamp = sample.stamp  # type: ignore[attr-defined]
            # Fuzz targets stamp capture_ns 0; only the values are checked here.
            restamped = dataclasses.replace(sample, stamp=dataclasses.replace(stamp, capture_ns=1))  # type: ignore[type-var]
            if self.range.check(restamped, self.track) is not None:
                return f"out-of-range {name}"
        return None


# ---------------------------------------------------------------------------------------------
# Running


@dataclass
class Finding:
    """One kind of failure and the (shrunk) input that shows it."""

    signature: str
    kind: str
    message: str
    traceback: str
    input_hex: str
    input_len: int
    count: int = 1


@dataclass
class TargetResult:
    """Counters of one target's run."""

    name: str
    inputs: int = 0
    accepted: int = 0
    wire_errors: int = 0
    exceptions: int = 0
    bad_ir: int = 0
    parse_s: float = 0.0
    total_s: float = 0.0
    slowest_us: float = 0.0
    float_sites: int = 0
    findings: dict[str, Finding] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        return {
            "target": self.name,
            "inputs": self.inputs,
            "accepted": self.accepted,
            "accepted_fraction": self.accepted / max(self.inputs, 1),
            "wire_errors": self.wire_errors,
            "other_exceptions": self.exceptions,
            "bad_ir": self.bad_ir,
            "us_per_input": 1e6 * self.parse_s / max(self.inputs, 1),
            "slowest_us": self.slowest_us,
            "wall_s": self.total_s,
            "float_sites": self.float_sites,
            "findings": [dataclasses.asdict(f) for f in self.findings.values()],
        }


def _outcome(fn: Callable[[bytes], object], check: IrCheck, data: bytes) -> tuple[str, str, str]:
    """(status, signature, detail) of one input: status ``ok``, ``wire``, ``exception`` or ``bad_ir``."""
    try:
        result = fn(data)
    except WireError:
        return "wire", "", ""
    except Exception as exc:
        tb = traceback.extract_tb(exc.__traceback__)
        last = tb[-1] if tb else None
        where = f"{Path(last.filename).name}:{last.lineno}" if last else "?"
        return "exception", f"{type(exc).__name__} at {where}", "".join(traceback.format_exception(exc))
    reason = check(result)
    if reason is not None:
        return "bad_ir", reason, reason
    return "ok", "", ""


def shrink(
    fn: Callable[[bytes], object], check: IrCheck, data: bytes, signature: str, budget: int = 3000
) -> bytes:
    """A smaller input with the same failure ``signature`` (greedy removal of ever smaller chunks)."""
    best = data
    tries = 0
    chunk = max(1, len(best) // 2)
    while chunk >= 1 and tries < budget:
        i = 0
        changed = False
        while i < len(best) and tries < budget:
            candidate = best[:i] + best[i + chunk :]
            tries += 1
            if _outcome(fn, check, candidate)[1] == signature:
                best = candidate
                changed = True
            else:
                i += chunk
        if not changed:
            chunk //= 2
    return best


def fuzz(
    target: Target, n: int, seed: int, advance: Callable[[int], None], *, warning_filter: str = "error"
) -> TargetResult:
    """Run ``n`` inputs of ``target``; ``advance(k)`` reports progress.

    ``warning_filter`` applies to warnings a parser emits: ``"error"`` (the default, as in the
    test suite, which runs with warnings as errors) makes them exceptions, hence findings.
    """
    with warnings.catch_warnings():
        warnings.simplefilter(warning_filter)  # type: ignore[arg-type]
        return _fuzz(target, n, seed, advance)


def _fuzz(target: Target, n: int, seed: int, advance: Callable[[int], None]) -> TargetResult:
    rng = random.Random(seed ^ zlib.crc32(target.name.encode()))
    mutate = Mutator(target, rng)
    check = IrCheck(target)
    result = TargetResult(target.name, float_sites=mutate.float_sites)
    fn = target.fn
    clock = time.perf_counter
    start = clock()
    step = max(1, n // 200)
    for i in range(n):
        data = mutate()
        t0 = clock()
        try:
            out = fn(data)
        except WireError:
            status, signature, detail = "wire", "", ""
        except Exception:
            status, signature, detail = _outcome(fn, check, data)
            if status == "ok":  # flaky: the same input passed on the second try
                status, signature, detail = "exception", "non-deterministic exception", ""
        else:
            reason = check(out)
            status, signature, detail = ("ok", "", "") if reason is None else ("bad_ir", reason, reason)
        dt = clock() - t0
        result.parse_s += dt
        result.slowest_us = max(result.slowest_us, dt * 1e6)
        result.inputs += 1
        if status == "ok":
            result.accepted += 1
            mutate.keep(data)
        elif status == "wire":
            result.wire_errors += 1
        else:
            if status == "exception":
                result.exceptions += 1
            else:
                result.bad_ir += 1
            found = result.findings.get(signature)
            if found is not None:
                found.count += 1
            elif len(result.findings) < _MAX_FINDINGS:
                small = shrink(fn, check, data, signature)
                detail = _outcome(fn, check, small)[2] or detail
                result.findings[signature] = Finding(
                    signature,
                    status,
                    detail.splitlines()[-1] if detail else signature,
                    detail,
                    small.hex(),
                    len(small),
                )
        if i % step == step - 1:
            advance(step)
    advance(n % step)
    result.total_s = clock() - start
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """Fuzz every target, print the table, write the JSON; 1 on any finding."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=100_000, help="inputs per target (default 10^5)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--targets", default="", help="comma-separated subset of targets (default all)")
    parser.add_argument(
        "--warnings",
        choices=("error", "ignore"),
        default="error",
        help="warnings a parser emits: 'error' (default, like the test suite) counts them as findings",
    )
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"JSON results (default {RESULTS})")
    args = parser.parse_args(argv)
    console = Console(width=None if sys.stdout.isatty() else 130)
    all_targets = targets()
    names = [t.name for t in all_targets]
    chosen = [s for s in args.targets.split(",") if s] or names
    unknown = sorted(set(chosen) - set(names))
    if unknown:
        console.print(f"[red]unknown target(s) {', '.join(unknown)}; valid: {', '.join(names)}[/red]")
        return 2
    results: list[TargetResult] = []
    columns = (TextColumn("{task.description:<11}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console) as progress:
        for target in (t for t in all_targets if t.name in chosen):
            task = progress.add_task(target.name, total=args.n)
            advance = functools.partial(progress.advance, task)
            results.append(fuzz(target, args.n, args.seed, advance, warning_filter=args.warnings))
    table = Table(title=f"Device parser fuzz: {args.n} inputs per target, seed {args.seed}")
    for col in (
        "target",
        "inputs",
        "non-WireError exceptions",
        "bad IR values",
        "accepted",
        "µs/input",
        "slowest ms",
    ):
        table.add_column(col, justify="left" if col == "target" else "right")
    for r in results:
        row = r.row()
        bad = "red" if r.exceptions or r.bad_ir else "green"
        table.add_row(
            r.name,
            f"{r.inputs:,}",
            f"[{bad}]{r.exceptions}[/{bad}]",
            f"[{bad}]{r.bad_ir}[/{bad}]",
            f"{row['accepted_fraction']:.1%}",
            f"{row['us_per_input']:.1f}",
            f"{r.slowest_us / 1e3:.1f}",
        )
    console.print(table)
    failed = [r for r in results if r.findings]
    for r in failed:
        for f in r.findings.values():
            console.print(f"[red]{r.name}: {f.kind} x{f.count}: {f.signature}[/red]")
            console.print(f"  reproducer ({f.input_len} bytes): {f.input_hex[:400]}", highlight=False)
            if f.traceback and f.kind == "exception":
                console.print(f.traceback.rstrip(), markup=False, highlight=False)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "n": args.n,
        "seed": args.seed,
        "warnings": args.warnings,
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    args.out.write_text(json.dumps({"meta": meta, "targets": [r.row() for r in results]}, indent=2))
    console.print(f"wrote {args.out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
