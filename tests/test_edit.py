"""The edit engine and the edit stack on a tiny procedural scene with known albedo (CPU)."""

from __future__ import annotations

import copy
import dataclasses
import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import edit_scene as es  # noqa: E402

from virgi_ns.edit.engine import VIEW_FIELDS, EditConfig, EditEngine  # noqa: E402
from virgi_ns.edit.pixels import pixel_batches  # noqa: E402
from virgi_ns.edit.recolor import RecolorRule, recolor  # noqa: E402
from virgi_ns.edit.scene import render_view  # noqa: E402
from virgi_ns.edit.stack import Edit, EditStack  # noqa: E402
from virgi_ns.errors import InputError  # noqa: E402
from virgi_ns.raster import Request, composite  # noqa: E402

BLUE_TO_RED = RecolorRule(h0=190, h1=260, shift=135, s_min=0.3, v_min=0.1)
EDIT_VIEW, HELD_OUT = 0, (1, 7)


@pytest.fixture(scope="module")
def world():
    """The scene, every view's contributions, unedited renders, and one fitted blue -> red edit."""
    with es.one_thread():
        S = es.build()
        cams = S.cameras
        contrib = [S.scene.contributions(cams.index(v), Request.whole_images(cams.index(v))) for v in range(len(cams))]
        before = [render_view(S.scene, cams, v, contrib=contrib[v]) for v in range(len(cams))]
        edited, _ = recolor(before[EDIT_VIEW]["rgb"], BLUE_TO_RED)
        eng = EditEngine(S.scene, cams.index(EDIT_VIEW), edited, EditStack(S.scene.fingerprint()))
        edit, timing = eng.fit()
        # per-pixel coverage of each object, from the known labels
        onehot = torch.nn.functional.one_hot(S.labels, 3).float()
        cover = [composite(c.gather(onehot), c)[0] for c in contrib]
        yield {"S": S, "contrib": contrib, "before": before, "edited": edited, "edit": edit, "timing": timing,
               "cover": cover, "engine": eng}


def _stack(world, *edits: Edit, directory=None) -> EditStack:
    st = EditStack(world["S"].scene.fingerprint(), directory)
    for e in edits:
        st.add(e)
    return st


def _render(world, v: int, stack=None, **kw):
    S = world["S"]
    return render_view(S.scene, S.cameras, v, stack, contrib=world["contrib"][v], **kw)


