"""The telerig command: rig checks, episode listing, one-line errors with exit code 2."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from telerig.cli.main import main
from telerig.store.episodes import EpisodeStore


def test_rig_check_accepts_the_demo_rig(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "check", "demo"]) == 0
    assert "ok rig 'demo'" in capsys.readouterr().out


def test_rig_check_reports_a_bad_rig_in_one_line_with_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "bad.yaml"
    rig.write_text("name: bad\ndevices: [{id: d, type: glove9}]\nrobots: []\nbindings: []\n")
    assert main(["rig", "check", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "devices[0].type: unknown device type 'glove9'. Valid:" in err


def test_rig_list_names_the_shipped_rigs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "list"]) == 0
    assert "demo" in capsys.readouterr().out


def test_episodes_list_and_show(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="demo", task="stack", operator="ana")
    draft.mcap_path.write_bytes(b"x")
    manifest = draft.commit({})
    store.begin(rig="demo", task="crashed", operator="ana")  # left in .incoming
    assert main(["episodes", "list", "--data-root", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert manifest.id in out
    assert "crashed" not in out
    assert main(["episodes", "list", "--all", "--data-root", str(tmp_path)]) == 0
    assert "interrupted" in capsys.readouterr().out
    assert main(["episodes", "show", manifest.id, "--data-root", str(tmp_path)]) == 0
    assert "episode.mcap" in capsys.readouterr().out


def test_episodes_show_unknown_id_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["episodes", "show", "ep-nope", "--data-root", str(tmp_path)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_no_command_prints_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: telerig" in capsys.readouterr().out


def test_calibrate_rejects_moving_hands_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from telerig.devices.udp_vr.fake import FakeVrSender

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    rig = tmp_path / "vr.yaml"
    rig.write_text(
        "name: vr\n"
        f"devices: [{{id: quest, type: udp_vr, host: 127.0.0.1, port: {port}}}]\n"
        "robots: []\nbindings: []\n"
    )
    sender = FakeVrSender(port, rate_hz=90.0)
    sender.start()
    try:
        code = main(
            [
                "calibrate",
                "--operator",
                "ana",
                "--rig",
                str(rig),
                "--duration",
                "1.5",
                "--data-root",
                str(tmp_path),
            ]
        )
    finally:
        sender.stop()
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1
    assert "moved during calibration" in err or "turned during calibration" in err
    assert not (tmp_path / "operators" / "ana.json").exists()


def test_calibrate_unknown_device_names_the_available_ones(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--operator", "ana", "--device", "glove7"]) == 2
    assert "Available: vr0" in capsys.readouterr().err


def test_rig_check_refuses_a_binding_target_no_retargeter_drives(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from telerig.config import shipped_rig_path

    rig = tmp_path / "tentacle.yaml"
    rig.write_text(shipped_rig_path("demo").read_text().replace("target: arm", "target: tentacle"))
    assert main(["rig", "check", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "bindings[0].target: retargeter 'absolute_pose' cannot drive target 'tentacle'. Valid: arm" in err


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"name: caf\xe9\n", "line 1: not UTF-8 text (byte 0xe9)"),
        (b"name: demo\n\x00\n", "line 2: invalid YAML"),
        (None, "is a directory"),
    ],
)
def test_rig_check_reports_unreadable_files_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, expected: str
) -> None:
    rig = tmp_path / "rig.yaml"
    if content is None:
        rig.mkdir()
    else:
        rig.write_bytes(content)
    assert main(["rig", "check", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert expected in err
