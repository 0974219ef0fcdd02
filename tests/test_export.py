"""Exports: glTF/GLB with KHR_gaussian_splatting (round trips, the glTF 2.0 container rules, the extension's
attribute table, independent parsers), sequences, and the material + skinning rig (a NumPy reference that
evaluates only the exported files matches the torch skinning field and simulator)."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from vid2sim.cli import main
from vid2sim.export.gltf import (
    ATTR_OPACITY,
    ATTR_ROTATION,
    ATTR_SCALE,
    EXTENSION,
    GltfFormatError,
    export_gltf,
    load_gltf_gaussians,
    read_gltf,
    sh_attribute,
)
from vid2sim.export.rig import (
    RigFormatError,
    evaluate_rig_numpy,
    export_rig,
    load_rig,
    neural_jacobian_numpy,
)
from vid2sim.export.sequence import export_sequence
from vid2sim.export.transform import rotation_to_y_up
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.sh import eval_sh

# runs the Khronos glTF-Validator (npm package gltf-validator) on one file and prints its JSON report
VALIDATE_JS = r"""
const fs = require('fs'), path = require('path');
const validator = require('gltf-validator');
if (process.argv[2] === '--probe') process.exit(0);
const file = process.argv[2];
const external = (uri) => new Promise((resolve, reject) => fs.readFile(
    path.resolve(path.dirname(file), decodeURIComponent(uri)), (e, d) => e ? reject(e.toString()) : resolve(new
    Uint8Array(d))));
validator.validateBytes(new Uint8Array(fs.readFileSync(file)),
                        {uri: path.basename(file), maxIssues: 1000, externalResourceFunction: external})
    .then((r) => console.log(JSON.stringify(r)), (e) => { console.error(e); process.exit(3); });
