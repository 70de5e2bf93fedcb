"""What a whole-view render keeps between frames, and the per-frame work that is left.

With frozen geometry and a trained field, a view changes only the view direction of each Gaussian.
So :class:`RenderCache` keeps, each level rebuilt when what it was computed from changes:

- **geometry** (:class:`GeometryCache`): gsplat's inputs of the frozen Gaussians (exponentiated
  scales, sigmoid opacities);
- **gate** (:class:`GateCache`): for each Gaussian the specular gate keeps, its mean and the
  direction-independent parts of MLP_spec's three pre-activations
  (:meth:`~virgi_ns.colour.field.DecoupledColourField.specular_parts`), and MLP_spec's per-view
  weights with the SH direction encoding folded into a weight on direction monomials;
- **edits** (:class:`EditCache`): every Gaussian's edited diffuse colour ``sigmoid(c_d'')``
  (through the edit stack and the live edit), and for gated Gaussians ``c_d'' + k p3`` and
  ``k B3``, so that the last layer lands on the final logit.

A view then costs, for the gated Gaussians only: directions, their monomials, three small matrix
products and a sigmoid, written over the cached diffuse colours (:func:`gated_colours`); nothing at
all when the gate keeps no Gaussian or ``k = 0``. On a GPU these dozen small kernels are recorded
once per cache state as a CUDA graph (:class:`ColourGraph`, kept on the edit level, so that every
rebuild of a level records anew) and replayed per view with the camera centre as its input.

Validity is checked per frame by cheap keys: each tensor's identity, in-place version counter,
storage and dtype (:func:`stamp`; optimizer steps and ``load_state_dict`` bump the version), the
edit stack's identity and :attr:`~virgi_ns.edit.stack.EditStack.revision`, a counter of live
edits, and the gate threshold. The field's parameters are not walked per frame: a
:class:`ModuleWatch` keeps them and checks that the field's structure is unchanged (no parameter,
buffer or submodule set, added or removed), and the key takes their version counters and storages.
Writes through ``.data`` bypass the version counter: call :meth:`RenderCache.clear` after those.
"""

from __future__ import annotations

import struct
import warnings
from collections.abc import MutableMapping
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, Optional

import torch
from torch import Tensor

from virgi_ns.colour.field import direction_monomials, monomial_degree, sh_monomial_matrix, view_directions

CHUNK = 1 << 18
"""Gaussians per chunk when a cache is filled (bounds the hash encoding's working memory)."""


def stamp(t: Optional[Tensor]) -> tuple:
    """What changes whenever a tensor's values may have: identity, in-place version, storage, dtype.
    (Callers keep the tensor alive, so its identity cannot pass to another.)"""
    if t is None:
        return (None,)
    return (id(t), t._version, t.data_ptr(), t.dtype)


class ModuleWatch:
    """A module's parameters and buffers, kept so that a frame need not walk the module for them:
    :meth:`current` checks (with dictionary look-ups, no walk) that the module still holds exactly
    them and the same submodules; :meth:`versions` and :meth:`storages` give what changes with their
    values (see :func:`stamp`). ``params`` are in ``module.parameters()``'s order."""

    def __init__(self, module: torch.nn.Module) -> None:
        mods = list(module.modules())
        self.module = module
        self._dicts = tuple(d for m in mods for d in (m._parameters, m._buffers, m._modules))
        self._sizes = tuple(map(len, self._dicts))
        self._entries = tuple((d, k, v) for d in self._dicts for k, v in d.items())
        self.params = tuple(dict.fromkeys(p for m in mods for p in m._parameters.values() if p is not None))
        self.ids = tuple(map(id, self.params))
        buffers = dict.fromkeys(b for m in mods for b in m._buffers.values() if b is not None)  # (by identity)
        self.tensors = self.params + tuple(b for b in buffers if id(b) not in self.ids)
        self._n = len(self.params)

    def current(self, module: torch.nn.Module) -> bool:
        """Whether ``module`` is the watched module with the same parameters, buffers and submodules."""
        if module is not self.module or tuple(map(len, self._dicts)) != self._sizes:
            return False
        for d, k, v in self._entries:
            if d.get(k) is not v:
                return False
        return True

    def versions(self) -> tuple:
        """In-place version counters: the parameters' (in order), then the buffers'."""
        return tuple([t._version for t in self.tensors])

    def param_stamp(self, versions: tuple) -> tuple:
        """(identities, versions) of the parameters, as :meth:`RenderPath._field_stamp` gives them."""
        return self.ids, versions[: self._n]

    def storages(self) -> tuple:
        return tuple([t.data_ptr() for t in self.tensors])


