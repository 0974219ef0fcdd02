"""The second, independent ground truth (NVIDIA Newton's VBD solver, :mod:`vid2sim.synthetic.independent`), checked
against physics and against our FEM:

* free fall: implicit Euler's closed form x_n = x_0 + n h v_0 + h² g n(n+1)/2 to float32 precision, which tends to
  g t²/2 as h → 0;
* no energy gain without contact (an undamped, spinning, vibrating body), linear momentum kept, angular momentum kept
  to implicit Euler's O(h); damping removes energy;
* the first axial vibration of a free-free bar: the same period as our FEM's on the identical mesh (so the two
  truths have the same stiffness for the same E and ν) and as the rod's π c / L;
* a drop on the floor comes to rest on it; the eight-way subdivision keeps the volume;
* a scene folder made with ``truth="newton"`` loads with :func:`vid2sim.scene.folder.load_scene`, with its engine,
  version, parameters and time convergence in scene.json.

Newton is optional (``pip install "vid2sim[newton]"``): without it these tests skip, saying so; with another version
installed than the tested one, the version test fails.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

from vid2sim.meshing.tetra import box_tet_mesh
from vid2sim.runtime.errors import ConfigError
from vid2sim.synthetic.fem import FEMConfig, InitialPose, simulate_fem
from vid2sim.synthetic.independent import (
    INSTALL_HINT,
    NEWTON_VERSION,
    NewtonConfig,
    NewtonResult,
    import_newton,
    simulate_newton,
    subdivide_quadratic,
)

try:
    newton, _ = import_newton()
except ConfigError:  # the optional engine is not installed: its tests skip, saying how to install it
    newton = None
needs_newton = pytest.mark.skipif(newton is None, reason=f"NVIDIA Newton is not installed ({INSTALL_HINT})")


def test_a_missing_engine_is_a_clear_error(monkeypatch, tmp_path):
    """Without Newton, asking for the independent truth names the extra to install (no fallback to our FEM)."""
    monkeypatch.setitem(sys.modules, "newton", None)  # `import newton` raises ImportError
    with pytest.raises(ConfigError, match=r"pip install \"vid2sim\[newton\]\""):
        import_newton()
    V, T = _box((1, 1, 1))
    with pytest.raises(ConfigError, match="newton"):
        simulate_newton(V, T, NewtonConfig(), None, frames=2, progress=False)
    from vid2sim.synthetic.scenes import make_benchmark

    with pytest.raises(ConfigError, match="newton"):  # before any scene is made
        make_benchmark(1, tmp_path / "suite", preset="small", progress=False, truth="newton")
    assert not (tmp_path / "suite").exists()


@needs_newton
def test_the_installed_engine_is_the_tested_version():
    assert newton.__version__ == NEWTON_VERSION


def _box(res=(3, 2, 2), size=(0.3, 0.2, 0.2)):
    mesh = box_tet_mesh(size, res, origin=tuple(-s / 2 for s in size))
    return mesh.vertices, mesh.tets


@needs_newton
def test_free_fall_is_implicit_euler_and_tends_to_g_t2_over_2():
    """No floor, no rotation: every vertex follows implicit Euler's closed form under the configured (tilted)
    gravity, x_n = x_0 + n h v_0 + h² g n(n+1)/2, within float32 rounding; that differs from the exact
    x_0 + v_0 t + g t²/2 by h g t / 2, which halves with h."""
    V, T = _box()
    pose = InitialPose(drop_height=0.0, linear_velocity=(0.5, -0.2, 1.0))
    errors = []
    for substeps in (4, 8):
        cfg = NewtonConfig(floor_height=None, substeps=substeps, dt=0.05, gravity=(0.8, -0.3, -9.0))
        result = simulate_newton(V, T, cfg, pose, frames=5, progress=False)
        x0 = result.trajectory[0].numpy()
        h, g, v0 = cfg.dt / substeps, np.array(cfg.gravity), np.array(pose.linear_velocity)
        for f in range(5):
            n = f * substeps
            expected = x0 + n * h * v0 + h * h * g * n * (n + 1) / 2
            np.testing.assert_allclose(result.trajectory[f].numpy(), expected, atol=2e-6)
        t = 4 * cfg.dt
        exact = x0 + v0 * t + 0.5 * g * t * t
        errors.append(np.abs(result.trajectory[4].numpy() - exact).max())
        assert errors[-1] == pytest.approx(h * np.linalg.norm(g, np.inf) * t / 2, rel=1e-3)
        assert float(result.energies["elastic"].abs().max()) < 1e-6
    assert errors[1] == pytest.approx(errors[0] / 2, rel=1e-3)
    print(f"\n[Newton free fall] |x - (x0 + v0 t + g t^2/2)| at t = 0.2 s: {errors[0]:.2e} m (h = 1/80 s), "
          f"{errors[1]:.2e} m (h = 1/160 s)")


def _spinning_jiggle(V: torch.Tensor) -> np.ndarray:
    """(N, 3) a rigid spin about a tilted axis plus a stretching velocity field along x."""
    X = V.numpy()
    omega = np.array([0.5, 1.0, 3.0])
    return np.cross(omega, X - X.mean(0)) + np.stack([0.6 * X[:, 0], 0 * X[:, 0], -0.3 * X[:, 0]], 1) + [0.2, 0.0, 0.0]


@needs_newton
def test_no_energy_gain_without_contact_and_momentum_is_kept():
    """No gravity, no floor: an undamped body that spins and stretches gains no energy (implicit Euler and VBD only
    dissipate); linear momentum is kept to 1e-3 of Σ m|v| (VBD's fixed sweeps leave a
    small force imbalance: 1.4e-4 measured) and angular momentum to 1 % (implicit Euler's O(h))."""
    V, T = _box()
    cfg = NewtonConfig(youngs_modulus=1e5, poisson_ratio=0.3, damping_ratio=0.0, floor_height=None,
                       gravity=(0.0, 0.0, 0.0), substeps=40, dt=0.02)
    result = simulate_newton(V, T, cfg, None, frames=11, initial_velocity=_spinning_jiggle(V), progress=False)
    total = result.energies["total"].numpy()
    assert (np.diff(total) <= 1e-6 * total[0]).all(), total
    assert result.energies["elastic"].max() > 1e-3 * total[0]  # it does deform (the check is not vacuous)
    m = result.masses.numpy()[:, None]
    x, v = result.trajectory.numpy(), result.velocities.numpy()
    p = (m * v).sum(1)
    momentum_drift = np.abs(p - p[0]).max() / np.abs(m * v[0]).sum()
    assert momentum_drift < 1e-3  # VBD's sweeps stop short of force balance: not exact
    c = (m * x).sum(1) / m.sum()
    L = (m * np.cross(x - c[:, None], v)).sum(1)
    assert np.linalg.norm(L - L[0], axis=1).max() < 1e-2 * np.linalg.norm(L[0])
    lost = 1 - total[-1] / total[0]
    angular_drift = np.linalg.norm(L - L[0], axis=1).max() / np.linalg.norm(L[0])
    print(f"\n[Newton energy] undamped: {100 * lost:.2f} % of the energy lost over 0.2 s, "
          f"angular momentum kept to {angular_drift:.1e}, linear momentum to {momentum_drift:.1e}")
    assert lost < 0.05


BAR_L, BAR_B, BAR_E, BAR_NU, BAR_RHO = 1.0, 0.1, 1e6, 0.3, 1000.0


def _axial_period(trajectory: np.ndarray, times: np.ndarray, X: np.ndarray) -> float:
    """The period from the zero crossings of the bar's stretch (mean x of the end at x = L minus the start's)."""
    left, right = X[:, 0] < 1e-9, X[:, 0] > BAR_L - 1e-9
    s = trajectory[:, right, 0].mean(1) - trajectory[:, left, 0].mean(1) - BAR_L
    idx = np.where(np.sign(s[1:-1]) != np.sign(s[2:]))[0] + 1
    crossings = np.array([times[i] - s[i] * (times[i + 1] - times[i]) / (s[i + 1] - s[i]) for i in idx])
    assert len(crossings) >= 3
    return float(np.diff(crossings).mean() * 2)


@needs_newton
def test_axial_vibration_period_matches_our_fem_and_the_rod():
    """A free-free bar 1 × 0.1 × 0.1 m (E = 1e6 Pa, ν = 0.3, undamped, no gravity) starts in its first axial mode,
    v_x = a cos(π x / L). Its period equals our FEM's on the identical linear tets within 1 % (the two engines
    give E and ν the same stiffness: Newton's stable Neo-Hookean with λ_nh = λ + μ linearises to our Lamé
    parameters; a wrong mapping, e.g. λ_nh = λ, shifts it by 5 %) and the rod's 2L / √(E/ρ) within 3 %."""
    mesh = box_tet_mesh((BAR_L, BAR_B, BAR_B), (20, 2, 2))
    X, T = mesh.vertices, mesh.tets
    c = math.sqrt(BAR_E / BAR_RHO)
    period_rod = 2 * BAR_L / c
    frames, dt = 40, period_rod / 16
    v0 = np.zeros(X.shape)
    v0[:, 0] = 0.05 * np.cos(math.pi * X[:, 0].numpy() / BAR_L)
    ours = simulate_fem(X, T, FEMConfig(youngs_modulus=BAR_E, poisson_ratio=BAR_NU, density=BAR_RHO, floor_height=None,
                                        gravity=(0.0, 0.0, 0.0), damping_ratio=0.0, dt=dt, substeps=8),
                        None, frames=frames, initial_velocity=v0, progress=False)
    theirs = simulate_newton(X, T, NewtonConfig(youngs_modulus=BAR_E, poisson_ratio=BAR_NU, density=BAR_RHO,
                                                floor_height=None, gravity=(0.0, 0.0, 0.0), damping_ratio=0.0,
                                                dt=dt, substeps=16),
                             None, frames=frames, initial_velocity=v0, progress=False)
    times = ours.times.numpy()
    p_ours = _axial_period(ours.trajectory.numpy(), times, X.numpy())
    p_theirs = _axial_period(theirs.trajectory.numpy(), times, X.numpy())
    print(f"\n[Newton vs FEM] first axial period: Newton {p_theirs * 1e3:.3f} ms, our FEM {p_ours * 1e3:.3f} ms "
          f"({100 * (p_theirs / p_ours - 1):+.2f} %), rod 2L/c {period_rod * 1e3:.3f} ms")
    assert p_theirs == pytest.approx(p_ours, rel=0.01)
    assert p_theirs == pytest.approx(period_rod, rel=0.03)


def _twist(trajectory: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(T,) the bar's twist: the mean rotation about x of the end x = L minus that of the end x = 0 (radians)."""
    out = []
    for end in (X[:, 0] > BAR_L - 1e-9, X[:, 0] < 1e-9):
        r0 = X[end, 1:] - X[end, 1:].mean(0)
        r = trajectory[:, end, 1:] - trajectory[:, end, 1:].mean(1, keepdims=True)
        out.append(np.arctan2((r0[:, 0] * r[..., 1] - r0[:, 1] * r[..., 0]).sum(-1), (r0 * r).sum((-2, -1))))
    return out[0] - out[1]


@needs_newton
def test_shear_damping_matches_our_kelvin_voigt():
    """The first torsion mode of the free-free bar (isochoric, so our Kelvin–Voigt damping 2τμĖ + τλ tr(Ė) I and
    Newton's shear-only viscosity d = τμ/2 on Ċ are the same there) decays at the same rate in both engines: the
    energy's log decay rate with ζ = 0.05 less the undamped one (each integrator's own loss) agrees within 10 %."""
    mesh = box_tet_mesh((BAR_L, BAR_B, BAR_B), (20, 2, 2))
    X, T = mesh.vertices, mesh.tets
    Xn = X.numpy()
    period = 2 * BAR_L / (0.92 * math.sqrt(BAR_E / (2 * (1 + BAR_NU)) / BAR_RHO))  # Saint-Venant, square section
    frames, dt = 33, period / 16
    v0 = np.zeros(X.shape)
    twist = 1.0 * np.cos(math.pi * Xn[:, 0] / BAR_L)
    v0[:, 1], v0[:, 2] = -twist * (Xn[:, 2] - BAR_B / 2), twist * (Xn[:, 1] - BAR_B / 2)
    rates = {}
    for engine in ("fem", "newton"):
        for zeta in (0.0, 0.05):
            common = dict(youngs_modulus=BAR_E, poisson_ratio=BAR_NU, density=BAR_RHO, floor_height=None,
                          gravity=(0.0, 0.0, 0.0), damping_ratio=zeta, dt=dt)
            if engine == "fem":
                result = simulate_fem(X, T, FEMConfig(**common, substeps=8), None, frames=frames, initial_velocity=v0,
                                      progress=False)
            else:
                result = simulate_newton(X, T, NewtonConfig(**common, substeps=16), None, frames=frames,
                                         initial_velocity=v0, progress=False)
            assert np.abs(_twist(result.trajectory.numpy(), Xn)).max() > 0.01  # it does twist
            energy = result.energies["total"].numpy()
            rates[engine, zeta] = -math.log(energy[-1] / energy[0]) / result.times[-1].item()
    excess = {e: rates[e, 0.05] - rates[e, 0.0] for e in ("fem", "newton")}
    print(f"\n[Newton vs FEM] torsion mode energy decay from damping: Newton {excess['newton']:.2f} /s, our FEM "
          f"{excess['fem']:.2f} /s (undamped losses {rates['newton', 0.0]:.2f} and {rates['fem', 0.0]:.2f} /s)")
    assert excess["newton"] == pytest.approx(excess["fem"], rel=0.10)


@needs_newton
def test_a_drop_comes_to_rest_on_the_floor():
    """A soft box dropped from 5 cm stops on the floor: it neither sinks through nor flies off, its contact depth is
    a small fraction of its size, and its kinetic energy dies out."""
    V, T = _box()
    cfg = NewtonConfig(youngs_modulus=1e5, substeps=32, floor_height=-0.7, friction=0.5)
    result = simulate_newton(V, T, cfg, InitialPose(drop_height=0.05), frames=25, progress=False)
    z_min = result.trajectory[..., 2].min(dim=1).values.numpy()
    assert z_min.min() > -0.7 - 0.01
    assert abs(z_min[-1] + 0.7) < 0.005
    assert result.energies["kinetic"][-1] < 1e-3 * result.energies["kinetic"].max()
    assert bool((result.min_det > 0).all())


def test_subdivision_keeps_the_volume_and_orientation():
    V, T = _box((2, 2, 1))
    nodes, tets = subdivide_quadratic(V, T)
    assert tets.shape == (8 * len(T), 4) and np.allclose(nodes[: len(V)], V.numpy())
    p = nodes[tets]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
    assert (volume > 0).all()
    assert volume.sum() == pytest.approx(0.3 * 0.2 * 0.2, rel=1e-12)


def test_config_errors():
    with pytest.raises(ConfigError, match="friction"):
        NewtonConfig(friction=-1.0)
    with pytest.raises(ConfigError, match="iterations"):
        NewtonConfig(iterations=0)
    from vid2sim.synthetic.scenes import SyntheticSceneConfig

    with pytest.raises(ConfigError, match="truth"):
        SyntheticSceneConfig(truth="bullet")


@needs_newton
def test_a_newton_scene_folder_loads(tmp_path):
    """A toy scene (a coarse procedural object, 3 frames, 2 views at 24 px) with ``truth="newton"``: a normal scene
    folder with the tet trajectory for evaluation, the engine, its version, parameters and time convergence in
    scene.json, and its result file."""
    from vid2sim.scene.folder import load_scene
    from vid2sim.synthetic.scenes import NEWTON_RESULT_NPZ, SyntheticSceneConfig, make_scene

    config = SyntheticSceneConfig(seed=3, truth="newton", youngs_modulus=1e4, views=2, resolution=24, frames=3,
                                  observed_frames=2, tet_edge_length=0.2, tet_envelope=1e-2, supersample=1)
    out = make_scene(config, tmp_path / "scene", progress=False)
    scene = load_scene(out)
    meta = scene.config.metadata
    assert meta["truth"] == "newton" and meta["E"] == 1e4
    info = meta["newton"]
    assert info["engine"]["version"] == NEWTON_VERSION and info["engine"]["name"] == "newton"
    assert info["parameters"]["lambda_nh"] == pytest.approx(info["parameters"]["k_lambda"] + info["parameters"]["k_mu"])
    tc = info["time_convergence"]
    assert tc["kept"] == 2 * tc["substeps"][0] and tc["mean_percent"] <= tc["tolerance_percent"]
    tet = scene.extras["tet_trajectory"]
    assert tet["vertices"].shape[0] == 3 and tet["tets"].shape[1] == 4
    assert int(tet["tets"].max()) < tet["vertices"].shape[1]
    result = NewtonResult.load(out / NEWTON_RESULT_NPZ)
    assert torch.equal(result.trajectory.float(), tet["vertices"])
    assert json.loads((out / "synthetic.json").read_text())["truth"] == "newton"
    assert scene.images.shape[:2] == (2, 3)
