"""Offline image metrics (virgi_ns.metrics)."""

from __future__ import annotations

import math
import socket
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from virgi_ns import metrics


@pytest.fixture
def offline_hub(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty torch hub cache, no network, and a fresh warn-once state."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None, raising=False)

    def no_network(*args, **kwargs):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    monkeypatch.setattr(metrics, "_warned", False)
    monkeypatch.setattr(metrics, "_cached_lpips", metrics._UNSET)
    return tmp_path / "torch_home" / "hub"


def _images(seed: int = 0, size: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(size, size, 3, generator=g)
    pred = (gt + 0.1 * torch.randn(size, size, 3, generator=g)).clamp(0, 1)
    return pred, gt


def test_no_cached_weights_gives_nan_lpips_and_one_warning(offline_hub: Path) -> None:
    assert metrics.alexnet_weights_path().parent.parent == offline_hub
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert metrics.make_lpips() is None
        assert metrics.make_lpips() is None
        pred, gt = _images()
        result = metrics.image_metrics(pred, gt)
    assert len([w for w in caught if "LPIPS unavailable" in str(w.message)]) == 1
    assert math.isnan(result["lpips"])
    assert not metrics.alexnet_weights_path().exists()  # nothing was downloaded

    from skimage.metrics import structural_similarity

    p, g = pred.double().numpy(), gt.double().numpy()
    assert result["psnr"] == pytest.approx(10 * np.log10(1.0 / np.mean((p - g) ** 2)), abs=1e-3)
    expected_ssim = structural_similarity(
        p, g, channel_axis=2, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    assert result["ssim"] == pytest.approx(expected_ssim, abs=1e-4)
    same = metrics.image_metrics(gt, gt, lpips=None)
    assert same["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert same["psnr"] > 80


def test_cached_weights_are_used_without_network(offline_hub: Path) -> None:
    from torchvision.models import alexnet

    path = metrics.alexnet_weights_path()
    path.parent.mkdir(parents=True)
    torch.manual_seed(0)
    torch.save(alexnet(weights=None).state_dict(), path)  # stands in for the cached ImageNet weights
    lpips = metrics.make_lpips()
    assert lpips is not None
    pred, gt = _images(seed=1)
    p, g = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    assert float(lpips(g, g)) == pytest.approx(0.0, abs=1e-6)
    assert float(lpips(p, g)) > 1e-4
    result = metrics.image_metrics(pred, gt, lpips=lpips)
    assert result["lpips"] == pytest.approx(float(lpips(p, g)), rel=1e-5)


def test_corrupt_cache_file_is_not_fatal(offline_hub: Path) -> None:
    path = metrics.alexnet_weights_path()
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not a checkpoint")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert metrics.make_lpips() is None
    assert len([w for w in caught if "LPIPS unavailable" in str(w.message)]) == 1


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.image_metrics(torch.zeros(16, 16, 3), torch.zeros(16, 17, 3), lpips=None)
    with pytest.raises(ValueError, match=r"\[H,W,3\]"):
        metrics.image_metrics(torch.zeros(16, 16), torch.zeros(16, 16), lpips=None)
