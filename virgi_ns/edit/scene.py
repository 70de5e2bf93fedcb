"""What the edit engine reads from a trained model, and rendering through an edit stack.

:class:`FrozenScene` bundles the frozen Gaussians, their colour field, the render background and
the rasterizer backend; :func:`render_view` renders a view through a stack with the full colour
model, including each pixel's segmentation, for tests, benchmarks and the demo.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from virgi_ns.colour.field import DecoupledColourField, view_directions
from virgi_ns.colour.file_colours import FileColours
from virgi_ns.edit.stack import EditStack
from virgi_ns.fingerprint import field_fingerprint
from virgi_ns.raster import Cameras, Contributions, Request, composite, rasterize


@dataclass
class SceneView:
    """What one view sees of a :class:`FrozenScene`: ``contrib``, its contribution lists; ``gaussians``
    [U], the Gaussian of each of its (view, Gaussian) pairs; per pair, the features ``feats`` [U,F] and
    ``h_diff`` [U,H], the base diffuse logits ``c_d`` [U,3], the specular logits ``c_s`` [U,3] and the unit
    directions ``dirs`` [U,3] from the view's camera to the Gaussian."""

    contrib: Contributions
    gaussians: Tensor
    feats: Tensor
    h_diff: Tensor
    c_d: Tensor
    c_s: Tensor
    dirs: Tensor


