"""Stage I training data with FEM drops (``make-training-data --truth fem``): the samples and their labels against
the FEM, the drop's physics, resuming after a kill (byte for byte, given the kept tet mesh), failures and errors.

Toy sizes: 2 objects × 2 draws, 8 frames of 16², 2 views, coarse linear tets (fTetWild edge 0.25 and envelope
0.01 of the diagonal: about 1 300 tets); one quadratic-tet drop checks the suite's settings. fTetWild runs twice
(the fixture); every other test reuses the tet meshes the fixture's shards store.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import torch

from vid2sim.meshing.tetra import TetMesh
from vid2sim.predictor import fem_truth
from vid2sim.predictor.data import (
    WORK,
    Draw,
    TrainingDataConfig,
    make_training_data,
    object_specs,
    prepare_object,
    render_draw,
    work_dir_of,
    write_npz,
)
from vid2sim.predictor.fem_truth import TET_MESH_FILE, FEMTruth, draw_file, simulate_fem_draw
from vid2sim.synthetic.fem import FEMSolverError

FEM_TINY = dict(truth="fem", objects=2, draws_per_object=2, resolution=16, frames=8, views=2, points=600,
                fem=FEMTruth(element_order=1, tet_edge_length=0.25, tet_envelope=1e-2))
NAMES = ("object_000000.npz", "object_000001.npz")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("fem") / "a"
    index = make_training_data(TrainingDataConfig(**FEM_TINY), out, workers=1, threads=1, progress=False)
    return out, index


def _stored_tet_mesh(shard) -> TetMesh:
    with np.load(shard) as z:
        return TetMesh(torch.from_numpy(z["tet_vertices"]), torch.from_numpy(z["tets"].astype(np.int64)))


def _killed_run(source, index: dict, out, objects: int) -> TrainingDataConfig:
    """``out`` as a run of the fixture's settings (with ``objects``) killed once fTetWild had meshed every object:
    its index.json and each object's work folder holding the tet mesh the fixture's shard stored."""
    config = TrainingDataConfig.from_dict({**index["config"], "objects": objects})
    out.mkdir()
    (out / "index.json").write_text(json.dumps({"format": index["format"], "config": config.to_dict(),
                                                "template_sha256": index["template_sha256"], "shards": []}))
    for spec in object_specs(config):
        tet = _stored_tet_mesh(source / spec.name)
        work = work_dir_of(out, spec)
        work.mkdir(parents=True)
        write_npz(work / TET_MESH_FILE, {"vertices": tet.vertices.numpy(), "tets": tet.tets.numpy()}, compress=False)
    return config


def _embedded(config: TrainingDataConfig, tet: TetMesh, index: int = 0):
    """The object's prepared mesh and its surface embedded in ``tet`` as the shard's maker embedded it."""
    from vid2sim.predictor.fem_truth import embed_surface

    prepared = prepare_object(config, object_specs(config)[index])
    return prepared, embed_surface(prepared.posed, tet, config)


# ---- the samples -----------------------------------------------------------------------------------------

def test_shards_hold_the_documented_samples(dataset):
    out, index = dataset
    assert index["complete"] and index["samples"] == 4 and [s["file"] for s in index["shards"]] == list(NAMES)
    assert index["config"]["truth"] == "fem" and index["config"]["fem"]["element_order"] == 1
    assert index["last_run"]["samples_made"] == 4 and index["last_run"]["median_sample_seconds"] > 0
    assert "tetrahedralize" in index["last_run"]["seconds_split"] and index["last_run"]["failed"] == []
    assert not (out / WORK).exists() or not any((out / WORK).iterdir())  # work folders go once shards are in
    lo, hi = (math.log10(e) for e in TrainingDataConfig(truth="fem").E_range)
    for name in NAMES:
        with np.load(out / name) as z:
            assert z["video"].shape == (2, 8, 16, 16, 3) and z["ring_video"].shape == (2, 1, 8, 16, 16, 3)
            assert z["last_layer"].shape == (650,) and z["tets"].shape[1] == 4 and z["tet_vertices"].dtype == np.float64
            assert z["surface"].shape[:2] == (2, 8) and z["surface"].dtype == np.float32
            assert np.all((z["log10_E"] >= lo) & (z["log10_E"] <= hi))
            assert np.all((z["nu"] >= 0.2) & (z["nu"] <= 0.49))
            assert np.all((z["damping_ratio"] >= 0.025) & (z["damping_ratio"] <= 0.1))
            assert z["converged"].all() and np.all(z["time_change_percent"] <= 1.0) and z["min_det_F"].min() > 0
            video = z["video"].astype(np.float64)
            assert video[:, :, 0, 0].min() == 255 and (video < 250).any()  # the object on white
            assert np.abs(video[:, -1] - video[:, 0]).mean() > 1.0  # it falls
            assert not np.array_equal(z["ring_video"][:, 0], z["video"])  # another view


def test_the_reader_serves_fem_shards(dataset):
    from vid2sim.predictor.dataset import TrainingData

    out, _ = dataset
    data = TrainingData(out, "all", normalize="unit")
    video, targets = data[1]
    assert len(data) == 4 and video.shape == (8, 3, 16, 16)
    with np.load(out / NAMES[0]) as z:
        assert float(targets["log10_E"]) == float(z["log10_E"][1])
        assert torch.equal(video, torch.from_numpy(z["video"][1]).permute(0, 3, 1, 2).float() / 255)


def test_a_video_is_the_fem_drop_of_its_labels(dataset):
    """Re-simulated from the shard alone (its tet mesh, labels and drop, as float32), draw 0 gives the stored
    surface and video: the labels are the material the FEM had (that E changes the drop: the next test). The
    stored surface renders the stored video again, bit for bit (other views can be rendered later)."""
    out, index = dataset
    config = TrainingDataConfig.from_dict(index["config"])
    tet = _stored_tet_mesh(out / NAMES[0])
    prepared, embedding = _embedded(config, tet)
    with np.load(out / NAMES[0]) as z:
        stored = z["video"][0].astype(np.float64)
        draw = Draw(10.0 ** float(z["log10_E"][0]), float(z["nu"][0]), float(z["drop_height"][0]),
                    tuple(map(float, z["linear_velocity"][0])), tuple(map(float, z["angular_velocity"][0])),
                    float(z["damping_ratio"][0]))
        stored_surface = torch.from_numpy(z["surface"][0])
    surface = simulate_fem_draw(tet, *embedding, draw, config).surface
    assert float((surface - stored_surface).abs().max()) < 1e-4  # float32 labels move it by far less than a pixel
    front = config.camera.ring(1, config.resolution)
    video = render_draw(prepared.mesh, surface, front, config.supersample)[0]
    assert np.abs(video.astype(np.float64) - stored).mean() < 0.05
    again = render_draw(prepared.mesh, stored_surface, front, config.supersample)[0]
    assert np.array_equal(again, stored.astype(np.uint8))  # the stored surface re-renders the video
    assert np.abs(stored[-1] - stored[0]).mean() > 1.0


def test_fem_drop_falls_freely_then_stiffer_deforms_less(dataset):
    """Before contact every surface point follows x0 + v t − ½ g t² (a spin-free drop); frame 0's lowest point
    is the drop height above the floor; at the contact E = 1e6 strains and squashes less than E = 1e4."""
    out, index = dataset
    config = TrainingDataConfig.from_dict(index["config"])
    tet = _stored_tet_mesh(out / NAMES[1])
    _, embedding = _embedded(config, tet, 1)
    v = (0.1, -0.05, -0.5)
    base = dict(poisson_ratio=0.3, drop_height=0.3, linear_velocity=v, angular_velocity=(0.0, 0.0, 0.0),
                damping_ratio=0.05)
    soft = simulate_fem_draw(tet, *embedding, Draw(youngs_modulus=1e4, **base), config)
    stiff = simulate_fem_draw(tet, *embedding, Draw(youngs_modulus=1e6, **base), config)
    x = soft.surface.double()
    assert float(x[0, :, 2].min()) == pytest.approx(config.floor_height + 0.3, abs=config.fem.tet_envelope)
    t = torch.arange(4, dtype=torch.float64) * config.dt  # contact at t ≈ 0.20 s: frames 0–3 are in the air
    ballistic = x[0] + t[:, None, None] * torch.tensor(v, dtype=torch.float64)
    ballistic[..., 2] -= 0.5 * 9.8 * t[:, None] ** 2
    h = config.dt / soft.substeps  # BDF2 starts with an implicit-Euler step: g h²/2 behind, then exact for g t²/2
    assert float((x[:4] - ballistic)[..., :2].abs().max()) < 1e-6
    assert float((x[:4] - ballistic)[..., 2].abs().max()) < 9.8 * h**2
    assert float(x[4:, :, 2].min()) > config.floor_height - 0.01  # the floor holds it
    assert stiff.max_strain < 0.5 * soft.max_strain and soft.max_strain > 0.1  # peaks at the contact point

    def least_height(surface: torch.Tensor) -> float:
        height = surface[..., 2].amax(1) - surface[..., 2].amin(1)
        return float(height.min() / height[0])

    assert least_height(stiff.surface) > least_height(soft.surface)
    assert stiff.substeps > soft.substeps  # a stiffer material needs finer steps to converge in time


def test_the_suite_settings_and_a_quadratic_drop_converged_in_time():
    """The default FEM truth is the suite's (quadratic tets of its size, its time tolerance); a quadratic-tet drop
    (a coarse box, for time) comes back converged in time, with the substeps the suite's check starts from."""
    from vid2sim.meshing.tetra import box_tet_mesh
    from vid2sim.physics.integrators import auto_substeps
    from vid2sim.synthetic.embedding import embed_points
    from vid2sim.synthetic.scenes import SyntheticSceneConfig, benchmark_overrides

    suite = SyntheticSceneConfig.preset("small", **benchmark_overrides("small", {}))
    config = TrainingDataConfig(truth="fem", frames=4)
    fem = config.fem
    assert (fem.element_order, fem.tet_edge_length, fem.tet_envelope, fem.time_tolerance) == (
        suite.element_order, suite.tet_edge_length, suite.tet_envelope, suite.time_tolerance) == (2, 0.08, 5e-3, 1.0)
    box = box_tet_mesh((0.6, 0.5, 0.4), (2, 2, 2), origin=(-0.3, -0.25, -0.2))
    corners = torch.tensor([[x, y, z] for x in (-0.3, 0.3) for y in (-0.25, 0.25) for z in (-0.2, 0.2)],
                           dtype=torch.float64)
    draw = Draw(1e5, 0.35, 0.05, (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 0.05)
    assert fem_truth.fem_config_of(draw, config).element_order == 2
    sim = simulate_fem_draw(box, *embed_points(corners, box.vertices, box.tets), draw, config)
    assert sim.time_change_percent <= 1.0 and sim.min_det > 0 and sim.max_strain > 1e-3  # it hit the floor
    assert sim.substeps >= 2 * max(4, auto_substeps(config.dt, 1e5, config.density, 1.0) // 2)
    assert sim.surface.shape == (4, 8, 3) and float(sim.surface[0, :, 2].min()) == pytest.approx(-0.65)


# ---- resuming, determinism, failures ---------------------------------------------------------------------

def test_a_killed_run_resumes_to_the_same_bytes(dataset, tmp_path, monkeypatch):
    """Killed after its first FEM draw, a run keeps that draw and the object's tet mesh; run again, it makes
    only the rest, and the shard is byte for byte the one an uninterrupted run with that mesh made (in a dataset
    of another size: an object's samples depend on its index alone)."""
    source, index = dataset
    out = tmp_path / "b"
    config = _killed_run(source, index, out, objects=1)
    real = fem_truth.simulate_fem_draw
    calls = []

    def killed_on_the_second_draw(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(fem_truth, "simulate_fem_draw", killed_on_the_second_draw)
    with pytest.raises(KeyboardInterrupt):
        make_training_data(config, out, workers=1, threads=1, progress=False)
    work = work_dir_of(out, object_specs(config)[0])
    assert sorted(p.name for p in work.iterdir()) == [draw_file(0), TET_MESH_FILE] and not (out / NAMES[0]).exists()
    monkeypatch.setattr(fem_truth, "simulate_fem_draw", real)
    index_b = make_training_data(config, out, workers=1, threads=1, progress=False)
    assert index_b["complete"] and index_b["last_run"]["samples_made"] == 1  # draw 0 was kept
    assert index_b["shards"][0]["seconds"]["draws_resumed"] == 1
    assert _sha(out / NAMES[0]) == _sha(source / NAMES[0])
    assert not work.exists()


def test_a_failing_object_is_recorded_and_the_others_still_run(dataset, tmp_path, monkeypatch):
    source, index = dataset
    out = tmp_path / "c"
    config = _killed_run(source, index, out, objects=2)
    real, first = fem_truth.simulate_fem_draw, _stored_tet_mesh(source / NAMES[0])

    def object_0_fails(tet, tet_index, bary, draw, config_):
        if torch.equal(tet.vertices, first.vertices):
            raise FEMSolverError("frame 3, substep 2/8: no descent direction")
        return real(tet, tet_index, bary, draw, config_)

    monkeypatch.setattr(fem_truth, "simulate_fem_draw", object_0_fails)
    with pytest.raises(FEMSolverError, match="object_000000.npz: 4 draws in a row failed"):
        make_training_data(config, out, workers=1, threads=1, progress=False)
    on_disk = json.loads((out / "index.json").read_text())
    assert [f["file"] for f in on_disk["last_run"]["failed"]] == [NAMES[0]]
    assert "no descent direction" in on_disk["last_run"]["failed"][0]["error"]
    assert (out / NAMES[1]).is_file() and _sha(out / NAMES[1]) == _sha(source / NAMES[1])
    assert (work_dir_of(out, object_specs(config)[0]) / TET_MESH_FILE).is_file()  # kept for the rerun


def test_the_command_names_a_failed_object_and_how_to_resume(tmp_path, monkeypatch, capsys):
    from vid2sim.cli import main

    def fails(*args, **kwargs):
        raise FEMSolverError("object_000003.npz: 4 draws in a row failed; last: frame 3: no descent direction")

    monkeypatch.setattr("vid2sim.cli.make_training_data.make_training_data", fails)
    assert main(["make-training-data", str(tmp_path / "out"), "--objects", "4", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "object_000003.npz: 4 draws in a row failed" in err and "run the command again to resume" in err
    assert len(err.splitlines()) == 1


def test_configs_resume_across_versions_and_truths_are_kept_apart(tmp_path):
    """An index.json written before the FEM truth (no ``truth``, one damping ratio) is the reduced truth's and
    resumes with it; asking another truth of a folder is refused, naming it."""
    reduced = TrainingDataConfig(truth="reduced", objects=1)
    old = {k: v for k, v in reduced.to_dict().items() if k not in ("truth", "views", "fem")}
    old["damping_ratio"] = 0.05
    assert TrainingDataConfig.from_dict(old) == reduced
    out = tmp_path / "old"
    out.mkdir()
    from vid2sim.predictor.data import FORMAT, file_sha256, template_path

    (out / "index.json").write_text(json.dumps({"format": FORMAT, "config": old, "shards": [],
                                                "template_sha256": file_sha256(template_path(reduced))}))
    with pytest.raises(ValueError, match="truth"):
        make_training_data(TrainingDataConfig(truth="fem", objects=1), out, workers=1, progress=False)
    assert TrainingDataConfig(truth="fem").draws_per_object == 2 and TrainingDataConfig(truth="reduced").views == 1


def test_bad_options_are_named(tmp_path, capsys):
    from vid2sim.cli import main

    assert main(["make-training-data", str(tmp_path / "out"), "--objects", "1", "--views", "0"]) == 2
    assert "--views must be an integer >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["make-training-data", str(tmp_path / "out"), "--objects", "1", "--truth", "cloth"])
    assert "argument --truth: invalid choice: 'cloth'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
