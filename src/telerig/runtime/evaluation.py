"""Task runs and their statistics: unattended episodes of a task rig (``telerig collect`` /
``telerig eval``), success with a Wilson 95 % interval, mean time to success, and a paired exact
McNemar test between two checkpoints rolled out on the same seeds.

Why these statistics: with 50 episodes a success rate's normal-approximation interval is wrong near
0 and 1 (it can leave [0, 1]); Wilson's score interval keeps its coverage there (Brown, Cai and
DasGupta 2001). Two checkpoints evaluated on identical seeds are paired: only the seeds where they
disagree carry information about which is better, and under "no difference" each disagreement is a
fair coin, so the exact two-sided binomial test on the discordant pairs (McNemar's exact test) is
the test, with no large-sample assumption.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

from telerig.config.schema import RigConfig
from telerig.errors import RecordingError
from telerig.runtime.rig import EpisodeResult, RigRuntime

__all__ = [
    "Z95",
    "PairedComparison",
    "TaskEpisode",
    "TaskSummary",
    "compare_paired",
    "mcnemar_exact",
    "run_task_episodes",
    "summarize",
    "task_episode",
    "wilson_interval",
]

#: The standard normal's 97.5 % quantile: a two-sided 95 % interval.
Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); ``(0, 1)`` when ``n`` is 0.

    Raises:
        ValueError: counts out of range.
    """
    if n < 0 or not 0 <= successes <= max(n, 0):
        raise ValueError(f"successes must be in [0, n] with n >= 0, got {successes} of {n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    # At k = 0 and k = n the bound is exactly 0 or 1; the formula leaves a rounding error there.
    lo = 0.0 if successes == 0 else max(0.0, center - half)
    hi = 1.0 if successes == n else min(1.0, center + half)
    return lo, hi


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided p-value of McNemar's exact test from the discordant pairs: ``only_a`` seeds where
    only A succeeded, ``only_b`` where only B did (1.0 when there are none).

    Raises:
        ValueError: a negative count.
    """
    if only_a < 0 or only_b < 0:
        raise ValueError(f"discordant counts must be >= 0, got {only_a}, {only_b}")
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    tail = Fraction(sum(math.comb(n, i) for i in range(k + 1)), 2**n)  # exact for any n
    return min(1.0, float(2 * tail))


@dataclass(frozen=True, slots=True)
class TaskEpisode:
    """One episode of a task run, as its manifest recorded it.

    Attributes:
        episode_id: The episode.
        status: ``complete`` or ``incomplete``.
        seed: The task seed it ran with; None when the manifest has no task record.
        success: The scene's verdict (False when there is none).
        time_to_success_s: When the final success began [s after start]; None without success.
        reason: The check's one line (``ok`` or what failed).
        gates: The quality gates' verdict (``pass``, ``fail``...) or None when they did not run.
    """

    episode_id: str
    status: str
    seed: int | None
    success: bool
    time_to_success_s: float | None
    reason: str
    gates: str | None = None


def task_episode(result: EpisodeResult, gates: str | None = None) -> TaskEpisode:
    """The task verdict of a recorded episode, read from its manifest (where it lies now).

    Raises:
        RecordingError: the manifest cannot be read.
    """
    path = result.path / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RecordingError(f"episode {result.episode_id}: cannot read {path}: {exc}") from None
    extra = manifest.get("extra") if isinstance(manifest, dict) else None
    task = extra.get("task") if isinstance(extra, dict) else None
    if not isinstance(task, dict):
        return TaskEpisode(result.episode_id, result.status, None, False, None, "no task record", gates)
    seed = task.get("seed")
    tts = task.get("time_to_success_s")
    success = task.get("success") is True and result.status == "complete"
    return TaskEpisode(
        result.episode_id,
        result.status,
        seed if isinstance(seed, int) else None,
        success,
        float(tts) if isinstance(tts, int | float) and success else None,
        str(task.get("reason", "")),
        gates,
    )


@dataclass(frozen=True, slots=True)
class TaskSummary:
    """Success over a run.

    Attributes:
        episodes: Episodes judged.
        successes: Of them, successes.
        rate: ``successes / episodes`` (NaN without episodes).
        interval: Wilson 95 % interval of the rate.
        mean_time_to_success_s: Over the successes [s]; NaN without any.
        gates: Gate verdict → episodes (``none`` where the gates did not run).
    """

    episodes: int
    successes: int
    rate: float
    interval: tuple[float, float]
    mean_time_to_success_s: float
    gates: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, object]:
        return {
            "episodes": self.episodes,
            "successes": self.successes,
            "rate": None if math.isnan(self.rate) else self.rate,
            "wilson95": list(self.interval),
            "mean_time_to_success_s": (
                None if math.isnan(self.mean_time_to_success_s) else self.mean_time_to_success_s
            ),
            "gates": dict(self.gates),
        }


def summarize(episodes: Sequence[TaskEpisode]) -> TaskSummary:
    """Success rate, Wilson interval, mean time to success and gate verdicts of a run."""
    n = len(episodes)
    k = sum(e.success for e in episodes)
    times = [e.time_to_success_s for e in episodes if e.success and e.time_to_success_s is not None]
    gates: dict[str, int] = {}
    for e in episodes:
        gates[e.gates or "none"] = gates.get(e.gates or "none", 0) + 1
    return TaskSummary(
        n,
        k,
        k / n if n else math.nan,
        wilson_interval(k, n),
        sum(times) / len(times) if times else math.nan,
        gates,
    )


@dataclass(frozen=True, slots=True)
class PairedComparison:
    """Two runs on identical seeds.

    Attributes:
        pairs: Seeds both ran.
        both: Seeds where both succeeded; ``neither`` where both failed.
        only_a: Seeds where only A succeeded; ``only_b`` where only B did.
        p_value: McNemar's exact two-sided p-value.
        significant: ``p_value < alpha``.
        alpha: The level it was judged at.
    """

    pairs: int
    both: int
    only_a: int
    only_b: int
    neither: int
    p_value: float
    significant: bool
    alpha: float = 0.05

    def to_json(self) -> dict[str, object]:
        return {
            "pairs": self.pairs,
            "both": self.both,
            "only_a": self.only_a,
            "only_b": self.only_b,
            "neither": self.neither,
            "mcnemar_exact_p": self.p_value,
            "significant": self.significant,
            "alpha": self.alpha,
        }


def compare_paired(
    a: Sequence[TaskEpisode], b: Sequence[TaskEpisode], alpha: float = 0.05
) -> PairedComparison:
    """Pair two runs by seed and test their difference (McNemar exact).

    Raises:
        ValueError: the runs do not cover the same seeds, or an episode has no seed.
    """
    by_a = {e.seed: e for e in a}
    by_b = {e.seed: e for e in b}
    if None in by_a or None in by_b or set(by_a) != set(by_b) or len(by_a) != len(a) or len(by_b) != len(b):
        raise ValueError("a paired comparison needs both runs on the same seeds, each seed once")
    both = only_a = only_b = neither = 0
    for seed, ea in by_a.items():
        sa, sb = ea.success, by_b[seed].success
        both += sa and sb
        only_a += sa and not sb
        only_b += sb and not sa
        neither += not sa and not sb
    p = mcnemar_exact(only_a, only_b)
    return PairedComparison(len(by_a), both, only_a, only_b, neither, p, p < alpha, alpha)


#: Called after each episode with (index from 0, its result).
EpisodeCallback = Callable[[int, TaskEpisode], None]
#: Called during an episode with (elapsed, total) seconds.
Elapsed = Callable[[float, float], None]


def run_task_episodes(
    config: RigConfig,
    *,
    episodes: int,
    seed: int | None,
    data_root: Path | None = None,
    duration_s: float | None = None,
    on_start: Callable[[int], Elapsed | None] | None = None,
    on_episode: EpisodeCallback | None = None,
    gates_wait_s: float = 30.0,
) -> list[TaskEpisode]:
    """Run ``episodes`` episodes of a task rig unattended: the scene reset from seed ``seed + k``
    before episode ``k``, everything recorded, success judged from the scene.

    An episode that ends incomplete counts as a failure of its seed (it is not run again: the
    seeds stay the ones asked for, so two runs stay paired).

    Args:
        config: A rig with a task robot (see :func:`telerig.runtime.task.with_task_seed`).
        episodes: How many.
        seed: Base seed; the task robot's own when None.
        data_root: Where episodes go; the rig's when None.
        duration_s: Seconds per episode; the rig's when None.
        on_start: Called with the episode index before it starts; may return a progress callback.
        on_episode: Called with each finished episode.
        gates_wait_s: How long to wait for each episode's quality gates at the end [s].
    """
    results: list[tuple[EpisodeResult, int]] = []
    with RigRuntime(config, data_root=data_root, task_seed=seed) as runtime:
        if not runtime.tasks:
            raise RecordingError(
                f"rig {config.name!r} has no randomized task on this station "
                "(a robot of type mujoco_pick_place)"
            )
        for k in range(episodes):
            progress = on_start(k) if on_start is not None else None
            result = runtime.run_episode(duration_s, progress=progress)
            results.append((result, k))
            if on_episode is not None:
                on_episode(k, task_episode(result))
        out = []
        for result, _ in results:
            outcome = runtime.storage.qa_outcome(result.episode_id, gates_wait_s)
            verdict = None if outcome is None else ("pass" if outcome.passed else "fail")
            out.append(task_episode(result, verdict))
    return out
