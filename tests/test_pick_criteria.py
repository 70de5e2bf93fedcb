"""The ``chroma_steps`` candidate of bench/pick_criteria.py on hand-made view maps: a tone that fades
gradually joins, a tone of the same hue met at an abrupt step does not, and grey stays out."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from script_module import script_module  # noqa: E402

from virgi_ns.edit.pick import ViewMaps  # noqa: E402

DEEP, PALE, GREY = torch.tensor([0.1, 0.2, 0.8]), torch.tensor([0.55, 0.6, 0.75]), torch.tensor([0.6, 0.6, 0.6])


def _maps(row: torch.Tensor) -> ViewMaps:
    """A 3-pixel-high view of the colours ``row`` [W,3], every pixel covered."""
    diffuse = row[None].expand(3, -1, -1).clone()
    H, W = diffuse.shape[:2]
    return ViewMaps(diffuse, diffuse, torch.randn(H, W, 4, generator=torch.Generator().manual_seed(0)),
                    torch.ones(H, W))


def test_chroma_steps_follows_gradual_tones_and_stops_at_steps():
    with script_module("bench/pick_criteria.py", "pick_criteria_test") as pc:
        blend = [DEEP + (PALE - DEEP) * k / 11 for k in range(12)]  # deep blue fading to pale blue
        row = torch.stack(blend + [GREY, GREY] + [DEEP] * 3 + [PALE] * 3)
        sel = pc.sel_chroma_steps(_maps(row), 0, 1, 0.2)[1]
        assert bool(sel[:12].all())  # the whole gradual blend
        assert not bool(sel[12:].any())  # grey, and what lies beyond it
        row = torch.stack([DEEP] * 4 + [PALE] * 4)  # the same hue, met at an abrupt step
        sel = pc.sel_chroma_steps(_maps(row), 0, 1, 0.2)[1]
        assert bool(sel[:4].all()) and not bool(sel[4:].any())


def test_an_unticked_contiguous_box_takes_the_same_colour_anywhere_in_the_view():
    """``contiguous=False`` selects every pixel that passes the criterion's colour tests, wherever it is:
    both patches of the clicked blue, not the grey between them nor the red; the default only the
    clicked patch."""
    from virgi_ns.edit.pick import select

    RED = torch.tensor([0.8, 0.15, 0.1])
    row = torch.stack([DEEP] * 3 + [GREY] * 2 + [DEEP] * 3 + [RED] * 2)
    diffuse = row[None].expand(3, -1, -1).clone()
    maps = ViewMaps(diffuse, diffuse, diffuse.clone(), torch.ones(3, 10))  # features follow the colour
    for criterion in ("chroma_steps", "colour_features"):
        one = select(maps, 1, 1, 0.2, criterion)
        every = select(maps, 1, 1, 0.2, criterion, contiguous=False)
        assert bool(one[:, :3].all()) and not bool(one[:, 3:].any()), criterion
        assert bool(every[:, :3].all()) and bool(every[:, 5:8].all()), criterion
        assert not bool(every[:, 3:5].any()) and not bool(every[:, 8:].any()), criterion
