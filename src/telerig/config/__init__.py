"""telerig.config."""
