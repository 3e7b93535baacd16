"""The operator command grammar: one table of phrases → commands, read by speech (JSGF) and text alike.

Every command maps onto a bus path that already exists (seed 002, TeMoto's instruction parser):

* mode switches → the whole-body controller's aid (``<robot>/wbc_mode_command``: ``whole_body``
  drives the base, ``ee`` moves the hand; :class:`~telerig.retarget.whole_body.WholeBodySwitches`);
* constraints → the virtual fixtures aid (``<robot>/fixture_command``), chosen by fixture *kind*
  (``plane``, ``orientation``, ``axis``, ``free``) among the fixtures the robot publishes, since
  fixture names are the rig's;
* scale → the motion scale aid (``<robot>/motion_scale_command``: ``up``, ``down``, a number);
* episode control → an episode command on ``coordinator/command`` (as ``telerig session`` sends);
* e-stop and its release → a safety command on ``safety/command`` (as ``telerig safety`` sends);
* perspective → the operator scene's view, retained JSON ``{"view": ...}`` on ``R/voice/view``
  (UI only: it moves no robot);
* plans → the robot's mobile reach planner (``<robot>/plan_command``,
  :mod:`telerig.retarget.reach_plan`): ``plan reach`` plans to the target the operator's marker
  designates and shows the preview; it also stages ``execute plan`` (critical), so ``robot please
  execute`` then runs the staged plan by its id; ``cancel`` drops or stops it.

Criticality: a command that lets a robot move (releasing the e-stop, executing a plan) is
*critical*: it is only staged, and runs when the operator then says the three distinct words
``robot please execute`` (TeMoto's rule, seed 002 §3.2). Everything else (mode, constraint, scale,
view, episode, e-stop, making or cancelling a plan) acts at once: it only changes the virtual
workspace, shows a preview or stops motion.

Matching is exact on normalized words (lower case, punctuation dropped). Words that only part of a
phrase has are not guessed at: they are rejected with the nearest phrases to say back (and as
*ambiguous* when they fit phrases of several commands, e.g. ``stop``).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

__all__ = [
    "COMMANDS",
    "CONFIRMATION",
    "MAX_TEXT_CHARS",
    "Action",
    "AidAction",
    "CancelAction",
    "Command",
    "ConfirmAction",
    "FixtureAction",
    "Group",
    "Match",
    "PlanAction",
    "SafetyAction",
    "SessionAction",
    "ViewAction",
    "command_named",
    "normalize",
    "parse",
    "phrases",
]

#: The three words that run a staged critical command (seed 002, Table 1).
CONFIRMATION = "robot please execute"
#: Longest text accepted [characters]; a spoken command is a few words.
MAX_TEXT_CHARS = 200

FixtureKind = Literal["free", "orientation", "axis", "plane"]
#: The operator scene's views (``static/scene.js``): ``navigation`` is top-down, ``manipulation``
#: over the shoulder, ``ee`` / ``ee-inverted`` the natural and inverted end-effector perspectives,
#: ``auto`` follows the control mode.
Perspective = Literal["auto", "navigation", "manipulation", "ee", "ee-inverted"]


class Group(StrEnum):
    """What a command is about (the instruction counts are kept per group)."""

    MODE = "mode"
    CONSTRAINT = "constraint"
    SCALE = "scale"
    PERSPECTIVE = "perspective"
    EPISODE = "episode"
    SAFETY = "safety"
    PLAN = "plan"
    CONFIRM = "confirm"


@dataclass(frozen=True, slots=True)
class SessionAction:
    """An episode command for the coordinator (``start``, ``stop``...; ``outcome`` with ``mark``)."""

    command: Literal["start", "stop", "pause", "resume", "restart", "discard", "mark", "end"]
    outcome: Literal["success", "failure"] | None = None


@dataclass(frozen=True, slots=True)
class SafetyAction:
    """A safety command: ``estop`` or ``reset`` (every robot, or the dispatcher's robot)."""

    command: Literal["estop", "reset"]


@dataclass(frozen=True, slots=True)
class AidAction:
    """A text command to a robot's live aid: ``<robot>/<aid>_command`` carrying ``text``."""

    aid: Literal["wbc_mode", "motion_scale"]
    text: str


@dataclass(frozen=True, slots=True)
class FixtureAction:
    """Select the robot's virtual fixture of this kind (its name comes from the robot's ``fixture`` state)."""

    kind: FixtureKind


@dataclass(frozen=True, slots=True)
class ViewAction:
    """Switch the operator's view (``auto``: follow the control mode)."""

    perspective: Perspective


@dataclass(frozen=True, slots=True)
class PlanAction:
    """A mobile reach plan: make one for the designated target, execute the staged one, cancel it."""

    command: Literal["plan", "execute", "cancel"]


@dataclass(frozen=True, slots=True)
class ConfirmAction:
    """Run the staged critical command."""


@dataclass(frozen=True, slots=True)
class CancelAction:
    """Drop the staged critical command."""


Action = (
    SessionAction
    | SafetyAction
    | AidAction
    | FixtureAction
    | ViewAction
    | PlanAction
    | ConfirmAction
    | CancelAction
)


@dataclass(frozen=True, slots=True)
class Command:
    """One command of the grammar.

    Attributes:
        name: Canonical id, e.g. ``navigation``, ``limit_directions``.
        group: What it is about.
        phrases: The phrasings that mean it (normalized words); the first is the one said back.
        action: What it does.
        critical: Whether it lets a robot move: staged until :data:`CONFIRMATION`.
        done: What the feedback says once it is sent, e.g. ``navigation mode``.
        stages: A critical command staged right after this one is sent (``plan reach`` stages
            ``execute_plan``), so the next phrase may be the confirmation.
    """

    name: str
    group: Group
    phrases: tuple[str, ...]
    action: Action
    done: str
    critical: bool = False
    stages: str | None = None


def _c(
    name: str,
    group: Group,
    action: Action,
    done: str,
    *phrases: str,
    critical: bool = False,
    stages: str | None = None,
) -> Command:
    return Command(name, group, phrases, action, done, critical, stages)


G = Group
#: The grammar. Several phrasings per command; no phrasing belongs to two commands.
COMMANDS: tuple[Command, ...] = (
    _c("navigation", G.MODE, AidAction("wbc_mode", "whole_body"), "navigation mode",
       "navigation", "navigation mode", "drive the base"),
    _c("manipulation", G.MODE, AidAction("wbc_mode", "ee"), "manipulation mode",
       "manipulation", "manipulation mode", "move the arm"),
    _c("limit_directions", G.CONSTRAINT, FixtureAction("plane"), "directions limited to the plane",
       "limit directions", "limit the directions", "stay in the plane"),
    _c("keep_orientation", G.CONSTRAINT, FixtureAction("orientation"), "orientation kept",
       "keep orientation", "lock orientation", "hold orientation"),
    _c("follow_axis", G.CONSTRAINT, FixtureAction("axis"), "motion limited to the axis",
       "follow the axis", "limit to axis"),
    _c("free_motion", G.CONSTRAINT, FixtureAction("free"), "constraints removed",
       "free motion", "remove constraints", "no constraints"),
    _c("scale_up", G.SCALE, AidAction("motion_scale", "up"), "scale up",
       "increase scale", "larger motion", "coarser motion"),
    _c("scale_down", G.SCALE, AidAction("motion_scale", "down"), "scale down",
       "decrease scale", "scale down", "finer motion", "smaller motion"),
    _c("scale_reset", G.SCALE, AidAction("motion_scale", "1"), "scale one",
       "normal scale", "reset scale"),
    _c("view_top_down", G.PERSPECTIVE, ViewAction("navigation"), "top down view",
       "top down view", "view from above"),
    _c("view_over_shoulder", G.PERSPECTIVE, ViewAction("manipulation"), "over the shoulder view",
       "over the shoulder view", "shoulder view"),
    _c("view_natural", G.PERSPECTIVE, ViewAction("ee"), "natural perspective",
       "natural perspective", "natural view"),
    _c("view_inverted", G.PERSPECTIVE, ViewAction("ee-inverted"), "inverted perspective",
       "inverted perspective", "inverted view"),
    _c("view_auto", G.PERSPECTIVE, ViewAction("auto"), "automatic view",
       "automatic view", "follow mode view"),
    _c("episode_start", G.EPISODE, SessionAction("start"), "episode starting",
       "start episode", "start recording", "begin episode"),
    _c("episode_stop", G.EPISODE, SessionAction("stop"), "episode stopped and kept",
       "stop episode", "stop recording", "finish episode"),
    _c("episode_pause", G.EPISODE, SessionAction("pause"), "episode paused",
       "pause episode", "pause recording"),
    _c("episode_resume", G.EPISODE, SessionAction("resume"), "episode resumed",
       "resume episode", "resume recording", "continue recording"),
    _c("episode_restart", G.EPISODE, SessionAction("restart"), "episode restarting",
       "restart episode", "record again"),
    _c("episode_discard", G.EPISODE, SessionAction("discard"), "episode discarded",
       "discard episode", "throw it away"),
    _c("mark_success", G.EPISODE, SessionAction("mark", "success"), "marked success",
       "mark success", "task succeeded"),
    _c("mark_failure", G.EPISODE, SessionAction("mark", "failure"), "marked failure",
       "mark failure", "task failed"),
    _c("session_end", G.EPISODE, SessionAction("end"), "session ending",
       "end session", "finish session"),
    _c("estop", G.SAFETY, SafetyAction("estop"), "emergency stop",
       "emergency stop", "stop the robot", "halt the robot"),
    _c("release_estop", G.SAFETY, SafetyAction("reset"), "emergency stop released",
       "release emergency stop", "reset the robot", "clear the stop", critical=True),
    _c("plan_reach", G.PLAN, PlanAction("plan"), "planning the reach",
       "plan reach", "plan the reach", "plan here", "plan a path", stages="execute_plan"),
    _c("execute_plan", G.PLAN, PlanAction("execute"), "executing the plan",
       "execute plan", "execute the plan", "run the plan", critical=True),
    _c("cancel_plan", G.PLAN, PlanAction("cancel"), "plan cancelled",
       "cancel plan", "cancel the plan", "drop the plan"),
    _c("execute", G.CONFIRM, ConfirmAction(), "executed", CONFIRMATION),
    _c("cancel", G.CONFIRM, CancelAction(), "cancelled", "cancel", "never mind"),
)  # fmt: skip


def _index(commands: Iterable[Command]) -> dict[str, Command]:
    by_phrase: dict[str, Command] = {}
    for command in commands:
        for phrase in command.phrases:
            if phrase != normalize(phrase):
                raise ValueError(f"phrase {phrase!r} of {command.name} is not normalized")
            other = by_phrase.setdefault(phrase, command)
            if other is not command:
                raise ValueError(f"phrase {phrase!r} means both {other.name} and {command.name}")
    return by_phrase


_WORD = re.compile(r"[a-z]+")


def normalize(text: str) -> str:
    """Lower-case words separated by single spaces; punctuation and digits dropped."""
    return " ".join(_WORD.findall(text.lower()))


_BY_PHRASE: Mapping[str, Command] = _index(COMMANDS)
_BY_NAME: Mapping[str, Command] = {c.name: c for c in COMMANDS}


def command_named(name: str) -> Command:
    """The grammar's command called ``name`` (``KeyError`` when there is none)."""
    return _BY_NAME[name]


def phrases() -> tuple[str, ...]:
    """Every phrase of the grammar, in table order (what the recognizer's JSGF allows)."""
    return tuple(p for c in COMMANDS for p in c.phrases)


@dataclass(frozen=True, slots=True)
class Match:
    """What a text means.

    Attributes:
        text: The normalized words.
        command: The command, or ``None`` when rejected.
        reason: Why it was rejected (one line to say back), ``None`` when it matched.
    """

    text: str
    command: Command | None
    reason: str | None = None


def parse(text: str) -> Match:
    """The command ``text`` says, or why it says none.

    Rejected: empty or over :data:`MAX_TEXT_CHARS` characters, unknown phrases (with the nearest
    phrase to try), and ambiguous ones (words that several commands' phrases contain, e.g.
    ``stop`` or ``scale``).
    """
    if len(text) > MAX_TEXT_CHARS:
        return Match(
            "", None, f"too long ({len(text)} characters, at most {MAX_TEXT_CHARS}): say one command"
        )
    words = normalize(text)
    if not words:
        return Match("", None, "no words heard: say a command, e.g. 'navigation'")
    command = _BY_PHRASE.get(words)
    if command is not None:
        return Match(words, command)
    said = set(words.split())
    holders = sorted(
        {c.name: c for p, c in _BY_PHRASE.items() if said <= set(p.split())}.values(),
        key=lambda c: c.name,
    )
    if len(holders) > 1:
        options = " or ".join(f"'{c.phrases[0]}'" for c in holders[:4])
        return Match(words, None, f"'{words}' is ambiguous: say {options}")
    if len(holders) == 1:
        return Match(words, None, f"'{words}' is not a command: did you mean '{holders[0].phrases[0]}'?")
    return Match(words, None, f"'{_clip(words)}' is not a command")


def _clip(words: str, limit: int = 60) -> str:
    return words if len(words) <= limit else words[: limit - 3] + "..."
