"""The material + skinning rig of an asset as documented JSON + weights, and a NumPy reference of it.

``export_rig(asset, folder)`` writes (docs/export.md has the full schema):

    rig.json          what every tensor is, the network architecture and its input normalisation, the
                      formulas from handle transforms z to positions and deformation gradients, the material,
                      gravity, floor, time step, initial velocity and the point sets
    rig.safetensors   the tensors: skinning network (and Neural Jacobian) weights, cubature and contact
                      points, interior samples, optionally a sequence of states z
    gaussians.ply     the rest Gaussians the rig moves (standard 3DGS PLY)

Everything is in the scene's world frame (metres, z up unless gravity says otherwise) — not glTF's y-up
frame; ``rig.json`` gives the rotation between the two.

:func:`evaluate_rig_numpy` evaluates skinning weights, positions and deformation gradients from those files
alone with NumPy (and :func:`neural_jacobian_numpy` the Neural Jacobian when an asset has one): the
reference another tool can port, checked in the tests against :class:`~vid2sim.physics.skinning.SkinningField`
and :meth:`~vid2sim.physics.solver.Simulator.positions`.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from vid2sim import __version__
from vid2sim.asset.folder import Asset
from vid2sim.export.transform import rotation_to_y_up
from vid2sim.physics.neural_jacobian import NeuralJacobian
from vid2sim.physics.skinning import SkinningField
from vid2sim.runtime.errors import InputError
from vid2sim.scene.writing import move_into_place
from vid2sim.splats.ply import save_ply
from vid2sim.splats.shading import Shading

RIG_FORMAT = "vid2sim-rig"
RIG_VERSION = 1
RIG_FILES = {"rig": "rig.json", "weights": "rig.safetensors", "gaussians": "gaussians.ply"}


class RigFormatError(InputError):
    """A rig folder that is incomplete or inconsistent (the message names the file and the problem)."""


def _np(t) -> np.ndarray:
    return t.detach().cpu().numpy()


def _up(gravity: list[float]) -> list[float]:
    g = np.asarray(gravity, dtype=np.float64)
    n = float(np.linalg.norm(g))
    return [0.0, 0.0, 1.0] if n == 0 else (-g / n + 0.0).tolist()


def rig_tensors(asset, z_sequence=None) -> dict[str, np.ndarray]:
    """The tensors of ``rig.safetensors`` for an :class:`~vid2sim.asset.folder.Asset` (name → array)."""
    out: dict[str, np.ndarray] = {}
    for key, value in asset.field.state_dict().items():
        out[f"skinning.{key}"] = _np(value)
    if asset.jacobian is not None:
        for key, value in asset.jacobian.state_dict().items():
            out[f"jacobian.{key}"] = _np(value)
    out["points.cubature"] = _np(asset.cubature_points)
    out["points.cubature_weights"] = _np(asset.cubature_weights)
    out["points.contact"] = _np(asset.contact_points)
    out["points.contact_areas"] = _np(asset.contact_areas)
    out["points.interior"] = _np(asset.points)
    if asset.shading is not None:
        out["shading.normals"] = _np(asset.shading.normals)
    if z_sequence is not None:
        z = np.asarray(z_sequence.detach().cpu().numpy() if hasattr(z_sequence, "detach") else z_sequence)
        h = asset.field.num_handles_total
        if z.ndim != 2 or z.shape[1] != 12 * h or not np.all(np.isfinite(z)):
            raise InputError(f"z_sequence must be finite with shape (T, {12 * h}) for {h} handles, got {z.shape}")
        out["states.z"] = z
    return out


def rig_document(asset, tensors: dict[str, np.ndarray]) -> dict[str, Any]:
    """The ``rig.json`` document for ``asset`` whose tensors are ``tensors``."""
    h = asset.field.num_handles_total
    return {
        "format": RIG_FORMAT,
        "version": RIG_VERSION,
        "generator": f"vid2sim {__version__}",
        "units": "SI (m, s, kg, Pa)",
        "files": dict(RIG_FILES),
        "frame": {
            "description": "the scene's world frame, metres; up = -gravity (z up for vid2sim scenes). The glTF "
            "export is y-up: p_gltf = gltf_from_world @ p",
            "gltf_from_world": rotation_to_y_up(_up(asset.gravity)).tolist(),
        },
        "skinning": _skinning_record(asset.field),
        "state": {
            "size": 12 * h,
            "layout": "z[12 j + 4 a + k] = Z_j[a, k]: handle-major, each handle a 3x4 displacement affine Z_j, "
            "row-major",
            "rest": "z = 0 is the rest state (the Gaussians as stored in gaussians.ply)",
            "sequence": "states.z (T, 12H), one state per video frame, when present",
        },
        "positions": "x(X) = X + sum_j w_j(X) Z_j [X; 1]",
        "deformation_gradient": "F(X) = I + sum_j Z_j ([I; 0] w_j(X) + [X; 1] dw_j/dX^T), i.e. "
        "F[a, c] = delta_ac + sum_j (w_j Z_j[a, c] + (Z_j [X; 1])_a dw_j/dX_c)",
        "gaussians": "a Gaussian with rest centre p and covariance Sigma = R S S^T R^T moves to x(p) with covariance "
        "F(p) Sigma F(p)^T; opacity and SH colour are unchanged",
        "shading": None if asset.shading is None else _shading_record(asset.shading),
        "material": _material_record(asset),
        "simulation": _simulation_record(asset),
        "points": {
            "points.cubature": "(K, 3) m: the simulator's quadrature points (rest positions)",
            "points.cubature_weights": "(K,) m^3: their volumes",
            "points.contact": "(S, 3) m: where floor and obstacles push (rest positions)",
            "points.contact_areas": "(S,) m^2: their areas",
            "points.interior": "(N, 3) m: interior samples of the object",
            "volume": float(asset.volume),
        },
        "jacobian": None if asset.jacobian is None else _jacobian_record(asset.jacobian),
        "tensors": {name: {"shape": list(a.shape), "dtype": str(a.dtype)} for name, a in tensors.items()},
    }


def _skinning_record(f: SkinningField) -> dict[str, Any]:
    """``rig.json``'s ``skinning``: how the weights w(X) (N, H) follow from the field's tensors."""
    n_layers = len(f.layers)
    layers = []
    for i, layer in enumerate(f.layers):
        layers.append({"weight": f"skinning.layers.{i}.weight", "bias": f"skinning.layers.{i}.bias",
                       "in": layer.in_features, "out": layer.out_features,
                       "activation": "elu" if i < n_layers - 1 else None})
    return {
        "num_handles_learned": f.num_handles,
        "num_handles_total": f.num_handles_total,
        "rigid_handle": "the last handle (index H-1); its weight is identically 1",
        "input_normalisation": {
            "formula": "Xc = (X - centre) / scale",
            "centre": [float(v) for v in _np(f.input_centre)],
            "scale": float(f.input_scale),
            "tensors": {"centre": "skinning.input_centre", "scale": "skinning.input_scale"},
        },
        "layers": layers,
        "linear": "y = x W^T + b with W (out, in), as torch.nn.Linear",
        "elu": "elu(u) = u if u > 0 else exp(u) - 1",
        "weights": "w(X) = [MLP(Xc), 1] with MLP = layers[-1](elu(layers[-2](... elu(layers[0](Xc)))))",
        "weight_gradients": "dw/dX = (1/scale) dMLP/dXc (chain rule through the layers; elu'(u) = 1 if u > 0 "
        "else exp(u)); the rigid column's gradient is 0",
    }


def _shading_record(shading: Shading) -> dict[str, Any]:
    """``rig.json``'s ``shading``: the light and how a moved Gaussian's colour follows from its normal."""
    return {
        **shading.to_record(),
        "normals": "shading.normals (N, 3): each Gaussian's rest-frame normal N (gaussians.ply order)",
        "colour": "gaussians.ply holds the colours lit at rest, c0 = a s(N); a moved Gaussian shows "
        "a s(n) with n = cof(F) N = det(F) F^-T N normalised and "
        "s(n) = ambient + (1 - ambient) max(0, n . light), light fixed in the world",
    }


def _material_record(asset: Asset) -> dict[str, Any]:
    """``rig.json``'s ``material``: the asset's material with the Lamé parameters the simulation uses, its energy
    and its damping in words."""
    mat = dict(asset.material)
    # the Lamé parameters the simulation uses: E times the subspace's stiffness calibration at ν (1 when absent)
    stiffness = asset.stiffness()
    nu = float(mat["nu"])
    e = float(mat["E"]) * (stiffness if isinstance(stiffness, float) else stiffness.at(nu))
    e_lam = float(mat["E"]) * (stiffness if isinstance(stiffness, float) else stiffness.lam_at(nu))  # two factors
    mat["lame_mu"] = e / (2 * (1 + nu))
    mat["lame_lambda"] = e_lam * nu / ((1 + nu) * (1 - 2 * nu))
    mat["energy"] = {"neo-hookean": "Psi = mu/2 (tr(F^T F) - 3) - mu ln J + lambda/2 (ln J)^2, J = det F",
                     "neo_hookean": "Psi = mu/2 (tr(F^T F) - 3) - mu ln J + lambda/2 (ln J)^2, J = det F",
                     "stvk": "Psi = mu tr(G^2) + lambda/2 tr(G)^2, G = (F^T F - I)/2"}.get(str(mat.get("model")), None)
    if mat.get("volumetric", "pointwise") == "projected" and mat["energy"] is not None:
        mat["energy"] = ("Psi = mu/2 (tr(F^T F) - 3) - mu ln J + lambda/2 (P ln J)^2, J = det F, where P ln J is the "
                         "volume-weighted least-squares projection of ln J over the cubature points onto the span "
                         "of the skinning weights (the constant handle included)")
    mat["damping"] = ("Kelvin-Voigt material damping with ratio zeta = damping_ratio at omega_ref = sqrt(E/density)"
                      " / length_scale (retardation time tau = 2 zeta length_scale sqrt(density/E))")
    return mat


def _simulation_record(asset: Asset) -> dict[str, Any]:
    """``rig.json``'s ``simulation``: frame time, solver settings, gravity, floor and initial velocity."""
    return {
        "dt": asset.dt,
        "sim_config": _sim_config(asset.sim_config),
        "gravity": list(map(float, asset.gravity)),
        "floor": None
        if asset.floor_height is None
        else {
            "height": float(asset.floor_height),
            "normal": _up(asset.gravity),
            "stiffness": float(asset.floor_stiffness),
            "friction": float(asset.floor_friction),
            "meaning": "penalty contact pressure stiffness (Pa per metre of penetration) on the contact points' "
                       "areas; friction: the Coulomb coefficient (0: frictionless)",
        },
        "length_scale": asset.length_scale,
        "initial_velocity": asset.initial_velocity,
        "initial_velocity_meaning": "v_i = linear + angular x (x_i - centre) at frame 0 (m/s, rad/s)",
    }


