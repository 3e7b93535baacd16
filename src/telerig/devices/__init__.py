"""telerig.devices."""