@dataclass
class FrozenScene:
    """Frozen Gaussians (``scales`` are standard deviations, ``opacities`` probabilities [N]),
    their colour field, the render background [3], and the rasterizer backend to use."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    field: DecoupledColourField
    background: Tensor
    backend: str = "auto"
    features: Optional[tuple[Tensor, Tensor, Tensor]] = None
    """Optional cache of every Gaussian's (f, h1, h_diff) (:meth:`precompute_features`); edits
    then gather them instead of running the hash grid and MLP_diff's first layers."""
    file_colours: Optional[FileColours] = None
    """The Gaussians' own colours when they are the base under edits (a run with
    ``base_colours="file"``): edits then start from the file's logits instead of the field's
    ``c_d`` and ``c_s`` (:mod:`virgi_ns.colour.file_colours`)."""

    @property
    def device(self) -> torch.device:
        return self.means.device

    @staticmethod
    def from_model(model) -> "FrozenScene":
        """From a trained :class:`virgi_ns.nerfstudio.model.VirgiModel` (or anything with splatfacto's
        ``means/quats/scales/opacities``, a ``field`` and a ``background_color``)."""
        dev = model.means.device
        backend = getattr(getattr(model, "config", None), "raster_backend", "auto")
        own = getattr(model, "file_colours", None)
        return FrozenScene(model.means.detach(), model.quats.detach(), torch.exp(model.scales.detach()),
                           torch.sigmoid(model.opacities.detach()).reshape(-1), model.field,
                           torch.as_tensor(model.background_color, dtype=torch.float32).to(dev).reshape(3), backend,
                           file_colours=own() if callable(own) else None)

    @torch.no_grad()
    def precompute_features(self, chunk: int = 1 << 18) -> "FrozenScene":
        """Fill :attr:`features` for all Gaussians (about 640 bytes each with the default field)."""
        parts: list[tuple[Tensor, Tensor, Tensor]] = []
        for s in range(0, self.means.shape[0], chunk):
            f = self.field.encode(self.means[s : s + chunk].float()).float()
            h1, h2 = self.field.diffuse_hidden(f)
            parts.append((f, h1.float(), h2.float()))
        self.features = tuple(torch.cat(x) for x in zip(*parts))  # type: ignore[assignment]
        return self

    def gaussian_features(self, idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(f, h1, h_diff) of Gaussians ``idx``, from the cache when present."""
        if self.features is not None:
            f, h1, h2 = self.features
            return f[idx], h1[idx], h2[idx]
        f = self.field.encode(self.means[idx].float()).float()
        h1, h2 = self.field.diffuse_hidden(f)
        return f, h1.float(), h2.float()

    @torch.no_grad()
    def view(self, camera: Cameras, contrib: Optional[Contributions] = None) -> "SceneView":
        """What one view (``camera``, one camera on this scene's device) sees: its contributions (``contrib``
        when the caller has them) and, per (view, Gaussian) pair, the colour field's features and the
        base diffuse and specular logits for this camera (:class:`SceneView`)."""
        if contrib is None:
            contrib = self.contributions(camera, Request.whole_images(camera))
        g = contrib.pair_gaussian.to(self.device)
        means = self.means[g].float()
        feats, h1, h2 = self.gaussian_features(g)
        c_d = self.field.diffuse(h2).float()
        dirs = view_directions(means, camera.camera_centers()[0].to(means).expand_as(means))
        c_s = self.field.specular(feats, dirs, h1, h2).float()
        return SceneView(contrib, g, feats, h2, c_d, c_s, dirs)

    def fingerprint(self) -> str:
        """The base run's fingerprint that every edit of it carries."""
        return field_fingerprint(self.means, self.field, [self.quats, self.scales, self.opacities])

    def contributions(self, cameras: Cameras, request: Request) -> Contributions:
        with torch.no_grad():
            return rasterize(self.means, self.quats, self.scales, self.opacities, cameras.to(self.device), request,
                             backend=self.backend)


@torch.no_grad()
def render_view(scene: FrozenScene, cameras: Cameras, view: int, stack: Optional[EditStack] = None,
                seg_index: Optional[int] = None, contrib: Optional[Contributions] = None,
                colour_map: Optional[Callable[[Tensor], Tensor]] = None,
                diffuse_map: Optional[Callable[[Tensor], Tensor]] = None) -> dict[str, Tensor]:
    """Render view ``view`` of ``cameras`` with the full (ungated) colour model through ``stack``:
    ``rgb`` [H,W,3] (``sigmoid(c_d'' + k c_s)``), ``diffuse`` (``sigmoid(c_d'')``), ``specular``
    (rgb - diffuse) and ``segmentation`` [H,W,1] (alpha of edit ``seg_index``, or the combined
    share of all enabled edits; zeros with no stack). ``contrib``: the view's contributions when
    the caller has them already (:meth:`FrozenScene.contributions` of the one-view camera).
    ``colour_map``: applied to each Gaussian's final colour [U,3] before ``rgb`` is composited
    (e.g. a recolour rule per Gaussian instead of per pixel). ``diffuse_map``: applied to each
    Gaussian's diffuse colour ``sigmoid(c_d'')`` [U,3], the specular part then added to its logit as
    usual (what an edit of the diffuse colour alone can reach)."""
    cams = cameras.index(view).to(scene.device, torch.float32)
    seen = scene.view(cams, contrib)
    contrib, f, h2, c_d, c_s = seen.contrib, seen.feats, seen.h_diff, seen.c_d, seen.c_s
    c_field = c_d
    k = 1.0
    seg = torch.zeros_like(c_d[:, :1])
    if stack is not None:
        c_d = stack.diffuse(f, h2.float(), c_d)
        k = stack.specular_strength
        if len(stack):
            seg = stack.segmentation(f, h2.float(), seg_index).float()
    own = scene.file_colours
    edited = None
    if own is not None:  # the file's own colours under the field's change
        edited = own.edited_logits(own.base_logits(seen.gaussians), c_field, c_d).float()
        offset, c_s = own.for_edit(seen.gaussians, seen.dirs, c_field, k)
        c_d, c_s = c_d + offset.float(), c_s.float()
    bg = scene.background.to(scene.device, torch.float32)
    if diffuse_map is not None:
        c_d = torch.logit(diffuse_map(torch.sigmoid(c_d)).clamp(1e-6, 1.0 - 1e-6))
    colours = torch.sigmoid(c_d + k * c_s)
    if edited is not None and diffuse_map is None:  # as the model renders them: exact where no edit touches
        colours = own.edited_colours(seen.gaussians, seen.dirs, edited, k).float()
    rgb = composite(colours if colour_map is None else colour_map(colours), contrib, bg)[0]
    diff = composite(torch.sigmoid(c_d), contrib, bg)[0]
    return {"rgb": rgb, "diffuse": diff, "specular": rgb - diff, "segmentation": composite(seg, contrib)[0]}



__all__ = ["FrozenScene", "SceneView", "render_view"]
