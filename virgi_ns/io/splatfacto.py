"""The Gaussians of a nerfstudio splatfacto run: from its ``step-*.ckpt`` or its ``config.yml``.

A splatfacto checkpoint is a torch pickle ``{"step", "pipeline": state_dict, ...}`` whose
pipeline state holds ``_model.gauss_params.{means, scales, quats, features_dc, features_rest,
opacities}`` (older checkpoints: ``_model.{means, ...}``). The conventions are already ours:
log scales, wxyz quaternions, logit opacities, ``features_dc`` = SH band 0, except for runs with
``sh_degree`` 0 (no ``features_rest`` bands): splatfacto then stores the colour's logit in
``features_dc`` (its colour is ``sigmoid(features_dc)``), which is converted to band 0 here.
"""

from __future__ import annotations

import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians

PARAMS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")


def _safe_load(path: Path) -> dict:
    """``torch.load`` with safe unpickling; allows only the numpy scalar types checkpoints may hold."""
    allowed = [np.dtype, np.ndarray]
    try:
        allowed += [np._core.multiarray.scalar, np._core.multiarray._reconstruct]  # numpy >= 2
    except AttributeError:  # pragma: no cover - numpy 1.x
        allowed += [np.core.multiarray.scalar, np.core.multiarray._reconstruct]
    allowed += [type(np.dtype(t)) for t in ("f4", "f8", "i4", "i8", "u1", "bool")]
    # torch's context removes its globals on exit: pass only those not allowed already, or it would
    # take back what other code (our checkpoint compat) allowed for good
    before = torch.serialization.get_safe_globals()
    allowed = [g for g in allowed if g not in before]
    try:
        with torch.serialization.safe_globals(allowed):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError,
            AttributeError, KeyError, IndexError, TypeError, UnicodeDecodeError) as e:
        text = re.sub(r"\x1b\[[0-9;]*m", "", str(e))
        glob = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        if glob:
            msg = f"it holds a {glob.group(1)} object, which safe loading refuses"
        else:
            msg = text.strip().splitlines()[0][:200] if text.strip() else type(e).__name__
        raise InputError(f"{path}: cannot read the checkpoint ({msg})") from None
    if not isinstance(obj, dict):
        raise InputError(f"{path}: checkpoint does not hold a dictionary")
    return obj


def gaussians_from_state(state: dict, where: str = "checkpoint") -> Gaussians:
    """Pick the Gaussian parameters out of a pipeline (or model) state dict."""
    found: dict[str, torch.Tensor] = {}
    for key, val in state.items():
        for p in PARAMS:
            k = str(key)
            if (k == f"gauss_params.{p}" or k.endswith(f".gauss_params.{p}") or k.endswith(f"_model.{p}")) \
                    and isinstance(val, torch.Tensor):
                found.setdefault(p, val)
    missing = [p for p in PARAMS if p not in found]
    if missing:
        raise InputError(f"{where}: not a splatfacto checkpoint (no Gaussian parameters {', '.join(missing)})")
    f = {k: v.detach().to("cpu", torch.float32) for k, v in found.items()}
    n = f["means"].shape[0]
    try:
        rest = f["features_rest"].reshape(n, -1, 3)
        dc = f["features_dc"].reshape(n, 1, 3)
        virgi = any(str(k).endswith("frozen") or ".field.hash." in str(k) for k in state)
        if rest.shape[1] == 0 and not virgi:  # sh_degree 0: splatfacto's colour is sigmoid(features_dc)
            dc = (torch.sigmoid(dc) - 0.5) / SH_C0
        sh = torch.cat([dc, rest], dim=1)
        return Gaussians(f["means"], f["scales"], f["quats"], f["opacities"].reshape(n), sh.contiguous())
    except (ValueError, RuntimeError) as e:
        raise InputError(f"{where}: Gaussian parameters have inconsistent shapes ({e})") from None


def load_checkpoint(path: Path) -> Gaussians:
    obj = _safe_load(path)
    state = obj.get("pipeline", obj)
    if not isinstance(state, dict):
        raise InputError(f"{path}: checkpoint's 'pipeline' entry is not a state dict")
    return gaussians_from_state(state, str(path))


def newest_checkpoint(config_path: Path) -> Path:
    """The highest-step ``step-*.ckpt`` beside a run's ``config.yml`` (in its model directory)."""
    run = config_path.parent
    rel = "nerfstudio_models"
    try:
        m = re.search(r"relative_model_dir:.*?\n- (\S+)", config_path.read_text(errors="replace"))
        if m:
            rel = m.group(1)
    except OSError as e:
        raise InputError(f"{config_path}: cannot read ({e.strerror})") from None
    candidates = sorted((run / rel).glob("step-*.ckpt")) or sorted((run / "nerfstudio_models").glob("step-*.ckpt"))
    if not candidates:
        raise InputError(f"{config_path}: no step-*.ckpt checkpoint in {run / rel}")

    def step(p: Path) -> int:
        digits = re.sub(r"\D", "", p.stem)
        return int(digits) if digits else -1

    return max(candidates, key=step)


def load_run(config_path: Path) -> Gaussians:
    return load_checkpoint(newest_checkpoint(config_path))