# ----------------------------------------------------------------------- engine parts
def test_sparse_pixel_batches_reproduce_composite(world):
    """The engine's CSR operators, split into random pixel sets, equal the contract's composite."""
    c = world["contrib"][EDIT_VIEW]
    U = c.pair_gaussian.shape[0]
    g = torch.Generator().manual_seed(3)
    colours = torch.rand(U, 3, generator=g, requires_grad=True)
    bg = torch.tensor([0.2, 0.3, 0.4])
    target = torch.rand(c.num_pixels, 3, generator=g)
    ref = composite(colours, c, bg).reshape(-1, 3)
    batches = pixel_batches(c, target, bg, 3, seed=5)
    assert sum(b.target.shape[0] for b in batches) == c.num_pixels
    got = torch.cat([b.render(colours) + b.background for b in batches])
    tgt = torch.cat([b.target for b in batches])
    # each batch's targets are its pixels' targets, so matching rows by target identifies the pixels
    idx = torch.cat([torch.nonzero((target[None] == t[:, None]).all(-1))[:, 1] for t in tgt.split(1000)])
    assert sorted(idx.tolist()) == list(range(c.num_pixels))
    torch.testing.assert_close(got, ref[idx], atol=1e-6, rtol=1e-5)
    one = pixel_batches(c, target, bg, 1, seed=0)[0]
    torch.testing.assert_close(one.render(colours) + one.background, ref, atol=1e-6, rtol=1e-5)
    # gradients through A^T equal autograd through the scatter composite
    w = torch.rand(c.num_pixels, 3, generator=g)
    (gr,) = torch.autograd.grad((ref * w).sum(), colours)
    (gs,) = torch.autograd.grad((got * w[idx]).sum(), colours)
    torch.testing.assert_close(gs, gr, atol=1e-5, rtol=1e-5)
    (g1,) = torch.autograd.grad(((one.render(colours)) * w).sum(), colours)
    torch.testing.assert_close(g1, gr, atol=1e-5, rtol=1e-5)
    # with changed pixels: every set holds its part of them, and they carry the share in every set
    changed = torch.zeros(c.num_pixels, dtype=torch.bool)
    changed[torch.randperm(c.num_pixels, generator=g)[:9]] = True
    for n in (1, 4):
        sets = pixel_batches(c, target, bg, n, seed=2, changed=changed, share=0.5)
        assert sum(b.target.shape[0] for b in sets) == c.num_pixels
        for b in sets:
            is_changed = (b.target[:, None] == target[changed][None]).all(-1).any(-1)
            assert int(is_changed.sum()) in (9 // n, 9 // n + 1)
            assert abs(float(b.weight.sum()) - 1.0) < 1e-5
            assert abs(float(b.weight[is_changed].sum()) - 0.5) < 1e-5
    # with weights for the unchanged pixels: within every set they split their half in proportion to them
    keep = torch.rand(c.num_pixels, generator=g) + 0.1
    for n, kind in ((1, "csr"), (4, "csr"), (4, "fused")):
        sets = pixel_batches(c, target, bg, n, seed=2, changed=changed, share=0.5, composite=kind, n_changed=9,
                             keep=keep)
        for b in sets:
            pix = torch.arange(c.num_pixels) if b.pixels is None else b.pixels
            ch = changed[pix]
            assert abs(float(b.weight[ch].sum()) - 0.5) < 1e-5
            torch.testing.assert_close(b.weight[~ch], 0.5 * keep[pix][~ch] / keep[pix][~ch].sum())


def test_colour_map_recolours_each_gaussian_before_compositing(world):
    """``render_view(colour_map=...)`` maps every Gaussian's colour before compositing: the identity
    gives the plain render, a constant colour c gives c (1 - T) + T bg per pixel."""
    S = world["S"]
    v = HELD_OUT[0]
    plain = _render(world, v)["rgb"]
    torch.testing.assert_close(_render(world, v, colour_map=lambda c: c)["rgb"], plain)
    c = torch.tensor([0.2, 0.7, 0.4])
    const = _render(world, v, colour_map=lambda x: c.to(x).expand_as(x).clone())["rgb"]
    T = world["contrib"][v].transmittance.reshape(plain.shape[:2])[..., None].to(const)
    bg = S.scene.background.to(const).reshape(3)
    torch.testing.assert_close(const, c.to(const) * (1 - T) + T * bg, atol=1e-5, rtol=0)


def test_diffuse_map_recolours_the_diffuse_colour_and_keeps_the_specular_part(world):
    """``render_view(diffuse_map=...)`` maps every Gaussian's diffuse colour and adds the specular
    logit back: the identity gives the plain render; a constant c makes the diffuse render
    c (1 - T) + T bg while the rgb keeps a view-dependent part on top of it."""
    S = world["S"]
    v = HELD_OUT[0]
    plain = _render(world, v)
    torch.testing.assert_close(_render(world, v, diffuse_map=lambda c: c)["rgb"], plain["rgb"], atol=1e-5, rtol=0)
    c = torch.tensor([0.2, 0.7, 0.4])
    out = _render(world, v, diffuse_map=lambda x: c.to(x).expand_as(x).clone())
    T = world["contrib"][v].transmittance.reshape(plain["rgb"].shape[:2])[..., None].to(out["rgb"])
    bg = S.scene.background.to(out["rgb"]).reshape(3)
    torch.testing.assert_close(out["diffuse"], c.to(out["rgb"]) * (1 - T) + T * bg, atol=1e-5, rtol=0)
    assert float((out["rgb"] - out["diffuse"]).abs().max()) > 1e-3  # the specular part is still there


def test_fresh_edit_changes_nothing(world, monkeypatch):
    """Without the colour-map start (this edit is below its share), before any step the edit's c_d' is
    the base head, so the preview is the unedited render; with it (forced here), alpha ~ sigmoid(-4)
    keeps the preview within a few hundredths of the render, moved towards the edit."""
    import virgi_ns.edit.engine as engine

    S = world["S"]
    before = world["before"][EDIT_VIEW]["rgb"]
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"])
    assert eng.colour_map is None
    torch.testing.assert_close(eng.preview()["rgb"], before, atol=1e-6, rtol=0)
    monkeypatch.setattr(engine, "MAP_START_SHARE", 0.0)
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"])
    assert eng.colour_map is not None
    prev = eng.preview()
    assert float((prev["rgb"] - before).abs().max()) < 0.05
    changed = (world["edited"] - before).abs().amax(-1) > 0.05
    assert float((prev["rgb"] - world["edited"]).abs()[changed].mean()) < float(
        (before - world["edited"]).abs()[changed].mean())
    # alpha starts near sigmoid(-4) on the object
    inside = world["cover"][EDIT_VIEW].sum(-1) > 0.99
    a = prev["alpha"][inside]
    assert 0.005 < float(a.mean()) < 0.05


def test_engine_refuses_bad_inputs(world):
    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    with pytest.raises(InputError, match="64x48"):
        EditEngine(S.scene, cam, torch.zeros(40, 64, 3))
    with pytest.raises(InputError, match="H x W x 3"):
        EditEngine(S.scene, cam, torch.zeros(48, 64))
    away = cam.viewmats.clone()
    away[0, 2, 3] -= 100.0  # scene now behind the camera
    from virgi_ns.raster import Cameras

    with pytest.raises(InputError, match="sees none"):
        EditEngine(S.scene, Cameras(cam.Ks, away, cam.widths, cam.heights), world["edited"])


# --------------------------------------------------------------------- propagation
def test_recolour_reaches_held_out_views(world):
    """One edited view moves the blue object towards the rule's red in other views."""
    stack = _stack(world, world["edit"])
    for v in HELD_OUT:
        before = world["before"][v]["rgb"]
        truth, mask = recolor(before, BLUE_TO_RED)
        after = _render(world, v, stack)["rgb"]
        assert int(mask.sum()) > 100
        miss_before = float((before - truth).abs()[mask].mean())
        miss_after = float((after - truth).abs()[mask].mean())
        assert miss_before > 0.3
        assert miss_after < 0.1 * miss_before, (v, miss_before, miss_after)
        # the object's mean colour is now red-dominant
        mean = after[mask].mean(0)
        assert mean[0] > 2 * mean[2]


def test_other_objects_unchanged(world):
    stack = _stack(world, world["edit"])
    for v in (EDIT_VIEW, *HELD_OUT):
        cov = world["cover"][v]
        others = (cov[..., es.BLUE] < 1e-3) & (cov.sum(-1) > 0.5)
        assert int(others.sum()) > 100
        diff = (_render(world, v, stack)["rgb"] - world["before"][v]["rgb"]).abs()[others]
        assert float(diff.mean()) < 0.01 and float(diff.max()) < 0.1, (v, float(diff.mean()), float(diff.max()))


def test_highlight_keeps_position_and_strength(world):
    """The near-white highlight on the recoloured object stays where it was, as white as it was."""
    stack = _stack(world, world["edit"])
    for v in (EDIT_VIEW, *HELD_OUT):
        before = world["before"][v]["rgb"]
        after = _render(world, v, stack)["rgb"]
        on_blue = world["cover"][v][..., es.BLUE] > 0.9
        wb = torch.where(on_blue, before.min(-1).values, torch.zeros(()))
        wa = torch.where(on_blue, after.min(-1).values, torch.zeros(()))
        assert float(wb.max()) > 0.8  # the scene has a real highlight there
        pb, pa = divmod(int(wb.argmax()), wb.shape[1]), divmod(int(wa.argmax()), wa.shape[1])
        assert abs(pb[0] - pa[0]) <= 1 and abs(pb[1] - pa[1]) <= 1, (v, pb, pa)
        assert abs(float(wa.max()) - float(wb.max())) < 0.06
        # near-white pixels stay near-white (the albedo under a partial highlight may show through)
        hl = wb > 0.8
        assert float((after - before).abs()[hl].mean()) < 0.08
        core = wb > 0.9
        assert int(core.sum()) > 0 and float((after - before).abs()[core].max()) < 0.12


def test_segmentation_selects_the_object(world):
    S = world["S"]
    stack = _stack(world, world["edit"])
    f = S.scene.field.encode(S.scene.means)
    _, h2 = S.scene.field.diffuse_hidden(f)
    with torch.no_grad():
        a = stack.segmentation(f, h2, 1)[:, 0]
        combined = stack.segmentation(f, h2)[:, 0]
    torch.testing.assert_close(a, combined)
    seen = world["contrib"][EDIT_VIEW].pair_gaussian
    blue = torch.zeros_like(S.labels, dtype=torch.bool)
    blue[seen] = S.labels[seen] == es.BLUE
    assert float(a[blue].mean()) > 0.8
    assert float(a[S.labels != es.BLUE].mean()) < 0.1
    img = _render(world, EDIT_VIEW, stack, seg_index=1)["segmentation"][..., 0]
    on_blue = world["cover"][EDIT_VIEW][..., es.BLUE] > 0.9
    assert float(img[on_blue].mean()) > 0.8


def test_pixel_subsampling_fits_too(world):
    S = world["S"]
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"], cfg=EditConfig(pixel_batches=4))
    assert len(eng.batches) == 4
    edit, timing = eng.fit()
    assert timing.steps == EditConfig().steps and timing.setup_s > 0 and timing.steps_s > 0
    v = HELD_OUT[0]
    truth, mask = recolor(world["before"][v]["rgb"], BLUE_TO_RED)
    after = _render(world, v, _stack(world, edit))["rgb"]
    assert float((after - truth).abs()[mask].mean()) < 0.05


# --------------------------------------------------------------------------- stack
def test_undo_disable_reset_restore_exact_renders(world, tmp_path):
    run = tmp_path / "run"
    stack = EditStack.open(run, world["S"].scene.fingerprint())
    stack.add(world["edit"])
    v = HELD_OUT[0]
    base = world["before"][v]["rgb"]
    assert not torch.equal(_render(world, v, stack)["rgb"], base)
    stack.set_enabled(1, False)
    assert torch.equal(_render(world, v, stack)["rgb"], base)
    stack.set_enabled(1, True)
    stack.undo()
    assert len(stack) == 0 and torch.equal(_render(world, v, stack)["rgb"], base)
    assert not (run / "edits" / "edit_0001.pt").exists()
    with pytest.raises(InputError, match="nothing to undo"):
        stack.undo()
    stack.add(world["edit"])
    stack.add(world["edit"])
    stack.set_specular_strength(0.5)
    assert stack.reset() == 2 and stack.specular_strength == 1.0
    assert torch.equal(_render(world, v, EditStack.open(run, stack.fingerprint))["rgb"], base)
    assert sorted(p.name for p in (run / "edits").iterdir()) == ["stack.json"]


def test_stack_persists_and_reloads(world, tmp_path):
    fp = world["S"].scene.fingerprint()
    stack = EditStack.open(tmp_path, fp)
    stack.add(world["edit"])
    stack.set_specular_strength(1.5)
    again = EditStack.open(tmp_path, fp)
    assert len(again) == 1 and again.specular_strength == 1.5
    assert again.rows()[0]["info"]["steps"] == world["timing"].steps
    v = HELD_OUT[1]
    torch.testing.assert_close(_render(world, v, again)["rgb"], _render(world, v, stack)["rgb"], atol=1e-6, rtol=0)
    man = json.loads((tmp_path / "edits" / "stack.json").read_text())
    assert man["fingerprint"] == fp and man["edits"][0]["enabled"] is True
    # files hold only small tensors and strings
    assert (tmp_path / "edits" / "edit_0001.pt").stat().st_size < 64_000


def test_foreign_and_damaged_edit_files_are_refused(world, tmp_path):
    fp = world["S"].scene.fingerprint()
    stack = EditStack.open(tmp_path / "run", fp)
    stack.add(world["edit"])
    listing = sorted(p.name for p in (tmp_path / "run" / "edits").iterdir())
    # an edit of another base run
    other = Edit(world["edit"].head_weight, world["edit"].head_bias, world["edit"].seg, world["edit"].source,
                 "0123456789abcdef")
    other.save(tmp_path / "other.pt")
    with pytest.raises(InputError, match="another base run"):
        stack.import_file(tmp_path / "other.pt")
    # not an edit at all
    (tmp_path / "notes.pt").write_text("hello")
    with pytest.raises(InputError, match="not a virgi edit file"):
        stack.import_file(tmp_path / "notes.pt")
    torch.save({"format": "something-else"}, tmp_path / "tensor.pt")
    with pytest.raises(InputError, match="not a virgi edit file"):
        Edit.load(tmp_path / "tensor.pt")
    assert sorted(p.name for p in (tmp_path / "run" / "edits").iterdir()) == listing and len(stack) == 1
    # the whole stack opened against another run is refused
    with pytest.raises(InputError, match="another base run"):
        EditStack.open(tmp_path / "run", "ffffffffffffffff")
    # and a good import works
    world["edit"].save(tmp_path / "mine.pt")
    assert stack.import_file(tmp_path / "mine.pt") == 2
    with pytest.raises(InputError, match="no edit number 5"):
        stack.set_enabled(5, False)


def test_specular_strength_scales_highlights(world):
    v = EDIT_VIEW
    k0 = EditStack(world["S"].scene.fingerprint(), specular_strength=0.0)
    k15 = EditStack(world["S"].scene.fingerprint(), specular_strength=1.5)
    r0 = _render(world, v, k0)
    torch.testing.assert_close(r0["rgb"], r0["diffuse"])  # k = 0: no highlight left
    base = world["before"][v]
    torch.testing.assert_close(r0["diffuse"], base["diffuse"])
    on_blue = world["cover"][v][..., es.BLUE] > 0.9
    hl = on_blue & (base["rgb"].min(-1).values > 0.6)
    assert int(hl.sum()) > 0
    spec = lambda r: (r["rgb"] - r["diffuse"])[hl].sum(-1).mean()  # noqa: E731
    assert float(spec(_render(world, v, k15))) > 1.05 * float(spec(base)) > 0
    assert float(r0["rgb"][hl].min(-1).values.max()) < 0.5  # the white is gone


def test_later_edit_overrides_earlier(world):
    """A second edit on top of the first (red -> green) wins where it applies."""
    S = world["S"]
    first = _stack(world, world["edit"])
    red_view = _render(world, EDIT_VIEW, first)["rgb"]
    red_to_green = RecolorRule(h0=330, h1=30, shift=120, s_min=0.3, v_min=0.1)
    edited2, _ = recolor(red_view, red_to_green)
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), edited2, first)
    # starts from the stack (c_d' starts as the base head, weighted by alpha ~ sigmoid(-4))
    assert float((eng.preview()["rgb"] - red_view).abs().max()) < 0.03
    second, _ = eng.fit()
    first.add(second)
    v = HELD_OUT[0]
    after = _render(world, v, first)["rgb"]
    truth, mask = recolor(recolor(world["before"][v]["rgb"], BLUE_TO_RED)[0], red_to_green)
    on_blue = world["cover"][v][..., es.BLUE] > 0.99
    assert float((after - truth).abs()[on_blue & mask].mean()) < 0.06
    mean = after[on_blue].mean(0)
    assert mean[1] > 2 * mean[0]
    first.set_enabled(2, False)  # disabling the second brings back the first's red
    torch.testing.assert_close(_render(world, v, first)["rgb"], _render(world, v, _stack(world, world["edit"]))["rgb"])


