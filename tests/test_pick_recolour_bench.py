"""``bench/pick_recolour.py``: a pick's recolour of the rule's pixels against the rule's, before any fit."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from script_module import script_module
from virgi_ns.errors import InputError


def test_shift_is_the_rule_s_recolour_and_hue_is_not_on_an_object_of_several_hues(tmp_path):
    """A real capture made of two photos whose blue can has two hues (the rule takes both): the shift
    mode gives the rule's pixels the rule's recolour up to rounding; one hue for all of them is
    measurably off. A missing capture is skipped; two equal images score None in the JSON (no infinity)."""
    h, w = 24, 32
    photo = np.full((h, w, 3), 230, np.uint8)  # a pale backdrop the rule leaves alone
    photo[4:20, 6:16] = (40, 90, 200)  # blue, about 222 degrees
    photo[4:20, 16:26] = (40, 160, 210)  # cyan-blue, about 198 degrees
    folder = tmp_path / "data" / "beercan" / "images"
    folder.mkdir(parents=True)
    for i in range(2):
        Image.fromarray(photo).save(folder / f"frame_{i}.png")
    with script_module("bench/pick_recolour.py", "bench_pick_recolour") as mod:
        rows = mod.main(mod.Args(scenes=["beercan", "fern"], data=tmp_path / "data", out=tmp_path / "r.json"))
        with pytest.raises(InputError, match="recolour mode"):
            mod.main(mod.Args(scenes=["beercan"], modes=["tint"], data=tmp_path / "data", out=tmp_path / "x.json"))
    assert list(rows) == ["beercan"]  # fern: no capture there
    r = json.loads((tmp_path / "r.json").read_text())["scenes"]["beercan"]
    assert r["view"] == 1 and r["mask_fraction"] == pytest.approx(320 / (h * w))
    shift, hue = r["modes"]["shift"], r["modes"]["hue"]
    assert shift["mask_psnr"] > 90 and rows["beercan"]["modes"]["shift"]["mask_psnr"] == shift["mask_psnr"]
    assert 15 < hue["mask_psnr"] < 60
    # the view's figure is the rule's pixels' figure spread over the view
    share = r["mask_fraction"]
    assert hue["view_psnr"] == pytest.approx(hue["mask_psnr"] - 10 * math.log10(share), abs=1e-6)


def test_equal_images_are_written_as_none():
    with script_module("bench/pick_recolour.py", "bench_pick_recolour") as mod:
        assert mod.finite_or_none({"a": [1.0, float("inf")], "b": {"c": float("inf")}}) == {"a": [1.0, None],
                                                                                            "b": {"c": None}}


def test_on_a_synthetic_scene_both_are_compared_with_the_truth(tmp_path):
    with script_module("bench/pick_recolour.py", "bench_pick_recolour") as mod:
        rows = mod.main(mod.Args(scenes=["syn_toy_on_white"], out=tmp_path / "s.json", size=(9, 80, 60, 0.05)))
    r = rows["syn_toy_on_white"]
    assert r["view"] % 8 != 0 and r["mask_fraction"] > 0
    for v in (r["rule_truth_view_psnr"], r["modes"]["hue"]["truth_view_psnr"], r["modes"]["shift"]["truth_view_psnr"]):
        assert math.isfinite(v) and v > 10
    # the rule's colour at the click is rounded to 8 bits, so shift is the rule's recolour up to that rounding
    shift, hue = r["modes"]["shift"], r["modes"]["hue"]
    assert shift["view_psnr"] > 55 and shift["view_psnr"] > hue["view_psnr"] + 5
    assert abs(shift["truth_view_psnr"] - r["rule_truth_view_psnr"]) < 0.1
