"""The simulation-ready asset: what ``vid2sim reconstruct`` writes and :func:`load_asset` reads back.

A folder (docs/asset-format.md)::

    asset.json          format/version, units, networks' architecture, simulator settings, floor and gravity,
                        initial rigid velocity, the canonical frame, the files below
    material.json       model, E (Pa), log10 E, ν, density (kg/m³), damping ratio
    gaussians.ply       the Gaussians at frame 0 (standard 3DGS PLY, any splat viewer opens it), lit as at frame 0
    shading.npz         (only for a shaded asset) the Gaussians' rest-frame normals, the light direction and
                        ambient share: the colours are then albedos lit by a light fixed in the world
    skinning.pt         the skinning field's weights (its input frame included)
    jacobian.pt         the Neural Jacobian's weights (only when the asset uses it)
    points.npz          cubature points and weights, their mass volumes, contact points and areas, interior
                        points, volume
    config.json         the reconstruction settings used
    log.json            the optimisation log (loss, E, ν per iteration) and stage timings

Written atomically (a temporary folder moved into place), so a folder named like an asset is complete.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.external import Floor, Gravity
from vid2sim.physics.neural_jacobian import NeuralJacobian
from vid2sim.physics.skinning import SkinningField
from vid2sim.physics.solver import Material, SimConfig, SimState, Simulator
from vid2sim.physics.stiffness_curve import StiffnessCurve
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.files import load_torch_file, read_json
from vid2sim.runtime.limits import npz_size_problem, outside
from vid2sim.scene.writing import move_into_place
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.ply import load_ply, save_ply
from vid2sim.splats.shading import Shading

ASSET_FORMAT = "vid2sim-asset"
ASSET_VERSION = 1
FILES = {"asset": "asset.json", "material": "material.json", "gaussians": "gaussians.ply", "skinning": "skinning.pt",
         "jacobian": "jacobian.pt", "points": "points.npz", "config": "config.json", "log": "log.json",
         "shading": "shading.npz"}


class AssetFormatError(InputError):
    """An asset folder is missing a file or holds an invalid value (the message names it)."""


@dataclass
class Asset:
    """A simulation-ready object.

    Attributes:
        gaussians: the Gaussians at frame 0 (the rest configuration, world frame).
        field: the skinning field (input frame = the object's canonical frame).
        jacobian: the Neural Jacobian, or None (closed-form dF/dz).
        material: {"model", "E", "log10_E", "nu", "density", "damping_ratio", "stiffness_scale" (optional, 1 when
            absent: the subspace's calibration, ``Simulator(stiffness_scale=)``; kept under material overrides),
            "stiffness_curve" (optional: the calibration as a function of ν, {"nu": [...], "scale": [...]} and,
            for a two-factor calibration, "lam_scale": [...], the factor on λ alone; when present the simulator
            uses it at its ν and "stiffness_scale" is its value at "nu"), "volumetric" (optional, "pointwise"
            when absent, or "projected": ``Simulator(volumetric=)``)}.
        cubature_points: (K, 3); cubature_weights: (K,) (m³).
        contact_points: (S, 3); contact_areas: (S,) (m²).
        points: (N, 3) interior samples; volume: m³.
        sim_config: the simulator's :class:`SimConfig`.
        gravity: (3,) m/s²; floor_height: m or None; floor_stiffness: Pa/m (a contact pressure per metre);
            floor_friction: the floor's Coulomb coefficient μ (0: frictionless; assets written before it had none).
        length_scale: the damping's and automatic substeps' length (m).
        initial_velocity: {"linear": [3], "angular": [3], "centre": [3]} at frame 0.
        continuation: the state fitted to the last observed frames, from which the captured drop goes on after
            them, or None (the drop is one rollout from frame 0): {"frame": a, "from_frame": T (the first frame
            after the observed ones), "z": [12H], "zdot": [12H], "t": s, "fit": its record}
            (:mod:`vid2sim.reconstruct.stages.continuation`).
        dt: the video frame time (s).
        extra: free-form records (canonical frame, source scene, timings).
        shading: a :class:`~vid2sim.splats.shading.Shading` (normals of the N Gaussians, a world-fixed light), or
            None. With it, ``gaussians`` hold albedos, and every render lights them by the current pose.
        mass_volumes: (K,) m³, the volumes the cubature points' mass is lumped on (``Simulator(mass_volumes=)``,
            :mod:`vid2sim.physics.mass`), or None for the cubature weights (assets written before they existed).
    """

    gaussians: Gaussians
    field: torch.nn.Module
    jacobian: torch.nn.Module | None
    material: dict[str, Any]
    cubature_points: Tensor
    cubature_weights: Tensor
    contact_points: Tensor
    contact_areas: Tensor
    points: Tensor
    volume: float
    sim_config: SimConfig
    gravity: list[float]
    floor_height: float | None
    floor_stiffness: float
    length_scale: float
    initial_velocity: dict[str, list[float]]
    dt: float
    extra: dict[str, Any] = field(default_factory=dict)
    shading: Shading | None = None
    mass_volumes: Tensor | None = None
    floor_friction: float = 0.0
    continuation: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.shading is not None and self.shading.num != self.gaussians.num:
            raise ConfigError(f"Asset: the shading has {self.shading.num} normals for {self.gaussians.num} Gaussians")

    def rest_gaussians(self) -> Gaussians:
        """The Gaussians as they look at rest (frame 0's pose): lit by the shading when the asset has one."""
        if self.shading is None:
            return self.gaussians
        return replace(self.gaussians, sh=self.shading.shade(self.gaussians.sh))

    def simulator(self, externals: list | None = None, **material_overrides: Any) -> Simulator:
        """A ready :class:`Simulator` for this asset (the captured floor and gravity unless ``externals``
        is given; ``material_overrides`` replace E (``youngs_modulus``), ``poisson_ratio``, ``density``,
        ``damping_ratio``, ``plasticity``)."""

        values = {"youngs_modulus": float(self.material["E"]), "poisson_ratio": float(self.material["nu"]),
                  "density": float(self.material["density"]), "damping_ratio": float(self.material["damping_ratio"])}
        values.update(material_overrides)
        if externals is None:
            externals = [Gravity(self.gravity)]
            if self.floor_height is not None:
                externals.append(Floor(height=self.floor_height, stiffness=self.floor_stiffness,
                                       friction=self.floor_friction))
        return Simulator(self.field, self.cubature_points, self.cubature_weights, Material(**values), externals,
                         self.sim_config, jacobian=self.jacobian, use_neural_jacobian=self.jacobian is not None,
                         length_scale=self.length_scale, contact_points=self.contact_points,
                         contact_weights=self.contact_areas,
                         stiffness_scale=self.stiffness(), volumetric=self.material.get("volumetric", "pointwise"),
                         mass_volumes=self.mass_volumes)

    def stiffness(self) -> float | StiffnessCurve:
        """The subspace's stiffness calibration: the curve s(ν) when the asset has one, else the number s."""
        curve = self.material.get("stiffness_curve")
        return StiffnessCurve.from_dict(curve) if curve else float(self.material.get("stiffness_scale", 1.0))

    def initial_state(self, sim: Simulator) -> SimState:
        """The captured initial state: rest shape moving with the recovered rigid velocity."""
        v = self.initial_velocity
        return sim.rigid_velocity_state(v["linear"], v["angular"], v["centre"])

    def continuation_state(self, sim: Simulator) -> SimState | None:
        """The state at frame ``continuation["frame"]`` fitted to the last observed frames, or None."""
        return None if self.continuation is None else recorded_state(self.continuation, sim)


def recorded_state(record: dict[str, Any], sim: Simulator) -> SimState:
    """The :class:`SimState` of a continuation record (``z``, ``zdot``: 12H numbers each, ``t``: s) in ``sim``'s
    dtype and device."""
    as_state = (lambda k: torch.tensor(record[k], dtype=sim.X.dtype, device=sim.X.device))
    return SimState(as_state("z"), as_state("zdot"), float(record["t"]))


def _tensor_list(x: Tensor) -> list:
    return x.detach().cpu().tolist()


def save_asset(asset: Asset, folder: str | Path, config: dict[str, Any] | None = None,
               log: dict[str, Any] | None = None) -> Path:
    """Write ``asset`` to ``folder`` (replaced if it exists) atomically; returns the folder."""

    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        save_ply(asset.rest_gaussians().detach(), tmp / FILES["gaussians"])
        if asset.shading is not None:
            sh = asset.shading.detach().to("cpu")
            np.savez(tmp / FILES["shading"], normals=sh.normals.numpy(), light=sh.light.numpy(),
                     ambient_logit=sh.ambient_logit.numpy())
        torch.save(asset.field.state_dict(), tmp / FILES["skinning"])
        if asset.jacobian is not None:
            torch.save(asset.jacobian.state_dict(), tmp / FILES["jacobian"])
        np.savez(tmp / FILES["points"], cubature_points=asset.cubature_points.detach().cpu().numpy(),
                 cubature_weights=asset.cubature_weights.detach().cpu().numpy(),
                 contact_points=asset.contact_points.detach().cpu().numpy(),
                 contact_areas=asset.contact_areas.detach().cpu().numpy(),
                 points=asset.points.detach().cpu().numpy(), volume=np.float64(asset.volume),
                 **({} if asset.mass_volumes is None else
                    {"mass_volumes": asset.mass_volumes.detach().cpu().numpy()}))
        (tmp / FILES["material"]).write_text(json.dumps(asset.material, indent=2))
        f = asset.field
        networks = {"skinning": {"num_handles": f.num_handles, "width": f.width, "hidden_layers": f.hidden_layers,
                                 "input_centre": _tensor_list(f.input_centre), "input_scale": float(f.input_scale)}}
        if asset.jacobian is not None:
            j = asset.jacobian
            networks["jacobian"] = {"num_handles_total": j.num_handles_total, "encoding_dim": j.encoding_dim,
                                    "widths": list(j.widths), "frequency_scale": j.frequency_scale}
        meta = {"format": ASSET_FORMAT, "version": ASSET_VERSION, "units": "SI (m, s, kg, Pa)",
                "dt": asset.dt, "gravity": list(asset.gravity), "floor_height": asset.floor_height,
                "floor_stiffness": asset.floor_stiffness, "floor_friction": asset.floor_friction,
                "length_scale": asset.length_scale,
                "sim_config": asdict(asset.sim_config), "initial_velocity": asset.initial_velocity,
                **({} if asset.continuation is None else {"continuation": asset.continuation}),
                "networks": networks, "files": {k: v for k, v in FILES.items() if (tmp / v).exists() or k in
                                                ("config", "log")},
                "extra": asset.extra}
        (tmp / FILES["asset"]).write_text(json.dumps(meta, indent=2))
        (tmp / FILES["config"]).write_text(json.dumps(config or {}, indent=2, default=str))
        (tmp / FILES["log"]).write_text(json.dumps(log or {}, default=float))
        move_into_place(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise AssetFormatError(f"{path}: missing (an asset folder holds {', '.join(FILES.values())})")
    return read_json(path, "a JSON object of an asset folder", AssetFormatError)


#: points.npz: array → (trailing shape, positive) — the first axis is the count (K, S or N)
_POINT_ARRAYS = {"cubature_points": ((3,), False), "cubature_weights": ((), True), "contact_points": ((3,), False),
                 "contact_areas": ((), True), "points": ((3,), False)}


def _read_points(path: Path, device: torch.device | str) -> tuple[dict[str, Tensor], float]:
    """The arrays of an asset's ``points.npz`` (checked: present, numeric, shaped, finite, weights and volume
    positive) and its volume; raises :class:`AssetFormatError` naming the file and the array."""
    import zipfile
    import zlib


    if not path.is_file():
        raise AssetFormatError(f"{path}: missing")
    too_big = npz_size_problem(path)
    if too_big is not None:
        raise AssetFormatError(f"{path}: {too_big}")
    try:
        with np.load(path, allow_pickle=False) as z:
            raw = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise AssetFormatError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    for key in (*_POINT_ARRAYS, "volume"):
        if key not in raw:
            raise AssetFormatError(f"{path}: the array {key!r} is missing")
    expected_len = {"cubature_weights": "cubature_points", "contact_areas": "contact_points",
                    "mass_volumes": "cubature_points"}
    arrays: dict[str, Tensor] = {}
    for key, a in raw.items():
        if key == "volume":
            continue
        trailing, positive = _POINT_ARRAYS.get(key, ((), True))
        if a.dtype.kind != "f" or a.ndim != 1 + len(trailing) or a.shape[1:] != trailing or a.shape[0] < 1:
            raise AssetFormatError(
                f"{path}: {key} must be floats of shape (n{', ' + str(trailing[0]) if trailing else ','}) "
                f"with n >= 1, got {a.dtype} {a.shape}"
            )
        if not np.isfinite(a).all() or (positive and not (a > 0).all()):
            raise AssetFormatError(f"{path}: {key} must be finite{' and > 0' if positive else ''}")
        ref = expected_len.get(key)
        if ref is not None and a.shape[0] != raw[ref].shape[0]:
            raise AssetFormatError(f"{path}: {key} has {a.shape[0]} entries for {raw[ref].shape[0]} {ref}")
        arrays[key] = torch.from_numpy(a).to(device)
    volume = raw["volume"]
    if volume.dtype.kind not in "fiu" or volume.size != 1 or not (np.isfinite(volume).all() and float(volume) > 0):
        raise AssetFormatError(f"{path}: volume must be one positive number, got {volume!r}")
    dtypes = {a.dtype for a in arrays.values()}
    if len(dtypes) != 1:
        raise AssetFormatError(f"{path}: the arrays mix precisions {sorted(map(str, dtypes))}")
    return arrays, float(volume)


def load_asset(folder: str | Path, device: torch.device | str = "cpu") -> Asset:
    """Read an asset folder written by :func:`save_asset` (``vid2sim reconstruct``).

    Raises:
        AssetFormatError: a missing file or invalid value, named.
    """

    folder = Path(folder)
    if not folder.is_dir():
        raise AssetFormatError(f"{folder}: not a folder (expected an asset written by `vid2sim reconstruct`)")

    for name in FILES.values():
        real = outside(folder, folder / name) if (folder / name).exists() else None
        if real is not None:
            raise AssetFormatError(f"{folder / name}: resolves to {real}, outside the asset folder (set "
                                   "VID2SIM_ALLOW_OUTSIDE_PATHS=1 to allow files elsewhere)")
    meta = _read_json(folder / FILES["asset"])
    if meta.get("format") != ASSET_FORMAT:
        raise AssetFormatError(
            f"{folder / FILES['asset']}: format must be {ASSET_FORMAT!r}, got {meta.get('format')!r}"
        )
    if meta.get("version") != ASSET_VERSION:
        raise AssetFormatError(f"{folder / FILES['asset']}: version {meta.get('version')!r} is not supported "
                               f"(this vid2sim reads version {ASSET_VERSION})")
    material = _read_json(folder / FILES["material"])
    for key in ("E", "nu", "density", "damping_ratio"):
        value = material.get(key)
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise AssetFormatError(f"{folder / FILES['material']}: {key} must be a finite number, got {value!r}")
    scale = material.get("stiffness_scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (0 < scale < math.inf):
        raise AssetFormatError(f"{folder / FILES['material']}: stiffness_scale must be a finite positive number, "
                               f"got {scale!r}")
    if material.get("stiffness_curve") is not None:
        try:
            StiffnessCurve.from_dict(material["stiffness_curve"])
        except (TypeError, ValueError) as exc:
            raise AssetFormatError(f"{folder / FILES['material']}: stiffness_curve: {exc}") from None
    if material.get("volumetric", "pointwise") not in ("pointwise", "projected"):
        raise AssetFormatError(f"{folder / FILES['material']}: volumetric must be 'pointwise' or 'projected', "
                               f"got {material['volumetric']!r}")
    arrays, volume = _read_points(folder / FILES["points"], device)
    dtype = arrays["cubature_points"].dtype  # the networks are loaded in the precision they were saved in
    nets = meta.get("networks", {})
    try:
        s = nets["skinning"]
        field_ = SkinningField(s["num_handles"], s["width"], s["hidden_layers"]).to(device=device, dtype=dtype)
        # the state dicts are read on the CPU and copied into the networks on ``device`` (load_state_dict)
        field_.load_state_dict(load_torch_file(folder / FILES["skinning"], "an asset's skinning weights",
                                               AssetFormatError))
        jac = None
        if "jacobian" in nets:
            j = nets["jacobian"]
            jac = NeuralJacobian(j["num_handles_total"], j["encoding_dim"], tuple(j["widths"]),
                                 frequency_scale=j["frequency_scale"]).to(device=device, dtype=dtype)
            jac.load_state_dict(load_torch_file(folder / FILES["jacobian"], "an asset's Neural Jacobian weights",
                                                AssetFormatError))
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as exc:
        if isinstance(exc, AssetFormatError):
            raise
        raise AssetFormatError(
            f"{folder / FILES['asset']}: cannot build the networks it describes from "
            f"{FILES['skinning']} ({type(exc).__name__}: {str(exc).splitlines()[0][:300]})"
        ) from None
    try:
        sim_config = SimConfig(**meta["sim_config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise AssetFormatError(f"{folder / FILES['asset']}: sim_config is invalid ({exc})") from None
    # the Gaussians and their shading are read and unshaded on the CPU, then moved, so that the loaded asset is the
    # same on every device (a CUDA unshade differs from the CPU's in the last bits, and an export of it in its bytes)
    gaussians = load_ply(folder / FILES["gaussians"], device="cpu")
    shading = None
    shading_path = folder / FILES["shading"]
    if shading_path.is_file():
        try:
            with np.load(shading_path, allow_pickle=False) as z:
                shading = Shading(*(torch.from_numpy(np.asarray(z[k])).to(dtype=gaussians.means.dtype)
                                    for k in ("normals", "light", "ambient_logit")))
        except (KeyError, ValueError) as exc:
            raise AssetFormatError(f"{shading_path}: {exc}") from None
        if shading.num != gaussians.num:
            raise AssetFormatError(f"{shading_path}: {shading.num} normals for the {gaussians.num} Gaussians of "
                                   f"{FILES['gaussians']}")
        gaussians = replace(gaussians, sh=shading.unshade(gaussians.sh))
        shading = Shading(*(t.to(device) for t in (shading.normals, shading.light, shading.ambient_logit)))
    gaussians = gaussians.to(device)
    return Asset(gaussians=gaussians, field=field_, jacobian=jac, shading=shading,
                 material=material, cubature_points=arrays["cubature_points"],
                 cubature_weights=arrays["cubature_weights"], contact_points=arrays["contact_points"],
                 contact_areas=arrays["contact_areas"], points=arrays["points"], volume=volume,
                 sim_config=sim_config, gravity=list(meta["gravity"]), floor_height=meta.get("floor_height"),
                 floor_stiffness=float(meta["floor_stiffness"]), floor_friction=float(meta.get("floor_friction", 0.0)),
                 length_scale=float(meta["length_scale"]),
                 initial_velocity=meta["initial_velocity"], dt=float(meta["dt"]), extra=meta.get("extra", {}),
                 mass_volumes=arrays.get("mass_volumes"),
                 continuation=_checked_continuation(meta.get("continuation"), 12 * field_.num_handles_total,
                                                    folder / FILES["asset"]))


def _checked_continuation(c: Any, dofs: int, path: Path) -> dict[str, Any] | None:
    """``asset.json``'s ``continuation`` (:class:`Asset`), checked: None, or frames 0 ≤ frame < from_frame, z and
    zdot of ``dofs`` finite numbers each and a finite time; raises :class:`AssetFormatError` naming the field."""
    if c is None:
        return None
    if not isinstance(c, dict):
        raise AssetFormatError(f"{path}: continuation must be an object, got {type(c).__name__}")
    frame, first = c.get("frame"), c.get("from_frame")
    if not all(isinstance(x, int) and not isinstance(x, bool) for x in (frame, first)) or not 0 <= frame < first:
        raise AssetFormatError(f"{path}: continuation needs integers 0 <= frame < from_frame, got {frame!r}, "
                               f"{first!r}")
    for key in ("z", "zdot"):
        v = c.get(key)
        if not isinstance(v, list) or len(v) != dofs or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
            raise AssetFormatError(f"{path}: continuation.{key} must be {dofs} finite numbers (12 per handle)")
    t = c.get("t")
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
        raise AssetFormatError(f"{path}: continuation.t must be a finite number (s), got {t!r}")
    return c
