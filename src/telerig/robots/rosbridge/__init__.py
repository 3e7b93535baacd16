"""Any ROS robot over the rosbridge v2 WebSocket protocol (JSON), with a fake rosbridge for dry runs."""

from telerig.robots.rosbridge.driver import RosbridgeRobot
from telerig.robots.rosbridge.fake import FakeRosbridge
from telerig.robots.rosbridge.protocol import CommandType, JointStateMsg

__all__ = ["CommandType", "FakeRosbridge", "JointStateMsg", "RosbridgeRobot"]
