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
from virgi_ns.raster import Cameras, Contributions, Request, composite, composite_depth


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
        """``c_d''`` of every Gaussian through ``stack``, recomputed when its enabled edits change."""
        key = tuple((id(e.edit), e.enabled) for e in stack.entries)
        if self._edited_cache is None or self._edited_cache[0] != key:
            self._edited_cache = (key, stack.diffuse_all(self.field, self.means.detach()))
        return self._edited_cache[1]

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
        rows = max(1, min(H, max_pixels // max(W, 1)))
        with_seg = self.edit_stack is not None and len(self.edit_stack) > 0
        names = ("rgb", "diffuse", "specular", "depth", "accumulation", "segmentation")
        parts: Dict[str, List[Tensor]] = {k: [] for k in names}
        for y0 in range(0, H, rows):
            h = min(rows, H - y0)
            req = Request(torch.zeros(1, dtype=torch.long), 0, y0, W, h)
            contrib = self._raster(cams, req)
            cols = self.pair_colours(contrib, cams, gated=gated, segmentation=with_seg)
            rgb = composite(cols["rgb"], contrib, bg)[0]
            if with_seg:
                parts["segmentation"].append(composite(cols["segmentation"], contrib)[0])
            else:
                parts["segmentation"].append(rgb.new_zeros(h, W, 1))
            diff = composite(cols["diffuse"], contrib, bg)[0]
            parts["rgb"].append(rgb)
            parts["diffuse"].append(diff)
            parts["specular"].append(rgb - diff)
            parts["depth"].append(composite_depth(contrib)[0].to(rgb))
            parts["accumulation"].append(contrib.accumulation()[0, ..., None].to(rgb))
        out: Dict[str, Tensor] = {k: torch.cat(v, dim=0) for k, v in parts.items()}
        out["rgb"] = out["rgb"].clamp(0, 1)
        out["diffuse"] = out["diffuse"].clamp(0, 1)
        out["background"] = bg
        return out

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: NSCameras, obb_box=None) -> Dict[str, Tensor]:
        if obb_box is not None and self.geometry_frozen and not getattr(self, "_crop_notice", False):
            self._crop_notice = True
            CONSOLE.log("virgi: crop boxes are ignored when rendering the colour field")
        self.set_crop(None if self.geometry_frozen else obb_box)
        return self.get_outputs(camera.to(self.device))  # type: ignore[return-value]


__all__ = ["RenderPath"]
