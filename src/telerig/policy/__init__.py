"""Trained policies at run time: checkpoint format, model definitions and inference (CPU torch).

Below the device, robot and camera layers so a policy source can load a checkpoint wherever it
runs; training and dataset reading live above, in :mod:`telerig.learn`.
"""
