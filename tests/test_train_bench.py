"""``bench/train.py --merge``: seeds trained in separate calls summarised as one (no GPU, no training)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from script_module import script_module
from virgi_ns.errors import InputError


@pytest.fixture(scope="module")
def bench():
    with script_module("bench/train.py", "bench_train") as mod:
        yield mod


def _row(method, seed, psnr, secs):
    return {"scene": "beercan", "method": method, "seed": seed, "psnr": psnr, "ssim": 0.9, "train_s": secs}


def _write(path: Path, rows, device="GPU X", steps=7000):
    path.write_text(json.dumps({"device": device, "steps": steps, "colour_steps": 1000, "rows": rows}))
    return path


def test_merge_pairs_seeds_across_files(bench, tmp_path):
    a = _write(tmp_path / "a.json", [_row("splatfacto", 42, 23.5, 50.0), _row("virgi", 42, 23.3, 70.0),
                                     _row("splatfacto", 43, 23.9, 52.0), _row("virgi", 43, 24.1, 65.0)])
    b = _write(tmp_path / "b.json", [_row("splatfacto", 44, 23.0, 48.0), _row("virgi", 44, 23.2, 72.0)])
    out = tmp_path / "out"
    bench.main(bench.Args(merge=[a, b], out=out))
    res = json.loads((out / "results.json").read_text())
    assert len(res["rows"]) == 6 and res["device"] == "GPU X"
    virgi = next(s for s in res["summary"] if s["method"] == "virgi")
    diffs = [23.3 - 23.5, 24.1 - 23.9, 23.2 - 23.0]  # paired by seed, computed here by hand
    assert virgi["runs"] == 3
    assert virgi["psnr_vs_splatfacto"] == pytest.approx(sum(diffs) / 3)
    assert virgi["psnr_vs_splatfacto_min"] == pytest.approx(-0.2)
    assert virgi["psnr_vs_splatfacto_max"] == pytest.approx(0.2)
    ratios = [70 / 50, 65 / 52, 72 / 48]
    assert virgi["train_time_vs_splatfacto"] == pytest.approx(sum(ratios) / 3)


def test_merge_refuses_mixed_or_repeated_runs(bench, tmp_path):
    a = _write(tmp_path / "a.json", [_row("splatfacto", 42, 23.5, 50.0)])
    other = _write(tmp_path / "b.json", [_row("splatfacto", 43, 23.5, 50.0)], steps=30000)
    with pytest.raises(InputError, match="steps=30000"):
        bench.merged_results([a, other])
    with pytest.raises(InputError, match="in both .* --first-seed"):
        bench.merged_results([a, a])
    no_seed = tmp_path / "no_seed.json"
    no_seed.write_text(json.dumps({"device": "GPU X", "steps": 7000, "colour_steps": 1000,
                                   "rows": [{"scene": "beercan", "method": "virgi", "psnr": 23.0}]}))
    with pytest.raises(InputError, match="not a bench/train.py results.json"):
        bench.merged_results([no_seed])
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not a bench/train.py results.json"):
        bench.merged_results([bad])
