"""The gsplat backend's wrapper, run on the CPU through gsplat's own Python front end.

``gsplat.rasterization`` is Python that calls five CUDA kernels (projection, tile intersection,
offsets, spherical harmonics, compositing). Here those five are replaced by PyTorch: the first four by
gsplat 1.5.3's own reference implementations (``gsplat.cuda._torch_impl``), compositing by a per-tile
loop written for this test from the rules of gsplat's ``RasterizeToPixels3DGSFwd.cu`` (α = min(0.999,
o·e^{-σ}), skip σ < 0 or α < 1/255, stop before the Gaussian that takes T to ≤ 1e-4). Everything else
— argument handling, the covariance → upper-triangle conversion, ``RGB+ED``, backgrounds, the
``meta`` layout — is gsplat's real code. So this checks, without a GPU, that
:func:`vid2sim.splats.gsplat_backend.render_gsplat` calls gsplat the way our torch backend renders
(images and gradients); ``tests/test_splats_gsplat.py`` checks the real kernels on a CUDA machine.

Needs gsplat 1.5.3 importable (it is in the ``test`` extra; its import compiles nothing).
"""

import importlib

import pytest
import torch

from vid2sim.splats.cameras import camera_ring, stack_cameras
from vid2sim.splats.gaussians import covariances_from_scales_quats, quat_to_rotmat
from vid2sim.splats.gsplat_backend import render_gsplat
from vid2sim.splats.render import render

gsplat = importlib.import_module("gsplat")  # a declared test dependency: a broken install fails
torch_impl = importlib.import_module("gsplat.cuda._torch_impl")  # a declared test dependency: a broken install fails
gs_rendering = importlib.import_module("gsplat.rendering")  # a declared test dependency: a broken install fails

ALPHA_THRESHOLD = 1.0 / 255.0


def _projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01,
                far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False, calc_compensations=False,
                camera_model="pinhole", opacities=None):
    """``fully_fused_projection`` (unpacked pinhole) from gsplat's reference projection."""
    assert not packed and camera_model == "pinhole" and radius_clip == 0.0
    if covars is None:
        full, _ = torch_impl._quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    else:  # the kernel reads the 6 upper-triangle entries as a symmetric matrix
        c = covars
        full = torch.stack([c[..., [0, 1, 2]], c[..., [1, 3, 4]], c[..., [2, 4, 5]]], dim=-2)
    radii, means2d, depths, conics, comp = torch_impl._fully_fused_projection(
        means, full, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations
    )
    if opacities is not None:  # the kernel culls Gaussians too faint to ever pass the α threshold
        radii = radii * (opacities[..., None, :, None] >= ALPHA_THRESHOLD)
    return radii, means2d, depths, conics, comp


def _isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, segmented=False,
                 packed=False, n_images=None, image_ids=None, gaussian_ids=None):
    assert not packed
    return torch_impl._isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort)


def _isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
    return torch_impl._isect_offset_encode(isect_ids, n_images, tile_width, tile_height)


def _spherical_harmonics(degrees_to_use, dirs, coeffs, masks=None):
    out = torch_impl._spherical_harmonics(degrees_to_use, dirs, coeffs)
    return out if masks is None else out * masks[..., None]


def _rasterize_to_pixels(means2d, conics, colors, opacities, image_width, image_height, tile_size,
                         isect_offsets, flatten_ids, backgrounds=None, masks=None, packed=False, absgrad=False):
    """Front-to-back compositing per 16×16 tile over the depth-sorted Gaussians the tile lists."""
    assert not packed and masks is None
    I, N = means2d.shape[:-2].numel(), means2d.shape[-2]  # images over all batch dims
    D = colors.shape[-1]
    m, con = means2d.reshape(I * N, 2), conics.reshape(I * N, 3)
    col, op = colors.reshape(I * N, D), opacities.reshape(I * N)
    offsets = isect_offsets.reshape(-1).tolist() + [flatten_ids.numel()]
    th, tw = isect_offsets.shape[-2:]
    images, alphas = [], []
    for img in range(I):
        rows_c, rows_a = [], []
        for ty in range(th):
            tiles_c, tiles_a = [], []
            for tx in range(tw):
                k = (img * th + ty) * tw + tx
                ids = flatten_ids[offsets[k]:offsets[k + 1]].long()
                y0, x0 = ty * tile_size, tx * tile_size
                h, w = min(tile_size, image_height - y0), min(tile_size, image_width - x0)
                ys, xs = torch.meshgrid(torch.arange(h, dtype=m.dtype) + y0 + 0.5,
                                        torch.arange(w, dtype=m.dtype) + x0 + 0.5, indexing="ij")
                dx = xs.reshape(-1, 1) - m[ids, 0]  # (P, K)
                dy = ys.reshape(-1, 1) - m[ids, 1]
                a, b, c = con[ids].unbind(-1)
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = torch.clamp(op[ids] * torch.exp(-sigma), max=0.999)
                valid = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
                alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
                T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
                stops = valid & (T * (1 - alpha) <= 1e-4)
                used = valid & (torch.cumsum(stops.int(), 1) == 0)
                wts = torch.where(used, alpha * T, torch.zeros_like(alpha))
                T_end = torch.prod(torch.where(used, 1 - alpha, torch.ones_like(alpha)), 1, keepdim=True)
                pix = wts @ col[ids]
                if backgrounds is not None:
                    pix = pix + T_end * backgrounds.reshape(I, D)[img]
                tiles_c.append(pix.reshape(h, w, D))
                tiles_a.append((1 - T_end).reshape(h, w, 1))
            rows_c.append(torch.cat(tiles_c, 1))
            rows_a.append(torch.cat(tiles_a, 1))
        images.append(torch.cat(rows_c, 0))
        alphas.append(torch.cat(rows_a, 0))
    shape = means2d.shape[:-2]
    return (torch.stack(images).reshape(*shape, image_height, image_width, D),
            torch.stack(alphas).reshape(*shape, image_height, image_width, 1))


