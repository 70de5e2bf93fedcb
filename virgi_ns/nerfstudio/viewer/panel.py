"""VIRGi's panel in nerfstudio's viewer: pick and recolour in place, or save a view, edit it
anywhere, upload it, apply it.

The panel is one nerfstudio :class:`ViewerElement` (and :class:`ViewerControl`) held by the model
as ``model.viewer_panel``; the viewer finds it by walking the pipeline's attributes, installs it
in its "Custom Elements" folder, then hands it the viewer (for the client's camera, the render
lock, the run directory and the output selector). It holds, top to bottom:

- a status line (progress and errors; a failed action never stops the server);
- **Display** (rgb, diffuse, specular, segmentation of the selected edit): sets the viewer's
  output type; **Specular strength** ``k``;
- **Keep other colours**: the colours an edit or a pick leaves unchanged get their own share of its
  fit (``virgi-edit --unchanged-weights colour``), so small parts of another colour on a recoloured
  object keep theirs;
- **Pick mode**, **New colour**, **Tolerance**, **Recolour mode** (hue or colour): a click on the
  render selects what it shows and recolours it live; a pause commits it (:mod:`.picking`);
- **Save this view**: renders the client's view (longest side **Save size**), writes
  ``<run>/views/view_NNN.png`` and its camera ``view_NNN.json`` (``virgi-render``'s CAM.json, in
  the capture's original frame, as the exported splat) and sends both to the browser;
- **Upload edited image** (:class:`ViewerUpload`, over viser's upload button), **Fit** (``joint``, the
  paper's recipe, or ``staged``: ``virgi-edit apply --recipe``) and **Apply edit**: fits an edit
  (:class:`virgi_ns.edit.engine.EditEngine`) for the saved view the image came from (its name holds
  ``view_NNN``; otherwise the last saved view), in a background thread with progress;
- the edits with enable toggles, the edit whose segmentation is shown, **Undo**, **Reset**;
- **Export**: bakes the edited scene to a splat file (:mod:`virgi_ns.nerfstudio.export`).

This module holds the widgets, their plumbing (status line, progress, render lock, the model's
edit stack) and the display settings. The actions are :class:`~.actions.PanelActions` and
:class:`~.picking.PickActions`; every one is also a plain method (:meth:`VirgiPanel.save_view`,
:meth:`VirgiPanel.upload`, :meth:`VirgiPanel.apply_edit`, :meth:`VirgiPanel.pick_at`, ...) usable
without a viewer.
"""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, List, Optional

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import (
    ViewerButton,
    ViewerCheckbox,
    ViewerControl,
    ViewerDropdown,
    ViewerElement,
    ViewerNumber,
    ViewerRGB,
    ViewerSlider,
)

from virgi_ns.errors import InputError, VirgiError
from virgi_ns.nerfstudio.viewer.actions import ALL_EDITS, PanelActions
from virgi_ns.nerfstudio.viewer.picking import PickActions
from virgi_ns.nerfstudio.viewer.upload import ViewerUpload
from virgi_ns.nerfstudio.viewer.views import SavedView

if TYPE_CHECKING:
    from viser import ViserServer

DISPLAYS = ["rgb", "diffuse", "specular", "segmentation"]


class VirgiPanel(PanelActions, PickActions, ViewerElement[None], ViewerControl):
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
        self.keep_colours = ViewerCheckbox("Keep other colours", False,
                                           hint="The colours your edit or pick leaves unchanged get their own share "
                                                "of the fit, so small parts of another colour on a recoloured object "
                                                "keep theirs (a pick takes it from its next click)")
        self.save_size = ViewerNumber("Save size (px)", self._default_save_size(),
                                      hint="Longest side of a saved view")
        self.save_button = ViewerButton("Save this view", cb_hook=lambda e: None)
        self.upload_element = ViewerUpload("Upload edited image", cb_hook=lambda e: self._on_upload(e),
                                           mime_type="image/*", hint="The saved view, recoloured in any editor")
        self.recipe = ViewerDropdown("Fit", "joint", ["joint", "staged"],
                                     hint="joint: the segmentation and the new colour together (the paper's recipe); "
                                          "staged: the segmentation first, so parts of another colour inside a "
                                          "recoloured object keep theirs")
        self.apply_button = ViewerButton("Apply edit", cb_hook=lambda e: self._guard(self.apply_edit))
        self.selected = ViewerDropdown("Segmentation of", ALL_EDITS, [ALL_EDITS],
                                       cb_hook=lambda e: self._guard(lambda: self.select_edit(e.value)))
        self.undo_button = ViewerButton("Undo", cb_hook=lambda e: self._guard(self.undo))
        self.reset_button = ViewerButton("Reset", cb_hook=lambda e: self._guard(self.reset))
        self.export_button = ViewerButton("Export", cb_hook=lambda e: None)
        self._init_pick()
        self.pick_mode = ViewerCheckbox("Pick mode", False,
                                        cb_hook=lambda e: self._guard(lambda: self.set_pick_mode(bool(e.value))),
                                        hint="Click on the render to select what it shows (no orbiting while on)")
        self.pick_colour = ViewerRGB("New colour", (208, 32, 32), cb_hook=lambda e: self._on_pick_params(),
                                     hint="The picked selection's new colour")
        self.tolerance = ViewerSlider("Tolerance", 0.2, 0.0, 1.0, 0.01, cb_hook=lambda e: self._on_pick_params(),
                                      hint="How far (x 90 degrees) a pixel's hue may turn from the clicked pixel's, "
                                           "and how fast its chroma may change between neighbours")
        self.contiguous = ViewerCheckbox("Contiguous", True, cb_hook=lambda e: self._on_pick_params(),
                                         hint="Select only what is connected to the clicked pixel; untick to take "
                                              "every pixel of the view that passes the same colour tests")
        self.pick_recolour = ViewerDropdown("Recolour mode", "hue", ["hue", "shift", "colour"],
                                            cb_hook=lambda e: self._on_pick_params(),
                                            hint="hue: keep shading and highlights; shift: the same, each pixel's "
                                                 "hue turned alike, so several hues stay apart; colour: the surface "
                                                 "takes the colour, shaded, highlights on it")

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
            for e in (self.display, self.specular, self.keep_colours, self.pick_mode, self.pick_colour, self.tolerance,
                      self.contiguous, self.pick_recolour, self.save_size, self.save_button, self.upload_element,
                      self.recipe, self.apply_button, self.selected):
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

    @property
    def unchanged_weights(self) -> str:
        """:attr:`~virgi_ns.edit.config.EditConfig.unchanged_weights` as **Keep other colours** sets it."""
        return "colour" if bool(self.keep_colours.value) else "count"

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
            self.settle_pick()
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


__all__ = ["ALL_EDITS", "DISPLAYS", "VirgiPanel"]
