"""The model renders through an edit stack: rgb, diffuse, specular strength and segmentation."""

from __future__ import annotations

import warnings

import pytest
import torch

from test_model_train import build, scene, train  # noqa: F401  (fixture re-exported)
from virgi_ns.edit.stack import Edit, EditSource, EditStack, SegmentationHead

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")


@pytest.fixture(scope="module")
def trained(scene):  # noqa: F811
    _, pipeline, optimizers, cbs = build(scene, steps=12)
    train(pipeline, optimizers, cbs, 12)
    pipeline.eval()
    model = pipeline.model
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    return model, cam


def _edit(model, red_shift: float, alpha_logit: float) -> Edit:
    head = model.field.diffuse_head
    seg = SegmentationHead(model.field.feature_dim, head.in_features, init_bias=alpha_logit)
    torch.nn.init.zeros_(seg.l2.weight)
    bias = head.bias.detach().clone()
    bias[0] += red_shift
    src = EditSource("synthetic.png", torch.eye(3), torch.eye(4), 8, 8)
    return Edit(head.weight.detach().clone(), bias, seg, src, model.fingerprint())


def _render(model, cam, gated=False):
    return model.render_camera(cam.to(model.device), gated=gated)


def test_identity_stack_and_identity_edit_leave_renders_unchanged(trained):
    model, cam = trained
    base = _render(model, cam)
    stack = EditStack(model.fingerprint())
    model.set_edit_stack(stack)
    assert torch.equal(_render(model, cam)["rgb"], base["rgb"])
    stack.add(_edit(model, red_shift=0.0, alpha_logit=12.0))  # alpha ~ 1, same head: c_d'' == c_d
    out = _render(model, cam)
    assert (out["rgb"] - base["rgb"]).abs().max() < 1e-5
    # the segmentation of an everywhere-on edit is the accumulated opacity
    assert (out["segmentation"] - out["accumulation"]).abs().max() < 1e-4
    model.set_edit_stack(None)
    assert torch.equal(_render(model, cam)["rgb"], base["rgb"])


def test_edit_recolours_diffuse_and_strength_scales_specular(trained):
    model, cam = trained
    base = _render(model, cam)
    stack = EditStack(model.fingerprint())
    stack.add(_edit(model, red_shift=3.0, alpha_logit=12.0))
    model.set_edit_stack(stack)
    out = _render(model, cam)
    covered = base["accumulation"][..., 0] > 0.5
    assert covered.any()
    assert (out["diffuse"][..., 0] - base["diffuse"][..., 0])[covered].mean() > 0.1
    assert (out["diffuse"][..., 1:] - base["diffuse"][..., 1:]).abs().max() < 1e-4
    # a disabled edit is not applied
    stack.set_enabled(1, False)
    assert (_render(model, cam)["rgb"] - base["rgb"]).abs().max() < 1e-6
    stack.set_enabled(1, True)
    # k = 0: no specular left, rgb is the diffuse render
    stack.set_specular_strength(0.0)
    k0 = _render(model, cam)
    assert k0["specular"].abs().max() < 1e-6
    # the gated path (cached edited diffuse colours) agrees with the full path
    stack.set_specular_strength(1.0)
    if not model.gate_ready():
        model.build_specular_gate(model._train_cameras_fn())
    full, gated = _render(model, cam), _render(model, cam, gated=True)
    assert (full["rgb"] - gated["rgb"]).abs().max() <= model.config.gate_threshold + 1e-5
    assert (full["diffuse"] - gated["diffuse"]).abs().max() < 1e-5
    model.set_edit_stack(None)


def test_gated_render_follows_an_edit_replaced_in_place(trained):
    """A pick adjusted after its release replaces its edit (EditStack.replace): the gated path's
    cached edited colours must follow, as the full path does."""
    model, cam = trained
    if not model.gate_ready():
        model.build_specular_gate(model._train_cameras_fn())
    stack = EditStack(model.fingerprint())
    stack.add(_edit(model, red_shift=3.0, alpha_logit=12.0))
    model.set_edit_stack(stack)
    first = _render(model, cam, gated=True)["diffuse"]
    stack.replace(1, _edit(model, red_shift=-3.0, alpha_logit=12.0))
    full, gated = _render(model, cam), _render(model, cam, gated=True)
    assert (full["diffuse"] - first).abs().max() > 0.1  # the replacement changes the colours
    assert (full["diffuse"] - gated["diffuse"]).abs().max() < 1e-5
    model.set_edit_stack(None)
