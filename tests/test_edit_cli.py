"""``virgi-edit`` on a tiny saved run (CPU): apply / list / undo / enable / specular, and every
bad input of the issue answered with one line, exit 2, nothing saved."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from rich.console import Console

from virgi_ns.cli.edit import Apply, Disable, Enable, Import, List, Pick, Reset, Specular, Undo, run
from virgi_ns.edit.recolor import RecolorRule, recolor
from virgi_ns.errors import InputError

from viewer_run import train_tiny
from virgi_scene import make_scene

from conftest import venv_command

REPO = Path(__file__).resolve().parents[1]
VIRGI_EDIT = venv_command("virgi-edit", "virgi_ns.cli.edit")
RULE = RecolorRule(h0=0, h1=360, shift=120, s_min=0.2, v_min=0.05)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    root = tmp_path_factory.mktemp("edit_cli")
    scene = make_scene(root / "scene")
    cfg, pipeline = train_tiny(scene, steps=20, output_dir=root / "outputs")
    config = cfg.get_base_dir() / "config.yml"
    model = pipeline.model
    cam = pipeline.datamanager.train_dataset.cameras[0:1]
    with torch.no_grad():
        rgb = model.get_outputs_for_camera(cam)["rgb"].cpu()
    edited, mask = recolor(rgb, RULE)
    assert int(mask.sum()) > 50
    png = root / "edited.png"
    Image.fromarray((edited.numpy() * 255 + 0.5).astype(np.uint8)).save(png)
    return {"config": config, "pipeline": pipeline, "png": png, "root": root, "edited": edited}


def _quiet() -> Console:
    return Console(file=open(os.devnull, "w"), stderr=False)


def _listing(config: Path) -> list[str]:
    d = config.parent / "edits"
    return sorted(p.name for p in d.iterdir()) if d.is_dir() else []


def _run_hash(config: Path) -> str:
    h = hashlib.sha256(config.read_bytes())
    for p in sorted((config.parent / "nerfstudio_models").glob("*.ckpt")):
        h.update(p.read_bytes())
    return h.hexdigest()


def _apply(saved, **kw) -> Apply:
    args = {"load_config": saved["config"], "image": saved["png"], "steps": 15}
    args.update(kw)
    if not any(k in kw for k in ("camera_index", "image_name", "camera_json")):
        args["camera_index"] = 0
    return Apply(**args)


@pytest.mark.slow  # three console-script runs, each loading the run through nerfstudio (~40 s)
def test_apply_list_undo_through_the_console_script(saved):
    cfg = str(saved["config"])
    before = _run_hash(saved["config"])
    p = subprocess.run([*VIRGI_EDIT, "apply", "--load-config", cfg, "--image", str(saved["png"]), "--camera-index", "0",
                        "--steps", "15"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "edit 1 saved" in p.stdout and "setup" in p.stdout
    assert _listing(saved["config"]) == ["edit_0001.pt", "stack.json"]
    p = subprocess.run([*VIRGI_EDIT, "list", "--load-config", cfg], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0 and "1 edit(s)" in p.stdout and "edited.png" in p.stdout
    p = subprocess.run([*VIRGI_EDIT, "undo", "--load-config", cfg], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0 and "0 edit(s) left" in p.stdout
    assert _listing(saved["config"]) == ["stack.json"]
    assert _run_hash(saved["config"]) == before  # the run itself is never written


def test_bad_input_is_one_line_and_exit_2(saved, tmp_path):
    txt = tmp_path / "notes.png"
    txt.write_text("not an image")
    listing = _listing(saved["config"])
    p = subprocess.run([*VIRGI_EDIT, "apply", "--load-config", str(saved["config"]), "--image", str(txt),
                        "--camera-index", "0"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "is not an image" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and _listing(saved["config"]) == listing


def test_python_api_apply_moves_the_render_and_undo_restores_it(saved):
    pl = saved["pipeline"]
    model = pl.model
    cam = pl.datamanager.train_dataset.cameras[0:1]
    base = model.get_outputs_for_camera(cam)["rgb"].detach().clone()
    out = run(_apply(saved, steps=60), _quiet(), pl)
    assert out.startswith("edit 1 saved")
    from virgi_ns.edit.stack import EditStack

    model.set_edit_stack(EditStack.open(saved["config"].parent, model.fingerprint()))
    after = model.get_outputs_for_camera(cam)["rgb"]
    err_before = float((base - saved["edited"]).abs().mean())
    err_after = float((after - saved["edited"]).abs().mean())
    assert err_after < 0.5 * err_before, (err_before, err_after)
    assert "edit 1 disabled" == run(Disable(saved["config"], 1), _quiet(), pl)
    model.set_edit_stack(EditStack.open(saved["config"].parent, model.fingerprint()))  # as stack.json says
    assert torch.equal(model.get_outputs_for_camera(cam)["rgb"], base)  # a disabled edit does not render
    assert "edit 1 enabled" == run(Enable(saved["config"], 1), _quiet(), pl)
    model.set_edit_stack(EditStack.open(saved["config"].parent, model.fingerprint()))
    torch.testing.assert_close(model.get_outputs_for_camera(cam)["rgb"], after, atol=1e-6, rtol=0)
    assert run(Specular(saved["config"], 1.5), _quiet(), pl) == "specular strength 1.5"
    assert "specular strength 1.5" in run(List(saved["config"]), _quiet(), pl)
    run(Undo(saved["config"]), _quiet(), pl)
    model.set_edit_stack(EditStack.open(saved["config"].parent, model.fingerprint()))
    model.edit_stack.set_specular_strength(1.0)
    assert torch.equal(model.get_outputs_for_camera(cam)["rgb"], base)
    run(Reset(saved["config"]), _quiet(), pl)
    model.set_edit_stack(None)


def _refused(saved, cmd, match: str) -> None:
    listing = _listing(saved["config"])
    before = _run_hash(saved["config"])
    with pytest.raises(InputError, match=match):
        run(cmd, _quiet(), saved["pipeline"])
    assert _listing(saved["config"]) == listing
    assert _run_hash(saved["config"]) == before


def test_bad_inputs_refused_with_nothing_saved(saved, tmp_path):
    ed = saved["edited"].numpy()
    h, w = ed.shape[:2]
    small = tmp_path / "small.png"
    Image.fromarray((ed[: h - 4, : w - 6] * 255).astype(np.uint8)).save(small)
    _refused(saved, _apply(saved, image=small), rf"is {w - 6}x{h - 4} but the camera renders {w}x{h}.*--resize")
    grey = tmp_path / "grey.png"
    Image.fromarray((ed.mean(-1) * 255).astype(np.uint8), mode="L").save(grey)
    _refused(saved, _apply(saved, image=grey), "grayscale")
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\x00\x01garbage")
    _refused(saved, _apply(saved, image=bad), "is not an image")
    n = len(saved["pipeline"].datamanager.train_dataset)
    _refused(saved, _apply(saved, camera_index=n), rf"out of range.*{n} training images")
    _refused(saved, _apply(saved, camera_index=-1), "out of range")
    _refused(saved, _apply(saved, image_name="no_such_frame.png"), "no image named 'no_such_frame.png'")
    _refused(saved, Apply(saved["config"], saved["png"], camera_index=0, image_name="x"), "exactly one of")
    _refused(saved, Apply(saved["config"], saved["png"]), "exactly one of")
    _refused(saved, _apply(saved, image=tmp_path / "missing.png"), "no such image")
    # an edit file of another base run
    from virgi_ns.edit.stack import Edit, EditSource, SegmentationHead

    model = saved["pipeline"].model
    foreign = Edit(model.field.diffuse_head.weight.detach(), model.field.diffuse_head.bias.detach(),
                   SegmentationHead(model.field.feature_dim, model.field.cfg.hidden),
                   EditSource("x.png", torch.eye(3), torch.eye(4), w, h), "0000000000000000")
    foreign.save(tmp_path / "foreign.pt")
    _refused(saved, Import(saved["config"], tmp_path / "foreign.pt"), "another base run")
    _refused(saved, Import(saved["config"], bad), "not a virgi edit file")
    _refused(saved, Enable(saved["config"], 3), "no edit number 3")
    _refused(saved, Specular(saved["config"], -1.0), ">= 0")


def test_rgba_is_accepted_with_a_note_and_resize_and_image_name_work(saved, tmp_path):
    ed = saved["edited"].numpy()
    rgba = np.concatenate([ed, np.full(ed.shape[:2] + (1,), 0.5, np.float32)], -1)
    p = tmp_path / "rgba.png"
    Image.fromarray((rgba * 255 + 0.5).astype(np.uint8), mode="RGBA").save(p)
    import io

    buf = io.StringIO()
    out = run(_apply(saved, image=p, steps=5), Console(file=buf), saved["pipeline"])
    assert "alpha channel ignored" in buf.getvalue() and out.startswith("edit 1 saved")
    big = tmp_path / "big.png"
    h, w = ed.shape[:2]
    Image.fromarray((ed * 255).astype(np.uint8)).resize((2 * w, 2 * h)).save(big)
    name = Path(saved["pipeline"].datamanager.train_dataset.image_filenames[2]).name
    buf = io.StringIO()
    out = run(_apply(saved, image=big, image_name=name, resize=True, steps=5), Console(file=buf), saved["pipeline"])
    assert out.startswith("edit 2 saved") and f"image {name}" in out and "resized" in buf.getvalue()
    assert run(Reset(saved["config"]), _quiet(), saved["pipeline"]).startswith("reset: removed 2")


def _render_saved(pipeline, path: Path) -> tuple[torch.Tensor, Path]:
    """(training view 0's render, ``path``, where it is saved as an 8-bit PNG: an --original)."""
    cam = pipeline.datamanager.train_dataset.cameras[0:1]
    with torch.no_grad():
        rgb = pipeline.model.get_outputs_for_camera(cam)["rgb"].cpu()
    Image.fromarray((rgb.numpy() * 255 + 0.5).astype(np.uint8)).save(path)
    return rgb, path


def test_original_image_limits_the_fit_to_changed_pixels(saved, tmp_path):
    """--original (here the render the edit was made from): the saved edit records the share of
    pixels the rule changed; --whole-image fits them all; an --original of another size is refused
    with nothing saved."""
    from virgi_ns.edit.stack import EditStack

    pl = saved["pipeline"]
    rgb, orig = _render_saved(pl, tmp_path / "render.png")
    _, mask = recolor(rgb, RULE)
    try:
        first = run(_apply(saved, original=orig), _quiet(), pl)
        run(_apply(saved, whole_image=True), _quiet(), pl)
        assert "edited + its slope x (render - photo))" in first, first
        st = EditStack.open(saved["config"].parent, pl.model.fingerprint())
        fr = [e.edit.info["changed_fraction"] for e in st.entries]
        assert abs(fr[0] - float(mask.float().mean())) < 0.03 and fr[0] < 0.9, fr
        assert fr[1] == 1.0
        run(Reset(saved["config"]), _quiet(), pl)  # the next edit starts from the unedited render again
        msg = run(_apply(saved, original=orig, changed_target="edited"), _quiet(), pl)
        assert "(original given, edited image)" in msg, msg
        st = EditStack.open(saved["config"].parent, pl.model.fingerprint())
        assert st.entries[0].edit.info["fit"].endswith("edited image)")
        assert st.entries[0].edit.info["changed_fraction"] >= 0.2  # a large edit: the map start
        assert st.entries[0].edit.info["start"] == "colour map"
        assert st.entries[0].edit.info["recipe"] == "joint"
        run(Reset(saved["config"]), _quiet(), pl)
        run(_apply(saved, original=orig, recipe="staged"), _quiet(), pl)
        st = EditStack.open(saved["config"].parent, pl.model.fingerprint())
        assert st.entries[0].edit.info["recipe"] == "staged" and st.entries[0].edit.info["start"] == "colour map"
        assert st.entries[0].edit.info["unchanged_weights"] == "count"
        run(Reset(saved["config"]), _quiet(), pl)
        run(_apply(saved, original=orig, unchanged_weights="colour"), _quiet(), pl)
        st = EditStack.open(saved["config"].parent, pl.model.fingerprint())
        assert st.entries[0].edit.info["unchanged_weights"] == "colour"
        small = tmp_path / "small.png"
        Image.fromarray(np.zeros((4, 5, 3), np.uint8)).save(small)
        _refused(saved, _apply(saved, original=small), "--original is 5x4.*--resize")
    finally:
        run(Reset(saved["config"]), _quiet(), pl)


def test_an_edit_that_barely_moves_its_changed_pixels_is_saved_with_a_warning(saved, tmp_path):
    """One step leaves the changed pixels nearly where they were: the summary says so on a line of its own,
    with what to try; the full fit's summary has no such line."""
    pl = saved["pipeline"]
    _, orig = _render_saved(pl, tmp_path / "render.png")
    try:
        short = run(_apply(saved, original=orig, steps=1), _quiet(), pl)
        full = run(_apply(saved, original=orig, steps=60), _quiet(), pl)
    finally:
        run(Reset(saved["config"]), _quiet(), pl)
    assert short.count("\n") == 1 and short.splitlines()[1].startswith("warning: the fit moved the changed pixels"), short
    assert "--recipe staged" in short and "changes almost nothing" in short
    assert "warning" not in full, full


def _objects(pipeline, index: int):
    """(render, the matte red sphere's pixels, the glossy blue sphere's pixels) of training view ``index``."""
    cam = pipeline.datamanager.train_dataset.cameras[index : index + 1]
    with torch.no_grad():
        out = pipeline.model.get_outputs_for_camera(cam)
    rgb, acc = out["rgb"].cpu(), out["accumulation"][..., 0].cpu()
    solid = acc > 0.95
    return rgb, solid & (rgb[..., 0] > rgb[..., 2] + 0.2), solid & (rgb[..., 2] > rgb[..., 0] + 0.2)


def _central(mask: torch.Tensor) -> tuple[int, int]:
    ys, xs = torch.nonzero(mask, as_tuple=True)
    i = int(((ys - ys.float().mean()) ** 2 + (xs - xs.float().mean()) ** 2).argmin())
    return int(xs[i]), int(ys[i])


def _pick(saved, **kw) -> Pick:
    args = {"load_config": saved["config"], "pixel": _central(_objects(saved["pipeline"], 0)[1]),
            "colour": "#20c040", "camera_index": 0, "steps": 40}
    args.update(kw)
    return Pick(**args)


def test_pick_recolours_the_clicked_sphere_only_and_saves_what_it_selected(saved, monkeypatch):
    """A pick on the red sphere in view 0 turns it green in another view and leaves the blue one;
    the edited image and the selection lie beside the edit; undo removes all three. A one-step fit is
    saved with a warning; a full joint fit that stalls is refitted staged, said in a line."""
    from virgi_ns.edit.stack import EditStack

    pl = saved["pipeline"]
    model = pl.model
    before, red, blue = _objects(pl, 3)
    assert int(red.sum()) > 20 and int(blue.sum()) > 20
    try:
        msg = run(_pick(saved), _quiet(), pl)
        assert msg.startswith("edit 1 saved") and "hue -> #20c040" in msg and "warning" not in msg, msg
        assert _listing(saved["config"]) == ["edit_0001.pt", "edit_0001_edited.png", "edit_0001_selection.png",
                                             "stack.json"]
        sel = np.asarray(Image.open(saved["config"].parent / "edits" / "edit_0001_selection.png")) > 127
        _, red0, blue0 = _objects(pl, 0)
        assert sel[red0.numpy()].mean() > 0.9 and not sel[blue0.numpy()].any()
        model.set_edit_stack(EditStack.open(saved["config"].parent, model.fingerprint()))
        after, _, _ = _objects(pl, 3)
        green = torch.tensor([0.125, 0.75, 0.25])
        gap_before = float((before[red] - green).abs().mean())
        assert float((after[red] - green).abs().mean()) < 0.6 * gap_before
        assert float(after[red][:, 1].mean()) > float(after[red][:, 0].mean())  # green over red now
        assert float((after - before)[blue].abs().mean()) < 0.03
        assert EditStack.open(saved["config"].parent, model.fingerprint()).entries[0].edit.info["unchanged_weights"] \
            == "count"
        run(Undo(saved["config"]), _quiet(), pl)
        assert _listing(saved["config"]) == ["stack.json"]
        model.set_edit_stack(None)
        run(_pick(saved, pixel=_central(red0), unchanged_weights="colour", steps=5), _quiet(), pl)
        assert EditStack.open(saved["config"].parent, model.fingerprint()).entries[0].edit.info["unchanged_weights"] \
            == "colour"
        run(Undo(saved["config"]), _quiet(), pl)
        short = run(_pick(saved, steps=1), _quiet(), pl)  # one step leaves the sphere red: saved, with a warning
        assert short.splitlines()[1].startswith("warning: the fit moved") and "pick again" in short, short
        run(Undo(saved["config"]), _quiet(), pl)
        # a joint fit whose segmentation starts dead stalls at its full steps: fitted again staged, said in a line
        import virgi_ns.edit.pick as pick

        monkeypatch.setattr(pick, "pick_config", lambda device: pick.EditConfig(seg_init_bias=-30.0))
        restaged = run(_pick(saved, steps=None), _quiet(), pl)
        monkeypatch.undo()
        assert restaged.splitlines()[1].startswith("the joint fit left the selection nearly unchanged") \
            and "refitted staged" in restaged and "warning" not in restaged, restaged
        assert EditStack.open(saved["config"].parent, model.fingerprint()).entries[0].edit.info["recipe"] == "staged"
        run(Undo(saved["config"]), _quiet(), pl)
    finally:
        model.set_edit_stack(None)
        if (saved["config"].parent / "edits" / "stack.json").is_file():
            run(Reset(saved["config"]), _quiet(), pl)


def test_bad_picks_are_one_line_with_nothing_saved(saved):
    pl = saved["pipeline"]
    rgb, _, _ = _objects(pl, 0)
    h, w = rgb.shape[:2]
    _refused(saved, _pick(saved, pixel=(w, 3)), rf"outside the {w}x{h} image")
    _refused(saved, _pick(saved, pixel=(2, -1)), "outside")
    _refused(saved, _pick(saved, pixel=(0, 0)), "background")
    for bad in ("green", "#12345", "#zz0000", ""):
        _refused(saved, _pick(saved, colour=bad), "#RRGGBB")
    for t in (-0.1, 1.5):
        _refused(saved, _pick(saved, tolerance=t), r"tolerance must be in \[0, 1\]")
    _refused(saved, _pick(saved, mode="tint"), "recolour mode")
    _refused(saved, _pick(saved, steps=0), "--steps must be >= 1")
    _refused(saved, _pick(saved, camera_index=None), "exactly one of")


def test_a_bad_pick_from_the_command_line_exits_2(saved):
    """Through the module's entry point (what the ``virgi-edit`` script runs): one line, exit 2; the
    colour and the tolerance are checked before the run is loaded."""
    listing = _listing(saved["config"])
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for extra, want in ((["--colour", "reddish"], "cannot read the colour 'reddish'"),
                        (["--colour", "#d02020", "--tolerance", "2"], "tolerance must be in [0, 1]")):
        p = subprocess.run([sys.executable, "-m", "virgi_ns.cli.edit", "pick", "--load-config", str(saved["config"]),
                            "--camera-index", "0", "--pixel", "5", "5"] + extra,
                           capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
        assert p.returncode == 2, p.stderr
        assert p.stderr.strip().count("\n") == 0 and want in p.stderr, p.stderr
    assert _listing(saved["config"]) == listing


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