# ------------------------------------------------------------------------------ a view
_CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "width", "height")
_WORD_CODES = {torch.float32: "f", torch.float64: "d", torch.int32: "i", torch.int64: "q"}
"""struct codes of the dtypes whose bytes :func:`_camera_numbers` moves as 32-bit words."""
_CAMERA_FORMATS: Dict[tuple, str] = {}
"""struct formats of single cameras by their fields' (dtype, shape, contiguity)."""


@dataclass
class View:
    """One pinhole view in gsplat's form: ``viewmat`` [1,4,4] (world-to-camera, OpenCV axes) and
    ``K`` [1,3,3] in float32 on the model's device, the camera centre [1,3], and the image size."""

    viewmat: Tensor
    K: Tensor
    centre: Tensor
    width: int
    height: int


def _camera_numbers(camera) -> list:
    """The first camera's 12 camera-to-world entries, fx, fy, cx, cy, width and height as Python numbers,
    gathered where they lie with one launch (each tensor's bytes taken as 32-bit words, so that float
    and integer fields share one ``cat``) and one copy to the host; decoded there."""
    fields = [camera.camera_to_worlds] + [getattr(camera, k) for k in _CAMERA_FIELDS]
    key = tuple((t.dtype, t.shape, t.is_contiguous()) for t in fields)
    fmt = _CAMERA_FORMATS.get(key)
    if fmt is not None:  # one camera of nerfstudio's shapes: the words are views
        words = [fields[0].view(1, 12).view(torch.int32)] + [t.view(torch.int32) for t in fields[1:]]
    else:
        words, fmt = [], "<"
        for i, t in enumerate(fields):
            n = 12 if i == 0 else 1
            code = _WORD_CODES.get(t.dtype)
            if code is None:  # an unusual dtype: as float64
                t, code = t.double(), "d"
            words.append(t.reshape(-1)[:n].reshape(1, n).contiguous().view(torch.int32))
            fmt += f"{n}{code}"
        if fields[0].shape == (1, 3, 4) and all(t.shape == (1, 1) for t in fields[1:]) and key[0][2]:
            _CAMERA_FORMATS[key] = fmt
    raw = torch.cat(words, dim=1).tolist()[0]
    return list(struct.unpack(fmt, struct.pack(f"<{len(raw)}i", *raw)))


def view_of(camera, device: torch.device, dtype: torch.dtype) -> View:
    """The first camera of a nerfstudio ``Cameras`` as a :class:`View`. Per frame: one gather of the
    camera's 18 numbers and one copy to the host (:func:`_camera_numbers`; the image size must be
    known there), the 4x4 algebra in float64 on Python floats, and one copy of the 28 results to
    ``device`` (on a GPU from pinned memory, without a sync)."""
    h = _camera_numbers(camera)
    # camera-to-world (OpenGL axes) -> world-to-camera (OpenCV axes): R' = R diag(1,-1,-1), viewmat = [R'^T, -R'^T t]
    a0, a1, a2 = h[0], h[4], h[8]
    b0, b1, b2 = -h[1], -h[5], -h[9]
    c0, c1, c2 = -h[2], -h[6], -h[10]
    tx, ty, tz = h[3], h[7], h[11]
    fx, fy, cx, cy, w, hh = h[12:18]
    vals = [a0, a1, a2, -(a0 * tx + a1 * ty + a2 * tz),
            b0, b1, b2, -(b0 * tx + b1 * ty + b2 * tz),
            c0, c1, c2, -(c0 * tx + c1 * ty + c2 * tz),
            0.0, 0.0, 0.0, 1.0,
            fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0,
            tx, ty, tz]
    if torch.device(device).type == "cuda":
        packed = torch.tensor(vals, dtype=torch.float32, pin_memory=True).to(device, non_blocking=True)
    else:
        packed = torch.tensor(vals, dtype=torch.float32, device=device)
    centre = packed.as_strided((1, 3), (3, 1), 25)  # (one call per view where slicing and viewing take two)
    return View(packed.as_strided((1, 4, 4), (16, 4, 1), 0), packed.as_strided((1, 3, 3), (9, 3, 1), 16),
                centre if dtype == torch.float32 else centre.to(dtype), int(round(w)), int(round(hh)))


