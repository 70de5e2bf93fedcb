"""``bench/edit_targets.py``: each changed_target's distance to the exact target, from dumped arrays."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from script_module import script_module
from virgi_ns.edit.recolor import RecolorRule, recolor
from virgi_ns.errors import InputError


def test_target_psnr_ranks_the_kinds_on_a_render_that_differs_from_the_photo(tmp_path):
    """A render that is the photo plus noise; a 120-degree hue shift (affine in colour): the affine
    target reaches the rule on the render, the edited photo is as far as the noise, and the figures
    equal a PSNR computed here."""
    g = torch.Generator().manual_seed(0)
    photo = torch.rand(40, 50, 3, generator=g) * 0.8 + 0.1
    render = (photo + 0.03 * torch.randn(40, 50, 3, generator=g)).clamp(0, 1)
    rule = RecolorRule(h0=0, h1=360, shift=120, s_min=0.0, v_min=0.0)
    arrays = {"photo": photo, "render": render, "edited": recolor(photo, rule)[0], "exact": recolor(render, rule)[0]}
    np.savez(tmp_path / "noise_targets.npz", **{k: v.numpy().astype(np.float16) for k, v in arrays.items()})
    with script_module("bench/edit_targets.py", "bench_edit_targets") as mod:
        mod.main(mod.Args(dumps=tmp_path, out=tmp_path / "out.json"))
        with pytest.raises(InputError, match="targets.npz"):
            mod.main(mod.Args(dumps=tmp_path / "none", out=tmp_path / "x.json"))
    row = json.loads((tmp_path / "out.json").read_text())["scenes"]["noise"]
    half = {k: torch.from_numpy(v.numpy().astype(np.float16).astype(np.float32)) for k, v in arrays.items()}
    changed = (half["edited"] - half["photo"]).abs().amax(-1) > 3 / 255
    mse = float(((half["edited"] - half["exact"])[changed] ** 2).mean())
    assert row["edited"] == pytest.approx(-10 * math.log10(mse), abs=1e-3)
    assert row["affine"] > 45 and row["affine"] > row["change"] + 10 and row["affine"] > row["edited"] + 10, row
