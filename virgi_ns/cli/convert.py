"""``virgi-convert IN OUT``: convert any supported splat file to an INRIA ``.ply``, ``.spz`` or ``.sog``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from virgi_ns.cli import run_command
from virgi_ns.errors import InputError
from virgi_ns.io import WRITABLE, load_splat, save_splat


@dataclass
class Convert:
    """Convert a splat (.ply, .compressed.ply, .spz, .sog, splatfacto .ckpt or config.yml) to .ply, .spz or .sog."""

    src: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="IN")]
    """Input splat: .ply, .compressed.ply, .spz, .sog (zip or a folder holding meta.json), a splatfacto .ckpt or its
    config.yml."""
    dst: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Output file: .ply (INRIA layout), .spz or .sog (PlayCanvas SOG version 2, zip)."""
    drop_invalid: bool = False
    """Drop Gaussians holding NaN or Inf values instead of refusing the file."""


def run(args: Convert) -> str:
    """Do the conversion; returns the one-line summary."""
    suffix = args.dst.suffix.lower()
    if suffix not in WRITABLE:
        raise InputError(f"output {args.dst} must end in .ply, .spz or .sog")
    if args.dst.name.lower().endswith(".compressed.ply"):
        raise InputError(f"output {args.dst}: writing .compressed.ply is not offered; use .ply, .spz or .sog")
    if args.dst.exists() and args.dst.resolve() == args.src.resolve():
        raise InputError(f"output {args.dst} is the input file")
    console = Console(stderr=True)
    with console.status(f"reading {args.src}"):
        g = load_splat(args.src, drop_invalid=args.drop_invalid)
    with console.status(f"writing {args.dst}"):
        save_splat(g, args.dst)
    return f"{args.dst}: {g.summary()}"


def entrypoint() -> None:
    run_command(Convert, run)


if __name__ == "__main__":
    entrypoint()
