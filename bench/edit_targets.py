"""Benchmark: how close each ``changed_target`` puts the edit's target to the exact one, on real renders.

The edit engine fits the pixels a user changed in a photo to a target built from the photo, its
edited copy and the model's render of that view (``EditConfig.changed_target``). The exact target
is the user's change applied to the render itself; for the evaluation set's rules it is known: the
rule on the render. ``bench/edit.py --dump-targets`` writes, per scene, the edit view's photo,
render, the rule on each (``SCENE_targets.npz``); this script builds every kind of target from the
photo, edited photo and render with the engine's own function (``changed_pixels_target``) and
prints its PSNR against the exact target on the changed pixels, without fitting anything. CPU is
enough.

    python bench/edit.py --data ../shared/data --out bench_out/edit --dump-targets --pictures 0
    python bench/edit_targets.py --dumps bench_out/edit --out bench_out/edit_targets.json
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from virgi_ns.errors import InputError, atomic_path, cli_entry

KINDS = ("edited", "change", "map", "affine")


@dataclass
class Args:
    dumps: Path = Path("bench_out/edit")
    """A folder of ``SCENE_targets.npz`` files (``bench/edit.py --dump-targets``)."""
    out: Path = Path("bench_out/edit_targets.json")
    kinds: List[str] = field(default_factory=lambda: list(KINDS))
    """The ``changed_target`` kinds to build."""


def target_psnr(arrays: dict, kinds: List[str]) -> dict:
    """Per kind, PSNR of its target against the exact target on the changed pixels; with the
    changed share and the map's answered share."""
    from virgi_ns.bench.recolor import psnr
    from virgi_ns.edit.engine import EditConfig, changed_pixels_target

    photo, render, edited, exact = (torch.from_numpy(arrays[k].astype(np.float32))
                                    for k in ("photo", "render", "edited", "exact"))
    changed = (edited - photo).abs().amax(-1) > EditConfig().unchanged_tol
    if not bool(changed.any()):
        raise InputError("the edited photo does not differ from the photo")
    row = {"changed_fraction": float(changed.float().mean())}
    for kind in kinds:
        target, answered = changed_pixels_target(EditConfig(changed_target=kind), render, edited, photo, changed)
        row[kind] = psnr(target, exact, changed)
        if answered is not None:
            row["map_answered"] = answered
    return row


def main(args: Args) -> None:
    files = sorted(args.dumps.glob("*_targets.npz"))
    if not files:
        raise InputError(f"no *_targets.npz under {args.dumps} (bench/edit.py --dump-targets writes them)")
    rows = {}
    for f in files:
        with np.load(f) as z:
            rows[f.name[: -len("_targets.npz")]] = target_psnr({k: z[k] for k in z.files}, args.kinds)
    t = Table(title="target PSNR against the exact target (the rule on the render), changed pixels")
    for c in ("scene", "changed", *args.kinds):
        t.add_column(c)
    for name, r in rows.items():
        t.add_row(name, f"{r['changed_fraction']:.1%}", *(f"{r[k]:.2f}" for k in args.kinds))
    Console(width=160).print(t)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps({"dumps": str(args.dumps), "kinds": args.kinds, "scenes": rows}, indent=1))
    print(f"wrote {args.out}")


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
