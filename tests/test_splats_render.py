"""The CPU renderer (compiled compositing kernels and the tensor path) against a brute-force per-pixel reference,
finite differences and analytic cases."""

import dataclasses
import importlib
import math
import sys
import types

import pytest
import torch

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.cameras import Camera, camera_ring
from vid2sim.splats.gaussians import Gaussians, covariances_from_scales_quats
from vid2sim.splats.rasterize import RasterOptions, auto_tile_size, composite, uses_compiled_kernels
from vid2sim.splats.render import render, render_gaussians, resolve_backend
from vid2sim.splats.sh import eval_sh

F64 = torch.float64


def reference_render(means, covars, opacities, colors, cam, background, sh_degree=None, eps2d=0.3, near=0.01):
    """Brute force: every Gaussian at every pixel, in depth order, one at a time (3DGS semantics).

    Returns rgb (H, W, D), alpha (H, W, 1), expected depth (H, W, 1). Plain autograd throughout.
    """
    dt = means.dtype
    w2c, K = cam.world_to_camera.to(dt), cam.K.to(dt)
    R, t = w2c[:3, :3], w2c[:3, 3]
    pc = means @ R.T + t
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    H, W = cam.height, cam.width
    if sh_degree is not None:
        centre = -R.T @ t
        colors = eval_sh(sh_degree, colors, means - centre)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dt) + 0.5, torch.arange(W, dtype=dt) + 0.5, indexing="ij")
    T = torch.ones(H, W, dtype=dt)
    out = torch.zeros(H, W, colors.shape[1], dtype=dt)
    D = torch.zeros(H, W, dtype=dt)
    done = torch.zeros(H, W, dtype=torch.bool)
    lim_x = (cx / fx + 0.15 * W / fx, (W - cx) / fx + 0.15 * W / fx)
    lim_y = (cy / fy + 0.15 * H / fy, (H - cy) / fy + 0.15 * H / fy)
    for i in torch.argsort(pc[:, 2]).tolist():
        x, y, z = pc[i]
        if z <= near:
            continue
        xc = z * torch.clamp(x / z, -lim_x[0], lim_x[1])
        yc = z * torch.clamp(y / z, -lim_y[0], lim_y[1])
        zero = torch.zeros((), dtype=dt)
        J = torch.stack([torch.stack([fx / z, zero, -fx * xc / z**2]), torch.stack([zero, fy / z, -fy * yc / z**2])])
        cov2 = J @ R @ covars[i] @ R.T @ J.T + eps2d * torch.eye(2, dtype=dt)
        inv = torch.linalg.inv(cov2)
        mu = torch.stack([fx * x / z + cx, fy * y / z + cy])
        dx, dy = xs - mu[0], ys - mu[1]
        power = 0.5 * (inv[0, 0] * dx * dx + inv[1, 1] * dy * dy) + 0.5 * (inv[0, 1] + inv[1, 0]) * dx * dy
        alpha = torch.clamp(opacities[i] * torch.exp(-power), max=0.999)
        use = (alpha >= 1 / 255) & ~done
        next_T = T * (1 - alpha)
        stop = use & (next_T <= 1e-4)
        done = done | stop
        use = use & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(alpha))
        out = out + w[..., None] * colors[i]
        D = D + w * z
        T = torch.where(use, next_T, T)
    a = 1 - T
    return out + T[..., None] * background, a[..., None], (D / a.clamp_min(1e-10))[..., None]