@dataclass
class ViewColours:
    """One colour per Gaussian for one view: ``rgb`` [N,3]; ``diffuse`` [N,3] (None: equal to
    ``rgb``, no Gaussian has a specular term); ``segmentation`` a function giving [N,1] (None:
    no edits)."""

    rgb: Tensor
    diffuse: Optional[Tensor]
    segmentation: Optional[Callable[[], Tensor]]


# ---------------------------------------------------------------------------- the caches
@dataclass(eq=False)
class BackgroundCache:
    """A render's background: ``key`` (its stamp and device), the ``source`` tensor, its copy ``on_device``,
    and, once asked for, the [1,3] float32 ``row`` gsplat takes and ``row_with_depth`` ([1,4], a zero for an
    expected-depth channel)."""

    key: tuple
    source: Tensor
    on_device: Tensor
    row: Optional[Tensor] = None
    row_with_depth: Optional[Tensor] = None


@dataclass(eq=False)
class GeometryCache:
    key: tuple
    refs: tuple
    means: Tensor
    quats: Tensor
    scales: Tensor
    """exp(log-scales) [N,3]"""
    opacities: Tensor
    """sigmoid(logit-opacities) [N]"""


@dataclass(eq=False)
class GateCache:
    key: tuple
    refs: tuple
    index: Tensor
    """[M] the gated Gaussians, ascending."""
    means: Tensor
    """[M,3] their means."""
    p1: Tensor
    """[M,H] ``B1``'s feature part plus bias."""
    p2: Tensor
    """[M,H] (or [1,H] without residual links) ``B2``'s link part plus bias."""
    p3: Tensor
    """[M,3] (or [1,3]) ``B3``'s link part plus bias."""
    w_mono: Tensor
    """[4^q,H] direction monomials -> ``B1``'s direction part (the SH encoding folded in)."""
    w_s1: Tensor
    """[H,H] ``B2``'s columns on ``s1``, transposed."""
    w_s2: Tensor
    """[H,3] ``B3``'s columns on ``s2``, transposed."""
    degree: int

    @property
    def size(self) -> int:
        return int(self.index.shape[0])


@dataclass(eq=False)
class EditCache:
    key: tuple
    refs: tuple
    gate: Optional[GateCache]
    diffuse: Tensor
    """[N,3] ``sigmoid(c_d'')`` of every Gaussian: the colour of every Gaussian without a
    specular term."""
    p3k: Optional[Tensor]
    """[M,3] ``c_d'' + k p3`` of the gated Gaussians (None: nothing specular to draw)."""
    w_s2k: Optional[Tensor]
    """[H,3] ``k B3`` on ``s2``."""
    segmentation: Dict[Optional[int], Tensor] = field(default_factory=dict)
    """Per-Gaussian alpha [N,1] by the shown edit (filled on first request)."""
    frames: int = 0
    """Views served eagerly from this state (see :data:`GRAPH_AFTER_FRAMES`)."""
    graph: Optional["ColourGraph"] = None
    """The state's colours as a CUDA graph, once recorded."""

    @property
    def matte(self) -> bool:
        return self.p3k is None


def colours_of_gated(gate: GateCache, edits: EditCache, centre: Tensor) -> Tensor:
    """[M,3] ``sigmoid(c_d'' + k c_s)`` of the gated Gaussians for a view from ``centre`` [1,3]."""
    d = view_directions(gate.means, centre)
    mono = direction_monomials(d, gate.degree)
    s1 = torch.addmm(gate.p1.to(mono.dtype), mono, gate.w_mono).relu_()
    s2 = torch.addmm(gate.p2.to(mono.dtype), s1, gate.w_s1).relu_()
    return torch.addmm(edits.p3k, s2, edits.w_s2k).sigmoid_()


def gated_colours(gate: GateCache, edits: EditCache, centre: Tensor) -> Tensor:
    """[N,3] colours for a view from camera centre ``centre`` [1,3]: the cached diffuse colours with
    the gated Gaussians' ``sigmoid(c_d'' + k c_s)`` written over them (the specification that
    :class:`ColourGraph` replays)."""
    return edits.diffuse.index_copy(0, gate.index, colours_of_gated(gate, edits, centre))


