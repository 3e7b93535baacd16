"""Rig runtime: device, control, camera and recorder nodes wired from a rig file."""
