"""``virgi-edit``: recolour a trained VIRGi run from one edited image, and manage its edit stack.

    virgi-edit apply --load-config CFG --image EDITED.png (--camera-index I | --image-name NAME | --camera-json CAM.json)
    virgi-edit pick --load-config CFG (--camera-index I | ...) --pixel X Y --colour '#RRGGBB' [--tolerance T] [--mode hue|shift|colour]
    virgi-edit list --load-config CFG
    virgi-edit undo --load-config CFG
    virgi-edit reset --load-config CFG
    virgi-edit enable --load-config CFG N        (and disable)
    virgi-edit specular --load-config CFG K      (0 removes highlights, 1.5 strengthens them)
    virgi-edit import --load-config CFG --edit-file EDIT.pt

Edits live in ``<run>/edits`` (beside ``config.yml``); the run itself is never written; ``pick``
saves the edited image it made and its selection beside the edit. ``apply``, ``pick`` and
``import`` load the run (:func:`virgi_ns.nerfstudio.runs.open_run`: from its files, without nerfstudio,
when it can) and refuse edits of another base run; the other commands work on the edit stack's
manifest alone (:mod:`virgi_ns.edit.manifest`), importing neither torch nor nerfstudio. Bad input
is one line on stderr, exit 2, nothing saved.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, Optional, Union

import tyro

from virgi_ns.errors import InputError, cli_entry

if TYPE_CHECKING:  # torch, numpy and rich load with the commands that need them (list and undo do not)
    import numpy as np
    from rich.console import Console

    from virgi_ns.nerfstudio.runs import OpenRun

GREY_MODES = ("1", "L", "LA", "I", "I;16", "I;16B", "I;16L", "F")


# ------------------------------------------------------------------------- commands
@dataclass
class Apply:
    """Fit an edit from EDITED (an image of the run seen from one camera) and add it to the stack."""

    load_config: Path
    """The run's config.yml."""
    image: Path
    """The edited image (PNG, JPEG, ...), the same size as the camera's render."""
    camera_index: Optional[int] = None
    """Camera: index among the run's training images."""
    image_name: Optional[str] = None
    """Camera: the training (or evaluation) image of this file name (with or without extension)."""
    camera_json: Optional[Path] = None
    """Camera: a CAM.json as the viewer's 'Save this view' and virgi-render use."""
    steps: Optional[int] = None
    """Optimisation steps (default: the engine's)."""
    resize: bool = False
    """Resize an image of another size to the camera's instead of refusing it."""
    pixel_batches: Optional[int] = None
    """Use 1/N of the pixels per step (N random sets)."""
    original: Optional[Path] = None
    """The unedited image (default: the training photo of --camera-index / --image-name). Pixels
    the edit left unchanged keep the scene's current colours instead of being fitted to the image."""
    whole_image: bool = False
    """Fit every pixel of the edited image, also those equal to the original."""
    changed_target: Literal["affine", "edited"] = "affine"
    """With an original photo: fit the changed pixels to your pixels moved by the render's error as
    your change moves colours (``affine``, the default: your change fitted as an affine function of
    colour, so the photo's detail the model never reproduced stays out of the edit) or to the edited
    image's own pixels (``edited``, the paper's). No effect with --whole-image."""
    recipe: Literal["joint", "staged"] = "joint"
    """``joint``: the segmentation and the new colour are fitted together (the paper's recipe);
    ``staged``: the segmentation first, from which Gaussians your change covers, so parts of another
    colour inside a recoloured object keep theirs."""
    unchanged_weights: Literal["count", "colour"] = "colour"
    """How the pixels your edit left unchanged share their part of the fit: ``count``, each the same;
    ``colour``, half of it spread equally over the colours the image shows only unchanged, so a small
    part of another colour on a recoloured object (studs, spots, a beak) keeps its colour."""


