"""VIRGi's panel in nerfstudio's viewer.

- :mod:`.panel`: the panel (widgets, status, display settings), held by the model;
- :mod:`.actions`: what its buttons do: save a view, fit an uploaded edit, undo, reset, export;
- :mod:`.picking`: Pick mode: a click selects, the colour recolours live, a pause commits;
- :mod:`.upload`: the file upload element and the decoding of an uploaded image;
- :mod:`.views`: views saved from the viewer (a PNG and its camera).
"""
