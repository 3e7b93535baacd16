"""The vertical slice end to end: scripted VR → Mosquitto → IK → safety → MuJoCo, recorded to episodes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import av
import numpy as np
import pytest
from mcap.reader import make_reader
from pydantic import JsonValue

from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.mcap_log import read_json, read_log
from telerig.ir.types import CameraFrame, ControllerState, JointCommand, JointState, Stamp, now_ns
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


#: What a hostile local client publishes into the demo during the episode: (topic, payload maker).
_FORGED_SENT = "telerig/v1/demo/arm0/joint_command_sent"
_INTRUDER_SENT = "telerig/v1/demo/intruder/joint_command_sent"
_CONTROLLER = "telerig/v1/demo/vr0/right_controller"


def _forge(url: str, stop: threading.Event) -> None:
    """Publish forged commands (a 5.46 rad jump) and 256 KB random payloads every 0.2 s until ``stop``."""
    bus = MqttBus(url, client_id="intruder").connect()
    seq = 0
    try:
        while not stop.wait(0.2):
            seq += 1
            t = now_ns()
            forged = wire.encode(JointCommand(Stamp("intruder", seq, t, t), ("j",), np.array([5.46])))
            bus.publish(_FORGED_SENT, forged)
            bus.publish(_INTRUDER_SENT, forged)
            bus.publish(_CONTROLLER, os.urandom(256 << 10))
    finally:
        bus.close()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 4 s episode of the demo rig (shortened cycle), recorded once for the tests below, while a
    forger publishes on the rig's bus."""
    root = tmp_path_factory.mktemp("data")
    with RigRuntime(load_rig("demo"), data_root=root) as runtime:
        assert runtime.broker_url is not None
        stop = threading.Event()
        forger = threading.Thread(target=_forge, args=(runtime.broker_url, stop))
        forger.start()
        try:
            result = runtime.run_episode(4.0)
        finally:
            stop.set()
            forger.join()
    assert result.status == "complete"
    return result.path


def _rejected(recorded: Path) -> list[dict[str, JsonValue]]:
    rows = read_json(recorded / "episode.mcap", topics=["telerig/v1/demo/recorder/rejected"])
    return [v for _, v, _ in rows if isinstance(v, dict)]


def test_forged_and_oversized_messages_stay_out_of_the_data_channels(recorded: Path) -> None:
    sources = {e.sample.stamp.source_id for e in read_log(recorded / "episode.mcap", topics=[_FORGED_SENT])}
    assert sources == {"arm0"}
    topics = {e.topic for e in read_log(recorded / "episode.mcap")}
    assert _INTRUDER_SENT not in topics
    rejected = _rejected(recorded)
    assert {(r["topic"], r["reason"]) for r in rejected} == {
        (_FORGED_SENT, "wrong_source"),
        (_INTRUDER_SENT, "unknown_stream"),
        (_CONTROLLER, "oversized"),
    }
    streams = {s["name"]: s for s in json.loads((recorded / "manifest.json").read_text())["extra"]["streams"]}
    assert set(streams[_FORGED_SENT]["rejected"]) == {"wrong_source"}
    assert set(streams[_CONTROLLER]["rejected"]) == {"oversized"}
    assert streams[_CONTROLLER]["messages"] > 0


def test_the_rigs_own_streams_are_never_rejected(recorded: Path) -> None:
    rejected = _rejected(recorded)
    forged = {_FORGED_SENT: "wrong_source", _INTRUDER_SENT: "unknown_stream", _CONTROLLER: "oversized"}
    assert [r for r in rejected if forged.get(str(r["topic"])) != r["reason"]] == []


def test_episode_has_mcap_video_and_manifest(recorded: Path) -> None:
    assert (recorded / "episode.mcap").is_file()
    assert (recorded / "cameras" / "scene.mp4").is_file()
    assert (recorded / "manifest.json").is_file()


