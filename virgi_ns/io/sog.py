"""PlayCanvas SOG ("spatially ordered Gaussians"), format version 2: reader and writer.

Written here: version 2, the current one (``meta.json`` with ``"version": 2``), as a zip archive
(``scene.sog``: the files at the archive's root, WebP entries stored, ``meta.json`` deflated).
Read: the zip archive or the folder form (a directory holding ``meta.json``, or ``meta.json`` itself);
version 1 files (no ``version`` key, per-channel ranges instead of codebooks) are refused.

``meta.json`` holds ``version`` (2), ``count``, ``antialias`` (false: gsplat's classic rasterization),
``asset.generator``, and per attribute its ``files`` (in order) and ``codebook`` or ranges, as below.
What the format stores (every image 8-bit, lossless WebP, alpha 255 where unused; Gaussian ``i`` is
pixel ``(i % W, i // W)`` of every per-Gaussian image, all of them ``W x H`` with ``W*H >= count``; this
writer makes ``W = 4 ceil(sqrt(N) / 4)``, ``H = 4 ceil(N / W / 4)`` as PlayCanvas's does):

- ``means_l.webp`` / ``means_u.webp`` (RGB = x y z): the low and high bytes of a 16-bit quantisation of
  ``n = sign(p) * log(1 + |p|)`` between ``meta.means.mins`` and ``maxs`` (per axis, in that log domain).
- ``quats.webp``: unit quaternion, smallest three: A = 252 + the index (w x y z order) of the largest
  component, which is made non-negative and left out; R G B = the other three in index order,
  ``byte = 255 * (v / sqrt2 + 0.5)``.
- ``scales.webp`` (RGB): indices into ``meta.scales.codebook`` (256 log standard deviations).
- ``sh0.webp``: RGB indices into ``meta.sh0.codebook`` (256 values of ``f_dc``, the band-0 coefficient),
  A = ``255 * sigmoid(opacity)``.
- ``shN_centroids.webp`` / ``shN_labels.webp`` (only with SH bands, ``meta.shN``: ``bands`` 1..3,
  palette ``count`` up to 65536): a palette of the higher bands, 64 entries per image row, entry ``e``'s
  coefficient ``c`` (1 .. 3/8/15 after band 0) at pixel ``((e % 64) * coeffs + c - 1, e // 64)``, its RGB
  the three colour channels as indices into ``meta.shN.codebook``; labels: palette index ``R + 256 G``.

Axes: PlayCanvas's writer stores the source PLY's coordinates unchanged (it bakes its "PLY" transform
before writing, and its reader tags what it reads as PLY-space), so a ``.sog`` holds the INRIA
``.ply`` axes used internally here: nothing is flipped. The specification's "y up" describes the
viewer's render space, which PlayCanvas reaches by turning PLY data 180 degrees about z.

How this writer quantises (the quantities in the file are the format's; how they are chosen is ours):

- order: Gaussians are written in Morton order of their means (21 bits per axis over the bounding
  box, stable), :func:`sog_order`; what a reader returns is the source in that order.
- positions, opacity, rotations: rounded to nearest. Bounds per value: log-domain position within
  ``h = (max - min) / 65535 / 2`` per axis, so ``|dp| <= (|p| + 2) (e^h - 1)``; ``sigmoid(opacity)``
  within ``0.5 / 255``; each of the three stored quaternion components within ``sqrt2 / 510``.
- codebooks (scales, sh0, shN): a 1-D k-means of 256 centres over all the values (Lloyd iterations on
  the sorted values, exact, float64, started at the cube-root-density quantiles; centres stored as
  float32, the ends pinned at the data's min and max), each value stored as its nearest centre: the
  error is at most half the widest codebook gap.
- higher SH bands: with at most ``palette`` (65536) Gaussians each is its own palette entry (only the
  256-entry codebook loses anything); above that, a k-means of the ``3 * coeffs`` coefficients into
  65536 entries, built as a tree: a node needing ``k`` centres splits its rows into ``ceil(k / 256)``
  groups (at most 256) and gives each group centres in proportion to its squared error, down to
  nodes of at most 256 centres. Each k-means is seeded k-means++ style (in 8 rounds, with a fixed
  seed) and runs at most ``iterations`` (5) Lloyd steps on a sample of 8 rows a centre; then every
  row takes its nearest centre and each centre moves to the mean of its rows. One torch thread.
  Cost: about two passes of ``N x 256 x 3 coeffs`` distances plus the leaves' fits (measured in
  bench/RESULTS.md, "Export").
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.gaussians import Gaussians
from virgi_ns.io.compressed_ply import logit

__all__ = ["read_sog", "read_sog_bytes", "write_sog", "sog_bytes", "sog_files", "sog_order", "is_sog_zip"]

VERSION = 2
MAX_PALETTE = 65536
CODEBOOK = 256
COEFFS = {1: 3, 2: 8, 3: 15}  # SH coefficients per colour channel after band 0, by bands
ENTRIES_PER_ROW = 64
MEANS_FILES = ["means_l.webp", "means_u.webp"]
SHN_FILES = ["shN_centroids.webp", "shN_labels.webp"]
SQRT2 = math.sqrt(2.0)
MORTON_BITS = 21
MAX_META_BYTES = 64 << 20
MAX_ENTRY_BYTES = 2 << 30
ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed, so a write is reproducible


# ------------------------------------------------------------------------------------ helpers
def _image_size(n: int) -> tuple[int, int]:
    """Width and height (multiples of 4, as PlayCanvas's writer makes them) holding ``n`` pixels."""
    if n == 0:
        return 4, 4
    w = int(math.ceil(math.sqrt(n) / 4)) * 4
    h = int(math.ceil(n / w / 4)) * 4
    return w, h


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between the low 21 bits of each value (uint64)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def sog_order(means: np.ndarray | torch.Tensor) -> np.ndarray:
    """The order :func:`write_sog` writes Gaussians in: Morton (z-order) codes of the means quantised
    to 21 bits per axis over their bounding box, sorted stably. ``read_sog(path)`` gives
    ``g.index(sog_order(g.means))`` within the quantisation."""
    m = means.detach().cpu().double().numpy() if isinstance(means, torch.Tensor) else np.asarray(means, np.float64)
    if len(m) == 0:
        return np.zeros(0, np.int64)
    lo, span = m.min(0), m.max(0) - m.min(0)
    top = (1 << MORTON_BITS) - 1
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(span > 0, (m - lo) / np.where(span > 0, span, 1.0), 0.0)
    q = np.clip(np.floor(t * top), 0, top).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


def _log_transform(p: np.ndarray) -> np.ndarray:
    return np.sign(p) * np.log1p(np.abs(p))


def _unlog(n: np.ndarray) -> np.ndarray:
    return np.sign(n) * np.expm1(np.abs(n))


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.floor(x + 0.5), 0, 255).astype(np.uint8)


