"""SuperSplat's chunked, quantized ``.compressed.ply`` layout: decoder and a matching encoder.

Gaussians are grouped in chunks of 256 consecutive rows. The ``chunk`` element holds, per chunk,
float min/max of position and of log-scale, and (in newer files) of the degree-0 colour
``0.5 + SH_C0 * f_dc``. The ``vertex`` element holds four packed uint32 per Gaussian:

- ``packed_position``, ``packed_scale``: x in bits 21..31 (11 bits), y in 11..20 (10), z in 0..10 (11),
  each an unsigned fraction of the chunk's [min, max];
- ``packed_rotation``: "smallest three": bits 30..31 index the largest-magnitude component of the
  unit quaternion (rot_0..rot_3 = w x y z, made non-negative), the other three follow in index
  order in 10-bit fields (the first one highest), each mapping [-1/sqrt2, 1/sqrt2] to [0, 1];
- ``packed_color``: r g b opacity, 8 bits each from the top; colour is a fraction of the chunk's
  colour range (or absolute in [0, 1] when the chunk has no colour range), opacity is sigmoid(logit).

An optional ``sh`` element holds ``f_rest_*`` as uchar (INRIA channel-major order), value
``(n - 0.5) * 8`` with ``n = (q + 0.5) / 256`` (0 and 255 map to the ends, -4 and 4).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.io.plyfmt import PlyData, ply_bytes

CHUNK = 256
POS_PROPS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
SCALE_PROPS = ["min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
COLOUR_PROPS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
SQRT2 = math.sqrt(2.0)
# Opacity bytes 0 and 255 are sigmoid 0 and 1; keep the logits finite by decoding them half a step inside.
ALPHA_EPS = 0.5 / 255.0


def is_compressed_ply(ply: PlyData) -> bool:
    chunk, vertex = ply.get("chunk"), ply.get("vertex")
    return chunk is not None and vertex is not None and "packed_position" in vertex.names


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def _unpack_111011(v: np.ndarray) -> np.ndarray:
    return np.stack([_unorm(v, 21, 11), _unorm(v, 11, 10), _unorm(v, 0, 11)], axis=1)


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    return lo * (1.0 - t) + hi * t


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, ALPHA_EPS, 1.0 - ALPHA_EPS)
    return np.log(p) - np.log1p(-p)


def unpack_smallest_three_wxyz(v: np.ndarray) -> np.ndarray:
    """Decode 2+10+10+10 packed quaternions into [N, 4] (same component order as encoded)."""
    n = v.shape[0]
    small = np.stack([_unorm(v, 20, 10), _unorm(v, 10, 10), _unorm(v, 0, 10)], axis=1)
    small = (small - 0.5) * SQRT2
    largest = (v >> np.uint32(30)).astype(np.int64)
    big = np.sqrt(np.clip(1.0 - (small**2).sum(1), 0.0, None))
    q = np.empty((n, 4))
    rows = np.arange(n)
    q[rows, largest] = big
    # the other three slots, in increasing index order
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]  # [N, 3]
    q[rows[:, None], others] = small
    return q


def gaussians_from_compressed(ply: PlyData, where: str = "file") -> Gaussians:
    chunk, vertex = ply.get("chunk"), ply.get("vertex")
    assert chunk is not None and vertex is not None
    missing = [p for p in POS_PROPS + SCALE_PROPS if p not in chunk.names]
    missing += [p for p in PACKED if p not in vertex.names]
    if missing:
        raise InputError(f"{where}: compressed PLY lacks properties {', '.join(missing)}")
    n = vertex.count
    if chunk.count != (n + CHUNK - 1) // CHUNK:
        raise InputError(
            f"{where}: compressed PLY has {chunk.count:,} chunks for {n:,} Gaussians; expected {(n + CHUNK - 1) // CHUNK:,}"
        )
    has_colour = all(p in chunk.names for p in COLOUR_PROPS)
    cd, vd = chunk.data, vertex.data
    ci = np.arange(n) // CHUNK
    cget = lambda names: np.stack([np.asarray(cd[p], np.float64) for p in names], 1)[ci]  # noqa: E731
    u32 = lambda name: np.asarray(vd[name]).astype(np.uint32)  # noqa: E731

    pos_mm, scale_mm = cget(POS_PROPS), cget(SCALE_PROPS)
    means = _lerp(pos_mm[:, :3], pos_mm[:, 3:], _unpack_111011(u32("packed_position")))
    scales = _lerp(scale_mm[:, :3], scale_mm[:, 3:], _unpack_111011(u32("packed_scale")))
    quats = unpack_smallest_three_wxyz(u32("packed_rotation"))
    pc = u32("packed_color")
    rgba = np.stack([_unorm(pc, 24, 8), _unorm(pc, 16, 8), _unorm(pc, 8, 8), _unorm(pc, 0, 8)], 1)
    rgb = rgba[:, :3]
    if has_colour:
        col_mm = cget(COLOUR_PROPS)
        rgb = _lerp(col_mm[:, :3], col_mm[:, 3:], rgb)
    f_dc = (rgb - 0.5) / SH_C0
    opac = logit(rgba[:, 3])

    k = 1
    rest = None
    sh_el = ply.get("sh")
    if sh_el is not None:
        names = sh_el.names
        r = len(names)
        if r not in (9, 24, 45, 72) or names != [f"f_rest_{i}" for i in range(r)]:
            raise InputError(f"{where}: compressed PLY 'sh' element must hold f_rest_0..f_rest_8/23/44/71, got {r} properties")
        if sh_el.count != n:
            raise InputError(f"{where}: compressed PLY 'sh' element has {sh_el.count:,} rows for {n:,} Gaussians")
        q = np.stack([np.asarray(sh_el.data[p]).astype(np.float64) for p in names], 1)  # [N, R]
        frac = np.where(q == 0, 0.0, np.where(q == 255, 1.0, (q + 0.5) / 256.0))
        k = r // 3 + 1
        rest = ((frac - 0.5) * 8.0).reshape(n, 3, k - 1).transpose(0, 2, 1)
    sh = np.zeros((n, k, 3))
    sh[:, 0] = f_dc
    if rest is not None:
        sh[:, 1:] = rest
    return Gaussians.from_numpy(means, scales, quats, opac, sh)


# ----------------------------------------------------------------------------------- encoder
def _pack_unorm(x: np.ndarray, bits: int) -> np.ndarray:
    t = (1 << bits) - 1
    return np.clip(np.floor(x * t + 0.5), 0, t).astype(np.uint32)


def _normalize(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    span = hi - lo
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(span < 1e-5, 0.0, (x - lo) / np.where(span == 0, 1, span))
    return np.clip(t, 0.0, 1.0)


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return (_pack_unorm(t[:, 0], 11) << np.uint32(21)) | (_pack_unorm(t[:, 1], 10) << np.uint32(11)) | _pack_unorm(t[:, 2], 11)


def pack_smallest_three(q: np.ndarray) -> np.ndarray:
    """[N, 4] quaternions -> 2+10+10+10 packed uint32 (component order kept)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True).clip(1e-30)
    largest = np.abs(q).argmax(1)
    rows = np.arange(q.shape[0])
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    small = q[rows[:, None], others]  # [N, 3] in index order
    out = largest.astype(np.uint32)
    for j in range(3):
        out = (out << np.uint32(10)) | _pack_unorm(small[:, j] / SQRT2 + 0.5, 10)
    return out