def test_mcap_opens_with_the_standard_reader(recorded: Path) -> None:
    with (recorded / "episode.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {c.topic for c in summary.channels.values()}
    assert any(t.endswith("/vr0/right_controller") for t in topics)
    assert any(t.endswith("/arm0/joint_command_requested") for t in topics)
    assert any(t.endswith("/arm0/joint_command_sent") for t in topics)
    assert any(t.endswith("/arm0/joint_state") for t in topics)
    assert any(t.endswith("/scene/frames") for t in topics)
    assert all(s.name == "telerig.v1.Envelope" for s in summary.schemas.values())


def test_every_stream_is_recorded_with_the_expected_types(recorded: Path) -> None:
    kinds: dict[str, set[type]] = {}
    for entry in read_log(recorded / "episode.mcap"):
        kinds.setdefault(entry.topic.rsplit("/", 1)[-1], set()).add(type(entry.sample))
        assert (
            entry.log_time_ns >= entry.publish_time_ns - 50_000_000
        )  # both times present, log after capture
    assert kinds["right_controller"] == {ControllerState}
    assert kinds["joint_command_requested"] == {JointCommand}
    assert kinds["joint_command_sent"] == {JointCommand}
    assert kinds["joint_state"] == {JointState}
    assert kinds["frames"] == {CameraFrame}


def test_video_frame_count_matches_recorded_frame_timestamps(recorded: Path) -> None:
    frames = [e.sample for e in read_log(recorded / "episode.mcap") if isinstance(e.sample, CameraFrame)]
    with av.open(str(recorded / "cameras" / "scene.mp4")) as container:
        decoded = sum(1 for _ in container.decode(video=0))
    assert decoded == len(frames)
    assert decoded > 0


def test_robot_state_is_recorded_at_about_100_hz(recorded: Path) -> None:
    states = [e for e in read_log(recorded / "episode.mcap") if isinstance(e.sample, JointState)]
    span_s = (states[-1].publish_time_ns - states[0].publish_time_ns) / 1e9
    assert 80 <= (len(states) - 1) / span_s <= 120


def test_sent_commands_never_jump(recorded: Path) -> None:
    sent = [e.sample for e in read_log(recorded / "episode.mcap") if e.topic.endswith("joint_command_sent")]
    positions = np.array([s.positions for s in sent if isinstance(s, JointCommand)])
    steps = np.abs(np.diff(positions, axis=0)).max()
    assert steps < 3.2 * 0.02 * 2  # 180 deg/s over at most two 10 ms ticks


def _run_cli(args: list[str], tmp: Path, **kw: object) -> subprocess.Popen[str]:
    # As a terminal starts it, Ctrl-C reaching telerig: an ignored or blocked SIGINT here would be
    # the child's too (see tests/conftest.py _sigint_kept).
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
    return subprocess.Popen(
        [sys.executable, "-m", "telerig.cli.main", *args, "--data-root", str(tmp)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )


def _children_alive(pid: int) -> bool:
    out = subprocess.run(["pgrep", "-s", str(pid)], check=False, capture_output=True, text=True)
    return bool(out.stdout.strip())


def test_demo_command_writes_episodes_prints_summary_and_leaves_no_process(tmp_path: Path) -> None:
    proc = _run_cli(["demo", "--episodes", "2", "--duration", "2"], tmp_path)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert "input-to-actuation latency" in out
    assert "episodes written" in out
    assert "replaying vr0 from" in out
    assert len(EpisodeStore(tmp_path).list(include_failures=True)) == 2  # the gates may reject them
    assert not _children_alive(proc.pid)


def test_ctrl_c_marks_the_running_episode_incomplete_and_keeps_earlier_ones(tmp_path: Path) -> None:
    proc = _run_cli(["demo", "--episodes", "3", "--duration", "3"], tmp_path)
    store = EpisodeStore(tmp_path)
    deadline = time.monotonic() + 90
    while not store.list(include_failures=True) and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)  # inside episode 2
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    committed = store.list(include_failures=True)  # the quality gates may have moved it to failures/
    assert len(committed) == 1
    assert committed[0].status == "complete"
    unfinished = [e for e in store.list(include_unfinished=True) if e.status != "complete"]
    assert [e.status for e in unfinished] == ["incomplete"]
    assert "Ctrl-C" in (unfinished[0].reason or "")
    assert not _children_alive(proc.pid)
