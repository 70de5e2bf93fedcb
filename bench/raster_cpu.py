"""Benchmark: the torch reference rasterizer on a CPU, one whole view, against the same module at another
git revision (the baseline), in one process.

The baseline's ``virgi_ns/raster/reference.py`` is read with ``git show REV:...`` and loaded as its
own module beside the current one; both rasterize the same view in alternation, after one unmeasured
call each. Their contribution lists are compared field by field (bit for bit, else the largest
difference), so a speed-up that changes a number shows. The views: one training view of a trained run
(``--load-config``, ``--camera-index``) and/or random scenes (``--random N SMIN SMAX``: N Gaussians
uniform in [-1, 1]^3, scales log-uniform in [SMIN, SMAX], one 800x532 camera 3.2 away, f = 640 px),
which span Gaussians from sub-pixel to tens of pixels wide. Prints a table and writes
``raster_cpu.json`` in ``--out``:

    python bench/raster_cpu.py --load-config demo_out/run/config.yml --camera-index 16 --baseline e7cfc99 \\
        --random 300000 0.0002 0.0008 300000 0.001 0.004 100000 0.01 0.05
"""

from __future__ import annotations

import importlib.util
import json
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FIELDS = ("pair_view", "pair_gaussian", "pair_depth", "pixel", "pair", "weight", "transmittance", "valid")


@dataclass
class Args:
    load_config: Optional[Path] = None
    """A trained run's config.yml: one of its training views is timed."""
    camera_index: int = 16
    """That training view."""
    random: List[Tuple[int, float, float]] = ()  # type: ignore[assignment]
    """Random scenes, each N SMIN SMAX, one after another after one flag."""
    baseline: str = "HEAD"
    """The git revision whose reference rasterizer is the baseline."""
    repeats: int = 5
    """Measured calls of each (alternated); the table gives medians."""
    threads: int = 0
    """torch threads (0: torch's default)."""
    out: Path = Path("bench_out/raster_cpu")


def _baseline_module(rev: str, out: Path):
    text = subprocess.run(["git", "show", f"{rev}:virgi_ns/raster/reference.py"], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout
    path = out / f"reference_{rev}.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location(f"reference_{rev}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _compare(a, b) -> dict:
    out = {}
    for k in FIELDS:
        x, y = getattr(a, k), getattr(b, k)
        if x.shape != y.shape:
            out[k] = f"shapes differ {tuple(x.shape)} / {tuple(y.shape)}"
        elif bool((x == y).all()):
            out[k] = "identical"
        else:
            out[k] = f"max difference {float((x.double() - y.double()).abs().max()):.3g}"
    return out


def _run_view(a: Args):
    """(description, inputs) of the run's training view."""
    from rich.console import Console

    from virgi_ns.cli.edit import resolve_camera
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.raster import Request

    run = open_run(a.load_config, Console(stderr=True))

    class Pick:  # what resolve_camera reads
        camera_index, image_name, camera_json = a.camera_index, None, None

    cams, where = resolve_camera(run, Pick)
    scene = FrozenScene.from_model(run.model)
    cams = cams.to("cpu")
    return where, (scene.means.cpu(), scene.quats.cpu(), scene.scales.cpu(), scene.opacities.cpu(), cams,
                   Request.whole_images(cams))


def _random_view(n: int, smin: float, smax: float, seed: int = 0):
    from virgi_ns.raster import Cameras, Request

    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen) * 2 - 1
    lo, hi = torch.log(torch.tensor(smin)), torch.log(torch.tensor(smax))
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=gen))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=gen)
    W, H, f = 800, 532, 640.0
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])[None]
    viewmat = torch.eye(4)[None].clone()
    viewmat[0, 2, 3] = 3.2
    cams = Cameras(K, viewmat, torch.tensor([W]), torch.tensor([H]))
    return f"random, scales {smin:g}-{smax:g}", (means, quats, scales, opacities, cams, Request.whole_images(cams))


def _time(view: str, inputs, impls: dict, repeats: int) -> dict:
    outs, times = {}, {k: [] for k in impls}
    with torch.no_grad():
        for name, fn in impls.items():
            outs[name] = fn(*inputs)  # unmeasured
        for _ in range(repeats):
            for name, fn in impls.items():
                t = time.perf_counter()
                fn(*inputs)
                times[name].append(time.perf_counter() - t)
    base, cur = list(impls)
    med = {k: statistics.median(v) for k, v in times.items()}
    cams = inputs[4]
    return {"view": view, "size": [int(cams.widths[0]), int(cams.heights[0])], "gaussians": int(inputs[0].shape[0]),
            "entries": int(outs[cur].weight.numel()), "seconds": times, "median_s": med,
            "speedup": med[base] / med[cur], "same_output": _compare(outs[cur], outs[base])}


def main(a: Args) -> dict:
    from virgi_ns.raster import reference

    if a.load_config is None and not a.random:
        raise SystemExit("nothing to time: give --load-config and/or --random N SMIN SMAX")
    a.out.mkdir(parents=True, exist_ok=True)
    if a.threads:
        torch.set_num_threads(a.threads)
    impls = {f"baseline ({a.baseline})": _baseline_module(a.baseline, a.out).rasterize, "current": reference.rasterize}
    views = ([_run_view(a)] if a.load_config is not None else []) + [_random_view(*r) for r in a.random]
    rows = [_time(view, inputs, impls, a.repeats) for view, inputs in views]
    base, cur = list(impls)
    print(f"{torch.get_num_threads()} threads; medians of {a.repeats}, alternated")
    print(f"| view | Gaussians | entries | {base} | current | speed-up | output |\n| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        same = all(v == "identical" for v in r["same_output"].values())
        print(f"| {r['view']} ({r['size'][0]}x{r['size'][1]}) | {r['gaussians']:,} | {r['entries']:,} | "
              f"{r['median_s'][base]:.3f} s | {r['median_s'][cur]:.3f} s | {r['speedup']:.2f}x | "
              + ("identical" if same else json.dumps(r["same_output"])) + " |")
    result = {"args": {k: str(v) for k, v in asdict(a).items()}, "threads": torch.get_num_threads(), "rows": rows}
    (a.out / "raster_cpu.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
