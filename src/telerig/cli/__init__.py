"""telerig.cli."""