@dataclass
class Pick:
    """Select what pixel X Y of a camera's view shows, recolour it to COLOUR and add that edit to the
    stack (the edited image and the selection are saved beside it)."""

    load_config: Path
    """The run's config.yml."""
    pixel: tuple[int, int]
    """X Y: the pixel to pick (column, row; 0, 0 is the top-left) of the camera's render."""
    colour: str
    """The new colour, #RRGGBB."""
    camera_index: Optional[int] = None
    """Camera: index among the run's training images."""
    image_name: Optional[str] = None
    """Camera: the training (or evaluation) image of this file name (with or without extension)."""
    camera_json: Optional[Path] = None
    """Camera: a CAM.json as the viewer's 'Save this view' and virgi-render use."""
    tolerance: float = 0.2
    """0..1: how far (x 90 degrees) a pixel's hue may turn from the picked pixel's, and (by chroma steps)
    how much its chroma may change from a selected neighbour's (a factor 1 + 4 x tolerance), and still be
    selected."""
    contiguous: bool = True
    """Select only what is connected to the pixel (``--no-contiguous``: every pixel of the view that
    passes the same colour tests, e.g. leaves all over a plant)."""
    depth_edges: bool = False
    """Also stop the selection at jumps in the surface's depth, so an object in front of another of its
    colour is taken alone. Off by default: on a textured or noisily reconstructed surface (a rug, a
    floor) the depth jumps between neighbouring pixels and the selection would stop short."""
    selection: Literal["chroma_steps", "colour_features"] = "chroma_steps"
    """How the selection grows from the pixel: ``chroma_steps`` (the default) by the diffuse colour's hue
    and gradual chroma; ``colour_features`` by the angles of the diffuse colour and of the colour
    field's features."""
    mode: Literal["hue", "shift", "colour"] = "hue"
    """``hue``: new hue and saturation, each pixel keeps its value (shading and highlights stay);
    ``shift``: the same, but every pixel's hue turns by the angle that takes the reference pixel's to
    the colour's, so an object of several hues keeps them apart; ``colour``: the surface takes the
    colour itself, shaded as it was, its highlights on it."""
    reference: Literal["click", "median"] = "click"
    """Which selected pixel takes exactly the colour's saturation (hue) or value (colour), the others
    keeping their ratio to it: the clicked one (the default), or the selection's median one."""
    steps: Optional[int] = None
    """Optimisation steps (default: the engine's)."""
    unchanged_weights: Literal["count", "colour"] = "colour"
    """How the pixels outside the selection share their part of the fit: ``count``, each the same;
    ``colour``, half of it spread equally over the colours the view shows only outside the selection, so
    a small part of another colour on the picked object keeps its colour."""


@dataclass
class List:
    """List the edits of a run."""

    load_config: Path


@dataclass
class Undo:
    """Remove the last edit."""

    load_config: Path


@dataclass
class Reset:
    """Remove every edit and set the specular strength back to 1."""

    load_config: Path


@dataclass
class Enable:
    """Enable edit N (as ``list`` numbers them)."""

    load_config: Path
    number: Annotated[int, tyro.conf.Positional, tyro.conf.arg(metavar="N")]


@dataclass
class Disable:
    """Disable edit N (it stays in the stack)."""

    load_config: Path
    number: Annotated[int, tyro.conf.Positional, tyro.conf.arg(metavar="N")]


@dataclass
class Specular:
    """Set the specular strength k applied at render time (0 removes highlights, 1.5 strengthens them)."""

    load_config: Path
    strength: Annotated[float, tyro.conf.Positional, tyro.conf.arg(metavar="K")]


@dataclass
class Import:
    """Add an edit file made elsewhere for this same run (refused for another base run)."""

    load_config: Path
    edit_file: Path


Command = Union[
    Annotated[Apply, tyro.conf.subcommand("apply")],
    Annotated[Pick, tyro.conf.subcommand("pick")],
    Annotated[List, tyro.conf.subcommand("list")],
    Annotated[Undo, tyro.conf.subcommand("undo")],
    Annotated[Reset, tyro.conf.subcommand("reset")],
    Annotated[Enable, tyro.conf.subcommand("enable")],
    Annotated[Disable, tyro.conf.subcommand("disable")],
    Annotated[Specular, tyro.conf.subcommand("specular")],
    Annotated[Import, tyro.conf.subcommand("import")],
]


# --------------------------------------------------------------------------- inputs
def load_edited_image(path: Path) -> tuple[np.ndarray, list[str]]:
    """[H,W,3] float32 in [0,1] and notes for the user. Non-images and grayscale images raise
    :class:`InputError`; an alpha channel is dropped with a note."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such image: {path}")
    notes: list[str] = []
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
                mode = im.mode
            if mode in GREY_MODES:
                raise InputError(f"{path} is a grayscale image ({mode}); an edit needs a colour (RGB) image")
            if mode in ("RGBA", "RGBa", "PA"):
                notes.append(f"{path.name}: alpha channel ignored (only RGB is used)")
            rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError, SyntaxError):
        raise InputError(f"{path} is not an image (PNG, JPEG, ...)") from None
    return rgb, notes


def fit_size(image: np.ndarray, width: int, height: int, resize: bool, name: str) -> tuple[np.ndarray, list[str]]:
    """The image at the camera's size: unchanged, resized (``resize``), or refused."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image, []
    if not resize:
        raise InputError(f"{name} is {w}x{h} but the camera renders {width}x{height} (pass --resize to resize it)")
    import numpy as np
    from PIL import Image

    im = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).resize((width, height),
                                                                                  Image.Resampling.LANCZOS)
    return np.asarray(im, dtype=np.float32) / 255.0, [f"{name}: resized from {w}x{h} to {width}x{height}"]


