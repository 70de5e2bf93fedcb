"""The INRIA 3D Gaussian Splatting ``.ply`` layout (what the original 3DGS code and most tools write).

One ``vertex`` element of float properties: ``x y z``, optional ``nx ny nz``, ``f_dc_0..2``,
``f_rest_0..R-1`` (channel-major: all of red's higher-band coefficients, then green's, then blue's),
``opacity`` (logit), ``scale_0..2`` (log), ``rot_0..3`` (w x y z).
"""

from __future__ import annotations

import numpy as np
import torch

from virgi_ns.errors import InputError
from virgi_ns.gaussians import Gaussians
from virgi_ns.io.plyfmt import PlyData, ply_bytes

REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _rest_count(names: list[str], where: str) -> int:
    rest = sorted(int(n[7:]) for n in names if n.startswith("f_rest_") and n[7:].isdigit())
    if rest != list(range(len(rest))):
        raise InputError(f"{where}: f_rest_* properties are not numbered 0..{len(rest) - 1} without gaps")
    if len(rest) % 3 or round((len(rest) // 3 + 1) ** 0.5) ** 2 != len(rest) // 3 + 1 or len(rest) > 72:
        raise InputError(f"{where}: {len(rest)} f_rest_* properties do not match an SH degree of 0..4 (0, 9, 24, 45 or 72)")
    return len(rest)


def gaussians_from_inria(ply: PlyData, where: str = "file") -> Gaussians:
    """Interpret a parsed PLY as INRIA-layout Gaussians (any SH degree 0..4)."""
    vertex = ply.get("vertex")
    if vertex is None:
        raise InputError(f"{where}: PLY has no 'vertex' element, so it holds no Gaussians")
    names = vertex.names
    missing = [n for n in REQUIRED if n not in names]
    if missing:
        raise InputError(
            f"{where}: not a Gaussian splat PLY: vertex properties lack {', '.join(missing)} "
            f"(it has {', '.join(names[:12])}{', ...' if len(names) > 12 else ''})"
        )
    n_rest = _rest_count(names, where)
    d = vertex.data
    col = lambda *ns: np.stack([np.asarray(d[n], dtype=np.float32) for n in ns], axis=1)  # noqa: E731
    n = vertex.count
    k = n_rest // 3 + 1
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0] = col("f_dc_0", "f_dc_1", "f_dc_2")
    if n_rest:
        rest = col(*[f"f_rest_{i}" for i in range(n_rest)])  # [N, 3*(K-1)] channel-major
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    return Gaussians.from_numpy(
        means=col("x", "y", "z"),
        scales=col("scale_0", "scale_1", "scale_2"),
        quats=col("rot_0", "rot_1", "rot_2", "rot_3"),
        opacities=np.array(d["opacity"], dtype=np.float32),  # a copy: the file buffer is read-only
        sh=sh,
    )


def inria_vertices(g: Gaussians) -> np.ndarray:
    """The Gaussians as the INRIA layout's ``vertex`` element: one float32 structured record each.
    The table is assembled where the Gaussians are (on a GPU: one copy to the host)."""
    n, k = len(g), g.sh.shape[1]
    t = lambda x: x.detach().to(torch.float32).reshape(n, x.shape[1:].numel())  # noqa: E731
    sh = t(g.sh).reshape(n, k, 3)
    rest = sh[:, 1:].transpose(1, 2).reshape(n, 3 * (k - 1))
    cols = [t(g.means), sh.new_zeros(n, 3), sh[:, 0], rest, t(g.opacities), t(g.scales), t(g.quats)]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    table = np.ascontiguousarray(torch.cat(cols, dim=1).cpu().numpy(), dtype="<f4")
    return table.view(np.dtype([(nm, "<f4") for nm in names])).reshape(n)


def inria_ply_bytes(g: Gaussians) -> bytes:
    """Serialise Gaussians in the INRIA layout, float32, in one vectorised pass."""
    return ply_bytes([("vertex", inria_vertices(g))])

