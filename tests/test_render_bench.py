"""``bench/render.py`` on a tiny trained run (CPU): a scene's row holds the sweep, the stage split of
the gated and matte frames and the render cache's memory, and the tables print."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest

from script_module import script_module
from test_model_train import build, scene, train  # noqa: F401  (fixture re-exported)

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")


@pytest.fixture(scope="module")
def bench_render():
    with script_module("bench/render.py", "bench_render_under_test") as mod:
        yield mod


def test_render_bench_row_on_a_cpu(scene, bench_render, monkeypatch):  # noqa: F811
    _, pipeline, optimizers, cbs = build(scene, steps=4)
    train(pipeline, optimizers, cbs, 4)
    pipeline.eval()
    import virgi_ns.nerfstudio.runs as runs

    monkeypatch.setattr(runs, "load_run", lambda path: (None, pipeline))
    args = bench_render.Args(thresholds=[0.0, 1 / 255], repeats=1, views=1)
    row = bench_render.bench_scene(args, SimpleNamespace(name="tiny"), Path("unused"))
    assert math.isnan(row["splat_sh3_fps"])  # no gsplat on a CPU
    assert math.isnan(row["splatfacto_sh3_fps"]) and math.isnan(row["splatfacto_sh0_fps"])  # (its frame needs CUDA)
    assert set(row["ratios"]) == {"gated_x_splatfacto_sh3", "gated_x_gsplat_sh3", "matte_x_splatfacto_sh0",
                                  "matte_x_gsplat_sh0"}
    assert [s["threshold"] for s in row["sweep"]] == [0.0, 1 / 255] and row["matte"]["kept"] == 0.0
    assert row["psnr_gated_vs_full"] > 45.0 and row["gated_fps"] > 0 and row["matte"]["fps"] > 0
    for name in ("gated", "matte"):
        st = row["stages_ms"][name]
        assert set(st) == set(bench_render.STAGES)
        assert math.isnan(st["splat"])  # gsplat's pass alone: a GPU's
        assert all(st[k] > 0 for k in bench_render.STAGES if k not in ("splat", "rest"))
        assert math.isclose(st["rest"], st["frame"] - st["camera"] - st["colours"] - st["raster"], abs_tol=1e-9)
    assert row["cache_mib"]["gate"] > 0 and row["cache_mib"]["edits"] > 0 and row["cache_served"]
    bench_render.print_tables([row], None, "cpu")


def test_the_splatfacto_baseline_is_splatfacto_on_the_same_gaussians_built_offline(scene, bench_render,  # noqa: F811
                                                                                   monkeypatch):
    """The baseline is nerfstudio's own SplatfactoModel (not ours), sharing the run's Gaussian tensors, with
    the geometry's SH at the asked degree, every band on, the run's background; built with downloads
    refused (splatfacto's LPIPS would fetch AlexNet's weights where they are not cached)."""
    import torch
    from nerfstudio.models.splatfacto import SplatfactoModel

    from virgi_ns.nerfstudio.model import VirgiModel

    _, pipeline, optimizers, cbs = build(scene, steps=1)
    model = pipeline.model

    def refuse(url, *a, **k):
        raise AssertionError(f"download of {url}")

    monkeypatch.setattr(torch.hub, "download_url_to_file", refuse)
    for degree in (3, 0):
        sf = bench_render.splatfacto_model(model, degree)
        assert isinstance(sf, SplatfactoModel) and not isinstance(sf, VirgiModel) and not sf.training
        for k in ("means", "scales", "quats", "opacities", "features_dc"):
            assert sf.gauss_params[k].data_ptr() == model.gauss_params[k].data_ptr(), k  # shared, not copied
        n = model.num_points
        assert sf.features_rest.shape == (n, (degree + 1) ** 2 - 1, 3)
        if degree == 3:
            assert torch.equal(sf.features_rest[:, : model.features_rest.shape[1]], model.features_rest.detach())
            assert min(sf.step // sf.config.sh_degree_interval, sf.config.sh_degree) == 3
        assert torch.equal(sf.background_color, model.background_color)


def test_the_warm_edit_is_the_apply_edit_fitted_in_process(scene, bench_render, capsys):  # noqa: F811
    """``warm_edit`` fits an edited training photo of a trained run in the bench's own process (set-up and
    steps, positive), and the CLI table prints the first edit of a fresh process as a multiple of it."""
    import torch

    _, pipeline, optimizers, cbs = build(scene, steps=2)
    train(pipeline, optimizers, cbs, 2)
    pipeline.eval()
    cam = pipeline.datamanager.train_dataset.cameras[0]
    H, W = int(cam.height), int(cam.width)
    photo = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    edited = photo.clone()
    edited[: H // 2, : W // 2] = torch.tensor([0.9, 0.1, 0.1])
    warm = bench_render.warm_edit(pipeline.model, cam, edited, photo, repeats=1)
    assert warm["setup_s"] > 0 and warm["steps_s"] > 0
    cli = {"scene": "tiny", "walls_s": {"apply": 2.0}, "edit_setup_s": 0.5, "edit_steps_s": 0.1,
           "edit_warm_setup_s": 0.02, "edit_warm_steps_s": 0.04}
    capsys.readouterr()
    bench_render.print_tables([], cli, "cpu")
    shown = capsys.readouterr().out
    assert "10.0x" in shown and "60 ms" in shown  # first edit 0.6 s against the warm 60 ms
