"""Benchmark (GPU): the edit engine on real captures, and its speed on a 1M-Gaussian scene.

Per scene (beercan, fern, cup; trained VIRGi runs), one training photo recoloured by a fixed HSV
rule is the edit (:mod:`virgi_ns.bench.recolor`), and the held-out views are measured:

  recolour PSNR/SSIM/LPIPS   edited render vs the rule on the held-out photos (beside the unedited PSNR)
  propagation PSNR           edited render vs the rule on the model's own unedited renders,
                             split into miss (inside the rule's mask) and leak (outside)
  edit time                  setup and steps separately, median of --repeats after a warm-up;
                             cold (hash grid + MLP_diff run for the view's Gaussians) and with the
                             scene's (f, h1, h_diff) cached, as a viewer session keeps them

Issue 5's targets, checked on every scene: propagation >= 35 dB, miss and leak >= 30 dB, recolour
PSNR within 0.5 dB of the unedited PSNR, edit wall time <= 0.25 s. Beside them, the recolour PSNR
a perfect edit would get (the rule on the render against the rule on the photo: the rule's
thresholds can widen the reconstruction error), and the propagation figures of an object-level reference: the
rule applied to every Gaussian's colour instead of to pixels (where a pixel blends recoloured and untouched
Gaussians, no per-Gaussian edit can match the per-pixel rule). beercan also gets the accuracy-time sweep
(JSON + PNG). ``--compare`` and ``--variants`` add rows measured on the same trained runs (other
fits, earlier rules, other EditConfig settings). Pictures: ``<scene>_view<i>.png`` = unedited | edited | truth (rule on the render) |
segmentation, for the first held-out views. A synthetic 1M-Gaussian scene at 1280x720 is timed too.

    python bench/edit.py --runs beercan bench_out/train/runs/beercan-virgi/virgi/run/config.yml \\
        fern CFG cup CFG --out bench_out/edit

A scene whose config is not given is looked up at ``<train-out>/runs/<scene>-virgi/virgi/run/config.yml``
(what ``bench/train.py`` writes); ``--train-missing`` trains it first (``--geometry-steps``,
``--colour-steps``).
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import torch
import tyro
from rich.console import Console
from rich.table import Table

from virgi_ns.bench.recolor import AccuracyTime, Bench, RuleArgs, _save_png, run_accuracy_time
from virgi_ns.bench.settings import split_settings, typed_like
from virgi_ns.errors import InputError, atomic_path, cli_entry

console = Console()

RULES: Dict[str, RuleArgs] = {
    # the can's blue -> red, the whole can (its pale blue back needs s_min 0.1); near-white
    # highlights and the grey-white floor are outside the rule
    "beercan": RuleArgs(h0=190.0, h1=250.0, shift=150.0, s_min=0.1, v_min=0.15),
    # the fern's green leaves -> blue (s_min low enough to take the pale leaves too: with 0.25 the
    # rule split the fern into shifted and unshifted leaves). A thin frond's pixels mix its green
    # with the background; the further the shift, the further the rule on a mixed pixel lands from
    # the mix of the shifted frond and the background, which no edit of the scene can produce
    # (bench/RESULTS.md, "Choosing the fern and cup rules": a 200-degree shift capped even a
    # per-Gaussian edit lower than this 120-degree one)
    "fern": RuleArgs(h0=60.0, h1=160.0, shift=120.0, s_min=0.12, v_min=0.1),
    # every warm tone -> green: the wooden shelf and the whole cup, beige and print (the cup's beige
    # and the sunlit shelf share hue; thresholds near zero leave no saturation or value edge
    # across the cup, so nothing there flips between shifted and unshifted from view to view; the
    # near-grey wall pixels the low thresholds take in barely move under a hue shift)
    "cup": RuleArgs(h0=0.0, h1=80.0, shift=120.0, s_min=0.02, v_min=0.02),
}
# the earlier rules (bench/RESULTS.md), measured again beside the current ones (--compare)
EARLIER_RULES: Dict[str, RuleArgs] = {
    # the can's deep blue only: the pale back and parts of the print fall on either side of s = 0.35
    "beercan": RuleArgs(h0=190.0, h1=250.0, shift=150.0, s_min=0.35, v_min=0.15),
    # the same leaves -> magenta
    "fern": RuleArgs(h0=60.0, h1=160.0, shift=200.0, s_min=0.12, v_min=0.1),
    # warm tones above s = 0.08 -> blue (the threshold ran through the cup's beige)
    "cup": RuleArgs(h0=5.0, h1=65.0, shift=190.0, s_min=0.08, v_min=0.15),
}
# fits measured on the same trained run with --compare: EditConfig fields (rule: the scene's)
VARIANTS: Dict[str, dict] = {
    "fit the render plus the change": {"changed_target": "change"},
    "fit the whole photo": {"whole_image": True},
}


@dataclass
class Args:
    runs: Dict[str, Path] = field(default_factory=dict)
    """Pairs 'scene config.yml' of trained VIRGi runs."""
    scenes: List[str] = field(default_factory=lambda: ["beercan", "fern", "cup"])
    out: Path = Path("bench_out/edit")
    train_out: Path = Path("bench_out/train")
    """Where bench/train.py put its runs (used for scenes not in --runs)."""
    train_missing: bool = False
    """Train a VIRGi run for scenes that have none (needs --data)."""
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    geometry_steps: int = 30000
    colour_steps: int = 10000
    edit_view: int = 0
    steps: Optional[int] = None
    """Edit steps (default: the engine's)."""
    repeats: int = 5
    whole_photo: bool = False
    """Fit the whole edited photo instead of only the pixels the rule recoloured."""
    max_views: int = 0
    pictures: int = 3
    sweep: bool = True
    """The accuracy-time sweep on beercan."""
    million: bool = True
    """Time the engine on a synthetic 1M-Gaussian scene at 1280x720."""
    variants: List[str] = field(default_factory=list)
    """More rows on the same runs, each a comma-separated list of EditConfig fields, e.g.
    'steps=200,seg_init_bias=-2', and/or another rule, 'rule=h0/h1/shift/s_min/v_min' (one timed
    fit each, no pictures). An entry that starts with 'SCENE:' (e.g. 'fern:rule=65/170/120/0.05/0.05')
    is measured on that scene only."""
    compare: bool = False
    """Also measure, on the same trained runs: the earlier sessions' rules and the fit variants
    of VARIANTS (one timed fit each, no pictures)."""


def variant_scene(text: str) -> tuple:
    """'fern:rule=...' -> ('fern', 'rule=...'); an entry without a scene prefix -> (None, text)."""
    head, sep, rest = text.partition(":")
    if sep and "=" not in head and "," not in head:
        if not rest.strip():
            raise InputError(f"--variants: '{text}' names a scene but no settings")
        return head.strip(), rest
    return None, text


def check_variant(text: str, scenes: List[str]) -> None:
    """Refuse a --variants entry before any training: bad settings, or a scene prefix that names
    no scene of this run (it would be skipped without a word)."""
    only, rest = variant_scene(text)
    if only is not None and only not in scenes:
        raise InputError(f"--variants: '{text}' names '{only}', which is not among --scenes ({', '.join(scenes)})")
    parse_variant(rest)


def parse_variant(text: str) -> dict:
    """'steps=200,seg_init_bias=-2' -> EditConfig fields, typed as the fields' defaults are, checked
    as EditConfig checks them; 'rule=h0/h1/shift/s_min/v_min' -> another rule (key ``rule``)."""
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
        if not hasattr(defaults, key):
            raise InputError(f"--variants: '{key}' is not an EditConfig field")
        out[key] = typed_like(getattr(defaults, key), value, key, "--variants")
    try:
        EditConfig(**{k: v for k, v in out.items() if k != "rule"})
    except ValueError as e:
        raise InputError(f"--variants: {e}") from None
    return out


def _config_for(args: Args, scene: str) -> Path:
    if scene in args.runs:
        return args.runs[scene]
    cfg = args.train_out / "runs" / f"{scene}-virgi" / "virgi" / "run" / "config.yml"
    if cfg.is_file() or not args.train_missing:
        return cfg
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from train import dataparser_for, quiet, train  # bench/train.py

    from method_configs.virgi import virgi_trainer_config

    c = virgi_trainer_config("virgi", geometry_steps=args.geometry_steps, colour_steps=args.colour_steps)
    c.pipeline.datamanager.dataparser = dataparser_for(scene, args.data)
    quiet(c, args.train_out, f"{scene}-virgi")
    console.log(f"training {scene} ({args.geometry_steps} + {args.colour_steps} steps)")
    trainer, secs, _, _ = train(c)
    console.log(f"trained {scene} in {secs:.0f} s")
    del trainer
    torch.cuda.empty_cache()
    return Path(c.get_base_dir()) / "config.yml"


def bench_scene(args: Args, scene: str) -> List[dict]:
    """The scene's row (engine defaults, pictures, cold and cached timing, the sweep on beercan),
    then one row per --compare and --variants entry (timed once, before the feature cache)."""
    from virgi_ns.cli.edit import load_run

    cfg = _config_for(args, scene)
    if not cfg.is_file():
        raise InputError(f"{scene}: no run at {cfg} (pass --runs {scene}=CONFIG or --train-missing)")
    _, pipeline = load_run(cfg)
    rule = RULES[scene].rule()
    b = Bench.load(pipeline, args.edit_view, args.max_views)
    edited = b.edited_image(rule, "photo")
    original = b.original("photo")
    edit, cold = b.fit(edited, args.steps, None, args.repeats, original, args.whole_photo)
    # the other fits first: their one timed run is cold too (before the feature cache below)
    extra = []
    variants = []
    if args.compare:
        variants = [(name, rule, dict(fields)) for name, fields in VARIANTS.items()]
        if scene in EARLIER_RULES:
            variants.append(("earlier rule", EARLIER_RULES[scene].rule(), {}))
    for v in args.variants:
        only, text = variant_scene(v)
        if only is not None and only != scene:
            continue
        v_cfg = parse_variant(text)
        variants.append((text, v_cfg.pop("rule", rule), v_cfg))
    for name, v_rule, v_cfg in variants:
        v_edited = b.edited_image(v_rule, "photo")
        v_cfg = {"whole_image": args.whole_photo, **v_cfg}
        v_edit, v_t = b.fit(v_edited, v_cfg.pop("steps", args.steps), v_cfg.pop("pixel_batches", None), 1, original,
                            **v_cfg)
        v_res, _ = b.measure(v_edit, v_rule, lpips=False)
        extra.append({"scene": scene, "variant": name, "rule": v_rule.to_dict(), "gaussians": int(b.scene.means.shape[0]),
                      **v_res["mean"], "timing_cold": v_t,
                      "timing_cached": {k: math.nan for k in ("setup_s", "steps_s", "total_s")}})
    t0 = time.perf_counter()
    b.scene.precompute_features()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    cache_s = time.perf_counter() - t0
    _, warm = b.fit(edited, args.steps, None, args.repeats, original, args.whole_photo)
    res, pics = b.measure(edit, rule, lpips=True, keep=args.pictures)
    args.out.mkdir(parents=True, exist_ok=True)
    for i, p in enumerate(pics):
        _save_png(args.out / f"{scene}_view{i}.png", p)
    _save_png(args.out / f"{scene}_edit.png", torch.cat([b.edit_photo.cpu(), edited.cpu()], 1))
    m = res["mean"]
    row = {"scene": scene, "whole_photo": args.whole_photo, "config": str(cfg), "gaussians": int(b.scene.means.shape[0]),
           "image": f"{int(b.edit_camera.widths[0])}x{int(b.edit_camera.heights[0])}", "rule": rule.to_dict(),
           "views": len(res["views"]), **m, "timing_cold": cold, "timing_cached": warm,
           "feature_cache_s": cache_s, "per_view": res["views"]}
    row["variant"] = "engine defaults" + (" (whole photo)" if args.whole_photo else "")
    row["targets"] = {  # issue 5's, set for beercan and asked "the same" of fern and cup
        "propagation>=35": m["propagation_psnr"] >= 35.0,
        "miss>=30": m["miss_psnr"] >= 30.0,
        "leak>=30": m["leak_psnr"] >= 30.0,
        "recolour within 0.5 dB of unedited": m["recolour_psnr"] >= m["unedited_psnr"] - 0.5,
        "edit <= 0.25 s (cold)": cold["total_s"] <= 0.25,
    }
    if scene == "beercan" and args.sweep:
        run_accuracy_time(AccuracyTime(cfg, out=args.out / "beercan_accuracy_time.json", rule=RULES[scene],
                                       edit_view=args.edit_view, repeats=max(1, args.repeats // 2),
                                       max_views=args.max_views, whole_photo=args.whole_photo), pipeline,
                          console)
    del pipeline, b
    torch.cuda.empty_cache()
    return [row, *extra]


@torch.no_grad()
def bench_million(repeats: int, steps: Optional[int], n: int = 1_000_000, width: int = 1280, height: int = 720,
                  device: str = "cuda") -> dict:
    """Setup and step times of one edit on ``n`` random Gaussians filling a 1280x720 view."""
    from virgi_ns.colour.field import ColorFieldConfig, DecoupledColorField
    from virgi_ns.edit.engine import EditConfig, EditEngine
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.raster import Cameras

    dev = torch.device(device)
    g = torch.Generator(device=dev).manual_seed(0)
    f = 0.9 * width
    z = 2.0 + 6.0 * torch.rand(n, generator=g, device=dev)
    x = (torch.rand(n, generator=g, device=dev) - 0.5) * z * width / f * 1.1
    y = (torch.rand(n, generator=g, device=dev) - 0.5) * z * height / f * 1.1
    means = torch.stack([x, y, z], -1)
    scales = torch.exp(math.log(0.004) + math.log(8.0) * torch.rand(n, 3, generator=g, device=dev))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, device=dev), dim=-1)
    opac = 0.3 + 0.7 * torch.rand(n, generator=g, device=dev)
    field_ = DecoupledColorField(ColorFieldConfig(log2_hashmap_size=19 if n > 100_000 else 12), torch.tensor([[-6.0, -4.0, 1.5], [6.0, 4.0, 8.5]])).to(dev)
    torch.nn.init.normal_(field_.spec_l3.weight, std=0.1)
    cams = Cameras.from_params(f, f, width / 2, height / 2, torch.eye(4, device=dev)[None], width, height)
    scene = FrozenScene(means, quats, scales, opac, field_, torch.zeros(3, device=dev))
    edited = torch.rand(height, width, 3, generator=g, device=dev)
    cfg = EditConfig() if steps is None else EditConfig(steps=steps)

    def timed() -> dict:
        with torch.enable_grad():
            EditEngine(scene, cams, edited, cfg=cfg).fit()  # warm-up
            ts = [EditEngine(scene, cams, edited, cfg=cfg).fit()[1] for _ in range(max(1, repeats))]
        med = lambda v: float(statistics.median(v))  # noqa: E731
        return {"setup_s": med([t.setup_s for t in ts]), "steps_s": med([t.steps_s for t in ts]),
                "total_s": med([t.total_s for t in ts]), "steps": cfg.steps}

    eng = EditEngine(scene, cams, edited, cfg=cfg)
    info = {"gaussians": n, "image": f"{width}x{height}", "contributing": int(eng.gaussians.numel()),
            "entries": int(eng.contrib.pixel.numel())}
    del eng
    cold = timed()
    scene.precompute_features()
    warm = timed()
    return {**info, "timing_cold": cold, "timing_cached": warm}


