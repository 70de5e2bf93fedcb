"""Which criterion of the pick's selection (:func:`virgi_ns.edit.pick.select`) stops its growth, measured
apart on CPU runs, and candidate selections judged by a rule fixed before they were tried.

**Runs.** The synthetic scenes of the evaluation set (:mod:`virgi_ns.bench.synthetic`: their captures
written by :func:`~virgi_ns.bench.evalset.capture_folder`, their known geometry imported and only the
colour stage trained, as ``bench/edit.py`` trains them, here with ``--colour-steps`` steps, fewer than
the set's 1000 on a CPU), and optionally trained runs given by ``--runs NAME CONFIG`` (e.g. the demo's
beercan run: ``demo_out/run/config.yml`` with the beercan rule). The edit view is the set's
(:func:`~virgi_ns.bench.evalset.edit_view`); the click is the GPU benchmark's (:mod:`virgi_ns.bench.pick`:
the deepest covered pixel of the largest component of the rule's mask on the edit view's render);
tolerance :data:`~virgi_ns.bench.pick.TOLERANCE` (0.2). The reference is the rule's mask on that render
(covered pixels); on the synthetic scenes also the target object's pixels (the capture's labels).

**Criteria measured apart** (all with coverage >= ``MIN_COVER`` and 8-connectivity to the click):
``current`` (colour and features, the shipped :func:`select`), ``colour`` (the diffuse colour's angle
only), ``features`` (the ``h_diff`` features' angle only), ``neither`` (coverage and connectivity only).
For each, the IoU with the rule's mask; and the 50/90/99th percentiles of each angle to the click's
vector over the rule mask's covered pixels and over the covered pixels outside it.

**Decision rule** (written before any candidate was tried): a candidate selection becomes the default
when, on every scene measured here, its IoU with the rule's mask is at least the current select's minus
0.01 (no scene gets worse beyond noise), on every scene where the current one's IoU is below 0.9 it is
higher by at least 0.05 (a real gain where the pick fails), and tests/test_pick.py (two objects of
different colours side by side stay apart) still passes. Constants inside a candidate are fixed by a
reason written beside it, never chosen by their scores here.

**Candidates** (:data:`CANDIDATES`), each at the same tolerance t = 0.2:

- ``chroma``: the diffuse colour compared in a shading-free chromaticity: each pixel's RGB divided by
  its sum (r, g, b chromaticity, which a uniform scaling of the colour, i.e. shading, does not move),
  the angle between the chromaticity vectors' offsets from grey (1/3, 1/3, 1/3) within t x 90 degrees
  (the offset's direction is the hue), and the offset's length (the chroma) within a factor
  ``1 + 4t`` of the click's either way (two tones of one hue: a pale and a deep one; 4t = 0.8 at the
  default, i.e. from 0.56x to 1.8x, and 1 + 4 = 5x at t = 1: the same scale of "how much" as t x 90
  degrees takes for hue); no features.
- ``features_z``: the current rule with the features standardised per dimension over the view's
  covered pixels first (each dimension's mean removed and divided by its standard deviation), so a
  few large dimensions that vary with position or shading no longer dominate the angle.
- ``region``: region growing: start from the current select's selection, then repeatedly admit
  connected covered pixels whose diffuse chromaticity (as ``chroma``) and standardised features lie
  within 3 standard deviations (per dimension, of the selection so far; a normal variable's 99.7%)
  of the selection's mean, until nothing joins (at most 8 rounds).
- ``chroma_steps``: ``chroma`` with the chroma compared step by step instead of to the click's: a
  pixel joins when its hue is within t x 90 degrees of the click's (as ``chroma``), its chroma is at
  least :data:`~virgi_ns.edit.pick.NEUTRAL_CHROMA` (below it the chromaticity's direction is no hue) and within a factor
  ``1 + 4t`` of that of an 8-neighbour already selected. Why: on the demo's beercan run ``chroma``
  stops at the click's tone (its chroma is the rule mask's 87th percentile; 59% of the mask is paler
  than the click / 1.8), while the can's pale and deep blues meet through gradual blends (print and
  highlights mixed into a pixel keep the hue and lower the chroma); another object of the same hue
  (the dark vase's pale blue-grey block) meets the clicked one at an edge, an abrupt step. A neutral
  click (chroma below the floor) has no hue: the current select decides.

**Without training** (``--direct SPACING VIEWS W H STEPS``, :func:`direct_scene`): on a shared 2-core
CPU a colour stage of 300 steps on a small capture (24 views, 240x180, spacing 0.025) ran at 2-18 s a
step and did not finish; this mode fits each synthetic scene's colour field (the model's default
config) directly to its Gaussians' known diffuse colours and measures on the diffuse render (no trained
specular part), the edit view being the one of VIEWS ring cameras whose diffuse render the rule takes
most. A proxy: its features are those of a field fitted to exact colours, not of a photometric run.

Prints a table and writes JSON (``--out``)::

    PYTHONPATH=. .venv/bin/python bench/pick_criteria.py --out bench_out/pick_criteria.json
    PYTHONPATH=. .venv/bin/python bench/pick_criteria.py --direct 0.025 8 240 180 300 --scenes syn_duck_beak

**Measured** (CPU, 2026-11-24, ``--direct 0.025 8 240 180 300 --scenes syn_duck_beak``, 8.8 min on a
loaded machine; JSON: ``bench/results/pick_criteria_cpu_duck.json``; the only scene measured): IoU with
the rule mask current 0.048, colour alone 0.048, features alone 0.029, neither 0.017; chroma 0.925,
features_z 0.562, region 0.029. Here the current select does not stop early, it leaks: 36% of the view
selected, 95% of it outside the rule's mask; the RGB angle lets the yellow duck run into the warm floor
(colour angle p50/90/99 over the rule's pixels 0.0/4.6/18.0, outside 18.3/32.5/57.9 degrees, i.e. the
18-degree limit sits at the outside's median), the features angle is no better (outside p50 10.7). The
chromaticity's hue angle separates them (inside 0.0/2.9/10.7, outside 23.4/158/173). ``chroma`` meets the
IoU part of the rule on this one scene, and the selection checks of tests/test_pick.py (the blue sphere
whole and alone, the green one alone) hold with it; it was not made the default: one proxy scene, whose
failure (a leak) is not the one the H100 runs showed (a selection stopped short, 0.9-1.7% selected).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable, Dict

import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from virgi_ns.bench.evalset import capture_folder, edit_view, find  # noqa: E402
from virgi_ns.bench.pick import TOLERANCE, click_pixel, coverage  # noqa: E402
from virgi_ns.edit.pick import MIN_COVER, ViewMaps, _angle, chromaticity, select, view_maps  # noqa: E402
from virgi_ns.edit.recolor import rule_mask  # noqa: E402

SYNTHETIC = ["syn_mug_handle", "syn_toy_on_white", "syn_dark_vase", "syn_pastel_cushion", "syn_glossy_ball",
             "syn_duck_beak"]
QUANTILES = (0.5, 0.9, 0.99)


def _bench_edit():
    """bench/edit.py as a module (its run_config trains a scene as the GPU benchmark does)."""
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location("bench_edit", ROOT / "bench" / "edit.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_edit"] = mod
    spec.loader.exec_module(mod)
    return mod


# ------------------------------------------------------------------------------ selections
def grow(allowed: Tensor, x: int, y: int, seed: Tensor | None = None) -> Tensor:
    """Bool [H,W]: the 8-connected part of ``allowed`` that holds (x, y) (or the pixels of ``seed``)."""
    allowed = allowed.clone()
    allowed[y, x] = True
    grown = torch.zeros_like(allowed) if seed is None else seed.clone()
    grown[y, x] = True
    g, free = grown[None, None].float(), allowed[None, None].float()
    while True:
        before = g
        for _ in range(8):
            g = torch.nn.functional.max_pool2d(g, 3, 1, 1) * free
        if torch.equal(g, before):
            return g[0, 0] > 0


def standardised(features: Tensor, covered: Tensor) -> Tensor:
    """Features with each dimension's mean over ``covered`` removed, divided by its standard deviation."""
    f = features[covered]
    return (features - f.mean(0)) / f.std(0).clamp_min(1e-6)


