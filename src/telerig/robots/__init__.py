"""telerig.robots."""
