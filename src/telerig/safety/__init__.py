"""telerig.safety."""
