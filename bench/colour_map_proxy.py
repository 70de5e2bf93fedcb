"""A CPU proxy of the colour map's target quality (``EditConfig.changed_target="map"``).

Written, with its decision rule, before any of its numbers were seen.

Definition
----------
For each scene of the evaluation set (:data:`virgi_ns.bench.evalset.EVAL_SET`: the real captures,
and the synthetic ones when ``--synthetic``; their captures are written by ``capture_folder`` on
the CPU, about a minute each, and kept under ``--synthetic-root``):

- P: the photo of the edited view, the training view that ``evalset.edit_view`` picks among the
  training photos (the train split of ``evalset.dataparser_config(folder)``, nerfstudio's parser:
  every 8th view held out; images read as 8-bit / 255, as nerfstudio's dataset does);
- E = rule(P), the user's edit;
- R = P blurred by a Gaussian of sigma 1 px (and, a second proxy, 2 px; reflected borders, radius
  3 sigma): a stand-in for the model's render of that view, which misses the photo's finest detail
  and blends colours at edges;
- T* = rule(R): what the render should become;
- changed pixels: ``|E - P|`` above the engine's ``unchanged_tol`` in some channel (the engine's
  own definition of the pixels it fits to the edit; about "P != E").

Each target variant gives every changed pixel a target as the engine's ``_mapped_target`` does:
``map.apply(R)`` where the variant uses its map (explains(P, E) at that pixel, and the variant's
gate at the render's colour), ``E`` elsewhere. Figures per scene, blur and variant:

- ``use``: share of changed pixels whose target is the map's;
- ``target``: PSNR (dB, peak 1) of the target against T* over the changed pixels;
- ``leak``: the map as a function of colour applied to R everywhere (``map.apply(R)`` where the
  variant's gate at R's colour passes, R elsewhere: what a colour layer fitted to such targets
  would do to pixels of other views), PSNR against R over the pixels of R that the rule does not
  change (rule_mask(R) false), so the error the map puts on colours the user did not change (fern's
  failure without the spread check). Capped at 100 dB (no error).

Variants: ``edited`` (target E; no map, leak 100), ``no_spread`` (the 17-grid map, gate = support
only), ``current`` (the 17-grid map with its spread check, the engine's ``changed_target="map"``), and candidates:

- ``multires``: maps on grids 17, 33 and 65; at each colour, the coarsest level that has support
  and whose change is one change (the spread check of that level) gives the change; no level: not
  one change (and the 17 map's change, for ``explains``). A finer level's kernel is narrower, so it
  separates colours that a coarse cell mixes (a hue threshold through dark colours);
- ``loclin``: local-linear kernel regression on the 17 grid: at each grid point, the change is
  fitted as an affine function of colour over the pixels in its tent (slope ridge-regularised
  towards 0), read back at a colour as the support-weighted blend of the 8 corners' affine models;
  its spread is that of the residuals (pooled over the corners) plus the corners' disagreement at
  the colour, so a smooth change's own slope is not counted as spread while a threshold is;
- ``multires_lib``: the library's multi-level map (``fit_colour_change(..., levels=3)``,
  ``EditConfig.map_levels=3``), added after the candidates were run: the same numbers as
  ``multires`` show that the library implements the measured candidate.

Added later, before their numbers were seen: ``current+change`` and ``multires_lib+change``, the
same maps with ``EditConfig.map_fallback="change"``: a changed pixel whose target is not the map's
gets ``R + E - P`` (clamped) instead of ``E``. Their ``use`` and ``leak`` are their map's; only
``target`` can differ. Reported; the choice is made on the GPU (bench/RESULTS.md, "Edit").

Decision rule (fixed before the candidates were run)
----------------------------------------------------
A candidate replaces ``current`` if, at both blur levels: on every scene its ``target`` is not lower
than current's by more than 0.1 dB and its ``leak`` not lower by more than 0.1 dB; and on cup its
``target`` is higher than current's. The proxy is trusted only if it reproduces the known GPU
outcomes first: on cup ``no_spread`` beats ``current`` on ``target``, and on fern ``no_spread`` is
worse than ``current`` on ``target`` or ``leak``.

The script prints the table, the reproduction checks and each candidate's failures of the rule
(:func:`verdict`), and writes them to ``--out``.

    PYTHONPATH=. python bench/colour_map_proxy.py --out bench/results/colour_map_proxy.json [--synthetic]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from virgi_ns.edit.colour_change import MIN_SUPPORT, SPREAD_SHARE, ColourChange, _corners, fit_colour_change  # noqa: E402
from virgi_ns.edit.recolor import RecolorRule, recolor, rule_mask  # noqa: E402

BLURS = (1.0, 2.0)
CAP = 100.0


# ----------------------------------------------------------------------------- data
def _read(path: Path) -> torch.Tensor:
    from PIL import Image

    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"))).float() / 255.0


def scene_photo(scene, data: Path, synthetic_root: Path) -> tuple[torch.Tensor, str]:
    """(P, its file name): the edited view's photo, chosen as the benchmark chooses it."""
    from virgi_ns.bench.evalset import capture_folder, dataparser_config, edit_view

    folder = capture_folder(scene, data, synthetic_root)
    out = dataparser_config(folder).setup().get_dataparser_outputs("train")
    photos = [_read(Path(p)) for p in out.image_filenames]
    view = edit_view(photos, scene.rule)
    return photos[view], Path(out.image_filenames[view]).name


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    t = img.permute(2, 0, 1)[None]
    t = torch.nn.functional.pad(t, (r, r, r, r), mode="reflect")
    t = torch.nn.functional.conv2d(t, k.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    t = torch.nn.functional.conv2d(t, k.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    return t[0].permute(1, 2, 0)


# ----------------------------------------------------------------------------- candidates
class NoSpread:
    """The 17 map with its support as the only gate."""

    def __init__(self, change: ColourChange):
        self.change = change

    def apply_where_one_change(self, colours):
        delta, support, _ = self.change.lookup(colours)
        return (colours + delta).clamp(0, 1), support >= MIN_SUPPORT

    def explains(self, original, edited):
        return self.change.explains(original, edited)


class MultiRes:
    """Maps on several grids; the coarsest level with support and one change gives the change."""

    def __init__(self, original, edited, grids=(17, 33, 65)):
        self.levels = [fit_colour_change(original, edited, g) for g in grids]

    def _delta(self, colours):
        delta = one = None
        for level in self.levels:
            d, support, spread = level.lookup(colours)
            ok = (support >= MIN_SUPPORT) & (spread <= SPREAD_SHARE * d.abs().amax(-1))
            if delta is None:
                delta, one = d, ok  # the 17 map's change unless a level is one change
            else:
                take = ok & ~one
                delta = torch.where(take[:, None], d, delta)
                one = one | ok
        return delta, one

    def apply_where_one_change(self, colours):
        delta, one = self._delta(colours)
        return (colours + delta).clamp(0, 1), one

    def explains(self, original, edited, tol=0.1):
        delta, _ = self._delta(original)
        return ((original + delta).clamp(0, 1) - edited).abs().amax(-1) <= tol


class LocalLinear:
    """Local-linear kernel regression on the grid (module docstring)."""

    RIDGE = 0.1  # slope ridge, as a share of the tent's own colour variance (h^2 / 6) times the weight

    def __init__(self, original, edited, grid=17):
        original, edited = original.reshape(-1, 3).float(), edited.reshape(-1, 3).float()
        self.grid = grid
        h = 1.0 / (grid - 1)
        G = grid ** 3
        XX, XD, DD = torch.zeros(G, 16), torch.zeros(G, 12), torch.zeros(G, 3)
        for s in range(0, original.shape[0], 1 << 17):  # chunks: [n,8,16] per pixel is large
            o, e = original[s:s + (1 << 17)], edited[s:s + (1 << 17)]
            n = o.shape[0]
            idx, w = _corners(o, grid)  # [n,8]
            u = (o[:, None, :] - self._node_colour(idx)) / h  # in cells, within [-1, 1]
            d = (e - o)[:, None, :].expand(n, 8, 3)
            x = torch.cat([torch.ones(n, 8, 1), u], -1)  # [n,8,4]
            flat = idx.reshape(-1)
            wx = x * w[..., None]
            XX.index_add_(0, flat, (wx[..., :, None] * x[..., None, :]).reshape(-1, 16))
            XD.index_add_(0, flat, (wx[..., :, None] * d[..., None, :]).reshape(-1, 12))
            DD.index_add_(0, flat, (w[..., None] * d * d).reshape(-1, 3))
        XX, XD = XX.view(G, 4, 4), XD.view(G, 4, 3)
        S0 = XX[:, 0, 0]
        reg = torch.diag(torch.tensor([0.0, 1.0, 1.0, 1.0])) * (self.RIDGE / 6.0) * S0[:, None, None]
        A = XX + reg + 1e-6 * torch.eye(4)
        beta = torch.linalg.solve(A, XD)  # [G,4,3]
        rss = (DD - 2 * (beta * XD).sum(1) + (beta * (XX @ beta)).sum(1)).clamp_min(0.0)  # per channel
        self.beta, self.rss, self.S0, self.h = beta, rss, S0, h

    def _node_colour(self, idx):
        g = self.grid
        k = torch.stack([idx // (g * g), (idx // g) % g, idx % g], -1).float()
        return k / (g - 1)

    def lookup(self, colours):
        colours = colours.reshape(-1, 3).float()
        idx, w = _corners(colours, self.grid)
        u = (colours[:, None, :].clamp(0, 1) - self._node_colour(idx)) / self.h
        x = torch.cat([torch.ones(*u.shape[:2], 1), u], -1)  # [N,8,4]
        m = (x[..., :, None] * self.beta[idx]).sum(-2)  # [N,8,3] each corner's model at the colour
        ws = w * self.S0[idx]
        den = ws.sum(1)
        safe = den.clamp_min(1e-12)[:, None]
        mean = (ws[..., None] * m).sum(1) / safe
        var = ((w[..., None] * self.rss[idx]).sum(1) + (ws[..., None] * (m - mean[:, None]) ** 2).sum(1)) / safe
        covered = (den >= MIN_SUPPORT)[:, None]
        zero = torch.zeros_like(mean)
        return torch.where(covered, mean, zero), den, torch.where(covered, var, zero).amax(-1).sqrt()

    def apply_where_one_change(self, colours):
        delta, support, spread = self.lookup(colours)
        one = (support >= MIN_SUPPORT) & (spread <= SPREAD_SHARE * delta.abs().amax(-1))
        return (colours + delta).clamp(0, 1), one

    def explains(self, original, edited, tol=0.1):
        delta, _, _ = self.lookup(original)
        return ((original + delta).clamp(0, 1) - edited).abs().amax(-1) <= tol


def variants(P, E):
    """name -> a map-like object (None: the edited image itself)."""
    base = fit_colour_change(P, E)
    return {
        "edited": lambda: None,
        "no_spread": lambda: NoSpread(base),
        "current": lambda: base,
        "multires": lambda: MultiRes(P, E),
        "multires_lib": lambda: fit_colour_change(P, E, levels=3),  # the library's (EditConfig.map_levels=3)
        "loclin": lambda: LocalLinear(P, E),
        "current+change": lambda: base,
        "multires_lib+change": lambda: fit_colour_change(P, E, levels=3),
    }


# ----------------------------------------------------------------------------- figures
def psnr(a, b, mask) -> float:
    if not bool(mask.any()):
        return float("nan")
    mse = float(((a - b) ** 2)[mask].mean())
    return CAP if mse <= 10 ** (-CAP / 10) else -10 * math.log10(mse)


def figures(m, P, E, R, rule: RecolorRule, changed, fallback: str = "edited") -> dict:
    """``fallback``: the target where the map is not used, ``E`` (``edited``) or ``R + E - P`` (``change``)."""
    flat_p, flat_e, flat_r = P.reshape(-1, 3), E.reshape(-1, 3), R.reshape(-1, 3)
    T = recolor(R, rule)[0].reshape(-1, 3)
    ch = changed.reshape(-1)
    unchanged_r = ~rule_mask(R, rule).reshape(-1)
    if m is None:
        target, use, leaked = flat_e, torch.zeros_like(ch), flat_r
    else:
        mapped, one = m.apply_where_one_change(flat_r)
        use = m.explains(flat_p, flat_e) & one
        other = flat_e if fallback == "edited" else (flat_r + flat_e - flat_p).clamp(0, 1)
        target = torch.where(use[:, None], mapped, other)
        leaked = torch.where(one[:, None], mapped, flat_r)
    return {"use": float(use[ch].float().mean()), "target": psnr(target, T, ch),
            "leak": psnr(leaked, flat_r, unchanged_r)}


def verdict(rows: list[dict]) -> dict:
    """The reproduction checks and, per candidate, the decision rule's failures (module docstring)."""
    by = {(r["scene"], r["variant"]): r for r in rows}
    scenes = sorted({r["scene"] for r in rows}, key=[r["scene"] for r in rows].index)
    keys = [f"s{s:g}" for s in BLURS]
    out = {}
    if ("cup", "no_spread") in by and ("cup", "current") in by:
        out["cup: no_spread beats current on target"] = all(
            by["cup", "no_spread"][f"target_{k}"] > by["cup", "current"][f"target_{k}"] for k in keys)
    if ("fern", "no_spread") in by and ("fern", "current") in by:
        out["fern: no_spread worse than current on target or leak"] = {
            fig: any(by["fern", "no_spread"][f"{fig}_{k}"] < by["fern", "current"][f"{fig}_{k}"] for k in keys)
            for fig in ("target", "leak")}
    for cand in sorted({r["variant"] for r in rows} - {"edited", "no_spread", "current"}):
        fails = []
        for sc in scenes:
            c, cur = by.get((sc, cand)), by.get((sc, "current"))
            if c is None or cur is None:
                continue
            for k in keys:
                for fig in ("target", "leak"):
                    if c[f"{fig}_{k}"] < cur[f"{fig}_{k}"] - 0.1:
                        fails.append(f"{sc} {fig} {k}: {c[f'{fig}_{k}']:.2f} < {cur[f'{fig}_{k}']:.2f} - 0.1")
                if sc == "cup" and not c[f"target_{k}"] > cur[f"target_{k}"]:
                    fails.append(f"cup target {k} not higher")
        out[cand] = {"wins": not fails, "fails": fails}
    return out


def main(argv=None) -> dict:
    from virgi_ns.bench.evalset import EVAL_SET
    from virgi_ns.edit.engine import EditConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--synthetic", action="store_true")
    ap.add_argument("--synthetic-root", type=Path, default=Path("/tmp/virgi_syn"))
    ap.add_argument("--scenes", nargs="*", default=[])
    ap.add_argument("--variants", nargs="*", default=[])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "colour_map_proxy.json")
    args = ap.parse_args(argv)
    torch.set_grad_enabled(False)
    tol = EditConfig().unchanged_tol
    rows = []
    for scene in EVAL_SET:
        if (scene.synthetic and not args.synthetic) or (args.scenes and scene.name not in args.scenes):
            continue
        P, name = scene_photo(scene, args.data, args.synthetic_root)
        E = recolor(P, scene.rule)[0]
        changed = (E - P).abs().amax(-1) > tol
        for name_v, make in variants(P, E).items():
            if args.variants and name_v not in args.variants:
                continue
            t0 = time.perf_counter()
            m = make()
            row = {"scene": scene.name, "view": name, "changed_share": float(changed.float().mean()), "variant": name_v}
            for sigma in BLURS:
                f = figures(m, P, E, blur(P, sigma), scene.rule, changed,
                            "change" if name_v.endswith("+change") else "edited")
                row.update({f"{k}_s{sigma:g}": v for k, v in f.items()})
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
            print(f"{scene.name:16s} {name_v:10s} " + "  ".join(
                f"s{s:g}: use {row[f'use_s{s:g}']:.3f} target {row[f'target_s{s:g}']:6.2f} leak {row[f'leak_s{s:g}']:6.2f}"
                for s in BLURS), flush=True)
    v = verdict(rows)
    print(json.dumps(v, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"blurs": BLURS, "rows": rows, "verdict": v}, indent=1))
    return {"rows": rows, "verdict": v}


if __name__ == "__main__":
    main()
