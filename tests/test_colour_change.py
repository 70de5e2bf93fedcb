"""The user's change learnt as a function of colour (virgi_ns.edit.colour_change), checked against the
hue rule that made the change, applied directly to colours the map never saw."""

from __future__ import annotations

import torch

from virgi_ns.edit.colour_change import EXPLAIN_TOL, MIN_SUPPORT, SPREAD_SHARE, fit_colour_change
from virgi_ns.edit.recolor import RecolorRule, hsv_to_rgb, recolor

RULE = RecolorRule(h0=190, h1=260, shift=120, s_min=0.3, v_min=0.1)


def _colours(n: int, h0: float, h1: float, seed: int) -> torch.Tensor:
    """``n`` colours of hue in [h0, h1] degrees, saturation 0.4-0.9, value 0.3-0.9."""
    g = torch.Generator().manual_seed(seed)
    h = torch.rand(n, generator=g) * (h1 - h0) + h0
    s = torch.rand(n, generator=g) * 0.5 + 0.4
    v = torch.rand(n, generator=g) * 0.6 + 0.3
    return hsv_to_rgb(torch.stack([h, s, v], -1))


def _rule(colours: torch.Tensor) -> torch.Tensor:
    return recolor(colours[None], RULE)[0][0]


def test_the_map_reproduces_the_rule_on_colours_it_never_saw():
    """A photo of blues (changed by the rule) and warm colours (left alone): the map learnt from it
    changes new blues as the rule does and leaves new warm colours, to a few hundredths."""
    photo = torch.cat([_colours(20000, 200, 250, 0), _colours(20000, 0, 60, 1)])
    change = fit_colour_change(photo, _rule(photo))
    blues, warm = _colours(4000, 203, 247, 2), _colours(4000, 3, 57, 3)
    assert float((_rule(blues) - blues).abs().amax(-1).mean()) > 0.3  # the rule moves the blues far
    for new in (blues, warm):
        err = (change.apply(new) - _rule(new)).abs().amax(-1)
        assert float(err.mean()) < 0.02 and float(err.quantile(0.99)) < 0.06, (float(err.mean()), float(err.max()))
    assert bool(change.explains(photo, _rule(photo)).all())


def test_an_edit_that_is_not_one_function_of_colour_is_not_explained():
    """The same blues changed on half of the pixels and left on the other half: the map averages the
    two answers, so it does not explain the changed pixels (the engine then keeps their edited colour)."""
    blues = _colours(10000, 200, 250, 4)
    edited = torch.cat([_rule(blues[:5000]), blues[5000:]])
    explained = fit_colour_change(blues, edited).explains(blues, edited)[:5000]
    size = (edited[:5000] - blues[:5000]).abs().amax(-1)
    # the residual is about half of the change: every change beyond 2.5x the tolerance is refused,
    # and only the smallest changes come near the tolerance
    assert not bool(explained[size > 2.5 * EXPLAIN_TOL].any())
    assert float(explained.float().mean()) < 0.15


def test_colours_the_photo_does_not_show_are_left_alone():
    """Only blues in the photo: greens away from them get no change, whatever the rule would do."""
    blues = _colours(5000, 200, 250, 5)
    change = fit_colour_change(blues, _rule(blues))
    greens = _colours(500, 100, 140, 6)
    assert float(change.support(greens).max()) < MIN_SUPPORT
    torch.testing.assert_close(change.apply(greens), greens)


def test_the_spread_marks_colours_whose_pixels_were_changed_two_ways():
    """Dark greens (changed to blue) and dark browns (kept) share grid cells: between them the map's
    mean change is a blend, and its spread says so; among blues alone it is one change."""
    g = torch.Generator().manual_seed(7)
    n = 4000
    dark_green = torch.tensor([0.06, 0.14, 0.05]) + 0.01 * torch.randn(n, 3, generator=g)
    dark_brown = torch.tensor([0.12, 0.09, 0.05]) + 0.01 * torch.randn(n, 3, generator=g)
    blues = _colours(n, 215, 235, 8)
    photo = torch.cat([dark_green, dark_brown, blues]).clamp(0, 1)
    edited = photo.clone()
    edited[:n] = photo[:n][:, [2, 0, 1]]  # green -> blue: a channel rotation
    edited[2 * n:] = _rule(photo[2 * n:])
    change = fit_colour_change(photo, edited)
    between = torch.tensor([[0.09, 0.115, 0.05]])
    _, _, spread_between = change.lookup(between)
    _, _, spread_blue = change.lookup(_colours(200, 220, 230, 9))
    move = float((edited[:n] - photo[:n]).abs().amax(-1).mean())
    delta_between, _, _ = change.lookup(between)
    assert float(spread_between) > 0.3 * move  # two populations, about half each
    assert float(spread_between) > SPREAD_SHARE * float(delta_between.abs().max())
    assert not bool(change.one_change(between).any())
    # one change, though it varies over the kernel's width (a rotation of hue moves each colour its own way)
    assert bool(change.one_change(_colours(200, 220, 230, 9)).all())
    assert float(spread_blue.max()) < 0.6 * EXPLAIN_TOL


