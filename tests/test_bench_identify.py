"""vid2sim bench identify at a tiny size: the pieces are consistent and the report is complete."""

from __future__ import annotations

import copy
import json
import math
import statistics

import numpy as np
import pytest
import torch

from vid2sim.apps.bench import identify
from vid2sim.cli import main
from vid2sim.reconstruct.config import CalibrationConfig, NetworksConfig, SimulatorConfig
from vid2sim.runtime.errors import ConfigError

pytestmark = pytest.mark.slow  # end to end: scene generation, reconstruction, suites

TINY = dict(scenes=1, frames=10, observed_frames=6, points=400, skinning_points=2000,
            networks=NetworksConfig(handles=4, skinning_iterations=40), fit_iterations=1, sweep_points=3,
            fem_element_order=1, coarse_log10_E=(5.5, 4.0, 5.0),
            # the plain model; each test turns on the calibration, the projected term or the fixed ζ it checks
            simulator=SimulatorConfig(cubature=120, volumetric="pointwise", mass="moments"),
            calibration=CalibrationConfig(enabled=False, nu="two_factor"), fit_damping=True)


def _content(x):
    """A hashable key of an argument's content: arrays and tensors by their bytes, a module by its state."""
    if isinstance(x, torch.nn.Module):
        return repr(x), tuple((k, _content(v)) for k, v in x.state_dict().items())
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x.dtype.str, x.shape, x.tobytes()
    if isinstance(x, (list, tuple)):
        return tuple(_content(v) for v in x)
    return repr(x)


def _once(function):
    """``function`` (a pure one) computed once per distinct content of its arguments; each call gets a copy."""
    results = {}

    def once(*args, **kwargs):
        key = (_content(args), tuple((k, _content(v)) for k, v in sorted(kwargs.items())))
        if key not in results:
            results[key] = function(*args, **kwargs)
        return copy.deepcopy(results[key])

    return once


@pytest.fixture(scope="module", autouse=True)
def each_eigensolve_once():
    """The tets' sparse eigensolves (1–2 s each) run once per distinct input in this module's process: they are
    pure functions of the mesh, material, field and cubature, keyed here on those values, so every caller still
    gets the numbers computed for its arguments. ``prepare_scene`` solves the scene's diagnostic frequencies
    (:func:`identify.lowest_frequencies`) on every call, and they depend on neither the calibration nor the contact
    layer nor the fit's switches: of the 15 preparations here 3 have inputs of their own (scene 0, scene 0 with the
    projected term, scene 1). The curve calibrations over ν ∈ (0.3, 0.45) with the pointwise and the projected term
    share the tets' curve, and the tests' reference frequencies at E = ρ = 1 are the prior's calibration's and each
    other's. The worker processes of test_workers_give_the_rows_of_one_process solve their own."""
    from vid2sim.physics import modes, tet_modes

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(identify, "lowest_frequencies", _once(identify.lowest_frequencies))
        patch.setattr(modes, "tet_frequency_curve", _once(modes.tet_frequency_curve))
        solve = _once(tet_modes.tet_frequencies)
        patch.setattr(modes, "tet_frequencies", solve)
        patch.setattr(tet_modes, "tet_frequencies", solve)
        yield


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """The one-scene report, run in this process with one torch thread: its row is also the one-process row that
    test_workers_give_the_rows_of_one_process compares the worker processes' with (results are reproducible per
    thread count)."""
    workdir = tmp_path_factory.mktemp("identify")
    config = identify.IdentifyConfig(**TINY)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return identify.run(config, workdir, progress=False), config, workdir
    finally:
        torch.set_num_threads(old)


