"""The stages of the reconstruction, one module each, in the order they run (docs/architecture.md).

=====================  =======================================================================================
``gaussians``          3D Gaussians fitted to frame 0 of the observed views
``points``             the object's interior at frame 0, its hull carved again with the later frames; cubature
``velocity``           the initial rigid velocity from the ballistic pre-contact frames
``appearance``         the Gaussians refined on the ballistic frames
``stage1``             the feed-forward predictor's material and skinning start (off by default)
``networks``           the skinning field (and the Neural Jacobian) trained data-free
``calibration``        the subspace's stiffness matched to quadratic tets
``joint``              the joint optimisation of material, initial velocity and networks (paper Eq. 6)
``motion_appearance``  the Gaussians refitted along the simulated motion
``continuation``       the state at the end of the observed clip, fitted to its last frames (the prediction's start)
=====================  =======================================================================================
"""

from __future__ import annotations

from vid2sim.reconstruct.runner import Stage
from vid2sim.reconstruct.stages.appearance import AppearanceStage
from vid2sim.reconstruct.stages.calibration import CalibrationStage
from vid2sim.reconstruct.stages.continuation import ContinuationStage
from vid2sim.reconstruct.stages.gaussians import GaussiansStage
from vid2sim.reconstruct.stages.joint import JointStage
from vid2sim.reconstruct.stages.motion_appearance import MotionAppearanceStage
from vid2sim.reconstruct.stages.networks import NetworksStage
from vid2sim.reconstruct.stages.points import PointsStage
from vid2sim.reconstruct.stages.stage1 import Stage1Stage
from vid2sim.reconstruct.stages.velocity import VelocityStage


def all_stages() -> list[Stage]:
    """A fresh instance of every stage, in order (a stage may hold a background job of its run)."""
    return [GaussiansStage(), PointsStage(), VelocityStage(), AppearanceStage(), Stage1Stage(), NetworksStage(),
            CalibrationStage(), JointStage(), MotionAppearanceStage(),
            ContinuationStage()]


#: the stages' names, in order
STAGES: tuple[str, ...] = tuple(s.name for s in all_stages())