def _scene(n, seed, dtype=F64, opacity=(0.15, 0.95), spread=0.8, scale=(0.03, 0.13)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * spread
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    ops = torch.rand(n, generator=g, dtype=dtype) * (opacity[1] - opacity[0]) + opacity[0]
    cols = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, scales, quats, ops, cols


@pytest.mark.parametrize("kernels", ["compiled", "tensor"])
@pytest.mark.parametrize(
    "seed,opacity,opts",
    [
        (0, (0.15, 0.95), RasterOptions()),
        (1, (0.9, 0.999), RasterOptions()),  # opaque: early termination matters
        (2, (0.5, 0.99), RasterOptions(tile_size=8, chunk=5, max_elements=4 * 5 * 64)),
        (3, (0.5, 0.99), RasterOptions(tile_size=1, chunk=3, max_elements=3 * 200)),
    ],
)
def test_images_match_brute_force_reference(seed, opacity, opts, kernels):
    opts = dataclasses.replace(opts, kernels=kernels)
    means, scales, quats, ops, cols = _scene(40, seed, opacity=opacity)
    cov = covariances_from_scales_quats(scales, quats)
    n_views = 3 if seed < 2 else 1  # the odd tilings are slow: one view is enough for them
    cams = camera_ring(n_views, 2.5, 20.0, 37, 29, fov_x_deg=45.0, azimuth_offset_deg=10.0 * seed)
    bg = torch.tensor([1.0, 0.5, 0.2], dtype=F64)
    out = render(means, ops, cols, cams, quats=quats, scales=scales, background=bg, raster_options=opts)
    assert out.rgb.shape == (n_views, 29, 37, 3) and out.alpha.shape == (n_views, 29, 37, 1)
    assert out.depth.shape == (n_views, 29, 37, 1)
    for v, cam in enumerate(cams):
        rgb, alpha, depth = reference_render(means, cov, ops, cols, cam, bg)
        assert torch.allclose(out.rgb[v], rgb, atol=1e-12)
        assert torch.allclose(out.alpha[v], alpha, atol=1e-12)
        assert torch.allclose(out.depth[v], depth, atol=1e-10)
    if opacity[0] > 0.8:
        assert float(out.alpha.max()) > 0.9998  # some pixels really did terminate


def test_auto_tile_size_follows_the_footprint():
    half = lambda h: torch.full((10, 2), h, dtype=torch.int32)  # noqa: E731
    assert auto_tile_size(half(3), backward=False) == 4 and auto_tile_size(half(5), backward=False) == 8
    assert auto_tile_size(half(20), backward=True) == 4
    assert auto_tile_size(torch.zeros(0, 2, dtype=torch.int32), backward=False) == 4


@pytest.mark.parametrize("grad", [False, True])
def test_default_tiling_is_chosen_per_render_and_changes_no_pixel(monkeypatch, grad):
    """With the tensor path, large splats take 8-pixel tiles in a forward-only render, small ones and differentiated
    renders 4; the compiled kernels take 16 always. The image is the reference's either way, and so are the
    gradients."""
    render_module = importlib.import_module("vid2sim.splats.render")  # the package's `render` is the function
    used = []
    original = render_module.bin_gaussians
    monkeypatch.setattr(render_module, "bin_gaussians",
                        lambda *a, **k: used.append((a[-1], k["compiled"])) or original(*a, **k))
    cams = camera_ring(1, 2.5, 20.0, 48, 40, fov_x_deg=45.0)
    bg = torch.tensor([1.0, 0.5, 0.2], dtype=F64)
    for scale, tile, kernels in (((0.01, 0.02), 4, "tensor"), ((0.1, 0.2), 4 if grad else 8, "tensor"),
                                 ((0.01, 0.02), 16, "auto"), ((0.1, 0.2), 16, "auto")):
        means, scales, quats, ops, cols = (t.requires_grad_(grad) for t in _scene(30, 4, scale=scale))
        out = render(means, ops, cols, cams, quats=quats, scales=scales, background=bg,
                     raster_options=RasterOptions(kernels=kernels))
        assert used[-1] == (tile, kernels == "auto")  # the compiled kernels bin the tiles too
        rgb, _, _ = reference_render(means, covariances_from_scales_quats(scales, quats), ops, cols, cams[0], bg)
        assert torch.allclose(out.rgb[0], rgb, atol=1e-12)
        if grad:
            g_out = torch.autograd.grad(out.rgb.sum(), [means, ops])
            g_ref = torch.autograd.grad(rgb.sum(), [means, ops])
            assert all(torch.allclose(a, b, atol=1e-9) for a, b in zip(g_out, g_ref))


def test_sh_colours_and_offscreen_gaussians_match_reference():
    means, scales, quats, ops, _ = _scene(30, 5, spread=1.6)  # several Gaussians leave the view
    g = torch.Generator().manual_seed(7)
    sh = torch.randn(30, 16, 3, generator=g, dtype=F64) * 0.3
    cov = covariances_from_scales_quats(scales, quats)
    cams = camera_ring(2, 2.0, -15.0, 24, 20, fov_x_deg=40.0)
    out = render(means, ops, sh, cams, covars=cov, sh_degree=3, background=0.0)
    for v, cam in enumerate(cams):
        rgb, alpha, _ = reference_render(means, cov, ops, sh, cam, torch.zeros(3, dtype=F64), sh_degree=3)
        assert torch.allclose(out.rgb[v], rgb, atol=1e-12)
        assert torch.allclose(out.alpha[v], alpha, atol=1e-12)


@pytest.mark.parametrize("kernels", ["compiled", "tensor"])
def test_gradients_match_brute_force_reference(kernels):
    means, scales, quats, ops, cols = _scene(25, 11, opacity=(0.6, 0.99), scale=(0.05, 0.15))
    leaves = [t.clone().requires_grad_() for t in (means, scales, quats, ops, cols)]
    cams = camera_ring(2, 2.5, 25.0, 20, 16, fov_x_deg=45.0)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=F64, requires_grad=True)
    g = torch.Generator().manual_seed(3)
    w_rgb, w_a, w_d = (torch.randn(2, 16, 20, c, generator=g, dtype=F64) for c in (3, 1, 1))
    out = render(leaves[0], leaves[3], leaves[4], cams, quats=leaves[2], scales=leaves[1], background=bg,
                 raster_options=RasterOptions(tile_size=4, chunk=3, kernels=kernels))
    loss = (out.rgb * w_rgb).sum() + (out.alpha * w_a).sum() + (out.depth * w_d).sum()
    grads = torch.autograd.grad(loss, leaves + [bg])
    ref_loss = 0.0
    for v, cam in enumerate(cams):
        cov = covariances_from_scales_quats(leaves[1], leaves[2])
        rgb, alpha, depth = reference_render(leaves[0], cov, leaves[3], leaves[4], cam, bg)
        ref_loss = ref_loss + (rgb * w_rgb[v]).sum() + (alpha * w_a[v]).sum() + (depth * w_d[v]).sum()
    ref = torch.autograd.grad(ref_loss, leaves + [bg])
    assert loss.item() == pytest.approx(ref_loss.item(), rel=1e-12)
    for name, a, b in zip(["means", "scales", "quats", "opacities", "colors", "background"], grads, ref):
        assert float(b.abs().max()) > 0, name
        assert torch.allclose(a, b, rtol=1e-8, atol=1e-9 * float(b.abs().max())), name


