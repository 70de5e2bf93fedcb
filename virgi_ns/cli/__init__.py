"""The command-line tools (``virgi-convert``, ``virgi-render``, ``virgi-edit``, ``virgi-export``).

A process that imports them leaves the objects alive at its exit out of the interpreter's last
garbage collections (``gc.freeze`` run by ``atexit``, after every other thread has ended): those
collections would traverse every object torch made (a measurable share of a short command's wall,
bench/RESULTS.md), and the memory goes back with the process. Anything a command writes is closed before it returns.
"""

from __future__ import annotations

import atexit
import gc
from typing import Any, Callable

atexit.register(gc.freeze)


def run_command(command: type, run: Callable[[Any], str]) -> None:
    """Parse ``command`` from the command line, ``run`` it and print the line it returns; user
    errors are one line on stderr and exit code 2 (:func:`virgi_ns.errors.cli_entry`)."""
    import tyro

    from virgi_ns.errors import cli_entry

    cli_entry(lambda: print(run(tyro.cli(command))))
