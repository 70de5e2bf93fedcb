"""User-facing errors and the command-line wrapper that turns them into one clear line.

Raise :class:`VirgiError` (or a subclass) for anything caused by the user's input: a missing
file, a corrupt splat, a wrong image size. :func:`cli_entry` prints ``error: <message>`` on
stderr and exits with code 2, without a traceback.
"""

from __future__ import annotations

import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator


class VirgiError(Exception):
    """An error in the user's input, reported as one line."""


class InputError(VirgiError):
    """Bad input file or argument."""


EXIT_USER_ERROR = 2


def cli_entry(main: Callable[[], object]) -> None:
    """Run ``main`` (typically ``tyro.cli(...)``) and map user errors to one line and exit 2."""
    try:
        main()
    except VirgiError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    except FileNotFoundError as e:
        print(f"error: no such file: {e.filename or e}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)


@contextmanager
def atomic_path(dest: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``dest``; on success rename it onto ``dest``, on any
    error remove it, so ``dest`` is never half-written and an existing file is never lost."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp" + "".join(dest.suffixes[-1:]), dir=dest.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; give the file ordinary permissions
    try:
        yield tmp_path
        os.replace(tmp_path, dest)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
