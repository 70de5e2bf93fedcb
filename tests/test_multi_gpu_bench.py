"""``bench/multi_gpu.py``: its arguments, its arithmetic on hand-made rows, and (slow) a run on two
CPU processes (gloo) of the procedural capture, which checks that the script runs end to end (its
figures on a CPU mean nothing)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from script_module import script_module
from virgi_scene import make_scene

ROOT = Path(__file__).resolve().parents[1]
TINY = ("pipeline.model.random_init=True,pipeline.model.num_random=150,pipeline.model.raster_backend=reference,"
        "pipeline.model.num_downscales=0,pipeline.model.colour_init_steps=20,"
        "pipeline.model.color_field.log2_hashmap_size=12,pipeline.model.color_field.levels=8,"
        "pipeline.datamanager.pixel_budget=2560,pipeline.datamanager.tile_size=16")


@pytest.fixture(scope="module")
def bench():
    with script_module("bench/multi_gpu.py", "bench_multi_gpu") as mod:
        yield mod


def test_arguments(bench, capsys, tmp_path):
    import tyro

    make_scene(tmp_path / "tiny")  # the bundled procedural capture: a clone has no ../shared

    with pytest.raises(SystemExit) as e:
        tyro.cli(bench.Args, args=["--help"])
    assert e.value.code == 0 and "--worlds" in capsys.readouterr().out
    args = tyro.cli(bench.Args, args=["--worlds", "1", "2", "--seeds", "42", "43", "--device", "cpu", "--steps", "8",
                                      "--data", str(tmp_path), "--scene", "tiny"])
    assert args.worlds == [1, 2] and args.seeds == [42, 43] and args.device == "cpu" and args.steps == 8
    cfg = bench.run_config(args, 2, 43)
    assert cfg.machine.num_devices == 2 and cfg.machine.seed == 43 and cfg.pipeline.model.geometry_steps == 8
    # the recipe's own evaluations and checkpoints stay: the whole run is what ns-train runs
    assert cfg.steps_per_save == 2000 and cfg.steps_per_eval_image == 500
    with pytest.raises(Exception, match="scene folder not found"):
        bench.main(tyro.cli(bench.Args, args=["--data", str(tmp_path), "--scene", "absent"]))
    with pytest.raises(Exception, match="must hold 1"):
        bench.main(tyro.cli(bench.Args, args=["--worlds", "2"]))


def test_speedups_and_summary(bench):
    def row(world, seed, geo, col, psnr, wall):
        return {"world": world, "seed": seed, "geometry_steps_per_s": geo, "colour_steps_per_s": col, "psnr": psnr,
                "whole_run_s": wall}

    rows = [row(1, 42, 10.0, 20.0, 25.0, 100.0), row(2, 42, 9.0, 18.0, 24.9, 50.0),
            row(1, 43, 10.0, 20.0, 25.4, 120.0), row(2, 43, 8.0, 19.0, 25.3, 80.0)]
    bench.speedups(rows)
    # views (pixels) per second over one process: N x the ratio of steps per second, by hand
    assert [r["geometry_speedup"] for r in rows] == pytest.approx([1.0, 1.8, 1.0, 1.6])
    assert [r["colour_speedup"] for r in rows] == pytest.approx([1.0, 1.8, 1.0, 1.9])
    two = next(s for s in bench.summary(rows) if s["world"] == 2)
    assert two["geometry_speedup"] == pytest.approx(1.7) and two["colour_speedup"] == pytest.approx(1.85)
    # the whole run: one GPU's wall over N's, paired by seed (100/50, 120/80)
    assert [r["whole_run_speedup"] for r in rows] == pytest.approx([1.0, 2.0, 1.0, 1.5])
    assert two["whole_run_speedup"] == pytest.approx(1.75) and two["whole_run_s_mean"] == pytest.approx(65.0)
    assert two["psnr_minus_one_gpu_mean"] == pytest.approx(-0.1)
    assert two["psnr_minus_one_gpu_range"] == pytest.approx([-0.1, -0.1])
    # one GPU's spread is 25.0..25.4: 24.9 lies outside it
    assert two["psnr_within_one_gpu_spread"] is False
    assert next(s for s in bench.summary(rows) if s["world"] == 1)["psnr_within_one_gpu_spread"] is True
    rows[1]["psnr"] = 25.1
    assert next(s for s in bench.summary(rows) if s["world"] == 2)["psnr_within_one_gpu_spread"] is True
    assert math.isnan(bench.steps_per_s(0.0)) and math.isnan(bench.steps_per_s(None))
    assert bench.steps_per_s(250.0) == pytest.approx(4.0)


@pytest.mark.slow  # three fresh interpreters loading nerfstudio; the arguments are checked above
def test_runs_on_two_cpu_processes(tmp_path):
    make_scene(tmp_path / "data" / "tiny")
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, str(ROOT / "bench" / "multi_gpu.py"), "--device", "cpu", "--data", str(tmp_path / "data"),
           "--scene", "tiny", "--steps", "4", "--colour-steps", "4", "--out", str(out), "--settings", TINY]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "per N over the seeds" in proc.stdout
    res = json.loads((out / "results.json").read_text())
    one, two = sorted(res["rows"], key=lambda r: r["world"])
    # the batch rule: half the steps of twice the batch, so the same views seen
    assert (one["world"], one["geometry_steps"], one["colour_steps"]) == (1, 4, 4)
    assert (two["world"], two["geometry_steps"], two["colour_steps"]) == (2, 2, 2)
    assert two["views_per_geometry_step"] == 2 * one["views_per_geometry_step"] == 2
    assert two["pixels_per_colour_step"] == 2 * one["pixels_per_colour_step"] == 2 * 2560
    assert all(math.isfinite(r["psnr"]) for r in (one, two))
    assert all(0 < r["train_s"] < r["whole_run_s"] for r in (one, two))  # the interpreter's start is in the wall
    assert [s["world"] for s in res["summary"]] == [1, 2] and res["device"] == "CPU (gloo)"
