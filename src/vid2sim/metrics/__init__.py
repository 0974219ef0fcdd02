"""Metrics: trajectory distances (and, as the pipeline grows, image and physical-parameter errors)."""

from vid2sim.metrics.trajectory import TrajectoryDistance, trajectory_distance

__all__ = ["TrajectoryDistance", "trajectory_distance"]
