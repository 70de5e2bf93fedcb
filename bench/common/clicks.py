"""The benchmark's measurement of a pick (a click and a colour, :mod:`virgi_ns.edit.pick`) for
``bench/edit.py --pick``: how far one click gets compared with the same edit made from the
rule-edited image, and how long the viewer takes from a colour change or a release to its frame.

**The click** (fixed before any result was seen): on the edit view the rule edit uses, the pixel of
the rule's mask on that view's unedited render (covered pixels only: accumulation >=
:data:`~virgi_ns.edit.pick.MIN_COVER`, elsewhere a click picks nothing) that lies deepest inside the
mask's largest 4-connected component: the largest city-block distance to the nearest pixel outside
that component (outside the image counts as outside); among equals the one nearest the component's
centroid, then the first in raster order. Why: the largest object the rule recolours, clicked where
its colour is least mixed with its neighbours' (away from its edges), as a user clicks an object.

**The colour**: the rule applied to the render's colour at that pixel, rounded to 8 bits as a
user's ``#RRGGBB``; mode ``hue``, tolerance :data:`TOLERANCE` (0.2: the default of the viewer's
slider and of ``virgi-edit pick``). The pick runs as ``virgi-edit pick`` runs it
(:class:`~virgi_ns.edit.pick.PickSession` with :func:`~virgi_ns.edit.pick.pick_config`, the
config's steps, :func:`~virgi_ns.edit.pick.commit` onto a fresh stack) and is measured by
:meth:`Bench.measure <virgi_ns.bench.recolor.Bench.measure>`, as the rule edit is.

**What the click is judged against** (:func:`judge_pick`), by the class of the rule's mask on the edit
view (the covered pixels the click is chosen among; :func:`mask_class`):

- *one object*: the mask's largest 4-connected component holds at least :data:`ONE_OBJECT_SHARE` (80%)
  of its pixels. The click (contiguous selection, as the viewer's default) is compared with the rule
  edit: it passes within :data:`WITHIN_DB` (1 dB) of the rule edit's propagation PSNR.
- *many parts*: below 80%, on a row whose rule is declared to take many separate parts of one kind
  (``EvalScene.click`` ``parts``, or ``auto``: leaves all over a plant, the pieces of one object its
  texture cuts apart). The click runs with ``contiguous=False`` (every pixel of the view that passes
  the colour test, as ``--no-contiguous``) and is compared with the rule edit, within 1 dB.
- *several objects*: below 80%, on a row whose rule is declared to take different objects
  (``EvalScene.click`` ``objects``: a cup and its shelf). One click is meant to recolour one of them,
  so it is judged by the clicked object alone: the clicked object's miss >= 30 dB and the leak outside
  the clicked object's rule pixels >= 30 dB (against the rule on the unedited render there, the render
  unchanged elsewhere).

  The clicked object is the mask's component holding the click on the edit view; on a held-out view,
  its rule pixels are the rule's mask there where the clicked object's Gaussians cover at least half
  the pixel's opacity (the object's Gaussians: those that put at least half their blending weight on
  the edit view inside that component; :func:`object_gaussians`). Why this reading: it carries the
  object by the scene's own geometry, independent of what the click selected (a mask read off the
  click's own segmentation would hide exactly the leak onto the other objects that it must count).

Why the declaration and not a measure: whether the pieces of a split mask are one kind or different
objects is what the rule is written to take (its row's ``why``), not something the pixel counts tell.

Whatever the class, a click that meets the edit's targets by itself passes (:data:`CLICK_TARGETS`:
propagation >= 35, miss >= 30, leak >= 30 against the rule on the unedited render, or for *several
objects* the clicked object's figures above), whatever its distance to the rule edit: two edits both
at 40-60 dB are not a miss. A row's class, the reason and the verdict are in ``pick.judged``; a row
recorded without a class (``n/a``) is judged as *one object*.

**A perfect click** (:func:`perfect_click`; *one object* and *many parts*): the click's colour change
applied to every Gaussian the rule takes, as a perfect selection and fit would, is the click's ceiling,
as the rule applied per Gaussian is the edit's (issue 41's answer: the same rule for every figure with
a ceiling). A click within :data:`AT_CEILING_DB` (0.1 dB) of its propagation passes; a click that misses
where the perfect click misses too (its own targets, and 1 dB of the rule edit) is "cannot" (``judged``
``cannot``: one colour cannot express what the rule does there), and the bench says so beside the
verdict. Added after run sets 88 and 89, before any run that it judges.

**Latency** (:func:`viewer_latency`): the calls the viewer's Pick mode makes
(:mod:`virgi_ns.nerfstudio.viewer.picking`) on a :class:`FrozenScene`, each frame rendered by
:class:`~virgi_ns.nerfstudio.render_path.RenderPath` (the code of every viewer frame of a
``VirgiModel``: ``get_outputs`` on frozen geometry is ``render_camera(gated=specular_gating)``) on a
host holding the scene (:class:`ViewerRender`), since a nerfstudio model of the synthetic
1M-Gaussian scene would need a dataset and a checkpoint. Drag to frame: ``PickSession.update`` with
:data:`~virgi_ns.nerfstudio.viewer.picking.LIVE_STEPS` steps and a quarter of the segmentation's
steps (``_live_pick``), the live-edit slot set, the frame rendered. Top-up to frame (``_top_up_pick``,
which the viewer runs as soon as the change is shown and nothing newer waits): the fit topped up to
the config's steps in chunks of ``LIVE_STEPS``, the live slot set, the frame rendered; with the drag,
a change to its finished frame (``change_to_final_s``). Release to frame (``_commit_pick``): the
topped-up edit committed to a stack in a directory (its edit file and pictures written, as the
viewer's stack is), the live slot cleared, the frame rendered. Not counted: the viewer's wait of
``COMMIT_AFTER_S`` without a change that it takes as the release, viser's encoding and sending of the
frame, and the GUI's refresh of the edit list.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from common.training import sync as _sync
from virgi_ns.edit.recolor import RecolorRule, hsv_to_rgb, recolor, rule_mask
from virgi_ns.errors import InputError
from virgi_ns.nerfstudio.render_path import RenderPath

TOLERANCE = 0.2
MODE = "hue"
WITHIN_DB = 1.0
"""A click compared with the rule edit passes when its propagation PSNR is at least the rule edit's minus this."""
ONE_OBJECT_SHARE = 0.8
"""The rule's mask is one object where its largest 4-connected component holds at least this share of it."""
CLICK_TARGETS = {"propagation_psnr": 35.0, "miss_psnr": 30.0, "leak_psnr": 30.0}
"""The edit's own targets: a click that meets them passes whatever its distance to the rule edit."""
OBJECT_TARGETS = {"object_miss_psnr": 30.0, "object_leak_psnr": 30.0}
"""A click on one of several objects: the clicked object's miss, the leak outside its rule pixels."""
AT_CEILING_DB = 0.1
"""A click within this of a perfect click's propagation (:func:`perfect_click`) is at its ceiling and passes, as an
edit within this of its ceiling meets its target (``bench/edit.py`` ``CEILING_TOLERANCE_DB``)."""
CLASSES = {"parts": "many parts", "auto": "many parts", "objects": "several objects"}
"""The class of a mask below :data:`ONE_OBJECT_SHARE`, by the row's declaration (``EvalScene.click``)."""
LATENCY_TARGET_S = 0.1