def _jacobian_record(j: NeuralJacobian) -> dict[str, Any]:
    """``rig.json``'s ``jacobian``: how the Neural Jacobian J(X) (N, 9, 12H) follows from its tensors."""
    blocks = []
    dims = (j.encoding_dim,) + tuple(j.widths)
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        blocks.append({"fc1": f"jacobian.blocks.{i}.fc1", "fc2": f"jacobian.blocks.{i}.fc2",
                       "proj": f"jacobian.blocks.{i}.proj.weight" if a != b else None, "in": a, "out": b})
    return {
        "num_handles_total": j.num_handles_total, "encoding_dim": j.encoding_dim, "widths": list(j.widths),
        "frequency_scale": j.frequency_scale,
        "input_normalisation": "Xc = (X - jacobian.input_centre) / jacobian.input_scale",
        "encoding": "gamma = [sin(2 pi Xc B^T), cos(2 pi Xc B^T)], B = jacobian.frequencies (encoding_dim/2, 3)",
        "blocks": blocks,
        "block": "y = gelu(P x + fc2(gelu(fc1(x)))), P = proj (no bias) when in != out, else identity; "
                 "gelu(u) = u/2 (1 + erf(u / sqrt 2)); fcK(x) = x W^T + b with W = <name>.weight, b = <name>.bias",
        "output": "J = (h W^T + b).reshape(N, 9, 12H), W = jacobian.output.weight, b = jacobian.output.bias",
        "meaning": "J(X) = dF/dz: F(X, z).reshape(9) = I.flatten() + J(X) z (row-major F); the simulator uses it "
                   "instead of the closed form at the cubature points when the asset was built with it",
    }


