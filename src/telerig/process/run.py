"""The pipeline run: every item through the stages in order, finished work skipped, failures kept.

One function, :func:`process_item`, takes an item through the stages; it runs in this process
(``workers=1``), on a local process pool (forkserver or spawned workers: no state inherited
from a threaded parent) or on the workers of a Dask distributed cluster
(``cluster="tcp://host:8786"``; the same function, so the outputs are the same).

Each stage's output directory gets a ``provenance.json`` (see
:class:`~telerig.process.stage.Provenance`); a stage is skipped when its record names the same
stage version, settings, source hash and upstream outputs, and its outputs still exist. A stage
that raises or reports ``failed`` ends that item (later stages are not run), is recorded in
``failures.json`` and the summary, and the batch goes on.

Stage metrics the summary adds up (a stage reports the ones it knows): ``seconds_in``,
``seconds_kept``, ``segments``, ``clips``, ``clips_annotated``.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import datetime
import logging
import multiprocessing
import multiprocessing.util
import os
import shutil
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

from telerig.errors import DependencyError, ProcessError
from telerig.process.stage import (
    Item,
    Provenance,
    Stage,
    StageContext,
    StageResult,
    hash_upstream,
    host_name,
    read_provenance,
    settings_hash,
    write_json_atomic,
    write_provenance,
)

if TYPE_CHECKING:
    # Discovery pulls in the episode store (and its SQL index); a pool worker never needs it.
    from telerig.process.items import Skipped

__all__ = [
    "Closable",
    "Finisher",
    "ItemOutcome",
    "PlannedStage",
    "RunSummary",
    "StageEvent",
    "StageOutcome",
    "item_dir",
    "plan",
    "process_item",
    "run_pipeline",
]

_log = logging.getLogger("telerig.process.run")

FAILURES_FILE = "failures.json"
SUMMARY_FILE = "summary.json"
LOCK_FILE = ".lock"
_MESSAGE_CHARS = 500


@runtime_checkable
class Finisher(Protocol):
    """A stage that also builds something over all items once they are done (the layout's index)."""

    def finish(self, work_root: Path, item_ids: Sequence[str], settings: Any) -> None:
        """Called once in the driver after every item ran (or was skipped)."""
        ...


@runtime_checkable
class Closable(Protocol):
    """A stage holding resources across items (the filter's hand detector process)."""

    def close(self) -> None:
        """Release them; idempotent."""
        ...


@dataclass(frozen=True)
class PlannedStage:
    """A stage with the settings it runs with (and their hash, part of its provenance)."""

    stage: Stage
    settings: Any
    settings_hash: str


def plan(stages: Iterable[Stage], settings: Mapping[str, Any] | None = None) -> tuple[PlannedStage, ...]:
    """Pair each stage with its settings (``settings[stage.name]``, ``None`` when absent).

    Raises:
        ProcessError: Two stages share a name (their outputs would share a directory).
    """
    out: list[PlannedStage] = []
    seen: set[str] = set()
    for stage in stages:
        if stage.name in seen:
            raise ProcessError(f"stage {stage.name!r} is listed twice; each stage runs once per item")
        seen.add(stage.name)
        value = (settings or {}).get(stage.name)
        out.append(PlannedStage(stage, value, settings_hash(value)))
    return tuple(out)


@dataclass(frozen=True)
class StageOutcome:
    """What happened to one stage of one item: ``reused`` when its earlier output was kept."""

    name: str
    status: Literal["ok", "empty", "failed"]
    reused: bool
    metrics: Mapping[str, float]
    message: str = ""
    seconds: float = 0.0


@dataclass(frozen=True)
class ItemOutcome:
    """One item's run: its stages in order (up to the failed one, if any)."""

    item_id: str
    kind: str
    source: str
    stages: tuple[StageOutcome, ...]
    host: str
    seconds_in: float | None = None

    @property
    def failed(self) -> StageOutcome | None:
        """The stage that failed, or ``None``."""
        return next((s for s in self.stages if s.status == "failed"), None)


@dataclass(frozen=True)
class StageEvent:
    """Progress of one item in one stage: ``fraction`` 0..1, ``done`` once the stage returned."""

    item_id: str
    stage: str
    fraction: float
    done: bool = False
    status: str = ""


@dataclass
class RunSummary:
    """The batch in numbers, as the summary table shows them."""

    work_root: Path
    outcomes: list[ItemOutcome] = field(default_factory=list)
    skipped_inputs: tuple[Skipped, ...] = ()
    seconds: float = 0.0

    def total(self, metric: str) -> float:
        """Sum of a stage metric over every item (each item's last stage that reports it)."""
        total = 0.0
        for outcome in self.outcomes:
            values = [s.metrics[metric] for s in outcome.stages if metric in s.metrics]
            total += values[-1] if values else 0.0
        return total

    @property
    def hours_in(self) -> float:
        """Hours of input video (a stage's ``seconds_in``, else the item's known duration)."""
        seconds = 0.0
        for outcome in self.outcomes:
            values = [s.metrics["seconds_in"] for s in outcome.stages if "seconds_in" in s.metrics]
            seconds += values[0] if values else (outcome.seconds_in or 0.0)
        return seconds / 3600.0

    @property
    def hours_kept(self) -> float:
        """Hours kept by filtering (``seconds_kept``); all of an item's input when nothing filters it."""
        seconds = 0.0
        for outcome in self.outcomes:
            if outcome.failed is not None:
                continue
            kept = [s.metrics["seconds_kept"] for s in outcome.stages if "seconds_kept" in s.metrics]
            if kept:
                seconds += kept[-1]
            else:
                given = [s.metrics["seconds_in"] for s in outcome.stages if "seconds_in" in s.metrics]
                seconds += given[0] if given else (outcome.seconds_in or 0.0)
        return seconds / 3600.0

    @property
    def failures(self) -> list[ItemOutcome]:
        """Items with a failed stage."""
        return [o for o in self.outcomes if o.failed is not None]

    def stage_counts(self, name: str) -> dict[str, int]:
        """Per stage: items ``ran``, ``reused``, ``empty``, ``failed``."""
        counts = {"ran": 0, "reused": 0, "empty": 0, "failed": 0}
        for outcome in self.outcomes:
            for s in outcome.stages:
                if s.name != name:
                    continue
                counts["reused" if s.reused else "ran"] += 1
                if s.status in ("empty", "failed"):
                    counts[s.status] += 1
        return counts

    def as_json(self) -> dict[str, Any]:
        """``summary.json``: the totals and each item's stages."""
        return {
            "hours_in": round(self.hours_in, 6),
            "hours_kept": round(self.hours_kept, 6),
            "segments": int(self.total("segments")),
            "clips": int(self.total("clips")),
            "clips_annotated": int(self.total("clips_annotated")),
            "failures": len(self.failures) + len(self.skipped_inputs),
            "seconds": round(self.seconds, 3),
            "items": [
                {
                    "id": o.item_id,
                    "kind": o.kind,
                    "source": o.source,
                    "host": o.host,
                    "stages": [
                        {
                            "name": s.name,
                            "status": s.status,
                            "reused": s.reused,
                            "metrics": dict(s.metrics),
                            "message": s.message,
                            "seconds": round(s.seconds, 3),
                        }
                        for s in o.stages
                    ],
                }
                for o in self.outcomes
            ],
        }


def item_dir(work_root: Path, item_id: str) -> Path:
    """``<processed>/items/<item id>``: every stage's output of one item."""
    return Path(work_root) / "items" / item_id


def _now() -> str:
    return datetime.datetime.now(tz=datetime.UTC).isoformat(timespec="milliseconds")


def _one_line(text: str) -> str:
    line = " ".join(text.split())
    return line if len(line) <= _MESSAGE_CHARS else line[: _MESSAGE_CHARS - 3] + "..."


def _reusable(prov: Provenance | None, want: Mapping[str, Any], out_dir: Path) -> bool:
    """Whether a stage's earlier output stands. A stage that finished with some of its parts failed
    (``metrics["failed"] > 0``, e.g. clips the model did not answer for) is redone: its caches make
    the redo cost only the failed parts, and a plain re-run is how a user retries them."""
    if prov is None or prov.status == "failed" or prov.metrics.get("failed", 0.0) > 0:
        return False
    if any(getattr(prov, key) != value for key, value in want.items()):
        return False
    return all((out_dir / rel).exists() for rel in prov.outputs)


def _fresh_dir(out_dir: Path) -> None:
    """An empty output directory: a redo never mixes old and new outputs."""
    if out_dir.is_symlink() or out_dir.is_file():
        out_dir.unlink()
    elif out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)


