"""An asset in motion: its Gaussians carried by its simulated (or a given) motion, and rendered.

:class:`GaussianRig` moves an asset's frame-0 Gaussians with a simulator state (LBS of the centres, the
deformation gradient F on the covariances); the functions below roll out an asset's own captured drop and
render it, which is what evaluation, reports, the demo and new simulations all need.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.metrics import carry_by_tets
from vid2sim.physics.reduced import lbs_rows
from vid2sim.physics.skinning import deform, deformation_gradient, gradient_basis
from vid2sim.physics.solver import Simulator
from vid2sim.splats.deform import deform_covariances, deform_gaussians
from vid2sim.splats.gaussians import Gaussians, quat_to_rotmat
from vid2sim.splats.render import render_gaussians


class GaussianRig:
    """Moves the frame-0 Gaussians with the simulator's state.

    Args:
        sim: the simulator (its field, and Neural Jacobian when ``sim.use_neural_jacobian``).
        gaussians: the Gaussians fitted to frame 0 (world frame = the rest configuration).
        shading: a :class:`~vid2sim.splats.shading.Shading` for the Gaussians (their colours are then albedos,
            lit per frame by its world-fixed light), or None (colours as stored).
    """

    def __init__(self, sim: Simulator, gaussians: Gaussians, shading: Any | None = None) -> None:
        self.sim = sim
        self.gaussians = gaussians
        self.shading = shading
        self.X = gaussians.means.detach()  # deformed in the Gaussians' dtype (the simulator's state is cast)

    def basis(self) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(w (N, H), gradient basis G (N, 3, 4H) or None, Neural Jacobian dF/dz (N, 9, 12H) or None) at the
        Gaussian centres, differentiable w.r.t. the networks."""

        if self.sim.use_neural_jacobian:
            return self.sim.field(self.X), None, self.sim.jacobian(self.X)
        w, dw = self.sim.field.weights_and_gradients(self.X)
        return w, gradient_basis(self.X, w, dw), None

    def deformed(self, z: Tensor, basis: tuple[Tensor, Tensor | None, Tensor | None]):
        """:class:`~vid2sim.splats.deform.DeformedGaussians` for the state z: (12H,)."""

        w, G, J = basis
        x = deform(self.X, w, z)
        if J is None:
            F = deformation_gradient(G, z)
        else:
            F = torch.eye(3, dtype=J.dtype, device=J.device) + (J @ z.to(J.dtype)).reshape(-1, 3, 3)
        g = self.gaussians
        return deform_gaussians(g, x.to(g.means.dtype), F.to(g.means.dtype), self.shading)

    def deformed_frames(self, Z: Tensor, basis: tuple[Tensor, Tensor | None, Tensor | None]) -> tuple[Tensor, Tensor]:
        """(means (T, N, 3), covariances F Σ Fᵀ (T, N, 3, 3)) of the Gaussians for T states Z: (T, 12H) in one batch
        (what :meth:`deformed` gives frame by frame; the colours are the Gaussians' own, so no shading)."""
        w, G, J = basis
        Z = Z.to(self.X.dtype)
        T, H = Z.shape[0], w.shape[1]
        Y = Z.view(T, H, 3, 4).transpose(1, 2).reshape(T, 3, 4 * H)  # Y[t, a, 4j + k] = Z_j[a, k]
        x = self.X + lbs_rows(self.X, w) @ Y.transpose(1, 2)
        if J is None:
            F = torch.einsum("tal,pcl->tpac", Y, G)
        else:
            F = (J @ Z.T).permute(2, 0, 1).reshape(T, -1, 3, 3)
        F = F + torch.eye(3, dtype=Z.dtype, device=Z.device)
        g = self.gaussians
        rs = quat_to_rotmat(g.quats) * g.scales[:, None, :]
        return x.to(g.means.dtype), deform_covariances(rs, F.to(g.means.dtype))


def simulate_gaussians(asset: Any, num_frames: int, progress: bool = True) -> list[Any]:
    """The asset's captured drop: its Gaussians deformed by the simulator, one set per frame.

    Args:
        asset: a loaded :class:`~vid2sim.asset.folder.Asset`.
        num_frames: T ≥ 1 frames (frame 0 is the initial state; frames are ``asset.dt`` apart).
        progress: tqdm bars for the rollout and the deformation.

    Returns:
        T :class:`~vid2sim.splats.deform.DeformedGaussians` (world frame, m), without gradients.
    """
    sim, states = simulate_states(asset, num_frames, progress=progress)
    return deform_states(asset, sim, states, progress=progress)


