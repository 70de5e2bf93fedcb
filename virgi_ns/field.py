"""Old home of the colour field's config, kept because a run's ``config.yml`` names its class by module path
and name (``virgi_ns.field.ColorFieldConfig``): such runs still load. The colour field lives in
:mod:`virgi_ns.colour.field`."""

from virgi_ns.colour.field import ColorFieldConfig

__all__ = ["ColorFieldConfig"]
