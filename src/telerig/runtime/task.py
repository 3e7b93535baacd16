"""Task episodes: seeded scene resets between episodes and success judged from the scene.

A rig whose simulated robot has a randomized task (:class:`~telerig.robots.base.EpisodicTask`,
e.g. ``type: mujoco_pick_place``) gets, per episode ``k`` of a run, the scene reset from seed
``base + k`` before the devices start, and a watcher that judges success from the scene state
every :data:`CHECK_PERIOD_S` while the episode runs. The manifest's ``task`` record keeps the
seed, what was drawn, the final check and the time to success; ``outcome`` is set from it unless
the operator marked the episode.

Seeds: ``telerig collect`` draws from ``[0, EVAL_SEED_BASE)`` and ``telerig eval`` from
``[EVAL_SEED_BASE, 2**31)``, so evaluation episodes are never training episodes.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pydantic import JsonValue

from telerig.config.schema import RigConfig
from telerig.errors import ConfigError, TelerigError
from telerig.robots.base import EpisodicTask, RobotDriver, TaskCheck

__all__ = [
    "CHECK_PERIOD_S",
    "COLLECT_SEED_BASE",
    "EVAL_SEED_BASE",
    "TaskEpisodes",
    "TaskResult",
    "check_seed_range",
    "task_robots",
    "with_task_seed",
]

log = logging.getLogger(__name__)

#: How often the watcher judges the scene during an episode [s].
CHECK_PERIOD_S = 0.05
#: First seed of ``telerig collect`` (demonstrations) by default.
COLLECT_SEED_BASE = 0
#: First seed of ``telerig eval``: collect's seeds stay below it (held-out evaluation scenes).
EVAL_SEED_BASE = 1_000_000
_MAX_SEED = 2**31 - 1


def check_seed_range(seed: int, episodes: int, *, held_out: bool) -> None:
    """Refuse a seed range that crosses into the other command's range.

    Raises:
        ConfigError: one line naming the allowed range.
    """
    last = seed + episodes - 1
    if held_out and not (seed >= EVAL_SEED_BASE and last <= _MAX_SEED):
        raise ConfigError(
            f"--seed {seed}: evaluation seeds are held out, in [{EVAL_SEED_BASE}, {_MAX_SEED}]; "
            f"seeds below {EVAL_SEED_BASE} are for collecting demonstrations"
        )
    if not held_out and not (seed >= 0 and last < EVAL_SEED_BASE):
        raise ConfigError(
            f"--seed {seed} with {episodes} episodes uses seeds up to {last}: demonstrations use "
            f"[0, {EVAL_SEED_BASE - 1}]; seeds from {EVAL_SEED_BASE} are held out for `telerig eval`"
        )


def task_robots(config: RigConfig) -> list[str]:
    """Ids of the rig's robots with a seeded task (their config has a ``seed``)."""
    return [r.id for r in config.robots if isinstance(getattr(r, "seed", None), int)]


def with_task_seed(config: RigConfig, seed: int) -> RigConfig:
    """The rig with base seed ``seed`` on every seeded component (task robots, scripted operators).

    Raises:
        ConfigError: the rig has no task robot (nothing would be randomized).
    """
    if not task_robots(config):
        raise ConfigError(
            f"rig {config.name!r} has no task with a seed (e.g. a robot of type mujoco_pick_place); "
            "use a task rig such as `pick_place`"
        )
    data = config.model_dump(mode="python")
    for section in ("robots", "devices"):
        for item in data[section]:
            if "seed" in item:
                item["seed"] = seed
    return RigConfig.model_validate(data)


@dataclass(frozen=True, slots=True)
class TaskResult:
    """One robot's task in one episode.

    Attributes:
        robot: Robot id.
        record: What the manifest's ``task`` keeps (seed, draw, final check, time to success).
        success: Whether the final check held.
        time_to_success_s: Time from the episode's start to the start of the success that lasted
            to its end [s]; None when it did not end in success.
    """

    robot: str
    record: dict[str, JsonValue]
    success: bool
    time_to_success_s: float | None


