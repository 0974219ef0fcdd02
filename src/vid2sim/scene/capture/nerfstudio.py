"""nerfstudio's ``transforms.json``: reading it into capture cameras, and writing it.

Facts of the format (nerfstudio's data conventions): intrinsics ``fl_x fl_y cx cy w h`` and distortion ``k1 k2
k3 k4 p1 p2`` at the top level or per frame (a frame's own values win), ``camera_model`` ``"OPENCV"`` (the default)
or ``"PINHOLE"`` here (fisheye and equirectangular models are refused), one ``frames`` entry per image with a
``file_path`` and a camera-to-world ``transform_matrix`` in OpenGL axes (x right, y up, z backward). The optional
``applied_transform`` (3×4) is the transform nerfstudio applied to the COLMAP world it started from; it is read so
that COLMAP's 3D points can be carried into this frame.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vid2sim.scene.capture.cameras import CaptureCamera, opengl_c2w_to_w2c, w2c_to_opengl_c2w
from vid2sim.scene.capture.errors import CaptureError

SUPPORTED_MODELS = ("OPENCV", "PINHOLE")
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")


def read_transforms(path: str | Path, camera_of_name: Callable[[str], str | None],
                    sizes: dict[str, tuple[int, int]] | None = None) -> tuple[dict[str, CaptureCamera],
                                                                              np.ndarray | None]:
    """Cameras of a nerfstudio ``transforms.json``, keyed by ``camera_of_name(file_path)``.

    Args:
        path: the file.
        camera_of_name: the capture's camera name of a ``file_path`` (None: it matches no camera, an error).
        sizes: (width, height) per camera name, used where the file gives no ``w``/``h``.

    Returns:
        cameras, and the ``applied_transform`` as a (4, 4) matrix (None when absent).

    Raises:
        CaptureError: unreadable JSON, a missing field, an unsupported camera model, a frame matching no camera,
            two frames of one camera (the message names the file and the camera).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CaptureError(f"not valid JSON: {exc}", file=path) from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise CaptureError("expected a JSON object with a non-empty 'frames' list", file=path)
    applied = None
    if "applied_transform" in data:
        m = np.asarray(data["applied_transform"], dtype=np.float64)
        if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
            raise CaptureError(f"applied_transform must be a 3x4 matrix, got shape {m.shape}", file=path)
        applied = np.eye(4)
        applied[:3] = m[:3]
    cameras: dict[str, CaptureCamera] = {}
    for i, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise CaptureError(f"frames[{i}] needs 'file_path' and 'transform_matrix'", file=path)
        file_path = str(frame["file_path"])
        name = camera_of_name(file_path)
        if name is None:
            raise CaptureError(f"frames[{i}]: file_path {file_path!r} matches no camera of the capture (its stem "
                               "must be a camera name: videos/<cam>.mp4 or frames/<cam>/)", file=path)
        if name in cameras:
            raise CaptureError(f"frames[{i}]: a second frame of this camera ({cameras[name].image_name} and "
                               f"{file_path}); a capture calibration has one frame per camera", camera=name, file=path)
        values: dict[str, Any] = {k: data[k] for k in _INTRINSICS if k in data}
        values.update({k: frame[k] for k in _INTRINSICS if k in frame})
        model = str(values.get("camera_model", "OPENCV"))
        if model not in SUPPORTED_MODELS:
            raise CaptureError(f"unknown camera model {model!r}; vid2sim reads {', '.join(SUPPORTED_MODELS)}",
                               camera=name, file=path)
        try:
            nums = {k: float(v) for k, v in values.items() if k != "camera_model"}
        except (TypeError, ValueError):
            raise CaptureError(f"frames[{i}]: intrinsics must be numbers", camera=name, file=path) from None
        if "w" not in nums or "h" not in nums:
            if sizes is None or name not in sizes:
                raise CaptureError(f"frames[{i}]: no image size (w, h)", camera=name, file=path)
            nums.setdefault("w", sizes[name][0])
            nums.setdefault("h", sizes[name][1])
        for key in ("fl_x", "cx", "cy"):
            if key not in nums:
                raise CaptureError(f"frames[{i}]: '{key}' is missing", camera=name, file=path)
        if model == "PINHOLE" and any(nums.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")):
            raise CaptureError("camera_model PINHOLE with distortion coefficients; use OPENCV", camera=name, file=path)
        if nums.get("k4", 0.0):
            raise CaptureError("k4 is not part of the OPENCV model vid2sim reads (k1 k2 k3 p1 p2)", camera=name,
                               file=path)
        fx = nums["fl_x"]
        fy = nums.get("fl_y", fx)
        K = np.array([[fx, 0.0, nums["cx"]], [0.0, fy, nums["cy"]], [0.0, 0.0, 1.0]])
        dist = np.array([nums.get("k1", 0.0), nums.get("k2", 0.0), nums.get("p1", 0.0), nums.get("p2", 0.0),
                         nums.get("k3", 0.0)])
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise CaptureError(f"frames[{i}]: transform_matrix must be a 4x4 matrix", camera=name, file=path)
        R = c2w[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise CaptureError(f"frames[{i}]: transform_matrix is not a rigid transform (its 3x3 block must be a "
                               "rotation)", camera=name, file=path)
        cameras[name] = CaptureCamera(name, int(nums["w"]), int(nums["h"]), K, dist, opengl_c2w_to_w2c(c2w),
                                      model=model, source=str(path), image_name=file_path)
    return cameras, applied


def write_transforms(cameras: Sequence[CaptureCamera], path: str | Path, image_folder: str = "background",
                     image_suffix: str = ".png") -> None:
    """Write a nerfstudio ``transforms.json`` (camera model OPENCV, intrinsics per frame) with one frame per
    camera, ``file_path`` ``<image_folder>/<name><suffix>``."""
    frames = []
    for cam in cameras:
        k1, k2, p1, p2, k3 = (float(v) for v in cam.distortion)
        intr = {"fl_x": float(cam.K[0, 0]), "fl_y": float(cam.K[1, 1]), "cx": float(cam.K[0, 2]),
                "cy": float(cam.K[1, 2]), "w": cam.width, "h": cam.height, "k1": k1, "k2": k2, "k3": k3,
                "p1": p1, "p2": p2}
        frame = {"file_path": f"{image_folder}/{cam.name}{image_suffix}",
                 "transform_matrix": w2c_to_opengl_c2w(cam.world_to_camera).tolist()}
        frames.append({**frame, **intr})
    Path(path).write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=2) + "\n")
