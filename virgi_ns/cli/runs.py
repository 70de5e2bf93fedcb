"""A trained run as the command-line tools use it, loaded the fast way when it can be.

:func:`open_run` loads a run from its files (:mod:`virgi_ns.nerfstudio.saved_run`: no nerfstudio import, no
dataparser, only the model's tensors built); a run that cannot be loaded so (no ``virgi_run.json``
beside its ``config.yml``, a config it does not recognise) goes through nerfstudio's loader
(:func:`virgi_ns.cli.export.load_run`) with a one-line note, and gets its ``virgi_run.json`` written
then, so the next command is fast. :meth:`OpenRun.from_pipeline` wraps a pipeline already loaded
(the Python API, tests, benchmarks) in the same interface.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from virgi_ns.errors import InputError

__all__ = ["OpenRun", "open_run"]


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
    module doc). Bad input raises :class:`InputError`."""
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
    from virgi_ns.cli.export import load_run
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
