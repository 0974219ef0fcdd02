"""Image metrics: PSNR by hand, SSIM against scikit-image and a zero-padded per-pixel loop, the stacks'
bookkeeping, the training loss's SSIM (the same implementation, "valid" variant) and FovVideoVDP."""

import math
import sys

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from vid2sim.metrics import image_metrics, psnr, ssim, ssim_map
from vid2sim.metrics.fvvdp import fovvdp
from vid2sim.metrics.images import _separable_blur, gaussian_window
from vid2sim.splats import losses


def smooth_images(n: int, h: int, w: int, seed: int) -> np.ndarray:
    """(n, h, w, 3) random images in [0, 1], smooth over a few pixels."""
    rng = np.random.default_rng(seed)
    x = gaussian_filter(rng.random((n, h, w, 3)), sigma=(0, 2, 2, 0))
    x -= x.min()
    return x / x.max()


def test_psnr_hand_computed():
    target = np.zeros((2, 2, 3))
    render = target.copy()
    render[0, 1, 2] = 0.5  # one channel of one pixel off by 0.5: MSE = 0.25 / 12
    assert psnr(render, target) == pytest.approx(-10 * math.log10(0.25 / 12), abs=1e-12)
    # Constant offset 0.1 over a batch: MSE 0.01, 20 dB.
    assert psnr(torch.full((3, 4, 5, 3), 0.6), torch.full((3, 4, 5, 3), 0.5)) == pytest.approx(20.0, abs=1e-5)
    # Mask: only the differing pixel → MSE over its 3 channels = 0.25 / 3; all other pixels → identical.
    mask = np.zeros((2, 2), dtype=bool)
    mask[0, 1] = True
    assert psnr(render, target, mask=mask) == pytest.approx(-10 * math.log10(0.25 / 3), abs=1e-12)
    assert psnr(render, target, mask=~mask) == pytest.approx(100.0)
    assert psnr(render[None], target[None], mask=mask[None, :, :, None]) == pytest.approx(-10 * math.log10(0.25 / 3))
    # Identical images: the MSE is clamped at 1e-10 → 100 dB, not infinity.
    assert psnr(target, target) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="no pixels"):
        psnr(render, target, mask=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="mask must have shape"):
        psnr(render, target, mask=np.ones((3, 2)))
    with pytest.raises(ValueError, match="same shape"):
        psnr(render, target[:1])


def test_ssim_identical_is_one_and_batch_is_mean_of_images():
    x = smooth_images(3, 24, 20, seed=0)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    assert ssim(x[0], x[0]) == pytest.approx(1.0, abs=1e-12)
    y = np.clip(x + 0.05 * np.random.default_rng(1).standard_normal(x.shape), 0, 1)
    per_image = [ssim(x[i], y[i]) for i in range(3)]
    assert ssim(x, y) == pytest.approx(np.mean(per_image), abs=1e-12)
    assert ssim(x, y) < 0.99
    assert ssim_map(x, y).shape == (3, 24, 20, 3)
    assert ssim_map(x[0], y[0], padding="valid").shape == (14, 10, 3)


def test_ssim_matches_scikit_image_in_the_interior():
    """scikit-image (Gaussian weights σ = 1.5 → an 11-pixel window, population covariance, L = 1) crops a
    5-pixel border; inside it the windows never reach the padding, so the maps must agree."""
    from skimage.metrics import structural_similarity

    x = smooth_images(1, 40, 48, seed=2)[0]
    y = np.clip(x + 0.3 * (smooth_images(1, 40, 48, seed=3)[0] - 0.5), 0, 1)
    mssim, full = structural_similarity(x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1.0, channel_axis=-1, full=True)
    ours = ssim_map(torch.from_numpy(x), torch.from_numpy(y)).numpy()
    assert ours.shape == full.shape
    assert np.abs(ours[5:-5, 5:-5] - full[5:-5, 5:-5]).max() < 1e-4
    assert abs(ours[5:-5, 5:-5].mean() - mssim) < 1e-4
    # The "valid" map is exactly the "same" map's interior.
    valid = ssim_map(torch.from_numpy(x), torch.from_numpy(y), padding="valid").numpy()
    np.testing.assert_allclose(valid, ours[5:-5, 5:-5], atol=1e-12)


def test_ssim_border_is_zero_padded_like_3dgs():
    """A per-pixel loop with an 11×11 window over a zero-padded image (3DGS's padding = window // 2)."""
    rng = np.random.default_rng(4)
    x, y = rng.random((14, 13, 3)), rng.random((14, 13, 3))
    k = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    k2 = np.outer(k, k) / np.outer(k, k).sum()
    xp, yp = np.pad(x, ((5, 5), (5, 5), (0, 0))), np.pad(y, ((5, 5), (5, 5), (0, 0)))
    ref = np.empty_like(x)
    c1, c2 = 0.01**2, 0.03**2
    for i in range(14):
        for j in range(13):
            for c in range(3):
                wx, wy = xp[i : i + 11, j : j + 11, c], yp[i : i + 11, j : j + 11, c]
                mx, my = (k2 * wx).sum(), (k2 * wy).sum()
                vx, vy = (k2 * wx * wx).sum() - mx * mx, (k2 * wy * wy).sum() - my * my
                cxy = (k2 * wx * wy).sum() - mx * my
                ref[i, j, c] = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    ours = ssim_map(torch.from_numpy(x), torch.from_numpy(y)).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-10)
    assert ssim(x, y) == pytest.approx(ref.mean(), abs=1e-10)


