"""Background jobs of the control center (exports, quality checks), each in its own worker process.

The web process never runs a job: :class:`JobRunner` inserts the job into the ``jobs`` table of the
data root's ``control.sqlite`` and starts ``python -m telerig.server.jobs run JOB_ID`` (at nice 10,
in its own session, so neither a closed browser nor a restarted web server stops it). The worker
writes its progress (done/total, a message), its state (``queued`` → ``running`` → ``done`` or
``failed``, with one error line) and its result to the table, which every client reads.

At most ``max_running`` jobs run at once; the rest wait ``queued`` and start as others end. When the
server starts it marks ``running`` jobs whose process is gone as ``failed`` (a crash or a reboot
killed them) and starts the queued ones.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import sqlalchemy as sa
from pydantic import BaseModel, ConfigDict, Field, StringConstraints, TypeAdapter
from sqlalchemy.engine import Engine

from telerig.server.accounts import control_engine

__all__ = [
    "EXPORT_DIR",
    "ExportParams",
    "Job",
    "JobKind",
    "JobRequest",
    "JobRunner",
    "JobState",
    "JobStore",
    "QaParams",
    "export_dir",
    "main",
]

_log = logging.getLogger("telerig.server.jobs")

#: Exports go to ``<data root>/exports/<name>``.
EXPORT_DIR = "exports"
#: Niceness of a worker process: the robots' control loops come first.
WORKER_NICE = 10
_DB_FILE = "control.sqlite"
_EPISODE_ID = r"^ep-\d{8}-\d{6}-[0-9a-f]{4}$"
_MAX_IDS = 1000
_TEXT = 200
_ERROR_TEXT = 500

JobKind = Literal["export", "qa"]
JobState = Literal["queued", "running", "done", "failed"]
_ACTIVE: tuple[JobState, ...] = ("queued", "running")

EpisodeId = Annotated[str, StringConstraints(pattern=_EPISODE_ID)]
ExportName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")]
ShortText = Annotated[str, StringConstraints(min_length=1, max_length=_TEXT)]


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ExportParams(_Params):
    """An export: which episodes, the format, and the dataset name under ``<data root>/exports/``.

    Attributes:
        format: Exporter (``lerobot``, ``hdf5``, ``robomimic``, ``rlds``).
        name: Dataset directory name (letters, digits, ``_.-``; re-using a name appends to it).
        ids: Only these episodes (empty: every committed episode matching the other filters).
        task: Only this task.
        operator: Only this operator.
        include_failures: Also episodes in the failures partition.
        fps: Dataset rate [Hz]; the camera's rate when ``None``.
        normalize: Map state and action to [-1, 1] from the robot limits.
    """

    format: Literal["lerobot", "hdf5", "robomimic", "rlds"]
    name: ExportName
    ids: list[EpisodeId] = Field(default_factory=list, max_length=_MAX_IDS)
    task: ShortText | None = None
    operator: ShortText | None = None
    include_failures: bool = False
    fps: int | None = Field(default=None, ge=1, le=1000)
    normalize: bool = False


class QaParams(_Params):
    """A quality check: these episodes, or (empty ``ids``) the unchecked ones, or with ``recheck``
    every committed episode, with the default thresholds."""

    ids: list[EpisodeId] = Field(default_factory=list, max_length=_MAX_IDS)
    recheck: bool = False


class ExportJobRequest(_Params):
    """Start an export job."""

    kind: Literal["export"]
    params: ExportParams


class QaJobRequest(_Params):
    """Start a quality-check job."""

    kind: Literal["qa"]
    params: QaParams


JobRequest = Annotated[ExportJobRequest | QaJobRequest, Field(discriminator="kind")]
_REQUEST: TypeAdapter[ExportJobRequest | QaJobRequest] = TypeAdapter(JobRequest)


class Job(BaseModel):
    """A job as every client sees it.

    Attributes:
        id: Job number.
        kind: ``export`` or ``qa``.
        params: What it was asked to do.
        state: ``queued``, ``running``, ``done`` or ``failed``.
        done: Items finished (episodes).
        total: Items to do; 0 while not known yet.
        message: What it is doing now, or what it did.
        error: Why it failed (one line); ``None`` otherwise.
        result: What it produced (e.g. the export's directory and episodes).
        user: Who started it.
        worker_pid: The worker process's id while it runs (never the web server's).
        created_ns, started_ns, finished_ns: Wall clock [ns].
    """

    model_config = ConfigDict(frozen=True)

    id: int
    kind: JobKind
    params: dict[str, Any]
    state: JobState
    done: int
    total: int
    message: str
    error: str | None
    result: dict[str, Any] | None
    user: str
    worker_pid: int | None
    created_ns: int
    started_ns: int | None
    finished_ns: int | None


_meta = sa.MetaData()
_jobs = sa.Table(
    "jobs",
    _meta,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("kind", sa.String(16), nullable=False),
    sa.Column("params", sa.Text, nullable=False),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("done", sa.Integer, nullable=False, default=0),
    sa.Column("total", sa.Integer, nullable=False, default=0),
    sa.Column("message", sa.String(_TEXT), nullable=False, default=""),
    sa.Column("error", sa.String(_ERROR_TEXT), nullable=True),
    sa.Column("result", sa.Text, nullable=True),
    sa.Column("user", sa.String(32), nullable=False),
    sa.Column("pid", sa.Integer, nullable=True),
    sa.Column("created_ns", sa.BigInteger, nullable=False),
    sa.Column("started_ns", sa.BigInteger, nullable=True),
    sa.Column("finished_ns", sa.BigInteger, nullable=True),
)
sa.Index("jobs_state", _jobs.c.state)


def export_dir(data_root: Path, name: str) -> Path:
    """``<data root>/exports/<name>``, for a checked name (no path can pass).

    Raises:
        ValueError: ``name`` is not a dataset name.
    """
    ExportParams.model_validate({"format": "hdf5", "name": name})
    return Path(data_root) / EXPORT_DIR / name


class JobStore:
    """The ``jobs`` table of a data root's ``control.sqlite`` (shared by the web and worker processes)."""

    def __init__(self, data_root: Path) -> None:
        self.data_root = Path(data_root)
        self.data_root.mkdir(parents=True, exist_ok=True)
        self._engine: Engine = control_engine(self.data_root / _DB_FILE)
        _meta.create_all(self._engine)

    def close(self) -> None:
        self._engine.dispose()

    def add(self, request: ExportJobRequest | QaJobRequest, user: str) -> Job:
        """Insert a ``queued`` job."""
        with self._engine.begin() as conn:
            job_id = conn.execute(
                sa.insert(_jobs).values(
                    kind=request.kind,
                    params=request.params.model_dump_json(),
                    state="queued",
                    done=0,
                    total=0,
                    message="queued",
                    user=user[:32],
                    created_ns=time.time_ns(),
                )
            ).inserted_primary_key
        assert job_id is not None
        return self.get(int(job_id[0]))

    def get(self, job_id: int) -> Job:
        """The job; ``KeyError`` when there is none."""
        with self._engine.connect() as conn:
            row = conn.execute(sa.select(_jobs).where(_jobs.c.id == job_id)).mappings().first()
        if row is None:
            raise KeyError(job_id)
        return _job(row)

    def request(self, job_id: int) -> ExportJobRequest | QaJobRequest:
        """What the job was asked to do (as checked when it was submitted)."""
        job = self.get(job_id)
        return _REQUEST.validate_python({"kind": job.kind, "params": job.params})

    def jobs(self, *, limit: int = 50, state: JobState | None = None) -> list[Job]:
        """Newest first."""
        q = sa.select(_jobs).order_by(_jobs.c.id.desc()).limit(max(1, min(limit, 500)))
        if state is not None:
            q = q.where(_jobs.c.state == state)
        with self._engine.connect() as conn:
            return [_job(r) for r in conn.execute(q).mappings()]

    def pids(self) -> dict[int, int | None]:
        """``running`` job → its worker's pid."""
        with self._engine.connect() as conn:
            rows = conn.execute(sa.select(_jobs.c.id, _jobs.c.pid).where(_jobs.c.state == "running"))
            return {r.id: r.pid for r in rows}

    def queued(self) -> list[int]:
        with self._engine.connect() as conn:
            q = sa.select(_jobs.c.id).where(_jobs.c.state == "queued").order_by(_jobs.c.id)
            return list(conn.execute(q).scalars())

    def claim(self, job_id: int, pid: int) -> bool:
        """``queued`` → ``running`` with this worker pid; False when it was not queued."""
        with self._engine.begin() as conn:
            done = conn.execute(
                sa.update(_jobs)
                .where(_jobs.c.id == job_id, _jobs.c.state == "queued")
                .values(state="running", pid=pid, started_ns=time.time_ns(), message="starting")
            )
        return done.rowcount == 1

    def set_pid(self, job_id: int, pid: int) -> None:
        with self._engine.begin() as conn:
            conn.execute(sa.update(_jobs).where(_jobs.c.id == job_id).values(pid=pid))

    def progress(self, job_id: int, done: int, total: int, message: str) -> None:
        with self._engine.begin() as conn:
            conn.execute(
                sa.update(_jobs)
                .where(_jobs.c.id == job_id, _jobs.c.state == "running")
                .values(done=done, total=total, message=message[:_TEXT])
            )

    def finish(
        self,
        job_id: int,
        *,
        error: str | None = None,
        result: dict[str, Any] | None = None,
        message: str = "",
        only_if_active: bool = False,
    ) -> bool:
        """``done`` (no error) or ``failed``; False when ``only_if_active`` and it already ended."""
        values: dict[str, Any] = {
            "state": "failed" if error is not None else "done",
            "error": None if error is None else _one_line(error),
            "finished_ns": time.time_ns(),
        }
        if result is not None:
            values["result"] = json.dumps(result)
        if message:
            values["message"] = message[:_TEXT]
        q = sa.update(_jobs).where(_jobs.c.id == job_id)
        if only_if_active:
            q = q.where(_jobs.c.state.in_(_ACTIVE))
        with self._engine.begin() as conn:
            return conn.execute(q.values(**values)).rowcount == 1


