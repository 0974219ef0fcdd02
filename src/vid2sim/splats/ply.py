"""Read and write Gaussians in the standard 3D Gaussian Splatting PLY layout.

The layout (what the reference 3DGS code writes and the common splat viewers read) is one ``vertex``
element, binary little-endian float32 properties in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 … f_rest_{3(K-1)-1}  opacity
    scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

with ``opacity`` the logit, ``scale_*`` the log standard deviations, ``rot_*`` the quaternion
(w, x, y, z) and ``f_rest`` the higher SH bands stored channel-major (all R coefficients, then G,
then B). The normals are written as zeros and ignored on reading.

The reader accepts any PLY whose ``vertex`` element holds those properties (ASCII or binary, any
byte order, float or double, extra properties ignored) and raises :class:`PlyFormatError` naming the
file and the problem otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from vid2sim.runtime.errors import InputError
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.sh import sh_degree_from_bases


class PlyFormatError(InputError):
    """A PLY file that is not a readable 3DGS Gaussian file."""


_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def _property_names(num_rest: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(num_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def save_ply(gaussians: Gaussians, path: str | os.PathLike) -> Path:
    """Write ``gaussians`` to ``path`` in the standard 3DGS PLY layout (binary little-endian float32).

    Returns the path written. Parent folders are created.
    """
    g = gaussians.detach().to("cpu", torch.float32)
    n = g.num
    k = g.sh.shape[1]
    rest = g.sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1))  # channel-major
    cols = [
        g.means,
        torch.zeros(n, 3),
        g.sh[:, 0, :],
        rest,
        g.opacity_logits[:, None],
        g.log_scales,
        g.quats,
    ]
    data = torch.cat(cols, dim=1).numpy().astype("<f4")
    names = _property_names(3 * (k - 1))
    assert data.shape[1] == len(names)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())
    return path


def _parse_header(f, path: Path) -> tuple[str, list[tuple[str, int, list[tuple[str, str | None, str]]]]]:
    """Returns (format, elements); each element is (name, count, [(prop, dtype or None for list, list spec)])."""
    first = f.readline()
    if first.strip() != b"ply":
        raise PlyFormatError(f"{path}: not a PLY file (first line is {first[:40]!r}, expected b'ply')")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None, str]]]] = []
    while True:
        raw = f.readline()
        if not raw:
            raise PlyFormatError(f"{path}: PLY header has no 'end_header' line")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError as e:
            raise PlyFormatError(f"{path}: PLY header line is not ASCII: {raw[:40]!r}") from e
        if not line or line.startswith("comment") or line.startswith("obj_info"):
            continue
        parts = line.split()
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            if len(parts) != 3 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise PlyFormatError(f"{path}: unsupported PLY format line {line!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise PlyFormatError(f"{path}: malformed element line {line!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise PlyFormatError(f"{path}: property line {line!r} before any element")
            if len(parts) == 5 and parts[1] == "list":
                elements[-1][2].append((parts[4], None, line))
            elif len(parts) == 3:
                if parts[1] not in _PLY_TYPES:
                    raise PlyFormatError(f"{path}: unknown PLY property type {parts[1]!r} in {line!r}")
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]], line))
            else:
                raise PlyFormatError(f"{path}: malformed property line {line!r}")
        else:
            raise PlyFormatError(f"{path}: unexpected PLY header line {line!r}")
    if fmt is None:
        raise PlyFormatError(f"{path}: PLY header has no 'format' line")
    return fmt, elements


def _read_vertex_table(path: Path) -> dict[str, np.ndarray]:
    with open(path, "rb") as f:
        fmt, elements = _parse_header(f, path)
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise PlyFormatError(f"{path}: PLY file has no 'vertex' element (elements: {names})")
        body = f.read()
    offset = 0
    text_lines: list[bytes] | None = body.split(b"\n") if fmt == "ascii" else None
    line_no = 0
    for name, count, props in elements:
        if any(dt is None for _, dt, _ in props):
            bad = next(spec for _, dt, spec in props if dt is None)
            if name == "vertex":
                raise PlyFormatError(f"{path}: the vertex element has a list property ({bad!r}); 3DGS files have none")
            raise PlyFormatError(
                f"{path}: element {name!r} before 'vertex' has a list property ({bad!r}); cannot locate the vertex data"
            )
        if fmt == "ascii":
            assert text_lines is not None
            if name != "vertex":
                line_no += count
                continue
            rows = [ln.split() for ln in text_lines[line_no : line_no + count]]
            if len(rows) != count or any(len(r) != len(props) for r in rows):
                raise PlyFormatError(
                    f"{path}: ASCII vertex data is truncated or malformed (expected {count} rows of {len(props)} "
                    f"values)"
                )
            try:
                table = np.array(rows, dtype=np.float64)
            except ValueError as e:
                raise PlyFormatError(f"{path}: non-numeric value in ASCII vertex data ({e})") from e
            return {p: table[:, i] for i, (p, _, _) in enumerate(props)}
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(p, endian + dt) for p, dt, _ in props])
        size = dtype.itemsize * count
        if name != "vertex":
            offset += size
            continue
        if len(body) - offset < size:
            raise PlyFormatError(
                f"{path}: file is truncated: vertex data needs {size} bytes for {count} vertices, "
                f"only {len(body) - offset} present"
            )
        arr = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
        return {p: arr[p].astype(np.float64) for p, _, _ in props}
    raise AssertionError("unreachable")


def load_ply(
    path: str | os.PathLike, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> Gaussians:
    """Read Gaussians from a 3DGS-layout PLY file (see module docstring).

    The SH degree is inferred from the number of ``f_rest_*`` properties (0, 9, 24 or 45 → degree
    0, 1, 2 or 3). Raises :class:`PlyFormatError` for missing files, malformed headers, truncated
    data, missing properties, a wrong ``f_rest`` count or non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(f"{path}: no such PLY file")
    cols = _read_vertex_table(path)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    required += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [r for r in required if r not in cols]
    if missing:
        raise PlyFormatError(
            f"{path}: vertex element lacks the 3DGS properties {missing}; found {sorted(cols)[:20]}"
        )
    rest_names = sorted((p for p in cols if p.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    num_rest = len(rest_names)
    if rest_names != [f"f_rest_{i}" for i in range(num_rest)] or num_rest % 3 != 0:
        raise PlyFormatError(
            f"{path}: f_rest_* properties must be f_rest_0..f_rest_{{3(K-1)-1}}, got {num_rest} of them"
        )
    try:
        sh_degree_from_bases(num_rest // 3 + 1)
    except ValueError:
        raise PlyFormatError(
            f"{path}: {num_rest} f_rest_* properties do not match an SH degree (expected 0, 9, 24 or 45)"
        ) from None
    n = len(cols["x"])

    def stack(names: list[str]) -> torch.Tensor:
        if not names:
            return torch.zeros(n, 0, dtype=torch.float64)
        return torch.from_numpy(np.stack([cols[k] for k in names], axis=1))

    means = stack(["x", "y", "z"])
    dc = stack(["f_dc_0", "f_dc_1", "f_dc_2"])
    rest = stack(rest_names).reshape(n, 3, num_rest // 3).transpose(1, 2)
    opac = torch.from_numpy(cols["opacity"].copy())
    log_scales = stack([f"scale_{i}" for i in range(3)])
    quats = stack([f"rot_{i}" for i in range(4)])
    for name, t in [("position", means), ("f_dc/f_rest", torch.cat([dc, rest.reshape(n, -1)], 1)),
                    ("opacity", opac), ("scale", log_scales), ("rot", quats)]:
        if not bool(torch.isfinite(t).all()):
            raise PlyFormatError(f"{path}: non-finite values in the {name} properties")
    if n and bool((quats.norm(dim=1) == 0).any()):
        raise PlyFormatError(f"{path}: some rot_* quaternions are zero")
    sh = torch.cat([dc[:, None, :], rest], dim=1)
    return Gaussians(means, log_scales, quats, opac, sh).to(device=device, dtype=dtype)
