"""Crowd SLAM: loop front end, factor graph, floor plan anchoring and pipeline (issue #20)."""
