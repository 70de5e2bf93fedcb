"""A trained VIRGi run read from its files without nerfstudio's loader: what ``virgi-edit apply|pick|import``
and ``virgi-export`` need of it.

nerfstudio's own loader (``eval_setup``, or :func:`virgi_ns.nerfstudio.runs.load_run`) imports the
classes a run's ``config.yml`` names (most of nerfstudio), runs the dataparser and builds the whole
model, re-reading an imported splat, before the checkpoint overwrites it all: seconds a command pays
for a handful of tensors. Here instead

- ``config.yml`` is read with a safe YAML loader that takes its python tags as plain mappings; the
  few settings the tools need are picked out (:func:`run_settings`);
- the cameras come from ``virgi_run.json`` (:class:`RunInfo`), which training writes beside
  ``config.yml`` (outside the checkpoint folder, where nerfstudio reads every name as a step): the
  training and evaluation cameras as nerfstudio's loader sees them (after the dataparser's
  transforms), their image files, the capture frame, the scene box and the background;
- the checkpoint is memory-mapped and only the Gaussians, the colour field and the specular gate are
  built from it (:class:`SavedModel`).

A run without ``virgi_run.json`` (saved before it existed), whose ``config.yml`` changed since it was
written, or whose config this module does not recognise, is loaded through nerfstudio
(:func:`virgi_ns.nerfstudio.runs.open_run` decides).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.raster import Cameras

RUN_INFO = "virgi_run.json"
RUN_INFO_FORMAT = "virgi-run-info"
RUN_INFO_VERSION = 1

VIRGI_MODEL_CLASSES = ("virgi_ns.nerfstudio.model.VirgiModelConfig", "virgi_ns.model.VirgiModelConfig")
FIELD_CLASSES = ("virgi_ns.colour.field.ColourFieldConfig", "virgi_ns.colour.field.ColorFieldConfig",
                 "virgi_ns.field.ColorFieldConfig")
RUN_DIR_CLASSES = ("virgi_ns.nerfstudio.pipeline.RunDirConfig",)
"""Trainer configs whose run directory is ``output_dir`` itself."""
SPLAT_PARSER_CLASSES = ("virgi_ns.data.splat.SplatDataParserConfig",)
"""Dataparser configs of runs on a splat file (:mod:`virgi_ns.data.splat`)."""
TRAINER_CLASSES = ("nerfstudio.engine.trainer.TrainerConfig", "virgi_ns.nerfstudio.trainer.VirgiTrainerConfig")
"""Trainer configs with nerfstudio's ``output_dir/experiment/method/timestamp`` layout."""

__all__ = ["RUN_INFO", "FullLoadNeeded", "RunInfo", "RunSettings", "SavedModel", "SavedRun", "Views",
           "config_digest", "load_saved_run", "read_config", "run_settings"]


class FullLoadNeeded(Exception):
    """This module cannot load the run by itself; ``note`` says why (None: say nothing, e.g. a
    config that nerfstudio's loader will judge)."""

    def __init__(self, note: Optional[str] = None) -> None:
        super().__init__(note or "")
        self.note = note


# ------------------------------------------------------------------------------- config.yml
def _config_loader():
    """A YAML loader that builds nothing: ``!!python/object:X`` mappings become dicts with
    ``__class__: X``, paths become :class:`Path`, tuples lists, names and other python tags their
    plain values."""
    import yaml

    class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc, valid-type]
        pass

    def plain(loader, node):
        if isinstance(node, yaml.MappingNode):
            return loader.construct_mapping(node, deep=True)
        if isinstance(node, yaml.SequenceNode):
            return loader.construct_sequence(node, deep=True)
        return loader.construct_scalar(node)

    def obj(loader, suffix, node):
        d = plain(loader, node)
        return {**(d if isinstance(d, dict) else {}), "__class__": suffix}

    def apply(loader, suffix, node):
        args = plain(loader, node)
        if isinstance(args, dict):  # the long form: args, state, ...
            args = args.get("args", [])
        if suffix.startswith("pathlib.") and isinstance(args, list):
            return Path(*map(str, args))
        return {"__class__": suffix, "args": args}

    Loader.add_multi_constructor("tag:yaml.org,2002:python/object:", obj)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/object/apply:", apply)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/object/new:", apply)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/name:", lambda loader, suffix, node: suffix)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/module:", lambda loader, suffix, node: suffix)
    Loader.add_multi_constructor("tag:yaml.org,2002:python/", lambda loader, suffix, node: plain(loader, node))
    return Loader


