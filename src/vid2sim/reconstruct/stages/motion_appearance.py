"""The Gaussians refitted along the simulated motion (the reconstruction's last stage).

The Gaussians are fitted to frame 0 and refined on the ballistic frames, where the object moves rigidly. After
the first bounce the object turns, and the observed views see it in poses frame 0 never showed:

* surfaces no camera saw at frame 0 (the underside, for cameras above the floor) come into view with colours
  that were never supervised;
* the scene's light is fixed in the world while the Gaussians carry the shading of frame 0 with them;
* Gaussians that frame 0's views could not tell from the surface (floaters behind it) appear in front of it.

Measured on four small benchmark scenes with ``vid2sim evaluate --true-motion``: without this stage, even moved
by the ground truth's own motion the assets' Gaussians reach only 24.5 dB on the observed frames, so no
dynamics could do better than that. This stage fixes what it can. The finished asset is simulated once (no
gradient to the physics: material, velocity and networks stay as the joint optimisation left them), and the
Gaussians in the rest frame are fitted to every observed frame and view *through* that motion with 3DGS's
photometric loss and learning rates (:class:`~vid2sim.splats.fitting.FitConfig`): colours (SH) and opacities,
and by default (``geometry=True``) also their rest-frame centres, scales and rotations. A centre that moves is
carried by the skinning field at its new place, exactly as the simulator will carry it later
(:class:`SkinnedMotion`), so the refitted asset renders the motion it was fitted on.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Any, Sequence

import torch
from torch import Tensor

from vid2sim.physics.skinning import deform, deformation_gradient, gradient_basis
from vid2sim.reconstruct.runner import Context, State
from vid2sim.runtime.files import read_json, save_torch_atomic, write_json_atomic
from vid2sim.splats.deform import deform_gaussians
from vid2sim.splats.fitting import scene_extent
from vid2sim.splats.losses import photometric_loss
from vid2sim.splats.ply import load_ply, save_ply
from vid2sim.splats.render import render_gaussians
from vid2sim.splats.shading import Shading, outward_normals

PLY, SHADING, RECORD = "gaussians_motion.ply", "shading_motion.pt", "motion_appearance.json"

SHADING_LR = 0.01
"""Adam learning rate of the shading's normals (unit vectors)."""
LIGHT_LR = 0.05
"""Adam learning rate of the light's direction (a unit vector) and its ambient share's logit."""


