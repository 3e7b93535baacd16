"""``telerig episodes plot``: a real demo episode becomes a valid PNG of the expected size with a
subplot per joint, the gripper and the residuals; gate events are red lines; bad input is one line."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg

from telerig.cli.main import main
from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import GripperCommand, JointCommand, JointState, RetargetResidual, Sample, Stamp
from telerig.qa.plot import DEFAULT_WIDTH_PX, plot_episode, plot_size
from telerig.qa.report import GateVerdict, QaReport
from telerig.store.episodes import EpisodeStore
from telerig.store.qa_file import QaRecord, write_qa

T0 = 1_800_000_000_000_000_000
UR5E_JOINTS = (
    "shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
    "wrist_1_joint", "wrist_2_joint", "wrist_3_joint",
)  # fmt: skip


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    assert data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _red_pixels(path: Path) -> int:
    rgb = mpimg.imread(path)[..., :3]
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    # Red at 70 % over white is (1, 0.3, 0.3); orange (1, 0.5, 0.05) and the residual colours are not.
    return int(np.sum((r > 0.9) & (g < 0.45) & (b < 0.45) & (np.abs(g - b) < 0.1)))


@pytest.fixture
def demo_episode(demo_recording: Path, tmp_path: Path) -> Path:
    """A copy of the real demo recording's data root (a test may overwrite an episode's qa.json). Its
    episodes may lie in ``failures``: on a loaded host the gates reject them (sync, teleop faults)."""
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    return root


def test_plot_of_a_real_episode_is_a_png_of_the_expected_size(
    demo_episode: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (first, *_) = EpisodeStore(demo_episode).list(include_failures=True)
    out = tmp_path / "plots" / "ep.png"
    assert main(["episodes", "plot", first.id[:-2], "--data-root", str(demo_episode), "--out", str(out)]) == 0
    # 6 UR5e joints, the gripper, the IK residual: 8 subplots in 2 columns of 4 rows.
    _, rows, width, height = plot_size(8)
    assert rows == 4
    assert _png_size(out) == (DEFAULT_WIDTH_PX, height) == (width, height)
    pixels = mpimg.imread(out)
    assert pixels.shape[:2] == (height, width)
    assert float(pixels[..., :3].std()) > 0.05  # something is drawn
    assert f"wrote {out} ({width}x{height} px): 8 subplot(s)" in " ".join(capsys.readouterr().out.split())
    summary = plot_episode(first.path, tmp_path / "again.png")
    assert summary.panels[:6] == tuple(f"arm0 / {j}" for j in UR5E_JOINTS)
    assert summary.panels[6:] == ("arm0 / gripper", "IK residual")
    assert summary.series[0] == ("requested", "sent", "measured")
    assert summary.series[7] == ("arm0 position",)  # position_error_m; the [rad] error is left out


def test_failed_gate_events_are_red_lines(demo_episode: Path, tmp_path: Path) -> None:
    (first, *_) = EpisodeStore(demo_episode).list(include_failures=True)
    plain = plot_episode(first.path, tmp_path / "plain.png", report=QaReport(first.id, (), 0.0))
    assert plain.gate_events == ()
    verdicts = (
        GateVerdict("sync", False, 80.0, 50.0, "ms", "gap of 80 ms", (1.0, 2.5)),
        GateVerdict("idle", True, 0.2, 0.6, "fraction", "20 % idle", (0.0,)),
        GateVerdict("fall", None, None, 0.5, "fraction", "no base"),
    )
    report = QaReport(first.id, verdicts, 0.2)
    write_qa(
        first.path, QaRecord(episode_id=first.id, checked_ns=0, thresholds_hash="t", report=report.to_json())
    )
    marked = plot_episode(first.path, tmp_path / "marked.png")
    assert marked.gate_events == (("sync", 1.0, True), ("sync", 2.5, True), ("idle", 0.0, False))
    # Two red lines through 8 subplots of ~130 px each: well over a thousand red pixels more.
    assert _red_pixels(tmp_path / "marked.png") > _red_pixels(tmp_path / "plain.png") + 1000


def test_width_option_sets_the_image_width(demo_episode: Path, tmp_path: Path) -> None:
    (first, *_) = EpisodeStore(demo_episode).list(include_failures=True)
    out = tmp_path / "narrow.png"
    assert (
        main(
            [
                "episodes",
                "plot",
                first.id,
                "--data-root",
                str(demo_episode),
                "--out",
                str(out),
                "--width",
                "900",
            ]
        )
        == 0
    )
    assert _png_size(out) == (900, plot_size(8)[3])


def _write(log: McapLog, topic: str, sample: Sample) -> None:
    ns = sample.stamp.capture_ns
    log.write(f"telerig/v1/test/{topic}", wire.encode(sample), log_time_ns=ns, publish_time_ns=ns)


@pytest.mark.parametrize("old_json", [False, True], ids=["typed", "json_before_issue_18"])
def test_gripper_state_is_the_measured_gripper_curve(tmp_path: Path, old_json: bool) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="grip", operator="op", start_ns=T0)
    with McapLog(draft.mcap_path) as log:
        for i in range(100):
            ns = T0 + i * 10_000_000
            stamp = Stamp("arm0", i, ns, ns)
            q = np.array([0.01 * i, -0.01 * i])
            _write(log, "arm0/joint_command_sent", JointCommand(stamp, ("a", "b"), q))
            _write(log, "arm0/joint_state", JointState(stamp, ("a", "b"), q, np.zeros(2)))
            _write(log, "arm0/gripper_command_sent", GripperCommand(stamp, 1.0 - 0.01 * i))
            _write(log, "arm0/gripper_state", GripperCommand(stamp, 1.0 - 0.009 * i))
            if old_json:  # how episodes recorded the residual before issue 18
                residual = {"capture_ns": ns, "flagged": False, "position_error_m": 0.001 * i}
                log.write_json("telerig/v1/test/arm0/residual", json.dumps(residual).encode(), log_time_ns=ns)
            else:  # typed; a non-finite error is left out of the curve
                error = 0.001 * i if i != 50 else float("inf")
                metrics = ("position_error_m", "orientation_error_rad")
                _write(log, "arm0/residual", RetargetResidual(stamp, False, metrics, (error, 0.1)))
    draft.commit(end_ns=T0 + 10**9)
    summary = plot_episode(draft.dir, tmp_path / "g.png")
    assert summary.panels == ("arm0 / a", "arm0 / b", "arm0 / gripper", "IK residual")
    assert summary.series == (
        ("sent", "measured"),
        ("sent", "measured"),
        ("sent", "measured"),
        ("arm0 position",),
    )
    assert _png_size(tmp_path / "g.png") == plot_size(4)[2:]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["ep-1999"], "episode 'ep-1999' not found in"),
        (["ep-", "--width", "wide"], "--width 'wide' is not an image width"),
        (["ep-", "--width", "50"], "--width '50' is not an image width"),
        (["ep-", "--out", "plot.jpg"], "--out plot.jpg must name a .png file"),
    ],
)
def test_bad_arguments_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="t", operator="op", start_ns=T0)
    draft.commit(end_ns=T0 + 10**9)
    assert main(["episodes", "plot", *args, "--data-root", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert message in err


def test_episode_without_streams_is_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="test", task="t", operator="op", start_ns=T0)
    with McapLog(draft.mcap_path):
        pass
    manifest = draft.commit(end_ns=T0 + 10**9)
    assert (
        main(
            ["episodes", "plot", manifest.id, "--data-root", str(tmp_path), "--out", str(tmp_path / "x.png")]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "recorded no joint, gripper or residual stream; nothing to plot" in err
    assert not (tmp_path / "x.png").exists()
