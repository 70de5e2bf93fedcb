"""The render path of :class:`~virgi_ns.nerfstudio.model.VirgiModel`: per-pair colours through the
edit stack (and the live edit of a pick, not yet on the stack), the specular gate, and whole-camera
renders.

Hash features and MLP_diff run once per distinct Gaussian of a contribution list, MLP_spec once per
(view, Gaussian) pair. An :class:`~virgi_ns.edit.stack.EditStack` set on the model recolours
``c_d`` and scales ``c_s`` at render time. After training the model measures every Gaussian's
specular magnitude over the training views (:meth:`RenderPath.build_specular_gate`); renders then
run MLP_spec only for Gaussians above ``gate_threshold`` and use cached (edited) diffuse colours
elsewhere.
"""

from __future__ import annotations

from typing import Dict, List

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from virgi_ns.colour.field import view_directions
from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.raster import Cameras, Contributions, Request, composite, expected_depth


class RenderPath:
    """Mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` (reads its config, Gaussians and
    field): colours per contribution pair, the specular gate, and renders of whole cameras."""

    # -------------------------------------------------------------- edit stack
    def set_edit_stack(self, stack) -> None:
        """Render through ``stack`` (a :class:`virgi_ns.edit.stack.EditStack`, or None for the base
        colours) from now on: its enabled edits recolour ``c_d``, its ``specular_strength`` scales
        ``c_s``."""
        self.edit_stack = stack.to(self.device) if stack is not None else None
        self._edited_cache = None

    def set_live_edit(self, edit) -> None:
        """Render ``edit`` (a :class:`virgi_ns.edit.stack.Edit`, or None) over the stack's edits without
        adding it to the stack: the uncommitted edit of a pick while its colour is dragged (nothing
        is written; committing adds it to the stack and clears this slot)."""
        self.live_edit = edit.to(self.device) if edit is not None else None

    def fingerprint(self) -> str:
        """The base run's fingerprint that every edit of it carries."""
        from virgi_ns.edit.stack import field_fingerprint

        return field_fingerprint(self.means.detach(), self.field,
                                 [self.quats.detach(), torch.exp(self.scales.detach()),
                                  torch.sigmoid(self.opacities.detach()).reshape(-1)])

    def _active_stack(self):
        st = self.edit_stack
        return None if st is None or st.is_identity else st

    def _edited_diffuse_cache(self, stack) -> Tensor:
        """``c_d''`` of every Gaussian through ``stack``, recomputed whenever the stack has changed
        since (:attr:`EditStack.revision`) or another stack is set. The cache holds the stack
        itself, so the identity it is compared by cannot pass to a new object."""
        cached = self._edited_cache
        if cached is None or cached[0] is not stack or cached[1] != stack.revision:
            self._edited_cache = (stack, stack.revision, stack.diffuse_all(self.field, self.means.detach()))
        return self._edited_cache[2]

    # ------------------------------------------------------------------ colours
    def pair_colours(self, contrib: Contributions, cams: Cameras, gated: bool = False,
                     segmentation: bool = False) -> Dict[str, Tensor]:
        """Per-pair ``rgb``, ``diffuse`` (sigmoid c_d), ``c_s`` (and ``segmentation``) for a
        contribution list, through the edit stack when one is set.

        Hash features and MLP_diff run once per distinct Gaussian, MLP_spec once per pair. With
        ``gated``, MLP_spec runs only for gated Gaussians and cached diffuse colours serve the rest.
        """
        pg = contrib.pair_gaussian.to(self.device)
        pv = contrib.pair_view.to(self.device)
        stack = self._active_stack()
        live = getattr(self, "live_edit", None)
        if pg.numel() == 0:
            z = torch.zeros(0, 3, device=self.device)
            return {"rgb": z, "diffuse": z, "c_s": z, "segmentation": z[:, :1]}
        means = self.means.detach()
        centres = cams.to(self.device).camera_centers().to(means.dtype)
        fld = self.field
        uniq = inv = f = h2 = None
        if gated and self.gate_ready() and fld.decoupled:
            cache = self._edited_diffuse_cache(stack) if stack is not None else self.diffuse_cache
            c_d = cache[pg]
            if live is not None:  # features of the visible Gaussians only: the live edit changes often
                u, i_u = torch.unique(pg, return_inverse=True)
                fu = fld.encode(means[u])
                c_d = live.over(fu, fld.diffuse_hidden(fu)[1], cache[u])[i_u]
            c_s = torch.zeros_like(c_d)
            sel = self.spec_gate[pg].nonzero().flatten()
            if sel.numel() > 0:
                g_sel = pg[sel]
                u_sel, i_sel = torch.unique(g_sel, return_inverse=True)
                fs = fld.encode(means[u_sel])
                hs1, hs2 = fld.diffuse_hidden(fs)
                d = view_directions(means[g_sel], centres[pv[sel]])
                c_s[sel] = fld.specular(fs[i_sel], d, hs1[i_sel], hs2[i_sel]).to(c_s.dtype)
        else:
            uniq, inv = torch.unique(pg, return_inverse=True)
            f = fld.encode(means[uniq])
            d = view_directions(means[pg], centres[pv])
            if fld.decoupled:
                h1, h2 = fld.diffuse_hidden(f)
                c_d_u = fld.diffuse(h2)
                if stack is not None:
                    c_d_u = stack.diffuse(f, h2, c_d_u)
                if live is not None:
                    c_d_u = live.over(f, h2, c_d_u)
                c_d = c_d_u[inv]
                c_s = fld.specular(f[inv], d, h1[inv], h2[inv])
            else:
                h1, h2p = fld.diffuse_hidden(f[inv], d)
                c_d = fld.diffuse(h2p)
                if stack is not None:
                    c_d = stack.diffuse(f[inv], h2p, c_d)
                if live is not None:
                    c_d = live.over(f[inv], h2p, c_d)
                c_s = torch.zeros_like(c_d)
        k = stack.specular_strength if stack is not None else 1.0
        out = {"rgb": torch.sigmoid(c_d + k * c_s), "diffuse": torch.sigmoid(c_d), "c_s": c_s}
        if segmentation:
            out["segmentation"] = self._pair_segmentation(pg, pv, cams, uniq, inv, f, h2)
        return out

    def _pair_segmentation(self, pg, pv, cams, uniq, inv, f, h2) -> Tensor:
        """Per-pair alpha of ``segmentation_edit`` (or of all enabled edits together) [U,1];
        zeros without edits."""
        st = self.edit_stack
        if st is None or len(st) == 0:
            return torch.zeros(pg.shape[0], 1, device=self.device)
        if self.segmentation_edit is not None and not 1 <= self.segmentation_edit <= len(st):
            self.segmentation_edit = None  # the selected edit was undone: show all enabled edits
        fld = self.field
        if f is None:  # the gated path computed no features for these pairs
            uniq, inv = torch.unique(pg, return_inverse=True)
            f = fld.encode(self.means.detach()[uniq])
        if h2 is None:  # gated, or the single MLP (whose hidden layers are per pair)
            if fld.decoupled:
                _, h2 = fld.diffuse_hidden(f)
            else:  # the single MLP's hidden layers need a direction: use each pair's
                centres = cams.to(self.device).camera_centers().to(f.dtype)
                d = view_directions(self.means.detach()[pg], centres[pv])
                _, h2 = fld.diffuse_hidden(f[inv], d)
                return st.segmentation(f[inv], h2, self.segmentation_edit).to(f.dtype)
        return st.segmentation(f, h2, self.segmentation_edit)[inv].to(f.dtype)

    # ----------------------------------------------------------- specular gate
    def gate_ready(self) -> bool:
        return self.spec_magnitude.numel() == self.num_points and self.diffuse_cache.shape[0] == self.num_points

    def drop_specular_gate(self) -> None:
        """Forget the gate and the cached diffuse colours (the field changes; renders take the full
        path until :meth:`build_specular_gate` runs again)."""
        self.spec_magnitude = self.spec_magnitude.new_zeros(0)
        self.diffuse_cache = self.diffuse_cache.new_zeros(0, 3)
        self._edited_cache = None

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
        self._edited_cache = None  # edited colours were computed from the previous field
        kept = float(self.spec_gate.float().mean()) if self.num_points else 0.0
        CONSOLE.log(f"virgi: specular gate keeps {kept:.1%} of {self.num_points:,} Gaussians")
        return {"kept_fraction": kept}

    # ------------------------------------------------------------------ renders
    @torch.no_grad()
    def render_camera(self, camera: NSCameras, gated: bool = False, max_pixels: int = 1 << 20
                      ) -> Dict[str, Tensor]:
        """Whole-image ``rgb``, ``diffuse``, ``specular`` (rgb - diffuse, no background), ``depth``,
        ``accumulation`` and ``segmentation`` (zeros without edits) for one camera, rendered in bands
        of rows, through the edit stack when one is set."""
        cams = raster_cameras(camera[0:1] if len(camera.shape) else camera.reshape((1,)))
        W, H = int(cams.widths[0]), int(cams.heights[0])
        bg = self.background_color.to(self.device)
        if self._renders_with_gsplat():
            return self._render_camera_gsplat(cams, gated, bg)
        rows = max(1, min(H, max_pixels // max(W, 1)))
        with_seg = self.edit_stack is not None and len(self.edit_stack) > 0
        names = ("rgb", "diffuse", "specular", "depth", "accumulation", "segmentation")
        parts: Dict[str, List[Tensor]] = {k: [] for k in names}
        # one composite per band for every output: rgb | diffuse | depth | segmentation channels
        # (the background only behind the two colours), so the lists are walked once
        zero = bg.new_zeros(1)
        bg_all = torch.cat([bg, bg, zero] + ([zero] if with_seg else []))
        for y0 in range(0, H, rows):
            h = min(rows, H - y0)
            req = Request(torch.zeros(1, dtype=torch.long), 0, y0, W, h)
            contrib = self._raster(cams, req)
            cols = self.pair_colours(contrib, cams, gated=gated, segmentation=with_seg)
            channels = [cols["rgb"], cols["diffuse"], contrib.pair_depth[:, None].to(cols["rgb"])]
            if with_seg:
                channels.append(cols["segmentation"].to(cols["rgb"]))
            img = composite(torch.cat(channels, dim=-1), contrib, bg_all)[0]
            rgb, diff, z_sum = img[..., 0:3], img[..., 3:6], img[..., 6:7]
            acc = contrib.accumulation()[0, ..., None].to(rgb)
            parts["rgb"].append(rgb)
            parts["diffuse"].append(diff)
            parts["specular"].append(rgb - diff)
            parts["depth"].append(expected_depth(z_sum, acc))
            parts["accumulation"].append(acc)
            parts["segmentation"].append(img[..., 7:8] if with_seg else rgb.new_zeros(h, W, 1))
        out: Dict[str, Tensor] = {k: torch.cat(v, dim=0) for k, v in parts.items()}
        out["rgb"] = out["rgb"].clamp(0, 1)
        out["diffuse"] = out["diffuse"].clamp(0, 1)
        out["background"] = bg
        return out

    def _renders_with_gsplat(self) -> bool:
        """Whole views on a GPU go through gsplat's forward rasterizer (``whole_view_renderer``)."""
        return self.config.whole_view_renderer == "gsplat" and self.device.type == "cuda"

    @torch.no_grad()
    def _render_camera_gsplat(self, cams: Cameras, gated: bool, bg: Tensor) -> Dict[str, Tensor]:
        """:meth:`render_camera`'s outputs from one gsplat rasterization. In one view every pair of
        a Gaussian has the same direction, so the colours are computed once per Gaussian (the same
        numbers the contribution path composites) and gsplat composites rgb, diffuse, segmentation
        and depth in one pass, at a plain splat's cost plus the colour model's."""
        from types import SimpleNamespace

        from gsplat.rendering import rasterization

        n = self.num_points
        with_seg = self.edit_stack is not None and len(self.edit_stack) > 0
        every = SimpleNamespace(pair_gaussian=torch.arange(n, device=self.device),
                                pair_view=torch.zeros(n, dtype=torch.long, device=self.device))
        cols = self.pair_colours(every, cams, gated=gated, segmentation=with_seg)  # type: ignore[arg-type]
        channels = [cols["rgb"], cols["diffuse"]] + ([cols["segmentation"].to(cols["rgb"])] if with_seg else [])
        colours = torch.cat(channels, dim=-1).float()
        zero = bg.new_zeros(1)
        bg_all = torch.cat([bg, bg] + ([zero] if with_seg else [])).float()[None]
        c = cams.to(self.device)
        W, H = int(c.widths[0]), int(c.heights[0])
        img, alpha, _ = rasterization(
            self.means.detach(), self.quats.detach(), torch.exp(self.scales.detach()),
            torch.sigmoid(self.opacities.detach()).reshape(-1), colours, c.viewmats.float(), c.Ks.float(), W, H,
            render_mode="RGB+ED", backgrounds=bg_all, packed=False, rasterize_mode="classic")
        img, acc = img[0], alpha[0]
        rgb, diff = img[..., 0:3].clamp(0, 1), img[..., 3:6].clamp(0, 1)
        return {"rgb": rgb, "diffuse": diff, "specular": img[..., 0:3] - img[..., 3:6],
                "depth": img[..., -1:] * (acc > 1e-10), "accumulation": acc,
                "segmentation": img[..., 6:7] if with_seg else rgb.new_zeros(H, W, 1), "background": bg}

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: NSCameras, obb_box=None) -> Dict[str, Tensor]:
        if obb_box is not None and self.geometry_frozen and not getattr(self, "_crop_notice", False):
            self._crop_notice = True
            CONSOLE.log("virgi: crop boxes are ignored when rendering the colour field")
        self.set_crop(None if self.geometry_frozen else obb_box)
        return self.get_outputs(camera.to(self.device))  # type: ignore[return-value]


__all__ = ["RenderPath"]
