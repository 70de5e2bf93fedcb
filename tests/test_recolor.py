"""The HSV recolouring rule against Python's colorsys, pixel by pixel."""

from __future__ import annotations

import colorsys
import math

import pytest
import torch

from virgi_ns.edit.recolor import RecolorRule, hsv_to_rgb, recolor, rgb_to_hsv


def _rule_by_colorsys(rgb, rule: RecolorRule):
    h, s, v = colorsys.rgb_to_hsv(*rgb)
    hd = h * 360.0
    in_hue = (rule.h0 <= hd <= rule.h1) if rule.h0 <= rule.h1 else (hd >= rule.h0 or hd <= rule.h1)
    if not (in_hue and s >= rule.s_min and v >= rule.v_min):
        return rgb, False
    h2 = ((hd + rule.shift) % 360.0) / 360.0
    s2 = min(max(s * rule.sat_scale, 0.0), 1.0)
    return colorsys.hsv_to_rgb(h2, s2, v), True


def test_hsv_round_trip_and_colorsys_agreement():
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(500, 3, generator=g, dtype=torch.float64)
    hsv = rgb_to_hsv(rgb)
    for i in range(0, 500, 7):
        h, s, v = colorsys.rgb_to_hsv(*rgb[i].tolist())
        assert hsv[i, 0].item() == pytest.approx(h * 360.0, abs=1e-9)
        assert hsv[i, 1].item() == pytest.approx(s, abs=1e-12)
        assert hsv[i, 2].item() == pytest.approx(v, abs=1e-12)
    torch.testing.assert_close(hsv_to_rgb(hsv), rgb, atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    "rule",
    [
        RecolorRule(h0=180, h1=260, shift=150, s_min=0.3, v_min=0.1),
        RecolorRule(h0=330, h1=30, shift=120, s_min=0.2, v_min=0.2, sat_scale=0.5),  # wraps through 0
        RecolorRule(h0=60, h1=180, shift=-90, s_min=0.0, v_min=0.0, sat_scale=2.0),
    ],
)
def test_rule_matches_colorsys_per_pixel(rule):
    g = torch.Generator().manual_seed(1)
    img = torch.rand(17, 23, 3, generator=g, dtype=torch.float64)
    img[0, 0] = torch.tensor([1.0, 1.0, 1.0])  # white: never selected with s_min > 0
    img[0, 1] = torch.tensor([0.0, 0.0, 0.0])
    out, mask = recolor(img, rule)
    assert out.shape == img.shape and mask.shape == img.shape[:2]
    n_sel = 0
    for y in range(17):
        for x in range(23):
            exp, sel = _rule_by_colorsys(img[y, x].tolist(), rule)
            assert bool(mask[y, x]) == sel
            n_sel += sel
            assert out[y, x].tolist() == pytest.approx(list(exp), abs=1e-9)
    assert 0 < n_sel < 17 * 23


def test_unselected_pixels_are_bit_identical_and_highlights_untouched():
    rule = RecolorRule(h0=200, h1=250, shift=150, s_min=0.3)
    img = torch.tensor([[[0.1, 0.2, 0.9], [0.95, 0.96, 1.0], [0.8, 0.2, 0.1]]], dtype=torch.float32)
    out, mask = recolor(img, rule)
    assert mask.tolist() == [[True, False, False]]
    assert torch.equal(out[0, 1:], img[0, 1:])
    # blue (hue ~233) + 150 -> ~23 degrees: red dominates
    assert out[0, 0, 0] > out[0, 0, 2] and out[0, 0].max().item() == pytest.approx(0.9, abs=1e-6)


def test_bad_rule_values():
    with pytest.raises(ValueError):
        RecolorRule(h0=-5, h1=20, shift=10)
    with pytest.raises(ValueError):
        RecolorRule(h0=5, h1=20, shift=10, sat_scale=-1)
    with pytest.raises(ValueError):
        recolor(torch.zeros(4, 4, 4), RecolorRule(0, 10, 5))


