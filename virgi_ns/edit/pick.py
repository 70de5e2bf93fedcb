"""A click and a colour instead of a painted image: select what was clicked in one view, recolour
it, and fit that as an edit.

The viewer panel's Pick mode and ``virgi-edit pick`` share this module (plain torch, no viewer):

- :func:`view_maps`: the view's render, its diffuse render, the colour field's per-Gaussian
  features composited per pixel, its coverage (accumulation), and the depth and diffuse colour of
  each pixel's median contributor (:func:`median_contributor`), from an
  :class:`~virgi_ns.edit.engine.EditEngine` set up on the view;
- :func:`select`: the selection grown from the clicked pixel over covered pixels (accumulation >=
  :data:`MIN_COVER`) connected to it (or, ``contiguous=False``, every covered pixel of the view that
  passes the same colour tests); with ``depth_edges``, never across a jump in the surface's depth
  (:data:`DEPTH_JUMP`: an object in front of another of its colour). By default
  (``chroma_steps``) a pixel joins when the hue of its diffuse colour (the direction of its
  chromaticity, which shading does not move; the highlight is not in the diffuse render) is within
  ``tolerance`` x 90 degrees of the click's, its chroma and its median contributor's are within a
  factor of the click's (:data:`CHROMA_BAND`: a near-neutral surface's hue is noise), and it is
  reached through neighbours whose chroma changes gradually: an object's pale and deep tones meet
  through blends, another object of the same hue meets it at a step. ``colour_features`` asks both the
  diffuse colour and the colour field's features to point within that angle of the click's (stricter:
  it stops where shading or texture turns the features);
- :func:`recolour`: the edited image: ``hue`` gives the selection the colour's hue and saturation
  and keeps each pixel's value (shading and highlights stay: saturation is scaled so a reference
  pixel gets the colour's, and a white highlight stays near white); ``shift`` does the same but turns
  each pixel's hue by the angle that takes the reference pixel's hue to the colour's, so an object
  of several hues (a gradient, a print, warm and cool shading) keeps them apart instead of taking one;
  ``colour`` makes the colour the
  surface's own: the diffuse render becomes ``colour x value / reference value`` (its shading
  kept, its brightness that of the colour) and each pixel keeps the render's view-dependent part
  over its diffuse colour (a logit offset), so highlights sit on the new colour as they would on a
  surface of it. The reference is the selection's median pixel for :func:`recolour` alone and the
  clicked pixel in a :class:`PickSession` (:data:`DEFAULT_REFERENCE`);
- :class:`PickSession`: one click on one view: every :meth:`~PickSession.update` (a new colour,
  tolerance, contiguity or mode) refits warm from the last fit (:meth:`EditEngine.retarget`), which is what a
  live drag needs; :func:`commit` puts the edit on a stack with its edited image and selection
  saved beside it.

The edit fits the selection as its changed pixels (the rest keeps the render), with the engine's
``joint`` recipe (:data:`PICK_RECIPE`; or ``staged``, whose segmentation is first a classifier of the
Gaussians the selection covers). A joint fit that ends with the changed pixels nearly where they were is
fitted again ``staged``, and the fit that moved them further is kept.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from virgi_ns.edit.engine import SMALL_PROGRESS, EditConfig, EditEngine
from virgi_ns.edit.recolor import hsv_to_rgb, rgb_to_hsv
from virgi_ns.edit.scene import FrozenScene
from virgi_ns.edit.stack import Edit, EditSource, EditStack
from virgi_ns.errors import InputError, atomic_path
from virgi_ns.raster import Cameras, Contributions, composite

MODES = ("hue", "shift", "colour")
MIN_COVER = 0.5
"""A pixel whose accumulation is below this shows mostly background: it is never selected, and a
click there picks nothing."""
_HEX = re.compile(r"#?([0-9a-fA-F]{6})")


# ------------------------------------------------------------------------------ inputs
def parse_colour(text: str) -> tuple[float, float, float]:
    """``'#RRGGBB'`` (or ``RRGGBB``) -> RGB in [0, 1]; anything else is an :class:`InputError`."""
    m = _HEX.fullmatch(str(text).strip())
    if m is None:
        raise InputError(f"cannot read the colour {text!r}: give it as #RRGGBB, e.g. '#d02020'")
    h = m.group(1)
    return tuple(int(h[i : i + 2], 16) / 255.0 for i in (0, 2, 4))  # type: ignore[return-value]


def colour_hex(colour: tuple[float, float, float]) -> str:
    """RGB in [0, 1] -> ``'#rrggbb'`` (the inverse of :func:`parse_colour` to 8 bits)."""
    return "#" + "".join(f"{round(255 * c):02x}" for c in colour)


def check_tolerance(tolerance: float) -> float:
    t = float(tolerance)
    if not 0.0 <= t <= 1.0:
        raise InputError(f"the tolerance must be in [0, 1], got {tolerance}")
    return t


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"the recolour mode must be {', '.join(MODES[:-1])} or {MODES[-1]}, got {mode!r}")
    return mode


PICK_RECIPE = "joint"
"""The recipe of a pick's edit: ``joint``, the engine's default; :func:`pick_config` takes ``staged`` too."""


def pick_config(device: torch.device, recipe: str = PICK_RECIPE) -> EditConfig:
    """The edit settings of a pick: ``recipe`` (default :data:`PICK_RECIPE`); with ``staged`` on a CPU
    its classifier trains on fewer samples and steps (a CPU's budget for an interactive tool)."""
    return staged_config(EditConfig(), device) if recipe == "staged" else EditConfig(recipe=recipe)


def staged_config(cfg: EditConfig, device: torch.device) -> EditConfig:
    """``cfg`` with the ``staged`` recipe; on a CPU its classifier on 8,192 samples for 150 steps."""
    if torch.device(device).type != "cuda":
        return dataclasses.replace(cfg, recipe="staged", seg_samples=8192, seg_steps=150)
    return dataclasses.replace(cfg, recipe="staged")


# ------------------------------------------------------------------------- selection
@dataclass
class ViewMaps:
    """Per-pixel maps of one view [H,W,*]: ``rgb`` (the render through the stack), ``diffuse``
    and ``features`` (the diffuse colour and the colour field's ``h_diff``, divided by coverage),
    ``accumulation`` [H,W], ``depth`` [H,W] and ``surface`` [H,W,3] (the depth and the diffuse colour
    of each pixel's median contributor, :func:`median_contributor`; None: :func:`select` does without
    them). ``features`` is computed by ``features_of()`` when first read: only the ``colour_features``
    criterion reads it."""

    rgb: Tensor
    diffuse: Tensor
    accumulation: Tensor
    depth: Optional[Tensor] = None
    surface: Optional[Tensor] = None
    features_of: Optional[Callable[[], Tensor]] = dataclasses.field(default=None, repr=False)

    @functools.cached_property
    def features(self) -> Tensor:
        if self.features_of is None:
            raise ValueError("these view maps were made without features")
        return self.features_of()


@torch.no_grad()
def median_contributor(contrib: Contributions) -> Tensor:
    """Long [H,W]: each pixel's median contributor in the first view of ``contrib``, as an index of its
    pairs: the first Gaussian (front to back) at which the pixel's accumulated opacity reaches half of
    its coverage; -1 where nothing contributes. Unlike the blended render, which mixes the front and
    the back object over the pixels an edge's splats overlap, it switches from one object to the other
    between two neighbouring pixels: the pixel belongs to the object that covers most of it."""
    _, H, W = contrib.shape
    w = contrib.weight.detach().double()
    pixel = contrib.pixel.long()
    M = int(w.numel())
    out = torch.full((H * W,), -1, dtype=torch.long, device=w.device)
    if M == 0:
        return out.reshape(H, W)
    run = torch.cumsum(w, 0)  # entries are grouped by pixel, front to back
    first = torch.ones(M, dtype=torch.bool, device=w.device)
    first[1:] = pixel[1:] != pixel[:-1]
    starts = torch.nonzero(first).squeeze(1)
    ends = torch.cat([starts[1:], starts.new_tensor([M])]) - 1
    before = run[starts] - w[starts]  # the running sum before each pixel's first entry
    half = torch.zeros(contrib.num_pixels, dtype=torch.float64, device=w.device)
    half[pixel[starts]] = before + 0.5 * (run[ends] - before)
    reached = run >= half[pixel]
    # within a pixel the running sum only grows: its reached entries are its last ones
    median = reached.clone()
    median[1:] &= first[1:] | ~reached[:-1]
    median = torch.nonzero(median).squeeze(1)
    out[pixel[median]] = contrib.pair[median].long()
    return out.reshape(H, W)


def _at_median(values: Tensor, median: Tensor) -> Tensor:
    """``values`` [U,*] of each pixel's median contributor (``median`` [H,W]: pair indices, -1 for none)
    as [H,W,*]; 0 where nothing contributes."""
    picked = values[median.clamp_min(0)]
    none = (median < 0).reshape(*median.shape, *([1] * (values.dim() - 1)))
    return picked.masked_fill(none, 0)


def surface_depth(contrib: Contributions, median: Optional[Tensor] = None) -> Tensor:
    """[H,W] the camera-space depth of each pixel's median contributor (``median``: the
    :func:`median_contributor` of ``contrib``, computed when not given); 0 where nothing contributes.
    It steps at an occlusion edge where the expected depth ramps."""
    median = median_contributor(contrib) if median is None else median
    return _at_median(contrib.pair_depth.float(), median)


@torch.no_grad()
def view_maps(engine: EditEngine) -> ViewMaps:
    """The maps of the engine's view (its contributions, features and colours through the stack)."""
    c = engine.contrib
    acc = c.accumulation()[0].to(engine.current)
    cover = acc[..., None].clamp_min(1e-6)
    colours = torch.sigmoid(engine.c_d)
    diffuse = composite(colours, c)[0] / cover
    median = median_contributor(c)
    surface = _at_median(colours.float(), median)
    dev = engine.current.device
    h_diff = engine.h_diff

    @torch.no_grad()
    def features() -> Tensor:
        return composite(h_diff.float(), c)[0] / cover

    return ViewMaps(engine.current, diffuse, acc, surface_depth(c, median).to(dev), surface.to(dev), features)


def _angle(a: Tensor, b: Tensor) -> Tensor:
    """Degrees between the vectors of ``a`` [...,D] and ``b`` [D]."""
    cos = (torch.nn.functional.normalize(a, dim=-1) * torch.nn.functional.normalize(b, dim=-1)).sum(-1)
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))


