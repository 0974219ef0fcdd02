"""Video files: lossy and lossless round trips through the bundled ffmpeg, errors, atomic writes,
and the per-camera video layout of scene folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vid2sim.scene.folder import Scene, SceneConfig
from vid2sim.scene.reading import load_scene
from vid2sim.scene.validation import SceneFormatError
from vid2sim.scene.video import (
    VideoError,
    load_video,
    probe_video,
    read_video,
    write_video,
)
from vid2sim.scene.writing import write_scene
from vid2sim.splats.cameras import camera_ring


def _have_ffmpeg() -> bool:
    try:
        import imageio_ffmpeg

        return Path(imageio_ffmpeg.get_ffmpeg_exe()).exists()
    except Exception:  # noqa: BLE001 - any failure means: no usable ffmpeg
        return False


pytestmark = pytest.mark.skipif(not _have_ffmpeg(), reason="imageio-ffmpeg's ffmpeg binary is not available")


def smooth_frames(T: int, H: int, W: int) -> np.ndarray:
    """(T, H, W, 3) float32 smooth colour fields in [0.1, 0.9] (what video codecs keep well)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = [
        np.stack(
            [
                0.5 + 0.4 * np.sin(x / 9.0 + 0.3 * t),
                0.5 + 0.4 * np.cos(y / 7.0 - 0.2 * t),
                0.5 + 0.4 * np.sin((x + y) / 13.0 + 0.1 * t),
            ],
            axis=-1,
        )
        for t in range(T)
    ]
    return np.stack(frames).astype(np.float32)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.double() - b.double()) ** 2).mean())
    return 10.0 * np.log10(1.0 / mse)


def test_lossy_round_trip_of_smooth_video(tmp_path: Path) -> None:
    frames = smooth_frames(6, 32, 48)
    path = write_video(tmp_path / "v.mp4", frames, fps=20)
    back, info = load_video(path)
    assert back.shape == (6, 32, 48, 3) and back.dtype == torch.float32
    assert (info.width, info.height, info.num_frames, info.fps) == (48, 32, 6, 20.0)
    assert info.codec == "h264"
    ref = torch.from_numpy(frames)
    assert psnr(back, ref) > 35.0
    assert float((back - ref).abs().mean()) < 0.008  # ~1 grey level with accurate colour conversion
    assert probe_video(path) == info
    assert torch.equal(read_video(path, dtype=torch.uint8), torch.round(back * 255).to(torch.uint8))


def test_odd_sizes_and_fractional_fps(tmp_path: Path) -> None:
    frames = smooth_frames(4, 17, 23)  # odd: encoded as yuv444p, no resizing
    path = write_video(tmp_path / "odd.mp4", frames, fps=29.97)
    back, info = load_video(path)
    assert back.shape == (4, 17, 23, 3)
    assert info.fps == pytest.approx(29.97, rel=1e-4)
    assert psnr(back, torch.from_numpy(frames)) > 35.0


def test_encoders_pass_ffmpeg_a_plain_float_rate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """imageio-ffmpeg 0.6 (what ``imageio-ffmpeg>=0.4.9`` allows; the GPU check's wheel) asserts that ``fps`` is a
    float or an int: a ``Fraction`` crashed the report's and the simulation's videos on first use there. Both
    encoders run here under that contract."""
    import imageio_ffmpeg

    from vid2sim.report import media
    from vid2sim.scene.video import ffmpeg_rate

    real, rates = imageio_ffmpeg.write_frames, []

    def strict(path, size, *args, fps=16, **kwargs):
        assert type(fps) in (float, int), f"fps must be float, got {type(fps).__name__}"
        rates.append(fps)
        return real(path, size, *args, fps=fps, **kwargs)

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", strict)
    frames = smooth_frames(3, 16, 16)
    write_video(tmp_path / "a.mp4", frames, fps=30000 / 1001)
    media.encode_video(tmp_path / "b", frames, fps=5, fmt="webm")
    assert rates == [ffmpeg_rate(30000 / 1001), 5.0]
    assert ffmpeg_rate(30000 / 1001) == 30000 / 1001 and ffmpeg_rate(1 / 0.05) == 20.0
    assert probe_video(tmp_path / "a.mp4").fps == pytest.approx(30000 / 1001, rel=1e-4)  # ffprobe prints 29.97


