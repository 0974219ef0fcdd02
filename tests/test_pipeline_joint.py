"""Stage II pieces: simulation points from masks, the Gaussian rig, the joint optimisation (it recovers E
from images the same model rendered), and the asset round trip."""

import dataclasses
import json

import pytest
import torch

from vid2sim.asset.folder import Asset, AssetFormatError, load_asset, save_asset
from vid2sim.asset.motion import GaussianRig
from vid2sim.physics import (
    Floor,
    Gravity,
    Material,
    Simulator,
    SkinningField,
    sample_cubature,
)
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.solver import SimConfig
from vid2sim.reconstruct.clip import Observations, render_states
from vid2sim.reconstruct.config import JointConfig, PointsConfig
from vid2sim.reconstruct.stages.joint import joint_optimisation
from vid2sim.reconstruct.stages.points import object_points
from vid2sim.splats.cameras import camera_ring
from vid2sim.splats.gaussians import Gaussians

FLOOR = -0.25


def _ellipsoid_points(n: int, radii=(0.2, 0.14, 0.1), seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(4 * n, 3, generator=g) * 2 - 1
    p = p[(p ** 2).sum(1) <= 1][:n]
    return p * torch.tensor(radii)


def _masks_of(points: torch.Tensor, cameras, radius_px: int = 0) -> torch.Tensor:
    """Rasterise dense points (dilated by a few pixels) into masks: (V, H, W)."""
    out = []
    for cam in cameras:
        uv, depth = cam.project(points)
        m = torch.zeros(cam.height, cam.width)
        u = uv[:, 0].floor().long()
        v = uv[:, 1].floor().long()
        for du in range(-radius_px, radius_px + 1):
            for dv in range(-radius_px, radius_px + 1):
                uu, vv = (u + du).clamp(0, cam.width - 1), (v + dv).clamp(0, cam.height - 1)
                m[vv, uu] = 1.0
        out.append(m)
    return torch.stack(out)


def _scene_setup(seed: int = 0):
    """A small textured ellipsoid of Gaussians over a floor, its simulator (float64) and 2 cameras."""
    torch.manual_seed(seed)
    pts = _ellipsoid_points(3000, seed=seed).double()
    field = SkinningField(num_handles=3, width=16, hidden_layers=2, seed=seed).double()
    for p in field.parameters():
        p.requires_grad_(False)
    volume = 4 / 3 * torch.pi * 0.2 * 0.14 * 0.1
    idx, w = sample_cubature(pts, 60, volume=volume, seed=0)
    surface = pts[(pts / torch.tensor([0.2, 0.14, 0.1], dtype=torch.float64)).norm(dim=1) > 0.85]
    areas = torch.full((surface.shape[0],), 4 * torch.pi * 0.14 ** 2 / surface.shape[0], dtype=torch.float64)
    sim = Simulator(field, pts[idx], w, Material(10 ** 4.5, 0.3), [Gravity(), Floor(FLOOR, AREA_CONTACT_STIFFNESS)],
                    SimConfig(), length_scale=0.5, contact_points=surface, contact_weights=areas)
    g = torch.Generator().manual_seed(1)
    centres = _ellipsoid_points(400, seed=seed + 1)
    colours = 0.2 + 0.6 * torch.rand(400, 3, generator=g)
    gaussians = Gaussians.from_values(centres, torch.full((400,), 0.03), colours, torch.full((400,), 0.9))
    cams = camera_ring(2, 1.2, 15.0, 32, 32, fov_x_deg=45.0, target=(0.0, 0.0, -0.15))
    return sim, gaussians, cams


def test_object_points_fill_the_object_and_estimate_its_volume():
    pts = _ellipsoid_points(60000)
    cams = camera_ring(6, 1.5, 25.0, 64, 64, fov_x_deg=40.0)
    masks = _masks_of(pts, cams)
    obj = object_points(masks, cams, config=PointsConfig(resolution=48, num_points=2000))
    true_volume = 4 / 3 * torch.pi * 0.2 * 0.14 * 0.1
    # a visual hull contains the object: its volume is an overestimate, by less than half for 6 views
    assert true_volume * 0.95 < obj.volume < true_volume * 1.5
    assert obj.points.shape == (2000, 3)
    inside = ((obj.points / torch.tensor([0.2, 0.14, 0.1])) ** 2).sum(1) <= 1.3 ** 2
    assert float(inside.float().mean()) > 0.97
    assert obj.scale == pytest.approx(2 * (0.2 ** 2 + 0.14 ** 2 + 0.1 ** 2) ** 0.5, rel=0.15)
    ellipsoid_area = (
        4 * torch.pi * ((0.2 * 0.14) ** 1.6 + (0.2 * 0.1) ** 1.6 + (0.14 * 0.1) ** 1.6) ** (1 / 1.6) / 3 ** (1 / 1.6)
    )
    assert float(obj.contact_areas.sum()) == pytest.approx(float(ellipsoid_area), rel=0.35)
    assert obj.canonical(obj.points).abs().max() <= 0.5 + 1e-6


def test_object_points_reject_masks_that_see_nothing():
    cams = camera_ring(3, 1.5, 25.0, 32, 32)
    with pytest.raises(ValueError, match="empty"):
        object_points(torch.zeros(3, 32, 32), cams)


def test_rig_at_rest_renders_the_gaussians_and_moves_rigidly():
    sim, gaussians, cams = _scene_setup()
    rig = GaussianRig(sim, gaussians)
    rest = sim.rest_state()
    basis = rig.basis()
    d = rig.deformed(rest.z, basis)
    assert torch.allclose(d.means, gaussians.means, atol=1e-6)
    assert torch.allclose(d.covars, gaussians.covariances(), atol=1e-7)
    moving = sim.rigid_velocity_state([0.0, 0.0, 1.0])
    z = moving.zdot * 0.1  # a pure translation by 0.1 m along z on the rigid handle
    assert torch.allclose(rig.deformed(z, basis).means, gaussians.means + torch.tensor([0, 0, 0.1]), atol=1e-6)


def test_coarse_minimum_is_the_parabola_vertex_between_the_best_samples_neighbours():
    from vid2sim.reconstruct.stages.joint import coarse_minimum

    grid = [4.0, 4.5, 5.0, 5.5, 6.0]
    assert coarse_minimum(grid, [(x - 4.8) ** 2 + 1 for x in grid]) == pytest.approx(4.8)  # exact on a parabola
    assert coarse_minimum(grid, [abs(x - 4.6) for x in grid]) == pytest.approx(4.5625)  # a kink: the parabola's vertex
    assert coarse_minimum(grid, [6 - x for x in grid]) == 6.0  # at the end of the grid: the sample itself
    assert coarse_minimum([5.0], [1.0]) == 5.0


def test_clip_loss_weights_its_frames():
    """Whole-clip losses weight frames 1 … T−1 equally (the paper) or by exp(−(t − 1)/τ), normalised; the
    weighted loss is the weighted sum of the per-frame image errors."""
    import math

    from vid2sim.reconstruct.clip import clip_loss, frame_weights

    assert frame_weights(5, None) == pytest.approx([0.25] * 4)
    w = frame_weights(5, 2.0)
    assert sum(w) == pytest.approx(1.0)
    assert [b / a for a, b in zip(w, w[1:])] == pytest.approx([math.exp(-0.5)] * 3)
    assert frame_weights(1, 2.0) == []
    for bad in (0.0, -1.0, math.inf, "4", True):
        with pytest.raises(ValueError, match="frame_decay"):
            JointConfig(frame_decay=bad)
    sim, gaussians, cams = _scene_setup()
    rig = GaussianRig(sim, gaussians)
    start = sim.rigid_velocity_state([0.1, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0])
    target = torch.rand(2, 5, 32, 32, 3, generator=torch.Generator().manual_seed(0))
    obs = Observations(target, cams)
    equal, states = clip_loss(sim, rig, start, obs)
    decayed, _ = clip_loss(sim, rig, start, obs, decay=2.0)
    with torch.no_grad():
        per_frame = [float(((render_states(rig, [states[t]], obs, [0, 1])[0] - target[:, t]) ** 2).mean())
                     for t in range(1, 5)]
    assert equal == pytest.approx(sum(per_frame) / 4, rel=1e-6)
    assert decayed == pytest.approx(sum(a * b for a, b in zip(w, per_frame)), rel=1e-6)
    # a shaded rig renders each frame with its own lit colours, exactly as frame by frame
    from vid2sim.splats.render import render
    from vid2sim.splats.shading import Shading

    normals = torch.randn(gaussians.num, 3, dtype=gaussians.means.dtype, generator=torch.Generator().manual_seed(1))
    lit = GaussianRig(sim, gaussians, Shading.create(normals, [0.3, 0.2, 1.0], 0.3))
    with torch.no_grad():
        together = render_states(lit, states[1:4], obs, [0, 1])
        basis = lit.basis()
        for t in range(3):
            d = lit.deformed(states[t + 1].z, basis)
            alone = render(d.means, d.opacities, d.sh, cams, covars=d.covars, sh_degree=d.sh_degree,
                           background=list(obs.background)).rgb
            assert torch.allclose(together[t], alone, atol=1e-6)
        assert not torch.allclose(together, render_states(rig, states[1:4], obs, [0, 1]), atol=1e-3)

def test_a_scaled_loss_sees_the_full_renders_through_the_same_filter_as_its_targets():
    """At a coarse scale the targets are area-averaged and so are the renders (made at the cameras' full size):
    a state whose full-size renders are the targets has zero loss at every scale. Rendering the Gaussians by
    half-size cameras instead leaves a floor (the footprint of a splat smaller than a pixel does not average)."""
    from vid2sim.reconstruct.clip import clip_loss, downsample

    sim, gaussians, cams = _scene_setup()
    rig = GaussianRig(sim, gaussians)
    start = sim.rigid_velocity_state([0.1, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0])
    with torch.no_grad():
        states = [start] + sim.rollout(start, 3)
        full = Observations(torch.zeros(2, 4, 32, 32, 3), cams)
        targets = render_states(rig, states, full, [0, 1]).transpose(0, 1)  # (V, T, H, W, 3)
    full = Observations(targets, cams)
    half = full.at_scale(0.5)
    assert half.images.shape == (2, 4, 16, 16, 3) and half.cameras is full.cameras
    assert torch.allclose(half.images, downsample(targets, (16, 16)))
    for obs in (full, half):
        loss, _ = clip_loss(sim, rig, start, obs)
        assert loss < 1e-12
    with torch.no_grad():  # the old way: half-size cameras render a different image than the averaged one
        direct = render_states(rig, states[1:], Observations(half.images, [c.resized(16, 16) for c in cams]), [0, 1])
    assert float(((direct - half.images[:, 1:].transpose(0, 1)) ** 2).mean()) > 1e-5


def test_joint_optimisation_recovers_E_from_images_of_the_same_model():
    """Images rendered from the model at log10 E = 4.5 → the coarse search and Adam find it from the prior 5."""
    sim, gaussians, cams = _scene_setup()
    start = sim.rigid_velocity_state([0.1, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0])
    with torch.no_grad():
        states = [start] + sim.rollout(start, 7)
        images = render_states(GaussianRig(sim, gaussians), states, Observations(torch.zeros(2, 8, 32, 32, 3), cams),
                               [0, 1]).transpose(0, 1).float()
    assert float(images.std()) > 0.05  # the object is in view
    with torch.no_grad():
        sim.log10_E.fill_(5.0)
    cfg = JointConfig(method="windows", iterations=6, coarse_log10_E=(4.0, 4.4, 4.8, 5.2, 5.6), coarse_scale=1.0,
                      validate_every=3,
                      lr_log10_E=0.02, lr_velocity=0.0, lr_skinning=0.0)
    result = joint_optimisation(sim, gaussians, Observations(images, cams), [0.1, 0.0, -1.0], [0.0, 1.0, 0.0],
                                [0.0, 0.0, 0.0], cfg, progress=False)
    losses = {round(r["log10_E"], 1): r["loss"] for r in result.coarse}
    assert min(losses, key=losses.get) == 4.4  # the grid point nearest the truth
    assert abs(result.log10_E - 4.5) < 0.08
    assert result.validation_loss < 1e-4
    assert [e["iteration"] for e in result.log if "loss" in e] == list(range(1, 7))
    assert float(sim.log10_E) == pytest.approx(result.log10_E)  # the simulator holds the best state


def test_centre_of_mass_search_finds_the_centre_the_images_were_made_with():
    """Images of a drop simulated with the masses' centre moved by 14 mm: the search from the unmoved masses comes
    within 5 mm of it (the bounce's spin shows where the centre is), leaves the simulator with those masses, and
    counts offsets the points cannot carry as infinitely bad."""
    from vid2sim.physics.mass import centre_shifted_volumes
    from vid2sim.reconstruct.stages.joint import centre_of_mass_search

    sim, gaussians, cams = _scene_setup()
    truth = torch.tensor([0.012, 0.0, -0.008], dtype=torch.float64)
    base = sim.mass_volumes
    sim.mass_volumes = centre_shifted_volumes(sim.X, base, truth)
    rig = GaussianRig(sim, gaussians)

    def start():
        return sim.rigid_velocity_state([0.3, 0.0, -1.0], [0.0, 2.0, 1.0], [0.0, 0.0, 0.0])

    with torch.no_grad():
        states = [start()] + sim.rollout(start(), 8)
        images = render_states(rig, states, Observations(torch.zeros(2, 9, 32, 32, 3), cams),
                               [0, 1]).transpose(0, 1).float()
    sim.mass_volumes = base
    offset, records = centre_of_mass_search(sim, rig, start, Observations(images, cams), 0.01, 2)
    assert records[0]["offset"] == [0.0, 0.0, 0.0] and len(records) <= 15
    assert float((torch.tensor(offset, dtype=torch.float64) - truth).norm()) < 0.005
    assert min(r["loss"] for r in records) == next(r["loss"] for r in records if r["offset"] == offset)
    assert torch.allclose(sim.mass_volumes, centre_shifted_volumes(sim.X, base, torch.tensor(offset).double()))
    sim.mass_volumes = base
    offset, records = centre_of_mass_search(sim, rig, start, Observations(images, cams), 0.3, 1)
    assert any(r["loss"] == float("inf") for r in records)  # 0.3 m is outside the 0.2 m ellipsoid
    assert all(abs(o) < 0.3 for o in offset)


def test_networks_that_are_not_optimised_stay_out_of_the_graph():
    """lr_skinning = 0: the field is frozen during the loop (no gradient reaches it, so the adjoint does not
    differentiate the skinning basis) and its requires_grad flags are restored afterwards."""
    sim, gaussians, cams = _scene_setup()
    for p in sim.field.parameters():
        p.requires_grad_(True)  # a freshly built field, as reconstruct hands it over
    seen = []
    original = sim.reduced_basis

    def spy():
        basis = original()
        seen.append(basis.b.requires_grad)
        return basis

    sim.reduced_basis = spy
    images = torch.ones(2, 6, 32, 32, 3)
    cfg = JointConfig(method="windows", iterations=2, coarse_log10_E=(), validate_every=2, lr_skinning=0.0)
    joint_optimisation(sim, gaussians, Observations(images, cams), [0.0, 0.0, -1.0], [0.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0], cfg, progress=False)
    assert seen and not any(seen)
    assert all(p.requires_grad and p.grad is None for p in sim.field.parameters())


def test_joint_optimisation_gradient_reaches_E_and_the_initial_velocity():
    """One window's image loss: d/d log10 E and d/d v0 by the adjoint + renderer agree with central differences."""
    sim, gaussians, cams = _scene_setup()
    # fixed substeps (the automatic count jumps with E) and Newton solved to round-off, so that central
    # differences see the same discrete problem the adjoint differentiates
    sim.config = dataclasses.replace(sim.config, substeps=8, newton_tol=1e-13, newton_rtol=1e-12, newton_max_iters=50,
                                     reuse_hessian=False)
    gaussians = gaussians.to(dtype=torch.float64)
    v0 = torch.tensor([0.1, 0.0, -1.0], dtype=torch.float64)
    rig = GaussianRig(sim, gaussians)
    obs = Observations(torch.zeros(2, 8, 32, 32, 3, dtype=torch.float64), cams)
    g = torch.Generator().manual_seed(0)
    target = torch.rand(3, 2, 32, 32, 3, generator=g, dtype=torch.float64)

    def loss(log10_E: float, v: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            sim.log10_E.fill_(log10_E)
        states = sim.rollout(sim.rigid_velocity_state(v, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), 3)
        return ((render_states(rig, states, obs, [0, 1]) - target) ** 2).mean()

    sim.log10_E.requires_grad_(True)
    v = v0.clone().requires_grad_(True)
    value = loss(4.5, v)
    gE, gv = torch.autograd.grad(value, [sim.log10_E, v])
    sim.log10_E.requires_grad_(False)
    # the rasterizer's cutoffs (a Gaussian's 3-sigma extent, alpha < 1/255 skipped) make the image piecewise
    # smooth: a small step stays within one smooth piece (h = 1e-4 crosses cutoffs here and is off by 2x for E
    # and 15x for v; the positions alone agree with central differences at any h)
    h = 1e-6
    with torch.no_grad():
        fdE = (loss(4.5 + h, v0) - loss(4.5 - h, v0)) / (2 * h)
        e = torch.tensor([0.0, 0.0, h], dtype=torch.float64)
        fdv = (loss(4.5, v0 + e) - loss(4.5, v0 - e)) / (2 * h)
    assert abs(float(gE) - float(fdE)) < 1e-3 * abs(float(fdE)) + 1e-9
    assert abs(float(gv[2]) - float(fdv)) < 1e-3 * abs(float(fdv)) + 1e-9


def _asset(sim, gaussians) -> Asset:
    return Asset(gaussians=gaussians, field=sim.field, jacobian=None,
                 material={"model": "neo-hookean", "E": 3e4, "log10_E": 4.477, "nu": 0.3, "density": 1000.0,
                           "damping_ratio": 0.05},
                 cubature_points=sim.X, cubature_weights=sim.vol, contact_points=sim.contact_points,
                 contact_areas=sim.contact_weights, points=sim.X, volume=float(sim.vol.sum()),
                 sim_config=sim.config, gravity=[0.0, 0.0, -9.8], floor_height=FLOOR,
                 floor_stiffness=AREA_CONTACT_STIFFNESS, length_scale=0.5,
                 initial_velocity={"linear": [0.1, 0.0, -1.0], "angular": [0.0, 1.0, 0.0], "centre": [0.0, 0.0, 0.0]},
                 dt=0.05)


def test_asset_round_trip_simulates_the_same(tmp_path):
    sim, gaussians, _ = _scene_setup()
    asset = _asset(sim, gaussians)
    folder = save_asset(asset, tmp_path / "asset", config={"note": "test"}, log={"iterations": []})
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["asset.json", "material.json", "gaussians.ply", "skinning.pt", "points.npz", "config.json", "log.json"])
    back = load_asset(folder)
    a = asset.simulator()
    b = back.simulator()
    za = a.rollout(asset.initial_state(a), 4)[-1].z
    zb = b.rollout(back.initial_state(b), 4)[-1].z
    assert torch.allclose(za, zb, atol=1e-10)
    assert torch.allclose(back.gaussians.means, gaussians.means)
    stiffer = back.simulator(youngs_modulus=1e6)
    assert float(stiffer.log10_E) == pytest.approx(6.0)
    assert not list(tmp_path.glob(".asset.*"))  # no staging folder left behind


def test_asset_errors_name_the_file_and_field(tmp_path):
    sim, gaussians, _ = _scene_setup()
    folder = save_asset(_asset(sim, gaussians), tmp_path / "asset")
    material = json.loads((folder / "material.json").read_text())
    material["nu"] = "soft"
    (folder / "material.json").write_text(json.dumps(material))
    with pytest.raises(AssetFormatError, match="material.json: nu must be a finite number"):
        load_asset(folder)
    (folder / "points.npz").unlink()
    (folder / "material.json").write_text(json.dumps({**material, "nu": 0.3}))
    with pytest.raises(AssetFormatError, match="points.npz"):
        load_asset(folder)
    with pytest.raises(AssetFormatError, match="not a folder"):
        load_asset(tmp_path / "nothing")


def test_an_asset_keeps_its_stiffness_curve_and_the_rig_uses_it_at_its_nu(tmp_path):
    """material.json's stiffness_curve (reconstruct --calibrate-stiffness) comes back as the simulator's s(ν),
    also under another ν; the exported rig's Lamé parameters use s at the asset's ν; a bad curve is named."""
    from vid2sim.export.rig import export_rig, load_rig
    from vid2sim.physics.stiffness_curve import StiffnessCurve

    sim, gaussians, _ = _scene_setup()
    asset = _asset(sim, gaussians)
    curve = StiffnessCurve((0.2, 0.3, 0.4, 0.49), (0.9, 0.85, 0.75, 0.5))
    asset.material.update(stiffness_curve=curve.to_dict(), stiffness_scale=curve.at(float(asset.material["nu"])))
    folder = save_asset(asset, tmp_path / "asset")
    back = load_asset(folder)
    assert back.stiffness() == curve and back.simulator().stiffness_scale == curve
    softer = back.simulator(poisson_ratio=0.45)
    assert float(softer.effective_youngs_modulus()) == pytest.approx(float(back.material["E"]) * curve.at(0.45),
                                                                     rel=1e-6)
    doc, _ = load_rig(export_rig(back, tmp_path / "rig"))
    nu = float(back.material["nu"])
    e = float(back.material["E"]) * curve.at(nu)
    assert doc["material"]["lame_mu"] == pytest.approx(e / (2 * (1 + nu)), rel=1e-12)
    material = json.loads((folder / "material.json").read_text())
    (folder / "material.json").write_text(json.dumps({**material, "stiffness_curve": {"nu": [0.3, 0.2],
                                                                                      "scale": [1.0, 1.0]}}))
    with pytest.raises(AssetFormatError, match="material.json: stiffness_curve: .*increase strictly"):
        load_asset(folder)
    (folder / "material.json").write_text(json.dumps({**material, "volumetric": "mixed"}))
    with pytest.raises(AssetFormatError, match="material.json: volumetric must be 'pointwise' or 'projected'"):
        load_asset(folder)
    (folder / "material.json").write_text(json.dumps({**material, "volumetric": "projected"}))
    projected = load_asset(folder)
    assert projected.simulator().volumetric == "projected"
    doc, _ = load_rig(export_rig(projected, tmp_path / "rig_projected"))
    assert "P ln J" in doc["material"]["energy"]  # the rig says which λ term the simulation uses


@pytest.mark.slow
def test_bench_speed_joint_section_times_one_iteration():
    from vid2sim.apps.bench.joint_speed import QUICK_GAUSSIANS, QUICK_RESOLUTION, run

    result = run(torch.device("cpu"), quick=True)
    settings = result["joint_settings"]
    assert (settings["gaussians"], settings["views"]) == (QUICK_GAUSSIANS, 4)
    assert (settings["resolution"], settings["gauss_newton_resolution"]) == (QUICK_RESOLUTION, QUICK_RESOLUTION // 2)
    for key in ("joint_iter_ms", "joint_iter_ms_half_resolution", "joint_iter_ms_with_networks",
                "joint_iter_ms_with_networks_neural_jacobian", "joint_gauss_newton_step_ms"):
        assert 0 < result[key] < 60_000
    assert result["joint_settings"]["gauss_newton_parameters"] == 9  # log10 E, ν, μ, 3 + 3 velocity components
    # one step = 9 rollouts of the 10-frame clip: more than one windows iteration (a 4-frame window), at most the
    # 9 × 9 frames' share of it
    assert result["joint_iter_ms_half_resolution"] < result["joint_gauss_newton_step_ms"]