def check_pixel(maps: ViewMaps, x: int, y: int) -> None:
    """Refuse a pixel outside the image or on the background (:data:`MIN_COVER`)."""
    H, W = maps.accumulation.shape
    if not (0 <= x < W and 0 <= y < H):
        raise InputError(f"the pixel ({x}, {y}) is outside the {W}x{H} image (x 0..{W - 1}, y 0..{H - 1})")
    cover = float(maps.accumulation[y, x])
    if cover < MIN_COVER:
        raise InputError(f"nothing to pick at ({x}, {y}): the render there is background (coverage {cover:.2f} "
                         f"< {MIN_COVER}); pick a pixel on an object")


CRITERIA = ("colour_features", "chroma_steps")
"""How :func:`select` decides which pixels join (see there)."""
DEFAULT_CRITERION = "chroma_steps"
NEUTRAL_CHROMA = 0.02
"""``chroma_steps``: chromaticity offsets shorter than this have no hue (about 6% HSV saturation, where
one 8-bit step of one channel of a mid grey turns the offset's direction by about 7.5 degrees, under
half the default 18-degree limit)."""
CHROMA_BAND = 15.0
"""``chroma_steps``: a pixel joins only if its chroma, and that of its median contributor's diffuse
colour (``ViewMaps.surface``), are within a factor ``1 + CHROMA_BAND x tolerance`` of the click's,
either way (4 at the default tolerance 0.2). A near-neutral surface (steel, grey plastic) has a hue
that is noise and may fall within a saturated click's hue window by chance, and a saturated object
may fall within a near-neutral click's: their chromas are an order of magnitude apart, where one
object's pale and deep tones stay within a few times of each other. The median contributor's colour
is that of the object covering most of the pixel, so an edge pixel mostly of a neutral neighbour
fails the band even where the blend keeps much of the click's chroma."""
DEPTH_JUMP = 0.1
"""Two neighbouring pixels whose surface depths (:func:`surface_depth`) differ by more than this share
of the nearer one are not connected: an occlusion edge, where the selection stops whatever the
colours. Within one surface a pixel's depth moves by its footprint times the surface's slope, a
small share of the depth at any incline short of grazing."""


