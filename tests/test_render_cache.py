"""The render cache serves what the colour model computes without it, and every change that must
invalidate it does: the edit stack (an edit added, replaced, undone, toggled, changed in place,
``k`` set, another stack), the live edit of a pick, the field (a training step, an in-place
change), the gate (rebuilt, another threshold) and the Gaussians. The served colours are compared
with the field's own forward over all Gaussians, never with the cache itself, and every change is
checked to move that reference, so a stale serve fails these tests."""

from __future__ import annotations

import gc
import warnings

import pytest
import torch

from test_model_train import build, scene, train  # noqa: F401  (fixture re-exported)
from virgi_ns.colour.field import view_directions
from virgi_ns.edit.stack import Edit, EditSource, EditStack, SegmentationHead
from virgi_ns.nerfstudio.render_cache import ColourGraph, ViewColours, ViewOutputs
from virgi_ns.raster import Cameras, Request, composite

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")

TOL = 1e-6


@pytest.fixture(scope="module")
def gated_model(scene):  # noqa: F811
    steps = 8
    _, pipeline, optimizers, cbs = build(scene, steps=steps)
    train(pipeline, optimizers, cbs, steps)  # the last step builds the gate
    pipeline.eval()
    model = pipeline.model
    assert model.gate_ready()
    # every Gaussian on the gated path: MLP_spec still runs everywhere, c_d comes from the cache,
    # so the two renders differ only by the cache
    model.config.gate_threshold = -1.0
    cam = pipeline.datamanager.eval_dataset.cameras[0:1].to(model.device)
    return pipeline, model, cam


def _edit(model, seed: int) -> Edit:
    """An edit with a random last layer and a segmentation that takes part of the scene."""
    g = torch.Generator().manual_seed(seed)
    head = model.field.diffuse_head
    seg = SegmentationHead(model.field.feature_dim, head.in_features, init_bias=0.0)
    with torch.no_grad():
        for p in seg.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    w = head.weight.detach().cpu().clone() + torch.randn(head.weight.shape, generator=g)
    b = head.bias.detach().cpu().clone() + torch.randn(3, generator=g)
    return Edit(w, b, seg, EditSource("random.png", torch.eye(3), torch.eye(4), 8, 8), model.fingerprint())


def _check(model, cam, previous=None) -> torch.Tensor:
    """The cached render equals the uncached one; returns it. With ``previous``, the change just
    made must also show (else the comparison could not catch a stale cache)."""
    cached = model.render_camera(cam, gated=True)
    fresh = model.render_camera(cam, gated=False)
    for key in ("rgb", "diffuse", "segmentation"):
        assert (cached[key] - fresh[key]).abs().max() <= TOL, key
    if previous is not None:
        assert (cached["rgb"] - previous).abs().max() > 1e-3, "the change did not show in the render"
    return cached["rgb"]


def test_cached_render_equals_uncached_render(gated_model):
    _, model, cam = gated_model
    model.set_edit_stack(None)
    _check(model, cam)
    stack = EditStack(model.fingerprint())
    stack.add(_edit(model, 1))
    model.set_edit_stack(stack)
    _check(model, cam)


def test_every_stack_change_invalidates_the_cached_colours(gated_model):
    _, model, cam = gated_model
    stack = EditStack(model.fingerprint())
    model.set_edit_stack(stack)
    img = _check(model, cam)
    stack.add(_edit(model, 2))  # an edit added
    img = _check(model, cam, img)
    stack.set_enabled(1, False)  # a toggle
    img = _check(model, cam, img)
    stack.set_enabled(1, True)
    img = _check(model, cam, img)
    stack.add(_edit(model, 3))
    img = _check(model, cam, img)
    stack.undo()  # an undo, then a new edit that may take the undone one's memory
    gc.collect()
    img = _check(model, cam, img)
    stack.add(_edit(model, 4))
    img = _check(model, cam, img)
    with torch.no_grad():  # an edit changed in place (a live refit), announced to the stack
        stack.entries[-1].edit.head_bias += 1.0
    stack.changed()
    img = _check(model, cam, img)
    stack.set_specular_strength(0.0)  # k: no highlights left
    img = _check(model, cam, img)
    other = EditStack(model.fingerprint())  # another stack object with other edits
    other.add(_edit(model, 5))
    model.set_edit_stack(other)
    img = _check(model, cam, img)
    stack.reset()  # a change to a stack no longer set must not matter; back to it: empty
    model.set_edit_stack(stack)
    _check(model, cam, img)


def test_the_revision_counts_every_change():
    stack = EditStack("fp")
    seen = [stack.revision]

    def bumped():
        seen.append(stack.revision)
        return seen[-1] > seen[-2]

    edit = Edit(torch.zeros(3, 4), torch.zeros(3), SegmentationHead(2, 4), EditSource("x", torch.eye(3), torch.eye(4), 1, 1),
                "fp")
    stack.add(edit)
    assert bumped()
    stack.set_enabled(1, False)
    assert bumped()
    stack.set_specular_strength(0.5)
    assert bumped()
    stack.to("cpu")
    assert bumped()
    stack.undo()
    assert bumped()
    stack.reset()
    assert bumped()