FERN = RecolorRule(h0=60, h1=160, shift=120, s_min=0.12, v_min=0.1)  # leaves -> blue, as the fern's


def test_finer_levels_hold_apart_two_dark_colours_that_share_a_coarse_cell():
    """A hue threshold through dark colours: a dark green (hue ~111, changed) and a dark brown (hue ~22,
    kept) 0.03 apart, inside one cell of the 17 grid. One level mixes them (neither is one change);
    with the 33 and 65 levels each gets its own change: the rule's for the green, none for the brown."""
    g = torch.Generator().manual_seed(11)
    n = 3000
    green = torch.tensor([0.08, 0.11, 0.075]) + 0.002 * torch.randn(n, 3, generator=g)
    brown = torch.tensor([0.11, 0.085, 0.07]) + 0.002 * torch.randn(n, 3, generator=g)
    photo = torch.cat([green, brown])
    edited, mask = recolor(photo, FERN)
    assert bool(mask[:n].all()) and not bool(mask[n:].any())  # the rule splits the two as intended
    probe = torch.tensor([[0.08, 0.11, 0.075], [0.11, 0.085, 0.07]])
    want = recolor(probe, FERN)[0]
    assert float((want[0] - probe[0]).abs().max()) > 0.02  # the green really moves
    coarse = fit_colour_change(photo, edited)
    assert not bool(coarse.one_change(probe).any())
    fine = fit_colour_change(photo, edited, levels=3)
    assert bool(fine.one_change(probe).all())
    torch.testing.assert_close(fine.apply(probe), want, atol=0.005, rtol=0)
    assert bool(fine.explains(photo, edited).all())


def test_a_smooth_hue_rotation_is_one_change_nearly_everywhere():
    """Warm colours all rotated by one rule (no threshold among them): with three levels, new colours of
    that range are one change almost everywhere and get the rule's colour. (One level refuses a few
    per cent, darker colours, where the rotation's own variation over the wide kernel passes the
    spread share: a finer level's kernel sees less of it.)"""
    rule = RecolorRule(h0=0, h1=90, shift=120, s_min=0.1, v_min=0.1)
    photo = _colours(30000, 5, 85, 12)
    edited = recolor(photo, rule)[0]
    new = _colours(3000, 10, 80, 13)
    want = recolor(new, rule)[0]
    coarse, fine = fit_colour_change(photo, edited), fit_colour_change(photo, edited, levels=3)
    assert float(fine.one_change(new).float().mean()) > 0.99
    assert float(fine.one_change(new).float().mean()) >= float(coarse.one_change(new).float().mean())
    err = (fine.apply(new) - want).abs().amax(-1)
    assert float(err.mean()) < 0.02 and float(err.max()) < EXPLAIN_TOL, (float(err.mean()), float(err.max()))


def test_finer_levels_answer_only_where_the_coarse_level_is_not_one_change():
    """Among blues alone (one change at the 17 grid) three levels give the 17 grid's lookup exactly."""
    photo = _colours(20000, 200, 250, 14)
    edited = _rule(photo)
    probe = _colours(2000, 205, 245, 15)
    coarse, fine = fit_colour_change(photo, edited), fit_colour_change(photo, edited, levels=3)
    one = coarse.one_change(probe)
    assert float(one.float().mean()) > 0.97
    for a, b in zip(coarse.lookup(probe[one]), fine.lookup(probe[one])):
        torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_a_tolerance_admits_a_split_change_whose_spread_is_below_it():
    """Pixels of one colour changed by +0.1 in red (60%) or kept (40%): the mean change 0.06 and the
    spread 0.1 sqrt(0.24) = 0.049 exceed the relative test (a quarter of 0.06), so it is not one
    change; with a tolerance of 0.06 it is, with 0.03 it is not."""
    c = torch.tensor([[0.5, 0.3, 0.2]]).expand(1000, 3).clone()
    edited = c.clone()
    edited[:600, 0] += 0.1
    change = fit_colour_change(c, edited)
    delta, _, spread = change.lookup(c[:1])
    assert abs(float(delta[0, 0]) - 0.06) < 1e-4 and abs(float(spread[0]) - 0.1 * 0.24 ** 0.5) < 1e-4
    assert not bool(change.one_change(c[:1])[0])
    for tol, one in ((0.06, True), (0.03, False)):
        mapped, ok = change.apply_where_one_change(c[:1], torch.tensor([tol]))
        assert bool(ok[0]) is one
        torch.testing.assert_close(mapped, (c[:1] + delta).clamp(0, 1))
