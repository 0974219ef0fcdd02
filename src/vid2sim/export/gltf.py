"""Gaussians as glTF 2.0 with the Khronos ``KHR_gaussian_splatting`` extension (docs/export.md).

Written against the extension's README and JSON schema in KhronosGroup/glTF at commit
77b44be7bef26e01fb0b140e3d5bb1716421c5e9 (extension text last changed in 63770cc, "Editorial review",
2026-04-15; status "Release Candidate" in that tree, "Complete, Ratified" on the published page). One
mesh with one ``POINTS`` primitive; every splat property is a separate tightly packed float accessor:

| our Gaussians (vid2sim)             | glTF attribute                              | accessor            |
|-------------------------------------|---------------------------------------------|---------------------|
| ``means`` (rotated to y-up)         | ``POSITION`` (with ``min``/``max``)          | VEC3 float          |
| ``quats`` (w,x,y,z), normalised     | ``KHR_gaussian_splatting:ROTATION`` (x,y,z,w) | VEC4 float          |
| ``exp(log_scales)``                 | ``KHR_gaussian_splatting:SCALE`` (linear)    | VEC3 float          |
| ``sigmoid(opacity_logits)``         | ``KHR_gaussian_splatting:OPACITY`` (linear)  | SCALAR float        |
| ``sh[:, 0]``                        | ``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0`` | VEC3 float          |
| ``sh[:, l² + n]`` (rotated)         | ``KHR_gaussian_splatting:SH_DEGREE_l_COEF_n`` | VEC3 float          |
| clamp(C0·sh0 + 0.5) → linear, opacity | ``COLOR_0`` (fallback point colour)        | VEC4 ubyte normalized |

vid2sim's SH basis, order (m = −l … l), Condon–Shortley signs and the +0.5 DC bias are the spec's, so the
coefficients are stored unchanged apart from the frame rotation. Colours are display-encoded sRGB (the
images are fitted as stored), hence ``colorSpace: "srgb_rec709_display"``.

The scene frame (z up, or up = −gravity) is turned into glTF's y-up frame by baking the rotation into
positions, quaternions and SH coefficients (:mod:`vid2sim.export.transform`); the node has no transform.
``asset.extras.vid2sim.gltf_from_world`` records the rotation so :func:`load_gltf_gaussians` can return
the Gaussians in the frame they were exported from.
"""

from __future__ import annotations

import base64
import json
import os
import struct
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vid2sim import __version__
from vid2sim.export.transform import (
    check_rotation,
    quat_multiply,
    quat_to_rotmat_np,
    rotate_gaussian_arrays,
    rotate_sh,
    rotation_to_y_up,
    rotmat_to_quat_np,
)
from vid2sim.runtime.errors import InputError
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.sh import C0, num_sh_bases

EXTENSION = "KHR_gaussian_splatting"
UNLIT = "KHR_materials_unlit"
SPEC_COMMIT = "77b44be7bef26e01fb0b140e3d5bb1716421c5e9"
COLOR_SPACE = "srgb_rec709_display"

ATTR_ROTATION = f"{EXTENSION}:ROTATION"
ATTR_SCALE = f"{EXTENSION}:SCALE"
ATTR_OPACITY = f"{EXTENSION}:OPACITY"


def sh_attribute(degree: int, coef: int) -> str:
    """The attribute semantic of SH coefficient ``coef`` (0 … 2·degree) of ``degree``."""
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{coef}"


# glTF constants
FLOAT, UNSIGNED_BYTE, BYTE, SHORT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5121, 5120, 5122, 5123, 5125
ARRAY_BUFFER = 34962
POINTS = 0
GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
_COMPONENT_DTYPES = {BYTE: "<i1", UNSIGNED_BYTE: "<u1", SHORT: "<i2", UNSIGNED_SHORT: "<u2",
                     UNSIGNED_INT: "<u4", FLOAT: "<f4"}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class GltfFormatError(InputError):
    """A glTF file that is not readable as Gaussians (the message names the file and the problem)."""


