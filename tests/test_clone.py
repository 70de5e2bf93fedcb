"""A clone has no ``../shared/data``: every test that reads it (through the ``shared_data`` fixture, so
marked ``shared_data``) must skip, not fail, where that folder is empty or missing. The tests are
found by the fixture, not listed: the files that name it, and in them the tests it marks. (A test that
reads the folder without the fixture fails in every run: see ``conftest.py``.)"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import REPO, SHARED_DATA_ENV

TESTS = Path(__file__).resolve().parent


def _files_using_the_fixture() -> list[str]:
    return sorted(str(p.relative_to(REPO)) for p in TESTS.glob("test_*.py")
                  if p.name != Path(__file__).name and re.search(r"\bshared_data\b", p.read_text(encoding="utf-8")))


def test_tests_of_real_data_skip_where_it_is_empty_or_missing(tmp_path):
    files = _files_using_the_fixture()
    assert files, "no test uses the shared_data fixture"
    (tmp_path / "empty").mkdir()
    runs = {}
    for case in ("empty", "missing"):  # both at once: each is mostly interpreter start and collection
        env = {**os.environ, SHARED_DATA_ENV: str(tmp_path / case)}
        cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider", "-m", "shared_data and not slow",
               *files]
        runs[case] = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True)
    for case, proc in runs.items():
        out, _ = proc.communicate(timeout=300)
        summary = out.strip().splitlines()[-1] if out.strip() else ""
        assert proc.returncode == 0, f"with {case} {SHARED_DATA_ENV}:\n{out[-4000:]}"
        assert not re.search(r"\d+ (failed|errors?)\b", summary), summary
        skipped = re.search(r"(\d+) skipped", summary)
        assert skipped and int(skipped.group(1)) > 0, summary