def test_feature_cache_gives_the_same_edit(world):
    """Cached (f, h1, h_diff) of every Gaussian: same renders and the same fitted edit."""
    import dataclasses

    S = world["S"]
    cached = dataclasses.replace(S.scene).precompute_features(chunk=500)
    assert cached.features[0].shape == (S.scene.means.shape[0], S.scene.field.feature_dim)
    v = HELD_OUT[0]
    torch.testing.assert_close(render_view(cached, S.cameras, v, contrib=world["contrib"][v])["rgb"],
                               world["before"][v]["rgb"], atol=1e-6, rtol=0)
    eng = EditEngine(cached, S.cameras.index(EDIT_VIEW), world["edited"], EditStack(S.scene.fingerprint()))
    edit, _ = eng.fit(20)
    ref, _ = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"]).fit(20)
    torch.testing.assert_close(edit.head_weight, ref.head_weight, atol=1e-5, rtol=1e-4)


def test_unchanged_pixels_keep_the_render_when_the_original_is_known(world):
    """A recoloured *photo* differs from the render everywhere (reconstruction error). Given the
    unedited photo, the engine fits only the pixels the user changed and targets the current render
    elsewhere: the other objects stay as they were, where fitting the whole photo drags them
    towards the photo's error."""
    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    render = world["before"][EDIT_VIEW]["rgb"]
    g = torch.Generator().manual_seed(4)
    photo = (render + 0.15 * (torch.rand(render.shape, generator=g) - 0.5) + 0.1).clamp(0, 1)  # "photo" = render + error
    edited, mask = recolor(photo, BLUE_TO_RED)
    assert 0.05 < float(mask.float().mean()) < 0.6
    cfg = EditConfig(steps=40)
    fits = {}
    for name, orig in (("whole", None), ("changed", photo)):
        eng = EditEngine(S.scene, cam, edited, cfg=cfg, original=orig)
        edit, _ = eng.fit()
        fits[name] = (eng, _stack(world, edit))
    assert fits["whole"][0].changed_fraction == 1.0 and fits["whole"][0].mode == "whole image"
    assert abs(fits["changed"][0].changed_fraction - float(mask.float().mean())) < 0.02
    for v in HELD_OUT:
        before = world["before"][v]["rgb"]
        _, m = recolor(before, BLUE_TO_RED)
        outside = ~m & (world["cover"][v].sum(-1) > 0.5)  # other objects
        leak = {k: float((_render(world, v, st)["rgb"] - before).abs()[outside].mean()) for k, (_, st) in fits.items()}
        assert leak["changed"] < 0.5 * leak["whole"], (v, leak)
        # the recolour itself still lands
        after = _render(world, v, fits["changed"][1])["rgb"]
        mean = after[m].mean(0)
        assert mean[0] > 2 * mean[2]
    with pytest.raises(InputError, match="does not differ"):
        EditEngine(S.scene, cam, photo, original=photo)
    with pytest.raises(InputError, match="original image"):
        EditEngine(S.scene, cam, edited, original=photo[:10])