def _align4(n: int) -> int:
    return (n + 3) & ~3


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _gaussian_arrays(gaussians: Gaussians, gltf_from_world: np.ndarray) -> dict[str, np.ndarray]:
    """The attribute arrays (float32 / uint8, C-contiguous) of ``gaussians`` in the glTF frame."""
    if not isinstance(gaussians, Gaussians):
        raise TypeError(f"gaussians must be a vid2sim Gaussians, got {type(gaussians).__name__}")
    if gaussians.num == 0:
        raise InputError("cannot export 0 Gaussians to glTF (accessors need count >= 1)")
    g = gaussians.detach().to("cpu", torch.float64)
    for name, t in g.tensors().items():
        if not bool(torch.isfinite(t).all()):
            raise InputError(f"Gaussians.{name} holds NaN or infinite values; cannot export")
    quats = g.quats.numpy()
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    if np.any(norms == 0):
        raise InputError(f"{int((norms == 0).sum())} Gaussians have a zero quaternion; cannot export")
    means, quats, sh = rotate_gaussian_arrays(g.means.numpy(), quats / norms, g.sh.numpy(), gltf_from_world)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    out: dict[str, np.ndarray] = {
        "POSITION": means.astype("<f4"),
        ATTR_ROTATION: quats[:, [1, 2, 3, 0]].astype("<f4"),  # glTF order (x, y, z, w)
        ATTR_SCALE: np.exp(g.log_scales.numpy()).astype("<f4"),
        ATTR_OPACITY: (1.0 / (1.0 + np.exp(-g.opacity_logits.numpy()))).astype("<f4"),
    }
    degree = g.sh_degree
    for lvl in range(degree + 1):
        for n in range(2 * lvl + 1):
            out[sh_attribute(lvl, n)] = sh[:, lvl * lvl + n, :].astype("<f4")
    return out


def _fallback_color(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """COLOR_0 per the spec's fallback note: clamp(C0·SH0 + 0.5, 0, 1) decoded from sRGB, alpha = opacity."""
    rgb = _srgb_to_linear(np.clip(C0 * arrays[sh_attribute(0, 0)].astype(np.float64) + 0.5, 0.0, 1.0))
    rgba = np.concatenate([rgb, arrays[ATTR_OPACITY].astype(np.float64)[:, None]], axis=1)
    return np.round(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8)


def build_gltf(gaussians: Gaussians, *, up: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0),
               fallback_color: bool = True, name: str = "gaussians",
               extras: dict[str, Any] | None = None) -> tuple[dict[str, Any], bytes]:
    """The glTF JSON document and its binary buffer for ``gaussians`` (see the module docstring).

    Args:
        gaussians: N ≥ 1 Gaussians in the scene frame (metres).
        up: the scene's up direction (−gravity); rotated to glTF's +Y.
        fallback_color: also write ``COLOR_0`` (and an unlit material) so viewers without the extension
            show a coloured point cloud.
        name: mesh and node name.
        extras: JSON-serialisable values stored under ``asset.extras.vid2sim``.
    Returns:
        (gltf JSON dict with ``buffers[0]`` lacking a ``uri``, the buffer bytes, length a multiple of 4).
    """
    rot = rotation_to_y_up(up)
    up_unit = np.asarray(up, dtype=np.float64).reshape(3)
    up_unit = up_unit / np.linalg.norm(up_unit) + 0.0  # + 0.0: no -0.0 in the JSON
    arrays = _gaussian_arrays(gaussians, rot)
    n = gaussians.num
    if fallback_color:
        arrays["COLOR_0"] = _fallback_color(arrays)
    accessor_specs = {  # attribute → (type, componentType, normalized)
        "POSITION": ("VEC3", FLOAT, False), ATTR_ROTATION: ("VEC4", FLOAT, False),
        ATTR_SCALE: ("VEC3", FLOAT, False), ATTR_OPACITY: ("SCALAR", FLOAT, False),
        "COLOR_0": ("VEC4", UNSIGNED_BYTE, True),
    }
    chunks: list[bytes] = []
    offset = 0
    buffer_views: list[dict[str, Any]] = []
    accessors: list[dict[str, Any]] = []
    attributes: dict[str, int] = {}
    for attr, data in arrays.items():
        kind, ctype, normalized = accessor_specs.get(attr, ("VEC3", FLOAT, False))
        raw = np.ascontiguousarray(data).tobytes()
        buffer_views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": ARRAY_BUFFER})
        acc: dict[str, Any] = {"bufferView": len(buffer_views) - 1, "componentType": ctype, "count": n, "type": kind}
        if normalized:
            acc["normalized"] = True
        if attr == "POSITION":  # required by the glTF spec; exact float32 bounds of the stored values
            acc["min"] = [float(v) for v in data.min(axis=0)]
            acc["max"] = [float(v) for v in data.max(axis=0)]
        accessors.append(acc)
        attributes[attr] = len(accessors) - 1
        padded = _align4(len(raw))
        chunks.append(raw + b"\x00" * (padded - len(raw)))
        offset += padded
    primitive: dict[str, Any] = {
        "attributes": attributes,
        "mode": POINTS,
        "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": COLOR_SPACE,
                                   "projection": "perspective", "sortingMethod": "cameraDistance"}},
    }
    used = [EXTENSION]
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": f"vid2sim {__version__}",
                  "extras": {"vid2sim": {"gltf_from_world": rot.tolist(), "world_up": up_unit.tolist(),
                                         "sh_degree": gaussians.sh_degree, "spec_commit": SPEC_COMMIT,
                                         **(extras or {})}}},
        "extensionsUsed": used,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": [primitive]}],
        "accessors": accessors,
        "bufferViews": buffer_views,
        "buffers": [{"byteLength": offset}],
    }
    if fallback_color:
        # the splat renderer ignores the material (spec); a point-cloud fallback shows COLOR_0 unlit
        primitive["material"] = 0
        doc["materials"] = [{"name": "splat_fallback", "pbrMetallicRoughness": {"metallicFactor": 0.0},
                             "extensions": {UNLIT: {}}}]
        used.append(UNLIT)
    return doc, b"".join(chunks)