def process_item(
    item: Item,
    stages: Sequence[PlannedStage],
    work_root: Path,
    report: Callable[[StageEvent], None] | None = None,
) -> ItemOutcome:
    """Take one item through ``stages`` in order; never raises for a stage's failure.

    Args:
        item: The input.
        stages: The planned stages, in pipeline order.
        work_root: The processed root; outputs go to ``<work_root>/items/<item.id>/<stage>/``.
        report: Receives progress events (called in this process; cheap).

    Returns:
        Each stage's outcome, up to and including a failed one.
    """
    root = item_dir(work_root, item.id)
    upstream_prov: dict[str, Provenance] = {}
    upstream_dirs: dict[str, Path] = {}
    outcomes: list[StageOutcome] = []
    host = host_name()
    for planned in stages:
        stage = planned.stage
        out_dir = root / stage.name
        want = {
            "stage": stage.name,
            "version": stage.version,
            "settings_hash": planned.settings_hash,
            "source_hash": item.source_hash,
            "upstream": hash_upstream(upstream_prov),
            "item_id": item.id,
        }
        try:
            prov = read_provenance(out_dir)
        except ProcessError as exc:
            _log.warning("%s: %s; redoing stage %s", item.id, exc, stage.name)
            prov = None
        if prov is not None and _reusable(prov, want, out_dir):
            outcome = StageOutcome(stage.name, prov.status, True, dict(prov.metrics), prov.message)
        else:
            prov, outcome = _run_stage(item, planned, out_dir, work_root, upstream_dirs, want, host, report)
        outcomes.append(outcome)
        if report is not None:
            report(StageEvent(item.id, stage.name, 1.0, done=True, status=outcome.status))
        if outcome.status == "failed":
            break
        upstream_prov[stage.name] = prov
        upstream_dirs[stage.name] = out_dir
    seconds_in = item.meta.get("duration_s")
    return ItemOutcome(
        item_id=item.id,
        kind=item.kind,
        source=str(item.episode_dir or (item.videos[0] if item.videos else "")),
        stages=tuple(outcomes),
        host=host,
        seconds_in=float(seconds_in) if isinstance(seconds_in, int | float) else _probe_seconds(item),
    )


