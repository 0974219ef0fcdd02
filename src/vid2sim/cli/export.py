"""``vid2sim export SOURCE OUT --format gltf|glb|ply|rig``: an asset or a simulated sequence in formats other
tools read (docs/export.md)."""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from vid2sim.asset.folder import AssetFormatError, load_asset
from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.export.gltf import export_gltf
from vid2sim.export.rig import export_rig
from vid2sim.export.sequence import export_sequence, find_sequence_frames
from vid2sim.scene.writing import move_into_place
from vid2sim.splats.ply import PlyFormatError, load_ply, save_ply

FORMATS = ("glb", "gltf", "ply", "rig")
_SUFFIXES = {".glb": "glb", ".gltf": "gltf", ".ply": "ply"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export an asset (Gaussians as glTF/GLB with KHR_gaussian_splatting or 3DGS PLY; the material + "
             "skinning rig as JSON + safetensors) or a simulated sequence (one glTF/GLB/PLY per frame)",
        description="SOURCE is an asset folder (vid2sim reconstruct), a simulate output folder (ply/0000.ply, ...) "
                    "or a 3DGS .ply file. For a single asset or PLY, an OUT ending in .glb/.gltf/.ply is written as "
                    "that file (a .gltf gets its .bin beside it); any other OUT is a folder. Sequences and rigs "
                    "are always folders. glTF output is y-up (the scene's up, -gravity, is rotated to +Y).")
    p.add_argument("source", help="asset folder, simulate output folder, or a 3DGS .ply file")
    p.add_argument("out", help="output file (.glb/.gltf/.ply) or folder")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="output format (default: from OUT's suffix, else glb)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--no-fallback-color", action="store_true",
                   help="glTF: leave out COLOR_0, the point colours viewers without the splat extension show")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_threads_option(p)
    p.set_defaults(func=run)


def _source_kind(source: Path) -> str:

    if source.is_file():
        if source.suffix.lower() == ".ply":
            return "ply"
        raise UserError(f"SOURCE {source} is a file but not a .ply; expected an asset folder, a simulate output "
                        f"folder or a 3DGS .ply file")
    if not source.is_dir():
        raise UserError(f"SOURCE {source} does not exist")
    if (source / "asset.json").is_file():
        return "asset"
    if find_sequence_frames(source):
        return "sequence"
    raise UserError(f"SOURCE {source} is neither an asset folder (no asset.json, see `vid2sim reconstruct`) nor a "
                    f"simulate output (no ply/0000.ply, ...)")


def _existing(paths: list[Path]) -> list[Path]:
    return [p for p in paths if p.exists() or p.is_symlink()]


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    source, out = Path(args.source), Path(args.out)
    kind = _source_kind(source)
    fmt = args.format or _SUFFIXES.get(out.suffix.lower(), "glb")
    single_file = kind in ("asset", "ply") and fmt != "rig" and _SUFFIXES.get(out.suffix.lower()) == fmt
    if out.suffix.lower() in _SUFFIXES and not single_file:
        raise UserError(f"OUT {out} ends in {out.suffix} but --format {fmt} from a {kind} writes a folder; "
                        f"give OUT without a file suffix (or --format {_SUFFIXES[out.suffix.lower()]})")
    if fmt == "rig" and kind != "asset":
        raise UserError(f"--format rig needs an asset folder (asset.json, skinning.pt); SOURCE {source} is a {kind}")
    targets = [out] + ([out.with_suffix(".bin")] if single_file and fmt == "gltf" else [])
    if source.resolve() in [t.resolve() for t in targets]:
        raise UserError(f"OUT {out} is SOURCE; choose another output")
    present = _existing(targets)
    if present and not args.overwrite:
        raise UserError(f"{present[0]} exists; pass --overwrite to replace it")
    progress = not args.quiet
    for p in present:  # a folder cannot atomically replace a file, nor a file a folder: clear the other kind
        if p.is_dir() != (not single_file):
            _remove(p)

    if kind == "sequence":

        path = export_sequence(source, out, fmt, fallback_color=not args.no_fallback_color, progress=progress)
        index = json.loads((path / "sequence.json").read_text())
        print(f"wrote {path}: {len(index['frames'])} frames as {fmt} ({_size(path)})")
        return 0


    up = (0.0, 0.0, 1.0)
    if kind == "asset":

        try:
            asset = load_asset(source)
        except AssetFormatError as exc:
            raise UserError(str(exc)) from exc
        gaussians = asset.rest_gaussians()  # as they look at rest (lit, for a shaded asset)
        g = asset.gravity
        if any(g):
            up = tuple(-float(v) for v in g)
        if fmt == "rig":

            path = export_rig(asset, out)
            print(f"wrote {path}: rig.json, rig.safetensors, gaussians.ply ({_size(path)})")
            return 0
    else:
        try:
            gaussians = load_ply(source)
        except PlyFormatError as exc:
            raise UserError(str(exc)) from exc

    if single_file:
        files = _write_gaussians(gaussians, out, fmt, up, not args.no_fallback_color)
        print(f"wrote {', '.join(str(f) for f in files)} ({gaussians.num} Gaussians, SH degree {gaussians.sh_degree}, "
              f"{_size(*files)})")
        return 0


    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _write_gaussians(gaussians, tmp / f"gaussians.{fmt}", fmt, up, not args.no_fallback_color)
        move_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(f"wrote {out}: gaussians.{fmt} ({gaussians.num} Gaussians, SH degree {gaussians.sh_degree}, {_size(out)})")
    return 0


def _write_gaussians(gaussians, path: Path, fmt: str, up, fallback_color: bool) -> list[Path]:
    if fmt == "ply":

        tmp = path.with_name(f".{path.name}.partial")
        save_ply(gaussians, tmp)
        tmp.replace(path)
        return [path]

    return export_gltf(gaussians, path, up=up, fallback_color=fallback_color)


def _size(*paths: Path) -> str:
    total = 0
    for p in paths:
        total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size
    return f"{total / 1e6:.2f} MB" if total >= 1e5 else f"{total / 1e3:.1f} kB"
