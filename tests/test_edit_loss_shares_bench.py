"""``bench/edit_loss_shares.py``: each object's share of an edit's loss on a synthetic scene's edit view."""

from __future__ import annotations

import json

import pytest

from script_module import script_module
from virgi_ns.errors import InputError


def test_loss_shares_split_each_half_of_the_loss_and_near_share_moves_the_kept_half(tmp_path):
    """On a small copy of the toy scene: over the objects, the changed pixels' weight never exceeds
    the changed share (the floor and backdrop take the rest) and the target holds most of it; the
    kept half goes to the pixels next to the change as near_share grows, so the red spots, unchanged
    inside the toy, carry more of it; the changed half does not move."""
    with script_module("bench/edit_loss_shares.py", "bench_edit_loss_shares") as mod:
        res = mod.main(mod.Args(scenes=["toy_on_white"], near_shares=[0.0, 0.5], out=tmp_path / "s.json",
                                size=(9, 80, 60, 0.05)))
        with pytest.raises(InputError, match="unknown synthetic scene"):
            mod.main(mod.Args(scenes=["nope"], out=tmp_path / "x.json", size=(9, 80, 60, 0.05)))
        with pytest.raises(InputError, match="near-shares"):
            mod.main(mod.Args(near_shares=[1.0], out=tmp_path / "x.json"))
    r = json.loads((tmp_path / "s.json").read_text())["scenes"]["toy_on_white"]
    assert r == json.loads(json.dumps(res["toy_on_white"]))
    assert r["edit_view"] % 8 != 0 and 0 < r["changed"] < r["pixels"]
    plain, near = r["near_shares"]["0.0"], r["near_shares"]["0.5"]
    turn = sum(v["turn"] for v in plain.values())
    assert 0.8 * 0.5 < turn <= 0.5 + 1e-6 and plain["toy"]["turn"] > 0.9 * turn
    for lab in plain:
        assert near[lab]["turn"] == pytest.approx(plain[lab]["turn"], rel=1e-6)
    assert near["toy_spots"]["keep"] > 3 * plain["toy_spots"]["keep"] > 0
    assert r["dominated_pixels"]["toy_spots"] > 0 and r["dominated_changed"]["toy_spots"] == 0