def test_training_the_field_drops_the_gate(scene):  # noqa: F811
    steps = 4
    _, pipeline, optimizers, cbs = build(scene, steps=steps)
    train(pipeline, optimizers, cbs, steps)
    model = pipeline.model
    assert model.gate_ready()
    cached = model.diffuse_cache.clone()
    # one more colour step (as a resumed run takes): the field moves, its cached colours go
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    pipeline.train()
    for cb in cbs:
        cb.run_callback_at_location(1, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    assert not model.gate_ready()
    # the gate built again serves the trained field's colours, not the old ones
    with torch.no_grad():
        model.field.diffuse_head.bias += 0.5
    model.build_specular_gate(model._train_cameras_fn())
    assert model.gate_ready()
    assert (model.diffuse_cache - cached).abs().min() > 0.4


@pytest.mark.gpu
def test_gsplat_whole_view_render_matches_the_contribution_lists(gated_model):
    """On a GPU whole views go through gsplat with one colour per Gaussian; they must show what the
    contribution lists composite (the rasterizers differ only at alpha cut-offs)."""
    pipeline, model, cam = gated_model
    pipeline.to("cuda")
    try:
        cam = cam.to("cuda")
        stack = EditStack(model.fingerprint())
        stack.add(_edit(model, 6))
        model.set_edit_stack(stack)
        for gated in (False, True):
            model.config.whole_view_renderer = "contributions"
            ref = model.render_camera(cam, gated=gated)
            model.config.whole_view_renderer = "gsplat"
            out = model.render_camera(cam, gated=gated)
            for key in ("rgb", "diffuse", "specular", "accumulation", "segmentation", "depth"):
                diff = (out[key] - ref[key]).abs()
                assert out[key].shape == ref[key].shape, key
                assert diff.mean() < 1e-3 and diff.max() < 5e-2, (key, float(diff.mean()), float(diff.max()))
    finally:
        model.set_edit_stack(None)
        pipeline.to("cpu")


# ------------------------------------------------------------ per-Gaussian colours
@pytest.fixture(scope="module")
def spec_model(scene):  # noqa: F811
    """A trained model whose specular branch is made strong (random MLP_spec), with a gate that
    keeps about half of the Gaussians."""
    pipeline = _gated_specular_pipeline(scene, steps=8, seed=0)
    model = pipeline.model
    cams = pipeline.datamanager.eval_dataset.cameras
    return pipeline, model, cams


def _strong_specular(model, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for layer in (model.field.spec_l1, model.field.spec_l2, model.field.spec_l3):
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) * 0.3)
            layer.bias.copy_(torch.randn(layer.bias.shape, generator=g) * 0.3)


def _gated_specular_pipeline(scene, steps: int, seed: int):  # noqa: F811
    """A model trained ``steps`` steps (``seed``), its specular branch made strong (random MLP_spec),
    with a gate that keeps about half of the Gaussians; in eval mode."""
    _, pipeline, optimizers, cbs = build(scene, steps=steps, seed=seed)
    train(pipeline, optimizers, cbs, steps)
    pipeline.eval()
    model = pipeline.model
    _strong_specular(model, seed=seed)
    model.build_specular_gate(model._train_cameras_fn())
    model.config.gate_threshold = float(model.spec_magnitude.median())
    return pipeline


def _centre(cam) -> torch.Tensor:
    """The camera centre straight from nerfstudio's camera-to-world matrix."""
    return cam.camera_to_worlds.reshape(-1, 3, 4)[0, :, 3][None]


@torch.no_grad()
def _reference(model, cam, gate) -> dict:
    """Per-Gaussian colours of ``cam``'s view from the field's forward over all Gaussians, the
    enabled edits (then the live edit) composed one by one, ``c_s`` kept where ``gate`` (a
    boolean [N], or None for every Gaussian) is true."""
    fld = model.field
    means = model.means.detach()
    out = fld(means, view_directions(means, _centre(cam)))
    f = fld.encode(means)
    _, h2 = fld.diffuse_hidden(f)
    c_d, c_s = out["c_d"], out["c_s"]
    st, k, keep = model.edit_stack, 1.0, torch.ones_like(c_d[:, :1])
    if st is not None:
        for e in st.entries:
            if e.enabled:
                c_d = e.edit.over(f, h2, c_d)
                keep = keep * (1 - e.edit.alpha(f, h2))
        k = st.specular_strength
    if model.live_edit is not None:
        c_d = model.live_edit.over(f, h2, c_d)
    if gate is not None:
        c_s = c_s * gate[:, None]
    if st is not None and model.segmentation_edit is not None:
        seg = st.entries[model.segmentation_edit - 1].edit.alpha(f, h2)
    else:
        seg = 1 - keep
    return {"rgb": torch.sigmoid(c_d + k * c_s), "diffuse": torch.sigmoid(c_d), "segmentation": seg}


def _check_colours(model, cam, gate="model", previous=None) -> torch.Tensor:
    """The gated colours served for ``cam`` equal :func:`_reference` (``gate="model"``: the
    model's measured magnitudes over its threshold); with ``previous``, the reference moved."""
    if isinstance(gate, str):
        gate = model.spec_magnitude > model.config.gate_threshold
    got = model.view_colours(model.view_of(cam), gated=True)
    want = _reference(model, cam, gate)
    assert (got.rgb - want["rgb"]).abs().max() <= TOL
    diffuse = got.diffuse if got.diffuse is not None else got.rgb
    assert (diffuse - want["diffuse"]).abs().max() <= TOL
    if model.edit_stack is not None and len(model.edit_stack) > 0:
        assert (got.segmentation() - want["segmentation"]).abs().max() <= TOL
    else:
        assert got.segmentation is None
    if previous is not None:
        assert (want["rgb"] - previous).abs().max() > 1e-3, "the change did not move the reference"
    return want["rgb"]


