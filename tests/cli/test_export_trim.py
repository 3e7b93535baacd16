"""``telerig export --trim-idle``: the idle head and pauses are cut, the first seconds of the idle
tail are kept (``--keep-idle-tail``) so a policy sees the robot hold still once the task is done."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from telerig.cli.main import main
from telerig.export.frames import read_episode_qa, read_manifest
from telerig.export.run import DEFAULT_KEEP_IDLE_TAIL_S, keep_idle_tail
from telerig.qa.report import QaReport
from telerig.store.episodes import EpisodeStore
from telerig.store.qa_file import write_qa

# What the quality gates found in a pick-and-place demonstration of 2026-11-26: an idle head, one
# pause, and the idle tail after the operator let go of the cube (it ends where the episode ends).
SPANS = ((0.0, 0.06), (5.0, 7.0), (13.36, 20.6745))
DURATION_S = 20.6745


def test_the_tail_keeps_its_first_seconds_and_the_rest_is_cut_as_before() -> None:
    assert keep_idle_tail(SPANS, DURATION_S, 1.0) == ((0.0, 0.06), (5.0, 7.0), (14.36, 20.6745))
    assert keep_idle_tail(SPANS, DURATION_S, 0.0) == SPANS
    # A tail shorter than what is kept is not cut at all; nothing else changes.
    assert keep_idle_tail(SPANS, DURATION_S, 10.0) == SPANS[:2]
    # A pause that ends before the episode does is not the tail; an unfinished episode has none.
    assert keep_idle_tail(SPANS, 30.0, 1.0) == SPANS
    assert keep_idle_tail(SPANS, None, 1.0) == SPANS


def _frames(dataset: Path) -> int:
    return sum(pq.read_metadata(f).num_rows for f in sorted((dataset / "data").rglob("*.parquet")))


def test_export_keeps_the_idle_tail_it_is_told_to(demo_recording: Path, tmp_path: Path) -> None:
    # The demo's scripted motion runs to its episodes' ends; a demonstration ends idle (the operator
    # waits for the episode to end). Give each copied episode that tail, as the gates record one.
    root = Path(shutil.copytree(demo_recording, tmp_path / "data"))
    episodes = EpisodeStore(root).list(include_failures=True)
    tail_s = 2.0
    for e in episodes:
        record = read_episode_qa(e.path)
        assert record is not None, "the demo recording carries its quality records"
        duration = read_manifest(e.path).duration_s
        assert duration is not None
        report = dict(record.report)
        report["idle_segments"] = [[round(duration - tail_s, 4), round(duration, 4)]]
        assert QaReport.from_json(report).idle_segments[-1][1] == round(duration, 4)
        write_qa(e.path, record.model_copy(update={"report": report}))

    def export(out: Path, *extra: str) -> int:
        argv = ["export", "--format", "lerobot", "--out", str(out), "--data-root", str(root)]
        assert main([*argv, "--include-failures", *extra]) == 0
        return _frames(out)

    whole = export(tmp_path / "whole")
    cut = export(tmp_path / "cut", "--trim-idle", "--keep-idle-tail", "0")
    default = export(tmp_path / "default", "--trim-idle")
    fps = json.loads((tmp_path / "whole" / "meta" / "info.json").read_text())["fps"]
    n = len(episodes)
    # The default keeps the tail's first second (within a frame of grid alignment per episode) and
    # still cuts the rest of it (the dataset's grid ends with the last camera frame, before the
    # recording does, so the rest is shorter than the tail's last second).
    assert abs((default - cut) - n * DEFAULT_KEEP_IDLE_TAIL_S * fps) <= n, (whole, default, cut)
    assert whole > default, (whole, default, cut)


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_a_bad_tail_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    argv = ["export", "--format", "lerobot", "--out", str(tmp_path / "ds"), "--data-root", str(tmp_path)]
    assert main([*argv, "--trim-idle", "--keep-idle-tail", value]) == 2
    err = capsys.readouterr().err.strip()
    assert "--keep-idle-tail must be seconds >= 0" in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "ds").exists()
