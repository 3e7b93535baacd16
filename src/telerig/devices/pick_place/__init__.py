"""The pick-and-place task's operators: a scripted operator planning from the observed cube, and a
recorded operator's replay re-targeted to a new cube pose."""
