"""The synthetic evaluation scenes (bench/common/synthetic.py): files, truth and labels, checked against
independent computations on a tiny capture."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from virgi_ns.edit.recolor import RecolorRule, recolor, rgb_to_hsv
from virgi_ns.errors import InputError
from virgi_ns.io import load_splat

from script_module import bench_module

_evalset, _synthetic = bench_module("evalset"), bench_module("synthetic")
EVAL_SET, REAL, find = _evalset.EVAL_SET, _evalset.REAL, _evalset.find
SCENES, hue_rotate, write_scene = _synthetic.SCENES, _synthetic.hue_rotate, _synthetic.write_scene

VIEWS, W, H, SPACING = 8, 64, 48, 0.05


def _read(path):
    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).float() / 255.0


def _view(root, i: int):
    """(photo, truth, per-pixel labels) of view ``i``."""
    name = f"frame_{i:03d}.png"
    label = torch.from_numpy(np.array(Image.open(root / "labels" / name))).long()
    return _read(root / "images" / name), _read(root / "truth" / name), label


@pytest.fixture(scope="module")
def vase(tmp_path_factory):
    root = tmp_path_factory.mktemp("syn") / "dark_vase"
    info = write_scene(SCENES["dark_vase"], root, VIEWS, W, H, SPACING)
    return root, info


def test_capture_files_labels_and_geometry(vase):
    root, info = vase
    meta = json.loads((root / "transforms.json").read_text())
    assert len(meta["frames"]) == VIEWS and (meta["w"], meta["h"]) == (W, H)
    labels = np.load(root / "labels.npy")
    g = load_splat(root / "geometry.ply")
    assert len(g) == len(labels) == info["gaussians"]
    names = info["labels"]
    assert set(names) >= {"vase", "block", "ball", "floor", "backdrop"} and info["target"] == "vase"
    for fr in meta["frames"]:
        name = fr["file_path"].split("/")[-1]
        for folder in ("images", "truth", "labels"):
            assert (root / folder / name).is_file()
    # the camera-to-world matrices are rigid (OpenGL axes) and the cameras look at the scene
    c2w = torch.tensor(meta["frames"][0]["transform_matrix"])
    torch.testing.assert_close(c2w[:3, :3] @ c2w[:3, :3].T, torch.eye(3), atol=1e-5, rtol=0)
    forward = -c2w[:3, 2]  # OpenGL cameras look down -z
    to_target = torch.tensor(SCENES["dark_vase"].look_at) - c2w[:3, 3]
    assert float(torch.nn.functional.cosine_similarity(forward, to_target, dim=0)) > 0.999


def test_truth_differs_from_the_photo_only_on_the_target(vase):
    root, info = vase
    target = info["labels"].index("vase")
    changed_total = 0
    for i in range(VIEWS):
        photo, truth, label = _view(root, i)
        changed = (photo - truth).abs().amax(-1) > 1.5 / 255.0
        changed_total += int(changed.sum())
        # where no target Gaussian lands the two photos are the same image; a changed pixel has the
        # target among its Gaussians (its label is the target, or it borders a target pixel)
        near = torch.nn.functional.max_pool2d((label == target).float()[None, None], 3, 1, 1)[0, 0] > 0
        assert not bool((changed & ~near).any()), i
    assert changed_total > 0.5 * info["target_fraction"] * VIEWS * W * H


def test_rule_on_a_photo_is_the_truth_on_clean_target_pixels(vase):
    """A hue rotation keeps HSV saturation and value, and the grey lobe changes neither hue nor the
    rotation's result: where the rule selects a pixel whose 3x3 neighbourhood is all target, the
    rule applied to the photo gives the truth (up to 8-bit rounding)."""
    root, info = vase
    rule = RecolorRule(**info["rule"])
    target = info["labels"].index("vase")
    checked = 0
    for i in range(VIEWS):
        photo, truth, label = _view(root, i)
        inner = -torch.nn.functional.max_pool2d(-(label == target).float()[None, None], 3, 1, 1)[0, 0] > 0
        ruled, selected = recolor(photo, rule)
        sel = inner & selected
        checked += int(sel.sum())
        if sel.any():
            assert float((ruled - truth).abs().amax(-1)[sel].max()) <= 3.0 / 255.0, i
    assert checked > 20


def test_hue_rotation_keeps_saturation_and_value():
    rgb = torch.rand(500, 3)
    out = hue_rotate(rgb, 137.0)
    a, b = rgb_to_hsv(rgb), rgb_to_hsv(out)
    torch.testing.assert_close(b[:, 1:], a[:, 1:], atol=1e-5, rtol=0)
    moved = a[:, 1] > 0.05
    torch.testing.assert_close(torch.remainder(b[moved, 0] - a[moved, 0], 360.0),
                               torch.full((int(moved.sum()),), 137.0), atol=1e-3, rtol=0)


def test_capture_is_deterministic(tmp_path):
    a = write_scene(SCENES["duck_beak"], tmp_path / "a", 4, 40, 30, 0.08)
    b = write_scene(SCENES["duck_beak"], tmp_path / "b", 4, 40, 30, 0.08)
    assert a == b
    for sub in ("images/frame_002.png", "truth/frame_002.png", "labels/frame_002.png", "geometry.ply"):
        assert (tmp_path / "a" / sub).read_bytes() == (tmp_path / "b" / sub).read_bytes()


def test_the_set_names_every_capture_once_with_a_reason():
    names = [s.name for s in EVAL_SET]
    assert len(set(names)) == len(names)
    assert {s.capture for s in REAL} == {"beercan", "fern", "cup", "fruit", "blowtorch", "fox"}
    assert {s.synthetic for s in EVAL_SET if s.synthetic} == set(SCENES)
    assert all(s.why for s in EVAL_SET)
    assert [s.name for s in find(["fern", "beercan"])] == ["fern", "beercan"] and len(find([])) == len(EVAL_SET)
    with pytest.raises(InputError, match="unknown evaluation scene"):
        find(["nope"])
