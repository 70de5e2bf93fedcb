"""Benchmark: our tile rasterizer against gsplat, forward + backward to the colours.

One tile batch for every row: 160 tiles of 32x32 and 40 of 64x64 (any position) from 8 views.
Rows per scene (random 1M / 3M Gaussians, and a real splat with cameras placed around it):

* ``ours tiles``         our CUDA backend on the tile batch (the 64-px tiles as 2x2 tiles of 32,
                         so one request), ``composite`` (fused for our lists); ``(plain)`` uses
                         ``contract.composite_plain`` (gather + index_add)
* ``gsplat per-tile``    gsplat 1.4.0 with one camera per tile (principal point shifted)
* ``ours whole``         our backend on the 8 whole views (deferred lists: the composite and its
                         gradient walk the tile lists, ``virgi_ns.raster.cuda``); ``(eager lists)``
                         stores every entry first, as smaller requests do
* ``gsplat whole``       gsplat on the 8 whole views

Prints one table (device named), writes ``results.json`` and ``renders.png`` under ``--out``.
Run on a GPU machine: ``python bench/raster.py --out bench/out/raster``.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from virgi_ns.errors import InputError, atomic_path, cli_entry
from virgi_ns.raster.contract import Cameras, Request, composite, composite_plain

REPO = Path(__file__).resolve().parents[1]


@dataclass
class Args:
    """Tile-batch rasterizer benchmark (needs a CUDA GPU)."""

    out: Path = Path("bench/out/raster")
    """Output folder for results.json and renders.png."""
    sizes: tuple[int, ...] = (1_000_000, 3_000_000)
    """Random scenes: numbers of Gaussians."""
    splat: Path | None = None
    """A real splat (any format virgi-convert reads); default: biker from .data/ or ../shared/data."""
    width: int = 1600
    height: int = 1064
    views: int = 8
    iters: int = 20
    warmup: int = 3
    gsplat: bool = True
    """Also time gsplat (skipped with a note when it is not installed)."""
    plain: bool = True
    """Also time our backend with the plain torch composite (gather + index_add)."""
    two_pass_row: bool = True
    """Also time the tile batch with the rasterization forced to two passes (count + fill)."""
    seed: int = 0
    profile: bool = False
    """Print a CUDA kernel profile of our steps (stderr)."""


@dataclass
class Scene:
    name: str
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor  # [N, 3]
    cameras: Cameras


@dataclass
class Row:
    scene: str
    method: str
    n_gaussians: int
    mpix: float
    ms: float
    ms_spread: float
    raster_ms: float | None = None
    peak_mb: float = 0.0
    mb_per_mpix: float = 0.0
    entries_per_px: float | None = None
    max_abs_vs_gsplat: float | None = None
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- scenes
def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World-to-camera (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z])
    M[:3, 3] = -M[:3, :3] @ eye
    return torch.as_tensor(M, dtype=torch.float32)


def ring_cameras(center, radius: float, views: int, width: int, height: int, f: float, dev) -> Cameras:
    center = np.asarray(center, dtype=np.float64)
    eyes = []
    for i in range(views):
        a = 2 * math.pi * i / views
        elev = 0.35 * radius * (1 if i % 2 else -0.5)
        eyes.append(center + np.array([radius * math.cos(a), -elev, radius * math.sin(a)]))
    vm = torch.stack([look_at(e, center) for e in eyes]).to(dev)
    return Cameras.from_params(f, f, width / 2, height / 2, vm, width, height)


def random_scene(n: int, args: Args, dev) -> Scene:
    g = torch.Generator(device=dev).manual_seed(args.seed + n)
    means = (torch.rand(n, 3, device=dev, generator=g) * 2 - 1)
    quats = torch.randn(n, 4, device=dev, generator=g)
    lo, hi = math.log(0.001), math.log(0.01)
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, device=dev, generator=g))
    opac = torch.rand(n, device=dev, generator=g) * 0.9 + 0.05
    colours = torch.rand(n, 3, device=dev, generator=g)
    cams = ring_cameras((0, 0, 0), 3.2, args.views, args.width, args.height, 0.8 * args.width, dev)
    return Scene(f"random {n / 1e6:g}M", means, quats, scales, opac, colours, cams)


def splat_scene(path: Path, args: Args, dev) -> Scene:
    from virgi_ns.io import load_splat

    g = load_splat(path)
    means = g.means.float().to(dev)
    center = means.median(0).values
    dist = (means - center).norm(dim=1)
    radius = float(dist.quantile(0.9)) * 2.2
    colours = (0.2820948 * g.sh[:, 0].float() + 0.5).clamp_min(0).to(dev)
    cams = ring_cameras(center.cpu().numpy(), radius, args.views, args.width, args.height, 0.8 * args.width, dev)
    return Scene(f"{path.name.split('.')[0]} {len(g) / 1e6:.2f}M", means, g.quats.float().to(dev),
                 g.scales.float().exp().to(dev), torch.sigmoid(g.opacities.float()).to(dev), colours, cams)


# ----------------------------------------------------------------------------- the tile batch
def tile_batch(args: Args) -> tuple[list[tuple[int, int, int, int]], Request]:
    """160 tiles of 32 and 40 of 64 (view, x0, y0, size), and our request: the 64-px tiles as
    2x2 tiles of 32 (the same pixels), so the batch is one request."""
    g = torch.Generator().manual_seed(args.seed)
    tiles = []
    for count, size in ((160, 32), (40, 64)):
        v = torch.arange(count) % args.views
        x0 = torch.randint(0, args.width - size + 1, (count,), generator=g)
        y0 = torch.randint(0, args.height - size + 1, (count,), generator=g)
        tiles += [(int(a), int(b), int(c), size) for a, b, c in zip(v, x0, y0)]
    rv, rx, ry = [], [], []
    for v, x0, y0, size in tiles:
        for dy in range(0, size, 32):
            for dx in range(0, size, 32):
                rv.append(v)
                rx.append(x0 + dx)
                ry.append(y0 + dy)
    return tiles, Request.tiles(torch.tensor(rv), torch.tensor(rx), torch.tensor(ry), 32)


def assemble_tiles(img32: torch.Tensor, tiles) -> list[torch.Tensor]:
    """Our [T32, 32, 32, 3] request output -> one image per original tile."""
    out, k = [], 0
    for _, _, _, size in tiles:
        n = (size // 32) ** 2
        sub = img32[k:k + n]
        k += n
        s = size // 32
        out.append(sub.reshape(s, s, 32, 32, 3).permute(0, 2, 1, 3, 4).reshape(size, size, 3))
    return out


# ----------------------------------------------------------------------------- timing
def measure(fn, iters: int, warmup: int) -> tuple[float, float, float]:
    """(median ms, spread ms (max - min of the middle half), peak extra MB of one call)."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    torch.cuda.synchronize()
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    times = []
    for _ in range(iters):
        s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        s.record()
        fn()
        e.record()
        e.synchronize()
        times.append(s.elapsed_time(e))
    times.sort()
    q = len(times) // 4
    return statistics.median(times), times[-1 - q] - times[q], peak


