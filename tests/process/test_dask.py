"""``--cluster``: the same per-item function on a real Dask distributed cluster (LocalCluster with
worker processes, bound to 127.0.0.1, no dashboard) gives the outputs the local run gives, records a
failing item and goes on, and an unreachable scheduler is a one-line error."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from core_kit import make_video
from core_stages import DoubleStage, ProbeStage

from telerig.errors import ProcessError
from telerig.process.items import discover
from telerig.process.run import item_dir, plan, run_pipeline

try:
    from distributed import LocalCluster
except ImportError:  # the suite needs it: fail with the fix, never skip
    pytest.fail("Dask distributed is missing: pip install -c constraints.txt -e '.[process]'")


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    with LocalCluster(  # type: ignore[no-untyped-call]
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        silence_logs=40,
    ) as local:
        yield str(local.scheduler_address)


def test_cluster_gives_the_local_outputs(tmp_path: Path, cluster: str) -> None:
    assert cluster.startswith("tcp://127.0.0.1:")
    folder = tmp_path / "videos"
    make_video(folder / "a.mp4", seconds=1.0)
    make_video(folder / "b.mp4", seconds=1.5, shade=60)
    (folder / "garbage.mp4").write_bytes(os.urandom(2000))
    found = discover(str(folder))
    stages = plan([ProbeStage(), DoubleStage()])
    remote = run_pipeline(found.items, stages, tmp_path / "dask", cluster=cluster)
    local = run_pipeline(found.items, stages, tmp_path / "local", workers=1)
    assert [(o.item_id, [(s.name, s.status) for s in o.stages]) for o in remote.outcomes] == [
        (o.item_id, [(s.name, s.status) for s in o.stages]) for o in local.outcomes
    ]
    assert remote.total("clips") == local.total("clips") == 2
    assert remote.hours_in == pytest.approx(local.hours_in)
    for item in found.items:
        if item.videos[0].name == "garbage.mp4":
            continue
        a, b = item_dir(tmp_path / "dask", item.id), item_dir(tmp_path / "local", item.id)
        assert (a / "double" / "double.json").read_text() == (b / "double" / "double.json").read_text()
        on_worker = json.loads((a / "probe" / "probe.json").read_text())
        assert on_worker["videos"] == json.loads((b / "probe" / "probe.json").read_text())["videos"]
        assert on_worker["pid"] != os.getpid()  # ran in a worker process
    failed = [o for o in remote.outcomes if o.failed is not None]
    assert [Path(o.source).name for o in failed] == ["garbage.mp4"]
    # A re-run on the cluster skips what the cluster did.
    again = run_pipeline(found.items, stages, tmp_path / "dask", cluster=cluster)
    assert again.stage_counts("double") == {"ran": 0, "reused": 2, "empty": 0, "failed": 0}


def test_unreachable_scheduler_is_one_line(tmp_path: Path) -> None:
    video = make_video(tmp_path / "a.mp4")
    found = discover(str(video))
    with pytest.raises(ProcessError, match="cannot reach the Dask scheduler") as info:
        run_pipeline(found.items, plan([ProbeStage()]), tmp_path / "p", cluster="tcp://127.0.0.1:9")
    assert "\n" not in str(info.value)
    for bad in ("localhost", "http://127.0.0.1:80", "tcp://[::1", "tcp://127.0.0.1:99999", "x" * 5000):
        with pytest.raises(ProcessError, match="expected tcp://HOST:PORT"):
            run_pipeline(found.items, plan([ProbeStage()]), tmp_path / "p", cluster=bad)
