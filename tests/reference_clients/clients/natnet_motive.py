"""The natnet client (PyPI) against Motive in unicast mode; prints the models and frames it read as JSON.

Usage: natnet_motive.py HOST COMMAND_PORT
"""

import json
import sys
import threading

from natnet import NatNetClient

host, port = sys.argv[1], int(sys.argv[2])
frames: list = []
models: list = []
got = threading.Event()


def on_frame(frame) -> None:  # type: ignore[no-untyped-def]
    if len(frames) < 3:
        frames.append(frame)
    if len(frames) >= 3 and models:
        got.set()


def on_models(descriptions) -> None:  # type: ignore[no-untyped-def]
    models.append(descriptions)


client = NatNetClient(
    server_ip_address=host, local_ip_address="127.0.0.1", command_port=port, use_multicast=False
)
client.on_data_frame_received_event.handlers.append(on_frame)
client.on_data_description_received_event.handlers.append(on_models)
client.connect(timeout=5)
client.request_modeldef()
client.run_async()
ok = got.wait(5)
client.shutdown()
if not ok:
    sys.exit(f"got {len(frames)} frames and {len(models)} model definitions within 5 s")
model = models[0]
print(
    json.dumps(
        {
            "rigid_bodies": [[rb.name, rb.id_num] for rb in model.rigid_bodies],
            "skeletons": [[s.name, s.id_num, len(s.rigid_body_descriptions)] for s in model.skeletons],
            "marker_sets": [m.name for m in model.marker_sets],
            "frames": [
                {
                    "number": f.prefix.frame_number,
                    "bodies": [
                        [b.id_num, list(b.pos), list(b.rot), b.tracking_valid] for b in f.rigid_bodies
                    ],
                    "skeleton_bones": [[s.id_num, len(s.rigid_bodies)] for s in f.skeletons],
                    "labeled_markers": [m.id_num for m in f.labeled_markers],
                    "timestamp": f.suffix.timestamp,
                    "stamp_camera_mid_exposure": f.suffix.stamp_camera_mid_exposure,
                    "stamp_transmit": f.suffix.stamp_transmit,
                }
                for f in frames
            ],
        }
    )
)