def crit_maps(m: ViewMaps, x: int, y: int) -> Dict[str, Tensor]:
    """The angles (degrees) of each pixel's vectors to the click's."""
    cov = m.accumulation >= MIN_COVER
    ch = chromaticity(m.diffuse)
    fz = standardised(m.features, cov)
    return {"colour": _angle(m.diffuse, m.diffuse[y, x]), "features": _angle(m.features, m.features[y, x]),
            "hue": _angle(ch, ch[y, x]), "features_z": _angle(fz, fz[y, x])}


def sel_current(m, x, y, t):
    return select(m, x, y, t, "colour_features")


def sel_colour(m, x, y, t):
    cov = m.accumulation >= MIN_COVER
    return grow(cov & (_angle(m.diffuse, m.diffuse[y, x]) <= 90.0 * t), x, y)


def sel_features(m, x, y, t):
    cov = m.accumulation >= MIN_COVER
    return grow(cov & (_angle(m.features, m.features[y, x]) <= 90.0 * t), x, y)


def sel_neither(m, x, y, t):
    return grow(m.accumulation >= MIN_COVER, x, y)


def sel_chroma(m, x, y, t):
    cov = m.accumulation >= MIN_COVER
    ch = chromaticity(m.diffuse)
    n, n0 = ch.norm(dim=-1), ch[y, x].norm()
    ratio = 1.0 + 4.0 * t
    ok = cov & (_angle(ch, ch[y, x]) <= 90.0 * t) & (n <= n0 * ratio) & (n >= n0 / ratio)
    return grow(ok, x, y)


