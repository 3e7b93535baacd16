"""URScript programs the UR driver uploads: the register-fed servoj loop with a watchdog, and the stop."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

__all__ = ["SCRIPT_PORT", "STOP_WORD", "ServoProgram", "stop_program"]

#: Secondary client interface: a ``def ...: end`` program sent here replaces the running program.
SCRIPT_PORT = 30002
#: Watchdog word that asks the servo loop to stop at once (any negative value does).
STOP_WORD = -1

_TEMPLATE = """\
def telerig_servo():
  # telerig servo loop: targets [rad] from input_double_register_{d0}..{d5},
  # watchdog word from input_int_register_{w} (must change every command; negative = stop).
  textmsg("telerig: servo loop started")
  word_last = read_input_integer_register({w})
  stale_cycles = 0
  armed = False
  while True:
    word = read_input_integer_register({w})
    if word < 0:
      textmsg("telerig: stop requested")
      break
    end
    if word != word_last:
      word_last = word
      stale_cycles = 0
      armed = True
    else:
      stale_cycles = stale_cycles + 1
    end
    if armed:
      if stale_cycles > {stale}:
        textmsg("telerig: watchdog expired, stopping")
        break
      end
      q = [{reads}]
      servoj(q, 0, 0, {period}, {lookahead}, {gain})
    else:
      sync()
    end
  end
  stopj({decel})
end
"""


@dataclass(frozen=True, slots=True)
class ServoProgram:
    """Parameters of the servo loop program.

    The loop idles (``sync()``) until the watchdog word first changes, then every ``period_s``
    calls ``servoj`` on the six double registers. When the word has not changed for more than
    ``watchdog_cycles`` loop cycles, or turns negative, it leaves the loop and calls ``stopj``.

    Attributes:
        int_register: Index of the input integer register holding the watchdog word.
        double_register: Index of the first of six input double registers holding the targets.
        period_s: ``servoj`` time per cycle [s]; the controller period (0.002 on e-Series, 0.008 on CB3).
        lookahead_s: ``servoj`` lookahead time [s], 0.03-0.2 (longer = smoother, more lag).
        gain: ``servoj`` proportional gain, 100-2000.
        watchdog_cycles: Loop cycles without a new word before the program stops.
        stop_deceleration: Joint deceleration of the final ``stopj`` [rad/s^2].
    """

    int_register: int = 0
    double_register: int = 0
    period_s: float = 0.002
    lookahead_s: float = 0.1
    gain: int = 300
    watchdog_cycles: int = 50
    stop_deceleration: float = 4.0

    def __post_init__(self) -> None:
        if not 0 <= self.int_register <= 47:
            raise ValueError(f"int_register must be in 0..47, got {self.int_register}")
        if not 0 <= self.double_register <= 42:
            raise ValueError(f"double_register must be in 0..42 (six registers), got {self.double_register}")
        if not 0.002 <= self.period_s <= 0.1:
            raise ValueError(f"period_s must be in [0.002, 0.1] s, got {self.period_s}")
        if not 0.03 <= self.lookahead_s <= 0.2:
            raise ValueError(f"lookahead_s must be in [0.03, 0.2] s (servoj), got {self.lookahead_s}")
        if not 100 <= self.gain <= 2000:
            raise ValueError(f"gain must be in 100..2000 (servoj), got {self.gain}")
        if self.watchdog_cycles < 1:
            raise ValueError(f"watchdog_cycles must be >= 1, got {self.watchdog_cycles}")
        if self.stop_deceleration <= 0:
            raise ValueError(f"stop_deceleration must be positive, got {self.stop_deceleration}")

    @property
    def double_registers(self) -> tuple[int, ...]:
        """The six double register indices, base joint first."""
        return tuple(range(self.double_register, self.double_register + 6))

    def render(self) -> str:
        """The URScript program text (ends with a newline, as the controller needs)."""
        reads = ", ".join(f"read_input_float_register({i})" for i in self.double_registers)
        return _TEMPLATE.format(
            w=self.int_register,
            d0=self.double_register,
            d5=self.double_register + 5,
            stale=self.watchdog_cycles,
            reads=reads,
            period=_num(self.period_s),
            lookahead=_num(self.lookahead_s),
            gain=self.gain,
            decel=_num(self.stop_deceleration),
        )

    @classmethod
    def parse(cls, text: str) -> ServoProgram | None:
        """Read the parameters back from the statements of a rendered program; None if it is not one.

        This is what :class:`~telerig.robots.ur.fake.FakeURController` runs instead of a URScript
        interpreter: it only understands programs of exactly this shape.
        """
        if not text.lstrip().startswith("def telerig_servo():"):
            return None
        ints = set(re.findall(r"read_input_integer_register\((\d+)\)", text))
        floats = [int(i) for i in re.findall(r"read_input_float_register\((\d+)\)", text)]
        servo = re.search(r"servoj\(q, 0, 0, ([0-9.]+), ([0-9.]+), (\d+)\)", text)
        stale = re.search(r"if stale_cycles > (\d+):", text)
        stop = re.search(r"^  stopj\(([0-9.]+)\)$", text, re.MULTILINE)
        if len(ints) != 1 or len(floats) != 6 or servo is None or stale is None or stop is None:
            return None
        if floats != list(range(floats[0], floats[0] + 6)):
            return None
        try:
            return cls(
                int_register=int(ints.pop()),
                double_register=floats[0],
                period_s=float(servo[1]),
                lookahead_s=float(servo[2]),
                gain=int(servo[3]),
                watchdog_cycles=int(stale[1]),
                stop_deceleration=float(stop[1]),
            )
        except ValueError:
            return None


def stop_program(action: Literal["protective_stop", "stopj"], deceleration: float = 4.0) -> str:
    """Program that replaces the running one and stops the arm.

    ``protective_stop`` makes the controller enter a protective stop, which latches on the robot
    until it is unlocked on the teach pendant (or the dashboard server); ``stopj`` only
    decelerates the joints at ``deceleration`` [rad/s^2] and leaves the robot ready.
    """
    if deceleration <= 0:
        raise ValueError(f"deceleration must be positive, got {deceleration}")
    body = "protective_stop()" if action == "protective_stop" else f"stopj({_num(deceleration)})"
    return f'def telerig_stop():\n  textmsg("telerig: emergency stop")\n  {body}\nend\n'


def _num(value: float) -> str:
    return f"{value:.6g}" if "." in f"{value:.6g}" else f"{value:.1f}"
