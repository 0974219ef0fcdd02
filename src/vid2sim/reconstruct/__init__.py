"""Stage I + Stage II: a scene folder in, a simulation-ready asset out (paper §4)."""

from vid2sim.reconstruct.pipeline import (
    ReconstructConfig,
    ReconstructionError,
    reconstruct,
)

__all__ = ["ReconstructConfig", "ReconstructionError", "reconstruct"]
