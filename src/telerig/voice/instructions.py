"""Operator instructions per episode (seed 002's task-independent metric), kept beside the episode.

An *instruction* is one discrete operator command that reached the rig during the episode, from
any source (voice, ``telerig say``/``session``/``safety``, the web UI): an episode command on
``coordinator/command``, a safety command on ``safety/command``, a text command to a robot's aid
(``wbc_mode_command`` = mode, ``fixture_command`` = constraint, ``motion_scale_command`` = scale,
``plan_command`` = plan: making, executing or cancelling a mobile reach plan; a ``target``
designation is the marker pointing, not an instruction) and a view chosen on ``voice/view``
(perspective). They are counted from the episode's recorded
MCAP, which has every one of those streams, and written to ``instructions.json`` (a sidecar, see
:mod:`telerig.store.sidecar`). Phrases the grammar rejected (``voice/feedback``) are counted apart:
they cost the operator effort but instructed nothing.

TeMoto's efficiency of a supervisory feature is :func:`eta`, the instructions a task took without
it over those it took with it (seed 002, eq. 7). For the mobile reach planner
(:mod:`telerig.retarget.reach_plan`) the record keeps that ratio per episode: each reach the
planner carried out (a ``done`` plan on the robot's ``plan`` stream) took two instructions (plan,
execute) where driving it by hand takes the plan's ``manual`` count
(:func:`telerig.retarget.mobile_reach.manual_instructions`: drive, turn, switch mode, move the hand).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from telerig.bus.catalogue import COMMAND, COORDINATOR, FEEDBACK, PLAN, SAFETY, VIEW, VOICE
from telerig.bus.topics import Topic
from telerig.errors import RecordingError
from telerig.ir.mcap_log import read_json
from telerig.store.sidecar import read_sidecar, write_sidecar

__all__ = [
    "INSTRUCTIONS_FILE",
    "PLANNED_REACH_INSTRUCTIONS",
    "InstructionsRecord",
    "count_instructions",
    "eta",
    "read_episode_instructions",
    "write_episode_instructions",
]

#: File name in the episode directory.
INSTRUCTIONS_FILE = "instructions.json"
_MCAP = "episode.mcap"
_AID_GROUPS = {
    "wbc_mode_command": "mode",
    "fixture_command": "constraint",
    "motion_scale_command": "scale",
    "plan_command": "plan",
}
#: Instructions one planned reach takes: the plan and its confirmation.
PLANNED_REACH_INSTRUCTIONS = 2
#: Most instructions the reach takes by hand (:func:`~telerig.retarget.mobile_reach.manual_instructions`).
_MAX_MANUAL = 4
#: Longest aid text command counted [characters] (the catalogue caps text payloads at 1 kB).
_MAX_TEXT = 1024


class InstructionsRecord(BaseModel):
    """``instructions.json``: the operator instructions of one episode.

    Attributes:
        episode_id: The episode (its directory's name).
        total: Instructions in the episode.
        by_group: Per group: ``episode``, ``safety``, ``mode``, ``constraint``, ``scale``,
            ``perspective``.
        rejected: Voice or text phrases the grammar rejected (not instructions).
        malformed: Messages on those streams that were not a command (dropped, not counted).
        reaches: Mobile reaches the planner carried out (plans that reached ``done``).
        reach_manual_instructions: Instructions those reaches take without the planner.
        reach_eta: ``reach_manual_instructions / (2 * reaches)``, seed 002's eta of the planner;
            None without a reach.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    episode_id: str = Field(min_length=1, max_length=200)
    total: int = Field(ge=0)
    by_group: dict[str, int]
    rejected: int = Field(default=0, ge=0)
    malformed: int = Field(default=0, ge=0)
    reaches: int = Field(default=0, ge=0)
    reach_manual_instructions: int = Field(default=0, ge=0)
    reach_eta: float | None = Field(default=None, ge=0)


def count_instructions(mcap: Path, episode_id: str) -> InstructionsRecord:
    """Count the instructions recorded in an episode's MCAP (see the module docs).

    Raises:
        RecordingError: The file is missing or not MCAP.
    """
    groups: Counter[str] = Counter()
    rejected = malformed = 0
    done: dict[tuple[str, str], int] = {}  # (robot, plan id) -> manual instructions
    for topic_name, value, _ in read_json(mcap):
        topic = Topic.try_parse(topic_name)
        if topic is None:
            continue
        node, stream = topic.node, topic.stream
        if stream == COMMAND and node in (COORDINATOR, SAFETY):
            if isinstance(value, dict) and isinstance(value.get("command"), str):
                groups["episode" if node == COORDINATOR else "safety"] += 1
            else:
                malformed += 1
        elif stream in _AID_GROUPS:
            if isinstance(value, str) and 0 < len(value.strip()) <= _MAX_TEXT:
                if not (stream == "plan_command" and value.split()[0].lower() == "target"):
                    groups[_AID_GROUPS[stream]] += 1
            else:
                malformed += 1
        elif stream == PLAN and isinstance(value, dict):
            plan_id, manual = value.get("id"), value.get("manual")
            if value.get("status") == "done" and isinstance(plan_id, str) and len(plan_id) <= 64:
                if isinstance(manual, int) and 0 <= manual <= _MAX_MANUAL:
                    done[(node, plan_id)] = manual
                else:
                    malformed += 1
        elif node == VOICE and stream == VIEW:
            if isinstance(value, dict) and isinstance(value.get("view"), str):
                groups["perspective"] += 1
            else:
                malformed += 1
        elif node == VOICE and stream == FEEDBACK and isinstance(value, dict):
            rejected += value.get("status") == "rejected"
    reaches, manual = len(done), sum(done.values())
    return InstructionsRecord(
        episode_id=episode_id,
        total=sum(groups.values()),
        by_group=dict(sorted(groups.items())),
        rejected=rejected,
        malformed=malformed,
        reaches=reaches,
        reach_manual_instructions=manual,
        reach_eta=eta(manual, PLANNED_REACH_INSTRUCTIONS * reaches) if reaches else None,
    )


def write_episode_instructions(
    episode_dir: Path, record: InstructionsRecord | None = None
) -> InstructionsRecord:
    """Count the instructions of the episode in ``episode_dir`` and write ``instructions.json``.

    Args:
        episode_dir: The episode's directory.
        record: The counts, when already made from this episode's MCAP (the recorder puts them in
            the manifest first); counted from ``episode.mcap`` when None.

    Raises:
        RecordingError: No ``episode.mcap`` there, or the sidecar cannot be written.
    """
    episode_dir = Path(episode_dir)
    mcap = episode_dir / _MCAP
    if not mcap.is_file():
        raise RecordingError(f"{episode_dir} has no {_MCAP}: is it an episode directory?")
    if record is None or record.episode_id != episode_dir.name:
        record = count_instructions(mcap, episode_dir.name)
    write_sidecar(episode_dir, INSTRUCTIONS_FILE, record.model_dump_json(indent=1) + "\n")
    return record


def read_episode_instructions(episode_dir: Path) -> InstructionsRecord | None:
    """The episode's ``instructions.json``; ``None`` when it has none.

    Raises:
        RecordingError: The file is not an instructions record of this episode (one line).
    """
    return read_sidecar(
        Path(episode_dir),
        INSTRUCTIONS_FILE,
        InstructionsRecord,
        what="an instructions record",
        max_bytes=64 << 10,
        redo="delete it and count again (telerig.voice.instructions.write_episode_instructions)",
    )


def eta(without: int, with_feature: int) -> float:
    """Seed 002's efficiency: instructions a task took without a feature over those it took with it.

    Raises:
        ValueError: a count is negative, or ``with_feature`` is 0 (no instruction: undefined).
    """
    if without < 0 or with_feature <= 0:
        raise ValueError(
            f"need without >= 0 and with_feature > 0 instructions, got {without} and {with_feature}"
        )
    return without / with_feature
