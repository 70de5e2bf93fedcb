"""The one in-memory type for a 3D Gaussian Splatting scene.

Every importer produces it, every exporter consumes it, the rasterizer reads its geometry.
Conventions (INRIA / gsplat / nerfstudio splatfacto):

- ``means``      [N, 3]  world positions
- ``scales``     [N, 3]  log standard deviations (``exp`` gives sigma)
- ``quats``      [N, 4]  rotation quaternions, w x y z, not necessarily normalised
- ``opacities``  [N]     logits (``sigmoid`` gives opacity)
- ``sh``         [N, K, 3] spherical-harmonic colour coefficients, K = (degree + 1) ** 2;
                 ``sh[:, 0]`` is INRIA's ``f_dc``; colour = 0.2820948 * f_dc + 0.5 at degree 0.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from torch import Tensor

SH_C0 = 0.28209479177387814


def sh_degree_from_coeffs(k: int) -> int:
    deg = int(round(k**0.5)) - 1
    if (deg + 1) ** 2 != k or deg < 0 or deg > 4:
        raise ValueError(f"{k} SH coefficients per channel is not (degree+1)^2 for a degree 0..4")
    return deg


@dataclass
class Gaussians:
    """A splat: ``means`` [N,3], log-``scales`` [N,3], ``quats`` [N,4] (wxyz), logit-``opacities`` [N] and
    ``sh`` [N,K,3], K = (degree + 1)^2 SH coefficients per channel in the 3DGS convention; the shapes are
    checked at construction."""

    means: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        n = len(self)
        expect = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,)}
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name} has shape {got}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh has shape {tuple(self.sh.shape)}, expected ({n}, K, 3)")
        sh_degree_from_coeffs(self.sh.shape[1])

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def to(self, device=None, dtype=None) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)})

    def index(self, idx) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    def replace(self, **kw) -> "Gaussians":
        return replace(self, **kw)

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """Truncate or zero-pad the SH bands to ``degree``."""
        k = (degree + 1) ** 2
        sh = self.sh
        if sh.shape[1] >= k:
            sh = sh[:, :k]
        else:
            pad = sh.new_zeros(sh.shape[0], k - sh.shape[1], 3)
            sh = torch.cat([sh, pad], dim=1)
        return self.replace(sh=sh.contiguous())

    # ------------------------------------------------------------ derived values
    @property
    def rgb(self) -> Tensor:
        """Degree-0 colour, clamped below at 0 (as 3DGS renderers do)."""
        return (SH_C0 * self.sh[:, 0] + 0.5).clamp_min(0.0)

    def normalized_quats(self) -> Tensor:
        return torch.nn.functional.normalize(self.quats, dim=-1)

    def invalid_rows(self) -> Tensor:
        """Bool [N]: rows holding a NaN or an infinity in any attribute."""
        bad = torch.zeros(len(self), dtype=torch.bool, device=self.device)
        for f in fields(self):
            v = getattr(self, f.name).reshape(len(self), -1) if len(self) else None
            if v is not None:
                bad |= ~torch.isfinite(v).all(dim=1)
        return bad

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self) == 0:
            z = np.zeros(3)
            return z, z
        m = self.means.detach().cpu().double().numpy()
        return m.min(0), m.max(0)

    def summary(self) -> str:
        lo, hi = self.bbox()
        fmt = lambda v: "(" + ", ".join(f"{x:.3f}" for x in v) + ")"  # noqa: E731
        return f"{len(self):,} Gaussians, SH degree {self.sh_degree}, bbox min {fmt(lo)} max {fmt(hi)}"

    # -------------------------------------------------------------- constructors
    @staticmethod
    def from_numpy(means, scales, quats, opacities, sh, dtype=torch.float32) -> "Gaussians":
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)  # noqa: E731
        return Gaussians(t(means), t(scales), t(quats), t(opacities).reshape(-1), t(sh))
