"""Quality gates on committed episodes (issue 13): each gate reads the recorded streams and the
robot model and gives a verdict with its measured value and threshold.

- :func:`evaluate`: every enabled gate on one episode directory → :class:`QaReport`.
- :class:`GateVerdict`, :class:`QaReport`: the results and their JSON form (index, manifest).
- Thresholds: :class:`telerig.config.qa.QaThresholds` (the rig file's ``qa:`` section).

Gates: ``fall`` and ``force_spike`` and ``calibration_drift`` and ``joint_limits`` and ``idle``
(:mod:`~telerig.qa.motion`), ``self_collision`` (:mod:`~telerig.qa.collision`), ``sync`` and
``teleop_faults`` (:mod:`~telerig.qa.timing`). Running them is off the control path: the CLI and
the station's background worker call :func:`evaluate` after commit.
"""

from telerig.config.qa import GATES, GateName, QaThresholds
from telerig.qa.gates import evaluate
from telerig.qa.report import GateVerdict, QaReport

__all__ = ["GATES", "GateName", "GateVerdict", "QaReport", "QaThresholds", "evaluate"]