# -------------------------------------------------------------------------- 1-D codebook (256)
def codebook_1d(values: np.ndarray, k: int = CODEBOOK, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """A ``k``-entry codebook for ``values`` and each value's index into it.

    Lloyd's k-means in one dimension on the sorted values (a cell is a run of them, its mean a
    difference of prefix sums), started where the asymptotically optimal quantiser puts its centres
    (point density proportional to the cube root of the values' density, from a histogram), which
    leaves the sparse tails far fewer and smaller gaps than quantiles do; the first and last centres
    stay on the data's min and max throughout, so no value lies outside the codebook. Centres are float32
    (as readers hold them), sorted; each value gets the nearest one. Returns ``(codebook [k] float32,
    labels uint8)``.
    """
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        return np.zeros(k, np.float32), np.zeros(0, np.uint8)
    s = np.sort(v)
    uniq = np.unique(s.astype(np.float32))
    if len(uniq) <= k:
        centres = uniq.astype(np.float64)
    else:
        n = len(s)
        hist, edges = np.histogram(s, bins=8192)
        cdf = np.concatenate([[0.0], np.cumsum(np.cbrt(hist.astype(np.float64)))])
        centres = np.unique(np.interp((np.arange(k) + 0.5) / k, cdf / cdf[-1], edges))
        centres[0], centres[-1] = s[0], s[-1]
        prefix = np.concatenate([[0.0], np.cumsum(s)])
        for _ in range(iterations):
            cut = np.searchsorted(s, (centres[1:] + centres[:-1]) / 2, side="right")
            start = np.concatenate([[0], cut])
            end = np.concatenate([cut, [n]])
            count = end - start
            new = np.sort(np.where(count > 0, (prefix[end] - prefix[start]) / np.maximum(count, 1), centres))
            new[0], new[-1] = s[0], s[-1]  # the ends stay on the data's extremes
            if np.array_equal(new, centres):
                break
            centres = new
    book = np.full(k, centres[-1], np.float32)
    book[: len(centres)] = np.sort(centres.astype(np.float32))
    # nearest entry: cut the line halfway between consecutive distinct centres
    b64 = book.astype(np.float64)
    idx = np.clip(np.searchsorted(b64, v), 1, k - 1)
    left, right = b64[idx - 1], b64[idx]
    labels = np.where(np.abs(v - left) <= np.abs(right - v), idx - 1, idx)
    # equal entries (padding, float32 ties): point at the first of a run
    first = np.searchsorted(b64, b64[labels], side="left")
    return book, first.astype(np.uint8)


# ---------------------------------------------------------------- SH palette (tree k-means)
def _assign(x: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest centre of each row of ``x`` and the squared distance to it."""
    n, k = x.shape[0], c.shape[0]
    cn = (c * c).sum(1)
    labels = torch.empty(n, dtype=torch.int64)
    dist = torch.empty(n, dtype=x.dtype)
    step = max(1, (1 << 22) // max(k, 1))
    for s in range(0, n, step):
        xs = x[s : s + step]
        d = torch.addmm(cn[None], xs, c.T, alpha=-2.0)
        m, i = d.min(1)
        labels[s : s + step] = i
        dist[s : s + step] = (m + (xs * xs).sum(1)).clamp_min(0.0)
    return labels, dist


def _member_means(x: torch.Tensor, labels: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Each centre moved to the mean of the rows labelled with it (kept where none is)."""
    k = c.shape[0]
    xn, ln = x.numpy(), labels.numpy()
    # numpy's bincount, one column at a time: single-threaded, and steady where torch's index_add_
    # stalls on a busy machine
    sums = np.stack([np.bincount(ln, xn[:, j], k) for j in range(xn.shape[1])], 1)
    count = np.bincount(ln, minlength=k)[:, None]
    return torch.from_numpy(np.where(count > 0, sums / np.maximum(count, 1), c.numpy()).astype(np.float32))


def _seed_centres(x: torch.Tensor, k: int, rng: np.random.Generator, rounds: int = 8) -> torch.Tensor:
    """k-means++ seeding in a few rounds: after one random row, each round draws its share of the
    centres, without replacement, with probability proportional to the squared distance from the
    centres so far (well-separated groups each get one), in ``rounds`` passes instead of ``k``."""
    n = x.shape[0]
    chosen = [int(rng.integers(n))]
    _, d2 = _assign(x, x[chosen])
    per = -(-(k - 1) // rounds)
    while len(chosen) < k:
        m = min(per, k - len(chosen))
        w = d2.double().numpy()
        live = int(np.count_nonzero(w))
        new = rng.choice(n, size=m, replace=m > live, p=w / w.sum() if live else None)
        chosen.extend(int(i) for i in new)
        _, d2_new = _assign(x, x[torch.from_numpy(new)])
        d2 = torch.minimum(d2, d2_new)
    return x[torch.tensor(chosen[:k])].clone()


def _lloyd(x: torch.Tensor, k: int, iterations: int, rng: np.random.Generator) -> torch.Tensor:
    """k-means centres of ``x`` (k < len(x)): k-means++ seeds, then Lloyd steps; an emptied centre
    restarts at a random row."""
    n = x.shape[0]
    c = _seed_centres(x, k, rng)
    for _ in range(iterations):
        labels, _ = _assign(x, c)
        count = torch.bincount(labels, minlength=k)
        new = _member_means(x, labels, c)
        empty = count == 0
        if bool(empty.any()):
            new[empty] = x[torch.from_numpy(rng.integers(n, size=int(empty.sum())))]
        if torch.equal(new, c):
            break
        c = new
    return c


def _allocate(total: int, weight: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Split ``total`` centres over groups: one each (non-empty groups), the rest in proportion to
    ``weight`` (largest remainders), never more than ``cap`` (the group's size)."""
    alloc = (cap > 0).astype(np.int64)
    left = min(total, int(cap.sum())) - int(alloc.sum())
    while left > 0:
        room = cap - alloc
        w = np.where(room > 0, weight, 0.0)
        if w.sum() <= 0:
            w = room.astype(np.float64)
        share = w / w.sum() * left
        add = np.minimum(np.floor(share).astype(np.int64), room)
        if add.sum() == 0:
            order = np.argsort(-(share - np.floor(share)), kind="stable")
            order = order[room[order] > 0][:left]
            add = np.zeros_like(alloc)
            add[order] = 1
        alloc += add
        left -= int(add.sum())
    return alloc


LEAF = 256  # the most centres one flat k-means fits
BRANCH = 256  # the most groups a node splits into


def _palette(x: torch.Tensor, k: int, rng: np.random.Generator, iterations: int,
             per_centre: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """At most ``k`` centres for the rows of ``x`` and each row's label: the rows themselves when they
    fit; a flat k-means for ``k <= LEAF``; otherwise ``ceil(k / 256)`` groups (at most 256), each
    given centres in proportion to its squared error, and so on down. Every k-means is fitted on a
    sample of ``per_centre`` rows a centre, then all rows are assigned once and each centre moves to
    the mean of its rows."""
    n = x.shape[0]
    if k >= n:
        return x.clone(), torch.arange(n)

    def fit(kk: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        sample = x if n <= kk * per_centre else x[torch.from_numpy(rng.choice(n, kk * per_centre, replace=False))]
        c = _lloyd(sample, kk, iterations, rng)
        labels, sq = _assign(x, c)
        return c, labels, sq

    if k <= LEAF:
        c, labels, _ = fit(k)
        return _member_means(x, labels, c), labels
    groups = min(BRANCH, -(-k // LEAF))
    _, group, sq = fit(groups)
    count = torch.bincount(group, minlength=groups).numpy()
    sse = torch.bincount(group, weights=sq.double(), minlength=groups).numpy()
    alloc = _allocate(k, sse, count)
    order = torch.argsort(group, stable=True)
    bounds = np.concatenate([[0], np.cumsum(count)])
    labels = torch.empty(n, dtype=torch.int64)
    centres = []
    offset = 0
    for gi in np.flatnonzero(count):
        rows = order[bounds[gi] : bounds[gi + 1]]
        cg, lg = _palette(x[rows], int(alloc[gi]), rng, iterations, per_centre)
        labels[rows] = lg + offset
        centres.append(cg)
        offset += cg.shape[0]
    return torch.cat(centres), labels


def sh_palette(rest: np.ndarray, palette: int = MAX_PALETTE, seed: int = 0,
               iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Palette ``[K, D]`` (``K <= palette``) and labels ``[N]`` for the higher-band vectors ``rest [N, D]``.

    Runs on one torch thread: its matrix products are a few thousand rows each, which gain little
    from more threads, and on a busy machine torch's thread pool stalls on them (bench/RESULTS.md,
    "Export")."""
    n = rest.shape[0]
    if n <= palette:
        return rest.astype(np.float64), np.arange(n)
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(np.ascontiguousarray(rest, dtype=np.float32))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        c, labels = _palette(x, palette, rng, iterations)
    finally:
        torch.set_num_threads(threads)
    return c.double().numpy(), labels.numpy()


# ------------------------------------------------------------------------------------ writing
def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    # exact: keep RGB under alpha 0 (an opacity byte of 0 must not lose its colour)
    Image.fromarray(np.ascontiguousarray(rgba)).save(buf, format="WEBP", lossless=True, exact=True, quality=50,
                                                     method=0)
    return buf.getvalue()


def sog_files(g: Gaussians, palette: int = MAX_PALETTE, seed: int = 0, iterations: int = 5) -> dict[str, bytes]:
    """Encode ``g`` as the files of a version-2 SOG: ``{"meta.json": ..., "means_l.webp": ..., ...}``.

    SH degree 4 keeps its first three bands (SOG holds at most three). ``palette`` caps the SH
    palette (at most 65536); ``seed`` and ``iterations`` fix the SH k-means.
    """
    if not 1 <= palette <= MAX_PALETTE:
        raise ValueError(f"palette must be 1..{MAX_PALETTE}, got {palette}")
    n = len(g)
    bad = int(g.invalid_rows().sum()) if n else 0
    if bad:
        raise InputError(f"{bad:,} of {n:,} Gaussians hold NaN or Inf values, which SOG cannot store; "
                         "use --drop-invalid when reading them")
    a = lambda t: t.detach().cpu().to(torch.float64).numpy()  # noqa: E731
    order = sog_order(g.means)
    means, scales, quats = a(g.means)[order], a(g.scales)[order], a(g.quats)[order]
    opac, sh = a(g.opacities)[order], a(g.sh)[order]
    bands = min(g.sh_degree, 3)
    w, h = _image_size(n)
    if w > 16383 or h > 16383:
        raise InputError(f"{n:,} Gaussians need {w}x{h} images; WebP stops at 16383 pixels a side")

    def image(channels: list[np.ndarray], alpha: np.ndarray | None = None, width: int = w, height: int = h,
              count: int = n) -> bytes:
        img = np.zeros((width * height, 4), np.uint8)
        img[:, 3] = 255
        for i, ch in enumerate(channels):
            img[:count, i] = ch
        if alpha is not None:
            img[:count, 3] = alpha
        return _webp(img.reshape(height, width, 4))

    files: dict[str, bytes] = {}
    # positions: 16 bits of the log-transformed value per axis
    nlog = _log_transform(means)
    mins = nlog.min(0) if n else np.zeros(3)
    maxs = nlog.max(0) if n else np.zeros(3)
    span = maxs - mins
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(span > 0, (nlog - mins) / np.where(span > 0, span, 1.0), 0.0)
    q16 = np.clip(np.floor(t * 65535.0 + 0.5), 0, 65535).astype(np.int64)
    files["means_l.webp"] = image([(q16[:, i] & 0xFF).astype(np.uint8) for i in range(3)])
    files["means_u.webp"] = image([(q16[:, i] >> 8).astype(np.uint8) for i in range(3)])

    # rotations: smallest three, w x y z component order, the largest made non-negative and left out
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    q = np.where(norm > 0, quats / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    largest = np.abs(q).argmax(1)
    rows = np.arange(n)
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    kept = q[rows[:, None], others]
    files["quats.webp"] = image([_u8(255.0 * (kept[:, j] / SQRT2 + 0.5)) for j in range(3)],
                                alpha=(252 + largest).astype(np.uint8))

    # scales: log standard deviations through a 256-entry codebook
    scale_book, scale_idx = codebook_1d(scales)
    scale_idx = scale_idx.reshape(n, 3)
    files["scales.webp"] = image([scale_idx[:, j] for j in range(3)])

    # band 0 through its codebook, opacity as an 8-bit sigmoid
    dc_book, dc_idx = codebook_1d(sh[:, 0])
    dc_idx = dc_idx.reshape(n, 3)
    alpha = _u8(255.0 / (1.0 + np.exp(-np.clip(opac, -100.0, 100.0))))
    files["sh0.webp"] = image([dc_idx[:, j] for j in range(3)], alpha=alpha)

    meta = {
        "version": VERSION,
        "asset": {"generator": "virgi-ns"},
        "count": n,
        "antialias": False,  # gsplat's classic rasterization (no anti-aliasing compensation)
        "means": {"mins": [float(x) for x in mins], "maxs": [float(x) for x in maxs], "files": list(MEANS_FILES)},
        "scales": {"codebook": [float(x) for x in scale_book], "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": [float(x) for x in dc_book], "files": ["sh0.webp"]},
    }
    if bands > 0 and n > 0:
        coeffs = COEFFS[bands]
        rest = sh[:, 1 : 1 + coeffs, :]  # [N, coeffs, 3]
        centres, labels = sh_palette(rest.reshape(n, coeffs * 3), palette, seed, iterations)
        k = centres.shape[0]
        book, idx = codebook_1d(centres)
        idx = idx.reshape(k, coeffs, 3)
        rows_c = int(math.ceil(k / ENTRIES_PER_ROW))
        cent = np.zeros((rows_c * ENTRIES_PER_ROW, coeffs, 4), np.uint8)
        cent[..., 3] = 255
        cent[:k, :, :3] = idx
        # entry e, coefficient c at pixel ((e % 64) * coeffs + c, e // 64): rows of 64 entries
        files["shN_centroids.webp"] = _webp(cent.reshape(rows_c, ENTRIES_PER_ROW * coeffs, 4))
        labels = labels.astype(np.int64)
        files["shN_labels.webp"] = image([(labels & 0xFF).astype(np.uint8), (labels >> 8).astype(np.uint8)])
        meta["shN"] = {"count": int(k), "bands": bands, "codebook": [float(x) for x in book], "files": list(SHN_FILES)}
    files = {"meta.json": json.dumps(meta, allow_nan=False).encode(), **files}
    return files


def sog_bytes(g: Gaussians, palette: int = MAX_PALETTE, seed: int = 0, iterations: int = 5) -> bytes:
    """The zip archive of :func:`sog_files` (``meta.json`` deflated, images stored, no zip64, no comment:
    what PlayCanvas's bundle reader parses)."""
    files = sog_files(g, palette, seed, iterations)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", allowZip64=False) as z:
        for name, data in files.items():
            info = zipfile.ZipInfo(name, date_time=ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED if name.endswith(".json") else zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            z.writestr(info, data)
    return buf.getvalue()


def write_sog(g: Gaussians, path: str | os.PathLike, palette: int = MAX_PALETTE, seed: int = 0,
              iterations: int = 5) -> None:
    """Write ``g`` as a bundled (zip) version-2 ``.sog`` at ``path``, atomically."""
    data = sog_bytes(g, palette, seed, iterations)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# ------------------------------------------------------------------------------------ reading
def is_sog_zip(src: bytes | str | os.PathLike) -> bool:
    """Whether ``src`` (a file's bytes or its path) is a zip archive holding ``meta.json`` at its root
    (torch checkpoints are zips too); only the archive's directory is read."""
    try:
        with zipfile.ZipFile(io.BytesIO(src) if isinstance(src, (bytes, bytearray)) else src) as z:
            return "meta.json" in z.namelist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return False


def _decode_image(data: bytes, name: str, where: str) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.mode not in ("RGB", "RGBA"):
                raise InputError(f"{where}: {name} is a {im.mode} image; SOG images are 8-bit RGB or RGBA")
            im.load()
            rgba = np.asarray(im.convert("RGBA"))
    except InputError:
        raise
    except Image.DecompressionBombError as e:
        raise InputError(f"{where}: {name} is too large to decode ({e})") from None
    except (OSError, ValueError, SyntaxError, EOFError, zlib.error) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{where}: {name} is not a readable image ({why})") from None
    return rgba


def _numbers(val, length: int | None, what: str, where: str) -> np.ndarray:
    if not isinstance(val, list) or (length is not None and len(val) != length) or not val:
        want = f"{length} numbers" if length else "a list of numbers"
        raise InputError(f"{where}: meta.json {what} must be {want}")
    out = []
    for x in val:
        if x is None:  # JSON has no NaN or infinity; some writers leave null there (fixed below)
            out.append(math.nan)
        elif isinstance(x, (int, float)) and not isinstance(x, bool):
            out.append(float(x))
        else:
            raise InputError(f"{where}: meta.json {what} holds {x!r}, not a number")
    return np.asarray(out, np.float64)


def _codebook(section: dict, what: str, where: str) -> np.ndarray:
    book = _numbers(section.get("codebook"), None, f"{what}.codebook", where)
    if len(book) > CODEBOOK:
        raise InputError(f"{where}: meta.json {what}.codebook has {len(book)} entries; at most {CODEBOOK}")
    if np.isinf(book).any():
        raise InputError(f"{where}: meta.json {what}.codebook holds an infinite value")
    finite = np.flatnonzero(~np.isnan(book))
    if len(finite) == 0:
        raise InputError(f"{where}: meta.json {what}.codebook holds no number")
    # null entries take the nearest earlier value (leading ones the first value), as PlayCanvas patches them
    fill = np.maximum.accumulate(np.where(np.isnan(book), -1, np.arange(len(book))))
    return np.where(fill >= 0, book[np.maximum(fill, 0)], book[finite[0]])


def _files(section, count: int, what: str, where: str) -> list[str]:
    names = section.get("files") if isinstance(section, dict) else None
    if not isinstance(names, list) or len(names) < count or not all(isinstance(s, str) and s for s in names[:count]):
        raise InputError(f"{where}: meta.json {what}.files must name {count} file(s)")
    return names[:count]


def _lookup(codebook: np.ndarray, idx: np.ndarray, what: str, where: str) -> np.ndarray:
    if idx.size and int(idx.max()) >= len(codebook):
        raise InputError(f"{where}: {what} index {int(idx.max())} lies beyond its {len(codebook)}-entry codebook")
    return codebook[idx]


def decode_sog(read: Callable[[str], bytes], where: str) -> Gaussians:
    """Decode a version-2 SOG whose files ``read(name)`` returns (raising InputError when absent)."""
    try:
        meta = json.loads(read("meta.json").decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{where}: meta.json is not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{where}: meta.json does not hold an object")
    version = meta.get("version")
    if version is None:
        raise InputError(f"{where}: SOG version 1 (meta.json without 'version') is not supported; "
                         "re-save it with PlayCanvas splat-transform")
    if version != VERSION or isinstance(version, bool):
        raise InputError(f"{where}: SOG version {version!r} is not supported (version {VERSION} is)")
    count = meta.get("count")
    if not isinstance(count, int) or isinstance(count, bool) or count < 0:
        raise InputError(f"{where}: meta.json count must be a non-negative integer, got {count!r}")
    for key in ("means", "scales", "quats", "sh0"):
        if not isinstance(meta.get(key), dict):
            raise InputError(f"{where}: meta.json lacks its '{key}' section")
    mins = _numbers(meta["means"].get("mins"), 3, "means.mins", where)
    maxs = _numbers(meta["means"].get("maxs"), 3, "means.maxs", where)
    if not (np.isfinite(mins).all() and np.isfinite(maxs).all()) or (np.abs(np.concatenate([mins, maxs])) > 700).any():
        raise InputError(f"{where}: meta.json means.mins/maxs must be finite log-domain values")
    scale_book = _codebook(meta["scales"], "scales", where)
    dc_book = _codebook(meta["sh0"], "sh0", where)
    names = {
        "means": _files(meta["means"], 2, "means", where),
        "quats": _files(meta["quats"], 1, "quats", where),
        "scales": _files(meta["scales"], 1, "scales", where),
        "sh0": _files(meta["sh0"], 1, "sh0", where),
    }
    shn = meta.get("shN")
    bands = 0
    if shn is not None:
        if not isinstance(shn, dict):
            raise InputError(f"{where}: meta.json shN must be an object")
        bands, palette = shn.get("bands"), shn.get("count")
        if bands not in COEFFS or isinstance(bands, bool):
            raise InputError(f"{where}: meta.json shN.bands must be 1, 2 or 3, got {bands!r}")
        if not isinstance(palette, int) or isinstance(palette, bool) or not 1 <= palette <= MAX_PALETTE:
            raise InputError(f"{where}: meta.json shN.count must be 1..{MAX_PALETTE}, got {palette!r}")
        shn_book = _codebook(shn, "shN", where)
        names["shN"] = _files(shn, 2, "shN", where)

    images: dict[str, np.ndarray] = {}
    size = None
    per_gaussian = [("means", 0), ("means", 1), ("quats", 0), ("scales", 0), ("sh0", 0)]
    per_gaussian += [("shN", 1)] if bands else []
    for key, i in per_gaussian:
        name = names[key][i]
        img = _decode_image(read(name), name, where)
        if size is None:
            size = img.shape[:2]
            if size[0] * size[1] < count:
                raise InputError(f"{where}: {name} is {size[1]}x{size[0]} = {size[0] * size[1]:,} pixels for "
                                 f"{count:,} Gaussians")
        elif img.shape[:2] != size:
            raise InputError(f"{where}: {name} is {img.shape[1]}x{img.shape[0]}, the other images "
                             f"{size[1]}x{size[0]}; every per-Gaussian image must have the same size")
        images[f"{key}{i}"] = img.reshape(-1, 4)[:count]

    lo, hi = images["means0"][:, :3].astype(np.int64), images["means1"][:, :3].astype(np.int64)
    t = (lo | (hi << 8)).astype(np.float64) / 65535.0
    means = _unlog(mins * (1.0 - t) + maxs * t)

    qi = images["quats0"]
    mode = qi[:, 3].astype(np.int64) - 252
    if ((mode < 0) | (mode > 3)).any():
        bad = int(np.flatnonzero((mode < 0) | (mode > 3))[0])
        raise InputError(f"{where}: quaternion of Gaussian {bad} has mode byte {int(qi[bad, 3])}; 252..255 are valid")
    small = (qi[:, :3].astype(np.float64) / 255.0 - 0.5) * SQRT2
    big = np.sqrt(np.clip(1.0 - (small**2).sum(1), 0.0, None))
    quats = np.empty((count, 4))
    rows = np.arange(count)
    quats[rows, mode] = big
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[mode]
    quats[rows[:, None], others] = small

    scales = _lookup(scale_book, images["scales0"][:, :3].astype(np.int64), "scale", where)
    sh0 = images["sh00"]
    f_dc = _lookup(dc_book, sh0[:, :3].astype(np.int64), "sh0 colour", where)
    opac = logit(sh0[:, 3].astype(np.float64) / 255.0)

    sh = np.zeros((count, (bands + 1) ** 2, 3))
    sh[:, 0] = f_dc
    if bands:
        coeffs = COEFFS[bands]
        name = names["shN"][0]
        cent = _decode_image(read(name), name, where)
        if cent.shape[1] != ENTRIES_PER_ROW * coeffs:
            raise InputError(f"{where}: {name} is {cent.shape[1]} pixels wide; {ENTRIES_PER_ROW * coeffs} expected "
                             f"for {bands} SH band(s)")
        if cent.shape[0] * ENTRIES_PER_ROW < palette:
            raise InputError(f"{where}: {name} has {cent.shape[0]} rows, too few for {palette:,} palette entries")
        entries = cent.reshape(-1, coeffs, 4)[:palette, :, :3].astype(np.int64)  # [palette, coeffs, rgb]
        table = _lookup(shn_book, entries, "shN", where)
        lab = images["shN1"]
        labels = lab[:, 0].astype(np.int64) | (lab[:, 1].astype(np.int64) << 8)
        if labels.size and int(labels.max()) >= palette:
            raise InputError(f"{where}: SH label {int(labels.max())} lies beyond the {palette:,}-entry palette")
        sh[:, 1:] = table[labels]
    return Gaussians.from_numpy(means, scales, quats, opac, sh)


def _zip_reader(buf: bytes, where: str) -> tuple[zipfile.ZipFile, Callable[[str], bytes]]:
    try:
        z = zipfile.ZipFile(io.BytesIO(buf))
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise InputError(f"{where}: not a readable zip archive, truncated or corrupt ({e})") from None
    members = {i.filename: i for i in z.infolist()}

    def read(name: str) -> bytes:
        info = members.get(name)
        if info is None:
            raise InputError(f"{where}: the SOG archive lacks {name}")
        limit = MAX_META_BYTES if name == "meta.json" else MAX_ENTRY_BYTES
        if info.file_size > limit:
            raise InputError(f"{where}: {name} claims {info.file_size:,} bytes (corrupt archive?)")
        try:
            return z.read(info)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error, NotImplementedError, RuntimeError) as e:
            raise InputError(f"{where}: cannot read {name} from the archive, truncated or corrupt ({e})") from None

    return z, read


def read_sog_bytes(buf: bytes, where: str = "file") -> Gaussians:
    """Decode a bundled (zip) ``.sog`` held in memory."""
    z, read = _zip_reader(buf, where)
    with z:
        return decode_sog(read, where)


def read_sog(path: str | os.PathLike) -> Gaussians:
    """Read a ``.sog``: a zip archive, a folder holding ``meta.json``, or that ``meta.json``."""
    path = Path(path)
    where = str(path)
    if path.is_dir() or path.name == "meta.json":
        folder = path if path.is_dir() else path.parent

        def read(name: str) -> bytes:
            if Path(name).is_absolute() or ".." in Path(name).parts:
                raise InputError(f"{where}: meta.json names {name!r}, outside the SOG folder")
            p = folder / name
            if not p.is_file():
                raise InputError(f"{where}: the SOG folder lacks {name}")
            try:
                return p.read_bytes()
            except OSError as e:
                raise InputError(f"{where}: cannot read {name}: {e.strerror}") from None

        return decode_sog(read, where)
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise InputError(f"cannot read {path}: {e.strerror}") from None
    if not buf:
        raise InputError(f"{path} is empty")
    return read_sog_bytes(buf, where)
