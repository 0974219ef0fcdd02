"""Ways to corrupt a file (or the folder entry holding it), each a function ``(path, rng) -> description``.

Byte-level (any file): truncation, bit flips, random bytes, an empty file, a directory or a dangling,
outside-pointing or looping symlink where the file belongs, the file missing, a name that is not UTF-8.
Structured (JSON and YAML): a value replaced by the wrong type, NaN, ±Inf, a huge or negative number; a key
removed or an unknown one added; the whole document not an object. Images (PNG): another size, another channel
count or bit depth, another format under the same name. NumPy archives: an array removed, reshaped, turned to
NaN, another dtype, or an object array (pickle).
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np

Mutation = Callable[[Path, np.random.Generator], str]


# ---- bytes and folder entries -------------------------------------------------------------------------

def truncate(path: Path, rng: np.random.Generator) -> str:
    data = path.read_bytes()
    keep = int(rng.integers(0, max(1, len(data))))
    path.write_bytes(data[:keep])
    return f"truncated to {keep} of {len(data)} bytes"


def bitflip(path: Path, rng: np.random.Generator) -> str:
    data = bytearray(path.read_bytes())
    if not data:
        return "empty (nothing to flip)"
    k = int(rng.integers(1, 9))
    for _ in range(k):
        i = int(rng.integers(len(data)))
        data[i] ^= 1 << int(rng.integers(8))
    path.write_bytes(bytes(data))
    return f"{k} bits flipped"


def garbage(path: Path, rng: np.random.Generator) -> str:
    n = int(rng.integers(1, 4096))
    path.write_bytes(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
    return f"replaced by {n} random bytes"


def empty(path: Path, rng: np.random.Generator) -> str:
    path.write_bytes(b"")
    return "emptied"


def directory(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    path.mkdir()
    return "replaced by a directory"


def missing(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    return "removed"


def symlink_outside(path: Path, rng: np.random.Generator) -> str:
    """The file replaced by a symlink to a file outside its folder (a copy of itself there)."""
    outside = path.parent.parent / f"outside-{path.name}"
    shutil.copyfile(path, outside) if not outside.exists() else None
    path.unlink()
    os.symlink(os.path.relpath(outside, path.parent), path)
    return f"a symlink to {outside.name} outside the folder"


def symlink_loop(path: Path, rng: np.random.Generator) -> str:
    other = path.with_name(path.name + ".loop")
    path.unlink()
    os.symlink(other.name, path)
    os.symlink(path.name, other)
    return "a symlink loop"


def symlink_dangling(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    os.symlink("does-not-exist", path)
    return "a dangling symlink"


def non_utf8_name(path: Path, rng: np.random.Generator) -> str:
    """The file renamed to a name that is not UTF-8 (so its referrer misses it, and a listing meets the name)."""
    new = os.path.join(os.fsencode(path.parent), b"\xff\xfe" + os.fsencode(path.name))
    os.rename(os.fsencode(path), new)
    return "renamed to a non-UTF-8 name"


BYTES: dict[str, Mutation] = {"truncate": truncate, "bitflip": bitflip, "garbage": garbage, "empty": empty,
                              "directory": directory, "missing": missing, "symlink_outside": symlink_outside,
                              "symlink_loop": symlink_loop, "symlink_dangling": symlink_dangling,
                              "non_utf8_name": non_utf8_name}


# ---- JSON and YAML ---------------------------------------------------------------------------------------

def _leaves(value: Any, path: tuple = ()) -> list[tuple]:
    """Paths of every value in a JSON tree (containers included, the root excluded)."""
    out: list[tuple] = []
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for k, v in items:
        out.append(path + (k,))
        out.extend(_leaves(v, path + (k,)))
    return out


def _get(tree: Any, path: tuple) -> Any:
    for k in path:
        tree = tree[k]
    return tree


def _set(tree: Any, path: tuple, value: Any) -> None:
    _get(tree, path[:-1])[path[-1]] = value


_REPLACEMENTS: tuple[tuple[str, Any], ...] = (
    ("NaN", math.nan), ("Infinity", math.inf), ("-Infinity", -math.inf), ("a huge number", 1e308),
    ("a negative number", -7.0), ("zero", 0), ("a string", "oops"), ("null", None), ("a list", [1, 2]),
    ("an object", {"a": 1}), ("true", True), ("a huge integer", 10**30), ("an empty list", []),
)


def _structured(load: Callable[[str], Any], dump: Callable[[Any], str]) -> dict[str, Mutation]:
    def read(path: Path) -> Any:
        return load(path.read_text(encoding="utf-8"))

    def replace_value(path: Path, rng: np.random.Generator) -> str:
        tree = read(path)
        leaves = _leaves(tree)
        if not leaves:
            return "nothing to replace"
        where = leaves[int(rng.integers(len(leaves)))]
        name, value = _REPLACEMENTS[int(rng.integers(len(_REPLACEMENTS)))]
        _set(tree, where, value)
        path.write_text(dump(tree), encoding="utf-8")
        return f"{'.'.join(map(str, where))} set to {name}"

    def remove_key(path: Path, rng: np.random.Generator) -> str:
        tree = read(path)
        keys = [p for p in _leaves(tree) if isinstance(_get(tree, p[:-1]), dict)]
        if not keys:
            return "no key to remove"
        where = keys[int(rng.integers(len(keys)))]
        del _get(tree, where[:-1])[where[-1]]
        path.write_text(dump(tree), encoding="utf-8")
        return f"{'.'.join(map(str, where))} removed"

    def unknown_key(path: Path, rng: np.random.Generator) -> str:
        tree = read(path)
        dicts = [()] + [p for p in _leaves(tree) if isinstance(_get(tree, p), dict)]
        where = dicts[int(rng.integers(len(dicts)))]
        target = _get(tree, where)
        if not isinstance(target, dict):
            return "no object"
        target["unknown_fuzz_key"] = 1
        path.write_text(dump(tree), encoding="utf-8")
        return f"unknown key added at {'.'.join(map(str, where)) or 'the top'}"

    def not_object(path: Path, rng: np.random.Generator) -> str:
        path.write_text(dump([1, 2, 3]), encoding="utf-8")
        return "a list instead of an object"

    def not_utf8(path: Path, rng: np.random.Generator) -> str:
        data = path.read_bytes()
        i = int(rng.integers(max(1, len(data))))
        path.write_bytes(data[:i] + b"\xff\xfe\xc3" + data[i:])
        return "bytes that are not UTF-8 inserted"

    return {"replace_value": replace_value, "remove_key": remove_key, "unknown_key": unknown_key,
            "not_object": not_object, "not_utf8": not_utf8}


def _yaml_load(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def _yaml_dump(tree: Any) -> str:
    import yaml

    return yaml.safe_dump(tree)


JSON = _structured(json.loads, lambda t: json.dumps(t))  # Python writes NaN and Infinity, as some tools do
YAML = _structured(_yaml_load, _yaml_dump)


# ---- images ------------------------------------------------------------------------------------------------

def image_size(path: Path, rng: np.random.Generator) -> str:
    from PIL import Image

    with Image.open(path) as im:
        im.load()
        w, h = im.size
        new = (max(1, w + int(rng.integers(-w + 1, w))), max(1, h + int(rng.integers(-h + 1, h))))
        if new == (w, h):
            new = (w + 1, h)
        im.resize(new).save(path, format="PNG")
    return f"resized from {w}x{h} to {new[0]}x{new[1]}"


def image_channels(path: Path, rng: np.random.Generator) -> str:
    from PIL import Image

    modes = ["L", "LA", "RGB", "RGBA", "I;16", "P", "1", "CMYK"]
    with Image.open(path) as im:
        im.load()
        mode = modes[int(rng.integers(len(modes)))]
        if mode == im.mode:
            mode = "LA"
        if mode == "I;16":  # a 16/32-bit grey PNG
            im.convert("I").save(path, format="PNG")
        elif mode == "CMYK":
            im.convert("CMYK").save(path, format="JPEG")
        else:
            im.convert(mode).save(path, format="PNG")
    return f"converted to mode {mode}"


def image_format(path: Path, rng: np.random.Generator) -> str:
    from PIL import Image

    fmt = ["JPEG", "BMP", "GIF", "TIFF"][int(rng.integers(4))]
    with Image.open(path) as im:
        im.load()
        (im.convert("RGB") if fmt == "JPEG" else im).save(path, format=fmt)
    return f"a {fmt} under the same name"


IMAGES: dict[str, Mutation] = {"image_size": image_size, "image_channels": image_channels,
                               "image_format": image_format}


# ---- NumPy archives ----------------------------------------------------------------------------------------

def _npz_edit(path: Path, rng: np.random.Generator, edit: Callable[[dict, str], str]) -> str:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if not arrays:
        return "no arrays"
    key = sorted(arrays)[int(rng.integers(len(arrays)))]
    what = edit(arrays, key)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    return what


def npz_remove(path: Path, rng: np.random.Generator) -> str:
    return _npz_edit(path, rng, lambda a, k: (a.pop(k), f"array {k} removed")[1])


def npz_nan(path: Path, rng: np.random.Generator) -> str:
    def edit(a: dict, k: str) -> str:
        a[k] = np.full(a[k].shape, np.nan) if a[k].dtype.kind == "f" else a[k].astype(np.float64) * np.nan
        return f"array {k} set to NaN"
    return _npz_edit(path, rng, edit)


def npz_reshape(path: Path, rng: np.random.Generator) -> str:
    def edit(a: dict, k: str) -> str:
        a[k] = np.resize(a[k], (max(0, a[k].size // 2 - 1),))
        return f"array {k} cut to {a[k].shape}"
    return _npz_edit(path, rng, edit)


def npz_dtype(path: Path, rng: np.random.Generator) -> str:
    def edit(a: dict, k: str) -> str:
        a[k] = np.array([str(v) for v in a[k].reshape(-1)[:5]]) if a[k].size else np.array(["x"])
        return f"array {k} made strings"
    return _npz_edit(path, rng, edit)


def npz_object(path: Path, rng: np.random.Generator) -> str:
    """An object array (loading it needs pickle, which vid2sim must refuse)."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    key = sorted(arrays)[int(rng.integers(len(arrays)))] if arrays else "x"
    arrays[key] = np.array([{"a": 1}, None], dtype=object)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    return f"array {key} an object array (pickle)"


NPZ: dict[str, Mutation] = {"npz_remove": npz_remove, "npz_nan": npz_nan, "npz_reshape": npz_reshape,
                            "npz_dtype": npz_dtype, "npz_object": npz_object}


def mutations_for(path: Path) -> dict[str, Mutation]:
    """The mutations that apply to ``path`` (by its suffix): the byte-level ones and its format's own."""
    suffix = path.suffix.lower()
    out = dict(BYTES)
    if suffix == ".json":
        out.update({f"json_{k}": v for k, v in JSON.items()})
    elif suffix in (".yaml", ".yml"):
        out.update({f"yaml_{k}": v for k, v in YAML.items()})
    elif suffix == ".png":
        out.update(IMAGES)
    elif suffix == ".npz":
        out.update(NPZ)
    return out
