"""Unitree G1 over DDS (``arm_sdk``), with a fake G1 for dry runs; needs the ``unitree`` extra.

The package itself imports nothing, so its rig config (:mod:`telerig.robots.unitree.config`)
validates without Cyclone DDS installed; :mod:`~telerig.robots.unitree.driver` and
:mod:`~telerig.robots.unitree.fake` need it.
"""
