"""Retargeting: operator motion to robot commands (alignment, arm IK, grippers)."""