"""


def random_gaussians(n: int = 300, degree: int = 3, seed: int = 0) -> Gaussians:
    """Gaussians with un-normalised quaternions of both signs, logits in [-6, 6], all SH bands non-zero."""
    g = torch.Generator().manual_seed(seed)
    quats = torch.randn(n, 4, generator=g) * 3.0
    quats[: n // 2, 0] = -quats[: n // 2, 0].abs()  # w < 0 for half of them: the sign must survive
    return Gaussians(means=torch.randn(n, 3, generator=g), log_scales=torch.rand(n, 3, generator=g) * 4 - 6,
                     quats=quats, opacity_logits=torch.rand(n, generator=g) * 12 - 6,
                     sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g))


def unit(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=1, keepdim=True)


def assert_same_covariances(a: Gaussians, b: Gaussians, rtol: float = 1e-5) -> None:
    """Covariances equal to ``rtol`` of each Gaussian's largest variance (entries near 0 have no relative
    precision of their own)."""
    err = (a.covariances().double() - b.covariances().double()).abs().amax(dim=(1, 2))
    assert bool((err <= rtol * b.scales.double().amax(dim=1) ** 2).all()), float(err.max())


# ---- glTF round trips ---------------------------------------------------------------------------------

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_round_trip_to_float32_precision(tmp_path, degree, suffix):
    g = random_gaussians(degree=degree, seed=degree)
    files = export_gltf(g, tmp_path / f"g{suffix}")
    assert [f.name for f in files] == ([f"g{suffix}"] if suffix == ".glb" else ["g.gltf", "g.bin"])
    r = load_gltf_gaussians(files[0])
    assert r.num == g.num and r.sh_degree == degree and r.dtype == torch.float32
    torch.testing.assert_close(r.means, g.means, atol=1e-6, rtol=0)
    torch.testing.assert_close(r.quats, unit(g.quats), atol=1e-6, rtol=0)  # normalised, sign kept
    torch.testing.assert_close(r.log_scales, g.log_scales, atol=1e-6, rtol=0)
    torch.testing.assert_close(r.opacities, g.opacities, atol=2.4e-7, rtol=0)  # 2 float32 ulps at 1
    p = g.opacities.double()  # a float32 opacity near 0 or 1 pins the logit only to ulp(p) / (p (1 - p))
    tol = (1.2e-7 / (p * (1 - p))).float() + 1e-6
    assert bool(((r.opacity_logits - g.opacity_logits).abs() <= tol).all())
    torch.testing.assert_close(r.sh, g.sh, atol=2e-6, rtol=1e-6)
    assert_same_covariances(r, g)


def test_gltf_stores_the_spec_activations_and_unit_quaternions(tmp_path):
    g = random_gaussians(degree=1)
    path = export_gltf(g, tmp_path / "g.glb")[0]
    doc, buffers = read_gltf(path)
    attrs = doc["meshes"][0]["primitives"][0]["attributes"]

    def raw(name):
        acc = doc["accessors"][attrs[name]]
        view = doc["bufferViews"][acc["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        return np.frombuffer(buffers[0], "<f4", acc["count"] * width, view["byteOffset"]).reshape(acc["count"], width)

    R = torch.from_numpy(rotation_to_y_up((0, 0, 1))).float()
    np.testing.assert_allclose(raw("POSITION"), (g.means @ R.T).numpy(), atol=1e-6)  # z up → y up
    q = raw(ATTR_ROTATION)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)  # unit, (x, y, z, w)
    np.testing.assert_allclose(raw(ATTR_SCALE), g.scales.numpy(), rtol=1e-6)  # linear, not log
    np.testing.assert_allclose(raw(ATTR_OPACITY)[:, 0], g.opacities.numpy(), atol=1e-7)  # linear, not logit
    np.testing.assert_allclose(raw(sh_attribute(0, 0)), g.sh[:, 0].numpy(), atol=1e-7)  # DC is rotation invariant


def test_gltf_frame_rotation_keeps_shape_and_view_dependent_colour(tmp_path):
    """A tilted gravity: the glTF frame is the scene turned so that up = +Y; positions, covariances and the
    colour seen along every direction turn with it (SH of degree 1-3 rotated, not copied)."""
    g = random_gaussians(degree=3, seed=5).to(dtype=torch.float64)
    up = np.array([0.3, -0.5, 2.0])
    path = export_gltf(g, tmp_path / "g.glb", up=up)[0]
    R = rotation_to_y_up(up)
    np.testing.assert_allclose(R @ (up / np.linalg.norm(up)), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    r = load_gltf_gaussians(path, source_frame=False, dtype=torch.float64)
    Rt = torch.from_numpy(R)
    torch.testing.assert_close(r.means, g.means @ Rt.T, atol=2e-6, rtol=0)
    err = (r.covariances() - Rt @ g.covariances() @ Rt.T).abs().amax(dim=(1, 2))
    assert bool((err <= 1e-5 * g.scales.amax(dim=1) ** 2).all())
    dirs = torch.randn(g.num, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(eval_sh(3, r.sh, dirs @ Rt.T), eval_sh(3, g.sh, dirs), atol=1e-5, rtol=0)
    # not a permutation: the SH were mixed within each band, so a plain copy would fail this
    assert (r.sh[:, 1:] - g.sh[:, 1:]).abs().max() > 0.1
    back = load_gltf_gaussians(path, dtype=torch.float64)
    torch.testing.assert_close(back.sh, g.sh, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.means, g.means, atol=2e-6, rtol=0)


# ---- the container, against the glTF 2.0 rules and the extension's attribute table ------------------

def _glb_chunks(path: Path) -> tuple[dict, bytes, bytes]:
    raw = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", raw, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(raw))
    jlen, jtype = struct.unpack_from("<II", raw, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    js = raw[20:20 + jlen]
    blen, btype = struct.unpack_from("<II", raw, 20 + jlen)
    assert btype == 0x004E4942 and blen % 4 == 0
    binary = raw[28 + jlen:28 + jlen + blen]
    assert 28 + jlen + blen == len(raw)
    return json.loads(js.decode("utf-8")), js, binary


def test_glb_layout_follows_gltf2_and_the_extension_table(tmp_path):
    g = random_gaussians(n=257, degree=2)
    path = export_gltf(g, tmp_path / "g.glb")[0]
    doc, js, binary = _glb_chunks(path)
    assert js.rstrip(b" ") == js.rstrip() and len(js) - len(js.rstrip(b" ")) < 4  # JSON padded with spaces
    assert doc["asset"]["version"] == "2.0"
    assert EXTENSION in doc["extensionsUsed"] and EXTENSION not in doc.get("extensionsRequired", [])
    buf = doc["buffers"][0]
    assert "uri" not in buf and buf["byteLength"] <= len(binary) < buf["byteLength"] + 4
    prim = doc["meshes"][doc["nodes"][doc["scenes"][doc["scene"]]["nodes"][0]]["mesh"]]["primitives"][0]
    assert prim["mode"] == 0
    ext = prim["extensions"][EXTENSION]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] == "srgb_rec709_display"  # the schema's required pair
    assert ext.get("projection", "perspective") == "perspective"
    assert ext.get("sortingMethod", "cameraDistance") == "cameraDistance"
    expected = {"POSITION": ("VEC3", 5126), ATTR_ROTATION: ("VEC4", 5126), ATTR_SCALE: ("VEC3", 5126),
                ATTR_OPACITY: ("SCALAR", 5126), "COLOR_0": ("VEC4", 5121)}
    expected.update({sh_attribute(d, c): ("VEC3", 5126) for d in range(3) for c in range(2 * d + 1)})
    assert set(prim["attributes"]) == set(expected)  # degree 2: all of degrees 0-2, none of degree 3
    sizes = {5126: 4, 5121: 1}
    comps = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
    for name, index in prim["attributes"].items():
        acc = doc["accessors"][index]
        assert (acc["type"], acc["componentType"]) == expected[name], name
        assert acc["count"] == g.num
        view = doc["bufferViews"][acc["bufferView"]]
        assert view["buffer"] == 0 and view["target"] == 34962 and "byteStride" not in view
        assert view["byteOffset"] % 4 == 0 and acc.get("byteOffset", 0) % sizes[acc["componentType"]] == 0
        assert acc.get("byteOffset", 0) + acc["count"] * comps[acc["type"]] * sizes[acc["componentType"]] \
            <= view["byteLength"]
        assert view["byteOffset"] + view["byteLength"] <= buf["byteLength"]
    pos_acc = doc["accessors"][prim["attributes"]["POSITION"]]
    view = doc["bufferViews"][pos_acc["bufferView"]]
    pos = np.frombuffer(binary, "<f4", g.num * 3, view["byteOffset"]).reshape(-1, 3)
    assert pos_acc["min"] == pos.min(axis=0).tolist() and pos_acc["max"] == pos.max(axis=0).tolist()  # exact
    color_acc = doc["accessors"][prim["attributes"]["COLOR_0"]]
    assert color_acc["normalized"] is True
    cview = doc["bufferViews"][color_acc["bufferView"]]
    rgba = np.frombuffer(binary, "u1", g.num * 4, cview["byteOffset"]).reshape(-1, 4)
    np.testing.assert_allclose(rgba[:, 3] / 255, g.opacities.numpy(), atol=0.5 / 255 + 1e-6)  # alpha = opacity
    # COLOR_0 is linear: the sRGB-decoded clamp(C0 SH0 + 0.5)
    srgb = np.clip(0.28209479177387814 * g.sh[:, 0].numpy() + 0.5, 0, 1)
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(rgba[:, :3] / 255, lin, atol=0.5 / 255 + 1e-6)
    assert "KHR_materials_unlit" in doc["materials"][prim["material"]]["extensions"]


def test_gltf_without_fallback_color_and_bad_input(tmp_path):
    g = random_gaussians(n=10, degree=0)
    doc, _, _ = _glb_chunks(export_gltf(g, tmp_path / "g.glb", fallback_color=False)[0])
    prim = doc["meshes"][0]["primitives"][0]
    assert "COLOR_0" not in prim["attributes"] and "material" not in prim and doc["extensionsUsed"] == [EXTENSION]
    with pytest.raises(ValueError, match=r"\.glb .*\.gltf"):
        export_gltf(g, tmp_path / "g.obj")
    with pytest.raises(ValueError, match="0 Gaussians"):
        export_gltf(g[torch.zeros(10, dtype=torch.bool)], tmp_path / "e.glb")
    bad = g.clone()
    bad.means[3, 1] = float("nan")
    with pytest.raises(ValueError, match="means"):
        export_gltf(bad, tmp_path / "n.glb")
    with pytest.raises(ValueError, match="up must be"):
        export_gltf(g, tmp_path / "u.glb", up=(0, 0, 0))


def test_pygltflib_reads_our_files(tmp_path):
    """An independent parser (pygltflib, test-only dependency) reads both containers and our data."""
    pygltflib = importlib.import_module("pygltflib")  # a declared test dependency: a broken install fails
    g = random_gaussians(n=50, degree=1)
    for suffix in (".glb", ".gltf"):
        path = export_gltf(g, tmp_path / f"g{suffix}")[0]
        gl = pygltflib.GLTF2().load(str(path))
        prim = gl.meshes[gl.nodes[gl.scenes[gl.scene].nodes[0]].mesh].primitives[0]
        assert prim.mode == pygltflib.POINTS and EXTENSION in prim.extensions
        assert EXTENSION in gl.extensionsUsed
        acc = gl.accessors[prim.attributes.POSITION]
        view = gl.bufferViews[acc.bufferView]
        blob = gl.binary_blob() if suffix == ".glb" else (tmp_path / gl.buffers[0].uri).read_bytes()
        pos = np.frombuffer(blob, "<f4", acc.count * 3, view.byteOffset).reshape(-1, 3)
        R = rotation_to_y_up((0, 0, 1))
        np.testing.assert_allclose(pos @ R, g.means.numpy(), atol=1e-6)
        assert acc.min == pos.min(axis=0).tolist() and acc.max == pos.max(axis=0).tolist()


def _validator_command(tmp_path: Path) -> list[str] | None:
    if shutil.which("node") is None:
        return None
    script = tmp_path / "validate.js"
    script.write_text(VALIDATE_JS)
    probe = subprocess.run(["node", str(script), "--probe"], capture_output=True, text=True, timeout=60)
    return ["node", str(script)] if probe.returncode == 0 else None


def test_khronos_gltf_validator(tmp_path):
    """The Khronos glTF-Validator (npm ``gltf-validator``; set NODE_PATH to where it is installed) finds
    no problem except the one it has with every KHR_gaussian_splatting file: it does not know the extension
    yet and rejects extension-prefixed attribute names (KhronosGroup/glTF-Validator issue #252)."""
    cmd = _validator_command(tmp_path)
    if cmd is None:
        if os.environ.get("CI"):  # .ci/run installs it: missing there is a broken CI, not a reason to skip
            pytest.fail("node and the npm package gltf-validator are missing in CI (.ci/run installs them)")
        pytest.skip("node and the npm package gltf-validator are needed (NODE_PATH=<dir>/node_modules)")
    g = random_gaussians(n=64, degree=3)
    for suffix in (".glb", ".gltf"):
        path = export_gltf(g, tmp_path / f"g{suffix}")[0]
        run = subprocess.run(cmd + [str(path)], capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        report = json.loads(run.stdout)
        issues = report["issues"]
        errors = [m for m in issues["messages"] if m["severity"] == 0]
        assert all(m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and
                   m["pointer"].startswith(f"/meshes/0/primitives/0/attributes/{EXTENSION}:") for m in errors), errors
        assert len(errors) == 3 + 16  # ROTATION, SCALE, OPACITY + 16 SH coefficients of degree 3
        assert issues["numWarnings"] == 0
        assert {m["code"] for m in issues["messages"] if m["severity"] > 0} <= {"UNSUPPORTED_EXTENSION"}
        assert report["info"]["totalVertexCount"] == 64 and report["info"]["drawCallCount"] == 1


# ---- reading other writers' files ---------------------------------------------------------------------

def _foreign_gltf(tmp_path: Path, node: dict, sh_degree: int = 1, drop: str | None = None) -> tuple[Path, dict]:
    """A .gltf with an embedded data: buffer written as another exporter might: quantized rotation (short
    normalized), opacity (ubyte normalized), position and scale interleaved in one strided bufferView."""
    import base64

    rng = np.random.default_rng(3)
    n = 40
    pos = rng.normal(size=(n, 3)).astype("<f4")
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q_i16 = np.round(q * 32767).astype("<i2")  # (x, y, z, w)
    scale = rng.uniform(0.01, 0.2, size=(n, 3)).astype("<f4")
    opac_u8 = rng.integers(1, 255, size=n).astype("u1")
    sh = rng.normal(size=(n, (sh_degree + 1) ** 2, 3)).astype("<f4")
    inter = np.zeros((n, 8), "<f4")  # stride 32: position (12 bytes) + scale (12 bytes) + 8 unused bytes
    inter[:, :3], inter[:, 3:6] = pos, scale
    parts = [inter.tobytes(), q_i16.tobytes(), opac_u8.tobytes() + b"\0" * (-n % 4)]
    parts += [sh[:, k].tobytes() for k in range(sh.shape[1])]
    offsets = np.cumsum([0] + [len(p) for p in parts]).tolist()
    blob = b"".join(parts)
    views = [{"buffer": 0, "byteOffset": offsets[0], "byteLength": len(parts[0]), "byteStride": 32, "target": 34962}]
    views += [{"buffer": 0, "byteOffset": offsets[i], "byteLength": len(parts[i])} for i in range(1, len(parts))]
    accessors = [
        {"bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": n, "type": "VEC3",
         "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
        {"bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": n, "type": "VEC3"},
        {"bufferView": 1, "componentType": 5122, "normalized": True, "count": n, "type": "VEC4"},
        {"bufferView": 2, "componentType": 5121, "normalized": True, "count": n, "type": "SCALAR"},
    ] + [{"bufferView": 3 + k, "componentType": 5126, "count": n, "type": "VEC3"} for k in range(sh.shape[1])]
    attributes = {"POSITION": 0, ATTR_SCALE: 1, ATTR_ROTATION: 2, ATTR_OPACITY: 3}
    for d in range(sh_degree + 1):
        for c in range(2 * d + 1):
            attributes[sh_attribute(d, c)] = 4 + d * d + c
    if drop:
        del attributes[drop]
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": [EXTENSION], "scene": 0,
           "scenes": [{"nodes": [0]}], "nodes": [{"children": [1], **node}, {"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": attributes, "mode": 0,
                                       "extensions": {EXTENSION: {"kernel": "ellipse",
                                                                  "colorSpace": "srgb_rec709_display"}}}]}],
           "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": len(blob),
                        "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}]}
    path = tmp_path / "foreign.gltf"
    path.write_text(json.dumps(doc))
    truth = {"pos": pos.astype(np.float64), "q": np.maximum(q_i16 / 32767.0, -1.0), "scale": scale.astype(np.float64),
             "opacity": opac_u8 / 255.0, "sh": sh.astype(np.float64)}
    return path, truth


def test_reader_dequantizes_and_applies_node_transforms(tmp_path):
    from vid2sim.export.transform import quat_to_rotmat_np, rotate_sh

    angle = 0.7
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    q_node = np.r_[axis * np.sin(angle / 2), np.cos(angle / 2)]  # glTF (x, y, z, w)
    node = {"translation": [0.5, -1.0, 2.0], "rotation": q_node.tolist(), "scale": [2.0, 2.0, 2.0]}
    path, t = _foreign_gltf(tmp_path, node)
    r = load_gltf_gaussians(path, dtype=torch.float64)
    Rn = quat_to_rotmat_np(q_node[[3, 0, 1, 2]])
    np.testing.assert_allclose(r.means.numpy(), 2.0 * t["pos"] @ Rn.T + [0.5, -1.0, 2.0], atol=1e-6)
    A = 2.0 * Rn
    Rq = quat_to_rotmat_np(t["q"][:, [3, 0, 1, 2]])
    cov = (A @ Rq * t["scale"][:, None, :] ** 2) @ np.transpose(A @ Rq, (0, 2, 1))
    np.testing.assert_allclose(r.covariances().numpy(), cov, atol=1e-9, rtol=1e-6)
    np.testing.assert_allclose(r.opacities.numpy(), t["opacity"], atol=1e-9)
    np.testing.assert_allclose(r.sh.numpy(), rotate_sh(t["sh"], Rn), atol=1e-9)
    # a non-uniform scale: the covariance is still A Σ Aᵀ (re-factored per Gaussian)
    node = {"matrix": [1.0, 0, 0, 0, 0.3, 2.0, 0, 0, 0, 0, 0.5, 0, 0, 0, 0, 1]}  # column-major, a shear too
    path, t = _foreign_gltf(tmp_path, node, sh_degree=0)
    r = load_gltf_gaussians(path, dtype=torch.float64)
    A = np.asarray(node["matrix"]).reshape(4, 4).T[:3, :3]
    Rq = quat_to_rotmat_np(t["q"][:, [3, 0, 1, 2]])
    cov = (A @ Rq * t["scale"][:, None, :] ** 2) @ np.transpose(A @ Rq, (0, 2, 1))
    np.testing.assert_allclose(r.covariances().numpy(), cov, atol=1e-9, rtol=1e-6)


@pytest.mark.parametrize("drop, message", [
    (ATTR_OPACITY, "lacks the required attributes"),
    (sh_attribute(1, 2), "SH degree 1 is partially defined"),
])
def test_reader_rejects_nonconforming_files(tmp_path, drop, message):
    path, _ = _foreign_gltf(tmp_path, {}, drop=drop)
    with pytest.raises(GltfFormatError, match=message):
        load_gltf_gaussians(path)


def test_reader_errors_name_the_problem(tmp_path):
    path, _ = _foreign_gltf(tmp_path, {})
    doc = json.loads(path.read_text())
    doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION]["kernel"] = "customShape"
    path.write_text(json.dumps(doc))
    with pytest.raises(GltfFormatError, match="kernel 'customShape'"):
        load_gltf_gaussians(path)
    del doc["meshes"][0]["primitives"][0]["extensions"]
    path.write_text(json.dumps(doc))
    with pytest.raises(GltfFormatError, match="no mesh primitive with the KHR_gaussian_splatting"):
        load_gltf_gaussians(path)
    (tmp_path / "junk.glb").write_bytes(b"glTF\x01\x00\x00\x00")
    with pytest.raises(GltfFormatError, match="truncated"):
        load_gltf_gaussians(tmp_path / "junk.glb")
    with pytest.raises(GltfFormatError, match="no such glTF file"):
        load_gltf_gaussians(tmp_path / "missing.glb")