def run_scene(sc: Scene, args: Args, tiles, req: Request, gsplat, rows: list[Row], pictures: dict) -> None:
    from virgi_ns.raster import cuda

    dev = sc.means.device
    n = sc.means.shape[0]
    colours = sc.colours.clone().requires_grad_(True)
    whole = Request.whole_images(sc.cameras)
    mp_tiles = sum(s * s for *_, s in tiles) / 1e6
    mp_whole = whole.num_pixels / 1e6
    geo = (sc.means, sc.quats, sc.scales, sc.opacities)

    def ours(request: Request, fused: bool):
        def step():
            colours.grad = None
            c = cuda.rasterize(*geo, sc.cameras, request)
            cols = c.gather(colours)
            img = (composite if fused else composite_plain)(cols, c, None)
            img.sum().backward()
            return c, img
        return step

    def raster_only(request: Request):
        return lambda: cuda.rasterize(*geo, sc.cameras, request)

    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        for label, request in (("tiles", req), ("whole", whole)):
            ours(request, True)()
            with profile(activities=[ProfilerActivity.CUDA]) as prof:
                ours(request, True)()
                torch.cuda.synchronize()
            print(f"--- profile: {sc.name}, ours {label}", file=sys.stderr)
            print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=14), file=sys.stderr)

    results = {}
    for label, request, mp in (("tiles", req, mp_tiles), ("whole", whole, mp_whole)):
        deferred_default = cuda.DEFERRED_MIN_PIXELS
        variants = [("", True, None, deferred_default)]
        if label == "whole":  # the stored lists, as before deferred lists
            variants.append((" (eager lists)", True, None, None))
        else:  # deferred lists for the tile batch too (not the default below DEFERRED_MIN_PIXELS)
            variants.append((" (deferred lists)", True, None, 0))
        if args.plain:
            variants.append((" (plain composite)", False, None, deferred_default))
        if label == "tiles" and args.two_pass_row:
            variants.append((" (two passes)", True, 0, deferred_default))
        for suffix, fused, single, deferred in variants:
            cuda.SINGLE_PASS = single
            cuda.DEFERRED_MIN_PIXELS = deferred
            ms, spread, peak = measure(ours(request, fused), args.iters, args.warmup)
            r_ms = measure(raster_only(request), max(5, args.iters // 2), 1)[0] if fused else None
            c, img = ours(request, fused)()
            cuda.SINGLE_PASS = None
            cuda.DEFERRED_MIN_PIXELS = deferred_default
            m_entries = c.num_entries
            rows.append(Row(sc.name, f"ours {label}{suffix}", n, mp, ms, spread, r_ms, peak, peak / mp,
                            m_entries / request.num_pixels,
                            extra={"pairs": int(c.pair_view.numel()), "entries": m_entries}))
            if not suffix:
                results[(label, True)] = img.detach()
            del c, img

    if gsplat is not None:
        Ks, vms = sc.cameras.Ks.float(), sc.cameras.viewmats.float()

        def per_tile_cams(size):
            sel = [(v, x0, y0) for v, x0, y0, s in tiles if s == size]
            v = torch.tensor([t[0] for t in sel], device=dev)
            K = Ks[v].clone()
            K[:, 0, 2] -= torch.tensor([t[1] for t in sel], device=dev, dtype=K.dtype)
            K[:, 1, 2] -= torch.tensor([t[2] for t in sel], device=dev, dtype=K.dtype)
            return vms[v].contiguous(), K.contiguous()

        cams32, cams64 = per_tile_cams(32), per_tile_cams(64)

        def gs_tiles():
            colours.grad = None
            loss, outs = 0, []
            for (vm, K), size in ((cams32, 32), (cams64, 64)):
                img, _, _ = gsplat.rasterization(*geo, colours, vm, K, size, size, packed=True,
                                                 rasterize_mode="classic", sh_degree=None)
                loss = loss + img.sum()
                outs.append(img)
            loss.backward()
            return outs

        def gs_whole():
            colours.grad = None
            img, _, _ = gsplat.rasterization(*geo, colours, vms, Ks, args.width, args.height, packed=True,
                                             rasterize_mode="classic", sh_degree=None)
            img.sum().backward()
            return img

        ms, spread, peak = measure(gs_tiles, args.iters, args.warmup)
        o32, o64 = gs_tiles()
        ours_tiles = assemble_tiles(results[("tiles", True)], tiles)
        gs_list = list(o32) + list(o64)
        diff_t = max(float((a - b.detach()).abs().max()) for a, b in zip(ours_tiles, gs_list))
        rows.append(Row(sc.name, "gsplat per-tile", n, mp_tiles, ms, spread, None, peak, peak / mp_tiles,
                        max_abs_vs_gsplat=diff_t))
        ms, spread, peak = measure(gs_whole, max(5, args.iters // 2), 1)
        gw = gs_whole().detach()
        diff_w = float((results[("whole", True)] - gw).abs().max())
        rows.append(Row(sc.name, "gsplat whole", n, mp_whole, ms, spread, None, peak, peak / mp_whole,
                        max_abs_vs_gsplat=diff_w))
        for r in rows:
            if r.scene == sc.name and r.method.startswith("ours whole"):
                r.max_abs_vs_gsplat = diff_w
            if r.scene == sc.name and r.method.startswith("ours tiles"):
                r.max_abs_vs_gsplat = diff_t
        pictures[sc.name + " gsplat"] = gw[0].clamp(0, 1).cpu()
    pictures[sc.name + " ours"] = results[("whole", True)][0].clamp(0, 1).cpu()
    pictures[sc.name + " ours tiles"] = torch.cat(
        [t for t in assemble_tiles(results[("tiles", True)], tiles)[:16] if t.shape[0] == 32], 1
    ).clamp(0, 1).cpu()
    del colours
    torch.cuda.empty_cache()


# ----------------------------------------------------------------------------- output
def write_png(pictures: dict, path: Path) -> None:
    ims = []
    for name, im in pictures.items():
        a = (im.numpy() * 255).astype(np.uint8)
        if a.shape[1] > 800:  # downsample whole views 2x
            a = a[::2, ::2]
        ims.append(a)
    width = max(a.shape[1] for a in ims)
    canvas = np.concatenate([np.pad(a, ((0, 4), (0, width - a.shape[1]), (0, 0))) for a in ims], 0)
    with atomic_path(path) as tmp:
        try:
            from PIL import Image

            Image.fromarray(canvas).save(tmp, format="PNG")
        except ImportError:
            import cv2

            ok, buf = cv2.imencode(".png", canvas[..., ::-1])
            Path(tmp).write_bytes(buf.tobytes())


def print_table(rows: list[Row], device: str, args: Args) -> str:
    head = f"Tile rasterizer, forward + backward to the colours, on {device}\n" \
           f"tile batch: 160 tiles 32x32 + 40 tiles 64x64 from {args.views} views of {args.width}x{args.height}; " \
           f"median of {args.iters} runs\n"
    cols = ["scene", "method", "ms", "±", "raster ms", "Mpix", "ms/Mpix", "x vs gsplat", "peak MB", "MB/Mpix",
            "entries/px", "max|d| gsplat"]
    lines = []
    for r in rows:
        ref = next((q for q in rows if q.scene == r.scene and q.method == (
            "gsplat per-tile" if "tiles" in r.method or "per-tile" in r.method else "gsplat whole")), None)
        speed = f"{ref.ms / r.ms:.2f}" if ref else "-"
        lines.append([r.scene, r.method, f"{r.ms:.2f}", f"{r.ms_spread:.2f}",
                      f"{r.raster_ms:.2f}" if r.raster_ms is not None else "-", f"{r.mpix:.3f}",
                      f"{r.ms / r.mpix:.2f}", speed, f"{r.peak_mb:.0f}", f"{r.mb_per_mpix:.0f}",
                      f"{r.entries_per_px:.1f}" if r.entries_per_px is not None else "-",
                      f"{r.max_abs_vs_gsplat:.1e}" if r.max_abs_vs_gsplat is not None else "-"])
    widths = [max(len(c), *(len(l[i]) for l in lines)) for i, c in enumerate(cols)]
    fmt = lambda vals: " | ".join(v.ljust(w) for v, w in zip(vals, widths))  # noqa: E731
    text = head + fmt(cols) + "\n" + "-+-".join("-" * w for w in widths) + "\n" + "\n".join(fmt(l) for l in lines)
    print(text)
    return text


def main(args: Args) -> None:
    if not torch.cuda.is_available():
        raise InputError("bench/raster.py needs a CUDA GPU")
    from virgi_ns.raster import cuda

    ok, why = cuda.available()
    if not ok:
        raise InputError(f"the CUDA rasterizer is unavailable: {why}")
    dev = torch.device("cuda")
    device = torch.cuda.get_device_name(0)
    gsplat = None
    if args.gsplat:
        try:
            import gsplat as _gs

            gsplat = _gs
        except ImportError:
            print("gsplat not installed: its rows are skipped", file=sys.stderr)
    tiles, req = tile_batch(args)
    splat = args.splat
    if splat is None:
        for cand in (REPO / ".data" / "biker.compressed.ply", REPO.parent / "shared" / "data" / "splats" / "biker.compressed.ply"):
            if cand.exists():
                splat = cand
                break
    rows: list[Row] = []
    pictures: dict = {}
    makers = [lambda n=n: random_scene(n, args, dev) for n in args.sizes]
    if splat is not None:
        makers.append(lambda: splat_scene(splat, args, dev))
    from rich.progress import Progress

    with Progress(transient=True) as prog:
        task = prog.add_task("scenes", total=len(makers))
        for make in makers:
            t0 = time.time()
            sc = make()
            run_scene(sc, args, tiles, req, gsplat, rows, pictures)
            print(f"{sc.name}: {time.time() - t0:.1f} s", file=sys.stderr)
            del sc
            torch.cuda.empty_cache()
            prog.advance(task)
    args.out.mkdir(parents=True, exist_ok=True)
    write_png(pictures, args.out / "renders.png")
    text = print_table(rows, device, args)
    payload = {"device": device, "torch": torch.__version__, "args": {k: str(v) for k, v in asdict(args).items()},
               "command": " ".join(sys.argv), "rows": [asdict(r) for r in rows], "table": text}
    with atomic_path(args.out / "results.json") as tmp:
        Path(tmp).write_text(json.dumps(payload, indent=1))


def entrypoint() -> None:
    import tyro

    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