# ------------------------------------------------------------------------------ the click rule
def _min4(x: Tensor, fill: int) -> Tensor:
    """Each pixel's smallest 4-neighbour (``fill`` beyond the image)."""
    p = torch.nn.functional.pad(x[None], (1, 1, 1, 1), value=fill)[0]
    return torch.minimum(torch.minimum(p[1:-1, :-2], p[1:-1, 2:]), torch.minimum(p[:-2, 1:-1], p[2:, 1:-1]))


def _until_stable(step: Callable[[Tensor], Tensor], x: Tensor, every: int = 16) -> Tensor:
    """Apply ``step`` until ``x`` no longer changes (checked every ``every`` steps: a check syncs)."""
    while True:
        before = x
        for _ in range(every):
            x = step(x)
        if torch.equal(x, before):
            return x


def largest_component(mask: Tensor) -> Tensor:
    """Bool [H,W]: the largest 4-connected component of ``mask`` (the first in raster order among
    equals; empty for an empty mask). Each pixel takes the smallest raster index of its component by
    repeated 4-neighbour minima."""
    H, W = mask.shape
    big = H * W
    index = torch.arange(big, device=mask.device).reshape(H, W)
    labels = torch.where(mask, index, big)
    labels = _until_stable(lambda lab: torch.where(mask, torch.minimum(lab, _min4(lab, big)), big), labels)
    if not bool(mask.any()):
        return mask.clone()
    counts = torch.bincount(labels[mask], minlength=big)
    return labels == int(torch.argmax(counts))  # argmax: the first (smallest label) among equals


