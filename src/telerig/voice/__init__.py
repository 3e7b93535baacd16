"""Operator commands by voice and text: one command grammar, offline speech recognition, spoken feedback.

Above the record/store layer and below quality gates and the runtime: it turns phrases into the
commands the runtime's existing topics already accept (session control, aids, perspective).
"""