def test_compiled_and_tensor_kernels_agree_on_a_dense_float32_drop():
    """The compiled CPU kernels and the tensor path on what the joint stage renders: 3 000 small, nearly opaque
    float32 Gaussians on a shell (most pixels terminate), 4 views, both tilings; images and gradients agree to float32
    rounding."""
    g = torch.Generator().manual_seed(5)
    d = torch.randn(3000, 3, generator=g)
    means = (0.4 * d / d.norm(dim=1, keepdim=True)).requires_grad_()
    scales = torch.full((3000, 3), 0.02).requires_grad_()
    quats = torch.randn(3000, 4, generator=g)
    ops = (0.6 + 0.39 * torch.rand(3000, generator=g)).requires_grad_()
    cols = torch.rand(3000, 3, generator=g).requires_grad_()
    cams = camera_ring(4, 2.0, 20.0, 64, 48, fov_x_deg=40.0)
    w = torch.randn(4, 48, 64, 3, generator=g)
    for tile in (4, 8):
        outs = []
        for kernels in ("compiled", "tensor"):
            out = render(means, ops, cols, cams, quats=quats, scales=scales, background=0.5,
                         raster_options=RasterOptions(tile_size=tile, kernels=kernels))
            outs.append((out.rgb, out.alpha, *torch.autograd.grad((out.rgb * w).sum(), [means, scales, ops, cols])))
        assert float(outs[0][1].detach().max()) > 0.9999  # pixels terminated
        for a, b in zip(*outs):
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-5 * max(1.0, float(b.detach().abs().max())))