def test_perfect_geometry_starts_exactly_where_the_fem_starts(report):
    _, config, workdir = report
    from vid2sim.synthetic.scenes import benchmark_parameters

    scene = identify.prepare_scene(0, benchmark_parameters(1, 0)[0], config, workdir)  # from the cache
    x0 = scene.positions(scene.start.z)
    assert torch.allclose(x0, scene.truth[0], atol=1e-9)  # the rigid pose is fitted exactly
    assert (scene.simulator.contact_weights > 0).all()
    assert scene.simulator.length_scale == pytest.approx(scene.size)
    # the truth's own material at frame 1: nearly ballistic, so the reduced model follows it closely
    truth = scene.material
    identify.set_material(scene.simulator, math.log10(truth["E"]), truth["nu"], truth["damping_ratio"])
    traj = scene.trajectory(2)
    assert float((traj[1] - scene.truth[1]).norm(dim=1).mean()) < 0.01 * scene.size
    assert scene.simulator.stiffness_scale == scene.info["stiffness_scale"] == 1.0
    # --calibrate-stiffness: the subspace's lowest mode at the prior ν is brought to the quadratic tets'
    from dataclasses import replace

    from vid2sim.physics.modes import subspace_frequencies

    calibrated = identify.prepare_scene(0, benchmark_parameters(1, 0)[0],
                                        replace(config, calibration=CalibrationConfig(nu="prior")), workdir)
    sim = calibrated.simulator
    s = sim.stiffness_scale
    assert s == calibrated.info["stiffness_scale"] and 0.3 < s < 1.0  # the subspace is stiffer than the tets
    assert calibrated.info["stiffness_curve"] is None
    from vid2sim.physics.stiffness_curve import StiffnessCurve
    from vid2sim.physics.tet_modes import tet_frequencies
    from vid2sim.synthetic.fem import FEMResult

    fem = FEMResult.load(workdir / "scene_000" / "fem_result.npz")
    X = fem.rest_vertices[: int(fem.tets.max()) + 1]
    # the quadratic tets' lowest mode at E = ρ = 1 (a sparse eigensolve each); ω scales as √(E/ρ)
    unit = {nu: tet_frequencies(X, fem.tets, 1.0, nu, 1.0, k=1, order=2)[0] for nu in {config.prior.nu, 0.3, 0.45}}
    tets = unit[config.prior.nu] * math.sqrt(2e5 / 900.0)
    omega = subspace_frequencies(sim.field, sim.X, sim.vol, 2e5 * s, config.prior.nu, 900.0, k=1,
                                 mass_volumes=sim.mass_volumes)[0]
    assert omega == pytest.approx(tets, rel=1e-6)
    # one factor as a curve: s(ν) brings the lowest mode to the tets' at every ν of its grid
    curved = identify.prepare_scene(0, benchmark_parameters(1, 0)[0],
                                    replace(config, calibration=CalibrationConfig(nu="curve"),
                                            calibration_nus=(0.3, 0.45)), workdir)
    curve = curved.simulator.stiffness_scale
    assert isinstance(curve, StiffnessCurve) and curve.nu == (0.3, 0.45)
    assert curve.at(0.3) == pytest.approx(s, rel=1e-9) == curved.info["stiffness_scale"]
    assert curved.info["stiffness_curve"] == curve.to_dict()
    tets = unit[0.45] * math.sqrt(2e5 / 900.0)
    omega = subspace_frequencies(sim.field, sim.X, sim.vol, 2e5 * curve.at(0.45), 0.45, 900.0, k=1,
                                 mass_volumes=sim.mass_volumes)[0]
    assert omega == pytest.approx(tets, rel=1e-6)
    # two factors (the default): μ by s(ν), λ by s_λ(ν); the lowest mode still on the tets' (weighted fit)
    two = identify.prepare_scene(0, benchmark_parameters(1, 0)[0],
                                 replace(config, calibration=CalibrationConfig(nu="two_factor"),
                                         calibration_nus=(0.3, 0.45)), workdir)
    curve2 = two.simulator.stiffness_scale
    assert curve2.lam_scale is not None and two.info["stiffness_curve"]["lam_scale"] == list(curve2.lam_scale)
    from scipy.linalg import eigh

    from vid2sim.physics.materials import lame_parameters
    from vid2sim.physics.modes import subspace_stiffness_parts
    from vid2sim.physics.reduced import lbs_rows

    with torch.no_grad():
        w, dw = sim.field.weights_and_gradients(sim.X)
        K_mu, K_lam, _ = (m.numpy() for m in subspace_stiffness_parts(sim.X, w, dw, 1.0, sim.vol))
        b = lbs_rows(sim.X, w)
        M = np.kron(np.eye(3), (b.T @ (b * sim.mass_volumes[:, None])).numpy())  # the simulator's lumped mass
    for nu in (0.3, 0.45):
        mu, lam = lame_parameters(1.0, nu)
        K = curve2.at(nu) * mu * K_mu + curve2.lam_at(nu) * lam * K_lam
        omega = math.sqrt(eigh(K, M + 1e-14 * M.trace() / len(M) * np.eye(len(M)), eigvals_only=True)[6])
        # 4 handles: the weighted six-mode fit gives the lowest mode up a little more than with 20 (≤ 0.2 %);
        # fTetWild's mesh differs from run to run, so the margin is wide (0.55 % seen)
        assert omega == pytest.approx(unit[nu], rel=2e-2)


