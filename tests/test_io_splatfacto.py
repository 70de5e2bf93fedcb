"""Gaussians from a nerfstudio splatfacto checkpoint (.ckpt) and from a run's config.yml: checkpoints
laid out as nerfstudio writes them, and a run written by nerfstudio itself (its splatfacto config's
``config.yml``, its trainer's checkpoint of a ``SplatfactoModel`` pipeline set up on the CPU)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from virgi_ns.errors import InputError
from virgi_ns.io import load_splat
from virgi_ns.io.splatfacto import _safe_load


def _checkpoint(n: int, degree: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    params = {"means": r(n, 3), "scales": r(n, 3), "quats": r(n, 4), "features_dc": r(n, 3),
              "features_rest": r(n, (degree + 1) ** 2 - 1, 3), "opacities": r(n, 1)}
    pipeline = {f"_model.gauss_params.{k}": v for k, v in params.items()}
    pipeline["_model.camera_optimizer.pose_adjustment"] = r(4, 6)
    pipeline["datamanager.train_camera_optimizer.pose_adjustment"] = r(4, 6)
    # the layout nerfstudio's Trainer.save_checkpoint writes, numpy scalars included
    return {"step": np.int64(seed), "pipeline": pipeline, "optimizers": {}, "schedulers": {},
            "scalers": {"scale": np.float64(1.0)}}, params


def test_checkpoint_loads_in_our_conventions(tmp_path):
    ckpt, p = _checkpoint(50, 3, seed=7)
    torch.save(ckpt, tmp_path / "step-000000007.ckpt")
    g = load_splat(tmp_path / "step-000000007.ckpt")
    assert len(g) == 50 and g.sh_degree == 3
    assert torch.equal(g.means, p["means"]) and torch.equal(g.quats, p["quats"])
    assert torch.equal(g.opacities, p["opacities"][:, 0])
    assert torch.equal(g.sh[:, 0], p["features_dc"]) and torch.equal(g.sh[:, 1:], p["features_rest"])


def test_config_yml_picks_the_newest_checkpoint(tmp_path):
    run = tmp_path / "outputs" / "scene" / "splatfacto" / "2024-01-01_000000"
    models = run / "nerfstudio_models"
    models.mkdir(parents=True)
    for step in (500, 29999, 3000):
        torch.save(_checkpoint(10 + step % 7, 0, seed=step)[0], models / f"step-{step:09d}.ckpt")
    (run / "config.yml").write_text(
        "!!python/object:nerfstudio.engine.trainer.TrainerConfig\n"
        "relative_model_dir: !!python/object/apply:pathlib.PosixPath\n- nerfstudio_models\n"
    )
    g = load_splat(run / "config.yml")
    assert len(g) == 10 + 29999 % 7
    assert torch.equal(g.means, _checkpoint(10 + 29999 % 7, 0, seed=29999)[1]["means"])
    assert len(load_splat(run)) == len(g)  # the run directory works too


def test_checkpoint_without_gaussians_is_refused(tmp_path):
    torch.save({"step": 1, "pipeline": {"_model.field.mlp.weight": torch.zeros(2, 2)}}, tmp_path / "a.ckpt")
    with pytest.raises(InputError, match="not a splatfacto checkpoint"):
        load_splat(tmp_path / "a.ckpt")


def test_corrupt_checkpoint_and_empty_run_are_refused(tmp_path):
    (tmp_path / "b.ckpt").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="cannot read the checkpoint"):
        load_splat(tmp_path / "b.ckpt")
    # arbitrary pickled objects are not unpickled (safe loading), only refused
    ckpt, _ = _checkpoint(5, 0, seed=1)
    torch.save({**ckpt, "extra": argparse.Namespace(a=1)}, tmp_path / "c.ckpt")
    with pytest.raises(InputError, match="cannot read the checkpoint"):
        load_splat(tmp_path / "c.ckpt")
    (tmp_path / "config.yml").write_text("x: 1\n")
    with pytest.raises(InputError, match="no step-\\*.ckpt checkpoint"):
        load_splat(tmp_path / "config.yml")


def test_degree_zero_checkpoint_colours_are_the_sigmoid_of_features_dc(tmp_path):
    """splatfacto with sh_degree 0 renders sigmoid(features_dc); loaded, band 0 must give that colour
    through the SH rule ``0.2820948 * f_dc + 0.5``."""
    ckpt, p = _checkpoint(40, 0, seed=3)
    torch.save(ckpt, tmp_path / "step-000000003.ckpt")
    g = load_splat(tmp_path / "step-000000003.ckpt")
    assert g.sh_degree == 0
    colour = 0.28209479177387814 * g.sh[:, 0].double() + 0.5
    torch.testing.assert_close(colour, torch.sigmoid(p["features_dc"].double()), atol=1e-6, rtol=0)


def test_reading_a_splatfacto_checkpoint_leaves_the_checkpoint_allow_list_alone(tmp_path):
    """The reader's temporary allow-list must not take back the numpy globals our compat module allowed
    for good (nerfstudio checkpoints need them later in the same process)."""
    import numpy as np

    import virgi_ns.nerfstudio.compat as compat

    compat.apply()
    before = set(map(str, torch.serialization.get_safe_globals()))
    assert str(np.dtype) in before
    path = tmp_path / "x.ckpt"
    torch.save({"pipeline": {}, "step": np.float64(1.0)}, path)
    assert _safe_load(path) == {"pipeline": {}, "step": 1.0}
    assert before <= set(map(str, torch.serialization.get_safe_globals()))


# ------------------------------------------------------------------ a run written by nerfstudio
def _splatfacto_config(data, output_dir, sh_degree: int):
    """``ns-train splatfacto``'s TrainerConfig (nerfstudio's method_configs["splatfacto"], whose module
    imports every method, rebuilt from the same pieces), on the CPU."""
    from nerfstudio.configs.base_config import MachineConfig
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
    from nerfstudio.engine.trainer import TrainerConfig
    from nerfstudio.models.splatfacto import SplatfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    def adam(lr, scheduler=None):
        return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": scheduler}

    return TrainerConfig(
        method_name="splatfacto", experiment_name="scene", timestamp="2026-01-01_000000", output_dir=output_dir,
        max_num_iterations=30000, mixed_precision=False, machine=MachineConfig(device_type="cpu"),
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(data=data, dataparser=NerfstudioDataParserConfig(load_3D_points=True),
                                                   cache_images_type="uint8"),
            # random_init: seeding from points moves them to CUDA in splatfacto's populate_modules
            model=SplatfactoModelConfig(sh_degree=sh_degree, random_init=True, num_random=300)),
        optimizers={
            "means": adam(1.6e-4, ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=30000)),
            "features_dc": adam(0.0025), "features_rest": adam(0.0025 / 20), "opacities": adam(0.05),
            "scales": adam(0.005), "quats": adam(0.001),
            "camera_opt": adam(1e-4, ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=30000,
                                                                     warmup_steps=1000, lr_pre_warmup=0)),
            "bilateral_grid": adam(2e-3, ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=30000,
                                                                         warmup_steps=1000, lr_pre_warmup=0)),
        },
    )


@pytest.fixture(scope="module")
def splatfacto_run(tmp_path_factory):
    """(config.yml, {step: Gaussian parameters}) of a splatfacto run written by nerfstudio: its
    ``TrainerConfig.save_config`` and its ``Trainer.save_checkpoint`` of the pipeline at two steps (the
    Gaussians moved in between, as training moves them). Built offline (LPIPS's weights stand-in)."""
    from nerfstudio.engine.trainer import Trainer

    from virgi_ns.metrics import offline_splatfacto_lpips
    from virgi_scene import make_scene

    import torchmetrics.image.lpip as lp

    root = tmp_path_factory.mktemp("splatfacto_run")
    scene = make_scene(root / "scene", n_per_sphere=20, views=8)
    torch.manual_seed(0)
    cfg = _splatfacto_config(scene.root, root / "outputs", sh_degree=3)
    cfg.save_only_latest_checkpoint = False  # keep both: the reader must pick the newest
    trainer = Trainer(cfg)
    lpips_class = lp.LearnedPerceptualImagePatchSimilarity
    try:
        offline_splatfacto_lpips()  # swaps torchmetrics' LPIPS class for the process: put it back after
        trainer.pipeline = cfg.pipeline.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    finally:
        lp.LearnedPerceptualImagePatchSimilarity = lpips_class
    trainer.optimizers = trainer.setup_optimizers()
    cfg.save_config()
    params = trainer.pipeline.model.gauss_params
    saved = {}
    for step in (1999, 29999):
        with torch.no_grad():
            for p in params.values():
                p.add_(torch.randn_like(p) * 0.1)
        trainer.save_checkpoint(step)
        saved[step] = {k: v.detach().clone() for k, v in params.items()}
    return cfg.get_base_dir() / "config.yml", saved


def _check_same(g, p) -> None:
    n = p["means"].shape[0]
    assert len(g) == n and g.sh_degree == 3
    assert torch.equal(g.means, p["means"]) and torch.equal(g.scales, p["scales"])
    assert torch.equal(g.quats, p["quats"]) and torch.equal(g.opacities, p["opacities"][:, 0])
    assert torch.equal(g.sh[:, 0], p["features_dc"]) and torch.equal(g.sh[:, 1:], p["features_rest"])


def test_a_checkpoint_nerfstudio_wrote_loads(splatfacto_run):
    config, saved = splatfacto_run
    ckpts = sorted((config.parent / "nerfstudio_models").glob("step-*.ckpt"))
    assert [c.name for c in ckpts] == ["step-000001999.ckpt", "step-000029999.ckpt"]
    _check_same(load_splat(ckpts[0]), saved[1999])
    _check_same(load_splat(ckpts[1]), saved[29999])


def test_a_config_nerfstudio_wrote_opens_its_newest_checkpoint(splatfacto_run):
    config, saved = splatfacto_run
    assert "nerfstudio.models.splatfacto.SplatfactoModelConfig" in config.read_text()
    _check_same(load_splat(config), saved[29999])
    _check_same(load_splat(config.parent), saved[29999])
