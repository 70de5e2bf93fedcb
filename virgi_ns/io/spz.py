"""Niantic ``.spz``: reader for versions 1-4 and writer for versions 2-4.

Versions 1-3 are one gzip stream holding a 16-byte header (magic ``NGSP``, version, count,
SH degree, fractional bits, flags, reserved), optional extension records when ``flags & 2``,
then the attributes one after the other: positions, alphas, colours, scales, rotations, SH.
Version 4 is not gzipped: a 32-byte header (the same first 15 bytes, then the number of
streams and the table-of-contents offset), extension records up to the table of contents,
a table of (compressed, uncompressed) uint64 sizes, and one ZSTD stream per attribute.

Encodings: positions are 24-bit signed fixed point with ``fractional_bits`` (version 1: float16);
alphas ``round(255 * sigmoid(logit))``; colours ``f_dc * 0.15 * 255 + 127.5``; scales
``(log_scale + 10) * 16``; rotations (x y z w order) are "smallest three" in 2+3x10 bits (9-bit
magnitude and a sign bit, components of magnitude at most 1/sqrt2) from version 3, x y z as
``127.5 * (q + 1)`` with w >= 0 in version 2; SH coefficients ``128 + 128 * c`` per byte,
coefficient-major with the colour channel innermost.
SPZ stores right-up-back axes, INRIA PLY right-down-forward: y and z flip for positions,
rotations and the odd SH basis functions.
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib

import numpy as np
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import Gaussians

MAGIC = 0x5053474E  # b"NGSP" little-endian
COLOUR_SCALE = 0.15
SQRT1_2 = 1.0 / math.sqrt(2.0)
MAX_POINTS = 50_000_000
ALPHA_EPS = 0.5 / 255.0
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2

# Sign of each real SH basis function (bands 1..4, standard order m = -l..l) under (x, y, z) -> (x, -y, -z):
# a monomial x^a y^b z^c flips when b + c is odd.
_SH_FLIP = np.array([
    -1, -1, 1,                            # l=1: y, z, x
    -1, 1, 1, -1, 1,                      # l=2: xy, yz, 3z^2-1, xz, x^2-y^2
    -1, 1, -1, -1, 1, -1, 1,              # l=3: y(3x^2-y^2), xyz, y(5z^2-1), z(5z^2-3), x(5z^2-1), z(x^2-y^2), x(x^2-3y^2)
    -1, 1, -1, 1, 1, -1, 1, -1, 1,        # l=4: xy(x^2-y^2), yz(3x^2-y^2), xy(7z^2-1), yz(7z^2-3), (35z^4..), xz(7z^2-3), (x^2-y^2)(7z^2-1), xz(x^2-3y^2), x^4-6x^2y^2+y^4
], dtype=np.float64)


def _dim_for_degree(deg: int) -> int:
    return (deg + 1) ** 2 - 1


def _zstd():
    try:
        import zstandard
    except ImportError:  # pragma: no cover - a declared dependency
        raise InputError("reading or writing SPZ version 4 needs the 'zstandard' package (pip install zstandard)") from None
    return zstandard


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, ALPHA_EPS, 1.0 - ALPHA_EPS)
    return np.log(p) - np.log1p(-p)


def _attr_sizes(n: int, version: int, sh_dim: int) -> list[int]:
    return [n * 3 * (2 if version == 1 else 3), n, n * 3, n * 3, n * (4 if version >= 3 else 3), n * sh_dim * 3]


# ------------------------------------------------------------------------------------ reading
def _decode(n: int, version: int, sh_deg: int, frac: int, parts: list[bytes]) -> Gaussians:
    pos_b, alpha_b, colour_b, scale_b, rot_b, sh_b = (np.frombuffer(p, dtype=np.uint8) for p in parts)
    if version == 1:
        means = np.frombuffer(parts[0], dtype="<f2").astype(np.float64).reshape(n, 3)
    else:
        b = pos_b.reshape(n * 3, 3).astype(np.int32)
        fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
        fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
        means = (fixed.astype(np.float64) / float(1 << frac)).reshape(n, 3)
    opac = _logit(alpha_b.astype(np.float64) / 255.0)
    f_dc = (colour_b.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOUR_SCALE
    scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version >= 3:
        r = rot_b.reshape(n, 4).astype(np.uint32)
        comp = r[:, 0] | (r[:, 1] << 8) | (r[:, 2] << 16) | (r[:, 3] << 24)
        largest = (comp >> 30).astype(np.int64)
        xyzw = np.zeros((n, 4))
        rows = np.arange(n)
        for i in range(3, -1, -1):  # fields are packed so that index 3's lands in the lowest bits
            mag = (comp & 511).astype(np.float64) * (SQRT1_2 / 511.0)
            val = np.where((comp >> 9) & 1, -mag, mag)
            here = largest != i
            xyzw[here, i] = val[here]
            comp = np.where(here, comp >> 10, comp)
        xyzw[rows, largest] = np.sqrt(np.clip(1.0 - (xyzw**2).sum(1), 0.0, None))
    else:
        xyz = rot_b.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz**2).sum(1), 0.0, None))
        xyzw = np.concatenate([xyz, w[:, None]], 1)
    sh_dim = _dim_for_degree(sh_deg)
    sh = np.zeros((n, sh_dim + 1, 3))
    sh[:, 0] = f_dc
    if sh_dim:
        sh[:, 1:] = (sh_b.reshape(n, sh_dim, 3).astype(np.float64) - 128.0) / 128.0 * _SH_FLIP[:sh_dim, None]
    # right-up-back -> right-down-forward
    means[:, 1:] *= -1.0
    quats = np.stack([xyzw[:, 3], xyzw[:, 0], -xyzw[:, 1], -xyzw[:, 2]], 1)
    return Gaussians.from_numpy(means, scales, quats, opac, sh)


def _check_header(version: int, n: int, sh_deg: int, frac: int, where: str) -> None:
    if version < 1 or version > 4:
        raise InputError(f"{where}: SPZ version {version} is not supported (1 to 4 are)")
    if sh_deg > 4:
        raise InputError(f"{where}: SPZ header claims SH degree {sh_deg}; at most 4 exists (corrupt file?)")
    if n > MAX_POINTS:
        raise InputError(f"{where}: SPZ header claims {n:,} Gaussians (corrupt file?)")
    if version >= 2 and frac > 23:
        raise InputError(f"{where}: SPZ header claims {frac} fractional bits for 24-bit positions (corrupt file?)")


def _read_legacy(raw: bytes, where: str) -> Gaussians:
    if len(raw) < 16:
        raise InputError(f"{where}: SPZ data ends inside its 16-byte header (truncated)")
    magic, version, n, sh_deg, frac, flags, _ = struct.unpack_from("<IIIBBBB", raw, 0)
    if magic != MAGIC:
        raise InputError(f"{where}: gzip stream does not hold SPZ data (bad magic)")
    if version == 4:
        raise InputError(f"{where}: SPZ version 4 data must not be gzipped (corrupt file?)")
    _check_header(version, n, sh_deg, frac, where)
    sizes = _attr_sizes(n, version, _dim_for_degree(sh_deg))
    need = 16 + sum(sizes)
    if len(raw) < need:
        raise InputError(f"{where}: SPZ data holds {len(raw):,} bytes, {need:,} needed for {n:,} Gaussians (truncated)")
    # extension records (flags & 2) sit between header and attributes; they are skipped as a block.
    off = 16 + (len(raw) - need if flags & FLAG_EXTENSIONS else 0)
    parts = []
    for s in sizes:
        parts.append(raw[off:off + s])
        off += s
    return _decode(n, version, sh_deg, frac, parts)


def _read_v4(buf: bytes, where: str) -> Gaussians:
    if len(buf) < 32:
        raise InputError(f"{where}: SPZ file ends inside its 32-byte header (truncated)")
    magic, version, n, sh_deg, frac, flags, n_streams, toc = struct.unpack_from("<IIIBBBBI", buf, 0)
    _check_header(version, n, sh_deg, frac, where)
    sizes = _attr_sizes(n, version, _dim_for_degree(sh_deg))
    if sizes[-1] == 0:
        sizes = sizes[:-1]
    if n_streams < len(sizes):
        raise InputError(f"{where}: SPZ v4 file has {n_streams} streams, {len(sizes)} needed (corrupt file?)")
    if toc < 32 or toc + 16 * n_streams > len(buf):
        raise InputError(f"{where}: SPZ v4 table of contents lies outside the file (truncated or corrupt)")
    entries = [struct.unpack_from("<QQ", buf, toc + 16 * i) for i in range(n_streams)]
    off = toc + 16 * n_streams
    zstd = _zstd()
    parts: list[bytes] = []
    for i, (csize, usize) in enumerate(entries):
        if off + csize > len(buf):
            raise InputError(f"{where}: SPZ v4 stream {i} runs past the end of the file (truncated)")
        if i < len(sizes):
            if usize != sizes[i]:
                raise InputError(f"{where}: SPZ v4 stream {i} holds {usize:,} bytes, {sizes[i]:,} expected for {n:,} Gaussians")
            try:
                data = zstd.ZstdDecompressor().decompress(buf[off:off + csize], max_output_size=max(usize, 1))
            except zstd.ZstdError as e:
                raise InputError(f"{where}: SPZ v4 stream {i} does not decompress ({e})") from None
            if len(data) != usize:
                raise InputError(f"{where}: SPZ v4 stream {i} decompressed to {len(data):,} bytes, {usize:,} expected")
            parts.append(data)
        off += csize
    if off != len(buf):
        raise InputError(f"{where}: SPZ v4 file has {len(buf) - off:,} bytes after its last stream (corrupt file?)")
    if len(parts) == 5:
        parts.append(b"")
    return _decode(n, version, sh_deg, frac, parts)


def read_spz_bytes(buf: bytes, where: str = "file") -> Gaussians:
    if len(buf) >= 4 and struct.unpack_from("<I", buf, 0)[0] == MAGIC:
        version = struct.unpack_from("<I", buf, 4)[0] if len(buf) >= 8 else 0
        if version == 4:
            return _read_v4(buf, where)
        return _read_legacy(buf, where)  # uncompressed legacy payload
    if buf[:2] != b"\x1f\x8b":
        raise InputError(f"{where}: not an SPZ file (neither gzip nor NGSP magic)")
    try:
        raw = gzip.decompress(buf)
    except (OSError, EOFError, zlib.error) as e:
        raise InputError(f"{where}: corrupt SPZ gzip stream ({e})") from None
    return _read_legacy(raw, where)


# ------------------------------------------------------------------------------------ writing
def spz_bytes(g: Gaussians, version: int = 3, fractional_bits: int | None = None) -> bytes:
    """Encode Gaussians as SPZ ``version`` 2, 3 (gzip) or 4 (ZSTD streams).

    ``fractional_bits`` defaults to 12 (1/4096 units) or fewer when positions would overflow
    24 bits. SH coefficients are stored with full 8-bit precision.
    """
    if version not in (2, 3, 4):
        raise ValueError("SPZ writing supports versions 2, 3 and 4")
    n = len(g)
    a = lambda x: x.detach().cpu().to(torch.float64).numpy().reshape(n, x.shape[1:].numel())  # noqa: E731
    means, scales, quats, opac, sh = a(g.means), a(g.scales), a(g.quats), a(g.opacities)[:, 0], a(g.sh)
    sh = sh.reshape(n, g.sh.shape[1], 3)
    deg = g.sh_degree
    if fractional_bits is None:
        extent = float(np.abs(means).max()) if n else 0.0
        fractional_bits = 12
        while fractional_bits > 0 and extent * (1 << fractional_bits) >= (1 << 23) - 1:
            fractional_bits -= 1
    # right-down-forward -> right-up-back
    means = means * np.array([1.0, -1.0, -1.0])
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True).clip(1e-30)
    xyzw = np.stack([q[:, 1], -q[:, 2], -q[:, 3], q[:, 0]], 1)

    u8 = lambda x: np.clip(np.round(x), 0, 255).astype(np.uint8)  # noqa: E731
    fixed = np.clip(np.round(means * (1 << fractional_bits)), -(1 << 23), (1 << 23) - 1).astype(np.int64).reshape(-1)
    fixed &= 0xFFFFFF
    pos = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    alpha = u8(255.0 / (1.0 + np.exp(-opac)))
    colour = u8(sh[:, 0] * (COLOUR_SCALE * 255.0) + 127.5)
    scale = u8((scales + 10.0) * 16.0)
    rows = np.arange(n)
    if version >= 3:
        largest = np.abs(xyzw).argmax(1)
        negate = xyzw[rows, largest] < 0
        comp = largest.astype(np.uint32)
        for i in range(4):
            here = largest != i
            mag = np.clip(np.floor(511.0 * np.abs(xyzw[:, i]) / SQRT1_2 + 0.5), 0, 511).astype(np.uint32)
            neg = ((xyzw[:, i] < 0) ^ negate).astype(np.uint32)
            comp = np.where(here, (comp << np.uint32(10)) | (neg << np.uint32(9)) | mag, comp)
        rot = np.stack([(comp >> np.uint32(s)) & np.uint32(0xFF) for s in (0, 8, 16, 24)], 1).astype(np.uint8)
    else:
        sgn = np.where(xyzw[:, 3] < 0, -1.0, 1.0)[:, None]
        rot = u8(xyzw[:, :3] * sgn * 127.5 + 127.5)
    sh_dim = _dim_for_degree(deg)
    shq = u8(sh[:, 1:] * _SH_FLIP[:sh_dim, None] * 128.0 + 128.0) if sh_dim else np.zeros((n, 0, 3), np.uint8)
    parts = [p.tobytes() for p in (pos, alpha, colour, scale, rot, shq)]
    if version == 4:
        if not sh_dim:
            parts = parts[:5]
        zstd = _zstd()
        comp_parts = [zstd.ZstdCompressor(level=12).compress(p) for p in parts]
        head = struct.pack("<IIIBBBBI", MAGIC, 4, n, deg, fractional_bits, 0, len(parts), 32) + bytes(12)
        toc = b"".join(struct.pack("<QQ", len(c), len(p)) for c, p in zip(comp_parts, parts))
        return head + toc + b"".join(comp_parts)
    head = struct.pack("<IIIBBBB", MAGIC, version, n, deg, fractional_bits, 0, 0)
    return gzip.compress(head + b"".join(parts), compresslevel=6, mtime=0)