def test_region_colour_error_against_hand_computed_figures():
    """The recoloured region's colour error: the circular mean hue across 0 degrees, and the mean
    saturation and value, each against figures computed by hand; pixels outside the mask never count."""
    from virgi_ns.bench.recolor import region_colour_error

    hsv = torch.tensor([[[350.0, 0.8, 0.6], [10.0, 0.6, 0.8], [120.0, 1.0, 1.0]]])  # one row of three pixels
    truth_hsv = torch.tensor([[[20.0, 0.9, 0.9], [40.0, 0.9, 0.9], [240.0, 0.0, 0.0]]])
    mask = torch.tensor([[True, True, False]])
    got = region_colour_error(hsv_to_rgb(hsv), hsv_to_rgb(truth_hsv), mask)
    # circular means: 0 degrees (350 and 10), 30 degrees (20 and 40): 0 - 30 = -30
    assert abs(got["region_hue_error_deg"] + 30.0) < 1e-4
    assert abs(got["region_saturation_error"] - (0.7 - 0.9)) < 1e-5
    assert abs(got["region_value_error"] - (0.7 - 0.9)) < 1e-5
    # across the wrap the other way: 10 against 350 is +20
    one = torch.tensor([[True, False, False]])
    got = region_colour_error(hsv_to_rgb(torch.tensor([[[10.0, 1.0, 1.0]] * 3])),
                              hsv_to_rgb(torch.tensor([[[350.0, 1.0, 1.0]] * 3])), one)
    assert abs(got["region_hue_error_deg"] - 20.0) < 1e-4
    assert all(math.isnan(v) for v in region_colour_error(hsv_to_rgb(hsv), hsv_to_rgb(hsv),
                                                           torch.zeros(1, 3, dtype=torch.bool)).values())


def test_the_chroma_weighted_hue_follows_the_colourful_pixels():
    """By hand: a saturated pixel (chroma 0.8) at hue 100 and a near-grey one (chroma 0.02) at hue 300, against
    both at 100. Every pixel alike, the image's mean hue is the circular mean of 100 and 300, 20 degrees, so
    the error is -80; weighted by chroma it is atan2(0.8 sin 100 + 0.02 sin 300, 0.8 cos 100 + 0.02 cos 300),
    about a degree from 100."""
    from virgi_ns.bench.recolor import region_colour_error

    image = hsv_to_rgb(torch.tensor([[[100.0, 0.8, 1.0], [300.0, 0.04, 0.5]]]))
    truth = hsv_to_rgb(torch.tensor([[[100.0, 0.8, 1.0], [100.0, 0.04, 0.5]]]))
    got = region_colour_error(image, truth, torch.ones(1, 2, dtype=torch.bool))
    rad = math.radians
    weighted = math.degrees(math.atan2(0.8 * math.sin(rad(100)) + 0.02 * math.sin(rad(300)),
                                       0.8 * math.cos(rad(100)) + 0.02 * math.cos(rad(300))))
    assert abs(got["region_chroma_hue_error_deg"] - (weighted - 100.0)) < 1e-3
    assert abs(got["region_hue_error_deg"] + 80.0) < 1e-3
    assert abs(got["region_chroma_hue_error_deg"]) < 2.0


def test_edit_figures_against_hand_computed_psnr():
    """The bench's per-view figures on a hand-made case: a 4-pixel view whose left half the rule
    recolours; the edit is exact inside the mask and off by 0.1 on one pixel outside it, so the miss is
    perfect, the leak and the propagation are the PSNR of that error over 2 and over 4 pixels."""
    from virgi_ns.bench.recolor import edit_figures

    rule = RecolorRule(0.0, 30.0, 120.0, 0.25, 0.1)
    base = torch.tensor([[[0.8, 0.1, 0.1], [0.8, 0.1, 0.1], [0.2, 0.2, 0.9], [0.2, 0.2, 0.9]]])
    truth, mask = recolor(base, rule)
    assert mask.tolist() == [[True, True, False, False]]
    after = truth.clone()
    after[0, 3, 0] += 0.1
    photo = base.clone()
    photo[0, 2] += 0.05  # the unedited render's error: one pixel, all three channels
    got = edit_figures(after, base, photo, truth, recolor(photo, rule)[0], mask)
    assert got["miss_psnr"] >= 119.0  # exact (the PSNR's floor of 1e-12)
    assert abs(got["leak_psnr"] - -10.0 * math.log10(0.01 / 6)) < 1e-3  # one channel off of 2 pixels x 3
    assert abs(got["propagation_psnr"] - -10.0 * math.log10(0.01 / 12)) < 1e-3
    assert abs(got["unedited_psnr"] - -10.0 * math.log10(3 * 0.0025 / 12)) < 1e-3
    assert got["mask_fraction"] == 0.5