def resolve_camera(run: "OpenRun", args: Union[Apply, Pick]):
    """(raster Cameras of one view, a description) for the chosen camera of ``args``."""
    chosen = [x is not None for x in (args.camera_index, args.image_name, args.camera_json)]
    if sum(chosen) != 1:
        raise InputError("choose the edited image's camera with exactly one of --camera-index, --image-name, "
                         "--camera-json")
    if args.camera_index is not None:
        train = run.train
        n = len(train)
        i = args.camera_index
        if not 0 <= i < n:
            raise InputError(f"--camera-index {i} is out of range: the run has {n} training images (0..{n - 1})")
        return train.camera(i), f"train index {i} ({Path(train.filenames[i]).name})"
    if args.image_name is not None:
        want = args.image_name
        found = run.find_image(want)
        if found is not None:
            views, i = found
            return views.camera(i), f"image {Path(views.filenames[i]).name}"
        some = [Path(f).name for f in run.train.filenames[:3]]
        raise InputError(f"no image named {want!r} in the run (e.g. {', '.join(some)})")
    return camera_from_json(run.model, Path(args.camera_json)), f"camera {Path(args.camera_json).name}"


def original_image(run: "OpenRun", args: Apply, shape: tuple, console: "Console"):
    """The unedited image as float32 HxWx3 in [0,1]: ``--original``, else the chosen training (or
    evaluation) photo; None for a --camera-json view without --original, or (with a note) when
    the photo's size differs from the edited image's."""
    import numpy as np

    if args.original is not None:
        img, _ = load_edited_image(args.original)  # read as the edited image is (alpha dropped)
        img, _ = fit_size(img, shape[1], shape[0], args.resize, "--original")
        where = str(args.original)
    else:
        found = None
        if args.camera_index is not None:
            found = (run.train, args.camera_index)
        elif args.image_name is not None:
            found = run.find_image(args.image_name)
        if found is None:
            return None
        views, i = found
        # the file's own pixels, alpha dropped as for the edited image (not blended onto a background)
        img = views.photo(i)[..., :3].astype(np.float32) / 255.0
        where = Path(views.filenames[i]).name
    if tuple(img.shape) != tuple(shape):
        console.print(f"note: the photo {where} is {img.shape[1]}x{img.shape[0]}, not the edited image's size: "
                      "fitting every pixel of the edited image")
        return None
    return img.astype(np.float32)


def camera_from_json(model, path: Path):
    """Raster Cameras of a CAM.json; ``"frame": "dataparser"`` means the run's own frame, anything
    else the capture's (as the viewer saves views)."""
    import torch

    from virgi_ns.io.camera_json import read_camera_json
    from virgi_ns.nerfstudio.frames import capture_frame, raster_camera_from_spec

    spec = read_camera_json(path)
    frame = json.loads(path.read_text(encoding="utf-8")).get("frame", "capture")
    if frame == "dataparser":
        T, s = torch.eye(4)[:3].double(), 1.0
    else:
        T, s = capture_frame(model)
    return raster_camera_from_spec(spec, T, s)


def _manifest(load_config: Path):
    """The edit stack's manifest of a run (no model, no torch)."""
    from virgi_ns.edit.manifest import read_manifest

    load_config = Path(load_config)
    if not load_config.is_file():
        raise InputError(f"no such config: {load_config}")
    return read_manifest(load_config.parent)


# -------------------------------------------------------------------------- running
def _run_of(load_config: Path, console: "Console", run=None) -> "OpenRun":
    """``run`` as an :class:`~virgi_ns.nerfstudio.runs.OpenRun`: one already (returned as is), a loaded
    nerfstudio pipeline (wrapped), or None (the run of ``load_config`` is opened)."""
    from virgi_ns.nerfstudio.runs import OpenRun, open_run

    if isinstance(run, OpenRun):
        return run
    if run is not None:
        return OpenRun.from_pipeline(run)
    with console.status(f"loading {load_config}"):
        return open_run(Path(load_config), console)