@dataclass
class SkinnedMotion:
    """A simulated motion that can carry any Gaussians: frozen copies of the skinning field (and Neural
    Jacobian), and the reduced state of every frame.

    Attributes:
        field: the skinning field, world points (N, 3) → weights (N, H); its parameters do not take gradients.
        jacobian: the Neural Jacobian (N, 3) → (N, 9, 12H), or None for the closed-form dF/dz.
        states: (T, 12H) the reduced state z of frames 0 … T−1.
    """

    field: Any
    jacobian: Any | None
    states: Tensor

    @classmethod
    def of_simulator(cls, sim: Any, states: Sequence[Any]) -> "SkinnedMotion":
        """From a :class:`~vid2sim.physics.solver.Simulator` and its states (``.z``: (12H,)), one per frame."""
        field = copy.deepcopy(sim.field).requires_grad_(False)
        jac = copy.deepcopy(sim.jacobian).requires_grad_(False) if sim.use_neural_jacobian else None
        return cls(field, jac, torch.stack([s.z.detach() for s in states]))

    @classmethod
    def of_asset(cls, asset: Any, num_frames: int, device: torch.device | str = "cpu") -> "SkinnedMotion":
        """The asset's captured drop over ``num_frames`` ≥ 1 frames (frame 0: its initial state), on ``device``."""
        if num_frames < 1:
            raise ValueError(f"SkinnedMotion.of_asset: num_frames must be >= 1, got {num_frames}")
        sim = asset.simulator()
        with torch.no_grad():
            start = asset.initial_state(sim)
            states = [start] + sim.rollout(start, num_frames - 1, progress=False)
        return cls.of_simulator(sim, states).to(device)

    def to(self, device: torch.device | str) -> "SkinnedMotion":
        return SkinnedMotion(self.field.to(device), None if self.jacobian is None else self.jacobian.to(device),
                             self.states.to(device))

    @property
    def num_frames(self) -> int:
        return int(self.states.shape[0])

    def carry(self, gaussians: Any, t: int, shading: Any | None = None, near: "FieldSample | None" = None) -> Any:
        """The rest-frame ``gaussians`` (a :class:`~vid2sim.splats.gaussians.Gaussians`, N of them) at frame t:
        a :class:`~vid2sim.splats.deform.DeformedGaussians`, lit by ``shading`` (a
        :class:`~vid2sim.splats.shading.Shading`) when given.

        The centres are carried by the skinning weights at their current place, exactly as the simulator carries
        them — or, given ``near`` (the field sampled at nearby centres, :meth:`sample`), by its first-order
        expansion there (:meth:`place_near`). It is differentiable with respect to the Gaussians' parameters, with
        one simplification in the gradient only: a centre's move reaches its deformed centre through F = ∂x/∂X
        (exact), but not its covariance through the change of F along the move (a second-order effect that would
        cost a differentiation through the field's own gradient at every step).
        """

        if near is None:
            x, F = self.place(gaussians.means, t)
        else:
            x, F = self.place_near(near, gaussians.means, t)
        X = gaussians.means.to(x.dtype)
        if X.requires_grad:  # value x, gradient Fᵀ ∂L/∂x to the rest-frame centre
            x = x + (F @ (X - X.detach())[:, :, None])[..., 0]
        dt = gaussians.means.dtype
        return deform_gaussians(gaussians, x.to(dt), F.to(dt), shading)

    def place(self, X: Tensor, t: int) -> tuple[Tensor, Tensor]:
        """The rest-frame points ``X`` (N, 3) at frame t: their places x (N, 3) and deformation gradients
        F = ∂x/∂X (N, 3, 3), in the states' dtype, without gradients (:meth:`carry` adds the centres'): the field
        sampled at ``X`` itself, where :meth:`place_near` is exact."""
        self._check_frame(t)
        return self.place_near(self.sample(X), X, t)

    def sample(self, X: Tensor) -> "FieldSample":
        """The skinning field (and Neural Jacobian) evaluated once at the rest-frame points ``X`` (N, 3), for
        :meth:`place_near` at any frame while the points stay near."""
        X = X.detach().to(self.states.dtype)
        with torch.no_grad():
            w, dw = self.field.weights_and_gradients(X)
            return FieldSample(X, w, dw, None if self.jacobian is None else self.jacobian(X))

    def place_near(self, sample: "FieldSample", X: Tensor, t: int) -> tuple[Tensor, Tensor]:
        """:meth:`place` from a :class:`FieldSample` taken at nearby points instead of the field: the weights
        expanded to first order, ``w(X) ≈ w(X_s) + ∇w(X_s)·(X − X_s)``, their gradients (and the Neural
        Jacobian) held at X_s. Exact at X = X_s; off by O(|X − X_s|²) in x and O(|X − X_s|) in F, where the motion
        is not rigid only (the weights' last column is constant, so a rigid motion is carried exactly anywhere).

        Args:
            sample: the field at N points X_s; X: (N, 3) the points now; t: the frame.
        Returns:
            x (N, 3), F (N, 3, 3) in the states' dtype, without gradients.
        """
        self._check_frame(t)
        z = self.states[t]
        X = X.detach().to(z.dtype)
        if X.shape != sample.X.shape:
            raise ValueError(f"SkinnedMotion.place_near: {tuple(X.shape)} points for a sample of "
                             f"{tuple(sample.X.shape)}")
        with torch.no_grad():
            w = sample.w + (sample.dw @ (X - sample.X)[:, :, None])[..., 0]
            if sample.jacobian is None:
                F = deformation_gradient(gradient_basis(X, w, sample.dw), z)
            else:
                F = torch.eye(3, dtype=z.dtype, device=z.device) + (sample.jacobian @ z).reshape(-1, 3, 3)
            return deform(X, w, z), F

    def _check_frame(self, t: int) -> None:
        if not 0 <= t < self.num_frames:
            raise ValueError(f"SkinnedMotion.carry: frame {t} asked, the motion has {self.num_frames} frames")


