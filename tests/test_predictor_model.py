"""The Stage I predictor: the VideoMAE network and its heads, the loss, position-table interpolation for a
user's checkpoint of another size, checkpoints (save/load/resume), training on a tiny generated dataset,
inference time, the shipped checkpoint, and the scene-side helpers (front view, frame resampling)."""

from __future__ import annotations

import importlib
import json
import os

import pytest
import torch
from torch import nn

importlib.import_module("transformers")  # a declared test dependency: a broken install fails

from vid2sim.cli import main  # noqa: E402
from vid2sim.predictor.model import (  # noqa: E402
    LossWeights,
    PhysicsPredictor,
    PredictorConfig,
    head_widths,
    interpolate_position_table,
    predictor_loss,
    sinusoid_table,
)
from vid2sim.predictor.predict import (  # noqa: E402
    DEFAULT_PREDICTOR,
    centred_grid,
    frame_for_model,
    front_video,
    object_box,
    object_crop,
    predict_video,
    resample_frames,
)
from vid2sim.predictor.train import (  # noqa: E402
    TrainConfig,
    errors_by_range,
    evaluate_predictor,
    load_predictor,
    read_checkpoint,
    save_predictor,
    train_predictor,
)

TINY_MODEL = dict(image_size=16, num_frames=4, patch_size=8, tubelet_size=2, hidden_size=48, num_layers=1,
                  num_heads=2, intermediate_size=96)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _linears(seq: nn.Sequential) -> list[int]:
    lin = [m for m in seq if isinstance(m, nn.Linear)]
    return [lin[0].in_features] + [m.out_features for m in lin]


def test_heads_follow_the_design_widths_and_use_gelu():
    assert head_widths(768) == [768, 512, 256, 128, 1]  # DESIGN.md's heads at VideoMAE-base width
    m = PhysicsPredictor(PredictorConfig(**TINY_MODEL))
    assert _linears(m.head_E) == head_widths(48) == [48, 32, 16, 8, 1]
    assert _linears(m.head_nu) == [48, 32, 16, 8, 1]
    assert _linears(m.hyper) == [48, 650, 650, 650, 650]
    assert sum(isinstance(x, nn.GELU) for x in m.hyper) == 3 and not isinstance(m.hyper[-1], nn.GELU)


def test_forward_shapes_mean_pooling_and_label_units():
    m = PhysicsPredictor(PredictorConfig(**TINY_MODEL)).eval()
    x = torch.randn(3, 4, 3, 16, 16)
    z = m(x)
    assert z["log10_E"].shape == (3,) and z["nu"].shape == (3,) and z["last_layer"].shape == (3, 650)
    tokens = m.backbone(x, m.position_table)
    assert tokens.shape == (3, 2 * 2 * 2, 48)  # (4/2) x (16/8)^2 tokens
    torch.testing.assert_close(m.features(x), tokens.mean(1))
    stats = {"log10_E": {"mean": torch.tensor(5.0), "std": torch.tensor(0.5)},
             "nu": {"mean": torch.tensor(0.3), "std": torch.tensor(0.1)},
             "last_layer": {"mean": torch.full((650,), 0.01), "std": torch.full((650,), 0.002)}}
    m.set_label_statistics(stats)
    y = m.predict(x[0])
    torch.testing.assert_close(y["log10_E"], 5.0 + 0.5 * m(x[:1])["log10_E"][0])
    torch.testing.assert_close(y["last_layer"], 0.01 + 0.002 * m(x[:1])["last_layer"][0])
    with pytest.raises(ValueError, match="frames of 16x16"):
        m(torch.randn(1, 4, 3, 32, 32))


