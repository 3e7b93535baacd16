"""Joint-space sources (a policy's action, a leader arm): joint targets passed through by name."""
