"""The scene folder: what every command reads — posed multi-view frames or videos, masks, cameras, timing
and optional ground truth (see docs/scene-format.md).

``folder`` loads (validating everything first) and writes (atomically) scene folders, ``validation`` holds the
checks and :class:`SceneFormatError`, ``video`` reads and writes the per-view videos.
"""