@pytest.fixture
def gsplat_on_cpu(monkeypatch):
    for name, fn in [("fully_fused_projection", _projection), ("isect_tiles", _isect_tiles),
                     ("isect_offset_encode", _isect_offset_encode), ("spherical_harmonics", _spherical_harmonics),
                     ("rasterize_to_pixels", _rasterize_to_pixels)]:
        assert hasattr(gs_rendering, name), f"gsplat.rendering no longer imports {name}"
        monkeypatch.setattr(gs_rendering, name, fn)


def _scene(n, seed, sh_degree, deformed, dtype=torch.float64, stored_degree=None):
    g = torch.Generator().manual_seed(seed)
    out = {"means": (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 0.8,
           "opacities": 0.1 + 0.85 * torch.rand(n, generator=g, dtype=dtype)}
    scales = 0.02 + 0.08 * torch.rand(n, 3, generator=g, dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    if deformed:  # Σ' = F Σ Fᵀ, as the simulator hands it over
        F = quat_to_rotmat(torch.randn(n, 4, generator=g, dtype=dtype)) @ torch.diag_embed(
            0.7 + 0.6 * torch.rand(n, 3, generator=g, dtype=dtype))
        out["covars"] = F @ covariances_from_scales_quats(scales, quats) @ F.transpose(1, 2)
    else:
        out["scales"], out["quats"] = scales, quats
    if sh_degree is None:
        out["colors"] = torch.rand(n, 3, generator=g, dtype=dtype)
    else:
        k = ((sh_degree if stored_degree is None else stored_degree) + 1) ** 2  # fitting stores all bands
        sh = 0.3 * torch.randn(n, k, 3, generator=g, dtype=dtype)
        sh[:, 0] = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) / 0.28209479177387814
        out["colors"] = sh
    return {k: t.requires_grad_() for k, t in out.items()}


@pytest.mark.parametrize(
    "sh_degree,deformed,background,stored_degree",
    [(None, False, 1.0, None), (3, False, (0.2, 0.4, 0.6), None), (1, True, 0.0, None), (1, False, 1.0, 3)],
)
def test_gsplat_wrapper_matches_the_torch_backend(gsplat_on_cpu, sh_degree, deformed, background, stored_degree):
    scene = _scene(120, seed=7, sh_degree=sh_degree, deformed=deformed, stored_degree=stored_degree)
    cams = camera_ring(2, 2.2, 25.0, 40, 32, fov_x_deg=45.0)
    extra = {k: scene[k] for k in ("quats", "scales", "covars") if k in scene}
    ref = render(scene["means"], scene["opacities"], scene["colors"], cams, sh_degree=sh_degree,
                 background=background, backend="torch", **extra)
    viewmats, Ks, width, height = stack_cameras(cams)
    bg = torch.as_tensor(background, dtype=torch.float64).expand(3)[None].expand(2, 3)
    rgb, alpha, depth, means2d, radii = render_gsplat(
        scene["means"], scene.get("quats"), scene.get("scales"), scene.get("covars"), scene["opacities"],
        scene["colors"], sh_degree, viewmats.double(), Ks.double(), width, height, bg)
    assert rgb.shape == ref.rgb.shape == (2, 32, 40, 3)
    assert alpha.shape == depth.shape == (2, 32, 40, 1)
    assert means2d.shape == (2, 120, 2) and radii.shape == (2, 120, 2)
    with torch.no_grad():
        assert float((rgb - ref.rgb).abs().max()) < 1e-6
        assert float((alpha - ref.alpha).abs().max()) < 1e-6
        solid = ref.alpha > 0.5
        assert torch.allclose(depth[solid], ref.depth[solid], rtol=1e-6)
        seen = (ref.radii > 0).all(-1) & (radii > 0).all(-1)
        assert int(seen.sum()) > 100
        assert torch.allclose(means2d[seen], ref.means2d[seen], atol=1e-9)

    g = torch.Generator().manual_seed(1)
    weights = [torch.randn(t.shape, generator=g, dtype=torch.float64) for t in (rgb, alpha, depth)]

    def grads(rgb_, alpha_, depth_):
        mask = (ref.alpha.detach() > 0.5).double()
        loss = (rgb_ * weights[0]).sum() + (alpha_ * weights[1]).sum() + (depth_ * mask * weights[2]).sum()
        return torch.autograd.grad(loss, list(scene.values()), retain_graph=True)

    for name, a, b in zip(scene, grads(ref.rgb, ref.alpha, ref.depth), grads(rgb, alpha, depth)):
        assert float(a.norm()) > 0, name
        assert torch.allclose(b, a, rtol=1e-5, atol=1e-8 * float(a.abs().max())), name


def test_screen_space_gradients_for_densification_match(gsplat_on_cpu):
    """``means2d.retain_grad()`` gives densification the same per-view pixel gradients from both."""
    scene = _scene(80, seed=3, sh_degree=None, deformed=False)
    cams = camera_ring(2, 2.2, 25.0, 40, 32, fov_x_deg=45.0)
    ref = render(scene["means"], scene["opacities"], scene["colors"], cams, quats=scene["quats"],
                 scales=scene["scales"], backend="torch")
    viewmats, Ks, width, height = stack_cameras(cams)
    rgb, _, _, means2d, radii = render_gsplat(
        scene["means"], scene["quats"], scene["scales"], None, scene["opacities"], scene["colors"], None,
        viewmats.double(), Ks.double(), width, height, torch.ones(2, 3, dtype=torch.float64))
    target = torch.rand(rgb.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for out_rgb, m2d in ((ref.rgb, ref.means2d), (rgb, means2d)):
        m2d.retain_grad()
        (out_rgb - target).abs().mean().backward()
    seen = (ref.radii > 0).all(-1) & (radii > 0).all(-1)
    assert float(ref.means2d.grad[seen].norm()) > 0
    assert torch.allclose(means2d.grad[seen], ref.means2d.grad[seen], rtol=1e-6, atol=1e-12)


def test_per_view_gaussians_go_to_gsplat_as_a_batch(gsplat_on_cpu):
    """Means (V, N, 3) and covariances (V, N, 3, 3) become gsplat's batch of V one-camera scenes: the same
    images and gradients as the torch backend's per-view render."""
    scene = _scene(60, seed=5, sh_degree=1, deformed=True)
    cams = camera_ring(2, 2.2, 25.0, 40, 32, fov_x_deg=45.0)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.06, -0.04, 0.05]], dtype=torch.float64)
    means = (scene["means"].detach()[None] + shift[:, None]).requires_grad_()
    covars = torch.stack([scene["covars"].detach(), 1.2 * scene["covars"].detach()]).requires_grad_()
    ref = render(means, scene["opacities"], scene["colors"], cams, covars=covars, sh_degree=1, backend="torch")
    viewmats, Ks, width, height = stack_cameras(cams)
    rgb, alpha, _, means2d, radii = render_gsplat(
        means, None, None, covars, scene["opacities"], scene["colors"], 1, viewmats.double(), Ks.double(),
        width, height, torch.ones(2, 3, dtype=torch.float64))
    assert rgb.shape == ref.rgb.shape == (2, 32, 40, 3) and means2d.shape == radii.shape == (2, 60, 2)
    with torch.no_grad():
        assert float((rgb - ref.rgb).abs().max()) < 1e-6 and float((alpha - ref.alpha).abs().max()) < 1e-6
    w = torch.randn(rgb.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    a = torch.autograd.grad((ref.rgb * w).sum(), [means, covars])
    b = torch.autograd.grad((rgb * w).sum(), [means, covars])
    for name, x, y in zip(("means", "covars"), a, b):
        assert float(x.norm()) > 0, name
        assert torch.allclose(y, x, rtol=1e-5, atol=1e-8 * float(x.abs().max())), name
