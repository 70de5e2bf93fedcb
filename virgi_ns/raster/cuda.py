"""CUDA backend of the rasterizer: our kernels in ``csrc/``, built on first use.

The extension is compiled with :func:`torch.utils.cpp_extension.load` the first time it is
needed and cached in torch's extensions directory (``TORCH_EXTENSIONS_DIR``, by default
``~/.cache/torch_extensions``); ``TORCH_CUDA_ARCH_LIST`` chooses the GPU architectures as for any
torch extension. A stamp beside the cache notes what the build was made from (:func:`build_key`),
so later processes import it directly (:func:`load_cached`). Each request projects every Gaussian
once per requested view, bins and sorts only the requested 16-px grid tiles, and emits the
contribution lists of :mod:`contract`.

Weights carry no autograd history to the geometry here (use the reference backend for geometry
gradients). The ordinary :func:`virgi_ns.raster.composite` runs a fused forward/backward to the
colours for these lists (:meth:`CudaContributions.composite`).

Large requests (whole images, :data:`DEFERRED_MIN_PIXELS` and up) get *deferred* lists
(:class:`DeferredCudaContributions`): the rasterizer runs only its count pass, which finds the
contributing pairs and each pixel's final transmittance, and the composite and its gradient
walk the depth-sorted tile lists again, recomputing each weight exactly as the count pass did,
instead of writing and reading hundreds of millions of stored entries; the count pass also keeps,
per 16-px tile, only the list elements that matter to its pixels, so those walks skip the
Gaussians that reach none of them. The entries
(``pixel``, ``pair``, ``weight``) are built on first access, equal to the eager lists.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import NamedTuple, Optional

import torch
from torch import Tensor

from virgi_ns.raster.contract import Cameras, Contributions, Request
from virgi_ns.raster.contract import composite as _composite
from virgi_ns.raster.contract import composite_plain as _plain_composite

CSRC = Path(__file__).resolve().parents[2] / "csrc"
SOURCES = ("extension.cpp", "raster_kernels.cu", "composite_kernels.cu", "edit_kernels.cu", "edit_heads.cu",
           "classifier.cu")
EXTENSION_NAME = "virgi_ns_raster"

TILE_BACKWARD_MIN_PIXELS = 1 << 20  # per-entry atomics are the faster backward below ~1 Mpix
# Size of the compact visible-pair arrays to try first; None: the extension estimates it (tests
# set a small value to exercise the overflow and its retry).
VISIBLE_CAPACITY: int | None = None
# The rasterization passes: None chooses by size (one pass into a padded per-pixel layout for
# small requests, count + fill otherwise); 0 forces two passes; n > 0 forces one pass with n
# entries reserved per pixel (falling back to two passes where a pixel has more).
SINGLE_PASS: int | None = None
# Requests of at least this many pixels get deferred lists (see the module docstring); 0 defers
# every request, None none.
DEFERRED_MIN_PIXELS: int | None = 1 << 20

_LOCK = threading.Lock()
_MODULE: ModuleType | None = None
_FAILURE: str | None = None


def cuda_home() -> str | None:
    """A CUDA toolkit root holding both ``bin/nvcc`` and the runtime headers, or None."""
    from torch.utils import cpp_extension

    candidates = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), cpp_extension.CUDA_HOME,
                  "/usr/local/cuda"]
    nvcc = shutil.which("nvcc")
    if nvcc:
        candidates.append(str(Path(os.path.realpath(nvcc)).parents[1]))
    for root in candidates:
        if root and (Path(root) / "bin" / "nvcc").exists() and \
                (Path(root) / "include" / "cuda_runtime_api.h").exists():
            return root
    return None


def _build_flags() -> dict:
    return dict(
        extra_cflags=["-O3"],
        extra_cuda_cflags=["-O3", "-fmad=false"],
    )


def build(verbose: bool = False) -> ModuleType:
    """Compile (or load the cached build of) the extension; needs nvcc, not a GPU."""
    from torch.utils import cpp_extension

    key = build_key()  # before CUDA_HOME is set below, as a later process will see the environment
    root = cuda_home()
    if root is None:
        raise RuntimeError("nvcc and the CUDA headers were not found (set CUDA_HOME)")
    # torch guesses the toolkit from the nvcc on PATH, which may be a wrapper script outside it.
    cpp_extension.CUDA_HOME = root
    os.environ.setdefault("CUDA_HOME", root)
    if not os.environ.get("TORCH_CUDA_ARCH_LIST") and not torch.cuda.is_available():
        raise RuntimeError("no GPU to build for: set TORCH_CUDA_ARCH_LIST (e.g. 9.0) to build without one")
    module = cpp_extension.load(
        name=EXTENSION_NAME,
        sources=[str(CSRC / s) for s in SOURCES],
        verbose=verbose,
        **_build_flags(),
    )
    _write_stamp(module, key)
    return module


def build_key() -> str:
    """What a build of the extension depends on: every file of ``csrc/``, the flags, torch, the CUDA
    toolkit, the architectures and the interpreter. Equal keys mean the cached build is this one."""
    h = hashlib.sha256()
    for f in sorted(CSRC.iterdir()):
        if f.suffix in (".cpp", ".cu", ".h", ".cuh"):
            h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    arch = os.environ.get("TORCH_CUDA_ARCH_LIST", "")
    if not arch and torch.cuda.is_available():  # the build targets the GPU it was made on
        arch = "sm_%d%d" % torch.cuda.get_device_capability()
    toolkit = os.environ.get("CUDA_HOME") or os.environ.get("CUDA_PATH") or shutil.which("nvcc") or ""
    h.update(json.dumps([_build_flags(), torch.__version__, torch.version.cuda, toolkit, arch, sys.version]).encode())
    return h.hexdigest()


def stamp_path() -> Path:
    """Where the last build's key and library are noted (beside torch's extension builds)."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR") or str(Path.home() / ".cache" / "torch_extensions")
    return Path(root) / f"{EXTENSION_NAME}.stamp.json"


