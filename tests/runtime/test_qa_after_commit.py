"""After each commit the station runs the quality gates in a low-priority child process, stopped while
an episode records: verdicts in qa.json and the index, a rejected episode in failures/, and nothing
in the station's own threads."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path
from typing import Literal

import pytest

from telerig.config import load_rig
from telerig.config.qa import QaThresholds
from telerig.qa.checker import unchecked
from telerig.runtime.qa_worker import QA_NICE, QaWorker
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore
from telerig.store.index import EpisodeIndex
from telerig.store.qa_file import read_qa

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

#: The data root, the episode ids, (gate pid, its nice, its policy), each episode's outcome.
Recorded = tuple[Path, list[str], list[int], dict[str, object]]
_WAIT_S = 180.0  # a loaded 2-core host runs the gates of a 3 s episode in well under this


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    """Two 3 s demo episodes (no camera) with the gates after commit; their outcomes and the gate pid."""
    root = tmp_path_factory.mktemp("qa_runtime") / "data"
    rig = load_rig("demo").model_copy(update={"cameras": []})
    pids: list[int] = []
    outcomes: dict[str, object] = {}
    with RigRuntime(rig, data_root=root) as runtime:
        ids = [runtime.run_episode(3.0).episode_id for _ in range(2)]
        worker = runtime.storage.qa
        assert worker is not None
        for episode_id in ids:
            outcomes[episode_id] = runtime.storage.qa_outcome(episode_id, _WAIT_S)
        assert worker.pid is not None
        pids.append(worker.pid)
        pids.append(_nice_of(worker.pid))
        pids.append(os.sched_getscheduler(worker.pid))
    return root, ids, pids, outcomes


def _nice_of(pid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, pid)


def _expected_nice() -> int:
    """QA_NICE steps nicer than this process (the station), at most 19."""
    return min(19, _nice_of(0) + QA_NICE)


def test_every_committed_episode_gets_its_verdicts(
    recorded: Recorded,
) -> None:
    root, ids, _, outcomes = recorded
    store = EpisodeStore(root)
    with EpisodeIndex.open(root) as index:
        for episode_id in ids:
            assert outcomes[episode_id] is not None, f"the gates did not run on {episode_id}"
            summary = store.find(episode_id)
            record = read_qa(summary.path)
            assert record is not None
            assert summary.partition == ("episodes" if record.passed else "failures")
            assert len(index.verdicts(episode_id)) == len(QaThresholds().gates)
            assert index.get(episode_id).status == ("complete" if record.passed else "failed_qa")
            assert index.get(episode_id).quality == record.score_total
    assert unchecked(store) == []


def test_the_gates_run_in_another_process_10_steps_nicer_under_sched_idle(
    recorded: Recorded,
) -> None:
    _, _, (pid, nice, policy), _ = recorded
    assert pid != os.getpid()
    assert nice == _expected_nice()
    assert policy == os.SCHED_IDLE  # qa.while_recording's default


def test_gates_off_in_the_rig_run_none(tmp_path: Path) -> None:
    rig = load_rig("demo").model_copy(update={"cameras": [], "qa": QaThresholds(after_commit=False)})
    with RigRuntime(rig, data_root=tmp_path / "data") as runtime:
        episode = runtime.run_episode(1.5).episode_id
        assert runtime.storage.qa is None
        assert runtime.storage.qa_outcome(episode) is None
    assert read_qa(tmp_path / "data" / "episodes" / episode) is None


# --- the worker alone, on copies of the recorded episodes ------------------------------------------


def _copy(recorded: Recorded, tmp_path: Path) -> Path:
    return Path(shutil.copytree(recorded[0], tmp_path / "data"))


@pytest.mark.parametrize(("while_recording", "policy"), [("idle", os.SCHED_IDLE), ("pause", os.SCHED_OTHER)])
def test_a_real_time_station_starts_its_gate_process_outside_real_time(
    recorded: Recorded, tmp_path: Path, while_recording: Literal["idle", "pause"], policy: int
) -> None:
    """The child inherits its creator's policy: a SCHED_RR station must not give it SCHED_RR."""
    root = _copy(recorded, tmp_path)
    result: dict[str, int] = {}

    def station() -> None:  # a thread of a station under SCHED_RR, as telerig run makes it
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
        thresholds = QaThresholds(gates=("joint_limits",), while_recording=while_recording)
        worker = QaWorker(root, thresholds, index_target=None)
        try:
            episode = EpisodeStore(root).list(include_failures=True)[0].id
            worker.submit(episode).result(_WAIT_S)
            assert worker.pid is not None
            result["policy"] = os.sched_getscheduler(worker.pid)
            result["nice"] = _nice_of(worker.pid)
        finally:
            worker.close()

    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
    except PermissionError:
        pytest.fail("this test needs CAP_SYS_NICE (root in the test container) to run a SCHED_RR station")
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    thread = threading.Thread(target=station)
    thread.start()
    thread.join(_WAIT_S + 30)
    assert result == {"policy": policy, "nice": _expected_nice()}


