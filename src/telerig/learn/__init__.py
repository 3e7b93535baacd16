"""Learning from telerig's datasets: the LeRobot v3 dataset reader and ``telerig train``.

A sibling of :mod:`telerig.runtime`: it reads what :mod:`telerig.export` wrote and trains the
models that :mod:`telerig.policy` defines and runs.
"""