class ColourGraph:
    """:func:`gated_colours` of one cache state recorded as a CUDA graph. Its inputs are the cache's
    tensors (fixed while the state lasts: the graph lives on the :class:`EditCache` it reads) and a
    static camera centre; its output is a static [N,3] buffer that holds the diffuse colours from the
    start, so a replay writes the gated rows only. A replay overwrites the previous one's colours."""

    def __init__(self, gate: GateCache, edits: EditCache, centre: Tensor) -> None:
        self.centre = centre.detach().to(gate.means.dtype).clone()
        self.out = edits.diffuse.clone()
        self.graph = torch.cuda.CUDAGraph()
        current = torch.cuda.current_stream(centre.device)
        side = torch.cuda.Stream(centre.device)
        side.wait_stream(current)
        with torch.cuda.stream(side):  # once eagerly: the libraries' handles and workspaces
            self._write(gate, edits)
        current.wait_stream(side)
        with torch.cuda.graph(self.graph, capture_error_mode="thread_local"):
            self._write(gate, edits)

    def _write(self, gate: GateCache, edits: EditCache) -> None:
        self.out.index_copy_(0, gate.index, colours_of_gated(gate, edits, self.centre))

    def __call__(self, centre: Tensor) -> Tensor:
        self.centre.copy_(centre)
        self.graph.replay()
        return self.out


def _recordable(centre: Tensor) -> bool:
    """Whether colours for ``centre`` can be recorded as a CUDA graph (on a GPU, outside another capture)."""
    return centre.is_cuda and not torch.cuda.is_current_stream_capturing()


GRAPH_AFTER_FRAMES = 1
"""Frames a cache state is served eagerly before its colours are recorded as a graph: a state that
lasts one frame (a pick's colour being dragged) never pays for a recording."""


