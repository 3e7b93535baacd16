"""ACT's temporal ensembling of action chunks, and the policy device sending it (issue 16)."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from telerig.devices.policy.device import PolicyDevice
from telerig.devices.policy.ensemble import TemporalEnsemble
from telerig.devices.policy.worker import PolicyInfo
from telerig.errors import DeviceError
from telerig.ir.types import JointCommand, Sample


def _chunk(values: list[float]) -> np.ndarray:
    return np.array(values, dtype=np.float64)[:, None]  # T ticks x 1 action entry


def test_each_tick_is_the_weighted_mean_of_the_chunks_that_cover_it() -> None:
    k = 0.5
    ens = TemporalEnsemble(k)
    ens.add(_chunk([0.0, 1.0, 2.0]))  # tick 0
    assert ens.next() == pytest.approx([0.0])
    ens.add(_chunk([10.0, 11.0, 12.0]))  # tick 1: its first action, the old chunk's second
    w = np.exp(-k * np.arange(2))  # the oldest weighs most
    assert ens.next() == pytest.approx([(w @ [1.0, 10.0]) / w.sum()])
    # Tick 2, no new chunk (a late inference): both chunks still cover it.
    assert ens.next() == pytest.approx([(w @ [2.0, 11.0]) / w.sum()])
    # Tick 3: the first chunk has expired; the second's last action alone.
    assert ens.next() == pytest.approx([12.0])
    assert ens.next() is None  # nothing covers tick 4: the chain sees a missed sample
    ens.add(_chunk([5.0]))
    ens.clear()
    assert ens.next() is None


def test_a_jittering_policy_is_smoothed() -> None:
    # Every chunk predicts "stay at 0" with independent noise: ensembling over 16 overlapping
    # chunks shrinks the tick-to-tick motion, which is what a still-arm check measures.
    rng = np.random.default_rng(0)
    ens = TemporalEnsemble(0.01)
    raw, smooth = [], []
    for _ in range(200):
        chunk = rng.normal(0.0, 0.01, size=(16, 1))
        raw.append(chunk[0, 0])
        ens.add(chunk)
        smooth.append(ens.next()[0])  # type: ignore[index]
    assert np.std(np.diff(smooth[20:])) < 0.35 * np.std(np.diff(raw[20:]))


@pytest.mark.parametrize("k", [0.0, -0.1, math.nan, math.inf])
def test_the_weight_decay_must_be_positive_and_finite(k: float) -> None:
    with pytest.raises(ValueError, match="must be a finite number > 0"):
        TemporalEnsemble(k)


def test_the_device_refuses_an_ensemble_with_chunks_run_open_loop() -> None:
    with pytest.raises(DeviceError, match="temporal_ensemble infers every tick"):
        PolicyDevice("pi", "x.pt", robot="arm0", execute_actions=8, temporal_ensemble=0.01)
    with pytest.raises(DeviceError, match="finite number > 0"):
        PolicyDevice("pi", "x.pt", robot="arm0", temporal_ensemble=-1.0)


def test_the_device_sends_the_ensemble_every_tick() -> None:
    info = PolicyInfo(("a",), ("a",), (), (8, 8), 100.0, 3, "id", "sha", "bc")
    device = PolicyDevice("pi", "x.pt", robot="arm0", temporal_ensemble=1.0)
    chunks = iter([_chunk([0.0, 1.0, 2.0]), _chunk([10.0, 11.0, 12.0]), None, None, None])
    device._ask = lambda *args: next(chunks, None)  # type: ignore[method-assign]
    device._process = object()  # type: ignore[assignment]
    sent: list[float] = []
    done = threading.Event()

    def sink(sample: Sample) -> None:
        assert isinstance(sample, JointCommand)
        sent.append(float(sample.positions[0]))

    thread = threading.Thread(target=lambda: (device._run(sink, info, 100.0), done.set()))
    thread.start()
    time.sleep(0.15)
    device._stop.set()
    thread.join(2.0)
    w = np.exp(-np.arange(2))
    # Ticks 0-3 as in the ensemble test; from tick 4 nothing covers the tick and nothing is sent.
    assert sent == pytest.approx([0.0, (w @ [1.0, 10.0]) / w.sum(), (w @ [2.0, 11.0]) / w.sum(), 12.0])
