"""Old home of the model classes, kept because a run's ``config.yml`` names classes by module path
(``!!python/object:virgi_ns.model.VirgiModelConfig``): runs trained before the package was
regrouped still load. The model lives in :mod:`virgi_ns.nerfstudio.model`."""

from virgi_ns.nerfstudio.model import VirgiModel, VirgiModelConfig

__all__ = ["VirgiModel", "VirgiModelConfig"]
