"""telerig.record."""
