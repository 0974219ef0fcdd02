"""Scene folders: round trips, the compositing and camera conventions, every validation error, and
atomic writes (nothing left behind when writing fails)."""

from __future__ import annotations

import json
import math
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import vid2sim.scene.folder as scene_mod
from vid2sim.scene.folder import (
    LAYOUTS,
    Scene,
    SceneConfig,
    SceneFormatError,
    load_scene,
    write_scene,
)
from vid2sim.splats.cameras import Camera, camera_ring

V, T, H, W = 3, 5, 12, 16


def make_scene(soft: bool = False, seed: int = 0, num_frames: int = T, **config) -> Scene:
    """A small scene whose pixels are exactly representable in uint8 and composited on white."""
    g = torch.Generator().manual_seed(seed)
    colour = torch.randint(0, 256, (V, num_frames, H, W, 3), generator=g, dtype=torch.uint8).float() / 255
    if soft:
        mask = torch.randint(0, 256, (V, num_frames, H, W), generator=g, dtype=torch.uint8).float() / 255
    else:
        mask = (torch.rand(V, num_frames, H, W, generator=g) > 0.4).float()
    images = colour * mask[..., None] + (1 - mask[..., None])
    if soft:  # keep the images uint8-representable too (the writer then inverts the compositing)
        images = torch.round(images * 255) / 255
    cfg = SceneConfig(
        floor_height=-0.7, metadata={"E": 2.5e5, "nu": 0.3, "material": "neo-hookean", "seed": seed}, **config
    )
    extras = {
        "tet_trajectory": {
            "vertices": torch.randn(num_frames, 9, 3, generator=g, dtype=torch.float64),
            "tets": torch.randint(0, 9, (6, 4), generator=g),
        }
    }
    cams = camera_ring(V, 2.5, 25.0, W, H, fov_x_deg=45.0, azimuth_offset_deg=10.0)
    return Scene(cams, images, mask, None, cfg, None, extras)


def assert_same_scene(a: Scene, b: Scene, image_atol: float = 0.0) -> None:
    assert a.num_views == b.num_views and a.num_frames == b.num_frames
    for ca, cb in zip(a.cameras, b.cameras):
        assert torch.allclose(ca.world_to_camera, cb.world_to_camera, atol=1e-6, rtol=0)
        assert torch.allclose(ca.K, cb.K, atol=1e-6, rtol=0)
        assert (ca.width, ca.height) == (cb.width, cb.height)
    if image_atol == 0.0:
        assert torch.equal(a.images, b.images)
    else:
        assert float((a.images - b.images).abs().max()) <= image_atol
    assert torch.equal(a.masks, b.masks)
    assert torch.allclose(a.times, b.times, atol=1e-7, rtol=0)
    assert a.config == b.config
    assert a.extras.keys() == b.extras.keys()
    for name in a.extras:
        assert a.extras[name].keys() == b.extras[name].keys()
        for key in a.extras[name]:
            assert a.extras[name][key].dtype == b.extras[name][key].dtype
            assert torch.equal(a.extras[name][key], b.extras[name][key])


@pytest.fixture()
def written(tmp_path: Path) -> Path:
    return write_scene(make_scene(), tmp_path / "scene")


def edit_json(path: Path, fn) -> None:
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


def problems_of(path: Path) -> tuple[str, list[str]]:
    with pytest.raises(SceneFormatError) as info:
        load_scene(path)
    return str(info.value), info.value.problems


# ---------------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", ["rgba", "rgb+mask"])
def test_round_trip_is_exact_for_uint8_data(tmp_path: Path, layout: str) -> None:
    scene = make_scene()
    out = write_scene(scene, tmp_path / "s", layout=layout)
    loaded = load_scene(out)
    assert loaded.root == out
    assert_same_scene(scene, loaded)
    assert loaded.images.dtype == torch.float32 and loaded.masks.dtype == torch.float32
    assert loaded.config.metadata["material"] == "neo-hookean"
    assert loaded.config.floor_height == -0.7
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    n_masks = V * T if layout == "rgb+mask" else 0
    assert len(files) == 2 + 1 + V * T + n_masks  # two JSON files, one npz, the images (+ masks)
    assert "images/c01_t003.png" in files


