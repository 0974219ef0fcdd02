"""Input fuzz: valid files of every kind vid2sim reads, corrupted one way each, fed to the command that reads them.

Seeds (:func:`make_seeds`, built once per campaign in a child process): a scene folder in each layout (RGBA
PNGs, RGB + mask PNGs, videos) with extras, an asset folder, a 3DGS PLY, a GLB, a scenario YAML, a Stage I
checkpoint (the shipped one) and a training-data folder. Case i copies one seed, applies one mutation of
:mod:`~vid2sim.apps.bench.fuzz.mutations` to one of its files (chosen by ``seed + i``) and runs the command that
reads it in a child with a time limit (:mod:`~vid2sim.apps.bench.fuzz.runner`):

| kind | command |
|---|---|
| scene | ``vid2sim fit-gaussians SCENE OUT --iterations 1`` |
| asset | ``vid2sim simulate ASSET OUT`` (2 frames, 8 px) or ``vid2sim export ASSET OUT.glb`` |
| scenario | ``vid2sim simulate ASSET OUT --scenario FILE.yaml`` |
| ply | ``vid2sim export FILE.ply OUT.glb`` |
| glb | :func:`vid2sim.export.gltf.load_gltf_gaussians` (no command reads glTF) |
| checkpoint, data | ``vid2sim eval-predictor CHECKPOINT DATA`` |

A case passes when the command either ends in one line ``vid2sim CMD: error: …`` naming the corrupted file
(exit code 2, no traceback, within the time limit) and leaves no output that looks complete, or succeeds (the
file was still usable: counted as ``accepted``) with a complete output.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vid2sim.apps.bench.fuzz import mutations
from vid2sim.apps.bench.fuzz.runner import (
    ChildResult,
    cli_call,
    judge,
    reader_call,
    run_in_child,
)

KINDS = ("scene_rgba", "scene_mask", "scene_video", "asset", "scenario", "ply", "glb", "checkpoint", "data")


# ---- seeds -------------------------------------------------------------------------------------------------

def _tiny_scene(layout: str):
    import torch

    from vid2sim.scene.folder import Scene, SceneConfig
    from vid2sim.splats.cameras import camera_ring

    V, T, H, W = 3, 4, 16, 16
    g = torch.Generator().manual_seed(0)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    mask = (((yy - H / 2) ** 2 + (xx - W / 2) ** 2) < (H / 3) ** 2).float().expand(V, T, H, W).contiguous()
    colour = torch.randint(0, 256, (V, T, H, W, 3), generator=g, dtype=torch.uint8).float() / 255
    images = colour * mask[..., None] + (1 - mask[..., None])
    cfg = SceneConfig(floor_height=-0.7, metadata={"E": 1e5, "nu": 0.3, "note": "fuzz seed"})
    extras = {"tet_trajectory": {"vertices": torch.randn(T, 9, 3, generator=g, dtype=torch.float64),
                                 "tets": torch.randint(0, 9, (6, 4), generator=g)}}
    return Scene(camera_ring(V, 2.5, 25.0, W, H, fov_x_deg=45.0), images, mask, None, cfg, None, extras)


def make_seeds(folder: Path, quick: bool = False) -> dict[str, Path]:
    """Write the valid seed files into ``folder``; returns kind → path."""
    import torch

    from vid2sim.apps.bench.fuzz.physics import build_asset
    from vid2sim.asset.folder import save_asset
    from vid2sim.export.gltf import export_gltf
    from vid2sim.scene.writing import write_scene
    from vid2sim.splats.ply import save_ply

    torch.set_num_threads(1)
    folder.mkdir(parents=True, exist_ok=True)
    seeds: dict[str, Path] = {}
    for kind, layout in (("scene_rgba", "rgba"), ("scene_mask", "rgb+mask"), ("scene_video", "video")):
        seeds[kind] = write_scene(_tiny_scene(layout), folder / kind, layout=layout)
    work = folder / "work"
    work.mkdir(exist_ok=True)
    asset = build_asset("icosphere", 2, 30, 0, work, skinning_iterations=5)
    seeds["asset"] = save_asset(asset, folder / "asset", config={"fuzz": True}, log={"fuzz": True})
    save_ply(asset.gaussians, folder / "gaussians.ply")
    seeds["ply"] = folder / "gaussians.ply"
    export_gltf(asset.gaussians, folder / "gaussians.glb")
    seeds["glb"] = folder / "gaussians.glb"
    (folder / "scenario.yaml").write_text(
        "frames: 2\ndt: 0.05\nfloor: {height: -0.7, stiffness: 5.0e+7}\n"
        "obstacles: [{center: [3.0, 0.0, -0.7], radius: 0.2}]\n"
        "initial: {translation: [0.0, 0.0, 0.1], linear_velocity: [0.5, 0.0, 0.0]}\n"
        "material: {preset: elastic, youngs_modulus: 1.0e+5, poisson_ratio: 0.3}\n"
        "cameras: {type: ring, views: 1}\nresolution: 8\n", encoding="utf-8")
    seeds["scenario"] = folder / "scenario.yaml"
    from vid2sim.predictor.data import TrainingDataConfig, make_training_data
    from vid2sim.predictor.predict import DEFAULT_PREDICTOR

    # the reduced truth: seconds, where the FEM truth takes minutes a draw
    cfg = TrainingDataConfig(truth="reduced", objects=1, draws_per_object=2, resolution=16, frames=16, points=400,
                             cubature_points=40, contact_points=60)
    make_training_data(cfg, folder / "data", workers=1, threads=1, progress=False)
    seeds["data"] = folder / "data"
    shutil.copyfile(DEFAULT_PREDICTOR, folder / "predictor.pt")
    seeds["checkpoint"] = folder / "predictor.pt"
    return seeds


# ---- cases ---------------------------------------------------------------------------------------------

def _files(root: Path) -> list[Path]:
    """The regular files of a seed (itself when it is a file), in a stable order."""
    if root.is_file():
        return [root]
    return sorted(p for p in root.rglob("*") if p.is_file() and not p.is_symlink())


def _copy(seed: Path, into: Path) -> Path:
    target = into / seed.name
    if seed.is_dir():
        shutil.copytree(seed, target, symlinks=True)
    else:
        shutil.copyfile(seed, target)
    return target


def _command(kind: str, target: Path, seeds: dict[str, Path], work: Path, rng: np.random.Generator
             ) -> tuple[Callable[[], int], Path | None, Callable[[Path], bool]]:
    """(child body, output path, "does the output look complete") for a mutated ``target`` of ``kind``."""
    out = work / "out"
    if kind.startswith("scene"):
        argv = ["fit-gaussians", str(target), str(out), "--iterations", "1", "--quiet", "--threads", "1"]
        return cli_call(argv), out, lambda o: (o / "gaussians.ply").is_file()
    if kind == "asset" and rng.random() < 0.5:
        glb = work / "out.glb"
        return cli_call(["export", str(target), str(glb), "--quiet"]), glb, lambda o: o.is_file()
    if kind in ("asset", "scenario"):
        asset = target if kind == "asset" else seeds["asset"]
        argv = ["simulate", str(asset), str(out), "--frames", "2", "--resolution", "8", "--cameras", "ring",
                "--views", "1", "--no-video", "--quiet"]
        if kind == "scenario":
            argv += ["--scenario", str(target)]
        return cli_call(argv), out, lambda o: (o / "summary.json").is_file()
    if kind == "ply":
        glb = work / "out.glb"
        return cli_call(["export", str(target), str(glb), "--quiet"]), glb, lambda o: o.is_file()
    if kind == "glb":
        from vid2sim.export.gltf import load_gltf_gaussians

        return reader_call("glTF reader", lambda: load_gltf_gaussians(target)), None, lambda o: True
    if kind in ("checkpoint", "data"):
        ckpt = target if kind == "checkpoint" else seeds["checkpoint"]
        data = target if kind == "data" else seeds["data"]
        js = work / "eval.json"
        return cli_call(["eval-predictor", str(ckpt), str(data), "--json", str(js)]), js, lambda o: o.is_file()
    raise ValueError(f"unknown kind {kind!r}")


def run_case(index: int, seed: int, seeds: dict[str, Path], timeout: float) -> dict[str, Any]:
    """Case ``index``: one kind, one file, one mutation (all from ``seed``); returns its record."""
    rng = np.random.default_rng([seed, 5300])
    kind = KINDS[int(rng.integers(len(KINDS)))]
    with tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-input-") as tmp:
        work = Path(tmp) / "case"
        (work / "in").mkdir(parents=True)
        root = _copy(seeds[kind], work / "in")
        files = _files(root)
        target = files[int(rng.integers(len(files)))]
        ops = mutations.mutations_for(target)
        name = sorted(ops)[int(rng.integers(len(ops)))]
        try:
            what = ops[name](target, rng)
        except Exception as exc:  # noqa: BLE001 - a mutation that does not apply to this file
            what = f"mutation not applicable ({type(exc).__name__}: {exc})"
        body, out, complete = _command(kind, root, seeds, work, rng)
        result: ChildResult = run_in_child(body, timeout, cwd=work)
        rel = target.relative_to(root.parent) if target != root else Path(target.name)
        names = [target.name, str(rel), root.name] if target == root else [target.name, str(rel)]
        if name == "non_utf8_name":  # the referrer misses the file under its old name
            names.append(target.name)
        verdict, why = judge(result, names)
        looks_complete = out is not None and out.exists() and complete(out)
        if verdict not in ("accepted",) and looks_complete:
            verdict, why = "left_output", f"failed ({verdict}) but {out.name} looks complete; {why}"
        elif verdict == "accepted" and out is not None and not looks_complete:
            verdict, why = "bug", "exit code 0 without a complete output"
        return {"index": index, "seed": seed, "kind": kind, "file": str(rel), "mutation": name, "what": what,
                "verdict": verdict, "why": why, "returncode": result.returncode,
                "seconds": round(result.seconds, 2)}


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The section's figures."""
    from collections import Counter

    verdicts = Counter(r["verdict"] for r in records)
    rejected = [r for r in records if r["verdict"] != "accepted"]
    clean = verdicts.get("clean", 0)
    return {
        "cases": len(records),
        "verdicts": dict(sorted(verdicts.items())),
        "rejected": len(rejected),
        "clean_one_line_errors": clean,
        "clean_percent": round(100.0 * clean / len(rejected), 2) if rejected else None,
        "by_kind": {k: dict(Counter(r["verdict"] for r in records if r["kind"] == k)) for k in KINDS},
        "slowest_seconds": max((r["seconds"] for r in records), default=None),
        "problems": [{k: r[k] for k in ("seed", "kind", "file", "mutation", "what", "verdict", "why")}
                     for r in records if r["verdict"] not in ("clean", "accepted")][:40],
    }


