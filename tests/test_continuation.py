"""The continuation (vid2sim.reconstruct.stages.continuation): the state at the end of the observed clip fitted to
its last frames, stored in the asset, and the captured drop going on from it."""

import json
from dataclasses import replace

import pytest
import torch

from vid2sim.asset import load_asset
from vid2sim.asset.folder import AssetFormatError, save_asset
from vid2sim.asset.motion import GaussianRig, simulate_states, simulated_centre_of_mass
from vid2sim.physics.rigid_motion import rigidly_moved
from vid2sim.physics.solver import SimState
from vid2sim.reconstruct.clip import Observations, render_states
from vid2sim.reconstruct.rollouts import RolloutPool
from vid2sim.reconstruct.stages.continuation import check_continuation, fit_continuation
from vid2sim.scene.reading import load_scene

TRUE = dict(rotation=[0.0, 0.1, -0.06], translation=[0.03, -0.02, 0.015], linear=[0.3, 0.0, -0.2],
            angular=[0.0, 1.5, 0.8])


def _moved_drop(asset, scene, anchor):
    """The asset's own drop over 5 frames with its state at ``anchor`` moved rigidly (``TRUE``), rendered in the
    scene's observed views: (sim, the unmoved states, the moved ones, the rig, Observations of the moved drop)."""
    sim, states = simulate_states(asset, 5, progress=False, continued=False)
    centre = [float(x) for x in simulated_centre_of_mass(sim, [states[anchor]])[0]]
    truth_start = rigidly_moved(states[anchor], centre=centre, **TRUE)
    with torch.no_grad():
        truth = states[:anchor] + [truth_start] + sim.rollout(truth_start, 4 - anchor)
    rig = GaussianRig(sim, asset.gaussians, asset.shading)
    views = list(scene.config.observed_views)
    cameras = [scene.cameras[v] for v in views]
    blank = Observations(torch.zeros(len(views), 5, *scene.images.shape[2:4], 3), cameras)
    images = render_states(rig, truth, blank, range(len(views))).transpose(0, 1)  # (V, T, H, W, 3)
    return sim, states, truth, rig, Observations(images, cameras)


def test_the_fit_finds_a_moved_end_state_from_its_images(tiny_asset, tiny_scene, one_torch_thread):
    """Images of the asset's own drop, its state at the window's first frame moved rigidly: the fit from the
    unmoved state puts the body where the moved one is, on both of the window's frames, and the loss falls."""
    asset, scene = load_asset(tiny_asset), load_scene(tiny_scene)
    anchor = 3
    sim, states, truth, rig, obs = _moved_drop(asset, scene, anchor)
    record = fit_continuation(sim, rig, obs, states[anchor], anchor, iterations=8)
    assert record["frame"] == anchor and record["from_frame"] == 5
    assert record["fit"]["loss"] < 0.05 * record["fit"]["loss_before"]
    half = fit_continuation(sim, rig, obs.at_scale(0.5), states[anchor], anchor, iterations=8)  # the full preset's
    assert half["fit"]["loss"] < 0.05 * half["fit"]["loss_before"]
    with RolloutPool(1) as pool:  # the Jacobian's rollouts shared with a worker process: the same fit, to rounding
        shared = fit_continuation(sim, rig, obs, states[anchor], anchor, iterations=8, pool=pool)
    assert shared["fit"]["iterations"] == record["fit"]["iterations"]
    assert torch.allclose(torch.tensor(shared["z"]), torch.tensor(record["z"]), rtol=1e-6, atol=1e-9)
    fitted = SimState(*(torch.tensor(record[k], dtype=sim.X.dtype) for k in ("z", "zdot")), record["t"])
    with torch.no_grad():
        fitted_next = sim.rollout(fitted, 1)[0]
    probe = asset.points[::5].to(sim.X.dtype)
    size = float((probe.max(0).values - probe.min(0).values).norm())
    at = (lambda state: sim.positions(probe, state.z).detach())
    for got, want, before in ((fitted, truth[anchor], states[anchor]), (fitted_next, truth[anchor + 1],
                                                                         states[anchor + 1])):
        error = float((at(got) - at(want)).norm(dim=1).mean())
        moved = float((at(before) - at(want)).norm(dim=1).mean())
        assert moved > 0.03 * size  # the truth was moved visibly
        assert error < 0.25 * moved


