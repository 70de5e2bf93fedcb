"""Where a fresh ``virgi-edit apply`` spends its wall time: the command run under cProfile in this
process (start it as a fresh interpreter), the top functions by cumulative time printed and the
profile written. Arguments after ``--`` are apply's own.

    python bench/profile_apply.py OUT.prof -- --load-config CFG --image EDITED.png --camera-json CAM.json
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import time


def main() -> None:
    out, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
    t0 = time.perf_counter()
    prof = cProfile.Profile()
    prof.enable()
    from virgi_ns.cli.edit import entrypoint

    sys.argv = ["virgi-edit", "apply", *args]
    try:
        entrypoint()
    except SystemExit:
        pass
    prof.disable()
    print(f"apply in this process: {time.perf_counter() - t0:.2f} s (imports included)")
    prof.dump_stats(out)
    pstats.Stats(prof).sort_stats("cumulative").print_stats(45)


if __name__ == "__main__":
    main()