# ---- the rig -----------------------------------------------------------------------------------------

def test_rig_numpy_reference_matches_torch(tiny_asset, tmp_path):
    from vid2sim.asset.folder import load_asset

    asset = load_asset(tiny_asset)
    folder = export_rig(asset, tmp_path / "rig")
    assert sorted(p.name for p in folder.iterdir()) == ["gaussians.ply", "rig.json", "rig.safetensors"]
    doc, tensors = load_rig(folder)
    material = json.loads((Path(tiny_asset) / "material.json").read_text())
    for key in ("E", "nu", "density", "damping_ratio", "model"):
        assert doc["material"][key] == material[key]
    meta = json.loads((Path(tiny_asset) / "asset.json").read_text())
    assert doc["simulation"]["dt"] == meta["dt"] and doc["simulation"]["gravity"] == meta["gravity"]
    assert doc["simulation"]["floor"]["height"] == meta["floor_height"]
    assert doc["simulation"]["initial_velocity"] == meta["initial_velocity"]
    assert doc["state"]["size"] == 12 * asset.field.num_handles_total
    for name, info in doc["tensors"].items():
        assert list(tensors[name].shape) == info["shape"]
    np.testing.assert_array_equal(tensors["points.cubature"], asset.cubature_points.numpy())
    np.testing.assert_array_equal(tensors["points.contact_areas"], asset.contact_areas.numpy())
    for key, value in asset.field.state_dict().items():  # the official reader agrees on every weight
        np.testing.assert_array_equal(tensors[f"skinning.{key}"], value.numpy())

    sim = asset.simulator()
    X = asset.gaussians.means
    h = asset.field.num_handles_total
    gen = torch.Generator().manual_seed(0)
    w_torch = asset.field(X).detach().numpy()
    for scale in (0.0, 0.05, 0.3):
        z = (torch.randn(12 * h, generator=gen) * scale).to(X.dtype)
        ref = evaluate_rig_numpy(folder, z.numpy(), X.numpy())  # only the exported files
        np.testing.assert_allclose(ref["weights"], w_torch, atol=1e-5)
        np.testing.assert_allclose(ref["positions"], sim.positions(X, z).detach().numpy(), atol=1e-5)
        np.testing.assert_allclose(ref["F"], sim.deformation_gradients(X, z).detach().numpy(), atol=1e-5)
    assert np.abs(ref["positions"] - X.numpy()).max() > 0.05  # the last z really moves the points
    # the shaded asset's light, as rig.json states it, gives the colours vid2sim renders
    from vid2sim.splats.deform import deform_gaussians
    from vid2sim.splats.ply import load_ply
    from vid2sim.splats.sh import C0

    assert asset.shading is not None and doc["shading"]["model"] == "lambert"
    np.testing.assert_array_equal(tensors["shading.normals"], asset.shading.normals.numpy())

    def s_of(n):
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        k, light = doc["shading"]["ambient"], np.asarray(doc["shading"]["light"])
        return k + (1 - k) * np.clip(n @ light, 0, None)

    N = tensors["shading.normals"].astype(np.float64)
    lit_rest = C0 * load_ply(folder / "gaussians.ply").sh[:, 0].double().numpy() + 0.5
    albedo = lit_rest / s_of(N)[:, None]
    cof = np.linalg.det(ref["F"])[:, None, None] * np.linalg.inv(ref["F"]).transpose(0, 2, 1)
    moved = albedo * s_of(np.einsum("nij,nj->ni", cof, N))[:, None]
    d = deform_gaussians(asset.gaussians, sim.positions(X, z).detach(), sim.deformation_gradients(X, z).detach(),
                         asset.shading)
    np.testing.assert_allclose(moved, C0 * d.sh[:, 0].double().numpy() + 0.5, atol=2e-4)
    with pytest.raises(RigFormatError, match="no Neural Jacobian"):
        neural_jacobian_numpy(folder, X.numpy())