def test_the_check_uses_a_continuation_only_where_it_predicts_better(tiny_asset, tiny_scene, one_torch_thread):
    """The check fits the window before the last one and predicts the last: on a drop whose state was moved at the
    check's anchor the continuation predicts the held-out frames far better than the one rollout; on the rollout's
    own images the rollout is exact and is kept."""
    asset, scene = load_asset(tiny_asset), load_scene(tiny_scene)
    sim, states, _, rig, obs = _moved_drop(asset, scene, 1)
    check = check_continuation(sim, rig, obs, states, 2, iterations=8)
    assert check["frame"] == 1 and check["predicted_frames"] == [3, 4]
    assert check["loss_continued"] < 0.2 * check["loss_single"]
    own = render_states(rig, states, obs, range(len(obs.cameras))).transpose(0, 1)
    exact = check_continuation(sim, rig, Observations(own, obs.cameras), states, 2, iterations=2)
    assert exact["loss_single"] < 1e-12 and not exact["loss_continued"] < exact["loss_single"]
    with pytest.raises(ValueError, match="needs 2·window \\+ 1 = 7 frames"):
        check_continuation(sim, rig, obs, states, 3)
    # the tiny asset's record says what its reconstruction's check found and whether the continuation is used
    record = asset.extra["continuation"]
    assert record["used"] == (record["check"]["loss_continued"] < record["check"]["loss_single"])
    assert record["used"] == (asset.continuation is not None)


def _with_continuation(tiny_asset, tiny_scene, folder):
    """A copy of the tiny asset that has a continuation (fitted here where its own check kept the one rollout)."""
    asset = load_asset(tiny_asset)
    if asset.continuation is None:
        scene = load_scene(tiny_scene)
        sim, states = simulate_states(asset, 5, progress=False)
        views = list(scene.config.observed_views)
        obs = Observations(scene.images[views][:, :5].float(), [scene.cameras[v] for v in views])
        rig = GaussianRig(sim, asset.gaussians, asset.shading)
        asset = replace(asset, continuation=fit_continuation(sim, rig, obs, states[3], 3, iterations=2))
    return load_asset(save_asset(asset, folder))


def test_the_captured_drop_goes_on_from_the_continuation(tiny_asset, tiny_scene, tmp_path):
    """The frames before the continuation's ``from_frame`` are the one rollout from frame 0, those after it the
    rollout from its state (kept through save and load); an asset without it is one rollout."""
    asset = _with_continuation(tiny_asset, tiny_scene, tmp_path / "continued")
    c = asset.continuation
    assert c["from_frame"] == 5 and c["frame"] == 3
    assert set(c["fit"]) >= {"correction", "loss_before", "loss", "iterations", "stop", "seconds"}
    sim, continued = simulate_states(asset, 8, progress=False)
    _, single = simulate_states(asset, 8, progress=False, continued=False)
    for t in range(5):
        assert torch.equal(continued[t].z, single[t].z)
    with torch.no_grad():
        tail = sim.rollout(asset.continuation_state(sim), 4)
    for t in range(5, 8):
        assert torch.equal(continued[t].z, tail[t - 4].z)
        assert not torch.equal(continued[t].z, single[t].z)
    plain = load_asset(save_asset(replace(asset, continuation=None), tmp_path / "plain"))
    assert plain.continuation is None
    assert "continuation" not in json.loads((tmp_path / "plain" / "asset.json").read_text())
    assert all(torch.equal(a.z, b.z) for a, b in zip(simulate_states(plain, 8, progress=False)[1], single))


@pytest.mark.parametrize("field, value, message", [
    ("z", [0.0, 1.0], "continuation.z must be"),
    ("frame", 7, "0 <= frame < from_frame"),
    ("t", "soon", "continuation.t must be a finite number"),
])
def test_a_bad_continuation_is_named(tiny_asset, tiny_scene, tmp_path, field, value, message):
    copy = tmp_path / "asset"
    _with_continuation(tiny_asset, tiny_scene, copy)
    meta = json.loads((copy / "asset.json").read_text())
    meta["continuation"][field] = value
    (copy / "asset.json").write_text(json.dumps(meta))
    with pytest.raises(AssetFormatError, match=message):
        load_asset(copy)
