"""Ant-Goal: the ant walks its torso to a goal position (x, y) on a disc of radius 3 m."""
