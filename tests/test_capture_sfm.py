"""COLMAP's own files and COLMAP's own structure from motion (pycolmap), not ours: the reader against models
COLMAP wrote, and ``calibrate-capture`` on a capture twin's plates and walkaround photos against the twin's true
cameras."""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import pytest
import torch

from vid2sim.apps.bench.capture import CaptureBenchConfig, similarity_to_model
from vid2sim.scene.capture.colmap import colmap_cameras, points_by_camera, read_colmap
from vid2sim.scene.capture.errors import CaptureError
from vid2sim.scene.capture.layout import discover_capture
from vid2sim.scene.capture.sfm import SfmConfig, calibrate_capture
from vid2sim.splats.cameras import Camera, look_at
from vid2sim.synthetic.capture import CaptureMotion, CaptureTwinConfig, read_truth, write_capture
from vid2sim.synthetic.shapes import make_procedural_object

pycolmap = pytest.importorskip("pycolmap", reason='COLMAP checks need pycolmap: pip install "vid2sim[colmap]"')

MODEL_PARAMS = {"SIMPLE_PINHOLE": [300.0, 64.0, 48.0], "PINHOLE": [300.0, 310.0, 64.5, 47.5],
                "SIMPLE_RADIAL": [290.0, 63.0, 49.0, -0.12], "RADIAL": [305.0, 64.0, 48.0, -0.1, 0.03],
                "OPENCV": [301.0, 299.0, 64.2, 47.9, -0.15, 0.02, 0.001, -0.0005]}


def _pycolmap_model(rng: np.random.Generator):
    """A reconstruction built with pycolmap: one camera and image per model, random poses, points with tracks."""
    rec = pycolmap.Reconstruction()
    poses = {}
    for i, (model, params) in enumerate(MODEL_PARAMS.items(), start=1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=128, height=96, params=params,
                                                        camera_id=i))
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        t = rng.normal(size=3)
        pts = [pycolmap.Point2D(rng.uniform(0, 96, 2)) for _ in range(8)]
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"background/c{i:02d}.png", points2D=pts, camera_id=i,
                                                        image_id=i), pycolmap.Rigid3d(pycolmap.Rotation3d(q), t))
        poses[f"c{i:02d}"] = rec.images[i].cam_from_world().matrix()
    tracks = {}
    for k in range(6):
        track = pycolmap.Track()
        seen = sorted(rng.choice(np.arange(1, 6), size=2, replace=False).tolist())
        for image_id in seen:
            track.add_element(image_id, k)
        xyz = rng.normal(size=3)
        tracks[tuple(xyz)] = {f"c{i:02d}" for i in seen}
        rec.add_point3D(xyz, track, np.array([10, 20, 30], np.uint8))
    return rec, poses, tracks


@pytest.mark.parametrize("binary", [False, True])
def test_reader_reads_models_colmap_wrote(tmp_path, binary):
    rec, poses, tracks = _pycolmap_model(np.random.default_rng(3))
    (rec.write_binary if binary else rec.write_text)(str(tmp_path))
    model = read_colmap(tmp_path)
    assert model.binary == binary
    cams = colmap_cameras(model, lambda name: name.split("/")[-1][:3])
    assert sorted(cams) == sorted(poses)
    for name, cam in cams.items():
        np.testing.assert_allclose(cam.world_to_camera[:3], poses[name], atol=1e-12)
        col = rec.cameras[int(name[1:])]
        assert cam.model == col.model.name and (cam.width, cam.height) == (128, 96)
        # the reader's pinhole + OpenCV distortion projects like COLMAP's own camera model
        xy = np.random.default_rng(0).uniform(-0.3, 0.3, (20, 2))
        uv_colmap = np.array([col.img_from_cam(np.array([x, y, 1.0])) for x, y in xy])
        uv, _ = cv2.projectPoints(np.c_[xy, np.ones(len(xy))], np.zeros(3), np.zeros(3), cam.K, cam.distortion)
        np.testing.assert_allclose(uv[:, 0], uv_colmap, atol=1e-6)
    xyz, rgb, seen = points_by_camera(model, cams)
    assert len(xyz) == len(tracks)
    for p, s in zip(xyz, seen):
        assert s == tracks[tuple(p)]
    assert (rgb == [10, 20, 30]).all()