def border_distance(mask: Tensor) -> Tensor:
    """Long [H,W]: each ``mask`` pixel's city-block distance to the nearest pixel outside ``mask``
    (beyond the image counts as outside); 0 outside."""
    zero = torch.zeros(mask.shape, dtype=torch.long, device=mask.device)
    return _until_stable(lambda d: torch.where(mask, _min4(d, 0) + 1, zero), zero)


def click_pixel(mask: Tensor) -> tuple[int, int, int]:
    """(x, y, depth) of the click the module docstring's rule chooses in ``mask`` [H,W]."""
    comp = largest_component(mask)
    if not bool(comp.any()):
        raise InputError("no pixel to click: the mask is empty")
    depth = border_distance(comp)
    ys, xs = torch.nonzero(depth == depth.max(), as_tuple=True)  # raster order
    cy, cx = (v.double().mean() for v in torch.nonzero(comp, as_tuple=True))
    k = int(torch.argmin((ys.double() - cy) ** 2 + (xs.double() - cx) ** 2))  # the first among equals
    return int(xs[k]), int(ys[k]), int(depth.max())


def _whole_view(scene, camera):
    """The contributions of ``camera``'s whole view (one camera) on ``scene``."""
    from virgi_ns.raster import Request

    cams = camera.to(scene.device, torch.float32)
    return scene.contributions(cams, Request.whole_images(cams))


def coverage(scene, camera) -> Tensor:
    """Float [H,W]: the view's accumulated opacity."""
    return _whole_view(scene, camera).accumulation()[0]


def rule_colour(render: Tensor, x: int, y: int, rule: RecolorRule) -> tuple[float, float, float]:
    """The rule's colour for the render's pixel (x, y), rounded to 8 bits (a user's #RRGGBB)."""
    c = recolor(render[y, x].clamp(0.0, 1.0), rule)[0]
    return tuple(round(255.0 * float(v)) / 255.0 for v in c)  # type: ignore[return-value]


# ------------------------------------------------------------------------------ what a click is judged against
def mask_class(mask: Tensor, declared: str = "auto") -> tuple[str, float]:
    """(class, the largest 4-connected component's share of ``mask``): ``one object`` where that share is
    at least :data:`ONE_OBJECT_SHARE`, else the class the row declares (:data:`CLASSES`). An empty mask:
    the declared class, share NaN."""
    if declared not in CLASSES:
        raise InputError(f"click kind must be one of {', '.join(CLASSES)}, got {declared!r}")
    total = int(mask.sum())
    share = int(largest_component(mask).sum()) / total if total else float("nan")
    return ("one object" if share >= ONE_OBJECT_SHARE else CLASSES[declared]), share