def deform_states(asset: Any, sim: Any, states: list[Any], progress: bool = True) -> list[Any]:
    """The asset's Gaussians deformed by each of the simulator ``sim``'s ``states`` (:func:`simulate_states`):
    one :class:`~vid2sim.splats.deform.DeformedGaussians` per state, without gradients."""


    with torch.no_grad():
        rig = GaussianRig(sim, asset.gaussians, asset.shading)
        basis = rig.basis()
        return [rig.deformed(s.z, basis) for s in tqdm(states, desc="deform", disable=not progress, leave=False)]


def simulate_states(asset: Any, num_frames: int, progress: bool = True,
                    continued: bool = True) -> tuple[Any, list[Any]]:
    """The asset's captured drop as simulator states: ``(simulator, T states)``, frame 0 the initial state.

    With ``continued`` and an asset that has a continuation (:attr:`~vid2sim.asset.folder.Asset.continuation`, the
    state fitted to its last observed frames), frames from its ``from_frame`` on are simulated from that state (the
    frames before it are the rollout from frame 0); otherwise every frame is the one rollout from frame 0.

    Raises:
        ValueError: ``num_frames`` < 1.
    """
    if num_frames < 1:
        raise ValueError(f"simulate_states: num_frames must be >= 1, got {num_frames}")
    sim = asset.simulator()
    start = asset.initial_state(sim)
    c = asset.continuation if continued else None
    with torch.no_grad():
        if c is None or num_frames <= c["from_frame"]:
            return sim, [start] + sim.rollout(start, num_frames - 1, progress=progress)
        first, anchor = int(c["from_frame"]), int(c["frame"])
        head = [start] + sim.rollout(start, first - 1, progress=progress)
        tail = sim.rollout(asset.continuation_state(sim), num_frames - 1 - anchor, progress=progress)
        return sim, head + tail[first - anchor - 1:]  # tail[k] is frame anchor + 1 + k


def simulated_centre_of_mass(sim: Any, states: list[Any]) -> torch.Tensor:
    """(T, 3) float64: the simulated body's centre of mass per state, Σ m_p x_p / Σ m_p over the simulator's
    mass points (its cubature points with their lumped masses, :meth:`~vid2sim.physics.Simulator.masses`)."""
    with torch.no_grad():
        m = sim.masses().double()
        return torch.stack([(m[:, None] * sim.positions(sim.X, s.z).double()).sum(0) / m.sum() for s in states])


def render_frames(frames: list[Any], cameras: list[Any], background: float = 1.0,
                  progress: bool = True) -> torch.Tensor:
    """Render deformed Gaussians (one set per frame, e.g. from :func:`simulate_gaussians`) in every camera.

    Returns:
        (V, T, H, W, 3) RGB in [0, 1] on the given ``background`` (1.0 = white, the scenes' background).
    """


    with torch.no_grad():
        renders = [render_gaussians(d, cameras, background=background).rgb
                   for d in tqdm(frames, desc="render", disable=not progress, leave=False)]
    return torch.stack(renders, dim=1).clamp(0, 1)


def true_motion_gaussians(asset: Any, tet_trajectory: dict[str, torch.Tensor]) -> list[Any]:
    """The asset's Gaussians carried by the ground truth's motion instead of the simulator's.

    Each Gaussian follows the frame-0 tet it lies in (or is least outside of) of the scene's ``tet_trajectory``
    extra (:func:`vid2sim.metrics.carry_by_tets`): its centre moves with the tet's affine map and its covariance
    is deformed by the tet's F. Scoring these images separates the appearance's share of the image error (what
    the Gaussians cannot show even on the true motion: lighting baked in at frame 0, surfaces no observed view
    saw) from the dynamics'.

    Returns:
        T :class:`~vid2sim.splats.deform.DeformedGaussians`, one per frame of the trajectory.
    """

    g = asset.gaussians
    vertices, tets = tet_trajectory["vertices"], tet_trajectory["tets"]
    used = vertices[:, : int(tets.max()) + 1]  # quadratic meshes list edge midpoints after the vertices
    x, F = carry_by_tets(g.means, used, tets)
    return [deform_gaussians(g, x[t].to(g.means.dtype), F[t].to(g.means.dtype), asset.shading) for t in range(len(x))]