def test_compiled_kernels_on_several_threads_give_the_serial_result():
    """Tiles in parallel (numba's pool, when torch has several threads) and one after the other (one thread) give the
    same image and gradients to the bit: each tile is composited alone, and the gradient rows are summed serially."""
    means, scales, quats, ops, cols = (t.float().requires_grad_() for t in _scene(60, 2, opacity=(0.5, 0.99)))
    cams = camera_ring(3, 2.5, 20.0, 40, 32, fov_x_deg=45.0)
    results = []
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = render(means, ops, cols, cams, quats=quats, scales=scales, background=0.5,
                         raster_options=RasterOptions(kernels="compiled"))
            results.append((out.rgb, *torch.autograd.grad(out.rgb.square().sum(), [means, scales, ops, cols])))
    finally:
        torch.set_num_threads(old)
    assert float(results[0][0].detach().std()) > 0
    for a, b in zip(*results):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_compiled_binning_lists_what_the_tensor_path_lists(dtype):
    """The compiled binning gives the tensor path's tile lists to the element, on one thread and on several: the same
    tiles (the circle test on the same numbers), and per tile the entries by depth with equal depths (many here, −0
    and +0 among them, and NaN, sorted last) in entry order. Also when nothing is visible."""
    from vid2sim.splats.rasterize import bin_gaussians

    g = torch.Generator().manual_seed(5)
    M, W, H, V, ts = 4000, 70, 45, 3, 8
    mux = torch.rand(M, generator=g, dtype=dtype) * (W + 20) - 10
    muy = torch.rand(M, generator=g, dtype=dtype) * (H + 20) - 10
    a, c = (torch.rand(M, generator=g, dtype=dtype) * 0.5 + 0.05 for _ in range(2))
    b = (torch.rand(M, generator=g, dtype=dtype) - 0.5) * 0.1
    log_o = torch.log(torch.rand(M, generator=g, dtype=dtype) * 0.99 + 0.001)  # some below 1/255
    params = torch.stack([mux, muy, a, b, c, log_o], 1)
    lam = 0.5 * (a + c) - torch.sqrt(0.25 * (a - c) ** 2 + b * b)
    r = torch.sqrt(2 * (math.log(255) + log_o).clamp_min(0) / lam).ceil().to(torch.int32)
    radii = torch.stack([r, r], 1)
    depths = torch.round(torch.rand(M, generator=g, dtype=dtype) * 40) / 10  # 41 distinct depths
    depths[::97] = float("nan")
    depths[1::89], depths[2::89], depths[3::101] = -0.0, 0.0, -1.5  # signed zeros sort as equals
    views = torch.randint(0, V, (M,), generator=g)
    tensor = bin_gaussians(params, radii, depths, views, V, W, H, ts)
    assert tensor.n_intersections > 2 * M
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for n in (M, 0):
                want = bin_gaussians(params[:n], radii[:n], depths[:n], views[:n], V, W, H, ts) if n < M else tensor
                got = bin_gaussians(params[:n], radii[:n], depths[:n], views[:n], V, W, H, ts, compiled=True)
                for name in ("isect_entry", "tile_start", "tile_count"):
                    assert torch.equal(getattr(got, name), getattr(want, name)), (threads, n, name)
                    assert getattr(got, name).dtype == torch.int64
    finally:
        torch.set_num_threads(old)


