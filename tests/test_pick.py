"""Picks (virgi_ns.edit.pick) on the tiny procedural scene of the edit tests: a glossy blue sphere
between a matte green and a matte yellow one, the colour field fitted to their known colours (CPU).

A click on the blue sphere in one view selects it, recolours it and fits the edit; held-out views
are then compared with the objects' known pixels (from the per-Gaussian labels) and with hues and
values computed by Python's ``colorsys``, independently of the code under test."""

from __future__ import annotations

import colorsys
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
import edit_scene as es  # noqa: E402

from virgi_ns.edit.engine import EditEngine  # noqa: E402
from virgi_ns.edit.pick import (PickSession, commit, connected_to, parse_colour, pick_config, recolour,  # noqa: E402
                                select)
from virgi_ns.edit.scene import render_view  # noqa: E402
from virgi_ns.edit.stack import EditStack  # noqa: E402
from virgi_ns.errors import InputError  # noqa: E402
from virgi_ns.raster import Request, composite  # noqa: E402

EDIT_VIEW, HELD_OUT = 0, (1, 7)
RED = "#d02020"
RED_HUE = 360.0 * colorsys.rgb_to_hsv(0xD0 / 255, 0x20 / 255, 0x20 / 255)[0]  # 0 degrees


@pytest.fixture(scope="module")
def world():
    with es.one_thread():
        S = es.build()
        cams = S.cameras
        onehot = torch.nn.functional.one_hot(S.labels, 3).float()
        cover, before = [], []
        for v in range(len(cams)):
            c = S.scene.contributions(cams.index(v), Request.whole_images(cams.index(v)))
            cover.append(composite(onehot[c.pair_gaussian.long()], c)[0])  # per-pixel share of each object
            before.append(render_view(S.scene, cams, v, contrib=c)["rgb"])
        inner = cover[EDIT_VIEW][..., es.BLUE] > 0.95
        ys, xs = torch.nonzero(inner, as_tuple=True)
        k = len(ys) // 2
        pixel = (int(xs[k]), int(ys[k]))  # a pixel well on the blue sphere
        sessions = {}
        for mode in ("hue", "shift", "colour"):
            s = PickSession(S.scene, cams.index(EDIT_VIEW), *pixel, EditStack(S.scene.fingerprint()),
                            pick_config("cpu"))
            sessions[mode] = (s, s.update(parse_colour(RED), 0.2, mode))
        yield {"S": S, "cover": cover, "before": before, "pixel": pixel, "sessions": sessions}


def _hsv(img: torch.Tensor) -> np.ndarray:
    """[..., 3] RGB -> HSV by colorsys (hue in degrees), pixel by pixel."""
    flat = img.detach().reshape(-1, 3).double().numpy()
    out = np.array([colorsys.rgb_to_hsv(*p) for p in flat])
    out[:, 0] *= 360.0
    return out.reshape(*img.shape[:-1], 3)


def _hue_gap(h: np.ndarray, target: float) -> np.ndarray:
    d = np.abs(h - target) % 360.0
    return np.minimum(d, 360.0 - d)


def _after(world, mode: str, v: int) -> torch.Tensor:
    S = world["S"]
    st = EditStack(S.scene.fingerprint())
    st.add(world["sessions"][mode][1])
    return render_view(S.scene, S.cameras, v, st)["rgb"]


def test_the_selection_is_the_clicked_object_whole(world):
    s, _ = world["sessions"]["hue"]
    cov = world["cover"][EDIT_VIEW]
    blue = cov[..., es.BLUE]
    assert bool((blue[s.mask] > 0.5).all())  # nothing of the neighbours
    inner = (blue > 0.9) & (s.maps.accumulation > 0.5)
    assert float(s.mask[inner].float().mean()) > 0.97  # the whole sphere, highlight included
    # a click on the green sphere takes the green one
    ys, xs = torch.nonzero(cov[..., es.GREEN] > 0.95, as_tuple=True)
    green = select(s.maps, int(xs[0]), int(ys[0]), 0.2)
    assert bool((cov[..., es.GREEN][green] > 0.5).all()) and int(green.sum()) > 20
    # the tolerance widens it; by colour and features, at 1 every covered pixel connected to the click joins
    wider = select(s.maps, *world["pixel"], 1.0)
    assert bool(wider[s.mask].all()) and int(wider.sum()) > int(s.mask.sum())
    everything = select(s.maps, *world["pixel"], 1.0, "colour_features")
    assert bool(everything[(cov.sum(-1) > 0.9) & (s.maps.accumulation > 0.5)].all())
    # both criteria take the clicked sphere and none of its neighbours here
    by_features = select(s.maps, *world["pixel"], 0.2, "colour_features")
    assert bool((blue[by_features] > 0.5).all()) and float(by_features[inner].float().mean()) > 0.97