def _write_stamp(module: ModuleType, key: str) -> None:
    lib = Path(module.__file__).resolve()
    stamp = {"key": key, "library": str(lib), "name": module.__name__, "mtime_ns": lib.stat().st_mtime_ns}
    path = stamp_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(stamp))
        os.replace(tmp, path)
    except OSError:  # a read-only cache: later processes take the slow path
        pass


def load_cached() -> ModuleType | None:
    """The cached build, imported directly, when its stamp's key is this tree's; else None.
    ``torch.utils.cpp_extension.load`` gives the same module but first imports the build tools and
    runs ninja to check the build, most of a second in a fresh process."""
    try:
        stamp = json.loads(stamp_path().read_text())
        lib = Path(stamp["library"])
        if stamp["key"] != build_key() or lib.stat().st_mtime_ns != stamp["mtime_ns"]:
            return None
        spec = importlib.util.spec_from_file_location(stamp["name"], lib)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    except (OSError, ValueError, KeyError, TypeError, ImportError, AttributeError):
        return None


def _loaded_from_cache() -> bool:
    """Whether the extension is loaded, trying the cached build (no build tools) if it is not yet."""
    global _MODULE
    with _LOCK:
        if _MODULE is None:
            _MODULE = load_cached()
        return _MODULE is not None


def _load() -> ModuleType:
    """The extension module: the cached build when it is current, else compiled (or checked by
    torch's build tools) with a console notice."""
    global _MODULE, _FAILURE
    with _LOCK:
        if _MODULE is not None:
            return _MODULE
        if _FAILURE is not None:
            raise RuntimeError(_FAILURE)
        _MODULE = load_cached()
        if _MODULE is not None:
            return _MODULE
        try:
            from rich.console import Console

            console = Console(stderr=True)
            with console.status("[bold]virgi-ns: loading the CUDA rasterizer "
                                "(the first use compiles it, about a minute)..."):
                _MODULE = build()
        except Exception as e:  # noqa: BLE001 - the reason is reported to the caller
            _FAILURE = f"building the CUDA rasterizer failed: {str(e).strip().splitlines()[-1] if str(e).strip() else e!r}"
            raise RuntimeError(_FAILURE) from e
        return _MODULE


