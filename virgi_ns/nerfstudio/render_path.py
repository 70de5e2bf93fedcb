"""The render path of :class:`~virgi_ns.nerfstudio.model.VirgiModel`: colours through the edit stack
(and the live edit of a pick, not yet on the stack), the specular gate, and whole-camera renders.

In one view every pair of a Gaussian has the same direction, so a whole-view render computes one
colour per Gaussian (:meth:`RenderPath.view_colours`) and composites them: on a GPU with gsplat,
elsewhere through our contribution lists. Tile batches (training) take :meth:`RenderPath.pair_colours`,
one colour per (view, Gaussian) pair.

An :class:`~virgi_ns.edit.stack.EditStack` set on the model recolours ``c_d`` and scales ``c_s`` at
render time. After training the model measures every Gaussian's specular magnitude over the
training views (:meth:`RenderPath.build_specular_gate`). Gated renders then take the
:class:`~virgi_ns.nerfstudio.render_cache.RenderCache`: MLP_spec's last steps for the Gaussians
above ``gate_threshold`` from cached view-independent parts, cached (edited) diffuse colours for
the rest, and nothing per frame for a matte scene.
"""

from __future__ import annotations

import functools
from typing import Dict, List, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from virgi_ns.colour.field import view_directions
from virgi_ns.nerfstudio.gsplat_pass import Projection, project, rasterize
from virgi_ns.nerfstudio.render_cache import (
    CHUNK,
    RenderCache,
    View,
    ViewColours,
    ViewOutputs,
    edited_diffuse,
    view_of,
)
from virgi_ns.raster import Cameras, Contributions, Request, composite, expected_depth

OUTPUTS = ("rgb", "diffuse", "specular", "depth", "accumulation", "segmentation", "background")