def _meets(p: dict, targets: dict) -> bool:
    return all(p.get(k, float("nan")) >= v for k, v in targets.items())


def judge_pick(p: dict) -> dict:
    """The verdict on a measured click ``p`` (its figures and ``class``), by the module docstring's rule:
    {class, share, reason, by (what passed it, or ``neither``), pass}. Reads only stored figures, so a
    merge judges old rows again (a row without ``class``: ``n/a``, judged as one object)."""
    klass, share = p.get("class", "n/a"), p.get("largest_share", float("nan"))
    part = f"largest part {share:.0%}" if share == share else "largest part n/a"
    if klass == "several objects":
        ok = _meets(p, OBJECT_TARGETS)
        reason = (f"several objects ({part}): the clicked object's miss "
                  f"{p.get('object_miss_psnr', float('nan')):.2f} and the leak outside its rule pixels "
                  f"{p.get('object_leak_psnr', float('nan')):.2f} (>= 30)")
        return {"class": klass, "share": share, "reason": reason, "by": "the clicked object" if ok else "neither",
                "pass": ok, "cannot": False}
    against = {"many parts": "--no-contiguous against the rule edit"}.get(klass, "against the rule edit")
    name = klass if klass != "n/a" else "class n/a"
    reason = f"{name} ({part}): {against}, within {WITHIN_DB:g} dB, or its own targets"
    own = _meets(p, CLICK_TARGETS)
    near = p.get("difference_db", float("nan")) >= -WITHIN_DB
    by = "its own targets" if own else f"within {WITHIN_DB:g} dB of the rule edit" if near else "neither"
    out = {"class": klass, "share": share, "reason": reason, "by": by, "pass": bool(own or near), "cannot": False}
    best = p.get("perfect_click_propagation_psnr", float("nan"))
    if out["pass"] or best != best:  # passed, or measured before the perfect click was
        return out
    if p["propagation_psnr"] >= best - AT_CEILING_DB:
        return {**out, "by": f"within {AT_CEILING_DB:g} dB of a perfect click {best:.2f}", "pass": True}
    perfect = {k: p.get(f"perfect_click_{k}", float("nan")) for k in CLICK_TARGETS}
    reachable = _meets(perfect, CLICK_TARGETS) or best - p.get("rule_propagation_psnr", float("nan")) >= -WITHIN_DB
    verdict = f"short of a perfect click {best:.2f}" if reachable else f"cannot: a perfect click scores {best:.2f}"
    return {**out, "by": verdict, "cannot": not reachable}


def object_gaussians(scene, camera, obj: Tensor) -> Tensor:
    """Bool [N]: the Gaussians of the object ``obj`` [H,W] shows on ``camera`` (one view): those that put
    at least half their blending weight on that view inside ``obj``."""
    c = _whole_view(scene, camera)
    g = c.gaussian().to(scene.device)
    w = c.weight.detach().float().to(scene.device)
    inside = obj.reshape(-1).to(scene.device)[c.pixel.to(scene.device)].float()
    total = torch.zeros(c.num_gaussians, device=scene.device).index_add(0, g, w)
    held = torch.zeros(c.num_gaussians, device=scene.device).index_add(0, g, w * inside)
    return (total > 0) & (held >= 0.5 * total)


def object_cover(scene, camera, gaussians: Tensor) -> Tensor:
    """Float [H,W]: the opacity the ``gaussians`` [N] bool composite to on ``camera`` (one view)."""
    from virgi_ns.raster import composite

    c = _whole_view(scene, camera)
    per_pair = gaussians.to(scene.device)[c.pair_gaussian.to(scene.device)].float()[:, None]
    return composite(per_pair, c)[0, ..., 0]


