"""vid2sim: simulation-ready assets from posed multi-view videos (Vid2Sim, CVPR 2025).

Layers (see docs/architecture.md): ``vid2sim.physics`` (mesh-free reduced-order simulator),
``vid2sim.splats`` (3D Gaussians and their rendering), ``vid2sim.scene`` (the scene-folder format),
``vid2sim.synthetic`` (the synthetic ground truth), ``vid2sim.metrics``, ``vid2sim.apps.bench`` (benchmarks) and
``vid2sim.cli`` (the command).
"""

__version__ = "0.1.0"