def print_table(rows: List[dict], device: str) -> None:
    t = Table(title=f"edit engine on {device}")
    for c in ("scene", "variant", "gaussians", "mask", "recolour PSNR", "unedited", "perfect edit", "SSIM", "LPIPS",
              "propagation", "miss", "leak", "rule per Gaussian", "edit view miss",
              "setup s", "steps s", "total s", "cached total s"):
        t.add_column(c)
    for r in rows:
        c, w = r["timing_cold"], r["timing_cached"]
        t.add_row(r["scene"], r["variant"], f"{r['gaussians']:,}", f"{r.get('mask_fraction', float('nan')):.1%}",
                  f"{r['recolour_psnr']:.2f}", f"{r['unedited_psnr']:.2f}",
                  f"{r.get('perfect_edit_recolour_psnr', float('nan')):.2f}",
                  f"{r['recolour_ssim']:.4f}", f"{r['recolour_lpips']:.4f}", f"{r['propagation_psnr']:.2f}",
                  f"{r['miss_psnr']:.2f}", f"{r['leak_psnr']:.2f}",
                  f"{r.get('per_gaussian_rule_propagation_psnr', float('nan')):.2f}",
                  f"{r.get('edit_view_miss_psnr', float('nan')):.2f}", f"{c['setup_s']:.3f}", f"{c['steps_s']:.3f}",
                  f"{c['total_s']:.3f}", f"{w['total_s']:.3f}")
    console.print(t)
    for r in rows:
        if "targets" in r:
            console.print(f"{r['scene']} targets: " + ", ".join(f"{k}: {'PASS' if v else 'FAIL'}"
                                                                for k, v in r["targets"].items()))


def _commit() -> Optional[str]:
    """The checkout's git commit (None outside a git checkout): which code made the figures."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def main(args: Args) -> None:
    if not torch.cuda.is_available():
        raise InputError("bench/edit.py times the engine on a GPU; none is available")
    for v in args.variants:  # refuse a bad --variants before any training
        check_variant(v, args.scenes)
    device = torch.cuda.get_device_name(0)
    rows = [r for s in args.scenes for r in bench_scene(args, s)]
    result: dict = {"device": device, "commit": _commit(), "scenes": rows}
    if rows:
        print_table(rows, device)
    if args.million:
        result["million"] = bench_million(args.repeats, args.steps)
        m = result["million"]
        console.print(f"1M Gaussians at {m['image']} ({m['contributing']:,} contribute, {m['entries']:,} entries): "
                      f"cold setup {m['timing_cold']['setup_s']:.3f} s + steps {m['timing_cold']['steps_s']:.3f} s; "
                      f"cached setup {m['timing_cached']['setup_s']:.3f} s + steps "
                      f"{m['timing_cached']['steps_s']:.3f} s ({m['timing_cold']['steps']} steps)")
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "results.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1, default=float))
    console.print(f"wrote {args.out / 'results.json'}")


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
