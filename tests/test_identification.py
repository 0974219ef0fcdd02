"""Identification against physics: a toy drop simulated by the project's FEM truth (Neo-Hookean tets,
:mod:`vid2sim.synthetic`) at E = 3e5 Pa, ν = 0.42 — off the reconstruction's prior (1e5, 0.3) in both — is
reconstructed at the demo's tiny sizes; the material must move toward the truth, and what the video cannot
determine must be reported as such rather than returned as found.

The scene is built and reconstructed once for the module (about 50 s of CPU: an 8-frame, 40² FEM drop whose first
contact is at frame 1, so the observed clip holds the bounce). The fit holds the floor frictionless, as the FEM's
floor is (``fit_friction`` off: a frictional rollout costs 2–3 frictionless ones, and the Gauss–Newton fit spent
them on a μ the truth does not have), and its coarse search brackets the start with three values of log10 E.

The object's tet mesh is frozen (``tests/data/identification_tets.npz``): fTetWild's tets differ from run to run
(even on one thread), and at this toy size the recovered E follows them. Over 6 fresh meshes of the same surface
|Δlog10 E| was 0.028, 0.113, 0.166, 0.197, 0.270 and 0.464 (4 of 6 within half the prior's 0.477 — the test's
bound; measured with 10 frames and μ fitted), so with fresh meshes the test failed one run in three. The frozen mesh
is one of those six, the one near their median (0.166 then); with it the reconstruction is the same on every run.
At 10 frames with μ fitted it gave |Δlog10 E| 0.154, ν 0.294 (the five-value coarse grid of then and these three
values start the fit at the same log10 E, 5.164); at these settings 0.125, ν 0.298 (measured twice). On three more
fresh meshes, each reconstructed both ways: 0.017, 0.134, 0.106 then and 0.099, 0.119, 0.065 at these settings (ν
not identifiable, within 0.006 of the prior, every time). The recovered E depends on the sizes (at 32² instead of
40² it was 0.405): re-measure after changing any.
"""

import json
import math
from pathlib import Path

import pytest

from vid2sim.reconstruct.uncertainty import NOT_IDENTIFIABLE

pytestmark = pytest.mark.slow  # a FEM scene and a reconstruction

TRUTH_E, TRUTH_NU = 3e5, 0.42


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    """(material.json, log.json, the prior) of the tiny reconstruction of the FEM drop at (3e5, 0.42)."""
    from vid2sim.apps.demo import TINY
    from vid2sim.reconstruct.config import ReconstructConfig
    from vid2sim.reconstruct.pipeline import reconstruct
    from vid2sim.runtime import config as configs
    from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene

    root = tmp_path_factory.mktemp("identify")
    tets = Path(__file__).parent / "data" / "identification_tets.npz"
    scene = make_scene(SyntheticSceneConfig.preset("small", seed=3, youngs_modulus=TRUTH_E, poisson_ratio=TRUTH_NU,
                                                   frames=8, observed_frames=8, resolution=40, views=4,
                                                   held_out_views=1, substeps=4, drop_height=0.02,
                                                   tet_mesh=str(tets)),
                       root / "scene", progress=False)
    config = configs.merge(
        ReconstructConfig(),
        {
            **TINY,
            "joint": {
                **TINY["joint"],
                "method": "gauss_newton",
                "fit_damping": True,
                "fit_friction": False,
                "gauss_newton_iterations": 4,
                "coarse_log10_E": [4.5, 5.0, 5.5],
            },
        },
    )
    asset = reconstruct(scene, root / "asset", config, progress=False)
    material = json.loads((asset / "material.json").read_text())
    log = json.loads((asset / "log.json").read_text())
    return material, log, config.prior


def test_reconstruct_moves_the_material_toward_the_fem_truth(identified):
    """log10 E ends at least half the prior's distance closer to the truth (the prior is 0.48 decades off); ν
    either moves toward 0.42 by 0.02 or — as at this size, where ν changes the clip's loss by a few per cent —
    is reported not identifiable from this video with the prior's width, never as found at the prior."""
    material, log, prior = identified
    truth = math.log10(TRUTH_E)
    start_error = abs(math.log10(prior.E) - truth)
    assert abs(material["log10_E"] - truth) <= 0.5 * start_error
    nu = material["uncertainty"]["nu"]
    moved = abs(prior.nu - TRUTH_NU) - abs(material["nu"] - TRUTH_NU)
    if nu["identifiable"]:
        assert moved >= 0.02 and nu["note"] == "found"
    else:
        assert nu["note"] == NOT_IDENTIFIABLE and nu["sd"] >= 0.9 * nu["prior_sd"]
        assert abs(material["nu"] - prior.nu) < nu["prior_sd"]  # the prior's value, moved a little


def test_the_reconstruction_reports_its_own_confidence(identified):
    """E is identifiable from the bounce: the images' own standard deviation of log10 E is below the prior's,
    its interval is narrower than the prior's and holds the value found; the joint fit's kept validation loss is
    no worse than its start's, and the frames before the first contact carry none of E's information."""
    material, log, _ = identified
    entry = material["uncertainty"]["log10_E"]
    assert entry["identifiable"] and entry["note"] == "found"
    assert entry["data_sd"] < entry["prior_sd"] and entry["sd"] < entry["prior_sd"]
    lo, hi = entry["interval"]
    assert lo < material["log10_E"] < hi and hi - lo < 2 * entry["prior_sd"]
    fit = log["joint_fit"]
    assert fit["method"] == "gauss_newton" and fit["validation_loss"] <= fit["start_validation_loss"]
    share = fit["information_by_frame"]["log10_E"]
    assert sum(share) == pytest.approx(1.0) and share[0] < 1e-3  # frame 1: still in the air