def check_criterion(criterion: str) -> str:
    if criterion not in CRITERIA:
        raise InputError(f"the selection criterion must be {' or '.join(CRITERIA)}, got {criterion!r}")
    return criterion


def chromaticity(rgb: Tensor) -> Tensor:
    """[...,3] -> the rgb chromaticity's offset from grey: its direction is the hue, its length the
    chroma, and shading (a scaling of the colour) moves neither."""
    return rgb / rgb.sum(-1, keepdim=True).clamp_min(1e-6) - 1.0 / 3.0


@torch.no_grad()
def select(maps: ViewMaps, x: int, y: int, tolerance: float, criterion: str = DEFAULT_CRITERION,
           contiguous: bool = True, depth_edges: bool = False) -> Tensor:
    """Bool [H,W]: the selection grown from pixel (x, y) over covered pixels, 8-connected to it
    (``contiguous=False``: every covered pixel of the view that passes the criterion's colour tests,
    connected or not, as a magic wand's "contiguous" box unticked: leaves all over a plant).
    ``depth_edges``: contiguous growth does not cross a depth edge either: neighbours whose surface
    depths (``maps.depth``) differ by more than :data:`DEPTH_JUMP` of the nearer one are not
    connected. It tells apart an object in front of another of its colour; off by default, because
    on a textured or noisily reconstructed surface the surface depth jumps between neighbours and
    the selection stops short of the surface.
    ``colour_features``: a pixel joins when its diffuse colour and its features both point within
    ``tolerance`` x 90 degrees of the clicked pixel's (see the module docstring). ``chroma_steps``:
    when its diffuse chromaticity's hue is within that angle of the click's, its chroma is at least
    :data:`NEUTRAL_CHROMA` and, with its median contributor's (``maps.surface``), within a factor
    ``1 + CHROMA_BAND x tolerance`` of the click's, and it is reached from the click through
    neighbours whose chromas differ by at most a factor ``1 + 4 tolerance`` step by step (an object's
    pale and deep tones meet through gradual blends, another object of its hue meets it at an abrupt
    step); a click on a neutral colour falls back to ``colour_features``."""
    check_pixel(maps, x, y)
    tolerance = check_tolerance(tolerance)
    if check_criterion(criterion) == "chroma_steps":
        chosen = _select_chroma_steps(maps, x, y, tolerance, contiguous, depth_edges)
        if chosen is not None:
            return chosen
    limit = 90.0 * tolerance
    allowed = ((maps.accumulation >= MIN_COVER)
               & (_angle(maps.diffuse, maps.diffuse[y, x]) <= limit)
               & (_angle(maps.features, maps.features[y, x]) <= limit))
    allowed[y, x] = True
    return connected_to(allowed, x, y, depth=maps.depth if depth_edges else None) if contiguous else allowed


