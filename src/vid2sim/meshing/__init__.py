"""Tet meshes of solids: fTetWild in a child process (``tetra.tetrahedralize``), box meshes, volumes and
uniform sampling in tets. Used by the synthetic ground truth (the FEM's meshes) and by the reconstruction
(the reference mesh of a reconstructed solid's stiffness calibration)."""