def test_gated_colours_equal_the_field_over_all_gaussians(spec_model):
    _, model, cams = spec_model
    median = model.config.gate_threshold
    try:
        model.set_edit_stack(None)
        for t in (median, -1.0, float("inf")):
            model.config.gate_threshold = t
            for i in range(2):  # two views: only the direction changes between them
                _check_colours(model, cams[i : i + 1])
            kept = model.render_cache.gate_level.size
            assert kept == {median: model.num_points // 2, -1.0: model.num_points}.get(t, 0)
        stack = EditStack(model.fingerprint())
        stack.add(_edit(model, 11))
        model.set_edit_stack(stack)
        model.config.gate_threshold = median
        for k in (0.5, 1.7, 0.0):
            stack.set_specular_strength(k)
            _check_colours(model, cams[0:1])
    finally:
        model.config.gate_threshold = median
        model.set_edit_stack(None)


def test_matte_colours_are_the_cached_tensor(spec_model):
    """A view the gate keeps nothing of (or with k = 0) is served the cached colours as they are:
    no per-frame work, diffuse = rgb."""
    _, model, cams = spec_model
    median = model.config.gate_threshold
    try:
        model.config.gate_threshold = float("inf")
        a = model.view_colours(model.view_of(cams[0:1]), gated=True)
        b = model.view_colours(model.view_of(cams[1:2]), gated=True)
        assert a.rgb is b.rgb and a.diffuse is None and b.diffuse is None
        model.config.gate_threshold = median
        stack = EditStack(model.fingerprint())
        stack.set_specular_strength(0.0)
        model.set_edit_stack(stack)
        a = model.view_colours(model.view_of(cams[0:1]), gated=True)
        assert a.diffuse is None and a.rgb is model.view_colours(model.view_of(cams[1:2]), gated=True).rgb
        _check_colours(model, cams[0:1])
    finally:
        model.config.gate_threshold = median
        model.set_edit_stack(None)


def test_every_change_reaches_the_cached_colours(spec_model):
    _, model, cams = spec_model
    cam = cams[0:1]
    median = model.config.gate_threshold
    try:
        stack = EditStack(model.fingerprint())
        model.set_edit_stack(stack)
        ref = _check_colours(model, cam)
        stack.add(_edit(model, 12))  # an edit added
        ref = _check_colours(model, cam, previous=ref)
        stack.add(_edit(model, 13))
        ref = _check_colours(model, cam, previous=ref)
        model.segmentation_edit = 1  # the segmentation of one edit, then of all
        _check_colours(model, cam)
        model.segmentation_edit = None
        stack.set_enabled(2, False)  # a toggle
        ref = _check_colours(model, cam, previous=ref)
        stack.set_enabled(2, True)
        ref = _check_colours(model, cam, previous=ref)
        stack.replace(2, _edit(model, 14))  # an edit replaced (a pick adjusted after its commit)
        ref = _check_colours(model, cam, previous=ref)
        stack.undo()  # an undo
        gc.collect()
        ref = _check_colours(model, cam, previous=ref)
        with torch.no_grad():  # an edit changed in place, announced to the stack
            stack.entries[-1].edit.head_bias += 1.0
        stack.changed()
        ref = _check_colours(model, cam, previous=ref)
        stack.set_specular_strength(0.4)  # k
        ref = _check_colours(model, cam, previous=ref)
        live = _edit(model, 15)  # a pick's live edit, changed, then cleared
        model.set_live_edit(live)
        ref = _check_colours(model, cam, previous=ref)
        with torch.no_grad():
            live.head_bias -= 2.0
        model.set_live_edit(live)
        ref = _check_colours(model, cam, previous=ref)
        model.set_live_edit(None)
        ref = _check_colours(model, cam, previous=ref)
        model.config.gate_threshold = float(model.spec_magnitude.quantile(0.9))  # another threshold
        ref = _check_colours(model, cam, previous=ref)
        model.config.gate_threshold = median
        ref = _check_colours(model, cam, previous=ref)
        other = EditStack(model.fingerprint())  # another stack
        other.add(_edit(model, 16))
        model.set_edit_stack(other)
        ref = _check_colours(model, cam, previous=ref)
        twin = EditStack(model.fingerprint())  # another stack at the same revision
        twin.add(_edit(model, 19))
        model.set_edit_stack(twin)
        assert twin.revision == other.revision
        ref = _check_colours(model, cam, previous=ref)
        model.set_edit_stack(None)  # no stack
        _check_colours(model, cam, previous=ref)
    finally:
        model.set_live_edit(None)
        model.set_edit_stack(None)
        model.config.gate_threshold = median


def test_a_changed_field_is_never_served_from_the_cache(scene):  # noqa: F811
    """A field changed after the gate was built (a training step, an in-place write) gets the full
    colour model until the gate is built again; the rebuilt gate serves the new field."""
    pipeline = _gated_specular_pipeline(scene, steps=4, seed=1)
    model = pipeline.model
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    ref = _check_colours(model, cam)
    # one optimizer step on the field (no callback drops the gate here)
    opt = torch.optim.Adam(model.field.parameters(), lr=0.05)
    means = model.means.detach()
    out = model.field(means, view_directions(means, _centre(cam)))
    (out["c_d"].sum() + out["c_s"].sum()).backward()
    opt.step()
    assert not model.gate_ready()
    ref = _check_colours(model, cam, gate=None, previous=ref)
    model.build_specular_gate(model._train_cameras_fn())  # the gate rebuilt for the new field
    assert model.gate_ready()
    ref = _check_colours(model, cam, previous=ref)
    with torch.no_grad():  # an in-place write to one layer
        model.field.spec_l2.bias += 0.5
    ref = _check_colours(model, cam, gate=None, previous=ref)
    model.build_specular_gate(model._train_cameras_fn())
    _check_colours(model, cam, previous=ref)


def test_the_geometry_level_follows_the_gaussians(spec_model):
    _, model, _ = spec_model
    g = model.render_cache.geometry(model)
    torch.testing.assert_close(g.opacities, torch.sigmoid(model.opacities.detach()).reshape(-1), rtol=0, atol=0)
    old = model.opacities.detach().clone()
    try:
        with torch.no_grad():
            model.opacities.add_(0.3)
        g = model.render_cache.geometry(model)
        torch.testing.assert_close(g.opacities, torch.sigmoid(model.opacities.detach()).reshape(-1), rtol=0, atol=0)
        torch.testing.assert_close(g.scales, torch.exp(model.scales.detach()), rtol=0, atol=0)
    finally:
        with torch.no_grad():
            model.opacities.copy_(old)


def test_gated_render_equals_the_reference_colours_rendered(spec_model):
    """The whole-view render of the cached colours equals the same renderer given the reference
    colours (a gate keeping half of the Gaussians, an edit on the stack)."""
    _, model, cams = spec_model
    cam = cams[0:1]
    stack = EditStack(model.fingerprint())
    stack.add(_edit(model, 17))
    model.set_edit_stack(stack)
    try:
        got = model.render_camera(cam, gated=True)
        want = _reference(model, cam, model.spec_magnitude > model.config.gate_threshold)
        ref = model.render_view(model.view_of(cam), ViewColours(want["rgb"], want["diffuse"],
                                                                lambda: want["segmentation"]))
        for key in ("rgb", "diffuse", "specular", "segmentation", "depth", "accumulation"):
            assert (got[key] - ref[key]).abs().max() <= TOL, key
        assert got["specular"].abs().max() > 1e-2
    finally:
        model.set_edit_stack(None)


def test_half_precision_cache_is_close(spec_model):
    """``render_cache_half`` stores MLP_spec's cached parts in float16: within 1e-3 of the field."""
    _, model, cams = spec_model
    model.config.render_cache_half = True
    try:
        got = model.view_colours(model.view_of(cams[0:1]), gated=True).rgb
        want = _reference(model, cams[0:1], model.spec_magnitude > model.config.gate_threshold)["rgb"]
        err = float((got - want).abs().max())
        assert TOL < err <= 1e-3, err
        assert model.render_cache.gate_level.p1.dtype == torch.float16
    finally:
        model.config.render_cache_half = False


# ------------------------------------------------- the GPU path's plumbing, on a CPU
def _splat_by_contributions(model, passes: list):
    """A stand-in for the model's gsplat pass with the same outputs (colours composited over the
    background, expected depth in RGB+ED), made of our contribution lists; records each pass's
    colour channels, mode and whether it was given a projection."""

    def splat(view, colours, backgrounds, mode, projection=None):
        passes.append((colours.shape[-1], mode, projection is not None))
        cams = Cameras(view.K, view.viewmat, [view.width], [view.height])
        contrib = model.contributions(cams, Request(torch.zeros(1, dtype=torch.long), 0, 0, view.width, view.height))
        pg = contrib.pair_gaussian
        chans, bg = [colours[pg]], backgrounds[0]
        if mode == "RGB+ED":
            chans.append(contrib.pair_depth[:, None].to(colours))
            bg = torch.cat([bg, bg.new_zeros(1)])
        img = composite(torch.cat(chans, -1), contrib, bg)[0]
        acc = contrib.accumulation()[0, ..., None].to(img)
        if mode == "RGB+ED":
            img = torch.cat([img[..., :-1], img[..., -1:] / acc.clamp_min(1e-10)], -1)
        return img, acc, "projection"

    return splat


@pytest.mark.parametrize("case", ["gated", "matte", "gated_edits", "matte_edits", "full"])
def test_gpu_outputs_read_lazily_equal_the_contribution_render(spec_model, monkeypatch, case):
    """The GPU path's outputs (gsplat swapped for a contribution-list stand-in) equal the CPU
    render; a frame that reads rgb and depth takes one pass, and diffuse, specular and segmentation
    take one more only where they differ from rgb / zero."""
    _, model, cams = spec_model
    cam = cams[0:1]
    median = model.config.gate_threshold
    if "matte" in case:
        model.config.gate_threshold = float("inf")
    if "edits" in case:
        stack = EditStack(model.fingerprint())
        stack.add(_edit(model, 18))
        model.set_edit_stack(stack)
    gated = case != "full"
    try:
        want = model.render_camera(cam, gated=gated)
        passes: list = []
        monkeypatch.setattr(model, "_renders_with_gsplat", lambda: True)
        monkeypatch.setattr(model, "_splat", _splat_by_contributions(model, passes))
        out = model.render_camera(cam, gated=gated)
        assert isinstance(out, ViewOutputs) and list(out.keys()) == list(want.keys())
        out["rgb"], out["depth"]
        assert passes == [(3, "RGB+ED", False)]  # a plain splat's pass
        for key in ("rgb", "depth", "accumulation", "diffuse", "specular", "segmentation"):
            assert out[key].shape == want[key].shape, key
            assert (out[key] - want[key]).abs().max() <= 1e-5, key
        # (the second pass composites in the main pass's projection)
        second = {"gated": [(3, "RGB", True)], "full": [(3, "RGB", True)], "gated_edits": [(4, "RGB", True)],
                  "matte_edits": [(1, "RGB", True)]}
        assert passes[1:] == second.get(case, [])
        out["viewer_extra"] = out["depth"]  # the viewer adds its own keys
        assert "viewer_extra" in out and len(out) == len(want) + 1
    finally:
        model.config.gate_threshold = median
        model.set_edit_stack(None)


@pytest.mark.parametrize("case", ["gated_edits", "matte_edits", "full"])
def test_the_gsplat_pass_on_a_cpu_shows_what_the_contribution_lists_show(spec_model, monkeypatch, case):
    """The GPU path end to end, through the model's own gsplat pass (``gsplat_pass.py``), with gsplat's
    projection and tile sort run on the CPU by gsplat's torch code and only its compositing kernel stood
    in for (``gsplat_cpu.py``): every output equals the CPU render up to the rasterizers' alpha cut-offs."""
    import gsplat_cpu

    _, model, cams = spec_model
    cam = cams[0:1]
    median = model.config.gate_threshold
    if "matte" in case:
        model.config.gate_threshold = float("inf")
    stack = EditStack(model.fingerprint())
    stack.add(_edit(model, 19))
    model.set_edit_stack(stack)
    old_bg = model.background_color
    model.set_background(torch.tensor([0.2, 0.5, 0.9]))
    gated = case != "full"
    try:
        want = model.render_camera(cam, gated=gated)
        gsplat_cpu.use_on_cpu(monkeypatch)
        monkeypatch.setattr(model, "_renders_with_gsplat", lambda: True)
        out = model.render_camera(cam, gated=gated)
        for key in ("rgb", "depth", "accumulation", "diffuse", "specular", "segmentation"):
            assert out[key].shape == want[key].shape, key
            diff = (out[key] - want[key]).abs()
            assert diff.mean() < 1e-4 and diff.max() < 2e-3, (key, float(diff.mean()), float(diff.max()))
        assert want["accumulation"].max() > 0.9 and (want["accumulation"] < 0.01).any()  # scene and background
        assert want["segmentation"].max() > 10 * 2e-3  # the edit shows (above the tolerance)
    finally:
        model.config.gate_threshold = median
        model.set_edit_stack(None)
        model.set_background(old_bg)


@pytest.mark.gpu
def test_gpu_cached_render_equals_the_reference_colours_rendered(spec_model):
    """On a GPU, with gsplat: the cached colours equal the field's forward (to the tolerance of GPU
    matrix products), the viewer's frame equals gsplat's render of the reference colours, and a
    frame that reads rgb and depth computes nothing else."""
    pipeline, model, cams = spec_model
    median = model.config.gate_threshold
    pipeline.to("cuda")
    try:
        cam = cams[0:1].to("cuda")
        stack = EditStack(model.fingerprint())
        stack.add(_edit(model, 20))
        model.set_edit_stack(stack)
        for t in (median, float("inf")):
            model.config.gate_threshold = t
            want = _reference(model, cam, model.spec_magnitude > t)
            got = model.view_colours(model.view_of(cam), gated=True)
            assert (got.rgb - want["rgb"]).abs().max() <= 1e-5
            out = model.get_outputs_for_camera(cam)
            out["rgb"], out["depth"]
            extra = {"diffuse"} if t == float("inf") else set()
            assert set(out.computed()) == {"rgb", "depth", "accumulation", "background"} | extra
            ref = model.render_view(model.view_of(cam), ViewColours(want["rgb"], want["diffuse"],
                                                                    lambda: want["segmentation"]))
            for key in ("rgb", "diffuse", "specular", "segmentation", "depth", "accumulation"):
                assert out[key].shape == ref[key].shape, key
                assert (out[key] - ref[key]).abs().max() <= 1e-5, key
    finally:
        model.set_edit_stack(None)
        model.config.gate_threshold = median
        pipeline.to("cpu")


# ---------------------------------------------------------------- the camera conversion
def _previous_view_of(camera, device, dtype):
    """The conversion as it was before it gathered the camera's numbers as words (numpy on the host)."""
    import numpy as np

    from virgi_ns.nerfstudio.render_cache import View

    host = torch.cat([camera.camera_to_worlds.reshape(-1, 12)[0]]
                     + [getattr(camera, k).reshape(-1)[:1].to(camera.camera_to_worlds.dtype)
                        for k in ("fx", "fy", "cx", "cy", "width", "height")]).cpu().double().numpy()
    c2w = host[:12].reshape(3, 4)
    rot = c2w[:, :3] * np.array([1.0, -1.0, -1.0])
    t = c2w[:, 3]
    vm = np.eye(4)
    vm[:3, :3] = rot.T
    vm[:3, 3] = -rot.T @ t
    fx, fy, cx, cy, w, h = host[12:]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    packed = torch.from_numpy(np.concatenate([vm.ravel(), K.ravel(), t]).astype(np.float32)).to(device)
    return View(packed[:16].view(1, 4, 4), packed[16:25].view(1, 3, 3), packed[25:28].view(1, 3).to(dtype),
                int(round(w)), int(round(h)))


def _random_cameras(seed: int, n: int, c2w_dtype=torch.float32, size_dtype=torch.int64):
    """``n`` nerfstudio pinhole cameras: random rotations and positions far from the origin,
    non-square images, principal points off the centre, fx != fy."""
    from nerfstudio.cameras.cameras import Cameras as NSCameras

    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.linalg.det(q))[:, None, None]  # proper rotations
    t = torch.randn(n, 3, 1, generator=g, dtype=torch.float64) * 30.0
    c2w = torch.cat([q, t], dim=-1).to(c2w_dtype)
    w = torch.randint(64, 2000, (n, 1), generator=g)
    h = torch.randint(64, 2000, (n, 1), generator=g)
    f = torch.rand(n, 1, generator=g) * 1500 + 100
    return NSCameras(camera_to_worlds=c2w, fx=f, fy=f * (0.8 + 0.4 * torch.rand(n, 1, generator=g)),
                     cx=w * torch.rand(n, 1, generator=g), cy=h * torch.rand(n, 1, generator=g),
                     width=w.to(size_dtype), height=h.to(size_dtype))


