"""Renders from cached diffuse colours equal renders without the cache, and every change of the edit
stack (an edit added, undone, toggled, changed in place, ``k`` set, another stack) or of the field
invalidates what it must: a stale cache fails these tests."""

from __future__ import annotations

import gc
import warnings

import pytest
import torch

from test_model_train import build, scene, train  # noqa: F401  (fixture re-exported)
from virgi_ns.edit.stack import Edit, EditSource, EditStack, SegmentationHead

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
