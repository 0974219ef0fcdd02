"""Stage ``appearance``: the Gaussians refined on all ballistic frames at once.

The object's fitted rigid pose in frame t (from the ``velocity`` stage) turns each camera into a virtual camera
looking at the frame-0 object, so K frames of V views become K·V views of one rigid object (a few views of frame 0
alone leave the Gaussians overfitted to those viewpoints; as the object turns and moves, that shows).
"""

from __future__ import annotations

import dataclasses

import torch

from vid2sim.reconstruct.runner import Context, State
from vid2sim.splats.cameras import Camera
from vid2sim.splats.fitting import fit_gaussians
from vid2sim.splats.ply import load_ply, save_ply

PLY = "gaussians_refined.ply"


class _Given:
    """An initializer that returns Gaussians already fitted (to refine them)."""

    def __init__(self, gaussians) -> None:
        self.gaussians = gaussians

    def __call__(self, images, masks, cameras, sh_degree, generator):
        return self.gaussians


def virtual_views(images: torch.Tensor, masks: torch.Tensor, cameras: list, rotations, translations
                  ) -> tuple[torch.Tensor, torch.Tensor, list]:
    """K frames of V views of a rigidly moving object as K·V views of the object at frame 0.

    Args:
        images: (V, K, H, W, 3); masks: (V, K, H, W); cameras: V cameras.
        rotations: (K, 3, 3), translations: (K, 3): frame t maps a frame-0 point X to R_t X + T_t.
    Returns:
        (K·V, H, W, 3) images, (K·V, H, W) masks, K·V cameras with world-to-camera = camera ∘ (R_t, T_t).
    """
    V, K = images.shape[:2]
    dev = cameras[0].world_to_camera.device
    R = torch.as_tensor(rotations, dtype=torch.float32, device=dev)
    T = torch.as_tensor(translations, dtype=torch.float32, device=dev)
    cams = []
    for t in range(K):
        M = torch.eye(4, device=dev)
        M[:3, :3], M[:3, 3] = R[t], T[t]
        cams += [Camera(c.world_to_camera @ M, c.K, c.width, c.height) for c in cameras]
    return (images.transpose(0, 1).reshape(K * V, *images.shape[2:]),
            masks.transpose(0, 1).reshape(K * V, *masks.shape[2:]), cams)


class AppearanceStage:
    """Refines the Gaussians on the ballistic frames (``config.appearance``); writes ``gaussians_refined.ply``."""

    name = "appearance"
    sections = ("appearance", "gaussians")
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        K = int(state.velocity["frames_used"])
        if ctx.config.appearance.iterations > 0 and K > 1:
            return f"refining the Gaussians on {K} ballistic frames x {len(ctx.observed.cameras)} views"
        return "keeping the frame-0 Gaussians (no ballistic frames to refine them on)"

    def run(self, ctx: Context, state: State) -> None:
        o, cfg, K = ctx.observed, ctx.config, int(state.velocity["frames_used"])
        g = state.gaussians
        if cfg.appearance.iterations > 0 and K > 1:
            views, vmasks, vcams = virtual_views(o.images[:, :K], o.masks[:, :K], o.cameras,
                                                 state.velocity["rotations"], state.velocity["translations"])
            refine = dataclasses.replace(cfg.gaussians, iterations=cfg.appearance.iterations, densify_from=0.0,
                                         densify_until=0.0, views_per_step=cfg.gaussians.views_per_step
                                         or len(o.cameras), sh_band_every=0.0, seed=cfg.seed)
            g = fit_gaussians(views, vmasks, vcams, refine, initializer=_Given(g), progress=ctx.progress)
        save_ply(g, ctx.path(PLY))

    def load(self, ctx: Context, state: State) -> None:
        state.gaussians = load_ply(ctx.path(PLY), device=ctx.device)
