"""Who drives a robot part that several sources are bound to: a policy, and an operator who takes over.

Rig bindings of one robot part with different ``priority`` become the :class:`Source` list of one
:class:`Handover`, which the robot's control node asks every tick which source drives the joints
and the gripper. In ``auto`` mode (the default) the highest-priority *engaged* source drives: a
source with a ``takeover_button`` is engaged while the button is held in its fresh samples (the
relative-mode clutch: holding it is the intervention), one without while its samples are fresh (a
policy). When an operator lets go, control goes back after ``hand_back_s`` (so a re-clutch does not
hand back). Operators' commands on ``<robot>/control_command``: ``operator`` (the highest-priority
operator drives until told otherwise, engaged or not), ``policy`` (the policy drives, until the
operator engages again) and ``auto``. The state is the ``control`` aid (retained JSON); every tick
the node publishes who drove on ``control_source`` (recorded), so every recorded tick of a rollout
says whether the policy or the operator was in control, and where the interventions were.

A handover never makes the robot jump: the incoming source's retargeter is reset, so an operator in
relative mode anchors on the current end-effector pose (its first target is where the arm is), and a
policy blends in from the commanded pose (:class:`~telerig.retarget.joints.passthrough.JointPassthrough`)
while the safety chain keeps tracking from the last command through its start-up ramp; the chain's
velocity and acceleration limits hold throughout. Absolute-mode operator sources are refused for
takeover (they would pull the arm to the hand).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from pydantic import JsonValue

from telerig.bus.catalogue import CONTROL
from telerig.errors import ConfigError
from telerig.ir.types import Sample
from telerig.retarget.binding import GripperRetargeter, Retargeter
from telerig.retarget.clutch import button_held

__all__ = ["CONTROL_MODES", "ControlMode", "Handover", "Source", "SourceKind"]

#: What kind of source drives: a trained policy or a person.
SourceKind = Literal["policy", "operator"]
#: ``auto``: priority and engagement decide; ``operator`` / ``policy``: that kind drives.
ControlMode = Literal["auto", "operator", "policy"]
CONTROL_MODES: tuple[ControlMode, ...] = ("auto", "operator", "policy")


@dataclass(slots=True)
class Source:
    """One device stream bound to the robot, with the parts it drives.

    Attributes:
        topic: The device stream's topic.
        device: Its device id.
        kind: ``policy`` or ``operator``.
        priority: Higher takes over from lower.
        joints: Its retargeter of the commanded joints, if it drives them.
        gripper: Its gripper retargeter, if it drives the gripper.
        takeover_button: Engaged while this button is held; None: while its samples are fresh.
    """

    topic: str
    device: str
    kind: SourceKind
    priority: int
    joints: Retargeter | None = None
    gripper: GripperRetargeter | None = None
    takeover_button: str | None = None
    seen_ns: int = 0
    held: bool = False
    released_ns: int = 0


class Handover:
    """Arbitrates the sources of one robot (see the module docs); an aid on the ``control`` stream.

    Args:
        sources: At least one; priorities must differ.
        fresh_s: A source without a takeover button is engaged while its last sample is younger [s].
        hand_back_s: After an operator lets go, how long control stays with it [s].

    Raises:
        ConfigError: no source, or two of the same priority.
    """

    stream = CONTROL

    def __init__(self, sources: Sequence[Source], *, fresh_s: float = 0.25, hand_back_s: float = 0.5) -> None:
        if not sources:
            raise ConfigError("a handover needs at least one source")
        priorities = [s.priority for s in sources]
        if len(set(priorities)) != len(priorities):
            raise ConfigError(f"sources of one robot part need different priorities, got {priorities}")
        self.sources = tuple(sorted(sources, key=lambda s: -s.priority))
        self._fresh_ns = int(fresh_s * 1e9)
        self._hand_back_ns = int(hand_back_s * 1e9)
        self.mode: ControlMode = "auto"
        self.active: Source | None = None
        #: Control changes from one source to another (the first selection is none).
        self.handovers = 0
        #: Handovers to an operator (interventions).
        self.interventions = 0
        self._policy_pinned = False

    @property
    def topics(self) -> frozenset[str]:
        return frozenset(s.topic for s in self.sources)

    def _engaged(self, source: Source, now_ns: int) -> bool:
        fresh = now_ns - source.seen_ns <= self._fresh_ns if source.seen_ns else False
        if source.takeover_button is None:
            return fresh
        return fresh and source.held

    def select(self, latest: Mapping[str, Sample], now_ns: int) -> tuple[Source | None, bool]:
        """This tick's driving source, and whether control changed hands this tick.

        Args:
            latest: This tick's admitted samples by topic.
            now_ns: The control node's time [ns].
        """
        for source in self.sources:
            sample = latest.get(source.topic)
            if sample is None:
                continue
            source.seen_ns = now_ns
            if source.takeover_button is not None:
                held = button_held(sample, source.takeover_button)
                if source.held and not held:
                    source.released_ns = now_ns
                if held and not source.held:
                    self._policy_pinned = False  # an operator's press always takes over
                source.held = held
        chosen = self._choose(now_ns)
        previous = self.active
        if chosen is None:
            chosen = previous  # nobody engaged: whoever drove keeps the part (it holds or times out)
        switched = chosen is not previous and previous is not None
        if switched:
            self.handovers += 1
            if chosen is not None and chosen.kind == "operator":
                self.interventions += 1
        self.active = chosen
        return chosen, switched

    def _choose(self, now_ns: int) -> Source | None:
        if self.mode == "operator":
            return next((s for s in self.sources if s.kind == "operator"), None)
        if self.mode == "policy" or self._policy_pinned:
            policy = next((s for s in self.sources if s.kind == "policy"), None)
            if policy is not None:
                return policy
        active = self.active
        for source in self.sources:
            if self._engaged(source, now_ns):
                # Letting go of the button hands back only after hand_back_s (a re-clutch keeps it).
                if (
                    active is not None
                    and active is not source
                    and active.priority > source.priority
                    and active.takeover_button is not None
                    and now_ns - active.released_ns < self._hand_back_ns
                    and now_ns - active.seen_ns <= self._fresh_ns
                ):
                    return active
                return source
        return None

    def reset_counts(self) -> None:
        """Start counting handovers and interventions afresh (a new episode)."""
        self.handovers = self.interventions = 0

    # -- the Aid protocol (state on ``control``, commands on ``control_command``) ---------------

    def update(self, sample: Sample) -> bool:
        """Buttons are read in :meth:`select`; nothing to do here."""
        return False

    def command(self, text: str) -> bool:
        """``operator``, ``policy`` or ``auto``; ValueError for anything else."""
        word = text.strip().lower()
        if word not in CONTROL_MODES:
            raise ValueError(f"control command {text[:40]!r} is not one of {', '.join(CONTROL_MODES)}")
        if word == "policy":
            # The policy drives now; an operator's next press still takes over (safety first).
            changed = self.mode != "auto" or not self._policy_pinned
            self.mode, self._policy_pinned = "auto", True
            for source in self.sources:
                source.held = False
            return changed
        changed = self.mode != word or self._policy_pinned
        self.mode, self._policy_pinned = word, False
        return changed

    def state(self) -> dict[str, JsonValue]:
        active = self.active
        return {
            "mode": "policy" if self._policy_pinned else self.mode,
            "active": None if active is None else active.device,
            "kind": None if active is None else active.kind,
            "handovers": self.handovers,
            "interventions": self.interventions,
            "sources": [{"device": s.device, "kind": s.kind, "priority": s.priority} for s in self.sources],
        }
