"""Stage I training data: the template skinning network and its last-layer labels, the samples, the shards
(determinism, resume, Ray), the Dataset reader and the command's errors. Tiny sizes (2 objects × 2 draws,
32², 6 frames, 60 cubature points)."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import torch

from vid2sim.predictor.data import (
    Draw,
    TrainingDataConfig,
    make_training_data,
    object_specs,
    simulate_draw,
)
from vid2sim.predictor.dataset import IMAGENET_MEAN, IMAGENET_STD, TrainingData
from vid2sim.predictor.front_view import FrontCamera, closest_view
from vid2sim.predictor.solid import sample_solid
from vid2sim.predictor.template import (
    canonical_gauge,
    field_from_last_layer,
    fit_last_layer,
    load_template,
    procedural_shape_points,
    skinning_loss_value,
    template_info,
    trunk_features,
)

TINY = dict(truth="reduced", objects=2, draws_per_object=2, resolution=32, frames=6, points=600, cubature_points=60,
            contact_points=100)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def template():
    return load_template()


@pytest.fixture(scope="module")
def shape():
    """A procedural shape outside the template's pool (its seeds start at 10⁶), turned and canonical."""
    return procedural_shape_points(3, [0, 3], 3000)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("td") / "a"
    index = make_training_data(TrainingDataConfig(**TINY), out, workers=1, threads=1, progress=False)
    return out, index


# ---- the template and the label --------------------------------------------------------------------------

def test_shipped_template_is_trained_and_its_features_are_the_fields(template):
    info = template_info()
    assert info["config"]["shapes"] >= 16 and info["config"]["iterations"] >= 1000
    assert len(info["loss_curve_per_50_steps"]) >= 10
    g = torch.Generator().manual_seed(0)
    X = torch.rand(200, 3, generator=g) - 0.5
    w, dw = template.weights_and_gradients(X)
    A = template.last_layer.weight.detach()
    b = template.last_layer.bias.detach()
    _, w2, dw2 = trunk_features(template, X).weights(A, b)
    assert torch.allclose(w2, w, atol=1e-6) and torch.allclose(dw2, dw, atol=1e-5)


def test_last_layer_round_trip_and_determinism(template, shape):
    pts, vol = shape
    before = {k: v.clone() for k, v in template.state_dict().items()}
    label = fit_last_layer(template, pts, 20, seed=1, volume=vol)
    assert label.shape == (650,) and label.dtype == torch.float32 and bool(torch.isfinite(label).all())
    assert torch.equal(label, fit_last_layer(template, pts, 20, seed=1, volume=vol))
    field = field_from_last_layer(template, label)
    assert torch.equal(field.get_last_layer(), label)  # the field made from template + label holds the label
    for k, v in template.state_dict().items():  # the template is untouched, the hidden layers shared
        assert torch.equal(v, before[k])
        if not k.startswith("layers.9"):
            assert torch.equal(field.state_dict()[k], v)
    # the weights are the template's features times the label
    X = pts[:50]
    A, b = label[:640].reshape(10, 64), label[640:]
    assert torch.allclose(field.learned_weights(X), trunk_features(template, X).h @ A.T + b, atol=1e-6)


def test_canonical_gauge_removes_the_orthogonal_ambiguity(template, shape):
    pts, vol = shape
    label = fit_last_layer(template, pts, 0, volume=vol)
    g = torch.Generator().manual_seed(4)
    Q, _ = torch.linalg.qr(torch.randn(10, 10, generator=g, dtype=torch.float64))
    A, b = label[:640].reshape(10, 64).double(), label[640:].double()
    mixed = torch.cat([(Q @ A).reshape(-1), Q @ b]).float()
    # the data-free loss cannot tell them apart (orthogonality exactly, elastic up to the random draws) ...
    l1 = skinning_loss_value(field_from_last_layer(template, label), pts, vol, repeats=8)
    l2 = skinning_loss_value(field_from_last_layer(template, mixed), pts, vol, repeats=8)
    assert l2["orthogonality"] == pytest.approx(l1["orthogonality"], rel=1e-3)
    assert l2["elastic"] == pytest.approx(l1["elastic"], rel=0.1)
    assert not torch.allclose(mixed, label, atol=1e-3)
    # ... and the gauge maps both to the same label
    assert torch.allclose(canonical_gauge(template, mixed, pts), label, rtol=1e-3, atol=1e-5 * float(label.abs().max()))


