"""Synthetic scenes: `vid2sim make-scene` / `make-benchmark` end to end, checked against the FEM ground truth.

One small scene (the ``small`` preset at 48×48) is generated through the command line and shared; the
checks compare what was rendered with an independent projection of the FEM tet vertices, and the
trajectory with the floor. Generation is deterministic once the tet mesh is fixed (fTetWild itself is not
reproducible), which the `--tet-mesh` reuse tests.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from vid2sim.cli import main
from vid2sim.scene.reading import load_scene
from vid2sim.synthetic.fem import FEMResult
from vid2sim.synthetic.scenes import (
    BENCHMARK_E_RANGE,
    BENCHMARK_NU_RANGE,
    SyntheticSceneConfig,
    benchmark_parameters,
    load_tet_mesh,
    make_benchmark,
    make_scene,
)

pytestmark = pytest.mark.slow  # end to end: scene generation, reconstruction, suites

RES = 48
FLOOR = -0.7


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synthetic") / "scene"
    rc = main(["make-scene", str(out), "--preset", "small", "--seed", "3", "--resolution", str(RES), "--quiet"])
    assert rc == 0
    return out


def _project(world_to_camera: torch.Tensor, K: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Pinhole projection written out here (independent of Camera.project): (N, 3) → (N, 2) pixels."""
    cam = points.double() @ world_to_camera[:3, :3].double().T + world_to_camera[:3, 3].double()
    K = K.double()
    return torch.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], 1)


def test_small_scene_folder_loads_with_the_ground_truth(small_scene):
    scene = load_scene(small_scene)
    assert scene.images.shape == (6, 24, RES, RES, 3) and scene.masks.shape == (6, 24, RES, RES)
    assert scene.config.observed_views == [0, 2, 3, 5] and scene.config.held_out_views == [1, 4]  # novel views
    assert scene.config.observed_frames == list(range(16)) and scene.config.held_out_frames == list(range(16, 24))
    assert scene.config.dt == pytest.approx(0.05) and scene.config.floor_height == pytest.approx(FLOOR)
    assert tuple(scene.config.gravity) == pytest.approx((0.0, 0.0, -9.8))
    meta = scene.config.metadata
    assert (meta["E"], meta["nu"], meta["density"], meta["material"], meta["seed"]) == (1e5, 0.3, 1000.0,
                                                                                         "neo_hookean", 3)
    fem = FEMResult.load(small_scene / "fem_result.npz")
    assert fem.trajectory.shape[0] == 24
    assert (fem.config.youngs_modulus, fem.config.poisson_ratio, fem.config.density) == (1e5, 0.3, 1000.0)
    tet = scene.extras["tet_trajectory"]
    torch.testing.assert_close(tet["vertices"], fem.trajectory.float())
    assert torch.equal(tet["tets"].long(), fem.tets.long())
    config = SyntheticSceneConfig.from_json(small_scene / "synthetic.json")
    assert config == SyntheticSceneConfig.preset("small", seed=3, resolution=RES)
    # the object is seen on every view and frame, on a white background
    coverage = scene.masks.mean(dim=(2, 3))
    assert bool((coverage > 0.01).all()) and bool((coverage < 0.6).all())
    background = scene.masks < 1e-3
    assert float(scene.images[background].min()) > 0.99


def test_object_is_rendered_where_the_fem_puts_it(small_scene):
    """The mask's bounding box equals the projected bounding box of the FEM tet vertices (within ~1 px)."""
    scene = load_scene(small_scene)
    fem = FEMResult.load(small_scene / "fem_result.npz")
    boundary = torch.unique(torch.as_tensor(_boundary_vertices(fem.tets)))
    worst = 0.0
    for v, cam in enumerate(scene.cameras):
        for t in (0, 5, 12, 23):
            uv = _project(cam.world_to_camera, cam.K, fem.trajectory[t][boundary])
            mask = scene.masks[v, t] > 0.5
            rows = torch.nonzero(mask.any(1)).flatten()
            cols = torch.nonzero(mask.any(0)).flatten()
            # pixel i covers [i, i + 1): a fully covered pixel range [c0, c1] spans [c0, c1 + 1]
            box_mask = torch.tensor([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=torch.float64)
            box_fem = torch.cat([uv.min(0).values, uv.max(0).values])
            worst = max(worst, float((box_mask - box_fem).abs().max()))
    assert worst < 1.5, f"mask and projected FEM bounding boxes differ by {worst:.2f} px"


def _boundary_vertices(tets: torch.Tensor) -> np.ndarray:
    faces = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3).numpy()
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1].ravel()


