"""Smoke test of ``benchmarks/soak.py``: a short soak of the demo rig runs end to end and writes its
JSON and plot with every field the endurance note reads.

The verdict itself is not asserted: on a shared, loaded host a short run has gaps and warm-up
growth that a quiet host would not (the one-hour run is for the note). What is asserted does not
depend on load: the episodes are recorded and complete-or-reported, every sample reads the
station's processes, the index holds one row per episode.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "soak.py"


def test_short_demo_soak_writes_its_report(tmp_path: Path, soak: Any) -> None:
    out, png = tmp_path / "soak.json", tmp_path / "soak.png"
    proc = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "--rig=demo",
            "--minutes=0.25",
            "--episode-s=4",
            "--sample-s=1",
            f"--out={out}",
            f"--plot={png}",
            f"--data-root={tmp_path / 'data'}",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode in (0, 1), proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "verdict:" in proc.stdout
    report = json.loads(out.read_text())
    assert report["verdict"] == ("pass" if proc.returncode == 0 else "fail")
    assert (report["verdict"] == "fail") == bool(report["failures"])
    # The demo rig's own settings (no --isolation or --idle-poll given): robots in processes, CPUs halting.
    assert report["runtime"] == {"isolation": "processes", "realtime_priority": 10, "idle_poll": False}

    episodes = report["episodes"]
    assert len(episodes) >= 3
    blackout_ms = soak.BLACKOUT_MS
    for e in episodes:
        assert e["status"] in ("complete", "incomplete")
        assert e["latency_count"] > 0
        assert 0 < e["latency_p50_ms"] <= e["latency_p99_ms"]
        assert e["messages"] > 0
        assert e["message_rate_hz"] == pytest.approx(e["messages"] / e["duration_s"], abs=0.1)
        # The wall time of the episode beyond its recording: opening, starting, stopping, hand-off.
        assert e["overhead_s"] == pytest.approx(e["end_s"] - e["start_s"] - e["duration_s"], abs=2e-3)
        assert e["camera_frames"] > 0
        for key in ("gaps", "stalls", "stream_drops", "camera_dropped", "malformed", "tick_faults"):
            assert e[key] >= 0
        # Where the gaps and drops were: every stream with any, and nothing else.
        assert sum(e["gaps_by_stream"].values()) == e["gaps"]
        assert sum(e["drops_by_stream"].values()) <= e["stream_drops"]
        assert all(n > 0 for n in [*e["gaps_by_stream"].values(), *e["drops_by_stream"].values()])
        # The host's stalls and the station's collections inside the episode, to tell a gap's cause:
        # the probes run (root here) and saw what they saw; each lies inside the episode.
        start_ns, end_ns = e["wall_ns"]
        assert start_ns < end_ns
        assert isinstance(e["rt_blackouts"], list)
        for at_s, ms in e["rt_blackouts"]:
            assert -ms / 1e3 <= at_s <= (end_ns - start_ns) / 1e9
            assert ms >= blackout_ms
        for at_s, generation, ms, thread in e["gc_pauses"]:
            assert 0 <= at_s <= (end_ns - start_ns) / 1e9 + 1e-3
            assert generation in (0, 1, 2)
            assert ms >= 2.0
            assert thread
    assert "real-time blackouts:" in proc.stdout
    assert "the station's garbage collections (gen 0: " in proc.stdout
    assert report["gates"] == "idle"  # the rig's qa.while_recording
    assert [e["index_rows"] for e in episodes] == list(range(1, len(episodes) + 1))
    # The gates' backlog: each complete episode is submitted, and the drain says what came of it.
    assert all(e["qa_waiting"] >= 0 for e in episodes)
    qa = report["qa"]
    assert set(qa) == {"submitted", "waiting_at_end", "drain_s", "unchecked_after_drain", "failed"}
    assert qa["submitted"] == sum(e["status"] == "complete" for e in episodes)
    assert 0 <= qa["unchecked_after_drain"] <= qa["waiting_at_end"] <= qa["submitted"]

    samples = report["samples"]
    assert len(samples) >= 8
    assert sum(s["between_episodes"] for s in samples) == len(episodes) + 1
    for s in samples:
        for role in ("station", "broker"):  # the embedded Mosquitto is the station's child
            assert s["rss_mib"][role] > 0
            assert s["fds"][role] > 0
            assert s["threads"][role] > 0
    assert samples[-1]["processes"].get("render") == 1  # the scene camera renders in its own process
    assert samples[-1]["data_root_bytes"] > 100_000
    assert samples[-1]["index_bytes"] > 0

    total = report["processes"]["total"]
    for key in ("rss_mib_per_min", "fds_between_episodes_per_min", "threads_between_episodes_per_min"):
        assert isinstance(total[key], float)
    assert report["storage"]["data_root_kb_per_episode"] > 0
    assert report["storage"]["index_closed_bytes"] > 0  # measured once the rig closed its index
    assert report["storage"]["index_kb_per_episode"] > 0
    assert set(report["overhead"]) == {"p50_s", "max_s", "drift_s_per_min"}
    assert 0 < report["warmup_end_s"] < report["wall_s"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments_are_refused_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--minutes=0", f"--out={tmp_path / 'x.json'}"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "--minutes, --episode-s and --sample-s must be > 0" in proc.stderr
    assert not (tmp_path / "x.json").exists()


def test_a_data_root_in_use_is_refused(tmp_path: Path) -> None:
    (tmp_path / "episodes").mkdir()
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), f"--data-root={tmp_path}", f"--out={tmp_path / 'x.json'}"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "is not empty: the soak measures a data root's growth from nothing" in proc.stderr
    assert not (tmp_path / "x.json").exists()


@pytest.fixture
def soak(load_benchmark: Callable[[str], ModuleType]) -> Any:
    return load_benchmark("soak")


def _episode(episode_id: str, messages: int, duration_s: float = 15.0) -> dict[str, object]:
    return {
        "episode_id": episode_id,
        "duration_s": duration_s,
        "messages": messages,
        "message_rate_hz": messages / duration_s if duration_s else 0.0,
    }


def test_an_episode_far_below_the_runs_message_rate_is_thin(soak: Any) -> None:
    # What 2026-11-26's steal burst recorded: "complete" episodes holding a fraction of the messages.
    run = [_episode(f"ep-{i}", 13_000) for i in range(5)] + [_episode("ep-burst", 3_526)]
    run.append(_episode("ep-long", 13_000 * 2, duration_s=30.0))  # rate, not count, is compared
    run.append(_episode("ep-just-above", 6_600))
    run.append({**soak.failed_episode("error: broker gone", 0.0, 1.0)})  # its own failure, no rate
    failures = soak.thin_episodes(run)
    assert len(failures) == 1
    assert failures[0].startswith("episode ep-burst: thin, 3526 messages (235/s, under 50% of the run's")
    assert soak.thin_episodes([]) == []
    assert soak.thin_episodes([soak.failed_episode("interrupted", 0.0, 1.0)]) == []


def test_gates_that_fall_behind_fail_the_verdict(soak: Any) -> None:
    keeping_up = [{**soak.failed_episode("x", 60.0 * i, 60.0 * i + 15), "qa_waiting": 2} for i in range(4)]
    behind = [{**e, "qa_waiting": 3 + i} for i, e in enumerate(keeping_up)]
    drained = {"submitted": 4, "waiting_at_end": 2, "drain_s": 3.0, "unchecked_after_drain": 0, "failed": 0}
    stuck = {**drained, "unchecked_after_drain": 1}

    def gate_failures(episodes: list[dict[str, object]], qa: dict[str, object]) -> list[str]:
        failures = soak.analyse([], episodes, 60.0, qa)["failures"]
        return [f for f in failures if "verdict" in f]

    assert gate_failures(keeping_up, drained) == []
    # The first episode ended inside the warm-up; the three after it waited on 4, 5 and 6 episodes.
    assert gate_failures(behind, drained) == [
        "the quality gates fell behind: 3 episodes after warm-up ended with more than 2 waiting for a "
        "verdict (up to 6)"
    ]
    assert gate_failures(keeping_up, stuck) == [
        f"1 of 4 episodes had no verdict {soak.QA_DRAIN_S:g} s after the last one ended"
    ]


def test_the_streams_with_the_most_gaps_come_first(soak: Any) -> None:
    episodes = [
        {
            **soak.failed_episode("x", 0.0, 1.0),
            "gaps_by_stream": {"fleet/ur5e/joint_state": 3, "fleet/vr/pose": 1},
        },
        soak.failed_episode("error: broker gone", 1.0, 2.0),  # none recorded
        {**soak.failed_episode("x", 2.0, 3.0), "gaps_by_stream": {"fleet/vr/pose": 4, "fleet/glove/hand": 1}},
    ]
    assert soak.stream_totals(episodes, "gaps_by_stream") == [
        ("fleet/vr/pose", 5),
        ("fleet/ur5e/joint_state", 3),
        ("fleet/glove/hand", 1),
    ]
    assert soak.stream_totals(episodes, "drops_by_stream") == []


def test_the_report_says_which_episodes_with_gaps_had_a_stall_of_the_host_or_the_collector(soak: Any) -> None:
    from gc_pauses import GcPause, GcPauses  # on the path once soak.py is loaded
    from rt_blackout import Blackout, RtBlackoutProbe

    t0 = 1_700_000_000_000_000_000
    episodes = [
        {
            **soak.failed_episode("x", 0.0, 15.0),
            "episode_id": "a",
            "gaps": 12,
            "wall_ns": [t0, t0 + 15 * 10**9],
        },
        {
            **soak.failed_episode("x", 16.0, 31.0),
            "episode_id": "b",
            "gaps": 1,
            "wall_ns": [t0 + 16 * 10**9, t0 + 31 * 10**9],
        },
        {
            **soak.failed_episode("x", 32.0, 47.0),
            "episode_id": "c",
            "wall_ns": [t0 + 32 * 10**9, t0 + 47 * 10**9],
        },
    ]

    probe = RtBlackoutProbe()
    probe.__exit__(None, None, None)  # a block that started no probe; then what they would have seen:
    probe.blackouts = [Blackout(1, t0 + 5 * 10**9, 21.0), Blackout(0, t0 + 40 * 10**9, 47.0)]
    line = soak.note_blackouts(episodes, probe)
    assert [e["rt_blackouts"] for e in episodes] == [[[5.0, 21.0]], [], [[8.0, 47.0]]]
    assert "1 of the 2 episodes with gaps had a real-time blackout (12 of the 13 gaps)" in line
    # A gap that fell in one is still a failure, with the blackout named beside it.
    failures = soak.analyse([], episodes, 0.0)["failures"]
    assert "episode a: gaps 12 (in an episode with 1 real-time blackouts, longest 21 ms)" in failures
    assert "episode b: gaps 1" in failures

    collections = GcPauses()  # not entered: what it would have noted
    collections.counts = {0: 90, 1: 8, 2: 2}
    collections.pauses = [
        GcPause(2, t0 + 17 * 10**9, 22.0, "recorder-writer"),
        GcPause(1, t0 + 33 * 10**9, 3.0, "MainThread"),
    ]
    line = soak.note_collections(episodes, collections)
    assert [e["gc_pauses"] for e in episodes] == [
        [],
        [[1.0, 2, 22.0, "recorder-writer"]],
        [[1.0, 1, 3.0, "MainThread"]],
    ]
    assert line.startswith(
        "the station's garbage collections (gen 0: 90, gen 1: 8, gen 2: 2): 2 of 2 ms or more, longest 22 ms "
        "(gen 2, thread recorder-writer); full ones: 1, median 22 ms"
    )
    assert "episodes with gaps" not in line  # every episode has some: only a gap's own time could tell
