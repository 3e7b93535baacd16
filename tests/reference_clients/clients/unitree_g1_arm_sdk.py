"""A plain Cyclone DDS client with Unitree's own IDL types and CRC (unitree_sdk2py) talking to a G1.

Usage: unitree_g1_arm_sdk.py DOMAIN_ID TARGET_LEFT_ELBOW
Reads rt/lowstate (checking each state's CRC), then drives the left elbow through rt/arm_sdk with
weight 1 for 0.6 s, sends one command with a wrong CRC, and prints JSON.

The unitree_sdk2 wheel's top-level __init__ imports modules it does not ship, so its package is
entered without running that file; its CRC's C library is not in the wheel either, so the CRC runs
through Unitree's pure-Python path (the one the SDK takes off Linux).
"""

import json
import platform
import sys
import sysconfig
import time
import types
from pathlib import Path

package = types.ModuleType("unitree_sdk2py")
package.__path__ = [str(Path(sysconfig.get_paths()["purelib"]) / "unitree_sdk2py")]
sys.modules["unitree_sdk2py"] = package

from cyclonedds.domain import Domain, DomainParticipant  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from unitree_sdk2py.idl.default import unitree_hg_msg_dds__LowCmd_  # noqa: E402
from unitree_sdk2py.idl.unitree_hg.msg.dds_ import LowCmd_, LowState_  # noqa: E402
from unitree_sdk2py.utils.crc import CRC  # noqa: E402

domain_id, target = int(sys.argv[1]), float(sys.argv[2])
LEFT_ELBOW, WEIGHT = 18, 29  # unitree_sdk2 g1 arm_sdk example: G1JointIndex.LeftElbow, kNotUsedJoint
# Loopback has no multicast: discovery goes to 127.0.0.1, as on the robot's network it goes by multicast.
domain = Domain(  # kept: the domain lives as long as this object
    domain_id,
    '<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    '<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers>'
    "</Discovery></Domain></CycloneDDS>",
)
participant = DomainParticipant(domain_id)
reader = DataReader(participant, Topic(participant, "rt/lowstate", LowState_))
writer = DataWriter(participant, Topic(participant, "rt/arm_sdk", LowCmd_))
linux = platform.system
platform.system = lambda: "unitree-python-crc"
crc = CRC()
platform.system = linux

states: list = []
deadline = time.monotonic() + 5
while len(states) < 3 and time.monotonic() < deadline:
    states += reader.take(N=8)
    time.sleep(0.01)
if not states:
    sys.exit("no rt/lowstate within 5 s")
first = states[0]
out = {
    "states": len(states),
    "crc_ok": all(s.crc == crc.Crc(s) for s in states[:3]),
    "mode_machine": first.mode_machine,
    "left_elbow": first.motor_state[LEFT_ELBOW].q,
}

cmd = unitree_hg_msg_dds__LowCmd_()
cmd.motor_cmd[WEIGHT].q = 1.0
cmd.motor_cmd[LEFT_ELBOW].q = target
cmd.motor_cmd[LEFT_ELBOW].kp = 60.0
cmd.motor_cmd[LEFT_ELBOW].kd = 1.5
end = time.monotonic() + 0.6
while time.monotonic() < end:
    cmd.crc = crc.Crc(cmd)
    writer.write(cmd)
    time.sleep(0.02)
cmd.crc = crc.Crc(cmd) ^ 1
writer.write(cmd)
time.sleep(0.1)
print(json.dumps(out))
