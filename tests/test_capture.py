"""import-capture: calibration readers, undistortion, masks against a shadow, metres/gravity/floor from free flight,
the bad-input errors, and the scene folder it writes.

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

from vid2sim.cli import main
from vid2sim.scene.capture import CaptureError, CaptureImportConfig, import_capture
from vid2sim.scene.capture.cameras import CaptureCamera, rigid
from vid2sim.scene.capture.colmap import colmap_cameras, read_colmap, write_colmap
from vid2sim.scene.capture.metric import MetricConfig
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
    from vid2sim.scene.folder import load_scene

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
    from scipy import ndimage

    from vid2sim.apps.bench.capture import _undistorted_alpha, import_figures
    from vid2sim.scene.folder import load_scene
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