RING_RADIUS = 2.4  # metres, the ring of _ring_twin's cameras


def _ring_twin(out, photos: int, size: int = 160):
    """A capture twin of a small object at rest on the floor, filmed for 2 frames by 6 cameras on a ring (60°
    apart), with ``photos`` walkaround photos: what ``calibrate-capture`` reads (plates and photos)."""
    obj = make_procedural_object(3)
    verts = obj.vertices.float() * 0.3
    verts[:, 2] -= verts[:, 2].min() + 0.7
    f = 0.5 * size / np.tan(np.radians(20))
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    cams = []
    for k in range(6):
        a = 2 * np.pi * k / 6
        eye = torch.tensor([RING_RADIUS * np.cos(a), RING_RADIUS * np.sin(a), 0.4])
        cams.append(Camera(look_at(eye, torch.tensor([0.0, 0.0, -0.5])), K.clone(), size, size))
    motion = CaptureMotion(verts[None].repeat(2, 1, 1), obj.faces, obj.uvs, obj.texture, cams, 0.05, -0.7)
    config = CaptureTwinConfig(resolution_scale=2, frames_format="frames", photos=photos, colmap_format="none",
                               camera_models=("OPENCV",))
    return write_capture(motion, out, config)


def test_calibrate_capture_recovers_the_rig_from_plates_and_photos(tmp_path):
    capture = _ring_twin(tmp_path / "cap", photos=24)
    assert len(list((capture / "photos").iterdir())) == 24
    report = calibrate_capture(capture, SfmConfig(max_features=4096, threads=2), progress=False)
    assert report.cameras == [f"c{k:02d}" for k in range(6)] and report.photos == 24
    assert report.photos_registered >= 12 and report.points > 100
    assert report.mean_reprojection_error_px < 1.0
    # 320 px plates are flagged as small; no camera's focal length stands out
    assert len(report.warnings) == 1 and "on their shorter side" in report.warnings[0], report.warnings
    assert json.loads((capture / "colmap" / "sfm_report.json").read_text())["points"] == report.points
    layout = discover_capture(capture)
    model = read_colmap(layout.colmap)
    assert model.binary and len(model.images) == 6  # the photos are not in the model
    cams = colmap_cameras(model, layout.camera_of_name)
    truth, _ = read_truth(capture)
    focal = max(abs(c.K[0, 0] / truth["true_cameras_calibration"][n]["K"][0][0] - 1) for n, c in cams.items())
    assert focal < 0.015, focal
    _, _, seen = points_by_camera(model, cams)
    assert min(len(s) for s in seen) >= 2  # points that only photos saw went with them
    # the cameras after the best similarity from the world to COLMAP's frame (the bench's truth of that frame)
    sim = similarity_to_model(capture)
    assert sim["centre_error_m"] / RING_RADIUS < 0.015 and sim["rotation_error_deg"] < 0.5, sim
    assert sim["centre_error_m"] < 0.03, sim
    R = np.array(sim["rotation"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)


def test_calibrate_capture_says_what_is_missing(tmp_path, monkeypatch):
    capture = _ring_twin(tmp_path / "cap", photos=0)
    # the plates alone: 60° apart, COLMAP cannot link them; the message says to add photos
    with pytest.raises(CaptureError, match=r"registered \d of 6 plates.*add photos"):
        calibrate_capture(capture, SfmConfig(max_features=1024, threads=1), progress=False)
    assert not (capture / "colmap").exists()
    (capture / "colmap").mkdir()
    (capture / "colmap" / "cameras.txt").write_text("")
    with pytest.raises(CaptureError, match="already there"):
        calibrate_capture(capture, progress=False)
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(CaptureError, match="needs pycolmap"):
        calibrate_capture(capture, overwrite=True, progress=False)
    (capture / "background" / "c03.png").unlink()
    with pytest.raises(CaptureError, match="no clean plate for camera.*c03"):
        calibrate_capture(capture, overwrite=True, progress=False)
    with pytest.raises(ValueError, match="camera_model"):
        SfmConfig(camera_model="FISHEYE")
    with pytest.raises(ValueError, match="photos"):
        CaptureBenchConfig(twin=CaptureTwinConfig(), sfm=True)
