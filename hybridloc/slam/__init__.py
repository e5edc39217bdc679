"""Crowd SLAM."""
