"""Configs of the mocap devices: ``natnet`` (OptiTrack Motive client) and ``bvh`` (file playback)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator, model_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["BvhConfig", "NatNetConfig"]

Axis = Literal["+x", "-x", "+y", "-y", "+z", "-z"]
Vec3 = tuple[float, float, float]
Port = Annotated[int, Field(ge=0, le=65535)]
_IPV4 = r"^\d{1,3}(\.\d{1,3}){3}$"


class _Mount(DeviceConfig):
    """Capture frame -> output frame: x forward, y left, z up, metres (see ``MountTransform``)."""

    up_axis: Axis = "+y"
    forward_axis: Axis = "+z"
    yaw_deg: Annotated[float, Field(ge=-360, le=360)] = 0.0
    offset_m: Vec3 = (0.0, 0.0, 0.0)
    frame_id: str = "mocap"

    @model_validator(mode="after")
    def _orthogonal(self) -> _Mount:
        if self.up_axis[1] == self.forward_axis[1]:
            raise ValueError(
                f"forward_axis: must be orthogonal to up_axis {self.up_axis!r}; got {self.forward_axis!r}"
            )
        return self


@DEVICES.register
class NatNetConfig(_Mount):
    """An OptiTrack Motive server streaming NatNet 3.x/4.x rigid bodies and skeletons.

    Lab default: data on multicast ``239.255.42.99:1511``, commands to ``server:1510``. Set
    ``multicast_group: null`` for Motive's unicast mode. ``version`` (e.g. ``"4.1"``) overrides
    the bitstream version the server announces. ``skeleton_coordinates`` must match Motive's
    streaming setting.
    """

    type: Literal["natnet"] = "natnet"
    server: Annotated[str, Field(pattern=_IPV4)] = "127.0.0.1"
    command_port: Port = 1510
    data_port: Port = 1511
    multicast_group: Annotated[str, Field(pattern=_IPV4)] | None = "239.255.42.99"
    local_address: Annotated[str, Field(pattern=_IPV4)] = "0.0.0.0"
    version: Annotated[str, Field(pattern=r"^[34]\.\d{1,3}$")] | None = None
    skeleton_coordinates: Literal["global", "local"] = "global"
    max_range_m: Annotated[float, Field(gt=0, le=1000)] = 100.0
    connect_timeout_s: Annotated[float, Field(ge=0, le=60)] = 2.0

    def build(self) -> Device:
        from telerig.devices.mocap._axes import MountTransform
        from telerig.devices.mocap.device import NatNetClient

        return NatNetClient(
            self.id,
            server=self.server,
            command_port=self.command_port,
            data_port=self.data_port,
            multicast_group=self.multicast_group,
            local_address=self.local_address,
            version=self.version,
            mount=MountTransform(
                up=self.up_axis, forward=self.forward_axis, yaw_deg=self.yaw_deg, offset=self.offset_m
            ),
            frame_id=self.frame_id,
            skeleton_coordinates=self.skeleton_coordinates,
            max_range_m=self.max_range_m,
            connect_timeout_s=self.connect_timeout_s,
        )


@DEVICES.register
class BvhConfig(_Mount):
    """Plays a BVH motion file as ``BodySkeleton`` samples with the file's frame timing.

    ``scale`` converts file units to metres; ``auto`` detects mm, cm, inches, the CMU mocap
    database's 0.056444 m or m from the body's proportions. ``normalize_names`` gives the shoulder,
    elbow, wrist and hip joints, found by the skeleton's structure, their CMU names (``LeftArm``,
    ``LeftForeArm``, ``LeftHand``, ``LeftUpLeg``) whatever the file calls them.
    """

    type: Literal["bvh"] = "bvh"
    #: A BVH file; a bare name that is not a file here names a clip shipped with telerig (``reach.bvh``).
    path: Path
    speed: Annotated[float, Field(gt=0, le=100)] = 1.0
    loop: bool = False
    scale: Annotated[float, Field(gt=0, le=100)] | Literal["auto"] = "auto"
    include_end_sites: bool = True
    normalize_names: bool = True

    @field_validator("path")
    @classmethod
    def _shipped_clip(cls, path: Path) -> Path:
        if path.is_absolute() or path.exists() or len(path.parts) != 1:
            return path
        shipped = Path(str(resources.files("telerig.devices.mocap") / "data" / path.name))
        return shipped if shipped.is_file() else path

    def build(self) -> Device:
        from telerig.devices.mocap.device import BvhPlayer

        return BvhPlayer(
            self.path,
            id=self.id,
            speed=self.speed,
            loop=self.loop,
            scale=None if self.scale == "auto" else self.scale,
            up_axis=self.up_axis,
            forward_axis=self.forward_axis,
            yaw_deg=self.yaw_deg,
            offset=self.offset_m,
            frame_id=self.frame_id,
            include_end_sites=self.include_end_sites,
            normalize_names=self.normalize_names,
        )