def test_fixed_damping_and_a_contact_layer_reach_the_fit(report):
    """--fixed-damping keeps ζ at the prior through the fit; --contact-layer gives the simulator a layer of
    that fraction of the size, which changes the motion once the object touches the floor."""
    from dataclasses import replace

    from vid2sim.synthetic.scenes import benchmark_parameters

    _, config, workdir = report
    params = benchmark_parameters(1, 0)[0]
    fixed = replace(config, fit_damping=False)
    scene = identify.prepare_scene(0, params, fixed, workdir)
    out = identify.fit(scene, fixed)
    assert all(h["damping_ratio"] == pytest.approx(config.prior.damping, rel=1e-12)
               for h in out["history"] if "loss" in h)
    layered = identify.prepare_scene(0, params, replace(config, contact_layer=0.1), workdir)
    assert layered.simulator.contact_layer == pytest.approx(0.1 * layered.size)
    plain = identify.prepare_scene(0, params, config, workdir)
    a, b = layered.trajectory(config.frames), plain.trajectory(config.frames)
    assert float((a - b).abs().max()) > 1e-4 * plain.size
    with pytest.raises(ValueError, match="contact_layer"):
        identify.IdentifyConfig(contact_layer=-0.1)
    # --fit-contact-layer: h is a fitted parameter beside E and ν, left on the simulator as a number
    fitted = replace(config, fit_contact_layer=True, fit_damping=False)
    scene = identify.prepare_scene(0, params, fitted, workdir)
    out = identify.fit(scene, fitted)
    steps = [h for h in out["history"] if "loss" in h]
    assert all(h["contact_layer"] > 0 for h in steps) and steps[0]["contact_layer"] == pytest.approx(0.005)
    assert out["contact_layer"] > 0 and isinstance(scene.simulator.contact_layer, float)
    assert scene.simulator.contact_layer == pytest.approx(out["contact_layer"] * scene.size)
    # --calibrate-contact: the layer that gives the subspace the tets' compliance under its own floor loads
    calibrated = replace(config, calibrate_contact=True, contact_iterations=2)
    scene = identify.prepare_scene(0, params, calibrated, workdir)
    rounds = identify.calibrate_contact(scene, calibrated, 5.0, 0.3)
    assert len(rounds) == 2 and scene.simulator.contact_layer == rounds[-1]["layer"] >= 0
    assert all(r["tet_compliance"] > 0 and r["subspace_compliance"] > 0 and math.isfinite(r["raw_layer"])
               for r in rounds)
    # four handles are far stiffer than the tets under a floor load: the layer is real
    assert rounds[0]["compliance_ratio"] > 1 and rounds[0]["layer"] > 0
    with pytest.raises(ValueError, match="contact_iterations"):
        identify.IdentifyConfig(contact_iterations=0)


def test_the_projected_volumetric_term_reaches_the_simulator_with_a_one_factor_curve(report):
    """--volumetric projected: the scene's simulator projects the λ term, calibrated by one factor s(ν) (its
    lowest frequency then equals the tets'); two factors are refused with it, by the config and the CLI flag."""
    from dataclasses import replace

    from vid2sim.physics.modes import subspace_frequencies
    from vid2sim.physics.tet_modes import tet_frequencies
    from vid2sim.synthetic.scenes import benchmark_parameters

    _, config, workdir = report
    projected = replace(config, simulator=replace(config.simulator, volumetric="projected"),
                        calibration=CalibrationConfig(nu="curve"), calibration_nus=(0.3, 0.45))
    scene = identify.prepare_scene(0, benchmark_parameters(1, 0)[0], projected, workdir)
    sim = scene.simulator
    assert sim.volumetric == "projected" and sim.stiffness_scale.lam_scale is None
    nu = 0.45
    ref = tet_frequencies(scene.tet_vertices, scene.tets, 1.0, nu, 1.0, k=1, order=2)[0]
    ours = subspace_frequencies(sim.field, sim.X, sim.vol, sim.stiffness_scale.at(nu), nu, 1.0, k=1,
                                volumetric="projected", mass_volumes=sim.mass_volumes)[0]
    assert ours == pytest.approx(ref, rel=1e-6)
    out = identify.fit(scene, replace(projected, fit_iterations=1, fit_damping=False))
    assert math.isfinite(out["log10_E"]) and 0 <= out["nu"] < 0.5
    with pytest.raises(ValueError, match="one factor"):
        identify.IdentifyConfig(simulator=SimulatorConfig(volumetric="projected"),
                                calibration=CalibrationConfig(enabled=True, nu="two_factor"))
    with pytest.raises(ValueError, match="simulator.volumetric must be"):
        identify.IdentifyConfig.from_dict({"simulator": {"volumetric": "mixed"}})


