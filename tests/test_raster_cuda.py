"""The CUDA rasterizer (csrc/) against the torch reference, and its build.

GPU tests (skipped without a GPU): the same contributions as the reference (same entries after a
canonical sort, weights and transmittances to float32 rounding), images within 1e-5, on random
scenes, the hard cases of ``test_raster_reference`` and tile requests of every kind; the fused
composite against the plain one, forward and backward.

CPU tests: every .cu file compiles with nvcc for one architecture (fast), and the whole
extension builds with torch's JIT loader (slow: a few minutes on a small machine).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from test_raster_reference import SCENES, make_cams, random_scene
from virgi_ns.raster import reference
from virgi_ns.raster.contract import Cameras, Request, composite, composite_plain

REPO = Path(__file__).resolve().parents[1]
CSRC = REPO / "csrc"
IMG_TOL = 1e-5
# Weights are products of up to hundreds of rounded factors: equal to float32 rounding means a
# relative error up to a few 1e-5 over ~40 factors (the reference on the GPU builds T with a
# parallel cumprod); images are held to 1e-5 absolute.
W_RTOL, W_ATOL = 1e-4, 1e-6


# ----------------------------------------------------------------------------- helpers
def _canonical(c):
    """Entries as (pixel, view, gaussian) long keys sorted, with their weights (float64)."""
    n = c.num_gaussians
    pix = c.pixel.long().cpu()
    pair = c.pair.long().cpu()
    view = c.pair_view.cpu()[pair]
    gau = c.pair_gaussian.cpu()[pair]
    key = (pix * (int(c.pair_view.max()) + 1 if len(c.pair_view) else 1) + view) * n + gau
    order = torch.argsort(key)
    return torch.stack([pix, view, gau], 1)[order], c.weight.detach().double().cpu()[order]


def assert_same_contributions(cu, ref):
    """Same entries, same pairs, weights and transmittance to float32 rounding, contract order."""
    assert cu.num_pixels == ref.num_pixels
    assert torch.equal(cu.valid.cpu(), ref.valid.cpu())
    assert torch.equal(cu.pair_view.cpu(), ref.pair_view.cpu())
    assert torch.equal(cu.pair_gaussian.cpu(), ref.pair_gaussian.cpu())
    assert torch.allclose(cu.pair_depth.cpu().double(), ref.pair_depth.detach().cpu().double(), rtol=1e-6, atol=1e-7)
    e_cu, w_cu = _canonical(cu)
    e_ref, w_ref = _canonical(ref)
    assert e_cu.shape == e_ref.shape, f"{len(e_cu)} entries vs the reference's {len(e_ref)}"
    assert torch.equal(e_cu, e_ref)
    if len(w_cu):
        err = ((w_cu - w_ref).abs() - W_RTOL * w_ref.abs()).max()
        assert err <= W_ATOL, f"weights differ by {float((w_cu - w_ref).abs().max()):.3g}"
    t_cu, t_ref = cu.transmittance.cpu().double(), ref.transmittance.detach().cpu().double()
    assert ((t_cu - t_ref).abs() - W_RTOL * t_ref.abs()).max() <= W_ATOL
    # contract order: grouped by pixel ascending, front to back inside a pixel
    pix = cu.pixel.long().cpu()
    assert torch.all(pix[1:] >= pix[:-1])
    same = pix[1:] == pix[:-1]
    d = cu.pair_depth.cpu()[cu.pair.long().cpu()]
    assert torch.all(d[1:][same] >= d[:-1][same])
    assert torch.all(cu.transmittance.cpu()[~cu.valid.cpu()] == 1)


def _run_both(scene, cams: Cameras, request: Request):
    from virgi_ns.raster import cuda

    dev = torch.device("cuda")
    m, q, s, o = (a.float().to(dev) for a in scene)
    cams32 = cams.to(dev, torch.float32)
    cu = cuda.rasterize(m, q, s, o, cams32, request)
    ref = reference.rasterize(m, q, s, o, cams32, request)
    return cu, ref


def _images(c, colours_vn, bg):
    cols = colours_vn[c.pair_view, c.pair_gaussian]
    return composite(cols, c, bg)


TILE_REQUESTS = {
    "whole": None,
    "tiles32": (32, [(0, 5, 7), (1, 5, 7), (0, 50, 30), (1, -10, -5), (0, 60, 40), (0, 5, 7)]),
    "tiles16": (16, [(0, 0, 0), (0, 64, 32), (1, 48, 16), (0, 200, 200)]),
    "tiles64": (64, [(1, 3, 0), (0, -20, -20)]),
}


def _request(kind, cams):
    if TILE_REQUESTS[kind] is None:
        return Request.whole_images(cams)
    size, tiles = TILE_REQUESTS[kind]
    v, x0, y0 = (torch.tensor(t) for t in zip(*tiles))
    return Request.tiles(v, x0, y0, size)


# ----------------------------------------------------------------------------- GPU
@pytest.mark.gpu
def test_cuda_backend_available():
    from virgi_ns.raster import cuda

    ok, why = cuda.available()
    assert ok, why


@pytest.mark.gpu
@pytest.mark.parametrize("lists", ["eager", "deferred"])
@pytest.mark.parametrize("kind", list(TILE_REQUESTS))
@pytest.mark.parametrize("name", list(SCENES))
def test_cuda_matches_reference(name, kind, lists, monkeypatch):
    from virgi_ns.raster import cuda

    # deferred lists composite straight from the tile lists; their entries are built on access
    monkeypatch.setattr(cuda, "DEFERRED_MIN_PIXELS", 0 if lists == "deferred" else None)
    cams = make_cams(70, 45, views=2)
    scene = SCENES[name]()
    req = _request(kind, cams)
    cu, ref = _run_both(scene, cams, req)
    dev = torch.device("cuda")
    colours = torch.rand(2, scene[0].shape[0], 3, device=dev, generator=torch.Generator(dev).manual_seed(1))
    bg = torch.tensor([0.2, 0.5, 0.9], device=dev)
    assert (_images(cu, colours, bg) - _images(ref, colours, bg)).abs().max() <= IMG_TOL
    assert_same_contributions(cu, ref)
    if name in ("random", "pile", "large") and kind == "whole":
        assert ref.weight.numel() > 100  # the comparison is not vacuous


@pytest.mark.gpu
@pytest.mark.parametrize("seed", [0, 1])
def test_cuda_matches_reference_larger_scene(seed):
    """Thousands of Gaussians, non-square images, 3 views, many grid tiles, mixed tile requests."""
    g = torch.Generator().manual_seed(seed)
    cams = make_cams(173, 98, views=3, f=120.0)
    scene = random_scene(4000, seed=seed, spread=1.0, scale=(0.005, 0.08))
    cu, ref = _run_both(scene, cams, Request.whole_images(cams))
    dev = torch.device("cuda")
    colours = torch.rand(3, 4000, 3, device=dev, generator=torch.Generator(dev).manual_seed(seed))
    assert (_images(cu, colours, None) - _images(ref, colours, None)).abs().max() <= IMG_TOL
    assert_same_contributions(cu, ref)
    assert ref.weight.numel() > 10_000
    views = torch.randint(0, 3, (40,), generator=g)
    x0 = torch.randint(-20, 173, (40,), generator=g)
    y0 = torch.randint(-20, 98, (40,), generator=g)
    req = Request.tiles(views, x0, y0, 32)
    cu_t, ref_t = _run_both(scene, cams, req)
    assert_same_contributions(cu_t, ref_t)
    # a tile equals the same pixels cut from the whole images
    whole = _images(cu, colours, None).cpu()
    tiles = _images(cu_t, colours, None).cpu().reshape(-1, 3)
    pv, px, py = req.pixel_coords()
    ok = req.valid_mask(cams)
    assert (tiles[ok] - whole[pv[ok], py[ok], px[ok]]).abs().max() <= 1e-6


@pytest.mark.gpu
def test_cuda_empty_cases():
    from virgi_ns.raster import cuda

    dev = torch.device("cuda")
    cams = make_cams(70, 45, views=2).to(dev, torch.float32)
    m, q, s, o = (a.float().to(dev) for a in random_scene(50, seed=6, spread=0.1, scale=(0.01, 0.02)))
    c = cuda.rasterize(m, q, s, o, cams, Request.tiles([0, 1], [0, 0], [0, 0], 16))  # nothing reaches
    assert c.weight.numel() == 0 and torch.all(c.transmittance == 1) and c.pair_view.numel() == 0
    behind = m.clone()
    behind[:, 2] = -10.0
    c = cuda.rasterize(behind, q, s, o, cams, Request.whole_images(cams))
    assert c.weight.numel() == 0 and torch.all(c.transmittance == 1)
    assert cuda.composite(torch.zeros(0, 3, device=dev), c, 0.5).eq(0.5).all()
    c = cuda.rasterize(m[:0], q[:0], s[:0], o[:0], cams, Request.whole_images(cams))
    assert c.weight.numel() == 0 and c.transmittance.shape == (2 * 45 * 70,)
    c = cuda.rasterize(m, q, s, o, cams, Request.tiles([1], [500], [500], 32))  # fully outside
    assert c.weight.numel() == 0 and not c.valid.any()


@pytest.mark.gpu
@pytest.mark.parametrize("kind", ["whole", "tiles"])
@pytest.mark.parametrize("d", [3, 1, 4, 5])
def test_fused_composite_matches_plain(d, kind, monkeypatch):
    """Fused forward and both backward paths (per tile for 1/3/4 channels, per entry otherwise)."""
    from virgi_ns.raster import cuda

    monkeypatch.setattr(cuda, "TILE_BACKWARD_MIN_PIXELS", 0 if kind == "whole" else 1 << 40)
    dev = torch.device("cuda")
    cams = make_cams(96, 64, views=2)
    m, q, s, o = (a.float().to(dev) for a in random_scene(800, seed=7, scale=(0.01, 0.15)))
    req = Request.whole_images(cams) if kind == "whole" else \
        Request.tiles([0, 1, 0, 0, 1], [5, -7, 40, 5, 80], [3, 30, 20, 3, 50], 32)  # overlap, repeat, border
    c = cuda.rasterize(m, q, s, o, cams.to(dev, torch.float32), req)
    assert c.weight.numel() > 1000
    gen = torch.Generator(dev).manual_seed(d)
    colours = torch.rand(len(c.pair_view), d, device=dev, generator=gen).requires_grad_(True)
    bg = torch.rand(d, device=dev, generator=gen).requires_grad_(True)
    up = torch.randn(*c.shape, d, device=dev, generator=gen)
    fused = cuda.composite(colours, c, bg)
    (g_c, g_b) = torch.autograd.grad((fused * up).sum(), (colours, bg))
    plain = composite_plain(colours, c, bg)
    (p_c, p_b) = torch.autograd.grad((plain * up).sum(), (colours, bg))
    assert (fused - plain).abs().max() <= 1e-5
    assert torch.allclose(g_c, p_c, atol=1e-4, rtol=1e-5)
    assert torch.allclose(g_b, p_b, atol=1e-3, rtol=1e-5)


@pytest.mark.gpu
@pytest.mark.parametrize("kind", ["whole", "tiles"])
@pytest.mark.parametrize("d", [3, 1, 5, 8])
def test_deferred_lists_equal_eager(d, kind, monkeypatch):
    """Deferred lists: the composite from the tile lists equals the fused composite of the stored
    entries (same weights, same order), its gradients equal the plain path's, and the entries built
    on access equal the two-pass lists exactly."""
    from virgi_ns.raster import cuda

    dev = torch.device("cuda")
    cams = make_cams(96, 64, views=2).to(dev, torch.float32)
    m, q, s, o = (a.float().to(dev) for a in random_scene(1500, seed=9, scale=(0.01, 0.15)))
    req = Request.whole_images(cams) if kind == "whole" else \
        Request.tiles([0, 1, 0, 0, 1], [5, -7, 40, 5, 80], [3, 30, 20, 3, 50], 32)
    monkeypatch.setattr(cuda, "DEFERRED_MIN_PIXELS", None)
    monkeypatch.setattr(cuda, "SINGLE_PASS", 0)
    eager = cuda.rasterize(m, q, s, o, cams, req)
    monkeypatch.setattr(cuda, "DEFERRED_MIN_PIXELS", 0)
    lazy = cuda.rasterize(m, q, s, o, cams, req)
    assert isinstance(lazy, cuda.DeferredCudaContributions) and lazy._lists is None
    assert eager.weight.numel() > 1000
    for name in ("transmittance", "valid", "pair_view", "pair_gaussian", "pair_depth"):
        assert torch.equal(getattr(lazy, name), getattr(eager, name)), name
    gen = torch.Generator(dev).manual_seed(d)
    colours = torch.rand(len(eager.pair_view), d, device=dev, generator=gen).requires_grad_(True)
    bg = torch.rand(d, device=dev, generator=gen).requires_grad_(True)
    up = torch.randn(*eager.shape, d, device=dev, generator=gen)
    for background in (bg, None):
        out = composite(colours, lazy, background)
        assert lazy._lists is None  # composited without building the entries
        want = composite(colours, eager, background) if d in (1, 3, 4) else composite_plain(colours, eager, background)
        assert (out - want).abs().max() <= 1e-6
        inputs = (colours, bg) if background is not None else (colours,)
        got_g = torch.autograd.grad((out * up).sum(), inputs)
        want_g = torch.autograd.grad((composite_plain(colours, eager, background) * up).sum(), inputs)
        for g, w in zip(got_g, want_g):
            assert torch.allclose(g, w, atol=1e-4, rtol=1e-5)
    assert lazy.num_entries == eager.weight.numel() and lazy._lists is None
    keep, keep_end = lazy.deferred.keep, lazy.deferred.keep_end
    if kind == "whole":  # one unit per slot: the walks use the kept elements only, fewer than the lists
        ranges = lazy.deferred.ranges.view(-1, 2)
        kept = int((keep_end.long() - ranges[:, 0].long()).sum())
        assert 0 < kept < int((ranges[:, 1] - ranges[:, 0]).sum()) and keep.numel() > 0
    for name in ("pixel", "pair", "weight", "pixel_offsets"):
        assert torch.equal(getattr(lazy, name), getattr(eager, name)), name


@pytest.mark.gpu
def test_composite_dispatches_to_fused(monkeypatch):
    """The ordinary contract.composite runs the fused kernels for CUDA lists (float32 colours),
    and the plain path for float64 colours or a plain Contributions; all give the same images."""
    from virgi_ns.raster import cuda
    from virgi_ns.raster.contract import Contributions

    calls = []
    real = cuda._FusedComposite.apply
    monkeypatch.setattr(cuda._FusedComposite, "apply", lambda *a: calls.append(1) or real(*a))
    dev = torch.device("cuda")
    cams = make_cams(64, 48, views=2)
    m, q, s, o = (a.float().to(dev) for a in random_scene(300, seed=3, scale=(0.01, 0.15)))
    c = cuda.rasterize(m, q, s, o, cams.to(dev, torch.float32), Request.whole_images(cams))
    colours = torch.rand(len(c.pair_view), 3, device=dev, generator=torch.Generator(dev).manual_seed(0))
    colours.requires_grad_(True)
    out = composite(colours, c, 0.25)
    assert len(calls) == 1
    (g,) = torch.autograd.grad(out.square().sum(), colours)
    ref = composite_plain(colours, c, 0.25)
    (g_ref,) = torch.autograd.grad(ref.square().sum(), colours)
    assert (out - ref).abs().max() <= 1e-5 and torch.allclose(g, g_ref, atol=1e-4, rtol=1e-5)
    out64 = composite(colours.double(), c, 0.25)  # not eligible: plain path
    assert len(calls) == 1 and out64.dtype == torch.float64
    fields = {f: getattr(c, f) for f in Contributions.__dataclass_fields__}
    plain_obj = Contributions(**fields)
    # (index_add on the GPU sums in any order: equal to float32 rounding)
    assert (composite(colours, plain_obj, 0.25) - ref).abs().max() <= 1e-6 and len(calls) == 1


@pytest.mark.gpu
@pytest.mark.parametrize("capacity", [1, 37])
def test_visible_capacity_overflow_retries(capacity, monkeypatch):
    """Compact visible-pair arrays that overflow are resized and the projection rerun: the output
    equals the default run exactly (the compact arrays, appended in any order, are sorted by
    their unique v*N+g)."""
    from virgi_ns.raster import cuda

    dev = torch.device("cuda")
    cams = make_cams(96, 64, views=3).to(dev, torch.float32)
    m, q, s, o = (a.float().to(dev) for a in random_scene(2000, seed=4, scale=(0.005, 0.1)))
    req = Request.tiles([0, 2, 1, 2], [5, 40, -7, 70], [3, 20, 30, 40], 32)
    want = cuda.rasterize(m, q, s, o, cams, req)
    again = cuda.rasterize(m, q, s, o, cams, req)
    monkeypatch.setattr(cuda, "VISIBLE_CAPACITY", capacity)
    got = cuda.rasterize(m, q, s, o, cams, req)
    assert want.weight.numel() > 1000 and len(want.pair_view) > capacity
    for name in ("pixel", "pair", "weight", "transmittance", "pair_view", "pair_gaussian", "pair_depth",
                 "pixel_offsets"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
        assert torch.equal(getattr(again, name), getattr(want, name)), name


@pytest.mark.gpu
@pytest.mark.parametrize("capacity", [None, 500])
def test_projection_many_visible_views(capacity, monkeypatch):
    """Six views of a small scene, nearly every pair visible: a warp's staging region of the
    projection (four views' worth) fills and is copied out mid-block; the lists still equal the
    reference's, also when the compact arrays overflow and the projection reruns."""
    from virgi_ns.raster import cuda

    monkeypatch.setattr(cuda, "VISIBLE_CAPACITY", capacity)
    cams = make_cams(64, 48, views=4).index([0, 1, 2, 3, 0, 2])
    m, q, s, o = random_scene(3000, seed=11, spread=0.5, scale=(0.01, 0.04))
    cu, ref = _run_both((m, q, s, o * 0.2), cams, Request.whole_images(cams))
    # more than 4 x 32 contributing (so visible) pairs per warp of 32 Gaussians on average
    assert len(ref.pair_view) > 0.75 * 6 * 3000
    assert_same_contributions(cu, ref)


@pytest.mark.gpu
@pytest.mark.parametrize("single", [2, 8, 512])
def test_single_pass_equals_two_passes(single, monkeypatch):
    """One pass into the padded layout (and its fallback when a pixel overflows it) gives exactly
    the two-pass lists."""
    from virgi_ns.raster import cuda

    dev = torch.device("cuda")
    cams = make_cams(96, 64, views=2).to(dev, torch.float32)
    m, q, s, o = (a.float().to(dev) for a in random_scene(1500, seed=8, scale=(0.01, 0.15)))
    for req in (Request.tiles([0, 1, 1, 0], [5, -9, 60, 5], [3, 30, 40, 3], 32), Request.whole_images(cams)):
        monkeypatch.setattr(cuda, "SINGLE_PASS", 0)
        want = cuda.rasterize(m, q, s, o, cams, req)
        monkeypatch.setattr(cuda, "SINGLE_PASS", single)
        got = cuda.rasterize(m, q, s, o, cams, req)
        counts = want.pixel_offsets[1:] - want.pixel_offsets[:-1]
        assert want.weight.numel() > 1000 and (single > 2 or int(counts.max()) > single)
        for name in ("pixel", "pair", "weight", "transmittance", "pair_view", "pair_gaussian", "pixel_offsets"):
            assert torch.equal(getattr(got, name), getattr(want, name)), name
        ref = reference.rasterize(m, q, s, o, cams, req)
        assert_same_contributions(got, ref)


@pytest.mark.gpu
def test_auto_backend_picks_cuda():
    from virgi_ns.raster import cuda, rasterize

    dev = torch.device("cuda")
    cams = make_cams(40, 30, views=1).to(dev, torch.float32)
    m, q, s, o = (a.float().to(dev) for a in random_scene(30))
    c = rasterize(m, q, s, o, cams, Request.whole_images(cams), backend="auto")
    assert isinstance(c, cuda.CudaContributions)


# ----------------------------------------------------------------------------- CPU: the build
def _nvcc() -> str | None:
    from virgi_ns.raster.cuda import cuda_home

    root = cuda_home()
    return str(Path(root) / "bin" / "nvcc") if root else None


@pytest.mark.parametrize("source", sorted(p.name for p in CSRC.glob("*.cu")))
def test_cuda_sources_compile(source, tmp_path):
    """Each kernel file compiles for sm_90 (the kernels need only the CUDA toolkit, not torch)."""
    nvcc = _nvcc()
    if nvcc is None:
        pytest.skip("nvcc not found")
    cmd = [nvcc, "-c", str(CSRC / source), "-o", str(tmp_path / "k.o"), "-std=c++17", "-O1",
           "-fmad=false", "-gencode=arch=compute_90,code=sm_90", "-Werror=all-warnings"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-4000:]


@pytest.mark.slow
def test_cuda_extension_builds(tmp_path):
    """The whole extension (kernels + torch bindings) builds with torch's JIT loader, no GPU needed."""
    if _nvcc() is None:
        pytest.skip("nvcc not found")
    if torch.version.cuda is None:
        pytest.skip("torch has no CUDA support")
    env = dict(os.environ)
    env.setdefault("TORCH_CUDA_ARCH_LIST", "9.0")
    env.setdefault("MAX_JOBS", str(os.cpu_count() or 2))
    code = ("from virgi_ns.raster import cuda; m = cuda.build(); "
            "assert hasattr(m, 'rasterize_contributions') and hasattr(m, 'composite_backward'); print('ok')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO)
    assert res.returncode == 0 and "ok" in res.stdout, (res.stdout + res.stderr)[-4000:]


def test_composite_dispatch_keeps_cpu_behaviour():
    """On the CPU a CudaContributions composites exactly as the plain path does, and both equal
    an independent per-pixel sum (float64)."""
    from virgi_ns.raster.cuda import CudaContributions
    from virgi_ns.raster.contract import Contributions

    cams = make_cams(30, 20, views=2)
    m, q, s, o = random_scene(60, seed=2)
    ref = reference.rasterize(m, q, s, o, cams, Request.tiles([0, 1, 1], [3, -4, 10], [2, 5, -3], 16))
    assert ref.weight.numel() > 50
    fields = {f: getattr(ref, f) for f in Contributions.__dataclass_fields__}
    counts = torch.bincount(ref.pixel, minlength=ref.num_pixels)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    cu_like = CudaContributions(**fields, pixel_offsets=offsets)
    g = torch.Generator().manual_seed(5)
    colours = torch.rand(len(ref.pair_view), 3, generator=g, dtype=torch.float64, requires_grad=True)
    bg = torch.tensor([0.1, 0.6, 0.3], dtype=torch.float64)
    got = composite(colours, cu_like, bg)
    assert torch.equal(got, composite_plain(colours, ref, bg))
    want = torch.zeros(ref.num_pixels, 3, dtype=torch.float64)
    w = ref.weight.detach()
    for e in range(len(w)):
        want[ref.pixel[e]] += w[e] * colours.detach()[ref.pair[e]]
    want += ref.transmittance.detach()[:, None] * bg
    assert (got.detach().reshape(-1, 3) - want).abs().max() <= 1e-12
    (gc,) = torch.autograd.grad(got.sum(), colours)
    gw = torch.zeros(len(ref.pair_view), dtype=torch.float64).index_add(0, ref.pair, w)
    assert torch.allclose(gc, gw[:, None].expand(-1, 3))


def test_available_reports_a_reason_without_gpu():
    from virgi_ns.raster import cuda

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    ok, why = cuda.available()
    assert not ok and "GPU" in why


# ------------------------------------------------------------------ CPU: the cached build's stamp
def _fake_library(tmp_path: Path, monkeypatch) -> Path:
    """A stand-in for the built library (a Python module: the loader imports either kind), with the
    stamp directory in ``tmp_path``."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    lib = tmp_path / "fake_virgi_ext.py"
    lib.write_text("VALUE = 7\n")
    return lib


def _csrc_copy(tmp_path: Path, monkeypatch) -> Path:
    """A copy of ``csrc/`` that the loader hashes instead of the real one (the tests change it)."""
    from virgi_ns.raster import cuda

    src = tmp_path / "csrc"
    src.mkdir()
    for f in CSRC.iterdir():
        (src / f.name).write_bytes(f.read_bytes())
    monkeypatch.setattr(cuda, "CSRC", src)
    return src


def _stamp_for(lib: Path):
    from types import SimpleNamespace

    from virgi_ns.raster import cuda

    cuda._write_stamp(SimpleNamespace(__file__=str(lib), __name__="fake_virgi_ext"), cuda.build_key())
    return cuda


def test_a_current_stamp_imports_the_cached_build(tmp_path, monkeypatch):
    """The stamp written for a build lets a later process import that build directly."""
    cuda = _stamp_for(_fake_library(tmp_path, monkeypatch))
    assert cuda.stamp_path().parent == tmp_path / "ext"
    module = cuda.load_cached()
    assert module is not None and module.VALUE == 7


@pytest.mark.parametrize("change", ["source", "library", "missing stamp", "corrupt stamp"])
def test_a_stale_stamp_takes_the_slow_path(change, tmp_path, monkeypatch):
    """Anything that makes the cached build another one sends the loader back to torch's build tools:
    a changed source file, a library rebuilt since the stamp, no stamp, an unreadable stamp."""
    lib = _fake_library(tmp_path, monkeypatch)
    src = _csrc_copy(tmp_path, monkeypatch)
    cuda = _stamp_for(lib)
    assert cuda.load_cached() is not None
    if change == "source":
        k = src / "edit_kernels.cu"
        k.write_text(k.read_text() + "\n// one more line\n")
    elif change == "library":
        st = lib.stat()
        os.utime(lib, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    elif change == "missing stamp":
        cuda.stamp_path().unlink()
    else:
        cuda.stamp_path().write_text("{not json")
    assert cuda.load_cached() is None


def test_the_build_key_follows_the_sources_and_the_flags(tmp_path, monkeypatch):
    from virgi_ns.raster import cuda

    src = _csrc_copy(tmp_path, monkeypatch)
    key = cuda.build_key()
    assert cuda.build_key() == key
    (src / "notes.txt").write_text("not a source")
    assert cuda.build_key() == key
    (src / "atomics.cuh").write_text((src / "atomics.cuh").read_text().replace("16-byte", "16 byte"))
    changed = cuda.build_key()
    assert changed != key
    monkeypatch.setattr(cuda, "_build_flags", lambda: {"extra_cflags": ["-O2"]})
    assert cuda.build_key() != changed
