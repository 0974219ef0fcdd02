"""Stage ``networks``: the skinning field trained data-free on the object's points (and the Neural Jacobian).

The field is trained in the object's canonical frame (centred, half the box diagonal 0.5: the paper's) and then
moved to the scene's metric frame by its input frame (:mod:`vid2sim.physics.input_frame`). It starts from Stage
I's prediction (the template's hidden layers with the predicted last layer) when Stage I ran with the template's
handle count, else from a seeded initialisation.
"""

from __future__ import annotations

import torch

from vid2sim.physics.neural_jacobian import (
    NeuralJacobian,
    NeuralJacobianTrainingConfig,
    train_neural_jacobian,
)
from vid2sim.physics.skinning import SkinningField
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.predictor.template import field_from_last_layer, load_template
from vid2sim.reconstruct.runner import Context, State
from vid2sim.runtime.files import save_torch_atomic

FIELD, JACOBIAN = "skinning.pt", "jacobian.pt"


def cpu_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The module's state dict with CPU tensors (work files and assets load on any device)."""
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}


def initial_networks(ctx: Context, state: State) -> tuple[SkinningField, NeuralJacobian | None]:
    """The untrained field (Stage I's start or a seeded one) and Neural Jacobian (or None), on the device."""
    cfg = ctx.config
    field = SkinningField(cfg.networks.handles, seed=cfg.seed)
    if state.stage1["ran"] and state.stage1.get("skinning_start", True):
        field = field_from_last_layer(load_template(), state.last_layer)
    jacobian = (NeuralJacobian(num_handles_total=cfg.networks.handles + 1, seed=cfg.seed)
                if cfg.networks.jacobian == "neural" else None)
    return field.to(ctx.device), (jacobian.to(ctx.device) if jacobian is not None else None)


class NetworksStage:
    """Trains the networks (``config.networks``); writes ``skinning.pt`` (and ``jacobian.pt``)."""

    name = "networks"
    sections = ("networks",)
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        return "training the skinning field data-free" + (
            " and the Neural Jacobian" if ctx.config.networks.jacobian == "neural" else "")

    def run(self, ctx: Context, state: State) -> None:
        cfg, obj = ctx.config, state.obj
        field, jacobian = initial_networks(ctx, state)
        train_skinning(field, obj.canonical(obj.points),
                       SkinningTrainingConfig(iterations=cfg.networks.skinning_iterations, seed=cfg.seed,
                                              objective=cfg.networks.skinning_objective),
                       progress=ctx.progress, volume=obj.volume / obj.scale ** 3)
        field.set_input_frame(obj.centre, obj.scale)
        save_torch_atomic(cpu_state(field), ctx.path(FIELD))
        if jacobian is not None:
            jacobian.set_input_frame(obj.centre, obj.scale)
            train_neural_jacobian(jacobian, field, obj.points, NeuralJacobianTrainingConfig(
                iterations=cfg.networks.jacobian_iterations, seed=cfg.seed), progress=ctx.progress)
            save_torch_atomic(cpu_state(jacobian), ctx.path(JACOBIAN))

    def load(self, ctx: Context, state: State) -> None:
        state.skinning, state.jacobian = initial_networks(ctx, state)
        state.skinning.load_state_dict(torch.load(ctx.path(FIELD), weights_only=True))  # onto the field's device
        if state.jacobian is not None:
            state.jacobian.load_state_dict(torch.load(ctx.path(JACOBIAN), weights_only=True))