def test_nu_sensitivity_measures_how_far_nu_moves_the_truth(report):
    """--nu-sensitivity: the FEM rerun at ν − Δν (same mesh, pose, steps) is cached; the distance it moves the
    truth grows about linearly with Δν, and the ν worth of the model error follows from it."""
    from dataclasses import replace

    from vid2sim.synthetic.scenes import benchmark_parameters

    _, config, workdir = report
    params = benchmark_parameters(1, 0)[0]
    scene = identify.prepare_scene(0, params, config, workdir)
    rows = {}
    for dnu in (0.04, 0.08):
        cfg = replace(config, nu_sensitivity=dnu)
        rows[dnu] = identify.nu_sensitivity(0, params, scene, cfg, workdir, model_error_observed_percent=2.0)
        assert rows[dnu]["dnu"] == pytest.approx(-dnu) and rows[dnu]["observed_percent"] > 0
        assert rows[dnu]["observed_percent_per_0_05"] == pytest.approx(rows[dnu]["observed_percent"] * 0.05 / dnu)
        assert rows[dnu]["nu_equivalent_of_model_error"] == pytest.approx(dnu * 2.0 / rows[dnu]["observed_percent"])
    ratio = rows[0.08]["observed_percent"] / rows[0.04]["observed_percent"]
    assert 1.6 < ratio < 2.4, ratio  # smooth in ν: about linear over a small change
    again = identify.nu_sensitivity(0, params, scene, replace(config, nu_sensitivity=0.04), workdir, 2.0)
    assert again["seconds"] == 0.0 and again["observed_percent"] == rows[0.04]["observed_percent"]  # cached
    assert (workdir / "scene_000" / "fem_result_nu-0.0400.npz").is_file()
    with pytest.raises(ValueError, match="nu_sensitivity"):
        identify.IdentifyConfig(nu_sensitivity=0.6)


def test_render_psnr_scores_the_models_motion_in_images(report):
    """--psnr: the textured object carried by the truth and by the model, rendered in the preset's observed
    cameras; the images see the model error (a wrong material scores lower), and frame 1 (before the floor)
    is the same rigid motion from the exact start."""
    from vid2sim.synthetic.scenes import benchmark_parameters

    _, config, workdir = report
    params = benchmark_parameters(1, 0)[0]
    scene = identify.prepare_scene(0, params, config, workdir)
    truth = scene.material
    identify.set_material(scene.simulator, math.log10(truth["E"]), truth["nu"], truth["damping_ratio"])
    at_truth = identify.render_psnr(0, params, scene, config, workdir)
    assert at_truth["resolution"] == 128 and at_truth["views"] == [0, 2, 3, 5]  # small preset: 2 of 6 held out
    assert len(at_truth["dynamic"]["psnr_per_frame"]) == config.observed_frames - 1
    assert len(at_truth["future"]["psnr_per_frame"]) == config.frames - config.observed_frames
    assert at_truth["dynamic"]["psnr_per_frame"][0] > 45  # frame 1: free flight, the same rigid motion
    identify.set_material(scene.simulator, math.log10(truth["E"]) - 1.0, 0.45, truth["damping_ratio"])
    wrong = identify.render_psnr(0, params, scene, config, workdir)
    assert wrong["dynamic"]["psnr"] < at_truth["dynamic"]["psnr"] - 1.0
    assert 0 < wrong["dynamic"]["ssim"] <= at_truth["dynamic"]["ssim"] <= 1


