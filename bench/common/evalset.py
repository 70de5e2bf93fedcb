"""The edit benchmark's evaluation set: which scenes, which recolour rule on each, and why.

Fixed before any tuning of the edit engine and not to be changed afterwards: a rule that turns
out to select something it should not is a rule problem, reported as such, not edited away.

Every scene is trained as a user would (``ns-train virgi``: geometry from the photos, then the
colour field), one training photo is recoloured by the scene's rule, and the edit is scored on the
held-out views (:mod:`virgi_ns.bench.recolor`). The real captures are those of ``shared/data``;
the synthetic ones (``bench/common/synthetic.py``) add a known truth, so their recolour PSNR is
measured against what the recoloured scene really looks like rather than against the rule.

Settings chosen once, with their reasons:

- the edited view is the training view whose photo the rule recolours most (a user edits a photo
  that shows the object well); held-out views are every 8th, as nerfstudio's parsers do;
- 7000 geometry + 1000 colour steps, the shortened training of the benchmarks, for the real
  captures; the synthetic ones import their known Gaussians and train the colour stage only: their
  truth is about the edit, and their evenly lit, untextured backdrop leaves a trained geometry's
  depth ambiguous (a first run left backdrop-coloured floaters in front of the held-out cameras);
- the synthetic captures: 48 views at 400x300 on two camera rings (the held-out ring positions
  are interleaved with the training ones), photos rendered from ~0.015-spaced surface Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

from virgi_ns.edit.recolor import RecolorRule
from virgi_ns.errors import InputError

GEOMETRY_STEPS = 7000
COLOUR_STEPS = 1000
SYNTHETIC_VIEWS, SYNTHETIC_WIDTH, SYNTHETIC_HEIGHT, SYNTHETIC_SPACING = 48, 400, 300, 0.015


@dataclass(frozen=True)
class EvalScene:
    """One row of the set: a capture and the rule that makes its edit."""

    name: str
    capture: str
    """A folder of the shared data (COLMAP or LLFF), or ``synthetic/<name>`` for a scene of
    ``common.synthetic.SCENES``."""
    rule: RecolorRule
    why: str
    click: Literal["auto", "parts", "objects"] = "auto"
    """What the rule is meant to select, for judging a click (``bench/common/clicks.py``) where the rule's
    mask on the edited view is not one object: ``parts`` (many separate parts of one kind: the leaves of
    a plant, the pieces of one object its texture or highlights cut apart), ``objects`` (several
    different objects: a cup and the shelf it stands on), ``auto`` (``parts``). Declared from the row's
    ``why`` (what the rule is written to take), never from a result."""

    @property
    def synthetic(self) -> Optional[str]:
        return self.capture.split("/", 1)[1] if self.capture.startswith("synthetic/") else None


def _synthetic_rows() -> tuple[EvalScene, ...]:
    from common.synthetic import SCENES

    return tuple(EvalScene(f"syn_{name}", f"synthetic/{name}", spec.rule, spec.why) for name, spec in SCENES.items())


REAL: tuple[EvalScene, ...] = (
    EvalScene("beercan", "beercan", RecolorRule(190.0, 250.0, 150.0, 0.1, 0.15),
              "the can's blue -> red, the whole can (s 0.1 takes its pale blue back); near-white highlights and "
              "the grey-white floor are outside the rule", click="parts"),
    EvalScene("beercan_yellow", "beercan", RecolorRule(190.0, 250.0, 180.0, 0.1, 0.15),
              "the same can -> yellow: a rule not used while the engine was built (a 180-degree shift)", click="parts"),
    EvalScene("fern", "fern", RecolorRule(60.0, 160.0, 120.0, 0.12, 0.1),
              "the fern's leaves -> blue; s 0.12 takes the pale leaves too (0.25 split the fern)", click="parts"),
    EvalScene("cup", "cup", RecolorRule(0.0, 80.0, 120.0, 0.02, 0.02),
              "every warm tone -> green (shelf and cup, beige and print): thresholds near zero leave no "
              "saturation or value edge across the cup", click="objects"),
    # Captures the engine was never run on, each rule written from the photos' hue histograms before any
    # training or edit of the capture (saturation >= 0.25, value >= 0.15 over every 5th photo):
    EvalScene("fruit", "fruit", RecolorRule(340.0, 30.0, 200.0, 0.25, 0.15),
              "the apple -> blue, touching the banana: the apple's hue mode is 8-24 degrees, the banana's 36-48; "
              "the rule cuts the empty valley between them at 30", click="parts"),
    EvalScene("blowtorch", "blowtorch", RecolorRule(316.0, 356.0, 230.0, 0.25, 0.1),
              "the crimson rug -> blue, a large textured surface: its hue mode spans 316-356 degrees with empty tails "
              "on both sides; the brass and wood sit at 8-40, the pale stripes below s 0.25", click="parts"),
    EvalScene("fox", "fox", RecolorRule(330.0, 8.0, 230.0, 0.25, 0.15),
              "the wallpaper's pink and crimson roses -> blue: their hues run 330-8 degrees; the fox's orange fur "
              "peaks at 28-40 with no valley between, so its reddest hairs may fall in the rule (a rule limit, "
              "reported as such)", click="parts"),
)
EVAL_SET: tuple[EvalScene, ...] = REAL + _synthetic_rows()
"""The whole set, real captures first."""


def find(names: list[str]) -> list[EvalScene]:
    """The set's rows named ``names`` (all when empty); refuses unknown names."""
    by_name = {s.name: s for s in EVAL_SET}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise InputError(f"unknown evaluation scene(s) {', '.join(unknown)}; the set: {', '.join(by_name)}")
    return [by_name[n] for n in names] if names else list(EVAL_SET)


