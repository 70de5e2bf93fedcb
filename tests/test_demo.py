"""The demo's pipeline on a reduced bundle, the bundled capture against COLMAP, the geometry script's frame."""

from __future__ import annotations

import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from script_module import script_module
from virgi_ns.data.bundle import BUNDLED_SCENE, BundleDataParserConfig, read_points_ply
from virgi_ns.data.make_bundle import shrink_bundle
from virgi_ns.edit.recolor import rule_mask
from virgi_ns.gaussians import Gaussians
from virgi_ns.io import load_splat, save_ply

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")


def _tiny_bundle(root: Path) -> Path:
    """8 bundled views at 45x80 and a small geometry at every 4th sparse point (capture frame)."""
    scene = shrink_bundle(BUNDLED_SCENE, root / "scene", views=8, factor=8)
    xyz, rgb = read_points_ply(scene / "sparse_pc.ply")
    xyz, rgb = xyz[::4], rgb[::4]
    gen = torch.Generator().manual_seed(0)
    n = len(xyz)
    g = Gaussians(means=torch.from_numpy(xyz).float(), scales=torch.full((n, 3), math.log(0.03)),
                  quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
                  opacities=torch.full((n,), 2.0),
                  sh=((torch.from_numpy(rgb).float() / 255 - 0.5) / 0.28209479177387814)[:, None, :])
    save_ply(g, scene / "geometry.ply")
    return scene


def test_demo_pipeline_on_a_tiny_capture(tmp_path):
    from virgi_ns.demo.config import DemoConfig
    from virgi_ns.demo.picture import COLUMNS
    from virgi_ns.demo.run import run

    scene = _tiny_bundle(tmp_path)
    out = tmp_path / "out"
    cfg = DemoConfig(out=out, scene=scene, colour_steps=4, tile_size=16, views_per_anchor=3, pixel_budget=768,
                     hash_log2=12, edit_steps=8, grid_views=1, export_directions=8, colour_init_steps=20,
                     colour_init_batch=512)
    metrics = run(cfg)
    assert metrics["geometry"] == str(scene / "geometry.ply")  # the bundle's geometry was imported
    assert metrics["train_views"] == 7 and metrics["held_out_views"] == 1  # every 8th held out: frame 0
    assert math.isfinite(metrics["reconstruction_psnr"]) and metrics["reconstruction_psnr"] > 5
    assert metrics["edit_time_s"]["steps_count"] == 8 and metrics["edit_time_s"]["total"] > 0
    # the colour stage started from the geometry's colours (the model's warm start), timed on its own
    assert metrics["colour_init"] == {"mode": "geometry", "steps": 20, "batch": 512}
    assert metrics["times_s"]["colour_init_s"] > 0
    # the click landed on the object's colour in its view, and its edit shows there and nowhere else:
    # the selection's hue moved towards the asked colour's, the rest of the view kept its render
    click, seen = metrics["click"], metrics["click_view"]
    assert click["colour"] == cfg.colour and click["mode"] == "hue" and 0 < click["selected_share"] < 1
    assert seen["object_pixels"] > 0 and seen["leak_psnr"] >= 30
    assert seen["hue_error_deg"] <= seen["unedited_hue_error_deg"] - 20
    # the held-out view was rendered with the edit (it changed), and away from the object hardly
    held = metrics["per_view"][0]
    assert 30 <= held["leak_psnr"] < 90
    # files
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["click_view"] == pytest.approx(metrics["click_view"])
    grid = np.asarray(Image.open(out / "grid.png").convert("RGB"))
    w, h, pad, title, scale = 45, 80, 4, 18, cfg.grid_scale
    assert grid.shape == (title + (scale * h + pad), len(COLUMNS) * (scale * w + pad) + pad, 3)
    # the grid's photo cell (below its label strip) is the held-out photo itself, each pixel shown scale x scale
    eval_name = saved["per_view"][0]["view"]
    photo = np.asarray(Image.open(scene / "images" / eval_name).convert("RGB"))
    cell = grid[title + scale * 14 : title + scale * h : scale, pad : pad + scale * w : scale].astype(int)
    assert np.abs(cell - photo[14:].astype(int)).max() <= 1
    # the clicked pixel shows the object's colour in the clicked view's photo (this briefly trained render shows
    # it nowhere, so the photo chose the click)
    meta = json.loads((scene / "transforms.json").read_text())
    train_names = [f["file_path"] for i, f in enumerate(meta["frames"]) if i % 8 != 0]
    img = torch.from_numpy(np.array(Image.open(scene / train_names[click["view_index"]]).convert("RGB")))
    x, y = click["pixel"]
    assert bool(rule_mask(img.float() / 255, cfg.object_rule())[y, x])
    # the edited scene: every Gaussian, SH degree 3, positions in the capture frame (the imported file's)
    g = load_splat(out / "edited_scene.ply")
    src = load_splat(scene / "geometry.ply")
    assert len(g) == len(src) and g.sh_degree == 3
    torch.testing.assert_close(g.means, src.means, atol=1e-4, rtol=1e-4)
    # the trained run: a nerfstudio run directory that the virgi commands (and ns-viewer) load,
    # and the printed pick lands on the object the rule recoloured
    from virgi_ns.nerfstudio.runs import load_run
    from virgi_ns.demo.run import next_commands

    run_cfg = out / "run" / "config.yml"
    assert saved["run"]["config"] == str(run_cfg) and list((out / "run" / "nerfstudio_models").glob("step-*.ckpt"))
    _, pipeline = load_run(run_cfg)
    pick = saved["run"]["pick"]
    cam = pipeline.datamanager.train_dataset.cameras[pick["camera_index"] : pick["camera_index"] + 1]
    with torch.no_grad():
        acc = pipeline.model.get_outputs_for_camera(cam)["accumulation"][..., 0]
    x, y = pick["pixel"]
    assert pick["camera_index"] == click["view_index"] and pick["pixel"] == click["pixel"] and float(acc[y, x]) > 0.5
    commands = next_commands(saved, out)
    assert [c.split()[0] for c in commands] == ["ns-viewer", "virgi-edit", "virgi-export"]
    assert f"--camera-index {pick['camera_index']} --pixel {x} {y} --colour '{cfg.colour}'" in commands[1]
    # the demo's object is every pixel of its colour: its pick, and the one it prints, are not contiguous
    assert click["contiguous"] is False and pick["contiguous"] is False and commands[1].endswith(" --no-contiguous")