def object_figures(after: Tensor, base: Tensor, truth_render: Tensor, obj: Tensor) -> dict:
    """A click on one of several objects, on one view: the clicked object's miss (``after`` against the rule
    on the render, ``truth_render``, on the object's rule pixels ``obj``) and the leak outside them
    (against the render ``base``, with the rule only on ``obj``: the rule's other objects unchanged)."""
    from virgi_ns.bench.recolor import psnr

    truth = torch.where(obj[..., None], truth_render, base)
    return {"object_miss_psnr": psnr(after, truth_render, obj), "object_leak_psnr": psnr(after, truth, ~obj),
            "object_fraction": float(obj.float().mean())}


def measure_object(b, stack, rule: RecolorRule, obj: Tensor) -> dict:
    """:func:`object_figures` averaged over ``b``'s held-out views for the edits of ``stack``, the clicked
    object ``obj`` [H,W] given on the edit view (module docstring: its rule pixels on a held-out view)."""
    from virgi_ns.bench.recolor import _mean
    from virgi_ns.edit.scene import render_view

    gaussians = object_gaussians(b.scene, b.edit_camera, obj)
    rows = []
    for cams, base in zip(b.views, b.base):
        truth_render, mask = recolor(base, rule)
        held = mask & (object_cover(b.scene, cams, gaussians) >= 0.5)
        after = render_view(b.scene, cams, 0, stack)["rgb"].clamp(0, 1)
        rows.append(object_figures(after, base, truth_render, held))
    return {k: _mean([r[k] for r in rows]) for k in rows[0]} if rows else {}


# ------------------------------------------------------------------------------ a perfect click
def perfect_click_colours(colours: Tensor, rule: RecolorRule, colour: tuple[float, float, float],
                          reference: Tensor) -> Tensor:
    """The click's recolour (:func:`~virgi_ns.edit.pick.recolour`, mode :data:`MODE`) applied to every colour
    of ``colours`` [U, 3] that ``rule`` takes, with the clicked pixel's colour ``reference`` [3] as the pixel
    whose saturation becomes ``colour``'s; the others unchanged."""
    from virgi_ns.edit.pick import recolour

    u = colours.shape[0]
    image = torch.cat([colours, reference.to(colours)[None]], 0)[:, None, :]
    takes = torch.cat([rule_mask(colours, rule), torch.ones(1, dtype=torch.bool, device=colours.device)])[:, None]
    return recolour(image, takes, colour, MODE, at=(0, u))[:u, 0]


def perfect_click(b, rule: RecolorRule, colour: tuple[float, float, float], x: int, y: int) -> dict:
    """A click's ceiling on ``b``'s held-out views: the click's colour change (:func:`perfect_click_colours`,
    the reference the clicked pixel (x, y) of the edit view's render) applied to every Gaussian whose colour
    the rule takes, as a perfect selection and a perfect fit would, composited and scored against the rule
    on the render as the click is (``perfect_click_`` + propagation / miss / leak, the views' means). Why:
    one colour cannot always express the rule (a hue shift keeps a plant's 100 degrees of leaves apart; one
    hue does not), and a click that misses where even this misses "cannot", as an edit below its ceiling."""
    from virgi_ns.bench.recolor import _mean, against_rule
    from virgi_ns.edit.scene import render_view

    reference = b.edit_base[y, x].clamp(0.0, 1.0)
    rows = []
    for cams, base in zip(b.views, b.base):
        after = render_view(b.scene, cams, 0, colour_map=lambda c: perfect_click_colours(c, rule, colour, reference))
        rows.append(against_rule(after["rgb"].clamp(0, 1), *recolor(base, rule)))
    return {f"perfect_click_{k}": _mean([r[k] for r in rows]) for k in CLICK_TARGETS} if rows else {}


# ------------------------------------------------------------------------------ pick on a trained run


