"""The gsplat CUDA backend against the pure-PyTorch backend: same images, same gradient directions.

Needs a CUDA device and gsplat 1.5.3 (``pip install "vid2sim[cuda]"``); skipped otherwise.
"""

import importlib

import pytest
import torch

from vid2sim.splats.cameras import camera_ring
from vid2sim.splats.gaussians import covariances_from_scales_quats, quat_to_rotmat
from vid2sim.splats.render import render

pytestmark = pytest.mark.cuda


@pytest.fixture(scope="module", autouse=True)
def _gsplat():
    importlib.import_module("gsplat")  # a declared test dependency: a broken install fails


def _scene(n: int, seed: int, sh_degree: int | None, deformed: bool) -> dict[str, torch.Tensor]:
    """n Gaussians in a 0.8-wide box at the origin; plain RGB or SH colours; optionally deformed by F."""
    g = torch.Generator().manual_seed(seed)
    out = {
        "means": (torch.rand(n, 3, generator=g) - 0.5) * 0.8,
        "opacities": 0.1 + 0.85 * torch.rand(n, generator=g),
    }
    scales = 0.02 + 0.08 * torch.rand(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    if deformed:  # Σ' = F Σ Fᵀ with F a rotation times a stretch, as the simulator produces
        F = quat_to_rotmat(torch.randn(n, 4, generator=g)) @ torch.diag_embed(0.7 + 0.6 * torch.rand(n, 3, generator=g))
        cov = covariances_from_scales_quats(scales, quats)
        out["covars"] = F @ cov @ F.transpose(1, 2)
    else:
        out["scales"], out["quats"] = scales, quats
    if sh_degree is None:
        out["colors"] = torch.rand(n, 3, generator=g)
    else:
        k = (sh_degree + 1) ** 2
        sh = 0.3 * torch.randn(n, k, 3, generator=g)
        sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) / 0.28209479177387814
        out["colors"] = sh
    return {name: t.cuda().requires_grad_() for name, t in out.items()}


def _render(scene: dict[str, torch.Tensor], backend: str, sh_degree: int | None, background):
    cams = [c.to("cuda") for c in camera_ring(3, 2.2, 25.0, 64, 48, fov_x_deg=45.0)]
    extra = {k: scene[k] for k in ("quats", "scales", "covars") if k in scene}
    return render(scene["means"], scene["opacities"], scene["colors"], cams, sh_degree=sh_degree,
                  background=background, backend=backend, **extra)


def _grads(scene, out, weights) -> dict[str, torch.Tensor]:
    w_rgb, w_alpha, w_depth = weights
    mask = (out.alpha.detach() > 0.5).float()  # expected depth is ill-conditioned where alpha ≈ 0
    loss = (out.rgb * w_rgb).sum() + (out.alpha * w_alpha).sum() + (out.depth * mask * w_depth).sum()
    grads = torch.autograd.grad(loss, list(scene.values()))
    return dict(zip(scene, grads))


@pytest.mark.parametrize(
    "sh_degree,deformed,background",
    [(None, False, 1.0), (3, False, (0.2, 0.4, 0.6)), (1, True, 0.0)],
)
def test_gsplat_matches_the_torch_backend(sh_degree, deformed, background):
    scene = _scene(300, seed=7, sh_degree=sh_degree, deformed=deformed)
    ref = _render(scene, "torch", sh_degree, background)
    out = _render(scene, "gsplat", sh_degree, background)
    assert ref.backend == "torch" and out.backend == "gsplat"
    assert out.rgb.shape == ref.rgb.shape == (3, 48, 64, 3)
    with torch.no_grad():
        assert float((out.rgb - ref.rgb).abs().max()) < 1e-2
        assert float((out.alpha - ref.alpha).abs().max()) < 1e-2
        solid = ref.alpha > 0.5
        assert torch.allclose(out.depth[solid], ref.depth[solid], rtol=1e-3)
        seen = (ref.radii > 0).all(-1) & (out.radii > 0).all(-1)
        assert torch.allclose(out.means2d[seen], ref.means2d[seen], atol=1e-3)

    g = torch.Generator(device="cuda").manual_seed(1)
    weights = [torch.randn(t.shape, generator=g, device="cuda") for t in (ref.rgb, ref.alpha, ref.depth)]
    g_ref, g_out = _grads(scene, ref, weights), _grads(scene, out, weights)
    for name in scene:
        a, b = g_ref[name].flatten(), g_out[name].flatten()
        assert float(a.norm()) > 0, name
        cos = float(torch.dot(a, b) / (a.norm() * b.norm()))
        assert cos > 0.99, (name, cos)


def test_auto_backend_picks_gsplat_on_cuda():
    scene = _scene(20, seed=3, sh_degree=None, deformed=False)
    assert _render(scene, "auto", None, 1.0).backend == "gsplat"