class RenderCache:
    """The three levels (see the module docstring); :meth:`clear` forgets them all."""

    def __init__(self) -> None:
        self.geometry_level: Optional[GeometryCache] = None
        self.gate_level: Optional[GateCache] = None
        self.edit_level: Optional[EditCache] = None
        self._background: Optional[BackgroundCache] = None
        self._watch: Optional[ModuleWatch] = None
        self.graph_failed = False
        """A recording failed once: colours are computed eagerly from then on."""

    def clear(self) -> None:
        self.geometry_level = self.gate_level = self.edit_level = None
        self._background = None
        self._watch = None

    def watch(self, module: torch.nn.Module) -> ModuleWatch:
        """The :class:`ModuleWatch` of ``module`` (the model's field), made again when the module or its
        structure changed."""
        w = self._watch
        if w is None or not w.current(module):
            w = self._watch = ModuleWatch(module)
        return w

    def levels(self, model) -> Optional[tuple]:
        """(gate level, edit level) for the model's field, gate and edits, each rebuilt if stale; None
        when the gate is not current (the field changed since it was measured: the caller takes the
        full colour model). The caller has checked that the field is decoupled."""
        w = self.watch(model.field)
        versions = w.versions()
        means = _gaussian_params(model)["means"]
        if not model.gate_current(w.param_stamp(versions), int(means.shape[0])):
            return None
        gate = self.gate(model, w, versions, means)
        return gate, self.edits(model, gate)

    def nbytes(self) -> Dict[str, int]:
        """Bytes held per level (what the cache adds to the model's own tensors)."""
        def size(*ts):
            return sum(t.numel() * t.element_size() for t in ts if t is not None)

        g, f, e = self.geometry_level, self.gate_level, self.edit_level
        return {"geometry": size(g.scales, g.opacities) if g else 0,
                "gate": size(f.index, f.means, f.p1, f.p2, f.p3, f.w_mono, f.w_s1, f.w_s2) if f else 0,
                "edits": size(e.diffuse, e.p3k, e.w_s2k, *e.segmentation.values(),
                              *((e.graph.out, e.graph.centre) if e.graph is not None else ())) if e else 0}

    # ---------------------------------------------------------------- colours
    def colours(self, gate: GateCache, edits: EditCache, centre: Tensor, graphs: bool = True,
                transient: bool = False) -> Tensor:
        """[N,3] colours of a view from ``centre`` [1,3] (:func:`gated_colours`; the cached tensor
        itself for a matte state). On a GPU with ``graphs``, a state served eagerly
        :data:`GRAPH_AFTER_FRAMES` times is then recorded as a :class:`ColourGraph` and replayed; its output
        is returned as it is with ``transient`` (the caller composites it before the next view's
        colours), else a copy. Where recording fails, a warning, and eager colours from then on."""
        if edits.matte:
            return edits.diffuse
        g = edits.graph
        record = g is None and graphs and edits.frames >= GRAPH_AFTER_FRAMES and not self.graph_failed
        if record and _recordable(centre):
            try:
                g = edits.graph = ColourGraph(gate, edits, centre)
            except Exception as e:  # noqa: BLE001 - any failure to record leaves the eager path
                self.graph_failed = True
                warnings.warn(f"virgi: render colours run without CUDA graphs: {type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else ''}")
        if g is not None and graphs:
            out = g(centre)
            return out if transient else out.clone()
        edits.frames += 1
        return gated_colours(gate, edits, centre)

    # ---------------------------------------------------------------- levels
    def background(self, bg: Tensor, device: torch.device) -> Tensor:
        """``bg`` on ``device`` (copied once per background tensor, not once per frame)."""
        key = (stamp(bg), device)
        if self._background is None or self._background.key != key:
            self._background = BackgroundCache(key, bg, bg.to(device))
        return self._background.on_device

    def background_row(self, bg: Tensor) -> Tensor:
        """``bg`` as :meth:`background` returned it, as gsplat takes backgrounds: [1,3] float32 (made once
        per background)."""
        b = self._background
        if b is None or b.on_device is not bg:
            return bg.float().reshape(1, -1)
        if b.row is None:
            b.row = bg.float().reshape(1, -1)
            b.row_with_depth = torch.cat([b.row, b.row.new_zeros(1, 1)], dim=1)
        return b.row

    def with_depth_channel(self, row: Tensor) -> Tensor:
        """[1,D] backgrounds and a zero for an expected-depth channel: [1,D+1] (kept for
        :meth:`background_row`'s row)."""
        b = self._background
        if b is not None and b.row is row:
            return b.row_with_depth
        return torch.cat([row, row.new_zeros(1, 1)], dim=1)

    def geometry(self, model) -> GeometryCache:
        gp = _gaussian_params(model)
        params = (gp["means"], gp["quats"], gp["scales"], gp["opacities"])
        key = tuple(map(stamp, params))
        g = self.geometry_level
        if g is None or g.key != key:
            with torch.no_grad():
                means, quats, scales, opac = (p.detach() for p in params)
                g = GeometryCache(key, params, means, quats, torch.exp(scales), torch.sigmoid(opac).reshape(-1))
            self.geometry_level = g
        return g

    def gate(self, model, watch: ModuleWatch, versions: tuple, means: Tensor) -> GateCache:
        """The gate level for the model's field (``watch``: its :class:`ModuleWatch`, current;
        ``versions``: its :meth:`~ModuleWatch.versions` now), Gaussians (``means``: the model's), gate
        and threshold (the caller has checked that the gate is current and the field decoupled)."""
        cfg = model.config
        mag = model.spec_magnitude
        key = (watch, versions, watch.storages(), stamp(means), stamp(mag), float(cfg.gate_threshold),
               bool(getattr(cfg, "render_cache_half", False)))
        g = self.gate_level
        if g is None or g.key != key:
            self.gate_level = None  # free the old level before the new one is filled
            self.edit_level = None
            g = _build_gate(model, key, (watch.module, watch.tensors, means, mag), key[-1])
            self.gate_level = g
        return g

    def edits(self, model, gate: GateCache) -> EditCache:
        stack = model.edit_stack
        key = (id(gate), stamp(model.diffuse_cache), id(stack), getattr(stack, "revision", None),
               getattr(model, "_live_revision", 0))
        e = self.edit_level
        if e is None or e.key != key:
            self.edit_level = None
            e = _build_edits(model, key, (gate, model.diffuse_cache, stack), gate)
            self.edit_level = e
        return e


def _gaussian_params(model) -> dict:
    """The model's Gaussian parameters by name: its ``gauss_params`` ParameterDict's own entries (a
    ParameterDict look-up takes a ``getattr``, and the model's ``means`` property one more)."""
    gp = model.gauss_params
    return getattr(gp, "_parameters", gp)