def _oracle(camera):
    """(viewmat [4,4], K [3,3], centre [3], width, height) of the first camera, in float64 through the
    project's own batched conversion."""
    from virgi_ns.nerfstudio.cameras import viewmats_from_c2w

    c2w = camera.camera_to_worlds.reshape(-1, 3, 4)[:1].double()
    K = torch.zeros(3, 3, dtype=torch.float64)
    K[0, 0], K[1, 1] = camera.fx.reshape(-1)[0].double(), camera.fy.reshape(-1)[0].double()
    K[0, 2], K[1, 2], K[2, 2] = camera.cx.reshape(-1)[0].double(), camera.cy.reshape(-1)[0].double(), 1.0
    return (viewmats_from_c2w(c2w)[0], K, c2w[0, :, 3], int(camera.width.reshape(-1)[0]),
            int(camera.height.reshape(-1)[0]))


@pytest.mark.parametrize("c2w_dtype,size_dtype,batch", [(torch.float32, torch.int64, "one"),
                                                         (torch.float32, torch.int64, "many"),
                                                         (torch.float64, torch.int32, "one"),
                                                         (torch.float32, torch.int64, "grid")])
def test_view_of_equals_the_float64_oracle_and_the_previous_conversion(c2w_dtype, size_dtype, batch):
    from virgi_ns.nerfstudio.render_cache import view_of

    for seed in range(25):
        cams = _random_cameras(seed, 3, c2w_dtype, size_dtype)
        cam = {"one": cams[1:2], "many": cams, "grid": cams.reshape((3, 1))}[batch]
        vm, K, centre, w, h = _oracle(cam)
        for dtype in (torch.float32, torch.float64):
            got = view_of(cam, torch.device("cpu"), dtype)
            assert (got.width, got.height) == (w, h)
            assert got.viewmat.shape == (1, 4, 4) and got.K.shape == (1, 3, 3) and got.centre.shape == (1, 3)
            assert got.viewmat.dtype == torch.float32 and got.K.dtype == torch.float32 and got.centre.dtype == dtype
            # float32 results of float64 algebra: within float32 rounding of the oracle
            torch.testing.assert_close(got.viewmat[0].double(), vm, rtol=1e-6, atol=1e-6 * float(vm.abs().max()))
            torch.testing.assert_close(got.K[0].double(), K, rtol=1e-6, atol=0.0)
            torch.testing.assert_close(got.centre[0].double(), centre, rtol=1e-6, atol=1e-6)
            # a point ahead of the camera lands on the principal point (to the float32 rounding of a
            # translation of ~50 at a focal length of up to 1600 pixels)
            ahead = centre - cam.camera_to_worlds.reshape(-1, 3, 4)[0, :, 2].double()  # OpenGL looks down -z
            p = got.viewmat[0].double() @ torch.cat([ahead, ahead.new_ones(1)])
            uv = (got.K[0].double() @ p[:3]) / p[2]
            torch.testing.assert_close(uv[:2], K[:2, 2], rtol=0.0, atol=2e-2)
            old = _previous_view_of(cam, torch.device("cpu"), dtype)
            for a, b in ((got.viewmat, old.viewmat), (got.K, old.K), (got.centre, old.centre)):
                torch.testing.assert_close(a, b, rtol=2e-7, atol=1e-6)
            assert (got.width, got.height) == (old.width, old.height)