def _run_stage(
    item: Item,
    planned: PlannedStage,
    out_dir: Path,
    work_root: Path,
    upstream_dirs: Mapping[str, Path],
    want: Mapping[str, Any],
    host: str,
    report: Callable[[StageEvent], None] | None,
) -> tuple[Provenance, StageOutcome]:
    stage = planned.stage
    started = _now()
    t0 = time.monotonic()
    try:
        _fresh_dir(out_dir)

        def progress(fraction: float) -> None:
            if report is not None:
                report(StageEvent(item.id, stage.name, min(max(float(fraction), 0.0), 1.0)))

        ctx = StageContext(
            out_dir=out_dir,
            work_root=Path(work_root),
            upstream=dict(upstream_dirs),
            settings=planned.settings,
            progress=progress,
        )
        result = stage.run(item, ctx)
        if not isinstance(result, StageResult):
            raise ProcessError(f"stage {stage.name} returned {type(result).__name__}, not a StageResult")
        if result.status not in ("ok", "empty", "failed"):
            raise ProcessError(f"stage {stage.name} returned status {str(result.status)[:40]!r}")
        status, message = result.status, _one_line(str(result.message))
        outputs = [str(o) for o in result.outputs]
        metrics = {str(k): float(v) for k, v in result.metrics.items()}
    except Exception as exc:  # any failure of a stage is recorded, never fatal
        _log.debug("%s: stage %s raised\n%s", item.id, stage.name, traceback.format_exc())
        status, outputs, metrics = "failed", [], {}
        message = _one_line(f"{type(exc).__name__}: {exc}")
    prov = Provenance(
        stage=stage.name,
        version=stage.version,
        settings_hash=planned.settings_hash,
        source_hash=item.source_hash,
        upstream=dict(want["upstream"]),
        item_id=item.id,
        status=status,
        outputs=outputs,
        metrics=metrics,
        message=message,
        started=started,
        finished=_now(),
        host=host,
    )
    try:
        write_provenance(out_dir, prov)
    except ProcessError as exc:
        status, message = "failed", _one_line(f"{message} {exc}".strip())
        prov = prov.model_copy(update={"status": status, "message": message})
    seconds = time.monotonic() - t0
    return prov, StageOutcome(stage.name, status, False, metrics, message, seconds)


