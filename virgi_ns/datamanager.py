"""Old home of the datamanager classes, kept because a run's ``config.yml`` names classes by module
path (``virgi_ns.datamanager.VirgiDataManagerConfig``): runs trained before the package was
regrouped still load. The datamanager lives in :mod:`virgi_ns.nerfstudio.datamanager`."""

from virgi_ns.nerfstudio.datamanager import VirgiDataManager, VirgiDataManagerConfig

__all__ = ["VirgiDataManager", "VirgiDataManagerConfig"]