@pytest.mark.gpu
def test_view_of_on_the_gpu_equals_the_cpu_conversion():
    """A camera on the GPU (as the viewer hands it over): the same View, on the GPU."""
    from virgi_ns.nerfstudio.render_cache import view_of

    for seed in range(5):
        cam = _random_cameras(seed, 2)[0:1]
        want = view_of(cam, torch.device("cpu"), torch.float32)
        got = view_of(cam.to("cuda"), torch.device("cuda"), torch.float32)
        assert got.viewmat.is_cuda and (got.width, got.height) == (want.width, want.height)
        for a, b in ((got.viewmat, want.viewmat), (got.K, want.K), (got.centre, want.centre)):
            assert torch.equal(a.cpu(), b)


# ------------------------------------------------------------------ the gsplat pass
@pytest.mark.gpu
def test_the_gsplat_pass_equals_gsplat_rasterization(spec_model):
    """The model's pass through gsplat's pieces gives what ``gsplat.rasterization`` gives as the
    baseline calls it (RGB+ED, unpacked, classic), with the background composited in; a second pass
    in the main pass's projection equals a fresh ``rasterization`` of its channels."""
    from gsplat.rendering import rasterization

    pipeline, model, cams = spec_model
    pipeline.to("cuda")
    try:
        cam = cams[0:1].to("cuda")
        view = model.view_of(cam)
        g = model.render_cache.geometry(model)
        n = g.means.shape[0]
        colours = torch.rand(n, 3, device="cuda", generator=torch.Generator("cuda").manual_seed(0))
        bg = torch.tensor([[0.2, 0.5, 0.9]], device="cuda")
        got, acc, proj = model._splat(view, colours, bg, "RGB+ED")
        want, want_acc, _ = rasterization(g.means, g.quats, g.scales, g.opacities, colours, view.viewmat, view.K,
                                          view.width, view.height, render_mode="RGB+ED", backgrounds=bg,
                                          packed=False, rasterize_mode="classic")
        assert got.shape == want[0].shape and acc.shape == want_acc[0].shape
        assert (got - want[0]).abs().max() <= 1e-6 and (acc - want_acc[0]).abs().max() <= 1e-6
        assert acc.max() > 0.5  # the view sees the scene
        extra = torch.rand(n, 4, device="cuda", generator=torch.Generator("cuda").manual_seed(1))
        bg4 = torch.tensor([[0.1, 0.3, 0.7, 0.0]], device="cuda")
        got2, _, _ = model._splat(view, extra, bg4, "RGB", proj)
        want2, _, _ = rasterization(g.means, g.quats, g.scales, g.opacities, extra, view.viewmat, view.K,
                                    view.width, view.height, render_mode="RGB", backgrounds=bg4, packed=False,
                                    rasterize_mode="classic")
        assert (got2 - want2[0]).abs().max() <= 1e-6
    finally:
        pipeline.to("cpu")


