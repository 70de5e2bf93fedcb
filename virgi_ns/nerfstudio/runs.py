"""A trained run opened for the tools: from its files when it can be, else through nerfstudio.

- :func:`open_run`: the run of a ``config.yml`` as an :class:`OpenRun` (the model, the training and
  evaluation views, the capture frame). It reads the run from its files
  (:mod:`virgi_ns.nerfstudio.saved_run`: no nerfstudio import, no dataparser, only the model's tensors
  built); a run that cannot be read so (no ``virgi_run.json`` beside its ``config.yml``, a config it
  does not recognise) goes through :func:`load_run` with a one-line note and gets its
  ``virgi_run.json`` written then, so the next command is fast.
- :func:`load_run`: nerfstudio's loader (``eval_setup`` without importing every method nerfstudio
  knows), for callers that want the whole pipeline.
- :meth:`OpenRun.from_pipeline`: a pipeline already loaded (the Python API, tests, benchmarks) in the
  same interface.

Bad input raises :class:`~virgi_ns.errors.InputError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from virgi_ns.errors import InputError

__all__ = ["OpenRun", "load_run", "open_run"]


@dataclass
class OpenRun:
    """``model`` (a VirgiModel or a :class:`~virgi_ns.nerfstudio.saved_run.SavedModel`), the training and
    evaluation :class:`~virgi_ns.nerfstudio.saved_run.Views`, the capture frame, and the nerfstudio
    ``pipeline`` when the run was loaded through it."""

    model: Any
    train: Any
    eval: Optional[Any]
    frame: Any
    pipeline: Any = None

    @staticmethod
    def from_pipeline(pipeline) -> "OpenRun":
        from virgi_ns.nerfstudio.frames import CaptureFrame
        from virgi_ns.nerfstudio.run_info import views_of

        dm = pipeline.datamanager
        views = []
        for ds in (getattr(dm, "train_dataset", None), getattr(dm, "eval_dataset", None)):
            v = views_of(ds)
            if v is not None:
                v.read_photo = ds.get_numpy_image  # the dataset's own reading
            views.append(v)
        return OpenRun(pipeline.model, views[0], views[1], CaptureFrame.from_pipeline(pipeline), pipeline)

    def splits(self) -> list:
        return [v for v in (self.train, self.eval) if v is not None]

    def find_image(self, name: str):
        """(views, index) of the training (or evaluation) image called ``name``, or None."""
        for views in self.splits():
            i = views.find(name)
            if i is not None:
                return views, i
        return None


def open_run(config_path: Path, console=None) -> OpenRun:
    """The run of ``config_path``: from its files when it can be, else through nerfstudio (see the
    module doc); ``console`` (rich) prints the note when it falls back."""
    from virgi_ns.nerfstudio.saved_run import FullLoadNeeded, load_saved_run

    config_path = Path(config_path)
    if not config_path.is_file():
        raise InputError(f"no such config: {config_path}")
    try:
        run = load_saved_run(config_path)
    except FullLoadNeeded as why:
        if why.note and console is not None:
            console.print(f"note: {why.note}; loading the run through nerfstudio (slower) and writing it for the "
                          "next command", soft_wrap=True)
        return _open_through_nerfstudio(config_path)
    from virgi_ns.nerfstudio.frames import CaptureFrame

    info = run.info
    return OpenRun(run.model, info.train, info.eval, CaptureFrame(info.capture_transform, info.capture_scale))


def _open_through_nerfstudio(config_path: Path) -> OpenRun:
    """nerfstudio's loader; then ``virgi_run.json`` is written beside ``config.yml`` (when it can
    be: a read-only run stays as it is)."""
    from virgi_ns.nerfstudio.saved_run import newest_checkpoint, run_settings

    _, pipeline = load_run(config_path)
    run = OpenRun.from_pipeline(pipeline)
    try:
        from virgi_ns.nerfstudio.run_info import run_info_of, write_run_info

        ckpt_dir = run_settings(config_path).checkpoint_dir
        if newest_checkpoint(ckpt_dir) is not None:
            write_run_info(run_info_of(pipeline.datamanager, pipeline.model), config_path)
    except Exception:  # noqa: BLE001 - a config this loader does not read, a read-only folder: no file, no harm
        pass
    return run


def load_run(config_path: Path):
    """``(config, pipeline)``: ``eval_setup`` of a VIRGi run, with its problems as :class:`InputError`."""
    import yaml

    from virgi_ns.nerfstudio.model import VirgiModel, VirgiModelConfig

    config_path = Path(config_path)
    if not config_path.is_file():
        raise InputError(f"no such config: {config_path}")
    try:
        cfg = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as e:  # noqa: BLE001 - any unreadable config is the same user error
        raise InputError(f"{config_path}: not a nerfstudio config ({type(e).__name__})") from None
    model_cfg = getattr(getattr(cfg, "pipeline", None), "model", None)
    if not isinstance(model_cfg, VirgiModelConfig):
        raise InputError(f"{config_path}: not a virgi run (method {getattr(cfg, 'method_name', '?')})")
    ckpt_dir = cfg.get_checkpoint_dir()
    if not ckpt_dir.is_dir() or not any(ckpt_dir.glob("step-*.ckpt")):
        raise InputError(f"{config_path}: no checkpoint (step-*.ckpt) in {ckpt_dir} (nerfstudio looks where the "
                         "run was trained, relative to the current directory)")
    pipeline = _setup_inference(cfg, ckpt_dir)
    if not isinstance(pipeline.model, VirgiModel):
        raise InputError(f"{config_path}: not a virgi run")
    return cfg, pipeline


def _setup_inference(cfg, ckpt_dir: Path):
    """The pipeline of ``cfg`` with its latest checkpoint, built for inference (no training images
    are read). What nerfstudio's ``eval_setup`` does, without importing every method nerfstudio
    knows, which a fresh process would otherwise pay for on every command."""
    import torch

    from virgi_ns.nerfstudio import compat

    compat.apply()  # checkpoints load with torch's safe unpickling (idempotent; other code may have narrowed it)

    steps = sorted(int(p.stem.split("-")[1]) for p in ckpt_dir.glob("step-*.ckpt") if p.stem.split("-")[1].isdigit())
    if not steps:
        raise InputError(f"no checkpoint (step-*.ckpt) in {ckpt_dir}")
    cfg.load_dir = ckpt_dir
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    pipeline = cfg.pipeline.setup(device=device, test_mode="inference")
    pipeline.eval()
    state = torch.load(ckpt_dir / f"step-{steps[-1]:09d}.ckpt", map_location="cpu")
    pipeline.load_pipeline(state["pipeline"], state["step"])
    return pipeline