def _sim_config(cfg) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(cfg)


def export_rig(asset, folder: str | Path, *, z_sequence=None) -> Path:
    """Write the rig of ``asset`` (a :class:`~vid2sim.asset.folder.Asset`) into ``folder`` atomically
    (the folder appears complete or not at all; an existing one is replaced).

    Args:
        asset: the loaded asset.
        folder: output folder.
        z_sequence: optional (T, 12H) states (e.g. a simulated sequence) stored as ``states.z``.
    Returns:
        the folder.
    """

    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tensors = rig_tensors(asset, z_sequence)
    doc = rig_document(asset, tensors)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        from safetensors.numpy import save_file

        save_file({k: np.array(v, order="C") for k, v in tensors.items()}, str(tmp / RIG_FILES["weights"]),
                  metadata={"format": RIG_FORMAT, "version": str(RIG_VERSION), "description": "see rig.json"})
        save_ply(asset.rest_gaussians().detach(), tmp / RIG_FILES["gaussians"])  # lit as at rest
        (tmp / RIG_FILES["rig"]).write_text(json.dumps(doc, indent=2))
        move_into_place(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def load_rig(folder: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(rig.json document, tensors) of a rig folder; raises :class:`RigFormatError` naming the problem."""
    folder = Path(folder)
    path = folder / RIG_FILES["rig"]
    if not path.is_file():
        raise RigFormatError(f"{path}: missing (a rig folder holds {', '.join(RIG_FILES.values())})")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise RigFormatError(f"{path}: not valid JSON ({exc})") from None
    if doc.get("format") != RIG_FORMAT or doc.get("version") != RIG_VERSION:
        raise RigFormatError(f"{path}: expected format {RIG_FORMAT!r} version {RIG_VERSION}, "
                             f"got {doc.get('format')!r} version {doc.get('version')!r}")
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    try:
        tensors = load_file(str(folder / doc["files"]["weights"]))
    except (SafetensorError, KeyError, OSError) as exc:
        raise RigFormatError(f"{folder}: cannot read the rig weights ({exc})") from None
    return doc, tensors


def _elu(u: np.ndarray) -> np.ndarray:
    return np.where(u > 0, u, np.expm1(np.minimum(u, 0.0)))


def evaluate_rig_numpy(rig: str | Path | tuple[dict[str, Any], dict[str, np.ndarray]], z: np.ndarray,
                       points: np.ndarray) -> dict[str, np.ndarray]:
    """Skinning weights, positions and deformation gradients from the exported rig files only (float64).

    Args:
        rig: a rig folder, or the ``(document, tensors)`` pair of :func:`load_rig`.
        z: (12H,) handle transforms (``rig.json`` → ``state``).
        points: (N, 3) rest positions in the world frame.
    Returns:
        ``weights`` (N, H), ``weight_gradients`` (N, H, 3), ``positions`` (N, 3), ``F`` (N, 3, 3).
    """
    doc, tensors = load_rig(rig) if isinstance(rig, (str, Path)) else rig
    sk = doc["skinning"]
    h = int(sk["num_handles_total"])
    X = np.asarray(points, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {X.shape}")
    if z.shape != (12 * h,):
        raise InputError(f"z must have shape ({12 * h},) for {h} handles, got {z.shape}")
    t = {k: v.astype(np.float64) for k, v in tensors.items()}
    centre = t[sk["input_normalisation"]["tensors"]["centre"]]
    scale = float(t[sk["input_normalisation"]["tensors"]["scale"]])
    n = X.shape[0]
    hid = (X - centre) / scale
    D = np.broadcast_to(np.eye(3) / scale, (n, 3, 3))  # D[p, c, :] = d hid / d X_c
    for layer in sk["layers"]:
        W, b = t[layer["weight"]], t[layer["bias"]]
        u = hid @ W.T + b
        D = D @ W.T
        if layer["activation"] == "elu":
            hid = _elu(u)
            D = D * np.where(u > 0, 1.0, np.exp(np.minimum(u, 0.0)))[:, None, :]
        elif layer["activation"] is None:
            hid = u
        else:
            raise RigFormatError(f"unknown activation {layer['activation']!r} in rig.json")
    w = np.concatenate([hid, np.ones((n, 1))], axis=1)
    dw = np.concatenate([np.transpose(D, (0, 2, 1)), np.zeros((n, 1, 3))], axis=1)  # (N, H, 3)
    Z = z.reshape(h, 3, 4)
    Xh = np.concatenate([X, np.ones((n, 1))], axis=1)
    ZX = np.einsum("jak,pk->pja", Z, Xh)  # Z_j [X; 1]
    x = X + np.einsum("pj,pja->pa", w, ZX)
    F = np.eye(3) + np.einsum("pj,jac->pac", w, Z[:, :, :3]) + np.einsum("pja,pjc->pac", ZX, dw)
    return {"weights": w, "weight_gradients": dw, "positions": x, "F": F}


def neural_jacobian_numpy(rig: str | Path | tuple[dict[str, Any], dict[str, np.ndarray]],
                          points: np.ndarray) -> np.ndarray:
    """The Neural Jacobian J(X) = dF/dz: (N, 9, 12H) from the rig files only (float64).

    Raises:
        RigFormatError: the rig has no Neural Jacobian.
    """
    from scipy.special import erf

    doc, tensors = load_rig(rig) if isinstance(rig, (str, Path)) else rig
    jac = doc.get("jacobian")
    if not jac:
        raise RigFormatError("this rig has no Neural Jacobian (its dF/dz is the skinning field's closed form)")
    t = {k: v.astype(np.float64) for k, v in tensors.items()}

    def gelu(u: np.ndarray) -> np.ndarray:
        return 0.5 * u * (1.0 + erf(u / math.sqrt(2.0)))

    X = np.asarray(points, dtype=np.float64)
    xc = (X - t["jacobian.input_centre"]) / float(t["jacobian.input_scale"])
    proj = 2.0 * math.pi * (xc @ t["jacobian.frequencies"].T)
    hid = np.concatenate([np.sin(proj), np.cos(proj)], axis=1)
    for blk in jac["blocks"]:
        skip = hid if blk["proj"] is None else hid @ t[blk["proj"]].T
        inner = gelu(hid @ t[blk["fc1"] + ".weight"].T + t[blk["fc1"] + ".bias"])
        hid = gelu(skip + inner @ t[blk["fc2"] + ".weight"].T + t[blk["fc2"] + ".bias"])
    out = hid @ t["jacobian.output.weight"].T + t["jacobian.output.bias"]
    return out.reshape(X.shape[0], 9, 12 * int(jac["num_handles_total"]))
