"""``comparison_image``: the target | render | error picture that ``fit-gaussians`` writes."""

import numpy as np
import pytest
import torch

from vid2sim.splats.preview import LABEL_HEIGHT, comparison_image


def _pair(v=2, h=12, w=10):
    g = torch.Generator().manual_seed(0)
    targets = torch.rand(v, h, w, 3, generator=g)
    renders = (targets + 0.1 * torch.randn(v, h, w, 3, generator=g)).clamp(0, 1)
    return targets, renders


def test_panels_are_target_render_and_amplified_error():
    targets, renders = _pair()
    picture = comparison_image(targets, renders, error_gain=4.0, headings=False)
    assert picture.dtype == np.uint8 and picture.shape == (2 * 12, 3 * 10, 3)
    as_float = torch.from_numpy(picture).float() / 255
    row1 = as_float[12:24]
    assert torch.allclose(row1[:, :10], targets[1], atol=0.5 / 255 + 1e-6)
    assert torch.allclose(row1[:, 10:20], renders[1], atol=0.5 / 255 + 1e-6)
    error = ((renders[1] - targets[1]).abs().mean(-1) * 4.0).clamp(0, 1)
    assert torch.allclose(row1[:, 20:, 0], error, atol=0.5 / 255 + 1e-6)
    assert torch.equal(row1[:, 20:, 0], row1[:, 20:, 2])  # grey


def test_identical_images_give_a_black_error_panel():
    targets, _ = _pair()
    picture = comparison_image(targets, targets, headings=False)
    assert int(picture[:, 20:].max()) == 0


def test_large_panels_are_averaged_down_in_whole_blocks():
    targets, renders = _pair(v=3, h=45, w=31)
    picture = comparison_image(
        targets, renders, max_size=20, headings=False
    )  # factor ceil(45 / 20) = 3 → 15 × 10 panels
    assert picture.shape == (3 * 15, 3 * 10, 3)
    block = targets[2, 6:9, 3:6].mean(dim=(0, 1))  # panel pixel (2, 1) of view 2
    assert torch.allclose(torch.from_numpy(picture[2 * 15 + 2, 1]).float() / 255, block, atol=0.5 / 255 + 1e-6)
    render_block = renders[0, 0:3, 27:30].mean(dim=(0, 1))  # the render panel's last column starts at 10
    assert torch.allclose(torch.from_numpy(picture[0, 10 + 9]).float() / 255, render_block, atol=0.5 / 255 + 1e-6)


def test_labels_get_a_strip_above_their_row_and_leave_the_panels_alone():
    targets, renders = _pair(h=30, w=60)
    plain = comparison_image(targets, renders, headings=False)
    labelled = comparison_image(targets, renders, labels=["view 0", "view 1 (held out): 30.0 dB"], headings=False)
    row = LABEL_HEIGHT + 30
    assert labelled.shape == (2 * row, 180, 3)
    for v in range(2):
        assert np.array_equal(labelled[v * row + LABEL_HEIGHT : (v + 1) * row], plain[v * 30 : (v + 1) * 30])
        strip = labelled[v * row : v * row + LABEL_HEIGHT]
        assert strip.max() > 200 and (strip == 0).mean() > 0.5  # white text on black
    # the longer label reaches further right
    assert np.argwhere(labelled[row : row + LABEL_HEIGHT].any(-1))[:, 1].max() > \
        np.argwhere(labelled[:LABEL_HEIGHT].any(-1))[:, 1].max()


@pytest.mark.parametrize(
    "targets, renders, kwargs, message",
    [
        (torch.zeros(2, 4, 4), torch.zeros(2, 4, 4), {}, r"targets must have shape \(V, H, W, 3\)"),
        (torch.zeros(2, 4, 4, 3), torch.zeros(2, 4, 5, 3), {}, "they must match"),
        (torch.zeros(2, 4, 4, 3), torch.zeros(2, 4, 4, 3), {"labels": ["a"]}, "1 labels for 2 views"),
        (torch.zeros(2, 4, 4, 3), torch.zeros(2, 4, 4, 3), {"max_size": 0}, "max_size must be"),
    ],
)
def test_bad_input_is_named(targets, renders, kwargs, message):
    with pytest.raises(ValueError, match=message):
        comparison_image(targets, renders, **kwargs)


def test_headings_name_the_three_columns_on_top():
    targets, renders = _pair(h=30, w=80)
    plain = comparison_image(targets, renders, headings=False)
    headed = comparison_image(targets, renders)
    assert headed.shape == (LABEL_HEIGHT + 2 * 30, 240, 3)
    assert np.array_equal(headed[LABEL_HEIGHT:], plain)
    strip = headed[:LABEL_HEIGHT]
    for column in range(3):  # text starts in each column's strip
        assert strip[:, column * 80 : column * 80 + 40].max() > 200