def test_report_has_per_scene_figures_and_means(report):
    result, config, _ = report
    (row,) = result["scenes"]
    for key in ("true", "fitted", "abs_error", "model_error_at_truth_percent", "trajectory_error_fitted_percent",
                "reduced_time_convergence_at_truth", "e_valley", "fit", "seconds"):
        assert key in row, key
    assert row["abs_error"]["log10_E"] == pytest.approx(abs(row["fitted"]["log10_E"] - row["true"]["log10_E"]))
    assert 0 < row["fitted"]["nu"] < 0.5 and row["fitted"]["damping_ratio"] >= 0
    # the fit starts at the coarse search's minimum (grid sorted, at the prior ν and ζ) and never ends worse
    from vid2sim.reconstruct.stages.joint import coarse_minimum

    grid = [c["log10_E"] for c in row["fit_coarse"]]
    assert grid == [4.0, 5.0, 5.5] == list(config.coarse_log10_E)
    losses = [h["loss"] for h in row["fit_history"] if "loss" in h]
    assert row["fit"]["loss"] == min(losses) <= losses[0]
    start = coarse_minimum(grid, [c["loss"] for c in row["fit_coarse"]])
    assert row["fit_history"][0]["log10_E"] == pytest.approx(start)
    assert row["fit_history"][0]["nu"] == pytest.approx(config.prior.nu)
    if start in grid:  # the first L-BFGS evaluation repeats the grid's
        assert losses[0] == pytest.approx(row["fit_coarse"][grid.index(start)]["loss"], rel=1e-9)
    assert len(row["e_valley"]["loss"]) == config.sweep_points
    at_truth = row["model_error_at_truth_percent"]
    # a rigid alignment per frame can only shrink the distance; deformations are non-negative
    assert 0 <= at_truth["observed_nonrigid_percent"] <= at_truth["observed_percent"] + 1e-9
    assert 0 <= at_truth["future_nonrigid_percent"] <= at_truth["future_percent"] + 1e-9
    assert at_truth["peak_deformation_percent"]["truth"] > 0 and at_truth["peak_deformation_percent"]["reduced"] > 0
    # the rotation off the truth's from the exact start: none at frame 0, and the drop bounces within its frames
    turn, contacts = at_truth["orientation"], at_truth["contacts"]
    assert turn["per_frame_deg"][0] == pytest.approx(0.0, abs=1e-5) and len(turn["per_frame_deg"]) == config.frames
    assert contacts["truth"] and contacts["simulated_frames"]
    assert contacts["truth"][0]["rotation_deg"]["before"] < 1.0  # free flight from the exact start: the same turn
    assert result["summary"]["mean_model_error_first_contact_added_rotation_deg"] == pytest.approx(
        contacts["first_added_rotation_deg"])
    assert (
        row["reduced_time_convergence_at_truth"]["refined_substeps"]
        == 4 * row["reduced_time_convergence_at_truth"]["substeps"]
    )
    freq = row["frequencies"]
    assert len(freq["quadratic_tets_hz"]) == 6 and all(f > 0 for f in freq["quadratic_tets_hz"])
    assert freq["quadratic_tets_hz"] == sorted(freq["quadratic_tets_hz"])
    for key in ("linear_tets_over_quadratic", "reduced_over_quadratic", "reduced_over_linear_tets"):
        assert len(freq[key]) == 6 and all(0.5 < r < 5 for r in freq[key]), (key, freq[key])
    ratio = freq["reduced_over_quadratic"][0] / freq["linear_tets_over_quadratic"][0]
    assert freq["reduced_over_linear_tets"][0] == pytest.approx(ratio)
    summary = result["summary"]
    assert summary["mean_abs_error_log10_E"] == pytest.approx(row["abs_error"]["log10_E"])
    assert summary["mean_lowest_frequency_linear_tets_over_quadratic"] == pytest.approx(
        freq["linear_tets_over_quadratic"][0]
    )
    json.dumps(result)  # JSON-ready


def _without_times(row: dict) -> dict:
    """A report row without its wall times (they differ between runs) and its diagnostic frequencies (sparse
    eigensolves in another process agree to ~1e-14, not bit for bit: compared separately)."""
    row = json.loads(json.dumps(row))
    row.pop("seconds")
    row.pop("fem_seconds")
    row.pop("frequencies")
    row["fit"].pop("seconds")
    return row


