"""import-capture: calibration readers, undistortion, masks against a shadow, metres/gravity/floor from free flight,
the bad-input errors, and the scene folder it writes; without rendering, the free flight's choices (the flight
before the first contact, a centre robust to one view's mask, the scale's sigma) and the masks' object box.

One small capture twin of a rigid toss (6 cameras filming 192² PNG frames, imported at 96², 16 frames of which 10 in
free flight) is made once per module (``vid2sim.synthetic.capture.rigid_drop`` stands in for the FEM); each bad-input
test copies and breaks it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image
from scipy import ndimage

from vid2sim.cli import main
from vid2sim.scene.capture import CaptureError, CaptureImportConfig, import_capture
from vid2sim.scene.capture import masks as mk
from vid2sim.scene.capture.ballistic import fit_segments
from vid2sim.scene.capture.cameras import CaptureCamera, rigid
from vid2sim.scene.capture.colmap import colmap_cameras, read_colmap, write_colmap
from vid2sim.scene.capture.metric import MetricConfig, Track, solve_metric_frame, track_object
from vid2sim.scene.capture.nerfstudio import read_transforms, write_transforms
from vid2sim.scene.capture.undistort import distort_normalised, distortion_maps, make_undistortion, to_opencv_K

G = 9.8  # the synthetic world's gravity
SIZE = 96  # the scene's image size (the twin films at twice that)
FRAMES = 16


def _cameras() -> list[CaptureCamera]:
    rng = np.random.default_rng(3)
    cams = []
    for i, (model, dist) in enumerate([("PINHOLE", [0, 0, 0, 0, 0]), ("SIMPLE_RADIAL", [-0.12, 0, 0, 0, 0]),
                                       ("RADIAL", [-0.15, 0.04, 0, 0, 0]), ("OPENCV", [-0.1, 0.02, 4e-4, -3e-4, 0])]):
        q = rng.normal(size=3)
        theta = np.linalg.norm(q)
        k = q / theta
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx
        fy = 150.0 if model in ("OPENCV", "PINHOLE") else 140.0
        K = np.array([[140.0, 0, 64.3], [0, fy, 63.1], [0, 0, 1]])
        cams.append(CaptureCamera(f"cam{i}", 128, 128, K, dist, rigid(R, rng.normal(size=3)), model=model))
    return cams


def test_colmap_text_binary_and_nerfstudio_agree_with_the_cameras(tmp_path: Path) -> None:
    cams = _cameras()
    models = [c.model for c in cams]
    pts = np.random.default_rng(0).normal(size=(20, 3))
    write_colmap(cams, models, tmp_path / "text", binary=False, points=pts, visible=[[0, 1], [2, 3]] * 10)
    write_colmap(cams, models, tmp_path / "bin", binary=True, points=pts, visible=[[0, 1], [2, 3]] * 10)
    write_transforms(cams, tmp_path / "transforms.json")
    names = {c.name for c in cams}
    stem = lambda n: Path(n).stem if Path(n).stem in names else None  # noqa: E731
    text = read_colmap(tmp_path / "text")
    binary = read_colmap(tmp_path / "bin")
    assert not text.binary and binary.binary
    read = [colmap_cameras(text, stem), colmap_cameras(binary, stem), read_transforms(tmp_path / "transforms.json",
                                                                                        stem)[0]]
    for cam in cams:
        for got in read:
            g = got[cam.name]
            np.testing.assert_allclose(g.K, cam.K, atol=1e-9)
            np.testing.assert_allclose(g.distortion, cam.distortion, atol=1e-12)
            np.testing.assert_allclose(g.world_to_camera, cam.world_to_camera, atol=1e-9)
    for model in (text, binary):
        np.testing.assert_allclose(model.points.xyz, pts, atol=1e-12)
        assert [t.tolist() for t in model.points.tracks[:2]] == [[1, 2], [3, 4]]  # image ids = camera index + 1


def test_undistortion_round_trip_against_opencv() -> None:
    cam = _cameras()[3]
    xy = np.random.default_rng(1).uniform(-0.4, 0.4, (50, 2))
    ours = distort_normalised(xy, cam.distortion) @ cam.K[:2, :2].T + cam.K[:2, 2]
    cv, _ = cv2.projectPoints(np.c_[xy, np.ones(50)], np.zeros(3), np.zeros(3), to_opencv_K(cam.K), cam.distortion)
    np.testing.assert_allclose(ours, cv[:, 0] + 0.5, atol=1e-9)  # OpenCV's pixel centres are at 0
    # an image of smooth stripes on the pinhole camera, distorted by the lens, then undistorted, equals the stripes
    und = make_undistortion(cam)
    pin = und.camera

    def stripes(K: np.ndarray, size: int) -> np.ndarray:
        u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
        return (0.5 + 0.5 * np.sin(9 * x) * np.cos(7 * y)).astype(np.float32)

    wide = pin.K.copy()
    wide[:2, :2] *= 0.7  # a wider pinhole view to sample the distorted image from
    wide[0, 2] = wide[1, 2] = 128.0
    mx, my = distortion_maps(wide, cam)
    distorted = cv2.remap(stripes(wide, 256), mx, my, cv2.INTER_CUBIC)
    back = und(distorted)
    truth = stripes(pin.K, 128)
    assert np.abs(back - truth)[4:-4, 4:-4].mean() < 0.01
    assert not np.allclose(pin.K, cam.K)  # K changed with the undistortion


# ---- a small capture twin -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def twin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from vid2sim.splats.cameras import camera_ring
    from vid2sim.synthetic.capture import CaptureMotion, CaptureTwinConfig, rigid_drop, write_capture
    from vid2sim.synthetic.shapes import make_procedural_object

    torch.manual_seed(0)
    mesh = make_procedural_object(3)
    verts = rigid_drop(mesh.vertices.double().numpy(), FRAMES, 0.05, -0.7, 0.9, velocity=(0.1, -0.05, 0.5),
                       omega=(0.3, 0.5, 0.1), gravity=G)
    cams = camera_ring(6, 2.4, 20, SIZE, SIZE, 50, (0, 0, -0.1))
    motion = CaptureMotion(torch.as_tensor(verts, dtype=torch.float32), mesh.faces, mesh.uvs, mesh.texture, cams, 0.05,
                           -0.7, (0.0, 0.0, -G))
    out = tmp_path_factory.mktemp("capture") / "twin"
    return write_capture(motion, out, CaptureTwinConfig(seed=2, frames_format="frames", colmap_format="both",
                                                        resolution_scale=2))


@pytest.fixture(scope="module")
def imported(twin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("imported") / "scene"
    return import_capture(twin, out, CaptureImportConfig(threads=1, held_out_views=["c01"], downscale=2,
                                                         metric=MetricConfig(gravity=G)))


def test_scene_loads_and_keeps_everything(imported: Path) -> None:
    from vid2sim.scene.reading import load_scene

    scene = load_scene(imported)
    assert scene.images.shape[:3] == (6, FRAMES, SIZE) and scene.config.held_out_views == [1]
    assert scene.config.floor_height == 0.0 and scene.config.gravity == (0.0, 0.0, -G)
    meta = scene.config.metadata["capture"]
    for key in ("metres_per_unit", "gravity_direction_calibration", "floor_calibration", "calibration_to_scene"):
        assert key in meta["metric"]
    assert meta["metric"]["metres_per_unit"]["sigma"] > 0
    report = json.loads((imported / "capture_report.json").read_text())
    assert len(report["masks"]["c00"]["area_px"]) == FRAMES and len(report["masks"]["c00"]["confidence"]) == FRAMES
    # the background outside the masks is white
    m = scene.masks < 0.01
    assert float(scene.images[m].min()) > 0.99


def test_masks_follow_the_true_coverage_and_leave_the_shadow(twin: Path, imported: Path) -> None:
    from vid2sim.apps.bench.capture import _undistorted_alpha, import_figures
    from vid2sim.scene.reading import load_scene
    from vid2sim.synthetic.capture import read_truth

    figures = import_figures(twin, imported)
    assert figures["mask_iou"] > 0.93, figures
    truth, alpha = read_truth(twin)
    report = json.loads((imported / "capture_report.json").read_text())
    scene = load_scene(imported)
    far = 0.0
    area = 0.0
    for v, name in enumerate(report["cameras"]):
        true = _undistorted_alpha(alpha[v], truth["true_cameras_calibration"][name],
                                  np.array(report["undistortion"][name]["K"]), 2)
        for t in range(true.shape[0]):
            d = ndimage.distance_transform_edt(true[t] < 0.5)
            far += float(scene.masks[v, t].numpy()[d > 3].sum())
            area += float(true[t].sum())
    assert far / area < 0.01  # nothing beyond 3 px of the object: not the shadow on the floor


def test_metres_gravity_and_floor_are_recovered(twin: Path, imported: Path) -> None:
    from vid2sim.apps.bench.capture import import_figures

    f = import_figures(twin, imported)
    assert abs(f["scale_error"]) < 0.02, f
    assert f["gravity_error_deg"] < 1.0, f
    assert abs(f["floor_error_m"]) < 0.005, f
    assert f["free_flight_frames"] >= 8


def test_without_points_the_floor_comes_from_the_plates(twin: Path, tmp_path: Path) -> None:
    """nerfstudio calibration (no 3D points): the floor and its normal from the clean plates."""
    from vid2sim.apps.bench.capture import import_figures

    cap = tmp_path / "cap"
    shutil.copytree(twin, cap, ignore=shutil.ignore_patterns("colmap"))
    out = import_capture(cap, tmp_path / "scene", CaptureImportConfig(threads=1, downscale=2,
                                                                      metric=MetricConfig(gravity=G)))
    f = import_figures(cap, out)
    assert f["floor_source"] == "plates", f
    assert abs(f["scale_error"]) < 0.02 and f["gravity_error_deg"] < 1.0 and abs(f["floor_error_m"]) < 0.005, f


def test_without_plates_they_are_estimated(twin: Path, tmp_path: Path) -> None:
    """No clean plates: plates estimated from the video (the object moves clear of where it rests)."""
    from vid2sim.apps.bench.capture import import_figures

    cap = tmp_path / "cap"
    shutil.copytree(twin, cap, ignore=shutil.ignore_patterns("colmap", "background"))
    out = import_capture(cap, tmp_path / "scene", CaptureImportConfig(threads=1, downscale=2,
                                                                      metric=MetricConfig(gravity=G)))
    f = import_figures(cap, out)
    report = json.loads((out / "capture_report.json").read_text())
    assert report["masks"]["c00"]["source"] == "estimated plate"
    # weaker than with plates (docs/capture.md): the masks, hence the free flight, are noisier
    assert f["mask_iou"] > 0.85 and abs(f["scale_error"]) < 0.1 and f["gravity_error_deg"] < 2.0, f
    assert abs(f["floor_error_m"]) < 0.01, f


# ---- bad input: one line naming the camera and the file --------------------------------------------------------


def _broken(twin: Path, tmp_path: Path) -> Path:
    cap = tmp_path / "cap"
    shutil.copytree(twin, cap)
    return cap


def _error(cap: Path, tmp_path: Path, *extra: str, capsys: pytest.CaptureFixture) -> str:
    code = main(["import-capture", str(cap), str(tmp_path / "scene"), "--threads", "1", "--quiet", *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert not (tmp_path / "scene").exists()  # nothing half-written
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".scene")]
    return err


def test_unsynchronised_frame_counts(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    (cap / "frames" / "c03" / f"{FRAMES - 1:05d}.png").unlink()
    err = _error(cap, tmp_path, capsys=capsys)
    assert "camera 'c03'" in err and "frames/c03" in err and f"{FRAMES - 1} frames" in err


def test_moving_camera(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    plate = np.asarray(Image.open(cap / "background" / "c02.png"))
    Image.fromarray(np.roll(plate, (4, 3), axis=(0, 1))).save(cap / "background" / "c02.png")
    err = _error(cap, tmp_path, capsys=capsys)
    assert "camera 'c02'" in err and "background/c02.png" in err and "static background" in err


def test_no_free_flight_asks_for_scale_and_gravity(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    for cam in (cap / "frames").iterdir():  # the object resting all along: every frame is the last one
        last = sorted(cam.iterdir())[-1]
        for f in sorted(cam.iterdir())[:-1]:
            shutil.copy(last, f)
    err = _error(cap, tmp_path, capsys=capsys)
    assert "--scale" in err and "--gravity-axis" in err and str(cap) in err


def test_object_leaving_the_view(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    masks = cap / "masks" / "c04"
    masks.mkdir(parents=True)
    n = 2 * SIZE
    for t in range(FRAMES):
        m = np.zeros((n, n), np.uint8)
        m[n // 3 : n // 2, n // 3 : n // 2] = 255
        if t == 5:
            m[0 : n // 5, n // 3 : n // 2] = 255
        Image.fromarray(m).save(masks / f"{t:05d}.png")
    err = _error(cap, tmp_path, capsys=capsys)
    assert "camera 'c04'" in err and "border" in err and "frame 5" in err and "frames/c04" in err


def test_unknown_camera_model(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    for p in cap.glob("colmap/*.bin"):
        p.unlink()
    text = (cap / "colmap" / "cameras.txt").read_text().splitlines()
    parts = text[3].split()
    text[3] = " ".join([parts[0], "FISHEYE_624", *parts[2:]])
    (cap / "colmap" / "cameras.txt").write_text("\n".join(text) + "\n")
    err = _error(cap, tmp_path, capsys=capsys)
    assert "FISHEYE_624" in err and "colmap/cameras.txt" in err and "camera 1" in err


def test_calibration_names_matching_no_video(twin: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cap = _broken(twin, tmp_path)
    transforms = json.loads((cap / "transforms.json").read_text())
    transforms["frames"][2]["file_path"] = "background/left_cam.png"
    (cap / "transforms.json").write_text(json.dumps(transforms))
    err = _error(cap, tmp_path, "--calibration", "transforms", capsys=capsys)
    assert "left_cam" in err and "transforms.json" in err
    # and a camera the calibration lacks is named too
    transforms["frames"].pop(2)
    (cap / "transforms.json").write_text(json.dumps(transforms))
    err = _error(cap, tmp_path, "--calibration", "transforms", capsys=capsys)
    assert "camera 'c02'" in err and "transforms.json" in err and "not in the calibration" in err


def test_import_error_names_camera_and_file() -> None:
    e = CaptureError("something", camera="c07", file="videos/c07.mp4")
    assert str(e) == "camera 'c07', videos/c07.mp4: something"


def test_colours_are_matched_to_the_reference_camera(twin: Path, imported: Path) -> None:
    """Each camera's colour map undoes its gain and white balance relative to the reference camera's (the twin's
    sensors are ``gain ⊙ x + black``): within 4 % of full scale over the colour range."""
    from vid2sim.synthetic.capture import read_truth

    truth, _ = read_truth(twin)
    report = json.loads((imported / "capture_report.json").read_text())
    ref = report["colour"]["reference"]
    g_ref, b_ref = np.array(truth["sensors"][ref]["gain"]), truth["sensors"][ref]["black"]
    x = np.linspace(0.1, 0.9, 9)[:, None] * np.ones(3)
    for name, m in report["colour"]["maps"].items():
        g, b = np.array(truth["sensors"][name]["gain"]), truth["sensors"][name]["black"]
        expected = g_ref * (x - b) / g + b_ref
        got = x @ np.array(m["A"]).T + np.array(m["b"])
        assert np.abs(got - expected).max() < 0.04, (name, m)


# ---- the free flight: the first flight, a robust centre, an honest sigma (no rendering) ---------------------------


def _similarity(seed: int) -> tuple[float, np.ndarray, np.ndarray]:
    """A random calibration frame: units per metre, rotation, translation."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return float(rng.uniform(0.5, 3.0)), q * np.sign(np.linalg.det(q)), rng.normal(size=3)


