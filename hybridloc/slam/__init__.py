"""Crowd SLAM: walk graph, loop front end, robust back end, floor-plan anchors and the crowd radio map (issue #20)."""
