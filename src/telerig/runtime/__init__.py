"""telerig.runtime."""