def _one_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return (lines[0] if lines else "failed")[:_ERROR_TEXT]


def _job(row: sa.RowMapping) -> Job:
    return Job(
        id=row["id"],
        kind=row["kind"],
        params=json.loads(row["params"]),
        state=row["state"],
        done=row["done"],
        total=row["total"],
        message=row["message"],
        error=row["error"],
        result=None if row["result"] is None else json.loads(row["result"]),
        user=row["user"],
        worker_pid=row["pid"] or None,
        created_ns=row["created_ns"],
        started_ns=row["started_ns"],
        finished_ns=row["finished_ns"],
    )


def _alive(pid: int | None, job_id: int) -> bool:
    """Whether ``pid`` is still this job's worker (a reused pid is some other process)."""
    if pid is None or pid <= 0:
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return b"telerig.server.jobs" in cmdline and str(job_id).encode() in cmdline


@dataclass
class _Running:
    process: subprocess.Popen[bytes]
    waiter: threading.Thread


class JobRunner:
    """Starts jobs in worker processes, at most ``max_running`` at once, and watches them end.

    Args:
        data_root: The data root (its ``control.sqlite`` holds the jobs, ``exports/`` the datasets).
        max_running: Jobs that may run at once; the others wait ``queued``.
        python: The interpreter of the workers.
    """

    def __init__(self, data_root: Path, *, max_running: int = 2, python: str = sys.executable) -> None:
        self.store = JobStore(data_root)
        self._max_running = max_running
        self._python = python
        self._lock = threading.Lock()
        self._running: dict[int, _Running] = {}
        self._closed = False

    def recover(self) -> list[int]:
        """Mark ``running`` jobs whose worker is gone as failed; start queued jobs. Returns the failed.

        Called when the server starts, and whenever the job list is read: a worker started by an
        earlier server (not this one's child, so not watched) that was killed shows as failed."""
        with self._lock:  # not while _start() has claimed a job but not yet recorded its pid
            lost = [
                job_id
                for job_id, pid in self.store.pids().items()
                if job_id not in self._running and not _alive(pid, job_id)
            ]
            for job_id in lost:
                self.store.finish(
                    job_id,
                    error="its worker process is gone (the server or machine restarted); start it again",
                    only_if_active=True,
                )
        self._dispatch()
        return lost

    def submit(self, request: ExportJobRequest | QaJobRequest, user: str) -> Job:
        """Queue a job and start it when a worker slot is free."""
        job = self.store.add(request, user)
        self._dispatch()
        return self.store.get(job.id)

    def close(self) -> None:
        """Stop watching (the workers go on; the next server marks or sees them)."""
        self._closed = True
        self.store.close()

    def wait(self, job_id: int, timeout_s: float) -> Job:
        """Block until the job ended or ``timeout_s`` passed; the job as it is then (for tests, CLIs)."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.store.get(job_id)
            if job.state not in _ACTIVE or time.monotonic() > deadline:
                return job
            time.sleep(0.1)

    def _dispatch(self) -> None:
        with self._lock:
            if self._closed:
                return
            external = sum(1 for j, pid in self.store.pids().items() if j not in self._running)
            for job_id in self.store.queued():
                if len(self._running) + external >= self._max_running:
                    return
                self._start(job_id)

    def _start(self, job_id: int) -> None:
        cmd = [
            self._python,
            "-m",
            "telerig.server.jobs",
            "run",
            "--data-root",
            str(self.store.data_root),
            str(job_id),
        ]
        if not self.store.claim(job_id, 0):  # pragma: no cover - ended meanwhile
            return
        try:
            process = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                start_new_session=True,  # a Ctrl-C of the server does not kill the job
                close_fds=True,
            )
        except OSError as exc:
            self.store.finish(job_id, error=f"cannot start a worker: {exc}", only_if_active=True)
            return
        self.store.set_pid(job_id, process.pid)
        waiter = threading.Thread(target=self._watch, args=(job_id, process), daemon=True)
        self._running[job_id] = _Running(process, waiter)
        waiter.start()

    def _watch(self, job_id: int, process: subprocess.Popen[bytes]) -> None:
        _, stderr = process.communicate()
        with self._lock:
            self._running.pop(job_id, None)
        if self._closed:
            return
        tail = stderr.decode(errors="replace").strip().splitlines()
        if process.returncode != 0:
            _log.warning("job %d: worker exited %d: %s", job_id, process.returncode, tail[-1:] or "")
        reason = tail[-1] if tail else f"the worker exited with status {process.returncode}"
        self.store.finish(job_id, error=reason, only_if_active=True)  # a worker that ended silently
        self._dispatch()


# --- the worker -------------------------------------------------------------------------------------


def run_job(store: JobStore, job_id: int) -> None:
    """Run one claimed job in this process, writing its progress and its end to ``store``."""
    request = store.request(job_id)
    try:
        if isinstance(request, ExportJobRequest):
            result = _run_export(store, job_id, request.params)
        else:
            result = _run_qa(store, job_id, request.params)
    except Exception as exc:  # every failure ends the job with its one line
        from telerig.errors import TelerigError

        if not isinstance(exc, TelerigError):
            traceback.print_exc()
        error = str(exc) if isinstance(exc, TelerigError) else f"{type(exc).__name__}: {exc}"
        store.finish(job_id, error=error)
        return
    store.finish(job_id, result=result, message=str(result.get("summary", "done")))


def _run_export(store: JobStore, job_id: int, params: ExportParams) -> dict[str, Any]:
    from telerig.export.run import EpisodeFilter, export

    out = export_dir(store.data_root, params.name)
    store.progress(job_id, 0, len(params.ids), "reading the episodes")

    def progress(done: int, total: int, episode_id: str) -> None:
        store.progress(job_id, done, total, f"wrote {episode_id}")

    summary = export(
        store.data_root,
        params.format,
        out,
        selection=EpisodeFilter(
            ids=tuple(params.ids),
            task=params.task,
            operator=params.operator,
            include_failures=params.include_failures,
        ),
        fps=params.fps,
        normalize=params.normalize,
        progress=progress,
    )
    added, skipped = len(summary.added), len(summary.skipped)
    store.progress(job_id, added + skipped, added + skipped, "validated")
    return {
        "summary": f"{params.format} export {params.name}: {added} added, {skipped} already there, "
        f"{summary.episodes_total} in the dataset",
        "out": f"{EXPORT_DIR}/{params.name}",
        "added": list(summary.added),
        "skipped": list(summary.skipped),
        "frames": summary.frames,
        "episodes_total": summary.episodes_total,
    }


def _run_qa(store: JobStore, job_id: int, params: QaParams) -> dict[str, Any]:
    from telerig.config.qa import QaThresholds
    from telerig.errors import TelerigError
    from telerig.qa.checker import check_episode, unchecked
    from telerig.store.episodes import EpisodeStore
    from telerig.store.index import EpisodeIndex

    episodes = EpisodeStore(store.data_root)
    if params.ids:
        ids = list(dict.fromkeys(params.ids))
    elif params.recheck:
        ids = [s.id for s in episodes.list(include_failures=True)]
    else:
        ids = [s.id for s in unchecked(episodes)]
    thresholds = QaThresholds()
    rejected: list[str] = []
    errors: list[str] = []
    store.progress(job_id, 0, len(ids), "checking" if ids else "nothing to check")
    with EpisodeIndex.open(store.data_root) as index:
        for i, episode_id in enumerate(ids):
            try:
                outcome = check_episode(episodes, episode_id, thresholds, index=index)
            except TelerigError as exc:
                errors.append(f"{episode_id}: {exc}")
            else:
                if outcome.partition == "failures":
                    rejected.append(episode_id)
            store.progress(job_id, i + 1, len(ids), f"checked {episode_id}")
    if errors and len(errors) == len(ids):
        raise RuntimeError(errors[0])
    return {
        "summary": f"{len(ids) - len(errors)} checked, {len(rejected)} rejected"
        + (f", {len(errors)} not checked" if errors else ""),
        "rejected": rejected,
        "errors": errors[:20],
    }


#: Exit status of ``plot`` when matplotlib is missing.
EXIT_NO_PLOTTING = 3
#: Longest a plot may take [s] before the web server gives up on it.
PLOT_TIMEOUT_S = 300.0


def render_plot(episode_dir: Path, out: Path, width_px: int) -> None:
    """Render an episode's plot (:func:`telerig.qa.plot.plot_episode`) in a worker process at nice
    10, so matplotlib and the episode's streams never load into (or slow) the web server.

    Raises:
        DependencyError: matplotlib is not installed.
        RecordingError: nothing to plot, or the worker failed or took too long (one line).
    """
    from telerig.errors import DependencyError, RecordingError

    cmd = [sys.executable, "-m", "telerig.server.jobs", "plot", str(episode_dir), str(out), str(width_px)]
    try:
        done = subprocess.run(
            cmd, stdin=subprocess.DEVNULL, capture_output=True, timeout=PLOT_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired:
        raise RecordingError(f"plotting {episode_dir.name} took over {PLOT_TIMEOUT_S:.0f} s") from None
    if done.returncode == 0:
        return
    lines = done.stderr.decode(errors="replace").strip().splitlines()
    message = lines[-1] if lines else f"the plot worker exited with status {done.returncode}"
    if done.returncode == EXIT_NO_PLOTTING:
        raise DependencyError(message)
    raise RecordingError(message)


def _plot_main(episode_dir: Path, out: Path, width_px: int) -> int:
    from telerig.errors import DependencyError, TelerigError
    from telerig.qa.plot import plot_episode

    try:
        plot_episode(episode_dir, out, width_px=width_px)
    except DependencyError as exc:
        print(exc, file=sys.stderr)
        return EXIT_NO_PLOTTING
    except TelerigError as exc:
        print(exc, file=sys.stderr)
        return 2
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m telerig.server.jobs run --data-root ROOT JOB_ID``: a worker process;
    ``... plot EPISODE_DIR OUT_PNG WIDTH``: render one episode plot."""
    parser = argparse.ArgumentParser(prog="python -m telerig.server.jobs")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one queued job")
    run.add_argument("--data-root", type=Path, required=True)
    run.add_argument("job_id", type=int)
    plot = sub.add_parser("plot", help="render one episode's plot")
    plot.add_argument("episode_dir", type=Path)
    plot.add_argument("out", type=Path)
    plot.add_argument("width_px", type=int)
    args = parser.parse_args(argv)
    with contextlib.suppress(OSError):  # not allowed here: run at the current priority
        os.nice(WORKER_NICE)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.command == "plot":
        return _plot_main(args.episode_dir, args.out, args.width_px)
    store = JobStore(args.data_root)
    try:
        job = store.get(args.job_id)
        if job.state == "queued":  # started by hand, not by a JobRunner
            store.claim(args.job_id, os.getpid())
        elif job.state != "running":
            print(f"job {args.job_id} is {job.state}; nothing to do", file=sys.stderr)
            return 2
        store.set_pid(args.job_id, os.getpid())
        run_job(store, args.job_id)
    finally:
        store.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
