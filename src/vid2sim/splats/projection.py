"""EWA projection of 3D Gaussians to image-plane Gaussians (pinhole cameras, OpenCV axes).

For a Gaussian with mean p and covariance Σ seen by a camera with world-to-camera (R, t) and
intrinsics (fx, fy, cx, cy):

    p_c = R p + t,            z = p_c.z,
    mean2d = (fx x/z + cx, fy y/z + cy),
    Σ2d = J R Σ Rᵀ Jᵀ + ε I,  J = [[fx/z, 0, −fx x'/z²], [0, fy/z, −fy y'/z²]],

where ε = ``eps2d`` (0.3 px², the usual low-pass filter that keeps every splat at least about a pixel
wide) and (x', y') are x, y with x/z, y/z clamped to 1.3× the image's extent (as the reference 3DGS
code and gsplat do, so that Gaussians far outside the view do not blow up the Jacobian). The inverse
Σ2d⁻¹ is returned as ``conics`` (a, b, c) = ((Σ2d⁻¹)₀₀, (Σ2d⁻¹)₀₁, (Σ2d⁻¹)₁₁).

A Gaussian is culled from a view (``radii == 0``) when its depth is outside (near, far), its 2D
covariance is degenerate, its opacity is below 1/255, or its screen bounding box misses the image.
The bounding-box half-size is ``ceil(extent · sqrt(Σ2d_ii))`` with
``extent = min(3.33, sqrt(2 ln(255 · opacity)))``: outside it the Gaussian's alpha is below 1/255
and compositing would skip it anyway, so culling does not change the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_EXTENT = 3.33


@dataclass
class Projection:
    """Image-plane Gaussians for V views of N Gaussians.

    Attributes:
        means2d: (V, N, 2) pixel coordinates of the projected centres (pixel centres at +0.5).
        conics: (V, N, 3) inverse 2D covariance (a, b, c), with the ε low-pass included.
        depths: (V, N) camera-space z of the centres.
        radii: (V, N, 2) int32 half sizes of the screen bounding boxes in pixels; 0 where culled.
        visible: (V, N) bool, not culled.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor


def project_gaussians(
    means: Tensor,
    covars: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Projection:
    """Project Gaussians into V pinhole views (differentiable w.r.t. means and covars).

    Args:
        means: (N, 3) world centres, or (V, N, 3) one set per view.
        covars: (N, 3, 3) world covariances (symmetrised here, so gradients come out symmetric), or
            (V, N, 3, 3) with per-view means.
        opacities: (N,) opacities in [0, 1], used only for culling and box sizes.
        viewmats: (V, 4, 4) world-to-camera transforms (OpenCV axes).
        Ks: (V, 3, 3) intrinsics.
        width, height: image size in pixels.
        eps2d: low-pass variance added to the 2D covariance, in px².
        near_plane, far_plane: depth range kept.
    """
    R = viewmats[:, :3, :3]  # (V, 3, 3)
    t = viewmats[:, :3, 3]  # (V, 3)
    p_c = torch.matmul(means, R.transpose(1, 2)) + t[:, None, :]  # (V, N, 3)
    x, y, z = p_c.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # (V, 1)
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    rz = 1.0 / z_safe
    u = x * rz
    v = y * rz
    mean2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)  # (V, N, 2)

    sym = 0.5 * (covars + covars.transpose(-1, -2))
    # the six entries (il) of R Σ Rᵀ are linear in Σ: Σ_jk R_ij R_lk Σ_jk, one small GEMM per view
    rows = torch.tensor([0, 0, 0, 1, 1, 2], device=R.device)
    cols = torch.tensor([0, 1, 2, 1, 2, 2], device=R.device)
    kron = (R[:, rows, :, None] * R[:, cols, None, :]).reshape(-1, 6, 9)  # (V, 6, 9)
    cov_c = torch.matmul(sym.reshape(*sym.shape[:-2], 9), kron.transpose(1, 2))  # (V, N, 6)
    c00, c01, c02, c11, c12, c22 = cov_c.unbind(-1)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u_c = torch.clamp(u, -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x)
    v_c = torch.clamp(v, -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)
    j00 = fx * rz
    j11 = fy * rz
    j02 = -fx * u_c * rz  # = −fx · x'/z²
    j12 = -fy * v_c * rz
    s00 = j00 * j00 * c00 + 2.0 * j00 * j02 * c02 + j02 * j02 * c22 + eps2d
    s11 = j11 * j11 * c11 + 2.0 * j11 * j12 * c12 + j12 * j12 * c22 + eps2d
    s01 = j00 * j11 * c01 + j00 * j12 * c02 + j02 * j11 * c12 + j02 * j12 * c22
    det = s00 * s11 - s01 * s01
    ok = in_depth & (det > 0)
    inv_det = 1.0 / torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([s11 * inv_det, -s01 * inv_det, s00 * inv_det], dim=-1)

    with torch.no_grad():
        op = opacities.detach()
        if op.ndim == 1:
            op = op[None].expand(z.shape)
        ok = ok & (op >= ALPHA_THRESHOLD)
        extent = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp(max=MAX_EXTENT)
        rx = torch.ceil(extent * torch.sqrt(s00.detach().clamp_min(0)))
        ry = torch.ceil(extent * torch.sqrt(s11.detach().clamp_min(0)))
        m = mean2d.detach()
        on_screen = (m[..., 0] + rx > 0) & (m[..., 0] - rx < width) & (m[..., 1] + ry > 0) & (m[..., 1] - ry < height)
        visible = ok & on_screen & ((rx > 0) | (ry > 0)) & torch.isfinite(m).all(-1)
        radii = torch.stack([rx, ry], dim=-1).nan_to_num(0.0).clamp(0, 2**30).to(torch.int32)
        radii = radii * visible[..., None].to(torch.int32)
    return Projection(means2d=mean2d, conics=conics, depths=z, radii=radii, visible=visible)
