"""Bake a VIRGi model into a plain 3DGS scene: SH degree 3 per Gaussian, in the capture's frame.

The colour field gives every Gaussian a colour per view direction ``d`` (camera centre to the
Gaussian's mean, as the model renders it)::

    C(d) = sigmoid(c_d'' + k c_s(d))

with ``c_d''`` the diffuse colour through the enabled edits of an :class:`EditStack` and ``k`` the
specular strength. :func:`bake` samples ``C`` per Gaussian over a set of directions (the
directions from which the training cameras see it, weighted by whether it is in their view, plus a
Fibonacci sphere with a small weight so the fit stays sane everywhere) and fits SH coefficients by
weighted least squares in the 3DGS convention, ``C(d) ~ SH(d) . coeffs + 0.5`` with
:func:`virgi_ns.colour.sh.sh_basis` (what ``virgi-render`` and other 3DGS viewers evaluate). Gaussians
whose colour does not depend on the direction (below the model's specular gate, every Gaussian
when ``k = 0``) get their exact colour in the DC coefficient alone, as the model renders them.
A run that shows the splat file's own colours (``base_colours="file"``) exports them: each
Gaussian's own coefficients, plus a fit of the edits' change where an edit touches it
(:func:`bake_file_colours`).

Geometry is moved back into the capture's original frame with
:class:`~virgi_ns.nerfstudio.frames.CaptureFrame`, the inverse of the frame change an imported splat
goes through. View directions are rotated the same way before the SH basis is evaluated, so the
exported colours are those the model shows from the same physical camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.colour.sh import sh_basis
from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.colour.file_colours import FileColours
from virgi_ns.nerfstudio.file_colour_path import edited_diffuse_logits
from virgi_ns.nerfstudio.frames import CaptureFrame, frame_of_model
from virgi_ns.raster import Cameras

__all__ = ["BakeConfig", "bake", "bake_pipeline", "export_model", "fibonacci_sphere", "fit_sh", "write_splat"]

SH_DEGREE = 3



# ----------------------------------------------------------------------------- directions
def fibonacci_sphere(n: int, dtype=torch.float32, device=None) -> Float[Tensor, "n 3"]:
    """``n`` nearly uniform unit vectors (a Fibonacci lattice)."""
    i = torch.arange(n, dtype=torch.float64, device=device) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1).to(dtype)


@dataclass
class BakeConfig:
    """How colours are sampled and fitted."""

    directions: int = 64
    """Fibonacci-sphere directions per Gaussian (shared by all): a weak prior that keeps each fit defined
    away from the cameras. 64 lie about 25 degrees apart, finer than the lobes SH degree 3 can hold."""
    max_cameras: int = 64
    """Training-camera directions per Gaussian (evenly strided when there are more cameras)."""
    unseen_weight: float = 0.05
    """Weight of a camera direction whose camera does not see the Gaussian (behind or outside)."""
    sphere_floor: float = 0.01
    """Weight of a sphere direction far from every camera direction."""
    kernel: float = 0.03
    """A sphere direction at angle a from a camera direction of weight w gets weight
    ``w exp((cos a - 1) / kernel)`` (largest over the cameras), so the fit follows the model
    closely around and between the views it was trained on (0.03: 1/e at about 14 degrees)."""
    ridge: float = 1e-4
    """Ridge on the non-DC coefficients, relative to each Gaussian's total weight."""
    use_gate: bool = True
    """Give Gaussians below the model's specular gate their exact (view-independent) colour in
    the DC term, as the model renders them."""
    pairs_per_chunk: int = 0
    """(Gaussian, direction) pairs evaluated at once; 0: 4M on a GPU, 64k on a CPU (where each of MLP_spec's
    hidden activations, [pairs, 64] floats, then stays within a CPU's last-level cache)."""