def test_bad_scene_exits_2_and_writes_nothing(tmp_path, monkeypatch, capsys):
    from virgi_ns.demo import run as demo

    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["demo", "--scene", str(tmp_path / "nowhere"), "--out", str(out)])
    with pytest.raises(SystemExit) as e:
        demo.entrypoint()
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "transforms.json" in err[0]
    assert not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
def test_full_resolution_without_a_gpu_is_refused(tmp_path, monkeypatch, capsys):
    from virgi_ns.demo import run as demo

    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["demo", "--full", "--out", str(out)])
    with pytest.raises(SystemExit) as e:
        demo.entrypoint()
    assert e.value.code == 2 and "GPU" in capsys.readouterr().err and not out.exists()


def test_bundle_matches_colmap_observations(shared_data):
    """Projecting COLMAP's points with the bundle's pinhole cameras lands on COLMAP's own
    (distorted) observations after undistortion: a median within one pixel of the full-size photos."""
    from nerfstudio.data.utils.colmap_parsing_utils import (read_cameras_binary, read_images_binary,
                                                             read_points3D_binary)

    sparse = shared_data / "beercan" / "sparse" / "0"
    cams = read_cameras_binary(sparse / "cameras.bin")
    ims = {im.name: im for im in read_images_binary(sparse / "images.bin").values()}
    pts = read_points3D_binary(sparse / "points3D.bin")
    meta = json.loads((BUNDLED_SCENE / "transforms.json").read_text())
    assert len(meta["frames"]) == 32 and meta["applied_transform"] == np.eye(4)[:3].tolist()
    errs = []
    for fr in meta["frames"][::5]:
        im = ims[fr["colmap_image"]]
        f, cx, cy, k1 = cams[im.camera_id].params
        ok = im.point3D_ids >= 0
        obs = im.xys[ok]
        X = np.stack([pts[i].xyz for i in im.point3D_ids[ok]])
        # the observation, undistorted by inverting x_d = x (1 + k1 r^2) (fixed point), then rescaled
        xd = (obs - [cx, cy]) / f
        x = xd.copy()
        for _ in range(20):
            x = xd / (1 + k1 * (x**2).sum(-1, keepdims=True))
        want = x * [fr["fl_x"], fr["fl_y"]] + [fr["cx"], fr["cy"]]
        c2w = np.asarray(fr["transform_matrix"])
        c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV camera axes
        w2c = np.linalg.inv(c2w)
        pc = X @ w2c[:3, :3].T + w2c[:3, 3]
        got = pc[:, :2] / pc[:, 2:3] * [fr["fl_x"], fr["fl_y"]] + [fr["cx"], fr["cy"]]
        errs.append(np.linalg.norm(got - want, axis=-1))
    err = np.concatenate(errs) * meta["downscale"]  # in full-size pixels
    assert np.median(err) < 1.0 and np.quantile(err, 0.95) < 4.0, (np.median(err), np.quantile(err, 0.95))


