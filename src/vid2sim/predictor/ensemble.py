"""Several trained Stage I predictors answering as one, with test-time mirroring.

Independently trained networks (another ``--seed``: another initialisation and batch order) make partly
independent errors, so their average is more accurate than each; a left-right mirrored drop has the same
E and ν (training mirrors half the videos for that reason), so a network's answers on the video and on its
mirror image can be averaged too. :class:`PredictorEnsemble` does both:

- log10 E and ν are the mean, in label units, over members × {video, mirrored video} (``mirror=True``) or
  over members (``mirror=False``);
- the skinning field's last layer is the mean over members on the video only: a mirrored video's last layer
  would describe the mirrored field.

It has the interface of :class:`~vid2sim.predictor.model.PhysicsPredictor` that inference and evaluation use
(``config``, ``image_size``, ``num_frames``, ``forward`` giving standardised outputs, ``standardise``,
``unstandardise``, ``predict``), with the first member's label statistics as its standardisation.

Checkpoint (``torch.save`` dict, format ``vid2sim-predictor-ensemble/1``): {"format", "mirror", "members"
(a list of single-network checkpoint dicts, :mod:`vid2sim.predictor.train`), "metrics" (the ensemble's own
validation figures, or None)}. :func:`vid2sim.predictor.train.load_predictor` reads both kinds;
:func:`save_ensemble` writes one from single-network checkpoints (``vid2sim ensemble-predictors``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torch import Tensor, nn

from vid2sim.predictor.model import LabelPredictor, PhysicsPredictor
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import save_torch_atomic

ENSEMBLE_FORMAT = "vid2sim-predictor-ensemble/1"


class PredictorEnsemble(LabelPredictor):
    """The mean of ``members`` (and of each on the mirrored video when ``mirror``); module docstring.

    Raises:
        ValueError: no members, or members that read another input (image size, frame count, framing) or
            predict another last layer than the first.
    """

    def __init__(self, members: Sequence[PhysicsPredictor], mirror: bool = True) -> None:
        super().__init__()
        if not members:
            raise InputError("PredictorEnsemble needs at least one member")
        first = members[0]
        for i, m in enumerate(members[1:], start=1):
            for what, a, b in (("image size", m.image_size, first.image_size),
                               ("frame count", m.num_frames, first.num_frames),
                               ("framing", m.config.framing, first.config.framing),
                               ("last-layer size", m.config.last_layer_size, first.config.last_layer_size)):
                if a != b:
                    raise InputError(f"ensemble member {i} has {what} {a!r}, member 0 has {b!r}")
        self.members = nn.ModuleList(members)
        self.mirror = bool(mirror)
        self.config = first.config
        self.image_size, self.num_frames = first.image_size, first.num_frames

    def standardise(self, y: dict[str, Tensor]) -> dict[str, Tensor]:
        return self.members[0].standardise(y)

    def unstandardise(self, z: dict[str, Tensor]) -> dict[str, Tensor]:
        return self.members[0].unstandardise(z)

    def label_statistics(self) -> dict[str, dict[str, Tensor]]:
        return self.members[0].label_statistics()

    def forward(self, video: Tensor) -> dict[str, Tensor]:
        """Standardised (member 0's statistics) means: {"log10_E": (B,), "nu": (B,), "last_layer": (B, 650)}
        of ``video`` (B, T, 3, H, W)."""
        sums: dict[str, Tensor] = {}
        counts = {"log10_E": 0, "nu": 0, "last_layer": 0}
        for m in self.members:
            views = (video, video.flip(-1)) if self.mirror else (video,)
            for j, v in enumerate(views):
                y = m.unstandardise(m(v))
                for k in (("log10_E", "nu") if j else ("log10_E", "nu", "last_layer")):
                    sums[k] = y[k] if k not in sums else sums[k] + y[k]
                    counts[k] += 1
        return self.standardise({k: sums[k] / counts[k] for k in sums})


def save_ensemble(checkpoints: Sequence[str | Path], out: str | Path, mirror: bool = True,
                  val_data: str | Path | None = None) -> Path:
    """Write the ensemble of the single-network checkpoints ``checkpoints`` to ``out`` (atomically), their
    weights stored as they are (train-predictor's ``predictor.pt`` is float16).

    ``val_data``: the training-data folder the members were trained on; the ensemble is then scored on their
    common validation split (:func:`~vid2sim.predictor.train.evaluate_predictor`) and the figures stored as
    its ``metrics`` (else None).

    Raises:
        FileNotFoundError / ValueError: a checkpoint is missing, is not a single-network predictor checkpoint,
            or reads another input than the first (see :class:`PredictorEnsemble`); with ``val_data``, members
            held out different validation splits.
    """
    from vid2sim.predictor.train import (
        evaluate_predictor,
        model_from_payload,
        read_checkpoint,
    )

    payloads = []
    for path in checkpoints:
        p = read_checkpoint(path)
        if p["format"] == ENSEMBLE_FORMAT:
            raise InputError(f"{path} is already an ensemble; give its members' checkpoints")
        payloads.append(p)
    PredictorEnsemble([model_from_payload(p) for p in payloads], mirror)  # checks that they fit together
    out = Path(out)
    payload = {"format": ENSEMBLE_FORMAT, "mirror": bool(mirror), "members": payloads, "metrics": None}
    if val_data is not None:
        splits = {(float((p.get("train_config") or {}).get("val_fraction", float("nan"))),
                   int((p.get("train_config") or {}).get("split_seed", -1))) for p in payloads}
        if len(splits) != 1 or -1 in {seed for _, seed in splits}:
            raise InputError(f"the members were trained with different (or unrecorded) validation splits "
                             f"(val_fraction, split_seed): {sorted(splits)}; score the ensemble on a separate "
                             "test set with eval-predictor instead")
        (fraction, seed), = splits
        tmp = out.with_name(f".{out.name}.unscored")
        save_torch_atomic(payload, tmp)
        try:
            figures = evaluate_predictor(tmp, val_data, "val", fraction, seed)
        finally:
            tmp.unlink(missing_ok=True)
        payload["metrics"] = {k: v for k, v in figures.items() if k not in ("checkpoint", "seconds")}
        payload["metrics"]["val_samples"] = figures["samples"]
    save_torch_atomic(payload, out)
    return out
