"""How well the video determines the fitted material: Laplace intervals and the information by frame.

At the fit θ̂ of :mod:`vid2sim.reconstruct.gauss_newton` the posterior Φ is approximated by a Gaussian
(a Laplace approximation) whose precision is Φ's Gauss–Newton Hessian,

    Λ = n JᵀJ / L̂ + J_cᵀJ_c + P,

the images' part scaled by the residual variance L̂/n (the loss per independent measurement left at the fit), J_c the
Jacobian of the track residuals when the fit has them (already divided by their standard deviation) and P the
prior's diagonal precision. The marginal standard deviation of a parameter is √(Λ⁻¹)_jj, and its interval at
level c is θ̂_j ± z σ_j, z the standard normal quantile of (1 + c)/2, clipped to the parameter's bounds.

A parameter is *identifiable from this video* when the images alone constrain it more tightly than the prior
does: its data-only standard deviation d (the same marginal of n JᵀJ / L̂ alone, the other parameters free) is below
the prior's σ. Otherwise its value is the prior's, moved a little, and the record says so instead of presenting
it as found.

**The model's own error.** The Laplace approximation measures how far the image noise moves the fit, as if the
reduced model could reproduce the video exactly. It cannot: against a continuum FEM drop a few-handle subspace is
too stiff at the contact, the geometry comes from four views, and the fit's E and ν carry that bias. On the 8-scene
quadratic-tet small suite the noise-only 68 % interval of log10 E held the truth on 2 of 8 scenes. A model error m
(``JointConfig.model_error_log10_E``, ``model_error_nu``: the RMS error of that suite's fits) is therefore added, in
the share w in which the images rather than the prior set the value:

    σ² = σ_L² + w m²,   w = 1 − σ_L² / σ_p²  (clipped to [0, 1]),

σ_L the Laplace marginal above and σ_p the prior's. A parameter the images determine (σ_L ≪ σ_p) gets
σ ≈ √(σ_L² + m²); one they do not (σ_L ≈ σ_p) keeps the prior's width, since its value is the prior's and the model's
bias cannot move it. Identifiability is judged on d alone (the loss's curvature), not on m.

The information by frame says which frames inform which parameter: the share of the diagonal of JᵀJ that each
frame's block contributes (the Fisher information about that parameter with the others held fixed).
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from vid2sim.reconstruct.gauss_newton import Linearisation, Parameter, prior_precision

NOT_IDENTIFIABLE = "not identifiable from this video"


def _marginal_sd(information: Tensor) -> Tensor:
    """(p,) √diag(information⁻¹), +inf where a direction carries no information (a pseudo-inverse on the
    eigenvectors above 1e-12 of the largest eigenvalue; a parameter with weight in the null space is unbounded)."""
    values, vectors = torch.linalg.eigh(0.5 * (information + information.T))
    top = float(values.abs().max()) if values.numel() else 0.0
    keep = values > 1e-12 * max(top, 1e-300)
    variance = (vectors[:, keep] ** 2 / values[keep]).sum(1)
    null = (vectors[:, ~keep] ** 2).sum(1) > 1e-6
    sd = variance.sqrt()
    sd[null] = math.inf
    return sd


def _model_variance(noise_sd: float, prior_sd: float, model_sd: float) -> float:
    """The variance the model error ``model_sd`` adds to a marginal of Laplace standard deviation ``noise_sd``
    under a prior of ``prior_sd`` (module docstring): model_sd² times the images' share 1 − noise_sd²/prior_sd²."""
    share = min(1.0, max(0.0, 1.0 - (noise_sd / prior_sd) ** 2)) if math.isfinite(noise_sd) else 0.0
    return model_sd ** 2 * share


def laplace_intervals(lin: Linearisation, parameters: Sequence[Parameter], n: float,
                      level: float = 0.68, model_error: Mapping[str, float] | None = None) -> dict[str, Any]:
    """The Laplace approximation at ``lin.theta`` (module docstring) for every parameter with a prior.

    Args:
        lin: the Gauss–Newton blocks at the fit.
        parameters: the fit's parameters (those without a prior, the velocities, are marginalised).
        n: the effective number of measurements (:func:`~vid2sim.reconstruct.gauss_newton.effective_images`).
        level: the intervals' probability.
        model_error: the model's own standard deviation per parameter name (module docstring; absent: 0, the
            image noise alone).
    Returns:
        ``{"method": "laplace", "level", "effective_measurements": n, "residual_loss": L̂, NAME: {"value",
        "sd" (the noise's and the model's), "noise_sd" (the Laplace marginal alone), "model_sd", "interval":
        [lo, hi], "data_sd" (None when the images carry no information about it), "prior_mean", "prior_sd",
        "identifiable": bool, "note"}}`` for each parameter with a prior.
    Raises:
        ValueError: a level outside (0, 1), or a negative or non-finite model error.
    """
    if not 0 < level < 1:
        raise ValueError(f"the interval level must lie in (0, 1), got {level}")
    model_error = dict(model_error or {})
    for name, value in model_error.items():
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"the model error of {name} must be a finite number >= 0, got {value}")
    loss = max(lin.loss, 1e-300)
    data = (n / loss) * lin.hessian + lin.track_hessian
    precision, _ = prior_precision(parameters)
    posterior_sd = _marginal_sd(data + torch.diag(precision))
    data_sd = _marginal_sd(data)
    z = NormalDist().inv_cdf(0.5 + level / 2)
    out: dict[str, Any] = {"method": "laplace", "level": level, "effective_measurements": n, "residual_loss": lin.loss}
    for j, q in enumerate(parameters):
        if q.prior_sd is None:
            continue
        value, noise_sd = lin.theta[j], float(posterior_sd[j])
        d_sd = float(data_sd[j])
        model_sd = float(model_error.get(q.name, 0.0))
        sd = math.sqrt(noise_sd ** 2 + _model_variance(noise_sd, q.prior_sd, model_sd))
        identifiable = d_sd < q.prior_sd
        interval = [max(q.lower, value - z * sd), min(q.upper, value + z * sd)]
        out[q.name] = {"value": value, "sd": sd, "noise_sd": noise_sd, "model_sd": model_sd, "interval": interval,
                       "data_sd": d_sd if math.isfinite(d_sd) else None, "prior_mean": q.prior_mean,
                       "prior_sd": q.prior_sd, "identifiable": identifiable,
                       "note": "found" if identifiable else NOT_IDENTIFIABLE}
    return out