def test_rig_neural_jacobian_numpy_matches_torch(tiny_asset, tmp_path):
    from vid2sim.asset.folder import load_asset
    from vid2sim.physics.neural_jacobian import NeuralJacobian

    asset = load_asset(tiny_asset)
    nj = NeuralJacobian(asset.field.num_handles_total, encoding_dim=8, widths=(8, 16), seed=3)
    with torch.no_grad():
        nj.output.weight.normal_(0, 0.1, generator=torch.Generator().manual_seed(4))
        nj.output.bias.normal_(0, 0.1, generator=torch.Generator().manual_seed(5))
    nj.set_input_frame(asset.field.input_centre, float(asset.field.input_scale))
    asset = dataclasses.replace(asset, jacobian=nj.to(asset.cubature_points.dtype))
    folder = export_rig(asset, tmp_path / "rig")
    doc, _ = load_rig(folder)
    assert doc["jacobian"]["widths"] == [8, 16] and doc["jacobian"]["blocks"][1]["proj"] is not None
    X = asset.cubature_points
    J = neural_jacobian_numpy(folder, X.numpy())
    np.testing.assert_allclose(J, nj(X).detach().numpy(), atol=1e-5)
    assert np.abs(J).max() > 0.01


def _fake_simulate_output(asset_folder: Path, out: Path, frames: int = 3) -> torch.Tensor:
    """What ``vid2sim simulate`` writes (per-frame PLYs, states.npz, summary.json), made with the asset's simulator."""
    from vid2sim.asset.folder import load_asset
    from vid2sim.splats.deform import deform_gaussians
    from vid2sim.splats.ply import save_ply

    asset = load_asset(asset_folder)
    sim = asset.simulator()
    states = sim.rollout(asset.initial_state(sim), frames)
    z = torch.stack([s.z.detach() for s in states])
    g = asset.gaussians
    for i, zi in enumerate(z):
        x = sim.positions(g.means, zi).detach()
        F = sim.deformation_gradients(g.means, zi).detach()
        save_ply(deform_gaussians(g, x, F).to_gaussians(), out / "ply" / f"{i:04d}.ply")
    np.savez(out / "states.npz", z=z.numpy(), zdot=torch.stack([s.zdot.detach() for s in states]).numpy(),
             times=np.array([s.t for s in states]))
    summary = {"dt": asset.dt, "externals": [{"type": "gravity", "acceleration": [0.0, -9.8, 0.0]},
                                             {"type": "floor", "height": -0.7}]}
    (out / "summary.json").write_text(json.dumps(summary))
    return z


