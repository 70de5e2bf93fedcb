"""Recolouring a trained scene from one edited view, and keeping the edits.

- :mod:`.engine`: fits one edit (a copy of the diffuse head and a segmentation head) to an edited
  image of one view, on frozen geometry; its settings are :mod:`.config`'s ``EditConfig``, what its
  loss fits :mod:`.targets`, how its steps run :mod:`.fitting` (with :mod:`.heads` and :mod:`.optim`);
- :mod:`.scene`: what the engine reads from a trained model, and rendering through a stack;
- :mod:`.pixels`: the edited view's pixels as sparse linear maps of the Gaussians' colours;
- :mod:`.stack`: edits as small files beside a run (:mod:`.manifest`: their ``stack.json``), composed in
  order at render time;
- :mod:`.pick`: a click and a colour instead of an edited image;
- :mod:`.recolor`: the deterministic HSV rule the benchmarks and the demo edit with;
- :mod:`.warmup`: a fresh process's first edit, paid while it loads its run.

Nothing here imports nerfstudio or :mod:`virgi_ns.nerfstudio`: a frozen scene is geometry, a
colour field and a background.
"""
