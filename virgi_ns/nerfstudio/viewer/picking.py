"""The panel's Pick mode: a click on the render selects what it shows, the colour, tolerance and
mode recolour it live, and a pause commits it to the edit stack.

How it runs (mixed into :class:`~virgi_ns.nerfstudio.viewer.panel.VirgiPanel`):

- **Pick mode** is a toggle: while viser has a pointer callback, a drag in the canvas no longer
  orbits, so the callback is registered only while the box is ticked;
- a click arrives on one of viser's pool threads with its place in the canvas; the panel renders
  the client's view at the save size, maps the place to a pixel of it and hands (camera, pixel) to
  the pick worker; colour, tolerance, contiguity and mode changes only bump a counter. Callbacks never wait
  for a fit or the render lock;
- one worker thread does the work, always on the newest request: a click starts a
  :class:`~virgi_ns.edit.pick.PickSession` (with the panel's **Keep other colours** as it stands then)
  and fits it; a change refits it warm in a few steps (:data:`LIVE_STEPS`) and shows the result
  through the model's live-edit slot (rendered over the stack, nothing written);
- **the fit tops up while nothing changes**: once the newest change is shown, the worker runs the
  rest of the config's steps in chunks of :data:`LIVE_STEPS` (a new change or click goes first) and
  shows the finished fit;
- **release commits**: viser reports no release of a slider or colour drag, so a pick is committed
  when no change has come for ``commit_after_s`` (:data:`COMMIT_AFTER_S`): the topped-up edit is
  added to the stack with its edited image and selection (undo, toggles and export then see it as
  any edit). Further changes of the same pick replace that edit at their
  own release. A new click, leaving Pick mode, or any other change of the stack (apply, undo,
  reset, toggles, specular strength, export) first commits what is pending and ends the pick.

The render lock is held only to swap the live edit or change the stack, and never while asking for
a redraw (the viewer's redraw hook takes it itself).
"""

from __future__ import annotations

import threading
import time
from typing import Optional

from virgi_ns.errors import InputError, VirgiError

COMMIT_AFTER_S = 1.0
"""Seconds without a change after which a pick's live edit is committed ("release")."""
LIVE_STEPS = 20
"""Fit steps of a live update, and of each chunk of the top-up to the config's steps that follows it."""