def _probe_seconds(item: Item) -> float | None:
    """Duration [s] of a plain video from its container (cheap; no decode); ``None`` if unreadable."""
    try:
        import av
    except ImportError:  # pragma: no cover - av is in the record extra every install has
        return None
    total = 0.0
    for video in item.videos:
        try:
            with av.open(str(video)) as container:
                if container.duration is None:
                    return None
                total += container.duration / 1e6
        except (OSError, av.FFmpegError, ValueError):
            return None
    return total


# --- execution ------------------------------------------------------------------------------------


_worker_queue: Any = None
"""The progress queue of a pool worker, set by :func:`_init_worker` (inherited at spawn)."""


_worker_stages: dict[str, Closable] = {}
"""Stages a pool worker ran that hold resources, closed when the worker exits."""


def _init_worker(queue: Any) -> None:
    global _worker_queue
    # A worker that ends must not wait for its queued progress to be read (nor for a lock a
    # killed sibling may hold): progress is best effort.
    queue.cancel_join_thread()
    _worker_queue = queue
    # Pool workers leave through os._exit (atexit does not run); multiprocessing's finalizers do.
    multiprocessing.util.Finalize(None, _close_worker_stages, exitpriority=10)


def _close_worker_stages() -> None:
    _close_all(list(_worker_stages.values()))


def _close_all(stages: Sequence[Closable]) -> None:
    for stage in stages:
        try:
            stage.close()
        except Exception as exc:  # closing one must not keep the others open
            _log.warning("closing stage %s: %s", type(stage).__name__, exc)


def _pool_item(item: Item, stages: Sequence[PlannedStage], work_root: Path) -> ItemOutcome:
    """:func:`process_item` in a pool worker, its progress sent back through the worker's queue."""

    def report(event: StageEvent) -> None:
        # Progress is best effort; the returned outcome carries the truth.
        with contextlib.suppress(Exception):
            _worker_queue.put_nowait(event)

    for planned in stages:
        if isinstance(planned.stage, Closable):  # each task unpickles its own copy: keep the last
            _worker_stages[planned.stage.name] = planned.stage
    return process_item(item, stages, work_root, report)


def _dead_worker(item: Item, reason: str) -> ItemOutcome:
    return ItemOutcome(
        item_id=item.id,
        kind=item.kind,
        source=str(item.episode_dir or (item.videos[0] if item.videos else "")),
        stages=(StageOutcome("worker", "failed", False, {}, _one_line(reason)),),
        host=host_name(),
    )


def _run_local(
    items: Sequence[Item],
    stages: Sequence[PlannedStage],
    work_root: Path,
    workers: int,
    on_event: Callable[[StageEvent], None],
    on_item: Callable[[ItemOutcome], None],
) -> None:
    if workers <= 1 or len(items) <= 1:
        for item in items:
            try:
                outcome = process_item(item, stages, work_root, on_event)
            except Exception as exc:  # a runner bug or a full disk must not end the batch either
                _log.exception("%s: the runner failed on it", item.id)
                outcome = _dead_worker(item, f"{type(exc).__name__}: {exc}")
            on_item(outcome)
        return
    ctx = _mp_context(stages)
    queue = ctx.Queue()
    broken = _pool_pass(items, stages, work_root, workers, ctx, queue, on_event, on_item)
    # A worker died (segfault, OOM kill) and took every item in flight with it: each of those runs
    # again alone, so only the one that kills its worker is recorded as failed.
    for item in broken:
        again = _pool_pass([item], stages, work_root, 1, ctx, queue, on_event, on_item)
        for lost in again:
            on_item(_dead_worker(lost, "its worker process died (killed, or crashed in native code)"))