def sel_features_z(m, x, y, t):
    cov = m.accumulation >= MIN_COVER
    fz = standardised(m.features, cov)
    ok = cov & (_angle(m.diffuse, m.diffuse[y, x]) <= 90.0 * t) & (_angle(fz, fz[y, x]) <= 90.0 * t)
    return grow(ok, x, y)


def sel_region(m, x, y, t, k: float = 3.0, rounds: int = 8):
    cov = m.accumulation >= MIN_COVER
    v = torch.cat([chromaticity(m.diffuse), standardised(m.features, cov)], -1)
    sel = select(m, x, y, t, "colour_features")
    for _ in range(rounds):
        s = v[sel]
        mu, sd = s.mean(0), s.std(0).clamp_min(1e-6) if len(s) > 1 else torch.ones_like(s[0])
        ok = cov & ((v - mu).abs() <= k * sd).all(-1)
        new = grow(ok | sel, x, y, sel)
        if torch.equal(new, sel):
            break
        sel = new
    return sel


def sel_chroma_steps(m, x, y, t):
    return select(m, x, y, t, "chroma_steps")


CRITERIA: Dict[str, Callable] = {"current": sel_current, "colour": sel_colour, "features": sel_features,
                                 "neither": sel_neither}
CANDIDATES: Dict[str, Callable] = {"chroma": sel_chroma, "features_z": sel_features_z, "region": sel_region,
                                   "chroma_steps": sel_chroma_steps}


# ------------------------------------------------------------------------------ measurement
def iou(a: Tensor, b: Tensor) -> float:
    u = int((a | b).sum())
    return int((a & b).sum()) / u if u else math.nan


def _diffuse_render(scene, cam) -> Tensor:
    from virgi_ns.edit.scene import render_view

    return render_view(scene, cam, 0)["diffuse"].clamp(0, 1)


def measure(name: str, scene, cam, rule, labels: Tensor | None, target: int | None, use_diffuse: bool = False) -> dict:
    """``use_diffuse``: the rule's mask and the click on the diffuse render (a field without a
    trained specular part)."""
    from virgi_ns.edit.engine import EditEngine
    from virgi_ns.edit.pick import pick_config
    from virgi_ns.edit.scene import render_view

    render = render_view(scene, cam, 0)["diffuse" if use_diffuse else "rgb"].clamp(0, 1)
    cov = coverage(scene, cam) >= MIN_COVER
    mask = rule_mask(render, rule) & cov
    x, y, depth = click_pixel(mask)
    m = view_maps(EditEngine(scene, cam, None, None, pick_config(scene.device)))
    out = {"scene": name, "pixel": [x, y], "depth": depth, "image": list(render.shape[:2]),
           "rule_share": float(mask.float().mean())}
    angles = crit_maps(m, x, y)
    out["angles"] = {k: {"in_rule": [float(torch.quantile(a[mask], q)) for q in QUANTILES],
                         "outside": [float(torch.quantile(a[cov & ~mask], q)) for q in QUANTILES]
                         if bool((cov & ~mask).any()) else []}
                     for k, a in angles.items()}
    obj = None if labels is None else (labels == target) & cov
    sels = {}
    for k, fn in {**CRITERIA, **CANDIDATES}.items():
        t0 = time.perf_counter()
        s = fn(m, x, y, TOLERANCE)
        sels[k] = {"iou": iou(s, mask), "selected": float(s.float().mean()), "s": time.perf_counter() - t0,
                   "outside_rule": float((s & ~mask).sum() / max(int(s.sum()), 1))}
        if obj is not None:
            sels[k]["iou_object"] = iou(s, obj)
    out["selections"] = sels
    return out