class _Watcher:
    """Judges one task every period on its own thread; remembers when the final success began."""

    def __init__(self, task: EpisodicTask, name: str) -> None:
        self._task = task
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._since: float | None = None
        self.checks = 0
        self._thread = threading.Thread(target=self._run, name=f"task-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(CHECK_PERIOD_S):
            self._observe()

    def _observe(self) -> TaskCheck:
        check = self._task.check_task()
        with self._lock:
            self.checks += 1
            if not check.success:
                self._since = None
            elif self._since is None:
                self._since = time.monotonic() - self._t0
        return check

    def finish(self) -> tuple[TaskCheck, float | None]:
        self._stop.set()
        self._thread.join(timeout=5.0)
        check = self._observe()
        with self._lock:
            return check, self._since


class TaskEpisodes:
    """The seeded tasks of a station's robots across a run: reset per episode, then judged.

    Args:
        robots: The station's local robots; those with a task are used.
        seed: Base seed overriding each robot's own (``telerig collect/eval --seed``); None keeps theirs.
    """

    def __init__(self, robots: Mapping[str, RobotDriver], *, seed: int | None = None) -> None:
        self.tasks: dict[str, EpisodicTask] = {
            rid: r for rid, r in robots.items() if isinstance(r, EpisodicTask)
        }
        self.seed = seed
        #: Episodes begun in this run (the next one is episode ``episode``).
        self.episode = 0
        self._begun: dict[str, tuple[dict[str, JsonValue], _Watcher]] = {}

    def __bool__(self) -> bool:
        return bool(self.tasks)

    def next_seed(self, robot: str) -> int:
        """The seed the next episode of ``robot``'s task uses."""
        base = self.seed if self.seed is not None else self.tasks[robot].task_seed
        return base + self.episode

    def begin(self) -> dict[str, int]:
        """Reset every task's scene for the next episode and start judging; returns robot → seed."""
        self.abort()
        seeds: dict[str, int] = {}
        for rid, task in self.tasks.items():
            seed = self.next_seed(rid)
            drawn = _json(task.begin_task(seed))
            self._begun[rid] = (
                {"robot": rid, "episode_index": self.episode, **drawn, "seed": seed},
                _Watcher(task, rid),
            )
            seeds[rid] = seed
        self.episode += 1
        return seeds

    def finish(self) -> list[TaskResult]:
        """Judge every begun task now; returns the results (empty when none was begun)."""
        results = []
        for rid, (record, watcher) in self._begun.items():
            check, since = watcher.finish()
            success = check.success
            results.append(
                TaskResult(
                    rid,
                    {
                        **record,
                        "success": success,
                        "reason": check.reason,
                        "checks": watcher.checks,
                        "time_to_success_s": None if since is None else round(since, 3),
                        "final": {k: _finite(v) for k, v in check.values.items()},
                    },
                    success,
                    since,
                )
            )
        self._begun.clear()
        return results

    def abort(self) -> None:
        """Stop judging without a result (an episode that ended in an exception)."""
        for _, watcher in self._begun.values():
            watcher.finish()
        self._begun.clear()


def _finite(value: float) -> JsonValue:
    return round(value, 6) if math.isfinite(value) else None


def _json(value: Mapping[str, object]) -> dict[str, JsonValue]:
    out: dict[str, JsonValue] = {}
    for key, item in value.items():
        out[str(key)] = _json_value(item)
    return out


def _json_value(item: Any) -> JsonValue:
    if item is None or isinstance(item, bool | int | float | str):
        return item
    if isinstance(item, Mapping):
        return _json(item)
    if isinstance(item, list | tuple):
        return [_json_value(v) for v in item]
    raise TelerigError(f"task record value {item!r} is not JSON data")
