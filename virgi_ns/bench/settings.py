"""``KEY=VALUE,KEY=VALUE`` settings on the benchmarks' command lines (``bench/edit.py --variants``,
``bench/train.py --colour-variants``): split and typed like the value they replace."""

from __future__ import annotations

from typing import Any, List, Tuple

from virgi_ns.errors import InputError

_TRUE, _FALSE = ("1", "true", "yes"), ("0", "false", "no")


def split_settings(text: str, flag: str) -> List[Tuple[str, str]]:
    """'a=1,b.c=x' -> [('a', '1'), ('b.c', 'x')]; refuses a part without '='."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        if not sep or not key.strip():
            raise InputError(f"{flag}: '{part}' is not KEY=VALUE")
        out.append((key.strip(), value.strip()))
    return out


def typed_like(old: Any, value: str, key: str, flag: str) -> Any:
    """``value`` parsed as the type of ``old`` (bool: true/false/yes/no/1/0 only)."""
    if old is None:
        raise InputError(f"{flag}: {key} has no default to take a type from")
    if isinstance(old, bool):
        if value.lower() not in _TRUE + _FALSE:
            raise InputError(f"{flag}: {key} takes true or false, got '{value}'")
        return value.lower() in _TRUE
    try:
        return type(old)(value)
    except (TypeError, ValueError):
        raise InputError(f"{flag}: {key} takes a {type(old).__name__}, got '{value}'") from None


__all__ = ["split_settings", "typed_like"]