# ------------------------------------------------------------- colours as a CUDA graph
class _EagerGraph:
    """A stand-in for :class:`ColourGraph` on a CPU with its interface and buffers: the static centre
    and output, replayed by running the recorded function again (counts the recordings)."""

    made: list = []

    def __init__(self, gate, edits, centre):
        self.centre = centre.detach().clone()
        self.out = edits.diffuse.clone()
        self._replay = lambda: ColourGraph._write(self, gate, edits)
        _EagerGraph.made.append(self)

    def __call__(self, centre):
        self.centre.copy_(centre)
        self._replay()
        return self.out


def _graph_frames(model, cam, n: int = 3) -> list:
    """``n`` frames' colours as the render path takes them (transient), each checked against the
    reference; returns the last."""
    got = None
    for _ in range(n):
        got = model.view_colours(model.view_of(cam), gated=True, transient=True)
        want = _reference(model, cam, model.spec_magnitude > model.config.gate_threshold)
        assert (got.rgb - want["rgb"]).abs().max() <= TOL
    return got


def test_colour_graphs_are_recorded_once_per_cache_state(spec_model, monkeypatch):
    """The graphed path's bookkeeping, with the graph stood in for on a CPU: a state is served eagerly
    once, then recorded once and replayed; every change of the cache state (an edit, an undo, ``k``, a
    live edit, the threshold) records again, the public call returns a copy that the next view does
    not overwrite, and a failed recording warns once and leaves eager colours."""
    import virgi_ns.nerfstudio.render_cache as rc

    _, model, cams = spec_model
    cam, other = cams[0:1], cams[1:2]
    median = model.config.gate_threshold
    monkeypatch.setattr(rc, "ColourGraph", _EagerGraph)
    monkeypatch.setattr(rc, "_recordable", lambda centre: True)
    _EagerGraph.made = []
    model.render_cache.clear()
    stack = EditStack(model.fingerprint())
    model.set_edit_stack(stack)
    try:
        _graph_frames(model, cam, 1)
        assert _EagerGraph.made == [] and model.render_cache.edit_level.frames == 1  # the first frame: eager
        last = _graph_frames(model, cam, 3)
        assert len(_EagerGraph.made) == 1 and last.rgb is _EagerGraph.made[0].out  # then recorded, replayed
        public = model.view_colours(model.view_of(cam), gated=True)
        assert public.rgb is not _EagerGraph.made[0].out
        before = public.rgb.clone()
        model.view_colours(model.view_of(other), gated=True, transient=True)  # another view replays
        assert torch.equal(public.rgb, before)
        changes = [lambda: stack.add(_edit(model, 21)), lambda: stack.add(_edit(model, 22)), stack.undo,
                   lambda: stack.set_specular_strength(0.6), lambda: model.set_live_edit(_edit(model, 23)),
                   lambda: model.set_live_edit(None),
                   lambda: setattr(model.config, "gate_threshold", float(model.spec_magnitude.quantile(0.7)))]
        ref = _reference(model, cam, model.spec_magnitude > model.config.gate_threshold)["rgb"]
        for i, change in enumerate(changes):
            change()
            gc.collect()
            now = _graph_frames(model, cam, 3)
            assert len(_EagerGraph.made) == i + 2, i  # one recording per state
            assert now.rgb is _EagerGraph.made[-1].out
            assert (now.rgb - ref).abs().max() > 1e-3, i  # the change shows
            ref = now.rgb.clone()
        # no graphs asked for: eager colours, nothing recorded
        model.config.render_cache_graphs = False
        stack.set_specular_strength(0.3)
        _graph_frames(model, cam, 3)
        assert len(_EagerGraph.made) == len(changes) + 1
        model.config.render_cache_graphs = True

        def fail(*a):
            raise RuntimeError("operation not permitted when stream is capturing")

        monkeypatch.setattr(rc, "ColourGraph", fail)
        stack.set_specular_strength(0.8)
        with pytest.warns(UserWarning, match="without CUDA graphs"):
            _graph_frames(model, cam, 2)
        assert model.render_cache.graph_failed and model.render_cache.edit_level.graph is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # warned once
            stack.set_specular_strength(0.9)
            _graph_frames(model, cam, 3)
    finally:
        model.config.render_cache_graphs = True
        model.config.gate_threshold = median
        model.set_live_edit(None)
        model.set_edit_stack(None)
        model.render_cache.graph_failed = False
        model.render_cache.clear()


