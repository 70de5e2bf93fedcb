"""bench/against_defaults.py: the rule's three conditions, on hand-made rows of two run sets."""

from __future__ import annotations

import json

import pytest

from script_module import script_module
from virgi_ns.errors import InputError


@pytest.fixture(scope="module")
def ad():
    with script_module("bench/against_defaults.py", "bench_against_defaults") as mod:
        yield mod


PASS = {"propagation_psnr": 40.0, "miss_psnr": 35.0, "leak_psnr": 40.0, "recolour_psnr": 19.9, "unedited_psnr": 20.0}
MISS = {**PASS, "miss_psnr": 28.0}  # one fit that misses the miss target


def _row(scene, seed, variant, passes, fits, prop=40.0):
    """A row as bench/edit.py writes it: its own figures (the medians), and its single fits."""
    return {**(PASS if passes else MISS), "scene": scene, "seed": seed, "variant": variant, "synthetic": False,
            "propagation_psnr": prop, "timing_warm": {"total_s": 0.05}, "per_seed": fits}


def _rows():
    rows = []
    for s in (1, 2):
        # defaults: a passes on both run sets (stable), b on run set 2 only, c on neither; single fits meeting every
        # target: a 1 of 3, b 1 of 3 on run set 2 and 0 on 1, c 0 (counted below)
        rows += [_row("a", s, "engine defaults", True, [PASS, MISS, MISS], prop=40.0),
                 _row("b", s, "engine defaults", s == 2, [PASS if s == 2 else MISS, MISS, MISS], prop=38.0),
                 _row("c", s, "engine defaults", False, [MISS, MISS, MISS], prop=36.0)]
        # good: a and b pass on both, c on run set 2; many more single fits pass
        rows += [_row("a", s, "good", True, [PASS, PASS, PASS], prop=41.0),
                 _row("b", s, "good", True, [PASS, PASS, MISS], prop=39.0),
                 _row("c", s, "good", s == 2, [PASS, MISS, MISS], prop=35.0)]
        # breaks: more fits, more rows over the two, but a (stable) fails on run set 2
        rows += [_row("a", s, "breaks", s == 1, [PASS, PASS, PASS], prop=40.0),
                 _row("b", s, "breaks", True, [PASS, PASS, PASS], prop=38.0),
                 _row("c", s, "breaks", True, [PASS, PASS, PASS], prop=36.0)]
        # noise: one single fit more than the defaults over the two run sets, the same rows
        rows += [_row("a", s, "noise", True, [PASS, PASS, MISS]), _row("b", s, "noise", s == 2, [MISS, MISS, MISS]),
                 _row("c", s, "noise", False, [MISS, MISS, MISS])]
        # fewer: many more single fits and no stable pass broken, but on run set 2 one row where the defaults pass two
        rows += [_row("a", s, "fewer", True, [PASS] * 3), _row("b", s, "fewer", s == 1, [PASS] * 3),
                 _row("c", s, "fewer", s == 1, [PASS] * 3)]
        # partial: a row short (no c on run set 2), otherwise the good variant's
        rows += [_row("a", s, "partial", True, [PASS] * 3), _row("b", s, "partial", True, [PASS] * 3)]
        if s == 1:
            rows.append(_row("c", s, "partial", True, [PASS] * 3))
    return rows


def test_the_three_conditions(ad, tmp_path):
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"scenes": _rows()}))
    v = ad.judge(ad.rows_by_run([path]))
    assert v["run_sets"] == [1, 2] and v["stable_scenes"] == ["a"]
    good, breaks, noise = v["variants"]["good"], v["variants"]["breaks"], v["variants"]["noise"]
    # defaults' single fits: a 1 + b 0 + c 0 on run set 1, a 1 + b 1 + c 0 on run set 2
    assert good["defaults_fits_passed"] == 3 and good["fits_passed"] == 2 * (3 + 2 + 1)
    assert good["per_run_set"]["1"]["passed"] == 2 and good["per_run_set"]["1"]["defaults_passed"] == 1
    assert good["candidate"] and good["mean_difference_db"] == pytest.approx((1 + 1 - 1) * 2 / 6)
    assert good["worst_difference_db"] == pytest.approx(-1.0)
    assert not breaks["candidate"] and breaks["broken"] == ["a (run set 2: miss>=30)"]
    assert [k for k, ok in breaks["conditions"].items() if not ok] == ["3: no stable pass broken"]
    assert noise["fits_passed"] == 4 and not noise["conditions"]["2: at least 3 more single fits"]
    assert noise["conditions"]["1: as many rows on each run set"] and not noise["candidate"]
    fewer = v["variants"]["fewer"]
    assert fewer["per_run_set"]["1"]["passed"] == 3 and fewer["per_run_set"]["2"]["passed"] == 1
    assert fewer["fits_passed"] == 18 and not fewer["broken"]
    assert [k for k, ok in fewer["conditions"].items() if not ok] == ["1: as many rows on each run set"]
    partial = v["variants"]["partial"]
    assert [k for k, ok in partial["conditions"].items() if not ok] == ["0: a row on every run set and scene"]


def test_refuses_rows_it_cannot_compare(ad, tmp_path):
    rows = _rows()
    twice = tmp_path / "twice.json"
    twice.write_text(json.dumps({"scenes": rows + rows[:1]}))
    with pytest.raises(InputError, match="twice"):
        ad.rows_by_run([twice])
    alone = tmp_path / "alone.json"
    alone.write_text(json.dumps({"scenes": [r for r in rows if not (r["scene"] == "c" and r["variant"] == "engine defaults")]}))
    with pytest.raises(InputError, match="no defaults row for c"):
        ad.judge(ad.rows_by_run([alone]))
    bare = tmp_path / "bare.json"  # a row without its single fits cannot be judged by the rule
    bare.write_text(json.dumps({"scenes": [{**rows[0], "per_seed": []}]}))
    with pytest.raises(InputError, match="no per-seed fits"):
        ad.rows_by_run([bare])
    short = tmp_path / "short.json"
    short.write_text(json.dumps({"scenes": [{**rows[0], "per_seed": [{"propagation_psnr": 40.0}]}]}))
    with pytest.raises(InputError, match="lacks leak_psnr, miss_psnr"):
        ad.rows_by_run([short])
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(InputError, match="not a bench/edit.py result"):
        ad.rows_by_run([bad])