def test_object_falls_and_ends_resting_on_the_floor(small_scene):
    fem = FEMResult.load(small_scene / "fem_result.npz")
    z = fem.trajectory[..., 2]
    assert float(z[0].min()) > FLOOR + 0.04  # dropped from above the floor (drop height >= 0.05 m)
    com = fem.trajectory.mean(1)
    assert float(com[-1, 2]) < float(com[0, 2]) - 0.04
    # last frames: touching the floor, hardly penetrating it, the centre no higher than the object's half size
    last = z[-4:].min(1).values
    assert bool((last > FLOOR - 0.01).all()) and bool((last < FLOOR + 0.03).all()), last
    half_diagonal = 0.5 * float((fem.rest_vertices.max(0).values - fem.rest_vertices.min(0).values).norm())
    assert float(com[-1, 2]) - FLOOR < half_diagonal
    assert fem.max_penetration < 0.01 and float(fem.min_det.min()) > 0


def test_reusing_the_tet_mesh_reproduces_the_scene(small_scene, tmp_path):
    """Same settings + the same tet mesh → identical files; and the first frames of the original FEM run."""
    config = SyntheticSceneConfig.preset(
        "small",
        seed=3,
        frames=3,
        observed_frames=2,
        resolution=32,
        views=2,
        held_out_views=0,
        tet_mesh=str(small_scene / "fem_result.npz"),
    )
    a = make_scene(config, tmp_path / "a", progress=False)
    b = make_scene(config, tmp_path / "b", progress=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        if rel.name != "fem_result.npz":  # holds the wall time
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    fa, fb = FEMResult.load(a / "fem_result.npz"), FEMResult.load(b / "fem_result.npz")
    assert torch.equal(fa.trajectory, fb.trajectory) and torch.equal(fa.velocities, fb.velocities)
    original = FEMResult.load(small_scene / "fem_result.npz")
    assert torch.equal(fa.trajectory, original.trajectory[:3])


def test_failure_leaves_nothing_behind(small_scene, tmp_path, monkeypatch):
    def broken_save(self, path):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(FEMResult, "save", broken_save)
    config = SyntheticSceneConfig.preset(
        "small",
        seed=3,
        frames=2,
        observed_frames=1,
        resolution=16,
        views=1,
        held_out_views=0,
        tet_mesh=str(small_scene / "fem_result.npz"),
    )
    with pytest.raises(OSError, match="disk full"):
        make_scene(config, tmp_path / "s", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_tet_mesh_of_another_object_is_refused(small_scene, tmp_path):
    config = SyntheticSceneConfig.preset("small", seed=4, frames=2, observed_frames=1,
                                         tet_mesh=str(small_scene / "fem_result.npz"))
    with pytest.raises(ValueError, match="does not fit the tet mesh"):
        make_scene(config, tmp_path / "s", progress=False)
    assert not (tmp_path / "s").exists()
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        load_tet_mesh(tmp_path / "bad.npz")


def test_user_mesh_scene(tmp_path):
    from vid2sim.synthetic.meshes import save_obj
    from vid2sim.synthetic.shapes import make_procedural_object

    mesh_file = save_obj(make_procedural_object(11), tmp_path / "mesh" / "thing.obj")
    out = tmp_path / "scene"
    assert main(["make-scene", str(out), "--mesh", str(mesh_file), "--preset", "small", "--quiet", "--E", "2e5",
                 "--drop-height", "0.1", "--frames", "2", "--observed-frames", "1", "--resolution", "24",
                 "--views", "1", "--held-out-views", "0", "--substeps", "2"]) == 0
    scene = load_scene(out)
    assert scene.config.metadata["object"] == "thing.obj" and scene.config.metadata["E"] == 2e5
    fem = FEMResult.load(out / "fem_result.npz")
    assert float(fem.trajectory[0, :, 2].min()) == pytest.approx(FLOOR + 0.1, abs=1e-9)
    assert float(scene.masks.sum()) > 10


@pytest.mark.parametrize("args, message", [
    (["--mesh", "/nonexistent/bunny.obj"], "/nonexistent/bunny.obj"),
    (["--E", "0"], "E"),
    (["--E", "-5"], "E"),
    (["--nu", "0.5"], "0.5"),
    (["--nu", "-1.2"], "-1.2"),
    (["--material", "plasticine"], "plasticine"),
    (["--resolution", "0"], "--resolution"),  # the flag typed, not the config field
    (["--frames", "10", "--observed-frames", "12"], "--observed-frames (12)"),
    (["--views", "2", "--held-out-views", "2"], "--held-out-views"),
    (["--views", "0"], "--views must be an integer >= 1"),  # the flag that is wrong, not its consequence
    (["--resolution", "100000"], "--resolution must be at most 4096"),  # before the FEM runs
    (["--resolution", "4000"], "GiB of images"),
])
def test_bad_options_are_clean_errors(tmp_path, capsys, args, message):
    out = tmp_path / "scene"
    assert main(["make-scene", str(out), "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("vid2sim make-scene: error:") and message in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_existing_non_empty_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["make-scene", str(out), "--preset", "small", "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["make-scene", str(out), "--preset", "small", "--quiet", "--overwrite"]) == 2
    assert "not a scene folder" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["scene"] and (out / "notes.txt").read_text() == "mine"


def test_benchmark_parameters_are_deterministic_and_in_range():
    params = benchmark_parameters(400, seed=7)
    assert params == benchmark_parameters(400, seed=7)
    assert params[:5] == benchmark_parameters(5, seed=7)  # scene i does not depend on N
    assert params != benchmark_parameters(400, seed=8)
    E = np.array([p["youngs_modulus"] for p in params])
    nu = np.array([p["poisson_ratio"] for p in params])
    assert E.min() >= BENCHMARK_E_RANGE[0] and E.max() <= BENCHMARK_E_RANGE[1]
    assert nu.min() >= BENCHMARK_NU_RANGE[0] and nu.max() <= 0.49
    # log-uniform: log10 E uniform on [4, 6] (mean 5, sd 2/sqrt(12)); each decade holds about half
    log_e = np.log10(E)
    assert abs(log_e.mean() - 5.0) < 0.1 and abs(log_e.std() - 2 / math.sqrt(12)) < 0.06
    assert 0.4 < np.mean(log_e < 5.0) < 0.6
    assert abs(np.mean(nu) - 0.35) < 0.02
    assert len({p["seed"] for p in params}) == 400
    with pytest.raises(ValueError, match="number of scenes"):
        benchmark_parameters(0)


TINY = ["--frames", "3", "--observed-frames", "2", "--resolution", "24", "--views", "2", "--held-out-views", "1",
        "--substeps", "4", "--element-order", "1"]


def test_make_benchmark_writes_an_index_and_resumes(tmp_path, capsys):
    root = tmp_path / "bench"
    root.mkdir()  # as a run killed while writing its first index.json leaves it: its temporary file alone
    (root / ".index.json.k1lled00.tmp").write_text('{"comp')
    assert main(["make-benchmark", str(root), "--n", "1", "--preset", "small", "--seed", "5", "--quiet", *TINY]) == 0
    assert not (root / ".index.json.k1lled00.tmp").exists()
    index = json.loads((root / "index.json").read_text())
    assert index["complete"] and [s["name"] for s in index["scenes"]] == ["scene_000"]
    stamps = {p: os.stat(root / p / "fem_result.npz").st_mtime_ns for p in ("scene_000",)}
    # resume with a larger N: the finished scene is kept untouched, only scene_001 is made
    assert main(["make-benchmark", str(root), "--n", "2", "--preset", "small", "--seed", "5", "--quiet", *TINY]) == 0
    assert {p: os.stat(root / p / "fem_result.npz").st_mtime_ns for p in stamps} == stamps
    index = json.loads((root / "index.json").read_text())
    expected = benchmark_parameters(2, seed=5)
    assert index["complete"] and [s["name"] for s in index["scenes"]] == ["scene_000", "scene_001"]
    for entry, p in zip(index["scenes"], expected):
        assert (entry["seed"], entry["E"], entry["nu"]) == (p["seed"], p["youngs_modulus"], p["poisson_ratio"])
        meta = load_scene(root / entry["name"]).config.metadata
        assert (meta["E"], meta["nu"], meta["seed"]) == (entry["E"], entry["nu"], entry["seed"])
    # other settings on the same folder are refused, before any work
    capsys.readouterr()
    assert main(["make-benchmark", str(root), "--n", "2", "--preset", "small", "--seed", "6", "--quiet", *TINY]) == 2
    assert "other settings" in capsys.readouterr().err


def test_make_benchmark_defaults_to_quadratic_tets_and_resumes_an_older_linear_suite(tmp_path, capsys):
    # a suite judges reconstructions, so its truth is converged in space by default: quadratic tets
    from vid2sim.synthetic.scenes import BENCHMARK_ELEMENT_ORDER

    assert BENCHMARK_ELEMENT_ORDER == 2
    root = tmp_path / "old"
    root.mkdir()
    # the index.json of a suite written when suites were linear by default: no element_order in its overrides
    flags = TINY[:-2]  # without --element-order
    header = {"preset": "small", "seed": 5, "n": 1, "complete": False, "scenes": [], "E_range": [1e4, 1e6],
              "nu_range": [0.2, 0.5], "overrides": {"frames": 3, "observed_frames": 2, "resolution": 24, "views": 2,
                                                   "held_out_views": 1, "substeps": 4}}
    (root / "index.json").write_text(json.dumps(header))
    # the default (quadratic) is refused on it before any work, naming the setting that differs
    assert main(["make-benchmark", str(root), "--n", "1", "--preset", "small", "--seed", "5", "--quiet", *flags]) == 2
    err = capsys.readouterr().err
    assert "other settings" in err and "'element_order': 1" in err and "'element_order': 2" in err
    assert not (root / "scene_000").exists()
    # asking for its linear tets resumes it
    assert main(["make-benchmark", str(root), "--n", "1", "--preset", "small", "--seed", "5", "--quiet", *TINY]) == 0
    index = json.loads((root / "index.json").read_text())
    assert index["complete"] and index["overrides"]["element_order"] == 1
    assert json.loads((root / "scene_000" / "synthetic.json").read_text())["element_order"] == 1


def test_a_suites_quadratic_tets_have_the_small_presets_size_at_every_preset():
    # quadratic tets of the full preset's size would take hours a scene; the small preset's are converged enough
    from vid2sim.synthetic.scenes import BENCHMARK_QUADRATIC_TETS, benchmark_overrides

    full = benchmark_overrides("full", {})
    assert full == {"element_order": 2, **BENCHMARK_QUADRATIC_TETS}
    config = SyntheticSceneConfig.preset("full", **full)
    assert (config.tet_edge_length, config.tet_envelope) == (0.08, 5e-3) and config.resolution == 448
    assert benchmark_overrides("small", {}) == {"element_order": 2}  # the small preset's own size: nothing to record
    assert benchmark_overrides("full", {"element_order": 1}) == {"element_order": 1}  # linear keeps the preset's
    assert benchmark_overrides("full", {"tet_edge_length": 0.05})["tet_edge_length"] == 0.05  # the caller's wins
    assert SyntheticSceneConfig.preset("full").tet_edge_length == 0.06  # a single scene keeps the preset's


def test_make_benchmark_refuses_a_foreign_folder(tmp_path):
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(FileExistsError, match="no index.json"):
        make_benchmark(1, tmp_path, progress=False)
    with pytest.raises(ValueError, match="cannot be overridden"):
        make_benchmark(1, tmp_path / "b", youngs_modulus=1e5, progress=False)
    assert not (tmp_path / "b").exists()
