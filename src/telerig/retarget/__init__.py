"""telerig.retarget."""