def _select_chroma_steps(maps: ViewMaps, x: int, y: int, tolerance: float, contiguous: bool = True,
                         depth_edges: bool = False) -> Optional[Tensor]:
    """``select``'s ``chroma_steps`` criterion; None for a neutral click. Not ``contiguous``: the
    pixels of the click's hue with a chroma, wherever they are (no chroma steps: they join no path)."""
    ch = chromaticity(maps.diffuse)
    chroma = ch.norm(dim=-1)
    at = float(chroma[y, x])
    if at < NEUTRAL_CHROMA:
        return None
    band = 1.0 + CHROMA_BAND * tolerance
    allowed = ((maps.accumulation >= MIN_COVER) & (_angle(ch, ch[y, x]) <= 90.0 * tolerance)
               & _in_band(chroma, at, band))
    if maps.surface is not None:  # and the colour of the object that covers most of the pixel
        allowed &= _in_band(chromaticity(maps.surface).norm(dim=-1), at, band)
    allowed[y, x] = True
    if not contiguous:
        return allowed
    log_chroma = torch.log(chroma.clamp_min(1e-6))
    return connected_to(allowed, x, y, log_chroma, math.log(1.0 + 4.0 * tolerance), maps.depth if depth_edges else None)


def _in_band(chroma: Tensor, at: float, band: float) -> Tensor:
    """Chromas with a hue (:data:`NEUTRAL_CHROMA`) within a factor ``band`` of ``at``, either way."""
    return (chroma >= max(NEUTRAL_CHROMA, at / band)) & (chroma <= at * band)


