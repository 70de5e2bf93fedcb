"""``virgi-bench recolor`` and ``virgi-bench accuracy-time``: how well and how fast one edited view
recolours a trained run, measured with the deterministic HSV rule of :mod:`virgi_ns.edit.recolor`.

The rule applied to one training view (its photo, or the model's render of it) is the edit;
applied to the held-out views it is the truth. Figures, per held-out view and averaged:

- **recolour** PSNR / SSIM / LPIPS: edited render vs the rule applied to the held-out *photo*,
  beside the same model's **unedited** PSNR (render vs photo), which bounds it;
- **propagation** PSNR: edited render vs the rule applied to the model's own *unedited render*,
  which isolates the edit from reconstruction error; split into inside the rule's mask
  (**miss**: recolour not done) and outside it (**leak**: recolour where none belongs);
- on a synthetic capture, **kept part** PSNR: the edited render vs the recoloured truth over each part the
  truth leaves as it is (every object but the recoloured one, floor and backdrop aside), its pixels of
  every held-out view pooled; the worst part's figure and its name (issue 41 item 1: a part of another
  colour keeps its colour);
- the edit's setup and step times (median over ``--repeats`` after one warm-up fit).

``accuracy-time`` sweeps the number of steps (and the pixel subsampling) and writes a JSON and a
PNG plot of recolour and propagation PSNR against edit wall time. Nothing of the run is written:
edits live in memory only.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
import torch
import tyro
from rich.console import Console

from virgi_ns.edit.recolor import RecolorRule, recolor
from virgi_ns.errors import InputError, atomic_path, cli_entry


# ---------------------------------------------------------------------------- options
@dataclass
class RuleArgs:
    """The recolouring rule (degrees for hues)."""

    h0: float = 190.0
    h1: float = 250.0
    shift: float = 150.0
    s_min: float = 0.1
    """Pixels less saturated than this are left alone: 0.1 takes beercan's can whole (its pale blue back
    too) and nothing of its grey-white floor."""
    v_min: float = 0.15
    sat_scale: float = 1.0

    def rule(self) -> RecolorRule:
        try:
            return RecolorRule(self.h0, self.h1, self.shift, self.s_min, self.v_min, self.sat_scale)
        except ValueError as e:
            raise InputError(str(e)) from None


@dataclass
class _EditedView:
    """What both commands read: the run, the rule and the training view it recolours."""

    load_config: Path
    """The run's config.yml."""
    rule: RuleArgs = field(default_factory=RuleArgs)
    edit_view: int = 0
    """Training image to edit."""
    edit_source: str = "photo"
    """Apply the rule to the training 'photo' or to the model's 'render' of it."""
    whole_photo: bool = False
    """Fit the whole edited photo (also the pixels the rule left alone) instead of only the
    recoloured pixels, as when the unedited photo is not known."""


@dataclass
class Recolor(_EditedView):
    """Edit one training view with the rule; measure the held-out views."""

    out: Path = Path("bench_out/recolor/results.json")
    """JSON results; pictures are written beside it."""
    steps: Optional[int] = None
    """Edit steps (default: the engine's)."""
    pixel_batches: Optional[int] = None
    """Pixel subsets per edit, one per step (default: the engine's)."""
    repeats: int = 3
    """Timed fits after one warm-up; the median is reported."""
    max_views: int = 0
    """Held-out views to measure (0: all)."""
    pictures: int = 3
    """Held-out views saved as before | after | truth | mask PNGs."""
    lpips: bool = True
    """Compute LPIPS when its weights are available offline."""
    changed_target: Literal["affine", "edited"] = "affine"
    """What the edit fits the changed pixels of an edited photo to (``EditConfig.changed_target``)."""


@dataclass
class AccuracyTime(_EditedView):
    """Sweep edit steps (and pixel subsampling): recolour PSNR against wall time."""

    out: Path = Path("bench_out/accuracy_time/accuracy_time.json")
    """JSON results; the PNG plot is written beside it (same stem)."""
    steps: tuple[int, ...] = (10, 25, 50, 75, 100, 150, 200, 300, 500)
    pixel_batches: tuple[int, ...] = (1, 4)
    repeats: int = 3
    max_views: int = 0


Command = Union[
    Annotated[Recolor, tyro.conf.subcommand("recolor")],
    Annotated[AccuracyTime, tyro.conf.subcommand("accuracy-time")],
]


