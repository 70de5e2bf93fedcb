"""``virgi-export --load-config CFG --out OUT.ply``: bake a trained VIRGi run into a standard splat
(INRIA ``.ply``, ``.spz`` or PlayCanvas ``.sog``).

The run's edits (``<run>/edits``, as the viewer panel and the edit tools keep them) and its
specular strength are applied unless ``--no-edits``; ``--specular-strength`` overrides ``k``.
Colours are fitted to SH degree 3 per Gaussian (:mod:`virgi_ns.nerfstudio.export`); geometry is put back in
the capture's original frame (the inverse of the run's ``dataparser_transforms.json``), so the file lines up with the source data and any splat imported from it.
The run is opened from its files when it can be (:func:`virgi_ns.nerfstudio.runs.open_run`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from virgi_ns.cli import run_command
from virgi_ns.errors import InputError


@dataclass
class Export:
    """Bake a VIRGi run (with its edits) into an INRIA .ply (SH degree 3), .spz or .sog."""

    load_config: Path
    """The run's config.yml."""
    out: Path
    """Output splat: .ply (INRIA layout), .spz or .sog (PlayCanvas SOG version 2, zip)."""
    specular_strength: Optional[float] = None
    """k, the factor on the specular colour (default: the edit stack's, else 1; 0 removes highlights)."""
    no_edits: bool = False
    """Export the base colours, ignoring the run's edits."""
    directions: int = 64
    """Sphere directions sampled per Gaussian (added to the training cameras' directions)."""
    frame: Literal["capture", "dataparser"] = "capture"
    """capture: the capture's original frame (lines up with the source data); dataparser: the run's frame."""


def _validate(args: Export) -> None:
    from virgi_ns.nerfstudio.export import check_output_path

    check_output_path(args.out)
    if args.directions < 0:
        raise InputError(f"--directions must be >= 0, got {args.directions}")
    k = args.specular_strength
    if k is not None and not (k >= 0.0 and k < float("inf")):
        raise InputError(f"--specular-strength must be a finite number >= 0, got {k}")
    if not args.load_config.is_file():
        raise InputError(f"no such config: {args.load_config}")


def run(args: Export) -> str:
    """Do the export; returns the one-line summary."""
    _validate(args)
    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.edit.stack import EditStack
    from virgi_ns.nerfstudio.export import BakeConfig, bake, write_splat
    from virgi_ns.nerfstudio.frames import CaptureFrame

    console = Console(stderr=True)
    with console.status(f"loading {args.load_config}"):
        opened = open_run(args.load_config, console)
    model = opened.model
    run_dir = args.load_config.parent
    stack = None if args.no_edits else EditStack.open(run_dir, model.fingerprint())
    if args.frame == "dataparser":
        frame = CaptureFrame.identity()
    elif (run_dir / "dataparser_transforms.json").is_file():
        frame = CaptureFrame.from_transforms_json(run_dir / "dataparser_transforms.json")
    else:
        frame = opened.frame
    k = args.specular_strength if args.specular_strength is not None else (
        stack.specular_strength if stack is not None else 1.0)
    n_edits = len(stack.active) if stack is not None else 0
    t0 = time.perf_counter()
    with Progress(TextColumn("baking colours"), BarColumn(), TextColumn("{task.completed:,}/{task.total:,} Gaussians"),
                  TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task("bake", total=model.num_points)
        g = bake(model, stack, k, frame, opened.train.cameras(), BakeConfig(directions=args.directions),
                 progress=lambda done, total: bar.update(task, completed=done))
    with console.status(f"writing {args.out}"):
        write_splat(g, args.out)
    secs = time.perf_counter() - t0
    return (f"{args.out}: {g.summary()}; {n_edits} edit(s), specular strength {k:g}, {args.frame} frame, "
            f"{secs:.1f} s")


def entrypoint() -> None:
    run_command(Export, run)


if __name__ == "__main__":
    entrypoint()
