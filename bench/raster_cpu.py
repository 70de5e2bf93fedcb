"""Benchmark: the torch reference rasterizer on a CPU, one whole view of a trained run, against the
same module at another git revision (the baseline), in one process.

The baseline's ``virgi_ns/raster/reference.py`` is read with ``git show REV:...`` and loaded as its
own module beside the current one; both rasterize the same view (``--camera-index``) of the run's
Gaussians in alternation, after one unmeasured call each. Their contribution lists are compared
field by field (bit for bit, then the largest difference), so a speed-up that changes a number shows.
Prints a table and writes ``raster_cpu.json`` in ``--out``:

    python bench/raster_cpu.py --load-config demo_out/run/config.yml --camera-index 16 --baseline e7cfc99
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

import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FIELDS = ("pair_view", "pair_gaussian", "pair_depth", "pixel", "pair", "weight", "transmittance", "valid")


@dataclass
class Args:
    load_config: Path
    """The trained run's config.yml."""
    camera_index: int = 16
    """The training view rasterized."""
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


def main(a: Args) -> dict:
    from rich.console import Console

    from virgi_ns.cli.edit import resolve_camera
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.raster import Request, reference

    a.out.mkdir(parents=True, exist_ok=True)
    if a.threads:
        torch.set_num_threads(a.threads)
    base = _baseline_module(a.baseline, a.out)
    run = open_run(a.load_config, Console(stderr=True))

    class Pick:  # what resolve_camera reads
        camera_index, image_name, camera_json = a.camera_index, None, None

    cams, where = resolve_camera(run, Pick)
    scene = FrozenScene.from_model(run.model)
    inputs = (scene.means.cpu(), scene.quats.cpu(), scene.scales.cpu(), scene.opacities.cpu(), cams.to("cpu"),
              Request.whole_images(cams))
    impls = {f"baseline ({a.baseline})": base.rasterize, "current": reference.rasterize}
    outs, times = {}, {k: [] for k in impls}
    with torch.no_grad():
        for name, fn in impls.items():
            outs[name] = fn(*inputs)  # unmeasured
        for _ in range(a.repeats):
            for name, fn in impls.items():
                t = time.perf_counter()
                fn(*inputs)
                times[name].append(time.perf_counter() - t)
    names = list(impls)
    med = {k: statistics.median(v) for k, v in times.items()}
    W, H = int(cams.widths[0]), int(cams.heights[0])
    result = {"args": {k: str(v) for k, v in asdict(a).items()}, "view": where, "size": [W, H],
              "gaussians": int(scene.means.shape[0]), "entries": int(outs["current"].weight.numel()),
              "threads": torch.get_num_threads(), "seconds": times, "median_s": med,
              "speedup": med[names[0]] / med[names[1]], "same_output": _compare(outs[names[1]], outs[names[0]])}
    print(f"{where}, {W}x{H}, {result['gaussians']:,} Gaussians, {result['entries']:,} entries, "
          f"{result['threads']} threads")
    print("| rasterizer | median | calls |\n| --- | --- | --- |")
    for k in names:
        print(f"| {k} | {med[k]:.3f} s | {', '.join(f'{t:.2f}' for t in times[k])} |")
    print(f"speed-up: {result['speedup']:.2f}x; output against the baseline: "
          + ", ".join(f"{k} {v}" for k, v in result["same_output"].items()))
    (a.out / "raster_cpu.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
