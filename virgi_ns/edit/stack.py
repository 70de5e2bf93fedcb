"""Edits as small files beside a run, and the stack that composes them at render time.

An :class:`Edit` is what one edited photo leaves behind: a fine-tuned copy of the colour field's
diffuse head (``c_d' = W h_diff + b``), a :class:`SegmentationHead`
(``alpha = sigmoid(MLP_seg([f, h_diff]))``), the source image's path and camera, and the
fingerprint of the base run it was made on.

The :class:`EditStack` applies the enabled edits in order::

    c_d''_0 = c_d;   c_d''_i = alpha_i c_d'_i + (1 - alpha_i) c_d''_{i-1}

so a later edit overrides earlier ones where its alpha is high; the rendered colour is
``sigmoid(c_d''_n + k c_s)`` with the stack's specular strength ``k`` (0 removes highlights,
1.5 strengthens them). With no enabled edit and ``k = 1`` the stack is the identity.

On disk (``<run>/edits/``): ``stack.json`` (order, enable flags, ``k``, the run's fingerprint, each
edit's ``info``; :mod:`virgi_ns.edit.manifest` reads and changes it without torch) and one
``edit_NNNN.pt`` per edit (plain tensors and strings, loadable with
``torch.load(weights_only=True)``). Every write goes through :func:`virgi_ns.errors.atomic_path`;
nothing of the run itself is ever written. The stack is deliberately not an ``nn.Module``, so it
never enters a model's checkpoint.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.edit.heads import SegmentationHead
from virgi_ns.edit.manifest import EDITS_DIR, MANIFEST, edits_dir, read_manifest, remove_edit_files, write_manifest
from virgi_ns.errors import InputError, atomic_path

EDIT_FORMAT = "virgi-edit"
EDIT_VERSION = 1


# ------------------------------------------------------------------------------- edit
@dataclass
class EditSource:
    """Where an edit came from: the edited image's path, and the camera it was painted on
    (OpenCV world-to-camera ``viewmat`` [4,4], intrinsics ``K`` [3,3], image size)."""

    image: str
    K: Tensor
    viewmat: Tensor
    width: int
    height: int
    camera: str = ""
    """How the camera was chosen (e.g. 'train index 3', 'image IMG_0001.jpg', a JSON path)."""

    def to_dict(self) -> dict:
        return {"image": self.image, "K": self.K.detach().cpu().float(), "viewmat": self.viewmat.detach().cpu().float(),
                "width": int(self.width), "height": int(self.height), "camera": self.camera}

    @staticmethod
    def from_dict(d: dict) -> "EditSource":
        return EditSource(str(d["image"]), d["K"], d["viewmat"], int(d["width"]), int(d["height"]),
                          str(d.get("camera", "")))


@dataclass
class Edit:
    """One edit: a diffuse head ``(weight [3,H], bias [3])``, a segmentation head, its source,
    and the base run's fingerprint."""

    head_weight: Tensor
    head_bias: Tensor
    seg: SegmentationHead
    source: EditSource
    fingerprint: str
    info: dict = field(default_factory=dict)
    """Free-form numbers (steps, loss, setup/step seconds, k used while fitting)."""

    def to(self, device=None) -> "Edit":
        return Edit(self.head_weight.to(device), self.head_bias.to(device), self.seg.to(device), self.source,
                    self.fingerprint, dict(self.info))

    def diffuse(self, h_diff: Float[Tensor, "N H"]) -> Float[Tensor, "N 3"]:
        """``c_d'`` of this edit."""
        return torch.nn.functional.linear(h_diff, self.head_weight.to(h_diff), self.head_bias.to(h_diff))

    def alpha(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"]) -> Float[Tensor, "N 1"]:
        return self.seg(feats, h_diff).to(h_diff.dtype)

    def over(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"], c_d: Float[Tensor, "N 3"]
             ) -> Float[Tensor, "N 3"]:
        """``alpha c_d' + (1 - alpha) c_d``: this edit composed over the diffuse colour ``c_d``."""
        a = self.alpha(feats, h_diff).to(c_d.dtype)
        return a * self.diffuse(h_diff).to(c_d.dtype) + (1.0 - a) * c_d

    # ---- files
    def to_payload(self) -> dict:
        return {
            "format": EDIT_FORMAT,
            "version": EDIT_VERSION,
            "fingerprint": self.fingerprint,
            "head_weight": self.head_weight.detach().cpu().float().clone(),
            "head_bias": self.head_bias.detach().cpu().float().clone(),
            "seg_dims": [self.seg.feature_dim, self.seg.hidden_dim, self.seg.width],
            "seg_state": {k: v.detach().cpu().float().clone() for k, v in self.seg.state_dict().items()},
            "source": self.source.to_dict(),
            "info": json.dumps(self.info),
        }

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        with atomic_path(path) as tmp:
            torch.save(self.to_payload(), tmp)
        return path

    @staticmethod
    def load(path: str | Path) -> "Edit":
        """Read an edit file; anything that is not one raises :class:`InputError`."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"no such edit file: {path}")
        try:
            d = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
            raise InputError(f"{path} is not a virgi edit file ({type(e).__name__})") from None
        if not isinstance(d, dict) or d.get("format") != EDIT_FORMAT:
            raise InputError(f"{path} is not a virgi edit file")
        if int(d.get("version", -1)) > EDIT_VERSION:
            raise InputError(f"{path} was written by a newer virgi-ns (edit format {d.get('version')})")
        try:
            fdim, hdim, width = (int(x) for x in d["seg_dims"])
            seg = SegmentationHead(fdim, hdim, width)
            seg.load_state_dict(d["seg_state"])
            w, b = d["head_weight"], d["head_bias"]
            if w.shape != (3, hdim) or b.shape != (3,):
                raise ValueError("head shape")
            return Edit(w, b, seg, EditSource.from_dict(d["source"]), str(d["fingerprint"]),
                        json.loads(d.get("info", "{}")))
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{path} is a damaged virgi edit file ({type(e).__name__}: {e})") from None


# ------------------------------------------------------------------------------ stack
@dataclass
class StackEntry:
    edit: Edit
    file: str
    enabled: bool = True


class EditStack:
    """Ordered edits of one base run plus the specular strength; see the module docstring.

    ``EditStack(fingerprint)`` is an in-memory stack; :meth:`EditStack.open` reads (or starts)
    the one in ``<run_dir>/edits`` and every change is then written there at once."""

    def __init__(self, fingerprint: str, directory: Path | None = None, specular_strength: float = 1.0) -> None:
        self.fingerprint = fingerprint
        self.directory = Path(directory) if directory is not None else None
        self.entries: list[StackEntry] = []
        self._k = float(specular_strength)
        self.device: torch.device | None = None
        self.revision = 0
        """Counts the changes (edits added, replaced, undone, enabled or disabled, moved; ``k`` set): a cache of
        colours rendered through the stack is current while the stack object and this number are."""

    # ------------------------------------------------------------ persistence
    @staticmethod
    def edits_dir(run_dir: str | Path) -> Path:
        return edits_dir(run_dir)

    @classmethod
    def open(cls, run_dir: str | Path, fingerprint: str) -> "EditStack":
        """The stack saved beside ``run_dir`` (empty if there is none). A stack or an edit made
        for another base run raises :class:`InputError`."""
        m = read_manifest(run_dir)
        d = m.directory
        stack = cls(fingerprint, d)
        if not m.exists:
            return stack
        fp = m.fingerprint
        if fp == "" and not m.entries:  # a manifest written before the run's fingerprint was known
            fp = fingerprint
        if fp != fingerprint:
            raise InputError(f"the edits in {d} were made for another base run (fingerprint {fp}, this run {fingerprint})")
        stack._k = m.specular_strength
        for it in m.entries:
            edit = Edit.load(d / it["file"])
            stack._check(edit, d / it["file"])
            stack.entries.append(StackEntry(edit, it["file"], it["enabled"]))
        return stack

    def _check(self, edit: Edit, where: Path | str) -> None:
        if edit.fingerprint != self.fingerprint:
            raise InputError(f"{where} was made for another base run (fingerprint {edit.fingerprint}, "
                             f"this run {self.fingerprint})")

    def _write_manifest(self) -> None:
        if self.directory is None:
            return
        write_manifest(self.directory, self.fingerprint, self._k,
                       [{"file": e.file, "enabled": e.enabled, "image": e.edit.source.image,
                         "camera": e.edit.source.camera, "info": e.edit.info} for e in self.entries])

    def next_file(self) -> str:
        """The file name the next added edit gets (``edit_NNNN.pt``); its pictures may share the stem."""
        used = {e.file for e in self.entries}
        i = len(self.entries) + 1
        while True:
            name = f"edit_{i:04d}.pt"
            if name not in used and (self.directory is None or not (self.directory / name).exists()):
                return name
            i += 1

    # ------------------------------------------------------------- operations
    def __len__(self) -> int:
        return len(self.entries)

    @property
    def specular_strength(self) -> float:
        """``k``: the factor on ``c_s`` at render time."""
        return self._k

    def set_specular_strength(self, k: float) -> None:
        if not (k >= 0.0 and k < float("inf")):
            raise InputError(f"specular strength must be a finite number >= 0, got {k}")
        self._k = float(k)
        self.changed()
        self._write_manifest()

    def add(self, edit: Edit) -> int:
        """Append an edit (saved to its own file first, then the manifest); returns its 1-based number."""
        self._check(edit, "the edit")
        name = self.next_file()
        if self.directory is not None:
            edit.save(self.directory / name)
        self.entries.append(StackEntry(edit.to(self.device) if self.device is not None else edit, name, True))
        self.changed()
        try:
            self._write_manifest()
        except BaseException:
            self.entries.pop()
            self._remove_files(name)
            raise
        return len(self.entries)

    def replace(self, number: int, edit: Edit) -> None:
        """Put ``edit`` in the place of edit ``number`` (a pick adjusted after its release): the new
        file is written first, then the manifest; the old file and its pictures go last."""
        self._check(edit, "the edit")
        i = self._index(number)
        old = self.entries[i]
        name = self.next_file()
        if self.directory is not None:
            edit.save(self.directory / name)
        self.entries[i] = StackEntry(edit.to(self.device) if self.device is not None else edit, name, old.enabled)
        self.changed()
        try:
            self._write_manifest()
        except BaseException:
            self.entries[i] = old
            self.changed()
            self._remove_files(name)
            raise
        self._remove_files(old.file)

    def _remove_files(self, file: str) -> None:
        """An edit's file and the pictures saved beside it (``<stem>_*.png``, a pick's)."""
        if self.directory is not None:
            remove_edit_files(self.directory, file)

    def import_file(self, path: str | Path) -> int:
        """Add an edit file made elsewhere (refused when made for another base run)."""
        edit = Edit.load(path)
        self._check(edit, path)
        return self.add(edit)

    def _index(self, number: int) -> int:
        if not 1 <= number <= len(self.entries):
            raise InputError(f"no edit number {number}: the stack holds {len(self.entries)} edit(s)"
                             + (f" (1..{len(self.entries)})" if self.entries else ""))
        return number - 1

    def set_enabled(self, number: int, enabled: bool) -> None:
        """Enable or disable edit ``number`` (1-based, as :meth:`rows` lists them)."""
        self.entries[self._index(number)].enabled = bool(enabled)
        self.changed()
        self._write_manifest()

    def undo(self) -> Edit:
        """Remove the last edit (its file too) and return it."""
        if not self.entries:
            raise InputError("nothing to undo: the edit stack is empty")
        last = self.entries.pop()
        self.changed()
        self._write_manifest()
        self._remove_files(last.file)
        return last.edit

    def reset(self) -> int:
        """Remove every edit and set the specular strength back to 1; returns how many were removed."""
        n = len(self.entries)
        files = [e.file for e in self.entries]
        self.entries.clear()
        self._k = 1.0
        self.changed()
        self._write_manifest()
        for f in files:
            self._remove_files(f)
        return n

    def rows(self) -> list[dict]:
        """One dict per edit: number, enabled, file, image, camera, info."""
        return [{"number": i + 1, "enabled": e.enabled, "file": e.file, "image": e.edit.source.image,
                 "camera": e.edit.source.camera, "info": e.edit.info} for i, e in enumerate(self.entries)]

    def to(self, device) -> "EditStack":
        """Move the edits' tensors (in place) and return self."""
        self.device = torch.device(device)
        for e in self.entries:
            e.edit = e.edit.to(self.device)
        self.changed()
        return self

    def changed(self) -> None:
        """Note a change of what the stack renders. Every operation here calls it; code that changes
        an edit's tensors in place (a live refit) must call it too."""
        self.revision += 1

    # ------------------------------------------------------------- rendering
    @property
    def active(self) -> list[Edit]:
        return [e.edit for e in self.entries if e.enabled]

    @property
    def is_identity(self) -> bool:
        """True when rendering through the stack changes nothing (no enabled edit, k = 1)."""
        return not self.active and self._k == 1.0

    def diffuse(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"], c_d: Float[Tensor, "N 3"]
                ) -> Float[Tensor, "N 3"]:
        """``c_d''``: the base ``c_d`` (pre-sigmoid) with every enabled edit composed in order."""
        out = c_d
        for edit in self.active:
            out = edit.over(feats, h_diff, out)
        return out

    def colour(self, c_d_edited: Tensor, c_s: Tensor) -> Tensor:
        """``sigmoid(c_d'' + k c_s)``."""
        return torch.sigmoid(c_d_edited + self._k * c_s)

    def segmentation(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"], index: int | None = None
                     ) -> Float[Tensor, "N 1"]:
        """Alpha of edit ``index`` (1-based, enabled or not); with ``index=None`` the share of the
        final diffuse colour that comes from any enabled edit, ``1 - prod(1 - alpha_i)``."""
        if index is not None:
            return self.entries[self._index(index)].edit.alpha(feats, h_diff)
        keep = feats.new_ones(feats.shape[0], 1, dtype=h_diff.dtype)
        for edit in self.active:
            keep = keep * (1.0 - edit.alpha(feats, h_diff))
        return 1.0 - keep

    @torch.no_grad()
    def diffuse_all(self, field_module, means: Tensor, chunk: int = 1 << 16) -> Tensor:
        """``c_d''`` of every Gaussian (e.g. to refill a model's cache of diffuse colours)."""
        out = []
        for s in range(0, means.shape[0], chunk):
            f = field_module.encode(means[s : s + chunk])
            _, h2 = field_module.diffuse_hidden(f)
            out.append(self.diffuse(f, h2, field_module.diffuse(h2)))
        return torch.cat(out) if out else means.new_zeros(0, 3)


def new_edit_info(**kw) -> dict:
    """The ``info`` of a fresh edit: the caller's numbers plus a creation time."""
    return {"created": time.strftime("%Y-%m-%d %H:%M:%S"), **kw}


__all__ = ["EDITS_DIR", "MANIFEST", "Edit", "EditSource", "EditStack", "SegmentationHead", "new_edit_info"]