def measure_pick(b, rule: RecolorRule, rule_propagation: float, keep: int = 0,
                 click: str = "auto") -> tuple[dict, list, Tensor]:
    """One click on ``b``'s edit view by the module docstring's rule, as ``virgi-edit pick`` makes it, measured as
    the rule edit is (``rule_propagation``: its propagation PSNR on the same run) and judged by
    :func:`judge_pick` (``click``: the row's declared kind, ``EvalScene.click``). Returns (figures, the
    held-out pictures of :meth:`Bench.measure`, the edit view's render | edited image | selection | rule mask)."""
    from virgi_ns.edit.pick import MIN_COVER, PickSession, commit, pick_config
    from virgi_ns.edit.stack import EditStack

    render = b.edit_base
    mask = rule_mask(render, rule)
    clickable = mask & (coverage(b.scene, b.edit_camera) >= MIN_COVER)
    klass, share = mask_class(clickable, click)
    x, y, depth = click_pixel(clickable)
    colour = rule_colour(render, x, y, rule)
    stack = EditStack(b.fingerprint)
    stack.to(b.scene.device)
    _sync(b.scene.device)
    t0 = time.perf_counter()
    cfg = pick_config(b.scene.device)
    session = PickSession(b.scene, b.edit_camera, x, y, stack, cfg)
    edit = session.update(colour, TOLERANCE, MODE, contiguous=klass != "many parts")
    _sync(b.scene.device)
    fit_s = time.perf_counter() - t0
    commit(stack, session, edit)
    res, pics = b.measure(stack.entries[0].edit, rule, lpips=False, keep=keep)
    sel = session.mask
    union = int((sel | mask).sum())
    m = res["mean"]
    out = {"pixel": [x, y], "depth": depth, "colour": session.settings["colour"], "mode": MODE,
           "criterion": session.criterion, "reference": session.reference, "recipe": session.engine.recipe,
           "contiguous": session.settings["contiguous"], "tolerance": TOLERANCE, "selected": session.settings["selected"],
           "iou": int((sel & mask).sum()) / union if union else float("nan"),
           "propagation_psnr": m["propagation_psnr"], "miss_psnr": m["miss_psnr"], "leak_psnr": m["leak_psnr"],
           "edit_view_propagation_psnr": m["edit_view_propagation_psnr"],
           "rule_propagation_psnr": rule_propagation, "difference_db": m["propagation_psnr"] - rule_propagation,
           "fit_s": fit_s, "steps": session.steps_done, "changed_progress": session.engine.changed_progress(),
           "restaged": edit.info.get("restaged"),
           "per_view_propagation": [v["propagation_psnr"] for v in res["views"]],
           "class": klass, "declared": click, "largest_share": share}
    if klass == "several objects":  # the clicked object: the click's component of the mask (the largest)
        out.update(measure_object(b, stack, rule, largest_component(clickable)))
    else:
        out.update(perfect_click(b, rule, colour, x, y))
    out["judged"] = judge_pick(out)
    out["pass"] = out["judged"]["pass"]
    grey = lambda t: t.float()[..., None].expand(-1, -1, 3)  # noqa: E731
    picture = torch.cat([render, session.edited, grey(sel), grey(mask)], dim=1).cpu()
    return out, pics, picture


