"""Virtual fixtures: constrain commanded motion to keep orientation, follow an axis, or stay in a plane."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import JsonValue

from telerig.ir.types import FloatArray, Sample
from telerig.retarget.clutch import button_held

__all__ = ["FREE", "Fixture", "FixtureKind", "FixtureSet"]

#: ``free``: no constraint; ``orientation``: keep the orientation, translate freely; ``axis``: translate
#: only along ``axis``; ``plane``: translate only in the plane whose normal is ``axis``.
FixtureKind = Literal["free", "orientation", "axis", "plane"]

_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True, slots=True)
class Fixture:
    """One virtual fixture, acting on the motion from an anchor pose.

    Attributes:
        name: Name shown in the UI and used by bus commands.
        kind: See :data:`FixtureKind`.
        axis: Unit direction (``axis``) or plane normal (``plane``) in the robot base frame; (0, 0, 0)
            for ``free`` and ``orientation``. Shape (3,).
        keep_orientation: Also hold the anchor orientation (always true for ``orientation``).
    """

    name: str
    kind: FixtureKind
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    keep_orientation: bool = False

    def __post_init__(self) -> None:
        if self.kind in ("axis", "plane"):
            n = math.sqrt(sum(c * c for c in self.axis))
            if not (math.isfinite(n) and n > 1e-9):
                raise ValueError(f"fixture {self.name!r}: {self.kind} needs a non-zero axis, got {self.axis}")
            object.__setattr__(self, "axis", tuple(float(c) / n for c in self.axis))
        else:
            object.__setattr__(self, "axis", (0.0, 0.0, 0.0))
        if self.kind == "orientation":
            object.__setattr__(self, "keep_orientation", True)

    def constrain(self, translation: FloatArray, rotation: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Remove the constrained components of a motion from the anchor.

        Args:
            translation: Displacement from the anchor position [m], robot base frame. Shape (3,).
            rotation: Rotation from the anchor orientation (w, x, y, z), base frame (applied on the
                left: ``q = rotation * q_anchor``). Shape (4,).

        Returns:
            The allowed displacement (3,) and rotation (4,).
        """
        if self.kind == "axis":
            a = np.array(self.axis)
            translation = float(translation @ a) * a
        elif self.kind == "plane":
            n = np.array(self.axis)
            translation = translation - float(translation @ n) * n
        if self.keep_orientation:
            rotation = _IDENTITY
        return translation, rotation

    def to_json(self) -> dict[str, JsonValue]:
        return {
            "name": self.name,
            "kind": self.kind,
            "axis": list(self.axis),
            "keep_orientation": self.keep_orientation,
        }


#: The unconstrained fixture.
FREE = Fixture("free", "free")


class FixtureSet:
    """The fixtures an operator can switch between live; the first one is active at start.

    Args:
        fixtures: Fixtures to cycle through, names unique. Non-empty.
        cycle_button: Button that activates the next fixture on press (see
            :func:`~telerig.retarget.clutch.button_held`); None to switch only by bus command.
        frame: Name of the robot base frame the axes are in, for the UI.
    """

    #: Stream the node publishes :meth:`state` on (retained JSON).
    stream = "fixture"

    __slots__ = ("_held", "_index", "cycle_button", "fixtures", "frame", "version")

    def __init__(
        self, fixtures: Sequence[Fixture], *, cycle_button: str | None = None, frame: str = "base"
    ) -> None:
        if not fixtures:
            raise ValueError("a fixture set needs at least one fixture, e.g. 'free'")
        names = [f.name for f in fixtures]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"fixture names must be unique, repeated: {', '.join(dupes)}")
        self.fixtures = tuple(fixtures)
        self.cycle_button = cycle_button
        self.frame = frame
        self._index = 0
        self._held = False
        #: Increments on every switch, so users of the fixture can re-anchor.
        self.version = 0

    @property
    def active(self) -> Fixture:
        """The fixture in force."""
        return self.fixtures[self._index]

    def select(self, name: str) -> bool:
        """Activate the fixture called ``name``; returns whether the active fixture changed.

        Raises:
            ValueError: no fixture has that name.
        """
        for i, fixture in enumerate(self.fixtures):
            if fixture.name == name:
                changed = i != self._index
                self._index = i
                self.version += int(changed)
                return changed
        raise ValueError(
            f"fixture {name!r} does not exist. Available: {', '.join(f.name for f in self.fixtures)}"
        )

    def cycle(self) -> bool:
        """Activate the next fixture (wrapping); returns whether the active fixture changed."""
        if len(self.fixtures) == 1:
            return False
        self._index = (self._index + 1) % len(self.fixtures)
        self.version += 1
        return True

    def update(self, sample: Sample) -> bool:
        """Cycle on the press edge of ``cycle_button``; returns whether the active fixture changed."""
        held = self.cycle_button is not None and button_held(sample, self.cycle_button)
        pressed = held and not self._held
        self._held = held
        return self.cycle() if pressed else False

    def command(self, text: str) -> bool:
        """Apply a bus command: ``next``, a fixture name, or ``kind:<kind>`` (the first fixture of that
        :data:`FixtureKind`: what a voice command such as "keep orientation" asks for, since names
        are the rig's); returns whether the active fixture changed.

        Raises:
            ValueError: no fixture has that name or kind.
        """
        word = text.strip()
        if word == "next":
            return self.cycle()
        if word.startswith("kind:"):
            kind = word[len("kind:") :]
            for fixture in self.fixtures:
                if fixture.kind == kind:
                    return self.select(fixture.name)
            have = ", ".join(f"{f.name} ({f.kind})" for f in self.fixtures)
            raise ValueError(f"no fixture of kind {kind!r}. Available: {have}")
        return self.select(word)

    def state(self) -> dict[str, JsonValue]:
        """What a UI draws: the active fixture, its frame and the available names."""
        return {
            **self.active.to_json(),
            "frame": self.frame,
            "options": [f.name for f in self.fixtures],
        }
