"""Readers that turn users' 3D data into a ``Scene``."""