def available() -> tuple[bool, str]:
    """(True, "") when a GPU is present and the extension builds/loads, else (False, reason)."""
    if not torch.cuda.is_available():
        return False, "no CUDA GPU is visible to torch"
    if torch.version.cuda is None:
        return False, "this torch build has no CUDA support"
    if not _loaded_from_cache() and cuda_home() is None:
        return False, "nvcc and the CUDA headers were not found (set CUDA_HOME)"
    try:
        _load()
    except RuntimeError as e:
        return False, str(e)
    return True, ""


@dataclass
class CudaContributions(Contributions):
    """Contributions plus each pixel's entry range (``pixel_offsets`` [P+1], int64), which the
    fused :func:`composite` uses. Entry indices (``pixel``, ``pair``) are int32. ``tile_lists``
    (the request's plan and its depth-sorted tile lists as pair ranks) lets the fused backward
    reduce per tile; it is dropped by anything that rebuilds the object."""

    pixel_offsets: Tensor | None = None
    tile_lists: tuple | None = None

    def composite(self, colours: Tensor, background: Tensor | float | None = None) -> Tensor:
        """Fused on the GPU (float32 [U, D] colours on CUDA, weights without history); anything
        else takes the plain torch path, as for any :class:`Contributions`."""
        fused = (self.pixel_offsets is not None and colours.is_cuda and colours.dtype == torch.float32
                 and colours.dim() == 2 and not self.weight.requires_grad)
        if not fused:
            return _plain_composite(colours, self, background)
        return self._run(_FusedComposite, colours, background)

    def _run(self, fn, colours: Tensor, background: Tensor | float | None) -> Tensor:
        """Check the colours against the pairs, shape the background as [D], apply the kernels'
        autograd function ``fn`` and return the [T, h, w, D] images."""
        if colours.shape[0] != self.pair_view.shape[0]:
            raise ValueError(f"composite: {colours.shape[0]} colours for {self.pair_view.shape[0]} pairs")
        d = colours.shape[1]
        bg = None
        if background is not None:
            bg = torch.as_tensor(background, dtype=colours.dtype, device=colours.device).reshape(-1).expand(d)
            bg = bg.contiguous()
        out = fn.apply(colours, bg, self)
        t, h, w = self.shape
        return out.reshape(t, h, w, d)


class DeferredLists(NamedTuple):
    """What the count pass of a deferred request keeps (``csrc/raster_kernels.cu``): the request's tile
    ``plan``, ``meta`` and each tile's list ``ranges``, the lists' pairs (``list_pair``), each pixel's entry
    count (``px_count``), the lists' sorted depth keys (``sorted_vals``), the records of the pass
    (``rec0``, ``rec1``), each pair's ``rank``, and per tile the list elements that matter to some pixel
    (``keep``, ranged by ``keep_end``)."""

    plan: Tensor
    meta: Tensor
    ranges: Tensor
    list_pair: Tensor
    px_count: Tensor
    sorted_vals: Tensor
    rec0: Tensor
    rec1: Tensor
    rank: Tensor
    keep: Tensor
    keep_end: Tensor


class DeferredCudaContributions(CudaContributions):
    """Contributions whose entries are built on first access (``pixel``, ``pair``, ``weight``,
    ``pixel_offsets``) from the count pass's :class:`DeferredLists`; :meth:`composite` works from the tile
    lists without them."""

    _LAZY = ("pixel", "pair", "weight", "pixel_offsets")

    def __init__(self, lists: DeferredLists, **kw) -> None:
        self.deferred = lists
        self._lists: dict | None = None
        super().__init__(pixel=None, pair=None, weight=None, pixel_offsets=None, **kw)

    def _materialize(self) -> dict:
        if self._lists is None:
            d = self.deferred
            pixel, pair, weight, offsets = _load().materialize_lists(d.plan, d.meta, d.ranges, d.sorted_vals, d.rec0,
                                                                    d.rec1, d.px_count, d.rank)
            self._lists = {"pixel": pixel, "pair": pair, "weight": weight, "pixel_offsets": offsets}
        return self._lists

    @property
    def num_entries(self) -> int:
        if self._lists is not None:
            return int(self._lists["weight"].numel())
        return int(self.deferred.px_count.sum())

    def composite(self, colours: Tensor, background: Tensor | float | None = None) -> Tensor:
        if not (colours.is_cuda and colours.dtype == torch.float32 and colours.dim() == 2
                and 1 <= colours.shape[1] <= 8):
            return super().composite(colours, background)
        return self._run(_DeferredComposite, colours, background)