def mark_unmoved(record: dict[str, Any], start: Mapping[str, float], kept_start: bool) -> None:
    """Record in a :func:`laplace_intervals` record which parameters the fit left exactly where it started
    (``moved`` false) and, when the whole fit kept its start (``kept_start``: no step lowered the validation loss),
    say so in the note of those the images constrain: the value is the start's — the prior's, or for log10 E the
    coarse search's grid value — and the interval is the curvature there, not around a minimum the fit found. (A
    parameter that stayed put while others moved, at a bound say, keeps its note.) ``start``: the fit's starting
    value per parameter name."""
    for name, entry in record.items():
        if not isinstance(entry, dict) or "value" not in entry or name not in start:
            continue
        s = float(start[name])
        entry["moved"] = abs(float(entry["value"]) - s) > 1e-12 * max(1.0, abs(s))
        if entry["moved"] or not kept_start or not str(entry.get("note", "")).startswith("found"):
            continue
        source = "the prior's" if s == entry.get("prior_mean") else "the coarse search's"
        entry["note"] = (f"left at {source} value: the images constrain it (data sd {entry.get('data_sd') or 0:.3g}) "
                         "but no step of the fit lowered the validation loss" + entry["note"][len("found"):])


def coarse_best(coarse: Sequence[Mapping[str, Any]]) -> Mapping[str, Any]:
    """The coarse search's row with the lowest loss (its friction and contact surface are the ones the fit keeps)."""
    return min(coarse, key=lambda r: r["loss"])


def _edge_and_end(coarse: Sequence[Mapping[str, float]], value: float) -> tuple[str, float] | None:
    """:func:`coarse_edge`'s answer and the log10 E of that end of the grid."""
    if not coarse:
        return None
    best = coarse_best(coarse)
    grid = sorted(r["log10_E"] for r in coarse if r.get("floor_friction") == best.get("floor_friction")
                  and r.get("contact_surface") == best.get("contact_surface"))
    if len(grid) < 2:
        return None
    half = 0.5 * min(b - a for a, b in zip(grid, grid[1:]))
    if best["log10_E"] == grid[0] and value <= grid[0] + half:
        return "lower", grid[0]
    if best["log10_E"] == grid[-1] and value >= grid[-1] - half:
        return "upper", grid[-1]
    return None


def coarse_edge(coarse: Sequence[Mapping[str, float]], value: float) -> str | None:
    """``"lower"`` or ``"upper"`` when the coarse search's best loss lies at that end of its log10 E grid (the grid of
    the best floor friction and contact surface, when it searched several) and the fit's ``value`` stayed within
    half a grid step of that end; None otherwise (no search, an interior minimum, or a fit that moved away from the
    edge).

    Args:
        coarse: the coarse search's records, ``{"log10_E", "loss"}`` (and ``"floor_friction"``, ``"contact_surface"``)
            each.
    """
    found = _edge_and_end(coarse, value)
    return None if found is None else found[0]


def mark_coarse_edge(record: dict[str, Any], coarse: Sequence[Mapping[str, float]]) -> None:
    """Record in a :func:`laplace_intervals` record whether log10 E was found at an end of the coarse search
    (:func:`coarse_edge`; ``log10_E["at_coarse_edge"]``, None when not) and say so in its note: the grid's lowest
    loss is at its end, so a material beyond the search may fit the video better, and the interval is the fit's
    local curvature only, not the loss's profile."""
    entry = record.get("log10_E")
    if not isinstance(entry, dict):
        return
    found = _edge_and_end(coarse, entry["value"])
    entry["at_coarse_edge"] = None if found is None else found[0]
    if found is not None:
        edge, end = found
        entry["note"] = (f"{entry['note']}; at the {edge} end of the coarse search (log10 E {end:g}), where its "
                         f"lowest loss is: a {'softer' if edge == 'lower' else 'stiffer'} material than the search "
                         "covers may fit the video better (widen --joint.coarse_log10_E to look)")


def information_by_frame(lin: Linearisation, parameters: Sequence[Parameter]) -> dict[str, list[float]]:
    """For each parameter, the share of its Fisher information (diag JᵀJ) each frame block gives: F numbers
    summing to 1 (all zero when the images carry none)."""
    diag = torch.diagonal(lin.frame_hessian, dim1=1, dim2=2)  # (F, p)
    total = diag.sum(0)
    out = {}
    for j, q in enumerate(parameters):
        t = float(total[j])
        out[q.name] = [float(x) / t if t > 0 else 0.0 for x in diag[:, j]]
    return out


def covers(record: dict[str, Any], name: str, truth: float) -> bool | None:
    """Whether the interval of ``name`` in a :func:`laplace_intervals` record holds ``truth`` (None when the record
    has no interval for it)."""
    entry = record.get(name) if isinstance(record, dict) else None
    if not isinstance(entry, dict) or not isinstance(entry.get("interval"), (list, tuple)):
        return None
    lo, hi = entry["interval"]
    return bool(lo <= truth <= hi)