def test_lossless_round_trip_is_bit_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (5, 15, 22, 3), dtype=np.uint8)  # worst case for a codec
    back = read_video(write_video(tmp_path / "n.mp4", noise, fps=20, lossless=True), dtype=torch.uint8)
    assert torch.equal(back, torch.from_numpy(noise))
    grey = (rng.random((5, 15, 22)) > 0.5).astype(np.float32)  # (T, H, W) grey → replicated channels
    back = read_video(write_video(tmp_path / "g.mkv", grey, fps=20, lossless=True))
    assert torch.equal(back, torch.from_numpy(grey)[..., None].expand(-1, -1, -1, 3))


def test_bad_input_is_rejected_clearly(tmp_path: Path) -> None:
    frames = smooth_frames(2, 8, 8)
    with pytest.raises(ValueError, match=r"frames must have shape \(T, H, W, 3\) or \(T, H, W\), got \(8, 8\)"):
        write_video(tmp_path / "a.mp4", frames[0, ..., 0], fps=20)
    with pytest.raises(ValueError, match=r"float frames must lie in \[0, 1\], got values in"):
        write_video(tmp_path / "a.mp4", frames * 3, fps=20)
    with pytest.raises(ValueError, match="fps must be a positive number, got 0"):
        write_video(tmp_path / "a.mp4", frames, fps=0)
    with pytest.raises(ValueError, match=r"quality must be in \[1, 10\], got 0"):
        write_video(tmp_path / "a.mp4", frames, fps=20, quality=0)
    with pytest.raises(VideoError, match="folder '.*missing' does not exist"):
        write_video(tmp_path / "missing" / "a.mp4", frames, fps=20)
    with pytest.raises(VideoError, match=r"video file '.*nothing.mp4' not found"):
        read_video(tmp_path / "nothing.mp4")
    (tmp_path / "junk.mp4").write_bytes(b"\x00\x01 definitely not a video" * 10)
    with pytest.raises(VideoError, match=r"cannot read video '.*junk.mp4'"):
        read_video(tmp_path / "junk.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mp4"]


def test_failed_encode_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import imageio_ffmpeg

    real = imageio_ffmpeg.write_frames
    partial_files: list[bool] = []

    def dying_writer(path, *args, **kwargs):
        gen = real(path, *args, **kwargs)

        def wrapped():
            gen.send(None)  # start ffmpeg: it creates the (temporary) output file
            sent = 0
            while True:
                frame = yield
                if sent == 2:
                    gen.close()  # ffmpeg finishes a truncated file ...
                    partial_files.append(Path(path).is_file() and Path(path).stat().st_size > 0)
                    raise BrokenPipeError("ffmpeg died (simulated)")  # ... and the caller sees a failure
                gen.send(frame)
                sent += 1

        return wrapped()

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", dying_writer)
    with pytest.raises(VideoError, match="cannot write video '.*v.mp4': ffmpeg died"):
        write_video(tmp_path / "v.mp4", smooth_frames(5, 16, 16), fps=20)
    assert partial_files == [True]  # a truncated temporary file existed ...
    assert list(tmp_path.iterdir()) == []  # ... and was removed; nothing at the target


# ---------------------------------------------------------------------------------------------
# the video layout of scene folders
# ---------------------------------------------------------------------------------------------


def video_scene(V: int = 2, T: int = 4, H: int = 24, W: int = 32) -> Scene:
    colour = torch.from_numpy(np.stack([smooth_frames(T, H, W) for _ in range(V)]))
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    masks = torch.stack(
        [
            torch.stack([(((x - 12 - 2 * t - 3 * v) ** 2 + (y - 12) ** 2) < 64).float() for t in range(T)])
            for v in range(V)
        ]
    )
    images = colour * masks[..., None] + (1 - masks[..., None])
    cams = camera_ring(V, 2.0, 15.0, W, H)
    return Scene(cams, images, masks, torch.arange(T) * 0.05 + 0.5, SceneConfig(metadata={"E": 1e5}))


