"""Gravity in calibration units from free flight: while nothing touches it, an object's centre of mass moves on a
parabola, ``x(t) = p + v t + ½ a t²``, whatever it does around it. ``a`` is gravity in the calibration's frame
and units: its direction is down, and ``|g| / |a|`` (|g| = 9.81 m/s²) is the number of metres per unit.

The tracked centre (:mod:`vid2sim.scene.capture.hull`) is only close to the centre of mass, and it is noisy, so the
fit is robust:

1. the tracking noise σ is measured from the third differences of the track (zero on any parabola);
2. free-flight windows are grown frame by frame from every start while one parabola still explains them (each
   new frame within tolerance of the prediction); moving windows whose acceleration is clearly not zero are
   candidates (a resting object also fits a parabola, with a ≈ 0), and the longest of those whose acceleration
   comes close to the largest starts (:func:`seed_window`): free fall is the largest acceleration an object
   keeps for many frames;
3. with a first ``a`` the object's lowest point along the gravity direction tells flight from contact: frames
   above the contact level are in the air, broken into segments where the vertical velocity jumps up (a bounce
   between two frames in the air);
4. the first flight — before the first contact — is measured alone when one parabola explains enough of it (its
   frames within tolerance of the parabola of its longest consistent run, :func:`flight_frames`: a release from
   the hand starts it): after a bounce a soft object wobbles, and its tracked
   centre strays from its centre of mass; otherwise all segments are fitted together, each with its own position
   and velocity and one shared ``a`` (linear least squares). 3–4 repeat twice. The covariance of ``a`` comes from
   the residuals (or from σ when too few); :func:`jackknife_sigma` measures the spread the frames themselves
   give.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class BallisticFit:
    """A joint parabola fit.

    Attributes:
        acceleration: (3,) a in calibration units / s²; covariance: (3, 3) its covariance.
        segments: the free-flight segments, each a list of frame indices.
        residual: RMS residual of the fit (calibration units); noise: the tracking noise σ assumed.
        direction_fixed: a was fitted along a given direction (only its magnitude free).
    """

    acceleration: np.ndarray
    covariance: np.ndarray
    segments: list[list[int]]
    residual: float
    noise: float
    direction_fixed: bool = False

    @property
    def frames(self) -> list[int]:
        return sorted(f for s in self.segments for f in s)

    def magnitude_sigma(self) -> float:
        """Standard deviation of |a|."""
        a = self.acceleration
        n = a / max(np.linalg.norm(a), 1e-300)
        return float(np.sqrt(max(n @ self.covariance @ n, 0.0)))

    def direction_sigma_deg(self) -> float:
        """Standard deviation of a's direction (degrees; the two perpendicular components combined)."""
        a = self.acceleration
        norm = max(np.linalg.norm(a), 1e-300)
        n = a / norm
        P = np.eye(3) - np.outer(n, n)
        return float(np.degrees(np.sqrt(max(np.trace(P @ self.covariance @ P), 0.0)) / norm))


def tracking_noise(x: np.ndarray) -> float:
    """Robust noise σ of a track (T, 3) (NaN rows skipped): the median absolute third difference per coordinate,
    scaled for a Gaussian (a third difference of white noise has std √20 σ)."""
    d = x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]
    d = d[np.isfinite(d).all(1)]
    if len(d) == 0:
        return float("nan")
    return float(np.median(np.abs(d)) / 0.6745 / np.sqrt(20.0))


