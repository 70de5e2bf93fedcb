"""VIRGi's panel in nerfstudio's viewer: save a view, edit it anywhere, upload it, apply it.

The panel is one nerfstudio :class:`ViewerElement` (and :class:`ViewerControl`) held by the model
as ``model.viewer_panel``; the viewer finds it by walking the pipeline's attributes, installs it
in its "Custom Elements" folder, then hands it the viewer (for the client's camera, the render
lock, the run directory and the output selector). It holds, top to bottom:

- a status line (progress and errors; a failed action never stops the server);
- **Display** (rgb, diffuse, specular, segmentation of the selected edit): sets the viewer's
  output type; **Specular strength** ``k``;
- **Save this view**: renders the client's view (longest side **Save size**), writes
  ``<run>/views/view_NNN.png`` and its camera ``view_NNN.json`` (``virgi-render``'s CAM.json, in
  the capture's original frame, as the exported splat) and sends both to the browser;
- **Upload edited image** (:class:`ViewerUpload`, over viser's upload button) and **Apply edit**:
  fits an edit (:class:`virgi_ns.edit.engine.EditEngine`) for the saved view the image came from (its
  name holds ``view_NNN``; otherwise the last saved view), in a background thread with progress;
- the edits with enable toggles, the edit whose segmentation is shown, **Undo**, **Reset**;
- **Export**: bakes the edited scene to a splat file (:mod:`virgi_ns.nerfstudio.export`).

Every action is also a plain method (:meth:`VirgiPanel.save_view`, :meth:`VirgiPanel.upload`,
:meth:`VirgiPanel.apply_edit`, ...) usable without a viewer.
"""

from __future__ import annotations

import io
import json
import re
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, List, Optional

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import (
    ViewerButton,
    ViewerCheckbox,
    ViewerControl,
    ViewerDropdown,
    ViewerElement,
    ViewerNumber,
    ViewerSlider,
)

from virgi_ns.errors import InputError, VirgiError, atomic_path
from virgi_ns.io.camera_json import parse_camera
from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.nerfstudio.frames import camera_from_spec, camera_spec, capture_frame

if TYPE_CHECKING:
    from viser import ViserServer

DISPLAYS = ["rgb", "diffuse", "specular", "segmentation"]
ALL_EDITS = "all enabled edits"
MAX_UPLOAD_BYTES = 64 << 20
MAX_DOWNLOAD_BYTES = 64 << 20
_VIEW_RE = re.compile(r"view_(\d+)")


# ------------------------------------------------------------------------ upload element
@dataclass
class Upload:
    """An uploaded file: its name and bytes."""

    name: str
    content: bytes


class ViewerUpload(ViewerElement[Optional[Upload]]):
    """A file upload button (viser's ``add_upload_button``); ``cb_hook(element)`` runs after each
    upload, with the file in ``element.value``."""

    def __init__(self, name: str, cb_hook: Callable[["ViewerUpload"], Any] = lambda element: None,
                 mime_type: str = "*/*", hint: Optional[str] = None, disabled: bool = False,
                 visible: bool = True) -> None:
        super().__init__(name, disabled=disabled, visible=visible, cb_hook=cb_hook)
        self.mime_type = mime_type
        self.hint = hint
        self._value: Optional[Upload] = None

    def _create_gui_handle(self, viser_server: "ViserServer") -> None:
        import viser

        self.gui_handle = viser_server.gui.add_upload_button(  # type: ignore[assignment]
            self.name, disabled=self.disabled, visible=self.visible, hint=self.hint, mime_type=self.mime_type,
            icon=viser.Icon.UPLOAD)

    def install(self, viser_server: "ViserServer") -> None:
        self._create_gui_handle(viser_server)
        assert self.gui_handle is not None

        def on_upload(event) -> None:
            f = event.target.value
            self._value = Upload(str(f.name), bytes(f.content))
            self.cb_hook(self)

        self.gui_handle.on_upload(on_upload)  # type: ignore[union-attr]

    @property
    def value(self) -> Optional[Upload]:
        return self._value

    @value.setter
    def value(self, value: Optional[Upload]) -> None:
        self._value = value


# ------------------------------------------------------------------------ saved views
@dataclass
class SavedView:
    """A view saved from the viewer: its number, files, the render [H,W,3] in [0,1] and camera
    (dataparser frame, the model's)."""

    number: int
    png: Path
    json: Path
    camera: NSCameras
    image: np.ndarray

    @property
    def name(self) -> str:
        return f"view_{self.number:03d}"


