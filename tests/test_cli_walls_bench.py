"""bench/cli_walls.py's reading of ``python -X importtime`` output, against sums made by hand."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from script_module import script_module  # noqa: E402

STDERR = """import time: self [us] | cumulative | imported package
import time:       100 |        100 |   _io
import time:       200 |        300 |   numpy.core
import time:       400 |        700 | numpy
import time:      5000 |     900000 | torch
import time:      3000 |       3000 |     torch._C
import time:        50 |         50 | tyro
not an import line
import time: garbled
"""


def test_import_breakdown_sums_self_times_and_takes_torch_cumulative():
    with script_module("bench/cli_walls.py", "cli_walls_under_test") as walls:
        got = walls.import_breakdown(STDERR)
    assert abs(got["imports_s"] - (100 + 200 + 400 + 5000 + 3000 + 50) / 1e6) < 1e-12
    assert got["torch_s"] == 0.9  # torch's own cumulative time, not its self time
    # packages by self time, torch left out: numpy's two modules together, then _io, then tyro
    assert list(got["largest_others_s"]) == ["numpy", "_io", "tyro"]
    assert abs(got["largest_others_s"]["numpy"] - 600 / 1e6) < 1e-12
