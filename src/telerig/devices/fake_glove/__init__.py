"""A data glove with no hardware: the glove device reading the public fake glove bridge in-process."""