def test_sequence_export_and_rig_replay(tiny_asset, tmp_path):
    from vid2sim.asset.folder import load_asset
    from vid2sim.splats.ply import load_ply

    sim_out = tmp_path / "sim"
    z = _fake_simulate_output(Path(tiny_asset), sim_out)
    out = export_sequence(sim_out, tmp_path / "seq", "glb", progress=False)
    index = json.loads((out / "sequence.json").read_text())
    assert index["frames"] == ["0000.glb", "0001.glb", "0002.glb"] and index["dt"] == pytest.approx(0.05)
    assert index["up"] == [0.0, 1.0, 0.0]  # from summary.json's gravity entry (y-up here: no rotation needed)
    doc, _ = read_gltf(out / "0001.glb")
    np.testing.assert_array_equal(doc["asset"]["extras"]["vid2sim"]["gltf_from_world"], np.eye(3))
    for i, name in enumerate(index["frames"]):
        ply = load_ply(sim_out / "ply" / f"{i:04d}.ply")
        back = load_gltf_gaussians(out / name)
        torch.testing.assert_close(back.means, ply.means, atol=2e-6, rtol=0)
        assert_same_covariances(back, ply)
        torch.testing.assert_close(back.sh, ply.sh, atol=2e-6, rtol=0)
    # the rig with the simulated states replays the sequence from its own files
    asset = load_asset(tiny_asset)
    rig = export_rig(asset, tmp_path / "rig", z_sequence=z)
    doc, tensors = load_rig(rig)
    rest = load_ply(rig / "gaussians.ply").means.numpy()
    for i in range(z.shape[0]):
        x = evaluate_rig_numpy((doc, tensors), tensors["states.z"][i], rest)["positions"]
        np.testing.assert_allclose(x, load_ply(sim_out / "ply" / f"{i:04d}.ply").means.numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="no per-frame PLYs"):
        export_sequence(tmp_path, tmp_path / "x", "glb", progress=False)


