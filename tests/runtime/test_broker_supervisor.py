"""The embedded broker's directory (its config, password hashes and ACL) does not outlive a station
killed with ``kill -9``: the next start removes it, and never a running broker's (issue 11 finding 6)."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import pytest

from telerig.bus.broker import MosquittoBroker
from telerig.config.schema import EmbeddedBrokerConfig
from telerig.runtime.broker_supervisor import BROKER_DIR_PREFIX, BrokerSupervisor

pytestmark = [pytest.mark.broker]


def _age(path: Path, seconds: float) -> None:
    t = time.time() - seconds
    os.utime(path, (t, t))


def test_the_next_start_removes_a_killed_brokers_directory_and_keeps_a_running_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    stale = Path(tempfile.mkdtemp(prefix=BROKER_DIR_PREFIX))
    (stale / "passwd").write_text("station:$7$...")
    _age(stale, 120.0)
    young = Path(tempfile.mkdtemp(prefix=BROKER_DIR_PREFIX))  # a broker may be starting
    with MosquittoBroker() as running:
        (running_dir,) = (d for d in tmp_path.glob(f"{BROKER_DIR_PREFIX}*") if d not in (stale, young))
        _age(running_dir, 120.0)
        supervisor = BrokerSupervisor("demo", EmbeddedBrokerConfig())
        try:
            supervisor.start()
            assert running.running
            assert running_dir.is_dir()
        finally:
            supervisor.close()
    assert not stale.exists()
    assert young.is_dir()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root or CAP_SYS_NICE (CI runs as root)")
def test_the_embedded_broker_runs_at_the_robot_processes_real_time_priority() -> None:
    # Robot processes under SCHED_RR starved a broker at normal priority on a full machine: the
    # samples they consume pass through it (fleet rig, 2 cores: 15 of 400 commands applied in 4 s).
    supervisor = BrokerSupervisor("demo", EmbeddedBrokerConfig(), realtime_priority=7)
    try:
        supervisor.start()
        broker = supervisor.embedded
        assert broker is not None
        assert broker.pid is not None
        assert os.sched_getscheduler(broker.pid) == os.SCHED_RR
        assert os.sched_getparam(broker.pid).sched_priority == 7
    finally:
        supervisor.close()
