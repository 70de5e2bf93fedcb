"""``bench/edit_step.py --cpu-smoke``: every composite kind checked against csr and timed on a tiny
scene (CPU), a kind that fails reported in its row while the others go on."""

from __future__ import annotations

import json

from script_module import script_module


def test_edit_step_bench_cpu_smoke(tmp_path):
    with script_module("bench/edit_step.py", "bench_edit_step") as mod:
        args = mod.Args(out=tmp_path / "es", cpu_smoke=True, variants=["segment", "no_such_kind", "embedding_bag",
                                                                        "index_add", "csr4", "fused",
                                                                        "fused,fused_heads=false", "fused,no_field=1"])
        res = mod.main(args)
    saved = json.loads((tmp_path / "es" / "results.json").read_text())
    assert saved["device"] == "cpu" and saved["image"] == "40x24"
    rows = {r["variant"]: r for r in saved["rows"]}
    assert list(rows)[:5] == ["csr", "segment", "no_such_kind", "embedding_bag", "index_add"]
    assert "batch_composite" in rows["no_such_kind"]["error"]
    for kind in ("csr", "segment", "embedding_bag", "index_add", "csr4"):
        r = rows[kind]
        assert "error" not in r, r.get("traceback")
        assert r["passed"] and r["fwd_rel_diff"] <= 1e-5 and r["bwd_rel_diff"] <= 1e-5, kind
        assert r["fwd_s"] > 0 and r["bwd_s"] > 0 and r["steps_s"] > 0 and r["steps"] == 6
        assert r["preview_max_diff_vs_csr"] < 1e-3 and r["batch_entries"] > 0
    fused = rows["fused"]  # one kernel (here its torch reference) for the loss and its gradient
    assert "error" not in fused, fused.get("traceback")
    assert fused["passed"] and fused["fwd_rel_diff"] <= 1e-5 and fused["bwd_rel_diff"] <= 1e-5
    assert fused["fwd_bwd_s"] > 0 and fused["steps"] == 6 and fused["preview_max_diff_vs_csr"] < 1e-3
    assert rows["csr"]["preview_max_diff_vs_csr"] == 0.0
    # a kind with other EditConfig settings; an unknown setting is that row's error
    assert rows["fused,fused_heads=false"]["passed"] and rows["fused,fused_heads=false"]["steps"] == 6
    assert "no_field" in rows["fused,no_field=1"]["error"]
    best = saved["fastest"]
    assert best["edit"] in rows and best["edit"] != "no_such_kind" and best["fwd"] in rows and best["bwd"] in rows
    assert res["fastest"] == best


def test_edit_step_bench_times_an_edit_of_part_of_the_render(tmp_path):
    """``--changed-region``: the edited image is the render with a box recoloured, so the timed edit fits
    the changed pixels (their share of the view about the box's), not the whole image."""
    with script_module("bench/edit_step.py", "bench_edit_step") as mod:
        res = mod.main(mod.Args(out=tmp_path / "es", cpu_smoke=True, variants=["fused"], changed_region=0.1))
    rows = {r["variant"]: r for r in res["rows"]}
    for kind in ("csr", "fused"):
        assert "error" not in rows[kind], rows[kind].get("traceback")
        assert 0.05 < rows[kind]["changed_fraction"] < 0.12 and rows[kind]["steps_s"] > 0
        assert rows[kind]["passed"], rows[kind]  # the kernels' check holds off the fit's start
    assert res["changed_region"] == 0.1
