"""The Gaussians' colours and opacities refitted along the simulated motion (the reconstruction's last stage).

The Gaussians are fitted to frame 0 and refined on the ballistic frames, where the object moves rigidly. After
the first bounce the object turns, and the observed views see it in poses frame 0 never showed:

* surfaces no camera saw at frame 0 (the underside, for cameras above the floor) come into view with colours
  that were never supervised;
* the scene's light is fixed in the world while the Gaussians carry the shading of frame 0 with them;
* Gaussians that frame 0's views could not tell from the surface (floaters behind it) appear in front of it.

Measured on four small benchmark scenes with ``vid2sim evaluate --true-motion``: without this stage, even moved
by the ground truth's own motion the assets' Gaussians reach only 24.5 dB on the observed frames, so no
dynamics could do better than that (26.7 dB with it; the simulated motion goes from 22.4 to 24.1 dB, the future
frames from 18.7 to 20.3, the novel views from 18.5 to 20.7). This stage fixes what it can: with the means and covariances given by
the simulation of the finished asset (no gradient to the physics), the colours (SH) and opacities are fitted
to every observed frame and view with 3DGS's photometric loss and learning rates
(:class:`~vid2sim.splats.fitting.FitConfig`). Positions and shapes stay the simulator's.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
from torch import Tensor


def refine_on_motion(gaussians: Any, frames: Sequence[Any], images: Tensor, cameras: Sequence[Any],
                     frame_ids: Sequence[int], fit: Any, iterations: int, seed: int = 0,
                     progress: bool = False) -> tuple[Any, dict]:
    """Fit the colours and opacities of ``gaussians`` to the observed frames along a given motion.

    Args:
        gaussians: the asset's :class:`~vid2sim.splats.gaussians.Gaussians` (N of them).
        frames: per frame t of the video, the Gaussians as the simulation deforms them
            (:class:`~vid2sim.splats.deform.DeformedGaussians`, N each; their colours and opacities are ignored).
        images: (V, T, H, W, 3) observed images in [0, 1] (views × frames, the frames of ``frame_ids``).
        cameras: the V cameras.
        frame_ids: the video frame of each of the T image columns (indices into ``frames``).
        fit: a :class:`~vid2sim.splats.fitting.FitConfig`: its ``lambda_dssim``, ``lr_sh_dc``, ``lr_sh_rest``,
            ``lr_opacity`` and ``views_per_step`` are used.
        iterations: optimisation steps; each renders one random observed frame in ``views_per_step`` views.
        seed: the frame and view draws.
        progress: a tqdm bar.

    Returns:
        (the Gaussians with the refitted ``sh`` and ``opacity_logits``, the rest unchanged; {"loss_first",
        "loss_last": means of the first and last 10 % of the steps' losses, "iterations"}).
    """
    from dataclasses import replace

    from tqdm.auto import tqdm

    from vid2sim.splats.deform import DeformedGaussians
    from vid2sim.splats.losses import photometric_loss
    from vid2sim.splats.render import render_gaussians

    if iterations < 1:
        raise ValueError(f"refine_on_motion: iterations must be >= 1, got {iterations}")
    V, T = images.shape[:2]
    if len(frame_ids) != T or len(cameras) != V:
        raise ValueError(f"refine_on_motion: images are {V} views x {T} frames, got {len(cameras)} cameras and "
                         f"{len(frame_ids)} frame ids")
    if max(frame_ids) >= len(frames):
        raise ValueError(f"refine_on_motion: frame {max(frame_ids)} asked, the motion has {len(frames)} frames")
    dc = gaussians.sh[:, :1].detach().clone().requires_grad_(True)
    rest = gaussians.sh[:, 1:].detach().clone().requires_grad_(True)
    logits = gaussians.opacity_logits.detach().clone().requires_grad_(True)
    groups = [{"params": [dc], "lr": fit.lr_sh_dc}, {"params": [logits], "lr": fit.lr_opacity}]
    if rest.shape[1] > 0:
        groups.append({"params": [rest], "lr": fit.lr_sh_rest})
    opt = torch.optim.Adam(groups, eps=1e-15)
    per_step = V if fit.views_per_step is None else min(V, fit.views_per_step)
    g = torch.Generator().manual_seed(seed)
    losses = []
    for _ in tqdm(range(iterations), desc="appearance on the motion", disable=not progress, leave=False):
        t = int(torch.randint(T, (1,), generator=g))
        views = torch.randperm(V, generator=g)[:per_step].tolist() if per_step < V else list(range(V))
        d = frames[frame_ids[t]]
        moved = DeformedGaussians(means=d.means.detach(), covars=d.covars.detach(), opacities=torch.sigmoid(logits),
                                  sh=torch.cat([dc, rest], 1))
        out = render_gaussians(moved, [cameras[v] for v in views], background=1.0).rgb
        loss = photometric_loss(out, images[views, t], fit.lambda_dssim)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    k = max(1, len(losses) // 10)
    refined = replace(gaussians, sh=torch.cat([dc, rest], 1).detach(), opacity_logits=logits.detach())
    return refined, {"iterations": iterations, "loss_first": sum(losses[:k]) / k, "loss_last": sum(losses[-k:]) / k}
