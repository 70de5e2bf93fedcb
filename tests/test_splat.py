"""Recolouring a splat file with no photos: the ``splat`` dataparser's camera rig and view cache, the
file's own colours as the base under edits, bad input, and the whole path on a small synthetic splat
(train, pick, export) on a CPU."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from splat_scene import make_splat, write_splat
from virgi_ns.colour.file_colours import FileColours
from virgi_ns.data.splat_views import (ViewSettings, cache_root, ensure_views, fibonacci_directions, place_cameras,
                                       raster_cameras_of, render_view_images, run_frame_gaussians)
from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")
REPO = Path(__file__).resolve().parents[1]
TINY = ViewSettings(views=6, eval_views=2, min_resolution=48, max_resolution=48)


# ------------------------------------------------------------------------------ the rig
def test_rig_follows_the_gaussians_and_ignores_floaters():
    g, _ = make_splat(400)
    rig = place_cameras(g, ViewSettings())
    # centre: between the two objects (the middle of the box of the middle 96%); the extent a 95% quantile
    lo, hi = torch.quantile(g.means, 0.02, dim=0), torch.quantile(g.means, 0.98, dim=0)
    torch.testing.assert_close(torch.from_numpy(rig.centre).float(), (lo + hi) / 2, atol=0.3, rtol=0)
    assert abs(rig.centre[0] - 3.0) < 0.5  # the ball at x = 3 - 5.5, the box at 3 + 5.5
    d = (g.means.double() - torch.from_numpy(rig.centre)).norm(dim=-1)
    assert float((d <= rig.radius).double().mean()) == pytest.approx(0.95, abs=0.01)
    # a few far floaters (2% of the Gaussians, 1000 units away, faint) barely move it
    n = len(g) // 50
    far = Gaussians(torch.full((n, 3), 1000.0), g.scales[:n], g.quats[:n], torch.full((n,), -2.0), g.sh[:n])
    both = Gaussians(*(torch.cat([getattr(g, k), getattr(far, k)]) for k in ("means", "scales", "quats", "opacities",
                                                                              "sh")))
    rig2 = place_cameras(both, ViewSettings())
    assert np.abs(rig2.centre - rig.centre).max() < 0.05 * rig.radius
    assert rig2.radius == pytest.approx(rig.radius, rel=0.05)
    # square images between the bounds; the camera distance frames the 95% sphere
    assert 256 <= rig.resolution <= 1024 and rig.resolution % 16 == 0
    assert rig.distance == pytest.approx(1 / math.sin(math.radians(25)))
    assert rig.near < rig.distance < rig.far


def test_held_out_views_lie_between_training_views():
    rig = place_cameras(make_splat(200)[0], ViewSettings(views=64))
    assert len(rig.train_c2w) == 64 and len(rig.eval_c2w) == 8
    tr = rig.train_c2w[:, :, 3] / rig.distance
    ev = rig.eval_c2w[:, :, 3] / rig.distance
    spacing = math.sqrt(4 * math.pi / 72)  # the lattice's mean spacing (radians)
    nearest = np.arccos(np.clip(ev @ tr.T, -1, 1)).min(axis=1)
    assert nearest.max() < 1.5 * spacing
    # every held-out direction lies inside the ring of its neighbouring training directions: seen from it
    # (in its tangent plane), they leave no gap of half a turn
    for e in ev:
        close = tr[np.arccos(np.clip(tr @ e, -1, 1)) < 2.0 * spacing]
        assert len(close) >= 4
        u = np.cross(e, [0.0, 0.0, 1.0] if abs(e[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(e, u)
        ang = np.sort(np.arctan2((close - e) @ v, (close - e) @ u))
        gaps = np.diff(np.concatenate([ang, ang[:1] + 2 * np.pi]))
        assert gaps.max() < np.pi
    # cameras look at the centre, upright about the file's -y
    for c2w in np.concatenate([rig.train_c2w, rig.eval_c2w]):
        R = c2w[:, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(-R[:, 2], -c2w[:, 3] / np.linalg.norm(c2w[:, 3]), atol=1e-9)
    assert np.allclose(np.linalg.norm(fibonacci_directions(10), axis=1), 1)


def test_degenerate_and_bad_settings_are_refused():
    g, _ = make_splat(50)
    point = g.replace(means=torch.zeros_like(g.means) + 3.0)
    with pytest.raises(InputError, match="degenerate extent"):
        place_cameras(point, ViewSettings())
    with pytest.raises(InputError, match="--views"):
        ViewSettings(views=0).check()


# ---------------------------------------------------------------------------- the cache
def test_views_are_cached_by_content_and_regenerated_identically(tmp_path):
    g, _ = make_splat(150)
    folder, rig, train, held = ensure_views(g, TINY, "two.ply", tmp_path)
    assert folder.parent == tmp_path / "splat-views" and len(train) == 6 and len(held) == 2
    stamp = {p: p.stat().st_mtime_ns for p in train + held}
    first = train[0].read_bytes()
    again = ensure_views(g, TINY, "two.ply", tmp_path)
    assert again[0] == folder and all(p.stat().st_mtime_ns == stamp[p] for p in stamp)  # nothing rendered
    train[0].unlink()
    ensure_views(g, TINY, "two.ply", tmp_path)
    assert train[0].read_bytes() == first  # rendered again, the same bytes
    other = ensure_views(g, ViewSettings(views=5, eval_views=1, min_resolution=48, max_resolution=48), "x", tmp_path)
    assert other[0] != folder  # other settings: another folder
    assert not list(folder.glob(".*.tmp*"))
    os.environ.pop("VIRGI_NS_CACHE", None)
    assert cache_root(Path("/x")) == Path("/x")


def test_views_are_the_splats_own_render(tmp_path):
    """Each cached image is the file's SH colours composited over the background (8-bit)."""
    g, red = make_splat(150)
    _, rig, train, _ = ensure_views(g, TINY, "two.ply", tmp_path)
    from PIL import Image

    img = np.asarray(Image.open(train[0]), dtype=np.float32) / 255
    cams = raster_cameras_of(rig.train_c2w[:1], rig)
    ref = next(render_view_images(run_frame_gaussians(g, rig), cams, (0.0, 0.0, 0.0))).numpy()
    assert np.abs(img - ref).max() <= 0.5 / 255 + 1e-6
    reds = (img[..., 0] > 0.5) & (img[..., 2] < 0.3)
    blues = (img[..., 2] > 0.5) & (img[..., 0] < 0.3)
    assert reds.sum() > 20 and blues.sum() > 20  # both objects are in view


