"""The paper's joint method (``JointConfig.method`` "windows"): Adam on random windows of the observed clip.

Adam on (log10 E, ν, skinning MLP, Jacobian net) with learning rates (5e-3, 1e-3, 5e-7, 5e-7) and the initial
velocity, windows of Δs = 4 frames starting at a random frame s ∈ [s′, T − Δs], loss = mean squared image error over
the views (docs/architecture.md, "The paper's numbers"). Beyond the paper: a window starts from the state at frame s
of the latest whole rollout (no gradients before s), refreshed every ``refresh_every`` iterations, and windows at
s = 0 carry gradients to the initial velocity; views subsampled per iteration (``views_per_iteration``) and a
coarse-to-fine resolution schedule; every ``validate_every`` iterations the whole observed clip is validated and the
best state kept. :func:`vid2sim.reconstruct.stages.joint.joint_optimisation` runs it after the coarse search.
"""

from __future__ import annotations

import copy
import math
import time
from typing import TYPE_CHECKING, Any, Callable

import torch
from torch import Tensor

from vid2sim.asset.motion import GaussianRig
from vid2sim.physics.solver import SimState, Simulator
from vid2sim.reconstruct.clip import Observations, clip_loss, detached_state, image_loss, render_states
from vid2sim.reconstruct.config import JointConfig
from vid2sim.reconstruct.gauss_newton import FitResult, Parameter, linearise

if TYPE_CHECKING:
    from vid2sim.reconstruct.stages.joint import ClipResiduals


def first_moving_frame(images: Tensor, threshold: float = 1e-3) -> int:
    """s′: the first frame (≥ 1) whose images differ from frame 0 by a mean squared error above ``threshold``
    (the paper's start of the window range); 1 when every frame differs."""
    T = images.shape[1]
    for t in range(1, T):
        if float(((images[:, t] - images[:, 0]) ** 2).mean()) > threshold:
            return t
    return 1


def windowed_adam(sim: Simulator, rig: GaussianRig, observations: Observations, coarse_obs: Observations,
                  start: list[float], centre: list[float], cfg: JointConfig, clip: ClipResiduals,
                  parameters: list[Parameter], progress: bool,
                  on_iteration: Callable[[dict[str, Any]], None] | None) -> FitResult:
    """The paper's Adam on random windows of ``cfg.window`` frames (module docstring), from the coarse search's
    start; the best state by the whole-clip validation is kept and linearised for the uncertainty."""
    from tqdm.auto import tqdm

    V, T = observations.images.shape[:2]
    gen = torch.Generator().manual_seed(cfg.seed)
    fit = _AdamFit(sim, rig, observations, cfg, start, centre)
    groups = _adam_groups(sim, cfg, [fit.v_lin, fit.v_ang])
    toggled, was = _train_only(sim, [p for g in groups for p in g["params"]])
    opt = torch.optim.Adam(groups)
    fixed_basis = _fixed_basis(sim, rig, cfg)
    best_loss, states = fit.validate()
    start_loss, best = best_loss, fit.snapshot()
    log: list[dict[str, Any]] = [{"iteration": 0, "validation_loss": best_loss, "log10_E": best["theta"][0],
                                  "nu": best["theta"][1]}]
    s_lo, s_hi = _window_starts(observations.images, cfg.window)
    n_views = V if cfg.views_per_iteration is None else min(V, cfg.views_per_iteration)
    bar = tqdm(range(1, cfg.iterations + 1), desc="joint optimisation", disable=not progress)
    try:
        for it in bar:
            t0 = time.perf_counter()
            scale = cfg.coarse_scale if it <= cfg.coarse_fraction * cfg.iterations else 1.0
            obs = coarse_obs if scale != 1.0 else observations
            s = int(torch.randint(s_lo, s_hi + 1, (1,), generator=gen))
            views = sorted(torch.randperm(V, generator=gen)[:n_views].tolist())
            loss = fit.window_step(opt, obs, s, views, states, fixed_basis)
            entry = {"iteration": it, "loss": loss, "log10_E": float(sim.log10_E.detach()),
                     "nu": float(sim.nu.detach()), "damping_ratio": float(sim.damping_ratio.detach()),
                     "window_start": s, "scale": scale,
                     "ms": 1000 * (time.perf_counter() - t0)}
            if it % cfg.validate_every == 0 or it == cfg.iterations:
                value, states = fit.validate()
                entry["validation_loss"] = value
                if value < best_loss:
                    best_loss, best = value, fit.snapshot()
            elif it % cfg.refresh_every == 0:
                states = fit.clip_states(T)
            log.append(entry)
            if on_iteration is not None:
                on_iteration(entry)
            bar.set_postfix(loss=f"{entry['loss']:.2e}", log10_E=f"{entry['log10_E']:.3f}", nu=f"{entry['nu']:.3f}")
    finally:
        for p, flag in zip(toggled, was):
            p.requires_grad_(flag)
    kept = fit.keep(best, parameters)
    with torch.no_grad():
        clip.basis = rig.basis()  # the kept networks' quantities at the Gaussians
    return FitResult(kept, linearise(clip, parameters, kept), math.nan, best_loss, start_loss, log,
                     f"{cfg.iterations} iterations")