def test_compiled_kernels_take_float32_and_float64_on_the_cpu_only():
    with pytest.raises(ConfigError, match="float32 or float64 CPU"):  # checked before the tile lists are read
        composite(torch.zeros(1, 6, device="meta"), torch.zeros(1, 3, device="meta"), None,
                  RasterOptions(kernels="compiled"))
    with pytest.raises(ConfigError, match="not torch.bfloat16"):
        composite(torch.zeros(1, 6, dtype=torch.bfloat16), torch.zeros(1, 3, dtype=torch.bfloat16), None,
                  RasterOptions(kernels="compiled"))
    assert uses_compiled_kernels(RasterOptions(), torch.zeros(1, dtype=torch.float32))
    assert not uses_compiled_kernels(RasterOptions(), torch.zeros(1, dtype=torch.bfloat16))  # the tensor path
    with pytest.raises(ConfigError, match="kernels must be one of"):
        RasterOptions(kernels="fast")


def test_without_numba_the_cpu_composites_with_tensors_and_says_so(monkeypatch):
    """numba is a dependency; where it does not import (a GPU check's bare machine), "auto" warns and takes the tensor
    path (the same image), and "compiled" names what is missing."""
    rasterize = importlib.import_module("vid2sim.splats.rasterize")
    means, scales, quats, ops, cols = _scene(20, 1)
    cams = camera_ring(1, 2.5, 20.0, 24, 20, fov_x_deg=45.0)
    expected = render(means, ops, cols, cams, quats=quats, scales=scales).rgb
    monkeypatch.setattr(rasterize, "raster_kernels", None)
    monkeypatch.setattr(rasterize, "_NO_KERNELS", "No module named 'numba'")
    with pytest.warns(RuntimeWarning, match="numba does not import"):
        out = render(means, ops, cols, cams, quats=quats, scales=scales).rgb
    assert torch.allclose(out, expected, atol=1e-12)
    with pytest.raises(ConfigError, match="needs numba"):
        render(means, ops, cols, cams, quats=quats, scales=scales, raster_options=RasterOptions(kernels="compiled"))


def test_covariance_gradients_are_symmetric_and_match_reference():
    means, scales, quats, ops, cols = _scene(12, 4, opacity=(0.5, 0.9))
    cov = covariances_from_scales_quats(scales, quats).requires_grad_()
    cam = camera_ring(1, 2.0, 10.0, 16, 16)
    out = render(means, ops, cols, cam, covars=cov)
    (g,) = torch.autograd.grad(out.rgb.sum() + out.depth.sum(), cov)
    rgb, _, depth = reference_render(means, cov, ops, cols, cam[0], torch.ones(3, dtype=F64))
    (r,) = torch.autograd.grad(rgb.sum() + depth.sum(), cov)
    assert torch.allclose(g, g.transpose(1, 2), atol=1e-12)
    assert torch.allclose(g, 0.5 * (r + r.transpose(1, 2)), rtol=1e-8, atol=1e-10)


def test_gradcheck_finite_differences():
    means, scales, quats, ops, cols = _scene(4, 21, opacity=(0.3, 0.7), spread=0.5, scale=(0.08, 0.15))
    cam = camera_ring(1, 2.0, 30.0, 10, 8, fov_x_deg=35.0)
    g = torch.Generator().manual_seed(0)
    w = torch.randn(1, 8, 10, 5, generator=g, dtype=F64)

    def f(m, log_s, q, logit_o, c):
        out = render(m, torch.sigmoid(logit_o), c, cam, quats=q, scales=torch.exp(log_s), background=0.5)
        return (torch.cat([out.rgb, out.alpha, out.depth], -1) * w).sum()

    inputs = (means, torch.log(scales), quats, torch.logit(ops), cols)
    assert torch.autograd.gradcheck(
        f, tuple(t.clone().requires_grad_() for t in inputs), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True
    )


