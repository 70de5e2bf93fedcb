"""``virgi-bench recolor`` / ``accuracy-time`` on a tiny trained run (CPU): files, figures, trends."""

from __future__ import annotations

import json
import math
import os

import pytest
import torch
from rich.console import Console

from virgi_ns.bench.recolor import AccuracyTime, Recolor, RuleArgs, psnr, run_accuracy_time, run_recolor, summary
from virgi_ns.errors import InputError

from script_module import script_module
from viewer_run import train_tiny
from virgi_scene import make_scene


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    scene = make_scene(tmp_path_factory.mktemp("bench_scene"))
    _, pl = train_tiny(scene, steps=20)
    return pl


# a short colour stage leaves dull colours: select every saturated pixel
BROAD = RuleArgs(h0=0.0, h1=360.0, shift=120.0, s_min=0.1, v_min=0.05)


def _quiet() -> Console:
    return Console(file=open(os.devnull, "w"))


def test_psnr_helper_against_direct_formula():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(5, 7, 3, generator=g), torch.rand(5, 7, 3, generator=g)
    mse = float(((a - b) ** 2).mean())
    assert psnr(a, b) == pytest.approx(-10 * math.log10(mse), rel=1e-5)
    m = torch.zeros(5, 7, dtype=torch.bool)
    m[1:3, 2:5] = True
    mse_m = float(((a[1:3, 2:5] - b[1:3, 2:5]) ** 2).mean())
    assert psnr(a, b, m) == pytest.approx(-10 * math.log10(mse_m), rel=1e-5)
    assert math.isnan(psnr(a, b, torch.zeros(5, 7, dtype=torch.bool)))


def test_recolor_bench_writes_results_and_pictures(pipeline, tmp_path):
    out = tmp_path / "r" / "results.json"
    args = Recolor(load_config=tmp_path / "unused.yml", out=out, rule=BROAD, edit_source="render", steps=40, repeats=1,
                   pictures=1, lpips=False)
    res = run_recolor(args, pipeline, _quiet())
    assert json.loads(out.read_text())["timing"]["steps"] == 40
    assert (tmp_path / "r" / "results_view0.png").is_file() and (tmp_path / "r" / "results_edit.png").is_file()
    m = res["mean"]
    assert 0 < m["mask_fraction"] < 1
    for k in ("recolour_psnr", "unedited_psnr", "propagation_psnr", "miss_psnr", "leak_psnr",
              "per_gaussian_rule_propagation_psnr", "perfect_edit_recolour_psnr"):
        assert math.isfinite(m[k]), k
    assert res["timing"]["setup_s"] > 0 and res["timing"]["steps_s"] > 0
    assert "propagation" in summary({**res, "mean": {**m, "recolour_lpips": math.nan}})


def test_accuracy_time_sweep_more_steps_help(pipeline, tmp_path):
    out = tmp_path / "at.json"
    args = AccuracyTime(load_config=tmp_path / "unused.yml", out=out, rule=BROAD, edit_source="render", steps=(1, 60),
                        pixel_batches=(1,), repeats=1)
    res = run_accuracy_time(args, pipeline, _quiet())
    assert out.is_file() and out.with_suffix(".png").stat().st_size > 1000
    p1, p60 = res["points"]
    assert p60["miss_psnr"] > p1["miss_psnr"] + 3.0, (p1["miss_psnr"], p60["miss_psnr"])


def test_bad_bench_arguments(pipeline, tmp_path):
    with pytest.raises(InputError, match="hue"):
        run_recolor(Recolor(tmp_path / "x.yml", rule=RuleArgs(h0=400)), pipeline, _quiet())
    with pytest.raises(InputError, match="out of range"):
        run_recolor(Recolor(tmp_path / "x.yml", edit_view=999), pipeline, _quiet())
    with pytest.raises(InputError, match="edit-source"):
        run_recolor(Recolor(tmp_path / "x.yml", edit_source="paint"), pipeline, _quiet())


@pytest.fixture
def bench_edit():
    with script_module("bench/edit.py", "bench_edit") as mod:
        yield mod


