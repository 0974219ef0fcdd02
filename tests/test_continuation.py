"""The continuation (vid2sim.reconstruct.stages.continuation): the state at the end of the observed clip fitted to
its last frames, stored in the asset, and the captured drop going on from it."""

import json
import shutil

import pytest
import torch

from vid2sim.asset import load_asset
from vid2sim.asset.folder import AssetFormatError
from vid2sim.asset.motion import GaussianRig, simulate_states, simulated_centre_of_mass
from vid2sim.physics.rigid_motion import rigidly_moved
from vid2sim.physics.solver import SimState
from vid2sim.reconstruct.clip import Observations, render_states
from vid2sim.reconstruct.stages.continuation import fit_continuation
from vid2sim.scene.reading import load_scene

TRUE = dict(rotation=[0.0, 0.1, -0.06], translation=[0.03, -0.02, 0.015], linear=[0.3, 0.0, -0.2],
            angular=[0.0, 1.5, 0.8])


def test_the_fit_finds_a_moved_end_state_from_its_images(tiny_asset, tiny_scene, one_torch_thread):
    """Images of the asset's own drop, its state at the window's first frame moved rigidly: the fit from the
    unmoved state puts the body where the moved one is, on both of the window's frames, and the loss falls."""
    asset, scene = load_asset(tiny_asset), load_scene(tiny_scene)
    sim, states = simulate_states(asset, 5, progress=False, continued=False)
    anchor = 3
    centre = [float(x) for x in simulated_centre_of_mass(sim, [states[anchor]])[0]]
    truth_start = rigidly_moved(states[anchor], centre=centre, **TRUE)
    with torch.no_grad():
        truth = states[:anchor] + [truth_start] + sim.rollout(truth_start, 1)
    rig = GaussianRig(sim, asset.gaussians, asset.shading)
    views = list(scene.config.observed_views)
    cameras = [scene.cameras[v] for v in views]
    blank = Observations(torch.zeros(len(views), 5, *scene.images.shape[2:4], 3), cameras)
    images = render_states(rig, truth, blank, range(len(views))).transpose(0, 1)  # (V, T, H, W, 3)
    record = fit_continuation(sim, rig, Observations(images, cameras), states[anchor], anchor, iterations=8)
    assert record["frame"] == anchor and record["from_frame"] == 5
    assert record["fit"]["loss"] < 0.05 * record["fit"]["loss_before"]
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


def test_the_captured_drop_goes_on_from_the_continuation(tiny_asset, tmp_path):
    """The tiny asset has a continuation (the stage runs by default); the frames before its ``from_frame`` are the
    one rollout from frame 0, those after it the rollout from its state; an asset without it is one rollout."""
    asset = load_asset(tiny_asset)
    c = asset.continuation
    assert c is not None and c["from_frame"] == 5 and c["frame"] == 3
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
    copy = tmp_path / "asset"
    shutil.copytree(tiny_asset, copy)
    meta = json.loads((copy / "asset.json").read_text())
    del meta["continuation"]
    (copy / "asset.json").write_text(json.dumps(meta))
    plain = load_asset(copy)
    assert plain.continuation is None
    assert all(torch.equal(a.z, b.z) for a, b in zip(simulate_states(plain, 8, progress=False)[1], single))


@pytest.mark.parametrize("field, value, message", [
    ("z", [0.0, 1.0], "continuation.z must be"),
    ("frame", 7, "0 <= frame < from_frame"),
    ("t", "soon", "continuation.t must be a finite number"),
])
def test_a_bad_continuation_is_named(tiny_asset, tmp_path, field, value, message):
    copy = tmp_path / "asset"
    shutil.copytree(tiny_asset, copy)
    meta = json.loads((copy / "asset.json").read_text())
    meta["continuation"][field] = value
    (copy / "asset.json").write_text(json.dumps(meta))
    with pytest.raises(AssetFormatError, match=message):
        load_asset(copy)