def glb_bytes(doc: dict[str, Any], binary: bytes) -> bytes:
    """A GLB container (header, JSON chunk padded with spaces, BIN chunk padded with zeros)."""
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (_align4(len(js)) - len(js))
    binary += b"\x00" * (_align4(len(binary)) - len(binary))
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([struct.pack("<III", GLB_MAGIC, GLB_VERSION, total), struct.pack("<II", len(js), CHUNK_JSON), js,
                     struct.pack("<II", len(binary), CHUNK_BIN), binary])


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def export_gltf(gaussians: Gaussians, path: str | os.PathLike, *,
                up: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0), fallback_color: bool = True,
                name: str = "gaussians", extras: dict[str, Any] | None = None) -> list[Path]:
    """Write ``gaussians`` as glTF with ``KHR_gaussian_splatting``: ``.glb`` (one binary file) or
    ``.gltf`` (JSON) + ``<stem>.bin`` beside it. Each file is written atomically (the ``.gltf`` last).

    Args:
        gaussians, up, fallback_color, name, extras: see :func:`build_gltf`.
        path: ``*.glb`` or ``*.gltf``.
    Returns:
        the files written.
    Raises:
        ValueError: another suffix, no Gaussians, or non-finite values.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise InputError(f"{path}: a glTF export must end in .glb (binary) or .gltf (JSON + .bin), got {suffix!r}")
    doc, binary = build_gltf(gaussians, up=up, fallback_color=fallback_color, name=name, extras=extras)
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".glb":
        _write_atomic(path, glb_bytes(doc, binary))
        return [path]
    bin_path = path.with_suffix(".bin")
    doc["buffers"][0]["uri"] = bin_path.name
    _write_atomic(bin_path, binary)
    _write_atomic(path, json.dumps(doc, indent=1).encode("utf-8"))
    return [path, bin_path]


# ---- reading ------------------------------------------------------------------------------------------

def read_gltf(path: str | os.PathLike) -> tuple[dict[str, Any], list[bytes]]:
    """Parse a ``.glb`` or ``.gltf`` file: (JSON document, the bytes of each buffer).

    Buffers may be the GLB BIN chunk, a file next to the ``.gltf`` or a base64 ``data:`` URI.

    Raises:
        GltfFormatError: missing file, bad GLB header or chunk, invalid JSON, or a missing buffer.
    """
    path = Path(path)
    if not path.is_file():
        raise GltfFormatError(f"{path}: no such glTF file")
    raw = path.read_bytes()
    glb_bin: bytes | None = None
    if raw[:4] == b"glTF":
        if len(raw) < 20:
            raise GltfFormatError(f"{path}: GLB file is truncated ({len(raw)} bytes)")
        _, version, total = struct.unpack_from("<III", raw, 0)
        if version != 2:
            raise GltfFormatError(f"{path}: GLB version {version} is not supported (expected 2)")
        if total > len(raw):
            raise GltfFormatError(f"{path}: GLB header says {total} bytes, the file has {len(raw)}")
        pos, doc_bytes = 12, None
        while pos + 8 <= total:
            length, ctype = struct.unpack_from("<II", raw, pos)
            body = raw[pos + 8:pos + 8 + length]
            if len(body) != length:
                raise GltfFormatError(f"{path}: GLB chunk at byte {pos} is truncated")
            if ctype == CHUNK_JSON and doc_bytes is None:
                doc_bytes = body
            elif ctype == CHUNK_BIN and glb_bin is None:
                glb_bin = body
            pos += 8 + length
        if doc_bytes is None:
            raise GltfFormatError(f"{path}: GLB file has no JSON chunk")
    else:
        doc_bytes = raw
    try:
        doc = json.loads(doc_bytes.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GltfFormatError(f"{path}: the glTF JSON is invalid ({exc})") from None
    if not isinstance(doc, dict) or not str(doc.get("asset", {}).get("version", "")).startswith("2."):
        raise GltfFormatError(f"{path}: not a glTF 2.x document (asset.version is missing or not 2.x)")
    buffers = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if glb_bin is None:
                raise GltfFormatError(f"{path}: buffers[{i}] has no uri and the file has no GLB BIN chunk")
            data = glb_bin
        elif uri.startswith("data:"):
            try:
                data = base64.b64decode(uri.split(",", 1)[1])
            except (IndexError, ValueError) as exc:
                raise GltfFormatError(f"{path}: buffers[{i}] has an invalid data: URI ({exc})") from None
        else:
            from urllib.parse import unquote

            bin_path = path.parent / unquote(uri)
            if not bin_path.is_file():
                raise GltfFormatError(f"{path}: buffers[{i}] refers to {bin_path}, which does not exist")
            data = bin_path.read_bytes()
        if len(data) < int(buf.get("byteLength", 0)):
            raise GltfFormatError(
                f"{path}: buffers[{i}] has {len(data)} bytes, byteLength says {buf.get('byteLength')}"
            )
        buffers.append(data)
    return doc, buffers


def read_accessor(doc: dict[str, Any], buffers: list[bytes], index: int, where: str = "") -> np.ndarray:
    """Accessor ``index`` as float64 ``(count, components)``, normalized integers mapped per glTF 2.0
    (unsigned: c / (2^b − 1); signed: max(c / (2^(b−1) − 1), −1)); byteStride honoured.

    Raises:
        GltfFormatError: a missing accessor/bufferView, sparse storage, or data beyond the buffer.
    """
    try:
        acc = doc["accessors"][index]
    except (KeyError, IndexError, TypeError):
        raise GltfFormatError(f"{where}accessor {index} does not exist") from None
    if "sparse" in acc:
        raise GltfFormatError(f"{where}accessor {index} is sparse; sparse accessors are not supported")
    ctype, kind, count = acc.get("componentType"), acc.get("type"), int(acc.get("count", 0))
    if ctype not in _COMPONENT_DTYPES or kind not in _TYPE_SIZES:
        raise GltfFormatError(f"{where}accessor {index} has componentType {ctype} / type {kind!r}, not readable")
    comps = _TYPE_SIZES[kind]
    dtype = np.dtype(_COMPONENT_DTYPES[ctype])
    if "bufferView" not in acc:
        values = np.zeros((count, comps))
    else:
        try:
            view = doc["bufferViews"][acc["bufferView"]]
            data = buffers[view["buffer"]]
        except (KeyError, IndexError, TypeError):
            raise GltfFormatError(f"{where}accessor {index} refers to a missing bufferView or buffer") from None
        start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
        elem = dtype.itemsize * comps
        stride = int(view.get("byteStride", 0)) or elem
        needed = start + (stride * (count - 1) + elem if count else 0)
        if needed > int(view.get("byteOffset", 0)) + int(view["byteLength"]) or needed > len(data):
            raise GltfFormatError(f"{where}accessor {index} reads beyond its bufferView/buffer")
        if stride == elem:
            values = np.frombuffer(data, dtype=dtype, count=count * comps, offset=start).reshape(count, comps)
        else:
            values = np.lib.stride_tricks.as_strided(np.frombuffer(data, dtype=np.uint8, offset=start),
                                                     shape=(count, elem), strides=(stride, 1)).copy()
            values = values.view(dtype).reshape(count, comps)
    values = values.astype(np.float64)
    if acc.get("normalized") and ctype != FLOAT:
        bits = dtype.itemsize * 8
        if dtype.kind == "u":
            values = values / (2.0 ** bits - 1)
        else:
            values = np.maximum(values / (2.0 ** (bits - 1) - 1), -1.0)
    return values


def _node_matrix(node: dict[str, Any]) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major in glTF
    m = np.eye(4)
    t = node.get("translation", [0.0, 0.0, 0.0])
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    s = node.get("scale", [1.0, 1.0, 1.0])
    m[:3, :3] = quat_to_rotmat_np(np.array([w, x, y, z])) * np.asarray(s, dtype=np.float64)[None, :]
    m[:3, 3] = t
    return m


def _splat_primitives(doc: dict[str, Any]) -> list[tuple[dict[str, Any], np.ndarray, str]]:
    """(primitive, global 4×4 matrix, where) for every splat primitive of the default scene (or, without
    scenes, of every mesh with the identity)."""
    meshes = doc.get("meshes", [])
    found: list[tuple[dict[str, Any], np.ndarray, str]] = []

    def add_mesh(mi: int, mat: np.ndarray) -> None:
        for pi, prim in enumerate(meshes[mi].get("primitives", [])):
            if EXTENSION in prim.get("extensions", {}):
                found.append((prim, mat, f"meshes[{mi}].primitives[{pi}]: "))

    scenes = doc.get("scenes")
    if scenes:
        nodes = doc.get("nodes", [])
        scene = scenes[doc.get("scene", 0)]

        def visit(ni: int, parent: np.ndarray, depth: int) -> None:
            if depth > 256:
                raise GltfFormatError("the node hierarchy is deeper than 256 levels (a cycle?)")
            node = nodes[ni]
            mat = parent @ _node_matrix(node)
            if "mesh" in node:
                add_mesh(node["mesh"], mat)
            for child in node.get("children", []):
                visit(child, mat, depth + 1)

        for root in scene.get("nodes", []):
            visit(root, np.eye(4), 0)
    else:
        for mi in range(len(meshes)):
            add_mesh(mi, np.eye(4))
    return found


def _apply_node_transform(means, quats, log_scales, sh, mat: np.ndarray):
    """Gaussians of a primitive in its node's space → the scene's space (spec: μ' = M μ + t,
    Σ' = A Σ Aᵀ with A the upper 3×3 of M, SH rotated by A's rotation part)."""
    a = mat[:3, :3]
    if np.allclose(mat, np.eye(4), atol=1e-12):
        return means, quats, log_scales, sh
    if np.linalg.det(a) <= 0:
        raise GltfFormatError("a splat node's transform has a non-positive determinant (mirror or degenerate), "
                              "which the extension leaves undefined")
    u, _, vt = np.linalg.svd(a)
    rot = u @ vt  # polar rotation of A
    means = means @ a.T + mat[:3, 3]
    sh = rotate_sh(sh, rot)
    scale_only = a @ rot.T  # symmetric stretch P with A = P R
    if np.allclose(scale_only, scale_only[0, 0] * np.eye(3), rtol=1e-9, atol=1e-12):  # rotation × uniform scale
        quats = quat_multiply(rotmat_to_quat_np(rot), quats)
        return means, quats, log_scales + np.log(scale_only[0, 0]), sh
    lmat = a[None] @ quat_to_rotmat_np(quats) * np.exp(log_scales)[:, None, :]  # A R S
    uu, ss, _ = np.linalg.svd(lmat)
    det = np.linalg.det(uu)
    uu[:, :, 2] *= np.where(det < 0, -1.0, 1.0)[:, None]
    quats = np.stack([rotmat_to_quat_np(r) for r in uu])
    return means, quats, np.log(np.maximum(ss, 1e-30)), sh


def load_gltf_gaussians(path: str | os.PathLike, *, source_frame: bool = True, device: torch.device | str = "cpu",
                        dtype: torch.dtype = torch.float32) -> Gaussians:
    """Read the Gaussians of every ``KHR_gaussian_splatting`` primitive of a glTF/GLB file.

    Reads what :func:`export_gltf` writes and other conforming files: any component type the spec allows
    (normalized integers are dequantized), interleaved buffer views, ``.gltf`` with external or ``data:``
    buffers, and node transforms (rotation/translation/scale are applied to the splats; SH are rotated).
    Several primitives are concatenated (SH zero-padded to the highest degree).

    Args:
        path: ``.glb`` or ``.gltf``.
        source_frame: if the file was written by vid2sim, undo the rotation to glTF's y-up frame
            (``asset.extras.vid2sim.gltf_from_world``) and return the scene frame it came from; other files
            (and ``source_frame=False``) are returned in the glTF scene frame.
        device, dtype: of the returned tensors.
    Returns:
        :class:`Gaussians` (quaternions (w, x, y, z) as stored, log scales, opacity logits, SH (N, K, 3)).
    Raises:
        GltfFormatError: no splat primitive, a missing required attribute, wrong accessor types or counts,
            partially defined SH degrees, values out of range, or an unsupported kernel / mode.
    """
    path = Path(path)
    doc, buffers = read_gltf(path)
    prims = _splat_primitives(doc)
    if not prims:
        raise GltfFormatError(f"{path}: no mesh primitive with the {EXTENSION} extension in the default scene")
    parts = []
    for prim, mat, where in prims:
        parts.append(_read_splat_primitive(doc, buffers, prim, mat, f"{path}: {where}"))
    info = doc.get("asset", {}).get("extras", {}).get("vid2sim", {})
    if source_frame and "gltf_from_world" in info:
        parts = _undo_gltf_from_world(parts, info["gltf_from_world"], path)
    return _concatenate_parts(parts).to(device=device, dtype=dtype)


#: one primitive's Gaussians as arrays: means (N, 3), quats (N, 4) (w, x, y, z), log scales (N, 3), opacity logits
#: (N,), SH (N, K, 3)
_SplatArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _read_splat_primitive(doc: dict[str, Any], buffers: list[bytes], prim: dict[str, Any], mat: np.ndarray,
                          where: str) -> _SplatArrays:
    """The Gaussians of one ``KHR_gaussian_splatting`` primitive, checked, with its node transform ``mat`` (4, 4)
    applied; ``where`` (the file and primitive) starts every message. Called by :func:`load_gltf_gaussians` only
    (its colour-space warning names that function's caller)."""
    ext = prim["extensions"][EXTENSION]
    if prim.get("mode", 4) != POINTS:
        raise GltfFormatError(f"{where}mode must be POINTS (0) for {EXTENSION}, got {prim.get('mode', 4)}")
    if ext.get("kernel") != "ellipse":
        raise GltfFormatError(f"{where}kernel {ext.get('kernel')!r} is not supported (only 'ellipse')")
    if ext.get("colorSpace") != COLOR_SPACE:
        warnings.warn(f"{where}colorSpace is {ext.get('colorSpace')!r}; the SH coefficients are returned as "
                      f"stored, vid2sim renders them as {COLOR_SPACE}", stacklevel=3)
    attrs = prim.get("attributes", {})
    missing = [
        a for a in ("POSITION", ATTR_ROTATION, ATTR_SCALE, ATTR_OPACITY, sh_attribute(0, 0)) if a not in attrs
    ]
    if missing:
        raise GltfFormatError(f"{where}lacks the required attributes {missing}")

    def get(attr: str, comps: int) -> np.ndarray:
        return _read_attribute(doc, buffers, attrs, attr, comps, where)

    means = get("POSITION", 3)
    n = means.shape[0]
    rot_xyzw, scales, opac = get(ATTR_ROTATION, 4), get(ATTR_SCALE, 3), get(ATTR_OPACITY, 1)[:, 0]
    sh = _read_sh(doc, buffers, attrs, n, where)
    for attr, values in (("rotation", rot_xyzw), ("scale", scales), ("opacity", opac), ("SH", sh)):
        if values.shape[0] != n:
            raise GltfFormatError(f"{where}the {attr} accessor has {values.shape[0]} elements, POSITION has {n}")
    if np.any(scales < 0):
        raise GltfFormatError(f"{where}{ATTR_SCALE} has negative values (the spec requires linear scales >= 0)")
    if np.any((opac < 0) | (opac > 1)):
        raise GltfFormatError(f"{where}{ATTR_OPACITY} has values outside [0, 1] (the spec stores linear opacity)")
    quats = rot_xyzw[:, [3, 0, 1, 2]]
    if np.any(np.linalg.norm(quats, axis=1) == 0):
        raise GltfFormatError(f"{where}{ATTR_ROTATION} has zero quaternions")
    log_scales = np.log(np.maximum(scales, 1e-30))
    means, quats, log_scales, sh = _apply_node_transform(means, quats, log_scales, sh, mat)
    p = np.clip(opac, 1e-12, 1 - 1e-12)
    return means, quats, log_scales, np.log(p) - np.log1p(-p), sh


def _read_attribute(doc: dict[str, Any], buffers: list[bytes], attrs: dict[str, int], attr: str, comps: int,
                    where: str) -> np.ndarray:
    """The (count, ``comps``) values of the primitive's attribute ``attr``, finite."""
    values = read_accessor(doc, buffers, attrs[attr], where)
    if values.shape[1] != comps:
        raise GltfFormatError(f"{where}{attr} must have {comps} components, got {values.shape[1]}")
    if not np.all(np.isfinite(values)):
        raise GltfFormatError(f"{where}{attr} holds NaN or infinite values")
    return values


def _read_sh(doc: dict[str, Any], buffers: list[bytes], attrs: dict[str, int], n: int, where: str) -> np.ndarray:
    """The SH coefficients (n, K, 3) of the primitive, to the highest degree whose coefficients are all present
    (every lower degree must be too)."""
    degree = 0
    for lvl in (1, 2, 3):
        present = [sh_attribute(lvl, c) in attrs for c in range(2 * lvl + 1)]
        if any(present) and not all(present):
            raise GltfFormatError(f"{where}SH degree {lvl} is partially defined ({sum(present)} of {2 * lvl + 1} "
                                  f"coefficients); the spec requires all or none")
        if all(present):
            if degree != lvl - 1:
                raise GltfFormatError(f"{where}SH degree {lvl} is present without degree {lvl - 1}")
            degree = lvl
    sh = np.zeros((n, num_sh_bases(degree), 3))
    for lvl in range(degree + 1):
        for c in range(2 * lvl + 1):
            sh[:, lvl * lvl + c] = _read_attribute(doc, buffers, attrs, sh_attribute(lvl, c), 3, where)
    return sh


def _undo_gltf_from_world(parts: list[_SplatArrays], gltf_from_world: Any, path: Path) -> list[_SplatArrays]:
    """``parts`` rotated back from glTF's y-up frame by the recorded ``gltf_from_world`` (3, 3) rotation."""
    try:
        rot = check_rotation(
            np.asarray(gltf_from_world, dtype=np.float64), "asset.extras.vid2sim.gltf_from_world"
        )
    except ValueError as exc:
        raise GltfFormatError(f"{path}: {exc}") from None
    undone = []
    for means, quats, log_scales, logits, sh in parts:
        means, quats, sh = rotate_gaussian_arrays(means, quats, sh, rot.T)
        undone.append((means, quats, log_scales, logits, sh))
    return undone


def _concatenate_parts(parts: list[_SplatArrays]) -> Gaussians:
    """One float64 :class:`Gaussians` of all ``parts``, their SH zero-padded to the highest degree."""
    max_k = max(p[4].shape[1] for p in parts)
    tensors = []
    for means, quats, log_scales, logits, sh in parts:
        pad = np.zeros((sh.shape[0], max_k - sh.shape[1], 3))
        t = [torch.from_numpy(np.ascontiguousarray(a)) for a in
             (means, quats, log_scales, logits, np.concatenate([sh, pad], axis=1))]
        tensors.append(Gaussians(means=t[0], quats=t[1], log_scales=t[2], opacity_logits=t[3], sh=t[4]))
    return Gaussians.cat(tensors)
