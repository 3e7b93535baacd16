"""Input devices: the Device interface, the scripted VR controller and stream replay."""

from telerig.devices.base import Device, SampleSink
from telerig.devices.replay import ReplayDevice
from telerig.devices.scripted import ButtonPress, ScriptedVRController

__all__ = ["ButtonPress", "Device", "ReplayDevice", "SampleSink", "ScriptedVRController"]