@pytest.mark.gpu
def test_graphed_colours_equal_eager_colours_on_a_gpu(spec_model):
    """On a GPU the graphed colours equal the eager ones (the same kernels) and the field's; after an
    edit, an undo and a change of ``k`` the graph is recorded again and the render follows; the public
    call's colours are not overwritten by the next view."""
    pipeline, model, cams = spec_model
    median = model.config.gate_threshold
    pipeline.to("cuda")
    model.render_cache.clear()
    stack = EditStack(model.fingerprint())
    model.set_edit_stack(stack)

    def graphed_vs_eager(cam):
        view = model.view_of(cam)
        model.config.render_cache_graphs = False
        eager = model.view_colours(view, gated=True).rgb
        model.config.render_cache_graphs = True
        for _ in range(3):
            got = model.view_colours(view, gated=True, transient=True).rgb
        assert model.render_cache.edit_level.graph is not None and got is model.render_cache.edit_level.graph.out
        assert (got - eager).abs().max() <= 1e-6
        want = _reference(model, cam, model.spec_magnitude > model.config.gate_threshold)["rgb"]
        assert (got - want).abs().max() <= 1e-5
        return got.clone(), model.render_cache.edit_level.graph

    try:
        cam = cams[0:1].to("cuda")
        for i in range(2):
            graphed_vs_eager(cams[i : i + 1].to("cuda"))
        img, graph = graphed_vs_eager(cam)
        frame = model.get_outputs_for_camera(cam)["rgb"].clone()
        for change in (lambda: stack.add(_edit(model, 24)), stack.undo, lambda: stack.set_specular_strength(0.4)):
            change()
            now, g = graphed_vs_eager(cam)
            assert g is not graph and (now - img).abs().max() > 1e-3
            again = model.get_outputs_for_camera(cam)["rgb"]
            assert (again - frame).abs().max() > 1e-3  # the render follows the new state
            img, graph, frame = now, g, again.clone()
        a = model.view_colours(model.view_of(cam), gated=True)
        kept = a.rgb.clone()
        model.view_colours(model.view_of(cams[1:2].to("cuda")), gated=True, transient=True)
        assert torch.equal(a.rgb, kept)
    finally:
        model.config.gate_threshold = median
        model.config.render_cache_graphs = True
        model.set_edit_stack(None)
        model.render_cache.clear()
        pipeline.to("cpu")


def test_a_new_background_reaches_the_gsplat_pass(spec_model, monkeypatch):
    """gsplat's backgrounds (the colour row and its zero-padded form for the depth channel) are kept per
    background tensor: the same tensor gives the same rows, and a new one (the viewer sets one every
    frame) or one changed in place shows in the next render."""
    _, model, cams = spec_model
    cam = cams[0:1]
    cache = model.render_cache
    old = model.background_color
    passes: list = []
    try:
        bg = cache.background(model.background_color, model.device)
        row = cache.background_row(bg)
        assert row is cache.background_row(bg) and row.shape == (1, 3)
        padded = cache.with_depth_channel(row)
        assert padded is cache.with_depth_channel(row)
        assert torch.equal(padded, torch.cat([row, row.new_zeros(1, 1)], 1))
        other = torch.rand(1, 2)
        assert torch.equal(cache.with_depth_channel(other), torch.cat([other, other.new_zeros(1, 1)], 1))
        monkeypatch.setattr(model, "_renders_with_gsplat", lambda: True)
        monkeypatch.setattr(model, "_splat", _splat_by_contributions(model, passes))
        colour = torch.tensor([0.9, 0.4, 0.1])
        for change in (lambda: model.set_background(colour), lambda: colour.copy_(torch.tensor([0.2, 0.7, 0.3])),
                       lambda: model.set_background(torch.tensor([0.5, 0.5, 1.0]))):
            change()
            out = model.render_camera(cam, gated=True)
            empty = out["accumulation"][..., 0] == 0
            assert empty.any()
            assert torch.equal(out["background"], model.background_color)
            torch.testing.assert_close(out["rgb"][empty], model.background_color.expand(int(empty.sum()), 3))
    finally:
        model.set_background(old)


