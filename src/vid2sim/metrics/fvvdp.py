"""FovVideoVDP (Mantiuk et al. 2021), a perceptual video-quality metric in JOD units, through ``pyfvvdp``.

``pyfvvdp`` is licensed CC BY-NC 4.0 (non-commercial), so it is an optional extra, imported only when
:func:`fovvdp` is called: ``pip install "vid2sim[fvvdp]"``. Written against pyfvvdp 1.2.2's API:
``pyfvvdp.fvvdp(display_name=..., quiet=..., device=...)`` and ``.predict(test, reference,
dim_order="FHWC", frames_per_second=fps)`` → ``(Q_JOD, stats)``. JOD 10 means no visible difference;
lower is worse. Report the display model with the score (``info`` holds pyfvvdp's own description
string, which its authors ask to be quoted with results).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import Tensor

ArrayLike = Tensor | np.ndarray

_INSTALL_HINT = ('FovVideoVDP needs the optional package pyfvvdp: pip install "vid2sim[fvvdp]" '
                 "(pyfvvdp is licensed CC BY-NC 4.0, non-commercial use only)")


def _video(x: ArrayLike, name: str) -> Tensor:
    t = (x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))).detach()
    if not t.is_floating_point():
        raise TypeError(f"{name} must hold floats in [0, 1], got dtype {t.dtype}")
    if t.ndim != 4 or t.shape[-1] != 3 or t.shape[0] == 0:
        raise ValueError(f"{name} must have shape (T, H, W, 3) with T ≥ 1, got {tuple(t.shape)}")
    return t


def fovvdp(renders: ArrayLike, targets: ArrayLike, fps: float, display: str = "standard_4k") -> dict:
    """FovVideoVDP quality of a rendered video against the reference video (non-foveated).

    The frames are taken as display-encoded sRGB in [0, 1] (values outside are clipped, as a display
    would) and passed to pyfvvdp as float32 — the float type its array input accepts. A single frame
    (T = 1) is scored as an image (fps ignored).

    Args:
        renders: (T, H, W, 3) test video, floats in [0, 1]. targets: (T, H, W, 3) reference video.
        fps: frames per second of the videos (> 0 when T > 1; 20 for the 0.05 s frames of vid2sim scenes).
        display: a display model of pyfvvdp's ``display_models.json`` (e.g. ``standard_4k``,
            ``standard_fhd``, ``standard_phone``); it sets the viewing geometry and peak luminance.

    Returns:
        ``{"jod": float, "display": str, "info": str}`` — the JOD score, the display model used and
        pyfvvdp's description of the configuration (version, pixels per degree, luminance).

    Raises:
        RuntimeError: pyfvvdp is not installed (with the install command and its licence), or pyfvvdp
            rejects the display name.
    """
    a, b = _video(renders, "renders"), _video(targets, "targets")
    if a.shape != b.shape:
        raise ValueError(f"renders and targets must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    T = a.shape[0]
    if T > 1 and not fps > 0:
        raise ValueError(f"fps must be positive for a video of {T} frames, got {fps}")
    try:
        import pyfvvdp
    except ImportError as err:
        raise RuntimeError(f"{_INSTALL_HINT} [import failed: {err}]") from err
    device = a.device
    test = a.to(torch.float32).clamp(0.0, 1.0).contiguous()
    ref = b.to(device=device, dtype=torch.float32).clamp(0.0, 1.0).contiguous()
    with warnings.catch_warnings(), torch.no_grad():
        # pyfvvdp 1.2.2 reads its CSF tables through a scipy namespace that scipy deprecates.
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"pyfvvdp(\.|$)")
        metric = pyfvvdp.fvvdp(display_name=display, heatmap=None, quiet=True, device=device)
        q, _stats = metric.predict(test, ref, dim_order="FHWC", frames_per_second=float(fps) if T > 1 else 0)
    return {"jod": float(q), "display": display, "info": metric.get_info_string().strip('"')}


__all__ = ["fovvdp"]
