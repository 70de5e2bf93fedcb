"""The ``splat`` dataparser: ``ns-train virgi --data scene.ply splat`` recolours a splat with no photos.

Any splat the project reads (INRIA ``.ply``, SuperSplat ``.compressed.ply``, ``.spz``, a
splatfacto run) is its own training data: :mod:`virgi_ns.data.splat_views` places cameras around
what it holds and renders the training and held-out views from its SH colours (cached, so
``ns-viewer`` and the commands find the same images). The run imports the file's Gaussians as its
frozen geometry (no geometry stage: the colour stage alone), shows each Gaussian's own colour
where no edit touches it (``base_colours="file"``), and renders over the views' background. The
capture frame is the file's, so exports land where the original was.

:func:`prepare_splat_run` turns a trainer config whose dataparser is this one into such a run
(virgi's trainer config calls it before ``ns-train`` writes ``config.yml``): the model's
``geometry_from`` is the file, read in the capture's frame; ``base_colours`` 'auto' becomes 'file';
the model's background is the views'; and a run left at the method's own length (geometry +
colour steps) trains ``--steps`` colour steps instead. It refuses a splat that cannot be
recoloured (no Gaussians, NaN or infinite values, a degenerate extent, more Gaussians than the
device holds) with one line, before anything is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Literal, Optional, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from virgi_ns.errors import InputError
from virgi_ns.data.splat_views import Rig, ViewSettings, check_splat, ensure_views, place_cameras
from virgi_ns.gaussians import Gaussians
# the checkpoint-loading work-arounds, in place once entry-point discovery imports this dataparser
from virgi_ns.nerfstudio import compat  # noqa: F401

__all__ = ["SplatDataParser", "SplatDataParserConfig", "load_checked_splat", "prepare_splat_run", "splat_dataparser"]


@dataclass
class SplatDataParserConfig(DataParserConfig):
    """A splat file rendered from cameras placed around it (see :mod:`virgi_ns.data.splat_views`)."""

    _target: Type = field(default_factory=lambda: SplatDataParser)
    data: Path = Path()
    """The splat: .ply, .compressed.ply, .spz, or a splatfacto .ckpt / config.yml."""
    views: int = 64
    """Training views (a Fibonacci sphere around the splat)."""
    eval_views: int = 0
    """Held-out views, between training views (0: views / 8)."""
    fov_degrees: float = 50.0
    """Field of view of the square images."""
    min_resolution: int = 256
    """Smallest image side (the resolution follows the Gaussians' sizes between the two bounds)."""
    max_resolution: int = 1024
    """Largest image side."""
    background: Literal["black", "white"] = "black"
    """Background of the views, and of the run's renders."""
    steps: int = 1000
    """Colour-stage steps of a run left at the method's own length (--max-num-iterations overrides)."""
    cache_dir: Optional[Path] = None
    """Where the rendered views are cached (default: $VIRGI_NS_CACHE, else $XDG_CACHE_HOME/virgi-ns or
    ~/.cache/virgi-ns)."""
    max_gaussians: int = 0
    """Refuse splats with more Gaussians (0: what the device's free memory holds)."""
    drop_invalid: bool = False
    """Drop Gaussians holding NaN or infinite values instead of refusing the file."""

    def view_settings(self) -> ViewSettings:
        return ViewSettings(self.views, self.eval_views, self.fov_degrees, self.min_resolution, self.max_resolution,
                            self.background)


_LOADED: Dict[tuple, Gaussians] = {}


def load_checked_splat(path: Path, config: SplatDataParserConfig, device: Optional[torch.device] = None) -> Gaussians:
    """The splat at ``path``, checked (:func:`~virgi_ns.data.splat_views.check_splat` against ``device``'s
    memory, default a GPU where there is one, and a degenerate extent); the last one read is kept for
    the process (training reads it more than once)."""
    from virgi_ns.io import load_splat

    path = Path(path)
    if str(path) in ("", "."):
        raise InputError("the splat dataparser needs the splat file: ns-train virgi --data FILE splat")
    if not path.exists():
        raise InputError(f"no such file: {path}")
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size, config.drop_invalid, config.max_gaussians)
    g = _LOADED.get(key)
    if g is None:
        g = load_splat(path, drop_invalid=config.drop_invalid)
        check_splat(g, str(path), config.max_gaussians, device)
        place_cameras(g, config.view_settings(), str(path))  # refuses a degenerate extent
        _LOADED.clear()
        _LOADED[key] = g
    return g


