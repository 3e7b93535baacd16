"""``telerig session`` and ``telerig episodes``: help that names the real program and what each
command ends, one-line errors with a fix that works, and SIGTERM recorded as such (issue 11 finding 13)."""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path

import pytest
import yaml

from telerig.cli.main import main
from telerig.config import load_rig
from telerig.store.episodes import EpisodeStore


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_session_help_names_telerig_session_and_its_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["session", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "usage: telerig session" in out
    assert "python -m" not in out
    for command in ("start", "stop", "discard", "restart", "mark", "end"):
        assert command in out


def test_session_stop_help_says_it_ends_only_the_episode(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["session", "stop", "--help"])
    assert exit_.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "usage: telerig session stop" in out
    assert "the run goes on with the next episode" in out


def test_session_end_help_says_it_ends_the_session(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["session", "end", "--help"])
    assert "ends the session" in " ".join(capsys.readouterr().out.split())


def test_an_unreachable_broker_names_the_url_to_give_not_to_omit_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    url = f"mqtt://127.0.0.1:{_closed_port()}"
    assert main(["session", "stop", "--url", url, "--rig", "demo"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "give no URL" not in err
    assert f"cannot reach the rig's broker at {url}" in err
    assert "telerig run" in err
    assert "Traceback" not in err


def test_episodes_list_of_a_missing_data_root_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "nonexistent"
    assert main(["episodes", "list", "--data-root", str(missing)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"data root {missing} does not exist" in err


@pytest.mark.sim
@pytest.mark.broker
@pytest.mark.slow
def test_sigterm_is_recorded_as_terminated_not_as_ctrl_c(tmp_path: Path) -> None:
    raw = load_rig("demo").model_dump(mode="json")
    raw["cameras"] = []
    rig_file = tmp_path / "demo.yaml"
    rig_file.write_text(yaml.safe_dump(raw))
    root = tmp_path / "data"

    def terminate_once_recording() -> None:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            if any((root / ".incoming").glob("ep-*/episode.mcap")):
                time.sleep(0.5)
                signal.raise_signal(signal.SIGTERM)
                return
            time.sleep(0.05)

    previous = signal.getsignal(signal.SIGTERM)
    killer = threading.Thread(target=terminate_once_recording)
    killer.start()
    try:
        code = main(["run", str(rig_file), "--episodes", "1", "--duration", "30", "--data-root", str(root)])
    finally:
        killer.join()
        signal.signal(signal.SIGTERM, previous)
    assert code == 143
    (episode,) = EpisodeStore(root).list(include_unfinished=True)
    assert episode.status == "incomplete"
    assert episode.reason == "terminated (SIGTERM)"


def test_episodes_list_shows_the_size_of_an_interrupted_draft(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Issue 11 finding 6: a torn draft showed as 0.0 MB.
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="demo", task="pick", operator="alice")
    draft.mcap_path.write_bytes(b"\0" * 2_500_000)
    assert main(["episodes", "list", "--all", "--data-root", str(tmp_path)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if draft.id in line)
    # The data files on disk; the space a draft reserves for its final manifest (.reserve) is not data.
    data = [f for f in draft.dir.rglob("*") if f.is_file() and not f.name.startswith(".")]
    on_disk = sum(f.stat().st_size for f in data)
    assert on_disk > 2_500_000
    assert "interrupted" in row
    assert f"{on_disk / 1e6:.1f}" in row.split()
