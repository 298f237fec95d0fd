"""Closed-loop evaluation: predicted keyframes executed by a motion planner in the simulator."""