# ---------------------------------------------------------------------------- helpers
def psnr(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR over all pixels, or over ``mask`` [H,W] (NaN for an empty mask)."""
    d = (a.float() - b.float()) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return math.nan
        d = d[mask]
    return float(-10.0 * torch.log10(d.mean().clamp_min(1e-12)))


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean of ``x`` over ``mask`` (NaN for an empty mask)."""
    return float(x[mask].float().mean()) if bool(mask.any()) else math.nan


MIN_PART_PIXELS = 50
"""A kept part seen on fewer held-out pixels than this, all views together, is not judged."""


def part_errors(image: torch.Tensor, truth: torch.Tensor, label_map: torch.Tensor, labels: tuple) -> dict:
    """{label: (the sum of squared errors of ``image`` against ``truth`` over the label's pixels of
    ``label_map`` [H,W], their count)} for each label index in ``labels``."""
    d = ((image.float() - truth.float()) ** 2).sum(-1)
    out = {}
    for k in labels:
        m = label_map == k
        out[k] = (float(d[m].sum()), int(m.sum()))
    return out


def worst_part_psnr(per_view: list, names: tuple) -> tuple[float, str]:
    """(the lowest PSNR of any label, each over its pixels of every view pooled, and that label's name)
    from :func:`part_errors` of each view; labels under :data:`MIN_PART_PIXELS` pixels are left out;
    (NaN, "") where none is left."""
    worst, name = math.nan, ""
    for k in (per_view[0] if per_view else {}):
        sse, n = sum(v[k][0] for v in per_view), sum(v[k][1] for v in per_view)
        if n < MIN_PART_PIXELS:
            continue
        value = float(-10.0 * math.log10(max(sse / (3 * n), 1e-12)))
        if math.isnan(worst) or value < worst:
            worst, name = value, names[k]
    return worst, name


def against_rule(after: torch.Tensor, truth_render: torch.Tensor, mask: torch.Tensor) -> dict:
    """``after`` against the rule on the render (``truth_render``, whose ``mask`` it recolours) over the whole
    view (propagation), inside the mask (miss) and outside it (leak)."""
    return {"propagation_psnr": psnr(after, truth_render), "miss_psnr": psnr(after, truth_render, mask),
            "leak_psnr": psnr(after, truth_render, ~mask)}


def edit_figures(after: torch.Tensor, base: torch.Tensor, photo: torch.Tensor, truth_render: torch.Tensor,
                 truth_photo: torch.Tensor, mask: torch.Tensor) -> dict:
    """One view's edit figures: ``after`` (the edited render) against ``truth_render`` (the rule applied
    to ``base``, the unedited render, whose ``mask`` it recoloured) over the whole view (propagation),
    inside the mask (miss) and outside it (leak); the unedited render against ``photo``; the recolour a
    perfect edit would score (``truth_render`` against ``truth_photo``, the rule on the photo: the
    rule's thresholds can amplify the reconstruction error); the mask's share of the view."""
    return {"unedited_psnr": psnr(base, photo),
            "perfect_edit_recolour_psnr": psnr(truth_render, truth_photo),
            **against_rule(after, truth_render, mask),
            "mask_fraction": float(mask.float().mean())}


def target_figures(target: torch.Tensor, changed: Optional[torch.Tensor], truth_render: torch.Tensor,
                   mask: torch.Tensor) -> dict:
    """What the edit is told in its own view, scored as the edit is: the image the engine fits
    (``target`` [H,W,3]; ``changed`` [H,W] the pixels it changes, None for a whole-image fit) against
    the rule on the view's render (``truth_render``, whose ``mask`` it recolours) inside the mask and
    outside it; and the view's share of pixels the edit changes outside the mask, and leaves unchanged
    inside it. Where these are low the target, not the fit or its propagation, sets the edit's limit:
    an edited photo changes the pixels the photo shows in the rule's colours, which a blurred or
    shifted render shows elsewhere."""
    told = against_rule(target, truth_render, mask)
    out = {"edit_target_miss_psnr": told["miss_psnr"], "edit_target_leak_psnr": told["leak_psnr"]}
    if changed is not None:
        out["edit_changed_outside_mask"] = float((changed & ~mask).float().mean())
        out["edit_mask_unchanged"] = float((mask & ~changed).float().mean())
    return out


def region_colour_error(image: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict:
    """How far ``image``'s colour over ``mask`` [H,W] is from ``truth``'s, as a person reads a recolour:
    the mean hue's difference in degrees (in (-180, 180]), and the mean saturation's and value's
    differences (``image`` minus ``truth``; negative: duller, darker). NaN for an empty mask.

    The mean hue two ways: ``region_hue_error_deg``, the circular mean of every pixel's hue alike; and
    ``region_chroma_hue_error_deg``, each pixel's hue weighted by its chroma (``max - min`` of its RGB,
    ``s v``), the hue of the region's mean colour in the chromatic plane. A pixel's hue turns by about
    ``e / chroma`` radians under a colour error ``e``, so in the first a near-grey pixel moves the mean
    as far as a saturated one under an error far smaller; in the second each pixel moves it in
    proportion to its colour error."""
    if not bool(mask.any()):
        return {"region_hue_error_deg": math.nan, "region_chroma_hue_error_deg": math.nan,
                "region_saturation_error": math.nan, "region_value_error": math.nan}
    from virgi_ns.edit.recolor import rgb_to_hsv

    a, b = rgb_to_hsv(image.clamp(0, 1)[mask].double()), rgb_to_hsv(truth.clamp(0, 1)[mask].double())

    def mean_hue(hsv: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        rad = torch.deg2rad(hsv[:, 0])
        return torch.atan2((weight * torch.sin(rad)).sum(), (weight * torch.cos(rad)).sum())

    def difference(weight_of) -> float:
        diff = torch.rad2deg(mean_hue(a, weight_of(a)) - mean_hue(b, weight_of(b)))
        diff = float(torch.remainder(diff + 180.0, 360.0) - 180.0)
        return diff if diff != -180.0 else 180.0

    return {"region_hue_error_deg": difference(lambda hsv: torch.ones_like(hsv[:, 0])),
            "region_chroma_hue_error_deg": difference(lambda hsv: hsv[:, 1] * hsv[:, 2]),
            "region_saturation_error": float(a[:, 1].mean() - b[:, 1].mean()),
            "region_value_error": float(a[:, 2].mean() - b[:, 2].mean())}


def _read_image(path: Path, dev) -> torch.Tensor:
    from PIL import Image

    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).float().div(255.0).to(dev)


def _read_labels(path: Path, dev) -> torch.Tensor:
    from PIL import Image

    return torch.from_numpy(np.array(Image.open(path))).long().to(dev)


def _mean(xs: list[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return float(sum(xs) / len(xs)) if xs else math.nan


@dataclass
class Bench:
    """A loaded run prepared for recolour measurements: the edit view and the held-out views
    with their photos and unedited renders (computed once)."""

    pipeline: object
    scene: object
    edit_camera: object
    edit_photo: torch.Tensor
    views: list  # raster Cameras, one view each
    photos: list[torch.Tensor]
    base: list[torch.Tensor]
    fingerprint: str
    edit_base: torch.Tensor  # the edit view's unedited render
    truths: Optional[list] = None
    """Per held-out view, the photo of the recoloured scene when it is known (synthetic scenes)."""
    fitted_target: Optional[object] = None
    """The :class:`~virgi_ns.edit.targets.Target` the last :meth:`fit` fitted (the engine's own, from its
    own render of the view), for :meth:`measure`."""
    label_maps: Optional[list] = None
    """Per held-out view, each pixel's object label (index into ``label_names``), when known."""
    label_names: tuple = ()
    kept_labels: tuple = ()
    """The labels (indices into ``label_names``) of the parts the truth leaves as they are: every object
    but the recoloured one, the floor and the backdrop (item 1 of issue 41: :meth:`measure`'s
    ``kept_part_psnr``)."""
    # per-Gaussian-rule figures by (rule, held-out view): they depend on neither the edit nor its
    # settings, so a sweep measures them once
    _reference: dict = field(default_factory=dict, repr=False)

    @staticmethod
    def load(pipeline, edit_view: int, max_views: int = 0, capture: Optional[Path] = None) -> "Bench":
        """``capture``: a synthetic capture's folder (:mod:`virgi_ns.bench.synthetic`), whose truth
        photos and pixel labels are then read for the held-out views."""
        from virgi_ns.edit.scene import FrozenScene, render_view
        from virgi_ns.nerfstudio.cameras import raster_cameras

        dm = pipeline.datamanager
        model = pipeline.model
        train, ev = dm.train_dataset, getattr(dm, "eval_dataset", None)
        if not 0 <= edit_view < len(train):
            raise InputError(f"--edit-view {edit_view} is out of range: {len(train)} training images")
        if ev is None or len(ev) == 0:
            raise InputError("the run has no held-out (eval) images to measure")
        scene = FrozenScene.from_model(model)
        dev = model.device
        idx = list(range(len(ev)))
        if max_views > 0 and len(idx) > max_views:
            idx = [idx[round(i * (len(idx) - 1) / max(max_views - 1, 1))] for i in range(max_views)]
        views, photos, base = [], [], []
        for i in idx:
            cams = raster_cameras(ev.cameras[i : i + 1]).to(dev)
            views.append(cams)
            photos.append(ev.get_image_float32(i)[..., :3].to(dev))
            base.append(render_view(scene, cams, 0)["rgb"].clamp(0, 1))
        ecam = raster_cameras(train.cameras[edit_view : edit_view + 1]).to(dev)
        b = Bench(pipeline, scene, ecam, train.get_image_float32(edit_view)[..., :3].to(dev), views, photos,
                  base, scene.fingerprint(), render_view(scene, ecam, 0)["rgb"].clamp(0, 1))
        if capture is not None and (capture / "truth").is_dir():  # truth and labels by image name
            names = [Path(ev.image_filenames[i]).name for i in idx]
            b.truths = [_read_image(capture / "truth" / n, dev) for n in names]
            if (capture / "labels").is_dir() and (capture / "scene.json").is_file():
                info = json.loads((capture / "scene.json").read_text())
                b.label_names = tuple(info["labels"])
                b.label_maps = [_read_labels(capture / "labels" / n, dev) for n in names]
                b.kept_labels = tuple(k for k, name in enumerate(b.label_names)
                                      if name not in (info.get("target"), "floor", "backdrop"))
        return b

    def edited_image(self, rule: RecolorRule, source: str) -> torch.Tensor:
        if source == "photo":
            img = self.edit_photo
        elif source in ("render", "render+original"):
            img = self.edit_base
        else:
            raise InputError(f"--edit-source must be 'photo', 'render' or 'render+original', got {source!r}")
        return recolor(img, rule)[0]

    def original(self, source: str):
        """The unedited image the engine compares the edit with (only changed pixels are fitted to
        the edit): the photo for a photo edit; None for a render edit (the engine recognises an
        edited render by itself); the render itself for ``render+original`` (a render edit whose
        changed pixels the engine is told, however many)."""
        return {"photo": self.edit_photo, "render+original": self.edit_base}.get(source)

    def fit(self, edited: torch.Tensor, steps: Optional[int], pixel_batches: Optional[int], repeats: int,
            original: Optional[torch.Tensor] = None, whole_image: bool = False, **config):
        """(edit, {setup_s, steps_s, total_s} medians) after one untimed warm-up fit; ``None`` for
        ``steps`` or ``pixel_batches`` takes the engine's default. ``original``: the unedited image
        (the engine then fits only the changed pixels); ``whole_image``: fit every pixel to
        ``edited``; ``config``: other :class:`~virgi_ns.edit.engine.EditConfig` fields."""
        from virgi_ns.edit.engine import EditConfig, EditEngine

        cfg = EditConfig(**config)
        if steps is not None:
            cfg.steps = int(steps)
        if pixel_batches is not None:
            cfg.pixel_batches = int(pixel_batches)
        cfg.whole_image = whole_image
        EditEngine(self.scene, self.edit_camera, edited, cfg=cfg, original=original).fit()  # warm-up
        times, edit, engine = [], None, None
        for _ in range(max(1, repeats)):
            engine = EditEngine(self.scene, self.edit_camera, edited, cfg=cfg, original=original)
            edit, t = engine.fit()
            times.append(t)
        self.fitted_target = engine.target
        med = lambda xs: float(statistics.median(xs))  # noqa: E731
        return edit, {"setup_s": med([t.setup_s for t in times]), "steps_s": med([t.steps_s for t in times]),
                      "total_s": med([t.total_s for t in times]), "steps": cfg.steps,
                      "pixel_batches": cfg.pixel_batches, "final_l1": times[-1].final_loss,
                      "fit_l1": engine.fit_loss(), "changed_progress": engine.changed_progress(),
                      "start": edit.info.get("start"), "changed_fraction": edit.info.get("changed_fraction")}

    def _per_gaussian_rule(self, i: int, rule: RecolorRule, truth: torch.Tensor, mask: torch.Tensor) -> dict:
        """Propagation and region-colour figures of an object-level reference edit for held-out view ``i``: the
        rule applied to every Gaussian's colour (not to pixels), composited. Where a pixel blends
        recoloured and untouched Gaussians (thin leaves over a bright background) the per-pixel rule
        and any per-Gaussian edit disagree; this says how much of the propagation error that alone
        explains. Rendered once per (rule, view)."""
        from virgi_ns.edit.scene import render_view

        key = (rule, i)
        if key not in self._reference:
            ref = render_view(self.scene, self.views[i], 0, colour_map=lambda c: recolor(c, rule)[0])["rgb"]
            ref = ref.clamp(0, 1)
            # the same rule on the diffuse colours only, the specular part kept: the most that any
            # edit of the diffuse colour (this method's) can reach
            dif = render_view(self.scene, self.views[i], 0, diffuse_map=lambda c: recolor(c, rule)[0])["rgb"]
            dif = dif.clamp(0, 1)
            if self.kept_labels:  # the kept parts of the rule per Gaussian, against the truth
                self._reference[key + ("parts",)] = part_errors(ref, self.truths[i], self.label_maps[i],
                                                                self.kept_labels)
            self._reference[key] = {**{f"per_gaussian_rule_{k}": v for k, v in against_rule(ref, truth, mask).items()},
                                    "diffuse_rule_propagation_psnr": psnr(dif, truth),
                                    "diffuse_rule_miss_psnr": psnr(dif, truth, mask),
                                    # the recoloured region's colour of both: the ceilings of the edit's
                                    **{f"per_gaussian_rule_{k}": v for k, v in region_colour_error(ref, truth, mask).items()},
                                    **{f"diffuse_rule_{k}": v for k, v in region_colour_error(dif, truth, mask).items()}}
        return self._reference[key]

    def _truth_figures(self, i: int, after: torch.Tensor, alpha: torch.Tensor) -> dict:
        """Against the known recoloured scene (synthetic captures): PSNR overall, on the pixels the
        recolour changes and elsewhere; the segmentation's mean alpha on each object's pixels."""
        if self.truths is None:
            return {}
        truth, photo = self.truths[i], self.photos[i]
        changed = (truth - photo).abs().amax(-1) > 3.0 / 255.0
        out = {"truth_psnr": psnr(after, truth), "truth_in_psnr": psnr(after, truth, changed),
               "truth_out_psnr": psnr(after, truth, ~changed)}
        if self.label_maps is not None:
            for k, name in enumerate(self.label_names):
                out[f"alpha[{name}]"] = _masked_mean(alpha, self.label_maps[i] == k)
        return out

    def measure(self, edit, rule: RecolorRule, lpips: bool = True, keep: int = 0,
                edited: Optional[torch.Tensor] = None, target=None) -> tuple[dict, list]:
        """Per-view and mean figures for ``edit``; the first ``keep`` views' pictures too. With the
        ``edited`` image the edit was fitted to, also how closely the edited view itself reaches it
        on the pixels the edit changed (the fit, apart from its propagation); with the engine's
        ``target`` (:attr:`fitted_target`), what the engine was told to fit there
        (:func:`target_figures`)."""
        from virgi_ns.edit.scene import render_view
        from virgi_ns.edit.stack import EditStack
        from virgi_ns.metrics import image_metrics

        stack = EditStack(self.fingerprint)
        stack.to(self.scene.device)
        stack.add(edit)
        rows, pics, parts = [], [], []
        for i, (cams, photo, base) in enumerate(zip(self.views, self.photos, self.base)):
            out = render_view(self.scene, cams, 0, stack)
            after = out["rgb"].clamp(0, 1)
            truth_photo, _ = recolor(photo, rule)
            truth_render, mask = recolor(base, rule)
            m = image_metrics(after, truth_photo, lpips="auto" if lpips else None)
            rows.append({
                "recolour_psnr": m["psnr"], "recolour_ssim": m["ssim"], "recolour_lpips": m["lpips"],
                **edit_figures(after, base, photo, truth_render, truth_photo, mask),
                **self._per_gaussian_rule(i, rule, truth_render, mask),
                # the edit's segmentation (composited alpha) where the rule recolours and elsewhere
                "alpha_in_mask": _masked_mean(out["segmentation"][..., 0], mask),
                "alpha_out_mask": _masked_mean(out["segmentation"][..., 0], ~mask),
                # the recoloured region's colour against the rule's (a large edit's dullness shows here)
                **region_colour_error(after, truth_render, mask),
                **self._truth_figures(i, after, out["segmentation"][..., 0]),
            })
            if self.kept_labels:
                parts.append(part_errors(after, self.truths[i], self.label_maps[i], self.kept_labels))
            if i < keep:
                seg = out["segmentation"].clamp(0, 1).expand(-1, -1, 3)
                truth = truth_render if self.truths is None else self.truths[i]
                pics.append(torch.cat([base, after, truth, seg], dim=1).cpu())
        mean = {k: _mean([r[k] for r in rows]) for k in rows[0]} if rows else {}
        if parts:  # each kept part against the truth, its pixels of every held-out view pooled; the worst
            mean["kept_part_psnr"], mean["kept_part"] = worst_part_psnr(parts, self.label_names)
            ref = [self._reference[(rule, i, "parts")] for i in range(len(parts))]
            mean["per_gaussian_rule_kept_part_psnr"], _ = worst_part_psnr(ref, self.label_names)
        # the same figures on the edited view itself, against the rule on its render (the edit was fitted
        # to the rule on the photo): far above the held-out figures, the edit carries badly to other
        # views; close to them, the fit itself is the limit
        ev = render_view(self.scene, self.edit_camera, 0, stack)
        after = ev["rgb"].clamp(0, 1)
        truth_render, mask = recolor(self.edit_base, rule)
        mean.update({**{f"edit_view_{k}": v for k, v in against_rule(after, truth_render, mask).items()},
                     "edit_view_alpha_in_mask": _masked_mean(ev["segmentation"][..., 0], mask),
                     "edit_view_mask_fraction": float(mask.float().mean())})
        if edited is not None:
            changed = (edited - self.edit_photo).abs().amax(-1) > 3.0 / 255.0
            mean["edit_fit_changed_psnr"] = psnr(after, edited, changed)
        if target is not None:
            mean.update(target_figures(target.image.to(after.device),
                                       None if target.changed is None else target.changed[..., 0].to(after.device),
                                       truth_render, mask))
        return {"mean": mean, "views": rows}, pics


def _save_png(path: Path, image: torch.Tensor) -> None:
    from PIL import Image

    arr = (image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def _write_json(path: Path, data: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, default=float))


def _device_name(dev: torch.device) -> str:
    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"


# ------------------------------------------------------------------------- commands
def run_recolor(args: Recolor, pipeline=None, console: Optional[Console] = None) -> dict:
    """The ``recolor`` benchmark; returns (and writes) its results."""
    console = console or Console(stderr=True)
    rule = args.rule.rule()
    if pipeline is None:
        from virgi_ns.nerfstudio.runs import load_run

        with console.status(f"loading {args.load_config}"):
            _, pipeline = load_run(args.load_config)
    with console.status("rendering the held-out views"):
        b = Bench.load(pipeline, args.edit_view, args.max_views)
    edited = b.edited_image(rule, args.edit_source)
    with console.status("fitting the edit"):
        edit, timing = b.fit(edited, args.steps, args.pixel_batches, args.repeats,
                             b.original(args.edit_source), args.whole_photo, changed_target=args.changed_target)
    with console.status("measuring"):
        res, pics = b.measure(edit, rule, args.lpips, args.pictures, edited=edited, target=b.fitted_target)
    out = {"config": str(args.load_config), "device": _device_name(b.scene.device),
           "gaussians": int(b.scene.means.shape[0]), "rule": rule.to_dict(), "edit_view": args.edit_view,
           "edit_source": args.edit_source, "whole_photo": args.whole_photo, "changed_target": args.changed_target,
           "timing": timing, **res}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for i, p in enumerate(pics):
        _save_png(args.out.with_name(f"{args.out.stem}_view{i}.png"), p)
    _save_png(args.out.with_name(f"{args.out.stem}_edit.png"), torch.cat([b.edit_photo.cpu(), edited.cpu()], 1))
    _write_json(args.out, out)
    return out


def summary(res: dict) -> str:
    m, t = res["mean"], res["timing"]
    return (f"recolour PSNR {m['recolour_psnr']:.2f} dB (unedited {m['unedited_psnr']:.2f}), SSIM "
            f"{m['recolour_ssim']:.4f}, LPIPS {m['recolour_lpips']:.4f}; propagation {m['propagation_psnr']:.2f} dB "
            f"(miss {m['miss_psnr']:.2f}, leak {m['leak_psnr']:.2f}); edit {t['total_s']:.3f} s "
            f"(setup {t['setup_s']:.3f} + {t['steps']} steps {t['steps_s']:.3f}) on {res['device']}")


def run_accuracy_time(args: AccuracyTime, pipeline=None, console: Optional[Console] = None) -> dict:
    """The sweep; writes JSON + PNG plot; returns the results."""
    console = console or Console(stderr=True)
    rule = args.rule.rule()
    if any(s < 1 for s in args.steps) or any(p < 1 for p in args.pixel_batches):
        raise InputError("--steps and --pixel-batches values must be >= 1")
    if pipeline is None:
        from virgi_ns.nerfstudio.runs import load_run

        with console.status(f"loading {args.load_config}"):
            _, pipeline = load_run(args.load_config)
    b = Bench.load(pipeline, args.edit_view, args.max_views)
    edited = b.edited_image(rule, args.edit_source)
    points = []
    for pb in args.pixel_batches:
        for s in args.steps:
            edit, timing = b.fit(edited, s, pb, args.repeats, b.original(args.edit_source), args.whole_photo)
            res, _ = b.measure(edit, rule, lpips=False)
            points.append({**timing, **res["mean"]})
            console.print(f"pixel_batches {pb} steps {s}: {timing['total_s']:.3f} s, recolour "
                          f"{res['mean']['recolour_psnr']:.2f} dB, propagation {res['mean']['propagation_psnr']:.2f} dB")
    out = {"config": str(args.load_config), "device": _device_name(b.scene.device), "rule": rule.to_dict(),
           "points": points}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    _write_json(args.out, out)
    plot_accuracy_time(out, args.out.with_suffix(".png"))
    return out


def plot_accuracy_time(res: dict, path: Path) -> None:
    """Recolour and propagation PSNR against edit wall time, one line per pixel subsampling."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = res["points"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for ax, key, title in ((axes[0], "recolour_psnr", "recolour PSNR (vs rule on photos)"),
                           (axes[1], "propagation_psnr", "propagation PSNR (vs rule on renders)")):
        for pb in sorted({p["pixel_batches"] for p in pts}):
            sel = sorted((p for p in pts if p["pixel_batches"] == pb), key=lambda p: p["total_s"])
            ax.plot([p["total_s"] for p in sel], [p[key] for p in sel], "o-",
                    label=f"1/{pb} of the pixels per step" if pb > 1 else "all pixels per step")
            for p in sel:
                ax.annotate(str(p["steps"]), (p["total_s"], p[key]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        if key == "recolour_psnr" and pts:
            ax.axhline(pts[0].get("unedited_psnr", math.nan), color="grey", ls="--", lw=1, label="unedited PSNR")
        ax.set_xlabel("edit wall time (s): setup + steps")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"accuracy vs time ({res['device']}; labels: steps)", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def main(argv: Optional[list[str]] = None) -> None:
    cmd = tyro.cli(Command, args=argv)  # type: ignore[arg-type]
    if isinstance(cmd, Recolor):
        print(summary(run_recolor(cmd)))
    else:
        res = run_accuracy_time(cmd)
        print(f"{len(res['points'])} points written to {cmd.out} and {cmd.out.with_suffix('.png')}")


def entrypoint() -> None:
    cli_entry(lambda: main(sys.argv[1:]))


__all__ = ["Bench", "Recolor", "AccuracyTime", "RuleArgs", "against_rule", "run_recolor", "run_accuracy_time", "psnr", "summary"]