def test_scene_video_layout_round_trip(tmp_path: Path) -> None:
    scene = video_scene()
    out = write_scene(scene, tmp_path / "s", layout="video")  # default quality 9, full-resolution chroma
    assert sorted(p.name for p in (out / "videos").iterdir()) == ["c00.mp4", "c00_mask.mp4", "c01.mp4", "c01_mask.mp4"]
    loaded = load_scene(out)
    assert torch.equal(loaded.masks, scene.masks)  # masks travel losslessly
    inside = scene.masks > 0
    err = (loaded.images - scene.images).abs()
    assert float(err[inside].mean()) < 0.01  # lossy colour inside the object (measured 0.006)
    assert float(err[inside].max()) < 0.08  # no colour bleeding from the white background (yuv444p)
    assert torch.equal(loaded.images[~inside], scene.images[~inside])  # background is exactly white
    assert torch.allclose(loaded.times, scene.times)
    for a, b in zip(scene.cameras, loaded.cameras):
        assert torch.allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
        assert torch.allclose(a.K, b.K, atol=1e-6)
    assert loaded.config == scene.config


def _video_folder(tmp_path: Path, fps: float = 20.0, n_masks: int = 4) -> Path:
    """A hand-written videos-layout folder: one RGB mp4 per camera + one mask PNG per frame."""
    root = tmp_path / "rig"
    (root / "cam0").mkdir(parents=True)
    write_video(root / "cam0" / "rgb.mp4", smooth_frames(4, 16, 16), fps=fps)
    mask = np.zeros((16, 16), np.uint8)
    mask[4:12, 5:11] = 255
    for t in range(n_masks):
        Image.fromarray(np.roll(mask, t, axis=1)).save(root / "cam0" / f"mask_{t}.png")
    transforms = {
        "fl_x": 20.0,
        "videos": [
            {
                "camera_index": 0,
                "video_path": "cam0/rgb.mp4",
                "mask_paths": [f"cam0/mask_{t}.png" for t in range(n_masks)],
                "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.5], [0, 0, 0, 1]],
            }
        ],
    }
    (root / "transforms.json").write_text(json.dumps(transforms))
    (root / "scene.json").write_text(json.dumps({"dt": 0.05}))
    return root


def test_video_with_mask_images(tmp_path: Path) -> None:
    scene = load_scene(_video_folder(tmp_path))
    assert scene.images.shape == (1, 4, 16, 16, 3)
    assert float(scene.masks[0, 2, 4, 7]) == 1.0 and float(scene.masks[0, 2, 4, 6]) == 0.0
    assert torch.equal(scene.images[0][scene.masks[0] == 0], torch.ones(int((scene.masks[0] == 0).sum()), 3))
    ref = torch.from_numpy(smooth_frames(4, 16, 16))
    inside = scene.masks[0] > 0
    assert float((scene.images[0] - ref).abs()[inside].mean()) < 0.02
    assert torch.allclose(scene.cameras[0].K, torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]))


def test_video_frame_rate_and_mask_count_are_checked(tmp_path: Path) -> None:
    root = _video_folder(tmp_path / "a", fps=30.0)
    with pytest.raises(SceneFormatError) as info:
        load_scene(root)
    assert (
        "transforms.json: videos[0] (camera 0): video 'cam0/rgb.mp4' runs at 30 fps but scene.json has dt = 0.05 s "
        "(20 fps)" in str(info.value)
    )
    root = _video_folder(tmp_path / "b", n_masks=3)
    with pytest.raises(SceneFormatError, match=r"mask_paths lists 3 files but video 'cam0/rgb.mp4' has 4 frames"):
        load_scene(root)
