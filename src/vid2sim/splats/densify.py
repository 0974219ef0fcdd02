"""Adaptive density control of 3D Gaussian Splatting: clone, split, prune, opacity reset.

The rules are those of the 3DGS paper (and gsplat's ``DefaultStrategy``):

- every Gaussian accumulates the norm of the screen-space gradient of its projected centre, in
  normalised device units (pixels × W/2 or H/2, times the number of views averaged in the loss),
  over the views where it is visible;
- at a densification step, Gaussians whose mean gradient exceeds ``grad_threshold`` are *cloned*
  when small (largest scale ≤ ``percent_dense`` × scene extent) or *split* into two when large (new
  centres sampled from the Gaussian, scales divided by 1.6);
- Gaussians with opacity below ``prune_opacity`` are removed, and after the first opacity reset also
  those larger than ``prune_scale`` × scene extent;
- periodically every opacity is clamped to at most ``reset_opacity`` (so that floaters must earn
  their opacity back or get pruned). gsplat 1.5.3's ``DefaultStrategy`` never performs this reset
  (its condition ``step % reset_every == 0 & step > 0`` parses as a chained comparison that is always
  false); this implementation does.

The optimiser is a ``torch.optim.Adam`` with one parameter group per tensor, each group carrying a
``"name"``; Adam's moments follow the Gaussians through every change (zeros for new ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from vid2sim.splats.gaussians import quat_to_rotmat


@dataclass
class DensifyConfig:
    """Thresholds of adaptive density control (3DGS defaults)."""

    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_scale: float = 0.1
    split_scale_divisor: float = 1.6
    reset_opacity: float = 0.01
    max_gaussians: int = 200_000


class Densifier:
    """Accumulates screen-space gradients and applies clone / split / prune / reset to a parameter dict.

    ``params`` maps names to leaf tensors with the Gaussians along dim 0: ``means (N, 3)``,
    ``log_scales (N, 3)``, ``quats (N, 4)``, ``opacity_logits (N,)`` and any number of colour
    tensors (N, …).
    """

    def __init__(self, config: DensifyConfig, scene_extent: float):
        if scene_extent <= 0:
            raise ValueError(f"scene_extent must be positive, got {scene_extent}")
        self.config = config
        self.extent = float(scene_extent)
        self.grad2d: Tensor | None = None
        self.count: Tensor | None = None

    def accumulate(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one step's screen-space gradients ``(V, N, 2)`` for the entries with ``radii (V, N, 2) > 0``."""
        V, N, _ = means2d_grad.shape
        scale = torch.tensor([width / 2.0 * V, height / 2.0 * V], dtype=means2d_grad.dtype, device=means2d_grad.device)
        norms = (means2d_grad * scale).norm(dim=-1)  # (V, N)
        visible = (radii > 0).all(dim=-1).to(norms.dtype)
        if self.grad2d is None or self.grad2d.shape[0] != N:
            self.grad2d = torch.zeros(N, dtype=norms.dtype, device=norms.device)
            self.count = torch.zeros(N, dtype=norms.dtype, device=norms.device)
        self.grad2d += (norms * visible).sum(0)
        self.count += visible.sum(0)

    def _reset_stats(self, n: int, like: Tensor) -> None:
        self.grad2d = torch.zeros(n, dtype=like.dtype, device=like.device)
        self.count = torch.zeros(n, dtype=like.dtype, device=like.device)

    @torch.no_grad()
    def densify_and_prune(self, params: dict[str, Tensor], optimizer: torch.optim.Optimizer,
                          generator: torch.Generator, prune_large: bool) -> dict[str, int]:
        """One densification step; updates ``params`` (and the optimiser) in place. Returns counts."""
        cfg = self.config
        n = params["means"].shape[0]
        if self.grad2d is None or self.grad2d.shape[0] != n:
            self._reset_stats(n, params["means"])
        grads = self.grad2d / self.count.clamp_min(1)
        high = grads >= cfg.grad_threshold
        max_scale = torch.exp(params["log_scales"]).amax(dim=1)
        small = max_scale <= cfg.percent_dense * self.extent
        clone = high & small
        split = high & ~small
        room = cfg.max_gaussians - n
        if room <= 0:
            clone[:] = False
            split[:] = False
        else:  # grow at most up to the cap: keep the highest-gradient candidates
            cand = clone | split
            if int(cand.sum()) > room:
                thr = torch.topk(grads[cand], room).values.min()
                clone &= grads >= thr
                split &= grads >= thr
        n_clone, n_split = int(clone.sum()), int(split.sum())

        # new rows: clones are copies; each split Gaussian yields two samples, the original is removed
        stds = torch.exp(params["log_scales"][split])
        rot = quat_to_rotmat(params["quats"][split])
        noise = torch.randn((2, n_split, 3), generator=generator, dtype=stds.dtype).to(stds.device)
        offsets = torch.einsum("nij,snj->sni", rot, noise * stds[None])
        split_means = (params["means"][split][None] + offsets).reshape(-1, 3)
        log_div = torch.log(torch.tensor(cfg.split_scale_divisor, dtype=stds.dtype, device=stds.device))

        def new_rows(name: str, t: Tensor) -> Tensor:
            rows_clone = t[clone]
            if name == "means":
                rows_split = split_means
            elif name == "log_scales":
                rows_split = (t[split] - log_div).repeat(2, *([1] * (t.ndim - 1)))
            else:
                rows_split = t[split].repeat(2, *([1] * (t.ndim - 1)))
            return torch.cat([rows_clone, rows_split])

        grown = n + n_clone + 2 * n_split
        keep = torch.ones(grown, dtype=torch.bool, device=params["means"].device)
        keep[:n][split] = False
        opac = torch.sigmoid(
            torch.cat([params["opacity_logits"], new_rows("opacity_logits", params["opacity_logits"])])
        )
        prune = opac < cfg.prune_opacity
        if prune_large:
            scales = torch.exp(torch.cat([params["log_scales"], new_rows("log_scales", params["log_scales"])]))
            prune |= scales.amax(dim=1) > cfg.prune_scale * self.extent
        keep &= ~prune
        n_pruned = int((~keep).sum()) - n_split
        for name in list(params):
            t = params[name]
            added = new_rows(name, t)
            params[name] = self._replace(optimizer, name, t, added, keep)
        self._reset_stats(int(keep.sum()), params["means"])
        return {"cloned": n_clone, "split": n_split, "pruned": n_pruned, "total": int(keep.sum())}

    @staticmethod
    def _replace(optimizer: torch.optim.Optimizer, name: str, old: Tensor, added: Tensor, keep: Tensor) -> Tensor:
        new = torch.cat([old.detach(), added])[keep].requires_grad_(True)
        for group in optimizer.param_groups:
            if group.get("name") == name:
                state = optimizer.state.pop(group["params"][0], None)
                if state:
                    for key in ("exp_avg", "exp_avg_sq"):
                        m = state[key]
                        state[key] = torch.cat([m, torch.zeros_like(added)])[keep]
                    optimizer.state[new] = state
                group["params"][0] = new
                return new
        raise KeyError(f"optimizer has no parameter group named {name!r}")

    @torch.no_grad()
    def reset_opacity(self, params: dict[str, Tensor], optimizer: torch.optim.Optimizer) -> None:
        """Clamp every opacity to at most ``reset_opacity`` and zero its Adam moments."""
        v = self.config.reset_opacity
        cap = torch.log(torch.tensor(v / (1 - v), dtype=params["opacity_logits"].dtype))
        old = params["opacity_logits"]
        new = torch.minimum(old.detach(), cap.to(old.device)).requires_grad_(True)
        for group in optimizer.param_groups:
            if group.get("name") == "opacity_logits":
                state = optimizer.state.pop(group["params"][0], None)
                if state:
                    state["exp_avg"] = torch.zeros_like(state["exp_avg"])
                    state["exp_avg_sq"] = torch.zeros_like(state["exp_avg_sq"])
                    optimizer.state[new] = state
                group["params"][0] = new
        params["opacity_logits"] = new