@dataclass
class FieldSample:
    """The skinning field evaluated at N rest-frame points (:meth:`SkinnedMotion.sample`).

    Attributes:
        X: (N, 3) the points; w: (N, H) their weights; dw: (N, H, 3) the weights' spatial gradients;
        jacobian: (N, 9, 12H) the Neural Jacobian there, or None for the closed-form dF/dz.
    """

    X: Tensor
    w: Tensor
    dw: Tensor
    jacobian: Tensor | None


REFRESH_FRACTION = 0.01
"""The Gaussians' refit samples the skinning field again once a centre has moved this share of the Gaussians'
bounding-box diagonal since the last sample (:meth:`SkinnedMotion.place_near` in between)."""


INITIAL_AMBIENT = 0.5
"""The ambient share the fitted light starts from."""


def initial_shading(gaussians: Any, interior: Tensor, volume: float, gravity: Sequence[float]) -> Shading:
    """The shading the last stage starts from: outward normals at the Gaussian centres from the object's interior
    samples (:func:`~vid2sim.splats.shading.outward_normals`, bandwidth twice the samples' mean spacing
    (volume / P)^(1/3)), a light straight above (against ``gravity``) and the ambient share
    :data:`INITIAL_AMBIENT`.

    Args:
        gaussians: the N rest-frame Gaussians; interior: (P, 3) samples of the object's interior (m);
        volume: the object's volume (m³); gravity: (3,) m/s² (its direction sets "above").
    """
    g = torch.as_tensor(list(gravity), dtype=gaussians.means.dtype, device=gaussians.means.device)
    if not float(g.norm()) > 0:
        raise ValueError(
            f"initial_shading: gravity must be non-zero to say where the light starts, got {list(gravity)}"
        )
    spacing = (float(volume) / max(1, interior.shape[0])) ** (1.0 / 3.0)
    normals = outward_normals(gaussians.means.detach(), interior.to(gaussians.means), 2.0 * spacing)
    return Shading.create(normals, -g / g.norm(), INITIAL_AMBIENT)


class _Carrier:
    """How :func:`refine_on_motion` carries its Gaussians to a frame. The skinning field is sampled at the centres
    and again only once one has moved :data:`REFRESH_FRACTION` of the Gaussians' diagonal (its evaluation was a
    third of a shaded step at 6 000 Gaussians, half of an unshaded one). Without geometry the centres stay: one
    sample, and each frame's places and deformation gradients computed once."""

    def __init__(self, motion: SkinnedMotion, means: Tensor, geometry: bool) -> None:
        self.motion, self.geometry, self.means = motion, geometry, means.detach()
        m = self.means
        self.refresh = REFRESH_FRACTION * float((m.amax(0) - m.amin(0)).norm()) if m.shape[0] else 0.0
        self.sample, self.samples = motion.sample(m), 1
        self.placed: dict[int, tuple[Tensor, Tensor]] = {}  # without geometry: frame → (x (N, 3), F (N, 3, 3))

    def __call__(self, gaussians: Any, t: int, shading: Any | None) -> Any:
        """The rest-frame ``gaussians`` (the refit's current ones) at frame t, lit by ``shading``."""
        if not self.geometry:
            if t not in self.placed:
                x, F = self.motion.place_near(self.sample, self.means, t)
                self.placed[t] = (x.to(self.means.dtype), F.to(self.means.dtype))
            return deform_gaussians(gaussians, *self.placed[t], shading)
        X = gaussians.means.detach()
        if float((X.to(self.sample.X.dtype) - self.sample.X).norm(dim=1).amax()) > self.refresh:
            self.sample, self.samples = self.motion.sample(X), self.samples + 1
        return self.motion.carry(gaussians, t, shading, near=self.sample)


