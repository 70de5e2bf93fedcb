"""The command-line tools (``virgi-convert``, ``virgi-render``, ``virgi-edit``, ``virgi-export``)."""

from __future__ import annotations

from typing import Any, Callable


def run_command(command: type, run: Callable[[Any], str]) -> None:
    """Parse ``command`` from the command line, ``run`` it and print the line it returns; user
    errors are one line on stderr and exit code 2 (:func:`virgi_ns.errors.cli_entry`)."""
    import tyro

    from virgi_ns.errors import cli_entry

    cli_entry(lambda: print(run(tyro.cli(command))))