class SplatDataParser(DataParser):
    """Cameras and cached images of a splat (see the module doc)."""

    config: SplatDataParserConfig

    def __init__(self, config: SplatDataParserConfig):
        super().__init__(config=config)
        self._views: Optional[tuple] = None

    def _ensure(self) -> tuple:
        if self._views is None:
            path = Path(self.config.data)
            g = load_checked_splat(path, self.config)
            settings = self.config.view_settings()
            with CONSOLE.status(f"[bold green]virgi: rendering the views of {path.name}"):
                folder, rig, train, held = ensure_views(g, settings, str(path), self.config.cache_dir)
            CONSOLE.log(f"virgi: {path.name}: {len(g):,} Gaussians, {len(train)} + {len(held)} views of "
                        f"{rig.resolution}x{rig.resolution} in {folder}")
            self._views = (folder, rig, train, held)
        return self._views

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        folder, rig, train, held = self._ensure()
        if split == "train":
            c2w, files = rig.train_c2w, train
        elif split in ("val", "test"):
            c2w, files = rig.eval_c2w, held
        else:
            raise ValueError(f"Unknown dataparser split {split}")
        res = rig.resolution
        cameras = Cameras(camera_to_worlds=torch.from_numpy(np.ascontiguousarray(c2w)).float(), fx=rig.focal,
                          fy=rig.focal, cx=res / 2.0, cy=res / 2.0, width=res, height=res,
                          camera_type=CameraType.PERSPECTIVE)
        r = rig.far_radius / rig.radius
        scene_box = SceneBox(aabb=torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32))
        return DataparserOutputs(
            image_filenames=list(files),
            cameras=cameras,
            scene_box=scene_box,
            dataparser_transform=torch.from_numpy(rig.transform()).float(),
            dataparser_scale=rig.scale,
            metadata={"virgi_splat": str(Path(self.config.data)), "virgi_splat_views": str(folder),
                      "virgi_splat_rig": rig_summary(rig)},
        )


def rig_summary(rig: Rig) -> dict:
    """The rig's numbers a reader of the run wants (near/far in the run's units)."""
    return {"resolution": rig.resolution, "focal": rig.focal, "distance": rig.distance, "near": rig.near,
            "far": rig.far, "radius": rig.radius, "centre": [float(x) for x in rig.centre]}


def prepare_splat_run(config) -> bool:
    """Make ``config`` (a virgi trainer config) a run on its splat when its dataparser is
    :class:`SplatDataParserConfig` (see the module doc); False otherwise. Idempotent; bad input
    raises :class:`InputError`."""
    pipeline = getattr(config, "pipeline", None)
    dm = getattr(pipeline, "datamanager", None)
    parser = getattr(dm, "dataparser", None)
    if not isinstance(parser, SplatDataParserConfig):
        return False
    data = getattr(dm, "data", None) or parser.data
    if data is None or str(data) in ("", "."):
        raise InputError("the splat dataparser needs the splat file: ns-train virgi --data FILE splat")
    path = Path(data).expanduser().resolve()
    parser.view_settings().check()
    machine = getattr(config, "machine", None)
    on_gpu = getattr(machine, "device_type", "cuda") == "cuda" and torch.cuda.is_available()
    load_checked_splat(path, parser, torch.device("cuda" if on_gpu else "cpu"))
    dm.data = path
    parser.data = path
    model = pipeline.model
    if model.geometry_from is not None and Path(model.geometry_from).expanduser().resolve() != path:
        raise InputError("the splat dataparser imports its file itself; drop --pipeline.model.geometry-from "
                         f"({model.geometry_from})")
    if getattr(model, "base_colours", "auto") == "auto":
        model.base_colours = "file"
    model.geometry_from = path
    model.geometry_frame = "capture"
    model.background_color = parser.background
    if config.max_num_iterations == model.geometry_steps + model.colour_steps:
        config.max_num_iterations = int(parser.steps)
    model.colour_steps = int(config.max_num_iterations)
    return True


splat_dataparser = DataParserSpecification(
    config=SplatDataParserConfig(),
    description="a splat file (.ply, .compressed.ply, .spz) rendered from cameras around it: recolour any splat",
)
