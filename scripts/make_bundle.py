"""Regenerate the bundled demo capture ``virgi_ns/assets/beercan_small`` from ``../shared/data/beercan``.

    python scripts/make_bundle.py                                          # 32 views at 1/2 size
    python scripts/make_bundle.py --downscale 1 --out /tmp/beercan_full    # the same views, full size

See :mod:`virgi_ns.data.make_bundle` for what is written.
"""

import tyro

from virgi_ns.data.make_bundle import Args, main
from virgi_ns.errors import cli_entry

if __name__ == "__main__":
    cli_entry(lambda: main(tyro.cli(Args)))
