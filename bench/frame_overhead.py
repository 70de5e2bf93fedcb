"""The Python overhead of a viewer frame outside gsplat, on a CPU: per stage, microseconds per call
(median of ``--calls`` calls after a warm-up), on the tests' tiny scene (240 Gaussians), with gsplat's
projection and rasterization replaced by stand-ins that return fixed tensors (so ``raster`` and ``frame`` are the Python
around the pass). Stages as ``bench/render.py`` names them; ``gated`` is a gate keeping half the
Gaussians, ``matte`` one keeping none.

Only the host's share is measured: on a GPU each launch also costs its latency, and ``camera``
waits there for one copy to the host. For comparing the code's overhead before and after a change.

    PYTHONPATH=. python bench/frame_overhead.py
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))
warnings.filterwarnings("ignore")


def _us(fn, calls: int) -> float:
    for _ in range(20):
        fn()
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e6 * statistics.median(times)


def main(calls: int = 2000) -> None:
    torch.set_num_threads(1)
    from test_model_train import build, train
    from virgi_scene import make_scene

    from render import frame_keys  # bench/render.py: the stage "keys" as it times it

    scene = make_scene(Path(tempfile.mkdtemp()))
    _, pipeline, optimizers, cbs = build(scene, steps=2)
    train(pipeline, optimizers, cbs, 2)
    pipeline.eval()
    model = pipeline.model
    model.build_specular_gate(model._train_cameras_fn())
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    n = model.num_points
    import virgi_ns.nerfstudio.render_path as rp

    img, acc = torch.zeros(40, 48, 4), torch.ones(40, 48, 1)
    model._renders_with_gsplat = lambda: True
    rp.project = lambda *a: None  # gsplat's pass: fixed outputs, the Python around it as it is
    rp.rasterize = lambda projection, colours, backgrounds, expected_depth: (img, acc)
    median = float(model.spec_magnitude.median())
    print(f"{n} Gaussians; microseconds per call (median of {calls})")
    print(f"{'frame':8s}" + "".join(f"{k:>10s}" for k in ("camera", "keys", "colours", "raster", "frame")))
    with torch.no_grad():
        for name, t in (("gated", median), ("matte", float("inf"))):
            model.config.gate_threshold = t
            view = model.view_of(cam)
            for _ in range(3):
                cols = model.view_colours(view, True, transient=True)

            def raster():
                out = model.render_view(view, cols)
                return out["rgb"], out["depth"]

            def frame():
                out = model.get_outputs_for_camera(cam)
                return out["rgb"], out["depth"]

            row = [_us(lambda: model.view_of(cam), calls), _us(lambda: frame_keys(model, True), calls),
                   _us(lambda: model.view_colours(view, True, transient=True), calls), _us(raster, calls),
                   _us(frame, calls)]
            print(f"{name:8s}" + "".join(f"{v:10.1f}" for v in row))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2000)
