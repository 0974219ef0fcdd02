"""Reading a Stage I training dataset (``vid2sim make-training-data``) as a torch ``Dataset``.

``TrainingData(folder, split)`` indexes every (shard, draw) pair of the shards listed in ``index.json``
and returns ``(video, targets)``:

- ``video``: float32 (T, 3, R, R), the uint8 frames / 255, then normalised per channel by ImageNet's mean
  (0.485, 0.456, 0.406) and standard deviation (0.229, 0.224, 0.225), the statistics VideoMAE was
  pre-trained with (``normalize="imagenet"``, default), or left in [0, 1] (``normalize="unit"``).
  The white background becomes (2.25, 2.43, 2.64).
- ``targets``: {"log10_E": float32 (), "nu": float32 (), "last_layer": float32 (650,)} — the issue's labels,
  unscaled (:meth:`TrainingData.label_statistics` gives the training split's means and standard deviations
  for standardising them).

The split is by object, so every draw of one object is on the same side. It is deterministic and stable
when the dataset grows: a shard goes to validation when the first 8 bytes of SHA-256("<seed>:<file>"),
read as a fraction of 2⁶⁴, fall below ``val_fraction``.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from vid2sim.predictor.data import FORMAT, INDEX
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import read_json
from vid2sim.runtime.limits import npz_size_problem, outside

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SPLITS = ("train", "val", "all")


def validation_fraction_of(name: str, seed: int) -> float:
    """The shard's position in [0, 1) that decides its split (SHA-256 of ``"<seed>:<name>"``)."""
    digest = hashlib.sha256(f"{seed}:{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2.0**64


def read_shard(path: Path, draws: int) -> dict[str, np.ndarray]:
    """The arrays of one shard (``video`` (D, T, H, W, 3) uint8, ``log10_E`` (D,), ``nu`` (D,), ``last_layer``
    (650,)), checked; raises InputError naming the shard when it is unreadable or not that."""
    import zipfile
    import zlib


    too_big = npz_size_problem(path)
    if too_big is not None:
        raise InputError(f"{path}: {too_big}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("video", "log10_E", "nu", "last_layer")}
    except KeyError as exc:
        raise InputError(f"{path}: a training-data shard without the array {exc}") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{path}: not a readable training-data shard ({type(exc).__name__}: {exc})") from None
    v, e, n, last = arrays["video"], arrays["log10_E"], arrays["nu"], arrays["last_layer"]
    if v.dtype != np.uint8 or v.ndim != 5 or v.shape[0] != draws or v.shape[-1] != 3:
        raise InputError(f"{path}: video must be uint8 of shape ({draws}, T, H, W, 3), got {v.dtype} {v.shape}")
    for key, a in (("log10_E", e), ("nu", n)):
        if a.dtype.kind != "f" or a.shape != (draws,) or not np.isfinite(a).all():
            raise InputError(f"{path}: {key} must be {draws} finite numbers, got {a.dtype} {a.shape}")
    if last.dtype.kind != "f" or last.ndim != 1 or not np.isfinite(last).all():
        raise InputError(f"{path}: last_layer must be a vector of finite numbers, got {last.dtype} {last.shape}")
    return arrays


class TrainingData(Dataset):
    """The samples of a training-data folder (module docstring).

    Args:
        folder: the dataset folder (``index.json`` + shards).
        split: "train", "val" or "all".
        val_fraction: share of objects held out for validation.
        split_seed: changes which objects are held out.
        normalize: "imagenet" (default) or "unit".
        cache_shards: decoded shards kept in memory (consecutive indices read one shard once).
    Raises:
        FileNotFoundError: no ``index.json``. ValueError: not a training-data folder, bad arguments, or a
        listed shard is missing.
    """

    def __init__(self, folder: str | Path, split: str = "train", val_fraction: float = 0.05, split_seed: int = 0,
                 normalize: str = "imagenet", cache_shards: int = 2) -> None:
        self.folder = Path(folder)
        index_path = self.folder / INDEX
        if not index_path.is_file():
            raise FileNotFoundError(f"{self.folder} has no {INDEX}; it is not a training-data folder "
                                    "(make one with `vid2sim make-training-data`)")
        self.index: dict[str, Any] = read_json(index_path, "a training-data index (vid2sim make-training-data)")
        if self.index.get("format") != FORMAT:
            raise InputError(f"{index_path}: format {self.index.get('format')!r}, expected {FORMAT!r}")
        if split not in SPLITS:
            raise InputError(f"split must be one of {SPLITS}, got {split!r}")
        if not 0.0 <= val_fraction < 1.0:
            raise InputError(f"val_fraction must lie in [0, 1), got {val_fraction}")
        if normalize not in ("imagenet", "unit"):
            raise InputError(f"normalize must be 'imagenet' or 'unit', got {normalize!r}")
        self.split, self.normalize = split, normalize
        config, shards = self.index.get("config"), self.index.get("shards")
        draws = config.get("draws_per_object") if isinstance(config, dict) else None
        if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
            raise InputError(f"{index_path}: config.draws_per_object must be an integer >= 1, got {draws!r}")
        if not isinstance(shards, list) or not all(isinstance(e, dict) and isinstance(e.get("file"), str)
                                                   for e in shards):
            raise InputError(f"{index_path}: shards must be a list of {{\"file\": NAME, ...}} entries")
        self.draws = draws
        names = [e["file"] for e in shards]
        for n in names:
            shard = self.folder / n
            if not shard.is_file():
                raise InputError(f"{self.folder}: shard {n} is listed in {INDEX} but missing")
            real = outside(self.folder, shard)
            if real is not None:
                raise InputError(f"{index_path}: shard {n} resolves to {real}, outside the training-data folder "
                                 "(set VID2SIM_ALLOW_OUTSIDE_PATHS=1 to allow files elsewhere)")

        def keep(name: str) -> bool:
            if split == "all":
                return True
            val = validation_fraction_of(name, split_seed) < val_fraction
            return val if split == "val" else not val

        self.shards = [n for n in names if keep(n)]
        self._cache: dict[str, dict[str, np.ndarray]] = {}
        self._cache_size = max(0, int(cache_shards))

    def __len__(self) -> int:
        return len(self.shards) * self.draws

    def _shard(self, name: str) -> dict[str, np.ndarray]:
        if name in self._cache:
            return self._cache[name]
        arrays = read_shard(self.folder / name, self.draws)
        if self._cache_size:
            while len(self._cache) >= self._cache_size:
                self._cache.pop(next(iter(self._cache)))
            self._cache[name] = arrays
        return arrays

    def sample_id(self, i: int) -> tuple[str, int]:
        """(shard file, draw) of sample ``i``."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample {i} out of range for {len(self)} samples")
        i %= len(self)
        return self.shards[i // self.draws], i % self.draws

    def __getitem__(self, i: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        name, d = self.sample_id(i)
        z = self._shard(name)
        video = torch.from_numpy(np.ascontiguousarray(z["video"][d])).permute(0, 3, 1, 2).float() / 255.0
        if self.normalize == "imagenet":
            mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
            std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
            video = (video - mean) / std
        targets = {"log10_E": torch.tensor(float(z["log10_E"][d])), "nu": torch.tensor(float(z["nu"][d])),
                   "last_layer": torch.from_numpy(z["last_layer"].astype(np.float32))}
        return video, targets

    def label_statistics(self) -> dict[str, dict[str, torch.Tensor]]:
        """Mean and standard deviation of each label over this split's samples (last_layer per component):
        {"log10_E": {"mean", "std"}, "nu": {...}, "last_layer": {"mean": (650,), "std": (650,)}}."""
        logs, nus, layers = [], [], []
        for name in self.shards:
            z = read_shard(self.folder / name, self.draws)
            logs.append(z["log10_E"])
            nus.append(z["nu"])
            layers.append(np.repeat(z["last_layer"][None], len(z["log10_E"]), axis=0))
        out = {}
        for key, arr in (("log10_E", np.concatenate(logs)), ("nu", np.concatenate(nus)),
                         ("last_layer", np.concatenate(layers))):
            a = torch.from_numpy(arr.astype(np.float64))
            out[key] = {"mean": a.mean(0).float(), "std": a.std(0, unbiased=False).float()}
        return out
