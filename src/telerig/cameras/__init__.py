"""telerig.cameras."""