def _lazy_field(name: str) -> property:
    def get(self):
        return self._materialize()[name]

    def set_(self, value):
        if value is not None:
            self._materialize()[name] = value

    return property(get, set_)


for _name in DeferredCudaContributions._LAZY:
    setattr(DeferredCudaContributions, _name, _lazy_field(_name))


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, cameras: Cameras,
              request: Request) -> CudaContributions:
    """Contributions of N Gaussians to the pixels of ``request`` (see :func:`virgi_ns.raster.rasterize`).

    Computes in float32 on the Gaussians' device; the outputs do not track geometry gradients.
    """
    ext = _load()
    dev = means.device
    if dev.type != "cuda":
        raise RuntimeError("the cuda rasterizer backend needs the Gaussians on a CUDA device")

    def f32(t: Tensor) -> Tensor:
        return t.detach().to(device=dev, dtype=torch.float32).contiguous()

    n = means.shape[0]
    deferred = DEFERRED_MIN_PIXELS is not None and request.num_pixels >= DEFERRED_MIN_PIXELS
    out = ext.rasterize_contributions(
        f32(means).reshape(n, 3), f32(quats).reshape(n, 4), f32(scales).reshape(n, 3),
        f32(opacities).reshape(n), f32(cameras.Ks), f32(cameras.viewmats),
        cameras.widths.contiguous(), cameras.heights.contiguous(),
        request.views.contiguous(), request.x0.contiguous(), request.y0.contiguous(),
        int(request.width), int(request.height), -1 if VISIBLE_CAPACITY is None else int(VISIBLE_CAPACITY),
        -1 if SINGLE_PASS is None else int(SINGLE_PASS), deferred,
    )
    pixel, pair, weight, transmittance, valid, offsets, pair_view, pair_gaussian, pair_depth = out[:9]
    if deferred:
        plan, meta, ranges, list_pair = out[9:13]
        return DeferredCudaContributions(
            DeferredLists(*out[9:]),
            request=request, num_gaussians=int(n), pair_view=pair_view, pair_gaussian=pair_gaussian,
            pair_depth=pair_depth, transmittance=transmittance, valid=valid,
            tile_lists=(plan, meta, ranges, list_pair))
    return CudaContributions(
        request=request, num_gaussians=int(n), pair_view=pair_view, pair_gaussian=pair_gaussian,
        pair_depth=pair_depth, pixel=pixel, pair=pair, weight=weight, transmittance=transmittance,
        valid=valid, pixel_offsets=offsets, tile_lists=tuple(out[9:13]),
    )


def _keep_for_backward(ctx, colours: Tensor, background: Tensor | None, contrib: CudaContributions) -> Tensor:
    """A composite's forward: keep what its backward reads (the lists, whether there is a background, the
    number of pairs); returns the background as the kernels take it ([D], or empty)."""
    ctx.contrib = contrib
    ctx.has_bg = background is not None
    ctx.num_pairs = colours.shape[0]
    bg = background if background is not None else torch.empty(0, device=colours.device)
    return bg.contiguous()


def _background_grad(ctx, grad: Tensor) -> Tensor | None:
    """A composite's gradient to its background [D]: the images' gradient weighed by each pixel's
    transmittance, or None where there is none to give."""
    if ctx.has_bg and ctx.needs_input_grad[1]:
        return (ctx.contrib.transmittance[:, None] * grad).sum(0)
    return None


