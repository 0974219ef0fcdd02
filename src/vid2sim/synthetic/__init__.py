"""The synthetic ground-truth generator: procedural and user meshes, the FEM drop (on tets from :mod:`vid2sim.meshing`),
the textured-mesh renderer, and the scenes and suites built from them (``scenes``).

Writes scene folders through :mod:`vid2sim.scene`; the reconstruction never imports this package.
"""