def test_edit_bench_measures_a_scene_and_its_variants_on_one_run(pipeline, bench_edit, tmp_path, monkeypatch):
    """``bench/edit.py``: a scene of the set, run as a user would edit it (the photo the rule
    recolours most), then one row per --variants entry on the same loaded run (CPU, tiny scene)."""
    from virgi_ns.bench.evalset import EvalScene, edit_view

    import virgi_ns.cli.edit as cli_edit

    loads = []
    monkeypatch.setattr(cli_edit, "load_run", lambda cfg: loads.append(cfg) or (None, pipeline))
    (tmp_path / "data" / "tiny").mkdir(parents=True)
    cfg = tmp_path / "config.yml"
    cfg.write_text("unused")
    scene = EvalScene("tiny", "tiny", BROAD.rule(), "every saturated pixel")
    args = bench_edit.Args(data=tmp_path / "data", runs={"tiny": cfg}, out=tmp_path / "out", steps=20, repeats=1,
                           pictures=1, variants=["pixel_batches=2", "steps=10,lr=0.05,rule=0/360/60/0.2/0.05",
                                                 "other:steps=5", "tiny:recipe=staged,seg_samples=512,seg_steps=20"])
    assert bench_edit.parse_variant("steps=20,pixel_batches=2") == {"steps": 20, "pixel_batches": 2}
    assert bench_edit.parse_variant("rule=10/20/30/0.1/0.2")["rule"] == RuleArgs(10, 20, 30, 0.1, 0.2).rule()
    for bad in ("steps", "colour=3", "steps=many", "rule=1/2/3", "changed_target=chnage", "whole_image=ture",
                "recipe=both"):
        with pytest.raises(InputError, match="--variants"):
            bench_edit.parse_variant(bad)
    assert bench_edit.variant_scene("fern:rule=1/2/3/0.1/0.1") == ("fern", "rule=1/2/3/0.1/0.1")
    assert bench_edit.variant_scene("steps=3") == (None, "steps=3")
    bench_edit.check_variant("tiny:steps=3", ["tiny"])
    for bad in ("fern:steps=3", "tiny:", "tiny:steps=x"):
        with pytest.raises(InputError, match="--variants"):
            bench_edit.check_variant(bad, ["tiny"])
    rows = bench_edit.bench_scene(args, scene, {})
    assert loads == [cfg]
    # the edited photo is the training photo the rule recolours most
    train = pipeline.datamanager.train_dataset
    photos = [train.get_image_float32(i)[..., :3] for i in range(len(train))]
    assert rows[0]["edit_view"] == edit_view(photos, scene.rule)
    from virgi_ns.edit.recolor import rule_mask

    counts = [int(rule_mask(p, scene.rule).sum()) for p in photos]
    assert counts[rows[0]["edit_view"]] == max(counts)
    # 'other:' entries belong to another scene; 'tiny:' ones to this one, named without the prefix
    assert [r["variant"] for r in rows] == ["engine defaults", "pixel_batches=2",
                                            "steps=10,lr=0.05,rule=0/360/60/0.2/0.05",
                                            "recipe=staged,seg_samples=512,seg_steps=20"]
    assert rows[2]["rule"]["s_min"] == 0.2 and rows[1]["rule"] == rows[0]["rule"] == BROAD.rule().to_dict()
    assert [r["timing_warm"]["steps"] for r in rows] == [20, 20, 10, 20]
    assert rows[1]["timing_warm"]["pixel_batches"] == 2
    assert set(rows[0]["targets"]) == {"propagation>=35", "miss>=30", "leak>=30",
                                       "recolour within 0.5 dB of unedited", "edit <= 0.25 s warm"}
    for r in rows:
        for k in ("propagation_psnr", "miss_psnr", "leak_psnr", "recolour_psnr", "edit_fit_changed_psnr",
                  "alpha_in_mask", "edit_view_alpha_in_mask"):
            assert math.isfinite(r[k]), (r["variant"], k)
        assert 0.0 <= r["alpha_in_mask"] <= 1.0 and 0.0 <= r["alpha_out_mask"] <= 1.0
    # the variants are different fits: their figures differ from the defaults'
    assert len({round(r["propagation_psnr"], 4) for r in rows}) == len(rows)
    assert (args.out / "tiny_view0.png").is_file() and (args.out / "tiny_edit.png").is_file()
    # the worst case row takes the engine defaults' rows only
    w = bench_edit.worst_case(rows + [{**rows[0], "variant": "x", "miss_psnr": -1.0}])
    assert w["miss_psnr"] == rows[0]["miss_psnr"] and w["rows"] == 1
    bench_edit.print_tables(rows, "cpu")
    # --merge: two calls' results as one table
    for name in ("a", "b"):
        (tmp_path / f"{name}.json").write_text(json.dumps({"device": "cpu", "commit": None, "scenes": rows},
                                                          default=float))
    m = bench_edit.merged([tmp_path / "a.json", tmp_path / "b.json"])
    assert len(m["scenes"]) == 2 * len(rows) and m["worst_case"]["rows"] == 2
    with pytest.raises(InputError, match="--merge"):
        bench_edit.merged([tmp_path / "missing.json"])


def test_benchmark_settings_are_split_and_typed_strictly():
    from virgi_ns.bench.settings import split_settings, typed_like

    assert split_settings("a=1, b.c = x,", "--f") == [("a", "1"), ("b.c", "x")]
    assert typed_like(3, "7", "a", "--f") == 7 and typed_like(0.5, "2e-2", "a", "--f") == 0.02
    assert typed_like(False, "Yes", "a", "--f") is True and typed_like(True, "0", "a", "--f") is False
    for bad in (lambda: split_settings("a", "--f"), lambda: split_settings("=3", "--f"),
                lambda: typed_like(False, "ture", "a", "--f"), lambda: typed_like(3, "3k", "a", "--f"),
                lambda: typed_like(None, "5", "a", "--f")):
        with pytest.raises(InputError, match="--f"):
            bad()
