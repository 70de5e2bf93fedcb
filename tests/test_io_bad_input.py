"""Bad input: every malformed file gives one line on stderr, exit code 2, no output file, no traceback;
and fuzzed files (random truncations and byte flips of small valid files) either load finite
Gaussians or raise InputError, never anything else."""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from convert_cli import run_convert
from virgi_ns.errors import InputError
from virgi_ns.gaussians import Gaussians
from virgi_ns.io import decode_splat, load_splat, save_ply
from virgi_ns.io.compressed_ply import compressed_ply_bytes
from virgi_ns.io.ply import inria_ply_bytes
from virgi_ns.io.spz import spz_bytes


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3), r(n, 3) - 4, r(n, 4), r(n), r(n, (degree + 1) ** 2, 3) * 0.3)


def _bad_files(d: Path) -> dict[str, tuple[Path, str]]:
    """name -> (input path, a phrase its error line must hold)."""
    good = inria_ply_bytes(random_gaussians(10, 1))
    header_end = good.index(b"end_header\n") + len(b"end_header\n")
    files = {
        "empty": (b"", "is empty"),
        "not_ply": (b"hello, this is text\n" * 5, "unrecognised splat file"),
        "header_only": (good[:header_end], "truncated"),
        "truncated": (good[: len(good) - 37], "truncated"),
        "unknown_type": (good.replace(b"property float opacity", b"property half opacity"), "unknown PLY property type"),
        "mesh": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                 b"property float z\nend_header\n" + bytes(12), "lack f_dc_0"),
        "ascii": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n", "ASCII PLY"),
        "spz_corrupt": (gzip.compress(b"NGSP" + bytes(60))[:-5], "corrupt SPZ"),
        "spz_garbage": (b"\x1f\x8b" + os.urandom(200), "corrupt SPZ"),
    }
    out = {}
    for name, (data, phrase) in files.items():
        p = d / (name + (".spz" if name.startswith("spz") else ".ply"))
        p.write_bytes(data)
        out[name] = (p, phrase)
    nan = random_gaussians(10, 0)
    nan.opacities[[2, 5, 6]] = float("nan")
    nan.means[9, 0] = float("inf")
    save_ply(nan, d / "nan.ply")
    out["nan"] = (d / "nan.ply", "4 of 10 Gaussians hold NaN or Inf")
    out["missing"] = (d / "does_not_exist.ply", "no such file")
    out["directory"] = (d, "is a directory")
    return out


def test_every_bad_input_gives_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    src = tmp_path / "in"
    src.mkdir()
    out_dir = tmp_path / "out"
    for name, (path, phrase) in _bad_files(src).items():
        code, out, err = run_convert(monkeypatch, capsys, str(path), str(out_dir / f"{name}.ply"))
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert code == 2, (name, err)
        assert len(lines) == 1 and lines[0].startswith("error: ") and phrase in lines[0], (name, err)
        assert "Traceback" not in err and out == ""
        assert not out_dir.exists() or not any(out_dir.iterdir()), name  # no output, no temp file left


def test_drop_invalid_drops_the_bad_rows(tmp_path, monkeypatch, capsys):
    path, _ = _bad_files(tmp_path)["nan"]
    code, out, err = run_convert(monkeypatch, capsys, str(path), str(tmp_path / "o.ply"), "--drop-invalid")
    assert code == 0, err
    assert out.startswith(f"{tmp_path / 'o.ply'}: 6 Gaussians, SH degree 0, bbox min (")
    assert len(load_splat(tmp_path / "o.ply")) == 6


def test_existing_output_survives_a_failed_conversion(tmp_path, monkeypatch, capsys):
    (tmp_path / "o.ply").write_bytes(b"precious")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    code, _, _ = run_convert(monkeypatch, capsys, str(tmp_path / "bad.ply"), str(tmp_path / "o.ply"))
    assert code == 2 and (tmp_path / "o.ply").read_bytes() == b"precious"


def test_cli_subprocess_end_to_end(tmp_path):
    """The installed console script, as a user runs it: two bad inputs and one good one, in parallel."""
    exe = Path(sys.executable).with_name("virgi-convert")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "virgi_ns.cli.convert"]
    bad = _bad_files(tmp_path)
    save_ply(random_gaussians(30, 2), tmp_path / "good.ply")
    cases = {
        "truncated": (bad["truncated"][0], 2, "truncated"),
        "spz_corrupt": (bad["spz_corrupt"][0], 2, "corrupt SPZ"),
        "good": (tmp_path / "good.ply", 0, ""),
    }
    procs = {k: subprocess.Popen([*cmd, str(p), str(tmp_path / "out" / f"{k}.ply")], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True) for k, (p, _, _) in cases.items()}
    for k, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        _, code, phrase = cases[k]
        assert proc.returncode == code, (k, err)
        if code:
            assert err.strip().count("\n") == 0 and err.startswith("error: ") and phrase in err, (k, err)
            assert not (tmp_path / "out" / f"{k}.ply").exists()
        else:
            assert "30 Gaussians, SH degree 2" in out
            assert torch.equal(load_splat(tmp_path / "out" / "good.ply").sh, load_splat(tmp_path / "good.ply").sh)


# ------------------------------------------------------------------------------------------ fuzz
def _fuzz_sources() -> dict[str, bytes]:
    g = random_gaussians(300, 1, seed=3)
    return {
        "inria": inria_ply_bytes(g.index(slice(0, 40))),
        "compressed": compressed_ply_bytes(g),
        "compressed_no_sh": compressed_ply_bytes(g.with_sh_degree(0)),
        "spz_v2": spz_bytes(g.index(slice(0, 40)), version=2),
        "spz_v3": spz_bytes(g.index(slice(0, 40)), version=3),
        "spz_v4": spz_bytes(g.index(slice(0, 40)), version=4),
        # the gzip CRC catches most flips above; fuzz the payload parser on the uncompressed form too
        "spz_v3_payload": gzip.decompress(spz_bytes(g.index(slice(0, 40)), version=3)),
    }


def _mutations(buf: bytes, rng: np.random.Generator, count: int):
    for i in range(count):
        if i % 3 == 0:
            yield buf[: int(rng.integers(0, len(buf)))]
        else:
            b = bytearray(buf)
            # half the flips go to the first bytes, where the structure lives, and keep ASCII text ASCII
            hi, top = (min(len(b), 400), 128) if i % 2 else (len(b), 256)
            for pos in rng.integers(0, hi, size=int(rng.integers(1, 6))):
                b[pos] ^= int(rng.integers(1, top))
            yield bytes(b)


@pytest.mark.parametrize("name", list(_fuzz_sources()))
def test_fuzzed_files_load_finite_or_raise_input_error(name):
    buf = _fuzz_sources()[name]
    assert len(decode_splat(buf)) > 0  # the unmutated file is valid
    rng = np.random.default_rng(sum(map(ord, name)))
    outcomes = {"loaded": 0, "refused": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # overflow or invalid-value warnings would be bugs too
        for i, mutated in enumerate(_mutations(buf, rng, 60)):
            try:
                g = decode_splat(mutated, f"{name}#{i}")
            except InputError as e:
                assert "\n" not in str(e)
                outcomes["refused"] += 1
            else:
                assert not g.invalid_rows().any(), f"{name}#{i}"
                outcomes["loaded"] += 1
    assert outcomes["refused"] > 0  # truncations at least must be refused
