"""Gaussian model, spherical harmonics and the standard 3DGS PLY layout."""

import math
import struct
import subprocess
import sys

import numpy as np
import pytest
import torch

from vid2sim.splats.gaussians import (
    Gaussians,
    covariances_from_scales_quats,
    quat_to_rotmat,
    rotmat_to_quat,
)
from vid2sim.splats.ply import PlyFormatError, load_ply, save_ply
from vid2sim.splats.sh import C0, eval_sh, num_sh_bases, rgb_to_sh_dc, sh_basis


def _random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, num_sh_bases(degree), 3, generator=g),
    )


def test_quaternion_rotation_matrices():
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]], dtype=torch.float64)
    R = quat_to_rotmat(q)[0]  # 90° about z: x → y
    assert torch.allclose(
        R @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    )
    qs = torch.randn(100, 4, dtype=torch.float64) * 3  # need not be unit
    Rs = quat_to_rotmat(qs)
    assert torch.allclose(Rs @ Rs.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(100, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(Rs), torch.ones(100, dtype=torch.float64))
    back = rotmat_to_quat(Rs)
    unit = qs / qs.norm(dim=1, keepdim=True)
    unit = unit * torch.sign(unit[:, :1])
    assert torch.allclose(back, unit, atol=1e-10)


def test_covariance_eigenvalues_are_squared_scales():
    g = _random_gaussians(50, 0).to(dtype=torch.float64)
    cov = g.covariances()
    evals = torch.linalg.eigvalsh(cov)
    assert torch.allclose(evals, torch.sort(g.scales**2, dim=1).values, rtol=1e-9)
    assert torch.allclose(cov, covariances_from_scales_quats(g.scales, g.quats))


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Gauss–Legendre in cos θ × uniform φ integrates the degree ≤ 6 products exactly
    x, w = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    ct = torch.tensor(np.repeat(x, 16), dtype=torch.float64)
    wt = torch.tensor(np.repeat(w, 16) * (2 * np.pi / 16), dtype=torch.float64)
    ph = torch.tensor(np.tile(phi, 8), dtype=torch.float64)
    st = torch.sqrt(1 - ct**2)
    dirs = torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], dim=1)
    Y = sh_basis(3, dirs)  # (Q, 16)
    gram = (Y * wt[:, None]).T @ Y
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-12)


def test_eval_sh_conventions():
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    sh = torch.zeros(1, 16, 3)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    d = torch.randn(1, 3)
    for deg in range(4):
        assert torch.allclose(eval_sh(deg, sh, d), rgb, atol=1e-6)
    # degree-1 band: Y_1 = −C1 y, Y_2 = C1 z, Y_3 = −C1 x; looking along +z the z-band adds C1·sh[2]
    sh[:, 2] = 0.1
    out = eval_sh(1, sh, torch.tensor([[0.0, 0.0, 2.0]]))
    assert torch.allclose(out, rgb + 0.4886025119029199 * 0.1, atol=1e-6)
    # negative colours are clamped at 0
    assert float(eval_sh(0, torch.full((1, 1, 3), -10.0), d).max()) == 0.0
    assert math.isclose(C0, 0.5 / math.sqrt(math.pi), rel_tol=1e-12)
    with pytest.raises(ValueError, match="sh_degree"):
        eval_sh(4, sh, d)


def test_gaussians_from_values_and_validation():
    means = torch.randn(5, 3)
    g = Gaussians.from_values(means, torch.full((5,), 0.1), torch.rand(5, 3), torch.full((5,), 0.3), sh_degree=2)
    assert g.sh_degree == 2 and g.num == 5
    assert torch.allclose(g.scales, torch.full((5, 3), 0.1))
    assert torch.allclose(g.opacities, torch.full((5,), 0.3), atol=1e-6)
    assert torch.allclose(g.rotation_matrices, torch.eye(3).expand(5, 3, 3))
    assert g[torch.tensor([True, False, True, False, False])].num == 2
    assert Gaussians.cat([g, g]).num == 10
    assert g.with_sh_degree(0).sh.shape == (5, 1, 3) and g.with_sh_degree(3).sh.shape == (5, 16, 3)
    with pytest.raises(ValueError, match="log_scales"):
        Gaussians(means, torch.zeros(4, 3), torch.zeros(5, 4), torch.zeros(5), torch.zeros(5, 1, 3))
    with pytest.raises(ValueError, match="SH"):
        Gaussians(means, torch.zeros(5, 3), torch.zeros(5, 4), torch.zeros(5), torch.zeros(5, 5, 3))
    with pytest.raises(ValueError, match="float64"):
        Gaussians(
            means, torch.zeros(5, 3, dtype=torch.float64), torch.zeros(5, 4), torch.zeros(5), torch.zeros(5, 1, 3)
        )
    with pytest.raises(ValueError, match="positive"):
        Gaussians.from_values(means, -torch.ones(5), torch.rand(5, 3), torch.full((5,), 0.3))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip(tmp_path, degree):
    g = _random_gaussians(37, degree, seed=degree)
    path = save_ply(g, tmp_path / f"deg{degree}.ply")
    back = load_ply(path)
    assert back.sh_degree == degree
    for name, t in g.tensors().items():
        assert torch.equal(getattr(back, name), t), name
    # header lists the standard properties in the standard order; payload is N * props * 4 bytes
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    props = [ln.split()[-1].decode() for ln in header.splitlines() if ln.startswith(b"property")]
    n_rest = 3 * (num_sh_bases(degree) - 1)
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9 : 9 + n_rest] == [f"f_rest_{i}" for i in range(n_rest)]
    assert props[9 + n_rest :] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert b"format binary_little_endian 1.0" in header and b"element vertex 37" in header
    assert len(body) == 37 * len(props) * 4
    # f_rest is channel-major: f_rest_0 is the red coefficient of the first higher band
    if degree > 0:
        first = np.frombuffer(body[: len(props) * 4], dtype="<f4")
        assert first[9] == pytest.approx(float(g.sh[0, 1, 0]))
        assert first[9 + (num_sh_bases(degree) - 1)] == pytest.approx(float(g.sh[0, 1, 1]))


