"""Hostile files: a scene, asset or checkpoint made by someone else that tries to run code, to make vid2sim read
outside what the user asked for, to inject script into a report, or to exhaust memory.

Each check builds the hostile file from a valid seed (:func:`~vid2sim.apps.bench.fuzz.inputs.make_seeds`), feeds
it to the command that reads it in a child process (:mod:`~vid2sim.apps.bench.fuzz.runner`), and records whether
the attack got through:

- ``pickle_*``: a torch file (asset skinning weights, Stage I checkpoint) whose pickle calls ``os.system`` /
  writes a marker file when unpickled by plain ``torch.load``; an ``.npz`` with an object array. Got through
  when the marker exists, or the command did not refuse the file.
- ``outside_*``: a ``transforms.json`` naming an absolute path outside the scene, ``../`` paths, a frame that is a
  symlink out of the folder; an asset file symlinked out of its folder. Got through when the command reads
  it (exit code 0) instead of refusing it with a line naming the file.
- ``report_injection``: ``scene.json`` metadata, a scene folder's name and the asset's material strings carrying
  ``<script>`` and ``onerror=`` payloads; the report is written and its HTML must hold them only escaped; when
  Chromium is installed, the page is loaded headless and the payload must not have run (it would add an element
  with id ``pwned`` to the DOM).
- ``bomb_*``: a PNG frame declaring 60 000 × 60 000 pixels (a few hundred bytes on disk), an ``.npz`` whose
  array inflates to 8 GB. Got through when the command takes more than the time limit or exits other than with
  a clear line naming the limit.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import tempfile
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vid2sim.apps.bench.fuzz.runner import cli_call, judge, run_in_child

#: what the injected script does when it runs: an element the DOM dump would show
PAYLOAD = "<script>document.body.insertAdjacentHTML('beforeend','<p id=pwned>pwned</p>')</script>"
PAYLOAD_ATTR = "\"><img src=x onerror=\"document.body.insertAdjacentHTML('beforeend','<p id=pwned>pwned</p>')\">"


class _Marker:
    """Unpickling this calls ``open(marker, 'w')`` — code a checkpoint must never get to run."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _torch_pickle(path: Path, marker: Path, wrap: Callable[[Any], Any] = lambda x: x) -> None:
    import torch

    torch.save(wrap({"weights": _Marker(str(marker))}), path)