def test_loss_is_the_issue_formula():
    m = PhysicsPredictor(PredictorConfig(**TINY_MODEL))
    m.set_label_statistics({"log10_E": {"mean": torch.tensor(5.0), "std": torch.tensor(2.0)},
                            "nu": {"mean": torch.tensor(0.3), "std": torch.tensor(0.1)},
                            "last_layer": {"mean": torch.zeros(650), "std": torch.full((650,), 0.5)}})
    z = {"log10_E": torch.tensor([0.5, -1.0]), "nu": torch.tensor([1.0, 0.0]), "last_layer": torch.ones(2, 650)}
    t = {"log10_E": torch.tensor([6.0, 3.0]), "nu": torch.tensor([0.35, 0.3]), "last_layer": torch.zeros(2, 650)}
    loss, parts = predictor_loss(m, z, t)
    # predictions in label units: log10 E = 6, 3 (exact), nu = 0.4, 0.3; last layer standardised: 1 vs 0
    assert parts["log10_E"] == pytest.approx(0.0)
    assert parts["nu"] == pytest.approx(0.5 * 0.05 ** 2)
    assert parts["last_layer"] == pytest.approx(1.0)
    assert float(loss) == pytest.approx(0.0 + 100 * 0.5 * 0.05 ** 2 + 1.0)
    loss2, _ = predictor_loss(m, z, t, LossWeights(log10_E=1, nu=0, last_layer=2))
    assert float(loss2) == pytest.approx(2.0)


def test_errors_by_range_bins_the_true_value():
    true = torch.tensor([4.1, 4.2, 4.6, 5.9, 6.0])
    pred = torch.tensor([4.3, 4.2, 4.5, 5.4, 6.0])
    bins = errors_by_range(pred, true)
    assert [(b["lo"], b["n"]) for b in bins] == [(4.0, 2), (4.5, 1), (5.75, 1), (6.0, 1)]
    assert bins[0]["mae"] == pytest.approx(0.1, abs=1e-6) and bins[0]["bias"] == pytest.approx(0.1, abs=1e-6)
    assert bins[2]["bias"] == pytest.approx(-0.5, abs=1e-6) and errors_by_range(torch.zeros(0), torch.zeros(0)) == []


def test_last_layer_mask_drops_mirrored_samples_from_the_last_layer_term():
    model = PhysicsPredictor(PredictorConfig(**TINY_MODEL))
    torch.manual_seed(0)
    z = {"log10_E": torch.randn(4), "nu": torch.randn(4), "last_layer": torch.randn(4, 650)}
    t = {"log10_E": torch.randn(4), "nu": torch.rand(4), "last_layer": torch.randn(4, 650)}
    _, full = predictor_loss(model, z, t)
    keep = torch.tensor([True, False, True, False])
    _, part = predictor_loss(model, z, t, last_layer_mask=keep)
    sub = {k: v[keep] for k, v in z.items()}, {k: v[keep] for k, v in t.items()}
    _, ref = predictor_loss(model, *sub)
    assert part["last_layer"] == pytest.approx(ref["last_layer"]) and part["log10_E"] == pytest.approx(full["log10_E"])
    loss, none = predictor_loss(model, z, t, last_layer_mask=torch.zeros(4, dtype=torch.bool))
    assert none["last_layer"] == 0.0 and loss.item() == pytest.approx(none["log10_E"] + 100 * none["nu"], rel=1e-5)


def test_position_table_matches_transformers_and_interpolates():
    from transformers.models.videomae.modeling_videomae import (
        get_sinusoid_encoding_table,
    )

    torch.testing.assert_close(sinusoid_table(40, 24)[None], get_sinusoid_encoding_table(40, 24))
    table = torch.randn(2 * 3 * 3, 5)
    assert torch.equal(interpolate_position_table(table, (2, 3, 3), (2, 3, 3))[0], table)
    up = interpolate_position_table(table, (2, 3, 3), (4, 6, 6))
    assert up.shape == (1, 4 * 6 * 6, 5)
    # a table linear in (t, row, col) stays linear: trilinear resampling of a linear field at the new centres
    g = torch.stack(torch.meshgrid(torch.arange(2.0), torch.arange(3.0), torch.arange(3.0), indexing="ij"), -1)
    lin = (g @ torch.tensor([1.0, 10.0, 100.0])).reshape(-1, 1)
    out = interpolate_position_table(lin, (2, 3, 3), (2, 3, 3 * 2)).reshape(2, 3, 6)
    # along columns, new centre j maps to old coordinate (j + 0.5)/2 - 0.5, clamped to [0, 2]
    cols = ((torch.arange(6.0) + 0.5) / 2 - 0.5).clamp(0, 2)
    torch.testing.assert_close(out[1, 2], 1 + 20 + 100 * cols)
    with pytest.raises(ValueError, match="rows"):
        interpolate_position_table(table, (2, 3, 4), (2, 3, 3))


