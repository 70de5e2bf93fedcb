"""Rendering and exporting a run whose unedited colours are the splat file's own (``base_colours="file"``).

:class:`FileColourPath` is mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` ahead of the
field's render path: with the option on, a view's colour per Gaussian is the file's SH colour plus
the edits' change (:class:`~virgi_ns.colour.file_colours.FileColours`), every Gaussian no edit
touches showing exactly the file's colour; the colour field is read only for the edits (their
segmentation and copied layer run on its features). The edit engine takes the same base through
:class:`~virgi_ns.edit.scene.FrozenScene` (``file_colours``), and :func:`virgi_ns.nerfstudio.export.bake_file_colours` exports
the file's own coefficients for untouched Gaussians and adds a fit of the change to the others.

The option needs geometry imported from a splat file in the capture's frame (the coefficients' own
frame, to which exports return) and the decoupled field (its diffuse head does not see the view).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch
from torch import Tensor

from virgi_ns.colour.file_colours import FileColours
from virgi_ns.errors import InputError

CHUNK = 1 << 18
CHECKPOINT_SUFFIXES = (".ckpt", ".yml", ".yaml", ".pt", ".pth")

__all__ = ["FileColourPath", "edited_diffuse_logits", "import_frame", "resolve_base_colours"]


def import_frame(geometry_from, geometry_frame: str) -> str:
    """The frame an imported splat is read in ('capture' or 'dataparser'), by the model's rule for
    ``geometry_frame="auto"``: splatfacto checkpoints and runs are 'dataparser', files 'capture'."""
    if geometry_frame != "auto":
        return geometry_frame
    path = Path(str(geometry_from))
    return "dataparser" if path.suffix.lower() in CHECKPOINT_SUFFIXES or path.is_dir() else "capture"


def resolve_base_colours(cfg, metadata: Optional[dict]) -> str:
    """``cfg.base_colours`` with 'auto' resolved ('file' for the splat dataparser's runs, whose
    metadata names the splat), checked against what 'file' needs."""
    mode = getattr(cfg, "base_colours", "auto")
    if mode == "auto":
        mode = "file" if (metadata or {}).get("virgi_splat") is not None else "field"
    if mode == "file":
        if cfg.geometry_from is None or import_frame(cfg.geometry_from, cfg.geometry_frame) != "capture":
            raise InputError("--pipeline.model.base-colours file needs the geometry imported from a splat file in the "
                             "capture's frame (--pipeline.model.geometry-from FILE, or the splat dataparser)")
        if not cfg.color_field.decoupled:
            raise InputError("--pipeline.model.base-colours file needs the decoupled colour field (virgi, not "
                             "virgi-vanilla)")
    return mode


class FileColourPath:
    """Mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` before
    :class:`~virgi_ns.nerfstudio.render_path.RenderPath`: with ``base_colours="file"`` it renders
    views from the file's colours (:meth:`view_colours`) and skips the specular gate, which only the
    field's colours use; otherwise it hands every call on."""

    def uses_file_colours(self) -> bool:
        return getattr(self, "base_colours", "field") == "file"

    def file_colours(self) -> Optional[FileColours]:
        """The Gaussians' own colours (their SH coefficients, in the capture's frame), or None
        without the option. Kept while the coefficients are unchanged."""
        if not self.uses_file_colours():
            return None
        dc, rest = self.features_dc, self.features_rest
        key = (id(dc), dc._version, id(rest), rest._version, dc.device)
        kept = getattr(self, "_file_colours_kept", None)
        if kept is None or kept[0] != key:
            rot = getattr(self, "_sh_rotation", None)
            fc = FileColours(dc.detach(), rest.detach(), None if rot is None else rot.to(dc.device))
            kept = self._file_colours_kept = (key, fc, {})
        return kept[1]

    # ---------------------------------------------------------------- rendering
    def view_colours(self, view, gated: bool = False, transient: bool = False):
        fc = self.file_colours()
        if fc is None:
            return super().view_colours(view, gated, transient)  # type: ignore[misc]
        return self._file_view_colours(fc, view)

    @torch.no_grad()
    def _file_view_colours(self, fc: FileColours, view):
        from virgi_ns.nerfstudio.render_cache import ViewColours

        means = self.means.detach()
        dirs = (means - view.centre.to(means)) if fc.view_dependent else None
        rgb = fc.colours(None, dirs)
        state = self._file_edit_state(fc)
        if state is not None and state["index"].numel():
            idx, e, k = state["index"], state["edited"], state["k"]
            b, s = fc.logits(idx, None if dirs is None else dirs[idx])
            rgb = rgb.index_copy(0, idx, rgb[idx] + fc.change(b, s, e, k))
        diffuse = None
        if fc.view_dependent:
            diffuse = state["diffuse"] if state is not None else fc.dc_colours()
        seg = (lambda: self._segmentation_from_field(view.centre)) if self._with_segmentation() else None
        return ViewColours(rgb.to(means.dtype), diffuse, seg)

    def _file_edit_state(self, fc: FileColours) -> Optional[dict]:
        """What the edits change, kept per edit state (the stack's identity and revision, the live edit,
        ``k``): the touched Gaussians' indices [T], their edited diffuse logits [T,3], and every
        Gaussian's edited degree-0 colour [N,3]. None when nothing is edited."""
        stack = self.active_stack()
        live = getattr(self, "live_edit", None)
        k = float(stack.specular_strength) if stack is not None else 1.0
        if stack is None and live is None:
            return None
        key = (id(stack), getattr(stack, "revision", None), id(live), getattr(self, "_live_revision", 0), k,
               id(self.field), tuple(p._version for p in self.field.parameters()))
        store = self._file_colours_kept[2]
        if store.get("key") == key:
            return store["state"]
        fld = self.field
        means = self.means.detach()
        b_all = fc.base_logits()
        edited = []
        for s in range(0, means.shape[0], CHUNK):
            f = fld.encode(means[s : s + CHUNK])
            _, h2 = fld.diffuse_hidden(f)
            c = fld.diffuse(h2)
            e = c
            if stack is not None:
                e = stack.diffuse(f, h2, e)
            if live is not None:
                e = live.over(f, h2, e)
            edited.append(fc.edited_logits(b_all[s : s + CHUNK], c, e))
        e_all = torch.cat(edited) if edited else b_all
        touched = fc.touched(b_all, e_all, k)
        idx = touched.nonzero().flatten()
        diffuse = fc.dc_colours().clone()
        diffuse[idx] = diffuse[idx] + torch.sigmoid(e_all[idx]) - torch.sigmoid(b_all[idx])
        state = {"index": idx, "edited": e_all[idx].contiguous(), "k": k, "diffuse": diffuse}
        store.clear()
        store.update(key=key, state=state)
        return state

    def build_specular_gate(self, cams, chunk: int = 65536):
        if self.uses_file_colours():  # renders never read the field's specular colours
            return {"kept_fraction": 0.0}
        return super().build_specular_gate(cams, chunk)  # type: ignore[misc]


# ------------------------------------------------------------------------------ export
@torch.no_grad()
def edited_diffuse_logits(model, fc: FileColours, stack) -> Tensor:
    """Every Gaussian's diffuse logit ``e`` after the stack's enabled edits: the file's, moved by the
    change the edits make to the field's (:meth:`FileColours.edited_logits`)."""
    b = fc.base_logits()
    if stack is None or not len(stack.active):
        return b
    fld = model.field
    means = model.means.detach()
    out = []
    for s in range(0, means.shape[0], CHUNK):
        f = fld.encode(means[s : s + CHUNK])
        _, h2 = fld.diffuse_hidden(f)
        c = fld.diffuse(h2)
        out.append(fc.edited_logits(b[s : s + CHUNK], c, stack.diffuse(f, h2, c)))
    return torch.cat(out) if out else b
