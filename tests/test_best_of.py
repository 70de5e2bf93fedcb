"""bench/best_of.py: which fit it keeps, how it judges the targets, and its totals, on hand-made rows."""

from __future__ import annotations

import json

import pytest

from script_module import script_module
from virgi_ns.errors import InputError


@pytest.fixture(scope="module")
def best_of():
    with script_module("bench/best_of.py", "bench_best_of") as mod:
        yield mod


def _fit(prop, miss, l1, own, rec=-0.1, truth=None, fit_l1=None):
    out = {"propagation_psnr": prop, "miss_psnr": miss, "leak_psnr": 40.0, "recolour_psnr": 20.0 + rec,
           "unedited_psnr": 20.0, "final_l1": l1, "fit_l1": l1 if fit_l1 is None else fit_l1,
           "edit_fit_changed_psnr": own}
    if truth is not None:
        out["truth_psnr"] = truth
    return out


def _row(scene, seed, variant, fits, synthetic=False, edit_s=0.05):
    return {"scene": scene, "seed": seed, "variant": variant, "synthetic": synthetic,
            "timing_warm": {"total_s": edit_s}, "per_seed": fits}


ROWS = [
    # the first fit misses (miss 28); the lowest loss is fit 2, which passes and gains 2 dB
    _row("a", 1, "engine defaults", [_fit(40, 28, 0.03, 30), _fit(38, 31, 0.02, 29), _fit(42, 33, 0.01, 31)]),
    # the lowest last loss is fit 1, which loses 3 dB; the loss on every set ranks fit 2 best, the own PSNR
    # fit 0; the first fit misses the truth target, the others meet it
    _row("b", 1, "engine defaults", [_fit(50, 40, 0.02, 35, truth=34.0, fit_l1=0.02),
                                     _fit(47, 38, 0.01, 33, truth=36.0, fit_l1=0.03),
                                     _fit(49, 39, 0.03, 34, truth=36.0, fit_l1=0.01)], synthetic=True),
    # the first fit is also the lowest loss; three fits' time breaks the 0.25 s target
    _row("a", 2, "engine defaults", [_fit(41, 35, 0.01, 30), _fit(43, 36, 0.02, 31), _fit(40, 34, 0.03, 29)],
         edit_s=0.1),
    _row("a", 1, "steps=200", [_fit(43, 34, 0.01, 31), _fit(40, 30, 0.02, 30)]),
]


def test_keeps_the_fit_its_own_figure_ranks_best(best_of):
    fits = ROWS[1]["per_seed"]
    assert best_of.chosen_fits(fits, "final_l1")[2] == 1
    assert best_of.chosen_fits(fits, "fit_l1")[2] == 2
    assert best_of.chosen_fits(fits, "edit_fit_changed_psnr")[2] == 0  # the highest PSNR
    with pytest.raises(InputError, match="not recorded"):
        best_of.chosen_fits([{"final_l1": 0.1}], "fit_l1")
    # a diverged fit ranks last, whichever way its figure runs
    nan = [{"final_l1": float("nan"), "edit_fit_changed_psnr": float("nan")},
           {"final_l1": 0.2, "edit_fit_changed_psnr": 20.0}, {"final_l1": 0.3, "edit_fit_changed_psnr": 10.0}]
    assert best_of.chosen_fits(nan, "final_l1")[2] == 1
    assert best_of.chosen_fits(nan, "edit_fit_changed_psnr")[2] == 1


