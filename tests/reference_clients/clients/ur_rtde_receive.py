"""ur_rtde's RTDEReceiveInterface and RTDEIOInterface against a controller; prints what they read as JSON.

Usage: ur_rtde_receive.py HOST [VARIABLES]   (VARIABLES comma-separated; empty = the library's defaults)
"""

import json
import sys
import time

import rtde_io
import rtde_receive

host = sys.argv[1]
variables = [v for v in (sys.argv[2] if len(sys.argv) > 2 else "").split(",") if v]
receive = rtde_receive.RTDEReceiveInterface(host, 500.0, variables)
first = receive.getTimestamp()
time.sleep(0.05)
out = {
    "connected": receive.isConnected(),
    "actual_q": receive.getActualQ(),
    "timestamps": [first, receive.getTimestamp()],
    "robot_mode": receive.getRobotMode(),
    "safety_mode": receive.getSafetyMode(),
}
if not variables:
    io = rtde_io.RTDEIOInterface(host)
    out["speed_slider"] = io.setSpeedSlider(0.5)
    out["int_register_18"] = io.setInputIntRegister(18, 42)
    out["double_register_19"] = io.setInputDoubleRegister(19, 2.5)
    io.disconnect()
receive.disconnect()
print(json.dumps(out))