# ------------------------------------------------------------------------------ the viewer's latency
class ViewerRender(RenderPath):
    """:class:`RenderPath`, the mixin a ``VirgiModel`` renders every viewer frame with, on a host that
    holds only what it reads from the model: a :class:`FrozenScene`'s Gaussians (stored as the model
    stores them: log scales, logit opacities), its field and background, and ``VirgiModelConfig``'s
    render settings (its defaults)."""

    def __init__(self, scene) -> None:
        from virgi_ns.nerfstudio.model import VirgiModelConfig

        d = VirgiModelConfig()
        self.config = SimpleNamespace(whole_view_renderer=d.whole_view_renderer, specular_gating=d.specular_gating,
                                      gate_threshold=d.gate_threshold, raster_backend=scene.backend)
        self.scene = scene
        self.field = scene.field
        self.means, self.quats = scene.means, scene.quats
        self.scales = torch.log(scene.scales)
        self.opacities = torch.logit(scene.opacities, eps=1e-6)[:, None]
        self.gauss_params = {"means": self.means, "quats": self.quats, "scales": self.scales,
                             "opacities": self.opacities}  # as the model holds them (the render cache reads these)
        self.background_color = scene.background
        self.device = scene.device
        self.num_points = int(scene.means.shape[0])
        self.spec_magnitude = torch.zeros(0, device=self.device)
        self.diffuse_cache = torch.zeros(0, 3, device=self.device)
        self.edit_stack = self.live_edit = self.segmentation_edit = None

    def contributions(self, cams, request):
        return self.scene.contributions(cams, request)

    def frame(self, camera) -> dict:
        """The viewer's frame of ``camera`` (nerfstudio cameras): what ``VirgiModel.get_outputs``
        renders for frozen geometry in eval mode."""
        return self.render_camera(camera, gated=self.config.specular_gating)


def _timed(device: torch.device, parts: list[tuple[str, Callable[[], object]]]) -> tuple[dict, object]:
    """Run ``parts`` in order, each synchronised with ``device``: ({name: seconds, 'total_s'}, the last
    part's value)."""
    times, value = {}, None
    _sync(device)
    start = t = time.perf_counter()
    for name, fn in parts:
        value = fn()
        _sync(device)
        now = time.perf_counter()
        times[name] = now - t
        t = now
    times["total_s"] = t - start
    return times, value