def _mp_context(stages: Sequence[PlannedStage]) -> Any:
    """Workers that inherit no thread state: never a plain fork (the driver may hold threads, e.g.
    the progress display, whose locks a fork would copy mid-use).

    Forkserver where the platform has it: one clean server process imports the stage modules once
    and forks each worker from it, so a worker starts in milliseconds instead of importing telerig,
    PyAV and the stages again (seconds each; a pool rerun after a dead worker pays it again).
    Elsewhere, spawn.
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    modules = sorted({__name__, *(type(p.stage).__module__ for p in stages)} - {"__main__"})
    ctx.set_forkserver_preload(modules)  # takes effect when this process first starts the server
    return ctx


def _pool_pass(
    items: Sequence[Item],
    stages: Sequence[PlannedStage],
    work_root: Path,
    workers: int,
    ctx: Any,
    queue: Any,
    on_event: Callable[[StageEvent], None],
    on_item: Callable[[ItemOutcome], None],
) -> list[Item]:
    """Run ``items`` on one pool; returns the items its broken workers lost."""
    lost: list[Item] = []
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(queue,)
    ) as pool:
        futures = {pool.submit(_pool_item, it, stages, work_root): it for it in items}
        waiting = set(futures)
        while waiting:
            done, waiting = concurrent.futures.wait(waiting, timeout=0.1)
            _drain(queue, on_event)
            for future in done:
                item = futures[future]
                try:
                    on_item(future.result())
                except concurrent.futures.process.BrokenProcessPool:
                    lost.append(item)
                except Exception as exc:  # e.g. an item or stage that does not pickle
                    on_item(_dead_worker(item, f"{type(exc).__name__}: {exc}"))
    _drain(queue, on_event)
    return lost


def _drain(queue: Any, on_event: Callable[[StageEvent], None]) -> None:
    import queue as queue_module

    while True:
        try:
            event = queue.get_nowait()
        except (queue_module.Empty, EOFError, OSError):
            return
        on_event(event)


def _run_dask(
    items: Sequence[Item],
    stages: Sequence[PlannedStage],
    work_root: Path,
    address: str,
    on_event: Callable[[StageEvent], None],
    on_item: Callable[[ItemOutcome], None],
) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise DependencyError(
            "--cluster needs Dask distributed: pip install 'telerig[process]' (dask[distributed])"
        ) from None
    _check_reachable(address)
    try:
        client = Client(address, timeout=10, set_as_default=False)  # type: ignore[no-untyped-call]
    except (OSError, TimeoutError) as exc:
        raise ProcessError(
            f"cannot reach the Dask scheduler at {address}: {exc}; "
            "start one (dask scheduler) or fix --cluster"
        ) from None
    with client:
        futures = {}
        for item in items:
            future = client.submit(
                process_item, item, stages, work_root, None, pure=False, key=f"process-{item.id}"
            )
            futures[future] = item
        with client.as_current():  # as_completed finds the client this way, not as a default
            for future in as_completed(list(futures)):  # type: ignore[no-untyped-call]
                item = futures[future]
                try:
                    outcome = future.result()
                except Exception as exc:  # a lost worker, a pickling error: that item fails
                    outcome = _dead_worker(item, f"{type(exc).__name__}: {exc}")
                for s in outcome.stages:
                    on_event(StageEvent(item.id, s.name, 1.0, done=True, status=s.status))
                on_item(outcome)


def _check_reachable(address: str) -> None:
    """Fail fast (one line) on a scheduler address nothing listens on, before Dask's 10 s retry."""
    import socket
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(address if "://" in address else f"tcp://{address}")
        scheme, host, port = parts.scheme, parts.hostname, parts.port
    except ValueError:
        scheme, host, port = "", None, None
    if scheme not in ("tcp", "tls") or not host or port is None:
        raise ProcessError(f"--cluster {address[:100]!r}: expected tcp://HOST:PORT of a Dask scheduler")
    try:
        socket.create_connection((host, port), timeout=5).close()
    except OSError as exc:
        raise ProcessError(
            f"cannot reach the Dask scheduler at {address}: {exc.strerror or exc}; "
            "start one (dask scheduler) or fix --cluster"
        ) from None