def test_last_layer_fit_reaches_a_full_data_free_training(template, shape):
    from vid2sim.physics import SkinningField, SkinningTrainingConfig, train_skinning

    pts, vol = shape
    n = 100
    label = fit_last_layer(template, pts, n, volume=vol)
    fitted = skinning_loss_value(field_from_last_layer(template, label), pts, vol)
    full = SkinningField(10, seed=0)
    train_skinning(full, pts, SkinningTrainingConfig(iterations=n), progress=False, volume=vol)
    trained = skinning_loss_value(full, pts, vol)
    assert fitted["total"] <= 1.2 * trained["total"]
    # and near the best any 10 handles can do: the orthogonality term's sampling floor (1 − 1/10)/1000
    assert fitted["orthogonality"] < 1.5 * 0.9e-3
    # the shipped template's own held-out record: the fit within 20 % of full trainings of as many iterations
    for row in template_info()["held_out"]:
        assert row["last_layer_total"] <= 1.2 * row["full_total"]


# ---- objects, physics -----------------------------------------------------------------------------------

def test_solid_samples_match_the_mesh():
    from vid2sim.synthetic.shapes import make_procedural_object

    mesh = make_procedural_object(5)
    s = sample_solid(mesh.vertices, mesh.faces, num_points=2000, max_contact_points=300, seed=0)
    assert s.volume == pytest.approx(mesh.volume(), rel=0.01)
    tri = mesh.vertices.double()[mesh.faces]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1).sum()
    assert float(s.contact_areas.sum()) == pytest.approx(float(area), rel=1e-4)
    assert s.contact_points.shape == (300, 3) and s.points.shape == (2000, 3)
    lo, hi = mesh.vertices.min(0).values, mesh.vertices.max(0).values
    assert bool(((s.points >= lo - 1e-3) & (s.points <= hi + 1e-3)).all())
    with pytest.raises(ValueError, match="not closed"):
        sample_solid(mesh.vertices, mesh.faces[: len(mesh.faces) // 2], num_points=100)


def test_stiffer_material_deforms_less(template):
    from vid2sim.physics.cubature import sample_cubature
    from vid2sim.synthetic.shapes import make_procedural_object

    cfg = TrainingDataConfig(**TINY)
    mesh = make_procedural_object(11)
    s = sample_solid(mesh.vertices, mesh.faces, num_points=600, max_contact_points=100, seed=0)
    idx, w = sample_cubature(s.points, 60, volume=s.volume, seed=0)
    field = field_from_last_layer(template, fit_last_layer(template, s.points, 0, volume=s.volume))
    results = {}
    for E in (1e4, 1e6):
        draw = Draw(E, 0.3, 0.05, (0.0, 0.0, -1.0), (0.0, 0.0, 0.0))
        sim = simulate_draw(field, mesh.vertices, s.points[idx], w, s.contact_points, s.contact_areas, s.points.mean(0),
                            draw, cfg)
        assert sim.converged
        v = sim.vertices
        # it starts 5 cm above the floor, then reaches it
        assert float(v[0, :, 2].min()) == pytest.approx(cfg.floor_height + 0.05, abs=1e-5)
        assert float(v[:, :, 2].min()) < cfg.floor_height + 0.01
        height = v[:, :, 2].amax(1) - v[:, :, 2].amin(1)
        results[E] = (sim.max_strain, float(height.min() / height[0]))
    assert results[1e6][0] < 0.2 * results[1e4][0]  # peak Green strain
    assert results[1e6][1] > results[1e4][1]  # squashed less at the contact


# ---- the dataset: labels, determinism, resume, Ray, reader --------------------------------------------

def test_shards_hold_the_documented_samples(dataset):
    out, index = dataset
    assert index["complete"] and index["samples"] == 4 and index["shards_written"] == 2
    assert [s["file"] for s in index["shards"]] == ["object_000000.npz", "object_000001.npz"]
    assert index["last_run"]["samples_per_second"] > 0
    assert set(index["last_run"]["seconds_split"]) == {"object", "fit", "simulate", "render", "total"}
    seeds = [spec.source for spec in object_specs(TrainingDataConfig(**TINY))]
    for name, seed in zip(("object_000000.npz", "object_000001.npz"), seeds):
        with np.load(out / name) as z:
            assert z["video"].shape == (2, 6, 32, 32, 3) and z["video"].dtype == np.uint8
            assert z["last_layer"].shape == (650,) and z["last_layer"].dtype == np.float32
            assert np.all((z["log10_E"] >= 4) & (z["log10_E"] <= 6))
            assert np.all((z["nu"] >= 0.2) & (z["nu"] <= 0.49))
            assert np.all((z["drop_height"] >= 0.05) & (z["drop_height"] <= 0.3))
            assert np.all(np.abs(z["linear_velocity"][:, :2]) <= 0.2) and np.all(z["linear_velocity"][:, 2] <= 0)
            assert np.linalg.norm(z["angular_velocity"], axis=1).max() <= 2.0
            assert int(z["object_seed"]) == seed and seed >= 10**9
            R = z["rotation"].astype(np.float64)
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) == pytest.approx(1, abs=1e-5)
            assert z["converged"].all()
            video = z["video"].astype(np.float64)
            assert (video < 250).any(axis=-1).any() and video[:, :, 0, 0].min() == 255  # object on white
            assert np.abs(video[:, -1] - video[:, 0]).mean() > 1.0  # it moves


def test_two_runs_give_identical_shards_and_resume_remakes_only_what_is_missing(dataset, tmp_path):
    out, _ = dataset
    other = tmp_path / "b"
    other.mkdir()  # as a run killed while writing its first index.json leaves it: its temporary file alone
    (other / ".index.json.k1lled00.tmp").write_text('{"comp')
    make_training_data(TrainingDataConfig(**TINY), other, workers=2, threads=1, progress=False)
    assert not (other / ".index.json.k1lled00.tmp").exists()
    for name in ("object_000000.npz", "object_000001.npz"):
        assert _sha(out / name) == _sha(other / name)  # identical bytes, whatever the number of workers
    kept = (other / "object_000000.npz").stat().st_mtime_ns
    reference = _sha(other / "object_000001.npz")
    (other / "object_000001.npz").unlink()
    made = []
    index = make_training_data(TrainingDataConfig(**TINY), other, workers=1, threads=1, progress=False,
                               on_shard=made.append)
    assert made == ["object_000001.npz"] and index["complete"]
    assert (other / "object_000000.npz").stat().st_mtime_ns == kept
    assert _sha(other / "object_000001.npz") == reference
    with pytest.raises(ValueError, match="draws_per_object"):  # resuming with other settings is refused
        make_training_data(TrainingDataConfig(**{**TINY, "draws_per_object": 3}), other, workers=1, progress=False)
    with pytest.raises(ValueError, match="objects"):  # a dataset grows but never shrinks
        make_training_data(TrainingDataConfig(**{**TINY, "objects": TINY["objects"] - 1}), other, workers=1,
                           progress=False)
    # growing keeps every shard made and adds only the new object, identical to a dataset made at that size
    made.clear()
    grown = make_training_data(TrainingDataConfig(**{**TINY, "objects": TINY["objects"] + 1}), other, workers=1,
                               threads=1, progress=False, on_shard=made.append)
    assert made == [f"object_{TINY['objects']:06d}.npz"] and grown["complete"]
    assert grown["config"]["objects"] == TINY["objects"] + 1
    assert (other / "object_000000.npz").stat().st_mtime_ns == kept
    fresh = tmp_path / "c"
    make_training_data(TrainingDataConfig(**{**TINY, "objects": TINY["objects"] + 1}), fresh, workers=1,
                       threads=1, progress=False)
    assert _sha(fresh / made[0]) == _sha(other / made[0])


def test_ray_local_instance_gives_identical_shards(dataset, tmp_path, ray_slot):
    pytest.importorskip("ray")
    out, _ = dataset
    cfg = TrainingDataConfig(**{**TINY, "objects": 1})
    with ray_slot():
        index = make_training_data(cfg, tmp_path / "r", threads=1, ray_address="local", progress=False)
    assert index["complete"] and index["last_run"]["ray_address"] == "local"
    assert _sha(tmp_path / "r" / "object_000000.npz") == _sha(out / "object_000000.npz")


def test_dataset_reader_shapes_normalisation_and_split(dataset):
    out, _ = dataset
    data = TrainingData(out, "all")
    assert len(data) == 4
    video, targets = data[3]
    assert video.shape == (6, 3, 32, 32) and video.dtype == torch.float32
    assert set(targets) == {"log10_E", "nu", "last_layer"} and targets["last_layer"].shape == (650,)
    with np.load(out / "object_000001.npz") as z:
        assert float(targets["log10_E"]) == pytest.approx(float(z["log10_E"][1]))
        assert torch.equal(targets["last_layer"], torch.from_numpy(z["last_layer"]))
        raw = torch.from_numpy(z["video"][1]).permute(0, 3, 1, 2).float() / 255
    mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    assert torch.allclose(video, (raw - mean) / std, atol=1e-6)
    assert torch.allclose(TrainingData(out, "all", normalize="unit")[3][0], raw)
    train, val = TrainingData(out, "train", val_fraction=0.5), TrainingData(out, "val", val_fraction=0.5)
    assert len(train) + len(val) == 4 and not set(train.shards) & set(val.shards)  # by object
    assert train.shards == TrainingData(out, "train", val_fraction=0.5).shards  # deterministic
    stats = TrainingData(out, "all").label_statistics()
    assert stats["last_layer"]["mean"].shape == (650,) and 4 <= float(stats["log10_E"]["mean"]) <= 6
    with pytest.raises(ValueError, match="split"):
        TrainingData(out, "test")


def test_front_camera_is_the_scene_ring_camera_0_and_closest_view_finds_it():
    from vid2sim.splats.cameras import camera_ring

    cam = FrontCamera().camera(64)
    ring = camera_ring(6, 2.4, 20.0, 64, 64, fov_x_deg=40.0, target=(0.0, 0.0, -0.4))
    assert torch.allclose(cam.world_to_camera, ring[0].world_to_camera) and torch.allclose(cam.K, ring[0].K)
    shifted = camera_ring(5, 3.0, 25.0, 64, 64, target=(0.0, 0.0, -0.4), azimuth_offset_deg=150.0)
    assert closest_view(shifted) == 3  # azimuth 150 + 72·k: k = 3 is at 366° ≡ 6°
    assert math.isclose(float(FrontCamera().direction().norm()), 1.0)


@pytest.mark.parametrize("extra, message", [
    (["--objects", "0"], "--objects must be >= 1"),
    (["--objects", "1", "--resolution", "4"], "--resolution must be an integer >= 8"),
    (["--objects", "1", "--draws", "0"], "--draws must be an integer >= 1"),
    (["--objects", "1", "--mesh", "no_such_mesh.obj"], "--mesh no_such_mesh.obj: no such file"),
    (["--objects", "1", "--workers", "0"], "--workers must be >= 1"),
    (["--objects", "1", "--threads", "0"], "--threads must be >= 1"),
])
def test_bad_options_are_named(tmp_path, capsys, extra, message):
    from vid2sim.cli import main

    assert main(["make-training-data", str(tmp_path / "out"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_missing_ray_is_a_clear_error(tmp_path, capsys, monkeypatch):
    import sys

    from vid2sim.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    assert main(["make-training-data", str(tmp_path / "out"), "--objects", "1", "--ray-address", "local"]) == 2
    assert 'pip install "vid2sim[ray]"' in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_index_records_the_config_and_template(dataset):
    out, index = dataset
    on_disk = json.loads((out / "index.json").read_text())
    assert on_disk["config"] == TrainingDataConfig(**TINY).to_dict()
    assert TrainingDataConfig.from_dict(on_disk["config"]) == TrainingDataConfig(**TINY)
    from vid2sim.predictor.template import TEMPLATE_PATH

    assert on_disk["template_sha256"] == hashlib.sha256(TEMPLATE_PATH.read_bytes()).hexdigest()
    assert on_disk["stats"]["converged_fraction"] == 1.0