class _BallTrack(Track):
    """A tracked ball: its lowest point is its centre less its radius along ``up``."""

    radius: float = 0.0

    def lowest_along(self, up: np.ndarray) -> np.ndarray:
        return self.centres @ up - self.radius


def _bouncing_ball(z0: float, vz0: float, r: float, seed: int = 5) -> tuple[_BallTrack, float, list[int], np.ndarray]:
    """A ball of radius ``r`` (m) from height ``z0`` at vertical speed ``vz0`` that flies to the floor z = 0,
    bounces, flies again while its tracked centre wobbles about its centre of mass (a soft object after impact),
    and rests; 70 frames at 60 fps, tracked with 0.3 mm noise in a random calibration frame. Returns the track,
    the units per metre, each frame's phase (0 before the first contact) and the true centres (T, 3) in metres."""
    dt = 1 / 60
    units, R, t0 = _similarity(seed)
    tc = (vz0 + np.sqrt(vz0 ** 2 + 2 * G * (z0 - r))) / G  # the first contact
    up_speed = 0.8 * (G * tc - vz0)
    world, phase = [], []
    for k in range(70):
        t = k * dt
        if t < tc:
            z, ph = z0 + vz0 * t - 0.5 * G * t * t, 0
        else:
            s = t - tc
            wobble = 0.02 * np.exp(-s / 0.3) * np.sin(2 * np.pi * 7 * s)
            z, ph = max(r + up_speed * s - 0.5 * G * s * s, r) + wobble, 1
        world.append([0.3 * t, 0.02 * np.sin(3 * t), z])
        phase.append(ph)
    world = np.array(world)
    rng = np.random.default_rng(0)
    centres = units * world @ R.T + t0 + rng.normal(0, 3e-4 * units, world.shape)
    track = _BallTrack(centres, [None] * len(centres), 2 * r * units)
    track.radius = r * units
    return track, units, phase, world


