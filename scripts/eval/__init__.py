"""Evaluations and experiments: measurements on the shared data, written up in ``docs/experiments``."""
