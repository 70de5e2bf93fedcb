"""Benchmark (CPU): PlayCanvas ``.sog`` writing time and round-trip fidelity.

1. ``--gaussians`` random Gaussians of SH degree 3 (the worst case for the SH palette's k-means:
   every Gaussian different) written with ``save_sog`` (what ``virgi-export --out x.sog`` runs) and
   read back: wall and CPU seconds, file size.
2. A real splat (``--splat``, default ``../shared/data/splats/biker.compressed.ply``; skipped when
   absent): ``.sog`` round trip, the error per attribute (RMS, 99th percentile, max) against the
   source in file order, and both rendered by ``virgi-render``'s path (reference rasterizer, SH
   colours) from ``--views`` cameras circling the splat's median at ``--size``: PSNR of the
   ``.sog`` against the source.

    python bench/sog.py --out bench/results/sog_cpu.json
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from virgi_ns.cli.render import render_image
from virgi_ns.gaussians import Gaussians
from virgi_ns.io import load_splat, save_sog
from virgi_ns.io.camera_json import CameraSpec
from virgi_ns.io.sog import sog_order


@dataclass
class Args:
    gaussians: int = 1_000_000
    splat: Path = Path(__file__).resolve().parents[2] / "shared" / "data" / "splats" / "biker.compressed.ply"
    views: int = 4
    size: tuple[int, int] = (160, 120)
    out: Path = Path("bench_out/sog.json")


def timing(n: int, tmp: Path) -> dict:
    gen = torch.Generator().manual_seed(0)
    r = lambda *s: torch.randn(*s, generator=gen)  # noqa: E731
    g = Gaussians(r(n, 3) * 3, r(n, 3) - 4, r(n, 4), r(n) * 2, r(n, 16, 3) * 0.3)
    load0 = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    save_sog(g, tmp / "random.sog")
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    read = time.perf_counter()
    load_splat(tmp / "random.sog")
    read = time.perf_counter() - read
    return {"gaussians": n, "sh_degree": 3, "write_wall_s": wall, "write_cpu_s": cpu, "read_wall_s": read,
            "bytes": (tmp / "random.sog").stat().st_size, "cpus": os.cpu_count(),
            "load_average": [load0, os.getloadavg()[0]]}


def orbit(means: np.ndarray, views: int, size: tuple[int, int]) -> list[CameraSpec]:
    """Cameras on a ring around the median, 1.5x the 90th-percentile radius out, looking at it (INRIA axes:
    y down, so 'up' is -y)."""
    med = np.median(means, 0)
    radius = 1.5 * np.percentile(np.linalg.norm(means - med, axis=1), 90)
    w, h = size
    out = []
    for k in range(views):
        a = 2 * math.pi * k / views
        eye = med + radius * np.array([math.cos(a), -0.3, math.sin(a)])
        f = (med - eye) / np.linalg.norm(med - eye)
        right = np.cross(f, [0.0, -1.0, 0.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(f, right), f])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        out.append(CameraSpec(w, h, 0.6 * w, 0.6 * w, w / 2, h / 2, w2c))
    return out


def real_splat(path: Path, tmp: Path, views: int, size: tuple[int, int]) -> dict:
    src = load_splat(path)
    wall = time.perf_counter()
    save_sog(src, tmp / "real.sog")
    wall = time.perf_counter() - wall
    got = load_splat(tmp / "real.sog")
    ref = src.index(torch.from_numpy(sog_order(src.means)))
    errors = {}
    for name, a, b in (("position", got.means, ref.means), ("log_scale", got.scales, ref.scales),
                       ("f_dc", got.sh[:, 0], ref.sh[:, 0]),
                       ("opacity", torch.sigmoid(got.opacities), torch.sigmoid(ref.opacities)),
                       ("sh_rest", got.sh[:, 1:], ref.sh[:, 1:])):
        e = (a - b).abs().double().flatten().numpy()
        if e.size:
            errors[name] = {"rms": float(np.sqrt((e**2).mean())), "p99": float(np.percentile(e, 99)),
                            "max": float(e.max())}
    qa, qb = got.normalized_quats().double(), ref.normalized_quats().double()
    angle = np.degrees(2 * np.arccos((qa * qb).sum(1).abs().clamp(0, 1).numpy()))
    errors["rotation_deg"] = {"rms": float(np.sqrt((angle**2).mean())), "p99": float(np.percentile(angle, 99)),
                              "max": float(angle.max())}
    psnr = []
    for spec in orbit(ref.means.double().numpy(), views, size):
        a, b = (np.clip(render_image(x, spec, "reference"), 0, 1) for x in (ref, got))
        psnr.append(float(-10 * math.log10(max(float(((a - b) ** 2).mean()), 1e-12))))
    return {"splat": path.name, "gaussians": len(src), "sh_degree": src.sh_degree, "write_wall_s": wall,
            "bytes": (tmp / "real.sog").stat().st_size, "source_bytes": path.stat().st_size, "errors": errors,
            "views": views, "size": list(size), "psnr": psnr}


def main(args: Args) -> dict:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result = {"timing": timing(args.gaussians, tmp)}
        print(json.dumps(result["timing"], indent=1))
        if args.splat.is_file():
            result["real"] = real_splat(args.splat, tmp, args.views, args.size)
            print(json.dumps(result["real"], indent=1))
        else:
            print(f"no real splat at {args.splat}; skipped")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
