"""3D Gaussians: model, PLY I/O, cameras, differentiable rendering, deformation, fitting.

This layer must not import ``vid2sim.physics``.
"""
