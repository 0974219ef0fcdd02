"""The scene folder: what every command reads — posed multi-view frames or videos, masks, cameras, timing
and optional ground truth (see docs/scene-format.md).

``folder`` holds the data model (:class:`~vid2sim.scene.folder.Scene`, :class:`~vid2sim.scene.folder.SceneConfig`),
``reading`` loads scene folders (validating everything first), ``writing`` writes them (atomically),
``validation`` holds the checks and :class:`SceneFormatError`, ``video`` reads and writes the per-view videos.
"""