def test_rows_and_totals(best_of):
    rows = [best_of.row_summary(r) for r in ROWS]
    a1, b1, a2, v = rows
    assert (a1["best_index"], a1["difference_db"]) == (2, 2.0)
    assert not a1["first"]["targets"]["miss>=30"] and all(a1["best"]["targets"].values())
    assert b1["difference_db"] == -3.0 and "truth>=35" in b1["first"]["targets"]  # synthetic: judged on truth
    with pytest.raises(InputError, match="truth_psnr"):  # a synthetic row's fits must carry the truth
        best_of.row_summary(_row("c", 1, "engine defaults", [_fit(40, 35, 0.1, 30)] * 2, synthetic=True))
    assert a2["best_index"] == 0 and a2["difference_db"] == 0.0
    assert a2["first"]["targets"]["edit <= 0.25 s warm"] and not a2["best"]["targets"]["edit <= 0.25 s warm"]
    tot = best_of.totals(rows)
    d = tot["engine defaults"]
    # run set 1: the first fits pass on neither row (a: miss, b: truth), the best on both
    assert d["per_run_set"]["1"] == {"rows": 2, "first_passed": 0, "best_passed": 2}
    assert d["per_run_set"]["2"] == {"rows": 1, "first_passed": 1, "best_passed": 0}
    assert b1["best"]["targets"]["truth>=35"] and not b1["first"]["targets"]["truth>=35"]
    assert d["mean_difference_db"] == pytest.approx((2.0 - 3.0 + 0.0) / 3)
    assert (d["median_difference_db"], d["worst_difference_db"]) == (0.0, -3.0)
    # a variant's first fit against the defaults' first fit on the same scene and run
    assert v["first_vs_defaults_db"] == 3.0
    assert tot["steps=200"]["first_vs_defaults_mean_db"] == 3.0
    # another rule's variant, or the same run in another results file, is not compared with these defaults
    fresh = {k: x for k, x in v.items() if k != "first_vs_defaults_db"}
    other = [{**r, "source": 0} for r in rows[:3]] + [
        {**fresh, "source": 0}, {**fresh, "rule": {"shift": 90}, "source": 0}, {**fresh, "source": 1}]
    best_of.against_defaults(other)
    assert other[3]["first_vs_defaults_db"] == 3.0
    assert "first_vs_defaults_db" not in other[4] and "first_vs_defaults_db" not in other[5]
    with pytest.raises(InputError, match="two default rows"):
        best_of.against_defaults([{**a1, "source": 0}, {**a1, "source": 0}])


def test_main_writes_its_json_and_refuses_results_without_fits(best_of, tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"scenes": ROWS}))
    best_of.main(best_of.Args(results=[path], out=tmp_path / "out", by="edit_fit_changed_psnr"))
    data = json.loads((tmp_path / "out" / "best_of.json").read_text())
    assert data["by"] == "edit_fit_changed_psnr" and len(data["rows"]) == 4
    assert data["rows"][1]["best_index"] == 0
    with pytest.raises(InputError, match="--by"):
        best_of.main(best_of.Args(results=[path], out=tmp_path / "out", by="loss"))
    path.write_text(json.dumps({"scenes": [{**ROWS[0], "per_seed": ROWS[0]["per_seed"][:1]}]}))
    with pytest.raises(InputError, match="no per-seed fits"):
        best_of.main(best_of.Args(results=[path], out=tmp_path / "out"))


def test_fit_spread_correlations_say_plus_one_where_the_better_fit_by_its_own_figure_carries_better():
    with script_module("bench/fit_spread.py", "bench_fit_spread") as fs:
        assert fs.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
        assert fs.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
        assert fs.spearman([1, 3, 2, 4], [1, 2, 3, 4]) == pytest.approx(0.8)  # 1 - 6 * 2 / (4 * 15)
        fits = [{"miss_psnr": 30 - k, "propagation_psnr": 40 + k, "final_l1": 0.01 * (k + 1),
                 "fit_l1": 0.01 * (k + 1), "edit_fit_changed_psnr": 25 - k} for k in range(4)]
        c = fs.correlations(fits)
        # a lower loss and a higher own PSNR go with a higher miss: +1; propagation runs the other way here
        assert c["fit_l1"]["miss_psnr"] == pytest.approx(1.0)
        assert c["final_l1"]["propagation_psnr"] == pytest.approx(-1.0)
        assert c["edit_fit_changed_psnr"]["miss_psnr"] == pytest.approx(1.0)