# ------------------------------------------------------------ cheap keys per frame
def test_the_module_watch_sees_every_change_of_the_field():
    """:class:`ModuleWatch` replaces a walk of the field's parameters per frame: its structure check fails
    for a parameter, buffer or submodule set, added or removed, and its versions and storages move with
    in-place writes and ``.data`` assignments; its parameters are ``parameters()``'s, in order."""
    from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField
    from virgi_ns.nerfstudio.render_cache import ModuleWatch

    def field():
        return DecoupledColourField(ColourFieldConfig(log2_hashmap_size=10, levels=4), torch.tensor([[-1.0] * 3, [1.0] * 3]))

    fld = field()
    w = ModuleWatch(fld)
    assert w.current(fld) and not w.current(field())
    assert [id(p) for p in w.params] == [id(p) for p in fld.parameters()] and w.ids == tuple(map(id, w.params))
    assert len(w.tensors) == len(w.params) + len(list(fld.buffers()))
    v, s = w.versions(), w.storages()
    with torch.no_grad():
        fld.spec_l2.bias += 1.0  # an in-place write
    assert w.current(fld) and w.versions() != v and w.storages() == s
    v = w.versions()
    fld.spec_l2.bias.data = fld.spec_l2.bias.detach().clone()  # new storage, same version
    assert w.current(fld) and w.versions() == v and w.storages() != s
    changes = [lambda m: setattr(m.spec_l2, "bias", torch.nn.Parameter(m.spec_l2.bias.detach().clone())),
               lambda m: setattr(m, "spec_l1", torch.nn.Linear(m.spec_l1.in_features, m.spec_l1.out_features)),
               lambda m: m.spec_l3.register_parameter("extra", torch.nn.Parameter(torch.zeros(1))),
               lambda m: m.register_buffer("extra", torch.zeros(1)),
               lambda m: setattr(m, "aabb", m.aabb.clone()),
               lambda m: m.add_module("extra", torch.nn.Linear(1, 1)),
               lambda m: delattr(m.spec_l3, "bias")]
    for i, change in enumerate(changes):
        fld = field()
        w = ModuleWatch(fld)
        change(fld)
        assert not w.current(fld), i
        assert ModuleWatch(fld).current(fld), i


def test_a_field_parameter_or_layer_set_anew_is_never_served_from_the_cache(scene):  # noqa: F811
    """A field parameter or a whole layer replaced by a new one (not written in place: no version
    counter moves) makes the gate stale, as a training step does; the rebuilt gate serves the new field
    from the cache."""
    pipeline = _gated_specular_pipeline(scene, steps=4, seed=2)
    model = pipeline.model
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    fld = model.field
    ref = _check_colours(model, cam)
    fld.spec_l2.bias = torch.nn.Parameter(fld.spec_l2.bias.detach() + 0.5)
    assert not model.gate_ready()
    ref = _check_colours(model, cam, gate=None, previous=ref)
    model.build_specular_gate(model._train_cameras_fn())
    ref = _check_colours(model, cam, previous=ref)
    assert model.render_cache.edit_level is not None  # served from the cache again
    layer = torch.nn.Linear(fld.spec_l1.in_features, fld.spec_l1.out_features)
    with torch.no_grad():
        layer.weight.copy_(fld.spec_l1.weight * 1.5)
        layer.bias.copy_(fld.spec_l1.bias)
    fld.spec_l1 = layer
    assert not model.gate_ready()
    ref = _check_colours(model, cam, gate=None, previous=ref)
    model.build_specular_gate(model._train_cameras_fn())
    _check_colours(model, cam, previous=ref)
    edits = model.render_cache.edit_level
    assert edits is not None and model.render_cache.levels(model)[1] is edits  # a frame unchanged: the same levels


def test_a_matte_frame_runs_no_tensor_operation(spec_model):
    """A matte view's colours are the cached tensor: the validity checks and the colours dispatch no tensor
    operation (so launch no kernel on a GPU); neither do the geometry level's checks."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops.append(func)
            return func(*args, **(kwargs or {}))

    _, model, cams = spec_model
    median = model.config.gate_threshold
    try:
        model.config.gate_threshold = float("inf")
        view = model.view_of(cams[0:1])
        first = model.view_colours(view, gated=True)
        model.render_cache.geometry(model)
        with Count() as count:
            got = model.view_colours(view, gated=True, transient=True)
            model.render_cache.geometry(model)
        assert count.ops == [] and got.rgb is first.rgb
        model.config.gate_threshold = median  # (the counter sees a gated frame's operations)
        with Count() as count:
            model.view_colours(view, gated=True, transient=True)
        assert count.ops
    finally:
        model.config.gate_threshold = median


def test_per_frame_methods_run_without_gradients_inside_and_outside_no_grad(spec_model):
    """The per-frame methods enter ``no_grad`` only where gradients are on (a cheaper decorator); either
    way their outputs carry no autograd graph, and the caller's grad mode is left as it was."""
    _, model, cams = spec_model
    cam = cams[0:1]
    with torch.enable_grad():
        view = model.view_of(cam)
        assert not model.view_colours(view, gated=False).rgb.requires_grad
        assert not model.render_camera(cam, gated=True)["rgb"].requires_grad
        assert not model.get_outputs_for_camera(cam)["rgb"].requires_grad
        assert torch.is_grad_enabled()
    with torch.no_grad():
        assert not model.get_outputs_for_camera(cam)["rgb"].requires_grad
        assert not torch.is_grad_enabled()


@pytest.mark.gpu
def test_a_camera_on_the_cpu_is_rendered_without_moving_it(spec_model, monkeypatch):
    """With frozen geometry, a camera on the CPU is read where it lies (no copy to the GPU and back): the
    frame equals the frame of the same camera on the GPU."""
    from nerfstudio.cameras.cameras import Cameras as NSCameras

    pipeline, model, cams = spec_model
    pipeline.to("cuda")
    try:
        cam = cams[0:1]
        want = model.get_outputs_for_camera(cam.to("cuda"))["rgb"].clone()
        monkeypatch.setattr(NSCameras, "to", lambda self, device: pytest.fail("the camera was moved"))
        got = model.get_outputs_for_camera(cam)["rgb"]
        assert got.is_cuda and torch.equal(got, want)
    finally:
        monkeypatch.undo()
        pipeline.to("cpu")
