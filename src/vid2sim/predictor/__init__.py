"""Stage I: the feed-forward predictor's training data and its template skinning network.

- :mod:`~vid2sim.predictor.template`: the template skinning network (hidden layers trained once over many
  shapes, shipped as ``template_skinning.pt``) and the per-object last-layer fit (the 650-number label).
- :mod:`~vid2sim.predictor.solid`: interior points, volume and contact points of a closed mesh.
- :mod:`~vid2sim.predictor.front_view`: the front camera Stage I sees.
- :mod:`~vid2sim.predictor.data`: training samples (reduced-simulator drops rendered from the front camera),
  shards and ``index.json`` (``vid2sim make-training-data``).
- :mod:`~vid2sim.predictor.dataset`: :class:`TrainingData`, the torch ``Dataset`` over such a folder.

See docs/training-data.md.
"""

from vid2sim.predictor.data import (
    TrainingDataConfig,
    make_object_shard,
    make_training_data,
    object_specs,
)
from vid2sim.predictor.dataset import TrainingData
from vid2sim.predictor.front_view import FrontCamera, closest_view
from vid2sim.predictor.template import (
    TEMPLATE_PATH,
    TemplateConfig,
    canonical_gauge,
    field_from_last_layer,
    fit_last_layer,
    load_template,
    spectral_last_layer,
    train_template,
)

__all__ = [
    "TEMPLATE_PATH",
    "FrontCamera",
    "TemplateConfig",
    "TrainingData",
    "TrainingDataConfig",
    "canonical_gauge",
    "closest_view",
    "field_from_last_layer",
    "fit_last_layer",
    "load_template",
    "make_object_shard",
    "make_training_data",
    "object_specs",
    "spectral_last_layer",
    "train_template",
]