def test_the_scale_comes_from_the_flight_before_the_first_contact() -> None:
    """A ball falls for 13 frames, bounces, flies 26 more while its tracked centre wobbles about its centre of mass
    (a soft object after impact), and rests: the scale is measured on the first flight alone, within 2 %, though
    the later flight is longer (the seed window) and alone would be off by more than that; the flight's clearance
    above the floor is its true one."""
    dt, r = 1 / 60, 0.1
    track, units, phase, world = _bouncing_ball(0.45, -0.5, r)
    centres = track.centres
    metric = solve_metric_frame(track, dt, MetricConfig(gravity=G), range(0, len(centres)))
    first = [k for k, p in enumerate(phase) if p == 0]
    assert set(metric.ballistic.frames) <= set(first) and len(metric.ballistic.frames) >= len(first) - 2
    assert abs(metric.scale * units - 1) < 0.02, metric.scale * units
    assert metric.scale_sigma > 0 and "jackknife" in metric.scale_sigma_parts
    true_clearance = np.median(world[metric.ballistic.frames, 2] - r) / (2 * r)
    assert abs(metric.flight_clearance - true_clearance) < 0.05, (metric.flight_clearance, true_clearance)
    tc = (-0.5 + np.sqrt(0.25 + 2 * G * (0.45 - r))) / G  # the first contact, as in _bouncing_ball
    up_speed = 0.8 * (G * tc + 0.5)
    later = [k for k, p in enumerate(phase) if p == 1 and world[k, 2] > r + 0.02 and k * dt < tc + 2 * up_speed / G]
    alone = fit_segments(centres, dt, [later])
    assert abs(G / np.linalg.norm(alone.acceleration) * units - 1) > 0.02


