"""Old home of :class:`ColorFieldConfig`, kept because a run's ``config.yml`` names it by module path
(``virgi_ns.field.ColorFieldConfig``): runs trained before the package was regrouped still load.
The colour field lives in :mod:`virgi_ns.colour.field`."""

from virgi_ns.colour.field import ColorFieldConfig

__all__ = ["ColorFieldConfig"]