@pytest.mark.parametrize("mode", ("hue", "shift"))
@pytest.mark.parametrize("v", HELD_OUT)
def test_hue_pick_recolours_the_object_in_held_out_views_and_leaves_the_others(world, v, mode):
    cov, before = world["cover"][v], world["before"][v]
    after = _after(world, mode, v)
    blue = cov[..., es.BLUE] > 0.9
    others = (cov[..., es.GREEN] + cov[..., es.YELLOW] > 0.99)
    assert int(blue.sum()) > 50 and int(others.sum()) > 50
    hb, ha = _hsv(before), _hsv(after)
    coloured = blue.numpy() & (ha[..., 1] > 0.3)  # the highlight is near white: no hue to speak of
    assert np.median(_hue_gap(hb[..., 0][coloured], RED_HUE)) > 90  # it was far from red
    assert np.median(_hue_gap(ha[..., 0][coloured], RED_HUE)) < 10, np.median(ha[..., 0][coloured])
    assert float((after - before).abs()[others].mean()) < 0.01


def test_a_collapsed_joint_fit_is_refitted_staged_and_recolours_the_object(world):
    """A joint fit whose segmentation starts dead (its output bias at -30: alpha and every gradient through
    it near 0) leaves the changed pixels where they were; the session fits the selection again ``staged``,
    keeps that fit, and the sphere turns red in a held-out view while the other spheres stay."""
    from virgi_ns.edit.engine import SMALL_PROGRESS, EditConfig

    S = world["S"]
    session = PickSession(S.scene, S.cameras.index(EDIT_VIEW), *world["pixel"], EditStack(S.scene.fingerprint()),
                          EditConfig(seg_init_bias=-30.0))
    joint = session.engine
    edit = session.update(parse_colour(RED), 0.2, "hue")
    info = edit.info["restaged"]
    assert info["joint_progress"] < SMALL_PROGRESS < info["staged_progress"]
    assert session.engine.recipe == "staged" and edit.info["recipe"] == "staged"
    # the refit shares the joint engine's view: the view is not rasterized again
    assert session.engine is not joint and session.engine.contrib is joint.contrib
    assert session.engine.changed_progress() == pytest.approx(info["staged_progress"])
    v = HELD_OUT[0]
    st = EditStack(S.scene.fingerprint())
    st.add(edit)
    after, before, cov = render_view(S.scene, S.cameras, v, st)["rgb"], world["before"][v], world["cover"][v]
    blue, others = cov[..., es.BLUE] > 0.9, cov[..., es.GREEN] + cov[..., es.YELLOW] > 0.99
    ha = _hsv(after)
    coloured = blue.numpy() & (ha[..., 1] > 0.3)
    assert int(coloured.sum()) > 50 and np.median(_hue_gap(ha[..., 0][coloured], RED_HUE)) < 15
    assert float((after - before).abs()[others].mean()) < 0.02


@pytest.mark.gpu
def test_a_collapsed_click_is_refitted_staged_on_the_gpu(world):
    """The same collapse on the GPU, where the staged classifier's steps replay a recorded CUDA graph: the
    refit reaches the colour and its alpha covers the selection."""
    from virgi_ns.edit.engine import SMALL_PROGRESS, EditConfig

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    S = world["S"]
    gpu = es.on_gpu(S.scene)
    session = PickSession(gpu, S.cameras.index(EDIT_VIEW), *world["pixel"], EditStack(gpu.fingerprint()),
                          EditConfig(seg_init_bias=-30.0))
    edit = session.update(parse_colour(RED), 0.2, "hue")
    info = edit.info["restaged"]
    assert info["joint_progress"] < SMALL_PROGRESS and info["staged_progress"] > 0.5
    alpha = session.engine.preview()["alpha"][..., 0]
    assert session.engine.recipe == "staged" and float(alpha[session.mask].mean()) > 0.8


