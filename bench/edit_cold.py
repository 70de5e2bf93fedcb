"""The first edit of a fresh process against the next ones, part by part, on the edit benchmark's
1M-Gaussian 1280x720 scene (GPU): creating the CUDA context, loading our extension, the view's
contributions (three times), then three whole edits (a fresh engine each: set-up, steps, the engine
built and fitted, and the wall, its release included).
Run it as a fresh interpreter; writes ``cold.json`` and prints it. ``--through-build-tools`` loads
the extension as before its stamp, through torch's build tools (the baseline of the load).
``--warm-up`` runs :mod:`virgi_ns.edit.warmup` while the scene is built, as ``virgi-edit apply`` does
while it loads the run, and waits for it before the first edit.

    PYTHONPATH=. python bench/edit_cold.py bench_out/edit_cold [--through-build-tools] [--warm-up]
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from edit import million_scene  # noqa: E402

from virgi_ns.edit import warmup  # noqa: E402
from virgi_ns.edit.engine import EditEngine  # noqa: E402
from virgi_ns.raster import Request, cuda  # noqa: E402


def _ms(t0: float) -> float:
    torch.cuda.synchronize()
    return round((time.perf_counter() - t0) * 1e3, 1)


def main(out: Path, through_build_tools: bool, warm_up: bool = False) -> None:
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"device": torch.cuda.get_device_name(), "through_build_tools": through_build_tools,
                 "warm_up": warm_up}
    t0 = time.perf_counter()
    torch.zeros(1, device="cuda")
    res["context_ms"] = _ms(t0)
    t0 = time.perf_counter()
    if through_build_tools:
        cuda._MODULE = cuda.build()
    cuda.available()
    res["load_extension_ms"] = _ms(t0)
    if warm_up:  # as virgi-edit apply: the warm-up runs while the scene is built, and is waited for
        t_warm = time.perf_counter()
        warmup.start("cuda")
    scene, cams = million_scene()
    scene.precompute_features()
    if warm_up:
        res["scene_ms"] = _ms(t_warm)
        warmup.wait()
        res["warm_up_wait_ms"] = _ms(t_warm) - res["scene_ms"]
        res["warm_up_ms"] = round(1e3 * (warmup.last_seconds or 0.0), 1)
        res["warm_up_error"] = warmup.last_error
    view = cams.to("cuda", torch.float32)
    for i in range(3):
        t0 = time.perf_counter()
        _ = scene.contributions(view, Request.whole_images(view)).pair  # deferred lists build on access
        res[f"contributions{i + 1}_ms"] = _ms(t0)
    edited = torch.rand(720, 1280, 3, generator=torch.Generator(device="cuda").manual_seed(1), device="cuda")
    for i in range(3):
        t0 = time.perf_counter()
        engine = EditEngine(scene, cams, edited)
        _, t = engine.fit()
        fitted = _ms(t0)
        del engine  # its recorded steps and buffers go back to the allocator
        res[f"edit{i + 1}_ms"] = {"setup": round(t.setup_s * 1e3, 1), "steps": round(t.steps_s * 1e3, 1),
                                  "fit": fitted, "wall": _ms(t0)}
    print(json.dumps(res))
    (out / "cold.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]), "--through-build-tools" in sys.argv[2:], "--warm-up" in sys.argv[2:])
