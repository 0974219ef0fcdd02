"""A simulated sequence (a folder of per-frame 3DGS PLYs) as one glTF/GLB or PLY file per frame.

Why one file per frame: ``KHR_gaussian_splatting`` has no time axis, and core glTF can only animate node
transforms — a rigid motion, not a deformation — so a deforming splat sequence cannot be one animated glTF.
A single glTF with one node per frame would show every frame at once in every viewer (hiding nodes needs
``KHR_node_visibility`` or zero scales, which the splat extension leaves undefined). Numbered files open in
every viewer that opens one frame, and ``sequence.json`` lists them with the frame time for players.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np

from vid2sim.export.gltf import export_gltf
from vid2sim.runtime.errors import InputError
from vid2sim.scene.writing import move_into_place
from vid2sim.splats.ply import load_ply

SEQUENCE_FORMAT = "vid2sim-sequence"
SEQUENCE_VERSION = 1
_FRAME = re.compile(r"^(\d+)\.ply$")


def find_sequence_frames(folder: str | Path) -> list[Path]:
    """The per-frame PLYs of a simulate output folder (``ply/0000.ply``, ``ply/0001.ply``, …) in frame order,
    or [] when ``folder`` has none."""
    ply = Path(folder) / "ply"
    if not ply.is_dir():
        return []
    frames = [(int(m.group(1)), p) for p in ply.iterdir() if (m := _FRAME.match(p.name)) and p.is_file()]
    return [p for _, p in sorted(frames)]


def sequence_metadata(folder: str | Path) -> dict[str, object]:
    """``dt`` (s) and ``gravity`` (m/s²) of a simulate output when one of its top-level JSON files records them
    (``summary.json`` of ``vid2sim simulate``: ``dt`` and a ``gravity`` entry in ``externals``; or top-level
    ``dt``/``gravity`` keys) or ``states.npz`` has ``dt``; missing values are None."""
    folder = Path(folder)
    meta: dict[str, object] = {"dt": None, "gravity": None}
    for path in sorted(folder.glob("*.json")):
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if not isinstance(doc, dict):
            continue
        for key in ("dt", "gravity"):
            value = doc.get(key)
            if meta[key] is None and value is not None:
                meta[key] = value
        externals = doc.get("externals")  # vid2sim simulate's summary.json: [{"type": "gravity", "acceleration": g}]
        if meta["gravity"] is None and isinstance(externals, list):
            for ext in externals:
                if isinstance(ext, dict) and ext.get("type") == "gravity":
                    meta["gravity"] = ext.get("acceleration")
    states = folder / "states.npz"
    if meta["dt"] is None and states.is_file():
        try:
            with np.load(states, allow_pickle=False) as z:
                if "dt" in z.files:
                    meta["dt"] = float(z["dt"])
        except (OSError, ValueError):
            pass
    g = meta["gravity"]
    if not (isinstance(g, list) and len(g) == 3 and all(isinstance(v, (int, float)) for v in g)):
        meta["gravity"] = None
    if not isinstance(meta["dt"], (int, float)):
        meta["dt"] = None
    return meta


def export_sequence(source: str | Path, out: str | Path, fmt: str = "glb", *,
                    up: Iterable[float] | None = None, fallback_color: bool = True, progress: bool = True) -> Path:
    """Export every frame of a simulate output folder into the folder ``out`` (atomically; replaced if it exists).

    Args:
        source: a folder with ``ply/NNNN.ply`` frames.
        out: output folder: ``NNNN.glb`` / ``NNNN.gltf`` + ``NNNN.bin`` / ``NNNN.ply`` per frame and
            ``sequence.json`` (format, frame files in order, dt, up, source).
        fmt: ``"glb"``, ``"gltf"`` or ``"ply"``.
        up: the scene's up direction for the glTF frame; default −gravity from the source's metadata, else +Z.
        fallback_color: glTF ``COLOR_0`` fallback (see :func:`vid2sim.export.gltf.build_gltf`).
        progress: tqdm progress bar.
    Raises:
        ValueError: an unknown format or a folder without frames.
    """
    from tqdm import tqdm


    if fmt not in ("glb", "gltf", "ply"):
        raise InputError(f"sequence format must be 'glb', 'gltf' or 'ply', got {fmt!r}")
    source, out = Path(source), Path(out)
    frames = find_sequence_frames(source)
    if not frames:
        raise InputError(f"{source}: no per-frame PLYs (expected {source / 'ply'}/0000.ply, 0001.ply, ...)")
    meta = sequence_metadata(source)
    if up is None:
        g = meta["gravity"]
        up = (0.0, 0.0, 1.0) if g is None or not any(g) else tuple(-float(v) for v in g)  # type: ignore[union-attr]
    up_arr = np.asarray(list(up), dtype=np.float64)
    up = tuple(float(v) for v in up_arr / (np.linalg.norm(up_arr) or 1.0) + 0.0)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        names = []
        for i, frame in enumerate(tqdm(frames, desc="export frames", disable=not progress)):
            name = f"{i:04d}.{fmt}"
            if fmt == "ply":
                shutil.copyfile(frame, tmp / name)
            else:
                export_gltf(load_ply(frame), tmp / name, up=up, fallback_color=fallback_color, name=f"frame_{i:04d}",
                            extras={"frame": i, "source": str(frame)})
            names.append(name)
        index = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "file_format": fmt, "frames": names,
                 "dt": meta["dt"], "up": list(up), "source": str(source.resolve()),
                 "frame": ("glTF y-up (the scene's up rotated to +Y, baked into the data)" if fmt != "ply"
                           else "the scene's world frame, as simulated")}
        (tmp / "sequence.json").write_text(json.dumps(index, indent=2))
        move_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