def test_changed_pixels_target_the_edited_pixels_and_refuse_other_targets(world):
    """``changed_target="edited"`` (the paper's): the changed pixels of an edited photo are fitted to
    the edited pixels themselves, the others to the current render. The default is ``affine`` (below);
    no other target is taken, at construction or by the engine."""
    assert EditConfig().changed_target == "affine"
    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    render = world["before"][EDIT_VIEW]["rgb"]
    photo = (render + 0.12).clamp(0, 1)
    edited, _ = recolor(photo, BLUE_TO_RED)
    changed = (edited - photo).abs().amax(-1) > EditConfig().unchanged_tol
    eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=0, pixel_batches=1, changed_target="edited"),
                     original=photo)
    assert eng.mode.endswith("edited image)")
    torch.testing.assert_close(eng.batches[0].target.reshape(render.shape),
                               torch.where(changed[..., None], edited, render), atol=0, rtol=0)
    with pytest.raises(ValueError, match="changed_target"):
        EditConfig(changed_target="change")  # type: ignore[arg-type]
    cfg = EditConfig()
    with pytest.raises(ValueError, match="changed_target"):  # set after construction: checked too
        cfg.changed_target = "photo"  # type: ignore[assignment]
    assert cfg.changed_target == "affine"
    cfg.steps = 7  # a valid value is taken
    assert cfg.steps == 7


def _checkered_photo(world):
    """(scene, edit camera, its render, a photo: the render with a checkerboard of +-0.08 the model
    never reproduced)."""
    S = world["S"]
    render = world["before"][EDIT_VIEW]["rgb"]
    H, W = render.shape[:2]
    checker = ((torch.arange(H)[:, None] + torch.arange(W)[None, :]) % 2).float()[..., None] * 0.16 - 0.08
    return S, S.cameras.index(EDIT_VIEW), render, (render + checker).clamp(0, 1)


def test_change_slope_recovers_an_affine_change_and_leaves_unvaried_directions_alone():
    """:func:`change_slope`: for edited colours that are an affine function of the originals, the
    function's matrix; where the originals do not vary (one colour), identity (no correction); for
    a change that is no function of colour, the slope shrunk by the little its fit explains."""
    from virgi_ns.edit.targets import change_slope

    g = torch.Generator().manual_seed(3)
    original = torch.rand(500, 3, generator=g)
    matrix = torch.tensor([[0.1, 0.2, 0.7], [0.8, 0.1, 0.0], [0.0, 0.9, 0.2]])
    edited = original @ matrix.T + torch.tensor([0.05, -0.1, 0.02])
    torch.testing.assert_close(change_slope(original, edited), matrix, atol=2e-3, rtol=0)
    flat = torch.tensor([[0.3, 0.5, 0.7]]).repeat(50, 1)
    torch.testing.assert_close(change_slope(flat, flat @ matrix.T), torch.eye(3), atol=1e-6, rtol=0)
    # a change that is no function of colour (paint strokes of random colours over colours varying
    # little, as over a flat region): no slope, although the colours correlate with it by chance
    from virgi_ns.edit.targets import SLOPE_MIN_PIXELS

    some = original[:200] * 0.05 + 0.4
    strokes = torch.rand(200, 3, generator=g)
    unscaled = torch.linalg.lstsq(torch.cat([some, torch.ones(200, 1)], 1), strokes - some).solution[:3].T
    assert float(unscaled.abs().max()) > 0.5  # what an unweighted slope would make of it
    assert float((change_slope(some, strokes) - torch.eye(3)).abs().max()) < 0.1 * float(unscaled.abs().max())
    # a small touch-up: too few pixels to tell a slope from chance
    n = SLOPE_MIN_PIXELS - 1
    assert torch.equal(change_slope(original[:n], original[:n] @ matrix.T), torch.eye(3))
    assert torch.equal(change_slope(original[:0], original[:0]), torch.eye(3))


def test_affine_target_is_the_rule_on_the_render_for_a_channel_permuting_edit(world):
    """``changed_target="affine"``: a hue shift of 120 degrees permutes the channels, so the edited
    pixel moved by the slope of the user's change times (render - photo) is the rule applied to the
    render itself, although the photo carries a checkerboard of +-0.08 the model never reproduced;
    held out, the edit misses the truth by less than one fitted to the edited photo's pixels."""
    S, cam, render, photo = _checkered_photo(world)
    rule = RecolorRule(h0=BLUE_TO_RED.h0, h1=BLUE_TO_RED.h1, shift=120, s_min=BLUE_TO_RED.s_min,
                       v_min=BLUE_TO_RED.v_min)
    edited, in_photo = recolor(photo, rule)
    rule_on_render, in_render = recolor(render, rule)
    miss = {}
    for target in ("affine", "edited"):
        eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=60, pixel_batches=1, changed_target=target),
                         original=photo)
        tgt = eng.batches[0].target.reshape(render.shape)
        if target == "affine":
            assert "slope" in eng.mode
            both = in_photo & in_render & ((edited - photo).abs().amax(-1) > EditConfig().unchanged_tol)
            assert float(both.float().mean()) > 0.02
            # (up to the slope's ridge, SLOPE_RIDGE; the render plus the pixel's own change is over
            # ten times further off)
            torch.testing.assert_close(tgt[both], rule_on_render[both], atol=5e-3, rtol=0)
            own = (render + edited - photo).clamp(0, 1)
            err = lambda x: float((x[both] - rule_on_render[both]).abs().amax())  # noqa: E731
            assert err(own) > 10 * err(tgt), (err(own), err(tgt))
            off = (edited - photo).abs().amax(-1) <= EditConfig().unchanged_tol
            torch.testing.assert_close(tgt[off], render[off])
        stack = _stack(world, eng.fit()[0])
        truth, m = recolor(world["before"][HELD_OUT[0]]["rgb"], rule)
        miss[target] = float((_render(world, HELD_OUT[0], stack)["rgb"] - truth).abs()[m].mean())
    assert miss["affine"] < miss["edited"], miss


def test_staged_recipe_segments_first_and_its_edit_renders_what_it_fitted(world):
    """``recipe="staged"``: the segmentation is a classifier of the view's Gaussians, fixed while the
    layer trains; the saved edit's head gives the same alpha at render time, high on the Gaussians
    that mostly land on changed pixels and low on the others."""
    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    cfg = EditConfig(recipe="staged", seg_samples=2048, seg_steps=150)
    eng = EditEngine(S.scene, cam, world["edited"], EditStack(S.scene.fingerprint()), cfg)
    seg_before = [p.detach().clone() for p in eng.seg.parameters()]
    edit, _ = eng.fit()
    assert edit.info["recipe"] == "staged" and edit.info["start"] == "colour map"
    for a, b in zip(seg_before, eng.seg.parameters()):  # the layer's steps leave the segmentation alone
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    alpha = edit.alpha(eng.feats, eng.h_diff)
    torch.testing.assert_close(alpha, eng.alpha_fixed, atol=1e-6, rtol=0)
    # an independent label: the share of each visible Gaussian's weight on the changed pixels
    c = eng.contrib
    changed = (world["edited"] - world["before"][EDIT_VIEW]["rgb"]).abs().amax(-1).reshape(-1) > 3 / 255
    U = eng.gaussians.numel()
    w = c.weight.detach()
    mass = torch.zeros(U).index_add_(0, c.pair.long(), w)
    share = torch.zeros(U).index_add_(0, c.pair.long(), w * changed[c.pixel.long()].float()) / mass.clamp_min(1e-12)
    clear_in, clear_out = (share > 0.9) & (mass > 0.5), (share < 0.1) & (mass > 0.5)
    assert float(alpha[clear_in].mean()) > 0.9 and float(alpha[clear_out].mean()) < 0.1
    # a whole-image fit knows no changed pixels: the joint recipe runs instead
    eng = EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(recipe="staged", whole_image=True, steps=2))
    assert eng.fit()[0].info["recipe"] == "joint"
    for bad in ({"recipe": "both"}, {"seg_samples": 1}, {"seg_steps": -1}, {"batch_composite": "segment"}):
        with pytest.raises(ValueError):
            EditConfig(**bad)


