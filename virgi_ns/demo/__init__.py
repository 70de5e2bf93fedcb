"""``make demo``: VIRGi end to end on the bundled beercan capture, written to ``demo_out/``.

1. **Geometry**: the bundle's pre-trained ``geometry.ply`` (capture frame) when present, else a
   short geometry stage on this machine (the reference rasterizer on a CPU: coarse, but it runs).
2. **Colour**: the colour stage of ``ns-train virgi``: the field is warm-started from the
   geometry's own colours (the model's ``colour_init``), then trained on multi-view tile batches.
   On a CPU every training view is rasterized once
   (:class:`~virgi_ns.nerfstudio.contrib_cache.ContributionCache`) and the tiles are sliced from those lists.
3. **Edit**: the recolour rule (:mod:`virgi_ns.edit.recolor`, the can's blue to red) applied to the
   photo of one training view (the one where the rule selects most pixels) is the edited image;
   :class:`~virgi_ns.edit.engine.EditEngine` fits the edit.
4. **Outputs**: ``grid.png`` (held-out views: photo, render, recoloured render, segmentation,
   diffuse, specular), ``metrics.json`` (reconstruction, recolour and propagation PSNR, edit
   time, stage times) and ``edited_scene.ply`` (the edited scene baked to SH, capture frame);
5. **The run**: ``run/config.yml`` and its checkpoint (the trained colour field, unedited), which
   ``ns-viewer --load-config`` and every ``virgi-*`` command open; a new demo replaces it (and the
   edits made on it). The demo prints the next commands, a pick of the edited object among them.

``python -m virgi_ns.demo --help`` lists the knobs; ``--full`` rebuilds the capture at full
resolution from the shared COLMAP data and is meant for a GPU.

:mod:`.config` holds the knobs, :mod:`.training` the in-process training, :mod:`.measure` the
figures, :mod:`.picture` the grid, and :mod:`.run` the demo end to end.
"""
