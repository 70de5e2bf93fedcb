"""The edit engine: one edited image of one view recolours the whole scene.

Geometry is frozen, so the edited view's pixels are a fixed linear map of per-Gaussian colours
(``pixel = A C + T bg``, :mod:`virgi_ns.raster.contract`). :class:`EditEngine` computes, once: the
view's contributions, the features ``f`` and ``h_diff`` of the Gaussians the view sees, the colour
``c_d`` the current stack gives them and their specular ``c_s`` for this camera
(:class:`~virgi_ns.edit.scene.FrozenScene`). Each step then trains only a copy of the diffuse head and a
segmentation head::

    c_d'  = W h_diff + b                       (W, b: the base diffuse head, or for a large edit
                                                M W, M b + t, the colour map's start)
    alpha = sigmoid(MLP_seg([f, h_diff]))      (starts near 0)
    c_d'' = alpha c_d' + (1 - alpha) c_d
    C'    = sigmoid(c_d'' + k c_s)
    loss  = L1(A C' + T bg, I_target)          (Adam, one pixel set per step)

The parts, each in its module: the settings (:class:`~virgi_ns.edit.config.EditConfig`), what the loss
fits (:mod:`virgi_ns.edit.targets`: only the pixels the user changed are fitted to the edit, the others
keep the current render, and the changed ones carry ``changed_share`` of the loss), the pixel sets and
their sparse matrices (:mod:`virgi_ns.edit.pixels`), the heads (:mod:`virgi_ns.edit.heads`), and how
the steps run (:mod:`virgi_ns.edit.fitting`: the schedule, the ``staged`` recipe's classifier, the
recorded CUDA graphs). The result is an :class:`~virgi_ns.edit.stack.Edit` for the
:class:`~virgi_ns.edit.stack.EditStack`.
"""

from __future__ import annotations

import copy
import functools
import warnings
from typing import Callable, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.edit.config import EditConfig
from virgi_ns.edit.fitting import (EditTiming, GraphedSteps, Stopwatch, classifier_samples,
                                   constant_segmentation, gaussian_labels, schedule, segmentation_rate,
                                   train_classifier, warm_up_and_record)
from virgi_ns.edit.heads import FusedHeads, FusedLayer, HeadsInputs, fresh_segmentation
from virgi_ns.edit.optim import EditAdam
from virgi_ns.edit.pixels import PixelBatch, pixel_batches, resolve_composite
from virgi_ns.edit.scene import FrozenScene
from virgi_ns.edit.stack import Edit, EditSource, EditStack, new_edit_info
from virgi_ns.edit.targets import MAP_START_SHARE, Target, find_target, logit_colour_map, unchanged_pixel_weights
from virgi_ns.errors import InputError
from virgi_ns.raster import Cameras, Request, composite

_UNMEASURED = object()  # EditEngine.changed_progress not yet computed for the current heads

VIEW_FIELDS = ("contrib", "gaussians", "feats", "h_diff", "c_s", "c_d", "k", "background", "current")
"""The engine's view: what :meth:`EditEngine._setup_view` computes for its camera and stack, fits only read,
and an engine built ``view_of`` another shares."""

SMALL_PROGRESS = 0.1
"""A fit that moved its changed pixels less than this share of the way from the render to their target
has not taken the edit: the commands say so (:meth:`EditEngine.small_progress_note`)."""


