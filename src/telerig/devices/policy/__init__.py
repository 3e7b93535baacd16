"""The ``policy`` device: a trained checkpoint rolled out through the rig (see :mod:`.device`)."""