def fit_sh(dirs: Float[Tensor, "N P 3"], colours: Float[Tensor, "N P 3"], weights: Float[Tensor, "N P"],
           degree: int = SH_DEGREE, ridge: float = 1e-4) -> Float[Tensor, "N K 3"]:
    """Weighted least-squares SH coefficients per row: ``min sum_p w_p |B(d_p) c + 0.5 - C_p|^2 +
    ridge * sum_p w_p * |c_{k>0}|^2``, with ``B`` :func:`virgi_ns.colour.sh.sh_basis` (3DGS signs)."""
    B = sh_basis(degree, torch.nn.functional.normalize(dirs, dim=-1))  # [N,P,K]
    Bw = B * weights[..., None]
    A = Bw.transpose(1, 2) @ B  # [N,K,K]
    rhs = Bw.transpose(1, 2) @ (colours - 0.5)  # [N,K,3]
    k = B.shape[-1]
    reg = torch.full((k,), ridge, dtype=A.dtype, device=A.device)
    reg[0] = 0.0  # the DC term is never shrunk
    A = A + torch.diag_embed(weights.sum(1, keepdim=True).clamp_min(1e-12) * reg)
    L, info = torch.linalg.cholesky_ex(A)
    if bool((info != 0).any()):  # degenerate rows (no weight at all): fall back to a solve with more ridge
        bad = info != 0
        A[bad] = A[bad] + torch.eye(k, dtype=A.dtype, device=A.device)
        L[bad] = torch.linalg.cholesky(A[bad])
    return torch.cholesky_solve(rhs, L)


def _camera_weights(means: Tensor, cams: Cameras, unseen: float) -> Tensor:
    """[N,V]: 1 where camera v sees mean n inside its image (in front of it), else ``unseen``."""
    R = cams.viewmats[:, :3, :3].to(means)
    t = cams.viewmats[:, :3, 3].to(means)
    pc = torch.einsum("vij,nj->nvi", R, means) + t[None]
    z = pc[..., 2]
    K = cams.Ks.to(means)
    u = K[None, :, 0, 0] * pc[..., 0] / z.clamp_min(1e-9) + K[None, :, 0, 2]
    v = K[None, :, 1, 1] * pc[..., 1] / z.clamp_min(1e-9) + K[None, :, 1, 2]
    W = cams.widths.to(means.device, means.dtype)[None]
    H = cams.heights.to(means.device, means.dtype)[None]
    seen = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return torch.where(seen, torch.ones_like(z), torch.full_like(z, unseen))


# -------------------------------------------------------------------------------- baking
def _baked(model, frame, sh: Tensor) -> Gaussians:
    """The model's Gaussians in ``frame``'s capture frame with the baked coefficients ``sh``."""
    m_cap, s_cap, q_cap = frame.gaussians_to_capture(model.means.detach().float(), model.scales.detach().float(),
                                                     model.quats.detach().float())
    return Gaussians(m_cap.contiguous(), s_cap.contiguous(), q_cap.contiguous(),
                     model.opacities.detach().float().reshape(-1).clone(), sh)