# ------------------------------------------------------------------------ file colours
def test_file_colours_are_exact_where_no_edit_touches():
    gen = torch.Generator().manual_seed(1)
    n = 64
    dc = torch.randn(n, 3, generator=gen)
    rest = 0.3 * torch.randn(n, 15, 3, generator=gen)
    fc = FileColours(dc, rest)
    dirs = torch.randn(n, 3, generator=gen)
    from virgi_ns.colour.sh import sh_colours

    want = sh_colours(torch.cat([dc[:, None], rest], 1), dirs)
    torch.testing.assert_close(fc.colours(None, dirs), want, atol=1e-6, rtol=0)
    b, s = fc.logits(None, dirs)
    torch.testing.assert_close(torch.sigmoid(b + s), want.clamp(1e-3, 1 - 1e-3), atol=1e-5, rtol=0)
    # no change: exactly the file's colours; a change on some: the others stay exact
    assert torch.equal(fc.edited_colours(None, dirs, b, 1.0), fc.colours(None, dirs))
    e = b.clone()
    e[:10] += 2.0
    e[10:20] += 1e-4  # below half an 8-bit step: untouched
    out = fc.edited_colours(None, dirs, e, 1.0)
    assert torch.equal(out[10:], fc.colours(None, dirs)[10:])
    torch.testing.assert_close(out[:10], want[:10] + torch.sigmoid(e[:10] + s[:10]) - torch.sigmoid(b[:10] + s[:10]))
    # the edit engine's form: the field's c_d, its change, and c_s = s + (b - c_d) / k give the same logit
    c_field = torch.randn(n, 3, generator=gen)
    c_edit = c_field + 0.7
    for k in (1.0, 0.5):
        off, c_s = fc.for_edit(None, dirs, c_field, k)
        e = fc.edited_logits(b, c_field, c_edit)
        torch.testing.assert_close(c_edit + off + k * c_s, e + k * s)
    # k != 1 touches every Gaussian of a view-dependent file; a view-independent file ignores k
    assert bool(fc.touched(b, b, 0.0).all())
    flat = FileColours(dc, torch.zeros(n, 15, 3))
    assert not flat.view_dependent and not bool(flat.touched(b, b, 0.0).any())
    torch.testing.assert_close(flat.colours(None, dirs), (SH_C0 * dc + 0.5).clamp_min(0))


