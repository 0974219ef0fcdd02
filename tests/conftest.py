"""Shared pytest setup: tests marked ``cuda`` skip cleanly on machines without a CUDA GPU; tests marked
``slow`` (end to end: reconstruction, suites, the demo, scene generation — and every test using the shared
tiny scene or asset) are left out by the quick check ``python -m pytest -m "not slow"``.

On a GPU machine, ``python -m pytest -m cuda`` runs exactly the GPU checks.
"""

import os
import shutil
from pathlib import Path

import pytest
import torch


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject.toml's default): one worker per core and one more, at most 8 (each holds about
    1.5 GB). The extra one keeps the cores busy while another waits on a child process, a Ray start, a file lock
    or the disk; each worker still gets one torch thread (:func:`pytest_configure`). On 2 cores, the tests of `a466679`:
    16.5 min with two workers, 16.0 with three; 15.1 once local Ray instances took turns (`4334169`), 14.8 and 15.5
    with the slowest files first (`376da9f`)."""
    cores = os.cpu_count() or 1
    return max(1, min(8, cores + 1))


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``-n``, pyproject.toml's default), share the cores among the workers: each worker's
    torch gets cores / workers threads (at least one), so the workers do not fight over the cores."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(workers)))
    # Ray starts its worker processes at niceness 15 (its `worker_niceness`), so beside the other pytest workers
    # (niceness 0) a Ray task got a few per cent of a core: in the run of 7b1528c, test_bench_suite's one-scene
    # Ray test took 396 s against 28 s alone, the longest test of the suite. The tests' local instances (and
    # those the CLI tests start in child processes, which inherit this) run their workers at the tests' niceness.
    os.environ.setdefault("RAY_worker_niceness", "0")


#: seconds the slowest test files took on two cores (summed over their tests, `--durations`, at `2adb4ca`, on a
#: machine about 1.4× slower than the one of the README's suite time): a scheduling hint only. They are handed to
#: the pytest-xdist workers first, longest first, and the many short files after them fill the end evenly; xdist's
#: own order (by test count) left a long file with few tests to run alone at the end. Out-of-date numbers cost
#: minutes, not correctness.
SLOWEST_FILES = {
    "test_pipeline_reconstruct.py": 268, "test_bench_identify.py": 210, "test_joint_gauss_newton.py": 202,
    "test_bench_suite.py": 186, "test_simulator.py": 107, "test_synthetic.py": 100, "test_predictor_fem_data.py": 91,
    "test_devices.py": 90, "test_identification.py": 86, "test_bench_ablation.py": 83, "test_fuzz.py": 82,
    "test_bench_speed.py": 75, "test_pipeline_joint.py": 69, "test_initial_state.py": 66,
    "test_pipeline_stiffness.py": 59, "test_modes.py": 57, "test_hull_track.py": 57, "test_capture_sfm.py": 55,
    "test_predictor_data.py": 53, "test_fused.py": 52, "test_skinning_modal.py": 52, "test_capture.py": 51,
    "test_demo.py": 50, "test_cli_fit.py": 38,
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # the slowest files first (pyproject.toml's --no-loadscope-reorder keeps this order); a stable sort keeps each
    # file's own order and the rest's
    items.sort(key=lambda item: -SLOWEST_FILES.get(item.path.name, 0))
    for item in items:  # end-to-end tests on the shared reconstructed scene are slow (`-m "not slow"` skips them)
        if {"tiny_scene", "tiny_asset"} & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (on one, `python -m pytest -m cuda` runs these)")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)


@pytest.fixture
def one_torch_thread():
    """Run the test with one torch thread (results of the data and training code are reproducible per thread
    count), restoring the previous count afterwards."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def tiny_training_data(tmp_path_factory):
    """A real ``make-training-data`` folder: 5 objects x 2 draws, 4 frames of 16x16 (a few seconds)."""
    from vid2sim.predictor.data import TrainingDataConfig, make_training_data

    out = tmp_path_factory.mktemp("s1data") / "data"
    cfg = TrainingDataConfig(truth="reduced", objects=5, draws_per_object=2, resolution=16, frames=4, points=600,
                             cubature_points=60, contact_points=100)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        make_training_data(cfg, out, workers=1, threads=1, progress=False)
    finally:
        torch.set_num_threads(old)
    return out


# --- a tiny synthetic scene and its reconstructed asset, shared by the pipeline, simulate, export and report
# tests (built once per test session: about half a minute on two cores).

def _tiny_reconstruct_config():
    """The demo's toy sizes (``vid2sim demo --size tiny``) on the defaults; the stiffness calibration is off (it
    is tested on its own)."""
    from vid2sim.apps.demo import TINY
    from vid2sim.reconstruct.config import ReconstructConfig
    from vid2sim.runtime import config as configs

    return configs.merge(ReconstructConfig(), TINY)


def fewer_fit_iterations(config):
    """``config`` (a ReconstructConfig, changed in place and returned) with the stages that tests of bookkeeping do
    not judge fitted at fewer iterations: Gaussians 10, appearance 2, motion appearance 2, skinning 4."""
    config.gaussians.iterations, config.appearance.iterations, config.motion_appearance.iterations = 10, 2, 2
    config.networks.skinning_iterations = 4
    return config


@pytest.fixture
def tiny_config():
    """A factory of the tiny ReconstructConfig (each call a fresh, mutable copy)."""
    return _tiny_reconstruct_config