# ---- the command -------------------------------------------------------------------------------------

def test_cli_exports_an_asset_in_every_format(tiny_asset, tmp_path, capsys):
    from vid2sim.splats.ply import load_ply

    ref = load_ply(Path(tiny_asset) / "gaussians.ply")
    assert main(["export", str(tiny_asset), str(tmp_path / "a.glb"), "--quiet"]) == 0
    assert "wrote" in capsys.readouterr().out
    torch.testing.assert_close(load_gltf_gaussians(tmp_path / "a.glb").means, ref.means, atol=2e-6, rtol=0)
    assert main(["export", str(tiny_asset), str(tmp_path / "b.gltf")]) == 0
    assert (tmp_path / "b.bin").is_file()
    assert main(["export", str(tiny_asset), str(tmp_path / "folder"), "--format", "gltf"]) == 0
    assert sorted(p.name for p in (tmp_path / "folder").iterdir()) == ["gaussians.bin", "gaussians.gltf"]
    assert main(["export", str(tiny_asset), str(tmp_path / "c.ply")]) == 0
    torch.testing.assert_close(load_ply(tmp_path / "c.ply").sh, ref.sh)
    assert main(["export", str(tiny_asset), str(tmp_path / "rig"), "--format", "rig"]) == 0
    load_rig(tmp_path / "rig")
    # a PLY file as SOURCE
    assert main(["export", str(tmp_path / "c.ply"), str(tmp_path / "d.glb"), "--no-fallback-color"]) == 0
    doc, _ = read_gltf(tmp_path / "d.glb")
    assert "COLOR_0" not in doc["meshes"][0]["primitives"][0]["attributes"]