def read_config(path: Path) -> dict:
    """``config.yml`` as plain data (see :func:`_config_loader`); nothing is imported or built."""
    import yaml

    try:
        doc = yaml.load(Path(path).read_text(), Loader=_config_loader())  # noqa: S506 - builds plain data only
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise InputError(f"{path}: not a nerfstudio config ({type(e).__name__})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: not a nerfstudio config")
    return doc


@dataclass
class RunSettings:
    """What the tools read of a run's ``config.yml``."""

    checkpoint_dir: Path
    """Where nerfstudio looks for ``step-*.ckpt`` (relative paths: to the current directory, as nerfstudio)."""
    method_name: str
    color_field: dict
    """The :class:`~virgi_ns.colour.field.ColourFieldConfig` values."""
    raster_backend: str = "auto"
    gate_threshold: float = 1.0 / 255.0
    specular_gating: bool = True
    base_colours: str = "field"
    """'field' or 'file' (the model's ``base_colours``, 'auto' resolved as the model resolves it)."""
    splat_views: Optional[dict] = None
    """The splat dataparser's settings (plain values) of a run on a splat file: its views can be
    rendered again where their cache is gone (:func:`virgi_ns.data.splat_views.photo_reader`)."""


def run_settings(path: Path) -> RunSettings:
    """The settings of a VIRGi run's ``config.yml``; :class:`FullLoadNeeded` (without a note) when
    it is not one this module recognises (nerfstudio's loader then reads it and says what is wrong)."""
    try:
        doc = read_config(path)
    except InputError:
        raise FullLoadNeeded() from None
    pipeline = doc.get("pipeline")
    model = pipeline.get("model") if isinstance(pipeline, dict) else None
    field_cfg = model.get("color_field") if isinstance(model, dict) else None
    if not isinstance(model, dict) or model.get("__class__") not in VIRGI_MODEL_CLASSES or \
            not isinstance(field_cfg, dict) or field_cfg.get("__class__") not in FIELD_CLASSES:
        raise FullLoadNeeded()
    top = doc.get("__class__")
    rel = doc.get("relative_model_dir", Path("nerfstudio_models"))
    if top in RUN_DIR_CLASSES:
        base = Path(str(doc.get("output_dir")))
    elif top in TRAINER_CLASSES:  # nerfstudio's ExperimentConfig.get_base_dir
        parts = (doc.get(k) for k in ("output_dir", "experiment_name", "method_name", "timestamp"))
        base = Path("/".join(map(str, parts)))
    else:
        raise FullLoadNeeded()
    dm = pipeline.get("datamanager") if isinstance(pipeline, dict) else None
    parser = dm.get("dataparser") if isinstance(dm, dict) else None
    splat = parser if isinstance(parser, dict) and parser.get("__class__") in SPLAT_PARSER_CLASSES else None
    base_colours = str(model.get("base_colours", "field"))
    if base_colours == "auto":  # (a run saved before the model resolved it) the splat dataparser's runs: 'file'
        base_colours = "file" if splat is not None else "field"
    try:
        return RunSettings(base / Path(str(rel)), str(doc.get("method_name")),
                           {k: v for k, v in field_cfg.items() if k != "__class__"},
                           str(model.get("raster_backend", "auto")), float(model.get("gate_threshold", 1.0 / 255.0)),
                           bool(model.get("specular_gating", True)), base_colours, splat)
    except (TypeError, ValueError):
        raise FullLoadNeeded() from None


