"""Exports of assets and simulated sequences in formats other tools read (docs/export.md).

- :mod:`vid2sim.export.gltf`: glTF 2.0 / GLB with ``KHR_gaussian_splatting`` (writer and reader),
- :mod:`vid2sim.export.rig`: the material + skinning rig as ``rig.json`` + ``rig.safetensors`` and a pure-NumPy
  reference evaluation of it,
- :mod:`vid2sim.export.sequence`: a simulated sequence (per-frame PLYs) as one glTF/GLB or PLY per frame,
- :mod:`vid2sim.export.transform`: rotations of Gaussians (positions, quaternions, SH) between frames.
"""

from vid2sim.export.gltf import GltfFormatError, export_gltf, load_gltf_gaussians
from vid2sim.export.rig import RigFormatError, evaluate_rig_numpy, export_rig
from vid2sim.export.sequence import export_sequence, find_sequence_frames

__all__ = ["GltfFormatError", "export_gltf", "load_gltf_gaussians", "RigFormatError", "evaluate_rig_numpy",
           "export_rig", "export_sequence", "find_sequence_frames"]