# --------------------------------------------------------------------------- bad input
def _prepared(data: Path, tmp_path: Path, **parser):
    from method_configs.virgi import virgi_trainer_config
    from virgi_ns.data.splat import SplatDataParserConfig

    cfg = virgi_trainer_config("virgi")
    cfg.output_dir = tmp_path / "outputs"
    cfg.pipeline.datamanager.data = data
    cfg.pipeline.datamanager.dataparser = SplatDataParserConfig(cache_dir=tmp_path / "cache", **parser)
    return cfg


def _bad_files(tmp_path: Path) -> dict:
    from virgi_ns.io import save_ply

    g, _ = make_splat(20)
    out = {}
    save_ply(g.index(torch.zeros(len(g), dtype=torch.bool)), tmp_path / "empty.ply")
    out["empty"] = (tmp_path / "empty.ply", {}, "holds no Gaussians")
    bad = g.means.clone()
    bad[3, 1] = float("nan")
    save_ply(g.replace(means=bad), tmp_path / "nan.ply")
    out["nan"] = (tmp_path / "nan.ply", {}, "NaN or Inf")
    inf = g.scales.clone()
    inf[5, 0] = float("inf")
    save_ply(g.replace(scales=inf), tmp_path / "inf.ply")
    out["inf"] = (tmp_path / "inf.ply", {}, "NaN or Inf")
    save_ply(g.replace(means=torch.ones_like(g.means)), tmp_path / "point.ply")
    out["point"] = (tmp_path / "point.ply", {}, "degenerate extent")
    save_ply(g, tmp_path / "many.ply")
    out["too_many"] = (tmp_path / "many.ply", {"max_gaussians": 10}, "more than --max-gaussians 10")
    out["missing"] = (tmp_path / "nothing.ply", {}, "no such file")
    return out


@pytest.mark.parametrize("case", ["empty", "nan", "inf", "point", "too_many", "missing"])
def test_bad_splats_are_one_line_exit_2_and_nothing_written(case, tmp_path, capsys):
    path, parser, message = _bad_files(tmp_path)[case]
    cfg = _prepared(path, tmp_path, **parser)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        cfg.print_to_terminal()  # ns-train's first step after parsing: before any output or file
    assert exit_.value.code == 2
    err = capsys.readouterr()
    assert err.out == "" and len(err.err.strip().splitlines()) == 1 and message in err.err
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "cache").exists()
    with pytest.raises(SystemExit):
        cfg.save_config()
    assert not (tmp_path / "outputs").exists()


def test_a_splat_run_is_a_colour_stage_on_the_files_gaussians(tmp_path):
    g, _ = write_splat(tmp_path / "two.ply", n_per_object=30)
    cfg = _prepared(tmp_path / "two.ply", tmp_path)
    from virgi_ns.data.splat import prepare_splat_run

    assert prepare_splat_run(cfg) and prepare_splat_run(cfg)  # idempotent
    m = cfg.pipeline.model
    assert m.geometry_from == (tmp_path / "two.ply").resolve() and m.geometry_frame == "capture"
    assert m.base_colours == "file" and m.background_color == "black"
    assert cfg.max_num_iterations == 1000 == m.colour_steps
    cfg2 = _prepared(tmp_path / "two.ply", tmp_path)
    cfg2.max_num_iterations = 77
    cfg2.pipeline.model.base_colours = "field"
    prepare_splat_run(cfg2)
    assert cfg2.max_num_iterations == 77 and cfg2.pipeline.model.base_colours == "field"
    cfg3 = _prepared(tmp_path / "two.ply", tmp_path)
    cfg3.pipeline.model.geometry_from = tmp_path / "other.ply"
    with pytest.raises(InputError, match="geometry-from"):
        prepare_splat_run(cfg3)


