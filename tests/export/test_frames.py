"""The export core on real demo episodes: schema from the recording, the frame grid, alignment errors."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from telerig.errors import ExportError
from telerig.export.frames import _keep_mask, episode_schema, load_episode, read_manifest
from telerig.export.schema import DatasetSchema, JointSpec
from telerig.record.align import load_streams
from telerig.store.episodes import EpisodeStore

UR5E_JOINTS = (
    "shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
    "wrist_1_joint", "wrist_2_joint", "wrist_3_joint",
)  # fmt: skip


@pytest.fixture(scope="module")
def episode_dir(demo_recording: Path) -> Path:
    return EpisodeStore(demo_recording).list(include_failures=True)[0].path


def test_schema_names_state_and_action_by_the_recorded_joint_order(episode_dir: Path) -> None:
    schema = episode_schema(episode_dir)
    assert schema.state_names == (*UR5E_JOINTS, "gripper")  # the measured opening: gripper_state
    assert schema.action_names[:6] == UR5E_JOINTS
    assert schema.action_names[-1] == "gripper"
    assert schema.parts("action")["arm0.joints"] == (0, 6)
    assert schema.robots == {"arm0": "ur5e_robotiq85"}
    assert [c.key for c in schema.cameras] == ["scene"]
    assert schema.cameras[0].shape == (480, 640, 3)
    assert schema.fps == 30


def test_schema_limits_come_from_the_robot_model(episode_dir: Path) -> None:
    schema = episode_schema(episode_dir)
    pan = schema.state[0]
    assert pan.lower == pytest.approx(-2 * math.pi, abs=1e-3)
    assert pan.upper == pytest.approx(2 * math.pi, abs=1e-3)
    assert 0 < pan.velocity < 10
    assert (schema.action[-1].lower, schema.action[-1].upper) == (0.0, 1.0)


def test_frames_sit_on_a_regular_grid_from_the_first_camera_frame(episode_dir: Path) -> None:
    frames = load_episode(episode_dir)
    assert frames.length > 60
    np.testing.assert_array_equal(frames.timestamp, np.arange(frames.length) / 30)
    steps = np.diff(frames.frame_ns)
    assert steps.min() >= 33_333_333
    assert steps.max() <= 33_333_334
    streams = load_streams(episode_dir / "episode.mcap")
    first_camera_frame = int(streams["telerig/v1/demo/scene/frames"].time_ns[0])
    assert frames.frame_ns[0] == first_camera_frame
    assert frames.state.shape == (frames.length, 7)
    assert frames.action.shape == (frames.length, 7)
    assert np.isfinite(frames.state).all()
    assert np.isfinite(frames.action).all()


def test_state_is_the_measured_joint_state_interpolated_at_each_frame(episode_dir: Path) -> None:
    frames = load_episode(episode_dir)
    stream = load_streams(episode_dir / "episode.mcap")["telerig/v1/demo/arm0/joint_state"]
    inside = (frames.frame_ns >= stream.time_ns[0]) & (frames.frame_ns <= stream.time_ns[-1]) & frames.valid
    for j in range(6):
        expected = np.interp(frames.frame_ns[inside], stream.time_ns, stream.fields["positions"][:, j])
        np.testing.assert_allclose(frames.state[inside, j], expected, atol=1e-5)


def test_action_holds_the_last_sent_command(episode_dir: Path) -> None:
    frames = load_episode(episode_dir)
    sent = load_streams(episode_dir / "episode.mcap")["telerig/v1/demo/arm0/joint_command_sent"]
    # A valid frame near the middle: a frame some stream missed (a loop that skipped a tick on a
    # loaded host) takes that stream's last valid sample instead (load_episode's documented fill).
    # How many frames are valid depends on the host's load (26 of 116 in a slow window), not on the
    # fill under test: a few are enough to pick one near the middle.
    usable = np.flatnonzero(frames.valid)
    assert usable.size >= 5, f"{usable.size} of {frames.length} frames valid"
    k = int(usable[usable.size // 2])
    i = int(np.searchsorted(sent.time_ns, frames.frame_ns[k], side="right")) - 1
    np.testing.assert_allclose(frames.action[k, :6], sent.fields["positions"][i], atol=1e-6)
    assert frames.raw_time_ns["arm0/joint_command_sent"][k] == sent.time_ns[i]


def test_alignment_error_is_carried_per_source_and_bounded_by_the_camera_period(episode_dir: Path) -> None:
    frames = load_episode(episode_dir)
    assert set(frames.alignment_error_ms) == {
        "arm0/joint_state", "arm0/gripper_state", "arm0/joint_command_sent", "arm0/gripper_command_sent",
        "scene/frames",
    }  # fmt: skip
    camera = frames.cameras["scene"]
    recorded = load_streams(episode_dir / "episode.mcap")["telerig/v1/demo/scene/frames"]
    nearest = np.abs(recorded.time_ns[:, None] - frames.frame_ns[None, :]).min(axis=0) / 1e6
    np.testing.assert_allclose(camera.error_ms, nearest, atol=1e-3)


def test_camera_frames_decode_once_per_dataset_frame_with_the_declared_shape(episode_dir: Path) -> None:
    frames = load_episode(episode_dir)
    images = list(frames.cameras["scene"].frames())
    assert len(images) == frames.length
    assert images[0].shape == (480, 640, 3)
    assert images[0].dtype == np.uint8


def test_normalized_values_map_the_limits_to_minus_one_and_one(episode_dir: Path) -> None:
    raw = load_episode(episode_dir)
    norm = load_episode(episode_dir, normalized=True)
    assert norm.schema.normalized
    np.testing.assert_allclose(norm.schema.denormalize(norm.action, "action"), raw.action, atol=1e-4)
    assert np.all(np.abs(norm.action) <= 1.0 + 1e-6)


def test_trimming_cuts_the_span_and_keeps_timestamps_regular(episode_dir: Path) -> None:
    full = load_episode(episode_dir)
    start = (full.frame_ns[0] - full.manifest.start_ns) / 1e9
    cut = load_episode(episode_dir, trim_s=[(start, start + 1.0)])
    assert full.length - cut.length == 30
    np.testing.assert_array_equal(cut.timestamp, np.arange(cut.length) / 30)
    assert cut.frame_ns[0] == full.frame_ns[30]
    assert cut.trimmed_s == ((start, start + 1.0),)


def test_a_frame_on_a_spans_end_is_kept_whatever_the_episodes_offset() -> None:
    # Compared in float seconds, the frame a whole second after a span's first one fell inside the
    # span for about 1 offset in 15 (the last bit of the division): trimming 1 s cut 31 frames.
    for offset_ns in range(0, 5_000_000_000, 7_777_777):
        grid = 1_000 + offset_ns + np.round(np.arange(61) * (1e9 / 30)).astype(np.int64)
        start = offset_ns / 1e9
        keep = _keep_mask(grid, 1_000, [(start, start + 1.0)])
        assert int((~keep).sum()) == 30, offset_ns
        assert keep[30]


def test_trimming_everything_is_refused(episode_dir: Path) -> None:
    with pytest.raises(ExportError, match="leaves no frame"):
        load_episode(episode_dir, trim_s=[(-1e9, 1e9)])


def test_a_directory_without_manifest_is_not_an_episode(tmp_path: Path) -> None:
    with pytest.raises(ExportError, match=r"no manifest\.json"):
        read_manifest(tmp_path)


def test_a_garbage_manifest_is_one_line(tmp_path: Path, episode_dir: Path) -> None:
    bad = tmp_path / "ep"
    shutil.copytree(episode_dir, bad)
    (bad / "manifest.json").write_text('{"id": 3, ' + "x" * 10_000)
    with pytest.raises(ExportError, match="unreadable manifest") as info:
        load_episode(bad)
    assert "\n" not in str(info.value)


def test_an_episode_without_fingerprint_is_refused(tmp_path: Path, episode_dir: Path) -> None:
    bad = tmp_path / "ep"
    shutil.copytree(episode_dir, bad)
    manifest = json.loads((bad / "manifest.json").read_text())
    del manifest["extra"]["fingerprint"]
    (bad / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ExportError, match="no rig fingerprint"):
        episode_schema(bad)


# --- schema ----------------------------------------------------------------------------------------


def _schema(**changes: object) -> DatasetSchema:
    base: dict[str, object] = {
        "rig": "r", "fingerprint": "abc", "fps": 30, "robots": {"a": "m"},
        "state": (JointSpec("j", "a", "joints", -1.0, 1.0, 2.0),),
        "action": (JointSpec("j", "a", "joints", -1.0, 1.0, 2.0), JointSpec("gripper", "a", "gripper", 0, 1)),
    }  # fmt: skip
    base.update(changes)
    return DatasetSchema(**base)  # type: ignore[arg-type]


def test_schema_json_round_trips() -> None:
    schema = _schema(state=(JointSpec("x", "a", "base"),))
    assert DatasetSchema.loads(schema.dumps()) == schema
    assert json.loads(schema.dumps())["state"][0]["lower"] is None


@pytest.mark.parametrize(
    ("change", "field"),
    [({"fingerprint": "other"}, "fingerprint"), ({"fps": 15}, "fps"), ({"state": ()}, "state")],
)
def test_a_different_dataset_is_refused_naming_what_differs(change: dict[str, object], field: str) -> None:
    with pytest.raises(ExportError, match=f"dataset's {field} is"):
        _schema().check_compatible(_schema(**change))


@pytest.mark.parametrize(
    "text",
    ["", "[]", '{"version": 99}', '{"version": 1, "rig": "r"}', '{"version": 1, "fps": "x"}', "\xff"],
)
def test_garbage_schema_files_fail_in_one_line(text: str) -> None:
    with pytest.raises(ExportError) as info:
        DatasetSchema.loads(text)
    assert "\n" not in str(info.value)


def test_repeated_entry_names_are_refused() -> None:
    with pytest.raises(ExportError, match="repeat"):
        _schema(state=(JointSpec("j", "a", "joints"), JointSpec("j", "b", "joints")))


def test_entries_without_finite_limits_are_not_normalized() -> None:
    schema = _schema(action=(JointSpec("j", "a", "joints", -2.0, 2.0), JointSpec("vx", "a", "base")))
    out = schema.normalize(np.array([[1.0, 5.0]]), "action")
    np.testing.assert_allclose(out, [[0.5, 5.0]])


# --- several robots ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bimanual_episode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One short episode of the shipped bimanual rig (two UR5e arms, three cameras)."""
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("bimanual") / "data"
    cmd = [
        sys.executable, "-m", "telerig.cli.main", "run", "bimanual",
        "--episodes", "1", "--duration", "2.5", "--data-root", str(root),
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return EpisodeStore(root).list(include_failures=True)[0].path


def test_a_bimanual_episode_exports_one_vector_with_named_parts_and_a_key_per_camera(
    bimanual_episode: Path,
) -> None:
    frames = load_episode(bimanual_episode)
    schema = frames.schema
    assert schema.parts("action") == {
        "left.joints": (0, 6), "left.gripper": (6, 7), "right.joints": (7, 13), "right.gripper": (13, 14),
    }  # fmt: skip
    assert schema.action_names[0] == "left.left_shoulder_pan_joint"
    assert schema.action_names[13] == "right.gripper"
    assert [c.key for c in schema.cameras] == ["left_wrist", "right_wrist", "scene"]
    assert set(frames.cameras) == {"left_wrist", "right_wrist", "scene"}
    assert frames.action.shape == (frames.length, 14)
    assert frames.state.shape == (frames.length, len(schema.state))
