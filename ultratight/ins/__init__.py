"""Geodesy and inertial navigation (lowest layer: imports nothing else of the project)."""
