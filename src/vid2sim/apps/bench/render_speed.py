"""Renderer timings for ``vid2sim bench speed``: forward + backward of :func:`vid2sim.splats.render`.

Figures (milliseconds, median of several runs):

- ``render_ms`` — always measured on the CPU with the pure-PyTorch backend: 20 000 Gaussians (SH
  degree 3), 4 views at 128 × 128, forward + backward of a loss on RGB, alpha and depth.
- ``render_forward_ms_448`` — CPU, pure-PyTorch backend: 20 000 Gaussians, 12 views at 448 × 448, a forward
  render only (what the Gauss–Newton fit, the validation, ``evaluate`` and ``simulate`` do at the full preset),
  with the automatic tile (:func:`vid2sim.splats.rasterize.auto_tile_size`); ``render_forward_tile4_ratio`` its
  time over the same render with 4-pixel tiles, timed alternately in the same run (below 1: the tile choice pays).
  ``--quick``: 2 views.
- ``render_ms_cuda_448`` — only when CUDA is available: 100 000 Gaussians, 12 views at 448 × 448,
  forward + backward, with ``backend="auto"`` (gsplat when it is installed, the torch backend on
  the GPU otherwise); ``render_cuda_backend`` names the backend that ran.

The scene stands in for a fitted object: Gaussians in a 5 cm-thick shell around a sphere of radius
0.5 (the canonical object size), spaced and sized like a converged 3DGS fit (scales about the mean
spacing, opacities 0.3–1), seen by a ring of cameras 2 units away with a 40° field of view, so the
object fills about 70 % of each image.
"""

from __future__ import annotations

import math
import statistics
from typing import Callable

import torch

from vid2sim.apps.bench.timing import time_ms
from vid2sim.splats.cameras import Camera, camera_ring
from vid2sim.splats.rasterize import RasterOptions
from vid2sim.splats.render import render, resolve_backend
from vid2sim.splats.sh import num_sh_bases, rgb_to_sh_dc


def benchmark_scene(
    n: int, device: torch.device | str = "cpu", seed: int = 0, sh_degree: int = 3
) -> dict[str, torch.Tensor]:
    """A reproducible shell-of-Gaussians scene (see module docstring) as leaf tensors needing grad.

    Returns a dict with ``means (n, 3)``, ``quats (n, 4)``, ``scales (n, 3)``, ``opacities (n,)``
    and ``sh (n, K, 3)``.
    """
    g = torch.Generator().manual_seed(seed)
    dirs = torch.randn(n, 3, generator=g)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    radius = 0.5 + 0.05 * (torch.rand(n, 1, generator=g) - 0.5)
    means = dirs * radius
    spacing = math.sqrt(4 * math.pi * 0.25 / n)
    scales = spacing * (0.5 + torch.rand(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.3 + 0.7 * torch.rand(n, generator=g)
    sh = 0.1 * torch.randn(n, num_sh_bases(sh_degree), 3, generator=g)
    sh[:, 0] = rgb_to_sh_dc(torch.rand(n, 3, generator=g))
    out = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "sh": sh}
    return {k: v.to(device).requires_grad_() for k, v in out.items()}


def benchmark_cameras(n_views: int, size: int, device: torch.device | str = "cpu") -> list[Camera]:
    """``n_views`` cameras on a ring 2 units from the origin, 20° elevation, 40° FoV, size × size."""
    return [c.to(device) for c in camera_ring(n_views, 2.0, 20.0, size, size, fov_x_deg=40.0)]


def time_render(
    n_gaussians: int,
    n_views: int,
    size: int,
    device: torch.device,
    backend: str = "auto",
    repeats: int = 5,
    sh_degree: int = 3,
) -> float:
    """Median milliseconds of one forward + backward render of the benchmark scene."""
    scene = benchmark_scene(n_gaussians, device, sh_degree=sh_degree)
    cams = benchmark_cameras(n_views, size, device)

    def step() -> None:
        out = render(
            scene["means"],
            scene["opacities"],
            scene["sh"],
            cams,
            quats=scene["quats"],
            scales=scene["scales"],
            sh_degree=sh_degree,
            backend=backend,
        )
        loss = out.rgb.mean() + out.alpha.mean() + 0.1 * out.depth.mean()
        loss.backward()

    return time_ms(step, device, repeats=repeats, warmup=1)


def time_forward_448(n_views: int, repeats: int) -> tuple[float, float]:
    """(median ms of a forward render of 20 000 benchmark Gaussians in ``n_views`` 448² views with the automatic
    tile, its median ratio to the same render with 4-pixel tiles), the two timed alternately on the CPU."""
    scene = {k: v.detach() for k, v in benchmark_scene(20_000).items()}
    cams = benchmark_cameras(n_views, 448)
    cpu = torch.device("cpu")

    def step(options: RasterOptions | None) -> Callable[[], object]:
        return lambda: render(scene["means"], scene["opacities"], scene["sh"], cams, quats=scene["quats"],
                              scales=scene["scales"], sh_degree=3, backend="torch", raster_options=options)

    auto, tile4 = [], []
    with torch.no_grad():
        for _ in range(repeats):
            auto.append(time_ms(step(None), cpu, repeats=1, warmup=0))
            tile4.append(time_ms(step(RasterOptions(tile_size=4)), cpu, repeats=1, warmup=0))
    return statistics.median(auto), statistics.median(a / b for a, b in zip(auto, tile4))


def run(device: torch.device, quick: bool = False) -> dict[str, float | str]:
    """Renderer timings (see module docstring). ``device`` is ignored for ``render_ms`` (always CPU)."""
    repeats = 1 if quick else 7
    result: dict[str, float | str] = {
        "render_ms": time_render(20_000, 4, 128, torch.device("cpu"), backend="torch", repeats=repeats)
    }
    result["render_forward_ms_448"], result["render_forward_tile4_ratio"] = time_forward_448(
        2 if quick else 12, 1 if quick else 3)
    if torch.cuda.is_available():
        cuda = device if device.type == "cuda" else torch.device("cuda")
        result["render_ms_cuda_448"] = time_render(100_000, 12, 448, cuda, backend="auto", repeats=repeats)
        result["render_cuda_backend"] = resolve_backend("auto", cuda, torch.float32)
    return result
