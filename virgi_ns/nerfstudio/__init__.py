"""VIRGi inside nerfstudio: the model, its datamanager and pipeline, the viewer panel, the export.

Everything that knows nerfstudio's classes lives here (the dataparsers excepted: :mod:`virgi_ns.data`);
the packages below it (:mod:`virgi_ns.raster`, :mod:`virgi_ns.colour`, :mod:`virgi_ns.edit`,
:mod:`virgi_ns.io`) do not import it.
"""
