"""Pose estimators and their registry; usable in-process, without any server."""
