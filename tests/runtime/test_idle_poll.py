"""Idle CPUs poll while a rig runs: the PM QoS request where a cpuidle driver runs, else one
SCHED_IDLE poller per CPU that never outranks anything and never outlives the station."""

from __future__ import annotations

import contextlib
import os
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import telerig.config
from telerig.config import load_rig
from telerig.errors import ConfigError
from telerig.runtime.idle_poll import IdlePoll
from telerig.runtime.rig import RigRuntime


def _driver(tmp_path: Path, name: str) -> Path:
    path = tmp_path / "current_driver"
    path.write_text(name + "\n")
    return path


def _gone(pid: int) -> bool:
    """The process ended (a zombie nobody reaped yet counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def _eventually(check: Callable[[], bool], what: str, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_without_a_cpuidle_driver_one_poller_per_cpu_spins_pinned_under_sched_idle(tmp_path: Path) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    poll = IdlePoll(cpuidle_driver=_driver(tmp_path, "none"), pm_qos=tmp_path / "latency")
    policies: list[int] = []

    def start_from_a_realtime_thread() -> None:  # the station's threads run under SCHED_RR
        with contextlib.suppress(PermissionError):
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
        poll.start()
        policies.extend(os.sched_getscheduler(pid) for pid in poll.pollers)

    starter = threading.Thread(target=start_from_a_realtime_thread)
    starter.start()
    starter.join()
    try:
        assert poll.how == f"{len(cpus)} SCHED_IDLE pollers (no cpuidle driver)"
        assert len(poll.pollers) == len(cpus)
        # Never above anything, not even while the interpreter starts: batch nice 19, then idle.
        assert set(policies) <= {os.SCHED_BATCH, os.SCHED_IDLE}
        for pid, cpu in zip(poll.pollers, cpus, strict=True):
            _eventually(
                lambda pid=pid, cpu=cpu: (
                    os.sched_getscheduler(pid) == os.SCHED_IDLE and os.sched_getaffinity(pid) == {cpu}
                ),
                f"poller {pid} under SCHED_IDLE on CPU {cpu}",
            )
        pids = poll.pollers
        assert not (tmp_path / "latency").exists()  # no request without a driver to honour it
    finally:
        poll.close()
    assert poll.how == "off"
    assert poll.pollers == ()
    assert all(_gone(pid) for pid in pids)
    poll.close()  # idempotent


def test_a_poller_that_exited_is_no_longer_reported(tmp_path: Path) -> None:
    """One poller gone (killed here; one refused ``SCHED_IDLE`` exits at once): ``pollers`` lists
    only those running and ``how`` says how many of the ones started still run."""
    poll = IdlePoll(cpuidle_driver=_driver(tmp_path, "none"), pm_qos=tmp_path / "latency").start()
    try:
        started = poll.pollers
        assert started
        os.kill(started[0], signal.SIGKILL)
        _eventually(lambda: poll.pollers == started[1:], "the killed poller dropped from pollers")
        assert poll.how == f"{len(started) - 1} of {len(started)} SCHED_IDLE pollers (no cpuidle driver)"
    finally:
        poll.close()
    assert (poll.how, poll.pollers) == ("off", ())


def test_the_pollers_die_with_the_process_that_started_them(tmp_path: Path) -> None:
    script = textwrap.dedent(
        f"""
        import sys, time
        from pathlib import Path
        from telerig.runtime.idle_poll import IdlePoll
        poll = IdlePoll(cpuidle_driver=Path({str(_driver(tmp_path, "none"))!r})).start()
        print(*poll.pollers, flush=True)
        time.sleep(60)
        """
    )
    with subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True) as station:
        try:
            assert station.stdout is not None
            pids = [int(p) for p in station.stdout.readline().split()]
            assert pids
            assert not any(_gone(pid) for pid in pids)
            os.kill(station.pid, signal.SIGKILL)  # no close(), no atexit
            station.wait(timeout=10)
            _eventually(lambda: all(_gone(pid) for pid in pids), "pollers outlived their station")
        finally:
            station.kill()


def test_with_a_cpuidle_driver_the_pm_qos_request_is_held_until_close(tmp_path: Path) -> None:
    request = tmp_path / "cpu_dma_latency"  # stands in for the device: the bytes written to it
    request.write_bytes(b"")
    poll = IdlePoll(cpuidle_driver=_driver(tmp_path, "intel_idle"), pm_qos=request).start()
    assert poll.how == "PM QoS cpu_dma_latency 0 us (intel_idle)"
    assert poll.pollers == ()
    assert request.read_bytes() == struct.pack("=i", 0)
    poll.close()
    assert poll.how == "off"


def test_a_refused_pm_qos_request_falls_back_to_pollers(tmp_path: Path) -> None:
    poll = IdlePoll(cpuidle_driver=_driver(tmp_path, "acpi_idle"), pm_qos=tmp_path / "no" / "device")
    with poll:
        assert poll.how.endswith("SCHED_IDLE pollers (PM QoS refused: No such file or directory)")
        assert len(poll.pollers) == len(os.sched_getaffinity(0))


def test_a_setting_that_is_not_a_boolean_gets_one_line_naming_it(tmp_path: Path) -> None:
    rig = tmp_path / "rig.yaml"
    text = (Path(telerig.config.__file__).parent / "rigs" / "demo.yaml").read_text()
    rig.write_text(text.replace("runtime:\n", "runtime:\n  idle_poll: maybe\n", 1))
    with pytest.raises(ConfigError) as info:
        load_rig(rig)
    assert "runtime.idle_poll: Input should be a valid boolean" in str(info.value)
    assert "\n" not in str(info.value)


def test_the_fleet_rig_polls_and_the_others_leave_the_cpus_alone() -> None:
    assert load_rig("fleet").runtime.idle_poll is True
    assert load_rig("demo").runtime.idle_poll is False


@pytest.mark.sim
@pytest.mark.broker
@pytest.mark.slow
def test_a_rig_polls_while_it_is_open(tmp_path: Path) -> None:
    rig = load_rig("demo").with_isolation("threads")
    rig = rig.model_copy(
        update={"cameras": [], "runtime": rig.runtime.model_copy(update={"idle_poll": True})}
    )
    runtime = RigRuntime(rig, data_root=tmp_path)
    assert runtime.idle_poll.how == "off"
    with runtime:
        assert runtime.idle_poll.how != "off"
        pids = runtime.idle_poll.pollers
        assert not any(_gone(pid) for pid in pids)
    assert runtime.idle_poll.how == "off"
    assert all(_gone(pid) for pid in pids)
