"""Real splats (skip without ../shared/data): biker as .compressed.ply and as .spz (v4) are two
independent encodings of one scene, in the same order; guitar as .compressed.ply."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from virgi_ns.io import load_splat
from virgi_ns.io.compressed_ply import CHUNK
from virgi_ns.io.plyfmt import read_ply_bytes


def _check_sane(g, n):
    assert len(g) == n
    assert not g.invalid_rows().any()
    torch.testing.assert_close(g.quats.norm(dim=1), torch.ones(n), atol=1e-5, rtol=0)


@pytest.fixture(scope="module")
def biker(shared_data):
    d = shared_data.need("splats", "splats/biker.spz", "splats/biker.compressed.ply")
    cply = load_splat(d / "biker.compressed.ply")
    spz = load_splat(d / "biker.spz")
    chunk = read_ply_bytes((d / "biker.compressed.ply").read_bytes()).get("chunk").data
    return cply, spz, chunk


def test_biker_both_encodings_load_sane(biker):
    cply, spz, _ = biker
    _check_sane(cply, 152_746)
    _check_sane(spz, 152_746)


def test_biker_positions_agree_within_quantization(biker):
    cply, spz, chunk = biker
    ci = np.arange(len(cply)) // CHUNK
    lo = np.stack([chunk[f"min_{a}"] for a in "xyz"], 1)[ci]
    hi = np.stack([chunk[f"max_{a}"] for a in "xyz"], 1)[ci]
    # per axis: the compressed file's half step ((max - min) / (2^bits - 1) / 2 for 11-10-11 bits, per chunk)
    # plus SPZ's half step (12 fractional bits: 2^-13), plus float32 rounding
    bound = (hi - lo) / np.array([2047, 1023, 2047]) / 2 + 2.0**-13 + 1e-6
    diff = (cply.means - spz.means).abs().numpy()
    assert (diff <= bound).all(), f"worst ratio {(diff / bound).max():.3f}"
    dist = np.linalg.norm(diff, axis=1)
    # measured: max 2.11e-4, median 1.20e-4 (scene extent about 3.8 units); SPZ's 2^-13 dominates
    assert dist.max() <= np.sqrt(3) * (2.0**-13 + (hi - lo).max() / 1023 / 2)
    assert np.median(dist) < 2.0**-13 * np.sqrt(3)


def test_biker_other_attributes_agree_within_quantization(biker):
    cply, spz, chunk = biker
    # same rotations up to sign (10-bit vs 9-bit smallest three)
    dot = (cply.normalized_quats() * spz.normalized_quats()).sum(1).abs()
    assert dot.min() > 1 - 1e-4
    # opacities: both 8-bit sigmoid, each within half a step
    assert (torch.sigmoid(cply.opacities) - torch.sigmoid(spz.opacities)).abs().max() <= 1 / 255 + 1e-6
    # log scales where SPZ can represent them ([-10, 5.94] in steps of 1/16) and the chunk range is 11/10/11 bits
    ci = np.arange(len(cply)) // CHUNK
    span = np.stack([chunk[f"max_scale_{a}"] - chunk[f"min_scale_{a}"] for a in "xyz"], 1)[ci]
    bound = torch.from_numpy(span / np.array([2047, 1023, 2047]) / 2 + 1 / 32 + 1e-5).float()
    inside = (cply.scales > -10 + 1 / 32) & (cply.scales < 5.9)
    assert inside.float().mean() > 0.999
    assert ((cply.scales - spz.scales).abs() <= bound)[inside].all()


def test_guitar_loads(shared_data):
    g = load_splat(shared_data.need("splats/guitar.compressed.ply"))
    _check_sane(g, 90_854)
    assert g.sh_degree == 0