def fit_segments(x: np.ndarray, dt: float, segments: list[list[int]], direction: np.ndarray | None = None,
                 noise: float | None = None, robust: bool = True) -> BallisticFit:
    """One parabola per segment with a shared acceleration, by (iteratively reweighted) linear least squares.

    Args:
        x: (T, 3) track; dt: seconds per frame; segments: lists of frame indices (≥ 3 each).
        direction: if given (3,), a = α·direction with only α free.
        noise: the σ to use when the fit has too few degrees of freedom to measure its own, and the scale of the
            robust weights.
        robust: Huber weights per frame (a frame whose residual exceeds 2σ counts less: a deforming object's hull
            strays from its centre of mass now and then).
    """
    rows = sum(len(s) for s in segments)
    n_acc = 1 if direction is not None else 3
    n_par = 6 * len(segments) + n_acc
    A = np.zeros((3 * rows, n_par))
    b = np.zeros(3 * rows)
    r = 0
    for k, seg in enumerate(segments):
        t0 = np.mean(seg)
        for f in seg:
            t = (f - t0) * dt
            for c in range(3):
                A[3 * r + c, 6 * k + c] = 1.0
                A[3 * r + c, 6 * k + 3 + c] = t
                if direction is None:
                    A[3 * r + c, 6 * len(segments) + c] = 0.5 * t * t
                else:
                    A[3 * r + c, 6 * len(segments)] = 0.5 * t * t * direction[c]
                b[3 * r + c] = x[f, c]
            r += 1
    w = np.ones(rows)
    for _ in range(6 if robust and noise is not None and np.isfinite(noise) and noise > 0 else 1):
        W = np.repeat(w, 3)
        sol, *_ = np.linalg.lstsq(A * np.sqrt(W)[:, None], b * np.sqrt(W), rcond=None)
        res = A @ sol - b
        per_frame = np.linalg.norm(res.reshape(rows, 3), axis=1)
        if robust and noise is not None and np.isfinite(noise) and noise > 0:
            k_h = 2.0 * np.sqrt(3.0) * noise
            w = np.where(per_frame <= k_h, 1.0, k_h / np.maximum(per_frame, 1e-300))
    W = np.repeat(w, 3)
    dof = len(b) - n_par
    rms = float(np.sqrt((res ** 2).mean())) if len(b) else 0.0
    sigma2 = float((W * res ** 2).sum() / max(W.mean(), 1e-12) / dof) if dof >= 3 else 0.0
    if noise is not None and np.isfinite(noise):
        sigma2 = max(sigma2, noise ** 2)
    cov_all = sigma2 * np.linalg.pinv((A * W[:, None]).T @ A / max(W.mean(), 1e-12))
    if direction is None:
        acc = sol[-3:]
        cov = cov_all[-3:, -3:]
    else:
        acc = sol[-1] * direction
        cov = cov_all[-1, -1] * np.outer(direction, direction)
    return BallisticFit(acc, cov, [list(s) for s in segments], rms, float(np.sqrt(sigma2)), direction is not None)


def jackknife_sigma(x: np.ndarray, dt: float, segments: list[list[int]], direction: np.ndarray | None = None,
                    noise: float | None = None, block: int = 3) -> float:
    """Block-jackknife standard deviation of |a|: the joint fit repeated without each block of ``block``
    consecutive frames (a mask's error lasts a few frames, so single frames would understate it); NaN with fewer
    than 4 blocks."""
    frames = sorted(f for s in segments for f in s)
    blocks = [set(frames[i:i + block]) for i in range(0, len(frames), block)]
    if len(blocks) < 4:
        return float("nan")
    mags = []
    for drop in blocks:
        kept = [[f for f in s if f not in drop] for s in segments]
        kept = [s for s in kept if len(s) >= 3]
        if kept:
            mags.append(float(np.linalg.norm(fit_segments(x, dt, kept, direction, noise=noise).acceleration)))
    m = len(mags)
    if m < 4:
        return float("nan")
    return float(np.sqrt((m - 1) / m * ((np.array(mags) - np.mean(mags)) ** 2).sum()))


def _windows(x: np.ndarray, dt: float, tol: float, min_len: int) -> list[list[int]]:
    """Maximal runs of consecutive tracked frames that one parabola explains (each new frame within ``tol`` of the
    prediction from the frames before it)."""
    T = len(x)
    ok = np.isfinite(x).all(1)
    out = []
    for s in range(T):
        if not ok[s]:
            continue
        seg = [s]
        e = s + 1
        while e < T and ok[e]:
            cand = seg + [e]
            if len(cand) >= 4:
                pred = _predict(x, dt, seg, fit_segments(x, dt, [seg]), e)
                if np.linalg.norm(pred - x[e]) > tol:
                    break
            seg = cand
            e += 1
        if len(seg) >= min_len:
            out.append(seg)
    return out


