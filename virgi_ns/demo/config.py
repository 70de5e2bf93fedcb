"""The demo's knobs (``python -m virgi_ns.demo --help``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Tuple

from virgi_ns.data.bundle import BUNDLED_SCENE
from virgi_ns.edit.recolor import RecolorRule

REPO = Path(__file__).resolve().parents[2]
SHARED_BEERCAN = REPO.parent / "shared" / "data" / "beercan"


@dataclass
class DemoConfig:
    """VIRGi on the bundled capture: train, recolour from one view, write pictures and numbers."""

    out: Path = Path("demo_out")
    """Output folder (grid.png, metrics.json, edited_scene.ply, the trained run in run/)."""
    scene: Path = BUNDLED_SCENE
    """A nerfstudio-format capture (transforms.json); the bundled beercan by default."""
    geometry: Optional[Path] = None
    """Pre-trained geometry (.ply/.spz/.compressed.ply in the capture's frame); default: the
    scene's geometry.spz or geometry.ply if it has one, otherwise geometry is trained here."""
    full: bool = False
    """Rebuild the capture at full resolution from --source first (use a GPU)."""
    source: Path = SHARED_BEERCAN
    """COLMAP beercan used by --full."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    geometry_steps: Optional[int] = None
    """Geometry steps when no pre-trained geometry is found; default 15000 on a GPU, 400 on a CPU
    (half at 1/4, half at 1/2 resolution, no densification: a coarse stand-in seeded from the
    sparse points)."""
    colour_steps: Optional[int] = None
    """Colour-stage steps; default 5000 on a GPU, 1000 on a CPU."""
    colour_init: Literal["geometry", "geometry_sh", "none"] = "geometry"
    """Warm-start the colour field from the geometry's own colours before the colour steps
    (the model's ``colour_init``), or start from a random field. The bundled geometry stores
    degree-0 colours only, for which 'geometry_sh' (the model's default) is the same as 'geometry'."""
    colour_init_steps: Optional[int] = None
    """Warm-start steps; default 200 on a CPU, the model's (300) on a GPU."""
    colour_init_batch: Optional[int] = None
    """Gaussians per warm-start step; default 4096 on a CPU, the model's (16384) on a GPU."""
    tile_size: int = 32
    views_per_anchor: int = 5
    pixel_budget: Optional[int] = None
    """Pixels per colour step (whole multi-view mini-batches); default 10240 on a CPU, 163840 on a GPU."""
    hash_log2: int = 17
    """log2 of the hash table size (the paper's 19 is for GPUs and large scenes)."""
    edit_steps: Optional[int] = None
    """Edit steps; default: the pick's (the edit engine's)."""
    colour: str = "#e0141e"
    """The colour the clicked object takes (#RRGGBB)."""
    mode: Literal["hue", "shift", "colour"] = "hue"
    """How the selection takes the colour (``virgi-edit pick --mode``): ``hue`` gives it the colour's hue
    and saturation and keeps each pixel's brightness, so shading stays and white highlights stay white."""
    tolerance: float = 0.2
    """The pick's tolerance (``virgi-edit pick --tolerance``)."""
    contiguous: bool = False
    """Select only what is connected to the click (``virgi-edit pick --contiguous``). Off by default: the demo's
    object is every pixel of its colour (``--hue-from`` ...), as its measures count it, and the bundled can's
    blue is cut in two by a printed stripe, where a contiguous pick from one side stops."""
    edit_view: Optional[int] = None
    """Training view to click in (index among training views); default: where the can shows most."""
    pixel: Optional[Tuple[int, int]] = None
    """X Y of the click in that view; default: the pixel deepest inside the can."""
    hue_from: float = 190.0
    """The object's colour, which finds it for the default click and marks it in the measures: the
    start of its hue range (degrees; the can's blue)."""
    hue_to: float = 260.0
    """The end of its hue range (degrees)."""
    sat_min: float = 0.25
    """Its least saturation."""
    val_min: float = 0.1
    """Its least value."""
    grid_views: int = 4
    """Held-out views shown in grid.png."""
    grid_scale: int = 2
    """grid.png shows each view this many times its render size (nearest neighbour: no detail made up)."""
    export: bool = True
    """Bake the edited scene to edited_scene.ply."""
    export_directions: int = 64
    """Sphere directions per Gaussian when baking SH."""
    seed: int = 0

    def object_rule(self) -> RecolorRule:
        """The pixels of the object's colour (a rule that selects them; its shift is unused)."""
        return RecolorRule(self.hue_from, self.hue_to, 0.0, self.sat_min, self.val_min)


def demo_device(choice: str):
    """The torch device a demo's ``--device`` names (``auto``: a CUDA GPU where one is visible, else the CPU);
    ``cuda`` without a visible GPU is an :class:`~virgi_ns.errors.InputError`."""
    import torch

    from virgi_ns.errors import InputError

    if choice == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA GPU is available")
    return torch.device("cuda" if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()) else "cpu")


__all__ = ["DemoConfig", "SHARED_BEERCAN", "demo_device"]
