"""How far one edit fit moves with its seed or with a perturbation too small to see, and which figure a
fit knows about itself tells a good fit from a bad one. On one row of the evaluation set (trained as
``bench/edit.py`` trains it, reused when present), the same edit is fitted with seeds 0..N-1 and, at
seed 0, with the edited image moved by Gaussian noise of ``--noise`` (1e-6: far below one 8-bit
level, and too small to change which pixels count as changed, which is checked). Each fit's held-out
miss and propagation are set beside its own figures: the last step's loss, the loss on every pixel
set (``EditEngine.fit_loss``) and its PSNR against the edited image on the changed pixels; the rank
correlation of each with the held-out figures is printed last.

    python bench/fit_spread.py --scene syn_duck_beak --colour-steps 300 --out bench_out/fit_spread

Runs on the CPU (the torch reference) or a GPU; writes ``fit_spread.json``."""

from __future__ import annotations

import json
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import torch
import tyro
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))

import edit as bench_edit  # noqa: E402  (bench/edit.py: the set's training and edit view)

from virgi_ns.bench.evalset import SYNTHETIC_SIZE, find  # noqa: E402
from virgi_ns.errors import InputError, atomic_path, cli_entry  # noqa: E402

console = Console(width=160)


@dataclass
class Args:
    scene: str = "syn_duck_beak"
    """A row of the evaluation set (``bench/edit.py``'s names)."""
    data: Path = bench_edit.Args.data
    """The real captures (for a real row)."""
    train_out: Path = Path("bench_out/edit_runs")
    """Trained runs (reused when present) and the synthetic captures."""
    out: Path = Path("bench_out/fit_spread")
    seed: int = 63
    """Training seed."""
    colour_steps: int = bench_edit.COLOUR_STEPS
    geometry_steps: int = bench_edit.GEOMETRY_STEPS
    synthetic_size: tuple[int, int, int, float] = SYNTHETIC_SIZE
    seeds: int = 6
    """Fits with EditConfig.seed 0..N-1."""
    perturbations: int = 3
    """More fits at seed 0, each with the edited image moved by fresh noise."""
    noise: float = 1e-6
    """Standard deviation of that noise (the image is in [0, 1])."""
    steps: Optional[int] = None
    """Steps of each fit (default: the engine's)."""
    lr_schedule: str = "constant"
    """EditConfig.lr_schedule of each fit (the constant rate: the default when this bench was written)."""
    lr_hold: float = 0.0
    """EditConfig.lr_hold of each fit, with the cosine (0: the decay from the first step, as the JSONs
    RESULTS cites were made)."""


def spearman(a: List[float], b: List[float]) -> float:
    """Rank correlation of two equally long lists (ties broken by order; NaN with fewer than 3)."""
    if len(a) < 3:
        return float("nan")

    def ranks(v: List[float]) -> List[float]:
        r = [0.0] * len(v)
        for k, i in enumerate(sorted(range(len(v)), key=lambda i: v[i])):
            r[i] = float(k)
        return r

    return statistics.correlation(ranks(a), ranks(b))


OWN = {"final_l1": "last step's loss", "fit_l1": "loss on every set", "edit_fit_changed_psnr": "PSNR vs edited"}
HELD_OUT = ("miss_psnr", "propagation_psnr")


def correlations(fits: List[dict]) -> dict:
    """For each figure a fit knows about itself, its rank correlation with each held-out figure. A
    loss is negated, so that +1 means: the better by its own figure, the better held out."""
    out = {}
    for own in OWN:
        sign = 1.0 if own.endswith("psnr") else -1.0
        mine = [sign * f[own] for f in fits]
        out[own] = {h: spearman(mine, [f[h] for f in fits]) for h in HELD_OUT}
    return out


def main(args: Args) -> None:
    from virgi_ns.edit.engine import EditConfig, EditEngine

    if args.seeds < 1 or args.perturbations < 0 or args.noise <= 0:
        raise InputError("--seeds must be >= 1, --perturbations >= 0 and --noise > 0")
    scene = find([args.scene])[0]
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    train_args = bench_edit.Args(scenes=[args.scene], data=args.data, train_out=args.train_out, seed=args.seed,
                                 colour_steps=args.colour_steps, geometry_steps=args.geometry_steps,
                                 synthetic_size=args.synthetic_size)
    b, _, _ = bench_edit.scene_bench(train_args, scene, {})
    edited, original = b.edited_image(scene.rule, "photo"), b.original("photo")
    b.scene.precompute_features()
    changed = int(EditEngine(b.scene, b.edit_camera, edited, cfg=EditConfig(), original=original)._changed.sum())
    g = torch.Generator().manual_seed(7)
    runs = [(f"seed {s}", s, edited) for s in range(args.seeds)]
    for k in range(args.perturbations):
        noise = args.noise * torch.randn(edited.shape, generator=g).to(edited)
        runs.append((f"seed 0, noise {k + 1}", 0, (edited + noise).clamp(0, 1)))
    fits = []
    for name, seed, image in runs:
        eng_changed = int(EditEngine(b.scene, b.edit_camera, image, cfg=EditConfig(seed=seed),
                                     original=original)._changed.sum())
        if eng_changed != changed:
            raise InputError(f"--noise {args.noise} changes which pixels count as changed ({eng_changed} against "
                             f"{changed}): use a smaller one")
        edit, t = b.fit(image, args.steps, None, 1, original, seed=seed, lr_schedule=args.lr_schedule,
                     lr_hold=args.lr_hold)
        m = b.measure(edit, scene.rule, lpips=False, edited=image)[0]["mean"]
        fits.append({"fit": name, "seed": seed, **{k: m[k] for k in HELD_OUT}, "truth_psnr": m.get("truth_psnr"),
                     "edit_fit_changed_psnr": m["edit_fit_changed_psnr"], "final_l1": t["final_l1"],
                     "fit_l1": t["fit_l1"]})
        console.print(f"{name}: miss {m['miss_psnr']:.2f}, propagation {m['propagation_psnr']:.2f}")
    corr = correlations(fits)
    table = Table(title=f"{args.scene} (training seed {args.seed}): one edit fitted {len(fits)} times")
    for c in ("fit", "miss", "propagation", "last step's loss", "loss on every set", "PSNR vs edited"):
        table.add_column(c)
    for f in fits:
        table.add_row(f["fit"], f"{f['miss_psnr']:.2f}", f"{f['propagation_psnr']:.2f}", f"{f['final_l1']:.5f}",
                      f"{f['fit_l1']:.5f}", f"{f['edit_fit_changed_psnr']:.2f}")
    console.print(table)
    for own, c in corr.items():
        console.print(f"rank correlation of the {OWN[own]} (better = higher) with the held-out miss "
                      f"{c['miss_psnr']:+.2f}, propagation {c['propagation_psnr']:+.2f}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "fit_spread.json"
    result = {"device": torch.cuda.get_device_name() if dev == "cuda" else "cpu", "commit": bench_edit._commit(),
              "source_digest": bench_edit._source(),
              "scene": args.scene, "training_seed": args.seed, "colour_steps": args.colour_steps,
              "synthetic_size": list(args.synthetic_size), "noise": args.noise, "changed_pixels": changed,
              "steps": EditConfig().steps if args.steps is None else args.steps, "lr_schedule": args.lr_schedule,
              "lr_hold": args.lr_hold,
              "fits": fits, "rank_correlations": corr}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    console.print(f"wrote {path}")


def entry() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entry()