@pytest.mark.parametrize("layout", ["rgba", "rgb+mask"])
def test_round_trip_with_soft_masks_within_half_a_grey_level(tmp_path: Path, layout: str) -> None:
    # fractional alpha: the writer inverts the compositing and rounds, so each pixel comes back
    # within 0.5/255 (|Δc|·a with |Δc| ≤ 0.5/255); masks exactly
    scene = make_scene(soft=True, seed=3)
    loaded = load_scene(write_scene(scene, tmp_path / "s", layout=layout))
    assert_same_scene(scene, loaded, image_atol=0.5 / 255 + 1e-6)
    assert float((scene.images - loaded.images).abs().mean()) < 0.25 / 255


def test_uint8_and_float64_loading(tmp_path: Path) -> None:
    scene = make_scene()
    out = write_scene(scene, tmp_path / "s")
    compact = load_scene(out, dtype=torch.uint8)
    assert compact.images.dtype == torch.uint8 and compact.masks.dtype == torch.uint8
    assert torch.equal(compact.images, torch.round(scene.images * 255).to(torch.uint8))
    assert torch.equal(compact.float_images(), scene.images)
    assert torch.equal(compact.image(2, 4), scene.images[2, 4])
    assert torch.equal(compact.mask(1, 0), scene.masks[1, 0])
    wide = load_scene(out, dtype=torch.float64)
    assert wide.images.dtype == torch.float64
    assert torch.allclose(wide.images, scene.images.double(), atol=1e-7, rtol=0)
    # the compact scene writes back to the same files
    again = load_scene(write_scene(compact, tmp_path / "s2"))
    assert_same_scene(scene, again)


def test_overwrite_replaces_a_scene(tmp_path: Path) -> None:
    out = write_scene(make_scene(seed=0), tmp_path / "s")
    with pytest.raises(FileExistsError, match="already exists; pass overwrite=True"):
        write_scene(make_scene(seed=1), out)
    write_scene(make_scene(seed=1), out, overwrite=True)
    assert_same_scene(make_scene(seed=1), load_scene(out))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_overwrite_refuses_folders_that_are_not_scenes(tmp_path: Path) -> None:
    other = tmp_path / "my_documents"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    with pytest.raises(FileExistsError, match="non-empty folder without scene.json"):
        write_scene(make_scene(), other, overwrite=True)
    assert (other / "thesis.tex").read_text() == "precious"
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    with pytest.raises(FileExistsError, match="is not a folder"):
        write_scene(make_scene(), a_file, overwrite=True)


# ---------------------------------------------------------------------------------------------
# conventions, checked on hand-written folders (independent of the writer)
# ---------------------------------------------------------------------------------------------


def _hand_written(tmp: Path, frames: list[dict], top: dict | None = None, scene: dict | None = None) -> Path:
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / "transforms.json").write_text(json.dumps({**(top or {}), "frames": frames}))
    (tmp / "scene.json").write_text(json.dumps(scene or {"dt": 0.05}))
    return tmp


