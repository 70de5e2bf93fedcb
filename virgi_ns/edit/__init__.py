"""Recolouring a trained scene from one edited view, and keeping the edits.

- :mod:`.engine`: fits one edit (a copy of the diffuse head and a segmentation head) to an edited
  image of one view, on frozen geometry;
- :mod:`.stack`: edits as small files beside a run, composed in order at render time;
- :mod:`.recolor`: the deterministic HSV rule the benchmarks and the demo edit with.

The engine reads a trained model through a frozen scene (geometry, colour field, background) and
the rasterizer's contribution lists; it knows nothing of nerfstudio.
"""