def test_a_fit_that_moves_its_pixels_is_kept_as_it_is(world, monkeypatch):
    """The default pick's joint fits reach their colour: none is refitted (no second engine is built), and
    the session keeps its engine."""
    import virgi_ns.edit.pick as pick

    for session, edit in world["sessions"].values():
        assert "restaged" not in edit.info and session.engine.recipe == "joint"
        assert session.engine.changed_progress() > 0.5
    built = []
    monkeypatch.setattr(pick, "EditEngine", lambda *a, **k: built.append(1) or EditEngine(*a, **k))
    S = world["S"]
    session = PickSession(S.scene, S.cameras.index(EDIT_VIEW), *world["pixel"], EditStack(S.scene.fingerprint()),
                          pick_config("cpu"))
    session.update(parse_colour(RED), 0.2, "hue")
    assert len(built) == 1 and session.engine.recipe == "joint"


def test_a_click_on_the_highlight_recolours_as_a_click_on_the_surface(world):
    """In hue mode the clicked pixel's saturation is the reference; a click on the sphere's near-white
    highlight (its render keeps under half its diffuse colour's saturation) takes the selection's
    median pixel instead, so the sphere is not scaled to full saturation by the highlight's near-zero
    one. A click on the surface keeps its own reference."""
    from virgi_ns.edit.pick import HIGHLIGHT_SATURATION_SHARE, _on_highlight
    from virgi_ns.edit.recolor import rgb_to_hsv

    s, _ = world["sessions"]["hue"]
    m, mask = s.maps, s.mask
    hsv = rgb_to_hsv(m.rgb.clamp(0.0, 1.0))
    sat = torch.where(mask, hsv[..., 1], torch.full_like(hsv[..., 1], 9.0))
    y, x = divmod(int(sat.argmin()), sat.shape[1])
    surface = float(rgb_to_hsv(m.diffuse[y, x].clamp(0.0, 1.0))[1])
    assert float(hsv[y, x, 1]) < HIGHLIGHT_SATURATION_SHARE * surface and float(hsv[y, x, 2]) > 0.8  # a highlight
    assert _on_highlight(hsv, m.diffuse, (x, y)) and not _on_highlight(hsv, m.diffuse, world["pixel"])
    red = parse_colour(RED)
    on_highlight = recolour(m.rgb, mask, red, "hue", m.diffuse, (x, y))
    by_median = recolour(m.rgb, mask, red, "hue", m.diffuse)
    torch.testing.assert_close(on_highlight, by_median, atol=0, rtol=0)
    on_surface = recolour(m.rgb, mask, red, "hue", m.diffuse, world["pixel"])
    px, py = world["pixel"]
    target_sat = float(rgb_to_hsv(torch.tensor(red))[1])
    assert abs(float(rgb_to_hsv(on_surface[py, px])[1]) - target_sat) < 0.02  # the clicked pixel gets the colour's
    assert float(rgb_to_hsv(on_highlight)[..., 1][mask].median()) < 0.97  # not the whole sphere at full saturation


@pytest.mark.parametrize("mode", ("hue", "shift"))
@pytest.mark.parametrize("v", (EDIT_VIEW,) + HELD_OUT)
def test_hue_pick_keeps_the_highlight_and_the_brightness(world, v, mode):
    cov, before = world["cover"][v], world["before"][v]
    after = _after(world, mode, v)
    on_blue = cov[..., es.BLUE] > 0.9
    wb = torch.where(on_blue, before.min(-1).values, torch.zeros(()))
    wa = torch.where(on_blue, after.min(-1).values, torch.zeros(()))
    assert float(wb.max()) > 0.8  # a real near-white highlight
    pb, pa = divmod(int(wb.argmax()), wb.shape[1]), divmod(int(wa.argmax()), wa.shape[1])
    assert abs(pb[0] - pa[0]) <= 1 and abs(pb[1] - pa[1]) <= 1, (pb, pa)
    assert abs(float(wa.max()) - float(wb.max())) < 0.06
    value_gap = np.abs(_hsv(after)[..., 2] - _hsv(before)[..., 2])[on_blue.numpy()]
    # most pixels keep their value; the mean also counts Gaussians the edit view hardly sees
    assert float(np.median(value_gap)) < 0.03 and float(value_gap.mean()) < 0.08, value_gap.mean()