def _run_lock(tmp_path_factory, name: str):
    """A file lock that every pytest-xdist worker of this run shares (in the run's common temporary folder), or
    None outside pytest-xdist (one process: nothing to share)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return None
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp().parent / "shared"
    root.mkdir(exist_ok=True)
    return FileLock(str(root / f"{name}.lock"))


def _built_once(tmp_path_factory, name: str, build) -> Path:
    """``build(folder)`` (a new folder → the path it made) once per test run: under pytest-xdist the workers share
    one build in the run's common temporary folder, the first to need it making it under a file lock while the
    others wait (the tiny asset took about 40 s of each worker on two cores). Its users only read it (those that
    write copy it first), as they did within one worker."""
    lock = _run_lock(tmp_path_factory, name)
    if lock is None:
        return build(tmp_path_factory.mktemp(name))
    root = Path(lock.lock_file).parent
    done = root / f"{name}.done"
    with lock:
        if not done.is_file():
            folder = root / name
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            done.write_text(str(build(folder)))
    return Path(done.read_text())


@pytest.fixture(scope="session")
def ray_slot(tmp_path_factory):
    """A context manager factory: ``with ray_slot():`` holds the run's one slot for a local Ray instance. Under
    pytest-xdist the workers take it in turn (a file lock in the run's common temporary folder): two local
    instances side by side, each with its own worker processes, beside a third pytest worker oversubscribed two
    cores several times over (a 11 s Ray test took 100 s). A worker waiting for the slot leaves the cores to the
    others."""
    from contextlib import nullcontext

    lock = _run_lock(tmp_path_factory, "ray")
    return nullcontext if lock is None else lambda: lock


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """A 4-view (1 held out), 40x40, 6-frame synthetic drop scene folder.

    Its tet mesh is frozen (``tests/data/tiny_scene_tets.npz``, fTetWild's mesh of the same seed-1 surface, made
    once): fTetWild's tets differ from run to run even on one thread, and the tests built on this scene (bounds
    on the reconstruction and on the asset's rollout) would otherwise vary with them (two flaky bounds were found
    that way)."""
    from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene

    tets = Path(__file__).parent / "data" / "tiny_scene_tets.npz"
    config = SyntheticSceneConfig.preset("small", seed=1, frames=6, observed_frames=5, resolution=40, views=4,
                                         held_out_views=1, substeps=4, tet_mesh=str(tets))
    return _built_once(tmp_path_factory, "tiny_scene", lambda folder: make_scene(config, folder / "drop",
                                                                                  progress=False))


@pytest.fixture(scope="session")
def tiny_asset(tiny_scene, tmp_path_factory):
    """The asset folder reconstructed from ``tiny_scene`` with the tiny config (masses matched to the voxels'
    moments, so that path is exercised too)."""

    from vid2sim.reconstruct.pipeline import reconstruct

    config = _tiny_reconstruct_config()
    config.simulator.mass = "moments"
    return _built_once(tmp_path_factory, "tiny_asset", lambda folder: reconstruct(tiny_scene, folder / "asset", config,
                                                                                  progress=False))


def box_points(n: int, seed: int, size=(0.6, 0.4, 0.6), dtype=torch.float64) -> torch.Tensor:
    """(n, 3) points uniform in a centred box of the given proportions, half its diagonal 0.5 (canonical)."""
    g = torch.Generator().manual_seed(seed)
    s = torch.tensor(size, dtype=torch.float64)
    s = s * (0.5 / float(s.norm() / 2))
    return ((torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * s).to(dtype)


@pytest.fixture(scope="module")
def trained_field():
    """A small data-free-trained skinning field (4 learned handles) on a box, float64, and its points."""
    from vid2sim.physics import SkinningField, SkinningTrainingConfig, train_skinning

    torch.manual_seed(0)
    pts = box_points(1500, 0)
    field = SkinningField(num_handles=4, seed=0).double()
    train_skinning(field, pts, SkinningTrainingConfig(iterations=150, points_per_step=500, batch_size=4, seed=0),
                   progress=False)
    for p in field.parameters():
        p.requires_grad_(False)
    return field, pts


class NoDeviceWaits:
    """A dispatch mode that raises on every aten operation that makes the host wait for the device on a GPU:
    reading a value (``.item()``, ``bool``, ``float``, ``int`` go through ``_local_scalar_dense``) or an output
    whose shape depends on values (``nonzero``, boolean-mask indexing, ``unique``). Code run under it on the CPU
    can be captured as a CUDA graph as far as waiting goes (vid2sim.runtime.training)."""

    WAITING = ("_local_scalar_dense", "nonzero", "masked_select", "_unique", "unique_dim", "_unique2",
               "unique_consecutive")

    def __enter__(self):
        from torch.utils._python_dispatch import TorchDispatchMode

        waiting = self.WAITING

        class _Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                name = func.__name__.split(".")[0]
                masks = name in ("index", "index_put", "index_put_") and any(
                    isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ()))
                if name in waiting or masks:
                    raise AssertionError(f"{func.__name__}{' with a boolean mask' if masks else ''} waits for the "
                                         "device")
                return func(*args, **(kwargs or {}))

        self._mode = _Mode()
        self._mode.__enter__()
        return self

    def __exit__(self, *exc):
        return self._mode.__exit__(*exc)


@pytest.fixture
def no_device_waits():
    """:class:`NoDeviceWaits`, to be used as ``with no_device_waits: ...``."""
    return NoDeviceWaits()