class _FitDirections:
    """The directions a Gaussian's view-dependent colour is sampled in for its SH fit, in the run's frame,
    with their weights: the training cameras' (at most ``cfg.max_cameras``, evenly strided) and a
    Fibonacci sphere's of ``cfg.directions`` (at least ``min_sphere``) weighted by their nearness to a
    camera direction. ``count`` directions a Gaussian; ``chunk`` Gaussians at a time fit
    ``cfg.pairs_per_chunk`` (or the device's default) pairs."""

    def __init__(self, cfg: BakeConfig, cameras, frame, means: Tensor, min_sphere: int) -> None:
        dev = means.device
        self.cfg = cfg
        sphere_cap = fibonacci_sphere(max(cfg.directions, min_sphere), device=dev)
        self.sphere_run = frame.directions_to_run(sphere_cap.double()).float()
        self.cams = None
        if cameras is not None and len(cameras) > 0:
            sel = torch.linspace(0, len(cameras) - 1, min(cfg.max_cameras, len(cameras))).round().long().unique()
            self.cams = cameras.index(sel).to(dev, torch.float32)
        self.centres = self.cams.camera_centers().to(means.dtype) if self.cams is not None else None
        self.count = (len(self.cams) if self.cams is not None else 0) + sphere_cap.shape[0]
        budget = cfg.pairs_per_chunk or ((4 << 20) if dev.type == "cuda" else (64 << 10))
        self.chunk = max(1, budget // max(self.count, 1))

    def at(self, m: Tensor) -> tuple[Tensor, Tensor]:
        """Directions [b,count,3] (run frame) and weights [b,count] for the Gaussians at ``m`` [b,3]."""
        cfg, cams, b = self.cfg, self.cams, m.shape[0]
        parts, wparts = [], []
        if cams is not None:
            parts.append(torch.nn.functional.normalize(m[:, None, :] - self.centres[None], dim=-1))
            w_cam = _camera_weights(m, cams, cfg.unseen_weight)
            wparts.append(w_cam)
        if self.sphere_run.shape[0]:
            sph = self.sphere_run[None].expand(b, -1, -1).to(m.dtype)
            parts.append(sph)
            w_s = torch.full((b, sph.shape[1]), cfg.sphere_floor if cams is not None else 1.0, device=m.device)
            if cams is not None:
                cos = sph @ parts[0].transpose(1, 2)  # [b,S,V]
                # the largest w exp((cos - 1) / kernel) over the cameras is exp of the largest exponent
                # plus log w (exp increases): one exp per sphere direction, not one per camera too
                exponent = cos.sub_(1.0).div_(max(cfg.kernel, 1e-6)).add_(torch.log(w_cam)[:, None, :])
                near = torch.exp(exponent.amax(-1))
                w_s = torch.maximum(w_s, near.to(w_s))
            wparts.append(w_s)
        return torch.cat(parts, dim=1), torch.cat(wparts, dim=1)


@torch.no_grad()
def bake(
    model,
    stack=None,
    specular_strength: Optional[float] = None,
    frame: Optional[CaptureFrame] = None,
    cameras: Optional[Cameras] = None,
    cfg: Optional[BakeConfig] = None,
    progress: Optional[Callable[[int, int], None]] = None,
) -> Gaussians:
    """The model's Gaussians with baked SH degree 3 colours, in ``frame``'s capture frame.

    ``model``: a :class:`virgi_ns.nerfstudio.model.VirgiModel` (frozen ``means/scales/quats/opacities`` and a
    ``field``). ``stack``: an :class:`~virgi_ns.edit.stack.EditStack` whose enabled edits recolour
    the diffuse term (None: the base colours). ``specular_strength``: ``k`` (default: the stack's,
    else 1). ``cameras``: the training cameras in the run's frame (rasterizer :class:`Cameras`),
    whose directions are sampled; without them only the sphere is. ``progress(done, total)`` is
    called per chunk of Gaussians.
    """
    cfg = cfg or BakeConfig()
    frame = frame or CaptureFrame.identity()
    k = float(specular_strength if specular_strength is not None
              else (stack.specular_strength if stack is not None else 1.0))
    if not (k >= 0.0 and math.isfinite(k)):
        raise InputError(f"specular strength must be a finite number >= 0, got {k}")
    own = getattr(model, "file_colours", None)
    own = own() if callable(own) else None
    if own is not None:  # the file's own coefficients, with the edits' change added where they touch
        return bake_file_colours(model, own, stack, k, frame, cameras, cfg, SH_DEGREE, progress)
    active = stack is not None and len(stack.active) > 0
    fld = model.field
    means = model.means.detach()
    dev = means.device
    n = means.shape[0]
    if active:
        stack.to(dev)
    K = (SH_DEGREE + 1) ** 2
    sh = torch.zeros(n, K, 3, device=dev, dtype=torch.float32)

    # which Gaussians need a view-dependent fit
    if not fld.decoupled:
        varying = torch.ones(n, dtype=torch.bool, device=dev)
    elif k == 0.0:
        varying = torch.zeros(n, dtype=torch.bool, device=dev)
    elif cfg.use_gate and model.gate_ready():
        varying = model.spec_gate.to(dev)
    else:
        varying = torch.ones(n, dtype=torch.bool, device=dev)

    dirs = _FitDirections(cfg, cameras, frame, means, min_sphere=0)
    P, chunk = dirs.count, dirs.chunk
    if P == 0:
        varying.zero_()
    fixed_chunk = 1 << 16
    total = n
    done = 0

    # view-independent Gaussians: exact colour in the DC term
    fixed = (~varying).nonzero().flatten()
    for s in range(0, fixed.numel(), fixed_chunk):
        idx = fixed[s : s + fixed_chunk]
        f = fld.encode(means[idx])
        _, h2 = fld.diffuse_hidden(f)
        c_d = fld.diffuse(h2)
        if active:
            c_d = stack.diffuse(f, h2, c_d)
        sh[idx, 0] = ((torch.sigmoid(c_d) - 0.5) / SH_C0).float()
        done += idx.numel()
        if progress is not None:
            progress(done, total)

    vary = varying.nonzero().flatten()
    for s in range(0, vary.numel(), chunk):
        idx = vary[s : s + chunk]
        m = means[idx]
        b = idx.numel()
        d_run, w = dirs.at(m)  # [b,P,3], [b,P]
        f = fld.encode(m)
        if fld.decoupled:
            h1, h2 = fld.diffuse_hidden(f)
            c_d = fld.diffuse(h2)
            if active:
                c_d = stack.diffuse(f, h2, c_d)
            # MLP_spec's view-independent parts once per Gaussian, broadcast over its P directions
            p1, p2, p3 = fld.specular_parts(f, h1, h2)
            c_s = fld.specular_from_parts(p1[:, None], p2[:, None], p3[:, None], d_run)  # [b,P,3]
            colour = torch.sigmoid(c_d[:, None] + k * c_s)
        else:  # the single view-dependent MLP: its hidden layers read the direction
            flat = d_run.reshape(-1, 3)
            rep = torch.arange(b, device=dev).repeat_interleave(P)
            h1, h2 = fld.diffuse_hidden(f[rep], flat)
            c = fld.diffuse(h2)
            if active:
                c = stack.diffuse(f[rep], h2, c)
            colour = torch.sigmoid(c)
        d_cap = frame.directions_to_capture(d_run.double()).float()
        sh[idx] = fit_sh(d_cap, colour.reshape(b, P, 3).float(), w.float(), SH_DEGREE, cfg.ridge)
        done += b
        if progress is not None:
            progress(done, total)

    return _baked(model, frame, sh)


@torch.no_grad()
def bake_file_colours(model, fc: FileColours, stack, k: float, frame, cameras, cfg, degree: int,
                      progress: Optional[Callable[[int, int], None]] = None) -> Gaussians:
    """:func:`bake` of a run with the file's colours: every Gaussian
    starts from the file's own coefficients (padded to ``degree``); a touched one gets the change
    the edits make (:meth:`FileColours.change`) added, in its DC term exactly when the file is view
    independent, else as a weighted least-squares SH fit over the directions ``bake`` samples (the
    training cameras' and a sphere's). Geometry goes back to ``frame``'s capture frame."""
    means = model.means.detach()
    dev = means.device
    fc = fc.to(dev)
    n = means.shape[0]
    own_rot = fc.rotation.double().cpu() if fc.rotation is not None else torch.eye(3, dtype=torch.float64)
    if fc.view_dependent and not torch.allclose(frame.rotation.double().cpu(), own_rot, atol=1e-6):
        raise InputError("this run shows its splat file's own view-dependent colours, whose coefficients hold in "
                         "the file's frame only: export it in the capture frame (--frame capture)")
    K = (degree + 1) ** 2
    sh = torch.zeros(n, K, 3, device=dev, dtype=torch.float32)
    sh[:, 0] = fc.dc.float()
    r = min(fc.rest.shape[1], K - 1)
    if r:
        sh[:, 1 : 1 + r] = fc.rest[:, :r].float()
    if stack is not None:
        stack.to(dev)
    b = fc.base_logits()
    e = edited_diffuse_logits(model, fc, stack)
    touched = fc.touched(b, e, k)
    idx = touched.nonzero().flatten()
    if not fc.view_dependent:
        # the change is view independent: the DC term gives C + change exactly (above 0)
        colour = fc.dc_colours(idx) + torch.sigmoid(e[idx]) - torch.sigmoid(b[idx])
        sh[idx, 0] = ((colour - 0.5) / SH_C0).float()
    elif idx.numel():
        dirs = _FitDirections(cfg, cameras, frame, means, min_sphere=1)
        chunk = dirs.chunk
        for s in range(0, idx.numel(), chunk):
            part = idx[s : s + chunk]
            nb = part.numel()
            d_run, w = dirs.at(means[part])  # [nb,P,3], [nb,P]
            P_ = d_run.shape[1]
            rep = part.repeat_interleave(P_)
            bb, ss = fc.logits(rep, d_run.reshape(-1, 3))
            change = fc.change(bb, ss, e[rep], k).reshape(nb, P_, 3)
            d_cap = frame.directions_to_capture(d_run.double()).float()
            sh[part] += fit_sh(d_cap, change.float() + 0.5, w.float(), degree, cfg.ridge)
            if progress is not None:
                progress(min(s + chunk, idx.numel()), idx.numel())
    if progress is not None:
        progress(n, n)
    return _baked(model, frame, sh)


def bake_pipeline(pipeline, stack=None, specular_strength: Optional[float] = None,
                  frame: Optional[CaptureFrame] = None, cfg: Optional[BakeConfig] = None,
                  progress: Optional[Callable[[int, int], None]] = None) -> Gaussians:
    """:func:`bake` a pipeline's model with its training cameras' directions, in the capture's
    frame (``frame`` defaults to :meth:`CaptureFrame.from_pipeline`)."""
    from virgi_ns.nerfstudio.cameras import raster_cameras

    frame = frame or CaptureFrame.from_pipeline(pipeline)
    dm = pipeline.datamanager
    cams = raster_cameras(dm.train_dataset.cameras) if getattr(dm, "train_dataset", None) is not None else None
    return bake(pipeline.model, stack, specular_strength, frame, cams, cfg, progress)


def write_splat(g: Gaussians, out: str | Path) -> Path:
    """Write ``.ply`` (INRIA), ``.spz`` or ``.sog`` by the name's suffix, atomically."""
    from virgi_ns.io import save_splat

    out = Path(out)
    check_output_path(out)
    save_splat(g, out)
    return out


def check_output_path(out: Path) -> None:
    if out.suffix.lower() not in (".ply", ".spz", ".sog") or out.name.lower().endswith(".compressed.ply"):
        raise InputError(f"output {out} must end in .ply (INRIA layout), .spz or .sog")
    if out.is_dir():
        raise InputError(f"output {out} is a directory")


_MODEL_STACK = "model"


def export_model(model_or_pipeline, out: str | Path, stack=_MODEL_STACK, specular_strength: Optional[float] = None,
                 frame: Optional[CaptureFrame] = None, cfg: Optional[BakeConfig] = None,
                 progress: Optional[Callable[[int, int], None]] = None) -> Gaussians:
    """Bake a model (or a pipeline's) and write it to ``out`` (.ply, .spz or .sog); returns the Gaussians.

    ``stack`` defaults to the edit stack the model renders with (``model.edit_stack``); None
    exports the base colours. With a pipeline the training cameras' directions are sampled and the
    frame comes from its datamanager; with a bare model, from its metadata (and the cameras its
    training callbacks recorded, if any)."""
    check_output_path(Path(out))
    if hasattr(model_or_pipeline, "datamanager"):
        pipeline, model = model_or_pipeline, model_or_pipeline.model
    else:
        pipeline, model = None, model_or_pipeline
    if isinstance(stack, str) and stack == _MODEL_STACK:
        stack = getattr(model, "edit_stack", None)
    if pipeline is not None:
        g = bake_pipeline(pipeline, stack, specular_strength, frame, cfg, progress)
    else:
        cams_fn = getattr(model, "_train_cameras_fn", None)
        cams = cams_fn() if cams_fn is not None else None
        g = bake(model, stack, specular_strength, frame or frame_of_model(model), cams, cfg, progress)
    write_splat(g, out)
    return g