# ---------------------------------------------------------------------- the whole path
def _red_click(images) -> tuple[int, tuple[int, int]]:
    from virgi_ns.demo.run import inner_pixel

    def counts(im):  # (red, blue) pixels
        return int(((im[..., 0] > 0.5) & (im[..., 2] < 0.3)).sum()), int(((im[..., 2] > 0.5) & (im[..., 0] < 0.3)).sum())

    best = max(range(len(images)), key=lambda i: min(counts(images[i])))  # both objects in view
    im = images[best]
    return best, inner_pixel((im[..., 0] > 0.5) & (im[..., 2] < 0.3))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A small synthetic splat (a red ball, a blue box) through the splat run with a tiny recipe (in
    process, as the demo trains it: the splat dataparser, the virgi recipe made a splat run), then
    ``virgi-edit pick`` on the ball to green and ``virgi-export``, unedited and recoloured."""
    from PIL import Image
    from rich.console import Console

    from virgi_ns.demo.splat import SplatDemoConfig, run

    tmp_path = tmp_path_factory.mktemp("splat_demo")
    g, red = write_splat(tmp_path / "two.ply", n_per_object=1000)
    settings = ViewSettings(views=6, eval_views=2, min_resolution=48, max_resolution=48)
    _, _, train, _ = ensure_views(g, settings, "two.ply", tmp_path / "cache")  # the demo finds them cached
    images = [np.asarray(Image.open(p), dtype=np.float32) / 255 for p in train]
    view, pixel = _red_click([torch.from_numpy(im) for im in images])
    cfg = SplatDemoConfig(splat=tmp_path / "two.ply", out=tmp_path / "out", device="cpu", views=6, eval_views=2,
                          min_resolution=48, max_resolution=48, steps=4, camera_index=view, pixel=pixel,
                          colour="#20c040", cache_dir=tmp_path / "cache", colour_init_steps=10, hash_log2=12,
                          pixel_budget=2 * 5 * 16 * 16)
    metrics = run(cfg, Console(quiet=True))
    return {"root": tmp_path, "red": red, "metrics": metrics, "config": Path(metrics["run"]), "view": view,
            "pixel": pixel}


def test_pick_recolours_one_object_and_the_export_keeps_the_rest(demo):
    """The ball turns green in the held-out views; the export keeps the file's own Gaussians and
    coefficients wherever the edit does not reach (the box), and all of them unedited."""
    from virgi_ns.io import load_splat

    root, red, metrics = demo["root"], demo["red"], demo["metrics"]
    orig = load_splat(root / "two.ply")
    plain = load_splat(root / "out" / "unedited.ply")
    assert torch.equal(plain.sh[:, :4], orig.sh) and not bool(plain.sh[:, 4:].any())  # degree 1, padded to 3
    torch.testing.assert_close(plain.means, orig.means, atol=2e-6, rtol=1e-6)  # where the file was
    assert torch.equal(plain.opacities, orig.opacities)
    assert metrics["fidelity_psnr_min"] >= 50.0
    rec = load_splat(root / "out" / "recoloured.ply")
    box = ~red
    dc = (SH_C0 * rec.sh[red, 0] + 0.5).clamp(0, 1)
    greenish = (dc[:, 1] > dc[:, 0] + 0.2) & (dc[:, 1] > dc[:, 2] + 0.2)
    assert float(greenish.float().mean()) >= 0.8
    # the box: what the tiny recipe's segmentation leaves on it stays far below a visible change
    assert float((SH_C0 * (rec.sh[box, 0] - orig.sh[box, 0])).abs().max()) < 0.05
    assert load_splat(root / "out" / "recoloured.spz").means.shape == rec.means.shape
    # held-out views: the ball's pixels turned; elsewhere (where no ball Gaussian reaches: the truth's
    # mask) the recoloured export stays within the leak target of the original's render
    assert metrics["views_with_part"] == 2
    assert metrics["recoloured_share_min"] >= 0.8
    for (a, c, ball) in held_out_renders(root, red):
        assert _psnr(c, a, ball < 0.01) >= 30.0
        assert float(((c - a).abs().amax(-1) > 0.2)[ball > 0.5].float().mean()) > 0.8  # the ball changed
    assert (root / "out" / "grid.png").is_file()


def _psnr(a, b, mask) -> float:
    return float(-10 * torch.log10(((a - b) ** 2)[mask].mean().clamp_min(1e-12)))


def held_out_renders(root: Path, red: torch.Tensor):
    """(original, recoloured export, the ball's share of each pixel) at each held-out view, in the
    file's frame (the reference rasterizer)."""
    from virgi_ns.demo.splat import render_splat
    from virgi_ns.io import load_splat
    from virgi_ns.nerfstudio.frames import CaptureFrame
    from virgi_ns.nerfstudio.saved_run import RunInfo
    from virgi_ns.raster import Cameras, Request, composite, rasterize

    info = RunInfo.read(root / "out" / "run")
    cams = info.eval.cameras()
    vm = CaptureFrame(info.capture_transform, info.capture_scale).viewmats_to_capture(cams.viewmats.double()).float()
    orig, rec = load_splat(root / "two.ply"), load_splat(root / "out" / "recoloured.ply")
    out = []
    for i in range(len(cams)):
        W, H, K = int(cams.widths[i]), int(cams.heights[i]), cams.Ks[i]
        one = Cameras(K[None], vm[i][None], [W], [H])
        contrib = rasterize(orig.means, orig.normalized_quats(), orig.scales.exp(), torch.sigmoid(orig.opacities), one,
                            Request.whole_images(one), backend="reference")
        ball = composite(red.float()[:, None][contrib.pair_gaussian], contrib)[0][..., 0]
        out.append((render_splat(orig, vm[i], K, W, H, (0.0, 0.0, 0.0), torch.device("cpu")),
                    render_splat(rec, vm[i], K, W, H, (0.0, 0.0, 0.0), torch.device("cpu")), ball))
    return out


def test_the_run_renders_the_files_colours_and_the_edit_as_exported(demo):
    """Through nerfstudio's loader (what ns-viewer opens): the model's render of a held-out view is the
    splat's own, and with the edit stack it matches the recoloured export rendered as a splat."""
    from virgi_ns.nerfstudio.runs import load_run
    from virgi_ns.demo.splat import render_splat
    from virgi_ns.edit.stack import EditStack
    from virgi_ns.io import load_splat
    from virgi_ns.nerfstudio.cameras import raster_cameras
    from virgi_ns.nerfstudio.frames import CaptureFrame

    root = demo["root"]
    _, pipeline = load_run(demo["config"])
    model = pipeline.model
    assert model.base_colours == "file"
    ds = pipeline.datamanager.eval_dataset
    cam = ds.cameras[0:1]
    base = model.get_outputs_for_camera(cam)["rgb"]
    assert float((base - ds.get_image_float32(0)).abs().max()) <= 0.5 / 255 + 1e-5
    model.set_edit_stack(EditStack.open(demo["config"].parent, model.fingerprint()))
    edited = model.get_outputs_for_camera(cam)["rgb"]
    rc = raster_cameras(cam)
    vm = CaptureFrame.from_pipeline(pipeline).viewmats_to_capture(rc.viewmats.double()).float()
    exported = render_splat(load_splat(root / "out" / "recoloured.ply"), vm[0], rc.Ks[0], int(rc.widths[0]),
                            int(rc.heights[0]), model.background_color, torch.device("cpu"))
    assert float((edited - base).abs().amax(-1).gt(0.2).float().mean()) > 0.02  # the ball changed
    assert float(((edited - exported) ** 2).mean()) < 1e-4  # >= 40 dB


def test_a_cleared_view_cache_is_rendered_again_for_the_commands(demo):
    """The commands read a training view as the edit's original; where the cache is gone they render it
    again, the same bytes."""
    from virgi_ns.nerfstudio.saved_run import load_saved_run

    run = load_saved_run(demo["config"], torch.device("cpu"))
    before = run.info.train.photo(1)
    Path(run.info.train.filenames[1]).unlink()
    after = load_saved_run(demo["config"], torch.device("cpu")).info.train.photo(1)
    assert np.array_equal(before, after) and Path(run.info.train.filenames[1]).is_file()


@pytest.mark.slow
def test_ns_train_on_a_splat_then_pick_and_export(tmp_path):
    """The same through the commands: ``ns-train virgi --data two.ply splat`` (a subprocess), then
    ``virgi-edit pick`` and ``virgi-export``; and bad input to ``ns-train``: one line, exit 2."""
    from virgi_ns.io import load_splat

    g, red = write_splat(tmp_path / "two.ply", n_per_object=1500)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p),
           "VIRGI_NS_CACHE": str(tmp_path / "cache"),
           "NERFSTUDIO_DATAPARSER_CONFIGS": "splat=virgi_ns.data.splat:splat_dataparser"}
    bin_ = Path(sys.executable).parent
    common = [str(bin_ / "ns-train"), "virgi", "--vis", "tensorboard", "--machine.device-type", "cpu",
              "--output-dir", str(tmp_path / "outputs"), "--timestamp", "t", "--max-num-iterations", "30",
              "--pipeline.model.color-field.log2-hashmap-size", "12", "--pipeline.model.colour-init-steps", "60",
              "--pipeline.datamanager.tile-size", "16", "--pipeline.datamanager.pixel-budget", "2560",
              "--steps-per-eval-image", "1000000"]
    tiny = ["splat", "--views", "8", "--eval-views", "2", "--min-resolution", "48", "--max-resolution", "48"]
    from virgi_ns.io import save_ply

    save_ply(g.index(torch.zeros(len(g), dtype=torch.bool)), tmp_path / "empty.ply")
    bad = subprocess.run(common + ["--data", str(tmp_path / "empty.ply")] + tiny, env=env, capture_output=True,
                         text=True, timeout=600)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("error: ")
    assert "holds no Gaussians" in bad.stderr and not (tmp_path / "outputs").exists()
    done = subprocess.run(common + ["--data", str(tmp_path / "two.ply")] + tiny, env=env, capture_output=True,
                          text=True, timeout=1200)
    assert done.returncode == 0, done.stderr[-2000:]
    config = next((tmp_path / "outputs").rglob("config.yml"))
    from virgi_ns.nerfstudio.saved_run import RunInfo

    from PIL import Image

    info = RunInfo.read(config.parent)
    images = [torch.from_numpy(np.asarray(Image.open(f), dtype=np.float32) / 255) for f in info.train.filenames]
    view, (x, y) = _red_click(images)
    for args in (["virgi-edit", "pick", "--load-config", str(config), "--camera-index", str(view), "--pixel", str(x),
                  str(y), "--colour", "#20c040"],
                 ["virgi-export", "--load-config", str(config), "--out", str(tmp_path / "rec.spz")]):
        out = subprocess.run([str(bin_ / args[0])] + args[1:], env=env, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
    rec = load_splat(tmp_path / "rec.spz")
    dc = (SH_C0 * rec.sh[red, 0] + 0.5).clamp(0, 1)
    assert float((dc[:, 1] > dc[:, 0] + 0.2).float().mean()) >= 0.8
    orig_blue = (SH_C0 * load_splat(tmp_path / "two.ply").sh[~red, 0] + 0.5)
    blue = (SH_C0 * rec.sh[~red, 0] + 0.5)
    assert float((blue - orig_blue).abs().max()) < 0.01  # (.spz stores colours in 8 bits)
    # with a field trained a little longer the box is not touched at all: its own coefficients exactly
    subprocess.run([str(bin_ / "virgi-export"), "--load-config", str(config), "--out", str(tmp_path / "rec.ply")],
                   env=env, check=True, capture_output=True, timeout=600)
    exact = load_splat(tmp_path / "rec.ply").sh[~red, :4] == load_splat(tmp_path / "two.ply").sh[~red]
    assert float(exact.all(dim=-1).all(dim=-1).float().mean()) >= 0.99


@pytest.mark.gpu
@pytest.mark.slow
@pytest.mark.parametrize("name", ["biker", "guitar"])
def test_a_real_splat_on_a_gpu(name, shared_data, tmp_path):
    """On one GPU: ``ns-train virgi --data SPLAT splat`` at the default views trains a run; then the demo
    (its own training, a click on the most colourful spot, exports): the unedited export within 35 dB of
    the original at every held-out view (rendered by gsplat), the recoloured one within 30 dB outside
    the edit's segmentation. (The command's wall is timed by bench/device_bench.sh, not here.)"""
    from rich.console import Console

    from virgi_ns.demo.splat import SplatDemoConfig, run

    splat = shared_data / "splats" / f"{name}.compressed.ply"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p),
           "VIRGI_NS_CACHE": str(tmp_path / "cache"),
           "NERFSTUDIO_DATAPARSER_CONFIGS": "splat=virgi_ns.data.splat:splat_dataparser"}
    train = "from nerfstudio.scripts.train import entrypoint; entrypoint()"
    done = subprocess.run([sys.executable, "-c", train, "virgi", "--data", str(splat), "--vis", "tensorboard",
                           "--output-dir", str(tmp_path / "outputs"), "splat"], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    metrics = run(SplatDemoConfig(splat=splat, out=tmp_path / "demo", device="cuda", cache_dir=tmp_path / "cache"),
                  Console(quiet=True))
    assert metrics["fidelity_psnr_min"] >= 35.0
    assert metrics["leak_psnr_min"] >= 30.0