def test_colour_pick_makes_the_colour_the_surface_s_and_keeps_the_highlight(world):
    """``colour``: the selection's diffuse colour becomes the colour itself (its typical pixel, in a
    held-out view too), and the highlight still sits on it, near white, where it was."""
    S = world["S"]
    for v in (EDIT_VIEW,) + HELD_OUT:
        st = EditStack(S.scene.fingerprint())
        st.add(world["sessions"]["colour"][1])
        out = render_view(S.scene, S.cameras, v, st)
        on_blue = world["cover"][v][..., es.BLUE] > 0.9
        typical = out["diffuse"][on_blue].median(0).values
        assert float((typical - torch.tensor(parse_colour(RED))).abs().max()) < 0.08, (v, typical)
        wb = torch.where(on_blue, world["before"][v].min(-1).values, torch.zeros(()))
        wa = torch.where(on_blue, out["rgb"].min(-1).values, torch.zeros(()))
        pb, pa = divmod(int(wb.argmax()), wb.shape[1]), divmod(int(wa.argmax()), wa.shape[1])
        assert abs(pb[0] - pa[0]) <= 1 and abs(pb[1] - pa[1]) <= 1, (v, pb, pa)
        assert float(wa.max()) > 0.7, (v, float(wa.max()))


def _random_selection(seed: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
    """A small random image, a random selection of it, its HSV by colorsys and the selection as numpy."""
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(6, 7, 3, generator=g) * 0.8 + 0.1
    mask = torch.rand(6, 7, generator=g) > 0.4
    return rgb, mask, _hsv(rgb), mask.numpy()


def test_recolour_rules_against_colorsys():
    rgb, mask, hsv, m = _random_selection(0)
    colour = (0.2, 0.7, 0.4)
    th, ts, tv = colorsys.rgb_to_hsv(*colour)
    s_typ, v_typ = np.median(hsv[..., 1][m]), np.median(hsv[..., 2][m])
    want = rgb.double().numpy().copy()
    for y, x in zip(*np.nonzero(m)):
        h, s, v = hsv[y, x]
        want[y, x] = colorsys.hsv_to_rgb(th, min(1.0, s * ts / s_typ), v)
    got = recolour(rgb, mask, colour, "hue")
    np.testing.assert_allclose(got.double().numpy(), want, atol=2e-5)
    want = rgb.double().numpy().copy()
    want[m] = np.clip(np.array(colour)[None] * hsv[..., 2][m][:, None] / v_typ, 0, 1)
    np.testing.assert_allclose(recolour(rgb, mask, colour, "colour").double().numpy(), want, atol=2e-5)
    # at a clicked pixel: that pixel's saturation (hue) or value (colour) is the reference instead
    cy, cx = (int(v[0]) for v in np.nonzero(m))
    s_at, v_at = hsv[cy, cx, 1], hsv[cy, cx, 2]
    want = rgb.double().numpy().copy()
    for y, x in zip(*np.nonzero(m)):
        h, s, v = hsv[y, x]
        want[y, x] = colorsys.hsv_to_rgb(th, min(1.0, s * ts / s_at), v)
    np.testing.assert_allclose(recolour(rgb, mask, colour, "hue", at=(cx, cy)).double().numpy(), want, atol=2e-5)
    assert np.allclose(colorsys.rgb_to_hsv(*recolour(rgb, mask, colour, "hue", at=(cx, cy))[cy, cx].tolist())[:2],
                       (th, ts), atol=1e-4)  # the clicked pixel takes the colour's hue and saturation
    want = rgb.double().numpy().copy()
    want[m] = np.clip(np.array(colour)[None] * hsv[..., 2][m][:, None] / v_at, 0, 1)
    np.testing.assert_allclose(recolour(rgb, mask, colour, "colour", at=(cx, cy)).double().numpy(), want, atol=2e-5)
    # with a diffuse render: the colour shades the diffuse, and the render's logit offset over the
    # diffuse (its view-dependent part) goes back on
    diffuse = (rgb * 0.7).clamp(0.02, 0.98)
    d = diffuse.double().numpy()
    d_typ = np.median(d.max(-1)[m])
    logit = lambda x: np.log(np.clip(x, 1 / 255, 254 / 255)) - np.log1p(-np.clip(x, 1 / 255, 254 / 255))  # noqa: E731
    want = rgb.double().numpy().copy()
    shaded = np.clip(np.array(colour)[None] * d.max(-1)[m][:, None] / d_typ, 0, 1)
    want[m] = 1 / (1 + np.exp(-(logit(shaded) + logit(want[m]) - logit(d[m]))))
    got = recolour(rgb, mask, colour, "colour", diffuse).double().numpy()
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_shift_turns_every_hue_by_the_click_s_angle_against_colorsys():
    """``shift``: the clicked pixel takes the colour's hue and saturation, every other selected pixel
    turns its hue by the same angle and keeps its saturation ratio and value; without a click the
    reference hue is the selection's saturation-weighted circular mean."""
    rgb, mask, hsv, m = _random_selection(1)
    colour = (0.2, 0.4, 0.7)
    th, ts, tv = colorsys.rgb_to_hsv(*colour)
    cy, cx = (int(v[0]) for v in np.nonzero(m))
    h_at, s_at = hsv[cy, cx, 0], hsv[cy, cx, 1]
    want = rgb.double().numpy().copy()
    for y, x in zip(*np.nonzero(m)):
        h, s, v = hsv[y, x]
        want[y, x] = colorsys.hsv_to_rgb(((h + 360.0 * th - h_at) % 360.0) / 360.0, min(1.0, s * ts / s_at), v)
    got = recolour(rgb, mask, colour, "shift", at=(cx, cy))
    np.testing.assert_allclose(got.double().numpy(), want, atol=2e-5)
    assert np.allclose(colorsys.rgb_to_hsv(*got[cy, cx].tolist())[:2], (th, ts), atol=1e-4)
    # without a click: reds on both sides of 0 degrees have a typical hue near 0, not near 180, and the
    # more saturated one weighs more
    reds = torch.tensor([[[0.9, 0.1, 0.25], [0.9, 0.6, 0.5]]])  # hues about 349 and 11 degrees
    both = torch.ones(1, 2, dtype=torch.bool)
    out = _hsv(recolour(reds, both, (0.1, 0.9, 0.1), "shift"))[0, :, 0]  # green: 120 degrees
    before = _hsv(reds)[0]
    rad, w = np.radians(before[:, 0]), before[:, 1]
    mean = np.degrees(np.arctan2((w * np.sin(rad)).sum(), (w * np.cos(rad)).sum())) % 360.0
    assert 0.0 < (360.0 - mean) % 360.0 < 5.0  # pulled towards the saturated 349 degrees
    np.testing.assert_allclose(out, (before[:, 0] + 120.0 - mean) % 360.0, atol=1e-3)
    # a near-grey click has no hue to speak of: the selection's typical hue is the reference
    mixed = torch.tensor([[[0.5, 0.5, 0.52], [0.8, 0.2, 0.2], [0.75, 0.25, 0.2]]])  # grey-blue, two reds
    every = torch.ones(1, 3, dtype=torch.bool)
    turned = _hsv(recolour(mixed, every, (0.1, 0.9, 0.1), "shift", at=(0, 0)))[0, 1:, 0]
    assert np.all(_hue_gap(turned, 120.0) < 10.0), turned  # the reds turn green, not by the grey's 240 degrees


def test_shift_with_the_rule_s_colour_at_the_click_is_the_rule_s_recolour():
    """What the evaluation set's pick asks (the rule's colour at the clicked pixel): on the rule's own
    pixels, ``shift`` turns every hue by the rule's shift and keeps saturation and value, as the rule does."""
    from virgi_ns.edit.recolor import RecolorRule, recolor, rule_mask

    g = torch.Generator().manual_seed(2)
    rgb = torch.rand(8, 9, 3, generator=g) * 0.85 + 0.1
    rule = RecolorRule(0.0, 360.0, 135.0, 0.2, 0.1)
    mask = rule_mask(rgb, rule)
    cy, cx = (int(v[0]) for v in torch.nonzero(mask, as_tuple=True))
    ruled = recolor(rgb, rule)[0]
    got = recolour(rgb, mask, tuple(ruled[cy, cx].tolist()), "shift", at=(cx, cy))
    torch.testing.assert_close(got, ruled, atol=2e-5, rtol=0)
    assert float((recolour(rgb, mask, tuple(ruled[cy, cx].tolist()), "hue", at=(cx, cy)) - ruled).abs().max()) > 0.1


def test_connected_to_follows_diagonals_and_stops_at_gaps():
    """The 8-connected component of the clicked pixel: a diagonal step joins, a gap of one pixel does
    not, and a pixel outside the allowed ones has no component."""
    allowed = torch.zeros(6, 7, dtype=torch.bool)
    for y, x in ((0, 0), (1, 1), (2, 1), (2, 3), (2, 4), (5, 0)):
        allowed[y, x] = True
    as_set = lambda m: {tuple(p) for p in m.nonzero().tolist()}  # noqa: E731
    assert as_set(connected_to(allowed, 0, 0)) == {(0, 0), (1, 1), (2, 1)}
    assert as_set(connected_to(allowed, 4, 2)) == {(2, 3), (2, 4)}
    assert as_set(connected_to(allowed, 6, 5)) == set()


def test_connected_through_small_steps_matches_a_breadth_first_search():
    """With values, a neighbour joins only through a step of at most ``step``: the same set as a plain
    breadth-first search over random masks and values."""
    from collections import deque

    g = torch.Generator().manual_seed(3)
    for trial in range(6):
        allowed = torch.rand(9, 11, generator=g) < 0.7
        value = torch.rand(9, 11, generator=g)
        y, x = int(allowed.nonzero()[0, 0]), int(allowed.nonzero()[0, 1])
        seen, todo = {(y, x)}, deque([(y, x)])
        while todo:
            cy, cx = todo.popleft()
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    ny, nx = cy + dy, cx + dx
                    if (0 <= ny < 9 and 0 <= nx < 11 and (ny, nx) not in seen and bool(allowed[ny, nx])
                            and abs(float(value[ny, nx]) - float(value[cy, cx])) <= 0.3):
                        seen.add((ny, nx))
                        todo.append((ny, nx))
        got = {tuple(p) for p in connected_to(allowed, x, y, value, 0.3).nonzero().tolist()}
        assert got == seen, trial


def test_bad_picks_are_refused(world):
    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    s, _ = world["sessions"]["hue"]
    assert parse_colour("#D02020") == parse_colour("d02020") == pytest.approx((208 / 255, 32 / 255, 32 / 255))
    for bad in ("red", "#12345", "#gg0000", "", "#d0202000"):
        with pytest.raises(InputError, match="#RRGGBB"):
            parse_colour(bad)
    for t in (-0.1, 1.5, float("nan")):
        with pytest.raises(InputError, match=r"tolerance must be in \[0, 1\]"):
            s.update(parse_colour(RED), t, "hue")
    with pytest.raises(InputError, match="recolour mode"):
        s.update(parse_colour(RED), 0.2, "tint")
    for x, y in ((es.W, 0), (-1, 5), (3, es.H)):
        with pytest.raises(InputError, match="outside the 64x48 image"):
            PickSession(S.scene, cam, x, y)
    assert float(s.maps.accumulation[0, 0]) < 0.5
    with pytest.raises(InputError, match="background"):
        PickSession(S.scene, cam, 0, 0)


def test_a_view_set_up_first_and_retargeted_fits_as_a_fresh_engine(world):
    """``EditEngine(..., None)`` then ``retarget`` is the same fit as an engine built with the target;
    a retarget with the same selection keeps the pixel batches and the staged segmentation."""
    S = world["S"]
    s, _ = world["sessions"]["hue"]
    cam = S.cameras.index(EDIT_VIEW)
    cfg = pick_config("cpu", "staged")  # its layer restarts from the colour map: a warm fit equals a fresh one
    fresh = EditEngine(S.scene, cam, s.edited, None, cfg, changed=s.mask)
    later = EditEngine(S.scene, cam, None, None, cfg)
    later.retarget(s.edited, s.mask)
    a, b = fresh.fit(10)[0], later.fit(10)[0]
    torch.testing.assert_close(a.head_weight, b.head_weight, atol=0, rtol=0)
    torch.testing.assert_close(fresh.alpha_fixed, later.alpha_fixed, atol=0, rtol=0)
    batches, alpha = later.batches, later.alpha_fixed
    targets, moments = [bt.target for bt in batches], later.opt.state_tensors()
    green = recolour(s.maps.rgb, s.mask, (0.1, 0.8, 0.2), "hue")
    later.retarget(green, s.mask)
    assert later.batches is batches and later.alpha_fixed is alpha
    # the same tensors (recorded GPU steps read them), holding what a fresh engine's would
    assert all(bt.target is t for bt, t in zip(later.batches, targets))
    assert later.opt.state_tensors() == moments
    assert all(float(t.abs().max()) == 0.0 for t in moments)
    c = EditEngine(S.scene, cam, green, None, cfg, changed=s.mask).fit(10)[0]
    torch.testing.assert_close(later.fit(10)[0].head_weight, c.head_weight, atol=0, rtol=0)
    assert fresh.mode == "changed pixels (a selection)"
    with pytest.raises(InputError, match="selection is empty"):
        later.retarget(s.edited, torch.zeros_like(s.mask))


def test_a_live_update_reaches_a_new_colour_in_few_steps(world):
    """A warm update (the live drag: the segmentation kept, the layer from the new colour map) with
    20 steps lands within 0.03 of a fresh fit of the new colour with the full steps."""
    S = world["S"]
    green = parse_colour("#20c040")
    s = PickSession(S.scene, S.cameras.index(EDIT_VIEW), *world["pixel"], EditStack(S.scene.fingerprint()),
                    pick_config("cpu"))
    s.update(parse_colour(RED), 0.2, "hue")
    s.update(green, 0.2, "hue", steps=20)
    live = s.engine.preview()["rgb"][s.mask]
    f = PickSession(S.scene, S.cameras.index(EDIT_VIEW), *world["pixel"], EditStack(S.scene.fingerprint()),
                    pick_config("cpu"))
    f.update(green, 0.2, "hue")
    full = f.engine.preview()["rgb"][f.mask]
    target = s.edited[s.mask]
    assert float((full - target).abs().mean()) < 0.05
    assert float((live - full).abs().mean()) < 0.03
    # the colour drag kept the click's selection; a new tolerance selects again
    assert torch.equal(s.mask, select(s.maps, *world["pixel"], 0.2))
    kept = s.mask
    s.update(green, 0.2, "hue", steps=0)
    assert s.mask is kept
    s.update(green, 1.0, "hue", steps=0)
    assert torch.equal(s.mask, select(s.maps, *world["pixel"], 1.0)) and not torch.equal(s.mask, kept)
    # so does a new contiguity, which the edit's settings record
    s.update(green, 1.0, "hue", steps=0, contiguous=False)
    assert torch.equal(s.mask, select(s.maps, *world["pixel"], 1.0, contiguous=False))
    assert s.settings["contiguous"] is False
    anywhere = s.mask
    s.update(parse_colour(RED), 1.0, "hue", steps=0, contiguous=False)
    assert s.mask is anywhere


def test_commit_saves_the_pictures_beside_the_edit_and_replaces_it(world, tmp_path):
    S = world["S"]
    s, edit = world["sessions"]["hue"]
    stack = EditStack(S.scene.fingerprint(), tmp_path)
    assert commit(stack, s, edit) == 1
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["edit_0001.pt", "edit_0001_edited.png", "edit_0001_selection.png", "stack.json"]
    sel = np.asarray(Image.open(tmp_path / "edit_0001_selection.png"))
    assert np.array_equal(sel > 127, s.mask.numpy())
    img = np.asarray(Image.open(tmp_path / "edit_0001_edited.png"), dtype=np.float32) / 255
    assert np.abs(img - s.edited.numpy()).max() <= 0.5 / 255 + 1e-6
    assert stack.entries[0].edit.source.image == str(tmp_path / "edit_0001_edited.png")
    assert commit(stack, s, world["sessions"]["colour"][1], replace=1) == 1
    assert len(stack) == 1 and sorted(p.name for p in tmp_path.iterdir()) == [
        "edit_0002.pt", "edit_0002_edited.png", "edit_0002_selection.png", "stack.json"]
    assert stack.entries[0].edit.info["pick"]["mode"] == "colour"
    stack.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stack.json"]
