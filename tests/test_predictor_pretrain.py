"""Masked-autoencoder pre-training of the predictor's backbone (vid2sim.predictor.pretrain): tube masks, the
reconstruction loss falling on real generated videos, exact resume, and its place before the supervised steps."""

from __future__ import annotations

import importlib
import json

import pytest
import torch

importlib.import_module("transformers")  # a declared test dependency: a broken install fails

from vid2sim.cli import main  # noqa: E402
from vid2sim.predictor.dataset import TrainingData  # noqa: E402
from vid2sim.predictor.model import PhysicsPredictor, PredictorConfig  # noqa: E402
from vid2sim.predictor.pretrain import (  # noqa: E402
    PRETRAIN_FILE,
    build_pretraining_model,
    decoder_width,
    pretrain_backbone,
    token_grid,
    tube_mask,
)
from vid2sim.predictor.train import (  # noqa: E402
    Split,
    TrainConfig,
    normalise_video,
    read_checkpoint,
    train_predictor,
)

# 4x4 patches of 16x16 frames: 16 patch positions per tubelet, so a 0.75 mask hides 12 and leaves 4
MODEL = dict(image_size=16, num_frames=4, patch_size=4, tubelet_size=2, hidden_size=48, num_layers=1, num_heads=2,
             intermediate_size=96)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _config(**kw) -> TrainConfig:
    base = dict(model=PredictorConfig(**MODEL), steps=6, batch_size=4, lr=1e-3, warmup=2, eval_every=30,
                val_fraction=0.2, split_seed=4, pretrain_steps=90, pretrain_batch_size=4, pretrain_lr=2e-3,
                pretrain_mask_ratio=0.75, pretrain_decoder_layers=1)
    return TrainConfig(**{**base, **kw})


def test_tube_mask_hides_the_same_positions_in_every_tubelet():
    g = torch.Generator().manual_seed(0)
    m = tube_mask(5, (3, 4, 4), 0.75, g)
    assert m.shape == (5, 48) and m.dtype == torch.bool
    per_time = m.view(5, 3, 16)
    assert torch.equal(per_time[:, 0], per_time[:, 1]) and torch.equal(per_time[:, 0], per_time[:, 2])
    assert (per_time[:, 0].sum(1) == 12).all()
    assert not torch.equal(per_time[0, 0], per_time[1, 0])  # drawn per video
    for ratio in (0.01, 0.99):
        with pytest.raises(ValueError, match="hides"):
            tube_mask(2, (2, 4, 4), ratio, g)
    assert decoder_width(128, 4) == 64 and decoder_width(48, 2) == 24 and decoder_width(6, 6) == 6


def test_pretraining_lowers_the_reconstruction_loss_and_resumes_exactly(tiny_training_data, tmp_path):
    cfg = _config()
    train = Split(TrainingData(tiny_training_data, "train", cfg.val_fraction, cfg.split_seed), 16, "object")
    model = PhysicsPredictor(cfg.model)
    before = {k: v.clone() for k, v in model.backbone.state_dict().items()}
    # the pre-training model's encoder starts as the backbone and uses its position table
    pre = build_pretraining_model(model, 1, 0)
    assert all(torch.equal(v, before[k]) for k, v in pre.videomae.state_dict().items())
    assert pre.videomae.embeddings.position_embeddings is model.position_table
    assert token_grid(model) == (2, 4, 4)

    (tmp_path / "a").mkdir()
    rec = pretrain_backbone(model, train, cfg, tmp_path / "a", progress=False)
    assert rec["complete"] and rec["steps_done"] == 90 and [c["step"] for c in rec["curve"]] == [30, 60, 90]
    assert rec["curve"][-1]["loss"] < rec["curve"][0]["loss"]
    # on the same videos and masks, the trained autoencoder reconstructs the hidden patches far better than at
    # its start
    video = normalise_video(train.videos)
    mask = tube_mask(len(train), (2, 4, 4), 0.75, torch.Generator().manual_seed(99))
    trained = build_pretraining_model(PhysicsPredictor(cfg.model), 1, 0)
    trained.load_state_dict(torch.load(tmp_path / "a" / PRETRAIN_FILE, weights_only=True)["state_dict"])
    with torch.no_grad():
        start, end = (float(m(pixel_values=video, bool_masked_pos=mask).loss) for m in (pre, trained))
    assert end < 0.75 * start
    changed = [k for k, v in model.backbone.state_dict().items() if not torch.equal(v, before[k])]
    assert "encoder.layer.0.attention.attention.query.weight" in changed
    # 30 steps, then the rest in a second call = all 90 at once, bit for bit
    (tmp_path / "b").mkdir()
    other = PhysicsPredictor(cfg.model)
    part = pretrain_backbone(other, train, cfg, tmp_path / "b", progress=False, stop_at_step=30)
    assert part["steps_done"] == 30 and not part["complete"]
    assert all(torch.equal(v, before[k]) for k, v in other.backbone.state_dict().items())  # untouched until done
    done = pretrain_backbone(other, train, cfg, tmp_path / "b", progress=False)
    assert done["complete"] and done["curve"] == rec["curve"]
    for k, v in model.backbone.state_dict().items():
        assert torch.equal(v, other.backbone.state_dict()[k]), k
    with pytest.raises(ValueError, match="other pre-training settings"):
        pretrain_backbone(PhysicsPredictor(cfg.model), train, _config(pretrain_lr=1e-3), tmp_path / "b",
                          progress=False)


def test_train_predictor_pretrains_first_and_a_stopped_pretraining_resumes(tiny_training_data, tmp_path, capsys):
    cfg = _config()
    stopped = train_predictor(tiny_training_data, tmp_path / "r", _config(max_minutes=1e-9), progress=False)
    assert not stopped["complete"] and stopped["steps_done"] == 0 and not stopped["pretrain"]["complete"]
    assert (tmp_path / "r" / PRETRAIN_FILE).is_file() and not (tmp_path / "r" / "last.pt").exists()
    rec = train_predictor(tiny_training_data, tmp_path / "r", cfg, progress=False)
    assert rec["complete"] and rec["steps_done"] == 6
    assert rec["pretrain"]["complete"] and len(rec["pretrain"]["curve"]) == 3
    assert json.loads((tmp_path / "r" / "train_log.json").read_text())["pretrain"]["steps_done"] == 90
    assert read_checkpoint(tmp_path / "r" / "predictor.pt")["train_config"]["pretrain_steps"] == 90
    # the same through the command line, which also takes the loss weights
    args = ["train-predictor", str(tiny_training_data), str(tmp_path / "c"), "--image-size", "16", "--patch-size", "4",
            "--width", "48", "--layers", "1", "--heads", "2", "--steps", "4", "--batch-size", "4",
            "--pretrain-steps", "4", "--pretrain-batch-size", "4", "--pretrain-mask-ratio", "0.75",
            "--loss-weights", "1", "10", "0.1",
            "--val-fraction", "0.2", "--threads", "1", "--quiet"]
    assert main(args) == 0  # the model takes the data's frame count (4)
    log = json.loads((tmp_path / "c" / "train_log.json").read_text())
    assert log["config"]["loss"] == {"log10_E": 1.0, "nu": 10.0, "last_layer": 0.1}
    assert log["pretrain"]["mask_ratio"] == 0.75
    assert log["config"]["model"]["num_frames"] == 4
    for bad, message in ((["--loss-weights", "1", "-1", "1"], "LossWeights.nu"),
                         (["--pretrain-mask-ratio", "1.5"], "pretrain_mask_ratio")):
        assert main(args + bad) == 2
        assert message in capsys.readouterr().err
