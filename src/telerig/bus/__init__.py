"""telerig.bus."""