class _AdamFit:
    """What the windowed Adam optimises besides the simulator's own parameters: the initial velocity v (3,) and
    ω (3,) about ``centre``, seen as θ = [log10 E, ν, (damping ratio,) v, ω] and snapshots of the networks."""

    def __init__(self, sim: Simulator, rig: GaussianRig, observations: Observations, cfg: JointConfig,
                 start: list[float], centre: list[float]) -> None:
        dtype, device = sim.X.dtype, sim.X.device
        self.sim, self.rig, self.observations, self.cfg, self.centre = sim, rig, observations, cfg, centre
        self.v_lin = torch.tensor(start[-6:-3], dtype=dtype, device=device).requires_grad_(True)
        self.v_ang = torch.tensor(start[-3:], dtype=dtype, device=device).requires_grad_(True)

    def initial_state(self) -> SimState:
        """The state at t = 0: the rest shape moving rigidly with (v, ω) about ``centre`` (with their graph)."""
        return self.sim.rigid_velocity_state(self.v_lin, self.v_ang, self.centre)

    def theta(self) -> list[float]:
        """θ = [log10 E, ν, (damping ratio,) v (3), ω (3)] now, as numbers."""
        sim = self.sim
        return [float(sim.log10_E.detach()), float(sim.nu.detach())] \
            + ([float(sim.damping_ratio.detach())] if self.cfg.fit_damping else []) \
            + [float(x) for x in self.v_lin.detach()] + [float(x) for x in self.v_ang.detach()]

    def snapshot(self) -> dict:
        """θ and copies of the networks' state dicts."""
        sim = self.sim
        return {"theta": self.theta(), "field": copy.deepcopy(sim.field.state_dict()),
                "jacobian": copy.deepcopy(sim.jacobian.state_dict()) if sim.jacobian is not None else None}

    def validate(self) -> tuple[float, list[SimState]]:
        """The whole clip's loss in every observed view at full resolution, and its T states."""
        start = detached_state(self.initial_state())
        return clip_loss(self.sim, self.rig, start, self.observations, self.cfg.frame_decay)

    def clip_states(self, T: int) -> list[SimState]:
        """The T states of the whole clip from the current θ, without gradients."""
        with torch.no_grad():
            s0 = detached_state(self.initial_state())
            return [s0] + self.sim.rollout(s0, T - 1)

    def window_step(self, opt: torch.optim.Optimizer, obs: Observations, s: int, views: list[int],
                    states: list[SimState], fixed_basis: Any) -> float:
        """One Adam step on the window of ``cfg.window`` frames after frame ``s`` (started from ``states[s]``, or
        from the initial velocity when s = 0) in ``views``; ν and the damping ratio are clamped after it. Returns
        the window's image loss."""
        sim, cfg = self.sim, self.cfg
        start_state = self.initial_state() if s == 0 else detached_state(states[s])
        opt.zero_grad(set_to_none=True)
        window_states = sim.rollout(start_state, cfg.window)
        renders = render_states(self.rig, window_states, obs, views, fixed_basis)
        target = obs.images[views][:, s + 1: s + 1 + cfg.window].transpose(0, 1).to(renders)
        loss = image_loss(renders, target)
        loss.backward()
        opt.step()
        with torch.no_grad():
            sim.nu.clamp_(*cfg.nu_bounds)
            sim.damping_ratio.clamp_(0.0, 1.0)
        return float(loss.detach())

    def keep(self, best: dict, parameters: list[Parameter]) -> list[float]:
        """Load the networks of the ``best`` snapshot; returns its θ clamped to the ``parameters``' bounds."""
        sim = self.sim
        with torch.no_grad():
            sim.field.load_state_dict(best["field"])
            if best["jacobian"] is not None:
                sim.jacobian.load_state_dict(best["jacobian"])
        return [min(max(x, q.lower), q.upper) for x, q in zip(best["theta"], parameters)]


