"""``vid2sim bench speed`` section ``joint``: one Stage II joint-optimisation iteration at the small preset.

The standard object of the physics section (a box, half-diagonal 0.5 m, 500 cubature points, 10 + 1 handles,
E = 1e5, ν = 0.3) carries 6 000 Gaussians on its surface (the small preset's cap) and 1 000 area-weighted
contact points on a floor; 4 cameras of 128² look at it (the small preset's observed views). One iteration =
a 4-frame window simulated with gradients (time-converged BDF2 substeps), rendered in the 4 views, the mean
squared image error against target images, and the backward pass through the renderer and the simulator's
adjoint to log10 E, ν and the initial velocity.

Figures: ``joint_iter_ms`` (the small preset: networks fixed, full resolution), ``joint_iter_ms_half_resolution``
(the first half of the small preset's iterations) and ``joint_iter_ms_with_networks`` (the paper's setting:
the skinning MLP optimised too, so its weights and gradients at the Gaussians are recomputed every
iteration), and ``joint_iter_ms_with_networks_neural_jacobian`` (the same with the paper's Neural Jacobian
for dF/dz instead of the exact closed form). Medians over repeats. ``joint_iter_ms_reference_kernels`` is
``joint_iter_ms`` with the simulator's per-term reference code (``SimConfig(fused_kernels=False)``) in the same
run, for a same-machine ratio.

``joint_gauss_newton_step_ms``: one step of the default method (``JointConfig.method`` "gauss_newton") on the same
object: the whole 10-frame clip's forward-difference Jacobian in the 9 physical parameters (log10 E, ν, the floor's
friction, the initial linear and angular velocity: 9 + 1 rollouts of the clip, each frame rendered in the 4 views at
half resolution,
the fit's ``coarse_scale``) and one trial step (a rollout and its loss), without gradients; ``joint_settings``
``gauss_newton_parameters`` says how many. A Gauss–Newton step does the work of many windows iterations: compare
whole fits (``bench suite``'s seconds), not the two per-iteration figures.

Operation counts (:mod:`vid2sim.apps.bench.op_count`; deterministic, unlike the timings): ``joint_iter_ops``, the
top-level aten operators one ``joint_iter_ms`` iteration dispatches on the device that runs it (on a GPU each is
a launch: the iteration is launch-bound there), ``joint_iter_aten_events`` all aten events (nested ones too),
and ``joint_iter_ops_render`` the share of the rendering alone (the window's frames rendered in the 4 views,
the image loss and its backward pass to the states; the torch rasteriser on a CPU, gsplat on a GPU).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch

from vid2sim.apps.bench.op_count import count_aten_ops
from vid2sim.apps.bench.physics_speed import (
    PhysicsBenchSettings,
    build_standard_simulator,
)
from vid2sim.apps.bench.timing import time_ms
from vid2sim.asset.motion import GaussianRig
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS, Floor, Gravity
from vid2sim.physics.neural_jacobian import NeuralJacobian
from vid2sim.physics.solver import Simulator
from vid2sim.reconstruct.clip import Observations, image_loss, render_states
from vid2sim.reconstruct.config import JointConfig
from vid2sim.reconstruct.gauss_newton import linearise, trajectory_loss
from vid2sim.reconstruct.stages.joint import ClipResiduals, physical_parameters, simulator_prior
from vid2sim.splats.cameras import camera_ring
from vid2sim.splats.gaussians import Gaussians

#: the small preset's cap of Gaussians and its observed views' resolution; ``quick``'s smaller ones
GAUSSIANS, RESOLUTION = 6000, 128
QUICK_GAUSSIANS, QUICK_RESOLUTION = 1500, 64
#: the bench drop's initial velocity about the box's centre: linear (m/s) and angular (rad/s)
START_LINEAR_VELOCITY = (0.1, 0.0, -1.0)
START_ANGULAR_VELOCITY = (0.0, 1.0, 0.0)


def _box_surface(n: int, size: torch.Tensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 3) points uniform on the surface of a centred box of edge lengths ``size`` (3,), and their areas."""
    g = torch.Generator().manual_seed(seed)
    a, b, c = (float(v) for v in size)
    faces = torch.tensor([b * c, b * c, a * c, a * c, a * b, a * b], dtype=torch.float64)
    face = torch.multinomial(faces / faces.sum(), n, replacement=True, generator=g)
    p = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * size
    axis, sign = face // 2, (face % 2) * 2 - 1
    p[torch.arange(n), axis] = sign.to(p.dtype) * size[axis] / 2
    return p.float(), torch.full((n,), float(faces.sum()) / n)