def png_bytes(image: np.ndarray) -> bytes:
    """8-bit PNG of an [H,W,3] image in [0,1]."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray((np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def decode_image(name: str, content: bytes) -> np.ndarray:
    """[H,W,3] float32 in [0,1] of an uploaded image; anything else is an :class:`InputError`."""
    from PIL import Image, UnidentifiedImageError

    if not content:
        raise InputError(f"{name or 'the upload'} is empty")
    if len(content) > MAX_UPLOAD_BYTES:
        raise InputError(f"{name} is larger than {MAX_UPLOAD_BYTES >> 20} MiB")
    try:
        with Image.open(io.BytesIO(content)) as im:
            im.load()
            if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
                im = im.convert("RGBA")
                rgb = np.asarray(im, dtype=np.float32)[..., :3] / 255.0
            else:
                rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError):
        raise InputError(f"{name or 'the upload'} is not an image (PNG, JPEG, ...)") from None
    return rgb


# ---------------------------------------------------------------------------- the panel
class VirgiPanel(ViewerElement[None], ViewerControl):
    """The VIRGi panel for ``model`` (a :class:`virgi_ns.nerfstudio.model.VirgiModel`); see the module
    docstring. ``run_dir``: where edits and saved views go (default: the viewer's run directory,
    else a temporary one)."""

    def __init__(self, model, run_dir: Optional[Path] = None, folder: str = "VIRGi edit") -> None:
        super().__init__(folder)
        self._model = model  # a plain attribute: the viewer walks public attributes only
        self._run_dir = Path(run_dir) if run_dir is not None else None
        self._own_lock = threading.Lock()
        self._busy = threading.Lock()
        self._worker: Optional[threading.Thread] = None
        self.viewer = None
        self._server: Any = None
        self.pending: Optional[tuple[str, np.ndarray, SavedView]] = None
        self.status = "Save a view, edit the PNG in any image editor, upload it and apply."
        self.status_is_error = False
        self.progress = 0.0
        self.views: List[SavedView] = []
        self.last_download: List[tuple[str, bytes]] = []
        self.last_export: Optional[Path] = None
        self._status_md = None
        self._progress_bar = None
        self._edits_folder = None
        self._edit_boxes: List[ViewerCheckbox] = []

        self.display = ViewerDropdown("Display", "rgb", list(DISPLAYS), cb_hook=lambda e: self._guard(lambda: self.set_display(e.value)),
                                      hint="rgb, diffuse, specular, or the selected edit's segmentation")
        self.specular = ViewerSlider("Specular strength", 1.0, 0.0, 2.0, 0.05,
                                     cb_hook=lambda e: self.set_specular_strength(float(e.value)),
                                     hint="k in sigmoid(c_d'' + k c_s): 0 removes highlights")
        self.save_size = ViewerNumber("Save size (px)", self._default_save_size(),
                                      hint="Longest side of a saved view")
        self.save_button = ViewerButton("Save this view", cb_hook=lambda e: None)
        self.upload_element = ViewerUpload("Upload edited image", cb_hook=lambda e: self._on_upload(e),
                                           mime_type="image/*", hint="The saved view, recoloured in any editor")
        self.apply_button = ViewerButton("Apply edit", cb_hook=lambda e: self._guard(self.apply_edit))
        self.selected = ViewerDropdown("Segmentation of", ALL_EDITS, [ALL_EDITS],
                                       cb_hook=lambda e: self._guard(lambda: self.select_edit(e.value)))
        self.undo_button = ViewerButton("Undo", cb_hook=lambda e: self._guard(self.undo))
        self.reset_button = ViewerButton("Reset", cb_hook=lambda e: self._guard(self.reset))
        self.export_button = ViewerButton("Export", cb_hook=lambda e: None)

    # ----------------------------------------------------------------- nerfstudio hooks
    def _create_gui_handle(self, viser_server: "ViserServer") -> None:
        self.gui_handle = viser_server.gui.add_folder(self.name)  # type: ignore[assignment]

    def install(self, viser_server: "ViserServer") -> None:
        """Add the panel's widgets (the viewer calls this inside its custom-elements folder)."""
        self._server = viser_server
        self._create_gui_handle(viser_server)
        with self.gui_handle:  # type: ignore[union-attr]
            self._status_md = viser_server.gui.add_markdown(self._status_text())
            self._progress_bar = viser_server.gui.add_progress_bar(0.0, visible=False)
            for e in (self.display, self.specular, self.save_size, self.save_button, self.upload_element,
                      self.apply_button, self.selected):
                e.install(viser_server)
            self._edits_folder = viser_server.gui.add_folder("Edits")
            for e in (self.undo_button, self.reset_button, self.export_button):
                e.install(viser_server)
        self.save_button.gui_handle.on_click(lambda ev: self._guard(lambda: self.save_view(client=ev.client)))
        self.export_button.gui_handle.on_click(lambda ev: self._guard(lambda: self.export(client=ev.client)))
        self._refresh_edits()

    def _setup(self, viewer) -> None:
        """Called by the viewer after installing: keep it, then load the run's saved edits."""
        ViewerControl._setup(self, viewer)
        self._server = viewer.viser_server
        if self._run_dir is None:
            log = getattr(viewer, "log_filename", None)
            if log is not None:
                self._run_dir = Path(log).parent
        if self.save_size.value == self.save_size.default_value:
            self.save_size.value = self._default_save_size()
        if getattr(self._model, "geometry_frozen", False):
            stack = self._guard(self._stack)
            if stack is not None and abs(float(self.specular.value) - stack.specular_strength) > 1e-9:
                self.specular.value = float(stack.specular_strength)
        self._refresh_edits()

    # --------------------------------------------------------------------- plumbing
    @property
    def model(self):
        return self._model

    @property
    def run_dir(self) -> Path:
        if self._run_dir is None:
            self._run_dir = Path(tempfile.mkdtemp(prefix="virgi_viewer_"))
        return self._run_dir

    def _lock(self):
        lock = getattr(self.viewer, "train_lock", None)
        return lock if lock is not None else self._own_lock

    def _rerender(self) -> None:
        """Ask the viewer for a new frame (the hook it installs takes its render lock)."""
        if self.viewer is not None:
            try:
                self.cb_hook(self)
            except Exception as e:  # noqa: BLE001 - never let a redraw request break an action
                CONSOLE.log(f"virgi viewer: rerender failed: {e}")

    def set_status(self, text: str, error: bool = False, log: bool = True) -> None:
        self.status, self.status_is_error = text, error
        if self._status_md is not None:
            self._status_md.content = self._status_text()
        if log:
            CONSOLE.log(f"virgi viewer: {'error: ' if error else ''}{text}")

    def _status_text(self) -> str:
        return f"**Error:** {self.status}" if self.status_is_error else self.status

    def _set_progress(self, fraction: Optional[float]) -> None:
        self.progress = 0.0 if fraction is None else float(fraction)
        bar = self._progress_bar
        if bar is not None:
            if fraction is None:
                bar.visible = False
            else:
                bar.value = max(0.0, min(100.0, 100.0 * float(fraction)))
                bar.visible = True

    def _guard(self, action: Callable[[], Any]) -> Any:
        """Run a panel action; user errors (and any other failure) go to the status line."""
        try:
            return action()
        except VirgiError as e:
            self.set_status(str(e), error=True)
        except Exception as e:  # noqa: BLE001 - the server keeps serving whatever happens
            self.set_status(f"{type(e).__name__}: {e}", error=True)
        return None

    def _default_save_size(self) -> int:
        dm = getattr(getattr(self.viewer, "pipeline", None), "datamanager", None)
        try:
            cams = dm.train_dataset.cameras  # type: ignore[union-attr]
            return int(max(int(cams.width.max()), int(cams.height.max())))
        except Exception:  # noqa: BLE001 - no dataset: a plain default
            return 1024

    def _stack(self):
        """The model's edit stack, opened from ``<run>/edits`` (or started) on first use."""
        from virgi_ns.edit.stack import EditStack

        m = self._model
        if m.edit_stack is None:
            if not getattr(m, "geometry_frozen", True):
                raise InputError("the geometry is still training: edits need the frozen colour stage")
            stack = EditStack.open(self.run_dir, m.fingerprint())
            with self._lock():
                m.set_edit_stack(stack)
        return m.edit_stack

    def _check_idle(self) -> None:
        if self._worker is not None and self._worker.is_alive():
            raise InputError("an edit is being applied; wait for it to finish")

    # ---------------------------------------------------------------------- display
    def _output_selector(self):
        return getattr(getattr(self.viewer, "control_panel", None), "_output_render", None)

    def set_display(self, value: str) -> None:
        """Show ``value`` (rgb, diffuse, specular, segmentation) in the viewer."""
        if value not in DISPLAYS:
            self.set_status(f"unknown display {value!r}", error=True)
            return
        st = self._model.edit_stack
        if value == "segmentation" and (st is None or len(st) == 0):
            self.set_status("segmentation needs an edit: apply one first", error=True)
            self.display.value = "rgb"
            return
        sel = self._output_selector()
        if sel is not None and sel.value != value:
            if value not in sel.options:
                sel.set_options(list(sel.options) + [value])
            sel.value = value  # the viewer's own callbacks redraw

    def set_specular_strength(self, k: float) -> None:
        def run():
            stack = self._stack()
            if abs(stack.specular_strength - k) < 1e-9:
                return
            with self._lock():
                stack.set_specular_strength(k)
            self.set_status(f"specular strength {k:.2f}")
            self._rerender()

        self._guard(run)

    def select_edit(self, value: str) -> None:
        """Which edit's segmentation the ``segmentation`` display shows."""
        m = self._model
        with self._lock():
            m.segmentation_edit = None if value == ALL_EDITS else int(value.split()[-1])
        if self.display.value == "segmentation":
            self._rerender()

    # --------------------------------------------------------------------- save view
    def _client_camera(self, client=None) -> NSCameras:
        if self.viewer is None or not self.viser_server.get_clients():
            raise InputError("no browser is connected to the viewer")
        cid = getattr(client, "client_id", None)
        clients = self.viser_server.get_clients()
        c = clients.get(cid) if cid is not None else next(iter(clients.values()))
        aspect = float(c.camera.aspect)
        L = int(self.save_size.value)
        if not 8 <= L <= 8192:
            raise InputError(f"save size must be 8..8192 pixels, got {L}")
        W, H = (L, max(1, round(L / aspect))) if aspect >= 1 else (max(1, round(L * aspect)), L)
        cam = self.get_camera(H, W, cid)
        if cam is None:
            raise InputError("no browser is connected to the viewer")
        return cam

    def save_view(self, camera: Optional[NSCameras] = None, client=None) -> SavedView:
        """Render ``camera`` (default: the browser's current view) through the current edits,
        write ``view_NNN.png`` + ``view_NNN.json`` under ``<run>/views`` and offer both as downloads."""
        m = self._model
        cam = camera if camera is not None else self._client_camera(client)
        cam = cam.reshape((1,)) if len(cam.shape) == 0 else cam[0:1]
        with self._lock():
            was_training = m.training
            m.eval()
            try:
                out = m.get_outputs_for_camera(cam.to(m.device))
            finally:
                m.train(was_training)
        image = out["rgb"][..., :3].detach().float().cpu().clamp(0, 1).numpy()
        T, s = capture_frame(m)
        spec = camera_spec(cam.to("cpu"), T, s)
        vdir = self.run_dir / "views"
        number = 1 + max([0] + [v.number for v in self.views]
                         + [int(mm.group(1)) for p in vdir.glob("view_*.json") if (mm := _VIEW_RE.fullmatch(p.stem))])
        view = SavedView(number, vdir / f"view_{number:03d}.png", vdir / f"view_{number:03d}.json", cam.to("cpu"),
                         image)
        png = png_bytes(image)
        meta = {**spec.to_dict(), "frame": "capture" if m.kwargs.get("metadata", {}).get(
            "virgi_capture_transform") is not None else "dataparser", "image": view.png.name}
        text = json.dumps(meta, indent=2) + "\n"
        with atomic_path(view.png) as tmp:
            tmp.write_bytes(png)
        with atomic_path(view.json) as tmp:
            tmp.write_text(text, encoding="utf-8")
        self.views.append(view)
        self.last_download = [(view.png.name, png), (view.json.name, text.encode())]
        target = client if client is not None else self.viser_server if self.viewer is not None else None
        if target is not None:
            for name, data in self.last_download:
                target.send_file_download(name, data)
        self.set_status(f"saved {view.name} ({spec.width}x{spec.height}) to {view.png.parent}; "
                        f"edit {view.png.name} and upload it")
        return view

    def _view_for(self, name: str) -> SavedView:
        """The saved view an uploaded file belongs to: ``view_NNN`` in its name, else the last."""
        mm = _VIEW_RE.search(name or "")
        if mm is not None:
            n = int(mm.group(1))
            for v in self.views:
                if v.number == n:
                    return v
            js = self.run_dir / "views" / f"view_{n:03d}.json"
            if js.is_file():
                return self._load_view(n, js)
        if self.views:
            return self.views[-1]
        raise InputError("no saved camera: press 'Save this view' first, then edit and upload that image")

    def _load_view(self, n: int, path: Path) -> SavedView:
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read {path}: {e}") from None
        spec = parse_camera(d, str(path))
        T, s = capture_frame(self._model) if d.get("frame", "capture") == "capture" else (torch.eye(4)[:3].double(),
                                                                                          1.0)
        view = SavedView(n, path.with_suffix(".png"), path, camera_from_spec(spec, T, s),
                         np.zeros((spec.height, spec.width, 3), np.float32))
        self.views.append(view)
        return view

    # ------------------------------------------------------------------- upload + apply
    def _on_upload(self, element: ViewerUpload) -> None:
        up = element.value
        if up is not None:
            self._guard(lambda: self.upload(up.name, up.content))

    def upload(self, name: str, content: bytes) -> tuple[np.ndarray, SavedView]:
        """Check an uploaded edited image against its saved view; keeps it for :meth:`apply_edit`."""
        self.pending = None
        image = decode_image(name, content)
        view = self._view_for(name)
        H, W = view.camera.height.item(), view.camera.width.item()
        if image.shape[:2] != (H, W):
            raise InputError(f"{name} is {image.shape[1]}x{image.shape[0]} but {view.name} is {W}x{H}: "
                             "upload the saved view's image, edited without resizing")
        self.pending = (name, image, view)
        self.set_status(f"{name} ({W}x{H}) is ready for {view.name}: press 'Apply edit'")
        return image, view

    def apply_edit(self, wait: bool = False, steps: Optional[int] = None) -> threading.Thread:
        """Fit an edit from the uploaded image for its saved view, in a background thread
        (``wait``: join it). Progress and the outcome go to the status line."""
        self._check_idle()
        if self.pending is None:
            if not self.views:
                raise InputError("no saved camera: press 'Save this view' first, then edit and upload that image")
            raise InputError("no edited image: upload the edited view first")
        name, image, view = self.pending
        stack = self._stack()
        self.pending = None
        return self._background(f"applying {name} to {view.name}", "the edit",
                                lambda progress: self._fit(name, image, view, stack, steps, progress), wait)

    def _background(self, label: str, what: str, job: Callable[[Callable[[int, int], None]], str],
                    wait: bool) -> threading.Thread:
        """Run ``job(progress)`` in a worker thread; its returned line (or its error) goes to the
        status line, ``progress(done, total)`` to the progress bar."""

        def progress(done: int, total: int) -> None:
            self._set_progress(done / max(total, 1))
            self.set_status(f"{label}: {done}/{total}", log=False)

        def run() -> None:
            try:
                self.set_status(job(progress))
            except VirgiError as e:
                self.set_status(str(e), error=True)
            except Exception as e:  # noqa: BLE001 - report, keep serving
                self.set_status(f"{what} failed: {type(e).__name__}: {e}", error=True)
            finally:
                self._set_progress(None)

        worker = threading.Thread(target=run, daemon=True, name="virgi-panel")
        self._worker = worker
        self._set_progress(0.0)
        self.set_status(f"{label} ...")
        worker.start()
        if wait:
            worker.join()
        return worker

    def _fit(self, name: str, image: np.ndarray, view: SavedView, stack, steps: Optional[int],
             progress: Callable[[int, int], None]) -> str:
        from virgi_ns.edit.engine import EditEngine
        from virgi_ns.edit.scene import FrozenScene
        from virgi_ns.edit.stack import EditSource

        m = self._model
        with self._lock():
            scene = FrozenScene.from_model(m)
        cams = raster_cameras(view.camera).to(m.device)
        source = EditSource(name, cams.Ks[0].cpu(), cams.viewmats[0].cpu(), int(cams.widths[0]),
                            int(cams.heights[0]), view.name)
        # the view's saved render is what the user painted over: the pixels they left alone match it
        original = torch.from_numpy(np.ascontiguousarray(view.image[..., :3], dtype=np.float32)) \
            if view.image is not None and tuple(view.image.shape[:2]) == tuple(image.shape[:2]) else None
        engine = EditEngine(scene, cams, torch.from_numpy(image), stack, source=source, original=original)
        edit, timing = engine.fit(steps, progress)
        with self._lock():
            number = stack.add(edit)
        self._refresh_edits()
        self._rerender()
        return (f"edit {number} applied from {name} ({timing.steps} steps, {timing.total_s:.1f} s, "
                f"L1 {timing.final_loss:.4f}; fitted {engine.mode}, {engine.changed_fraction:.0%} of the view)")

    def wait(self, timeout: Optional[float] = None) -> None:
        """Join a running edit or export (for scripts and tests)."""
        if self._worker is not None:
            self._worker.join(timeout)

    # -------------------------------------------------------------------- the stack
    def set_enabled(self, number: int, enabled: bool) -> None:
        stack = self._stack()
        with self._lock():
            stack.set_enabled(number, enabled)
        self.set_status(f"edit {number} {'enabled' if enabled else 'disabled'}")
        self._rerender()

    def undo(self) -> None:
        self._check_idle()
        stack = self._stack()
        with self._lock():
            self._leave_segmentation_if(len(stack) <= 1)
            stack.undo()
        self._refresh_edits()
        self.set_status(f"undone; {len(stack)} edit(s) left")
        self._rerender()

    def reset(self) -> None:
        self._check_idle()
        stack = self._stack()
        with self._lock():
            self._leave_segmentation_if(True)
            n = stack.reset()
        self.specular.value = 1.0
        self._refresh_edits()
        self.set_status(f"reset: removed {n} edit(s), specular strength 1")
        self._rerender()

    def _leave_segmentation_if(self, emptying: bool) -> None:
        """Before the last edit goes: show rgb again (the segmentation output disappears)."""
        self._model.segmentation_edit = None
        if emptying:
            sel = self._output_selector()
            if sel is not None and sel.value == "segmentation":
                sel.value = "rgb"
            if self.display.value == "segmentation":
                self.display.value = "rgb"

    def _refresh_edits(self) -> None:
        """Rebuild the edit list (one enable toggle per edit) and the segmentation selector."""
        st = self._model.edit_stack
        rows = st.rows() if st is not None else []
        m = self._model
        if m.segmentation_edit is not None and not 1 <= m.segmentation_edit <= len(rows):
            m.segmentation_edit = None
        options = [ALL_EDITS] + [f"edit {r['number']}" for r in rows]
        self.selected.set_options(options)
        want = ALL_EDITS if m.segmentation_edit is None else f"edit {m.segmentation_edit}"
        if self.selected.value != want:
            self.selected.value = want
        for box in self._edit_boxes:
            box.remove()
        self._edit_boxes = []
        for r in rows:
            n = int(r["number"])
            label = f"{n}: {Path(str(r['image'])).name or 'edit'}" + (f" ({r['camera']})" if r["camera"] else "")
            box = ViewerCheckbox(label, bool(r["enabled"]), cb_hook=lambda e, n=n: self._guard(lambda: self.set_enabled(n, bool(e.value))),
                                 hint="Show this edit")
            if self._edits_folder is not None and self._server is not None:
                with self._edits_folder:
                    box.install(self._server)
            self._edit_boxes.append(box)

    # ------------------------------------------------------------------------ export
    def export(self, path: Optional[Path] = None, wait: bool = False, client=None) -> threading.Thread:
        """Bake the model with its enabled edits and specular strength (:mod:`virgi_ns.nerfstudio.export`) into
        ``path`` (default ``<run>/exports/edited.ply``) in a background thread; files up to
        ``MAX_DOWNLOAD_BYTES`` are also sent to the browser."""
        self._check_idle()
        out = Path(path) if path is not None else self.run_dir / "exports" / "edited.ply"
        target = self.viewer.pipeline if getattr(self.viewer, "pipeline", None) is not None else self._model

        def job(progress: Callable[[int, int], None]) -> str:
            try:
                from virgi_ns.nerfstudio.export import export_model
            except ImportError as e:
                raise InputError(f"export is not available in this installation ({e})") from None
            g = export_model(target, out, progress=progress)
            self.last_export = out
            size = out.stat().st_size
            dest = client if client is not None else self.viser_server if self.viewer is not None else None
            if dest is not None and size <= MAX_DOWNLOAD_BYTES:
                dest.send_file_download(out.name, out.read_bytes())
            return f"exported {len(g):,} Gaussians to {out} ({size / 2**20:.1f} MiB)"

        return self._background(f"exporting to {out.name}", "the export", job, wait)


__all__ = ["VirgiPanel", "ViewerUpload", "Upload", "SavedView", "decode_image"]
