"""Image metrics that never touch the network: PSNR, SSIM and (when its weights are cached) LPIPS.

PSNR comes from torchmetrics and SSIM from pytorch_msssim, as in nerfstudio's models. LPIPS uses
torchmetrics' AlexNet variant, whose backbone weights torchvision would download on construction;
:func:`make_lpips` builds it only when those weights already sit in the torch hub cache, and with
downloads blocked while it builds, so an offline machine reports LPIPS as NaN after one warning.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from pathlib import Path
from typing import Callable, Dict, Iterator, Optional
from urllib.parse import urlparse

import torch
from jaxtyping import Float
from torch import Tensor

LpipsFn = Callable[[Tensor, Tensor], Tensor]

_warned = False
_UNSET = object()
_cached_lpips: object = _UNSET


def alexnet_weights_path() -> Path:
    """Where torchvision keeps (or would download) the AlexNet weights LPIPS needs."""
    from torchvision.models import AlexNet_Weights

    filename = os.path.basename(urlparse(AlexNet_Weights.DEFAULT.url).path)
    return Path(torch.hub.get_dir()) / "checkpoints" / filename


class DownloadBlocked(RuntimeError):
    """Raised if anything tries to download while LPIPS is being built."""


@contextlib.contextmanager
def _no_downloads() -> Iterator[None]:
    """Make torch hub downloads raise instead of reaching the network."""

    def refuse(url: str, *args, **kwargs) -> None:
        raise DownloadBlocked(f"download of {url} blocked")

    original = torch.hub.download_url_to_file
    torch.hub.download_url_to_file = refuse
    try:
        yield
    finally:
        torch.hub.download_url_to_file = original


def _warn_once(message: str) -> None:
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def make_lpips() -> Optional[LpipsFn]:
    """LPIPS (AlexNet, inputs in [0, 1], [B,3,H,W]) if its weights are cached, else None (warns once)."""
    path = alexnet_weights_path()
    if not path.is_file():
        _warn_once(f"LPIPS unavailable: AlexNet weights not cached at {path}; LPIPS is reported as NaN")
        return None
    try:
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        with _no_downloads():
            module = LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)
    except Exception as err:  # a corrupt cache file or a blocked download: no LPIPS, no crash
        _warn_once(f"LPIPS unavailable ({type(err).__name__}: {err}); LPIPS is reported as NaN")
        return None
    module.eval()

    def lpips(pred: Tensor, gt: Tensor) -> Tensor:
        module.to(pred.device)
        with torch.no_grad():
            return module(pred.clamp(0, 1), gt.clamp(0, 1))

    return lpips


def _default_lpips() -> Optional[LpipsFn]:
    global _cached_lpips
    if _cached_lpips is _UNSET:
        _cached_lpips = make_lpips()
    return _cached_lpips  # type: ignore[return-value]


def _as_bchw(image: Tensor) -> Tensor:
    """[H,W,3] (nerfstudio's image layout) or [B,3,H,W] -> [B,3,H,W]."""
    if image.ndim == 3 and image.shape[-1] == 3:
        return image.permute(2, 0, 1)[None]
    if image.ndim == 4 and image.shape[1] == 3:
        return image
    raise ValueError(f"expected an [H,W,3] or [B,3,H,W] image, got shape {tuple(image.shape)}")


def image_metrics(
    pred: Float[Tensor, "..."], gt: Float[Tensor, "..."], lpips: object = "auto"
) -> Dict[str, float]:
    """PSNR, SSIM and LPIPS of ``pred`` against ``gt`` (values in [0, 1]); LPIPS is NaN when unavailable.

    ``lpips``: "auto" (built once per process with :func:`make_lpips`), a callable, or None.
    """
    from pytorch_msssim import ssim
    from torchmetrics.functional.image import peak_signal_noise_ratio

    p, g = _as_bchw(pred.float()), _as_bchw(gt.float())
    if p.shape != g.shape:
        raise ValueError(f"image shapes differ: {tuple(p.shape)} vs {tuple(g.shape)}")
    fn = _default_lpips() if lpips == "auto" else lpips
    with torch.no_grad():
        out = {
            "psnr": float(peak_signal_noise_ratio(p, g, data_range=1.0)),
            "ssim": float(ssim(p, g, data_range=1.0, size_average=True)),
            "lpips": float(fn(p, g)) if callable(fn) else math.nan,
        }
    return out


def offline_splatfacto_lpips() -> None:
    """Let nerfstudio's splatfacto be built offline: it constructs torchmetrics' LPIPS, which
    downloads AlexNet. When the weights are not cached, swap that class for a stand-in that returns
    NaN (before splatfacto is built). For benchmarks that train splatfacto as a baseline and score
    every row with :func:`image_metrics`; our own model never builds torchmetrics' LPIPS."""
    if make_lpips() is not None:
        return
    import torchmetrics.image.lpip as lp

    class _NoLpips(torch.nn.Module):
        def __init__(self, *a, **k) -> None:
            super().__init__()

        def forward(self, a, b):
            return torch.tensor(float("nan"))

    lp.LearnedPerceptualImagePatchSimilarity = _NoLpips  # type: ignore[misc]