def test_rgba_is_composited_on_white_and_camera_follows_the_opengl_convention(tmp_path: Path) -> None:
    w, h = 8, 6
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., :3] = (200, 100, 50)
    rgba[0, 0, 3] = 0  # transparent black-ish pixel → white
    rgba[0, 1, 3] = 255
    rgba[0, 2, 3] = 51  # a = 0.2
    rgba[1:, :, 3] = 255
    rgba[0, 3:, 3] = 255
    (tmp_path / "img").mkdir()
    Image.fromarray(rgba).save(tmp_path / "img" / "r_0.png")
    # OpenGL camera-to-world: camera at (0, 0, 2) with identity rotation looks down -z at the origin
    c2w = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]
    angle = 0.9
    root = _hand_written(
        tmp_path,
        # NeRF-style path without suffix, 'rotation' (a Blender leftover) is accepted and ignored
        [{"file_path": "./img/r_0", "rotation": 0.1, "transform_matrix": c2w, "camera_index": 0, "time_index": 0}],
        top={"camera_angle_x": angle, "aabb_scale": 16},
    )
    scene = load_scene(root)
    img, mask = scene.image(0, 0), scene.mask(0, 0)
    colour = torch.tensor([200, 100, 50], dtype=torch.float32) / 255
    assert torch.equal(img[0, 0], torch.ones(3)) and float(mask[0, 0]) == 0.0
    assert torch.equal(img[0, 1], colour) and float(mask[0, 1]) == 1.0
    a = 51 / 255
    assert torch.allclose(img[0, 2], colour * a + (1 - a), atol=1e-7)
    assert math.isclose(float(mask[0, 2]), a, rel_tol=1e-7)
    # intrinsics from camera_angle_x: fx = fy = w / (2 tan(angle/2)), principal point at the centre
    cam = scene.cameras[0]
    fx = 0.5 * w / math.tan(angle / 2)
    assert torch.allclose(cam.K, torch.tensor([[fx, 0, w / 2], [0, fx, h / 2], [0, 0, 1]], dtype=torch.float32))
    # geometry: the origin lands on the principal point 2 m in front; world +x goes right in the
    # image (u grows), world +y (up for this camera) goes up in the image (v shrinks)
    pix, depth = cam.project(torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    assert torch.allclose(pix[0], torch.tensor([w / 2, h / 2]), atol=1e-5)
    assert torch.allclose(depth, torch.full((3,), 2.0), atol=1e-6)
    assert math.isclose(float(pix[1, 0]) - w / 2, fx * 0.1 / 2, rel_tol=1e-5)
    assert math.isclose(h / 2 - float(pix[2, 1]), fx * 0.1 / 2, rel_tol=1e-5)


def test_rgb_jpg_with_mask_files_and_explicit_intrinsics(tmp_path: Path) -> None:
    w, h = 8, 6
    (tmp_path / "rgb").mkdir()
    (tmp_path / "m").mkdir()
    rng = np.random.default_rng(0)
    mask = np.zeros((h, w), np.uint8)
    mask[2:5, 3:7] = 255
    Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(tmp_path / "rgb" / "a.jpg", quality=100)
    Image.fromarray(mask).save(tmp_path / "m" / "a.png")
    # a mask saved as an RGB image with equal channels is accepted too
    Image.fromarray(np.repeat(mask[..., None], 3, axis=2)).save(tmp_path / "m" / "b.png")
    Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(tmp_path / "rgb" / "b.png")
    c2w = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]
    frames = [
        {"file_path": f"rgb/{n}", "mask_path": f"m/{m}", "transform_matrix": c2w[:3], "camera_index": 0,
         "time_index": i, "time": 1.0 + 0.04 * i}
        for i, (n, m) in enumerate([("a.jpg", "a.png"), ("b.png", "b.png")])
    ]
    root = _hand_written(
        tmp_path, frames, top={"fl_x": 10.0, "fl_y": 11.0, "cx": 4.5, "cy": 2.5, "w": w, "h": h, "k1": 0.0},
        scene={"dt": 0.04, "gravity": [0, -9.8, 0], "floor_height": 0.0},
    )
    scene = load_scene(root)
    assert torch.allclose(scene.cameras[0].K, torch.tensor([[10.0, 0, 4.5], [0, 11.0, 2.5], [0, 0, 1]]))
    assert torch.allclose(scene.times, torch.tensor([1.0, 1.04]))
    assert scene.config.up == pytest.approx((0.0, 1.0, 0.0))
    expected_mask = torch.from_numpy(mask).float() / 255
    assert torch.equal(scene.masks[0, 0], expected_mask) and torch.equal(scene.masks[0, 1], expected_mask)
    assert torch.equal(scene.images[0, 0][expected_mask == 0], torch.ones(int((expected_mask == 0).sum()), 3))
    assert float((scene.images[0, 0][expected_mask == 1] - 90 / 255).abs().max()) <= 2 / 255  # jpeg q100
    # camera centre = translation of camera-to-world
    assert torch.allclose(scene.cameras[0].center, torch.tensor([0.5, 0.0, 3.0]), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# validation errors: each names the file, the frame/camera and the field
# ---------------------------------------------------------------------------------------------

TJ, SJ = "transforms.json", "scene.json"


def _frame(obj: dict, camera: int, t: int) -> dict:
    return next(f for f in obj["frames"] if f["camera_index"] == camera and f["time_index"] == t)


def _scale_matrix(obj: dict) -> None:
    m = np.array(obj["frames"][4]["transform_matrix"])
    m[:3, :3] *= 2.0
    obj["frames"][4]["transform_matrix"] = m.tolist()


def _shear_matrix(obj: dict) -> None:
    obj["frames"][4]["transform_matrix"][0][1] += 0.3


def _reflect_matrix(obj: dict) -> None:
    m = np.array(obj["frames"][6]["transform_matrix"])
    m[:3, 0] *= -1
    obj["frames"][6]["transform_matrix"] = m.tolist()


def _move_camera(obj: dict) -> None:
    _frame(obj, 2, 3)["transform_matrix"][0][3] += 0.2


CASES = {
    "missing file": (
        lambda root: (root / "images" / "c01_t003.png").unlink(),
        f"{TJ}: frame 8 (camera 1, time index 3): file 'images/c01_t003.png' not found",
    ),
    "missing frame": (
        lambda root: edit_json(root / TJ, lambda o: o["frames"].remove(_frame(o, 2, 4))),
        f"{TJ}: missing frame 4 of camera 2",
    ),
    "scaled matrix": (
        lambda root: edit_json(root / TJ, _scale_matrix),
        f"{TJ}: frame 4 (camera 0, time index 4): transform_matrix is not a rigid transform: "
        "its 3x3 block is a rotation scaled by 2",
    ),
    "sheared matrix": (
        lambda root: edit_json(root / TJ, _shear_matrix),
        f"{TJ}: frame 4 (camera 0, time index 4): transform_matrix is not a rigid transform: "
        "its 3x3 block is not a rotation",
    ),
    "reflection": (
        lambda root: edit_json(root / TJ, _reflect_matrix),
        f"{TJ}: frame 6 (camera 1, time index 1): transform_matrix is not a rigid transform: "
        "its 3x3 block is a reflection",
    ),
    "bad last row": (
        lambda root: edit_json(root / TJ, lambda o: o["frames"][2]["transform_matrix"][3].__setitem__(0, 0.5)),
        "transform_matrix is not a rigid transform: its last row is [0.5, 0.0, 0.0, 1.0]",
    ),
    "matrix shape": (
        lambda root: edit_json(root / TJ, lambda o: o["frames"][1].__setitem__("transform_matrix", [[1, 0], [0, 1]])),
        f"{TJ}: frame 1 (camera 0, time index 1): transform_matrix must be a 4x4 (or 3x4) nested list of numbers",
    ),
    "w/h differ from image": (
        lambda root: edit_json(root / TJ, lambda o: o.__setitem__("w", 20)),
        f"{TJ}: frame 0 (camera 0, time index 0): image size 16x12 of 'images/c00_t000.png' differs from w/h 20x12",
    ),
    "one image of another size": (
        lambda root: Image.new("RGBA", (16, 10)).save(root / "images" / "c02_t001.png"),
        f"{TJ}: frame 11 (camera 2, time index 1): image 'images/c02_t001.png' is 16x10 but camera 2's other "
        "images are 16x12",
    ),
    "the first image of a camera of another size": (  # the odd image is named, not the good ones after it
        lambda root: Image.new("RGBA", (16, 10)).save(root / "images" / "c02_t000.png"),
        f"{TJ}: frame 10 (camera 2, time index 0): image 'images/c02_t000.png' is 16x10 but camera 2's other "
        "images are 16x12",
    ),
    "unknown top-level key": (
        lambda root: edit_json(root / TJ, lambda o: o.__setitem__("fl_z", 3.0)),
        f"unknown key 'fl_z' in {TJ} (top level) (did you mean 'fl_",
    ),
    "unknown frame key": (
        lambda root: edit_json(root / TJ, lambda o: o["frames"][7].__setitem__("maskpath", "x.png")),
        f"unknown key 'maskpath' in {TJ}: frame 7 (camera 1, time index 2) (did you mean 'mask_path'?)",
    ),
    "unknown scene.json key": (
        lambda root: edit_json(root / SJ, lambda o: o.__setitem__("floor_heigth", 0.0)),
        f"unknown key 'floor_heigth' in {SJ} (did you mean 'floor_height'?)",
    ),
    "negative dt": (
        lambda root: edit_json(root / SJ, lambda o: o.update(dt=-1, fps=-1)),
        f"{SJ}: dt must be > 0, got -1",
    ),
    "gravity shape": (
        lambda root: edit_json(root / SJ, lambda o: o.__setitem__("gravity", [0, -9.8])),
        f"{SJ}: gravity must be 3 finite numbers (m/s², world frame), got [0, -9.8]",
    ),
    "fps disagrees with dt": (
        lambda root: edit_json(root / SJ, lambda o: o.__setitem__("fps", 24)),
        f"{SJ}: fps = 24 disagrees with dt = 0.05 s",
    ),
    "view index out of range": (
        lambda root: edit_json(root / SJ, lambda o: o.update(observed_views=[0, 3], held_out_views=None)),
        f"{SJ}: observed_views contains 3, but the scene has 3 views (indices 0..2)",
    ),
    "observed and held out overlap": (
        lambda root: edit_json(root / SJ, lambda o: o.update(observed_frames=[0, 1, 2], held_out_frames=[2, 3])),
        f"{SJ}: observed_frames and held_out_frames both contain 2; they must be disjoint",
    ),
    "moving camera": (
        lambda root: edit_json(root / TJ, _move_camera),
        f"{TJ}: camera 2 moves: transform_matrix of frame 13 (time index 3) differs from frame 10 (time index 0)",
    ),
    "intrinsics change over time": (
        lambda root: edit_json(root / TJ, lambda o: _frame(o, 1, 2).__setitem__("fl_x", 30.0)),
        f"{TJ}: camera 1: intrinsics of frame 7 (fl_x = 30.0) differ from frame 5",
    ),
    "duplicate frame": (
        lambda root: edit_json(root / TJ, lambda o: o["frames"].append(dict(_frame(o, 0, 2)))),
        f"{TJ}: frames 2 and 15 both are camera 0, time index 2",
    ),
    "camera gap": (
        lambda root: edit_json(
            root / TJ, lambda o: [f.__setitem__("camera_index", 3) for f in o["frames"] if f["camera_index"] == 2]
        ),
        f"{TJ}: camera indices must run 0..3 without gaps; nothing has camera index 2",
    ),
    "focal length and angle disagree": (
        lambda root: edit_json(root / TJ, lambda o: o.__setitem__("camera_angle_x", 1.2)),
        "fl_x = 19.3137 and camera_angle_x = 1.2 (which gives fl_x = 11.6936 for w = 16) disagree",
    ),
    "no focal length": (
        lambda root: edit_json(root / TJ, lambda o: [o.pop(k) for k in ("camera_angle_x", "fl_x", "fl_y")]),
        f"{TJ}: frame 0 (camera 0, time index 0): no focal length; give fl_x or camera_angle_x",
    ),
    "lens distortion": (
        lambda root: edit_json(root / TJ, lambda o: o.__setitem__("k1", 0.05)),
        f"{TJ} (top level): lens distortion is not supported (k1 = 0.05)",
    ),
    "times disagree with dt": (
        lambda root: edit_json(root / SJ, lambda o: o.update(dt=0.04, fps=25)),
        f"{TJ}: frame times step by 0.05 s from time index 0 to 1, but scene.json has dt = 0.04 s",
    ),
    "unsynchronised cameras": (
        lambda root: edit_json(root / TJ, lambda o: _frame(o, 1, 3).__setitem__("time", 0.16)),
        f"{TJ}: time index 3 has different times in frame 3 (0.15 s) and frame 8 (0.16 s)",
    ),
    "RGB without mask": (
        lambda root: Image.new("RGB", (16, 12), (9, 9, 9)).save(root / "images" / "c00_t002.png"),
        f"{TJ}: frame 2 (camera 0, time index 2): image 'images/c00_t002.png' has no alpha channel and the frame has "
        "no mask_path",
    ),
    "corrupt image": (
        lambda root: (root / "images" / "c01_t000.png").write_bytes(b"not a png at all"),
        f"{TJ}: frame 5 (camera 1, time index 0): cannot read image 'images/c01_t000.png'",
    ),
    "invalid JSON": (
        lambda root: (root / SJ).write_text('{"dt": 0.05,\n "gravity": [0, 0, -9.8,]}'),
        f"{SJ}: not valid JSON: Expecting value at line 2, column 25",
    ),
    "missing scene.json": (
        lambda root: (root / SJ).unlink(),
        "scene.json not found (expected the file",
    ),
    "missing extras file": (
        lambda root: (root / "extras" / "tet_trajectory.npz").unlink(),
        f"{SJ}: extras 'tet_trajectory': file 'extras/tet_trajectory.npz' not found",
    ),
    "newer format version": (
        lambda root: edit_json(root / SJ, lambda o: o.__setitem__("version", 7)),
        f"{SJ}: format version 7 is newer than this vid2sim reads (up to 1)",
    ),
    "frames and videos": (
        lambda root: edit_json(root / TJ, lambda o: o.__setitem__("videos", [])),
        f"{TJ}: give exactly one of 'frames'",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_validation_error_names_file_frame_and_field(written: Path, case: str) -> None:
    mutate, expected = CASES[case]
    mutate(written)
    message, problems = problems_of(written)
    assert isinstance(SceneFormatError(["x"]), ValueError)  # the CLI prints ValueErrors cleanly
    assert message.startswith(f"invalid scene folder '{written}'")
    assert any(expected in p for p in problems), f"expected {expected!r} in {problems}"
    assert expected in message


def test_every_problem_is_reported_at_once(written: Path) -> None:
    for name in ("c00_t001.png", "c02_t004.png", "c01_t002.png"):
        (written / "images" / name).unlink()
    message, problems = problems_of(written)
    assert len(problems) == 3
    assert message.splitlines()[0].endswith("3 problems:")
    for frame, cam, t, name in ((1, 0, 1, "c00_t001.png"), (14, 2, 4, "c02_t004.png"), (7, 1, 2, "c01_t002.png")):
        assert f"frame {frame} (camera {cam}, time index {t}): file 'images/{name}' not found" in message


def test_missing_folder_and_file_instead_of_folder(tmp_path: Path) -> None:
    with pytest.raises(SceneFormatError, match="the folder does not exist"):
        load_scene(tmp_path / "nope")
    (tmp_path / "f").write_text("x")
    with pytest.raises(SceneFormatError, match="not a folder"):
        load_scene(tmp_path / "f")


def test_alpha_and_mask_path_together_is_ambiguous(written: Path) -> None:
    (written / "m.png").write_bytes((written / "images" / "c00_t000.png").read_bytes())
    edit_json(written / TJ, lambda o: o["frames"][0].__setitem__("mask_path", "m.png"))
    message, _ = problems_of(written)
    assert "has a (non-opaque) alpha channel and the frame also has mask_path 'm.png'" in message
    # a colour (non-grey) mask is refused too
    Image.fromarray(
        np.dstack([np.zeros((12, 16), np.uint8), np.full((12, 16), 255, np.uint8), np.zeros((12, 16), np.uint8)])
    ).save(written / "m.png")
    rgb = np.asarray(Image.open(written / "images" / "c00_t000.png"))[..., :3]
    Image.fromarray(rgb).save(written / "images" / "c00_t000.png")
    message, _ = problems_of(written)
    assert "cannot use mask 'm.png': it is a colour image" in message


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------


def _failing_png_writer(monkeypatch: pytest.MonkeyPatch, fail_at: int) -> list[int]:
    real = scene_mod._write_png
    calls = [0]
    lock = threading.Lock()

    def flaky(path, array):
        with lock:
            calls[0] += 1
            n = calls[0]
        if n == fail_at:
            raise OSError(28, "No space left on device (simulated)")
        real(path, array)

    monkeypatch.setattr(scene_mod, "_write_png", flaky)
    return calls


@pytest.mark.parametrize("workers", [1, 3])
def test_failed_write_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int) -> None:
    calls = _failing_png_writer(monkeypatch, fail_at=3)
    target = tmp_path / "scene"
    with pytest.raises(OSError, match="No space left on device"):
        write_scene(make_scene(), target, workers=workers)
    assert calls[0] >= 3
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary folder either


def test_failed_overwrite_keeps_the_old_scene(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old = make_scene(seed=5)
    target = write_scene(old, tmp_path / "scene")
    _failing_png_writer(monkeypatch, fail_at=7)
    with pytest.raises(OSError):
        write_scene(make_scene(seed=6), target, overwrite=True)
    assert_same_scene(old, load_scene(target))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


# ---------------------------------------------------------------------------------------------
# Scene and SceneConfig in memory
# ---------------------------------------------------------------------------------------------


def test_config_defaults_follow_the_paper() -> None:
    cfg = SceneConfig()
    assert cfg.dt == 0.05 and cfg.fps == pytest.approx(20.0)
    assert cfg.gravity == (0.0, 0.0, -9.8) and cfg.up == pytest.approx((0.0, 0.0, 1.0))
    full = cfg.resolved(num_views=12, num_frames=24)
    assert full.observed_frames == list(range(16)) and full.held_out_frames == list(range(16, 24))
    assert full.observed_views == list(range(12)) and full.held_out_views == []
    short = cfg.resolved(num_views=2, num_frames=10)
    assert short.observed_frames == list(range(10)) and short.held_out_frames == []
    # one list given: the other is its complement
    held = SceneConfig(held_out_views=[1, 4]).resolved(6, 24)
    assert held.observed_views == [0, 2, 3, 5]
    obs = SceneConfig(observed_frames=[3, 0, 1]).resolved(6, 5)
    assert obs.observed_frames == [0, 1, 3] and obs.held_out_frames == [2, 4]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"dt": -1}, "SceneConfig: dt must be > 0, got -1"),
        ({"dt": "fast"}, "dt must be a finite number of seconds, got 'fast'"),
        ({"gravity": (0, 0)}, "gravity must be 3 finite numbers"),
        ({"gravity": (0, 0, 0), "floor_height": 0.0}, "floor_height needs a non-zero gravity"),
        ({"observed_views": [0, -1]}, "observed_views must hold indices >= 0, got -1"),
        ({"held_out_frames": [2, 2]}, "held_out_frames lists index 2 more than once"),
        ({"metadata": {"f": object()}}, "metadata must be JSON-serialisable"),
    ],
)
def test_config_rejects_bad_values(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        SceneConfig(**kwargs)


def test_scene_rejects_inconsistent_arrays() -> None:
    good = make_scene()
    cams, img, msk = good.cameras, good.images, good.masks
    with pytest.raises(ValueError, match=r"images must have shape \(V, T, H, W, 3\) with V = 3 cameras, got \(2, 5"):
        Scene(cams, img[:2], msk)
    with pytest.raises(ValueError, match=r"masks must have shape \(V, T, H, W\) = \(3, 5, 12, 16\), got \(3, 5, 12, "
                                         r"15\)"):
        Scene(cams, img, msk[..., :15])
    with pytest.raises(ValueError, match=r"images must lie in \[0, 1\], got values in \[0, 2\]"):
        Scene(cams, img * 2, msk)
    with pytest.raises(ValueError, match="masks contains NaN"):
        Scene(cams, img, msk * float("nan"))
    with pytest.raises(ValueError, match="cameras\\[1\\] is 8x12 but the images are 16x12"):
        Scene([cams[0], Camera(cams[1].world_to_camera, cams[1].K, 8, 12), cams[2]], img, msk)
    with pytest.raises(ValueError, match=r"time index 1 → 2 steps by 0.1 s"):
        Scene(cams, img, msk, torch.tensor([0.0, 0.05, 0.15, 0.2, 0.25]))
    with pytest.raises(ValueError, match="extras name 'bad name' is not allowed"):
        Scene(cams, img, msk, extras={"bad name": {"a": torch.zeros(2)}})
    with pytest.raises(ValueError, match="observed_views contains 5, but the scene has 3 views"):
        Scene(cams, img, msk, config=SceneConfig(observed_views=[5]))


def test_subset_renumbers_views_and_frames() -> None:
    scene = make_scene(num_frames=24, held_out_views=[1])
    assert scene.config.observed_frames == list(range(16))
    sub = scene.subset(views=[2, 1], frames=range(12, 20))
    assert sub.num_views == 2 and sub.num_frames == 8
    assert torch.equal(sub.images[0, 3], scene.images[2, 15])
    assert torch.equal(sub.masks[1, 7], scene.masks[1, 19])
    assert torch.equal(sub.times, scene.times[12:20])
    assert sub.cameras[0] is scene.cameras[2]
    assert sub.config.observed_frames == [0, 1, 2, 3] and sub.config.held_out_frames == [4, 5, 6, 7]
    assert sub.config.observed_views == [0] and sub.config.held_out_views == [1]
    with pytest.raises(ValueError, match="frames must be a non-empty range"):
        scene.subset(frames=range(0, 24, 2))


def test_write_rejects_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="layout must be one of rgba, rgb\\+mask, video, got 'gif'"):
        write_scene(make_scene(), tmp_path / "s", layout="gif")
    with pytest.raises(TypeError, match="scene must be a Scene"):
        write_scene({"images": 1}, tmp_path / "s")  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []
    assert LAYOUTS == ("rgba", "rgb+mask", "video")


