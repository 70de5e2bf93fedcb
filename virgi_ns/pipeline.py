"""Old home of the pipeline classes, kept because a run's ``config.yml`` names classes by module
path (``virgi_ns.pipeline.VirgiPipelineConfig``): runs trained before the package was regrouped
still load. The pipeline lives in :mod:`virgi_ns.nerfstudio.pipeline`."""

from virgi_ns.nerfstudio.pipeline import VirgiPipeline, VirgiPipelineConfig

__all__ = ["VirgiPipeline", "VirgiPipelineConfig"]
