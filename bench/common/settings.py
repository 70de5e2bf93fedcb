"""``KEY=VALUE,KEY=VALUE`` settings on the benchmarks' command lines (``bench/edit.py --variants``,
``bench/train.py --colour-variants``, ``--train-settings``): split and typed like the value they replace."""

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


def apply_settings(cfg, text: str, flag: str) -> None:
    """Set 'a.b.c=value,...' on a TrainerConfig (dict keys and attributes alike), typed as the
    value already there; refuses unknown paths, naming ``flag``, the option that gave them."""
    for path, value in split_settings(text, flag):
        *parents, leaf = path.split(".")
        node = cfg
        for name in parents:
            node = node.get(name) if isinstance(node, dict) else getattr(node, name, None)
            if node is None:
                raise InputError(f"{flag}: no '{path}' in the trainer config")
        if not (leaf in node if isinstance(node, dict) else hasattr(node, leaf)):
            raise InputError(f"{flag}: no '{path}' in the trainer config")
        old = node[leaf] if isinstance(node, dict) else getattr(node, leaf)
        new = typed_like(old, value, path, flag)
        if isinstance(node, dict):
            node[leaf] = new
        else:
            setattr(node, leaf, new)


def edit_settings(text: str) -> dict:
    """'steps=200,seg_init_bias=-2' -> EditConfig fields, typed as the fields' defaults are and checked as
    EditConfig checks them; 'rule=h0/h1/shift/s_min/v_min' -> another rule (key ``rule``); 'source=render'
    -> the rule applied to the edit view's render instead of its photo (key ``source``): the edit with an
    exact target, which tells the target's error from the fit's; 'source=render+original' -> the same with
    the render given as the original, so the engine fits only the changed pixels as it does for a photo
    edit. Bad settings are an :class:`InputError` naming ``--variants``."""
    from virgi_ns.bench.recolor import RuleArgs
    from virgi_ns.edit.engine import EditConfig

    defaults = EditConfig()
    out: dict = {}
    for key, value in split_settings(text, "--variants"):
        key = key.replace("-", "_")
        if key == "rule":
            try:
                h0, h1, shift, s_min, v_min = (float(x) for x in value.split("/"))
            except ValueError:
                raise InputError(f"--variants: rule takes h0/h1/shift/s_min/v_min, got '{value}'") from None
            out["rule"] = RuleArgs(h0=h0, h1=h1, shift=shift, s_min=s_min, v_min=v_min).rule()
            continue
        if key == "source":
            if value not in ("photo", "render", "render+original"):
                raise InputError(f"--variants: source takes photo, render or render+original, got '{value}'")
            out["source"] = value
            continue
        if not hasattr(defaults, key):
            raise InputError(f"--variants: '{key}' is not an EditConfig field")
        out[key] = typed_like(getattr(defaults, key), value, key, "--variants")
    try:
        EditConfig(**{k: v for k, v in out.items() if k not in ("rule", "source")})
    except ValueError as e:
        raise InputError(f"--variants: {e}") from None
    return out


__all__ = ["apply_settings", "edit_settings", "split_settings", "typed_like"]