def test_cli_errors(tiny_asset, tmp_path, capsys):
    (tmp_path / "a.glb").write_bytes(b"x")
    assert main(["export", str(tiny_asset), str(tmp_path / "a.glb")]) == 2
    assert "a.glb exists; pass --overwrite" in capsys.readouterr().err
    assert main(["export", str(tiny_asset), str(tmp_path / "a.glb"), "--overwrite"]) == 0
    load_gltf_gaussians(tmp_path / "a.glb")
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "neither an asset folder" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exc:
        main(["export", str(tiny_asset), str(tmp_path / "o"), "--format", "obj"])
    assert exc.value.code == 2
    assert "invalid choice: 'obj'" in capsys.readouterr().err
    assert main(["export", str(tiny_asset), str(tmp_path / "o.ply"), "--format", "glb"]) == 2
    assert "ends in .ply" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing"), str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    sim = tmp_path / "sim"
    (sim / "ply").mkdir(parents=True)
    shutil.copyfile(Path(tiny_asset) / "gaussians.ply", sim / "ply" / "0000.ply")
    assert main(["export", str(sim), str(tmp_path / "r"), "--format", "rig"]) == 2
    assert "--format rig needs an asset folder" in capsys.readouterr().err
    assert main(["export", str(sim), str(tmp_path / "seq"), "--format", "ply", "--quiet"]) == 0
    assert (tmp_path / "seq" / "0000.ply").is_file()
    assert main(["export", str(sim), str(tmp_path / "seq"), "--quiet"]) == 2
    assert main(["export", str(sim), str(tmp_path / "seq"), "--quiet", "--overwrite"]) == 0
    assert (tmp_path / "seq" / "0000.glb").is_file() and not (tmp_path / "seq" / "0000.ply").exists()