def refine_on_motion(gaussians: Any, motion: SkinnedMotion, images: Tensor, cameras: Sequence[Any],
                     frame_ids: Sequence[int], fit: Any, iterations: int, geometry: bool = True, seed: int = 0,
                     progress: bool = False, shading: Any | None = None,
                     loss_power: float = 1.0) -> tuple[Any, Any | None, dict]:
    """Fit ``gaussians`` to the observed frames along a given motion.

    Args:
        gaussians: the asset's rest-frame :class:`~vid2sim.splats.gaussians.Gaussians` (N of them).
        motion: the simulated motion (:class:`SkinnedMotion`) that carries them to every frame.
        images: (V, T, H, W, 3) observed images in [0, 1] (views × frames, the frames of ``frame_ids``).
        cameras: the V cameras.
        frame_ids: the video frame of each of the T image columns (indices into the motion's frames).
        fit: a :class:`~vid2sim.splats.fitting.FitConfig`: its ``lambda_dssim``, learning rates and
            ``views_per_step`` are used. Centres move at the constant rate ``lr_means`` × the cameras' extent
            (:func:`~vid2sim.splats.fitting.scene_extent`), 3DGS's initial rate.
        iterations: optimisation steps; each renders one random observed frame in ``views_per_step`` views.
        geometry: also fit the centres, scales and rotations (default); False fits colours and opacities only.
        seed: the frame and view draws.
        progress: a tqdm bar.
        shading: a starting :class:`~vid2sim.splats.shading.Shading` (N normals): the colours are then albedos
            lit by its world-fixed light, and the light's direction, its ambient share and the normals are fitted
            along with them (Adam at :data:`SHADING_LR` and :data:`LIGHT_LR`).
            None: the colours render as stored.
        loss_power: p in (0, 1]: each step minimises (3DGS's image loss)^p. 1: the loss itself; below 1 the
            frames the motion explains well (small loss) weigh more against those it does not, by loss^(p − 1).

    Returns:
        (the refitted Gaussians, same count N; the fitted shading or None; {"iterations", "geometry",
        "loss_first", "loss_last": means of the first and last 10 % of the steps' losses, "field_samples": how
        often the skinning field was evaluated at the centres (:data:`REFRESH_FRACTION`), and "shading": the
        fitted light, when shaded}).
    """
    from tqdm.auto import tqdm


    if iterations < 1:
        raise ValueError(f"refine_on_motion: iterations must be >= 1, got {iterations}")
    if not 0 < loss_power <= 1:
        raise ValueError(f"refine_on_motion: loss_power must be in (0, 1], got {loss_power}")
    V, T = images.shape[:2]
    if len(frame_ids) != T or len(cameras) != V:
        raise ValueError(f"refine_on_motion: images are {V} views x {T} frames, got {len(cameras)} cameras and "
                         f"{len(frame_ids)} frame ids")
    if max(frame_ids) >= motion.num_frames or min(frame_ids) < 0:
        bad = max(frame_ids) if max(frame_ids) >= motion.num_frames else min(frame_ids)
        raise ValueError(f"refine_on_motion: frame {bad} asked, the motion has {motion.num_frames} frames")
    params = {"sh_dc": gaussians.sh[:, :1], "sh_rest": gaussians.sh[:, 1:], "opacity_logits": gaussians.opacity_logits,
              "means": gaussians.means, "log_scales": gaussians.log_scales, "quats": gaussians.quats}
    params = {k: v.detach().clone() for k, v in params.items()}
    lrs = {"sh_dc": fit.lr_sh_dc, "sh_rest": fit.lr_sh_rest, "opacity_logits": fit.lr_opacity}
    if geometry:
        lrs.update(means=fit.lr_means * scene_extent(cameras), log_scales=fit.lr_scales, quats=fit.lr_quats)
    if shading is not None:
        if shading.num != gaussians.num:
            raise ValueError(f"refine_on_motion: the shading has {shading.num} normals for {gaussians.num} Gaussians")
        params.update(normals=shading.normals.detach().clone(), light=shading.light.detach().clone(),
                      ambient_logit=shading.ambient_logit.detach().clone())
        lrs.update(normals=SHADING_LR, light=LIGHT_LR, ambient_logit=LIGHT_LR)
    trained = [k for k in lrs if params[k].numel() > 0]
    for k in trained:
        params[k].requires_grad_(True)
    opt = torch.optim.Adam([{"params": [params[k]], "lr": lrs[k]} for k in trained], eps=1e-15)

    def current() -> Any:
        return replace(gaussians, means=params["means"], log_scales=params["log_scales"], quats=params["quats"],
                       opacity_logits=params["opacity_logits"], sh=torch.cat([params["sh_dc"], params["sh_rest"]], 1))

    def current_shading() -> Any:
        if shading is None:
            return None
        return Shading(params["normals"], params["light"], params["ambient_logit"])

    per_step = V if fit.views_per_step is None else min(V, fit.views_per_step)
    g = torch.Generator().manual_seed(seed)
    losses = []
    carrier = _Carrier(motion, gaussians.means, geometry)
    for _ in tqdm(range(iterations), desc="appearance on the motion", disable=not progress, leave=False):
        t = int(torch.randint(T, (1,), generator=g))
        views = torch.randperm(V, generator=g)[:per_step].tolist() if per_step < V else list(range(V))
        moved = carrier(current(), frame_ids[t], current_shading())
        out = render_gaussians(moved, [cameras[v] for v in views], background=1.0).rgb
        loss = photometric_loss(out, images[views, t], fit.lambda_dssim)
        opt.zero_grad(set_to_none=True)
        (loss if loss_power == 1 else loss.clamp_min(1e-12) ** loss_power).backward()
        opt.step()
        losses.append(float(loss.detach()))
    k = max(1, len(losses) // 10)
    refined = current().detach()
    lit = None if shading is None else current_shading().detach()
    record = {"iterations": iterations, "geometry": geometry, "loss_power": loss_power,
              "loss_first": sum(losses[:k]) / k, "loss_last": sum(losses[-k:]) / k, "field_samples": carrier.samples}
    if lit is not None:
        record["shading"] = lit.to_record()
    return refined, lit, record


# ---- the stage -------------------------------------------------------------------------------------------------


class MotionAppearanceStage:
    """Refits the asset's Gaussians through its simulated motion (``config.motion_appearance``; skipped at 0
    iterations); writes ``gaussians_motion.ply``, ``shading_motion.pt`` and ``motion_appearance.json``, and
    loading it puts them into ``state.asset``."""

    name = "motion_appearance"
    sections = ("motion_appearance", "gaussians")
    revision = 0

    def title(self, ctx: Context, state: State) -> str | None:
        cfg = ctx.config.motion_appearance
        if cfg.iterations == 0:
            return None
        what = "Gaussians" if cfg.geometry else "colours"
        return f"refitting the {what} on {ctx.observed.frames} observed frames along the simulated motion"

    def run(self, ctx: Context, state: State) -> None:
        cfg, o, g = ctx.config, ctx.observed, state.gaussians
        motion = SkinnedMotion.of_asset(state.asset, o.frames, device=ctx.device)
        start, shading = g, None
        if cfg.motion_appearance.shading:
            shading = initial_shading(g, state.obj_cpu.points.to(ctx.device), state.obj.volume, o.gravity)
            start = replace(g, sh=shading.unshade(g.sh))
        refined, shading, record = refine_on_motion(
            start, motion, o.images, o.cameras, list(range(o.frames)), cfg.gaussians, cfg.motion_appearance.iterations,
            geometry=cfg.motion_appearance.geometry, seed=cfg.seed, progress=ctx.progress, shading=shading,
            loss_power=cfg.motion_appearance.loss_power)
        save_ply(refined.to("cpu"), ctx.path(PLY))
        if shading is not None:
            save_torch_atomic(shading.to("cpu").__dict__, ctx.path(SHADING))
        else:  # an earlier run of this stage with shading (rerun with other settings) must not lend it its shading
            ctx.path(SHADING).unlink(missing_ok=True)
        write_json_atomic(ctx.path(RECORD), record)

    def load(self, ctx: Context, state: State) -> None:
        if ctx.config.motion_appearance.iterations == 0:
            return
        shading_path = ctx.path(SHADING)
        shading = Shading(**torch.load(shading_path, weights_only=True)) if shading_path.is_file() else None
        state.asset = replace(state.asset, gaussians=load_ply(ctx.path(PLY)), shading=shading)
        state.asset.extra["motion_appearance"] = read_json(ctx.path(RECORD), "the motion-appearance record")
