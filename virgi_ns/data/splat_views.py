"""Views of a splat rendered from itself: where the cameras go, and the cached images.

A splat file carries its own appearance. Rendered from cameras placed around what it holds, it is
its own training data (:mod:`virgi_ns.data.splat` hands the views to nerfstudio). Every number of
the rig comes from the Gaussians' distribution, by these rules (chosen once, for any splat; each
with its reason):

1. **Weights.** A Gaussian counts by its opacity: fog and near-transparent floaters hardly show in
   any render, so they should hardly move the rig.
2. **Centre**: axis by axis, the midpoint of the opacity-weighted 2% and 98% quantiles of the means
   (the centre of the box holding the middle 96% of the opacity). A minority of far floaters (under
   2% on a side) does not move it however far away they are, where a mean follows them; and a scene
   of two objects is centred between them, where a median would sit at the edge of the gap.
3. **Extent**: ``radius``, the opacity-weighted 95% quantile of the distances to the centre (the
   sphere holding 95% of the opacity; the outer 5%, stray background and floaters, may leave the
   frame), and ``far_radius``, the 99.9% quantile (the content's outer edge: the near/far bounds and
   the scene box). A radius of (almost) zero is a degenerate splat and is refused.
4. **Frame of the run**: the capture frame is the file's; the run's is ``x_run = (x - centre) /
   radius`` (a translation and a uniform scale, no rotation: the SH coefficients need no turning),
   so every scene reaches nerfstudio at the same size, whatever its units, and the rasterizer's
   fixed near plane (0.01) is 1% of the extent. Exports go back to the file's frame.
5. **Directions**: ``views + eval_views`` directions on a Fibonacci sphere around the centre (nearly
   uniform over the whole sphere: a file does not say which way is up, and any side of an object may
   be recoloured), its pole on the file's -y axis (the 3DGS/COLMAP frames' up), so images are upright
   for such files. Every ``(views + eval_views) / eval_views``-th direction of the lattice is held out
   (``eval_views`` defaults to ``views / 8``, nerfstudio's interval), so each held-out camera sits
   between training cameras.
6. **Distance**: ``radius / sin(fov / 2)``: the 95% sphere just fills a square image of field of view
   ``fov`` (50 degrees) from every direction, every camera looking at the centre.
7. **Resolution** (square images): one pixel at the centre's depth spans the footprint of the median
   Gaussian (opacity-weighted; the footprint is ``sqrt(s1 s2)`` of its two largest standard
   deviations, since a splat's Gaussians are often flat): ``2 radius / (cos(fov/2) footprint)``, up to
   a multiple of 16, within ``[min_resolution, max_resolution]`` (256 to 1024: the floor keeps small
   scenes legible, the cap bounds time and memory).
8. **Near/far**: the depth range ``distance -/+ far_radius`` (run units) over which every camera sees
   the content; recorded with the views (the rasterizer's own near and far planes are gsplat's).

The images (RGB over the background, 8-bit PNG, rendered by :mod:`virgi_ns.raster` with the file's
SH colours, :class:`~virgi_ns.colour.file_colours.FileColours`) are cached in a folder keyed by a
digest of the decoded Gaussians and the view settings: ``$VIRGI_NS_CACHE`` or
``$XDG_CACHE_HOME/virgi-ns`` (else ``~/.cache/virgi-ns``), then ``splat-views/<digest>/``. Why there:
the dataparser runs before a run's folder exists and knows nothing of it, the splat's own folder may
be read-only, and a key on what is rendered lets any process (training, ``ns-viewer``, the commands)
find the same images, or render them again identically, wherever the run was made. Every image and
the folder's ``views.json`` (written last) go through :func:`~virgi_ns.errors.atomic_path`, so
processes rendering the same views at once only race to write the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.gaussians import Gaussians

VIEWS_FORMAT = "virgi-splat-views"
VIEWS_VERSION = 1
VIEWS_FILE = "views.json"
BYTES_PER_GAUSSIAN = 4096
"""Device memory a Gaussian may take in a run (its parameters, the colour field's per-Gaussian features
and caches, contribution lists of whole views): the bound for "more Gaussians than the device holds"."""
BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}

__all__ = ["Rig", "ViewSettings", "cache_root", "check_splat", "ensure_views", "photo_reader", "place_cameras",
           "render_view_images", "splat_digest"]


@dataclass(frozen=True)
class ViewSettings:
    """What decides the views besides the Gaussians (the dataparser's options)."""

    views: int = 64
    eval_views: int = 0
    """0: ``views // 8`` (at least 1)."""
    fov_degrees: float = 50.0
    min_resolution: int = 256
    max_resolution: int = 1024
    background: str = "black"

    @property
    def held_out(self) -> int:
        return self.eval_views if self.eval_views > 0 else max(1, self.views // 8)

    def check(self) -> None:
        if self.views < 1:
            raise InputError(f"--views must be at least 1, got {self.views}")
        if self.eval_views < 0:
            raise InputError(f"--eval-views must be 0 (views / 8) or more, got {self.eval_views}")
        if not 1.0 <= self.fov_degrees <= 150.0:
            raise InputError(f"--fov-degrees must lie in [1, 150], got {self.fov_degrees}")
        if not 16 <= self.min_resolution <= self.max_resolution:
            raise InputError(f"resolutions must satisfy 16 <= --min-resolution <= --max-resolution, got "
                             f"{self.min_resolution} and {self.max_resolution}")
        if self.background not in BACKGROUNDS:
            raise InputError(f"--background must be one of {', '.join(BACKGROUNDS)}, got {self.background}")


@dataclass
class Rig:
    """The cameras of a splat (see the module doc): in the file's frame ``centre``, ``radius``,
    ``far_radius`` and ``footprint``; in the run's frame (``x_run = (x - centre) / radius``) the
    OpenGL camera-to-world matrices ``train_c2w`` [V,3,4] and ``eval_c2w`` [M,3,4], at ``distance``,
    with depth bounds ``near``, ``far``; square images of ``resolution`` pixels, focal ``focal``."""

    centre: np.ndarray
    radius: float
    far_radius: float
    footprint: float
    resolution: int
    focal: float
    distance: float
    near: float
    far: float
    train_c2w: np.ndarray
    eval_c2w: np.ndarray

    @property
    def scale(self) -> float:
        """``s`` of ``x_run = s (x + t)``."""
        return 1.0 / self.radius

    def transform(self) -> np.ndarray:
        """``[R | t]`` (3x4) of ``x_run = scale (R x + t)``: ``[I | -centre]``."""
        return np.concatenate([np.eye(3), -self.centre.reshape(3, 1)], axis=1)

    def to_json(self) -> dict:
        return {"centre": [float(x) for x in self.centre], "radius": self.radius, "far_radius": self.far_radius,
                "footprint": self.footprint, "resolution": self.resolution, "focal": self.focal,
                "distance": self.distance, "near": self.near, "far": self.far,
                "train_c2w": self.train_c2w.reshape(-1, 12).tolist(), "eval_c2w": self.eval_c2w.reshape(-1, 12).tolist()}


# --------------------------------------------------------------------------- checks
def device_capacity(device: torch.device) -> int:
    """How many Gaussians ``device`` holds by :data:`BYTES_PER_GAUSSIAN` (its free memory now)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
    else:
        try:
            free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return 1 << 62
    return int(free // BYTES_PER_GAUSSIAN)


def check_splat(g: Gaussians, where: str, max_gaussians: int = 0, device: Optional[torch.device] = None) -> None:
    """Refuse a splat that cannot be recoloured: no Gaussians, non-finite values (the loader refuses
    those first), or more Gaussians than ``max_gaussians`` (0: what ``device`` holds, see
    :func:`device_capacity`). A degenerate extent is refused by :func:`place_cameras`."""
    n = len(g)
    if n == 0:
        raise InputError(f"{where}: the splat holds no Gaussians")
    bad = int(g.invalid_rows().sum())
    if bad:
        raise InputError(f"{where}: {bad:,} of {n:,} Gaussians hold NaN or Inf values")
    if max_gaussians > 0:
        limit, what = max_gaussians, f"--max-gaussians {max_gaussians:,}"
    else:
        dev = device or torch.device("cuda" if torch.cuda.is_available() else "cpu")
        limit = device_capacity(dev)
        what = f"the {'GPU' if dev.type == 'cuda' else 'free memory'} can hold (about {limit:,} at " \
            f"{BYTES_PER_GAUSSIAN} bytes each)"
    if n > limit:
        raise InputError(f"{where}: {n:,} Gaussians are more than {what}")


# ------------------------------------------------------------------------- placement
def weighted_quantile(values: Tensor, weights: Tensor, q: float) -> float:
    """The ``q`` quantile of ``values`` [N] where each counts by ``weights`` [N] (the smallest value
    whose cumulative weight reaches ``q`` of the total)."""
    v, order = torch.sort(values.double())
    w = weights.double()[order]
    cum = torch.cumsum(w, 0)
    k = int(torch.searchsorted(cum, q * cum[-1]).clamp_max(v.numel() - 1))
    return float(v[k])


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` unit vectors of a Fibonacci lattice, index 0 nearest the pole -y and the last nearest +y."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    # lattice axes (x, y, z) -> world (x, -z, y): the lattice's pole z is the world's -y
    return np.stack([r * np.cos(phi), -z, r * np.sin(phi)], axis=-1)


def look_at(eye: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world [3,4] of a camera at ``eye`` looking at the origin, image up along ``up``
    as far as the view allows."""
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-6:  # looking along the up axis: any right vector will do
        right = np.cross(fwd, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    return np.stack([right, cam_up, -fwd, eye], axis=1)


def held_out_indices(total: int, held: int) -> list[int]:
    """``held`` indices of ``total`` lattice directions, evenly spread along the lattice."""
    return sorted({min(total - 1, int((j + 0.5) * total / held)) for j in range(held)})


def place_cameras(g: Gaussians, settings: ViewSettings, where: str = "splat") -> Rig:
    """The rig of ``g`` by the module doc's rules."""
    means = g.means.detach().double().cpu()
    w = torch.sigmoid(g.opacities.detach().double().cpu()).reshape(-1)
    if not bool(w.sum() > 0):
        w = torch.ones_like(w)
    centre = torch.tensor([0.5 * (weighted_quantile(means[:, a], w, 0.02) + weighted_quantile(means[:, a], w, 0.98))
                           for a in range(3)], dtype=torch.float64)
    dist = (means - centre).norm(dim=-1)
    radius = weighted_quantile(dist, w, 0.95)
    far_radius = max(weighted_quantile(dist, w, 0.999), radius)
    size = float(means.abs().max()) if means.numel() else 0.0
    if not radius > 1e-7 * max(1.0, size):
        raise InputError(f"{where}: degenerate extent: the Gaussians' opacity sits at one point "
                         f"(95% within {radius:.3g} of {tuple(round(float(x), 6) for x in centre)})")
    s = torch.sort(torch.exp(g.scales.detach().double().cpu()), dim=-1).values  # ascending
    footprint = weighted_quantile(torch.sqrt(s[:, 1] * s[:, 2]), w, 0.5)
    half = math.radians(settings.fov_degrees) / 2.0
    if footprint > 0 and math.isfinite(footprint):
        res = 2.0 * radius / (math.cos(half) * footprint)
        res = int(math.ceil(min(res, 1e6) / 16.0) * 16)
    else:
        res = settings.max_resolution
    res = int(min(max(res, settings.min_resolution), settings.max_resolution))
    focal = (res / 2.0) / math.tan(half)
    distance = 1.0 / math.sin(half)  # run units: the radius is 1
    far_rel = far_radius / radius
    near, far = max(distance - far_rel, 0.01), distance + far_rel
    held = settings.held_out
    total = settings.views + held
    dirs = fibonacci_directions(total)
    eval_idx = held_out_indices(total, held)
    up = np.array([0.0, -1.0, 0.0])
    c2w = np.stack([look_at(distance * d, up) for d in dirs])
    mask = np.zeros(total, dtype=bool)
    mask[eval_idx] = True
    return Rig(centre.numpy(), float(radius), float(far_radius), float(footprint), res, float(focal), float(distance),
               float(near), float(far), c2w[~mask], c2w[mask])


# --------------------------------------------------------------------------- images
def cache_root(cache_dir: Optional[Path] = None) -> Path:
    """Where the views are cached (see the module doc)."""
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get("VIRGI_NS_CACHE"):
        return Path(os.environ["VIRGI_NS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "virgi-ns"


def splat_digest(g: Gaussians, settings: ViewSettings) -> str:
    """sha256 over the decoded Gaussians (float32 bytes) and the view settings: the cache's key."""
    h = hashlib.sha256()
    h.update(f"{VIEWS_FORMAT}/{VIEWS_VERSION}".encode())
    h.update(json.dumps(asdict(settings), sort_keys=True).encode())
    for t in (g.means, g.scales, g.quats, g.opacities.reshape(-1), g.sh):
        h.update(np.ascontiguousarray(t.detach().cpu().float().numpy()).tobytes())
    return h.hexdigest()


def run_frame_gaussians(g: Gaussians, rig: Rig) -> Gaussians:
    """``g`` moved into the run's frame, as a capture-frame import moves it
    (:func:`~virgi_ns.nerfstudio.frames.transform_gaussians`, float32)."""
    from virgi_ns.nerfstudio.frames import transform_gaussians

    T = torch.as_tensor(rig.transform(), dtype=torch.float32)
    m, s, q = transform_gaussians(g.means.float(), g.scales.float(), g.quats.float(), T, rig.scale)
    return Gaussians(m, s, q, g.opacities.float().reshape(-1), g.sh.float())


def raster_cameras_of(c2w: np.ndarray, rig: Rig):
    """Rasterizer cameras of OpenGL camera-to-world ``c2w`` [V,3,4] with the rig's intrinsics."""
    from virgi_ns.nerfstudio.cameras import viewmats_from_c2w
    from virgi_ns.raster import Cameras

    vm = viewmats_from_c2w(torch.as_tensor(c2w, dtype=torch.float32))
    c = rig.resolution / 2.0
    return Cameras.from_params(rig.focal, rig.focal, c, c, vm, rig.resolution, rig.resolution)


@torch.no_grad()
def render_view_images(g_run: Gaussians, cams, background, device: Optional[torch.device] = None,
                       backend: str = "auto"):
    """Yield each camera's HxWx3 float32 image of ``g_run`` (the file's SH colours, composited over
    ``background``), one view at a time."""
    from virgi_ns.colour.file_colours import FileColours
    from virgi_ns.raster import Request, composite, rasterize

    dev = device or torch.device("cuda" if torch.cuda.is_available() else "cpu")
    g = g_run.to(dev)
    sh = g.sh
    colours = FileColours(sh[:, 0], sh[:, 1:])
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev)
    quats, scales, opac = g.normalized_quats(), torch.exp(g.scales), torch.sigmoid(g.opacities)
    for i in range(len(cams)):
        cam = cams.index(i).to(dev, torch.float32)
        contrib = rasterize(g.means, quats, scales, opac, cam, Request.whole_images(cam), backend=backend)
        dirs = g.means - cam.camera_centers()[0] if colours.view_dependent else None
        per_gaussian = colours.colours(None, dirs)
        yield composite(per_gaussian[contrib.pair_gaussian.to(dev)], contrib, bg)[0].float().cpu()


def _to_png(img: Tensor, path: Path) -> None:
    from PIL import Image

    arr = (img.clamp(0.0, 1.0).numpy() * 255.0 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def image_names(rig: Rig) -> tuple[list[str], list[str]]:
    return ([f"train_{i:04d}.png" for i in range(len(rig.train_c2w))],
            [f"eval_{i:04d}.png" for i in range(len(rig.eval_c2w))])


def ensure_views(g: Gaussians, settings: ViewSettings, source: str, cache_dir: Optional[Path] = None,
                 device: Optional[torch.device] = None,
                 progress: Optional[Callable[[int, int], None]] = None) -> tuple[Path, Rig, list[Path], list[Path]]:
    """The rig of ``g`` and its cached images (rendered now where missing): (folder, rig, training
    image paths, held-out image paths). ``source``: the file's path, recorded in ``views.json``."""
    settings.check()
    rig = place_cameras(g, settings, source)
    digest = splat_digest(g, settings)
    folder = cache_root(cache_dir) / "splat-views" / digest[:24]
    train_names, eval_names = image_names(rig)
    todo = [(n, c) for n, c in zip(train_names + eval_names, list(rig.train_c2w) + list(rig.eval_c2w))
            if not (folder / n).is_file()]
    meta = folder / VIEWS_FILE
    if todo or not meta.is_file():
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise InputError(f"cannot create the view cache {folder} ({e.strerror}); set --cache-dir or VIRGI_NS_CACHE") \
                from None
        if todo:
            cams = raster_cameras_of(np.stack([c for _, c in todo]), rig)
            g_run = run_frame_gaussians(g, rig)
            for k, img in enumerate(render_view_images(g_run, cams, BACKGROUNDS[settings.background], device)):
                _to_png(img, folder / todo[k][0])
                if progress is not None:
                    progress(k + 1, len(todo))
        with atomic_path(meta) as tmp:
            tmp.write_text(json.dumps({"format": VIEWS_FORMAT, "version": VIEWS_VERSION, "digest": digest,
                                       "source": str(source), "settings": asdict(settings), "rig": rig.to_json(),
                                       "train": train_names, "eval": eval_names}, indent=1))
    return folder, rig, [folder / n for n in train_names], [folder / n for n in eval_names]


def photo_reader(views, parser: dict) -> Callable[[int], np.ndarray]:
    """A reader of ``views``' images (uint8 [H,W,3]) for a saved run on a splat, whose dataparser
    settings ``parser`` (plain values of :class:`~virgi_ns.data.splat.SplatDataParserConfig`) tell how
    to render them again where the cache no longer holds them (a cleared cache, another machine)."""

    def read(i: int) -> np.ndarray:
        from PIL import Image

        path = Path(views.filenames[i])
        if not path.is_file():
            from virgi_ns.io import load_splat

            data = Path(str(parser.get("data", "")))
            settings = ViewSettings(**{k: parser[k] for k in ("views", "eval_views", "fov_degrees", "min_resolution",
                                                              "max_resolution", "background") if k in parser})
            g = load_splat(data, drop_invalid=bool(parser.get("drop_invalid", False)))
            cache = parser.get("cache_dir")
            folder, *_ = ensure_views(g, settings, str(data), Path(str(cache)) if cache else None)
            path = folder / path.name
        try:
            with Image.open(path) as im:
                return np.array(im.convert("RGB"), dtype=np.uint8)
        except OSError as e:
            raise InputError(f"cannot read the view {path} ({type(e).__name__})") from None

    return read