class PickActions:
    """Pick mode (see the module docstring); its state starts in :meth:`_init_pick`."""

    def _init_pick(self) -> None:
        self._pick_cond = threading.Condition()
        self.commit_after_s = COMMIT_AFTER_S
        self._pick_click: Optional[tuple] = None  # (camera, x, y) not yet handled
        self._pick_version = 0  # bumped by every colour / tolerance / mode change
        self._pick_last_change = 0.0
        self._pick_jobs = 0  # jobs taken by the worker (for waiters)
        self._pick_working = False
        self._pick_thread: Optional[threading.Thread] = None
        self._pick_busy = threading.Lock()  # held while the session changes (fits, commits)
        self._pick_session = None
        self._pick_done = -1  # the version the live edit was fitted for
        self._pick_live = None  # the live edit, not yet committed
        self._pick_committed: Optional[int] = None  # the stack number of this pick's commit
        self._pick_registered = False  # the click callback is on viser's scene

    @property
    def commit_after_s(self) -> float:
        """Seconds without a change after which the live edit is committed."""
        return self._commit_after_s

    @commit_after_s.setter
    def commit_after_s(self, seconds: float) -> None:
        # wake the worker: it may be sleeping until a commit due under the previous value
        with self._pick_cond:
            self._commit_after_s = float(seconds)
            self._pick_cond.notify_all()

    # ---------------------------------------------------------------------- requests
    def set_pick_mode(self, on: bool) -> None:
        """Tick (register the click callback) or untick Pick mode (commit what is pending)."""
        server = self._server if self.viewer is not None else None
        if on:
            self._stack()  # refuses while the geometry still trains
            if server is not None:
                server.scene.on_pointer_event("click")(lambda ev: self._guard(lambda: self._on_scene_click(ev)))
                self._pick_registered = True
            self.set_status("Pick mode: click on the render to select what it shows; the colour, tolerance, "
                            f"contiguity and mode recolour it live, {self.commit_after_s:g} s without a change commits it")
            return
        if server is not None and self._pick_registered:
            server.scene.remove_pointer_callback()
            self._pick_registered = False
        self.settle_pick()
        self.set_status("Pick mode off")

    def _on_scene_click(self, ev) -> None:
        state = getattr(self.viewer, "render_tab_state", None)
        if state is not None and state.preview_render:
            raise InputError("leave the Render tab's preview to pick: it changes the camera")
        u, v = ev.screen_pos[0]
        cam = self._client_camera(ev.client)
        W, H = int(cam.width[0, 0]), int(cam.height[0, 0])
        self.pick_at(cam, min(int(u * W), W - 1), min(int(v * H), H - 1))

    def pick_at(self, camera, x: int, y: int, wait: bool = False) -> None:
        """Pick pixel (x, y) of ``camera`` (a nerfstudio camera of one view) with the panel's colour,
        tolerance and mode (``wait``: until the live edit shows and its fit is topped up)."""
        self._check_idle()
        with self._pick_cond:
            self._pick_click = (camera, int(x), int(y))
            self._pick_last_change = time.monotonic()
            self._pick_cond.notify_all()
        self._start_pick_worker()
        if wait:
            self.wait_pick(commit=False)

    def _on_pick_params(self) -> None:
        """A colour, tolerance, contiguity or mode change: the worker refits the current pick."""
        with self._pick_cond:
            self._pick_version += 1
            self._pick_last_change = time.monotonic()
            self._pick_cond.notify_all()

    def wait_pick(self, commit: bool = True, timeout: float = 600.0) -> None:
        """Wait until the worker has handled every request (``commit``: and committed the pick)."""
        deadline = time.monotonic() + timeout

        def idle() -> bool:
            if self._pick_working or self._pick_job(time.monotonic())[0] in ("click", "live", "top-up"):
                return False
            return not commit or self._pick_live is None

        with self._pick_cond:
            while not idle():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("the pick worker did not finish")
                self._pick_cond.wait(min(left, 0.05))

    def settle_pick(self) -> None:
        """Commit the pending live edit and end the pick (before anything else changes the stack)."""
        with self._pick_cond:
            self._pick_click = None
        with self._pick_busy:
            if self._pick_live is not None:
                self._commit_pick()
            self._pick_session, self._pick_committed = None, None

    # ------------------------------------------------------------------------ worker
    def _start_pick_worker(self) -> None:
        if self._pick_thread is None or not self._pick_thread.is_alive():
            self._pick_thread = threading.Thread(target=self._pick_loop, daemon=True, name="virgi-pick")
            self._pick_thread.start()

    def _pick_job(self, now: float) -> tuple[str, Optional[float]]:
        """(the next job: 'click', 'live', 'top-up', 'commit' or '' for none; seconds until a commit
        is due)."""
        if self._pick_click is not None:
            return "click", None
        session = self._pick_session  # read once: settle_pick may end the pick from another thread
        if session is None:
            return "", None
        if self._pick_version != self._pick_done:
            return "live", None
        if self._pick_live is not None and session.steps_left:
            return "top-up", None
        if self._pick_live is not None:
            due = self._pick_last_change + self.commit_after_s - now
            return ("commit", None) if due <= 0 else ("", due)
        return "", None

    def _pick_loop(self) -> None:
        while True:
            with self._pick_cond:
                while True:
                    job, wait = self._pick_job(time.monotonic())
                    if job:
                        break
                    self._pick_cond.wait(wait)
                click, self._pick_click = self._pick_click, None
                version = self._pick_version
                self._pick_working = True
            try:
                with self._pick_busy:
                    if job == "click":
                        self._start_pick(*click, version)
                    elif job == "live" and self._pick_session is not None:
                        self._live_pick(version)
                    elif job == "top-up" and self._pick_live is not None:
                        self._top_up_pick()
                    elif job == "commit" and self._pick_live is not None:
                        self._commit_pick()
            except VirgiError as e:
                self.set_status(str(e), error=True)
            except Exception as e:  # noqa: BLE001 - report, keep serving
                self.set_status(f"the pick failed: {type(e).__name__}: {e}", error=True)
            finally:
                with self._pick_cond:
                    self._pick_working = False
                    self._pick_jobs += 1
                    self._pick_cond.notify_all()

    def _pick_params(self) -> tuple:
        """(colour, tolerance, mode, contiguous) as the panel shows them."""
        r, g, b = self.pick_colour.value
        return ((r / 255.0, g / 255.0, b / 255.0), float(self.tolerance.value), str(self.pick_recolour.value),
                bool(self.contiguous.value))

    def _start_pick(self, camera, x: int, y: int, version: int) -> None:
        """A click: commit the last pick, set up the new one, fit it and show it."""
        from virgi_ns.edit.pick import PickSession, pick_config
        from virgi_ns.edit.scene import FrozenScene
        from virgi_ns.edit.stack import EditSource
        from virgi_ns.nerfstudio.cameras import raster_cameras

        if self._pick_live is not None:
            self._commit_pick()
        self._pick_session, self._pick_committed = None, None
        m = self._model
        stack = self._stack()
        with self._lock():
            scene = FrozenScene.from_model(m)
        cams = raster_cameras(camera.reshape((1,)) if len(camera.shape) == 0 else camera[0:1]).to(m.device)
        W, H = int(cams.widths[0]), int(cams.heights[0])
        source = EditSource("", cams.Ks[0].cpu(), cams.viewmats[0].cpu(), W, H, f"viewer pick at {x} {y}")
        cfg = pick_config(m.device)
        cfg.unchanged_weights = self.unchanged_weights
        self._pick_session = PickSession(scene, cams, x, y, stack, cfg, source)
        self._live_pick(version, first=True)

    def _live_pick(self, version: int, first: bool = False) -> None:
        """Refit the pick for the panel's current colour, tolerance, contiguity and mode; show it, unwritten."""
        session = self._pick_session
        colour, tolerance, mode, contiguous = self._pick_params()
        seg = session.engine.cfg.seg_steps
        edit = session.update(colour, tolerance, mode, LIVE_STEPS, None if first else max(1, seg // 4),
                              contiguous=contiguous)
        with self._lock():
            self._model.set_live_edit(edit)
        self._pick_live, self._pick_done = edit, version
        self._rerender()
        st = session.settings
        self.set_status(f"pick at {session.x} {session.y}: {st['selected']:.0%} of the view selected, {mode} -> "
                        f"{st['colour']} (live; committed {self.commit_after_s:g} s after the last change)", log=first)

    def _top_up_pick(self) -> None:
        """One chunk of the live fit's top-up to the config's steps; the last one shows the result."""
        session = self._pick_session
        try:
            edit = session.refine(min(LIVE_STEPS, session.steps_left))
        except Exception:
            session.steps_done = session.engine.cfg.steps  # no retry loop: a commit takes the live fit as it is
            raise
        if not session.steps_left:
            self._pick_live = edit  # what a commit takes, even if showing it fails
            with self._lock():
                self._model.set_live_edit(edit)
            self._rerender()

    def _commit_pick(self) -> None:
        """Put the live fit, topped up to the config's steps, on the stack (in the place of this
        pick's earlier commit)."""
        from virgi_ns.edit.pick import commit

        session = self._pick_session
        edit = session.refine(session.steps_left) if session.steps_left else self._pick_live
        stack = self._stack()
        with self._lock():
            number = commit(stack, session, edit, self._pick_committed)
            self._model.set_live_edit(None)
        self._pick_live, self._pick_committed = None, number
        self._refresh_edits()
        self._rerender()
        note = session.engine.small_progress_note()
        self.set_status(f"edit {number} committed from the pick at {session.x} {session.y} "
                        f"({session.settings['selected']:.0%} of the view"
                        + ("; refitted staged, the joint fit having stalled" if "restaged" in edit.info else "") + ")"
                        + ("" if note is None else f". Warning: {note}; pick again elsewhere"))


__all__ = ["COMMIT_AFTER_S", "LIVE_STEPS", "PickActions"]