def test_single_gaussian_matches_analytic_ewa_footprint():
    # isotropic Gaussian of std s at depth z on the optical axis: a 2D Gaussian of variance (f s / z)² + 0.3
    f, z, s, o = 40.0, 3.0, 0.05, 0.8
    cam = Camera(torch.eye(4), Camera.intrinsics(f, f, 16.0, 16.0), 32, 32)
    means = torch.tensor([[0.0, 0.0, z]], dtype=F64)
    out = render(means, torch.tensor([o], dtype=F64), torch.ones(1, 3, dtype=F64), cam,
                 covars=(s * s * torch.eye(3, dtype=F64))[None], background=0.0)
    var = (f * s / z) ** 2 + 0.3
    ys, xs = torch.meshgrid(torch.arange(32, dtype=F64) + 0.5, torch.arange(32, dtype=F64) + 0.5, indexing="ij")
    expected = o * torch.exp(-((xs - 16) ** 2 + (ys - 16) ** 2) / (2 * var))
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    assert torch.allclose(out.alpha[0, ..., 0], expected, atol=1e-12)
    assert torch.allclose(out.depth[0, ..., 0][expected > 0], torch.full_like(expected[expected > 0], z))


def test_two_layers_composite_front_to_back():
    # an opaque red sheet in front of a green one: the red wins; swap depths and the green wins
    cam = Camera(torch.eye(4), Camera.intrinsics(20.0, 20.0, 8.0, 8.0), 16, 16)
    cov = torch.diag(torch.tensor([1.0, 1.0, 1e-4], dtype=F64))[None].repeat(2, 1, 1)
    cols = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=F64)
    ops = torch.tensor([0.9, 0.9], dtype=F64)
    for zr, zg, winner in [(2.0, 3.0, 0), (3.0, 2.0, 1)]:
        means = torch.tensor([[0, 0, zr], [0, 0, zg]], dtype=F64)
        out = render(means, ops, cols, cam, covars=cov, background=0.0)
        centre = out.rgb[0, 8, 8]
        a0 = 0.9 * math.exp(-0.5 * 0.25 * 2 / (400 * 1.0 / min(zr, zg) ** 2 + 0.3))
        assert float(centre[winner]) > 0.85 and float(centre[1 - winner]) < 0.1
        assert float(centre[winner]) == pytest.approx(a0, rel=1e-3)


def test_culling_background_and_dtypes():
    means, scales, quats, ops, cols = _scene(20, 8)
    cams = camera_ring(2, 2.5, 0.0, 24, 24)
    behind = torch.tensor([[0.0, 0.0, 0.0]], dtype=F64) + 10 * cams[0].center.to(F64)  # behind camera 0
    out = render(
        torch.cat([means, behind]),
        torch.cat([ops, ops[:1]]),
        torch.cat([cols, cols[:1]]),
        cams,
        quats=torch.cat([quats, quats[:1]]),
        scales=torch.cat([scales, scales[:1] * 50]),
        background=(0.1, 0.2, 0.3),
    )
    ref = render(means, ops, cols, cams, quats=quats, scales=scales, background=(0.1, 0.2, 0.3))
    assert int(out.radii[0, -1].max()) == 0  # culled in the view it is behind
    empty = out.alpha[..., 0] == 0
    assert bool(empty.any())
    assert torch.allclose(out.rgb[empty], torch.tensor([0.1, 0.2, 0.3], dtype=F64).expand(int(empty.sum()), 3))
    assert bool((out.depth[empty] == 0).all())
    assert torch.allclose(out.rgb[0], ref.rgb[0], atol=1e-12)
    out32 = render(means.float(), ops.float(), cols.float(), cams, quats=quats.float(), scales=scales.float())
    out64 = render(means, ops, cols, cams, quats=quats, scales=scales)
    assert out32.rgb.dtype == torch.float32
    assert float((out32.rgb.double() - out64.rgb).abs().max()) < 2e-4


