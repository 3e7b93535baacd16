"""Motion scaling knob: a logarithmic factor on relative motion, stepped live by buttons or bus commands."""

from __future__ import annotations

import math

from pydantic import JsonValue

from telerig.ir.types import Sample
from telerig.retarget.clutch import button_held

__all__ = ["ScaleKnob"]


class ScaleKnob:
    """Scale factor in ``[minimum, maximum]``, multiplied or divided by ``step_factor`` per button press.

    Steps are multiplicative, so the knob moves evenly on a log scale: with the default factor 2,
    ten presses cover three decades. A 15 cm hand motion at scale 0.005 is a 0.75 mm tool move.

    Args:
        initial: Starting scale (dimensionless), clamped into the range.
        minimum: Smallest scale, > 0.
        maximum: Largest scale, >= ``minimum``.
        step_factor: Factor per press, > 1.
        up_button: Button that multiplies by ``step_factor`` on press (see
            :func:`~telerig.retarget.clutch.button_held`); None for none.
        down_button: Button that divides by ``step_factor`` on press; None for none.
    """

    #: Stream the node publishes :meth:`state` on (retained JSON).
    stream = "motion_scale"

    __slots__ = (
        "_down_held",
        "_scale",
        "_up_held",
        "down_button",
        "maximum",
        "minimum",
        "step_factor",
        "up_button",
        "version",
    )

    def __init__(
        self,
        initial: float = 1.0,
        *,
        minimum: float = 1e-3,
        maximum: float = 100.0,
        step_factor: float = 2.0,
        up_button: str | None = None,
        down_button: str | None = None,
    ) -> None:
        if not (math.isfinite(minimum) and minimum > 0 and math.isfinite(maximum) and maximum >= minimum):
            raise ValueError(f"need 0 < minimum <= maximum, got {minimum} and {maximum}")
        if not (math.isfinite(step_factor) and step_factor > 1.0):
            raise ValueError(f"step_factor must be > 1, got {step_factor}")
        if not (math.isfinite(initial) and initial > 0):
            raise ValueError(f"initial scale must be > 0, got {initial}")
        if up_button is not None and up_button == down_button:
            raise ValueError(f"up_button and down_button must differ, both are {up_button!r}")
        self.minimum = float(minimum)
        self.maximum = float(maximum)
        self.step_factor = float(step_factor)
        self.up_button = up_button
        self.down_button = down_button
        self._scale = min(self.maximum, max(self.minimum, float(initial)))
        self._up_held = False
        self._down_held = False
        #: Increments on every change, so users of the scale can re-anchor.
        self.version = 0

    @property
    def scale(self) -> float:
        """Current scale factor (dimensionless)."""
        return self._scale

    def set(self, value: float) -> bool:
        """Set the scale, clamped into the range; returns whether it changed (non-finite or <= 0: ignored)."""
        if not (math.isfinite(value) and value > 0):
            return False
        new = min(self.maximum, max(self.minimum, float(value)))
        if new == self._scale:
            return False
        self._scale = new
        self.version += 1
        return True

    def step(self, steps: int) -> bool:
        """Multiply by ``step_factor ** steps`` (clamped); returns whether the scale changed."""
        return self.set(self._scale * self.step_factor**steps)

    def update(self, sample: Sample) -> bool:
        """Step on the press edges of the up/down buttons in ``sample``; returns whether the scale changed."""
        up = self.up_button is not None and button_held(sample, self.up_button)
        down = self.down_button is not None and button_held(sample, self.down_button)
        steps = int(up and not self._up_held) - int(down and not self._down_held)
        self._up_held, self._down_held = up, down
        return self.step(steps) if steps else False

    def command(self, text: str) -> bool:
        """Apply a bus command: ``up``, ``down`` or a number (the new scale); returns whether it changed.

        Raises:
            ValueError: ``text`` is none of those.
        """
        word = text.strip().lower()
        if word == "up":
            return self.step(1)
        if word == "down":
            return self.step(-1)
        try:
            value = float(word)
        except ValueError:
            raise ValueError(f"motion scale command must be 'up', 'down' or a number, got {text!r}") from None
        return self.set(value)

    def state(self) -> dict[str, JsonValue]:
        """What a UI shows: the scale and its range."""
        return {
            "scale": self._scale,
            "min": self.minimum,
            "max": self.maximum,
            "step_factor": self.step_factor,
        }
