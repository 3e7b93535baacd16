"""Register maps, as data: Inspire RH56 hands over Modbus TCP and DH-Robotics grippers over Modbus RTU."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum, IntFlag

__all__ = [
    "DH",
    "DH_STATUS_BLOCK",
    "INSPIRE",
    "INSPIRE_JOINTS",
    "DHGripState",
    "DHInitState",
    "InspireError",
    "InspireJoint",
    "InspireStatus",
]


class INSPIRE:
    """Inspire RH56 (DFX/DFTP) holding registers, one 16-bit register per value.

    Source: Inspire-Robots RH56DFX / RH56DFTP user manual, register table (the Modbus TCP
    address equals the manual's address; six per-finger 16-bit values occupy six consecutive
    registers, six per-finger 8-bit values are packed two per register, low byte first).
    Cross-checked against Inspire's own demo code as published by TechShare Inc.
    (github.com/TechShare-inc/inspire_demos, ``inspire_demos/inspire_serial.py`` and
    ``inspire_modbus.py``). Finger order everywhere: little, ring, middle, index,
    thumb bend, thumb rotation.
    """

    HAND_ID = 1000
    CLEAR_ERROR = 1004  #: write 1: clear the error flags of every finger
    SAVE = 1005
    RESET_PARA = 1006
    FORCE_SENSOR_CALIB = 1009
    POS_SET = 1474  #: 6 x actuator position target (raw actuator units; not used)
    ANGLE_SET = 1486  #: 6 x angle target, 0..1000 (0 = flexed / closed, 1000 = extended / open)
    FORCE_SET = 1498  #: 6 x force threshold, 0..1000 [g]
    SPEED_SET = 1522  #: 6 x speed, 0..1000 (1000 = full speed)
    POS_ACT = 1534
    ANGLE_ACT = 1546  #: 6 x measured angle, 0..1000
    FORCE_ACT = 1582  #: 6 x measured force, int16 [g]
    CURRENT = 1594  #: 6 x actuator current [mA]
    ERROR = 1606  #: 6 x uint8 error flags (3 registers), see :class:`InspireError`
    STATUS = 1612  #: 6 x uint8 status code (3 registers), see :class:`InspireStatus`
    TEMP = 1618  #: 6 x uint8 actuator temperature [degC] (3 registers)

    #: Every per-finger 16-bit block is 6 registers; every 8-bit block packs into 3.
    N = 6
    N_PACKED = 3
    #: Angle, force and speed registers hold 0..1000.
    UNIT_MAX = 1000
    #: FORCE_SET / FORCE_ACT unit: 1 gram-force [N].
    FORCE_UNIT_N = 9.80665e-3


class InspireError(IntFlag):
    """Per-finger ERROR bits (RH56DFX manual, ERROR register)."""

    LOCKED_ROTOR = 1 << 0
    OVER_TEMPERATURE = 1 << 1
    OVER_CURRENT = 1 << 2
    MOTOR_ABNORMAL = 1 << 3
    COMMUNICATION = 1 << 4


class InspireStatus(IntEnum):
    """Per-finger STATUS codes (RH56DFX manual, STATUS register)."""

    RELEASING = 0
    GRASPING = 1
    POSITION_REACHED = 2
    FORCE_REACHED = 3
    CURRENT_PROTECTION = 5
    LOCKED_ROTOR_STOP = 6
    FAULT_STOP = 7


@dataclass(frozen=True, slots=True)
class InspireJoint:
    """One actuated degree of freedom of the hand and its angle range.

    The register value u in 0..1000 maps linearly onto the joint angle:
    ``angle = angle_at_0 + u / 1000 * (angle_at_1000 - angle_at_0)``.

    Attributes:
        name: Joint name (suffix; the driver prefixes it, e.g. ``"right_"``).
        angle_at_0: Joint angle at register value 0 (flexed / closed) [rad].
        angle_at_1000: Joint angle at register value 1000 (extended / open) [rad].
    """

    name: str
    angle_at_0: float
    angle_at_1000: float

    @property
    def lower(self) -> float:
        """Smaller end of the range [rad]."""
        return min(self.angle_at_0, self.angle_at_1000)

    @property
    def upper(self) -> float:
        """Larger end of the range [rad]."""
        return max(self.angle_at_0, self.angle_at_1000)


#: The six actuated DoF with the angle ranges of the RH56DFX manual (fingers 19..176.7 deg,
#: thumb bend -13..53.6 deg, thumb rotation 90..165 deg; 0 -> low end, 1000 -> high end).
#: The same ranges appear in public drivers that convert degrees to register units, e.g.
#: ``self.finger_limit = [19, 176.7]``, ``thumb_band_limit = [-13, 53.6]``, ``thumb_rot_limit = [90, 165]``.
#: Mimic joints (distal phalanges, thumb intermediate/distal) follow in the hand's mechanism.
INSPIRE_JOINTS: tuple[InspireJoint, ...] = (
    InspireJoint("little", math.radians(19.0), math.radians(176.7)),
    InspireJoint("ring", math.radians(19.0), math.radians(176.7)),
    InspireJoint("middle", math.radians(19.0), math.radians(176.7)),
    InspireJoint("index", math.radians(19.0), math.radians(176.7)),
    InspireJoint("thumb_bend", math.radians(-13.0), math.radians(53.6)),
    InspireJoint("thumb_rotation", math.radians(90.0), math.radians(165.0)),
)


class DH:
    """DH-Robotics AG / PGE / PGC / CGC / RGI gripper holding registers (Modbus RTU, fc 0x03/0x06).

    Source: DH-Robotics short manuals, "Basic control register map" (e.g. PGC-50 §2.3.3,
    CGC-80 / RGI-30 §2.3.4; www.dh-robotics.com): 0x0100 initialization (write 1 = initialize,
    0xA5 = full initialization), 0x0101 force 20..100 %, 0x0103 position 0..1000 permille,
    0x0104 speed 1..100 %, 0x0200 initialization state, 0x0201 gripper state, 0x0202 position
    feedback, 0x0300 save, 0x0301 initialization direction, 0x0302 slave address, 0x0303 baud rate.
    Serial defaults: 115200 baud, 8 data bits, no parity, 1 stop bit, slave address 1.
    """

    INIT = 0x0100
    FORCE = 0x0101  #: closing force, 20..100 [%] of the rated force
    POSITION = 0x0103  #: finger position target, 0..1000 permille of the stroke (0 closed, 1000 open)
    SPEED = 0x0104  #: 1..100 [%] of the rated speed
    INIT_STATE = 0x0200  #: see :class:`DHInitState`
    GRIP_STATE = 0x0201  #: see :class:`DHGripState`
    POSITION_ACT = 0x0202  #: measured finger position, permille
    SAVE = 0x0300
    INIT_DIRECTION = 0x0301
    SLAVE_ADDRESS = 0x0302
    BAUD_RATE = 0x0303

    INIT_CMD = 0x01
    FULL_INIT_CMD = 0xA5
    POSITION_MAX = 1000
    FORCE_MIN = 20
    FORCE_MAX = 100
    SPEED_MIN = 1
    SPEED_MAX = 100


#: One read covers init state, grip state and position feedback.
DH_STATUS_BLOCK = (DH.INIT_STATE, 3)


class DHInitState(IntEnum):
    """0x0200: initialization state."""

    NOT_INITIALIZED = 0
    INITIALIZED = 1
    INITIALIZING = 2


class DHGripState(IntEnum):
    """0x0201: gripper state."""

    MOVING = 0
    REACHED = 1
    OBJECT_CAUGHT = 2
    OBJECT_DROPPED = 3
