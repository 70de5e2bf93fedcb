"""Where a warm edit's time goes, part by part, on the edit benchmark's 1M-Gaussian 1280x720 scene (GPU).

Per configuration: the set-up's parts (the view's contributions, the pixel sets, the whole set-up),
the first fit's steps (one eager step and the recording of the CUDA graphs included), a warm
retarget and a second fit that only replays the recorded steps (per step), and a CUDA profile of
five eager steps by kernel. Writes ``breakdown.json`` and prints the tables.

    PYTHONPATH=. python bench/edit_breakdown.py bench_out/edit_breakdown
"""
from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from edit import million_scene  # noqa: E402

import virgi_ns.edit.engine as E  # noqa: E402
import virgi_ns.edit.pixels as PX  # noqa: E402

T: dict = {}


def timed(name: str, fn):
    """``fn`` with its synchronised wall time appended to ``T[name]``."""
    def wrap(*a, **k):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        r = fn(*a, **k)
        torch.cuda.synchronize()
        T.setdefault(name, []).append(time.perf_counter() - t0)
        return r
    return wrap


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    scene, cams = million_scene()
    scene.precompute_features()
    edited = torch.rand(720, 1280, 3, generator=torch.Generator(device="cuda").manual_seed(1), device="cuda")
    # wrap the set-up's parts
    scene.contributions = timed("contributions", scene.contributions)
    scene.gaussian_features = timed("gaussian_features", scene.gaussian_features)
    E.pixel_batches = timed("pixel_batches", E.pixel_batches)
    E.composite = timed("current_composite", E.composite)
    E.EditEngine._setup_view = timed("setup_view", E.EditEngine._setup_view)
    E.EditEngine._set_target = timed("set_target", E.EditEngine._set_target)
    E.EditEngine._fit_graphed = timed("fit_graphed", E.EditEngine._fit_graphed)
    res: dict = {}
    for label, kw in [("segment/csr32", {"batch_composite": "segment/csr32"}),
                      ("fused_atomics", {"batch_composite": "fused_atomics"}),
                      ("fused", {"batch_composite": "fused"})]:
        cfg = lambda: E.EditConfig(**kw)  # noqa: E731
        with torch.enable_grad():
            for _ in range(2):
                E.EditEngine(scene, cams, edited, cfg=cfg()).fit()
            T.clear()
            tot = []
            for _ in range(3):
                eng = E.EditEngine(scene, cams, edited, cfg=cfg())
                _, t = eng.fit()
                tot.append((t.setup_s, t.steps_s))
            # replay only: the same engine again (graphs kept)
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            eng._set_target(edited, None, None, warm=True)
            torch.cuda.synchronize()
            t1 = time.perf_counter()
            _, t2 = eng.fit()
            n = eng.cfg.steps
            # one eager step, profiled by kernel
            from torch.profiler import ProfilerActivity, profile
            eng.step(0)
            torch.cuda.synchronize()
            with profile(activities=[ProfilerActivity.CUDA]) as prof:
                for _ in range(5):
                    eng.step(0)
                torch.cuda.synchronize()
            ktab = prof.key_averages().table(sort_by="cuda_time_total", row_limit=14, max_name_column_width=70)
        row = {k: statistics.median(v) * 1e3 for k, v in T.items()}
        row.update({"setup_ms": statistics.median(a for a, _ in tot) * 1e3,
                    "steps_ms": statistics.median(b for _, b in tot) * 1e3,
                    "warm_retarget_ms": (t1 - t0) * 1e3, "replay_steps_ms": t2.steps_s * 1e3,
                    "replay_per_step_ms": t2.steps_s * 1e3 / n,
                    "batch_pixels": int(eng.batches[0].target.shape[0])})
        res[label] = row
        print(label, json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}))
        print(ktab)
    (out / "breakdown.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
