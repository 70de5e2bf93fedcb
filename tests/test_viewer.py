"""The viewer panel's actions called directly (no browser): save a view, upload, apply, toggle,
undo, reset, errors. A tiny trained run on the CPU."""

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
    assert "edit 1 applied" in panel.status and panel.progress == 0.0
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
    panel.commit_after_s = 60.0  # hold the release: the live edit first
    panel.pick_at(cam, int(xs[k]), int(ys[k]), wait=True)
    assert not panel.status_is_error, panel.status
    assert model.live_edit is not None and len(model.edit_stack) == 0 and "edit_0001.pt" not in files()
    # while nothing changes the fit is topped up to the config's steps and shown, still unwritten
    session, topped = panel._pick_session, model.live_edit
    assert session.steps_done == session.engine.cfg.steps
    live = render(model, cam)
    assert live[red][:, 1].mean() > before[red][:, 1].mean() + 0.1  # turning green while "dragged"
    panel.commit_after_s = 0.05
    panel.wait_pick(commit=True)
    assert model.live_edit is None and len(model.edit_stack) == 1, panel.status
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
