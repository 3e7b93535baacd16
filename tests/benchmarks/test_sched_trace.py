"""benchmarks/sched_trace.py: the kernel's scheduler trace read into CPU and wake-to-run latency per role.

The lines below are in the format of this machine's kernel (6.18: ``events/sched/*/format``, taken
from a live trace), with the tasks and times of a made-up schedule whose every figure is known.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest


@pytest.fixture
def st(load_benchmark: Callable[[str], ModuleType]) -> Any:
    return load_benchmark("sched_trace")


def _switch(cpu: int, ts: str, prev: tuple[str, int, int, str], nxt: tuple[str, int, int]) -> str:
    return (
        f"{prev[0]:>16}-{prev[1]:<7} [{cpu:03d}] d..2. {ts}: sched_switch: prev_comm={prev[0]} "
        f"prev_pid={prev[1]} prev_prio={prev[2]} prev_state={prev[3]} ==> "
        f"next_comm={nxt[0]} next_pid={nxt[1]} next_prio={nxt[2]}\n"
    )


def _wakeup(cpu: int, ts: str, task: tuple[str, int, int], target: int) -> str:
    return (
        f"          python-20949   [{cpu:03d}] dNs4. {ts}: sched_wakeup: comm={task[0]} pid={task[1]} "
        f"prio={task[2]} target_cpu={target:03d}\n"
    )


IDLE0, IDLE1 = ("swapper/0", 0, 120), ("swapper/1", 0, 120)
WORKER = ("recorder-writer", 20, 130)
UR5E, PANDA = ("control-ur5e", 11, 88), ("control-panda", 12, 88)
SPACED = ("Thread-1 (work", 30, 120)  # a default Python thread name: the comm has a space
PHYSICS = ("panda-physics", 40, 89)
POLLER = ("python", 50, 120)

TRACE = [
    "# tracer: nop\n",
    "# entries-in-buffer/entries-written: 21/21   #P:2\n",
    _switch(0, "100.000000", (*IDLE0, "R"), WORKER),
    _wakeup(0, "100.001000", UR5E, 0),
    _switch(0, "100.001500", (*WORKER, "R+"), UR5E),  # UR5e woken 0.5 ms before; the writer preempted
    _switch(0, "100.002000", (*UR5E, "S"), WORKER),  # the writer back after 0.5 ms in the queue
    _wakeup(0, "100.002100", WORKER, 0),  # woken while on the CPU: no wait
    _switch(0, "100.003000", (*WORKER, "S"), IDLE0),
    _wakeup(1, "100.004000", SPACED, 1),
    _switch(1, "100.006500", (*IDLE1, "R"), SPACED),  # waited 2.5 ms: long, not a control loop
    _switch(1, "100.007000", (*SPACED, "S"), PHYSICS),
    "garbage that is no event\n",
    "  task-1 [000] d..2. 100.007500: sched_switch: prev_comm= nothing to read\n",
    "CPU:1 [LOST 42 EVENTS]\n",
    _wakeup(0, "100.010000", PANDA, 1),
    _switch(1, "100.013000", (*PHYSICS, "R"), PANDA),  # the Panda's loop waited 3 ms behind physics
    _switch(1, "100.013400", (*PANDA, "S"), IDLE1),
    # The UR5e's loop, woken on CPU 0, is preempted there and moves to CPU 1, whose clock is a
    # microsecond behind: its switch-in there shows before its switch-out on CPU 0. It ran at once.
    _wakeup(0, "100.014400", UR5E, 0),
    _switch(0, "100.014500", (*IDLE0, "R"), UR5E),
    _switch(1, "100.015000", (*IDLE1, "R"), UR5E),
    _switch(0, "100.015001", (*UR5E, "R+"), WORKER),
    _wakeup(0, "100.015500", UR5E, 1),  # woken while it runs on CPU 1: no wait
    _switch(1, "100.016000", (*UR5E, "S"), IDLE1),
    _switch(0, "100.016001", (*WORKER, "S"), IDLE0),
    _switch(1, "100.020000", (*IDLE1, "R"), POLLER),
    # The physics, runnable since 100.013, gets the CPU back after an ordinary task had it 50 ms:
    # what the kernel's RT throttling or fair server does.
    _switch(1, "100.070000", (*POLLER, "R"), PHYSICS),
]


def test_each_threads_cpu_and_waits_come_from_its_switches_and_wakeups(st: Any) -> None:
    trace = st.parse(TRACE)
    assert (trace.events, trace.malformed, trace.lost) == (21, 2, 42)
    assert trace.span_s == pytest.approx(0.070)
    writer, ur5e, spaced, panda = (trace.threads[t] for t in (20, 11, 30, 12))
    assert writer.on_cpu_s == pytest.approx(0.0035)  # 1.5 ms, preempted, then 1 ms, later 1 ms
    assert writer.wake_ms == []  # its one wake-up came while it ran
    assert writer.preempted_ms == pytest.approx([0.5])
    assert ur5e.wake_ms == pytest.approx([0.5, 0.1])
    assert ur5e.preempted_ms == []
    assert ur5e.on_cpu_s == pytest.approx(0.0005 + 0.0005 + 0.001, abs=2e-6)
    assert spaced.comm == "Thread-1 (work"
    assert spaced.wake_ms == pytest.approx([2.5])
    assert panda.wake_ms == pytest.approx([3.0])
    assert trace.threads[40].preempted_ms == pytest.approx([57.0])
    assert trace.threads[50].preempted_ms == []  # still waiting when the trace ends
    assert sorted((round(w[0], 3), w[5]) for w in trace.long_waits) == [
        (2.5, "woken"),
        (3.0, "woken"),
        (57.0, "preempted"),
    ]


def test_roles_and_the_control_loops_worst_waits_say_what_ran_meanwhile(st: Any) -> None:
    who = {11: (5, "robot host"), 12: (6, "robot host"), 20: (1, "station"), 40: (6, "robot host")}
    summary = st.summarize(st.parse(TRACE), who, seconds=0.07)
    roles = summary["roles"]
    control = roles["robot host: control loop"]
    assert control["threads"] == 2
    assert control["wake_max_ms"] == pytest.approx(3.0)
    assert control["waits_over_1ms"] == 1
    assert control["cpu_cores"] == pytest.approx((0.002 + 0.0004) / 0.070, abs=1e-4)
    assert roles["station: recorder"]["preempted_max_ms"] == pytest.approx(0.5)
    assert roles["robot host: physics"]["threads"] == 1
    # Thread 30 was never seen in /proc: its name alone gives its role.
    assert "ended: main and other threads" in roles
    [worst] = summary["worst_control_waits"]
    assert (worst["thread"], worst["kind"], worst["cpu"]) == ("control-panda", "woken", 1)
    assert worst["meanwhile_ms"] == pytest.approx({"panda-physics": 3.0})
    assert worst["ordinary_tasks_ms"] == 0.0  # the physics is real-time too
    # The real-time threads' waits (the 2.5 ms wait was an ordinary thread's), longest first: the
    # physics waited 57 ms, 50 of them while an ordinary task had its CPU.
    physics, panda = summary["worst_realtime_waits"]
    assert (physics["thread"], physics["kind"], panda["thread"]) == (
        "panda-physics",
        "preempted",
        "control-panda",
    )
    assert physics["ordinary_tasks_ms"] == pytest.approx(50.0)
    assert physics["meanwhile_ms"] == pytest.approx(
        {"python": 50.0, "idle": 5.6, "control-ur5e": 1.0, "control-panda": 0.4}
    )


def test_an_empty_or_hostile_trace_gives_empty_figures(st: Any) -> None:
    hostile = ["\x00" * 10_000, "[999] x 1.0: sched_switch: " + "prev_comm=" * 1000, "#\n", "\n"]
    trace = st.parse(hostile)
    assert (trace.events, trace.threads, trace.span_s) == (0, {}, 0.0)
    assert trace.malformed == 2
    summary = st.summarize(trace, {}, seconds=1.0)
    assert summary["roles"] == {}
    assert summary["worst_control_waits"] == []


def _fake_tracefs(root: Path) -> None:
    for name, value in {
        "tracing_on": "0\n",
        "buffer_size_kb": "7\n",
        "trace_clock": "[local] global counter mono\n",
        "trace": "",
        "events/sched/sched_switch/enable": "0\n",
        "events/sched/sched_wakeup/enable": "0\n",
    }.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(value)


def _trace_then_fail(st: Any, root: Path) -> None:
    with st.Tracefs(65536, root=root) as tracefs:
        assert (root / "buffer_size_kb").read_text() == "65536"
        assert (root / "trace_clock").read_text() == "mono"
        assert (root / "events/sched/sched_switch/enable").read_text() == "1"
        tracefs.on()
        assert (root / "tracing_on").read_text() == "1"
        raise RuntimeError("boom")


def test_the_tracing_state_is_put_back_as_it_was(st: Any, tmp_path: Path) -> None:
    _fake_tracefs(tmp_path)
    with pytest.raises(RuntimeError, match="boom"):
        _trace_then_fail(st, tmp_path)
    assert (tmp_path / "tracing_on").read_text() == "0"
    assert (tmp_path / "buffer_size_kb").read_text() == "7"
    assert (tmp_path / "trace_clock").read_text() == "local"
    assert (tmp_path / "events/sched/sched_wakeup/enable").read_text() == "0"


def test_without_tracefs_it_says_how_to_get_it(st: Any, tmp_path: Path) -> None:
    with pytest.raises(st.TraceUnavailableError, match=r"no tracefs at .*mount -t tracefs"):
        st.Tracefs(1024, root=tmp_path).__enter__()


def test_the_trace_reads_the_same_without_its_flags_and_with_each_tasks_tgid(st: Any) -> None:
    # options/irq-info off drops the flags column; options/record-tgid adds "(  tgid)" after the task.
    plain = [re.sub(r"(\[\d{3}\]) \S+ ", r"\1 ", line) for line in TRACE]
    tgid = [re.sub(r"^(\s*\S+-\d+\s+)(\[)", r"\1(  777) \2", line) for line in TRACE]
    assert plain != TRACE != tgid
    want = st.parse(TRACE)
    for lines in (plain, tgid):
        got = st.parse(lines)
        assert (got.events, got.malformed, got.lost) == (want.events, want.malformed, want.lost)
        assert {t: th.wake_ms for t, th in got.threads.items()} == {
            t: th.wake_ms for t, th in want.threads.items()
        }


def test_an_empty_summary_still_plots(st: Any, tmp_path: Path) -> None:
    st._plot({"wake_ms_by_role": {}}, tmp_path / "empty.png", "nothing traced")
    assert (tmp_path / "empty.png").stat().st_size > 0


def test_an_unknown_rig_is_one_line_not_a_traceback(
    st: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "out.json"
    monkeypatch.setattr("sys.argv", ["sched_trace.py", "--rig", "no-such-rig", "--out", str(out)])
    assert st.main() == 2
    printed = capsys.readouterr().out
    assert "no-such-rig" in printed
    assert "Traceback" not in printed
    assert not out.exists()