def test_bundle_parses_with_its_hold_out():
    out_train = BundleDataParserConfig().setup().get_dataparser_outputs("train")
    out_val = BundleDataParserConfig().setup().get_dataparser_outputs("val")
    assert len(out_train.image_filenames) == 28 and len(out_val.image_filenames) == 4
    assert [p.name for p in out_val.image_filenames] == [
        json.loads((BUNDLED_SCENE / "transforms.json").read_text())["frames"][i]["file_path"].split("/")[-1]
        for i in (0, 8, 16, 24)]
    assert out_train.metadata["points3D_xyz"].shape[0] == len(read_points_ply(BUNDLED_SCENE / "sparse_pc.ply")[0])


def test_geometry_script_returns_gaussians_to_the_capture_frame(tmp_path):
    """What the GPU script writes, imported by the model (capture frame), is where it trained."""
    with script_module("scripts/train_demo_geometry.py", "train_demo_geometry") as mod:
        _check_geometry_script(mod, tmp_path)


def _check_geometry_script(mod, tmp_path):
    from virgi_ns.demo.config import DemoConfig
    from virgi_ns.demo.training import trainer_config

    scene = _tiny_bundle(tmp_path)
    tc = trainer_config(DemoConfig(scene=scene, hash_log2=12), scene, scene / "geometry.ply", use_cache=False)
    pipeline = tc.pipeline.setup(device="cpu", test_mode="val")
    model = pipeline.model
    params = {k: v.detach() for k, v in model.gauss_params.items()}
    out = pipeline.datamanager.train_dataparser_outputs
    assert float(out.dataparser_scale) != 1.0  # a real frame change
    g = mod.to_capture_frame(params, out.dataparser_transform, float(out.dataparser_scale))
    src = load_splat(scene / "geometry.ply")
    torch.testing.assert_close(g.means, src.means, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(g.scales, src.scales, atol=1e-4, rtol=1e-4)
    dots = (g.quats * torch.nn.functional.normalize(src.quats, dim=-1)).sum(-1).abs()
    assert bool((dots > 1 - 1e-4).all())


def test_the_default_click_is_the_pixel_deepest_inside_the_object():
    """A can-like object with print at its centre: the click lands in the widest plain part, not beside the
    print (the centroid's neighbour), so the pick reads the object's own colour. The image's edge is an
    edge of the object too."""
    from virgi_ns.demo.run import inner_pixel

    mask = torch.zeros(60, 30, dtype=torch.bool)
    mask[5:55, 5:25] = True  # the object, 20 px wide
    mask[22:38, 8:22] = False  # print across its middle
    x, y = inner_pixel(mask)
    # deepest: 9-10 px from every edge, in the plain band above or below the print
    depth = min(x - 5 + 1, 25 - x, y - 5 + 1, 55 - y, 22 - y if y < 22 else y - 37)
    assert depth >= 8, (x, y)
    assert mask[y, x]
    # an object cut by the image's left edge: the click keeps away from that edge as from its own
    cut = torch.zeros(40, 40, dtype=torch.bool)
    cut[10:30, 0:20] = True
    x, y = inner_pixel(cut)
    assert 8 <= x <= 11 and 18 <= y <= 21, (x, y)
    assert inner_pixel(torch.ones(9, 9, dtype=torch.bool)) == (4, 4)  # the whole image: its centre


def test_the_default_click_reads_the_render_then_the_photo():
    """The click is where the render shows the object's colour (what the pick reads); only where the render shows
    it nowhere (a field trained too briefly) does the photo decide; never where no Gaussian covers."""
    from virgi_ns.demo.config import DemoConfig
    from virgi_ns.demo.run import default_click

    blue, grey = torch.tensor([0.1, 0.2, 0.9]), torch.tensor([0.5, 0.5, 0.5])
    render = grey.expand(40, 60, 3).clone()
    photo = grey.expand(40, 60, 3).clone()
    render[5:25, 5:25] = blue  # the render shows the object on the left
    photo[5:25, 35:55] = blue  # the photo on the right
    covered = torch.ones(40, 60, dtype=torch.bool)
    rule = DemoConfig().object_rule()
    x, y = default_click(render, photo, covered, rule)
    assert 5 <= x < 25 and 5 <= y < 25
    x, y = default_click(grey.expand(40, 60, 3), photo, covered, rule)
    assert 35 <= x < 55 and 5 <= y < 25
    uncovered = covered.clone()
    uncovered[:, :30] = False
    x, y = default_click(render, photo, uncovered, rule)  # the render's object is not covered: the photo's
    assert 35 <= x < 55
    assert default_click(grey.expand(40, 60, 3), grey.expand(40, 60, 3), covered, rule) is None