def test_workers_give_the_rows_of_one_process(report, one_torch_thread):
    """Two worker processes give the rows of one process, and --only reruns a subset from the same cache with the
    full suite's rows. The one-process rows: scene 0's is the report's (this config's scene 0, same cache, one
    torch thread), scene 1's the subset's (each scene is computed from its own seed and cache alone)."""
    result, _, workdir = report
    config = identify.IdentifyConfig(**{**TINY, "scenes": 2})
    two = identify.run(config, workdir, progress=False, workers=2, threads_per_worker=1)  # scene 1 made here
    # --only: with one scene to run, two workers are one (no process pool): the rows of this process
    subset = identify.run(identify.IdentifyConfig(**{**TINY, "scenes": 2, "only": (1,)}), workdir, progress=False,
                          workers=2)
    assert subset["workers"] == 1 and [r["scene"] for r in subset["scenes"]] == [1]
    assert subset["summary"]["mean_abs_error_nu"] == pytest.approx(subset["scenes"][0]["abs_error"]["nu"])
    one = [result["scenes"][0], subset["scenes"][0]]
    assert result["workers"] == 1 and result["threads"] == 1 and [r["scene"] for r in one] == [0, 1]
    assert two["workers"] == 2 and two["threads"] == 1
    assert [r["scene"] for r in two["scenes"]] == [0, 1]
    assert [_without_times(r) for r in two["scenes"]] == [_without_times(r) for r in one]
    for a, b in zip(one, two["scenes"]):
        for key, values in a["frequencies"].items():
            assert b["frequencies"][key] == pytest.approx(values, rel=1e-9)
    assert two["summary"]["median_abs_error_nu"] == pytest.approx(
        statistics.median(r["abs_error"]["nu"] for r in one)
    )
    with pytest.raises(ValueError, match="workers"):
        identify.run(config, workdir, progress=False, workers=0)
    for bad in ((2,), (1, 1), (-1,)):
        with pytest.raises(ValueError, match="only"):
            identify.IdentifyConfig(**{**TINY, "scenes": 2, "only": bad})


def test_nu_scan_finds_the_true_nu_of_the_models_own_motion(report):
    """With the reduced model's own motion as the truth, the ν scan at the true E has its zero at the true ν
    and rises on both sides; the grid and the CLI's step are validated."""
    from dataclasses import replace

    from vid2sim.synthetic.scenes import benchmark_parameters

    _, config, workdir = report
    scene = identify.prepare_scene(0, benchmark_parameters(1, 0)[0], config, workdir)
    truth = scene.material
    nu = round(truth["nu"], 6)  # a grid value the scan hits exactly
    scene.material = {**truth, "nu": nu}
    identify.set_material(scene.simulator, math.log10(truth["E"]), nu, truth["damping_ratio"])
    scene.truth = scene.trajectory(config.frames)
    grid = (nu - 0.2, nu - 0.1, nu, nu + 0.1, nu + 0.15)
    scan = identify.scan_nu(scene, replace(config, nu_scan=grid))
    assert scan["nu"] == list(grid) and scan["loss"][2] < 1e-20  # exact up to the rigid alignment's rounding
    assert scan["loss"][0] > scan["loss"][1] > 0 and 0 < scan["loss"][3] < scan["loss"][4]
    assert abs(scan["argmin_error"]) < 0.03 and scan["argmin_nu"] - nu == scan["argmin_error"]
    assert float(scene.simulator.nu) == nu  # left at the true material
    with pytest.raises(ValueError, match="nu_scan"):
        identify.IdentifyConfig(nu_scan=(0.3, 0.2))
    with pytest.raises(ValueError, match="nu_scan"):
        identify.IdentifyConfig(nu_scan=(0.0, 0.2))


