"""Benchmarks: commands that measure speed and accuracy (never timed tests)."""