def test_render_gaussians_and_validation_errors():
    g = Gaussians.from_values(
        torch.zeros(3, 3), torch.full((3,), 0.1), torch.rand(3, 3), torch.full((3,), 0.5), sh_degree=1
    )
    cams = camera_ring(2, 2.0, 10.0, 8, 8)
    assert render_gaussians(g, cams).rgb.shape == (2, 8, 8, 3)
    m, o, c = g.means, g.opacities, g.colors_dc
    with pytest.raises(ValueError, match="means must"):
        render(m[:, :2], o, c, cams, covars=g.covariances())
    with pytest.raises(ValueError, match="either covars"):
        render(m, o, c, cams, covars=g.covariances(), quats=g.quats, scales=g.scales)
    with pytest.raises(ValueError, match="pass covars"):
        render(m, o, c, cams, quats=g.quats)
    with pytest.raises(ValueError, match="SH coefficients"):
        render(m, o, c, cams, covars=g.covariances(), sh_degree=1)
    with pytest.raises(ValueError, match="background"):
        render(m, o, c, cams, covars=g.covariances(), background=(1.0, 1.0))
    with pytest.raises(ValueError, match="backend must be"):
        render(m, o, c, cams, covars=g.covariances(), backend="vulkan")
    with pytest.raises(ValueError, match="CUDA"):
        resolve_backend("gsplat", torch.device("cpu"), torch.float32)
    assert resolve_backend("auto", torch.device("cpu"), torch.float32) == "torch"
    with pytest.raises(ValueError, match="tile_size"):
        RasterOptions(tile_size=3)


def test_backend_choice_when_gsplat_cannot_run(monkeypatch):
    """On CUDA tensors, 'auto' falls back to torch with a warning that says why; 'gsplat' raises it."""
    render_module = importlib.import_module("vid2sim.splats.render")  # the attribute is the function

    cuda = torch.device("cuda")  # a device object only: nothing is allocated on it
    monkeypatch.setattr(render_module, "gsplat_unavailable_reason", lambda: "gsplat found no CUDA toolkit")
    with pytest.warns(RuntimeWarning, match="torch backend on cuda: gsplat found no CUDA toolkit"):
        assert resolve_backend("auto", cuda, torch.float32) == "torch"
    with pytest.raises(RuntimeError, match="gsplat found no CUDA toolkit.*backend='torch'"):
        resolve_backend("gsplat", cuda, torch.float32)
    assert resolve_backend("auto", cuda, torch.float64) == "torch"  # gsplat renders float32 only
    monkeypatch.setattr(render_module, "gsplat_unavailable_reason", lambda: None)
    assert resolve_backend("auto", cuda, torch.float32) == "gsplat"
    assert resolve_backend("auto", torch.device("cpu"), torch.float32) == "torch"


def test_gsplat_probe_names_what_is_missing(monkeypatch):
    render_module = importlib.import_module("vid2sim.splats.render")
    fake = types.ModuleType("gsplat.cuda._backend")
    fake._C = None
    monkeypatch.setitem(sys.modules, "gsplat", types.ModuleType("gsplat"))
    monkeypatch.setitem(sys.modules, "gsplat.cuda", types.ModuleType("gsplat.cuda"))
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", fake)
    assert "no CUDA toolkit" in render_module._probe_gsplat()
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat → ImportError
    assert "not importable" in render_module._probe_gsplat()


def test_screen_space_gradients_for_densification():
    means, scales, quats, ops, cols = _scene(10, 2)
    cams = camera_ring(2, 2.0, 10.0, 16, 16)
    means = means.float().requires_grad_()
    out = render(means, ops.float(), cols.float(), cams, quats=quats.float(), scales=scales.float())
    out.means2d.retain_grad()
    out.rgb.sum().backward()
    assert out.means2d.grad.shape == (2, 10, 2)
    visible = out.radii.amax(-1) > 0
    assert bool((out.means2d.grad.norm(dim=-1)[~visible] == 0).all())
    assert float(out.means2d.grad.norm(dim=-1)[visible].max()) > 0