def open_view(args: Union[Apply, Pick], console: "Console", pipeline=None):
    """(the run, its edit stack on the model's device, the camera on it, its description): what
    ``apply`` and ``pick`` edit. ``pipeline``: an already loaded run (a nerfstudio pipeline or an
    :class:`~virgi_ns.nerfstudio.runs.OpenRun`)."""
    from virgi_ns.edit.stack import EditStack

    run = _run_of(args.load_config, console, pipeline)
    model = run.model
    stack = EditStack.open(Path(args.load_config).parent, model.fingerprint())
    cams, where = resolve_camera(run, args)
    return run, stack.to(model.device), cams.to(model.device), where


def apply(args: Apply, console: "Console", pipeline=None) -> str:
    """Fit and save one edit; returns the summary line. ``pipeline``: an already loaded run."""
    import torch
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from virgi_ns.edit import warmup
    from virgi_ns.edit.engine import EditConfig, EditEngine
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.edit.stack import EditSource

    _check_steps(args.steps)
    if args.pixel_batches is not None and args.pixel_batches < 1:
        raise InputError(f"--pixel-batches must be >= 1, got {args.pixel_batches}")
    if not Path(args.load_config).is_file():
        raise InputError(f"no such config: {args.load_config}")
    image, notes = load_edited_image(args.image)
    _warm_up_while_loading(pipeline)
    run, stack, cams, where = open_view(args, console, pipeline)
    model = run.model
    W, H = int(cams.widths[0]), int(cams.heights[0])
    image, more = fit_size(image, W, H, args.resize, Path(args.image).name)
    for n in notes + more:
        console.print(f"note: {n}")
    original = None if args.whole_image else original_image(run, args, image.shape, console)
    scene = FrozenScene.from_model(model)
    source = EditSource(str(Path(args.image).resolve()), cams.Ks[0].cpu(), cams.viewmats[0].cpu(), W, H, where)
    cfg = EditConfig()
    if args.pixel_batches is not None:
        cfg.pixel_batches = args.pixel_batches
    if args.steps is not None:
        cfg.steps = args.steps
    cfg.whole_image = args.whole_image
    cfg.changed_target = args.changed_target
    cfg.recipe = args.recipe
    cfg.unchanged_weights = args.unchanged_weights
    warmup.wait()
    with torch.no_grad():
        engine = EditEngine(scene, cams, torch.from_numpy(image), stack, cfg, source,
                            original=None if original is None else torch.from_numpy(original))
    with Progress(TextColumn("fitting the edit"), BarColumn(), TextColumn("{task.completed}/{task.total} steps"),
                  TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task("edit", total=cfg.steps)
        edit, timing = engine.fit(progress=lambda done, total: bar.update(task, completed=done))
    number = stack.add(edit)
    return _noted(f"edit {number} saved to {stack.directory / stack.entries[-1].file} ({where}; {timing.steps} steps, "
                  f"setup {timing.setup_s:.3f} s + steps {timing.steps_s:.3f} s, L1 {timing.final_loss:.4f}; fitted "
                  f"{engine.mode}, {engine.changed_fraction:.0%} of the view)", engine,
                  ("more --steps, or paint more of the object" if engine.recipe == "staged"
                   else "try --recipe staged, more --steps, or paint more of the object"))


def _restaged_note(edit) -> str:
    """A line where the pick's joint fit stalled and the selection was fitted again ``staged``."""
    r = edit.info.get("restaged")
    return "" if r is None else (f"\nthe joint fit left the selection nearly unchanged ({max(r['joint_progress'], 0.0):.0%} "
                                 f"of the way); refitted staged ({r['staged_progress']:.0%})")


def _noted(summary: str, engine, remedy: str) -> str:
    """``summary``, and a warning line where the fit left the changed pixels nearly unchanged."""
    note = engine.small_progress_note()
    return summary if note is None else f"{summary}\nwarning: {note}; {remedy} (`virgi-edit undo` removes it)"


def _warm_up_while_loading(pipeline) -> None:
    """In a process that loads its run (no ``pipeline`` given), the GPU's first edit runs on a
    background thread meanwhile (:mod:`virgi_ns.edit.warmup`); the caller waits for it before its edit."""
    if pipeline is None:
        from virgi_ns.edit import warmup

        warmup.start("cuda")  # nothing where no GPU is available


def _check_steps(steps: Optional[int]) -> None:
    if steps is not None and steps < 1:
        raise InputError(f"--steps must be >= 1, got {steps}")


def pick(args: Pick, console: "Console", pipeline=None) -> str:
    """Pick, recolour, fit and save one edit with its edited image and selection; returns the
    summary line. Every argument is checked before the run is loaded, the pixel before any fit."""
    import torch

    from virgi_ns.edit import warmup
    from virgi_ns.edit.pick import PickSession, check_tolerance, commit, parse_colour, pick_config
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.edit.stack import EditSource

    colour = parse_colour(args.colour)
    tolerance = check_tolerance(args.tolerance)
    _check_steps(args.steps)
    if not Path(args.load_config).is_file():
        raise InputError(f"no such config: {args.load_config}")
    _warm_up_while_loading(pipeline)
    run, stack, cams, where = open_view(args, console, pipeline)
    model = run.model
    W, H = int(cams.widths[0]), int(cams.heights[0])
    x, y = args.pixel
    source = EditSource("", cams.Ks[0].cpu(), cams.viewmats[0].cpu(), W, H, f"{where}, pixel {x} {y}")
    warmup.wait()
    with torch.no_grad(), console.status("fitting the pick"):
        cfg = pick_config(model.device)
        if args.steps is not None:  # the rate's schedule spans the config's steps: set them there
            cfg.steps = args.steps
        cfg.unchanged_weights = args.unchanged_weights
        session = PickSession(FrozenScene.from_model(model), cams, x, y, stack, cfg, source,
                              criterion=args.selection, reference=args.reference)
        edit = session.update(colour, tolerance, args.mode, args.steps, contiguous=args.contiguous,
                              depth_edges=args.depth_edges)
    number = commit(stack, session, edit)
    st = session.settings
    return _noted(f"edit {number} saved to {stack.directory / stack.entries[-1].file} (pick at {x} {y} of {where}: "
                  f"{st['selected']:.0%} of the view selected, {args.mode} -> {st['colour']}; edited image and "
                  f"selection beside it: {Path(stack.entries[-1].file).stem}_edited.png, _selection.png)"
                  + _restaged_note(edit),
                  session.engine, "pick again at another pixel or --tolerance")


def run(cmd: object, console: Optional["Console"] = None, pipeline=None) -> str:
    """Run one parsed command; returns the line to print. ``pipeline``: an already loaded run (a
    nerfstudio pipeline or an :class:`~virgi_ns.nerfstudio.runs.OpenRun`) for the commands that load one."""
    if isinstance(cmd, (Apply, Pick, Import)):
        if console is None:
            from rich.console import Console

            console = Console(stderr=True)
        if isinstance(cmd, Apply):
            return apply(cmd, console, pipeline)
        if isinstance(cmd, Pick):
            return pick(cmd, console, pipeline)
        from virgi_ns.edit.stack import EditStack

        if not Path(cmd.edit_file).is_file():
            raise InputError(f"no such edit file: {cmd.edit_file}")
        model = _run_of(cmd.load_config, console, pipeline).model
        stack = EditStack.open(Path(cmd.load_config).parent, model.fingerprint())
        n = stack.import_file(cmd.edit_file)
        return f"edit {n} imported from {cmd.edit_file}"
    m = _manifest(cmd.load_config)  # type: ignore[attr-defined]
    if isinstance(cmd, List):
        return _listing(m)
    if isinstance(cmd, Undo):
        m.undo()
        return f"undone: {len(m.entries)} edit(s) left"
    if isinstance(cmd, Reset):
        n = m.reset()
        return f"reset: removed {n} edit(s), specular strength 1"
    if isinstance(cmd, (Enable, Disable)):
        m.set_enabled(cmd.number, isinstance(cmd, Enable))
        return f"edit {cmd.number} {'enabled' if isinstance(cmd, Enable) else 'disabled'}"
    if isinstance(cmd, Specular):
        m.set_specular_strength(cmd.strength)
        return f"specular strength {cmd.strength:g}"
    raise InputError(f"unknown command {cmd!r}")


def _listing(m) -> str:
    """``list``'s lines from the manifest; an edit's ``info`` comes from its file only when the
    manifest predates recording it there."""
    if not m.entries:
        return f"no edits (specular strength {m.specular_strength:g})"
    lines = [f"{len(m.entries)} edit(s), specular strength {m.specular_strength:g}"]
    for number, e in enumerate(m.entries, 1):
        info = e.get("info")
        if not isinstance(info, dict):
            from virgi_ns.edit.stack import Edit

            info = Edit.load(m.directory / e["file"]).info
        t = f", {info['setup_s'] + info['steps_s']:.2f} s" if "setup_s" in info and "steps_s" in info else ""
        lines.append(f"  {number:>3}  {'on ' if e['enabled'] else 'off'}  {e['file']}  "
                     f"{Path(str(e.get('image', ''))).name or '-'}  [{e.get('camera') or '-'}{t}]")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> None:
    cmd = tyro.cli(Command, args=argv)  # type: ignore[arg-type]
    print(run(cmd))


def entrypoint() -> None:
    cli_entry(lambda: main(sys.argv[1:]))


if __name__ == "__main__":
    entrypoint()
