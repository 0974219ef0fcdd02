"""The bottom layer: what every other layer may use and nothing of theirs.

- :mod:`~vid2sim.runtime.device`: which torch device a command runs on;
- :mod:`~vid2sim.runtime.files`: atomic writes and checked reads of JSON and torch files;
- :mod:`~vid2sim.runtime.workers`: local process pools for the data generators;
- :mod:`~vid2sim.runtime.ray_runner`: the same tasks on a Ray cluster.
"""