def test_a_flight_close_to_the_floor_records_its_clearance() -> None:
    """A large ball hops up from just above the floor and never rises more than a fifth of its size: the metric
    frame records the flight's clearance over the object's size, the true one."""
    dt, r = 1 / 60, 0.25
    track, units, phase, world = _bouncing_ball(r + 0.005, 1.0, r)
    metric = solve_metric_frame(track, dt, MetricConfig(gravity=G), range(0, len(track.centres)))
    true_clearance = np.median(world[metric.ballistic.frames, 2] - r) / (2 * r)
    assert true_clearance < 0.1 and abs(metric.flight_clearance - true_clearance) < 0.05
    assert metric.to_json()["free_flight"]["clearance_over_size"] == metric.flight_clearance


def _look_at(eye: np.ndarray, target: np.ndarray, name: str, size: int = 96, f: float = 110.0) -> CaptureCamera:
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    Rw = np.stack([right, down, forward])
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    return CaptureCamera(name, size, size, K, np.zeros(5), rigid(Rw, -Rw @ eye))


def _sphere_masks(cam: CaptureCamera, spheres: np.ndarray, radius: float, supersample: int = 2) -> np.ndarray:
    """Coverage (H, W) of balls (S, 3) of ``radius`` seen by a pinhole camera (rays through sub-pixel centres)."""
    n = cam.width * supersample
    u = (np.arange(n) + 0.5) / supersample
    px = np.stack(np.meshgrid(u, u, indexing="xy"), -1).reshape(-1, 2)
    d = np.linalg.solve(cam.K, np.concatenate([px, np.ones((len(px), 1))], 1).T).T @ cam.rotation
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hit = np.zeros(len(d), bool)
    for c in spheres:
        w = c - cam.center
        along = d @ w
        hit |= (along > 0) & ((w @ w) - along ** 2 < radius ** 2)
    return hit.reshape(n // supersample, supersample, n // supersample, supersample).mean((1, 3)).astype(np.float32)


def test_a_spinning_dumbbell_with_one_view_missing_part_of_it() -> None:
    """A non-convex object (two balls on an axis) spins at 6 rad/s in free flight before 6 upright cameras; one
    view's masks lose a bite of it for 10 frames (colours like the background's). The robust hull's centroid stays
    nearer the centre of mass than the strict hull's; the flight keeps those frames (they are offset together, which
    breaks a run grown frame by frame, but they lie near the whole flight's parabola), and the scale is within
    2 %, its sigma covering the error."""
    dt, T, r, arm = 1 / 60, 24, 0.12, 0.16
    cams = [_look_at(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 0.8]), np.array([0.0, 0.0, 0.3]), f"c{i}")
            for i, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]
    p0, v0, w = np.array([-0.2, 0.1, 0.15]), np.array([0.4, -0.1, 1.6]), np.array([1.0, 2.0, 5.0])
    axis0 = np.array([1.0, 0.0, 0.3]) / np.linalg.norm([1.0, 0.0, 0.3])
    coms, masks = [], np.zeros((6, T, 96, 96), np.float32)
    for k in range(T):
        t = k * dt
        com = p0 + v0 * t + 0.5 * np.array([0.0, 0.0, -G]) * t * t
        theta = np.linalg.norm(w) * t
        n = w / np.linalg.norm(w)
        axis = axis0 * np.cos(theta) + np.cross(n, axis0) * np.sin(theta) + n * (n @ axis0) * (1 - np.cos(theta))
        coms.append(com)
        for v, cam in enumerate(cams):
            masks[v, k] = _sphere_masks(cam, np.stack([com + arm * axis, com - arm * axis]), r)
    coms = np.array(coms)
    yy, xx = np.mgrid[:96, :96]
    for k in range(8, 18):  # view 0 loses the top of the object: a bite of 4 px
        ys, xs = np.nonzero(masks[0, k] > 0.5)
        top = np.argmin(ys)
        masks[0, k][(yy - ys[top] - 2) ** 2 + (xx - xs[top]) ** 2 < 16] = 0.0
    usable = np.ones((6, T), bool)
    config = MetricConfig(gravity=G)
    track = track_object(cams, list(masks), usable, config)
    robust = np.linalg.norm(track.centres - coms, axis=1)
    strict = np.linalg.norm(track.strict_centres - coms, axis=1)
    assert robust[8:18].mean() < 0.5 * strict[8:18].mean(), (robust[8:18].mean(), strict[8:18].mean())
    metric = solve_metric_frame(track, dt, config, range(T), cameras=cams, floor=-10.0)
    assert set(range(8, 18)) <= set(metric.ballistic.frames)
    err = metric.scale - 1.0
    assert abs(err) < 0.02, err
    assert metric.scale_sigma >= 0.5 * abs(err), (metric.scale_sigma, err)


