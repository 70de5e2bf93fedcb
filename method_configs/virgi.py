"""Method specifications registered with nerfstudio (``ns-train virgi``, ``ns-train virgi-vanilla``).

``virgi``: splatfacto geometry (30k steps, or imported with ``--pipeline.model.geometry-from``),
frozen, then 10k colour-field steps on multi-view tile batches.
``virgi-vanilla``: the paper's baseline through the same code: one view-dependent colour MLP
(``color_field.decoupled=False``) and single-view batches.
Both train on several GPUs with ``--machine.num-devices N`` (virgi's trainer; see the README).
"""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from virgi_ns.colour.field import ColourFieldConfig
from virgi_ns.nerfstudio import compat  # noqa: F401  (checkpoint-loading work-arounds for torch >= 2.6)
from virgi_ns.nerfstudio.datamanager import VirgiDataManagerConfig
from virgi_ns.nerfstudio.model import VirgiModelConfig
from virgi_ns.nerfstudio.pipeline import VirgiPipelineConfig
from virgi_ns.nerfstudio.trainer import AdamConfig, VirgiTrainerConfig

GEOMETRY_STEPS = 30000
COLOUR_STEPS = 10000


def virgi_trainer_config(
    name: str = "virgi",
    decoupled: bool = True,
    batch_mode: str = "multiview",
    geometry_steps: int = GEOMETRY_STEPS,
    colour_steps: int = COLOUR_STEPS,
) -> VirgiTrainerConfig:
    """The full training recipe; the two registered methods differ only in the switches."""
    total = geometry_steps + colour_steps

    def adam(lr: float) -> AdamConfig:
        return AdamConfig(lr=lr, eps=1e-15)

    return VirgiTrainerConfig(
        method_name=name,
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=100000,
        max_num_iterations=total,
        mixed_precision=False,
        pipeline=VirgiPipelineConfig(
            datamanager=VirgiDataManagerConfig(
                dataparser=NerfstudioDataParserConfig(load_3D_points=True),
                cache_images_type="uint8",
                batch_mode=batch_mode,  # type: ignore[arg-type]
            ),
            model=VirgiModelConfig(
                geometry_steps=geometry_steps,
                colour_steps=colour_steps,
                color_field=ColourFieldConfig(decoupled=decoupled),
            ),
        ),
        optimizers={
            "means": {
                "optimizer": adam(1.6e-4),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max(geometry_steps, 1)),
            },
            "features_dc": {"optimizer": adam(0.0025), "scheduler": None},
            "features_rest": {"optimizer": adam(0.0025 / 20), "scheduler": None},
            "opacities": {"optimizer": adam(0.05), "scheduler": None},
            "scales": {"optimizer": adam(0.005), "scheduler": None},
            "quats": {"optimizer": adam(0.001), "scheduler": None},
            "camera_opt": {
                "optimizer": adam(1e-4),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=max(geometry_steps, 1)),
            },
            # the colour field's schedules are re-anchored at the colour stage's first step by the model
            "field_grid": {
                "optimizer": adam(1e-2),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-3, max_steps=total),
            },
            "field_mlp": {
                "optimizer": adam(1e-3),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=total),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


virgi_method = MethodSpecification(
    config=virgi_trainer_config("virgi"),
    description="VIRGi: frozen splat geometry + decoupled diffuse/specular colour field, multi-view tile training",
)

virgi_vanilla_method = MethodSpecification(
    config=virgi_trainer_config("virgi-vanilla", decoupled=False, batch_mode="singleview"),
    description="VIRGi baseline: one view-dependent colour MLP, single-view batches",
)