def config_digest(path: Path) -> str:
    """sha256 of ``config.yml``'s bytes: :class:`RunInfo` records it, so a config edited since
    (its data moved, say) sends the tools back to nerfstudio's loader."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def newest_checkpoint(ckpt_dir: Path) -> Optional[Path]:
    """The highest ``step-NNN.ckpt`` in ``ckpt_dir`` (None if there is none)."""
    steps = []
    for p in Path(ckpt_dir).glob("step-*.ckpt"):
        s = p.stem.split("-")[1]
        if s.isdigit():
            steps.append((int(s), p))
    return max(steps)[1] if steps else None


# ---------------------------------------------------------------------------------- cameras
@dataclass
class Views:
    """The cameras of one split as nerfstudio's loader sees them: OpenGL camera-to-world ``c2w``
    [V,3,4] and intrinsics ``K`` [V,3,3] (float32, the dataparser's frame), image sizes, the image
    files and the dataset's ``scale_factor`` (the photos are read at it)."""

    c2w: Tensor
    K: Tensor
    widths: Tensor
    heights: Tensor
    filenames: list[str]
    scale_factor: float = 1.0
    read_photo: Optional[Callable[[int], np.ndarray]] = None
    """Reads photo ``i`` (default: :meth:`photo`'s own reading, nerfstudio's ``get_numpy_image``)."""

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def cameras(self) -> Cameras:
        """All views as rasterizer cameras (what ``raster_cameras`` makes of the dataset's)."""
        from virgi_ns.nerfstudio.cameras import viewmats_from_c2w

        return Cameras(self.K, viewmats_from_c2w(self.c2w), self.widths, self.heights)

    def camera(self, i: int) -> Cameras:
        """View ``i`` alone (computed on its own, as ``raster_cameras(cameras[i:i+1])``)."""
        from virgi_ns.nerfstudio.cameras import viewmats_from_c2w

        return Cameras(self.K[i : i + 1], viewmats_from_c2w(self.c2w[i : i + 1]), self.widths[i : i + 1],
                       self.heights[i : i + 1])

    def find(self, name: str) -> Optional[int]:
        """Index of the image called ``name`` (file name, stem or path), or None."""
        for i, fn in enumerate(self.filenames):
            p = Path(fn)
            if name in (p.name, p.stem, str(p)):
                return i
        return None

    def photo(self, i: int) -> np.ndarray:
        """Photo ``i`` as uint8 [H,W,3 or 4], read as nerfstudio's dataset reads it (resized by
        ``scale_factor``, grey repeated to three channels)."""
        if self.read_photo is not None:
            return self.read_photo(i)
        from PIL import Image

        path = self.filenames[i]
        try:
            with Image.open(path) as im:
                if self.scale_factor != 1.0:
                    w, h = im.size
                    im = im.resize((int(w * self.scale_factor), int(h * self.scale_factor)),
                                   resample=Image.Resampling.BILINEAR)
                image = np.array(im, dtype="uint8")
        except OSError as e:
            raise InputError(f"cannot read the photo {path} ({type(e).__name__})") from None
        if image.ndim == 2:
            image = image[:, :, None].repeat(3, axis=2)
        if image.ndim != 3 or image.shape[2] not in (3, 4):
            raise InputError(f"the photo {path} is not an RGB image (shape {image.shape})")
        return image

    def to_json(self) -> dict:
        return {"filenames": list(self.filenames), "scale_factor": float(self.scale_factor),
                "width": [int(w) for w in self.widths], "height": [int(h) for h in self.heights],
                "c2w": self.c2w.reshape(-1, 12).tolist(), "K": self.K.reshape(-1, 9).tolist()}

    @staticmethod
    def from_json(d: dict) -> "Views":
        n = len(d["filenames"])
        c2w = torch.tensor(d["c2w"], dtype=torch.float64).reshape(n, 3, 4).float()
        K = torch.tensor(d["K"], dtype=torch.float64).reshape(n, 3, 3).float()
        return Views(c2w, K, torch.tensor(d["width"], dtype=torch.long).reshape(n),
                     torch.tensor(d["height"], dtype=torch.long).reshape(n), [str(f) for f in d["filenames"]],
                     float(d.get("scale_factor", 1.0)))


# ----------------------------------------------------------------------------- the sidecar
@dataclass
class RunInfo:
    """``virgi_run.json`` beside a run's ``config.yml``: what the tools need of the data, as
    nerfstudio's loader of the run would see it. Floats are stored as JSON numbers (float32
    values are exact in them)."""

    train: Views
    eval: Optional[Views]
    background: Tensor
    """The model's background colour [3]."""
    scene_box: Tensor
    """The dataparser's scene box [2,3]."""
    capture_transform: Tensor
    """``x_run = capture_scale (R x_capture + t)``: ``[R|t]`` [3,4] (float64)."""
    capture_scale: float
    config_sha256: Optional[str] = None
    """:func:`config_digest` of the ``config.yml`` it was written with."""

    def to_json(self) -> dict:
        return {"format": RUN_INFO_FORMAT, "version": RUN_INFO_VERSION, "config_sha256": self.config_sha256,
                "background": [float(x) for x in self.background.reshape(3)],
                "scene_box": self.scene_box.reshape(2, 3).tolist(),
                "capture_transform": self.capture_transform.double().reshape(3, 4).tolist(),
                "capture_scale": float(self.capture_scale),
                "train": self.train.to_json(), "eval": self.eval.to_json() if self.eval is not None else None}

    @staticmethod
    def from_json(d: dict) -> "RunInfo":
        if not isinstance(d, dict) or d.get("format") != RUN_INFO_FORMAT:
            raise ValueError("not a virgi run info file")
        if int(d.get("version", -1)) > RUN_INFO_VERSION:
            raise ValueError(f"written by a newer virgi-ns (version {d.get('version')})")
        return RunInfo(Views.from_json(d["train"]), Views.from_json(d["eval"]) if d.get("eval") else None,
                       torch.tensor(d["background"], dtype=torch.float32).reshape(3),
                       torch.tensor(d["scene_box"], dtype=torch.float32).reshape(2, 3),
                       torch.tensor(d["capture_transform"], dtype=torch.float64).reshape(3, 4),
                       float(d["capture_scale"]), d.get("config_sha256"))

    def write(self, run_dir: Path) -> Path:
        """Write ``run_dir/virgi_run.json`` atomically (``run_dir``: the folder of ``config.yml``; never
        the checkpoint folder, where nerfstudio reads every name as ``step-N.ckpt``)."""
        path = Path(run_dir) / RUN_INFO
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(self.to_json()))
        return path

    @staticmethod
    def read(run_dir: Path, ckpt_dir: Optional[Path] = None) -> "RunInfo":
        """Read ``run_dir/virgi_run.json``; :class:`FullLoadNeeded` with a note when it is missing
        or unreadable. One that earlier versions wrote into ``ckpt_dir`` (where it stops nerfstudio's
        ``ns-viewer``, ``ns-eval`` and ``ns-render`` from finding the checkpoint) is moved beside
        ``config.yml`` first, where the folder allows."""
        path = Path(run_dir) / RUN_INFO
        legacy = None if ckpt_dir is None else Path(ckpt_dir) / RUN_INFO
        if not path.is_file() and legacy is not None and legacy.is_file():
            try:
                os.replace(legacy, path)
            except OSError:  # a read-only run: read it where it is
                path = legacy
        if not path.is_file():
            raise FullLoadNeeded(f"no {path.name} beside {Path(run_dir) / 'config.yml'} (a run saved before it existed)")
        try:
            return RunInfo.from_json(json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError, RuntimeError) as e:
            raise FullLoadNeeded(f"{path} is unreadable ({type(e).__name__}: {e})") from None


