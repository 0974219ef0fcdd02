"""Mesh-free reduced-order simulation (paper §3, §4.2; see docs/architecture.md).

Skinning field and LBS, cubature points, materials (Neo-Hookean, StVK, plasticine, sand), external
energies (gravity, floor, moving floor, spheres), the implicit-Euler Newton solver with its per-step
adjoint, data-free training of the skinning field and the Neural Jacobian.
"""

from vid2sim.physics.cubature import farthest_point_sampling, sample_cubature
from vid2sim.physics.external import (
    Floor,
    Gravity,
    MovingFloor,
    SphereObstacle,
    external_from_dict,
)
from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.neural_jacobian import (
    NeuralJacobian,
    NeuralJacobianTrainingConfig,
    train_neural_jacobian,
)
from vid2sim.physics.plasticity import DruckerPrager, VonMises
from vid2sim.physics.skinning import SkinningField
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.physics.solver import (
    Material,
    SimConfig,
    SimState,
    SimulationError,
    Simulator,
)

__all__ = [
    "DruckerPrager",
    "Floor",
    "Gravity",
    "Material",
    "MovingFloor",
    "NeuralJacobian",
    "NeuralJacobianTrainingConfig",
    "SimConfig",
    "SimState",
    "SimulationError",
    "Simulator",
    "SkinningField",
    "SkinningTrainingConfig",
    "SphereObstacle",
    "VonMises",
    "external_from_dict",
    "farthest_point_sampling",
    "lame_parameters",
    "sample_cubature",
    "train_neural_jacobian",
    "train_skinning",
]