def run_pipeline(
    items: Sequence[Item],
    stages: Sequence[PlannedStage],
    work_root: Path,
    *,
    workers: int | None = None,
    cluster: str | None = None,
    skipped: Sequence[Skipped] = (),
    on_event: Callable[[StageEvent], None] | None = None,
    on_item: Callable[[ItemOutcome], None] | None = None,
) -> RunSummary:
    """Run every item through ``stages``; write ``failures.json`` and ``summary.json`` in ``work_root``.

    Args:
        items: The inputs (see :mod:`telerig.process.items`).
        stages: The planned stages, in pipeline order (see :func:`plan`).
        work_root: The processed root (created).
        workers: Local processes; ``None``: one per CPU core; 1 runs in this process.
        cluster: A Dask scheduler address (``tcp://10.0.0.5:8786``); its workers must see
            ``work_root`` and the inputs at the same paths (a shared filesystem).
        skipped: Inputs discovery could not read; counted as failures.
        on_event: Progress (called in this process).
        on_item: Called with each item's outcome as it finishes.

    Raises:
        ProcessError: The processed root cannot be created, or the cluster cannot be reached.
    """
    work_root = Path(work_root)
    try:
        (work_root / "items").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ProcessError(f"cannot create {work_root}: {exc.strerror or exc}") from None
    with _root_lock(work_root):
        return _run_locked(items, stages, work_root, workers, cluster, skipped, on_event, on_item)


@contextlib.contextmanager
def _root_lock(work_root: Path) -> Iterator[None]:
    """One run per processed root at a time (two would redo and delete each other's outputs)."""
    import fcntl

    fd = os.open(work_root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise ProcessError(
                f"another telerig process is writing {work_root}; wait for it to finish or give another --out"
            ) from None
        yield
    finally:
        os.close(fd)


def _run_locked(
    items: Sequence[Item],
    stages: Sequence[PlannedStage],
    work_root: Path,
    workers: int | None,
    cluster: str | None,
    skipped: Sequence[Skipped],
    on_event: Callable[[StageEvent], None] | None,
    on_item: Callable[[ItemOutcome], None] | None,
) -> RunSummary:
    summary = RunSummary(work_root=work_root, skipped_inputs=tuple(skipped))
    t0 = time.monotonic()

    def collect(outcome: ItemOutcome) -> None:
        summary.outcomes.append(outcome)
        if on_item is not None:
            on_item(outcome)

    event_sink = on_event or (lambda _e: None)
    try:
        if cluster:
            _run_dask(items, stages, work_root, cluster, event_sink, collect)
        else:
            n = workers if workers is not None else (os.cpu_count() or 1)
            _run_local(items, stages, work_root, max(1, n), event_sink, collect)
    finally:  # what ran in this process (workers=1) holds its resources here
        _close_all([p.stage for p in stages if isinstance(p.stage, Closable)])
    order = {item.id: i for i, item in enumerate(items)}
    summary.outcomes.sort(key=lambda o: order.get(o.item_id, len(order)))
    for planned in stages:
        if isinstance(planned.stage, Finisher):
            done = [o.item_id for o in summary.outcomes if o.failed is None]
            planned.stage.finish(work_root, done, planned.settings)
    summary.seconds = time.monotonic() - t0
    _write_reports(summary)
    return summary


def _write_reports(summary: RunSummary) -> None:
    failures = [
        {"item": o.item_id, "source": o.source, "stage": f.name, "message": f.message, "host": o.host}
        for o in summary.outcomes
        if (f := o.failed) is not None
    ] + [
        {"item": None, "source": s.path, "stage": "discover", "message": s.reason, "host": host_name()}
        for s in summary.skipped_inputs
    ]
    write_json_atomic(summary.work_root / FAILURES_FILE, {"run_finished": _now(), "failures": failures})
    write_json_atomic(summary.work_root / SUMMARY_FILE, summary.as_json())
