"""Stage ``gaussians``: 3D Gaussians fitted to frame 0 of the observed views.

3DGS; :func:`vid2sim.splats.fit_gaussians`.
"""

from __future__ import annotations

from vid2sim.reconstruct.runner import Context, State
from vid2sim.splats.fitting import fit_gaussians
from vid2sim.splats.ply import load_ply, save_ply

PLY = "gaussians.ply"


class GaussiansStage:
    """Fits the Gaussians to frame 0 (``config.gaussians``); writes ``gaussians.ply``."""

    name = "gaussians"
    sections = ("gaussians",)
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        return "fitting Gaussians to frame 0"

    def run(self, ctx: Context, state: State) -> None:
        o = ctx.observed
        g = fit_gaussians(o.images[:, 0], o.masks[:, 0], o.cameras, ctx.config.gaussians, progress=ctx.progress)
        save_ply(g, ctx.path(PLY))

    def load(self, ctx: Context, state: State) -> None:
        state.gaussians = load_ply(ctx.path(PLY), device=ctx.device)
