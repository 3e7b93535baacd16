"""Motion capture: OptiTrack NatNet rigid bodies and skeletons, and BVH file playback."""

from telerig.devices.mocap.device import BvhPlayer, NatNetClient

__all__ = ["BvhPlayer", "NatNetClient"]