@pytest.mark.parametrize("mean_pooling", [True, False])
def test_backbone_is_transformers_videomae_to_float_precision(mean_pooling):
    """Our encoder and ``transformers.VideoMAEModel`` share parameter names, outputs and gradients."""
    from transformers import VideoMAEConfig, VideoMAEModel

    from vid2sim.predictor.videomae import VideoMAEBackbone

    torch.manual_seed(5)
    ref = VideoMAEModel(VideoMAEConfig(image_size=16, num_frames=4, patch_size=8, tubelet_size=2, hidden_size=24,
                                       num_hidden_layers=2, num_attention_heads=3, intermediate_size=40,
                                       use_mean_pooling=mean_pooling))
    for p in ref.parameters():  # not the initial zeros / ones: every parameter matters
        p.data.normal_(0, 0.3)
    ours = VideoMAEBackbone(ref.config.to_dict())
    assert ours.config.to_dict()["model_type"] == "videomae"
    ours.load_state_dict(ref.state_dict())  # strict: the same names and shapes
    table = torch.randn(1, 2 * 2 * 2, 24)
    ref.embeddings.position_embeddings = table
    x = torch.randn(3, 4, 3, 16, 16, requires_grad=True)
    a = ours(x, table)
    b = ref(pixel_values=x).last_hidden_state
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    w = torch.randn_like(a)
    (ga,) = torch.autograd.grad((a * w).sum(), x)
    (gb,) = torch.autograd.grad((b * w).sum(), x)
    torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="video must be"):
        ours(torch.randn(1, 4, 3, 8, 8), table)
    with pytest.raises(ValueError, match="position table"):
        ours(x, table[:, :4])