class _FusedComposite(torch.autograd.Function):
    """images = sum_k w_k colours[pair_k] + T background, gradient to colours and background."""

    @staticmethod
    def forward(ctx, colours: Tensor, background: Tensor | None, contrib: CudaContributions) -> Tensor:
        bg = _keep_for_backward(ctx, colours, background, contrib)
        return _load().composite_forward(colours.contiguous(), contrib.pair, contrib.weight,
                                         contrib.pixel_offsets, contrib.transmittance, bg)

    @staticmethod
    def backward(ctx, grad: Tensor):
        c: CudaContributions = ctx.contrib
        grad = grad.contiguous()
        g_colours = None
        if ctx.needs_input_grad[0]:
            # per tile (warp sums, one atomic per tile and Gaussian) pays off on whole images,
            # where a Gaussian reaches many pixels; small tile batches are faster per entry
            if c.tile_lists is not None and grad.shape[1] in (1, 3, 4) and \
                    c.num_pixels >= TILE_BACKWARD_MIN_PIXELS:
                g_colours = _load().composite_backward_tiles(grad, c.pixel_offsets, c.pair, c.weight,
                                                            ctx.num_pairs, *c.tile_lists)
            else:
                g_colours = _load().composite_backward(grad, c.pixel, c.pair, c.weight, ctx.num_pairs)
        return g_colours, _background_grad(ctx, grad), None


class _DeferredComposite(torch.autograd.Function):
    """The same function as :class:`_FusedComposite`, from deferred lists."""

    @staticmethod
    def forward(ctx, colours: Tensor, background: Tensor | None, contrib: DeferredCudaContributions) -> Tensor:
        d = contrib.deferred
        bg = _keep_for_backward(ctx, colours, background, contrib)
        return _load().deferred_composite_forward(colours.contiguous(), bg, d.plan, d.meta, d.ranges,
                                                  d.sorted_vals, d.list_pair, d.rec0, d.rec1, contrib.transmittance,
                                                  d.keep, d.keep_end)

    @staticmethod
    def backward(ctx, grad: Tensor):
        d = ctx.contrib.deferred
        g_colours = None
        if ctx.needs_input_grad[0]:
            g_colours = _load().deferred_composite_backward(grad.contiguous(), ctx.num_pairs, d.plan, d.meta, d.ranges,
                                                           d.sorted_vals, d.list_pair, d.rec0, d.rec1, d.keep,
                                                           d.keep_end)
        return g_colours, _background_grad(ctx, grad), None


def composite(colours: Tensor, contrib: Contributions, background: Tensor | float | None = None) -> Tensor:
    """The same as :func:`virgi_ns.raster.composite` (kept for callers of this module)."""
    return _composite(colours, contrib, background)


def edit_by_gaussian(pair: Tensor, weight: Tensor, pixel_offsets: Tensor, rows: Tensor, starts: Tensor,
                     loss_weight: Tensor, U: int) -> list[Tensor]:
    """Every pixel set's entries sorted by Gaussian, for :func:`edit_l1_step`'s gathered gradient (the
    arguments as :class:`virgi_ns.edit.pixels.FusedSets` holds them): [t_start [sets + 1], each entry's
    Gaussian, row (int32), and weight x its row's loss weight / 3]. No host sync."""
    return list(_load().edit_by_gaussian(pair, weight, pixel_offsets, rows, starts, loss_weight, int(U)))


def edit_l1_step(colours: Tensor, pair: Tensor, weight: Tensor, pixel_offsets: Tensor, rows: Tensor, starts: Tensor,
                 counter: Tensor, background: Tensor, target: Tensor, loss_weight: Tensor,
                 max_rows: int, by_gaussian: Optional[list[Tensor]] = None) -> tuple[Tensor, Tensor]:
    """One step of an edit's weighted L1 pixel loss on the pixel set ``counter % (len(starts) - 1)``
    (:class:`virgi_ns.edit.pixels.FusedSets` says what each argument holds): (loss [1], its gradient
    to ``colours`` [U, 4], the last column padding); advances ``counter``. No host sync. The gradient
    is scattered by one atomic per entry, or, with ``by_gaussian`` (:func:`edit_by_gaussian`'s),
    gathered per Gaussian."""
    gather = (None,) * 4 if by_gaussian is None else tuple(by_gaussian)
    loss, grad = _load().edit_l1_step(colours, pair, weight, pixel_offsets, rows, starts, counter, background, target,
                                      loss_weight, int(max_rows), *gather)
    return loss, grad


