"""roslibpy (the rosbridge client from PyPI) against rosbridge: reads joint states, commands the robot.

Usage: roslibpy_robot.py HOST PORT JOINT_NAMES TARGETS
Prints JSON: the first JointState received, the rosapi topic list and the answer to an unknown service.
"""

import json
import sys
import threading
import time

import roslibpy

host, port = sys.argv[1], int(sys.argv[2])
names = sys.argv[3].split(",")
targets = [float(v) for v in sys.argv[4].split(",")]

ros = roslibpy.Ros(host=host, port=port)
ros.run(timeout=5)
got = threading.Event()
first: dict = {}


def on_state(msg: dict) -> None:
    if not got.is_set():
        first.update(msg)
        got.set()


states = roslibpy.Topic(ros, "/joint_states", "sensor_msgs/msg/JointState")
states.subscribe(on_state)
if not got.wait(5):
    sys.exit("no JointState within 5 s")

topics = ros.get_topics()
failed: list[str] = []
done = threading.Event()
roslibpy.Service(ros, "/no_such_service", "std_srvs/Trigger").call(
    roslibpy.ServiceRequest(),
    callback=lambda _: done.set(),
    errback=lambda e: (failed.append(str(e)), done.set()),
)
done.wait(5)

command = roslibpy.Topic(
    ros, "/joint_trajectory_controller/joint_trajectory", "trajectory_msgs/JointTrajectory"
)
command.publish(
    roslibpy.Message(
        {
            "joint_names": names,
            "points": [{"positions": targets, "time_from_start": {"sec": 0, "nanosec": 200_000_000}}],
        }
    )
)
time.sleep(0.5)
estop = roslibpy.Topic(ros, "/telerig/estop", "std_msgs/Bool")
estop.publish(roslibpy.Message({"data": True}))
time.sleep(0.1)
states.unsubscribe()
command.unadvertise()
estop.unadvertise()
ros.close()
print(json.dumps({"state": first, "topics": topics, "unknown_service": failed}))