def test_the_classifier_gradients_are_autograds():
    """The staged classifier's written-out gradient (``classifier_gradients``) is autograd's gradient of the
    mean binary cross-entropy of the head's logits, in float64, with units on both sides of the ReLU."""
    from virgi_ns.edit.fitting import classifier_gradients
    from virgi_ns.edit.heads import SegmentationHead

    g = torch.Generator().manual_seed(3)
    torch.manual_seed(3)
    seg = SegmentationHead(5, 7, 16).double()
    torch.nn.init.normal_(seg.l2.weight, std=0.5)
    x = torch.randn(300, 12, generator=g, dtype=torch.float64)
    y = (torch.rand(300, 1, generator=g) > 0.4).double()
    loss = torch.nn.functional.binary_cross_entropy_with_logits(seg.logits_of(x), y)
    expected = torch.autograd.grad(loss, list(seg.parameters()))
    for p in seg.parameters():
        p.requires_grad_(False)
    classifier_gradients(seg, x, y)
    for p, e in zip(seg.parameters(), expected):
        torch.testing.assert_close(p.grad, e, rtol=1e-12, atol=1e-14)


@pytest.mark.gpu
def test_the_recorded_classifier_steps_give_the_eager_classifier():
    """The staged classifier's steps replayed from one CUDA graph train the head as the eager steps do."""
    from virgi_ns.edit.fitting import train_classifier
    from virgi_ns.edit.heads import SegmentationHead

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    g = torch.Generator().manual_seed(0)
    # the second problem replays the step recorded for the first (same shapes): its own head, samples and
    # a fresh Adam must reach it; the third goes on warm from the second's head
    problems = []
    for k in range(2):
        x = torch.randn(4096, 24, generator=g).cuda()
        problems.append((x, ((x[:, :1] if k == 0 else -x[:, 2:3]) + 0.3 * x[:, 1:2] > 0).float()))
    heads, alphas = {}, {}
    for graphs in (True, False):
        for k, (x, y) in enumerate(problems):
            torch.manual_seed(k)
            heads[graphs, k] = SegmentationHead(12, 12, 32).cuda()
            alphas[graphs, k] = train_classifier(heads[graphs, k], x, y, x, EditConfig(cuda_graphs=graphs), steps=47)
        x, y = problems[0]  # step counts that replay the graph of several steps and the graph of one
        alphas[graphs, "warm"] = train_classifier(heads[graphs, 1], x, y, x, EditConfig(cuda_graphs=graphs),
                                                  warm=True, steps=23)
    for k in (0, 1, "warm"):
        assert float((alphas[True, k] - alphas[False, k]).abs().max()) < 1e-4, k
    for k in (0, 1):
        assert float(((alphas[True, k] > 0.5).float() - problems[k][1]).abs().mean()) < 0.05  # it learnt the labels


@pytest.mark.gpu
def test_the_classifier_kernels_give_the_float64_gradient():
    """The staged classifier's gradient on our kernels (``written_out_gradients``) is the float64 reference's
    (``classifier_gradients``), on the default head's shape and on odd ones (samples that do not fill the
    last tile, several tiles per block, a width past one pass of 64 units, widths and inputs that are no
    multiple of the register tiles), and the same on every run."""
    from virgi_ns.edit.fitting import classifier_gradients, written_out_gradients
    from virgi_ns.edit.heads import SegmentationHead
    from virgi_ns.raster import cuda

    if not cuda.available()[0]:
        pytest.skip("needs a CUDA GPU and the extension")
    g = torch.Generator().manual_seed(5)
    for S, F, H, W in ((8192, 32, 64, 64), (70000, 32, 64, 64), (1000, 5, 32, 48), (3000, 16, 16, 100), (33, 7, 3, 37)):
        torch.manual_seed(S)
        seg = SegmentationHead(F, H, W)
        torch.nn.init.normal_(seg.l2.weight, std=0.5)
        x = torch.randn(S, F + H, generator=g)
        y = (torch.rand(S, 1, generator=g) > 0.4).float()
        oracle = copy.deepcopy(seg).double()
        for p in list(oracle.parameters()) + list(seg.parameters()):
            p.requires_grad_(False)
        classifier_gradients(oracle, x.double(), y.double())
        seg = seg.cuda()
        assert cuda.classifier_fits(F + H, W, torch.device("cuda"))
        written_out_gradients(seg, x.cuda(), y.cuda())
        first = [p.grad.clone() for p in seg.parameters()]
        written_out_gradients(seg, x.cuda(), y.cuda())
        for p, q, e in zip(seg.parameters(), first, oracle.parameters()):
            assert p.grad.shape == p.shape and torch.equal(p.grad, q)
            scale = float(e.grad.abs().max())
            assert float((p.grad.double().cpu() - e.grad).abs().max()) <= 1e-5 * scale + 1e-9, (S, W, p.shape)


@pytest.mark.gpu
def test_the_classifier_on_our_kernels_trains_as_torchs():
    """Trained on our kernels (``fused_heads``), recorded or eager, the staged classifier reaches torch's
    head; a head too large for the kernels trains through torch."""
    from virgi_ns.edit.fitting import train_classifier, writes_out
    from virgi_ns.edit.heads import SegmentationHead
    from virgi_ns.raster import cuda

    if not cuda.available()[0]:
        pytest.skip("needs a CUDA GPU and the extension")
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4096, 96, generator=g).cuda()
    y = (x[:, 3:4] - 0.5 * x[:, 40:41] > 0).float()
    alphas = {}
    for fused, graphs in ((False, False), (True, False), (True, True)):
        torch.manual_seed(0)
        seg = SegmentationHead(32, 64, 64).cuda()
        cfg = EditConfig(fused_heads=fused, cuda_graphs=graphs)
        assert writes_out(seg, x, cfg) == fused
        alphas[fused, graphs] = train_classifier(seg, x, y, x, cfg, steps=100)
    for k in ((True, False), (True, True)):
        assert float((alphas[k] - alphas[False, False]).abs().max()) < 1e-3, k
    assert float(((alphas[True, True] > 0.5).float() - y).abs().mean()) < 0.05
    assert not writes_out(SegmentationHead(32, 64, 256).cuda(), x, EditConfig())
    assert not cuda.classifier_fits(96, 256, x.device) and cuda.classifier_fits(96, 64, x.device)


def test_an_engine_on_another_engines_view_fits_the_edit_a_fresh_engine_fits(world):
    """``view_of`` shares the view (contributions, features, colours, render) of an engine of the same
    camera: its fit is the one a fresh engine makes, bit for bit, and the first engine's view is untouched.
    An engine of another camera is refused."""
    S = world["S"]
    rgb, _, small = _patch_edit(world)
    cfg = EditConfig(steps=12)
    cam = S.cameras.index(EDIT_VIEW)
    first = EditEngine(S.scene, cam, small, cfg=cfg, original=rgb)
    current = first.current.clone()
    first.fit()
    shared = EditEngine(S.scene, cam, small, cfg=cfg, original=rgb, view_of=first)
    fresh = EditEngine(S.scene, cam, small, cfg=cfg, original=rgb)
    assert shared.contrib is first.contrib and fresh.contrib is not first.contrib
    a, b = shared.fit()[0], fresh.fit()[0]
    assert torch.equal(a.head_weight, b.head_weight) and torch.equal(a.head_bias, b.head_bias)
    for p, q in zip(a.seg.parameters(), b.seg.parameters()):
        assert torch.equal(p, q)
    assert torch.equal(first.current, current)
    with pytest.raises(ValueError, match="same scene, camera"):
        EditEngine(S.scene, S.cameras.index(HELD_OUT[0]), None, cfg=cfg, view_of=first)
    larger = dataclasses.replace(cam, widths=cam.widths + 8)  # the same pose, another image size
    with pytest.raises(ValueError, match="same scene, camera"):
        EditEngine(S.scene, larger, None, cfg=cfg, view_of=first)