@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_float64_sums_equal_the_float32_convolutions_and_are_differentiable(padding):
    """float64 blurs with shifted sums, other dtypes with depthwise convolutions: the same map, and the sums'
    gradient is the finite differences'."""
    x = torch.from_numpy(smooth_images(2, 23, 19, seed=5))
    y = torch.from_numpy(np.clip(smooth_images(2, 23, 19, seed=6) + 0.1, 0, 1))
    m64 = ssim_map(x, y, padding=padding)
    m32 = ssim_map(x.float(), y.float(), padding=padding)
    assert m64.dtype == torch.float64 and m32.dtype == torch.float32
    assert (m64 - m32.double()).abs().max() < 1e-4  # float32's own round-off in the variances
    g = gaussian_window(11, 1.5, torch.float64, x.device)
    pad = 5 if padding == "same" else 0
    images = x.permute(0, 3, 1, 2)
    direct = torch.nn.functional.conv2d(images, torch.outer(g, g).expand(3, 1, 11, 11), padding=pad, groups=3)
    assert (_separable_blur(images, g, pad) - direct).abs().max() < 1e-14
    assert (_separable_blur(images.float(), g.float(), pad).double() - direct).abs().max() < 1e-6
    small_x = x[:1, :13, :12, :2].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a: ssim_map(a, y[:1, :13, :12, :2], window=5, padding=padding),
                                    (small_x,))


def test_training_loss_uses_the_valid_variant_and_stays_differentiable():
    a = torch.rand(2, 16, 18, 3, requires_grad=True)
    b = torch.rand(2, 16, 18, 3)
    m = losses.ssim_map(a, b)
    assert m.shape == (2, 6, 8, 3) and m.dtype == torch.float32
    torch.testing.assert_close(m, ssim_map(a, b, padding="valid"))
    (g,) = torch.autograd.grad(losses.photometric_loss(a, b), a)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_image_metrics_stacks():
    T, V = 3, 2
    target = torch.from_numpy(smooth_images(T * V, 16, 16, seed=5)).reshape(T, V, 16, 16, 3)
    noise = 0.02 * torch.arange(1, T * V + 1, dtype=torch.float64).reshape(T, V, 1, 1, 1)
    render = (target + noise * torch.randn(target.shape, generator=torch.Generator().manual_seed(0),
                                           dtype=torch.float64)).clamp(0, 1)
    tv = image_metrics(render, target, layout="TV")
    vt = image_metrics(render.transpose(0, 1), target.transpose(0, 1), layout="VT")
    assert tv["num_images"] == T * V and tv["layout"] == "TV" and vt["layout"] == "VT"
    for key in ("psnr", "ssim", "psnr_per_frame", "ssim_per_frame", "psnr_per_view", "ssim_per_view",
                "psnr_per_image", "ssim_per_image"):
        np.testing.assert_allclose(tv[key], vt[key], atol=1e-12, err_msg=key)
    assert len(tv["psnr_per_frame"]) == T and len(tv["psnr_per_view"]) == V
    for t in range(T):
        for v in range(V):
            assert tv["psnr_per_image"][t][v] == pytest.approx(psnr(render[t, v], target[t, v]), abs=1e-9)
            assert tv["ssim_per_image"][t][v] == pytest.approx(ssim(render[t, v], target[t, v]), abs=1e-9)
        assert tv["psnr_per_frame"][t] == pytest.approx(np.mean(tv["psnr_per_image"][t]), abs=1e-9)
    assert tv["psnr"] == pytest.approx(np.mean(tv["psnr_per_image"]), abs=1e-9)
    assert tv["ssim"] == pytest.approx(np.mean(tv["ssim_per_image"]), abs=1e-9)
    # More noise, lower scores.
    assert tv["psnr_per_image"][0][0] > tv["psnr_per_image"][2][1]
    flat = image_metrics(render.reshape(T * V, 16, 16, 3), target.reshape(T * V, 16, 16, 3))
    assert flat["psnr_per_frame"] == pytest.approx(sum(tv["psnr_per_image"], []), abs=1e-12)
    assert "layout" not in flat and flat["num_images"] == T * V
    with pytest.raises(ValueError, match="layout='TV'"):
        image_metrics(render, target)
    with pytest.raises(ValueError, match="layout is only for 5-D"):
        image_metrics(render[0], target[0], layout="TV")


def test_fovvdp_without_pyfvvdp_explains_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyfvvdp", None)  # makes `import pyfvvdp` raise ImportError
    x = torch.rand(2, 8, 8, 3)
    with pytest.raises(RuntimeError, match=r'pip install "vid2sim\[fvvdp\]".*CC BY-NC'):
        fovvdp(x, x, fps=20.0)


def test_fovvdp_prefers_identical_videos():
    pytest.importorskip("pyfvvdp")
    ref = torch.from_numpy(smooth_images(4, 32, 32, seed=6)).float()
    noisy = (ref + 0.1 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    same = fovvdp(ref.clone(), ref, fps=20.0)
    worse = fovvdp(noisy, ref, fps=20.0, display="standard_fhd")
    assert same["display"] == "standard_4k" and worse["display"] == "standard_fhd"
    assert "standard_fhd" in worse["info"]
    assert same["jod"] == pytest.approx(10.0, abs=1e-3)
    assert worse["jod"] < same["jod"] - 0.3
