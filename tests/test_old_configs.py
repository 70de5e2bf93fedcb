"""Runs trained before the package was regrouped still load: a run's config.yml names its classes
by module path, and older ones name ``virgi_ns.model``, ``.datamanager``, ``.pipeline`` and
``.field`` (kept as aliases of the modules that moved)."""

from __future__ import annotations

import yaml

from method_configs.virgi import virgi_trainer_config

OLD_CONFIG = """\
!!python/object:virgi_ns.pipeline.VirgiPipelineConfig
_target: !!python/name:virgi_ns.pipeline.VirgiPipeline ''
datamanager: !!python/object:virgi_ns.datamanager.VirgiDataManagerConfig
  _target: !!python/name:virgi_ns.datamanager.VirgiDataManager ''
  tile_size: 16
model: !!python/object:virgi_ns.model.VirgiModelConfig
  _target: !!python/name:virgi_ns.model.VirgiModel ''
  colour_init_steps: 7
  color_field: !!python/object:virgi_ns.field.ColorFieldConfig
    hidden: 32
"""


def test_a_config_naming_the_old_module_paths_loads_the_new_classes():
    from virgi_ns.colour.field import ColourFieldConfig
    from virgi_ns.nerfstudio.datamanager import VirgiDataManager, VirgiDataManagerConfig
    from virgi_ns.nerfstudio.model import VirgiModel, VirgiModelConfig
    from virgi_ns.nerfstudio.pipeline import VirgiPipeline, VirgiPipelineConfig

    cfg = yaml.load(OLD_CONFIG, Loader=yaml.Loader)  # as nerfstudio's eval_setup reads config.yml
    assert type(cfg) is VirgiPipelineConfig and cfg._target is VirgiPipeline
    assert type(cfg.datamanager) is VirgiDataManagerConfig and cfg.datamanager._target is VirgiDataManager
    assert cfg.datamanager.tile_size == 16
    assert type(cfg.model) is VirgiModelConfig and cfg.model._target is VirgiModel
    assert cfg.model.colour_init_steps == 7
    assert type(cfg.model.color_field) is ColourFieldConfig and cfg.model.color_field.hidden == 32

    # a whole saved config, as written before the move, loads as today's (the modules that moved are
    # renamed; virgi_ns.nerfstudio.trainer came later and never lived elsewhere)
    new = yaml.dump(virgi_trainer_config())
    old = new.replace("virgi_ns.colour.field.ColourFieldConfig", "virgi_ns.field.ColorFieldConfig")
    for module in ("model", "datamanager", "pipeline"):
        old = old.replace(f"virgi_ns.nerfstudio.{module}.", f"virgi_ns.{module}.")
    for name in ("model.VirgiModelConfig", "datamanager.VirgiDataManagerConfig", "pipeline.VirgiPipelineConfig",
                 "field.ColorFieldConfig"):
        assert f"virgi_ns.{name}" in old
    assert yaml.dump(yaml.load(old, Loader=yaml.Loader)) == new
    # and one written after the move, when the colour field's config was spelt ColorFieldConfig
    spelt = new.replace("ColourFieldConfig", "ColorFieldConfig")
    assert spelt != new and yaml.dump(yaml.load(spelt, Loader=yaml.Loader)) == new


def test_the_fast_loader_takes_every_name_of_the_colour_fields_config():
    from virgi_ns.nerfstudio.saved_run import FIELD_CLASSES

    assert set(FIELD_CLASSES) == {"virgi_ns.colour.field.ColourFieldConfig", "virgi_ns.colour.field.ColorFieldConfig",
                                  "virgi_ns.field.ColorFieldConfig"}