def _write_ply(path, fmt, props, rows, extra_header=""):
    lines = ["ply", f"format {fmt} 1.0", extra_header, f"element vertex {len(rows)}"]
    lines += [f"property {t} {n}" for t, n in props] + ["end_header"]
    head = ("\n".join(ln for ln in lines if ln) + "\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows).encode()
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        code = "".join("f" if t == "float" else "d" for t, _ in props)
        body = b"".join(struct.pack(e + code, *r) for r in rows)
    path.write_bytes(head + body)


_MIN_PROPS = [
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ply_reads_other_encodings_and_extra_properties(tmp_path, fmt):
    props = [("double", n) for n in _MIN_PROPS] + [("float", "extra")]
    rows = [[1, 2, 3, 0.1, 0.2, 0.3, -1, -2, -3, -4, 1, 0, 0, 0, 9], [4, 5, 6, 0, 0, 0, 2, -1, -1, -1, 0, 1, 0, 0, 9]]
    _write_ply(tmp_path / "a.ply", fmt, props, rows, extra_header="comment written by a test")
    g = load_ply(tmp_path / "a.ply")
    assert g.sh_degree == 0
    assert torch.allclose(g.means, torch.tensor([[1.0, 2, 3], [4, 5, 6]]))
    assert torch.allclose(g.opacity_logits, torch.tensor([-1.0, 2.0]))
    assert torch.allclose(g.quats[1], torch.tensor([0.0, 1, 0, 0]))


def test_ply_malformed_files_give_clear_errors(tmp_path):
    good = save_ply(_random_gaussians(4, 1), tmp_path / "good.ply").read_bytes()
    cases = {
        "not_ply.ply": (b"hello\n", "not a PLY"),
        "truncated.ply": (good[:-10], "truncated"),
        "no_end.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "end_header"),
        "bad_format.ply": (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported PLY format"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(PlyFormatError, match=msg) as err:
            load_ply(tmp_path / name)
        assert name in str(err.value)
    with pytest.raises(PlyFormatError, match="no such"):
        load_ply(tmp_path / "missing.ply")
    # a point cloud without Gaussian properties
    _write_ply(
        tmp_path / "cloud.ply", "binary_little_endian", [("float", "x"), ("float", "y"), ("float", "z")], [[0, 0, 0]]
    )
    with pytest.raises(PlyFormatError, match="lacks the 3DGS properties"):
        load_ply(tmp_path / "cloud.ply")
    # f_rest count that matches no SH degree
    props = [("float", n) for n in _MIN_PROPS] + [("float", f"f_rest_{i}") for i in range(5)]
    _write_ply(tmp_path / "rest.ply", "binary_little_endian", props, [[0] * 10 + [1] + [0] * 8])
    with pytest.raises(PlyFormatError, match="f_rest"):
        load_ply(tmp_path / "rest.ply")
    # NaN positions
    props = [("float", n) for n in _MIN_PROPS]
    _write_ply(tmp_path / "nan.ply", "binary_little_endian", props, [[float("nan")] + [0] * 9 + [1, 0, 0, 0]])
    with pytest.raises(PlyFormatError, match="non-finite"):
        load_ply(tmp_path / "nan.ply")


def test_package_exports_without_importing_physics():
    code = (
        "import sys, vid2sim.splats as s\n"
        "missing = [n for n in s.__all__ if not hasattr(s, n)]\n"
        "assert not missing, missing\n"
        "bad = [m for m in sys.modules if m.startswith('vid2sim.physics')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