def _predict(x: np.ndarray, dt: float, seg: list[int], fit: BallisticFit, frame: int) -> np.ndarray:
    """The fitted parabola of ``seg`` at ``frame``."""
    t0 = np.mean(seg)
    ts = (np.array(seg) - t0) * dt
    # refit position and velocity with the fitted acceleration (closed form)
    y = x[seg] - 0.5 * np.outer(ts * ts, fit.acceleration)
    A = np.stack([np.ones_like(ts), ts], 1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    t = (frame - t0) * dt
    return coef[0] + coef[1] * t + 0.5 * fit.acceleration * t * t


def flight_segments(x: np.ndarray, lowest: np.ndarray, sigma_h: float, contact_level: float) -> list[list[int]]:
    """Runs of tracked frames in the air: the lowest point above ``contact_level`` by 4σ_h."""
    T = len(x)
    air = np.isfinite(lowest) & (lowest > contact_level + 4.0 * sigma_h) & np.isfinite(x).all(1)
    runs, cur = [], []
    for t in range(T):
        if air[t]:
            cur.append(t)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    return runs


def split_bounces(h: np.ndarray, runs: list[list[int]], g_dt: float, sigma_h: float, dt: float) -> list[list[int]]:
    """Split runs where the height's (T,) frame-to-frame velocity does not fall by g·dt (``g_dt``) but rises by more
    than half of it beyond the noise: a bounce happened between those frames."""
    out = []
    tol = 4.0 * np.sqrt(2.0) * sigma_h / dt
    for run in runs:
        cur = [run[0]]
        for k in range(1, len(run)):
            if k >= 2:
                v_prev = (h[run[k - 1]] - h[run[k - 2]]) / dt
                v_now = (h[run[k]] - h[run[k - 1]]) / dt
                if v_now - v_prev > -g_dt + tol + 0.5 * g_dt:
                    out.append(cur)
                    cur = []
            cur.append(run[k])
        out.append(cur)
    return [s for s in out if s]


@dataclass
class BallisticSearch:
    """Settings of :func:`find_ballistic`.

    Attributes:
        min_frames: fewest frames a free-flight window needs to count (3 determines a parabola exactly).
        tolerance: a frame belongs to a parabola when it lies within max(5√3 σ, ``tolerance`` × the object's size)
            of it: the tracked centre is not exactly the centre of mass, and drifts from it as the object turns.
        min_travel: a candidate window's object must move by at least this share of its size (a resting object fits
            a parabola too, with a ≈ 0).
        significance: a candidate window's |a| must exceed this many standard deviations.
        max_angle_deg: a candidate's acceleration must lie within this angle of the rough down direction (when one
            is given: the cameras are assumed upright, give or take this much).
        iterations: rounds of segment finding and joint fitting.
        seed_frames, seed_ratio: the seed window is the longest of the windows of at least ``seed_frames`` frames
            whose |a| reaches ``seed_ratio`` × the largest |a| among them (:func:`seed_window`).
        first_flight: measure on the first flight alone (before the first contact), when one parabola explains
            at least ``first_flight_frames`` of its frames: later flights follow a bounce, after which a soft
            object wobbles and spins, and its tracked centre strays further from its centre of mass.
    """

    min_frames: int = 3
    tolerance: float = 0.01
    min_travel: float = 0.05
    significance: float = 5.0
    max_angle_deg: float = 60.0
    iterations: int = 3
    seed_frames: int = 8
    seed_ratio: float = 0.75
    first_flight: bool = True
    first_flight_frames: int = 6


def noise_and_tolerance(x: np.ndarray, size: float, search: BallisticSearch) -> tuple[float, float]:
    """The track's (T, 3) noise σ (:func:`tracking_noise`) and the distance within which a frame belongs to a
    parabola."""
    sigma = tracking_noise(x)
    if not np.isfinite(sigma) or sigma <= 0:
        sigma = 1e-9 * max(1.0, float(np.nanmax(np.abs(x))))
    return sigma, max(5.0 * np.sqrt(3.0) * sigma, search.tolerance * size)


def candidate_windows(x: np.ndarray, dt: float, sigma: float, tol: float, size: float, search: BallisticSearch,
                      direction: np.ndarray | None = None, rough_down: np.ndarray | None = None) -> list[BallisticFit]:
    """The windows (:func:`_windows`) in which the object moves with a clearly non-zero acceleration that points
    the way gravity may (along ``direction``; within ``search.max_angle_deg`` of ``rough_down``), each fitted."""
    candidates: list[BallisticFit] = []
    for seg in _windows(x, dt, tol, max(search.min_frames, 3)):
        travel = float(np.linalg.norm(x[seg] - x[seg[0]], axis=1).max())
        if travel < search.min_travel * size:  # resting (or nearly): a ≈ 0 fits too
            continue
        fit = fit_segments(x, dt, [seg], direction, noise=sigma)
        mag = np.linalg.norm(fit.acceleration)
        if mag < search.significance * max(fit.magnitude_sigma(), 1e-300):
            continue
        if direction is not None and fit.acceleration @ direction <= 0:
            continue
        if rough_down is not None and fit.acceleration @ rough_down < mag * np.cos(np.radians(search.max_angle_deg)):
            continue
        candidates.append(fit)
    return candidates


def seed_window(candidates: list[BallisticFit], search: BallisticSearch) -> BallisticFit | None:
    """The candidate that seeds the search. Free fall is the largest acceleration an object keeps for many frames:
    contact, rolling and sliding keep a smaller one (friction stays below g), a bounce's contact a larger one for a
    few frames only. So among the windows of at least ``search.seed_frames`` frames, those whose |a| reaches
    ``search.seed_ratio`` × the largest; the longest of them (then the larger |a|). Without such windows, the
    largest |a| among the windows of 4+ frames (3-frame ones otherwise)."""
    if not candidates:
        return None
    mag = lambda c: float(np.linalg.norm(c.acceleration))  # noqa: E731
    long_ones = [c for c in candidates if len(c.frames) >= search.seed_frames]
    if long_ones:
        top = max(mag(c) for c in long_ones)
        pool = [c for c in long_ones if mag(c) >= search.seed_ratio * top]
        return max(pool, key=lambda c: (len(c.frames), mag(c)))
    short = [c for c in candidates if len(c.frames) >= 4] or candidates
    return max(short, key=mag)


def longest_window(x: np.ndarray, dt: float, frames: list[int], tol: float) -> list[int]:
    """The longest run of the consecutive ``frames`` that one parabola explains (the earliest of equal ones):
    a flight that begins in a hand starts at the release."""
    best: list[int] = []
    for seg in _windows(x[frames[0]:frames[-1] + 1], dt, tol, 3):
        if len(seg) > len(best):
            best = seg
    return [frames[0] + f for f in best]


def _trimmed(x: np.ndarray, dt: float, frames: list[int], tol: float, sigma: float,
             direction: np.ndarray | None) -> list[int]:
    """``frames`` less their worst-fitting frame, one at a time and refitting, until the rest lie within ``tol`` of
    their parabola (fewer than 3: what is left)."""
    kept = list(frames)
    while len(kept) >= 3:
        fit = fit_segments(x, dt, [kept], direction, noise=sigma)
        res = np.linalg.norm(np.stack([_predict(x, dt, kept, fit, f) for f in kept]) - x[kept], axis=1)
        worst = int(np.argmax(res))
        if res[worst] <= tol:
            break
        kept.pop(worst)
    return kept


def _grown(x: np.ndarray, dt: float, frames: list[int], tol: float, sigma: float,
           direction: np.ndarray | None) -> list[int]:
    """The longest run of ``frames`` one parabola explains (:func:`longest_window`), then every frame of ``frames``
    within ``tol`` of the parabola fitted so far, refitted until the set settles."""
    kept = longest_window(x, dt, frames, tol)
    for _ in range(len(frames)):
        if len(kept) < 3:
            break
        fit = fit_segments(x, dt, [kept], direction, noise=sigma)
        near = [f for f in frames if np.linalg.norm(_predict(x, dt, kept, fit, f) - x[f]) <= tol]
        if near == kept or len(near) < 3:
            break
        kept = near
    return kept


def flight_frames(x: np.ndarray, dt: float, frames: list[int], tol: float, sigma: float,
                  direction: np.ndarray | None = None) -> list[int]:
    """The most frames of one flight (consecutive ``frames``) that one parabola explains within ``tol``: the larger
    of two robust sets — all its frames less the worst-fitting ones (a few frames offset together, e.g. while a
    mask lost part of the object, stay in: they lie within ``tol`` of the whole flight's parabola, though they
    break a run grown frame by frame), and the longest run one parabola explains grown by the frames near its
    parabola (a flight that begins in a hand starts at the release however long it was held)."""
    trimmed = _trimmed(x, dt, frames, tol, sigma, direction)
    grown = _grown(x, dt, frames, tol, sigma, direction)
    return trimmed if len(trimmed) >= len(grown) else grown


def air_segments(x: np.ndarray, dt: float, acceleration: np.ndarray, lowest_along: Callable[[np.ndarray], np.ndarray],
                 sigma: float, tol: float) -> list[list[int]]:
    """The runs of frames (4+ each) in which the object is in the air, with gravity along ``acceleration``: its
    lowest point above the contact level (the 10th percentile over the frames), broken at bounces."""
    up = -acceleration / np.linalg.norm(acceleration)
    low = lowest_along(up)
    finite = low[np.isfinite(low)]
    if len(finite) == 0:
        return []
    contact = float(np.percentile(finite, 10))
    sigma_h = max(sigma, tol / (5.0 * np.sqrt(3.0)))
    runs = flight_segments(x, low, sigma_h, contact)
    return [s for s in split_bounces(x @ up, runs, np.linalg.norm(acceleration) * dt, sigma_h, dt) if len(s) >= 4]


def find_ballistic(x: np.ndarray, dt: float, lowest_along: Callable[[np.ndarray], np.ndarray], size: float,
                   search: BallisticSearch | None = None, direction: np.ndarray | None = None,
                   rough_down: np.ndarray | None = None) -> BallisticFit | None:
    """The free-flight fit of a track (T, 3) (module docstring), or None when no free flight shows.

    Args:
        size: the object's size (calibration units), for the tolerance.
        lowest_along: the object's lowest height (T,) along a unit up vector (3,), frame by frame.
        direction: a known gravity direction (3,), unit; then only |a| is fitted.
        rough_down: a rough down direction (3,), unit (the cameras' mean image-down axis): a candidate window's
            acceleration must lie within ``search.max_angle_deg`` of it. A bouncing object decelerates upwards over
            several frames, as steadily as a parabola — this keeps it from passing for free fall.
    """
    search = BallisticSearch() if search is None else search
    sigma, tol = noise_and_tolerance(x, size, search)
    best = seed_window(candidate_windows(x, dt, sigma, tol, size, search, direction, rough_down), search)
    if best is None:
        return None
    for _ in range(search.iterations):
        segs = air_segments(x, dt, best.acceleration, lowest_along, sigma, tol)
        if not segs:  # e.g. a throw starting at floor level: keep the seed
            break
        first = flight_frames(x, dt, segs[0], tol, sigma, direction) if search.first_flight else []
        only_first = len(first) >= search.first_flight_frames
        if only_first:
            segs = [first]
        fit = fit_segments(x, dt, segs, direction, noise=sigma)
        if not np.isfinite(fit.acceleration).all() or fit.acceleration @ best.acceleration <= 0:
            break
        # drop segments whose frames the joint fit does not explain, then refit
        good = [s for s in segs if np.linalg.norm(np.stack([_predict(x, dt, s, fit, f) for f in s]) - x[s],
                                                  axis=1).max() <= tol]
        if not good:
            break
        fit = fit_segments(x, dt, good, direction, noise=sigma)
        if not only_first and len(fit.frames) < len(best.frames) and fit.magnitude_sigma() > best.magnitude_sigma():
            break
        best = fit
    best.noise = max(best.noise, sigma)
    return best