@dataclass
class JointBench:
    """The bench's joint setting, ready to run iterations (:func:`build_joint_bench`).

    Attributes:
        sim: the simulator (floor with 1 000 area-weighted contact points, E guessed at 10^5.3).
        rig: the 6 000 Gaussians on the box's surface (``quick``: 1 500), moved by ``sim``.
        full: the target images (V = 4, T = 10, 128, 128, 3; ``quick``: 64²) and cameras; ``half`` the same at
            half the resolution.
        fixed: the rig's basis at the Gaussians with the networks fixed (``rig.basis()``).
        window_start: the state the 4-frame window starts from (frame 5).
    """

    sim: Any
    rig: Any
    full: Any
    half: Any
    fixed: Any
    window_start: Any
    _window: Any = None

    def iteration(self, obs: Any | None = None, basis: Any = "fixed") -> None:
        """One joint iteration (forward + backward) on ``obs`` (default ``full``) with the rig's ``basis``
        (default the fixed one; None: recomputed from the networks, differentiably)."""

        sim, obs = self.sim, self.full if obs is None else obs
        basis = self.fixed if isinstance(basis, str) else basis
        sim.log10_E.requires_grad_(True)
        sim.nu.requires_grad_(True)
        out = sim.rollout(self.window_start, 4)
        renders = render_states(self.rig, out, obs, range(4), basis)
        loss = image_loss(renders, obs.images[:, 6:10].transpose(0, 1))
        loss.backward()
        sim.log10_E.grad = sim.nu.grad = None
        sim.log10_E.requires_grad_(False)
        sim.nu.requires_grad_(False)

    def render_iteration(self, obs: Any | None = None) -> None:
        """The rendering part of :meth:`iteration` alone: the window's states (simulated once, without gradients)
        rendered, the image loss and its backward pass to the states."""

        obs = self.full if obs is None else obs
        if self._window is None:
            with torch.no_grad():
                self._window = self.sim.rollout(self.window_start, 4)
        states = [type(s)(s.z.detach().requires_grad_(True), s.zdot) for s in self._window]
        renders = render_states(self.rig, states, obs, range(4), self.fixed)
        image_loss(renders, obs.images[:, 6:10].transpose(0, 1)).backward()

    def gauss_newton_step(self) -> int:
        """One Gauss–Newton step (module docstring) from the bench's wrong guess; returns the parameter count."""
        sim, cfg = self.sim, JointConfig()
        prior = simulator_prior(sim)
        parameters = physical_parameters(sim, cfg, prior, float(sim.config.dt))
        clip = ClipResiduals(sim, self.rig, self.half, [0.0, 0.0, 0.0], cfg.frame_decay, [q.name for q in parameters])
        velocity = dict(zip([f"{kind}_velocity_{a}" for kind in ("linear", "angular") for a in "xyz"],
                            [*START_LINEAR_VELOCITY, *START_ANGULAR_VELOCITY]))
        theta = [prior[q.name] if q.name in prior else velocity[q.name] for q in parameters]
        try:
            lin = linearise(clip, parameters, theta)
            trial = list(theta)
            trial[0] += 0.1
            trajectory_loss(clip, clip.simulate(trial, lin.substeps))  # the trial step's rollout and loss
        finally:
            clip.apply(theta)
        return len(parameters)

    def with_networks(self) -> None:
        """One iteration with the skinning MLP (and the Neural Jacobian, when in use) optimised too."""
        sim = self.sim
        nets = list(sim.field.parameters()) + (list(sim.jacobian.parameters()) if sim.use_neural_jacobian else [])
        for p in nets:
            p.requires_grad_(True)
        self.iteration(self.full, None)
        for p in nets:
            p.requires_grad_(False)
            p.grad = None


