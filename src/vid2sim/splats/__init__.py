"""3D Gaussians: model, PLY I/O, cameras, differentiable rendering, deformation, fitting.

This layer must not import ``vid2sim.physics``: the simulator hands it plain tensors (positions x
and deformation gradients F) through :func:`deform_gaussians`.
"""

from vid2sim.splats.cameras import (
    Camera,
    camera_ring,
    camera_sphere,
    look_at,
    stack_cameras,
)
from vid2sim.splats.deform import (
    DeformedGaussians,
    deform_covariances,
    deform_gaussians,
)
from vid2sim.splats.densify import Densifier, DensifyConfig
from vid2sim.splats.fitting import FitConfig, fit_gaussians, scene_extent
from vid2sim.splats.gaussians import (
    Gaussians,
    covariances_from_scales_quats,
    quat_to_rotmat,
    rotmat_to_quat,
)
from vid2sim.splats.losses import l1, photometric_loss, psnr, ssim
from vid2sim.splats.ply import PlyFormatError, load_ply, save_ply
from vid2sim.splats.rasterize import RasterOptions
from vid2sim.splats.render import (
    BACKENDS,
    RenderOutput,
    render,
    render_gaussians,
    resolve_backend,
)
from vid2sim.splats.sh import eval_sh, num_sh_bases, rgb_to_sh_dc, sh_dc_to_rgb
from vid2sim.splats.visual_hull import Initializer, VisualHullInitializer, visual_hull

__all__ = [
    "BACKENDS",
    "Camera",
    "DeformedGaussians",
    "Densifier",
    "DensifyConfig",
    "FitConfig",
    "Gaussians",
    "Initializer",
    "PlyFormatError",
    "RasterOptions",
    "RenderOutput",
    "VisualHullInitializer",
    "camera_ring",
    "camera_sphere",
    "covariances_from_scales_quats",
    "deform_covariances",
    "deform_gaussians",
    "eval_sh",
    "fit_gaussians",
    "l1",
    "load_ply",
    "look_at",
    "num_sh_bases",
    "photometric_loss",
    "psnr",
    "quat_to_rotmat",
    "render",
    "render_gaussians",
    "resolve_backend",
    "rgb_to_sh_dc",
    "rotmat_to_quat",
    "save_ply",
    "scene_extent",
    "sh_dc_to_rgb",
    "ssim",
    "stack_cameras",
    "visual_hull",
]
