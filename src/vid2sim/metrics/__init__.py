"""Metrics: trajectory distances, body rotations and contacts, image quality (PSNR, SSIM, optional FovVideoVDP),
geometry (Chamfer distance, surface sampling) and material-parameter errors — the library behind ``vid2sim evaluate``.

``fovvdp`` imports its CC BY-NC dependency ``pyfvvdp`` only when called (``pip install "vid2sim[fvvdp]"``).
"""

from vid2sim.metrics.contacts import (
    ContactEvent,
    body_rotations,
    contact_events,
    motion_around_contacts,
    rotation_angles,
)
from vid2sim.metrics.fvvdp import fovvdp
from vid2sim.metrics.geometry import (
    ChamferDistance,
    chamfer,
    chamfer_distance,
    material_errors,
    nearest_neighbours,
    sample_surface,
    surface_chamfer,
)
from vid2sim.metrics.images import gaussian_window, image_metrics, psnr, ssim, ssim_map
from vid2sim.metrics.trajectory import (
    TrajectoryDistance,
    best_rotation,
    carry_by_tets,
    deformation,
    nonrigid_distance,
    rigidly_aligned,
    tet_centre_of_mass,
    trajectory_distance,
)

__all__ = [
    "ChamferDistance",
    "ContactEvent",
    "TrajectoryDistance",
    "best_rotation",
    "body_rotations",
    "carry_by_tets",
    "chamfer",
    "chamfer_distance",
    "contact_events",
    "deformation",
    "fovvdp",
    "gaussian_window",
    "image_metrics",
    "material_errors",
    "motion_around_contacts",
    "nearest_neighbours",
    "nonrigid_distance",
    "psnr",
    "rigidly_aligned",
    "rotation_angles",
    "sample_surface",
    "ssim",
    "ssim_map",
    "surface_chamfer",
    "tet_centre_of_mass",
    "trajectory_distance",
]
