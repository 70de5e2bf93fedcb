"""The command-line tools' own run loader (:mod:`virgi_ns.nerfstudio.saved_run`, :func:`virgi_ns.nerfstudio.runs.open_run`)
on a tiny saved run (CPU): it gives the Gaussians, colour field, cameras and photos nerfstudio's
loader gives; ``list``/``undo`` import neither nerfstudio nor torch and ``apply``/``export`` only
nerfstudio's field components (the colour field's encodings); runs without ``virgi_run.json`` still load (through nerfstudio, which writes it)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image
from rich.console import Console

from virgi_ns.errors import InputError

from viewer_run import train_tiny
from virgi_scene import make_scene

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A run saved by ``save_run`` (virgi_run.json beside its config.yml) and the same run loaded
    through nerfstudio (:func:`virgi_ns.nerfstudio.runs.load_run`, the independent path)."""
    from virgi_ns.nerfstudio.runs import load_run

    root = tmp_path_factory.mktemp("saved_run")
    scene = make_scene(root / "scene")
    cfg, pipeline = train_tiny(scene, steps=6, output_dir=root / "outputs")
    config = cfg.get_base_dir() / "config.yml"
    _, full = load_run(config)
    with torch.no_grad():
        rgb = full.model.get_outputs_for_camera(full.datamanager.train_dataset.cameras[1:2])["rgb"].cpu()
    edited = root / "edited.png"
    Image.fromarray((rgb.flip(-1).numpy() * 255 + 0.5).astype(np.uint8)).save(edited)  # red and blue swapped
    return {"config": config, "full": full, "root": root, "edited": edited}


def _quiet() -> Console:
    return Console(file=open(os.devnull, "w"), stderr=False)


def _copy_run(saved, dest: Path) -> Path:
    """A copy of the run in ``dest`` as a run folder of its own (a RunDirConfig naming ``dest``), its
    virgi_run.json taking the new config's digest as training there would have written it."""
    from dataclasses import fields

    from nerfstudio.engine.trainer import TrainerConfig

    from virgi_ns.nerfstudio.pipeline import RunDirConfig
    from virgi_ns.nerfstudio.saved_run import RUN_INFO, config_digest

    shutil.copytree(saved["config"].parent, dest)
    doc = yaml.load(saved["config"].read_text(), Loader=yaml.Loader)
    run_dir = RunDirConfig(**{f.name: getattr(doc, f.name) for f in fields(TrainerConfig)})
    run_dir.output_dir = dest
    (dest / "config.yml").write_text(yaml.dump(run_dir))
    info = dest / RUN_INFO
    d = json.loads(info.read_text())
    d["config_sha256"] = config_digest(dest / "config.yml")
    info.write_text(json.dumps(d))
    return dest / "config.yml"


def test_the_run_info_stays_out_of_nerfstudios_checkpoint_folder(saved, tmp_path):
    """nerfstudio's loaders (ns-viewer, ns-eval, ns-render) read every name in the checkpoint folder as
    ``step-N.ckpt``: training leaves nothing else there, and a run of an earlier version, whose
    virgi_run.json lay there, gets it moved beside config.yml when a virgi command loads it."""
    from virgi_ns.nerfstudio.saved_run import RUN_INFO, load_saved_run

    cfg = _copy_run(saved, tmp_path / "a")
    ckpt = cfg.parent / "nerfstudio_models"

    def nerfstudio_steps() -> list[int]:  # eval_utils.eval_load_checkpoint's own parse of the folder
        return sorted(int(x[x.find("-") + 1 : x.find(".")]) for x in os.listdir(ckpt))

    assert nerfstudio_steps() and (cfg.parent / RUN_INFO).is_file()
    (cfg.parent / RUN_INFO).rename(ckpt / RUN_INFO)  # as earlier versions wrote it
    with pytest.raises(ValueError):
        nerfstudio_steps()
    load_saved_run(cfg, torch.device("cpu"))  # the fast path: it found the file and moved it
    assert (cfg.parent / RUN_INFO).is_file() and not (ckpt / RUN_INFO).exists()
    assert nerfstudio_steps()


