"""``virgi-render``, CAM.json and SH colours, on tiny PLY files written here."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from virgi_ns.cli.render import Render, run
from virgi_ns.colour.sh import sh_colours, view_colours
from virgi_ns.errors import InputError
from virgi_ns.gaussians import Gaussians
from virgi_ns.io.camera_json import CameraSpec, parse_camera, read_camera_json, write_camera_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_raster_reference import brute_force, look_at  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
W, H = 24, 20


def tiny_gaussians(degree: int = 0, n: int = 12, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    scales = torch.log(0.05 + 0.2 * torch.rand(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opac = torch.randn(n, generator=g) * 2
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g) * 0.8
    return Gaussians(means, scales, quats, opac, sh)


def spec() -> CameraSpec:
    return CameraSpec(W, H, 22.0, 23.0, 11.5, 10.0, look_at((0.3, -0.2, -3.0)).numpy())


def write_inputs(tmp_path: Path, degree: int = 0):
    from virgi_ns.io import save_ply

    g = tiny_gaussians(degree)
    save_ply(g, tmp_path / "s.ply")
    write_camera_json(tmp_path / "cam.json", spec())
    return g


def expected_image(g: Gaussians, sp: CameraSpec, background, colours: np.ndarray) -> np.ndarray:
    """Brute force per pixel (float64) of the stored (float32-rounded) Gaussians."""
    cams = sp.to_cameras(torch.float64)
    means, quats = g.means.double(), g.quats.double()
    scales, opac = torch.exp(g.scales.double()), torch.sigmoid(g.opacities.double())
    pix = [(x, y) for y in range(sp.height) for x in range(sp.width)]
    out = np.zeros((sp.height, sp.width, 3))
    for (x, y), (lst, T) in zip(pix, brute_force(means, quats, scales, opac, cams, 0, pix)):
        out[y, x] = sum((w * colours[i] for i, w in lst), np.zeros(3)) + T * np.asarray(background)
    return out


def test_render_npy_and_png_match_brute_force(tmp_path):
    g = write_inputs(tmp_path)
    bg = (0.1, 0.6, 0.3)
    msg = run(Render(tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "o.npy", "reference", bg))
    assert "24x20" in msg
    img = np.load(tmp_path / "o.npy")
    assert img.dtype == np.float32 and img.shape == (H, W, 3)
    f_dc = g.sh[:, 0].double().numpy()
    colours = np.maximum(0.2820948 * f_dc + 0.5, 0.0)
    ref = expected_image(g, spec(), bg, colours)
    assert np.abs(img - ref).max() < 1e-5
    assert np.abs(img - np.asarray(bg)).max() > 0.1  # something was drawn

    run(Render(tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "o.png", "reference", bg))
    from PIL import Image

    png = np.asarray(Image.open(tmp_path / "o.png"))
    assert png.dtype == np.uint8 and png.shape == (H, W, 3)
    assert np.abs(png.astype(int) - np.round(np.clip(img, 0, 1) * 255).astype(int)).max() <= 1


def test_render_higher_sh_bands(tmp_path):
    g = write_inputs(tmp_path, degree=2)
    run(Render(tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "o.npy", "reference"))
    img = np.load(tmp_path / "o.npy")
    center = spec().to_cameras(torch.float64).camera_centers()[0]
    gs = pytest.importorskip("gsplat.cuda._torch_impl")
    dirs = g.means.double() - center
    colours = torch.clamp_min(gs._spherical_harmonics(2, dirs, g.sh.double()) + 0.5, 0).numpy()
    ref = expected_image(g, spec(), (0, 0, 0), colours)
    assert np.abs(img - ref).max() < 1e-5
    flat = np.maximum(0.2820948 * g.sh[:, 0].double().numpy() + 0.5, 0.0)
    assert np.abs(img - expected_image(g, spec(), (0, 0, 0), flat)).max() > 1e-3  # the bands matter


def test_sh_matches_gsplat_convention_all_degrees():
    gs = pytest.importorskip("gsplat.cuda._torch_impl")
    gen = torch.Generator().manual_seed(0)
    for degree in range(5):
        sh = torch.randn(50, (degree + 1) ** 2, 3, generator=gen, dtype=torch.float64)
        d = torch.randn(50, 3, generator=gen, dtype=torch.float64) * 3
        ref = torch.clamp_min(gs._spherical_harmonics(degree, d, sh) + 0.5, 0)
        assert (sh_colours(sh, d) - ref).abs().max() < 1e-6
    sh0 = torch.tensor([[[1.0, -2.0, 0.0]]])
    assert torch.allclose(sh_colours(sh0), torch.tensor([[0.2820948 + 0.5, 0.0, 0.5]]), atol=1e-6)
    assert torch.allclose(view_colours(sh0, torch.zeros(1, 3), torch.ones(3)), sh_colours(sh0))


def test_camera_json_round_trip_and_errors(tmp_path):
    sp = spec()
    write_camera_json(tmp_path / "c.json", sp)
    back = read_camera_json(tmp_path / "c.json")
    assert (back.width, back.height, back.fx, back.fy, back.cx, back.cy) == (W, H, 22.0, 23.0, 11.5, 10.0)
    assert np.allclose(back.world_to_camera, sp.world_to_camera)
    cams = back.to_cameras(torch.float64)
    assert torch.allclose(cams.Ks[0], torch.tensor([[22.0, 0, 11.5], [0, 23.0, 10.0], [0, 0, 1]], dtype=torch.float64))

    good = sp.to_dict()
    bad_cases = {
        "missing": {k: v for k, v in good.items() if k != "fy"},
        "neg_width": {**good, "width": -3},
        "float_width": {**good, "width": 12.5},
        "zero_fx": {**good, "fx": 0},
        "nan_cx": {**good, "cx": float("nan")},
        "str_fy": {**good, "fy": "500"},
        "shape": {**good, "world_to_camera": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "last_row": {**good, "world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]},
        "scaled": {**good, "world_to_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
        "mirror": {**good, "world_to_camera": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
        "list": [good],
    }
    for name, d in bad_cases.items():
        with pytest.raises(InputError):
            parse_camera(d, name)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_camera_json(tmp_path / "bad.json")
    with pytest.raises(InputError, match="no such camera file"):
        read_camera_json(tmp_path / "absent.json")


def _cli(*args, cwd):
    exe = Path(sys.executable).parent / "virgi-render"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "virgi_ns.cli.render"]
    return subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_cli_subprocess_ok_and_bad_input(tmp_path):
    write_inputs(tmp_path)
    r = _cli(tmp_path / "s.ply", "--camera", tmp_path / "cam.json", "--out", tmp_path / "a.npy",
             "--backend", "reference", "--background", "1", "1", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    img = np.load(tmp_path / "a.npy")
    run(Render(tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "b.npy", "reference", (1.0, 1.0, 1.0)))
    assert img.shape == (H, W, 3) and np.array_equal(img, np.load(tmp_path / "b.npy"))

    # a bad input through the installed script: exit 2, one line, no output
    r = _cli(tmp_path / "s.ply", "--camera", tmp_path / "cam.json", "--out", tmp_path / "o.jpg", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error:"), r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o.jpg").exists()


def test_cli_bad_inputs_one_line_exit_2(tmp_path, monkeypatch, capsys):
    from virgi_ns.cli.render import entrypoint

    write_inputs(tmp_path)
    (tmp_path / "bad.json").write_text(json.dumps({"width": 10}))
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    cases = [
        (tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "o.jpg"),  # unsupported output
        (tmp_path / "absent.ply", tmp_path / "cam.json", tmp_path / "o.npy"),  # no splat
        (tmp_path / "s.ply", tmp_path / "bad.json", tmp_path / "o.npy"),  # bad camera
        (tmp_path / "s.ply", tmp_path / "absent.json", tmp_path / "o.png"),  # no camera
        (tmp_path / "cam.json", tmp_path / "cam.json", tmp_path / "o.npy"),  # not a splat
        (tmp_path / "junk.ply", tmp_path / "cam.json", tmp_path / "o.npy"),  # a PLY without Gaussians
    ]
    for splat, cam, out in cases:
        monkeypatch.setattr(sys, "argv", ["virgi-render", str(splat), "--camera", str(cam), "--out", str(out),
                                          "--backend", "reference"])
        with pytest.raises(SystemExit) as e:
            entrypoint()
        err = capsys.readouterr().err
        assert e.value.code == 2, (splat, cam, out, err)
        assert len(err.strip().splitlines()) == 1 and err.startswith("error:"), err
        assert not out.exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".o.")]  # no temporary left behind


def test_cli_cuda_backend_without_gpu_is_a_clear_error(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    write_inputs(tmp_path)
    with pytest.raises(InputError, match="needs a CUDA GPU"):
        run(Render(tmp_path / "s.ply", tmp_path / "cam.json", tmp_path / "o.npy", "cuda"))
    assert not (tmp_path / "o.npy").exists()


def test_render_real_splat_smoke(shared_data, tmp_path):
    """biker.spz from a camera 4 units out, looking at its centre: a finite, non-empty picture."""
    from virgi_ns.io import load_splat

    g = load_splat(shared_data.need("splats/biker.spz"))
    keep = torch.randperm(len(g), generator=torch.Generator().manual_seed(0))[:20000]
    lo, hi = g.means.quantile(0.05, dim=0), g.means.quantile(0.95, dim=0)
    centre = ((lo + hi) / 2).double().numpy()
    radius = float((hi - lo).norm())
    sp = CameraSpec(64, 48, 60.0, 60.0, 32.0, 24.0, look_at(centre + np.array([0, 0, -radius]), centre).numpy())
    from virgi_ns.cli.render import render_image

    img = render_image(g.index(keep), sp, "reference", (0, 0, 0))
    assert np.isfinite(img).all() and img.max() > 0.05 and math.isfinite(float(img.mean()))