# -------------------------------------------------------------------------------- the model
def _load_state(path: Path) -> dict:
    """The checkpoint's pipeline state, memory-mapped (tensors nobody reads, the optimizers'
    moments, are never read from disk); safe unpickling with the numpy globals nerfstudio's
    checkpoints hold."""
    import virgi_ns.nerfstudio.compat  # noqa: F401  (the allow-list; imports no nerfstudio)

    try:
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as e:  # a file in torch's legacy format cannot be mapped
            if "mmap" not in str(e):
                raise
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable checkpoint is the same user error
        raise InputError(f"{path}: cannot read the checkpoint ({type(e).__name__})") from None
    state = ckpt.get("pipeline") if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        raise InputError(f"{path}: not a nerfstudio checkpoint (no pipeline state)")
    return state


def model_state(pipeline_state: dict) -> dict:
    """The model's part of a pipeline state dict, as nerfstudio's ``VanillaPipeline`` takes it out
    (``module.`` prefixes of DDP dropped)."""
    state = {(k[len("module."):] if k.startswith("module.") else k): v for k, v in pipeline_state.items()}
    model = {k[len("_model."):]: v for k, v in state.items() if k.startswith("_model.")}
    if model and all(k.startswith("module.") for k in model):
        model = {k[len("module."):]: v for k, v in model.items()}
    return model


