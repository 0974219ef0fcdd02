"""StiffnessCurve: s(ν) interpolated smoothly, monotone where the data are, differentiable in ν."""

import math

import numpy as np
import pytest
import torch

from vid2sim.physics.stiffness_curve import StiffnessCurve

NUS = (0.0, 0.1, 0.2, 0.3, 0.35, 0.4, 0.43, 0.46, 0.48, 0.49)
# the shape measured on a bench-identify object with 10 handles: flat, then falling fast towards ½
SCALES = (0.93, 0.932, 0.935, 0.93, 0.925, 0.90, 0.87, 0.82, 0.76, 0.70)


def test_the_curve_passes_through_its_values_and_is_held_outside():
    curve = StiffnessCurve(NUS, SCALES)
    for nu, s in zip(NUS, SCALES):
        assert curve.at(nu) == pytest.approx(s, rel=1e-12)
    assert curve.at(-0.1) == pytest.approx(SCALES[0]) and curve.at(0.499) == pytest.approx(SCALES[-1])


def test_monotone_data_give_a_monotone_curve_and_no_overshoot():
    curve = StiffnessCurve(NUS[3:], SCALES[3:])  # strictly falling from ν = 0.3
    values = [curve.at(v) for v in np.linspace(0.3, 0.49, 400)]
    assert all(b <= a + 1e-15 for a, b in zip(values, values[1:]))
    assert max(values) <= SCALES[3] + 1e-15 and min(values) >= SCALES[-1] - 1e-15


def test_the_gradient_in_nu_is_the_derivative_and_is_continuous():
    curve = StiffnessCurve(NUS, SCALES)
    h = 1e-6
    slopes = []
    for nu in (0.05, 0.25, 0.333, 0.41, 0.47, 0.485):
        x = torch.tensor(nu, dtype=torch.float64, requires_grad=True)
        (g,) = torch.autograd.grad(curve(x), x)
        fd = (curve.at(nu + h) - curve.at(nu - h)) / (2 * h)
        assert float(g) == pytest.approx(fd, rel=1e-6, abs=1e-9)
    for node in NUS[1:-1]:  # C¹: the slope is the same on both sides of every grid value
        for side in (-1e-9, 1e-9):
            x = torch.tensor(node + side, dtype=torch.float64, requires_grad=True)
            slopes.append(float(torch.autograd.grad(curve(x), x)[0]))
        assert slopes[-2] == pytest.approx(slopes[-1], rel=1e-5, abs=1e-8)


def test_round_trip_and_clear_errors():
    curve = StiffnessCurve(NUS, SCALES)
    assert StiffnessCurve.from_dict(curve.to_dict()) == curve
    with pytest.raises(ValueError, match="increase strictly"):
        StiffnessCurve((0.3, 0.2), (1.0, 1.0))
    with pytest.raises(ValueError, match="increase strictly"):
        StiffnessCurve((0.3, 0.5), (1.0, 1.0))
    with pytest.raises(ValueError, match="finite and positive"):
        StiffnessCurve((0.2, 0.3), (1.0, -1.0))
    with pytest.raises(ValueError, match="finite and positive"):
        StiffnessCurve((0.2, 0.3), (1.0, math.inf))
    with pytest.raises(ValueError, match="n >= 2"):
        StiffnessCurve((0.2,), (1.0,))
    with pytest.raises(ValueError, match="stiffness curve must be"):
        StiffnessCurve.from_dict({"nu": [0.2, 0.3]})


def test_two_factor_curve_round_trip_and_lambda_factor():
    lam = tuple(0.5 * s for s in SCALES)
    curve = StiffnessCurve(NUS, SCALES, lam)
    assert StiffnessCurve.from_dict(curve.to_dict()) == curve and "lam_scale" in curve.to_dict()
    assert "lam_scale" not in StiffnessCurve(NUS, SCALES).to_dict()
    for nu in (0.1, 0.33, 0.47):
        assert curve.lam_at(nu) == pytest.approx(0.5 * curve.at(nu), rel=1e-12)
        x = torch.tensor(nu, dtype=torch.float64)
        assert float(StiffnessCurve(NUS, SCALES).lam_factor(x)) == 1.0
    with pytest.raises(ValueError, match="lam_scale must hold"):
        StiffnessCurve(NUS, SCALES, lam[:-1])
    with pytest.raises(ValueError, match="lam_scale must hold"):
        StiffnessCurve((0.2, 0.3), (1.0, 1.0), (1.0, 0.0))
    with pytest.raises(ValueError, match="stiffness curve must be"):
        StiffnessCurve.from_dict({"nu": [0.2, 0.3], "scale": [1, 1], "other": [1, 1]})