def test_the_fast_loader_gives_what_nerfstudios_loader_gives(saved):
    """Gaussians, field, gate, background, fingerprint, cameras (all and one by one), image files,
    photos and the capture frame equal those of the pipeline nerfstudio's loader builds."""
    from virgi_ns.nerfstudio.cameras import raster_cameras
    from virgi_ns.nerfstudio.frames import CaptureFrame
    from virgi_ns.nerfstudio.saved_run import RUN_INFO, load_saved_run

    full = saved["full"]
    fm = full.model
    assert (saved["config"].parent / RUN_INFO).is_file()  # written by save_run
    run = load_saved_run(saved["config"], torch.device("cpu"))
    m = run.model
    for name in ("means", "scales", "quats", "opacities", "features_dc", "features_rest"):
        assert torch.equal(getattr(m, name), getattr(fm, name).detach()), name
    sd, fsd = m.field.state_dict(), fm.field.state_dict()
    assert list(sd) == list(fsd) and all(torch.equal(sd[k], fsd[k]) for k in sd)
    g = torch.Generator().manual_seed(0)
    pos = fm.means.detach()[torch.randint(len(fm.means), (200,), generator=g)]
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    with torch.no_grad():
        assert torch.equal(m.field(pos, dirs)["rgb"], fm.field(pos, dirs)["rgb"])
    assert m.gate_ready() and fm.gate_ready()
    assert torch.equal(m.spec_magnitude, fm.spec_magnitude) and torch.equal(m.diffuse_cache, fm.diffuse_cache)
    assert torch.equal(m.spec_gate, fm.spec_gate)
    assert torch.equal(m.background_color, fm.background_color.float())
    assert m.fingerprint() == fm.fingerprint()
    assert m.config.raster_backend == fm.config.raster_backend and m.config.gate_threshold == fm.config.gate_threshold
    dm = full.datamanager
    for views, ds in ((run.info.train, dm.train_dataset), (run.info.eval, dm.eval_dataset)):
        ref = raster_cameras(ds.cameras)
        cams = views.cameras()
        for a, b in ((cams.Ks, ref.Ks), (cams.viewmats, ref.viewmats), (cams.widths, ref.widths),
                     (cams.heights, ref.heights)):
            assert torch.equal(a, b)
        for i in (0, len(ds) - 1):  # one camera alone, as --camera-index computes it
            one, ref1 = views.camera(i), raster_cameras(ds.cameras[i : i + 1])
            assert torch.equal(one.Ks, ref1.Ks) and torch.equal(one.viewmats, ref1.viewmats)
        assert views.filenames == [str(f) for f in ds.image_filenames]
        assert np.array_equal(views.photo(1), ds.get_numpy_image(1))
    ref_frame = CaptureFrame.from_pipeline(full)
    assert torch.equal(run.info.capture_transform, ref_frame.transform) and run.info.capture_scale == ref_frame.scale
    from virgi_ns.nerfstudio.saved_run import run_settings

    assert run_settings(saved["config"]).checkpoint_dir == yaml.load(saved["config"].read_text(),
                                                                      Loader=yaml.Loader).get_checkpoint_dir()


def test_an_edit_and_an_export_are_the_same_through_either_loader(saved, tmp_path):
    """``apply`` through the fast loader and through nerfstudio's pipeline save the same edit, and
    ``virgi-export`` writes the same file (the two runs are copies of one run)."""
    from virgi_ns.cli.edit import Apply, run
    from virgi_ns.cli.export import Export
    from virgi_ns.cli.export import run as export
    from virgi_ns.edit.stack import Edit
    from virgi_ns.io import load_splat

    from virgi_ns.nerfstudio.runs import open_run

    cfg_a = _copy_run(saved, tmp_path / "a")
    cfg_b = _copy_run(saved, tmp_path / "b")
    for cfg, fast in ((cfg_a, True), (cfg_b, False)):
        info = cfg.parent / "virgi_run.json"
        if not fast:
            info.unlink()
        opened = open_run(cfg, _quiet())
        assert (opened.pipeline is None) == fast
        torch.manual_seed(0)  # after the load: building nerfstudio's model draws random numbers
        assert run(Apply(cfg, saved["edited"], camera_index=1, steps=4), _quiet(), opened).startswith("edit 1")
        if not fast:
            info.unlink()
        export(Export(load_config=cfg, out=cfg.parent / "out.ply", directions=16))
    a = Edit.load(cfg_a.parent / "edits" / "edit_0001.pt")
    b = Edit.load(cfg_b.parent / "edits" / "edit_0001.pt")
    assert a.fingerprint == b.fingerprint
    assert torch.equal(a.head_weight, b.head_weight) and torch.equal(a.source.viewmat, b.source.viewmat)
    ga, gb = load_splat(cfg_a.parent / "out.ply"), load_splat(cfg_b.parent / "out.ply")
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(ga, name), getattr(gb, name)), name
    # the nerfstudio load wrote virgi_run.json, the same as training wrote
    from virgi_ns.nerfstudio.saved_run import config_digest

    ja = json.loads((cfg_a.parent / "virgi_run.json").read_text())
    jb = json.loads((cfg_b.parent / "virgi_run.json").read_text())
    assert jb.pop("config_sha256") == config_digest(cfg_b)
    ja.pop("config_sha256")
    assert ja == jb