GAUSS_PARAMS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")


class SavedModel:
    """The parts of a trained :class:`~virgi_ns.nerfstudio.model.VirgiModel` the tools read: its
    Gaussians (``means``, log ``scales``, ``quats``, logit ``opacities``), colour ``field``,
    ``background_color``, specular gate, settings (``config``) and capture frame (``kwargs``'s
    metadata, as the datamanager records it), with the model's :meth:`fingerprint`. Everything
    :class:`~virgi_ns.edit.scene.FrozenScene`, :func:`~virgi_ns.nerfstudio.export.bake` and the
    edit tools use of a model."""

    def __init__(self, gauss_params: dict[str, Tensor], field, background_color: Tensor, spec_magnitude: Tensor,
                 diffuse_cache: Tensor, config: SimpleNamespace, capture_transform: Tensor, capture_scale: float):
        self.gauss_params = gauss_params
        self.field = field
        self.background_color = background_color
        self.spec_magnitude = spec_magnitude
        self.diffuse_cache = diffuse_cache
        self.config = config
        self.kwargs = {"metadata": {"virgi_capture_transform": capture_transform,
                                    "virgi_capture_scale": float(capture_scale)}}

    means = property(lambda self: self.gauss_params["means"])
    scales = property(lambda self: self.gauss_params["scales"])
    quats = property(lambda self: self.gauss_params["quats"])
    opacities = property(lambda self: self.gauss_params["opacities"])
    features_dc = property(lambda self: self.gauss_params["features_dc"])
    features_rest = property(lambda self: self.gauss_params["features_rest"])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def num_points(self) -> int:
        return int(self.means.shape[0])

    def gate_ready(self) -> bool:
        return self.spec_magnitude.numel() == self.num_points and self.diffuse_cache.shape[0] == self.num_points

    def file_colours(self):
        """The Gaussians' own colours when the run shows them (``base_colours="file"``; their SH
        coefficients are in the capture's frame), else None (see :mod:`virgi_ns.colour.file_colours`)."""
        if getattr(self.config, "base_colours", "field") != "file":
            return None
        if getattr(self, "_file_colours", None) is None:
            from virgi_ns.colour.file_colours import FileColours

            T = torch.as_tensor(self.kwargs["metadata"]["virgi_capture_transform"], dtype=torch.float64)
            self._file_colours = FileColours(self.features_dc, self.features_rest, T[:3, :3].float().to(self.device))
        return self._file_colours

    @property
    def spec_gate(self) -> Tensor:
        return self.spec_magnitude > self.config.gate_threshold

    def fingerprint(self) -> str:
        """The base run's fingerprint that every edit of it carries (as the model computes it)."""
        from virgi_ns.fingerprint import field_fingerprint

        return field_fingerprint(self.means.detach(), self.field,
                                 [self.quats.detach(), torch.exp(self.scales.detach()),
                                  torch.sigmoid(self.opacities.detach()).reshape(-1)])

    @staticmethod
    def from_state(state: dict, settings: RunSettings, info: RunInfo, device: torch.device,
                   where: str = "checkpoint") -> "SavedModel":
        """Build from a model state dict (:func:`model_state`) on ``device``."""
        from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField

        try:
            gauss = {p: state[f"gauss_params.{p}"].to(device, torch.float32) for p in GAUSS_PARAMS}
            known = {f.name for f in fields(ColourFieldConfig)}
            cfg = ColourFieldConfig(**{k: v for k, v in settings.color_field.items() if k in known})
            field_state = {k[len("field."):]: v for k, v in state.items() if k.startswith("field.")}
            field = DecoupledColourField(cfg, field_state["aabb"], empty=True)
            field.load_state_dict(field_state)
            field.to(device).eval()
            spec = state.get("spec_magnitude", torch.zeros(0)).to(device)
            cache = state.get("diffuse_cache", torch.zeros(0, 3)).to(device)
        except (KeyError, RuntimeError, ValueError, TypeError) as e:
            raise InputError(f"{where}: not a checkpoint of this virgi run ({type(e).__name__}: "
                             f"{str(e).splitlines()[0][:200] if str(e) else ''})") from None
        config = SimpleNamespace(raster_backend=settings.raster_backend, gate_threshold=settings.gate_threshold,
                                 specular_gating=settings.specular_gating, color_field=cfg,
                                 base_colours=settings.base_colours)
        return SavedModel(gauss, field, info.background.to(device), spec, cache, config,
                          info.capture_transform, info.capture_scale)