def test_the_shared_view_is_everything_the_view_set_up_computes(world):
    """An engine built ``view_of`` another copies :data:`VIEW_FIELDS`; those must be exactly the attributes the
    view's set-up writes, so that a field added to one and not the other fails here, not in a user's refit."""
    S = world["S"]
    bare = EditEngine.__new__(EditEngine)
    bare.scene, bare.camera, bare.stack, bare.cfg = S.scene, S.cameras.index(EDIT_VIEW), None, EditConfig()
    before = set(vars(bare))
    bare._setup_view()
    assert set(vars(bare)) - before == set(VIEW_FIELDS)


def _patch_edit(world) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(the edit view's render, a 7x7 patch at the centre of its blue object, the render with that patch
    recoloured blue -> red): a user's edit of a small part of an object."""
    rgb = world["before"][EDIT_VIEW]["rgb"]
    edited, mask = recolor(rgb, BLUE_TO_RED)
    ys, xs = torch.nonzero(mask, as_tuple=True)
    cy, cx = int(ys.float().mean()), int(xs.float().mean())
    patch = torch.zeros_like(mask)
    patch[cy - 3 : cy + 4, cx - 3 : cx + 4] = True
    patch &= mask
    return rgb, patch, torch.where(patch[..., None], edited, rgb)


def test_a_small_edit_is_not_outvoted_by_the_unchanged_pixels(world):
    """A user recolours a 7x7 patch of the blue object (under 1% of the view). With the original
    known, the changed pixels carry half the loss (``changed_share``): the whole object turns red in
    the held-out views. Weighted by their number instead, the unchanged pixels (asking for no change
    at all) win and nothing happens."""
    S = world["S"]
    rgb, patch, small = _patch_edit(world)
    assert 0 < float(patch.float().mean()) < 0.01
    miss = {}
    for name, share in (("balanced", 0.5), ("by count", float(patch.float().mean()))):
        eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), small, cfg=EditConfig(steps=40, changed_share=share),
                         original=rgb)
        stack = _stack(world, eng.fit()[0])
        b = world["before"][HELD_OUT[0]]["rgb"]
        truth, m = recolor(b, BLUE_TO_RED)
        miss[name] = float((_render(world, HELD_OUT[0], stack)["rgb"] - truth).abs()[m].mean())
    assert miss["balanced"] < 0.25 * miss["by count"], miss
    assert miss["balanced"] < 0.1
    # without the original: the edited render's untouched pixels are recognised as such
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), small, cfg=EditConfig(steps=40))
    assert eng.mode == "changed pixels (an edited render)"
    assert abs(eng.changed_fraction - float(patch.float().mean())) < 0.002
    whole = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), small, cfg=EditConfig(whole_image=True))
    assert whole.mode == "whole image" and whole.changed_fraction == 1.0
    # a render edited for a training view: the photo given as the original is not what it started from
    photo = (rgb + 0.2).clamp(0, 1)
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), small, original=photo)
    assert eng.mode == "changed pixels (an edited render)"
    with pytest.raises(InputError, match="current render"):
        EditEngine(S.scene, S.cameras.index(EDIT_VIEW), rgb)
    stack = _stack(world, eng.fit()[0])
    b = world["before"][HELD_OUT[0]]["rgb"]
    truth, m = recolor(b, BLUE_TO_RED)
    assert float((_render(world, HELD_OUT[0], stack)["rgb"] - truth).abs()[m].mean()) < 0.1


def test_logit_colour_map_recovers_affine_maps():
    """The least-squares map in logit space: a channel permutation (a hue shift of 120 degrees) and
    a random affine map are found again; pixels of one colour leave the map at the identity."""
    from virgi_ns.edit.targets import logit_colour_map

    g = torch.Generator().manual_seed(0)
    src = 0.05 + 0.9 * torch.rand(5000, 3, generator=g)
    shifted, mask = recolor(src, RecolorRule(h0=0, h1=360, shift=120, s_min=0.0, v_min=0.0))
    assert bool(mask.all())
    assert torch.allclose(shifted, src[:, [2, 0, 1]], atol=1e-5)  # +120 degrees = (r, g, b) -> (b, r, g)
    B = logit_colour_map(src, shifted, ridge=0.0, ridge_floor=0.0)
    P = torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
    assert torch.allclose(B[:, :3], P, atol=1e-4) and B[:, 3].abs().max() < 1e-4
    A = torch.tensor([[0.8, 0.3, -0.1], [0.0, 1.2, 0.2], [-0.3, 0.1, 0.9]])
    t = torch.tensor([0.2, -0.4, 0.1])
    tgt = torch.sigmoid(torch.logit(src) @ A.T + t)
    inside = ((tgt > 0.02) & (tgt < 0.98)).all(-1)  # the fit clamps colours outside [0.02, 0.98]
    B = logit_colour_map(src[inside], tgt[inside], ridge=0.0, ridge_floor=0.0, max_pixels=1 << 20)
    assert torch.allclose(B[:, :3], A, atol=1e-3) and torch.allclose(B[:, 3], t, atol=1e-3)
    # one colour (plus a little noise): M stays near the identity, t carries the change
    one = torch.tensor([0.2, 0.3, 0.7]) + 0.01 * torch.randn(200, 3, generator=g)
    red = torch.tensor([0.7, 0.3, 0.2]) + 0.01 * torch.randn(200, 3, generator=g)
    B = logit_colour_map(one, red)
    assert torch.allclose(B[:, :3], torch.eye(3), atol=0.3), B
    mapped = torch.sigmoid(torch.logit(one) @ B[:, :3].T + B[:, 3])
    assert float((mapped - red).abs().mean()) < 0.02


def test_colour_map_start_fits_a_channel_swap_sooner(world, monkeypatch):
    """A hue shift of 120 degrees is a channel permutation, exactly a logit-space map: the edit that
    starts from the fitted map has a lower loss after a few steps than one starting from the
    unedited layer, and both land the recolour. The map is used only for edits that change at least
    ``MAP_START_SHARE`` of the view."""
    import virgi_ns.edit.engine as engine

    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    render = world["before"][EDIT_VIEW]["rgb"]
    rule = RecolorRule(h0=190, h1=260, shift=120, s_min=0.3, v_min=0.1)
    edited, mask = recolor(render, rule)
    share = float(((edited - render).abs().amax(-1) > 3 / 255).float().mean())
    assert 0.02 < share < 0.5
    loss = {}
    for init in (True, False):
        monkeypatch.setattr(engine, "MAP_START_SHARE", share - 0.01 if init else share + 0.01)
        eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=15), original=render)
        assert (eng.colour_map is not None) == init
        _, timing = eng.fit()
        loss[init] = timing.final_loss
        out = eng.preview()["rgb"]
        assert float((out - edited).abs()[mask].mean()) < float((render - edited).abs()[mask].mean())
    assert loss[True] < 0.8 * loss[False], loss


