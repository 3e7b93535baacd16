"""Robot models shared by real and simulated robots: descriptions, kinematics, limits, collision geometry.

One module per robot family, each with its description as data (model files found by path in the
package that ships them, joint order, home, position/velocity/acceleration limits, end-effector
site) and a builder of its kinematic model (a compiled MuJoCo model without world, whose collision
geoms are the robot's own, for IK and the self-collision guard):

- :mod:`~telerig.robots.models.arms`: arm and gripper descriptions (UR5e + Robotiq 2F-85, Panda).
- :mod:`~telerig.robots.models.arm`: :func:`~telerig.robots.models.arm.build_arm_kinematics`,
  :class:`~telerig.robots.models.arm.ArmScene`.
- :mod:`~telerig.robots.models.g1`: the 29-DoF Unitree G1 (example-robot-data URDF), its 17 arm_sdk joints.
- :mod:`~telerig.robots.models.tiago`: the PAL TIAGo mobile manipulator.
- :mod:`~telerig.robots.models.hands`: dexterous hands (Inspire, Ability, Allegro).
- :mod:`~telerig.robots.models.mjcf`: where model files come from and how they load.

Simulated drivers (:mod:`telerig.robots.sim`), IK (:mod:`telerig.retarget`) and the safety
guards read models from here; this package imports none of them (a layer contract checks it).
Importing it does not import MuJoCo: the kinematic builders do, when called.
"""

from telerig.robots.models.arms import ARM_MODELS, GRIPPER_MODELS, ArmModel, GripperModel, arm_model
from telerig.robots.models.robot import ModelledRobot, arm_kinematics_of

__all__ = [
    "ARM_MODELS",
    "GRIPPER_MODELS",
    "ArmModel",
    "GripperModel",
    "ModelledRobot",
    "arm_kinematics_of",
    "arm_model",
]