@dataclass
class SavedRun:
    """A run loaded by :func:`load_saved_run`."""

    config_path: Path
    checkpoint: Path
    settings: RunSettings
    info: RunInfo
    model: SavedModel


def load_saved_run(config_path: Path, device: Optional[torch.device] = None) -> SavedRun:
    """Load a VIRGi run from its files (see the module doc). A run this cannot load raises
    :class:`FullLoadNeeded`; a missing checkpoint or a damaged one :class:`InputError`."""
    config_path = Path(config_path)
    settings = run_settings(config_path)
    ckpt_dir = settings.checkpoint_dir
    ckpt = newest_checkpoint(ckpt_dir) if ckpt_dir.is_dir() else None
    if ckpt is None:
        raise InputError(f"{config_path}: no checkpoint (step-*.ckpt) in {ckpt_dir} (nerfstudio looks where the "
                         "run was trained, relative to the current directory)")
    info = RunInfo.read(config_path.parent, ckpt_dir)
    if info.config_sha256 is not None and info.config_sha256 != config_digest(config_path):
        raise FullLoadNeeded(f"{config_path.name} changed since {RUN_INFO} was written")
    if device is None:
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model = SavedModel.from_state(model_state(_load_state(ckpt)), settings, info, device, str(ckpt))
    if settings.splat_views is not None:  # views rendered from the splat: rendered again if their cache is gone
        from virgi_ns.data.splat_views import photo_reader

        for views in (info.train, info.eval):
            if views is not None:
                views.read_photo = photo_reader(views, settings.splat_views)
    if not math.isfinite(info.capture_scale) or info.capture_scale <= 0:
        raise FullLoadNeeded(f"{RUN_INFO}: capture scale {info.capture_scale} is not a positive number")
    return SavedRun(config_path, ckpt, settings, info, model)
