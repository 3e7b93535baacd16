"""telerig.store."""