@pytest.mark.gpu
@pytest.mark.parametrize("recipe,most", [("joint", False), ("staged", False), ("joint", True)])
def test_cuda_graph_steps_give_the_eager_steps_edit(world, recipe, most):
    """``cuda_graphs``: the recorded steps replay the eager steps' kernels in the eager order, so the
    edit (layer, segmentation, final loss) is the eager one's: the schedule's rate too, computed on the
    device from Adam's step count at each replay, and (``most``: a selection of most of the view) the
    segmentation head's own rate."""
    S = world["S"]
    sc = S.scene
    gpu = es.on_gpu(sc)
    cam = S.cameras.index(EDIT_VIEW)
    edited = world["edited"].cuda()
    H = edited.shape[0]
    selection = None
    if most:
        selection = torch.zeros(edited.shape[:2], dtype=torch.bool, device="cuda")
        selection[: 3 * H // 4] = True
    fits = {}
    for graphs in (True, False):
        cfg = EditConfig(steps=30, cuda_graphs=graphs, recipe=recipe, seg_samples=4096, seg_steps=50)
        eng = EditEngine(gpu, cam, edited, EditStack(gpu.fingerprint()), cfg, changed=selection)
        assert eng.opt.scales[2:] == [2.0 if most else 1.0] * (len(eng.opt.scales) - 2)
        fits[graphs] = eng.fit()
    (e_g, t_g), (e_e, t_e) = fits[True], fits[False]
    torch.testing.assert_close(e_g.head_weight, e_e.head_weight, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(e_g.head_bias, e_e.head_bias, atol=1e-5, rtol=1e-5)
    x = torch.randn(64, e_g.seg.l1.in_features, device="cuda")
    torch.testing.assert_close(e_g.seg.logits_of(x), e_e.seg.logits_of(x), atol=1e-4, rtol=1e-4)
    assert abs(t_g.final_loss - t_e.final_loss) < 1e-5
    assert not torch.equal(e_g.head_weight, torch.as_tensor(sc.field.diffuse_head.weight).cuda())  # it trained


@pytest.mark.gpu
def test_written_out_heads_give_the_autograd_edit(world):
    """``fused_heads`` (virgi_ns.edit.heads): from the same state, a step with the heads' backward
    written out gives every parameter autograd's gradient (on a target every pixel is far from: where
    a pixel's L1 error is 0 up to rounding, its sign is rounding's); a whole fit then renders
    autograd's edit. (The parameters themselves drift apart further: Adam divides gradients near its
    epsilon by their own size, so rounding of the order of 1e-9 there moves a weight by up to lr / 10.)"""
    from virgi_ns.raster import cuda

    if not cuda.available()[0]:
        pytest.skip("needs our CUDA extension")
    S = world["S"]
    sc = S.scene
    gpu = es.on_gpu(sc)
    cam = S.cameras.index(EDIT_VIEW)
    edited = world["edited"].cuda()
    grads, fits = {}, {}
    for written in (True, False):
        cfg = EditConfig(steps=30, batch_composite="fused", fused_heads=written, whole_image=True)
        eng = EditEngine(gpu, cam, 0.1 + 0.8 * edited, EditStack(gpu.fingerprint()), cfg)
        assert (eng._heads is not None) == written
        with torch.enable_grad():
            eng.step(0)
        grads[written] = [p.grad.clone() for p in (eng.weight, eng.bias, *eng.seg.parameters())]
        cfg = EditConfig(steps=30, batch_composite="fused", fused_heads=written)
        eng = EditEngine(gpu, cam, edited, EditStack(gpu.fingerprint()), cfg)
        edit, timing = eng.fit()
        fits[written] = (eng.preview()["rgb"], timing.final_loss, edit)
    for i, (got, want) in enumerate(zip(grads[True], grads[False])):
        assert got.shape == want.shape
        diff, scale = float((got - want).abs().max()), float(want.abs().max())
        assert diff <= 1e-5 * scale + 1e-9, (i, diff, scale)
    (rgb_w, loss_w, e_w), (rgb_a, loss_a, _) = fits[True], fits[False]
    assert abs(loss_w - loss_a) <= 1e-3 * loss_a, (loss_w, loss_a)
    diff = float((rgb_w - rgb_a).abs().max())
    assert diff <= 2e-3, diff  # half an 8-bit level
    assert not torch.equal(e_w.head_weight, torch.as_tensor(sc.field.diffuse_head.weight).cuda())  # it trained


@pytest.mark.gpu
def test_the_written_out_staged_step_gives_the_autograd_edit(world):
    """``fused_heads`` with the staged recipe (``FusedLayer``): from the same state (the same fixed
    segmentation), a step gives the copied layer autograd's gradient, and a whole fit renders autograd's
    edit; the layer step holds the engine's fixed alpha, which a retarget writes in place."""
    from virgi_ns.edit.heads import FusedLayer
    from virgi_ns.raster import cuda

    if not cuda.available()[0]:
        pytest.skip("needs our CUDA extension")
    S = world["S"]
    gpu = es.on_gpu(S.scene)
    cam = S.cameras.index(EDIT_VIEW)
    rgb = world["before"][EDIT_VIEW]["rgb"]
    edited, _ = recolor(rgb, BLUE_TO_RED)
    grads, fits = {}, {}
    for written in (True, False):
        cfg = EditConfig(steps=30, batch_composite="fused", fused_heads=written, recipe="staged", seg_steps=40,
                         seg_samples=2048)
        eng = EditEngine(gpu, cam, edited.cuda(), EditStack(gpu.fingerprint()), cfg, original=rgb.cuda())
        assert isinstance(eng._heads, FusedLayer) == written
        if written:
            assert eng._heads.alpha is eng.alpha_fixed
        with torch.enable_grad():
            eng.step(0)
        grads[written] = [eng.weight.grad.clone(), eng.bias.grad.clone()]
        eng = EditEngine(gpu, cam, edited.cuda(), EditStack(gpu.fingerprint()), cfg, original=rgb.cuda())
        edit, timing = eng.fit()
        fits[written] = (eng.preview()["rgb"], timing.final_loss)
    for i, (got, want) in enumerate(zip(grads[True], grads[False])):
        assert got.shape == want.shape
        diff, scale = float((got - want).abs().max()), float(want.abs().max())
        assert scale > 0.0 and diff <= 1e-5 * scale + 1e-9, (i, diff, scale)
    (rgb_w, loss_w), (rgb_a, loss_a) = fits[True], fits[False]
    assert abs(loss_w - loss_a) <= 1e-3 * loss_a, (loss_w, loss_a)
    assert float((rgb_w - rgb_a).abs().max()) <= 2e-3  # half an 8-bit level


def test_a_fresh_segmentation_head_is_drawn_from_the_seed_and_copied_per_edit(world):
    """The engine's fresh head equals one drawn anew with the config's seed, whatever ran before, and
    training one engine's head leaves the next engine's start untouched."""
    from virgi_ns.edit.heads import SegmentationHead

    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    cfg = EditConfig(steps=5, seed=3)
    first = EditEngine(S.scene, cam, world["edited"], cfg=cfg)
    torch.manual_seed(123)  # the global RNG's state must not matter
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        want = SegmentationHead(first.feats.shape[1], first.h_diff.shape[1], cfg.seg_width, cfg.seg_init_bias)
    start = {k: v.clone() for k, v in first.seg.state_dict().items()}
    for k, v in want.state_dict().items():
        assert torch.equal(start[k], v), k
    first.fit()
    assert not torch.equal(first.seg.l2.weight, start["l2.weight"])  # trained
    second = EditEngine(S.scene, cam, world["edited"], cfg=cfg)
    for k, v in second.seg.state_dict().items():
        assert torch.equal(v, start[k]), k
    other = EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=5, seed=4))
    assert not torch.equal(other.seg.l1.weight, second.seg.l1.weight)