def _png_bomb(path: Path, side: int = 60_000) -> None:
    """A valid PNG header declaring ``side`` × ``side`` RGB pixels, with a tiny (truncated) image stream."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    row = b"\x00" + b"\xff" * (3 * side)
    body = zlib.compressobj(9).compress(row * 8)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def _npz_bomb(path: Path, keys: list[str], gigabytes: float = 8.0) -> None:
    """An .npz whose first array inflates to ``gigabytes`` (zeros compress ~1000:1), the others 1 element."""
    import zipfile

    n = int(gigabytes * (1 << 30) / 8)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (n // 3, 3)})
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        with z.open(f"{keys[0]}.npy", "w", force_zip64=True) as f:
            f.write(header.getvalue())
            block = bytes(1 << 24)
            for _ in range((n // 3 * 3 * 8) // len(block)):
                f.write(block)
        for k in keys[1:]:
            buf = io.BytesIO()
            np.save(buf, np.ones(1))
            z.writestr(f"{k}.npy", buf.getvalue())


# ---- the checks ------------------------------------------------------------------------------------------

def _copy(seed: Path, into: Path) -> Path:
    target = into / seed.name
    shutil.copytree(seed, target) if seed.is_dir() else shutil.copyfile(seed, target)
    return target


def _fit(scene: Path, work: Path) -> Callable[[], int]:
    return cli_call(["fit-gaussians", str(scene), str(work / "fit"), "--iterations", "1", "--quiet", "--threads", "1"])


def _simulate(asset: Path, work: Path) -> Callable[[], int]:
    return cli_call(["simulate", str(asset), str(work / "sim"), "--frames", "2", "--resolution", "8", "--cameras",
                     "ring", "--views", "1", "--no-video", "--quiet"])


def check(name: str, seeds: dict[str, Path], work: Path, timeout: float, browser: bool, quick: bool = False
          ) -> dict[str, Any]:
    """Run the hostile check ``name``; returns {"name", "got_through", "why", ...}."""
    work.mkdir(parents=True, exist_ok=True)
    marker = work / "MARKER-code-ran"
    record: dict[str, Any] = {"name": name}

    def refused(result, names: list[str]) -> tuple[bool, str]:
        verdict, why = judge(result, names)
        return verdict in ("clean", "noisy", "vague"), f"{verdict}: {why}"

    if name == "pickle_asset_weights":
        asset = _copy(seeds["asset"], work)
        _torch_pickle(asset / "skinning.pt", marker)
        ok, why = refused(run_in_child(_simulate(asset, work), timeout), ["skinning.pt"])
    elif name == "pickle_checkpoint":
        ckpt = work / "predictor.pt"
        _torch_pickle(ckpt, marker, lambda x: {"format": "vid2sim-predictor/1", **x})
        ok, why = refused(run_in_child(cli_call(["eval-predictor", str(ckpt), str(seeds["data"])]), timeout),
                          ["predictor.pt"])
    elif name == "pickle_npz_object":
        asset = _copy(seeds["asset"], work)
        with np.load(asset / "points.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["cubature_weights"] = np.array([_Marker(str(marker))], dtype=object)
        np.savez(asset / "points.npz", **arrays)
        ok, why = refused(run_in_child(_simulate(asset, work), timeout), ["points.npz"])
    elif name in ("outside_absolute", "outside_dotdot", "outside_symlink_frame"):
        scene = _copy(seeds["scene_rgba"], work)
        secret = work / "secret.png"
        shutil.copyfile(next((scene / "images").iterdir()), secret)
        doc = json.loads((scene / "transforms.json").read_text())
        frame = doc["frames"][0]
        if name == "outside_absolute":
            frame["file_path"] = str(secret.resolve())
        elif name == "outside_dotdot":
            frame["file_path"] = "../secret.png"
        else:
            target = scene / frame["file_path"]
            target = target if target.exists() else target.with_name(target.name + ".png")
            target.unlink()
            os.symlink(secret.resolve(), target)
        (scene / "transforms.json").write_text(json.dumps(doc))
        ok, why = refused(run_in_child(_fit(scene, work), timeout), ["outside the scene folder"])
    elif name == "outside_asset_symlink":
        asset = _copy(seeds["asset"], work)
        shutil.move(asset / "material.json", work / "material.json")
        os.symlink((work / "material.json").resolve(), asset / "material.json")
        ok, why = refused(run_in_child(_simulate(asset, work), timeout), ["outside the asset folder"])
    elif name == "bomb_png":
        scene = _copy(seeds["scene_rgba"], work)
        first = sorted((scene / "images").iterdir())[0]
        _png_bomb(first)
        ok, why = refused(run_in_child(_fit(scene, work), timeout), ["VID2SIM_MAX_IMAGE_PIXELS"])
    elif name == "bomb_npz":
        asset = _copy(seeds["asset"], work)
        # quick: a 64 MiB bomb against a limit lowered to 32 MiB (the same path, a hundredth of the work)
        _npz_bomb(asset / "points.npz", ["points", "cubature_points", "cubature_weights", "contact_points",
                                         "contact_areas", "volume"], gigabytes=1 / 16 if quick else 8.0)
        env = {"VID2SIM_MAX_ARRAY_BYTES": str(32 << 20)} if quick else None
        ok, why = refused(run_in_child(_simulate(asset, work), timeout, env=env), ["VID2SIM_MAX_ARRAY_BYTES"])
    elif name == "report_injection":
        ok, why, extra = _report_injection(seeds, work, timeout, browser)
        record.update(extra)
    else:
        raise ValueError(f"unknown hostile check {name!r}")
    ran = marker.exists()
    record.update(got_through=ran or not ok, code_ran=ran, why=why)
    return record


def _report_injection(seeds: dict[str, Path], work: Path, timeout: float, browser: bool
                      ) -> tuple[bool, str, dict[str, Any]]:
    """Write a report of an asset on a scene whose strings carry script; (escaped and inert, why, details)."""
    scene = work / f"scene{PAYLOAD_ATTR[:20].replace('/', '')}"
    shutil.copytree(seeds["scene_rgba"], scene)
    doc = json.loads((scene / "scene.json").read_text())
    doc.setdefault("metadata", {}).update({"note": PAYLOAD, "material": PAYLOAD_ATTR, "E": 1e5})
    (scene / "scene.json").write_text(json.dumps(doc))
    asset = _copy(seeds["asset"], work)
    material = json.loads((asset / "material.json").read_text())
    material["model_note"] = PAYLOAD
    (asset / "material.json").write_text(json.dumps(material))
    out = work / "report"
    result = run_in_child(cli_call(["report", str(asset), str(out), "--scene", str(scene), "--quiet"]), timeout)
    if result.returncode != 0:
        return False, f"the report was not written: {' | '.join(result.error_lines()[-2:])}", {}
    page = (out / "index.html").read_text(encoding="utf-8")
    raw = [p for p in (PAYLOAD, "<img src=x onerror", "<p id=pwned>") if p in page]
    extra: dict[str, Any] = {"unescaped_in_html": raw, "browser": None}
    if raw:
        return False, f"the HTML holds the payload unescaped: {raw}", extra
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser and chromium:
        import subprocess

        dom = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                              f"--user-data-dir={work / 'profile'}", "--virtual-time-budget=3000", "--dump-dom",
                              (out / "index.html").resolve().as_uri()], capture_output=True, text=True,
                             timeout=timeout)
        ran = 'id="pwned"' in dom.stdout or "id=pwned" in dom.stdout
        extra["browser"] = {"chromium": chromium, "payload_ran": ran, "dom_bytes": len(dom.stdout)}
        if ran or not dom.stdout:
            return False, "the payload ran in Chromium" if ran else f"Chromium gave no DOM: {dom.stderr[-300:]}", extra
    return True, "escaped" + (" and inert in Chromium" if extra["browser"] else " (no browser check)"), extra


CHECKS = ("pickle_asset_weights", "pickle_checkpoint", "pickle_npz_object", "outside_absolute", "outside_dotdot",
          "outside_symlink_frame", "outside_asset_symlink", "bomb_png", "bomb_npz", "report_injection")


def run(config, records_path: str | Path | None, seeds: dict[str, Path], progress: bool = False) -> dict[str, Any]:
    """Every hostile check on ``seeds`` (:func:`~vid2sim.apps.bench.fuzz.inputs.seeds_in_child`), resumed from
    ``records_path``; returns the figures."""
    from vid2sim.apps.bench.fuzz.records import RecordFile, read_records

    done = read_records(records_path) if records_path is not None else {}
    sink = RecordFile(records_path)
    results = dict(done)
    with tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-hostile-") as tmp:
        for i in [i for i in range(len(CHECKS)) if i not in done]:
            record = check(CHECKS[i], seeds, Path(tmp) / f"case{i}", config.timeout, config.browser, config.quick)
            record["index"] = i
            results[i] = record
            sink.add(record)
            if progress:
                print(f"hostile {CHECKS[i]}: {'GOT THROUGH' if record['got_through'] else 'stopped'} "
                      f"({record['why'][:200]})", flush=True)
    records = [results[i] for i in sorted(results)]
    return {"checks": len(records), "got_through": sum(1 for r in records if r["got_through"]),
            "code_ran": sum(1 for r in records if r.get("code_ran")),
            "results": {r["name"]: {"got_through": r["got_through"], "why": r["why"][:300]} for r in records}}