class EditEngine:
    """Fits one edit of ``scene`` from ``edited`` [H,W,3] (float, [0,1]) seen by ``camera`` (one
    view). The stack's current edits and specular strength are the starting point. Usage:
    ``edit, timing = EditEngine(scene, camera, edited, stack).fit()``.

    Args:
        scene: the frozen Gaussians and colour field.
        camera: one view.
        edited: [H,W,3] the edited image, or None to set up the view only (its contributions,
            features and render, :attr:`current`); :meth:`retarget` then gives the target, and again
            for every new target of the same view (a live drag).
        stack: the run's edits (the new edit goes on top of them); None: the base colours.
        cfg: the settings (:class:`EditConfig`).
        source: where the edit came from (recorded in the edit).
        original: [H,W,3] the image the user started from (a training photo), which tells the changed
            pixels (:func:`~virgi_ns.edit.targets.find_target`).
        changed: [H,W] bool, the changed pixels when the caller knows them (a pick's selection).
        view_of: an engine of the same scene, camera and stack whose view (contributions, features,
            colours and render, which fits only read) this one shares instead of computing it again."""

    def __init__(
        self,
        scene: FrozenScene,
        camera: Cameras,
        edited: Optional[Float[Tensor, "H W 3"]],
        stack: Optional[EditStack] = None,
        cfg: Optional[EditConfig] = None,
        source: Optional[EditSource] = None,
        original: Optional[Float[Tensor, "H W 3"]] = None,
        changed: Optional[Tensor] = None,
        view_of: Optional["EditEngine"] = None,
    ) -> None:
        self.scene = scene
        self.cfg = cfg or EditConfig()
        self.stack = stack
        if len(camera) != 1:
            raise ValueError(f"EditEngine: one camera expected, got {len(camera)}")
        W, H = int(camera.widths[0]), int(camera.heights[0])
        if edited is not None:
            _check_images(edited, original, changed, W, H)
        self.camera = camera
        self.source = source or EditSource("", camera.Ks[0], camera.viewmats[0], W, H, "")
        self.fingerprint = stack.fingerprint if stack is not None else scene.fingerprint()
        self.target: Optional[Target] = None
        self.recipe = self.cfg.recipe
        """The recipe the fit runs: the config's, or ``joint`` where the changed pixels are unknown."""
        self.batches: list[PixelBatch] = []
        self.colour_map: Optional[Tensor] = None
        self.alpha_fixed: Optional[Tensor] = None
        self.opt: Optional[EditAdam] = None
        self._graphs: Optional[GraphedSteps] = None  # the recorded steps (_fit_graphed)
        self._heads: Optional[FusedHeads | FusedLayer] = None  # the written-out step (_set_heads), else autograd
        self._progress: object = _UNMEASURED  # changed_progress() of the current heads, once asked
        with Stopwatch(scene.device) as watch:
            if view_of is None:
                self._setup_view()
            else:
                self._share_view(view_of)
            self._fresh_heads()
            if edited is not None:
                self._set_target(*self._on_device(edited, original, changed), warm=False)
        self.setup_s = watch.seconds

    # ------------------------------------------------------------------ what the fit reads
    @property
    def mode(self) -> str:
        """What the loss fits, in words."""
        return "whole image" if self.target is None else self.target.mode

    @property
    def changed_fraction(self) -> float:
        """The share of the view's pixels the edit changed (1 for a whole-image fit)."""
        return 1.0 if self.target is None else self.target.fraction

    # ------------------------------------------------------------------ setup
    @torch.no_grad()
    def _setup_view(self) -> None:
        """The view's contributions, the visible Gaussians' features and colours, and its render."""
        sc, dev = self.scene, self.scene.device
        cams = self.camera.to(dev, torch.float32)
        contrib = sc.contributions(cams, Request.whole_images(cams))
        if contrib.pair_gaussian.numel() == 0:
            raise InputError("the edit's camera sees none of the scene")
        view = sc.view(cams, contrib)
        self.contrib, self.gaussians = view.contrib, view.gaussians
        self.feats, self.h_diff, self.c_s = view.feats, view.h_diff, view.c_s
        self.c_d = self.stack.diffuse(self.feats, self.h_diff, view.c_d) if self.stack is not None else view.c_d
        self.k = self.stack.specular_strength if self.stack is not None else 1.0
        if sc.file_colours is not None:  # the Gaussians' own colours under the field's change
            offset, c_s = sc.file_colours.for_edit(view.gaussians, view.dirs, view.c_d, self.k)
            self.c_d, self.c_s = self.c_d + offset.float(), c_s.float()
        self.background = sc.background.to(dev, torch.float32).reshape(3)
        # the view's render through the stack [H,W,3]: what unchanged pixels keep
        self.current = composite(torch.sigmoid(self.c_d + self.k * self.c_s), self.contrib, self.background)[0]

    def _share_view(self, other: "EditEngine") -> None:
        """The view of ``other`` (the same scene, camera and stack), shared: fits never write it."""
        a, b = other.camera, self.camera
        same_camera = all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("viewmats", "Ks", "widths", "heights"))
        if other.scene is not self.scene or other.stack is not self.stack or not same_camera:
            raise ValueError("EditEngine: view_of must be an engine of the same scene, camera and stack")
        for name in VIEW_FIELDS:
            setattr(self, name, getattr(other, name))

    @torch.no_grad()
    def _fresh_heads(self) -> None:
        """A fresh segmentation head (from ``cfg.seed``) and the copied layer set to the base's."""
        sc, dev, cfg = self.scene, self.scene.device, self.cfg
        self.seg = copy.deepcopy(fresh_segmentation(self.feats.shape[1], self.h_diff.shape[1], cfg.seg_width,
                                                    cfg.seg_init_bias, cfg.seed, torch.device(dev)))
        self.seg_input = self.seg.inputs(self.feats, self.h_diff)
        head = sc.field.diffuse_head
        self.weight = head.weight.detach().float().clone().requires_grad_(True)
        self.bias = head.bias.detach().float().clone().requires_grad_(True)

    def _on_device(self, edited: Tensor, original: Optional[Tensor], changed: Optional[Tensor]) -> tuple:
        dev = self.scene.device
        return (edited.to(dev, torch.float32), None if original is None else original.to(dev, torch.float32),
                None if changed is None else changed.to(dev))

    @torch.no_grad()
    def _set_target(self, edited: Tensor, original: Optional[Tensor], selection: Optional[Tensor], warm: bool,
                    seg_steps: Optional[int] = None) -> None:
        """The loss's target (:func:`~virgi_ns.edit.targets.find_target`), its pixel sets, and the heads'
        start: fresh, or (``warm``) from the current fit (:meth:`retarget`)."""
        target = find_target(self.cfg, self.current, edited, original, selection)
        self._progress = _UNMEASURED
        previous, same = self._set_batches(target, warm)
        self.target = target
        self.recipe = self.cfg.recipe if target.changed is not None else "joint"
        staged = self.recipe == "staged"
        self._start_layer(target, warm, previous, staged)
        self._set_segmentation(target, warm, same, staged, seg_steps)
        self._set_heads()
        self._set_optimizer(staged)

    def _set_batches(self, target: Target, warm: bool) -> tuple[Optional[Tensor], bool]:
        """The pixel sets of ``target``: where a warm retarget keeps the same changed pixels, only their
        targets move (in place: recorded steps read them). Returns (the last target image when the pixel
        sets are kept, whether they are)."""
        flat, image = target.flat, target.image.reshape(-1, 3)
        kind = resolve_composite(self.cfg.batch_composite, image.device)
        last = self.target
        same = bool(warm and self.batches and self.batches[0].composite == kind and last is not None
                    and (flat is None) == (last.flat is None) and (flat is None or torch.equal(flat, last.flat)))
        if same:
            for b in self.batches:
                b.target.copy_(image if b.pixels is None else image[b.pixels])
            return last.image, True
        keep = None
        if flat is not None and self.cfg.unchanged_weights == "colour":
            c = self.contrib
            keep = unchanged_pixel_weights(c.pixel, c.pair, c.weight, torch.sigmoid(self.c_d), flat,
                                           getattr(c, "pixel_offsets", None))
        self.batches = pixel_batches(self.contrib, image, self.background, self.cfg.pixel_batches, self.cfg.seed,
                                     flat, self.cfg.changed_share, kind, target.count, keep)
        for b in self.batches:
            if b.pixels is None:  # the whole image: its own copy, which a warm retarget writes into
                b.target = b.target.clone()
        self._graphs = None
        return None, False

    def _start_layer(self, target: Target, warm: bool, previous: Optional[Tensor], staged: bool) -> None:
        """The copied layer's start: the colour map of the changed pixels (a large edit, or ``staged``),
        else the base layer (a fresh fit) or where the last fit left it (warm), moved by the colour map
        from the last target to this one when only the colours of the same pixels changed."""
        flat, image = target.flat, target.image.reshape(-1, 3)
        head = self.scene.field.diffuse_head
        self.colour_map = None
        if flat is not None and (staged or target.fraction >= MAP_START_SHARE):
            # fitted on the current render (earlier edits and specular included) but applied to the base
            # layer: with a stack, c_d' starts at M c_d_base + t, only a starting point
            self.colour_map = logit_colour_map(self.current.reshape(-1, 3)[flat], image[flat], self.cfg.seed)
            self._set_layer_mapped(self.colour_map, head.weight.detach().float(), head.bias.detach().float())
        elif not warm:
            self.weight.copy_(head.weight.detach().float())
            self.bias.copy_(head.bias.detach().float())
        elif previous is not None and flat is not None:
            self._set_layer_mapped(logit_colour_map(previous.reshape(-1, 3)[flat], image[flat], self.cfg.seed),
                                   self.weight, self.bias)

    def _set_layer_mapped(self, colour_map: Tensor, weight: Tensor, bias: Tensor) -> None:
        """The copied layer set to ``weight``, ``bias`` followed by the logit colour map ``[M | t]``
        (in place: recorded steps read the layer)."""
        M, t = colour_map[:, :3], colour_map[:, 3]
        new_weight, new_bias = M @ weight, M @ bias + t  # before writing: weight may be the layer itself
        self.weight.copy_(new_weight)
        self.bias.copy_(new_bias)

    def _set_segmentation(self, target: Target, warm: bool, same: bool, staged: bool,
                          seg_steps: Optional[int]) -> None:
        """``staged``: the segmentation classified from the changed pixels (kept when they are the same),
        its alpha fixed; back on the joint recipe, the head trains again."""
        if staged and not (same and self.alpha_fixed is not None):
            alpha = self._classify(target, warm=warm and self.alpha_fixed is not None,
                                   steps=self.cfg.seg_steps if seg_steps is None else seg_steps)
            if self.alpha_fixed is None:
                self.alpha_fixed = alpha
                self._graphs = None
            else:  # in place: recorded steps read it
                self.alpha_fixed.copy_(alpha)
        elif not staged and self.alpha_fixed is not None:
            self.alpha_fixed = None
            self._graphs = None
            for p in self.seg.parameters():
                p.requires_grad_(True)

    def _classify(self, target: Target, warm: bool, steps: int) -> Tensor:
        """The ``staged`` recipe's segmentation: each of the view's Gaussians labelled by where its pixel
        weight lands (:func:`~virgi_ns.edit.fitting.gaussian_labels`), the head trained as their classifier
        with unlabelled Gaussians of the whole scene as weak negatives; returns its alpha [U, 1]."""
        c, dev = self.contrib, self.h_diff.device
        # the entries' indices as they are (int32 from the kernels): a copy to int64 costs more than the sums
        on_changed = torch.index_select(target.flat, 0, c.pixel.to(dev))
        label, trust = gaussian_labels(c.pair.to(dev), c.weight.detach().to(dev).float(), on_changed,
                                       self.gaussians.numel())
        drawn = classifier_samples(label, trust, self.cfg, self.scene.means.shape[0])
        if drawn is None:  # one class: a constant alpha
            return constant_segmentation(self.seg, self.seg_input, positive=bool(float((trust * label).sum()) > 0.0))
        idx, anywhere = drawn
        x, y = self.seg_input[idx], label[idx].float()[:, None]
        if anywhere.numel() > 0:
            f, _, h2 = self.scene.gaussian_features(anywhere)
            x = torch.cat([x, self.seg.inputs(f, h2)])
            y = torch.cat([y, torch.zeros(anywhere.numel(), 1, device=dev)])
        return train_classifier(self.seg, x, y, self.seg_input, self.cfg, warm=warm, steps=steps)

    def _set_heads(self) -> None:
        """The written-out step (:attr:`EditConfig.fused_heads`) where it runs, on the fused kind's pixel sets
        on a GPU: the joint recipe's heads (:class:`FusedHeads`), or the staged recipe's copied layer with
        its segmentation fixed (:class:`FusedLayer`); otherwise None (autograd). A change drops the
        recorded steps."""
        sets = self.batches[0].sets if self.batches else None
        use = self.cfg.fused_heads and sets is not None and FusedHeads.runs_on(self.seg, self.h_diff.device)
        kind = None if not use else FusedHeads if self.alpha_fixed is None else FusedLayer
        current = self._heads
        if current is None and kind is None:
            return
        if type(current) is kind and (kind is FusedHeads or current.alpha is self.alpha_fixed):
            return  # the same step on the same tensors: the recorded steps stand
        inputs = HeadsInputs(self.seg_input, self.feats.shape[1], self.c_d, self.c_s, self.k)
        if kind is FusedHeads:
            self._heads = FusedHeads(self.seg, self.weight, self.bias, inputs)
        elif kind is FusedLayer:
            self._heads = FusedLayer(self.alpha_fixed, self.weight, self.bias, inputs)
        else:
            self._heads = None
        self._graphs = None

    def _set_optimizer(self, staged: bool) -> None:
        """Adam over the trained tensors (the layer, and the segmentation head unless ``staged``), started
        afresh; the same tensors at the same rates keep their optimizer, restarted in place."""
        trainable = [self.weight, self.bias] + ([] if staged else list(self.seg.parameters()))
        rate = segmentation_rate(self.cfg, None if self.target.changed is None else self.target.fraction)
        scales = [1.0, 1.0] + [rate] * (len(trainable) - 2)
        if (self.opt is not None and [id(p) for p in self.opt.params] == [id(p) for p in trainable]
                and self.opt.scales == scales):
            self.opt.restart()  # the same tensors, which recorded steps read and write
        else:
            hold, decay = schedule(self.cfg)
            self.opt = EditAdam(trainable, lr=self.cfg.lr, decay_steps=decay, hold_steps=hold, scales=scales)
            self._graphs = None

    def retarget(self, edited: Float[Tensor, "H W 3"], changed: Optional[Tensor] = None,
                 original: Optional[Float[Tensor, "H W 3"]] = None, seg_steps: Optional[int] = None) -> None:
        """A new target for the same view, warm-started from the current fit (the live drag of a pick):
        the view's contributions and features are kept; the pixel sets too when the changed pixels are
        the same, and so is a staged segmentation, which otherwise trains on from where it is
        (``seg_steps``: how long; default the config's); the layer starts from the new target's colour
        map where a fresh fit would (staged, or a large edit), else where the last fit left it, moved by
        the colour map from the last target to this one when the changed pixels are the same (a new
        colour for the same selection); Adam starts afresh. :meth:`fit` then runs the steps."""
        W, H = int(self.camera.widths[0]), int(self.camera.heights[0])
        _check_images(edited, original, changed, W, H)
        with Stopwatch(self.scene.device) as watch:
            self._set_target(*self._on_device(edited, original, changed), warm=True, seg_steps=seg_steps)
        self.setup_s = watch.seconds

    # ------------------------------------------------------------------ steps
    def colours(self) -> tuple[Tensor, Tensor]:
        """(C' [U,3], alpha [U,1]) of the view's Gaussians under the current heads."""
        alpha = self.alpha_fixed if self.alpha_fixed is not None else torch.sigmoid(self.seg.logits_of(self.seg_input))
        c_dp = torch.nn.functional.linear(self.h_diff, self.weight, self.bias)
        c_dd = alpha * c_dp + (1.0 - alpha) * self.c_d
        return torch.sigmoid(c_dd + self.k * self.c_s), alpha

    def step(self, i: int) -> Tensor:
        """Step ``i`` of a fit: one Adam step on pixel set ``i % len(self.batches)`` (the ``fused`` kind
        takes the set its device counter names, which :meth:`fit` keeps equal to it)."""
        self._progress = _UNMEASURED
        if self._heads is not None:  # the fused kind's sets and the written-out step
            loss = self._heads.step(self.batches[0].sets)
            self.opt.step()
            return loss
        self.opt.zero_grad()
        C, _ = self.colours()
        loss = self.batches[i % len(self.batches)].loss(C)
        loss.backward()
        self.opt.step()
        return loss.detach()

    def fit(self, steps: Optional[int] = None, progress: Optional[Callable[[int, int], None]] = None
            ) -> tuple[Edit, EditTiming]:
        """Run ``steps`` (default the config's) steps; returns the edit and its timing. ``progress(done,
        total)`` is called every 10 steps (it never forces a GPU sync)."""
        n = self.cfg.steps if steps is None else int(steps)
        dev = self.scene.device
        self._progress = _UNMEASURED
        with Stopwatch(dev) as watch:
            loss = torch.zeros((), device=dev)
            sets = self.batches[0].sets
            if sets is not None:  # the fused kind picks its set on the device: step 0 takes the first
                sets.restart()
            with torch.enable_grad():  # callers may hold a no_grad context (viewer threads, scripts)
                done = 0
                if self.cfg.cuda_graphs and dev.type == "cuda" and (
                        n > 2 * len(self.batches) or (self._graphs is not None and n > 0)):
                    done, loss = self._fit_graphed(n, progress)
                for i in range(done, n):
                    loss = self.step(i)
                    if progress is not None and ((i + 1) % 10 == 0 or i + 1 == n):
                        progress(i + 1, n)
        timing = EditTiming(self.setup_s, watch.seconds, n, float(loss))
        return self.edit(timing), timing

    @torch.no_grad()
    def fit_loss(self) -> float:
        """The loss the steps minimise, on every pixel set at once under the current heads (each set's
        loss, averaged): steadier than the last step's, which saw one set."""
        C, _ = self.colours()
        return float(torch.stack([b.reference_loss(C) for b in self.batches]).mean())

    def _fit_graphed(self, n: int, progress: Optional[Callable[[int, int], None]]) -> tuple[int, Tensor]:
        """Up to ``n`` steps as replays of recorded CUDA graphs, in the eager order: one graph per pixel
        set, or one for all when the sets are chosen on the device (the ``fused`` kind). Recorded at the
        first such fit and replayed by later fits while the tensors they read stay the same (a warm
        :meth:`retarget` writes its targets, alpha and Adam's state in place; anything else drops them).
        Returns (steps done, last loss): where a step cannot be recorded only the first step is done and
        the caller runs the rest eagerly."""
        start = 0
        if self._graphs is None:
            count = 1 if self.batches[0].sets is not None else len(self.batches)
            recording = warm_up_and_record(lambda: self.step(0),
                                           [functools.partial(self.step, b) for b in range(count)],
                                           self.scene.device)
            if recording.graphs is None:
                warnings.warn(f"edit steps run without CUDA graphs: {recording.error}")
                self.cfg.cuda_graphs = False
                return 1, recording.first
            self._graphs, start = GraphedSteps(recording.graphs, recording.results), 1
        return n, self._graphs.replay(start, n, progress)

    def edit(self, timing: Optional[EditTiming] = None) -> Edit:
        """The current heads as an :class:`Edit` (copies)."""
        times = ({"steps": timing.steps, "setup_s": timing.setup_s, "steps_s": timing.steps_s,
                  "loss": timing.final_loss} if timing is not None else {})
        info = new_edit_info(k=self.k, changed_fraction=self.changed_fraction, fit=self.mode, recipe=self.recipe,
                             unchanged_weights=self.cfg.unchanged_weights,
                             start="colour map" if self.colour_map is not None else "unedited layer", **times)
        return Edit(self.weight.detach().clone(), self.bias.detach().clone(), copy.deepcopy(self.seg).eval(),
                    self.source, self.fingerprint, info)

    @torch.no_grad()
    def changed_progress(self) -> Optional[float]:
        """How far the current heads moved the changed pixels of the edit view towards their target:
        ``1 - mean|preview - target| / mean|render - target|`` over them (1: reached, 0: unmoved, below 0:
        moved away). None for a whole-image fit, or where the render already showed their target to within
        ``unchanged_tol`` on average (nothing was asked of them). One read from the GPU, kept until the heads
        or the target change (a pick's refit check and the commands' warning ask for it in turn)."""
        if self._progress is _UNMEASURED:
            self._progress = self._measure_progress()
        return self._progress  # type: ignore[return-value]

    def _measure_progress(self) -> Optional[float]:
        t = self.target
        if t is None or t.changed is None:
            return None
        m = t.changed.to(t.image.dtype)
        before, after = torch.stack([((self.current - t.image).abs() * m).sum(),
                                     ((self.preview()["rgb"] - t.image).abs() * m).sum()]).tolist()
        if not before > self.cfg.unchanged_tol * 3.0 * max(t.count or 0, 1):
            return None
        return 1.0 - after / before

    def small_progress_note(self) -> Optional[str]:
        """A line for the user where the fit left its changed pixels nearly where they were
        (:data:`SMALL_PROGRESS`), else None."""
        p = self.changed_progress()
        if p is None or p >= SMALL_PROGRESS:
            return None
        return (f"the fit moved the changed pixels only {max(p, 0.0):.0%} of the way to their new colour: "
                f"this edit changes almost nothing")

    @torch.no_grad()
    def preview(self) -> dict[str, Tensor]:
        """The edited view under the current heads: ``rgb`` [H,W,3] and ``alpha`` [H,W,1]."""
        C, alpha = self.colours()
        bg = self.scene.background.to(C)
        return {"rgb": composite(C, self.contrib, bg)[0], "alpha": composite(alpha, self.contrib)[0]}


def _check_images(edited: Tensor, original: Optional[Tensor], changed: Optional[Tensor], W: int, H: int) -> None:
    """Refuse an edited image, original or changed mask that does not fit a ``W`` x ``H`` view."""
    if edited.ndim != 3 or edited.shape[-1] != 3:
        raise InputError(f"the edited image must be H x W x 3, got shape {tuple(edited.shape)}")
    if tuple(edited.shape[:2]) != (H, W):
        raise InputError(f"the edited image is {edited.shape[1]}x{edited.shape[0]} but the camera renders "
                         f"{W}x{H}")
    if original is not None and tuple(original.shape) != tuple(edited.shape):
        raise InputError(f"the original image is {tuple(original.shape)}, the edited one {tuple(edited.shape)}")
    if changed is not None and (tuple(changed.shape) != (H, W) or changed.dtype != torch.bool):
        raise ValueError(f"EditEngine: changed must be a bool [{H}, {W}] mask, got {changed.dtype} "
                         f"{tuple(changed.shape)}")


__all__ = ["SMALL_PROGRESS", "VIEW_FIELDS", "EditConfig", "EditEngine", "EditTiming"]
