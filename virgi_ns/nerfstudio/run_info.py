"""Writing ``virgi_run.json`` (:class:`virgi_ns.nerfstudio.saved_run.RunInfo`) beside a run's ``config.yml``.

The file records the cameras as nerfstudio's loader of the run sees them: a datamanager set up for
inference (``test_mode="inference"``: no image is read, the dataparser runs at downscale 1, the
evaluation split is ``test``), which is what :func:`virgi_ns.nerfstudio.runs.load_run` builds. Training
builds one such datamanager once from its config (:func:`training_run_info`) and writes the file at
every checkpoint (nerfstudio's ``save_only_latest_checkpoint`` clears the folder); a command that had
to load a run through nerfstudio writes it from the pipeline it loaded (:func:`run_info_of`).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Optional

import torch

from virgi_ns.nerfstudio.saved_run import RunInfo, Views, config_digest

__all__ = ["run_info_of", "training_run_info", "views_of", "write_run_info"]


def views_of(dataset) -> Optional[Views]:
    """The cameras and image files of a nerfstudio dataset (None for a missing or empty one)."""
    if dataset is None or len(dataset) == 0:
        return None
    cams = dataset.cameras.flatten() if len(dataset.cameras.shape) != 1 else dataset.cameras
    c2w = cams.camera_to_worlds.float()
    K = cams.get_intrinsics_matrices().float().to(c2w.device)
    return Views(c2w.detach().cpu().clone(), K.detach().cpu().clone(), cams.width.reshape(-1).cpu().long(),
                 cams.height.reshape(-1).cpu().long(), [str(f) for f in dataset.image_filenames],
                 float(getattr(dataset, "scale_factor", 1.0)))


def run_info_of(datamanager, model, config_path: Optional[Path] = None) -> RunInfo:
    """The run info of an inference-mode ``datamanager`` and its ``model`` (for the background);
    ``config_path``: the ``config.yml`` it belongs to (its digest is recorded)."""
    train = views_of(datamanager.train_dataset)
    if train is None:
        raise ValueError("the run has no training views")
    meta = getattr(datamanager.train_dataset, "metadata", None) or {}
    outs = datamanager.train_dataparser_outputs
    T = meta.get("virgi_capture_transform")
    if T is not None:
        T, s = torch.as_tensor(T, dtype=torch.float64)[:3, :4], float(meta.get("virgi_capture_scale", 1.0))
    else:
        T, s = torch.as_tensor(outs.dataparser_transform, dtype=torch.float64)[:3, :4], float(outs.dataparser_scale)
    digest = config_digest(config_path) if config_path is not None and Path(config_path).is_file() else None
    return RunInfo(train, views_of(getattr(datamanager, "eval_dataset", None)),
                   torch.as_tensor(model.background_color, dtype=torch.float32).detach().cpu().reshape(3),
                   outs.scene_box.aabb.detach().float().cpu().reshape(2, 3), T.clone(), s, digest)


def training_run_info(trainer_config, model) -> RunInfo:
    """The run info of a run being trained with ``trainer_config``: an inference-mode datamanager
    set up from (a copy of) its datamanager config, as the run's loader will."""
    dm_config = copy.deepcopy(trainer_config.pipeline.datamanager)
    dm = dm_config.setup(device="cpu", test_mode="inference")
    config_path = Path(trainer_config.get_base_dir()) / "config.yml"
    return run_info_of(dm, model, config_path)


def write_run_info(info: RunInfo, config_path: Path) -> Path:
    """Write ``info`` beside the run's ``config_path`` (not into the checkpoint folder, whose every
    name nerfstudio reads as a step); its digest is (re)taken now, after ``config.yml`` was written."""
    if Path(config_path).is_file():
        info.config_sha256 = config_digest(config_path)
    return info.write(Path(config_path).parent)