def edit_heads_forward(pre: Tensor, x: Tensor, w2: Tensor, b2: Tensor, wd: Tensor, bd: Tensor, cd: Tensor,
                       cs: Tensor, k: float, hd_offset: int) -> tuple[Tensor, Tensor, Tensor]:
    """The edit heads' forward from ``pre = x W1^T + b1`` (:mod:`virgi_ns.edit.heads` says what each
    argument holds): (colours [U, 3], alpha [U], the copied layer's output [U, 3])."""
    colours, alpha, cdp = _load().edit_heads_forward(pre, x, w2, b2, wd, bd, cd, cs, float(k), int(hd_offset))
    return colours, alpha, cdp


def edit_heads_backward(grad_colours: Tensor, colours: Tensor, alpha: Tensor, cdp: Tensor, cd: Tensor, pre: Tensor,
                        w2: Tensor) -> tuple[Tensor, Tensor]:
    """The edit heads' backward from the loss's gradient to the colours ([U, 4], the last column
    padding): (the gradients to ``pre`` and to the layer's output, then a 0 [U, S + 4], the summed
    gradients of b1, w2, b2 and bd [2 S + 4])."""
    rows, sums = _load().edit_heads_backward(grad_colours, colours, alpha, cdp, cd, pre, w2)
    return rows, sums


def edit_layer_forward(alpha: Tensor, x: Tensor, wd: Tensor, bd: Tensor, cd: Tensor, cs: Tensor, k: float,
                       hd_offset: int) -> tuple[Tensor, Tensor]:
    """The staged recipe's forward, the segmentation fixed at ``alpha`` [U] (the other arguments as in
    :func:`edit_heads_forward`): (colours [U, 3], the copied layer's output [U, 3])."""
    colours, cdp = _load().edit_layer_forward(alpha, x, wd, bd, cd, cs, float(k), int(hd_offset))
    return colours, cdp


def edit_layer_backward(grad_colours: Tensor, colours: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    """The staged recipe's backward from the loss's gradient to the colours ([U, 4], the last column
    padding): (the gradient to the layer's output, then a 0 [U, 4], its sums over the Gaussians [4],
    the last 0)."""
    rows, sums = _load().edit_layer_backward(grad_colours, colours, alpha)
    return rows, sums


def heaviest_pair(pair: Tensor, weight: Tensor, pixel_offsets: Tensor) -> Tensor:
    """[P] each pixel's pair of largest weight (among equals the largest index; -1 where none) over its
    entries ``pixel_offsets[p]:pixel_offsets[p+1]`` of ``pair`` (int32) and ``weight`` (float32): what
    :func:`virgi_ns.edit.targets.heaviest_gaussian` finds, one thread per pixel. No host sync."""
    return _load().heaviest_pair(pair, weight, pixel_offsets)


def classifier_fits(inputs: int, width: int, device: torch.device) -> bool:
    """Whether :func:`classifier_gradients` takes a head of ``width`` hidden units over ``inputs`` inputs on
    ``device``: the kernel's own shape and shared-memory check."""
    index = device.index if device.index is not None else torch.cuda.current_device()
    return bool(_load().classifier_fits(inputs, width, index))


def classifier_gradients(x: Tensor, y: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor) -> Tensor:
    """The staged classifier's gradient (:func:`virgi_ns.edit.fitting.classifier_gradients` says what it
    is) over the samples ``x`` [S, D] with labels ``y`` [S, 1], flat [W D + 2 W + 1]: W1's (row-major), b1's,
    w2's, b2's. Two kernels, no atomics: the same sums on every run. No host sync."""
    return _load().classifier_gradients(x, y, w1, b1, w2, b2)


__all__ = ["available", "build", "classifier_fits", "classifier_gradients", "composite", "cuda_home",
           "edit_by_gaussian", "edit_heads_backward", "edit_heads_forward", "edit_l1_step", "edit_layer_backward",
           "edit_layer_forward", "heaviest_pair", "rasterize", "CudaContributions", "DeferredCudaContributions"]

if __name__ == "__main__":  # pragma: no cover - manual build check: python -m virgi_ns.raster.cuda
    build(verbose=True)
    print("built", file=sys.stderr)
