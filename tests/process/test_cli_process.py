"""``telerig process`` end to end in-process (the real segment, clips, offline annotate and layout
stages): default output beside the inputs, summary table, index database, re-run, exit codes and
one-line errors for bad paths, queries, stages and options."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from core_kit import make_episode, make_video

from telerig.cli.main import main
from telerig.store.index import EpisodeIndex

_STAGES = ["--stages", "segment,clips,annotate,layout", "--workers", "1"]


def test_data_root_to_processed_partition_and_index(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    episode_id = make_episode(root, seconds=3.0)
    assert main(["process", str(root), *_STAGES]) == 0
    out = capsys.readouterr().out
    assert "hours in" in out
    assert "clips annotated" in out
    processed = root / "processed"
    index = json.loads((processed / "index.json").read_text())
    assert [c["source_id"] for c in index["clips"]] == [episode_id]
    with EpisodeIndex.open(root / "index.sqlite") as db:
        assert [r.source_id for r in db.processed_clips()] == [episode_id]
    # Re-run by query: everything reused.
    assert main(["process", "task=pick", "--data-root", str(root), *_STAGES]) == 0
    rerun = capsys.readouterr().out
    assert "segment  │   0 │      1" in rerun.replace("┃", "│")


def test_video_folder_with_a_garbage_file_exits_1_and_keeps_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "videos"
    make_video(folder / "good.mp4", seconds=2.0)
    (folder / "bad.mp4").write_bytes(os.urandom(5000))
    assert main(["process", str(folder), *_STAGES]) == 1
    out = capsys.readouterr().out
    assert "failed: video-" in out
    failures = json.loads((folder / "processed" / "failures.json").read_text())["failures"]
    assert [Path(f["source"]).name for f in failures] == ["bad.mp4"]
    summary = json.loads((folder / "processed" / "summary.json").read_text())
    good = next(i for i in summary["items"] if i["source"].endswith("good.mp4"))
    assert all(s["status"] != "failed" for s in good["stages"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["process", "nowhere/at/all"], "not a file, folder, data root or episode"),
        (["process", "ep-20260101-000000-abcd", "--data-root", "data"], "not found"),
        (["process", "colour=blue", "--data-root", "data"], "expected KEY=VALUE"),
        (["process", "data", "--stages", "segment,dance"], "unknown pipeline stage 'dance'. Valid:"),
        (["process", "data", "--stages", ","], "name at least one stage"),
        (["process", "data", "--workers", "0"], "--workers 0"),
        (["process", "data", "--cluster", "tcp://127.0.0.1:9", "--stages", "segment"], "cannot reach"),
        (["process", "data", "--cluster", "x" * 3000, "--stages", "segment"], "expected tcp://HOST:PORT"),
        (["process", "data", "--rig", "no-such-rig"], "no-such-rig"),
        (["process", "\udcff" * 300], "not a file, folder"),
    ],
)
def test_bad_input_is_one_line_error(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    message: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    make_episode(tmp_path / "data", seconds=1.0)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in " ".join(err.split())
    assert len(err.strip().splitlines()) <= 3  # one message (rich may wrap it on a narrow console)
    assert "Traceback" not in err
