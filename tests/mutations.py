"""Deliberate breaks, one at a time, each against the default tests that guard it: does the suite fail
when the code breaks? Run by hand (it is not a test; a full run takes a while):

    python tests/mutations.py                  # every break: a table, exit 1 if any survived
    python tests/mutations.py --list           # the breaks
    python tests/mutations.py NAME [NAME ...]  # only these

Each break (``mutations.toml``) is a name, a file, an original snippet, its replacement and the tests that guard it. The tree is copied once to a temporary
folder (without .git, .venv and outputs; the real files are never edited); for each break the copy's file
gets the replacement, ``python -m pytest -x -q TESTS`` runs in the copy with ``PYTHONPATH=<copy>`` (the
default selection: no ``slow``, GPU tests skip without a GPU, and no ``../shared`` in reach, as in a
clone), and the file is put back. **killed**: a test failed; **survived**: they all passed; **stale**:
the snippet is not in the file any more (update the list); **error**: pytest could not run them.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as the package tomli (pytest's own dependency there)
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Break:
    name: str
    file: str
    original: str
    replacement: str
    tests: tuple[str, ...]
    what: str


BREAKS_FILE = Path(__file__).with_name("mutations.toml")


def load_breaks(path: Path = BREAKS_FILE) -> list[Break]:
    """The breaks listed in ``path`` (``mutations.toml``: one ``[[break]]`` table each)."""
    with open(path, "rb") as f:
        return [Break(b["name"], b["file"], b["original"], b["replacement"], tuple(b["tests"]), b["what"])
                for b in tomllib.load(f)["break"]]


BREAKS = load_breaks()


def _copy_tree(dest: Path) -> Path:
    ignore = shutil.ignore_patterns(".git", ".venv", "bench_out", "demo_out", "__pycache__", ".pytest_cache", "*.egg-info")
    shutil.copytree(REPO, dest, ignore=ignore, symlinks=True)
    return dest


def run_break(b: Break, copy: Path, timeout: float) -> tuple[str, float, str]:
    """(result, seconds, last line of pytest's output) of one break applied to ``copy``."""
    path = copy / b.file
    if not path.is_file():
        return "stale", 0.0, f"{b.file} does not exist"
    text = path.read_text(encoding="utf-8")
    n = text.count(b.original)
    if n != 1:
        return ("stale" if n == 0 else "error"), 0.0, f"the snippet occurs {n} times in {b.file}"
    env = {**os.environ, "PYTHONPATH": str(copy) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "PYTHONDONTWRITEBYTECODE": "1"}  # no bytecode: a restored file of the same size must not reuse it
    env.pop("VIRGI_SHARED_DATA", None)
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *b.tests]
    t0 = time.monotonic()
    try:
        path.write_text(text.replace(b.original, b.replacement), encoding="utf-8")
        try:
            p = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
            rc, out = p.returncode, (p.stdout + p.stderr).strip()
        except subprocess.TimeoutExpired:
            rc, out = -1, f"timed out after {timeout:.0f} s"
    finally:
        path.write_text(text, encoding="utf-8")
    secs = time.monotonic() - t0
    last = out.splitlines()[-1] if out else ""
    if rc == 1:
        return "killed", secs, last
    if rc == 0:
        return "survived", secs, last
    if rc == -1:  # a hang is a failure the suite would report too (pytest-timeout)
        return "killed", secs, last
    return "error", secs, f"pytest exit {rc}: {last}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="only these breaks")
    ap.add_argument("--list", action="store_true", help="list the breaks and exit")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per break")
    args = ap.parse_args()
    if args.list:
        for b in BREAKS:
            print(f"{b.name:32s} {b.file}: {b.what}")
        return 0
    unknown = set(args.names) - {b.name for b in BREAKS}
    if unknown:
        ap.error(f"no such break: {', '.join(sorted(unknown))}")
    chosen = [b for b in BREAKS if not args.names or b.name in args.names]
    rows = []
    with tempfile.TemporaryDirectory(prefix="virgi_mutations_") as tmp:
        copy = _copy_tree(Path(tmp) / "repo")
        for b in chosen:
            result, secs, last = run_break(b, copy, args.timeout)
            rows.append((b, result, secs, last))
            print(f"{result:9s} {secs:6.0f} s  {b.name}: {last}", flush=True)
    print()
    print("| break | file | guarded by | result |")
    print("| --- | --- | --- | --- |")
    for b, result, secs, _ in rows:
        tests = ", ".join(t.replace("tests/", "") for t in b.tests)
        print(f"| {b.what} | `{b.file}` | {tests} | **{result}** ({secs:.0f} s) |")
    bad = [b.name for b, r, _, _ in rows if r != "killed"]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} breaks killed" + (f"; not killed: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
