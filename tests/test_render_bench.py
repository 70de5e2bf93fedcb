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
    import virgi_ns.cli.export as export

    monkeypatch.setattr(export, "load_run", lambda path: (None, pipeline))
    args = bench_render.Args(thresholds=[0.0, 1 / 255], repeats=1, views=1)
    row = bench_render.bench_scene(args, SimpleNamespace(name="tiny"), Path("unused"))
    assert math.isnan(row["splat_sh3_fps"])  # no gsplat on a CPU
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
