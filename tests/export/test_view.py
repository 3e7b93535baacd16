"""``telerig view``: a real demo episode as a Rerun .rrd, read back with rerun's own reader; the
episode's MCAP log stays readable the way Foxglove reads it (schemas, channels, encodings)."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap.records import Schema

from telerig.cli.main import main
from telerig.export.view import TIMELINE, view_episode
from telerig.ir.mcap_log import read_log
from telerig.ir.types import CameraFrame
from telerig.store.episodes import EpisodeStore
from telerig.store.qa_file import QaRecord, write_qa

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_UR5E_REACH_M = 0.85 + 0.25  # the arm's reach plus the gripper to its grasp point


@pytest.fixture(scope="module")
def demo_episode(demo_recording: Path) -> tuple[Path, str]:
    """Data root and id of the first episode the shared ``demo_recording`` fixture recorded with
    ``telerig run demo`` (a real rig run; read only)."""
    first = EpisodeStore(demo_recording).list(include_failures=True)[0]  # gates may have rejected it
    return demo_recording, first.id


def _read_rrd(path: Path) -> tuple[Any, dict[str, int], dict[str, list[Any]]]:
    """(recordings, rows per temporal entity, static chunks per entity) of an .rrd, by rerun's reader."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    rows: Counter[str] = Counter()
    static: dict[str, list[Any]] = {}
    for chunk in reader.stream():
        if chunk.is_static:
            static.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
        else:
            assert chunk.timeline_names == [TIMELINE] or TIMELINE in chunk.timeline_names
            rows[chunk.entity_path] += chunk.num_rows
    return reader.recordings(), dict(rows), static


def _temporal(path: Path, entity: str) -> list[Any]:
    from rerun.chunk import RrdReader

    return [
        c.to_record_batch() for c in RrdReader(path).stream() if c.entity_path == entity and not c.is_static
    ]


