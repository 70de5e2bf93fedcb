"""SuperSplat .compressed.ply: bit layout on hand-packed values, and encode -> decode within the
quantization error that each field's bit width allows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.io import decode_splat, load_splat, save_compressed_ply
from virgi_ns.io.compressed_ply import CHUNK, COLOUR_PROPS, PACKED, POS_PROPS, SCALE_PROPS
from virgi_ns.io.plyfmt import ply_bytes


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3) * 3, r(n, 3) - 4, r(n, 4), r(n) * 2, r(n, (degree + 1) ** 2, 3))


def _struct(names, dtype, rows):
    arr = np.zeros(len(rows), dtype=[(n, dtype) for n in names])
    for i, row in enumerate(rows):
        arr[i] = tuple(row)
    return arr


def test_hand_packed_gaussian_decodes_to_known_values():
    # chunk ranges chosen so that the 11/10/11-bit position fields read back as integers
    chunk = _struct(POS_PROPS + SCALE_PROPS + COLOUR_PROPS, "<f4",
                    [[0, 0, 0, 2047, 1023, 2047, -1, -2, -3, 1, 2, 3, 0, 0, 0, 1, 1, 1]])
    w, x, z = 0.3, -0.2, 0.1  # y is the largest component (index 2 of w x y z)
    f = lambda v: round((v / math.sqrt(2) + 0.5) * 1023)  # noqa: E731
    rot = (2 << 30) | (f(w) << 20) | (f(x) << 10) | f(z)
    pos = (5 << 21) | (7 << 11) | 9
    scale = (2047 << 21) | (0 << 11) | 1023  # x at max, y at min, z at 1023/2047 of its range
    color = (255 << 24) | (0 << 16) | (51 << 8) | 128  # r g b a
    vertex = _struct(PACKED, "<u4", [[pos, rot, scale, color]])
    g = decode_splat(ply_bytes([("chunk", chunk), ("vertex", vertex)]))
    assert g.means[0].tolist() == [5.0, 7.0, 9.0]
    np.testing.assert_allclose(g.scales[0].numpy(), [1.0, -2.0, -3 + 6 * 1023 / 2047], atol=1e-6)
    np.testing.assert_allclose(g.quats[0].numpy(), [w, x, math.sqrt(1 - w * w - x * x - z * z), z], atol=1.5e-3)
    np.testing.assert_allclose((g.sh[0, 0] * SH_C0 + 0.5).numpy(), [1.0, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(torch.sigmoid(g.opacities[0]).item(), 128 / 255, atol=1e-6)


def test_chunk_without_colour_range_reads_colour_as_absolute():
    chunk = _struct(POS_PROPS + SCALE_PROPS, "<f4", [[0, 0, 0, 1, 1, 1, 0, 0, 0, 1, 1, 1]])
    vertex = _struct(PACKED, "<u4", [[0, 3 << 30, 0, (102 << 24) | (204 << 16) | (255 << 8) | 255]])
    g = decode_splat(ply_bytes([("chunk", chunk), ("vertex", vertex)]))
    np.testing.assert_allclose((g.sh[0, 0] * SH_C0 + 0.5).numpy(), [0.4, 0.8, 1.0], atol=1e-6)
    assert torch.isfinite(g.opacities).all()  # opacity byte 255 stays a finite logit


@pytest.mark.parametrize("degree,with_sh", [(0, False), (1, True), (2, True), (3, True), (3, False)])
def test_encode_decode_within_quantization_error(tmp_path, degree, with_sh):
    n = 3 * CHUNK + 17  # a partial last chunk
    g = random_gaussians(n, degree, seed=degree)
    g.sh[:, 1:] = g.sh[:, 1:].clamp(-3.9, 3.9)
    save_compressed_ply(g, tmp_path / "a.compressed.ply", with_sh=with_sh)
    h = load_splat(tmp_path / "a.compressed.ply")
    assert len(h) == n and h.sh_degree == (degree if with_sh else 0)

    ci = torch.arange(n) // CHUNK
    def half_step(x: torch.Tensor, bits: list[int]) -> torch.Tensor:
        # per chunk, per axis: half of (max - min) / (2^bits - 1), plus float32 rounding
        lo = torch.stack([x[ci == c].min(0).values for c in range(int(ci.max()) + 1)])[ci]
        hi = torch.stack([x[ci == c].max(0).values for c in range(int(ci.max()) + 1)])[ci]
        return (hi - lo) / (2 ** torch.tensor(bits, dtype=torch.float32) - 1) / 2 + 1e-6 * (1 + x.abs())

    assert ((h.means - g.means).abs() <= half_step(g.means, [11, 10, 11])).all()
    assert ((h.scales - g.scales).abs() <= half_step(g.scales, [11, 10, 11])).all()
    col = g.sh[:, 0] * SH_C0 + 0.5
    assert ((h.sh[:, 0] - g.sh[:, 0]).abs() * SH_C0 <= half_step(col, [8, 8, 8])).all()
    assert ((torch.sigmoid(h.opacities) - torch.sigmoid(g.opacities)).abs() <= 0.5 / 255 + 1e-6).all()
    # rotation: each stored component is a 10-bit fraction of [-1/sqrt2, 1/sqrt2] -> half step sqrt2/2046;
    # the largest (>= 1/2) is rebuilt from the other three: error <= 3 * (1/sqrt2) * (sqrt2/2046) / (1/2)
    q = g.normalized_quats()
    q = q * torch.where(q.gather(1, q.abs().argmax(1, keepdim=True)) < 0, -1.0, 1.0)
    dq = (h.quats - q).abs()
    largest = q.abs().argmax(1)
    small_err = dq.scatter(1, largest[:, None], 0.0)
    assert (small_err <= math.sqrt(2) / 2046 + 1e-6).all()
    assert (dq.gather(1, largest[:, None]) <= 6 / 2046 + 1e-6).all()
    if with_sh and degree:
        # 8-bit codes over [-4, 4]: bucket 1/32, decoded at the bucket centre (ends at -4 and 4)
        assert ((h.sh[:, 1:] - g.sh[:, 1:]).abs() <= 1 / 64 + 1e-6).all()


def test_chunk_count_mismatch_is_refused():
    chunk = _struct(POS_PROPS + SCALE_PROPS, "<f4", [[0] * 12, [0] * 12])
    vertex = _struct(PACKED, "<u4", [[0, 0, 0, 0]] * 3)
    with pytest.raises(InputError, match="2 chunks for 3 Gaussians"):
        decode_splat(ply_bytes([("chunk", chunk), ("vertex", vertex)]))


def test_sh_element_with_wrong_property_count_is_refused():
    chunk = _struct(POS_PROPS + SCALE_PROPS, "<f4", [[0] * 12])
    vertex = _struct(PACKED, "<u4", [[0, 0, 0, 0]])
    sh = _struct([f"f_rest_{i}" for i in range(10)], "u1", [[0] * 10])
    with pytest.raises(InputError, match="'sh' element"):
        decode_splat(ply_bytes([("chunk", chunk), ("vertex", vertex), ("sh", sh)]))