@pytest.mark.parametrize("pixel_batches,composite", [(1, "csr"), (4, "csr"), (4, "fused")])
def test_fit_loss_is_the_weighted_l1_of_the_preview_against_the_target(world, pixel_batches, composite):
    """``EditEngine.fit_loss`` (a fit's loss on every pixel set at once) against the same loss computed
    on the whole preview: the changed pixels carry ``changed_share`` of it, the rest the remainder,
    each group's |preview - target| averaged over its pixels and channels (the ``count`` weights, named
    so the test holds whichever weights are the default). The sets split each group
    evenly, so their mean equals the whole view's up to one pixel's share of a set."""
    S = world["S"]
    render = world["before"][EDIT_VIEW]["rgb"]
    g = torch.Generator().manual_seed(5)
    photo = (render + 0.1 * (torch.rand(render.shape, generator=g) - 0.5)).clamp(0, 1)
    edited, _ = recolor(photo, BLUE_TO_RED)
    cfg = EditConfig(steps=15, pixel_batches=pixel_batches, changed_share=0.7, batch_composite=composite,
                     unchanged_weights="count")
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), edited, cfg=cfg, original=photo)
    eng.fit()
    err = (eng.preview()["rgb"] - eng.target.image).abs().mean(-1).reshape(-1)
    changed = eng.target.flat
    assert 0 < int(changed.sum()) < changed.numel()
    expected = 0.7 * float(err[changed].mean()) + 0.3 * float(err[~changed].mean())
    assert eng.batches[0].composite == composite
    assert eng.fit_loss() == pytest.approx(expected, rel=1e-6 if pixel_batches == 1 else 2e-4)
    # and it is the fit's own: a fresh engine's heads (no steps) score worse on the same target
    fresh = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), edited, cfg=cfg, original=photo)
    assert fresh.fit_loss() > 1.5 * eng.fit_loss()


def _fitted_on_the_worlds_edit(world, **settings) -> EditEngine:
    """An engine fitted to the world's edit (a small one) with these EditConfig settings."""
    S = world["S"]
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"], cfg=EditConfig(**settings))
    eng.fit()
    return eng


def test_an_edit_of_most_of_the_view_alone_steps_the_segmentation_head_faster(world):
    """Where the changed pixels are more of the view than ``changed_share`` (here: a share below the
    world's changed fraction) but not all of it, the joint recipe's segmentation head steps at
    ``LARGE_EDIT_SEG_RATE`` times ``lr``; not at the share itself, not for a selection of the whole view
    (no unchanged pixel to outweigh anything), not for an edit under the share."""
    from virgi_ns.edit.fitting import LARGE_EDIT_SEG_RATE

    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    small = _fitted_on_the_worlds_edit(world, steps=5)
    assert small.changed_fraction < EditConfig().changed_share
    assert small.opt.scales == [1.0] * len(small.opt.scales)
    fraction = small.changed_fraction
    H, W = world["edited"].shape[:2]
    for share, whole, want in ((0.5 * fraction, False, LARGE_EDIT_SEG_RATE), (fraction, False, 1.0), (0.5, True, 1.0)):
        selection = torch.ones(H, W, dtype=torch.bool) if whole else None
        eng = EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=1, changed_share=share), changed=selection)
        assert eng.changed_fraction == (1.0 if whole else fraction)
        assert eng.opt.scales[:2] == [1.0, 1.0]
        assert eng.opt.scales[2:] == [want] * (len(eng.opt.scales) - 2), (share, whole)


@pytest.mark.parametrize("steps,hold", [(100, 50), (3, 1), (2, 0), (1, 0), (7, 3)])
def test_the_hold_leaves_at_least_one_step_to_decay(world, steps, hold):
    """The engine's hold is the floor of ``LR_HOLD * steps``, at most ``steps - 2`` (the cosine's first
    step is still at ``lr``), and the decay spans the rest: the last step's rate is below ``lr``
    whenever there are two steps or more."""
    S = world["S"]
    eng = EditEngine(S.scene, S.cameras.index(EDIT_VIEW), world["edited"], cfg=EditConfig(steps=steps))
    assert (eng.opt.hold_steps, eng.opt.decay_steps) == (hold, max(steps - hold, 1))
    if steps > 1:
        assert eng.opt.lr_at(steps - 1) < eng.cfg.lr


def _constant_rate(eng: EditEngine) -> EditEngine:
    """``eng`` with its optimizer's schedule off: the rate is ``eng.opt.lr`` at every step."""
    eng.opt.decay_steps, eng.opt.hold_steps = None, 0
    return eng


def test_the_schedule_is_the_constant_fit_with_its_rate_decayed_step_by_step(world):
    """The edit's schedule (the rate computed on the device from Adam's step count) against a
    constant-rate engine stepped by hand with the rate set before each step: lr for the first
    ``LR_HOLD * n`` steps h, then lr (1 + cos(pi (k - h) / (n - h))) / 2."""
    import math

    from virgi_ns.edit.fitting import LR_HOLD

    S = world["S"]
    cam = S.cameras.index(EDIT_VIEW)
    n = 20
    h = round(LR_HOLD * n)
    eng = EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=n))
    eng.fit()
    hand = _constant_rate(EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=n)))
    with torch.enable_grad():
        for k in range(n):
            hand.opt.lr = hand.cfg.lr if k < h else 0.5 * hand.cfg.lr * (1 + math.cos(math.pi * (k - h) / (n - h)))
            hand.step(k)
    torch.testing.assert_close(eng.weight, hand.weight, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(eng.preview()["rgb"], hand.preview()["rgb"], atol=1e-5, rtol=0)
    constant = _constant_rate(EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=n)))
    constant.fit()
    assert float((constant.weight - eng.weight).abs().max()) > 1e-3  # the schedule changes the fit
    # the schedule spans every fit of one target: 8 steps, then 12 more, are the 20 steps at once
    split = EditEngine(S.scene, cam, world["edited"], cfg=EditConfig(steps=n))
    split.fit(8)
    split.fit(n - 8)
    torch.testing.assert_close(split.weight, eng.weight, atol=1e-6, rtol=1e-6)


def test_a_fit_that_leaves_the_changed_pixels_where_they_were_says_so(world):
    """``changed_progress``: how far the fit moved the changed pixels towards their target, against the same
    figure computed here from the preview; a fit that stalls (a 7x7 patch outvoted by the unchanged pixels at a
    tiny share) gets the note, one that takes the edit does not, and a whole-image fit has no figure."""
    from virgi_ns.edit.engine import SMALL_PROGRESS

    S = world["S"]
    rgb, patch, small = _patch_edit(world)
    cam = S.cameras.index(EDIT_VIEW)
    taken = EditEngine(S.scene, cam, small, cfg=EditConfig(steps=40), original=rgb)
    assert taken.changed_progress() == pytest.approx(0.0, abs=1e-6)  # before any step: nothing moved
    taken.fit()
    stalled = EditEngine(S.scene, cam, small, cfg=EditConfig(steps=40, changed_share=0.02), original=rgb)
    stalled.fit()
    for eng in (taken, stalled):  # against the preview and the edited patch, computed here
        after = eng.preview()["rgb"][patch]
        want = 1.0 - float((after - small[patch]).abs().mean()) / float((eng.current[patch] - small[patch]).abs().mean())
        assert eng.changed_progress() == pytest.approx(want, abs=1e-4)
    assert taken.changed_progress() > 0.5 and taken.small_progress_note() is None
    assert stalled.changed_progress() < SMALL_PROGRESS
    assert "changes almost nothing" in stalled.small_progress_note()
    whole = EditEngine(S.scene, cam, small, cfg=EditConfig(steps=5, whole_image=True))
    whole.fit()
    assert whole.changed_progress() is None and whole.small_progress_note() is None
    # a selection recoloured to its own colour asks nothing of its pixels: no figure, no warning
    same = EditEngine(S.scene, cam, rgb, cfg=EditConfig(steps=5), changed=patch)
    same.fit()
    assert same.changed_progress() is None and same.small_progress_note() is None
