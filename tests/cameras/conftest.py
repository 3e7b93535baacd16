"""Camera tests render offscreen with Mesa: pick the GL backend before MuJoCo is imported."""

import os

# The Makefile exports these; set them here too so that a bare `pytest tests/cameras` renders.
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