@pytest.mark.cuda
def test_torch_backend_on_cuda_matches_cpu():
    means, scales, quats, ops, cols = (t.float() for t in _scene(200, 9))
    cams = camera_ring(3, 2.5, 20.0, 64, 48)
    cpu = render(means, ops, cols, cams, quats=quats, scales=scales, backend="torch")
    gpu = render(means.cuda(), ops.cuda(), cols.cuda(), [c.to("cuda") for c in cams],
                 quats=quats.cuda(), scales=scales.cuda(), backend="torch")
    assert torch.allclose(gpu.rgb.cpu(), cpu.rgb, atol=1e-5)


def test_gaussians_out_of_every_view_render_the_background():
    """When no Gaussian reaches any tile of any camera (the object left the views) the image is the background."""
    n = 20
    g = Gaussians(means=(torch.randn(n, 3) * 0.1 + torch.tensor([0.0, 0.0, -50.0])).requires_grad_(),
                  log_scales=torch.full((n, 3), -3.0), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  opacity_logits=torch.zeros(n), sh=torch.rand(n, 1, 3))
    out = render_gaussians(g, camera_ring(2, 2.0, 20.0, 32, 32), background=0.25)
    assert out.rgb.shape == (2, 32, 32, 3) and bool((out.rgb == 0.25).all())
    out.rgb.sum().backward()
    assert bool((g.means.grad == 0).all())


def test_per_view_gaussians_render_like_one_call_per_view():
    """Means (V, N, 3) and covariances (V, N, 3, 3): view v shows set v — images and gradients equal V
    separate renders (this is how the joint optimisation composites a window's frames in one call)."""
    means, scales, quats, ops, _ = _scene(30, 8, opacity=(0.5, 0.95))
    g = torch.Generator().manual_seed(2)
    sh = (0.3 * torch.randn(30, 4, 3, generator=g, dtype=F64)).requires_grad_()
    cov = covariances_from_scales_quats(scales, quats)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.05, 0.02], [-0.08, 0.03, 0.1]], dtype=F64)
    per_means = (means[None] + shift[:, None]).requires_grad_()
    A = torch.eye(3, dtype=F64) + 0.1 * torch.randn(3, 30, 3, 3, generator=g, dtype=F64)
    per_cov = (A @ cov @ A.transpose(-1, -2)).requires_grad_()
    cams = camera_ring(3, 2.3, 20.0, 24, 20, fov_x_deg=45.0)
    w = torch.randn(3, 20, 24, 3, generator=g, dtype=F64)
    out = render(per_means, ops, sh, cams, covars=per_cov, sh_degree=1, background=0.3)
    assert out.rgb.shape == (3, 20, 24, 3) and out.means2d.shape == (3, 30, 2)
    grads = torch.autograd.grad((out.rgb * w).sum(), [per_means, per_cov, sh])
    loss = 0.0
    for v, cam in enumerate(cams):
        one = render(per_means[v], ops, sh, [cam], covars=per_cov[v], sh_degree=1, background=0.3)
        assert torch.allclose(out.rgb[v], one.rgb[0], atol=1e-13)
        assert torch.allclose(out.means2d[v], one.means2d[0], atol=1e-13)
        loss = loss + (one.rgb[0] * w[v]).sum()
    ref = torch.autograd.grad(loss, [per_means, per_cov, sh])
    for name, a, b in zip(("means", "covars", "sh"), grads, ref):
        assert float(b.abs().max()) > 0, name
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max())), name


def test_per_view_gaussians_need_one_set_per_camera_and_covariances():
    means, scales, quats, ops, cols = _scene(5, 1)
    cov = covariances_from_scales_quats(scales, quats)
    cams = camera_ring(2, 2.3, 20.0, 8, 8)
    with pytest.raises(ValueError, match="one set per camera"):
        render(means[None].expand(3, 5, 3), ops, cols, cams, covars=cov[None].expand(3, 5, 3, 3))
    with pytest.raises(ValueError, match="covars must have shape"):
        render(means[None].expand(2, 5, 3), ops, cols, cams, covars=cov)
    with pytest.raises(ValueError, match="per-view covars"):
        render(means[None].expand(2, 5, 3), ops, cols, cams, quats=quats, scales=scales)
