"""``make demo``: VIRGi end to end on the bundled beercan capture, written to ``demo_out/``.

1. **Geometry**: the bundle's pre-trained ``geometry.spz`` (capture frame) when present, else a
   short geometry stage on this machine (the reference rasterizer on a CPU: coarse, but it runs).
2. **Colour**: the colour stage of ``ns-train virgi``: the field is warm-started from the
   geometry's own colours (the model's ``colour_init``), then trained on multi-view tile batches.
   On a CPU every training view is rasterized once
   (:class:`~virgi_ns.nerfstudio.contrib_cache.ContributionCache`) and the tiles are sliced from those lists.
3. **Edit**: a click, as ``virgi-edit pick`` makes one (:class:`~virgi_ns.edit.pick.PickSession`):
   in the training view whose photo shows most of the object's colour (the can's blue), at the
   pixel of the render deepest inside it, the object takes the asked colour (``--colour``,
   ``--mode``) and the edit is fitted.
4. **Outputs**: ``grid.png`` (held-out views: photo, render, recoloured render, segmentation, the
   highlight layer scaled to be seen), ``metrics.json`` (reconstruction PSNR; the edit's leak away
   from the object, how much of the object took the colour's hue; pick and stage times) and
   ``edited_scene.ply`` (the edited scene baked to SH, capture frame);
5. **The run**: ``run/config.yml`` and its checkpoint (the trained colour field, unedited), which
   ``ns-viewer --load-config`` and every ``virgi-*`` command open; a new demo replaces it (and the
   edits made on it). The demo prints the next commands, the same click among them.

``python -m virgi_ns.demo --help`` lists the knobs; ``--full`` rebuilds the capture at full
resolution from the shared COLMAP data and is meant for a GPU.

:mod:`.config` holds the knobs, :mod:`.training` the in-process training, :mod:`.measure` the
figures, :mod:`.picture` the grid, and :mod:`.run` the demo end to end.
"""
