"""CPU priorities by role (runtime.priorities, telerig.priority) on the threads and processes of a
real rig run: the control thread above the station's other threads, the render process idle; and
a host that refuses raising a priority still records its episode and says what applied."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from typing import Any

import pytest

from telerig import priority
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]

_OTHER, _BATCH = os.SCHED_OTHER, os.SCHED_BATCH
_CAP_SYS_NICE = 23


def _can_raise() -> bool:
    """Whether this process may raise a priority (CAP_SYS_NICE in its effective set)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> _CAP_SYS_NICE & 1)
    return False


def _sched(pid: int, tid: int) -> tuple[int, int]:
    """``(policy, niceness)`` of thread ``tid`` of process ``pid``, as the kernel reports them."""
    fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[38]), int(fields[16])  # stat fields 41 (policy) and 19 (nice)


def _threads(pid: int) -> list[int]:
    return [int(t) for t in os.listdir(f"/proc/{pid}/task")]


def _render_processes() -> list[int]:
    """This process's children running a simulated camera's renderer."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError):  # a process that ended meanwhile
            stat = Path(f"/proc/{entry}/stat").read_text()
            parent = int(stat.rsplit(")", 1)[1].split()[1])
            if parent == os.getpid() and b"_render_worker" in Path(f"/proc/{entry}/cmdline").read_bytes():
                found.append(int(entry))
    return found


def _demo(**priorities: Any) -> RigConfig:
    raw: dict[str, Any] = load_rig("demo").model_dump(mode="json")
    raw["cameras"][0].update(width=160, height=120, fps=10.0)
    raw["runtime"] = {"priorities": priorities}
    raw["qa"] = {"after_commit": False}  # the priorities are under test, not a loaded host's gates
    return RigConfig.model_validate(raw)


def test_a_rig_run_puts_control_above_its_encoder_previews_and_renderer(tmp_path: Path) -> None:
    seen: dict[str, tuple[int, int]] = {}
    render: list[tuple[int, int]] = []
    main = threading.get_native_id()
    station = _sched(os.getpid(), main)  # (policy, niceness) of the station: ``nice pytest`` raises it
    lowered = max(10, station[1])

    def look(elapsed: float, total: float) -> None:
        if render:
            return
        names = {t.name: t.native_id for t in threading.enumerate() if t.native_id is not None}
        for name, tid in names.items():
            for prefix in ("control-", "encoder-", "preview-", "mcap-flush"):
                if name.startswith(prefix):
                    with contextlib.suppress(OSError):  # a thread that ended meanwhile
                        seen[prefix] = _sched(os.getpid(), tid)
        if "encoder-" in seen and "preview-" in seen:
            for pid in _render_processes():
                with contextlib.suppress(OSError):
                    render.extend(_sched(pid, tid) for tid in _threads(pid))

    with RigRuntime(_demo(), data_root=tmp_path) as runtime:
        result = runtime.run_episode(1.5, progress=look)
    assert result.status == "complete"
    raised = _can_raise()
    assert seen["control-"] == (_OTHER, -10 if raised else 0)
    for worker in ("encoder-", "preview-", "mcap-flush"):
        assert seen[worker] == (_BATCH, lowered), worker
    # The renderer and every thread of it (numpy's, llvmpipe's) below control; Mesa lowers its
    # shader-cache thread further itself (SCHED_BATCH nice 19), and lower stays lower.
    assert render, "no render process was found during the episode"
    assert all(policy == _BATCH and nice >= lowered for policy, nice in render), render
    assert any(nice == lowered for _, nice in render), render
    assert _sched(os.getpid(), main) == station  # the rest of the station is left as it was
    extra = EpisodeExtra.of(EpisodeStore(tmp_path).get(result.episode_id))
    assert extra.priorities["work"] == f"SCHED_BATCH nice {lowered}"
    assert extra.priorities["render"] == f"SCHED_BATCH nice {lowered}"
    assert extra.priorities["control"].startswith("SCHED_OTHER nice -10" if raised else "SCHED_OTHER nice 0")


def test_control_under_round_robin_and_priorities_off() -> None:
    """``control_realtime`` puts a control thread under SCHED_RR (where allowed); ``enabled: false``
    changes no thread."""
    got: dict[str, str] = {}

    def run() -> None:
        got["rr"] = priority.enter("control", priority.Priorities(control_realtime=7))
        got["rr_sched"] = priority.describe()
        got["off"] = priority.enter("work", priority.Priorities(enabled=False))
        got["off_sched"] = priority.describe()

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    if _can_raise():
        assert got["rr"] == got["rr_sched"] == "SCHED_RR priority 7"
    else:
        assert got["rr"].startswith("SCHED_OTHER nice 0 (refused: SCHED_RR 7: ")
    assert got["off"] == "unchanged"
    assert got["off_sched"] == got["rr_sched"]


_REFUSED_RIG = textwrap.dedent(
    """
    import json, os, sys
    from pathlib import Path
    from telerig.config.schema import RigConfig
    from telerig.runtime.process_settings import control_process
    from telerig.runtime.rig import RigRuntime
    from telerig.store.episodes import EpisodeStore
    from telerig.store.manifest_extra import EpisodeExtra

    rig = RigConfig.model_validate_json(sys.argv[1])
    root = Path(sys.argv[2])
    with control_process(), RigRuntime(rig, data_root=root) as runtime:
        result = runtime.run_episode(1.5)
    extra = EpisodeExtra.of(EpisodeStore(root).get(result.episode_id))
    print(json.dumps({"status": result.status, "priorities": extra.priorities}))
    """
)


def test_a_host_that_refuses_raising_priority_still_records_and_says_what_applied(tmp_path: Path) -> None:
    """Without CAP_SYS_NICE (dropped with setpriv where this test runs as root) the control thread
    cannot be raised: the episode is recorded all the same, one warning names the fix, and the
    manifest says the control thread stayed at nice 0."""
    command = [sys.executable, "-c", _REFUSED_RIG]
    if _can_raise():
        setpriv = shutil.which("setpriv")
        assert setpriv, "setpriv (util-linux) is needed to drop CAP_SYS_NICE: apt-get install util-linux"
        command = [setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", *command]
    rig = _demo(control_realtime=5).model_copy(update={"cameras": []})
    out = subprocess.run(
        [*command, rig.model_dump_json(), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["status"] == "complete"
    control = report["priorities"]["control"]
    station = os.getpriority(os.PRIO_PROCESS, 0)  # the child's, inherited (``nice pytest`` raises it)
    assert control.startswith(
        f"SCHED_OTHER nice {station} (refused: SCHED_RR 5: Operation not permitted; nice -10: "
    )
    lowered = max(10, station)
    assert report["priorities"]["work"] == f"SCHED_BATCH nice {lowered}"  # lowering needs no rights
    assert out.stderr.count(f"control threads run at SCHED_OTHER nice {station}") == 1
    assert "CAP_SYS_NICE" in out.stderr