def connected_to(allowed: Tensor, x: int, y: int, value: Optional[Tensor] = None, step: float = 0.0,
                 depth: Optional[Tensor] = None, jump: float = DEPTH_JUMP) -> Tensor:
    """Bool [H,W]: the pixels of ``allowed`` [H,W] 8-connected to pixel (x, y) through ``allowed``
    ones (empty when (x, y) is not allowed); with ``value`` [H,W], only through neighbours whose values
    differ by at most ``step``; with ``depth`` [H,W], only through neighbours whose depths differ by
    at most ``jump`` times the nearer one. Labelled on the host by scipy in one pass, where a flood
    fill on the GPU takes a dilation per pixel of the object's extent and a sync every few."""
    ok = allowed.cpu().numpy()
    if not ok[y, x]:
        return torch.zeros_like(allowed, dtype=torch.bool)
    from scipy import ndimage

    labels, _ = ndimage.label(ok, structure=np.ones((3, 3), dtype=bool))
    component = labels == labels[y, x]
    if value is None and depth is None:
        return torch.from_numpy(component).to(allowed.device)
    # a link test only removes links: the answer lies within the plain component, so the graph is
    # built over that component's bounding box alone
    rows, cols = np.flatnonzero(component.any(1)), np.flatnonzero(component.any(0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    inner = _linked_component(component[box], y - rows[0], x - cols[0],
                              None if value is None else value.detach().cpu().double().numpy()[box], step,
                              None if depth is None else depth.detach().cpu().float().numpy()[box], jump)
    out = np.zeros_like(ok)
    out[box] = inner
    return torch.from_numpy(out).to(allowed.device)


def _linked_component(ok: np.ndarray, y: int, x: int, v: Optional[np.ndarray], step: float, z: Optional[np.ndarray],
                      jump: float) -> np.ndarray:
    """:func:`connected_to`'s component of (x, y) in ``ok`` through the links its value and depth tests keep."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    H, W = ok.shape
    index = np.arange(H * W).reshape(H, W)
    src, dst = [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # each neighbour pair once
        a = (slice(0, H - dy), slice(max(0, -dx), W - max(0, dx)))
        b = (slice(dy, H), slice(max(0, dx), W + min(0, dx)))
        link = ok[a] & ok[b]
        if v is not None:
            link &= np.abs(v[a] - v[b]) <= step
        if z is not None:
            link &= np.abs(z[a] - z[b]) <= jump * np.minimum(z[a], z[b])
        src.append(index[a][link])
        dst.append(index[b][link])
    i, j = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(H * W, H * W))
    _, labels = connected_components(graph, directed=False)
    return (labels == labels[y * W + x]).reshape(H, W)


def _typical(values: Tensor, mask: Tensor) -> float:
    """The median of ``values`` over ``mask`` (the mean of the middle two for an even count)."""
    return float(torch.quantile(values[mask].float(), 0.5))


def _typical_hue(hsv: Tensor, mask: Tensor) -> float:
    """The selection's typical hue in degrees: the direction of its pixels' hues weighed by their
    saturation (a circular mean: reds on both sides of 0 degrees average to red, and grey pixels,
    whose hue means nothing, weigh nothing)."""
    h, s = hsv[..., 0][mask].double(), hsv[..., 1][mask].double()
    rad = torch.deg2rad(h)
    return float(torch.rad2deg(torch.atan2((s * torch.sin(rad)).sum(), (s * torch.cos(rad)).sum())) % 360.0)


def _logit(x: Tensor) -> Tensor:
    x = x.clamp(1.0 / 255.0, 254.0 / 255.0)
    return torch.log(x) - torch.log1p(-x)


REFERENCES = ("median", "click")
"""Which pixel :func:`recolour` gives the chosen colour's saturation (hue) or value (colour): the
selection's median one, or the clicked one (the others keep their ratio to it)."""
DEFAULT_REFERENCE = "click"
"""The clicked pixel takes the chosen colour: the pixel the user pointed at shows the colour they chose (with
the median as reference, a selection of pale and deep tones gets the colour's saturation on its median
tone, and its deep tones more than the colour has)."""


HIGHLIGHT_SATURATION_SHARE = 0.5
"""A pixel whose render keeps less than this share of its diffuse colour's saturation is mostly
highlight: in ``hue`` and ``shift`` mode a click there takes its reference saturation (and hue) from the
selection instead (scaling the selection by a highlight's near-zero saturation would saturate it all)."""


GREY_SATURATION = 0.05
"""Saturation under which a pixel is taken for grey: its hue means nothing (``shift`` then turns the
selection from its typical hue), and a reference saturation is never taken below it."""


def _on_highlight(hsv: Tensor, diffuse: Tensor, at: tuple[int, int]) -> bool:
    """Whether the render's pixel ``at`` (x, y) is mostly highlight (:data:`HIGHLIGHT_SATURATION_SHARE`)."""
    x, y = at
    surface = float(rgb_to_hsv(diffuse[y, x].clamp(0.0, 1.0))[1])
    return float(hsv[y, x, 1]) < HIGHLIGHT_SATURATION_SHARE * surface


@torch.no_grad()
def recolour(rgb: Tensor, mask: Tensor, colour: tuple[float, float, float], mode: str,
             diffuse: Optional[Tensor] = None, at: Optional[tuple[int, int]] = None) -> Tensor:
    """The edited image: ``rgb`` [H,W,3] with the ``mask`` pixels recoloured towards ``colour`` by
    ``mode`` (see the module docstring); other pixels unchanged. ``diffuse`` [H,W,3]: the view's
    diffuse render, which ``colour`` shades and puts the render's view-dependent part back on
    (without it, ``colour`` shades ``rgb`` and adds nothing). ``at`` (x, y): the pixel whose saturation
    (hue) or value (colour) becomes the colour's, the others scaled alike (``shift``: its hue too, the
    others turned by the same angle); default the selection's typical pixel (the median saturation or
    value, the saturation-weighted mean hue), which also stands in for an ``at`` on a highlight."""
    check_mode(mode)
    target = torch.tensor(colour, dtype=rgb.dtype, device=rgb.device)
    ref = (lambda v: _typical(v, mask)) if at is None else (lambda v: float(v[at[1], at[0]]))  # noqa: E731
    if mode in ("hue", "shift"):
        hsv = rgb_to_hsv(rgb.clamp(0.0, 1.0))
        t_hsv = rgb_to_hsv(target)
        typical = at is None or (diffuse is not None and _on_highlight(hsv, diffuse, at))
        if typical:
            ref = lambda v: _typical(v, mask)  # noqa: E731  (a highlight's saturation is not the surface's)
        sat = (hsv[..., 1] * float(t_hsv[1]) / max(ref(hsv[..., 1]), GREY_SATURATION)).clamp(0.0, 1.0)
        if mode == "hue":
            hue = torch.full_like(sat, float(t_hsv[0]))
        else:  # a near-grey click's hue is noise: the selection's typical hue stands in for it
            by_click = not typical and float(hsv[at[1], at[0], 1]) >= GREY_SATURATION
            turn = float(t_hsv[0]) - (float(hsv[at[1], at[0], 0]) if by_click else _typical_hue(hsv, mask))
            hue = torch.remainder(hsv[..., 0] + turn, 360.0)
        new = hsv_to_rgb(torch.stack([hue, sat, hsv[..., 2]], -1))
    else:
        base = (rgb if diffuse is None else diffuse).clamp(0.0, 1.0)
        value = base.amax(-1, keepdim=True)
        new = (target * (value / max(ref(value[..., 0]), 1e-3))).clamp(0.0, 1.0)
        if diffuse is not None:
            new = torch.sigmoid(_logit(new) + _logit(rgb) - _logit(base))
    return torch.where(mask[..., None], new, rgb)


# ---------------------------------------------------------------------------- session
class PickSession:
    """One click at pixel (x, y) of ``camera`` (one view): the view is set up once; each
    :meth:`update` selects, recolours and fits again, warm from the last fit."""

    def __init__(self, scene: FrozenScene, camera: Cameras, x: int, y: int, stack: Optional[EditStack] = None,
                 cfg: Optional[EditConfig] = None, source: Optional[EditSource] = None,
                 criterion: str = DEFAULT_CRITERION, reference: str = DEFAULT_REFERENCE) -> None:
        W, H = int(camera.widths[0]), int(camera.heights[0])
        if not (0 <= x < W and 0 <= y < H):  # before the view is rasterized
            raise InputError(f"the pixel ({x}, {y}) is outside the {W}x{H} image (x 0..{W - 1}, y 0..{H - 1})")
        self.x, self.y = int(x), int(y)
        self.criterion = check_criterion(criterion)  # how select() grows the selection
        if reference not in REFERENCES:
            raise InputError(f"the recolour reference must be {' or '.join(REFERENCES)}, got {reference!r}")
        self.reference = reference  # which pixel recolour() gives the colour's saturation or value
        self.engine = EditEngine(scene, camera, None, stack, cfg or pick_config(scene.device), source)
        self.maps = view_maps(self.engine)
        check_pixel(self.maps, self.x, self.y)
        self.mask: Optional[Tensor] = None
        self._selection: Optional[tuple[tuple[float, bool, bool], Tensor]] = None  # ((tolerance, contiguous,
        # depth_edges), its selection)
        self.edited: Optional[Tensor] = None
        self.settings: dict = {}
        self.steps_done = 0

    def update(self, colour: tuple[float, float, float], tolerance: float, mode: str, steps: Optional[int] = None,
               seg_steps: Optional[int] = None, timer: Optional[Callable[[str], None]] = None,
               contiguous: bool = True, depth_edges: bool = False) -> Edit:
        """Select with ``tolerance`` (``contiguous``: only what is connected to the click; ``depth_edges``:
        and not across a jump in depth, :func:`select`),
        recolour towards ``colour`` by ``mode`` and fit ``steps``
        (default: the config's) from the last fit; ``seg_steps``: the staged segmentation's steps
        when the selection changed (default: the config's). Returns the edit. ``timer(part)``, if
        given, is called as each part ends (``select``, ``recolour``, ``retarget``, ``steps``): a
        benchmark's breakdown."""
        tick = timer or (lambda part: None)
        tolerance, mode = check_tolerance(tolerance), check_mode(mode)
        # a drag of the colour keeps the selection (it depends on the click and the selection settings only)
        key = (tolerance, bool(contiguous), bool(depth_edges))
        if self._selection is None or self._selection[0] != key:
            self._selection = (key, select(self.maps, self.x, self.y, tolerance, self.criterion, bool(contiguous),
                                           bool(depth_edges)))
        mask = self._selection[1]
        tick("select")
        edited = recolour(self.maps.rgb, mask, colour, mode, self.maps.diffuse,
                          (self.x, self.y) if self.reference == "click" else None)
        tick("recolour")
        self.engine.retarget(edited, mask, seg_steps=seg_steps)
        tick("retarget")
        self.mask, self.edited, self.steps_done = mask, edited, 0
        self.settings = {"pixel": [self.x, self.y], "colour": colour_hex(colour),
                         "tolerance": tolerance, "contiguous": bool(contiguous), "depth_edges": bool(depth_edges),
                         "mode": mode, "criterion": self.criterion,
                         "reference": self.reference,
                         "selected": float(mask.float().mean())}
        edit = self.refine(self.engine.cfg.steps if steps is None else steps)
        tick("steps")
        return edit

    @property
    def steps_left(self) -> int:
        """Steps of the config's count the current fit has yet to run (the top-up after a live update)."""
        return max(0, self.engine.cfg.steps - self.steps_done)

    def refine(self, steps: int) -> Edit:
        """``steps`` more steps of the current fit; returns the edit. Where they complete a ``joint`` fit
        of at least the default steps that left the changed pixels nearly where they were, the selection
        is fitted again ``staged`` (:meth:`_restage_if_collapsed`); a fit shortened on purpose is partial,
        not stalled."""
        edit, _ = self.engine.fit(max(0, int(steps)))
        self.steps_done += max(0, int(steps))
        full = self.engine.cfg.steps >= EditConfig.steps
        if full and self.steps_done >= self.engine.cfg.steps and self.engine.recipe == "joint":
            edit = self._restage_if_collapsed(edit)
        edit.info["pick"] = dict(self.settings)
        return edit

    def _restage_if_collapsed(self, edit: Edit) -> Edit:
        """``edit``, or where its fit moved the changed pixels less than :data:`SMALL_PROGRESS` of the way
        (the joint segmentation stalled at alpha near 0), the same selection fitted from a fresh start on the
        same view (shared, not rasterized again) with the ``staged`` recipe, whose segmentation is a
        classifier of the selected Gaussians and cannot stall: whichever moved them further, the session
        going on with its engine. The staged edit's ``info`` keeps both figures (``restaged``)."""
        joint = self.engine.changed_progress()
        if joint is None or joint >= SMALL_PROGRESS:
            return edit
        old = self.engine
        staged = EditEngine(old.scene, old.camera, None, old.stack, staged_config(old.cfg, old.scene.device),
                            old.source, view_of=old)
        staged.retarget(self.edited, self.mask)
        staged_edit, _ = staged.fit()
        progress = staged.changed_progress()
        if progress is None or progress <= joint:
            return edit
        self.engine = staged
        staged_edit.info["restaged"] = {"joint_progress": joint, "staged_progress": progress}
        return staged_edit


def _png(path: Path, image: np.ndarray) -> None:
    """Write a PNG with zlib's fastest level: a commit waits for its pictures, and the default level
    takes about three times as long for files a few percent smaller."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", compress_level=1)


def commit(stack: EditStack, session: PickSession, edit: Edit, replace: Optional[int] = None) -> int:
    """Add ``edit`` to ``stack`` (or put it in the place of edit ``replace``) with the session's
    edited image and selection saved beside it as ``edit_NNNN_edited.png`` and
    ``edit_NNNN_selection.png`` (a stack without a directory saves none); returns its number."""
    if session.edited is None or session.mask is None:
        raise InputError("nothing picked yet: update the pick first")
    stem = Path(stack.next_file()).stem
    pictures: list[Path] = []
    try:
        if stack.directory is not None:
            pictures = [stack.directory / f"{stem}_edited.png", stack.directory / f"{stem}_selection.png"]
            # 8-bit where the images are (a quarter of the bytes to copy), both encoded at once (zlib
            # releases the interpreter): a release waits for these files
            images = [(session.edited.detach().float().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy(),
                      session.mask.to(torch.uint8).mul(255).cpu().numpy()]
            with ThreadPoolExecutor(2) as pool:
                for done in [pool.submit(_png, path, image) for path, image in zip(pictures, images)]:
                    done.result()
            edit = dataclasses.replace(edit, source=dataclasses.replace(edit.source, image=str(pictures[0])))
        if replace is None:
            return stack.add(edit)
        stack.replace(replace, edit)
        return replace
    except BaseException:
        for p in pictures:
            p.unlink(missing_ok=True)
        raise


__all__ = ["CHROMA_BAND", "CRITERIA", "DEFAULT_CRITERION", "DEFAULT_REFERENCE", "DEPTH_JUMP", "MIN_COVER", "MODES",
           "NEUTRAL_CHROMA", "PICK_RECIPE", "REFERENCES", "PickSession", "ViewMaps", "check_criterion", "check_mode",
           "check_pixel", "check_tolerance", "chromaticity", "colour_hex", "commit", "connected_to",
           "median_contributor", "parse_colour", "pick_config", "recolour", "select", "staged_config", "surface_depth", "view_maps"]
