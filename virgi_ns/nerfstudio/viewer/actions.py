"""What the panel does: save a view, take an uploaded edit of it and fit the edit, manage the edit
stack, export (each change of the stack first commits a pending pick, :mod:`.picking`). Mixed into :class:`~virgi_ns.nerfstudio.viewer.panel.VirgiPanel`, whose widgets,
status line, render lock and edit stack these methods use; each is also a plain method usable
without a viewer (scripts, tests)."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.viewer.viewer_elements import ViewerCheckbox

from virgi_ns.errors import InputError, VirgiError, atomic_path
from virgi_ns.io.camera_json import parse_camera
from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.nerfstudio.frames import camera_from_spec, camera_spec, capture_frame
from virgi_ns.nerfstudio.viewer.upload import ViewerUpload, decode_image
from virgi_ns.nerfstudio.viewer.views import VIEW_RE, SavedView, png_bytes

ALL_EDITS = "all enabled edits"
MAX_DOWNLOAD_BYTES = 64 << 20


class PanelActions:
    """The panel's actions (see the module docstring)."""

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
                         + [int(mm.group(1)) for p in vdir.glob("view_*.json") if (mm := VIEW_RE.fullmatch(p.stem))])
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
        mm = VIEW_RE.search(name or "")
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
        self.settle_pick()
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
        from virgi_ns.edit.engine import EditConfig, EditEngine
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
        # the rate's schedule spans the config's steps, so other steps are set there, not only run
        cfg = EditConfig(recipe=str(self.recipe.value), unchanged_weights=self.unchanged_weights,
                         **({} if steps is None else {"steps": int(steps)}))
        engine = EditEngine(scene, cams, torch.from_numpy(image), stack, cfg, source=source, original=original)
        edit, timing = engine.fit(progress=progress)
        with self._lock():
            number = stack.add(edit)
        self._refresh_edits()
        self._rerender()
        note = engine.small_progress_note()
        return (f"edit {number} applied from {name} ({timing.steps} steps, {timing.total_s:.1f} s, "
                f"L1 {timing.final_loss:.4f}; fitted {engine.mode}, {engine.changed_fraction:.0%} of the view)"
                + ("" if note is None else f". Warning: {note}; paint more of the object, or undo it"))

    def wait(self, timeout: Optional[float] = None) -> None:
        """Join a running edit or export (for scripts and tests)."""
        if self._worker is not None:
            self._worker.join(timeout)

    # -------------------------------------------------------------------- the stack
    def set_enabled(self, number: int, enabled: bool) -> None:
        self.settle_pick()
        stack = self._stack()
        with self._lock():
            stack.set_enabled(number, enabled)
        self.set_status(f"edit {number} {'enabled' if enabled else 'disabled'}")
        self._rerender()

    def undo(self) -> None:
        stack, _ = self._remove_edits(lambda st: st.undo(), emptying=lambda st: len(st) <= 1)
        self._refresh_edits()
        self.set_status(f"undone; {len(stack)} edit(s) left")
        self._rerender()

    def reset(self) -> None:
        _, n = self._remove_edits(lambda st: st.reset(), emptying=lambda st: True)
        self.specular.value = 1.0
        self._refresh_edits()
        self.set_status(f"reset: removed {n} edit(s), specular strength 1")
        self._rerender()

    def _remove_edits(self, remove: Callable[[Any], Any], emptying: Callable[[Any], bool]) -> tuple[Any, Any]:
        """(stack, ``remove(stack)``), run under the render lock once no edit is being fitted; the
        segmentation display is left first when ``emptying(stack)`` says the stack will be empty."""
        self.settle_pick()
        self._check_idle()
        stack = self._stack()
        with self._lock():
            self._leave_segmentation_if(emptying(stack))
            out = remove(stack)
        return stack, out

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
        self.settle_pick()
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


__all__ = ["ALL_EDITS", "MAX_DOWNLOAD_BYTES", "PanelActions"]