def direct_scene(name: str, spacing: float, views: int, width: int, height: int, steps: int):
    """A synthetic scene without photometric training (a CPU's budget): its known Gaussians, the
    colour field (the model's default config) fitted directly to each Gaussian's known diffuse colour
    (albedo x Lambert shade, as a logit; no specular part), as tests/edit_scene.py fits its scene.
    Returns (scene, ``views`` ring cameras, the spec, the label names, the fit's last loss, each
    Gaussian's label)."""
    from virgi_ns.bench.synthetic import SCENES, gaussians_of, scene_cameras, surface_points
    from virgi_ns.colour.field import ColorFieldConfig, DecoupledColorField
    from virgi_ns.edit.scene import FrozenScene

    spec = SCENES[name.removeprefix("syn_")]
    pts = surface_points(spec, spacing)
    g = gaussians_of(pts, spacing)
    L = torch.nn.functional.normalize(torch.tensor(spec.light, dtype=torch.float64), dim=0)
    lambert = 0.45 + 0.55 * (pts.normals @ L).clamp_min(0.0)
    shade = torch.where(pts.lit, lambert, torch.full_like(lambert, 0.95))
    target = torch.logit((pts.albedo * shade[:, None]).clamp(1e-3, 1 - 1e-3)).float()
    torch.manual_seed(0)
    field = DecoupledColorField(ColorFieldConfig(), torch.stack([g.means.min(0).values, g.means.max(0).values]))
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    with torch.enable_grad():
        for _ in range(steps):
            loss = ((field.diffuse(field.diffuse_hidden(field.encode(g.means))[1]) - target) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    field.eval()
    for q in field.parameters():
        q.requires_grad_(False)
    scene = FrozenScene(g.means, torch.nn.functional.normalize(g.quats, dim=-1), torch.exp(g.scales),
                        torch.sigmoid(g.opacities), field, torch.zeros(3), backend="reference")
    names = sorted(set(pts.labels))
    return scene, scene_cameras(spec, views, width, height), spec, names, float(loss), pts.labels


def load(config: Path):
    from virgi_ns.nerfstudio.runs import load_run
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.nerfstudio.cameras import raster_cameras

    _, pipeline = load_run(config)
    train = pipeline.datamanager.train_dataset
    return pipeline, train, FrozenScene.from_model(pipeline.model), raster_cameras


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="*", default=SYNTHETIC)
    p.add_argument("--runs", nargs=2, action="append", default=[], metavar=("SCENE", "CONFIG"),
                   help="a trained run for a row of the evaluation set (its rule), "
                        "e.g. beercan demo_out/run/config.yml")
    p.add_argument("--train-out", type=Path, default=Path("bench_out/pick_criteria_runs"))
    p.add_argument("--colour-steps", type=int, default=300)
    p.add_argument("--synthetic-size", nargs=4, type=float, default=None, metavar=("VIEWS", "W", "H", "SPACING"),
                   help="smaller synthetic captures for a CPU (default: the set's, 48 400 300 0.015)")
    p.add_argument("--out", type=Path, default=Path("bench_out/pick_criteria.json"))
    p.add_argument("--direct", nargs=5, type=float, default=None, metavar=("SPACING", "VIEWS", "W", "H", "STEPS"),
                   help="no training: the synthetic scenes' fields fitted directly to the known diffuse colours "
                        "(direct_scene); the edit view: the view whose diffuse render the rule takes most")
    a = p.parse_args()
    torch.set_grad_enabled(False)
    be = _bench_edit()
    args = be.Args(train_out=a.train_out, colour_steps=a.colour_steps)
    if a.synthetic_size:
        v, w, h, sp = a.synthetic_size
        args.synthetic_size = (int(v), int(w), int(h), float(sp))
    jobs = [(s, None) for s in a.scenes] + [(s, Path(c)) for s, c in a.runs]
    rows = []
    if a.direct:
        jobs = []
        sp, nv, w, h, st = a.direct
        for name in a.scenes:
            t0 = time.perf_counter()
            scene, cams, spec, names, loss, _ = direct_scene(name, sp, int(nv), int(w), int(h), int(st))
            shares = [int(rule_mask(_diffuse_render(scene, cams.index(i)), spec.rule).sum()) for i in range(len(cams))]
            best = max(range(len(cams)), key=lambda i: (shares[i], -i))
            row = measure(name, scene, cams.index(best), spec.rule, None, None, use_diffuse=True)
            row.update(direct=list(a.direct), fit_loss=loss, edit_view=best, gaussians=int(scene.means.shape[0]),
                       s=time.perf_counter() - t0)
            rows.append(row)
            print_row(row)
    for name, config in jobs:
        sc = find([name])[0]
        folder = None
        if config is None:
            folder = capture_folder(sc, args.data, args.train_out / "captures", "cpu", None, args.synthetic_size)
            torch.set_grad_enabled(True)
            config = be.run_config(args, sc, folder)
            torch.set_grad_enabled(False)
        pipeline, train, scene, raster_cameras = load(config)
        view = edit_view([train.get_image_float32(i)[..., :3] for i in range(len(train))], sc.rule)
        cam = raster_cameras(train.cameras[view: view + 1]).to(scene.device)
        labels = target = None
        if folder is not None and (folder / "labels").is_dir():
            from virgi_ns.bench.recolor import _read_labels

            info = json.loads((folder / "scene.json").read_text())
            labels = _read_labels(folder / "labels" / Path(train.image_filenames[view]).name, scene.device)
            target = info["labels"].index(info["target"])
        row = measure(name, scene, cam, sc.rule, labels, target)
        ckpt = sorted(f.name for f in (config.parent / "nerfstudio_models").glob("step-*.ckpt"))[-1:]
        row.update(config=str(config), edit_view=view, checkpoint=ckpt,
                   synthetic_size=list(args.synthetic_size) if folder else None)
        rows.append(row)
        print_row(row)
        del pipeline, scene
    verdict = decide(rows)
    print_table(rows, verdict)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"tolerance": TOLERANCE, "rows": rows, "verdict": verdict}, indent=1))
    print(f"wrote {a.out}")