def _no_grad(fn):
    """``torch.no_grad()`` as a decorator of a method called per frame, entered only where gradients are on:
    a frame's calls nest (the viewer's own ``no_grad``, then four of ours), and each ``no_grad`` entered
    costs its context object's set-up in Python."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if not torch.is_grad_enabled():
            return fn(*args, **kwargs)
        with torch.no_grad():
            return fn(*args, **kwargs)

    return call


class RenderPath:
    """Mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` (reads its config, Gaussians and
    field): colours per Gaussian of a view and per contribution pair, the specular gate, and
    renders of whole cameras."""

    # -------------------------------------------------------------- edit stack
    def set_edit_stack(self, stack) -> None:
        """Render through ``stack`` (a :class:`virgi_ns.edit.stack.EditStack`, or None for the base
        colours) from now on: its enabled edits recolour ``c_d``, its ``specular_strength`` scales
        ``c_s``."""
        self.edit_stack = stack.to(self.device) if stack is not None else None

    def set_live_edit(self, edit) -> None:
        """Render ``edit`` (a :class:`virgi_ns.edit.stack.Edit`, or None) over the stack's edits without
        adding it to the stack: the uncommitted edit of a pick while its colour is dragged (nothing
        is written; committing adds it to the stack and clears this slot). Each call counts as a
        change for the render cache, so an edit changed in place must be set again."""
        self.live_edit = edit.to(self.device) if edit is not None else None
        self._live_revision = getattr(self, "_live_revision", 0) + 1

    def fingerprint(self) -> str:
        """The base run's fingerprint that every edit of it carries."""
        from virgi_ns.fingerprint import field_fingerprint

        return field_fingerprint(self.means.detach(), self.field,
                                 [self.quats.detach(), torch.exp(self.scales.detach()),
                                  torch.sigmoid(self.opacities.detach()).reshape(-1)])

    def active_stack(self):
        """The edit stack renders go through, or None where it changes nothing (none set, or the identity)."""
        st = self.edit_stack
        return None if st is None or st.is_identity else st

    @property
    def render_cache(self) -> RenderCache:
        cache = getattr(self, "_render_cache", None)
        if cache is None:
            cache = self._render_cache = RenderCache()
        return cache

    # ------------------------------------------------------- colours per pair
    def pair_colours(self, contrib: Contributions, cams: Cameras) -> Dict[str, Tensor]:
        """Per-pair ``rgb``, ``diffuse`` (sigmoid c_d) and ``c_s`` of a contribution list (tile
        batches: many views), through the edit stack when one is set. Hash features and MLP_diff run
        once per distinct Gaussian, MLP_spec once per pair."""
        pg = contrib.pair_gaussian.to(self.device)
        pv = contrib.pair_view.to(self.device)
        stack = self.active_stack()
        live = getattr(self, "live_edit", None)
        if pg.numel() == 0:
            z = torch.zeros(0, 3, device=self.device)
            return {"rgb": z, "diffuse": z, "c_s": z}
        means = self.means.detach()
        centres = cams.to(self.device).camera_centers().to(means.dtype)
        fld = self.field
        uniq, inv = torch.unique(pg, return_inverse=True)
        f = fld.encode(means[uniq])
        d = view_directions(means[pg], centres[pv])
        if fld.decoupled:
            h1, h2 = fld.diffuse_hidden(f)
            c_d = edited_diffuse(fld, f, h2, stack, live)[inv]
            c_s = fld.specular(f[inv], d, h1[inv], h2[inv])
        else:
            _, h2p = fld.diffuse_hidden(f[inv], d)
            c_d = edited_diffuse(fld, f[inv], h2p, stack, live)
            c_s = torch.zeros_like(c_d)
        k = stack.specular_strength if stack is not None else 1.0
        return {"rgb": torch.sigmoid(c_d + k * c_s), "diffuse": torch.sigmoid(c_d), "c_s": c_s}

    # ---------------------------------------------------- colours per Gaussian
    def view_of(self, camera: NSCameras) -> View:
        """The first camera of ``camera`` as a :class:`~virgi_ns.nerfstudio.render_cache.View`."""
        return view_of(camera, self.device, self.means.dtype)

    @_no_grad
    def view_colours(self, view: View, gated: bool = False, transient: bool = False) -> ViewColours:
        """One colour per Gaussian for ``view``. ``gated`` (and a current gate): from the render
        cache; otherwise the full colour model over every Gaussian. ``transient``: ``rgb`` may be a
        buffer that the next view's colours overwrite (a CUDA graph's output), for a caller that
        composites it first."""
        cache = self.render_cache
        levels = cache.levels(self) if gated and self.field.decoupled else None
        if levels is not None:
            gate, edits = levels
            rgb = cache.colours(gate, edits, view.centre, getattr(self.config, "render_cache_graphs", True), transient)
            seg = (lambda: self._cached_segmentation(edits)) if self._with_segmentation() else None
            return ViewColours(rgb, None if edits.matte else edits.diffuse, seg)
        return self._full_colours(view.centre)

    def _full_colours(self, centre: Tensor) -> ViewColours:
        """Every Gaussian's colour from the field (no cache): the reference the cached colours
        must equal."""
        fld = self.field
        stack = self.active_stack()
        live = getattr(self, "live_edit", None)
        k = stack.specular_strength if stack is not None else 1.0
        means = self.means.detach()
        rgbs, diffs = [], []
        for s in range(0, means.shape[0], CHUNK):
            m = means[s : s + CHUNK]
            f = fld.encode(m)
            d = view_directions(m, centre)
            if fld.decoupled:
                h1, h2 = fld.diffuse_hidden(f)
            else:
                h1, h2 = fld.diffuse_hidden(f, d)
            c_d = edited_diffuse(fld, f, h2, stack, live)
            if fld.decoupled:
                rgbs.append(torch.sigmoid(c_d + k * fld.specular(f, d, h1, h2)))
            diffs.append(torch.sigmoid(c_d))
        diffuse = torch.cat(diffs) if diffs else means.new_zeros(0, 3)
        rgb = (torch.cat(rgbs) if rgbs else diffuse) if fld.decoupled else diffuse
        seg = (lambda: self._segmentation_from_field(centre)) if self._with_segmentation() else None
        return ViewColours(rgb, diffuse if fld.decoupled else None, seg)

    def _with_segmentation(self) -> bool:
        return self.edit_stack is not None and len(self.edit_stack) > 0

    def _segmentation_index(self) -> Optional[int]:
        st = self.edit_stack
        if self.segmentation_edit is not None and not 1 <= self.segmentation_edit <= len(st):
            self.segmentation_edit = None  # the selected edit was undone: show all enabled edits
        return self.segmentation_edit

    def _segmentation_from_field(self, centre: Optional[Tensor]) -> Tensor:
        """[N,1] alpha of ``segmentation_edit`` (or of all enabled edits together) per Gaussian; the
        single MLP's hidden layers need the view's ``centre``."""
        st, fld, index = self.edit_stack, self.field, self._segmentation_index()
        means = self.means.detach()
        out = []
        for s in range(0, means.shape[0], CHUNK):
            m = means[s : s + CHUNK]
            f = fld.encode(m)
            _, h2 = fld.diffuse_hidden(f) if fld.decoupled else fld.diffuse_hidden(f, view_directions(m, centre))
            out.append(st.segmentation(f, h2, index).to(means.dtype))
        return torch.cat(out) if out else means.new_zeros(0, 1)

    def _cached_segmentation(self, edits) -> Tensor:
        index = self._segmentation_index()
        if index not in edits.segmentation:
            edits.segmentation[index] = self._segmentation_from_field(None)
        return edits.segmentation[index]

    # ----------------------------------------------------------- specular gate
    def _field_stamp(self) -> tuple:
        """The field's parameters' identities and in-place version counters (optimizer steps and loads
        bump them; a parameter set anew is another tensor), in ``parameters()``'s order."""
        params = tuple(self.field.parameters())
        return tuple(map(id, params)), tuple(p._version for p in params)

    def gate_ready(self) -> bool:
        """A gate is built for these Gaussians and the field has not changed since."""
        return self.gate_current(None)

    def gate_current(self, field_stamp: Optional[tuple], n: Optional[int] = None) -> bool:
        """Whether the gate was measured for these Gaussians and this field (``field_stamp``: the field's
        :meth:`_field_stamp` now, or None to take it; ``n``: the number of Gaussians, or None)."""
        built = getattr(self, "_gate_stamp", None)
        n = self.num_points if n is None else n
        if self.spec_magnitude.numel() != n or self.diffuse_cache.shape[0] != n:
            return False
        return built is None or built == (field_stamp if field_stamp is not None else self._field_stamp())

    def drop_specular_gate(self) -> None:
        """Forget the gate, the cached diffuse colours and the render cache (the field changes;
        renders take the full path until :meth:`build_specular_gate` runs again)."""
        self.spec_magnitude = self.spec_magnitude.new_zeros(0)
        self.diffuse_cache = self.diffuse_cache.new_zeros(0, 3)
        self.render_cache.clear()

    @property
    def spec_gate(self) -> Tensor:
        return self.spec_magnitude > self.config.gate_threshold

    @torch.no_grad()
    def build_specular_gate(self, cams: Cameras, chunk: int = 65536) -> Dict[str, float]:
        """Measure max over training views of |sigmoid(c_d + c_s) - sigmoid(c_d)| per Gaussian
        (directions from each training camera's centre; visibility is not checked, which only
        keeps more Gaussians) and cache every Gaussian's ``c_d``."""
        fld = self.field
        means = self.means.detach()
        centres = cams.to(self.device).camera_centers().to(means.dtype)
        mag = torch.zeros(self.num_points, device=self.device)
        cache = torch.zeros(self.num_points, 3, device=self.device)
        if fld.decoupled:
            for s in range(0, self.num_points, chunk):
                m = means[s : s + chunk]
                f = fld.encode(m)
                h1, h2 = fld.diffuse_hidden(f)
                c_d = fld.diffuse(h2)
                cache[s : s + chunk] = c_d
                base = torch.sigmoid(c_d)
                for c in centres:
                    d = torch.nn.functional.normalize(m - c, dim=-1)
                    c_s = fld.specular(f, d, h1, h2)
                    eff = (torch.sigmoid(c_d + c_s) - base).abs().amax(-1)
                    mag[s : s + chunk] = torch.maximum(mag[s : s + chunk], eff)
        else:  # the single MLP is view dependent throughout: keep every Gaussian on the full path
            mag.fill_(float("inf"))
        self.spec_magnitude = mag
        self.diffuse_cache = cache
        self._gate_stamp = self._field_stamp()
        self.render_cache.clear()  # its colours were computed from the previous field
        kept = float(self.spec_gate.float().mean()) if self.num_points else 0.0
        CONSOLE.log(f"virgi: specular gate keeps {kept:.1%} of {self.num_points:,} Gaussians")
        return {"kept_fraction": kept}

    # ------------------------------------------------------------------ renders
    @_no_grad
    def render_camera(self, camera: NSCameras, gated: bool = False, max_pixels: int = 1 << 20):
        """Whole-image ``rgb``, ``diffuse``, ``specular`` (rgb - diffuse, no background), ``depth``,
        ``accumulation`` and ``segmentation`` (zeros without edits) for the first camera of
        ``camera``, through the edit stack when one is set (see :meth:`render_view`)."""
        view = self.view_of(camera)
        return self.render_view(view, self.view_colours(view, gated, transient=True), max_pixels)

    def render_view(self, view: View, colours: ViewColours, max_pixels: int = 1 << 20):
        """Composite one colour per Gaussian in ``view``. On a GPU (``whole_view_renderer="gsplat"``)
        one gsplat pass gives rgb, depth and accumulation, and a :class:`ViewOutputs` computes
        diffuse, specular and segmentation (a second pass) only when they are read; elsewhere our
        contribution lists, in bands of rows, give them all."""
        bg = self.render_cache.background(self.background_color, self.device)
        if self._renders_with_gsplat():
            return self._render_view_gsplat(view, colours, bg)
        return self._render_view_contributions(view, colours, bg, max_pixels)

    def _render_view_contributions(self, view: View, colours: ViewColours, bg: Tensor, max_pixels: int
                                   ) -> Dict[str, Tensor]:
        cams = Cameras(view.K, view.viewmat, [view.width], [view.height])
        W, H = view.width, view.height
        rows = max(1, min(H, max_pixels // max(W, 1)))
        seg = colours.segmentation() if colours.segmentation is not None else None
        diffuse = colours.diffuse if colours.diffuse is not None else colours.rgb
        parts: Dict[str, List[Tensor]] = {k: [] for k in OUTPUTS[:-1]}
        # one composite per band for every output: rgb | diffuse | depth | segmentation channels
        # (the background only behind the two colours), so the lists are walked once
        zero = bg.new_zeros(1)
        bg_all = torch.cat([bg, bg, zero] + ([zero] if seg is not None else []))
        for y0 in range(0, H, rows):
            h = min(rows, H - y0)
            contrib = self.contributions(cams, Request(torch.zeros(1, dtype=torch.long), 0, y0, W, h))
            pg = contrib.pair_gaussian.to(self.device)
            channels = [colours.rgb[pg], diffuse[pg], contrib.pair_depth[:, None].to(colours.rgb)]
            if seg is not None:
                channels.append(seg[pg].to(colours.rgb))
            img = composite(torch.cat(channels, dim=-1), contrib, bg_all)[0]
            rgb, diff, z_sum = img[..., 0:3], img[..., 3:6], img[..., 6:7]
            acc = contrib.accumulation()[0, ..., None].to(rgb)
            parts["rgb"].append(rgb)
            parts["diffuse"].append(diff)
            parts["specular"].append(rgb - diff)
            parts["depth"].append(expected_depth(z_sum, acc))
            parts["accumulation"].append(acc)
            parts["segmentation"].append(img[..., 7:8] if seg is not None else rgb.new_zeros(h, W, 1))
        out: Dict[str, Tensor] = {k: torch.cat(v, dim=0) for k, v in parts.items()}
        out["rgb"] = out["rgb"].clamp(0, 1)
        out["diffuse"] = out["diffuse"].clamp(0, 1)
        out["background"] = bg
        return out

    def _renders_with_gsplat(self) -> bool:
        """Whole views on a GPU go through gsplat's forward rasterizer (``whole_view_renderer``)."""
        return self.config.whole_view_renderer == "gsplat" and self.device.type == "cuda"

    @_no_grad
    def _splat(self, view: View, colours: Tensor, backgrounds: Tensor, mode: str,
               projection: Optional[Projection] = None) -> Tuple[Tensor, Tensor, Projection]:
        """gsplat's forward rasterization of the frozen Gaussians with one colour per Gaussian
        (:mod:`~virgi_ns.nerfstudio.gsplat_pass`: ``gsplat.rasterization``'s work for one camera):
        ([H,W,D] image, or [H,W,D+1] ending in the expected depth for ``mode="RGB+ED"``; [H,W,1]
        accumulation; the projection, which a later pass of the same view passes back)."""
        if projection is None:
            g = self.render_cache.geometry(self)
            projection = project(g.means, g.quats, g.scales, g.opacities, view.viewmat, view.K, view.width,
                                 view.height)
        if mode == "RGB+ED":
            img, alpha = rasterize(projection, colours, self.render_cache.with_depth_channel(backgrounds), True)
        else:
            img, alpha = rasterize(projection, colours, backgrounds, False)
        return img, alpha, projection

    def _render_view_gsplat(self, view: View, colours: ViewColours, bg: Tensor) -> ViewOutputs:
        """:meth:`render_view` on a GPU. The main pass is a plain splat's (colour + expected depth);
        diffuse and segmentation take a second pass of their own when read (the main pass's projection
        again), and a matte view (no specular term anywhere) has diffuse = rgb and specular = 0
        without one."""
        row = self.render_cache.background_row(bg)
        img, acc, proj = self._splat(view, colours.rgb.float(), row, "RGB+ED")
        rgb_raw = img[..., 0:3]
        rgb = rgb_raw.clamp(0, 1)
        H, W = view.height, view.width
        second: Dict[str, Tensor] = {}

        def pass2() -> Dict[str, Tensor]:
            if not second:
                chans, bgs = [], []
                if colours.diffuse is not None:
                    chans.append(colours.diffuse.float())
                    bgs.append(row)
                if colours.segmentation is not None:
                    chans.append(colours.segmentation().float())
                    bgs.append(row.new_zeros(1, 1))
                img2, _, _ = self._splat(view, torch.cat(chans, -1), torch.cat(bgs, -1), "RGB", proj)
                i = 0
                if colours.diffuse is not None:
                    second["diffuse_raw"], i = img2[..., 0:3], 3
                if colours.segmentation is not None:
                    second["segmentation"] = img2[..., i : i + 1]
            return second

        lazy = {
            "specular": (lambda: rgb_raw - pass2()["diffuse_raw"]) if colours.diffuse is not None
            else (lambda: rgb.new_zeros(H, W, 3)),
            "segmentation": (lambda: pass2()["segmentation"]) if colours.segmentation is not None
            else (lambda: rgb.new_zeros(H, W, 1)),
        }
        # expected depth: gsplat's, 0 where nothing is drawn (every drawn Gaussian's alpha is at least
        # 1/255, so the accumulation is 0 exactly there, and the composited depth with it)
        ready = {"rgb": rgb, "depth": img[..., 3:4], "accumulation": acc, "background": bg}
        if colours.diffuse is not None:
            lazy["diffuse"] = lambda: pass2()["diffuse_raw"].clamp(0, 1)
        else:
            ready["diffuse"] = rgb
        return ViewOutputs(OUTPUTS, ready, lazy)

    @_no_grad
    def get_outputs_for_camera(self, camera: NSCameras, obb_box=None):
        if obb_box is not None and self.geometry_frozen and not getattr(self, "_crop_notice", False):
            self._crop_notice = True
            CONSOLE.log("virgi: crop boxes are ignored when rendering the colour field")
        crop = None if self.geometry_frozen else obb_box
        if crop is not None or self.crop_box is not None:
            self.set_crop(crop)
        # frozen geometry renders a camera wherever its numbers lie (view_of reads them there: a camera on
        # the CPU is read without a device sync and not copied to the device and back); splatfacto's
        # geometry stage needs it on the device
        if not self.geometry_frozen and camera.camera_to_worlds.device != self.device:
            camera = camera.to(self.device)
        return self.get_outputs(camera)  # type: ignore[return-value]


__all__ = ["OUTPUTS", "RenderPath"]
