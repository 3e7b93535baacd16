"""The runner with real small stages: outputs and provenance, skip on re-run, redo after a version
or settings change (that stage and later ones only), failures recorded while the batch goes on,
damaged provenance redone, the process pool giving what the in-process run gives."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from core_kit import make_video
from core_stages import CopyStage, CrashStage, DoubleStage, OddStage, PartlyStage, ProbeStage

from telerig.errors import ProcessError
from telerig.process.items import discover
from telerig.process.run import item_dir, plan, run_pipeline
from telerig.process.stage import Stage, read_provenance, record_edit


def _folder(tmp_path: Path) -> Path:
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=1.0)
    make_video(folder / "b.mp4", seconds=2.0, shade=40)
    (folder / "garbage.mp4").write_bytes(os.urandom(3000))
    return folder


def _started(work: Path, item_id: str, stage: str) -> str:
    prov = read_provenance(item_dir(work, item_id) / stage)
    assert prov is not None
    return prov.started


def test_run_writes_outputs_provenance_and_summary(tmp_path: Path) -> None:
    found = discover(str(_folder(tmp_path)))
    work = tmp_path / "processed"
    summary = run_pipeline(found.items, plan([ProbeStage(), DoubleStage()]), work, workers=1)
    by_name = {Path(o.source).name: o for o in summary.outcomes}
    assert [s.status for s in by_name["a.mp4"].stages] == ["ok", "ok"]
    a = next(i for i in found.items if i.videos[0].name == "a.mp4")
    probe = json.loads((item_dir(work, a.id) / "probe" / "probe.json").read_text())
    assert probe["videos"]["a.mp4"]["frames"] == 10
    assert json.loads((item_dir(work, a.id) / "double" / "double.json").read_text()) == {"a.mp4": 20}
    prov = read_provenance(item_dir(work, a.id) / "double")
    assert prov is not None
    assert (prov.stage, prov.version, prov.source_hash) == ("double", "1", a.source_hash)
    assert set(prov.upstream) == {"probe"}
    # The garbage file fails in probe (PyAV cannot open it); the others are done regardless.
    failed = by_name["garbage.mp4"].failed
    assert failed is not None
    assert failed.name == "probe"
    assert len(by_name["garbage.mp4"].stages) == 1
    assert summary.hours_in == pytest.approx(3.0 / 3600)
    assert summary.hours_kept == pytest.approx(1.5 / 3600)
    assert summary.total("clips") == 2
    failures = json.loads((work / "failures.json").read_text())["failures"]
    assert [(f["stage"], Path(f["source"]).name) for f in failures] == [("probe", "garbage.mp4")]
    assert "\n" not in failures[0]["message"]
    written = json.loads((work / "summary.json").read_text())
    assert (written["clips"], written["failures"]) == (2, 1)


def test_rerun_skips_and_version_bump_redoes_that_stage_and_later(tmp_path: Path) -> None:
    found = discover(str(_folder(tmp_path)))
    work = tmp_path / "processed"
    item = next(i for i in found.items if i.videos[0].name == "a.mp4")
    run_pipeline(found.items, plan([ProbeStage(), DoubleStage()]), work, workers=1)
    probe_at, double_at = _started(work, item.id, "probe"), _started(work, item.id, "double")

    again = run_pipeline(found.items, plan([ProbeStage(), DoubleStage()]), work, workers=1)
    assert again.stage_counts("probe") == {"ran": 1, "reused": 2, "empty": 0, "failed": 1}
    assert _started(work, item.id, "probe") == probe_at
    assert _started(work, item.id, "double") == double_at

    # A new version of the later stage redoes only it.
    run_pipeline(found.items, plan([ProbeStage(), DoubleStage(version="2")]), work, workers=1)
    assert _started(work, item.id, "probe") == probe_at
    assert _started(work, item.id, "double") != double_at
    double_at = _started(work, item.id, "double")

    # A new version of the first stage redoes it and everything after it.
    run_pipeline(found.items, plan([ProbeStage(version="2"), DoubleStage(version="2")]), work, workers=1)
    assert _started(work, item.id, "probe") != probe_at
    assert _started(work, item.id, "double") != double_at


def test_settings_change_and_failing_setting_are_recorded(tmp_path: Path) -> None:
    found = discover(str(_folder(tmp_path)))
    work = tmp_path / "processed"
    stages: list[Stage] = [ProbeStage(), DoubleStage()]
    run_pipeline(found.items, plan(stages), work, workers=1)
    summary = run_pipeline(found.items, plan(stages, {"probe": {"fail_prefix": "a"}}), work, workers=1)
    failed = {Path(o.source).name: o.failed.message for o in summary.outcomes if o.failed is not None}
    assert set(failed) == {"a.mp4", "garbage.mp4"}
    assert failed["a.mp4"] == "RuntimeError: refusing a.mp4 by setting fail_prefix"
    b = next(o for o in summary.outcomes if Path(o.source).name == "b.mp4")
    assert [s.reused for s in b.stages] == [False, False]  # new settings hash: redone, and it passed


@pytest.mark.parametrize(
    "damage", [b"", b"{not json", b'{"stage": "probe"}', b"\x00" * 10, b"[" * 100000, None]
)
def test_damaged_provenance_redoes_the_stage(tmp_path: Path, damage: bytes | None) -> None:
    video = make_video(tmp_path / "v" / "a.mp4")
    found = discover(str(video))
    work = tmp_path / "processed"
    run_pipeline(found.items, plan([ProbeStage(), DoubleStage()]), work, workers=1)
    out = item_dir(work, found.items[0].id) / "probe"
    if damage is None:
        (out / "probe.json").unlink()  # an output gone: the record alone does not count as done
    else:
        (out / "provenance.json").write_bytes(damage)
    summary = run_pipeline(found.items, plan([ProbeStage(), DoubleStage()]), work, workers=1)
    stages = summary.outcomes[0].stages
    # The redone probe has the same identity (version, settings, source), so double's input is the
    # same and double is kept: stages are pure functions of that identity.
    assert [(s.status, s.reused) for s in stages] == [("ok", False), ("ok", True)]
    assert read_provenance(out) is not None


def test_pool_gives_the_in_process_outputs_and_survives_a_dead_worker(tmp_path: Path) -> None:
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=1.0)
    make_video(folder / "b.mp4", seconds=2.0, shade=40)
    make_video(folder / "crash.mp4")
    found = discover(str(folder))
    stages = plan([CrashStage(), ProbeStage(), DoubleStage()])
    events: list[str] = []
    pooled = run_pipeline(
        found.items, stages, tmp_path / "pool", workers=2, on_event=lambda e: events.append(e.stage)
    )
    by_name = {Path(o.source).name: o for o in pooled.outcomes}
    crashed = by_name["crash.mp4"].failed
    assert crashed is not None
    assert "worker process died" in crashed.message
    assert [o.failed for n, o in by_name.items() if n != "crash.mp4"] == [None, None]
    assert {"probe", "double"} <= set(events)
    # The same items in this process give the same outputs (only the pid differs).
    rest = [i for i in found.items if i.videos[0].name != "crash.mp4"]
    run_pipeline(rest, plan([ProbeStage(), DoubleStage()]), tmp_path / "inline", workers=1)
    for item in rest:
        pool_dir, inline_dir = item_dir(tmp_path / "pool", item.id), item_dir(tmp_path / "inline", item.id)
        assert (pool_dir / "double" / "double.json").read_text() == (
            inline_dir / "double" / "double.json"
        ).read_text()
        pooled_probe = json.loads((pool_dir / "probe" / "probe.json").read_text())
        inline_probe = json.loads((inline_dir / "probe" / "probe.json").read_text())
        assert pooled_probe["videos"] == inline_probe["videos"]
        assert pooled_probe["pid"] != os.getpid() == inline_probe["pid"]


def test_second_run_on_the_same_root_is_refused(tmp_path: Path) -> None:
    import fcntl

    found = discover(str(make_video(tmp_path / "v" / "a.mp4")))
    work = tmp_path / "processed"
    work.mkdir()
    with (work / ".lock").open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # as a running telerig process holds it
        with pytest.raises(ProcessError, match="another telerig process is writing"):
            run_pipeline(found.items, plan([ProbeStage()]), work, workers=1)
    assert run_pipeline(found.items, plan([ProbeStage()]), work, workers=1).failures == []


def test_outputs_inside_the_input_folder_are_not_inputs(tmp_path: Path) -> None:
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4")
    found = discover(str(folder))
    run_pipeline(found.items, plan([ProbeStage(), CopyStage()]), folder / "out", workers=1)
    assert list((folder / "out").rglob("*.mp4"))  # the run wrote a video into the folder...
    assert [i.videos[0].name for i in discover(str(folder)).items] == ["a.mp4"]  # ...not an input


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("none", "returned NoneType, not a StageResult"),
        ("status", "returned status 'done'"),
        ("metrics", "ValueError: could not convert string to float"),
    ],
)
def test_a_stage_returning_garbage_fails_its_item_only(tmp_path: Path, kind: str, message: str) -> None:
    found = discover(str(_folder(tmp_path)))
    summary = run_pipeline(
        found.items, plan([OddStage()], {"odd": {"kind": kind}}), tmp_path / "p", workers=1
    )
    assert len(summary.outcomes) == 3
    for outcome in summary.outcomes:
        failed = outcome.failed
        assert failed is not None
        assert message in failed.message


def test_a_stage_with_failed_parts_is_redone_on_rerun_until_none_fail(tmp_path: Path) -> None:
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=1.0)
    found = discover(str(folder))
    work, ready = tmp_path / "processed", tmp_path / "model-is-up"
    stages = plan([PartlyStage()], {"partly": {"ready": str(ready)}})
    run_pipeline(found.items, stages, work, workers=1)
    first = _started(work, found.items[0].id, "partly")
    ready.touch()
    again = run_pipeline(found.items, stages, work, workers=1)
    assert again.stage_counts("partly")["ran"] == 1
    second = _started(work, found.items[0].id, "partly")
    assert second != first
    third = run_pipeline(found.items, stages, work, workers=1)
    assert third.stage_counts("partly")["reused"] == 1
    assert _started(work, found.items[0].id, "partly") == second


def test_a_persons_edit_of_a_stage_output_redoes_the_later_stages_only(tmp_path: Path) -> None:
    """The review page notes its segment edits with record_edit: the next run keeps the edited
    stage's output (the edit lives there) and redoes the stages that read it."""
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=1.0)
    found = discover(str(folder))
    work, item = tmp_path / "processed", found.items[0]
    stages = plan([ProbeStage(), DoubleStage()])
    run_pipeline(found.items, stages, work, workers=1)
    probe_at, double_at = _started(work, item.id, "probe"), _started(work, item.id, "double")
    assert record_edit(item_dir(work, item.id) / "probe", b'{"edited": true}')
    assert not record_edit(tmp_path / "never-ran", b"{}")
    again = run_pipeline(found.items, stages, work, workers=1)
    assert again.stage_counts("probe")["reused"] == 1
    assert again.stage_counts("double")["ran"] == 1
    assert _started(work, item.id, "probe") == probe_at
    assert _started(work, item.id, "double") != double_at
    third = run_pipeline(found.items, stages, work, workers=1)
    assert third.stage_counts("double")["reused"] == 1