def seeds_in_child(folder: Path, quick: bool = False) -> dict[str, Path]:
    """:func:`make_seeds` into ``folder`` in a forked child (the campaign's own process stays free of torch
    threads, so that its later forks are safe); returns kind → path."""
    made = run_in_child(lambda: (make_seeds(folder, quick), 0)[1], 600.0)
    if made.returncode != 0:
        raise RuntimeError(f"could not build the fuzz seeds: {made.stderr[-2000:]}")
    return {k: folder / v for k, v in _SEED_NAMES.items()}


def run(config, records_path: str | Path | None, seeds: dict[str, Path], progress: bool = False) -> dict[str, Any]:
    """``config.inputs`` cases on ``seeds`` (:func:`seeds_in_child`), resumed from ``records_path``; returns the
    figures."""
    from vid2sim.apps.bench.fuzz.records import RecordFile, read_records, todo

    done = read_records(records_path) if records_path is not None else {}
    sink = RecordFile(records_path)
    results = dict(done)
    for i in todo(range(config.inputs), done):
        record = run_case(i, config.seed + i, seeds, config.timeout)
        results[i] = record
        sink.add(record)
        if progress:
            print(f"inputs {len(results)}/{config.inputs}: {record['kind']} {record['file']} "
                  f"{record['mutation']}: {record['verdict']} ({record['seconds']} s)", flush=True)
    return summarize([results[i] for i in sorted(results) if i < config.inputs])


#: where :func:`make_seeds` puts each kind (relative to its folder)
_SEED_NAMES = {"scene_rgba": "scene_rgba", "scene_mask": "scene_mask", "scene_video": "scene_video",
               "asset": "asset", "scenario": "scenario.yaml", "ply": "gaussians.ply", "glb": "gaussians.glb",
               "checkpoint": "predictor.pt", "data": "data"}