FIELD_PARTS = "nerfstudio,nerfstudio.field_components.*,nerfstudio.utils.*,nerfstudio.data,nerfstudio.data.scene_box"
"""What of nerfstudio loading a run's colour field may import: its encodings and their helpers,
none of its models, pipelines, data managers, cameras or viewer."""


def _blocked(module: str, blocked: str, *args: str, allowed: str = "") -> subprocess.CompletedProcess:
    """Run ``python -m module args`` in a fresh process where importing any of ``blocked``
    (comma-separated top-level packages) raises, except the modules ``allowed`` names
    (comma-separated; ``pkg.*`` allows a package and its submodules)."""
    code = ("import os, runpy, sys\n"
            "def ok(name):\n"
            "    for a in filter(None, os.environ['ALLOWED'].split(',')):\n"
            "        if name == a or (a.endswith('.*') and (name == a[:-2] or name.startswith(a[:-1]))):\n"
            "            return True\n"
            "    return False\n"
            "class Block:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] in os.environ['BLOCKED'].split(',') and not ok(name):\n"
            "            raise ImportError(name + ' must not be imported here')\n"
            "sys.meta_path.insert(0, Block())\n"
            "sys.argv = [os.environ['MOD']] + sys.argv[1:]\n"
            "runpy.run_module(os.environ['MOD'], run_name='__main__', alter_sys=True)\n")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "BLOCKED": blocked, "ALLOWED": allowed, "MOD": module}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=600, cwd=REPO)


def test_stack_commands_import_neither_nerfstudio_nor_torch_and_apply_export_only_its_field_parts(saved, tmp_path):
    cfg = _copy_run(saved, tmp_path / "run")
    p = _blocked("virgi_ns.cli.edit", "nerfstudio", "apply", "--load-config", str(cfg), "--image",
                 str(saved["edited"]), "--camera-index", "1", "--steps", "2", allowed=FIELD_PARTS)
    assert p.returncode == 0 and p.stdout.startswith("edit 1 saved"), p.stderr
    p = _blocked("virgi_ns.cli.export", "nerfstudio", "--load-config", str(cfg), "--out", str(tmp_path / "o.ply"),
                 "--directions", "4", allowed=FIELD_PARTS)
    assert p.returncode == 0 and "1 edit(s)" in p.stdout, p.stderr
    for args, want in ((["list"], "1 edit(s), specular strength 1"), (["specular", "1.5"], "specular strength 1.5"),
                       (["disable", "1"], "edit 1 disabled"), (["list"], "off  edit_0001.pt  edited.png"),
                       (["enable", "7"], "error: no edit number 7"), (["undo"], "undone: 0 edit(s) left"),
                       (["undo"], "error: nothing to undo")):
        p = _blocked("virgi_ns.cli.edit", "nerfstudio,torch,numpy", args[0], "--load-config", str(cfg), *args[1:])
        assert want in p.stdout + p.stderr, (args, p.stdout, p.stderr)
        assert p.returncode == (2 if want.startswith("error") else 0), (args, p.stderr)
        assert "Traceback" not in p.stderr
    assert sorted(x.name for x in (cfg.parent / "edits").iterdir()) == ["stack.json"]