def drag_frame(host: ViewerRender, session, camera, colour: tuple, tolerance: float, mode: str) -> tuple[dict, dict]:
    """A colour change during a drag to its frame, as ``PickActions._live_pick`` makes it:
    ({fit_s, render_s, total_s, fit_parts: the update's parts in seconds}, the frame)."""
    from virgi_ns.nerfstudio.viewer.picking import LIVE_STEPS

    seg = max(1, session.engine.cfg.seg_steps // 4)
    parts: dict = {}
    last = [0.0]

    def tick(part: str) -> None:
        _sync(host.device)
        now = time.perf_counter()
        parts[f"{part}_s"] = now - last[0]
        last[0] = now

    def refit() -> None:
        last[0] = time.perf_counter()
        host.set_live_edit(session.update(colour, tolerance, mode, LIVE_STEPS, seg, timer=tick))

    times, frame = _timed(host.device, [("fit_s", refit), ("render_s", lambda: host.frame(camera))])
    return {**times, "fit_parts": parts}, frame


def top_up_frame(host: ViewerRender, session, camera) -> tuple[dict, dict, object]:
    """The top-up after a change to its frame, as ``PickActions._top_up_pick`` makes it while nothing
    changes (chunks of ``LIVE_STEPS`` to the config's steps, then the live slot set): ({fit_s,
    render_s, total_s}, the frame, the topped-up edit)."""
    from virgi_ns.nerfstudio.viewer.picking import LIVE_STEPS

    edits: list = []

    def top_up() -> None:
        while session.steps_left:
            edits.append(session.refine(min(LIVE_STEPS, session.steps_left)))
        host.set_live_edit(edits[-1])

    times, frame = _timed(host.device, [("fit_s", top_up), ("render_s", lambda: host.frame(camera))])
    return times, frame, edits[-1]


def release_frame(host: ViewerRender, stack, session, camera, topped=None) -> tuple[dict, dict]:
    """A release to its frame, as ``PickActions._commit_pick`` makes it (the first commit of the pick):
    ({fit_s (what is left of the top-up: none after :func:`top_up_frame`, whose edit is ``topped``),
    commit_s (pictures and stack files), clear_s (the live slot), render_s, total_s}, the frame)."""
    from virgi_ns.edit.pick import commit

    edit: list = []

    def top_up() -> None:
        left = session.steps_left
        edit.append(session.refine(left) if left or topped is None else topped)

    return _timed(host.device, [("fit_s", top_up), ("commit_s", lambda: commit(stack, session, edit[0])),
                                ("clear_s", lambda: host.set_live_edit(None)), ("render_s", lambda: host.frame(camera))])


def _hue(degrees: float) -> tuple[float, float, float]:
    """A saturated colour of hue ``degrees``."""
    return tuple(float(v) for v in hsv_to_rgb(torch.tensor([degrees % 360.0, 0.8, 0.85])))  # type: ignore[return-value]


def viewer_latency(scene, cams, repeats: int, cfg=None) -> dict:
    """Median drag-to-frame and release-to-frame times (seconds, by part) of picks on ``scene``'s one
    view ``cams``, after one warm-up pick. Each pick: a click (the deepest covered pixel by
    :func:`click_pixel`, set up and fitted untimed, as its first frame shows), one timed colour change,
    the timed release, then undone (each pick is the stack's only edit). ``cfg``: the pick's
    :class:`EditConfig` (default: the viewer's, :func:`~virgi_ns.edit.pick.pick_config`)."""
    from virgi_ns.edit.pick import MIN_COVER, PickSession, pick_config
    from virgi_ns.edit.stack import EditStack
    from virgi_ns.nerfstudio.cameras import ns_cameras
    from virgi_ns.nerfstudio.viewer.picking import LIVE_STEPS

    host = ViewerRender(scene)
    gate = host.build_specular_gate(cams)
    camera = ns_cameras(cams).to(scene.device)
    x, y, _ = click_pixel(coverage(scene, cams) >= MIN_COVER)
    cfg = cfg or pick_config(scene.device)
    drags, top_ups, releases, selected = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="virgi_pick_bench_") as run_dir:
        stack = EditStack.open(run_dir, scene.fingerprint())
        host.set_edit_stack(stack)
        for r in range(max(1, repeats) + 1):
            session = PickSession(scene, cams, x, y, stack, cfg)
            host.set_live_edit(session.update(_hue(40.0 * r), TOLERANCE, MODE, LIVE_STEPS))
            host.frame(camera)
            drag, _ = drag_frame(host, session, camera, _hue(40.0 * r + 20.0), TOLERANCE, MODE)
            top_up, _, topped = top_up_frame(host, session, camera)
            release, _ = release_frame(host, stack, session, camera, topped)
            stack.undo()
            if r:  # the first pick warms up
                drags.append(drag)
                top_ups.append({**top_up, "change_to_final_s": drag["total_s"] + top_up["total_s"]})
                releases.append(release)
                selected.append(session.settings["selected"])
    def med(rows: list) -> dict:  # per key, nested dicts too
        return {k: med([t[k] for t in rows]) if isinstance(v, dict) else float(statistics.median(t[k] for t in rows))
                for k, v in rows[0].items()}

    return {"gaussians": host.num_points, "image": f"{int(cams.widths[0])}x{int(cams.heights[0])}",
            "renderer": "gsplat" if host._renders_with_gsplat() else "contributions",
            "gate_kept": gate["kept_fraction"], "pixel": [x, y], "selected": float(statistics.median(selected)),
            "live_steps": LIVE_STEPS, "steps": cfg.steps, "repeats": len(drags), "drag": med(drags),
            "top_up": med(top_ups), "release": med(releases), "target_s": LATENCY_TARGET_S}


__all__ = ["CLASSES", "CLICK_TARGETS", "LATENCY_TARGET_S", "MODE", "OBJECT_TARGETS", "ONE_OBJECT_SHARE", "TOLERANCE",
           "WITHIN_DB", "ViewerRender", "border_distance", "click_pixel", "coverage", "drag_frame", "judge_pick",
           "largest_component", "mask_class", "measure_object", "measure_pick", "object_cover", "object_figures",
           "object_gaussians",
           "release_frame", "rule_colour", "top_up_frame", "viewer_latency"]