def build_joint_bench(device: torch.device, settings: PhysicsBenchSettings | None = None,
                      quick: bool = False) -> JointBench:
    """The joint setting of the module docstring (``quick``: a 20-iteration skinning pretraining, 1 500 Gaussians
    and 64² images, a check that the figures come out at a quarter of the cost)."""

    s = settings or PhysicsBenchSettings()
    n, resolution = (QUICK_GAUSSIANS, QUICK_RESOLUTION) if quick else (GAUSSIANS, RESOLUTION)
    if quick:
        s = replace(s, skinning_pretrain_iters=20)
    base, pts = build_standard_simulator(s, device)
    size = pts.max(0).values - pts.min(0).values
    contact, areas = _box_surface(1000, size.double().cpu(), s.seed)
    sim = Simulator(base.field, base.X, base.vol, base.material,
                    [Gravity(), Floor(height=s.floor_height, stiffness=AREA_CONTACT_STIFFNESS)], base.config,
                    length_scale=1.0, contact_points=contact.to(pts), contact_weights=areas.to(pts))
    centres, _ = _box_surface(n, size.double().cpu(), s.seed + 1)
    g = torch.Generator().manual_seed(s.seed)
    gaussians = Gaussians.from_values(centres.to(pts), torch.full((n,), 0.012, device=device),
                                      (0.2 + 0.6 * torch.rand(n, 3, generator=g)).to(pts),
                                      torch.full((n,), 0.9, device=device))
    cams = camera_ring(4, 2.4, 20.0, resolution, resolution, fov_x_deg=40.0, target=(0.0, 0.0, -0.4))
    rig = GaussianRig(sim, gaussians)
    start = sim.rigid_velocity_state(list(START_LINEAR_VELOCITY), list(START_ANGULAR_VELOCITY), [0.0, 0.0, 0.0])
    with torch.no_grad():
        states = [start] + sim.rollout(start, 9)
        target = render_states(rig, states, Observations(torch.zeros(4, 10, resolution, resolution, 3), cams),
                               range(4)).transpose(0, 1)  # (V, T, H, W, 3)
    full = Observations(target, cams)
    with torch.no_grad():
        sim.log10_E.fill_(5.3)  # a wrong guess: the gradients are not zero
        fixed = rig.basis()
    for p in sim.field.parameters():  # fixed networks: no gradients to the skinning MLP
        p.requires_grad_(False)
    return JointBench(sim, rig, full, full.at_scale(0.5), fixed, states[5])


def run(device: torch.device, quick: bool = False, settings: PhysicsBenchSettings | None = None) -> dict[str, Any]:
    """The figures of the module docstring (``quick``: one timed run of each and no warm-up after the first, a
    check that the figures come out rather than a measurement)."""

    s = settings or PhysicsBenchSettings()
    repeats, warmup = (1, 0) if quick else (5, 1)
    bench = build_joint_bench(device, s, quick)
    sim = bench.sim
    # the closed-form dF/dz (the default) first: the Neural Jacobian below stays switched on in ``sim``
    fixed_full = time_ms(lambda: bench.iteration(bench.full), device, repeats)
    ops = count_aten_ops(lambda: bench.iteration(bench.full))
    bench.render_iteration()
    render_ops = count_aten_ops(bench.render_iteration)
    default = sim.config
    sim.config = replace(default, fused_kernels=False)
    reference = time_ms(lambda: bench.iteration(bench.full), device, repeats, warmup)
    sim.config = default
    fixed_half = time_ms(lambda: bench.iteration(bench.half), device, repeats, warmup)
    closed_form = time_ms(bench.with_networks, device, repeats, warmup)
    # the paper's Neural Jacobian instead of the exact closed-form dF/dz (untrained: the cost is the same)
    sim.jacobian = NeuralJacobian(num_handles_total=sim.field.num_handles_total, seed=s.seed).to(bench.fixed[0])
    sim.use_neural_jacobian = True
    neural = time_ms(bench.with_networks, device, repeats, warmup)
    sim.use_neural_jacobian = False
    parameters: list[int] = []
    gauss_newton = time_ms(lambda: parameters.append(bench.gauss_newton_step()), device, repeats, warmup)
    gauss_newton_parameters = parameters[0]

    return {
        "joint_iter_ms": fixed_full,
        "joint_iter_ms_reference_kernels": reference,
        "joint_iter_ops": ops.top_level,
        "joint_iter_aten_events": ops.total,
        "joint_iter_ops_render": render_ops.top_level,
        "joint_iter_ms_half_resolution": fixed_half,
        "joint_iter_ms_with_networks": closed_form,
        "joint_iter_ms_with_networks_neural_jacobian": neural,
        "joint_gauss_newton_step_ms": gauss_newton,
        "joint_settings": {"gaussians": bench.rig.gaussians.num, "views": 4,
                           "resolution": int(bench.full.images.shape[2]), "window": 4, "contact_points": 1000,
                           "substeps": sim.substeps(), "gauss_newton_parameters": gauss_newton_parameters,
                           "gauss_newton_resolution": int(bench.half.images.shape[2])},
    }
