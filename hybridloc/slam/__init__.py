"""Crowd SLAM (issue #20): walk graph, loop front end, floor-plan anchoring and the robust back end."""