def test_copy_of_a_written_scene_loads_from_its_new_place(tmp_path: Path) -> None:
    # every path in the JSON files is relative, so a scene folder can be moved
    scene = make_scene()
    out = write_scene(scene, tmp_path / "a")
    shutil.move(str(out), str(tmp_path / "b"))
    assert_same_scene(scene, load_scene(tmp_path / "b"))


def test_sixteen_bit_masks_palette_images_and_moving_to_a_device(tmp_path: Path) -> None:
    w, h = 6, 4
    (tmp_path / "i").mkdir()
    pal = Image.new("P", (w, h))
    pal.putpalette([0, 0, 0, 255, 0, 0] + [0] * 762)
    pal.putpixel((1, 1), 1)  # one red pixel through the palette
    pal.save(tmp_path / "i" / "p.png")
    mask16 = np.zeros((h, w), np.uint16)
    mask16[1, 1] = 65535
    mask16[2, 2] = 32768
    Image.fromarray(mask16).save(tmp_path / "i" / "m16.png")
    c2w = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]
    root = _hand_written(
        tmp_path,
        [
            {
                "file_path": "i/p.png",
                "mask_path": "i/m16.png",
                "transform_matrix": c2w,
                "camera_index": 0,
                "time_index": 0,
            }
        ],
        top={"fl_x": 5.0},
    )
    scene = load_scene(root)
    assert float(scene.masks[0, 0, 1, 1]) == 1.0
    assert math.isclose(float(scene.masks[0, 0, 2, 2]), 32768 / 65535, rel_tol=1e-6)
    assert torch.equal(scene.images[0, 0, 1, 1], torch.tensor([1.0, 0.0, 0.0]))  # red, fully opaque
    assert torch.allclose(scene.images[0, 0, 2, 2], torch.full((3,), 1 - 32768 / 65535))  # black at a ≈ 0.5
    moved = scene.to("cpu")
    assert torch.equal(moved.images, scene.images) and moved.config == scene.config
    with pytest.raises(ValueError, match="dtype must be torch.uint8, torch.float32 or torch.float64"):
        load_scene(root, dtype=torch.int32)


def test_one_odd_image_size_is_one_problem_naming_that_image(written: Path) -> None:
    """A camera's first image of the wrong size must not make every good image after it 'differ'."""
    Image.new("RGBA", (16, 10)).save(written / "images" / "c02_t000.png")
    _, problems = problems_of(written)
    assert len(problems) == 1 and "'images/c02_t000.png' is 16x10" in problems[0]


def test_finished_folders_get_the_usual_permissions_not_mkdtemps_private_ones(tmp_path: Path) -> None:
    import os
    import stat
    import tempfile

    from vid2sim.scene.folder import move_into_place

    old = os.umask(0o022)
    try:
        tmp = Path(tempfile.mkdtemp(dir=tmp_path))  # 0700
        move_into_place(tmp, tmp_path / "out")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755