SYNTHETIC_SIZE = (SYNTHETIC_VIEWS, SYNTHETIC_WIDTH, SYNTHETIC_HEIGHT, SYNTHETIC_SPACING)

REAL_CAPTURE_COST = 3
"""How many synthetic rows one real capture costs on a GPU, the weight :func:`split_for_devices`
balances by: a real capture trains 7000 geometry + 1000 colour steps (beercan about 100 s, RESULTS
"Training"), a synthetic one writes its photos and trains the colour stage only (about 40 s)."""


def split_for_devices(names: list[str], parts: int) -> list[list[str]]:
    """The rows ``names`` (all when empty) as at most ``parts`` lists to run side by side, one per GPU:
    the rows of one capture in one list (its run is trained once), a real capture weighing
    :data:`REAL_CAPTURE_COST` synthetic rows, each capture (heaviest first) onto the lightest list;
    within a list the order of ``names`` (the set's when empty)."""
    rows = find(names)
    captures: dict[str, list[EvalScene]] = {}
    for r in rows:
        captures.setdefault(r.capture, []).append(r)
    load = [0] * max(1, parts)
    where: dict[str, int] = {}
    for cap in sorted(captures, key=lambda c: -(1 if captures[c][0].synthetic else REAL_CAPTURE_COST)):
        i = min(range(len(load)), key=lambda k: load[k])
        where[cap] = i
        load[i] += 1 if captures[cap][0].synthetic else REAL_CAPTURE_COST
    out = [[r.name for r in rows if where[r.capture] == i] for i in range(len(load))]
    return [o for o in out if o]


def capture_folder(scene: EvalScene, data: Path, synthetic_root: Path, device: str = "cpu", console=None,
                   size: tuple = SYNTHETIC_SIZE) -> Path:
    """The scene's capture folder; a synthetic capture (``size``: views, width, height, spacing) is
    written under ``synthetic_root`` first when it is not there yet (deterministic: the same files
    every time)."""
    name = scene.synthetic
    if name is None:
        folder = data / scene.capture
        if not folder.is_dir():
            raise InputError(f"{scene.name}: capture folder not found: {folder} (--data)")
        return folder
    from common.synthetic import SCENES, write_scene

    folder = synthetic_root / name
    if not (folder / "scene.json").is_file():
        if console is not None:
            console.log(f"writing the synthetic capture {name} to {folder}")
        write_scene(SCENES[name], folder, *size, device=device)
    return folder


HELD_OUT_EVERY = 8
"""Every 8th view of a capture (0, 8, 16, ...) is held out, as nerfstudio's interval split does."""


def capture_images(folder: Path) -> str:
    """The folder of a real capture's photos that its parser reads: COLMAP's ``images``, an LLFF
    capture's ``images_8`` where there is one."""
    if (folder / "sparse" / "0").is_dir() or not (folder / "images_8").is_dir():
        return "images"
    return "images_8"


def dataparser_config(folder: Path):
    """nerfstudio's parser for a capture folder: COLMAP (``sparse/0``), a nerfstudio-format capture
    (``transforms.json``: the synthetic ones), or LLFF; every 8th view held out."""
    if (folder / "sparse" / "0").is_dir():
        from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

        return ColmapDataParserConfig(data=folder, colmap_path=Path("sparse/0"), images_path=Path("images"),
                                      eval_mode="interval", eval_interval=HELD_OUT_EVERY, load_3D_points=True,
                                      downscale_factor=1)
    if (folder / "transforms.json").is_file():
        from virgi_ns.data.bundle import BundleDataParserConfig

        return BundleDataParserConfig(data=folder)
    from virgi_ns.data.llff import LLFFDataParserConfig

    return LLFFDataParserConfig(data=folder, images_dir=capture_images(folder), llffhold=HELD_OUT_EVERY)


def edit_view(photos: list, rule: RecolorRule) -> int:
    """The training view whose photo the rule recolours most (the first on ties)."""
    from virgi_ns.edit.recolor import rule_mask

    counts = [int(rule_mask(p, rule).sum()) for p in photos]
    if not counts or max(counts) == 0:
        raise InputError("the rule recolours no pixel of any training photo")
    return max(range(len(counts)), key=lambda i: (counts[i], -i))


def edit_view_of_capture(photos: list, rule: RecolorRule) -> int:
    """:func:`edit_view` over all of a capture's photos in order, the held-out ones
    (:data:`HELD_OUT_EVERY`) left out: the index of the edited photo among all of them."""
    train = [i for i in range(len(photos)) if i % HELD_OUT_EVERY != 0]
    return train[edit_view([photos[i] for i in train], rule)]


__all__ = ["EvalScene", "EVAL_SET", "REAL", "GEOMETRY_STEPS", "COLOUR_STEPS", "HELD_OUT_EVERY", "find",
           "split_for_devices", "capture_folder", "capture_images", "dataparser_config", "edit_view",
           "edit_view_of_capture"]
