"""Benchmark: the edit engine on the whole evaluation set, in one command, one table.

For every scene of the evaluation set (``bench/common/evalset.py``: real captures and synthetic scenes with a known
truth): train VIRGi as a user would (geometry then colour, ``--geometry-steps`` + ``--colour-steps``;
a run already under ``--train-out`` is reused), recolour the photo of the training view the rule
recolours most with the scene's rule, fit the edit, and measure the held-out views
(:mod:`virgi_ns.bench.recolor`, ``virgi-bench``'s):

  propagation / miss / leak   edited render vs the rule on the unedited render (all / inside the rule's
                              mask / outside it): the edit apart from reconstruction error
  recolour - unedited         recolour PSNR (edited render vs the rule on the photo) minus the
                              unedited PSNR (render vs photo)
  truth                       (synthetic) edited render vs the photo of the really recoloured scene
  kept parts                  (synthetic) the same over each part the truth leaves as it is (every object
                              but the recoloured one), its held-out pixels pooled: the worst part
  edit ms                     setup + steps, median of --repeats after a warm-up, with the scene's
                              features cached (as a viewer session keeps them); cold beside it

Targets: propagation >= 35 dB, miss and leak >= 30, recolour within 0.5 dB of unedited,
truth >= 35 dB and kept parts >= 30 dB on the synthetic scenes, edit <= 0.25 s warm; a figure with a ceiling on its run
(:data:`CEILINGS`: the rule per Gaussian, a perfect edit, the reconstruction) also meets its target within
0.1 dB of that ceiling's figure. The last row is the set's worst case. Beside each missed target, its
ceiling: "cannot" where even that misses the target (the rule's or the reconstruction's limit, not the
edit's), "short of" where the edit falls short of it; beside a target met at the ceiling, that ceiling.
A second table gives the diagnostics that tell the suspects apart: how closely the edited view itself
reaches the edited photo on the changed pixels, the segmentation's mean alpha inside and outside the
rule's mask, and (synthetic) on each object's pixels.

``--variants`` measures other EditConfig settings on the same trained runs (e.g. the staged recipe,
``recipe=staged``); ``--merge`` joins the results of several calls (other scenes, other seeds) into one table.

``--pick`` adds, on the same runs, one click per scene on the rule's object with the rule's
colour (the click and colour by the rule of ``bench/common/clicks.py``), measured as the rule edit
is: a third table of its propagation against the rule edit's, judged by the class of the rule's mask
(``clicks.judge_pick``: one object or many parts, within 1 dB of the rule edit; one of several
objects, the clicked object's miss and the leak outside it; any click meeting the edit's own targets
passes), with the class and reason (``pick.judged``), its selection's
share of the view and IoU with the rule's mask, its fit time (features cached, as the rule edit's
warm time); and the viewer's pick latency on the synthetic 1M-Gaussian scene at 1280x720 (drag to
frame, release to frame; target <= 100 ms), in results.json as ``pick`` per row and ``pick_latency``.

    python bench/edit.py --data ../shared/data --out bench_out/edit --variants recipe=staged
    python bench/edit.py --data ../shared/data --out bench_out/edit --pick
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.evalset import COLOUR_STEPS, GEOMETRY_STEPS, SYNTHETIC_SIZE, EvalScene, capture_folder, edit_view, find
from common.results import provenance, safe_name, write_json
from common.scenes import million_scene
from common.settings import edit_settings
from common.training import evalset_run, sync
from virgi_ns.bench.recolor import Bench, _save_png
from virgi_ns.errors import InputError, cli_entry

console = Console(width=220)
TARGETS = {"propagation": 35.0, "miss": 30.0, "leak": 30.0, "recolour_gap": -0.5, "truth": 35.0, "kept_part": 30.0,
           "edit_s": 0.25}


@dataclass
class Args:
    scenes: List[str] = field(default_factory=list)
    """Rows of the evaluation set to run (default: all)."""
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    """The real captures (beercan, fern, cup)."""
    out: Path = Path("bench_out/edit")
    train_out: Path = Path("bench_out/edit_runs")
    """Trained runs (reused when present) and the synthetic captures."""
    runs: Dict[str, Path] = field(default_factory=dict)
    """Pairs 'capture config.yml' of runs trained elsewhere (capture: a scene's capture, e.g. beercan)."""
    seed: int = 42
    """Training seed (a fresh run set: another seed and another --train-out)."""
    train_settings: str = ""
    """Trainer-config settings for the runs trained here, e.g. 'pipeline.model.refine_stop_fraction=1.0'
    (the runs' names carry them)."""
    geometry_steps: int = GEOMETRY_STEPS
    colour_steps: int = COLOUR_STEPS
    steps: Optional[int] = None
    """Edit steps (default: the engine's)."""
    repeats: int = 3
    pictures: int = 2
    variant_pictures: bool = False
    """Also save each variant's pictures (its first fit's, as many as ``--pictures``), named
    ``SCENE__ENTRY_viewI.png`` (the --variants entry, each character but letters, digits, '.' and
    '_' written as '_'): where a variant may become the default, its pictures come from
    the run that decides it."""
    variants: List[str] = field(default_factory=list)
    """More rows on the same runs, each a comma-separated list of EditConfig fields (and ``rule``, ``source``:
    :func:`common.settings.edit_settings`), e.g. 'recipe=staged' or 'steps=200,seg_init_bias=-2'; an entry that starts with 'SCENE:' is measured on
    that scene only."""
    million: bool = False
    """Also time the engine on a synthetic 1M-Gaussian scene at 1280x720."""
    pick: bool = False
    """Also a pick on every scene (one click on the rule's object with the rule's colour, measured as
    the rule edit is, ``bench/common/clicks.py``) and the viewer's pick latency on the synthetic
    1M-Gaussian scene at 1280x720 (drag to frame, release to frame)."""
    edit_seeds: int = 1
    """Fit every row's edit with this many seeds (``EditConfig.seed`` 0..N-1: the segmentation head's
    start and the pixel sets) and report each figure's median over them, with the seeds' figures in
    ``per_seed``; the timings and pictures are seed 0's. One fit of a small object can move its miss
    by several dB: a decision between variants should not rest on one."""
    merge: List[Path] = field(default_factory=list)
    """Print one table of these results.json files (no training, no GPU) and write it to --out."""
    synthetic_size: tuple[int, int, int, float] = SYNTHETIC_SIZE
    """Views, width, height and Gaussian spacing of the synthetic captures (the set's are fixed;
    smaller ones are for tests)."""


# ------------------------------------------------------------------------------ variants
def variant_scene(text: str) -> tuple:
    """'fern:steps=3' -> ('fern', 'steps=3'); an entry without a scene prefix -> (None, text)."""
    head, sep, rest = text.partition(":")
    if sep and "=" not in head and "," not in head:
        if not rest.strip():
            raise InputError(f"--variants: '{text}' names a scene but no settings")
        return head.strip(), rest
    return None, text


def check_variant(text: str, scenes: List[str]) -> None:
    """Refuse a --variants entry before any training: bad settings, or a scene prefix that names no
    scene of ``scenes`` (the whole evaluation set: a call given some of its rows, as each process of
    a call split over GPUs is, measures the entry where its scene runs and skips it elsewhere)."""
    only, rest = variant_scene(text)
    if only is not None and only not in scenes:
        raise InputError(f"--variants: '{text}' names '{only}', which is not among the scenes ({', '.join(scenes)})")
    edit_settings(rest)


# ------------------------------------------------------------------------------ runs
def engine_defaults() -> dict:
    """The EditConfig defaults of this call, recorded beside its rows."""
    from dataclasses import asdict

    from virgi_ns.edit.engine import EditConfig

    return asdict(EditConfig())


CEILING_TOLERANCE_DB = 0.1
"""A figure within this of its ceiling's (:data:`CEILINGS`) meets its target, whatever the threshold."""


def targets(m: dict, edit_s: float, synthetic: bool) -> Dict[str, bool]:
    """The set's targets. The recolour figure is judged against the truth where it is known (the
    synthetic scenes, whose reconstruction is far above a real capture's, so that a rule on a photo
    is no longer the measure) and against the unedited PSNR on the real captures. Each figure with a
    ceiling (:data:`CEILINGS`) meets its target where it reaches the threshold **or** comes within
    :data:`CEILING_TOLERANCE_DB` of its ceiling's figure on the same run (:func:`meets`): an edit
    as good as an edit no fit beats is not the edit's miss."""
    out = {name: meets(m, name) for name in ("propagation>=35", "miss>=30", "leak>=30")}
    if synthetic:
        out["truth>=35"] = meets(m, "truth>=35")
        if not math.isnan(m.get("kept_part_psnr", math.nan)):  # a row measured with its kept parts
            out["kept parts>=30"] = meets(m, "kept parts>=30")
    else:
        out["recolour within 0.5 dB of unedited"] = meets(m, "recolour within 0.5 dB of unedited")
    out["edit <= 0.25 s warm"] = edit_s <= TARGETS["edit_s"]
    return out


CEILINGS = {
    "propagation>=35": ("propagation", TARGETS["propagation"], "the rule per Gaussian",
                        lambda m: m.get("per_gaussian_rule_propagation_psnr", math.nan)),
    "miss>=30": ("miss", TARGETS["miss"], "the rule per Gaussian",
                 lambda m: m.get("per_gaussian_rule_miss_psnr", math.nan)),
    "leak>=30": ("leak", TARGETS["leak"], "the rule per Gaussian",
                 lambda m: m.get("per_gaussian_rule_leak_psnr", math.nan)),
    "recolour within 0.5 dB of unedited": ("recolour", TARGETS["recolour_gap"], "a perfect edit",
                                           lambda m: m.get("perfect_edit_recolour_psnr", math.nan)
                                           - m["unedited_psnr"]),
    "truth>=35": ("truth", TARGETS["truth"], "the reconstruction", lambda m: m["unedited_psnr"]),
    "kept parts>=30": ("kept parts", TARGETS["kept_part"], "the rule per Gaussian",
                       lambda m: m.get("per_gaussian_rule_kept_part_psnr", math.nan)),
}
"""For each target of :func:`targets` (its short name, its threshold, what the ceiling is, the ceiling's
figure): the same figure of an edit no fit can beat on this run, from the row's own measures: the
rule applied to every Gaussian's colour (a scene edit that puts each Gaussian's colour where the rule on a
pixel of it alone would), the rule on the render scored as the recolour (``perfect_edit_recolour_psnr``;
the figure is the gap to unedited, as the edit's), and the unedited render against its photo (on a
synthetic scene, what any render of the model reaches against a photo, the recoloured truth's included).
A row meets a target at its threshold or within :data:`CEILING_TOLERANCE_DB` of that figure; a row that
meets neither is "cannot" where the ceiling's figure misses the threshold too (the rule or the
reconstruction, not the edit, sets the limit), "short of" where the ceiling reaches it."""

FIGURES = {
    "propagation>=35": lambda m: m["propagation_psnr"],
    "miss>=30": lambda m: m["miss_psnr"],
    "leak>=30": lambda m: m["leak_psnr"],
    "recolour within 0.5 dB of unedited": lambda m: m["recolour_psnr"] - m["unedited_psnr"],
    "truth>=35": lambda m: m.get("truth_psnr", math.nan),
    "kept parts>=30": lambda m: m.get("kept_part_psnr", math.nan),
}
"""The row's own figure each target of :data:`CEILINGS` judges (the recolour: its gap to unedited)."""


def meets(m: dict, name: str) -> bool:
    """Target ``name`` of :data:`CEILINGS` on row ``m``: its figure at the threshold, or within
    :data:`CEILING_TOLERANCE_DB` of its ceiling's figure (a NaN ceiling: the threshold alone)."""
    _, threshold, _, ceiling = CEILINGS[name]
    value = FIGURES[name](m)
    return bool(value >= threshold or value >= ceiling(m) - CEILING_TOLERANCE_DB)


def at_ceiling(m: dict) -> Dict[str, float]:
    """The targets of row ``m`` met only through the ceiling's tolerance (below the threshold, within
    :data:`CEILING_TOLERANCE_DB` of the ceiling): {target: the ceiling's figure}."""
    out = {}
    for name, ok in m["targets"].items():
        if ok and name in CEILINGS and not FIGURES[name](m) >= CEILINGS[name][1]:
            out[name] = CEILINGS[name][3](m)
    return out


def limits(m: dict) -> Dict[str, dict]:
    """Each missed target of a row (``m`` with its ``targets``): the ceiling's figure, what it is, and
    whether it passes (``reachable``: False where the ceiling's figure misses the threshold too, the
    row "cannot" meet it on this run). A row measured before a ceiling was recorded gets NaN there,
    and reachable None."""
    out = {}
    for name, ok in m["targets"].items():
        if ok or name not in CEILINGS:
            continue
        _, threshold, what, figure = CEILINGS[name]
        value = figure(m)
        out[name] = {"ceiling": what, "value": value,
                     "reachable": None if math.isnan(value) else bool(value >= threshold)}
    return out


def limits_text(m: dict) -> str:
    """The table's words for :func:`limits` (``cannot (the reconstruction 32.67)``, ``short of 36.90``) and
    :func:`at_ceiling` (``met within 0.1 dB of a perfect edit -0.62``)."""
    parts = []
    for name, lim in limits(m).items():
        short = CEILINGS[name][0]
        v = _f(lim["value"], "+.2f" if short == "recolour" else ".2f")
        verdict = {None: "ceiling unknown", False: f"cannot ({lim['ceiling']} {v})",
                   True: f"short of {lim['ceiling']} {v}"}[lim["reachable"]]
        parts.append(f"{short}: {verdict}")
    for name, value in at_ceiling(m).items():
        short = CEILINGS[name][0]
        v = _f(value, "+.2f" if short == "recolour" else ".2f")
        parts.append(f"{short}: met within {CEILING_TOLERANCE_DB:g} dB of {CEILINGS[name][2]} {v}")
    return "; ".join(parts)


def scene_bench(args: Args, scene: EvalScene, loaded: dict) -> tuple[Bench, int, Path]:
    """The scene's :class:`Bench` on its edit view (the training photo its rule recolours most), that
    view's index and the config of its run, trained here when absent; ``loaded`` keeps the last loaded run, so that two rules
    on one capture share it."""
    from virgi_ns.nerfstudio.runs import load_run

    folder = capture_folder(scene, args.data, args.train_out / "captures",
                            "cuda" if torch.cuda.is_available() else "cpu", console, args.synthetic_size)
    cfg = evalset_run(args, scene, folder)
    if loaded.get("config") != cfg:
        loaded.clear()
        _, pipeline = load_run(cfg)
        loaded.update(config=cfg, pipeline=pipeline)
    pipeline = loaded["pipeline"]
    train = pipeline.datamanager.train_dataset
    view = edit_view([train.get_image_float32(i)[..., :3] for i in range(len(train))], scene.rule)
    return Bench.load(pipeline, view, 0, capture=folder if scene.synthetic else None), view, cfg


def bench_scene(args: Args, scene: EvalScene, loaded: dict) -> List[dict]:
    """The scene's rows: the engine's defaults (timed cold and warm, pictures), then one row per
    --variants entry (timed warm, once)."""
    b, view, cfg = scene_bench(args, scene, loaded)
    edited = b.edited_image(scene.rule, "photo")
    original = b.original("photo")
    b.scene.features = None
    edit, cold = b.fit(edited, args.steps, None, 1, original)
    sync()
    t0 = time.perf_counter()
    b.scene.precompute_features()
    sync()
    cache_s = time.perf_counter() - t0
    edit, warm = b.fit(edited, args.steps, None, args.repeats, original)
    res, pics = b.measure(edit, scene.rule, lpips=False, keep=args.pictures, edited=edited, target=b.fitted_target)
    res["mean"] = median_over_seeds(args, b, (edited, args.steps, None, 1, original), {}, scene.rule, edited,
                                    res["mean"], warm)
    args.out.mkdir(parents=True, exist_ok=True)
    for i, p in enumerate(pics):
        _save_png(args.out / f"{scene.name}_view{i}.png", p)
    _save_png(args.out / f"{scene.name}_edit.png", torch.cat([b.edit_photo.cpu(), edited.cpu()], 1))
    base = {"scene": scene.name, "capture": scene.capture, "synthetic": scene.synthetic is not None,
            "seed": args.seed, "train_settings": args.train_settings, "config": str(cfg), "gaussians": int(b.scene.means.shape[0]), "edit_view": view,
            "image": f"{int(b.edit_camera.widths[0])}x{int(b.edit_camera.heights[0])}", "rule": scene.rule.to_dict(),
            "why": scene.why, "feature_cache_s": cache_s, "engine_defaults": engine_defaults()}
    rows = [{**base, "variant": "engine defaults", **res["mean"], "timing_cold": cold, "timing_warm": warm,
             "per_view": res["views"], "targets": targets(res["mean"], warm["total_s"], scene.synthetic is not None)}]
    rows[0]["limits"] = limits(rows[0])
    if args.pick:
        rows[0]["pick"] = bench_pick(args, scene, b, res["mean"]["propagation_psnr"])
    for v in args.variants:
        only, text = variant_scene(v)
        if only is not None and only != scene.name:
            continue
        v_cfg = edit_settings(text)
        v_rule = v_cfg.pop("rule", scene.rule)
        v_source = v_cfg.pop("source", "photo")
        v_edited = b.edited_image(v_rule, v_source)
        fit = (v_edited, v_cfg.pop("steps", args.steps), v_cfg.pop("pixel_batches", None), 1, b.original(v_source))
        v_edit, v_t = b.fit(*fit, **v_cfg)
        v_res, v_pics = b.measure(v_edit, v_rule, lpips=False, keep=args.pictures if args.variant_pictures else 0,
                                  edited=v_edited, target=b.fitted_target)
        for i, p in enumerate(v_pics):
            _save_png(args.out / f"{scene.name}__{safe_name(v)}_view{i}.png", p)  # 'cup:x' apart from 'x'
        v_res["mean"] = median_over_seeds(args, b, fit, v_cfg, v_rule, v_edited, v_res["mean"], v_t)
        rows.append({**base, "variant": text, "rule": v_rule.to_dict(), **v_res["mean"], "timing_warm": v_t,
                     "targets": targets(v_res["mean"], v_t["total_s"], scene.synthetic is not None)})
        rows[-1]["limits"] = limits(rows[-1])
    del b
    torch.cuda.empty_cache()
    return rows


SEED_FIGURES = ("propagation_psnr", "miss_psnr", "leak_psnr", "recolour_psnr", "unedited_psnr", "truth_psnr",
                "edit_fit_changed_psnr", "edit_view_propagation_psnr", "edit_view_miss_psnr")
"""Each fit's figures kept in ``per_seed``: the held-out ones and the edited view's own, to see whether
what a fit can know about itself predicts how it carries."""
LOSS_FIGURES = ("final_l1", "fit_l1")
"""Each fit's losses kept in ``per_seed`` beside them: its last step's (``final_l1``) and its loss on
every pixel set at the end (``fit_l1``)."""


def median_over_seeds(args: Args, b: Bench, fit: tuple, config: dict, rule, edited: torch.Tensor, first: dict,
                      first_timing: dict) -> dict:
    """``first`` (the figures of the fit with the row's seed, s: 0 unless the variant sets one), or with
    ``--edit-seeds N`` each figure's median over the fits with seeds s..s+N-1 (``fit``: ``Bench.fit``'s
    positional arguments), plus ``per_seed`` (``first_timing``: the first fit's ``Bench.fit`` timing, with
    its losses). Each figure's median is taken on its own, so a row's figures may come from different fits."""
    if args.edit_seeds <= 1:
        return first
    runs, losses = [first], [{k: first_timing[k] for k in LOSS_FIGURES}]
    base = int(config.get("seed", 0))
    for seed in range(base + 1, base + args.edit_seeds):
        edit, timing = b.fit(*fit, **{**config, "seed": seed})
        runs.append(b.measure(edit, rule, lpips=False, edited=edited, target=b.fitted_target)[0]["mean"])
        losses.append({k: timing[k] for k in LOSS_FIGURES})
    median = {k: float(statistics.median(r[k] for r in runs)) for k, v in first.items()
              if isinstance(v, float) and all(isinstance(r.get(k), float) for r in runs)}
    per_seed = [{**{k: r[k] for k in SEED_FIGURES if k in r}, **loss} for r, loss in zip(runs, losses)]
    return {**first, **median, "per_seed": per_seed}


def bench_pick(args: Args, scene: EvalScene, b: Bench, rule_propagation: float) -> dict:
    """The scene's pick (``bench/common/clicks.py`` ``measure_pick``) on the run the rule edit used, its pictures
    beside the rule edit's. A pick refused (no pixel to click, an empty selection) is a failed row with the
    reason, not the end of the call."""
    from common.clicks import measure_pick

    try:
        p, pics, picture = measure_pick(b, scene.rule, rule_propagation, keep=args.pictures, click=scene.click)
    except InputError as e:
        console.log(f"{scene.name}: the pick failed: {e}")
        return {"error": str(e), "rule_propagation_psnr": rule_propagation, "pass": False}
    for i, pic in enumerate(pics):
        _save_png(args.out / f"{scene.name}_pick_view{i}.png", pic)
    _save_png(args.out / f"{scene.name}_pick.png", picture)
    return p


@torch.no_grad()
def bench_million(repeats: int, steps: Optional[int], n: int = 1_000_000, width: int = 1280, height: int = 720,
                  device: str = "cuda") -> dict:
    """Setup and step times of one edit on ``n`` random Gaussians filling a 1280x720 view."""
    from virgi_ns.edit.engine import EditConfig, EditEngine

    scene, cams = million_scene(n, width, height, device)
    g = torch.Generator(device=torch.device(device)).manual_seed(1)
    edited = torch.rand(height, width, 3, generator=g, device=torch.device(device))
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
    return {**info, "timing_cold": cold, "timing_warm": warm}


def pick_latency(repeats: int, n: int = 1_000_000, width: int = 1280, height: int = 720, device: str = "cuda") -> dict:
    """The viewer's pick latency (``bench/common/clicks.py`` ``viewer_latency``) on ``million_scene``,
    without the features cache (the viewer's pick sets up its scene afresh: ``FrozenScene.from_model``)."""
    from common.clicks import viewer_latency

    scene, cams = million_scene(n, width, height, device)
    return viewer_latency(scene, cams, repeats)


# ------------------------------------------------------------------------------ tables
def _f(x: float, fmt: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def worst_case(rows: List[dict]) -> dict:
    """The set's worst figure of each kind over the engine-default rows (the highest edit time)."""
    d = [r for r in rows if r["variant"] == "engine defaults"]
    nanmin = lambda xs: min((x for x in xs if not math.isnan(x)), default=math.nan)  # noqa: E731
    return {"propagation_psnr": nanmin([r["propagation_psnr"] for r in d]),
            "miss_psnr": nanmin([r["miss_psnr"] for r in d]), "leak_psnr": nanmin([r["leak_psnr"] for r in d]),
            "recolour_gap": nanmin([r["recolour_psnr"] - r["unedited_psnr"] for r in d if not r["synthetic"]]),
            "truth_psnr": nanmin([r.get("truth_psnr", math.nan) for r in d]),
            "kept_part_psnr": nanmin([r.get("kept_part_psnr", math.nan) for r in d]),
            "edit_s": max((r["timing_warm"]["total_s"] for r in d), default=math.nan),
            "passed": sum(all(r["targets"].values()) for r in d), "rows": len(d),
            "cannot": sum(any(lim["reachable"] is False for lim in limits(r).values()) for r in d),
            "pick_difference_db": nanmin([r["pick"].get("difference_db", math.nan) for r in d if "pick" in r]),
            "pick_passed": sum(r["pick"]["pass"] for r in d if "pick" in r), "pick_rows": sum("pick" in r for r in d),
            "pick_cannot": sum(bool(r["pick"].get("judged", {}).get("cannot")) for r in d if "pick" in r)}


def _label(row: dict) -> str:
    """The row's variant, with the training settings of its run when they are not the defaults."""
    ts = row.get("train_settings")
    return row["variant"] + (f" [{ts}]" if ts else "")


def print_tables(rows: List[dict], device: str) -> None:
    t = Table(title=f"edit engine on the evaluation set ({device})")
    for c in ("scene", "seed", "variant", "mask", "propagation", "miss", "leak", "recolour - unedited", "truth",
              "kept part", "edit ms (cold)", "targets", "what limits a missed target"):
        t.add_column(c)
    for r in rows:
        cold = r.get("timing_cold", {}).get("total_s", math.nan)
        failed = [k for k, ok in r["targets"].items() if not ok]
        t.add_row(r["scene"], str(r["seed"]), _label(r), _f(r.get("mask_fraction", math.nan), ".1%"),
                  _f(r["propagation_psnr"]), _f(r["miss_psnr"]), _f(r["leak_psnr"]),
                  _f(r["recolour_psnr"] - r["unedited_psnr"], "+.2f"), _f(r.get("truth_psnr", math.nan)),
                  f"{_f(r.get('kept_part_psnr', math.nan))} {r.get('kept_part', '')}".strip(),
                  f"{1e3 * r['timing_warm']['total_s']:.0f} ({_f(1e3 * cold, '.0f')})",
                  "PASS" if not failed else "FAIL: " + ", ".join(failed), limits_text(r))
    w = worst_case(rows)
    t.add_row("worst case", "", "engine defaults", "", _f(w["propagation_psnr"]), _f(w["miss_psnr"]),
              _f(w["leak_psnr"]), _f(w["recolour_gap"], "+.2f"), _f(w["truth_psnr"]), _f(w["kept_part_psnr"]),
              f"{1e3 * w['edit_s']:.0f}",
              f"{w['passed']}/{w['rows']} rows pass",
              f"{w['cannot']} of the failing rows cannot pass on their run" if w["rows"] > w["passed"] else "")
    console.print(t)
    d = Table(title="diagnostics: the edited view's own fit, and where the segmentation lands")
    for c in ("scene", "seed", "variant", "start", "changed", "changed outside the mask / mask unchanged",
              "target: miss / leak", "edit view fit (changed px)", "edit view alpha in mask",
              "alpha in mask", "alpha outside", "alpha per object (synthetic)"):
        d.add_column(c)
    for r in rows:
        per = ", ".join(f"{k[6:-1]} {v:.2f}" for k, v in r.items() if k.startswith("alpha[") and not math.isnan(v)
                        and k[6:-1] not in ("floor", "backdrop"))
        d.add_row(r["scene"], str(r["seed"]), _label(r), str(r["timing_warm"].get("start")),
                  _f(r["timing_warm"].get("changed_fraction", math.nan), ".1%"),
                  f"{_f(r.get('edit_changed_outside_mask', math.nan), '.1%')} / "
                  f"{_f(r.get('edit_mask_unchanged', math.nan), '.1%')}",
                  f"{_f(r.get('edit_target_miss_psnr', math.nan))} / {_f(r.get('edit_target_leak_psnr', math.nan))}",
                  _f(r.get("edit_fit_changed_psnr", math.nan)), _f(r.get("edit_view_alpha_in_mask", math.nan)),
                  _f(r.get("alpha_in_mask", math.nan)), _f(r.get("alpha_out_mask", math.nan), ".3f"), per)
    console.print(d)


def print_pick(rows: List[dict], latencies: List[dict]) -> None:
    """The pick table: each scene's pick, its class and what it is judged against (``common.clicks``
    ``judge_pick``: the rule edit within 1 dB, or the clicked object's miss and leak, or its own
    targets); then the latency lines."""
    from common.clicks import WITHIN_DB, judge_pick

    picked = [r for r in rows if "pick" in r]
    if picked:
        t = Table(title=f"one click with the rule's colour: its own targets, or vs the rule edit (within {WITHIN_DB:g} "
                        "dB), or on one of several objects its object's miss and leak")
        for c in ("scene", "seed", "pixel", "colour", "selected", "IoU with rule mask", "pick propagation (miss, leak)",
                  "object miss, leak", "rule propagation", "difference", "pick fit s", "class: judged by", "pass"):
            t.add_column(c)
        for r in picked:
            p = r["pick"]
            if "error" in p:
                t.add_row(r["scene"], str(r["seed"]), "", "", "", "", "", "", _f(p["rule_propagation_psnr"]), "", "",
                          "", f"FAIL: {p['error']}")
                continue
            j = p.get("judged") or judge_pick(p)
            obj = (f"{_f(p['object_miss_psnr'])}, {_f(p['object_leak_psnr'])}" if "object_miss_psnr" in p else "")
            t.add_row(r["scene"], str(r["seed"]), f"{p['pixel'][0]} {p['pixel'][1]}", p["colour"],
                      _f(p["selected"], ".1%"), _f(p["iou"], ".3f"),
                      f"{_f(p['propagation_psnr'])} ({_f(p['miss_psnr'])}, {_f(p['leak_psnr'])})", obj,
                      _f(p["rule_propagation_psnr"]), _f(p["difference_db"], "+.2f"), _f(p["fit_s"], ".3f"),
                      j["reason"], ("PASS (" + j["by"] + ")") if p["pass"]
                      else ("CANNOT (" + j["by"] + ")") if j.get("cannot") else f"FAIL ({j['by']})")
        w = worst_case(rows)
        t.add_row("worst case", "", "", "", "", "", "", "", "", _f(w["pick_difference_db"], "+.2f"), "", "",
                  f"{w['pick_passed']}/{w['pick_rows']} pass, {w['pick_cannot']} cannot")
        console.print(t)
    for lat in latencies:
        console.print(latency_line(lat))


def latency_line(lat: dict) -> str:
    """One line of :func:`pick_latency`'s medians against the 100 ms target."""
    d, r, u = lat["drag"], lat["release"], lat.get("top_up")
    ok = lambda s: "PASS" if s <= lat["target_s"] else "FAIL"  # noqa: E731
    top_up = ("" if u is None else f"; top-up to {lat['steps']} steps + frame {1e3 * u['total_s']:.0f} ms while "
              f"nothing changes (a change -> its finished frame {1e3 * u['change_to_final_s']:.0f} ms)")
    return (f"pick latency, {lat['gaussians']:,} Gaussians at {lat['image']} ({lat.get('device', '?')}; "
            f"{lat['renderer']} frames, gate keeps {lat['gate_kept']:.0%}, {lat['selected']:.0%} selected; median of "
            f"{lat['repeats']}): drag -> frame {1e3 * d['total_s']:.0f} ms ({lat['live_steps']} steps "
            f"{1e3 * d['fit_s']:.0f} + render {1e3 * d['render_s']:.0f}) {ok(d['total_s'])}{top_up}; release -> frame "
            f"{1e3 * r['total_s']:.0f} ms (fit left {1e3 * r['fit_s']:.0f} + commit {1e3 * r['commit_s']:.0f} + render "
            f"{1e3 * r['render_s']:.0f}) {ok(r['total_s'])} (target <= {1e3 * lat['target_s']:.0f} ms)")


def _write(path: Path, result: dict) -> None:
    write_json(path, result, console)


def read_result(path: Path, flag: str) -> dict:
    """A results.json of this bench, or an InputError naming ``flag`` (the option that named the file)."""
    try:
        r = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{flag}: cannot read {path}: {e}") from None
    if "scenes" not in r:
        raise InputError(f"{flag}: {path} is not a bench/edit.py result")
    return r


def merged(paths: List[Path]) -> dict:
    """One result of several calls' results.json (rows concatenated, judged again by today's targets;
    devices and commits listed)."""
    from common.clicks import judge_pick

    rows, devices, commits, sources, latencies = [], [], [], [], []
    for p in paths:
        r = read_result(p, "--merge")
        for row in r["scenes"]:  # judged again: the targets may have been refined since the call
            row["targets"] = targets(row, row["timing_warm"]["total_s"], row["synthetic"])
            row["limits"] = limits(row)
            p = row.get("pick", {})
            if "difference_db" in p:  # the verdict as today's rule has it, from the stored figures
                p["judged"] = judge_pick(p)
                p["pass"] = p["judged"]["pass"]
        rows += r["scenes"]
        if "pick_latency" in r:
            latencies.append({"device": r.get("device"), **r["pick_latency"]})
        latencies += r.get("pick_latencies", [])  # a merge's, kept by a merge of merges
        devices.append(r.get("device"))
        commits += r["commits"] if "commits" in r else [r.get("commit")]
        sources += r["source_digests"] if "source_digests" in r else [r.get("source_digest")]
    return {"device": ", ".join(sorted(set(filter(None, devices)))), "commits": commits, "source_digests": sources,
            "merged": [str(p) for p in paths],
            "scenes": rows, "worst_case": worst_case(rows), "pick_latencies": latencies}


def main(args: Args) -> None:
    if args.merge:
        result = merged(args.merge)
        print_tables(result["scenes"], result["device"])
        print_pick(result["scenes"], result["pick_latencies"])
        _write(args.out / "results.json", result)
        return
    scenes = find(args.scenes)
    whole_set, this_call = [s.name for s in find([])], [s.name for s in scenes]
    for v in args.variants:  # refuse a bad --variants before any training
        check_variant(v, whole_set)
        only = variant_scene(v)[0]
        if only is not None and only not in this_call:
            console.print(f"--variants '{v}': {only} is not among this call's rows, so it is not measured here")
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    rows: List[dict] = []
    loaded: dict = {}
    result: dict = {"device": device, **provenance(), "scenes": rows}
    for s in scenes:
        rows += bench_scene(args, s, loaded)
        result["worst_case"] = worst_case(rows)
        _write(args.out / "results.json", result)  # after every scene: a call cut short keeps what it measured
    loaded.clear()
    if rows:
        print_tables(rows, device)
    if args.pick:
        result["pick_latency"] = {"device": device, **pick_latency(args.repeats)}
        _write(args.out / "results.json", result)
        print_pick(rows, [result["pick_latency"]])
    if args.million:
        result["million"] = bench_million(args.repeats, args.steps)
        m = result["million"]
        console.print(f"1M Gaussians at {m['image']} ({m['contributing']:,} contribute): warm setup "
                      f"{m['timing_warm']['setup_s']:.3f} s + steps {m['timing_warm']['steps_s']:.3f} s; cold "
                      f"{m['timing_cold']['total_s']:.3f} s ({m['timing_warm']['steps']} steps)")
    _write(args.out / "results.json", result)


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