def test_an_unreadable_episode_fails_alone_and_the_next_is_checked(
    recorded: Recorded, tmp_path: Path
) -> None:
    root = _copy(recorded, tmp_path)
    store = EpisodeStore(root)
    broken, good = (s.id for s in store.list(include_failures=True))
    (store.find(broken).path / "episode.mcap").write_bytes(b"not an mcap")
    (store.find(broken).path / "qa.json").unlink()  # its earlier check is not what this one says
    with QaWorker(root, QaThresholds(gates=("joint_limits", "idle")), index_target=root) as worker:
        first, second = worker.submit(broken), worker.submit(good)
        with pytest.raises(RuntimeError):
            first.result(_WAIT_S)
        outcome = second.result(_WAIT_S)
    assert outcome.episode_id == good
    assert read_qa(outcome.path) is not None
    assert [s.id for s in unchecked(store)] == [broken]  # `telerig qa` tries it again


def test_close_cuts_a_check_short_and_leaves_it_for_telerig_qa(recorded: Recorded, tmp_path: Path) -> None:
    root = _copy(recorded, tmp_path)
    store = EpisodeStore(root)
    for s in store.list(include_failures=True):  # as if never checked
        (s.path / "qa.json").unlink()
        if s.partition == "failures":
            store.restore_from_failures(s.id)
    episodes = [s.id for s in store.list()]
    worker = QaWorker(root, QaThresholds(), index_target=root)
    futures = [worker.submit(e) for e in episodes]
    deadline = time.monotonic() + _WAIT_S
    while worker.pid is None and time.monotonic() < deadline:  # the process is up, the first check runs
        time.sleep(0.05)
    t0 = time.monotonic()
    worker.close(grace_s=0.0)
    assert time.monotonic() - t0 < 15.0
    assert all(f.done() for f in futures)
    done = {e for e, f in zip(episodes, futures, strict=True) if not f.cancelled() and f.exception() is None}
    # Every episode is either checked (qa.json agrees with where it lies) or left for `telerig qa`.
    assert {s.id for s in unchecked(store)} == set(episodes) - done
    for s in store.list(include_failures=True):
        assert (root / s.partition / s.id).is_dir()


def _state(pid: int) -> str:
    """The process state letter of /proc/<pid>/stat: R, S, T (stopped)..."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_a_paused_worker_checks_nothing_until_resumed(recorded: Recorded, tmp_path: Path) -> None:
    """With ``qa.while_recording: pause`` the station stops the gates (SIGSTOP) while an episode
    records, as it pauses uploads."""
    root = _copy(recorded, tmp_path)
    store = EpisodeStore(root)
    episode = store.list(include_failures=True)[0].id
    (store.find(episode).path / "qa.json").unlink()
    thresholds = QaThresholds(gates=("joint_limits",), while_recording="pause")
    with QaWorker(root, thresholds, index_target=None) as worker:
        deadline = time.monotonic() + _WAIT_S
        while worker.pid is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert worker.pid is not None
        worker.pause()
        future = worker.submit(episode)
        time.sleep(3.0)
        assert _state(worker.pid) == "T"
        assert not future.done()
        assert read_qa(store.find(episode).path) is None
        worker.resume()
        outcome = future.result(_WAIT_S)
    assert read_qa(outcome.path) is not None


def test_by_default_the_gates_check_on_under_sched_idle_while_an_episode_records(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A station recording back to back (pause before every episode, resume for a moment between
    them) must still get its verdicts: the gate process runs under SCHED_IDLE and is never stopped."""
    root = _copy(recorded, tmp_path)
    store = EpisodeStore(root)
    episode = store.list(include_failures=True)[0].id
    (store.find(episode).path / "qa.json").unlink()
    thresholds = QaThresholds(gates=("joint_limits",))
    assert thresholds.while_recording == "idle"
    with QaWorker(root, thresholds, index_target=None) as worker:
        deadline = time.monotonic() + _WAIT_S
        while worker.pid is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert worker.pid is not None
        tasks = [int(t) for t in os.listdir(f"/proc/{worker.pid}/task")]
        assert {os.sched_getscheduler(t) for t in tasks} == {os.SCHED_IDLE}
        worker.pause()
        future = worker.submit(episode)
        outcome = future.result(_WAIT_S)  # while "paused"
        assert worker.paused
        assert _state(worker.pid) != "T"
    assert read_qa(outcome.path) is not None


_STATION = """
import sys, time
from pathlib import Path
from telerig.config.qa import QaThresholds
from telerig.runtime.qa_worker import QaWorker
worker = QaWorker(Path(sys.argv[1]), QaThresholds(while_recording="pause"), index_target=None)
worker.start()
while worker.pid is None:
    time.sleep(0.05)
worker.pause()
print(worker.pid, flush=True)
time.sleep(600)
"""


def test_a_station_killed_while_recording_leaves_no_stopped_gate_process(tmp_path: Path) -> None:
    """The gate process is stopped while an episode records; kill -9 of the station must not leave
    it stopped (and orphaned) for ever."""
    import signal
    import subprocess
    import sys

    station = subprocess.Popen(
        [sys.executable, "-c", _STATION, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert station.stdout is not None
        child = int(station.stdout.readline())
        deadline = time.monotonic() + 10
        while _state(child) != "T" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _state(child) == "T"
    finally:
        station.send_signal(signal.SIGKILL)
        station.communicate(timeout=30)
    deadline = time.monotonic() + 10
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child)


def _alive(pid: int) -> bool:
    try:
        state = _state(pid)
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"