def decide(rows: list) -> dict:
    """Each candidate's failures of the module docstring's rule (the test is run apart)."""
    out = {}
    for c in CANDIDATES:
        fails = []
        for r in rows:
            cur, new = r["selections"]["current"]["iou"], r["selections"][c]["iou"]
            if new < cur - 0.01:
                fails.append(f"{r['scene']}: IoU {new:.3f} < current {cur:.3f} - 0.01")
            elif cur < 0.9 and new < cur + 0.05:
                fails.append(f"{r['scene']}: IoU {new:.3f} < current {cur:.3f} + 0.05")
        out[c] = {"passes_ious": not fails, "failures": fails}
    return out


def print_row(r: dict) -> None:
    print(f"\n{r['scene']} (click {r['pixel']}, depth {r['depth']}, rule mask {100 * r['rule_share']:.1f}%)")
    for k, a in r["angles"].items():
        q = lambda v: "/".join(f"{x:5.1f}" for x in v) if v else "-"  # noqa: E731
        print(f"  angle {k:10s} p50/90/99 in rule {q(a['in_rule'])}   outside {q(a['outside'])}")


def print_table(rows: list, verdict: dict) -> None:
    names = list(CRITERIA) + list(CANDIDATES)
    print("\nIoU with the rule mask (with the target object's pixels) at tolerance", TOLERANCE)
    print(f"{'scene':22s}" + "".join(f"{n:>16s}" for n in names))
    for r in rows:
        cells = []
        for n in names:
            s = r["selections"][n]
            o = f" ({s['iou_object']:.2f})" if "iou_object" in s else ""
            cells.append(f"{s['iou']:.3f}{o}")
        print(f"{r['scene']:22s}" + "".join(f"{c:>16s}" for c in cells))
    for c, v in verdict.items():
        print(f"{c}: {'passes the IoU part of the rule' if v['passes_ious'] else 'fails: ' + '; '.join(v['failures'])}")


if __name__ == "__main__":
    main()