def test_using_the_shipped_predictor_does_not_import_transformers():
    """Loading and running a predictor needs neither transformers nor its import (seconds; docs/predictor.md)."""
    import subprocess
    import sys

    code = ("import sys, torch\n"
            "from vid2sim.predictor.predict import DEFAULT_PREDICTOR, predict_video\n"
            "from vid2sim.predictor.train import load_predictor\n"
            "m = load_predictor(DEFAULT_PREDICTOR)\n"
            "out = predict_video(m, torch.rand(16, 3, 64, 64))\n"
            "assert 0 <= out['nu'] <= 0.49, out\n"
            "print(sorted(k for k in sys.modules if k.split('.')[0] == 'transformers'))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_user_checkpoint_of_another_size_is_loaded_locally_with_interpolated_positions(tmp_path):
    from transformers import VideoMAEConfig, VideoMAEModel

    torch.manual_seed(3)
    src = VideoMAEModel(VideoMAEConfig(image_size=32, num_frames=4, patch_size=8, tubelet_size=2, hidden_size=48,
                                       num_hidden_layers=1, num_attention_heads=2, intermediate_size=96))
    src.save_pretrained(tmp_path / "videomae")
    cfg = PredictorConfig(image_size=16, num_frames=8, pretrained=str(tmp_path / "videomae"))
    m = PhysicsPredictor(cfg)
    assert m.width == 48 and m.image_size == 16 and m.num_frames == 8
    # the pre-trained weights are there (the patch projection does not depend on the input size)
    torch.testing.assert_close(m.backbone.embeddings.patch_embeddings.projection.weight,
                               src.embeddings.patch_embeddings.projection.weight)
    torch.testing.assert_close(m.backbone.encoder.layer[0].attention.attention.query.weight,
                               src.encoder.layer[0].attention.attention.query.weight)
    # the position table: the checkpoint's (2, 4, 4) grid resampled to (4, 2, 2)
    expected = interpolate_position_table(src.embeddings.position_embeddings[0], (2, 4, 4), (4, 2, 2))
    torch.testing.assert_close(m.position_table, expected)
    assert m(torch.randn(2, 8, 3, 16, 16))["last_layer"].shape == (2, 650)
    # the same size: the table is the checkpoint's own
    same = PhysicsPredictor(PredictorConfig(image_size=32, num_frames=4, pretrained=str(tmp_path / "videomae")))
    torch.testing.assert_close(same.position_table, src.embeddings.position_embeddings)
    # local only: a model id absent from the cache is an error, not a download
    with pytest.raises(OSError):
        PhysicsPredictor(PredictorConfig(pretrained="vid2sim-test/no-such-videomae"))
    # and a checkpoint of it reloads without the original folder, table included
    save_predictor(m, tmp_path / "p.pt")
    (tmp_path / "videomae" / "config.json").unlink()
    back = load_predictor(tmp_path / "p.pt")
    torch.testing.assert_close(back.position_table, expected)
    x = torch.randn(1, 8, 3, 16, 16)
    torch.testing.assert_close(back(x)["nu"], m.eval()(x)["nu"])


def test_checkpoint_round_trip_and_fp16(tmp_path):
    m = PhysicsPredictor(PredictorConfig(**TINY_MODEL)).eval()
    m.label_mean_log10_E.fill_(5.0)
    x = torch.randn(2, 4, 3, 16, 16)
    save_predictor(m, tmp_path / "a.pt", metrics={"mae_log10_E": 0.1})
    back = load_predictor(tmp_path / "a.pt")
    for k, v in m.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k
    assert back.metrics == {"mae_log10_E": 0.1}
    save_predictor(m, tmp_path / "h.pt", half=True)
    payload = read_checkpoint(tmp_path / "h.pt")
    assert payload["state_dict"]["hyper.0.weight"].dtype == torch.float16
    assert payload["state_dict"]["label_mean_log10_E"].dtype == torch.float32  # statistics stay exact
    half = load_predictor(tmp_path / "h.pt")
    torch.testing.assert_close(half(x)["log10_E"], m(x)["log10_E"], atol=2e-2, rtol=0)
    (tmp_path / "bad.pt").write_bytes(b"nope")
    with pytest.raises(Exception):
        load_predictor(tmp_path / "bad.pt")
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_predictor(tmp_path / "missing.pt")


def test_training_decreases_the_loss_resumes_exactly_and_logs_baselines(tiny_training_data, tmp_path, capsys):
    model = PredictorConfig(**TINY_MODEL)
    cfg = TrainConfig(model=model, steps=40, batch_size=4, lr=1e-3, warmup=2, eval_every=20, val_fraction=0.2,
                      split_seed=4)  # seed 4 holds out one of the five objects
    rec = train_predictor(tiny_training_data, tmp_path / "a", cfg, progress=False)
    curve = [r["loss"] for r in rec["train_curve"]]
    assert rec["complete"] and rec["steps_done"] == 40 and len(curve) == 2
    assert curve[-1] < curve[0]
    log = json.loads((tmp_path / "a" / "train_log.json").read_text())
    assert log["data"]["val_samples"] + log["data"]["train_samples"] == 10 and log["data"]["val_samples"] > 0
    base = log["baselines_constant_mean"]
    assert base["mae_log10_E"] > 0 and base["mae_nu"] > 0
    assert {"mae_log10_E", "mae_nu", "mse_last_layer_std", "loss"} <= set(log["val_curve"][-1])
    for name in ("best.pt", "last.pt", "predictor.pt"):
        assert (tmp_path / "a" / name).is_file()
    assert read_checkpoint(tmp_path / "a" / "predictor.pt")["state_dict"]["hyper.0.weight"].dtype == torch.float16
    # scoring the shipped-format checkpoint on the held-out objects gives the log's best figures and baselines
    held_out = evaluate_predictor(
        tmp_path / "a" / "predictor.pt", tiny_training_data, "val", val_fraction=0.2, split_seed=4
    )
    assert held_out["samples"] == log["data"]["val_samples"]
    assert held_out["mae_log10_E"] == pytest.approx(rec["best"]["mae_log10_E"], rel=0.02, abs=1e-3)
    for k in ("mae_log10_E", "mae_nu", "mse_last_layer_std"):
        assert held_out[f"baseline_{k}"] == pytest.approx(base[k], rel=1e-4), k
    assert main(["eval-predictor", str(tmp_path / "a" / "predictor.pt"), str(tiny_training_data), "--json",
                 str(tmp_path / "e.json"), "--threads", "1"]) == 0
    scored = json.loads((tmp_path / "e.json").read_text())
    assert scored["samples"] == 10 and sum(b["n"] for b in scored["by_log10_E"]) == 10
    for bad, message in (([str(tmp_path / "none.pt"), str(tiny_training_data)], "no such predictor checkpoint"),
                         ([str(tmp_path / "a" / "predictor.pt"), str(tmp_path)], "no index.json")):
        assert main(["eval-predictor", *bad]) == 2
        assert message in capsys.readouterr().err
    # resume: 20 steps in one call, 20 more in a second = 40 at once, bit for bit
    first = train_predictor(tiny_training_data, tmp_path / "b", cfg, progress=False, stop_at_step=20)
    assert first["steps_done"] == 20 and not first["complete"]
    second = train_predictor(tiny_training_data, tmp_path / "b", cfg, progress=False)
    assert second["steps_done"] == 40 and second["complete"]
    a = read_checkpoint(tmp_path / "a" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "b" / "last.pt")["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert second["val_curve"][-1]["mae_log10_E"] == pytest.approx(rec["val_curve"][-1]["mae_log10_E"])
    with pytest.raises(ValueError, match="other training settings"):
        train_predictor(tiny_training_data, tmp_path / "b", TrainConfig(**{**cfg.__dict__, "lr": 5e-4}), progress=False)


def test_colour_permutation_keeps_labels_and_is_deterministic(tiny_training_data, tmp_path):
    from vid2sim.predictor.train import Split, normalise_video, random_channel_orders

    orders = random_channel_orders(600, torch.Generator().manual_seed(0))
    assert (orders.sort(dim=1).values == torch.arange(3)).all()  # every row a permutation
    assert len({tuple(o) for o in orders.tolist()}) == 6  # all six orders drawn
    split = Split.__new__(Split)
    split.videos = torch.randint(0, 256, (3, 2, 3, 4, 4), dtype=torch.uint8)
    split.targets = {"log10_E": torch.arange(3.0), "nu": torch.arange(3.0), "last_layer": torch.zeros(3, 650)}
    idx = torch.tensor([2, 0])
    order = torch.tensor([[2, 0, 1], [0, 1, 2]])
    permuted, targets = split.batch(idx, order)
    plain, same = split.batch(idx)
    torch.testing.assert_close(permuted[1], plain[1])
    torch.testing.assert_close(permuted[0], normalise_video(split.videos[2][:, [2, 0, 1]]))
    assert all(torch.equal(targets[k], same[k]) for k in targets)  # labels unchanged
    cfg = TrainConfig(model=PredictorConfig(**TINY_MODEL), steps=4, batch_size=4, lr=1e-3, warmup=1, eval_every=4,
                      val_fraction=0.2, split_seed=4, colour_permute=True)
    a = train_predictor(tiny_training_data, tmp_path / "a", cfg, progress=False)
    b = train_predictor(tiny_training_data, tmp_path / "b", cfg, progress=False)
    c = train_predictor(tiny_training_data, tmp_path / "c", TrainConfig(**{**cfg.__dict__, "colour_permute": False}),
                        progress=False)
    assert a["train_curve"] == b["train_curve"] and a["train_curve"] != c["train_curve"]
    assert a["config"]["colour_permute"] is True


def test_inference_on_one_video_answers_in_range():
    """(Its speed is a benchmark figure, docs/predictor.md, not a test.)"""
    m = PhysicsPredictor(PredictorConfig()).eval()  # the default (shipped) architecture
    x = torch.randn(16, 3, 64, 64)
    out = predict_video(m, x)
    assert out["last_layer"].shape == (650,) and 0.0 <= out["nu"] <= 0.49
    assert out["E"] == pytest.approx(10 ** out["log10_E"])


@pytest.mark.skipif(not DEFAULT_PREDICTOR.is_file(), reason="no shipped predictor checkpoint")
def test_shipped_checkpoint_is_small_and_beats_the_constant_baseline():
    assert DEFAULT_PREDICTOR.stat().st_size <= 20 * 2 ** 20
    m = load_predictor(DEFAULT_PREDICTOR)
    assert m.image_size == 64 and m.num_frames == 16 and m.config.framing == "object"
    met = m.metrics
    assert met["mae_log10_E"] < met["baseline_mae_log10_E"] and met["mae_nu"] < met["baseline_mae_nu"]


def test_scene_side_helpers():
    from vid2sim.splats.cameras import camera_ring

    imgs = torch.arange(5.0).view(5, 1, 1, 1).expand(5, 4, 4, 3)
    frames, padded = resample_frames(imgs, 0.025, 0.05, 4)  # a scene at twice the frame rate
    assert frames[:, 0, 0, 0].tolist() == [0, 2, 4, 4] and padded == 1
    frames, padded = resample_frames(imgs, 0.05, 0.05, 3)
    assert frames[:, 0, 0, 0].tolist() == [0, 1, 2] and padded == 0
    cams = camera_ring(4, 2.4, 20.0, 32, 32, target=(0.0, 0.0, -0.4), azimuth_offset_deg=90.0)  # 90, 180, 270, 0
    video = torch.rand(4, 6, 32, 32, 3)
    x, view, padded = front_video(video, cams, 0.05, 16, num_frames=4)
    assert view == 3 and padded == 0 and x.shape == (4, 3, 16, 16)
    assert centred_grid((4.0, 4.5, 5.0, 5.5, 6.0), 5.8) == pytest.approx((4.8, 5.3, 5.8, 6.3, 6.8))


def _moving_square(side: int, scale: float, offset: tuple[int, int], frames: int = 6) -> torch.Tensor:
    """White (T, side, side, 3) frames with a dark square falling and widening, drawn at ``scale`` and moved by
    ``offset``: the same motion seen by a closer or farther camera."""
    video = torch.ones(frames, side, side, 3)
    for t in range(frames):
        y0, x0, h, w = 4 + 3 * t, 10, 8, 8 + t  # pixels at scale 1
        r0, c0 = offset[0] + round(scale * y0), offset[1] + round(scale * x0)
        video[t, r0:r0 + round(scale * h), c0:c0 + round(scale * w)] = torch.tensor([0.2, 0.3, 0.6])
    return video


def test_object_framing_crops_the_motion_and_undoes_the_camera_distance():
    near = _moving_square(96, 2.0, (2, 4))
    far = _moving_square(96, 1.0, (40, 50))  # half the size elsewhere in the frame
    top, left, side = object_box(far)
    # the motion covers rows 44..66 and columns 60..72 of the far view: a 23-pixel square widened by 10 % a side
    assert side == round(23 * 1.2) and top == (44 + 67 - side) // 2 and left == (60 + 73 - side) // 2
    crop = object_crop(far)
    assert crop.shape == (6, side, side, 3)
    assert torch.equal(crop[:, 1:-1, 1:-1], far[:, top + 1:top + side - 1, left + 1:left + side - 1])
    a, b = frame_for_model(near, 32), frame_for_model(far, 32)
    full = (frame_for_model(near, 32, "full") - frame_for_model(far, 32, "full")).abs().mean()
    assert (a - b).abs().mean() < 0.35 * full  # what is left is the far view's pixel rounding
    edge = object_crop(_moving_square(40, 1.0, (-2, 26)))  # the motion touches the image's top and right edges
    assert edge.shape[1] == edge.shape[2] and (edge[:, 0] == 1).all() and (edge[:, :, -1] == 1).all()
    with pytest.raises(ValueError, match="no object"):
        object_box(torch.ones(3, 8, 8, 3))
    with pytest.raises(ValueError, match="framing"):
        frame_for_model(near, 32, "zoom")
    with pytest.raises(ValueError, match="framing"):
        PredictorConfig(framing="zoom")


def test_checkpoints_without_framing_load_as_full_frame(tmp_path):
    model = PhysicsPredictor(PredictorConfig(**TINY_MODEL, framing="full"))
    path = save_predictor(model, tmp_path / "old.pt")
    payload = torch.load(path, weights_only=True)
    payload["config"].pop("framing")  # as written before framing existed
    torch.save(payload, path)
    assert load_predictor(path).config.framing == "full"
    assert PredictorConfig().framing == "object"


def test_training_split_holds_each_video_as_the_model_sees_it(tiny_training_data):
    """The in-memory split (filled in place, freed memory trimmed as it loads) holds every sample's frames
    exactly as `frame_for_model` gives them, rounded to uint8, and its labels."""
    from vid2sim.predictor.dataset import IMAGENET_MEAN, IMAGENET_STD, TrainingData
    from vid2sim.predictor.predict import frame_for_model
    from vid2sim.predictor.train import Split, release_freed_memory

    data = TrainingData(tiny_training_data, "all")
    split = Split(data, 8, "object")
    assert split.videos.shape == (len(data), 4, 3, 8, 8) and split.videos.dtype == torch.uint8
    mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    for i in range(len(data)):
        v, t = data[i]
        u = frame_for_model((v * std + mean).permute(0, 2, 3, 1), 8, "object") * std + mean
        assert torch.equal(split.videos[i], (u * 255).round().clamp(0, 255).to(torch.uint8))
        assert float(split.targets["log10_E"][i]) == float(t["log10_E"])
    release_freed_memory()  # callable any time (a no-op off glibc)


def test_decoded_split_is_cached_and_remade_when_its_source_changes(tiny_training_data, tmp_path, monkeypatch):
    """`Split.cached` decodes once into a file that later runs read back memory-mapped, equal to a fresh decode;
    another size (or other shards) decodes again and replaces the file."""
    from vid2sim.predictor.dataset import TrainingData
    from vid2sim.predictor.train import Split

    data = TrainingData(tiny_training_data, "all")
    path = tmp_path / "split.pt"
    first = Split.cached(data, 8, "object", path)
    assert path.is_file()
    decodes = []
    original = Split.__init__
    monkeypatch.setattr(Split, "__init__", lambda self, *a, **k: (decodes.append(a), original(self, *a, **k))[1])
    again = Split.cached(data, 8, "object", path)
    assert decodes == []  # read back, not decoded
    assert torch.equal(again.videos, first.videos)
    for k in first.targets:
        assert torch.equal(again.targets[k], first.targets[k])
    other = Split.cached(data, 16, "object", path)
    assert len(decodes) == 1 and other.videos.shape[-1] == 16
    assert Split.cached(TrainingData(tiny_training_data, "train", 0.2, 4), 16, "object", path).videos.shape[0] < len(
        data
    )
    assert len(decodes) == 2
    path.write_bytes(b"not a torch file")  # torn: decoded again
    assert torch.equal(Split.cached(data, 8, "object", path).videos, first.videos) and len(decodes) == 3


def _tiny_member(seed: int, log_e_mean: float) -> PhysicsPredictor:
    m = PhysicsPredictor(PredictorConfig(**TINY_MODEL, seed=seed)).eval()
    m.label_mean_log10_E.fill_(log_e_mean)
    m.label_std_log10_E.fill_(0.5)
    return m


def test_ensemble_averages_members_and_mirror_images_but_not_the_mirrored_last_layer():
    from vid2sim.predictor.ensemble import PredictorEnsemble

    a, b = _tiny_member(0, 5.0), _tiny_member(1, 4.5)  # other statistics: the mean is taken in label units
    x = torch.randn(2, 4, 3, 16, 16)
    with torch.no_grad():
        ys = [m.unstandardise(m(v)) for m in (a, b) for v in (x, x.flip(-1))]
        ens = PredictorEnsemble([a, b], mirror=True)
        y = ens.unstandardise(ens(x))
        plain = PredictorEnsemble([a, b], mirror=False)
        yp = plain.unstandardise(plain(x))
    for k in ("log10_E", "nu"):
        torch.testing.assert_close(y[k], sum(v[k] for v in ys) / 4)
        torch.testing.assert_close(yp[k], (ys[0][k] + ys[2][k]) / 2)
    torch.testing.assert_close(y["last_layer"], (ys[0]["last_layer"] + ys[2]["last_layer"]) / 2)
    assert ens.image_size == 16 and ens.num_frames == 4 and ens.label_statistics()["log10_E"]["mean"] == 5.0
    one = predict_video(ens, x[0])
    assert one["log10_E"] == pytest.approx(float(y["log10_E"][0]), abs=1e-5) and 0 <= one["nu"] <= 0.49
    with pytest.raises(ValueError, match="member 1 has frame count 8"):
        PredictorEnsemble([a, PhysicsPredictor(PredictorConfig(**{**TINY_MODEL, "num_frames": 8}))])
    with pytest.raises(ValueError, match="at least one"):
        PredictorEnsemble([])


def test_ensemble_checkpoint_round_trip_scores_on_the_members_validation_split(tiny_training_data, tmp_path,
                                                                                capsys):
    from vid2sim.predictor.ensemble import ENSEMBLE_FORMAT, PredictorEnsemble

    split = {"val_fraction": 0.2, "split_seed": 4}
    for i in range(2):
        save_predictor(_tiny_member(i, 5.0), tmp_path / f"m{i}.pt", half=True, train_config=split)
    save_predictor(_tiny_member(2, 5.0), tmp_path / "other.pt", train_config={"val_fraction": 0.1, "split_seed": 0})
    members = [str(tmp_path / f"m{i}.pt") for i in range(2)]
    assert main(["ensemble-predictors", str(tmp_path / "e.pt"), *members, "--val-data", str(tiny_training_data),
                 "--threads", "1"]) == 0
    assert "2 networks, mirroring on" in capsys.readouterr().out
    payload = read_checkpoint(tmp_path / "e.pt")
    assert payload["format"] == ENSEMBLE_FORMAT and payload["mirror"] is True and len(payload["members"]) == 2
    ens = load_predictor(tmp_path / "e.pt")
    assert isinstance(ens, PredictorEnsemble) and not ens.training
    direct = PredictorEnsemble([load_predictor(m) for m in members])
    x = torch.randn(1, 4, 3, 16, 16)
    torch.testing.assert_close(ens(x)["log10_E"], direct(x)["log10_E"])
    # the stored figures are the ensemble's on the held-out objects, as eval-predictor scores them
    scored = evaluate_predictor(tmp_path / "e.pt", tiny_training_data, "val", **split)
    assert ens.metrics["mae_log10_E"] == pytest.approx(scored["mae_log10_E"])
    assert ens.metrics["val_samples"] == scored["samples"] > 0
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    for bad, message in (([str(tmp_path / "x.pt"), members[0], str(tmp_path / "other.pt"), "--val-data",
                           str(tiny_training_data)], "different (or unrecorded) validation splits"),
                         ([str(tmp_path / "x.pt"), str(tmp_path / "e.pt")], "already an ensemble"),
                         ([str(tmp_path / "x.pt"), str(tmp_path / "none.pt")], "no such predictor checkpoint")):
        assert main(["ensemble-predictors", *bad]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()