def test_cli_rejects_bad_options_with_the_flag_name(tmp_path, capsys):
    assert main(["bench", "identify", "--n", "0", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--n must be an integer >= 1" in err
    assert main(["bench", "identify", "--workers", "0", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err
    assert main(["bench", "identify", "--nu-sensitivity", "0.7", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "--nu-sensitivity must be a number in [0, 0.5)" in capsys.readouterr().err
    assert main(["bench", "identify", "--only", "6", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "--only must be distinct scene indices in [0, 6)" in capsys.readouterr().err
    for step in ("0.3", "0"):
        assert main(["bench", "identify", "--nu-scan", step, "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
        assert "--nu-scan must be a step in (0, 0.25)" in capsys.readouterr().err


def _setting(config, path: str):
    for part in path.split("."):
        config = getattr(config, part)
    return config


def test_cli_defaults_are_the_configuration_the_readme_reports(tmp_path, monkeypatch):
    """No flags: 30 handles, the projected term calibrated by one factor per ν, moment-matched masses, ζ fixed
    (#10's figures). --volumetric pointwise takes two factors unless --calibration-nu is given; the switches
    turn the calibration off and the damping fit on. The flags are generated from IdentifyConfig's tree
    (--networks.handles), the flat spellings of before are aliases, and --config repeats a report's settings."""

    class Stop(Exception):
        pass

    seen = []

    def fake_run(config, *args, **kwargs):
        seen.append(config)
        raise Stop

    monkeypatch.setattr(identify, "run", fake_run)
    report = tmp_path / "report.json"
    saved = identify.IdentifyConfig(scenes=3, only=(2,), networks=NetworksConfig(handles=7), fit_damping=True)
    report.write_text(json.dumps({"config": saved.to_dict(), "summary": {}, "scenes": []}))
    cases = [([], {"networks.handles": 30, "calibration.enabled": True, "calibration.nu": "curve",
                   "simulator.volumetric": "projected", "simulator.mass": "moments", "fit_damping": False}),
             (["--volumetric", "pointwise"], {"simulator.volumetric": "pointwise", "calibration.nu": "two_factor"}),
             (["--simulator.volumetric", "pointwise"], {"calibration.nu": "two_factor"}),
             (["--volumetric", "pointwise", "--calibration-nu", "prior"], {"calibration.nu": "prior"}),
             (["--no-calibrate-stiffness", "--fit-damping", "--handles", "12"],
              {"calibration.enabled": False, "fit_damping": True, "networks.handles": 12}),
             (["--networks.handles", "12", "--prior.nu", "0.25", "--calibration.enabled", "--mass", "cubature"],
              {"networks.handles": 12, "prior.nu": 0.25, "calibration.enabled": True, "simulator.mass": "cubature"}),
             (["--n", "8", "--only", "4,5", "--psnr", "--fit-damping", "--fixed-damping", "--nu-scan", "0.1",
               "--skinning-iterations", "30", "--fem-element-order", "1", "--coarse_log10_E", "5", "4"],
              {"scenes": 8, "only": (4, 5), "render_psnr": True, "fit_damping": False,
               "nu_scan": (0.1, 0.2, 0.3, 0.4), "networks.skinning_iterations": 30, "fem_element_order": 1,
               "coarse_log10_E": (4.0, 5.0)}),
             (["--only", "0", "1", "--simulator.integration.integrator", "implicit_euler"],
              {"only": (0, 1), "simulator.integration.integrator": "implicit_euler"}),
             (["--config", str(report), "--networks.skinning_iterations", "5"],
              {"scenes": 3, "only": (2,), "networks.handles": 7, "networks.skinning_iterations": 5,
               "fit_damping": True})]
    for flags, expected in cases:
        with pytest.raises(Stop):
            main(["bench", "identify", "--workdir", str(tmp_path / "w"), "--quiet", *flags])
        assert {k: _setting(seen[-1], k) for k in expected} == expected, flags
    assert identify.IdentifyConfig() == seen[0]


def test_the_configuration_saved_in_the_report_loads_back_and_unknown_settings_are_named(tmp_path, capsys):
    config = identify.IdentifyConfig(only=(1, 3), networks=NetworksConfig(handles=12), nu_scan=(0.2, 0.3),
                                     simulator=SimulatorConfig(volumetric="pointwise", mass="cubature"),
                                     calibration=CalibrationConfig(nu="two_factor"), coarse_log10_E=(5.0, 4.0))
    data = json.loads(json.dumps(config.to_dict()))
    assert data["networks"]["handles"] == 12 and data["simulator"]["integration"]["dt"] == 0.05
    assert identify.IdentifyConfig.from_dict(data) == config
    for bad, name in (({"handels": 3}, "unknown setting handels"),
                      ({"networks": {"handels": 3}}, "unknown setting networks.handels"),
                      ({"networks": {"handles": "many"}}, "networks.handles must be an integer"),
                      ({"networks": {"jacobian": "neural"}}, "jacobian must be 'closed_form'"),
                      ({"prior": {"nu": 0.0}}, "PriorConfig.nu and PriorConfig.damping must be > 0"),
                      ({"handles": 3, "networks": {"handles": 4}}, r"handles \(now networks.handles\) is given twice")):
        with pytest.raises(ConfigError, match=name):
            identify.IdentifyConfig.from_dict(bad)
    # a report of before the sections: its flat names move to them
    old = identify.IdentifyConfig.from_dict({"handles": 12, "prior_nu": 0.25, "calibrate_stiffness": False,
                                             "calibration_nu": "two_factor", "volumetric": "pointwise",
                                             "mass": "cubature", "cubature": 300, "skinning_objective": "random_z"})
    assert (old.networks, old.prior.nu, old.calibration.enabled, old.calibration.nu) == \
        (NetworksConfig(handles=12, skinning_objective="random_z"), 0.25, False, "two_factor")
    assert (old.simulator.volumetric, old.simulator.mass, old.simulator.cubature) == ("pointwise", "cubature", 300)
    # on the command line: the flag or the file named
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"networks": {"handels": 3}}))
    assert main(["bench", "identify", "--config", str(bad), "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "unknown setting networks.handels" in capsys.readouterr().err
    assert main(["bench", "identify", "--handles", "0", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "--handles must be >= 1" in capsys.readouterr().err
    assert main(["bench", "identify", "--prior.nu", "0.7", "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    assert "nu=0.7" in capsys.readouterr().err


def test_shape_and_centre_loss_is_blind_to_orientation_and_sees_centre_and_shape():
    """The default fit loss: a trajectory turned per frame about its centre costs nothing; a shifted one
    costs the squared shift; a deformed one costs its shape error. Its autograd gradient matches finite
    differences through the per-frame rigid alignment."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(0)
    truth = torch.rand(5, 40, 3, generator=g, dtype=torch.float64)
    angles = torch.linspace(0.0, 2.5, 5, dtype=torch.float64)
    c, s = torch.cos(angles), torch.sin(angles)
    R = torch.zeros(5, 3, 3, dtype=torch.float64)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    centre = truth.mean(1, keepdim=True)
    turned = (truth - centre) @ R.transpose(1, 2) + centre

    def scene(traj):
        return SimpleNamespace(trajectory=lambda frames, grad=False: traj[:frames], truth=truth, size=2.0)

    loss = identify.trajectory_loss
    assert float(loss(scene(turned), 5, kind="shape_and_centre")) == pytest.approx(0.0, abs=1e-20)
    assert float(loss(scene(turned), 5, kind="positions")) > 1e-3
    shift = torch.tensor([0.03, -0.04, 0.0], dtype=torch.float64)
    assert float(loss(scene(turned + shift), 5, kind="shape_and_centre")) == pytest.approx(0.05**2 / 4, rel=1e-9)
    stretched = truth.clone()
    stretched[..., 2] = centre[..., 2] + 1.1 * (truth[..., 2] - centre[..., 2])
    assert float(loss(scene(stretched), 5, kind="shape_and_centre")) > 1e-5
    x = (turned + 0.01 * torch.randn(turned.shape, generator=g, dtype=torch.float64)).requires_grad_()
    loss(scene(x), 5, kind="shape_and_centre").backward()
    direction = torch.randn(x.shape, generator=g, dtype=torch.float64)
    eps = 1e-6
    with torch.no_grad():
        fd = (loss(scene(x + eps * direction), 5, kind="shape_and_centre")
              - loss(scene(x - eps * direction), 5, kind="shape_and_centre")) / (2 * eps)
    assert float((x.grad * direction).sum()) == pytest.approx(float(fd), rel=1e-5)
    with pytest.raises(ValueError, match="loss must be one of"):
        identify.IdentifyConfig(loss="pose")


def test_summary_counts_the_fits_a_failed_line_search_ended():
    """A fit whose line search pushed E or ν where the simulation fails stops early; the summary counts it (it was
    only in the per-scene history)."""
    from vid2sim.apps.bench.identify import summarise

    def row(failures: int) -> dict:
        pct = {"observed_percent": 1.0, "future_percent": 2.0, "observed_nonrigid_percent": 0.5,
               "future_nonrigid_percent": 0.6}
        return {"abs_error": {"log10_E": 0.1, "nu": 0.05, "damping_ratio": 0.0}, "model_error_at_truth_percent": pct,
                "trajectory_error_fitted_percent": pct, "e_valley": {"depth_at_minus": 3.0, "depth_at_plus": 4.0},
                "reduced_time_convergence_at_truth": {"mean_percent": 0.2}, "stiffness_scale": 1.0,
                "fit": {"seconds": 1.0, "line_search_failures": failures,
                        "line_search_error": "line search failed" if failures else None},
                "frequencies": {k: [1.0] for k in ("linear_tets_over_quadratic", "reduced_over_quadratic",
                                                    "reduced_over_linear_tets")}}

    assert summarise([row(0), row(1), row(1)])["summary"]["fit_line_search_failures"] == 2
    assert "mean_model_error_rotation_observed_deg" not in summarise([row(0)])["summary"]  # rows without it
    assert summarise([row(0)])["summary"]["fit_line_search_failures"] == 0