def _adam_groups(sim: Simulator, cfg: JointConfig, velocity: list[Tensor]) -> list[dict[str, Any]]:
    """Adam's parameter groups with their learning rates: log10 E, ν, the initial ``velocity`` (v, ω), and the
    skinning field, the Neural Jacobian and the damping ratio when ``cfg`` fits them."""
    groups = [{"params": [sim.log10_E], "lr": cfg.lr_log10_E}, {"params": [sim.nu], "lr": cfg.lr_nu},
              {"params": velocity, "lr": cfg.lr_velocity}]
    if cfg.lr_skinning > 0:
        groups.append({"params": [p for p in sim.field.parameters()], "lr": cfg.lr_skinning})
    if sim.use_neural_jacobian and cfg.lr_jacobian > 0:
        groups.append({"params": list(sim.jacobian.parameters()), "lr": cfg.lr_jacobian})
    if cfg.fit_damping:
        groups.append({"params": [sim.damping_ratio], "lr": cfg.lr_damping})
    return groups


def _train_only(sim: Simulator, trainable: list[Tensor]) -> tuple[list[Tensor], list[bool]]:
    """Make ``trainable`` require gradients and freeze the networks' other parameters for the loop: otherwise every
    rollout's skinning basis would carry a graph and each step's adjoint would differentiate it for nothing.
    Returns the parameters toggled and their former ``requires_grad``, to restore."""
    net_params = [p for p in sim.field.parameters()]
    chosen = {id(p) for p in trainable}
    frozen = [p for p in net_params + (list(sim.jacobian.parameters()) if sim.jacobian is not None else [])
              if id(p) not in chosen]
    toggled = trainable + frozen
    was = [p.requires_grad for p in toggled]
    for p in trainable:
        p.requires_grad_(True)
    for p in frozen:
        p.requires_grad_(False)
    return toggled, was


def _fixed_basis(sim: Simulator, rig: GaussianRig, cfg: JointConfig) -> Any:
    """The networks' quantities at the Gaussians, computed once when no network is optimised (else None)."""
    networks_trained = cfg.lr_skinning > 0 or (sim.use_neural_jacobian and cfg.lr_jacobian > 0)
    if networks_trained:
        return None
    with torch.no_grad():
        return rig.basis()


def _window_starts(images: Tensor, window: int) -> tuple[int, int]:
    """The range [s_lo, s_hi] of window starts for the observed ``images`` (V, T, H, W, 3): s ∈ [s′ − 1, T − 1 − Δs]
    compares frames s + 1 … s + Δs (s′ the first moving frame); s = 0 reaches the initial velocity."""
    T = images.shape[1]
    s_hi = T - 1 - window
    s_lo = min(first_moving_frame(images) - 1, s_hi)
    return s_lo, s_hi
