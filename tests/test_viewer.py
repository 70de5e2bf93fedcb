"""The viewer panel on a tiny trained run (CPU): its actions called directly (save a view, upload,
apply, toggle, undo, reset, pick, errors), then the same through nerfstudio's viewer on a real viser
server, driven by a client that sends what the browser sends (``viser_client.py``)."""

from __future__ import annotations

import io
import json
import threading
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from virgi_ns.io.camera_json import read_camera_json
from virgi_ns.nerfstudio.frames import camera_from_spec, camera_spec, capture_frame
from virgi_ns.nerfstudio.viewer.panel import ALL_EDITS, VirgiPanel
from virgi_ns.nerfstudio.viewer.upload import Upload

from viewer_run import train_tiny
from virgi_scene import make_scene


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    scene = make_scene(tmp_path_factory.mktemp("viewer_scene"))
    _, pipeline = train_tiny(scene, steps=4)
    return scene, pipeline


class OutputSelector:
    """Stands in for the viewer's "Output type" dropdown."""

    def __init__(self) -> None:
        self.value = "rgb"
        self.options = ["rgb", "diffuse", "specular", "depth", "accumulation"]

    def set_options(self, options) -> None:
        self.options = list(options)


def png(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def render(model, cam) -> np.ndarray:
    return model.get_outputs_for_camera(cam)["rgb"].detach().cpu().numpy()


def test_camera_json_round_trip_and_capture_frame(run):
    """The saved camera sees the capture-frame splat where the model's camera sees the model's."""
    scene, pipeline = run
    model = pipeline.model
    cam = pipeline.datamanager.train_dataset.cameras[2:3]
    T, s = capture_frame(model)
    assert s != 1.0 or not torch.allclose(T, torch.eye(4)[:3].double())  # a real transform is exercised
    spec = camera_spec(cam, T, s)
    vm = torch.as_tensor(spec.world_to_camera, dtype=torch.float64)
    K = torch.tensor([[spec.fx, 0, spec.cx], [0, spec.fy, spec.cy], [0, 0, 1]], dtype=torch.float64)

    def project(means, viewmat, K):
        pc = means.double() @ viewmat[:3, :3].T + viewmat[:3, 3]
        p = pc @ K.T
        return p[:, :2] / p[:, 2:3]

    from virgi_ns.nerfstudio.cameras import raster_cameras

    rc = raster_cameras(cam)
    want = project(model.means.detach(), rc.viewmats[0].double(), rc.Ks[0].double())
    got = project(scene.gaussians.means, vm, K)  # original capture-frame means, saved camera
    torch.testing.assert_close(got, want, atol=1e-3, rtol=1e-5)
    back = camera_from_spec(spec, T, s)
    torch.testing.assert_close(back.camera_to_worlds.double(), cam.camera_to_worlds.double(), atol=1e-5, rtol=1e-5)


def test_panel_save_upload_apply_undo(run, tmp_path):
    scene, pipeline = run
    model = pipeline.model
    model.set_edit_stack(None)
    panel = VirgiPanel(model, run_dir=tmp_path)

    # no saved camera yet: errors land in the status line
    panel._guard(lambda: panel.upload("view_001.png", png(np.zeros((40, 48, 3)))))
    assert panel.status_is_error and "no saved camera" in panel.status
    panel._guard(panel.apply_edit)
    assert panel.status_is_error and "no saved camera" in panel.status

    cam = pipeline.datamanager.train_dataset.cameras[1:2]
    view = panel.save_view(cam)
    assert not panel.status_is_error and view.png.is_file() and view.json.is_file()
    before = render(model, cam)
    saved = np.asarray(Image.open(view.png), dtype=np.float32) / 255.0
    assert saved.shape == before.shape
    assert np.abs(saved - before).max() <= 0.5 / 255 + 1e-6
    spec = read_camera_json(view.json)  # virgi-render's reader accepts it
    assert (spec.width, spec.height) == (48, 40)
    assert json.loads(view.json.read_text())["frame"] == "capture"
    assert [n for n, _ in panel.last_download] == ["view_001.png", "view_001.json"]
    assert panel.last_download[0][1] == view.png.read_bytes()

    # bad uploads: not an image, wrong size; the panel keeps working
    up = panel.upload_element
    up.value = Upload("notes.txt", b"hello, not a picture")
    panel._on_upload(up)
    assert panel.status_is_error and "not an image" in panel.status and panel.pending is None
    panel._guard(lambda: panel.upload("view_001.png", png(np.zeros((20, 30, 3)))))
    assert panel.status_is_error and "30x20" in panel.status and "48x40" in panel.status
    panel._guard(panel.apply_edit)
    assert panel.status_is_error and "upload" in panel.status

    # an edit: the scene's pixels of the saved view painted green
    mask = np.abs(saved - saved[0, 0]).max(-1) > 0.05
    assert mask.mean() > 0.05
    edited = saved.copy()
    edited[mask] = (0.1, 0.8, 0.15)
    up.value = Upload("view_001 edited.png", png(edited))
    panel._on_upload(up)
    assert not panel.status_is_error, panel.status
    panel.apply_edit(wait=True, steps=120)
    assert not panel.status_is_error, panel.status
    assert "edit 1 applied" in panel.status and panel.progress == 0.0 and "Warning" not in panel.status
    stack = model.edit_stack
    assert len(stack) == 1 and (tmp_path / "edits" / "stack.json").is_file()
    after = render(model, cam)
    err_before = np.abs(before - edited).mean()
    err_after = np.abs(after - edited).mean()
    assert err_after < 0.5 * err_before, (err_before, err_after)
    assert [e.name for e in panel._edit_boxes] == ["1: view_001 edited.png (view_001)"]
    assert panel.selected.options == [ALL_EDITS, "edit 1"]
    out = model.get_outputs_for_camera(cam)
    assert out["segmentation"].shape == (40, 48, 1)
    seg = out["segmentation"][..., 0].numpy()
    assert seg[mask].mean() > 0.5 and seg[~mask].mean() < 0.1  # the recoloured pixels are selected

    # export bakes the edited colours; the exported file seen from the saved CAM.json (capture
    # frame) looks like the model's edited render from the same view
    panel.export(tmp_path / "out" / "edited.ply", wait=True)
    assert not panel.status_is_error, panel.status
    from virgi_ns.cli.render import render_image
    from virgi_ns.io import load_splat

    g = load_splat(tmp_path / "out" / "edited.ply")
    assert len(g) == model.num_points
    baked = render_image(g, read_camera_json(view.json), backend="reference")
    assert np.abs(baked - after).mean() < 0.03, np.abs(baked - after).mean()

    # toggle off: back to the base colours; on again
    panel.set_enabled(1, False)
    np.testing.assert_allclose(render(model, cam), before, atol=1e-5)
    panel.set_enabled(1, True)
    np.testing.assert_allclose(render(model, cam), after, atol=1e-5)

    # specular strength reaches the stack (and its file)
    panel.set_specular_strength(0.0)
    assert stack.specular_strength == 0.0
    assert json.loads((tmp_path / "edits" / "stack.json").read_text())["specular_strength"] == 0.0

    # the segmentation display needs edits; selecting one edit reaches the model
    panel.select_edit("edit 1")
    assert model.segmentation_edit == 1

    # a new panel on the same run finds the saved edit and view
    model.set_edit_stack(None)
    other = VirgiPanel(model, run_dir=tmp_path)
    assert len(other._stack()) == 1 and other._stack().specular_strength == 0.0
    assert other._view_for("my view_001.png").number == 1
    np.testing.assert_allclose(other._view_for("view_001.png").camera.camera_to_worlds.numpy(),
                               cam.camera_to_worlds.numpy(), atol=1e-5)
    panel = other

    # the display dropdown drives the viewer's output selector; emptying the stack returns it to rgb
    sel = OutputSelector()
    panel.viewer = SimpleNamespace(control_panel=SimpleNamespace(_output_render=sel), train_lock=threading.Lock())
    panel.set_display("diffuse")
    assert sel.value == "diffuse"
    panel.set_display("segmentation")
    assert sel.value == "segmentation" and "segmentation" in sel.options and not panel.status_is_error
    panel.display.value = "segmentation"

    panel.undo()
    assert sel.value == "rgb" and panel.display.value == "rgb"
    assert len(model.edit_stack) == 0 and model.segmentation_edit is None
    np.testing.assert_allclose(render(model, cam), before, atol=0.05)  # k is still 0
    panel._guard(panel.undo)
    assert panel.status_is_error and "nothing to undo" in panel.status
    panel.reset()
    assert model.edit_stack.specular_strength == 1.0
    np.testing.assert_allclose(render(model, cam), before, atol=1e-5)
    panel.set_display("segmentation")
    assert panel.status_is_error and "needs an edit" in panel.status

    # one step leaves the painted pixels nearly where they were: applied, with a warning in the status line
    panel._on_upload(up)
    panel.apply_edit(wait=True, steps=1)
    assert not panel.status_is_error and "edit 1 applied" in panel.status, panel.status
    assert "Warning: the fit moved the changed pixels" in panel.status, panel.status
    panel.undo()


def test_panel_pick_live_commit_replace_undo(run, tmp_path):
    """Pick mode without a browser: a click (``pick_at``) shows a live edit, nothing written; a pause
    commits it with its pictures; a colour change after the release replaces that edit; undo
    restores the render; a click on the background is a status-line error with nothing saved."""
    _, pipeline = run
    model = pipeline.model
    model.set_edit_stack(None)
    panel = VirgiPanel(model, run_dir=tmp_path)
    panel.commit_after_s = 0.05
    cam = pipeline.datamanager.train_dataset.cameras[0:1]
    out = model.get_outputs_for_camera(cam)
    before = out["rgb"].detach().cpu().numpy()
    acc = out["accumulation"][..., 0].detach().cpu().numpy()
    red = (acc > 0.95) & (before[..., 0] > before[..., 2] + 0.2)
    blue = (acc > 0.95) & (before[..., 2] > before[..., 0] + 0.2)
    assert red.sum() > 20 and blue.sum() > 20
    ys, xs = np.nonzero(red)
    k = int(((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2).argmin())
    edits = tmp_path / "edits"

    def files() -> list[str]:
        return sorted(p.name for p in edits.iterdir()) if edits.is_dir() else []

    # the background: an error in the status line, nothing saved, the panel keeps working
    panel.pick_at(cam, 0, 0)
    panel.wait_pick()
    assert panel.status_is_error and "background" in panel.status and model.live_edit is None
    assert files() in ([], ["stack.json"])

    panel.pick_colour.value = (32, 192, 64)
    panel.commit_after_s = 600.0  # hold the release: the live edit first
    panel.pick_at(cam, int(xs[k]), int(ys[k]), wait=True)
    assert not panel.status_is_error, panel.status
    assert model.live_edit is not None and len(model.edit_stack) == 0 and "edit_0001.pt" not in files()
    # while nothing changes the fit is topped up to the config's steps and shown, still unwritten
    session, topped = panel._pick_session, model.live_edit
    assert session.steps_done == session.engine.cfg.steps
    live = render(model, cam)
    assert live[red][:, 1].mean() > before[red][:, 1].mean() + 0.1  # turning green while "dragged"
    panel.commit_after_s = 0.05  # wakes the worker, asleep until a commit due in 600 s
    panel.wait_pick(commit=True, timeout=30)
    assert model.live_edit is None and len(model.edit_stack) == 1, panel.status
    assert "committed from the pick" in panel.status and "Warning" not in panel.status, panel.status
    assert files() == ["edit_0001.pt", "edit_0001_edited.png", "edit_0001_selection.png", "stack.json"]
    np.testing.assert_array_equal(model.edit_stack.entries[0].edit.head_weight.cpu().numpy(),
                                  topped.head_weight.cpu().numpy())  # the release commits the topped-up fit
    after = render(model, cam)
    assert after[red][:, 1].mean() > after[red][:, 0].mean()  # green over red now
    assert np.abs(after - before)[blue].mean() < 0.03  # the other sphere stays
    # a change of the same pick after its release replaces its edit
    panel.pick_colour.value = (40, 60, 220)
    panel._on_pick_params()
    panel.wait_pick(commit=True)
    assert len(model.edit_stack) == 1 and model.edit_stack.entries[0].edit.info["pick"]["colour"] == "#283cdc"
    assert files() == ["edit_0002.pt", "edit_0002_edited.png", "edit_0002_selection.png", "stack.json"]
    panel.undo()
    assert files() == ["stack.json"] and len(model.edit_stack) == 0
    np.testing.assert_allclose(render(model, cam), before, atol=1e-5)
    # bad settings are refused in the status line
    panel.tolerance.value = 1.5
    panel.pick_at(cam, int(xs[k]), int(ys[k]))
    panel.wait_pick()
    assert panel.status_is_error and "tolerance" in panel.status and files() == ["stack.json"]
    panel.set_pick_mode(False)


def test_panel_fit_settings_reach_the_applied_edit_and_the_pick(run, tmp_path):
    """**Fit** and **Keep other colours** reach what Apply fits and what a click starts: each edit
    records the recipe and the unchanged pixels' weights it was fitted with; the defaults are the
    engine's."""
    _, pipeline = run
    model = pipeline.model
    model.set_edit_stack(None)
    panel = VirgiPanel(model, run_dir=tmp_path)
    assert (panel.recipe.value, panel.unchanged_weights) == ("joint", "count")
    cam = pipeline.datamanager.train_dataset.cameras[1:2]
    saved = np.asarray(Image.open(panel.save_view(cam).png), dtype=np.float32) / 255.0
    edited = saved.copy()
    edited[np.abs(saved - saved[0, 0]).max(-1) > 0.05] = (0.1, 0.8, 0.15)
    for recipe, keep, weights in (("staged", True, "colour"), ("joint", False, "count")):
        panel.recipe.value, panel.keep_colours.value = recipe, keep
        panel.upload("view_001 edited.png", png(edited))
        panel.apply_edit(wait=True, steps=10)
        assert not panel.status_is_error, panel.status
        info = model.edit_stack.entries[-1].edit.info
        assert (info["recipe"], info["unchanged_weights"]) == (recipe, weights)

    panel.reset()
    cam = pipeline.datamanager.train_dataset.cameras[0:1]
    out = model.get_outputs_for_camera(cam)
    rgb, acc = out["rgb"].detach().cpu().numpy(), out["accumulation"][..., 0].detach().cpu().numpy()
    ys, xs = np.nonzero((acc > 0.95) & (rgb[..., 0] > rgb[..., 2] + 0.2))
    k = int(((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2).argmin())
    panel.keep_colours.value = True
    panel.commit_after_s = 600.0
    panel.pick_at(cam, int(xs[k]), int(ys[k]), wait=True)
    assert not panel.status_is_error, panel.status
    assert model.live_edit is not None and model.live_edit.info["unchanged_weights"] == "colour"
    panel.set_pick_mode(False)


# --------------------------------------------------------------------------------------------------
# The panel inside nerfstudio's viewer on a real viser server, driven by a websocket client that
# speaks viser's protocol as the browser does (tests/viser_client.py): the viewer finds the panel on
# the model, installs it and sets it up; the client sends its camera, presses the panel's buttons,
# sets its dropdowns, checkboxes and colour, uploads, clicks in the scene, and reads back the panel's
# status line, the files it is sent and the frames the viewer renders for it.

PANEL = "VIRGi edit"


@pytest.fixture(scope="module")
def served(run, tmp_path_factory):
    """(viewer, panel, client, cam): ``ns-viewer``'s set-up (``_start_viewer``) over the tiny run on a
    free port, frames as PNG at the training views' size, and a client whose camera is training view
    0's (``cam``)."""
    import viser.transforms  # noqa: F401  (the client converts its camera with it)
    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.viewer.viewer import Viewer

    from virgi_ns.nerfstudio.distributed import _free_port
    from viser_client import ViserClient

    from nerfstudio.utils.writer import GLOBAL_BUFFER, EventName

    _, pipeline = run
    model = pipeline.model
    model.set_edit_stack(None)
    # the viewer sizes a frame by the rays per second it has measured: start it at a slow machine's, so
    # the frames of lower resolution a CI runner gets come in every run, not only on slow machines
    saved_buffer = dict(GLOBAL_BUFFER)
    GLOBAL_BUFFER.update(max_buffer_size=GLOBAL_BUFFER.get("max_buffer_size", 20),
                         steps_per_log=GLOBAL_BUFFER.get("steps_per_log", 10),
                         events={**GLOBAL_BUFFER.get("events", {}),
                                 EventName.VIS_RAYS_PER_SEC.value: {"avg": 1000.0, "buffer": [1000.0]}})
    root = tmp_path_factory.mktemp("served")
    config = ViewerConfig(websocket_host="127.0.0.1", websocket_port=_free_port(), image_format="png")
    viewer = Viewer(config, log_filename=root / "run" / config.relative_log_filename,
                    datapath=pipeline.datamanager.get_datapath(), pipeline=pipeline, train_lock=threading.Lock())
    client = None
    try:
        viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="completed",
                          eval_dataset=pipeline.datamanager.eval_dataset)
        viewer.control_panel._max_res.value = 48  # frames at the training views' 48x40
        cam = pipeline.datamanager.train_dataset.cameras[0:1]
        client = ViserClient(viewer.viser_server.get_port())
        H, W, fy = int(cam.height), int(cam.width), float(cam.fy)
        client.send_camera(cam.camera_to_worlds[0].double().numpy(), 2 * np.arctan(H / 2 / fy), W / H)
        client.wait_frame(lambda f: f.shape == (H, W, 3), message="a first frame of the client's view")
        panels = [c for c in viewer.viewer_controls if isinstance(c, VirgiPanel)]
        assert panels == [model.viewer_panel], "the viewer did not find the model's panel"
        yield viewer, panels[0], client, cam
    finally:
        if client is not None:
            client.close()
        viewer.viser_server.stop()
        # nerfstudio's render threads keep rendering (daemons) until told to stop; a render still running while
        # the interpreter exits aborts it ("terminate called without an active exception")
        from nerfstudio.viewer.render_state_machine import RenderStateMachine

        for machine in [t for t in threading.enumerate() if isinstance(t, RenderStateMachine)]:
            machine.running = False  # also those a disconnect already let go, which may still be rendering
            machine.join(timeout=30)
        model.set_edit_stack(None)
        GLOBAL_BUFFER.clear()
        GLOBAL_BUFFER.update(saved_buffer)


def _frame_render(viewer, model, cam) -> np.ndarray:
    """What the client's frames should show: the model's render of ``cam`` over the viewer's
    background, as 8 bits."""
    with viewer.train_lock:
        rgb = model.get_outputs_for_camera(cam)["rgb"].detach().cpu().numpy()
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def _full(want: np.ndarray, where):
    """``where`` over frames of ``want``'s size only: while renders are slow nerfstudio's viewer also sends
    frames at a lower resolution, which a mask or a pixel of the full view cannot index."""
    return lambda frame: frame.shape == want.shape and where(frame)


def _near(frame: np.ndarray, want: np.ndarray) -> bool:
    if frame.shape != want.shape:
        return False
    d = np.abs(frame.astype(int) - want.astype(int))
    return d.mean() < 1.0 and d.max() <= 8


def _status(client, panel_ids) -> str:
    return client.text(panel_ids["status"])


def _panel_ids(client) -> dict:
    """The panel's components as the browser sees them, by label inside the panel's folder."""
    ids = {k: client.find(label, inside=PANEL) for k, label in (
        ("display", "Display"), ("pick", "Pick mode"), ("colour", "New colour"), ("tolerance", "Tolerance"),
        ("save", "Save this view"), ("upload", "Upload edited image"), ("apply", "Apply edit"),
        ("undo", "Undo"), ("reset", "Reset"), ("specular", "Specular strength"))}
    folder = client.find(PANEL)
    ids["status"] = client.wait_for(lambda: next((i for i, c in client.gui.items() if c["kind"] == "GuiAddMarkdownMessage"
                                                  and c.get("container_id") == folder), None), 30, "the status line")
    return ids


def test_viewer_save_upload_apply_display_toggle_undo(run, served):
    """Through the browser's messages: save the view (the files come to the client), upload an edited
    copy, apply it (the frame turns, the stack grows, an edit toggle appears), show the segmentation
    (the viewer's output type follows), toggle the edit off and on, undo (back to the render)."""
    viewer, panel, client, cam = served
    model = run[1].model
    ids = _panel_ids(client)
    before = _frame_render(viewer, model, cam)
    client.wait_frame(lambda f: _near(f, before), message="a frame of the unedited render")

    client.click(ids["save"])
    client.wait_for(lambda: "view_001.png" in client.downloads and "view_001.json" in client.downloads, 60,
                    "the saved view's download")
    saved = np.asarray(Image.open(io.BytesIO(client.downloads["view_001.png"])).convert("RGB"))
    assert saved.shape == before.shape and np.abs(saved.astype(int) - before.astype(int)).max() <= 8
    assert json.loads(client.downloads["view_001.json"])["frame"] == "capture"
    assert (panel.run_dir / "views" / "view_001.png").is_file()

    # paint the red sphere green, upload, apply
    image = saved.astype(np.float32) / 255
    red = (image[..., 0] > image[..., 2] + 0.2) & (image[..., 0] > 0.35)
    blue = (image[..., 2] > image[..., 0] + 0.2)
    assert red.sum() > 20 and blue.sum() > 20
    edited = image.copy()
    edited[red] = (0.1, 0.8, 0.15)
    client.upload(ids["upload"], "view_001 edited.png", png(edited))
    client.wait_for(lambda: "ready for view_001" in _status(client, ids), 60, "the upload's status")
    assert panel.pending is not None
    client.click(ids["apply"])
    client.wait_for(lambda: "edit 1 applied" in _status(client, ids), 120, "the applied edit's status")
    assert len(model.edit_stack) == 1 and (panel.run_dir / "edits" / "stack.json").is_file()
    edited_frame = client.wait_frame(_full(before, lambda f: f[red][:, 1].mean() > f[red][:, 0].mean() + 40),
                                     message="a frame with the red sphere turned green")
    assert np.abs(edited_frame[blue].astype(int) - before[blue].astype(int)).mean() < 8  # the blue one stays
    toggle = client.find("1: view_001 edited.png (view_001)", inside=PANEL)
    assert client.value(toggle) is True

    # the segmentation display: the viewer's own output selector follows, the frame shows the mask
    output_type = client.find("Output type")
    client.set(ids["display"], "segmentation")
    client.wait_for(lambda: client.value(output_type) == "segmentation", 60, "the viewer's output type")
    seg = client.wait_frame(_full(before, lambda f: np.abs(f.astype(int) - edited_frame.astype(int)).mean() > 20),
                            message="a segmentation frame")
    assert np.abs(seg[red].astype(float).mean(0) - seg[blue].astype(float).mean(0)).max() > 60
    client.set(ids["display"], "rgb")
    client.wait_for(lambda: client.value(output_type) == "rgb", 60, "the output type back to rgb")

    # the edit's toggle: off shows the render, on the edit again
    n = client.frame_count()
    client.set(toggle, False)
    client.wait_frame(lambda f: _near(f, before), after=n, message="the unedited frame with the edit off")
    assert not model.edit_stack.entries[0].enabled
    n = client.frame_count()
    client.set(toggle, True)
    client.wait_frame(_full(before, lambda f: f[red][:, 1].mean() > f[red][:, 0].mean() + 40), after=n,
                      message="the edited frame with the edit on")

    # the specular strength slider reaches the stack and its file
    client.set(ids["specular"], 0.0)
    client.wait_for(lambda: model.edit_stack.specular_strength == 0.0, 30, "k = 0 in the stack")
    # the panel's status follows the stack's file (written after the stack itself)
    client.wait_for(lambda: "specular strength 0.00" in _status(client, ids), 30, "the status of k = 0")
    assert json.loads((panel.run_dir / "edits" / "stack.json").read_text())["specular_strength"] == 0.0
    client.set(ids["specular"], 1.0)
    client.wait_for(lambda: model.edit_stack.specular_strength == 1.0, 30, "k = 1 in the stack")

    # undo: the stack empties, its toggle leaves the browser, the frame is the render again
    n = client.frame_count()
    client.click(ids["undo"])
    client.wait_for(lambda: "0 edit(s) left" in _status(client, ids), 60, "undo's status")
    assert len(model.edit_stack) == 0
    client.wait_for(lambda: toggle not in client.gui, 30, "the edit's toggle removed")
    client.wait_frame(lambda f: _near(f, before), after=n, message="the unedited frame after undo")

    # a file that is no image: an error in the status line, the viewer keeps serving
    client.upload(ids["upload"], "notes.txt", b"hello, not a picture", "text/plain")
    client.wait_for(lambda: "not an image" in _status(client, ids), 60, "the bad upload's error")
    assert panel.status_is_error and panel.pending is None


def test_viewer_pick_click_live_commit_recolour(run, served):
    """Pick mode through the browser's messages: ticking it enables scene clicks in the browser; a
    click on the red sphere (at a pixel whose transpose is not on it) turns what was clicked green
    live, nothing written; a pause commits it; a new colour replaces it; a click on the background is
    a status-line error; unticking disables clicks."""
    viewer, panel, client, cam = served
    model = run[1].model
    with panel._lock():
        model.set_edit_stack(None)  # whatever the test before left
    ids = _panel_ids(client)
    before = _frame_render(viewer, model, cam)
    image = before.astype(np.float32) / 255
    red = (image[..., 0] > image[..., 2] + 0.2) & (image[..., 0] > 0.35)
    H, W = red.shape
    ys, xs = np.nonzero(red)
    order = np.argsort((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2)
    # the clicked pixel: near the sphere's centre, where (y, x) would land off it
    k = next(i for i in order if not red[min(xs[i], H - 1), min(ys[i], W - 1)])
    x, y = int(xs[k]), int(ys[k])

    client.set(ids["pick"], True)
    client.wait_for(lambda: client.pointer_enabled, 30, "scene clicks enabled in the browser")
    panel.commit_after_s = 600.0  # hold the release: the live edit first
    client.set(ids["colour"], (32, 192, 64))
    client.wait_for(lambda: tuple(panel.pick_colour.value) == (32, 192, 64), 30, "the colour reaching the panel")
    n = client.frame_count()
    client.click_scene((x + 0.5) / W, (y + 0.5) / H)
    client.wait_for(lambda: f"pick at {x} {y}" in _status(client, ids) and "live" in _status(client, ids), 120,
                    "the live pick's status")
    live = client.wait_frame(_full(before, lambda f: int(f[y, x, 1]) > int(f[y, x, 0]) + 40), after=n,
                             message="the clicked pixel turned green, live")
    assert live[red][:, 1].mean() > before[red][:, 1].mean() + 25
    assert model.live_edit is not None and len(panel._stack()) == 0
    assert not (panel.run_dir / "edits" / "edit_0001.pt").exists()

    panel.commit_after_s = 0.05  # a pause: the pick is committed (the worker, asleep for 600 s, wakes)
    client.wait_for(lambda: "edit 1 committed" in _status(client, ids), 30, "the commit's status")
    assert model.live_edit is None and len(model.edit_stack) == 1
    assert (panel.run_dir / "edits" / "edit_0001_selection.png").is_file()
    n = client.frame_count()
    client.set(ids["colour"], (40, 60, 220))  # a change after the release replaces the pick's edit
    client.wait_for(lambda: model.edit_stack.entries[0].edit.info["pick"]["colour"] == "#283cdc"
                    and "edit 1 committed" in _status(client, ids), 60, "the new colour committed")
    assert len(model.edit_stack) == 1 and model.live_edit is None
    client.wait_frame(_full(before, lambda f: int(f[y, x, 2]) > int(f[y, x, 0]) + 40), after=n,
                      message="the clicked pixel blue")

    # the background: an error in the status line, nothing added
    client.click_scene(0.5 / W, 0.5 / H)
    client.wait_for(lambda: "background" in _status(client, ids), 60, "the background click's error")
    assert panel.status_is_error and len(model.edit_stack) == 1

    client.set(ids["pick"], False)
    client.wait_for(lambda: not client.pointer_enabled, 30, "scene clicks disabled in the browser")
    client.click(ids["reset"])
    client.wait_for(lambda: "reset" in _status(client, ids), 60, "reset's status")
    assert len(model.edit_stack) == 0
