"""Recolouring a trained scene from one edited view, and keeping the edits.

- :mod:`.engine`: fits one edit (a copy of the diffuse head and a segmentation head) to an edited
  image of one view, on frozen geometry;
- :mod:`.scene`: what the engine reads from a trained model, and rendering through a stack;
- :mod:`.pixels`: the edited view's pixels as sparse linear maps of the Gaussians' colours;
- :mod:`.stack`: edits as small files beside a run, composed in order at render time;
- :mod:`.recolor`: the deterministic HSV rule the benchmarks and the demo edit with.

Nothing here imports nerfstudio or :mod:`virgi_ns.nerfstudio`: a frozen scene is geometry, a
colour field and a background.
"""