@torch.no_grad()
def _build_gate(model, key: tuple, refs: tuple, half: bool) -> GateCache:
    fld = model.field
    means = model.means.detach()
    index = (model.spec_magnitude > model.config.gate_threshold).nonzero().flatten()
    means_g = means[index].contiguous()
    p1s, p2s, p3s = [], [], []
    for s in range(0, means_g.shape[0], CHUNK):
        f = fld.encode(means_g[s : s + CHUNK])
        h1, h2 = fld.diffuse_hidden(f)
        p1, p2, p3 = fld.specular_parts(f, h1, h2)
        p1s.append(p1)
        p2s.append(p2 if fld.cfg.residual_links else p2[:1])
        p3s.append(p3 if fld.cfg.residual_links else p3[:1])
    h, dt = fld.cfg.hidden, means.dtype
    if p1s and fld.cfg.residual_links:
        p1, p2, p3 = torch.cat(p1s), torch.cat(p2s), torch.cat(p3s)
    elif p1s:
        p1, p2, p3 = torch.cat(p1s), p2s[0], p3s[0]
    else:
        p1, p2, p3 = means.new_zeros(0, h), means.new_zeros(0, h), means.new_zeros(0, 3)
    w_dir, w_s1, w_s2 = fld.specular_direction_weights()
    levels = fld.dir_encoding.levels
    a = sh_monomial_matrix(levels).to(means.device)
    w_mono = (a @ w_dir.detach().double().t()).to(dt)
    store = torch.float16 if half else dt
    return GateCache(key, refs, index, means_g, p1.to(store).contiguous(), p2.to(store).contiguous(),
                     p3.to(dt).contiguous(), w_mono.contiguous(), w_s1.detach().t().to(dt).contiguous(),
                     w_s2.detach().t().to(dt).contiguous(), monomial_degree(levels))


def edited_diffuse(fld, f: Tensor, h2: Tensor, stack, live) -> Tensor:
    """Diffuse logits of Gaussians with features ``f`` / ``h2``: the base head, then the edit stack's
    edits, then the live (uncommitted) edit over them."""
    c = fld.diffuse(h2)
    if stack is not None:
        c = stack.diffuse(f, h2, c)
    if live is not None:
        c = live.over(f, h2, c)
    return c


@torch.no_grad()
def _build_edits(model, key: tuple, refs: tuple, gate: Optional[GateCache]) -> EditCache:
    stack = model.active_stack()
    live = getattr(model, "live_edit", None)
    means = model.means.detach()
    if stack is None and live is None:
        c_d = model.diffuse_cache.to(means.dtype)
    else:
        fld = model.field
        parts = []
        for s in range(0, means.shape[0], CHUNK):
            f = fld.encode(means[s : s + CHUNK])
            _, h2 = fld.diffuse_hidden(f)
            parts.append(edited_diffuse(fld, f, h2, stack, live))
        c_d = torch.cat(parts) if parts else means.new_zeros(0, 3)
    k = stack.specular_strength if stack is not None else 1.0
    p3k = w_s2k = None
    if gate is not None and gate.size > 0 and k != 0.0:
        p3k = (c_d[gate.index] + k * gate.p3).contiguous()
        w_s2k = (gate.w_s2 * k).contiguous()
    return EditCache(key, refs, gate, torch.sigmoid(c_d).contiguous(), p3k, w_s2k)


# ----------------------------------------------------------------------------- outputs
class ViewOutputs(MutableMapping):
    """A render's outputs by name, as nerfstudio's viewer and scripts read them (``keys()``,
    ``out[name]``, ``out[name] = ...``). Names given as functions are computed on first access
    and kept: the viewer shows one output (and depth), so a frame does not pay for the others."""

    def __init__(self, order: tuple, ready: Dict[str, Tensor], lazy: Dict[str, Callable[[], Tensor]]) -> None:
        self._order = [k for k in order if k in ready or k in lazy]
        self._ready = dict(ready)
        self._lazy = dict(lazy)

    def __getitem__(self, key: str) -> Tensor:
        if key not in self._ready:
            if key not in self._lazy:
                raise KeyError(key)
            self._ready[key] = self._lazy.pop(key)()
        return self._ready[key]

    def __setitem__(self, key: str, value) -> None:
        self._lazy.pop(key, None)
        if key not in self._ready and key not in self._order:
            self._order.append(key)
        self._ready[key] = value

    def __delitem__(self, key: str) -> None:
        if key not in self._ready and key not in self._lazy:
            raise KeyError(key)
        self._ready.pop(key, None)
        self._lazy.pop(key, None)
        self._order.remove(key)

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._order))

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, key) -> bool:
        return key in self._ready or key in self._lazy

    def computed(self) -> list:
        """Names computed so far (for tests and benchmarks)."""
        return [k for k in self._order if k in self._ready]

    def __repr__(self) -> str:
        return f"ViewOutputs({self._order}, computed={self.computed()})"


__all__ = ["ColourGraph", "EditCache", "GateCache", "GeometryCache", "ModuleWatch", "RenderCache", "View", "ViewColours",
           "ViewOutputs", "colours_of_gated", "edited_diffuse", "gated_colours", "stamp", "view_of"]