def test_view_writes_an_rrd_rerun_reads_back_with_every_sample(
    demo_episode: tuple[Path, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, episode_id = demo_episode
    out = tmp_path / "ep.rrd"
    assert main(["view", episode_id, "--data-root", str(root), "--out", str(out)]) == 0
    assert "video: asset" in capsys.readouterr().out
    recordings, rows, static = _read_rrd(out)
    assert [(r.application_id, r.recording_id) for r in recordings] == [("telerig", episode_id)]

    # Every recorded sample of the MCAP log is a row, per joint and kind.
    episode_dir = EpisodeStore(root).episode_dir(episode_id)
    counts: Counter[str] = Counter()
    names: dict[str, tuple[str, ...]] = {}
    first_state_ns = None
    frames: list[CameraFrame] = []
    for entry in read_log(episode_dir / "episode.mcap"):
        stream = entry.topic.rsplit("/", 1)[-1]
        counts[stream] += 1
        names.setdefault(stream, getattr(entry.sample, "names", ()))
        if stream == "joint_state" and first_state_ns is None:
            first_state_ns = entry.sample.stamp.capture_ns
        if isinstance(entry.sample, CameraFrame):
            frames.append(entry.sample)
    assert counts["joint_state"] > 100
    assert len(names["joint_state"]) == 6
    for stream, kind in (
        ("joint_state", "measured"),
        ("joint_command_sent", "sent"),
        ("joint_command_requested", "requested"),
    ):
        for joint in names["joint_state"]:
            assert rows[f"/robots/arm0/joints/{joint}/{kind}"] == counts[stream], (joint, kind)
    assert rows["/robots/arm0/gripper/sent"] == counts["gripper_command_sent"]
    assert rows["/robots/arm0/gripper/requested"] == counts["gripper_command_requested"]
    assert counts["gripper_state"] > 100  # the simulated arm records its gripper and wrist F/T
    assert rows["/robots/arm0/gripper/measured"] == counts["gripper_state"]
    for name in ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z", "force_norm"):
        assert rows[f"/robots/arm0/wrench/{name}"] == counts["wrench"]

    # Joint rows sit at the samples' capture times.
    (batch, *_) = _temporal(out, f"/robots/arm0/joints/{names['joint_state'][0]}/measured")
    assert batch.column(TIMELINE)[0].value == first_state_ns

    # The video: the MP4's bytes as an asset and a frame reference per video frame (also one whose
    # frame record a loaded recorder lost), at the frame's capture time; its video timestamp is the
    # capture time relative to the first frame (the pts, in microseconds).
    with av.open(str(episode_dir / "cameras" / "scene.mp4")) as container:
        packets = np.array(sorted(p.pts for p in container.demux(video=0) if p.pts is not None))
    assert rows["/cameras/scene"] == len(packets) >= len(frames) > 5
    (asset,) = static["/cameras/scene"]
    blob = asset.column("AssetVideo:blob")[0].as_py()[0]
    assert bytes(blob) == (episode_dir / "cameras" / "scene.mp4").read_bytes()
    refs = _temporal(out, "/cameras/scene")
    video_ts = np.concatenate(
        [np.array(b.column("VideoFrameReference:timestamp").to_pylist()).ravel() for b in refs]
    )
    capture = np.concatenate([b.column(TIMELINE).cast("int64").to_numpy() for b in refs])
    np.testing.assert_array_equal(video_ts // 1000, packets)
    for frame in frames:  # the frame records' capture times, to the pts' microsecond
        assert abs(capture[frame.frame_index] - frame.stamp.capture_ns) < 1000

    # The end effector's path: one point per joint state, within the UR5e's reach, and it moves
    # (the demo task carries the cube 23 cm to the right).
    (strip,) = static["/robots/arm0/ee_path"]
    path = np.array(strip.column("LineStrips3D:strips")[0].as_py()[0])
    assert path.shape == (counts["joint_state"], 3)
    assert rows["/robots/arm0/ee"] == counts["joint_state"]
    assert np.linalg.norm(path, axis=1).max() < _UR5E_REACH_M
    assert np.ptp(path, axis=0).max() > 0.1


def test_gate_markers_come_from_qa_json(demo_episode: tuple[Path, str], tmp_path: Path) -> None:
    root, episode_id = demo_episode
    episode_dir = tmp_path / episode_id
    shutil.copytree(EpisodeStore(root).episode_dir(episode_id), episode_dir)
    start = json.loads((episode_dir / "manifest.json").read_text())["start_ns"]
    verdicts = [
        {"gate": "idle", "passed": True, "value": 0.2, "threshold": 0.6, "unit": "fraction", "events": []},
        {
            "gate": "joint_limits",
            "passed": False,
            "value": 0.09,
            "threshold": 0.05,
            "unit": "fraction",
            "detail": "wrist_2_joint 9 % beyond its limit at t=1.0 s",
            "events": [1.0, 2.5],
        },
    ]
    report = {"format": 1, "verdicts": verdicts, "idle_segments": [[0.0, 0.4]]}
    write_qa(episode_dir, QaRecord(episode_id=episode_id, checked_ns=1, thresholds_hash="x", report=report))
    summary = view_episode(episode_dir, tmp_path / "qa.rrd")
    _, rows, _ = _read_rrd(tmp_path / "qa.rrd")
    assert rows["/qa/idle"] == 1
    assert rows["/qa/joint_limits"] == 2
    assert rows["/qa/idle_segments"] == 1
    (batch,) = _temporal(tmp_path / "qa.rrd", "/qa/joint_limits")
    times = batch.column(TIMELINE).cast("int64").to_pylist()
    assert times == [start + 10**9, start + 2_500_000_000]  # events count from the episode start
    text = batch.column("TextLog:text").to_pylist()[0][0]
    assert text.startswith("joint_limits: FAIL, value 0.09 fraction (threshold 0.05 fraction): wrist_2_joint")
    assert batch.column("TextLog:level").to_pylist()[0] == ["WARN"]
    assert summary.entities["qa/joint_limits"] == 2


def test_an_unknown_episode_is_one_line_with_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["view", "ep-20200101-000000-abcd", "--data-root", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "ep-20200101-000000-abcd" in err


class _JsonDecoderFactory(McapDecoderFactory):
    """Decodes ``json`` channels as Foxglove does: each message is one JSON document."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


def test_the_episode_mcap_opens_the_way_foxglove_reads_it(demo_episode: tuple[Path, str]) -> None:
    """Foxglove reads an MCAP through its summary (schemas, channels, statistics, chunk indexes) and
    decodes each channel by its message encoding: protobuf channels need a schema whose data is a
    FileDescriptorSet holding the named message (what mcap-protobuf-support's decoder, like
    Foxglove's, builds the message class from); JSON channels are self-describing (the MCAP registry
    lets their schema be absent) and every message must parse as JSON."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet
    from mcap_protobuf.decoder import DecoderFactory

    root, episode_id = demo_episode
    mcap = EpisodeStore(root).episode_dir(episode_id) / "episode.mcap"
    with open(mcap, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _JsonDecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        assert summary.chunk_indexes, "no chunk indexes: Foxglove cannot seek"
        topics = {c.topic for c in summary.channels.values()}
        for stream in ("joint_state", "joint_command_sent", "joint_command_requested", "frames", "residual"):
            assert any(t.endswith("/" + stream) for t in topics), stream
        for channel_id, channel in summary.channels.items():
            assert summary.statistics.channel_message_counts.get(channel_id, 0) > 0, channel.topic
            if channel.message_encoding == "protobuf":
                schema = summary.schemas[channel.schema_id]
                assert schema.encoding == "protobuf", channel.topic
                fds = FileDescriptorSet.FromString(schema.data)
                declared = {
                    f"{file.package}.{m.name}" if file.package else m.name
                    for file in fds.file
                    for m in file.message_type
                }
                assert schema.name in declared, channel.topic
            else:
                assert channel.message_encoding == "json", channel.topic
                assert channel.schema_id == 0 or summary.schemas[channel.schema_id].encoding == "jsonschema"
        decoded: Counter[str] = Counter()
        for _, channel, message, value in reader.iter_decoded_messages(log_time_order=False):
            decoded[channel.topic] += 1
            if channel.message_encoding == "protobuf":
                assert value.ByteSize() == len(message.data)
    assert decoded == {
        c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()
    }
