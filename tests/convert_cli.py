"""``virgi-convert`` run in the test's own process, as its console script runs it."""

from __future__ import annotations

import sys


def run_convert(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``virgi-convert ARGS``; ``monkeypatch`` sets ``sys.argv``."""
    from virgi_ns.cli import convert

    monkeypatch.setattr(sys, "argv", ["virgi-convert", *args])
    code = 0
    try:
        convert.entrypoint()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    cap = capsys.readouterr()
    return code, cap.out, cap.err
