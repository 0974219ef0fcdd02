"""Renderer timings for ``vid2sim bench speed``: forward + backward of :func:`vid2sim.splats.render`.

Figures (milliseconds, median of several runs):

- ``render_ms`` — always measured on the CPU with the torch backend (its defaults: the compiled compositing
  kernels): 20 000 Gaussians (SH degree 3), 4 views at 128 × 128, forward + backward of a loss on RGB, alpha and
  depth; ``render_tensor_ratio`` its time over the same step with the tensor-op compositing
  (``RasterOptions(kernels="tensor")``, its automatic tile), timed alternately in the same run.
- ``render_forward_ms_448`` — CPU, torch backend, defaults: 20 000 Gaussians, 12 views at 448 × 448, a forward
  render only (what the Gauss–Newton fit, the validation, ``evaluate`` and ``simulate`` do at the full preset);
  ``render_forward_tensor_ratio`` its time over the tensor-op compositing's, timed alternately in the same run.
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


def render_step(n_gaussians: int, n_views: int, size: int, device: torch.device, backend: str = "auto",
                sh_degree: int = 3, backward: bool = True,
                options: RasterOptions | None = None) -> Callable[[], None]:
    """One render of the benchmark scene (``backward``: and the backward pass of a loss on RGB, alpha and depth;
    else without gradients), as a function to time."""
    scene = benchmark_scene(n_gaussians, device, sh_degree=sh_degree)
    if not backward:
        scene = {k: v.detach() for k, v in scene.items()}
    cams = benchmark_cameras(n_views, size, device)

    def step() -> None:
        with torch.set_grad_enabled(backward):
            out = render(scene["means"], scene["opacities"], scene["sh"], cams, quats=scene["quats"],
                         scales=scene["scales"], sh_degree=sh_degree, backend=backend, raster_options=options)
            if backward:
                (out.rgb.mean() + out.alpha.mean() + 0.1 * out.depth.mean()).backward()

    return step


def time_render(n_gaussians: int, n_views: int, size: int, device: torch.device, backend: str = "auto",
                repeats: int = 5, sh_degree: int = 3) -> float:
    """Median milliseconds of one forward + backward render of the benchmark scene."""
    return time_ms(render_step(n_gaussians, n_views, size, device, backend, sh_degree), device, repeats=repeats,
                   warmup=1)


def time_against_tensor_path(n_views: int, size: int, backward: bool, repeats: int) -> tuple[float, float]:
    """(median ms of a CPU render of 20 000 benchmark Gaussians with the defaults, the median ratio of its time to
    the tensor-op compositing's), the two timed alternately (one warm-up each)."""
    cpu = torch.device("cpu")
    default = render_step(20_000, n_views, size, cpu, "torch", backward=backward)
    tensor = render_step(20_000, n_views, size, cpu, "torch", backward=backward,
                         options=RasterOptions(kernels="tensor"))
    default()
    tensor()
    times, ratios = [], []
    for _ in range(repeats):
        a, b = time_ms(default, cpu, repeats=1, warmup=0), time_ms(tensor, cpu, repeats=1, warmup=0)
        times.append(a)
        ratios.append(a / b)
    return statistics.median(times), statistics.median(ratios)


def run(device: torch.device, quick: bool = False) -> dict[str, float | str]:
    """Renderer timings (see module docstring). ``device`` is ignored for ``render_ms`` (always CPU)."""
    repeats = 1 if quick else 7
    result: dict[str, float | str] = {}
    result["render_ms"], result["render_tensor_ratio"] = time_against_tensor_path(4, 128, True, repeats)
    result["render_forward_ms_448"], result["render_forward_tensor_ratio"] = time_against_tensor_path(
        2 if quick else 12, 448, False, 1 if quick else 3)
    if torch.cuda.is_available():
        cuda = device if device.type == "cuda" else torch.device("cuda")
        result["render_ms_cuda_448"] = time_render(100_000, 12, 448, cuda, backend="auto", repeats=repeats)
        result["render_cuda_backend"] = resolve_backend("auto", cuda, torch.float32)
    return result
