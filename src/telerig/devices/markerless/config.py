"""Config of the markerless (webcam / video file + MediaPipe) device."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["MarkerlessConfig"]

Probability = Annotated[float, Field(ge=0, le=1)]


@DEVICES.register
class MarkerlessConfig(DeviceConfig):
    """Hands (``HandPose``) and body (``BodySkeleton``) from a webcam or video file via MediaPipe.

    The tracker runs in its own venv (``python``; create it with
    ``python -m telerig.devices.markerless.install``) and streams to this device over UDP on
    ``listen_host``:``listen_port`` (0 = any free port). ``source`` is a video file or a V4L2
    device such as ``/dev/video0``; leave it empty to only listen for a tracker started elsewhere.
    ``mirrored`` says the frames are a mirror image (selfie preview). Coordinates: metres, operator
    axes (x toward the camera, y operator's left, z up); hands around the hand's centre
    (``hand_frame_id``), body around the hips (``body_frame_id``).
    """

    type: Literal["markerless"] = "markerless"
    source: str | None = None
    python: Path = Path(".venv-markerless/bin/python")
    listen_host: str = "127.0.0.1"
    listen_port: Annotated[int, Field(ge=0, le=65535)] = 0
    hands: bool = True
    pose: bool = True
    max_hands: Annotated[int, Field(ge=1, le=4)] = 2
    hand_model: Literal["lite", "full"] = "full"
    mirrored: bool = False
    realtime: bool = True
    loop: bool = False
    min_detection_confidence: Probability = 0.5
    min_tracking_confidence: Probability = 0.5
    width: Annotated[int, Field(ge=16, le=7680)] = 640
    height: Annotated[int, Field(ge=16, le=4320)] = 480
    fps: Annotated[float, Field(gt=0, le=240)] = 30.0
    input_format: str = ""
    hand_frame_id: str = "hand"
    body_frame_id: str = "hips"

    def build(self) -> Device:
        from telerig.devices.markerless.device import MarkerlessDevice

        return MarkerlessDevice(
            self.id,
            source=self.source,
            python=self.python,
            listen=(self.listen_host, self.listen_port),
            hands=self.hands,
            pose=self.pose,
            max_hands=self.max_hands,
            hand_model=self.hand_model,
            mirrored=self.mirrored,
            realtime=self.realtime,
            loop=self.loop,
            min_detection_confidence=self.min_detection_confidence,
            min_tracking_confidence=self.min_tracking_confidence,
            width=self.width,
            height=self.height,
            fps=self.fps,
            input_format=self.input_format,
            hand_frame_id=self.hand_frame_id,
            body_frame_id=self.body_frame_id,
        )
