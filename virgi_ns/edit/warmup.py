"""A fresh process's first edit, paid while the process loads its run.

The first edit of a process runs many GPU kernels, cuBLAS's and ours, for the first time: each is
loaded on first use, and cuBLAS sets itself up on its first product. That made the first edit of a
``virgi-edit apply`` several times a warm one. :func:`start` runs one small edit of a made-up scene
on a background thread while the caller loads its run, and :func:`wait` joins it before the real
edit (whose recorded CUDA graphs must not share the device with another thread's work).

The warm-up draws its scene from its own generator, and builds its colour field with the global
random state forked, under the lock the engine holds while it seeds its segmentation head
(:data:`~virgi_ns.edit.heads.GLOBAL_RNG_LOCK`): it changes nothing a caller's seeds decide. A
warm-up that fails only leaves the first edit slow: its error is kept (:data:`last_error`), never
raised.
"""

from __future__ import annotations

import atexit
import math
import threading
import time
from typing import Optional

import torch

_thread: Optional[threading.Thread] = None
last_error: Optional[str] = None
"""Why the last warm-up failed (None when it did not)."""
last_seconds: Optional[float] = None
"""How long the last warm-up took."""

GAUSSIANS, WIDTH, HEIGHT = 60_000, 320, 180
"""The made-up scene: enough Gaussians that the view sees tens of thousands, as a real view does
(cuBLAS picks its kernels by the products' sizes), on a small image."""


@torch.no_grad()
def _scene(device: torch.device, n: int, width: int, height: int):
    """(scene, camera, generator): ``n`` random Gaussians in front of one camera of ``width`` x
    ``height``, a colour field of the default size, all drawn from one seeded generator."""
    from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField
    from virgi_ns.edit.heads import GLOBAL_RNG_LOCK
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.raster import Cameras

    g = torch.Generator(device=device).manual_seed(0)
    f = 0.9 * width

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, device=device)

    z = 2.0 + 6.0 * rand(n)
    means = torch.stack([(rand(n) - 0.5) * z * width / f, (rand(n) - 0.5) * z * height / f, z], -1)
    scales = torch.exp(math.log(0.01) + math.log(4.0) * rand(n, 3))
    quats = torch.nn.functional.normalize(rand(n, 4) - 0.5, dim=-1)
    aabb = torch.tensor([[-6.0, -4.0, 1.5], [6.0, 4.0, 8.5]])
    with GLOBAL_RNG_LOCK, torch.random.fork_rng(devices=[]):  # the layers' initialisation draws from it
        field = DecoupledColourField(ColourFieldConfig(), aabb, empty=True).to(device)
    for p in field.parameters():
        p.copy_((rand(*p.shape) - 0.5) * 0.2)
    cams = Cameras.from_params(f, f, width / 2, height / 2, torch.eye(4, device=device)[None], width, height)
    return FrozenScene(means, quats, scales, 0.3 + 0.7 * rand(n), field, torch.zeros(3, device=device)), cams, g


def warm_up(device: "torch.device | str", gaussians: int = GAUSSIANS, width: int = WIDTH,
            height: int = HEIGHT) -> float:
    """One small edit on ``device`` (a few eager steps, no CUDA graphs); returns its seconds."""
    from virgi_ns.edit.engine import EditConfig, EditEngine

    device = torch.device(device)
    t0 = time.perf_counter()
    scene, cams, g = _scene(device, gaussians, width, height)
    # a photo and its edit as a user's: a part of the view recoloured (a channel swap), large enough
    # for every step of the engine's set-up (the change's slope, the colour-map start)
    original = torch.rand(height, width, 3, generator=g, device=device)
    edited = original.clone()
    edited[:, : int(0.4 * width)] = original[:, : int(0.4 * width)].roll(1, dims=-1)
    EditEngine(scene, cams, edited, cfg=EditConfig(steps=3, cuda_graphs=False), original=original).fit()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def _run(device: torch.device) -> None:
    global last_error, last_seconds
    try:
        last_seconds = warm_up(device)
        last_error = None
    except Exception as e:  # noqa: BLE001  a failed warm-up only leaves the first edit slow
        last_error = f"{type(e).__name__}: {e}"


def start(device: "torch.device | str") -> bool:
    """Start the warm-up on a background thread when ``device`` is a GPU and none runs yet; returns
    whether one was started."""
    global _thread
    device = torch.device(device)
    if device.type != "cuda" or not torch.cuda.is_available() or (_thread is not None and _thread.is_alive()):
        return False
    _thread = threading.Thread(target=_run, args=(device,), name="virgi-edit-warm-up", daemon=True)
    _thread.start()
    atexit.register(wait)  # a process that stops early (bad input) ends after it, not during its GPU work
    return True


def wait() -> None:
    """Until the warm-up (if one was started) has finished."""
    global _thread
    if _thread is not None:
        _thread.join()
        _thread = None


__all__ = ["start", "wait", "warm_up"]