def test_a_run_without_virgi_run_json_loads_through_nerfstudio_with_a_note(saved, tmp_path):
    """No file, a damaged one, or a config changed since: a one-line note, nerfstudio's loader,
    the same model; the file is (re)written for the next command."""
    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.nerfstudio.saved_run import RUN_INFO

    cfg = _copy_run(saved, tmp_path / "run")
    info = cfg.parent / RUN_INFO
    good = info.read_text()
    fingerprint = saved["full"].model.fingerprint()
    for damage, note in ((lambda: info.unlink(), f"no {RUN_INFO}"), (lambda: info.write_text("{"), "unreadable"),
                         (lambda: cfg.write_text(cfg.read_text() + "\n"), "changed since")):
        damage()
        out = tmp_path / "console.txt"
        with open(out, "w") as f:
            run = open_run(cfg, Console(file=f, width=80))
        text = out.read_text()
        assert note in text and text.count("\n") == 1, text
        assert run.pipeline is not None and run.model.fingerprint() == fingerprint
        assert json.loads(info.read_text())["train"] == json.loads(good)["train"]
        assert open_run(cfg, _quiet()).pipeline is None  # the next one is fast
    assert open_run(cfg, _quiet()).model.fingerprint() == fingerprint


def test_bad_runs_are_one_clear_line(saved, tmp_path):
    from virgi_ns.nerfstudio.runs import open_run

    with pytest.raises(InputError, match="no such config"):
        open_run(tmp_path / "none.yml", _quiet())
    cfg = _copy_run(saved, tmp_path / "run")
    ckpt = next((cfg.parent / "nerfstudio_models").glob("step-*.ckpt"))
    ckpt.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="cannot read the checkpoint"):
        open_run(cfg, _quiet())
    ckpt.unlink()
    with pytest.raises(InputError, match=r"no checkpoint \(step-\*.ckpt\)"):
        open_run(cfg, _quiet())
    other = tmp_path / "other.yml"  # not a virgi run: nerfstudio's loader judges it
    other.write_text(cfg.read_text().replace("virgi_ns.nerfstudio.model.VirgiModelConfig",
                                             "nerfstudio.models.splatfacto.SplatfactoModelConfig"))
    with pytest.raises(InputError, match="not a virgi run"):
        open_run(other, _quiet())
    garbage = tmp_path / "garbage.yml"
    garbage.write_text("{{{: [")
    with pytest.raises(InputError, match="not a nerfstudio config"):
        open_run(garbage, _quiet())


def test_list_reads_timings_from_the_manifest_and_from_older_stacks_edit_files(saved, tmp_path):
    """The manifest records each edit's info; a stack written before it did still lists its
    timings (read from the edit files)."""
    from virgi_ns.cli.edit import Apply, List, run

    cfg = _copy_run(saved, tmp_path / "run")
    run(Apply(cfg, saved["edited"], camera_index=1, steps=2), _quiet())
    listed = run(List(cfg))
    assert "1 edit(s)" in listed and " s]" in listed
    man = cfg.parent / "edits" / "stack.json"
    m = json.loads(man.read_text())
    assert "setup_s" in m["edits"][0]["info"]
    for e in m["edits"]:
        del e["info"]
    man.write_text(json.dumps(m))
    assert run(List(cfg)) == listed


def test_virgis_trainer_writes_virgi_run_json_beside_its_config(saved, tmp_path):
    """``ns-train``'s path: virgi's trainer saves its checkpoint, then virgi_run.json beside config.yml
    (the checkpoint folder holds checkpoints only, as nerfstudio's loaders need), which the commands'
    loader takes (no nerfstudio load) and which describes the cameras nerfstudio's loader sees."""
    from viewer_run import tiny_config

    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.nerfstudio.cameras import raster_cameras
    from virgi_ns.nerfstudio.saved_run import RUN_INFO

    scene = make_scene(tmp_path / "scene")
    cfg = tiny_config(scene, 2, tmp_path / "outputs")
    cfg.vis = "tensorboard"
    cfg.steps_per_eval_image = cfg.steps_per_eval_batch = cfg.steps_per_eval_all_images = 10**9
    cfg.steps_per_save = 10**9
    cfg.save_config()
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    ckpt_dir = cfg.get_checkpoint_dir()
    assert [p.name for p in ckpt_dir.iterdir()] == [p.name for p in ckpt_dir.glob("step-*.ckpt")] != []
    assert (cfg.get_base_dir() / RUN_INFO).is_file()
    opened = open_run(cfg.get_base_dir() / "config.yml", _quiet())
    assert opened.pipeline is None
    assert opened.model.fingerprint() == trainer.pipeline.model.fingerprint()
    ref = raster_cameras(saved["full"].datamanager.train_dataset.cameras)  # the same capture layout
    assert torch.equal(opened.train.cameras().Ks, ref.Ks) and len(opened.train) == len(ref)
