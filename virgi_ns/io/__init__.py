"""Splat import and export: every supported file becomes one :class:`~virgi_ns.gaussians.Gaussians`.

Reads INRIA ``.ply`` (any SH degree), SuperSplat ``.compressed.ply`` (with or without ``sh``),
Niantic ``.spz`` (versions 1-4), PlayCanvas ``.sog`` (version 2, a zip or a folder holding
``meta.json``) and nerfstudio splatfacto checkpoints (``.ckpt`` or a run's ``config.yml``).
Writes INRIA ``.ply``, ``.spz``, ``.sog`` and (for tests and export) ``.compressed.ply``.
Every problem with the input raises :class:`~virgi_ns.errors.InputError` with one clear line.
"""

from __future__ import annotations

import os
from pathlib import Path

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.gaussians import Gaussians
from virgi_ns.io.compressed_ply import compressed_ply_bytes, gaussians_from_compressed, is_compressed_ply
from virgi_ns.io.ply import gaussians_from_inria, inria_vertices
from virgi_ns.io.plyfmt import is_ply, read_ply_bytes, write_ply
from virgi_ns.io.spz import MAGIC as _SPZ_MAGIC
from virgi_ns.io.spz import read_spz_bytes, spz_bytes

__all__ = ["load_splat", "decode_splat", "save_ply", "save_spz", "save_sog", "save_splat", "save_compressed_ply",
           "check_finite", "WRITABLE"]

SUPPORTED = ".ply, .compressed.ply, .spz, .sog (zip or folder), a splatfacto .ckpt or its config.yml"
WRITABLE = (".ply", ".spz", ".sog")  # the suffixes save_splat writes (INRIA layout for .ply)


def check_finite(g: Gaussians, drop_invalid: bool, where: str) -> Gaussians:
    """Refuse (or with ``drop_invalid`` drop) rows holding NaN or infinity."""
    if len(g) == 0:
        return g
    bad = g.invalid_rows()
    n_bad = int(bad.sum())
    if n_bad == 0:
        return g
    if not drop_invalid:
        first = bad.nonzero().flatten()[:5].tolist()
        raise InputError(
            f"{where}: {n_bad:,} of {len(g):,} Gaussians hold NaN or Inf values (rows {', '.join(map(str, first))}"
            f"{', ...' if n_bad > 5 else ''}); use --drop-invalid to drop them"
        )
    return g.index(~bad)


def decode_splat(buf: bytes, name: str = "file", drop_invalid: bool = False) -> Gaussians:
    """Decode a PLY (INRIA or compressed), SPZ or bundled SOG file held in memory; the format comes
    from its content."""
    if not buf:
        raise InputError(f"{name} is empty")
    if buf[:4] == b"PK\x03\x04":  # a zip: SOG is the one splat format that is one
        from virgi_ns.io.sog import read_sog_bytes

        g = read_sog_bytes(buf, name)
    elif is_ply(buf[:5]):
        ply = read_ply_bytes(buf, name)
        g = gaussians_from_compressed(ply, name) if is_compressed_ply(ply) else gaussians_from_inria(ply, name)
    elif buf[:2] == b"\x1f\x8b" or buf[:4] == _SPZ_MAGIC.to_bytes(4, "little"):
        g = read_spz_bytes(buf, name)
    else:
        raise InputError(f"{name}: unrecognised splat file; expected {SUPPORTED}")
    return check_finite(g, drop_invalid, name)


def load_splat(path: str | os.PathLike, drop_invalid: bool = False) -> Gaussians:
    """Load any supported splat file; the format is decided by content (then by name for checkpoints).

    A directory is a splatfacto run (``config.yml``) or a SOG folder (``meta.json``); a zip is a SOG
    when it is named ``.sog`` or holds ``meta.json``, else a torch checkpoint."""
    from virgi_ns.io import sog

    path = Path(path)
    if not path.exists():
        raise InputError(f"no such file: {path}")
    if path.is_dir():
        if (path / "config.yml").is_file():
            path = path / "config.yml"
        elif (path / "meta.json").is_file():
            return check_finite(sog.read_sog(path), drop_invalid, str(path))
        else:
            raise InputError(f"{path} is a directory, not a splat file")
    if path.name.lower() == "meta.json":
        return check_finite(sog.read_sog(path), drop_invalid, str(path))
    from virgi_ns.io import splatfacto  # torch pickle handling, only when needed

    suffix = path.suffix.lower()
    if suffix in (".yml", ".yaml"):
        return check_finite(splatfacto.load_run(path), drop_invalid, str(path))
    try:
        with open(path, "rb") as f:
            head = f.read(4)
            is_zip = head == b"PK\x03\x04"
            # torch checkpoints are zips too: a zip is a SOG when named so or when it holds meta.json
            is_ckpt = suffix in (".ckpt", ".pt", ".pth") or (is_zip and suffix != ".sog" and not sog.is_sog_zip(path))
            buf = b"" if is_ckpt else head + f.read()
    except OSError as e:
        raise InputError(f"cannot read {path}: {e.strerror}") from None
    if is_ckpt:
        return check_finite(splatfacto.load_checkpoint(path), drop_invalid, str(path))
    return decode_splat(buf, str(path), drop_invalid)


def _write(data: bytes, path: str | os.PathLike) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def save_ply(g: Gaussians, path: str | os.PathLike) -> None:
    """Write INRIA-layout binary ``.ply`` atomically (float32, normals zero)."""
    vertex = inria_vertices(g)  # before the destination is touched
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        write_ply(f, [("vertex", vertex)])


def save_spz(g: Gaussians, path: str | os.PathLike, version: int = 3) -> None:
    """Write ``.spz`` (version 3, gzip, by default; 4 uses ZSTD streams) atomically."""
    _write(spz_bytes(g, version=version), path)


def save_sog(g: Gaussians, path: str | os.PathLike) -> None:
    """Write a bundled PlayCanvas ``.sog`` (version 2, zip) atomically."""
    from virgi_ns.io.sog import write_sog

    write_sog(g, path)


def save_splat(g: Gaussians, path: str | os.PathLike) -> None:
    """Write ``.ply`` (INRIA layout), ``.spz`` or ``.sog`` by the name's suffix, atomically."""
    suffix = Path(path).suffix.lower()
    if suffix not in WRITABLE or Path(path).name.lower().endswith(".compressed.ply"):
        raise InputError(f"output {path} must end in {', '.join(WRITABLE[:-1])} or {WRITABLE[-1]}")
    {".ply": save_ply, ".spz": save_spz, ".sog": save_sog}[suffix](g, path)


def save_compressed_ply(g: Gaussians, path: str | os.PathLike, with_sh: bool = True) -> None:
    """Write SuperSplat ``.compressed.ply`` atomically."""
    _write(compressed_ply_bytes(g, with_sh=with_sh), path)