def compressed_ply_bytes(g: Gaussians, with_sh: bool = True) -> bytes:
    """Encode Gaussians in the SuperSplat compressed layout (18 chunk properties, optional ``sh`` element)."""
    n = len(g)
    a = lambda x: x.detach().cpu().to(torch.float64).numpy()  # noqa: E731
    means, scales, quats, opac, sh = a(g.means), a(g.scales), a(g.quats), a(g.opacities), a(g.sh)
    nc = (n + CHUNK - 1) // CHUNK
    colour = sh[:, 0] * SH_C0 + 0.5

    def minmax(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pad = nc * CHUNK - n
        lo = np.concatenate([x, np.repeat(x[-1:], pad, 0)]).reshape(nc, CHUNK, -1).min(1) if n else x[:0]
        hi = np.concatenate([x, np.repeat(x[-1:], pad, 0)]).reshape(nc, CHUNK, -1).max(1) if n else x[:0]
        return lo.astype(np.float32).astype(np.float64), hi.astype(np.float32).astype(np.float64)

    pmin, pmax = minmax(means)
    smin, smax = minmax(np.clip(scales, -20, 20))
    cmin, cmax = minmax(colour)
    ci = np.arange(n) // CHUNK
    chunk_cols = np.concatenate([pmin, pmax, smin, smax, cmin, cmax], 1).astype("<f4")
    chunk = chunk_cols.view(np.dtype([(p, "<f4") for p in POS_PROPS + SCALE_PROPS + COLOUR_PROPS])).reshape(nc)

    vertex = np.empty(n, dtype=np.dtype([(p, "<u4") for p in PACKED]))
    vertex["packed_position"] = _pack_111011(_normalize(means, pmin[ci], pmax[ci]))
    vertex["packed_rotation"] = pack_smallest_three(quats)
    vertex["packed_scale"] = _pack_111011(_normalize(scales, smin[ci], smax[ci]))
    ct = _normalize(colour, cmin[ci], cmax[ci])
    alpha = 1.0 / (1.0 + np.exp(-opac))
    vertex["packed_color"] = ((_pack_unorm(ct[:, 0], 8) << np.uint32(24)) | (_pack_unorm(ct[:, 1], 8) << np.uint32(16))
                              | (_pack_unorm(ct[:, 2], 8) << np.uint32(8)) | _pack_unorm(alpha, 8))
    elements = [("chunk", chunk), ("vertex", vertex)]
    k = sh.shape[1]
    if with_sh and k > 1:
        rest = sh[:, 1:].transpose(0, 2, 1).reshape(n, 3 * (k - 1))
        q = np.clip(np.floor((rest / 8.0 + 0.5) * 256.0), 0, 255).astype("u1")
        sh_arr = np.ascontiguousarray(q).view(np.dtype([(f"f_rest_{i}", "u1") for i in range(q.shape[1])])).reshape(n)
        elements.append(("sh", sh_arr))
    return ply_bytes(elements, comments=("Generated by virgi-ns",))