def test_the_typical_shadow_is_the_shadow_not_the_faint_darkenings() -> None:
    """A camera that sees a little of the object's shadow (ratio 0.45) and many faint darkenings just past the noise
    (penumbrae, compression; ratio 0.95): the darkest ratio that passes as shadow lies below the shadow, not between
    it and the faint ones (counted alone, the faint ones won the mode and the shadow scored as object)."""
    rng = np.random.default_rng(0)
    a = np.concatenate([rng.normal(0.45, 0.01, 800), rng.normal(0.95, 0.01, 4000)]).astype(np.float32)
    floor = mk._shadow_floor(a, np.ones(a.shape, bool), mk.MaskConfig())
    assert floor is not None and 0.3 < floor < 0.43, floor


def test_clean_keeps_the_outline_the_opening_would_take_but_not_specks_or_bridged_blobs() -> None:
    """An object whose outline the test finds as a comb (teeth 2 px deep: stripes coloured like the background between
    them), a speck, and a blob joined to the object by a 2 px bridge: the teeth stay, the speck, the blob and all
    but the bridge's first pixels go."""
    H = W = 256
    yy, xx = np.mgrid[:H, :W]
    r = np.hypot(yy - 100, xx - 100)
    teeth = (r >= 30) & (r < 32) & ((np.degrees(np.arctan2(yy - 100, xx - 100)) // 8) % 2 == 0)
    speck = (np.abs(yy - 40) < 2) & (np.abs(xx - 200) < 2)
    blob = (np.abs(yy - 100) < 8) & (np.abs(xx - 180) < 8)
    bridge = (np.abs(yy - 100) < 1) & (xx >= 100) & (xx < 175)
    found = (r < 30) | teeth | speck | blob | bridge
    m = mk.clean(found, mk.MaskConfig(), H / 128.0)
    assert (m & teeth).sum() == teeth.sum()
    assert not (m & speck).any() and not (m & blob).any()
    assert (m & bridge & (xx > 140)).sum() == 0


def test_holes_that_show_the_background_stay_open_and_patches_are_filled() -> None:
    """A ring whose hole shows the background stays a ring: over a plain wall in full light (the plate at its own
    brightness), and over a textured room with the ring's shadow across most of the hole (the room's texture). A
    disc with a dark patch that passes for shadow (the wall's colour at half its brightness) is filled, and so is a
    disc with a patch in the room's colours but not the texture behind it. The ring's hole in shadow over the plain
    wall is filled too: nothing tells it from such a dark patch (the documented limit)."""
    rng = np.random.default_rng(3)
    H = W = 128
    yy, xx = np.mgrid[:H, :W]

    def room(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return np.stack([0.45 + 0.2 * np.sin(x / 3.0) * np.cos(y / 4.0), 0.5 + 0.15 * np.cos(x / 5.0 + y / 7.0),
                         0.45 + 0.15 * np.sin(y / 3.5)], -1)

    r = np.hypot(yy - 60, xx - 64)
    ring, disc, hole = (r < 30) & (r > 11), r < 30, r < 9
    textured = room(yy, xx)
    plain = np.broadcast_to(np.array([0.5, 0.5, 0.45]), (H, W, 3))

    def masks(plate: np.ndarray, paint) -> np.ndarray:
        frames = np.repeat(plate[None], 3, 0).copy()
        for f in frames:
            paint(f)
        frames += rng.normal(0.0, 0.008, frames.shape)
        return mk.masks_from_plate(np.clip(frames, 0, 1).astype(np.float32), plate.astype(np.float32)).masks[1] > 0.5

    def ring_lit(f: np.ndarray) -> None:
        f[ring] = [0.85, 0.25, 0.15]

    def ring_shadowed(f: np.ndarray) -> None:
        f[(yy > 54) & (r < 40) & ~ring] *= 0.55  # its shadow falls across most of the hole
        f[ring] = [0.85, 0.25, 0.15]

    for plate, paint in ((plain, ring_lit), (textured, ring_shadowed)):
        m = masks(plate, paint)
        assert not m[hole].any()
        assert (m & ring).sum() / (m | ring).sum() > 0.97
        assert mk.holes_filled(m[None].astype(np.float32))[0][hole].all()  # the track's silhouette

    def disc_dark_patch(f: np.ndarray) -> None:
        f[disc] = [0.85, 0.25, 0.15]
        f[hole] = 0.5 * plain[hole]

    def disc_room_patch(f: np.ndarray) -> None:
        f[disc] = [0.85, 0.25, 0.15]
        f[hole] = room(yy + 11, xx + 7)[hole]  # the room's colours, not what lies behind the patch

    assert masks(plain, disc_dark_patch)[hole].all()
    assert masks(textured, disc_room_patch)[hole].all()
    assert masks(plain, ring_shadowed)[hole].all()


def test_a_soft_shadow_edge_on_a_textured_floor_is_not_object() -> None:
    """A flat-coloured disc and its shadow on a floor of 2 px coloured chips (a terrazzo, like the capture twins'), the
    shadow's edge a 6 px penumbra: the shadow keeps the floor's texture, darkened more on one side of each window than
    the other. Correlated with the plate alone, that edge scored as object (6 % of the disc's area added, IoU 0.94);
    with the plate darkened by the frame's local ratio it is shadow."""
    rng = np.random.default_rng(2)
    H = W = 128
    yy, xx = np.mgrid[:H, :W]
    chips = ndimage.zoom(rng.integers(0, 3, (H // 2, W // 2)), 2, order=0)
    palette = np.array([[0.7, 0.62, 0.4], [0.52, 0.42, 0.55], [0.38, 0.34, 0.36]])
    plate = ndimage.gaussian_filter(palette[chips], (0.6, 0.6, 0))
    disc = np.hypot(yy - 55, xx - 50) < 20
    edge = np.hypot(yy - 70, (xx - 75) / 1.6) - 26  # the shadow: an ellipse, darkened by 0.6 inside
    shade = 1 - 0.6 * np.clip(0.5 - edge / 6.0, 0, 1)
    frames = np.repeat((plate * shade[..., None])[None], 3, 0)
    frames[:, disc] = [0.2, 0.6, 0.55]
    frames = np.clip(frames + rng.normal(0, 0.006, frames.shape), 0, 1).astype(np.float32)
    m = mk.masks_from_plate(frames, plate.astype(np.float32)).masks[1]
    shadow_only = (shade < 0.98) & ~ndimage.binary_dilation(disc, iterations=2)
    assert (m * shadow_only).sum() / disc.sum() < 0.01
    assert np.minimum(m, disc).sum() / np.maximum(m, disc).sum() > 0.99


def test_soft_edges_leave_the_shadow_that_borders_the_object() -> None:
    """A dark object whose own shadow borders its bottom (anti-aliased, 8× supersampled truth, sensor noise): the soft
    coverage follows the true one and its centroid stays on the object's, not pulled into the shadow (explained as
    object colour plus a plate scaled per pixel, the shadow read as a rim of object that shifted the centroid 1 px
    down)."""
    rng = np.random.default_rng(0)
    H = W = 64
    k = 8
    yy, xx = (np.mgrid[: H * k, : W * k] + 0.5) / k
    disc = ((yy - 28.3) ** 2 + (xx - 31.7) ** 2 < 12.5**2).astype(np.float64)
    shadow = ((yy - 33.0) ** 2 / 1.2 + (xx - 34.0) ** 2 < 14.0**2) * (1.0 - disc)

    def down(a: np.ndarray) -> np.ndarray:
        return a.reshape(H, k, W, k).mean((1, 3))

    alpha = down(disc)
    shade = np.where(alpha > 0.999, 1.0, 1.0 - 0.55 * down(shadow) / np.maximum(1.0 - alpha, 1e-9))
    plate = np.array([0.6, 0.55, 0.65]) * (1 + 0.05 * ndimage.gaussian_filter(rng.normal(size=(H, W)), 2))[..., None]
    frame = alpha[..., None] * np.array([0.30, 0.26, 0.36]) + ((1 - alpha) * shade)[..., None] * plate
    frame += rng.normal(0.0, 0.004, frame.shape)
    soft = mk.soft_edges(alpha > 0.5, frame.astype(np.float32), plate.astype(np.float32), 0.004)
    rows = np.arange(H)[:, None] + 0.5
    shift = (soft * rows).sum() / soft.sum() - (alpha * rows).sum() / alpha.sum()
    assert abs(shift) < 0.25, shift
    assert np.abs(soft - alpha).sum() / alpha.sum() < 0.1


def test_masks_on_the_object_box_equal_the_whole_frame() -> None:
    """masks_from_plate cleans and softens each frame on the box around what its test found: the same masks,
    confidence and stray share as the clean-up and soft edges over the whole frame."""
    rng = np.random.default_rng(1)
    H = W = 64
    plate = np.clip(0.5 + 0.2 * ndimage.gaussian_filter(rng.normal(size=(H, W, 3)), (3, 3, 0)), 0, 1).astype(np.float32)
    frames = np.repeat(plate[None], 5, 0) + rng.normal(0, 0.004, (5, H, W, 3)).astype(np.float32)
    yy, xx = np.mgrid[:H, :W]
    for t in range(5):
        disc = (yy - 20 - 3 * t) ** 2 + (xx - 30 - 4 * t) ** 2 < 64
        frames[t][disc] = [0.8, 0.2, 0.3]
        frames[t][((yy - 34 - 3 * t) ** 2 + (xx - 34 - 4 * t) ** 2 < 40) & ~disc] *= 0.6  # its shadow
    frames = np.clip(frames, 0, 1).astype(np.float32)
    config = mk.MaskConfig()
    got = mk.masks_from_plate(frames, plate, config)
    F, B = mk.blur(frames, config.blur_sigma), mk.blur(plate, config.blur_sigma)
    sigma = mk.noise_level(F, B, config.noise_floor)
    score = mk.object_score(F, B, sigma, config)
    detected = mk.hysteresis(score, config.high, config.low)
    scale = H / 128.0
    for t in range(5):
        m = mk.clean(detected[t], config, scale, mk.see_through(frames[t], B, sigma, config, scale))
        soft = mk.soft_edges(m, frames[t], plate, sigma, config.edge_width, config.edge_depth)
        outside = ~mk.dilate(m, mk.CROSS, max(1, int(round(2 * scale))))
        np.testing.assert_allclose(got.masks[t], soft, atol=1e-6)
        assert got.confidence[t] == pytest.approx((detected[t] & m).sum() / max(m.sum(), 1))
        assert got.stray[t] == pytest.approx((score[t][outside] > config.low).mean())
    assert got.masks.sum() > 100


def test_bench_capture_summary_names_the_worst_scene() -> None:
    """``bench capture``'s means: the worst scene of each figure is its lowest IoU and its largest error."""
    from vid2sim.apps.bench.capture import _means

    def record(iou: float, worst: float, scale: float) -> dict:
        return {"status": "ok", "import": {"mask_iou": iou, "mask_iou_worst": worst, "scale_error": scale,
                                          "gravity_error_deg": 0.01, "floor_error_m": -1e-4, "import_seconds": 9.0}}

    m = _means([record(0.96, 0.93, -0.03), record(0.94, 0.90, 0.01), {"status": "failed"}])
    assert m["scenes"] == 2
    assert m["mask_iou"] == pytest.approx(0.95) and m["worst_mask_iou"] == 0.94
    assert m["worst_mask_iou_worst"] == 0.90
    assert m["abs_scale_error"] == pytest.approx(0.02) and m["worst_abs_scale_error"] == 0.03
    assert m["worst_abs_floor_error_m"] == pytest.approx(1e-4)
