"""Benchmark: the wall of each console script in a fresh process, against ``python -c 'import torch'``.

For one trained run (``--load-config``) the commands ``virgi-edit list``, ``virgi-edit pick``,
``virgi-edit apply``, ``virgi-export`` (and ``virgi-render`` of the exported file) each run in a new
process, interleaved with a bare ``python -c 'import torch'``: one unmeasured pass first (it fills
the page cache and, by default, a bytecode cache, so every measured call is at least a second call),
then ``--repeats`` measured passes. The table gives each command's median wall, its ratio to the
median ``import torch`` of the same passes, what the command itself reports of its fit (``apply``:
set-up + steps; ``export``: bake + write), and from one more pass under ``python -X importtime``
the seconds spent importing (all modules; torch's part; the largest other packages).

The run is never written: its ``config.yml``, ``virgi_run.json`` and ``edits/`` are copied into
``--out`` (the checkpoint is read where the config points), and the copy's edit stack is put
back before every call, so each ``pick``/``apply`` adds one edit to the same stack and each
``export`` bakes the same edits. ``apply`` fits the edited image the warm-up ``pick`` saved.
``--gaussians N`` times a copy of the run resampled to N Gaussians (jittered copies of its own,
as ``bench/export.py`` times the bake), e.g. ``--gaussians 1000000`` on a GPU.

    python bench/cli_walls.py --load-config demo_out/run/config.yml --device cpu \\
        --camera-index 16 --pixel 267 307 --colour '#e0141e'
    python bench/cli_walls.py --load-config outputs/.../config.yml --device cuda --gaussians 1000000

``--device cpu`` hides the GPUs from the commands (``CUDA_VISIBLE_DEVICES=``). The console scripts
are those beside this interpreter (``virgi-edit``, ...), else ``python -m virgi_ns.cli.*``; the
package they import is printed (``PYTHONPATH`` decides which tree). Writes ``cli_walls.json`` in
``--out``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import tyro

COMMANDS = ("list", "pick", "apply", "export", "render")
SCRIPTS = {"virgi-edit": "virgi_ns.cli.edit", "virgi-export": "virgi_ns.cli.export", "virgi-render": "virgi_ns.cli.render"}
BASELINE = "import torch"


@dataclass
class Args:
    load_config: Path
    """The trained run's config.yml (read only)."""
    out: Path = Path("bench_out/cli_walls")
    device: Literal["cpu", "cuda"] = "cpu"
    """cpu: the commands see no GPU; cuda: they see this machine's."""
    repeats: int = 3
    """Measured passes (after one unmeasured pass); the table gives medians."""
    commands: Tuple[str, ...] = COMMANDS
    """Which of list, pick, apply, export, render to time."""
    camera_index: int = 0
    """The training view ``pick`` and ``apply`` edit."""
    pixel: Optional[Tuple[int, int]] = None
    """X Y of ``pick`` (default: the view's centre)."""
    colour: str = "#e0141e"
    """``pick``'s new colour."""
    gaussians: int = 0
    """Time a copy of the run resampled to this many Gaussians (0: the run as it is)."""
    bytecode_cache: bool = True
    """Let the commands keep compiled bytecode (in a cache under --out, as a usual install keeps it in
    its packages); ``--no-bytecode-cache``: the environment as it is."""
    importtime: bool = True
    """One more pass under ``python -X importtime`` for the import breakdown (not in the walls)."""
    profile: bool = True
    """One more pass under cProfile for the phases (imports, run load, fit, write; not in the walls)."""


# ------------------------------------------------------------------------------ the run copy
def _writable_copy(config: Path, dest: Path) -> Path:
    """``dest/config.yml`` beside copies of the run's sidecar and edits; the checkpoint stays put."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in ("config.yml", "virgi_run.json", "dataparser_transforms.json"):
        if (config.parent / name).is_file():
            shutil.copy2(config.parent / name, dest / name)
    (dest / "edits").mkdir()
    if (config.parent / "edits").is_dir():
        shutil.copytree(config.parent / "edits", dest / "edits", dirs_exist_ok=True)
    return dest / "config.yml"


def _resampled_copy(config: Path, dest: Path, n: int, seed: int = 0) -> Path:
    """A run at ``dest`` whose Gaussians are ``n`` jittered copies of ``config``'s run's (its field,
    cameras and frame as they are; no edits: they belong to the original run's Gaussians)."""
    import torch

    from virgi_ns.nerfstudio.saved_run import RUN_INFO, config_digest, newest_checkpoint, run_settings

    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    text = config.read_text()
    # the config points at the copy: output_dir's path items replaced by dest's
    parts = ["/"] + [p for p in dest.resolve().parts[1:]]
    block = "output_dir: !!python/object/apply:pathlib.PosixPath\n" + "".join(f"- {p}\n" for p in parts)
    text, count = re.subn(r"^output_dir: !!python/object/apply:pathlib\.PosixPath\n(?:- .*\n)+", block, text,
                          flags=re.M)
    if count != 1:
        raise SystemExit(f"{config}: no output_dir path to point at the copy")
    new_config = dest / "config.yml"
    new_config.write_text(text)
    src_ckpt = newest_checkpoint(run_settings(config).checkpoint_dir)
    if src_ckpt is None:
        raise SystemExit(f"{config}: no checkpoint")
    ckpt = torch.load(src_ckpt, map_location="cpu", weights_only=False)
    state = ckpt["pipeline"]
    means_key = next(k for k in state if k.endswith("gauss_params.means"))
    m = state[means_key].shape[0]
    gen = torch.Generator().manual_seed(seed)
    idx = torch.randint(m, (n,), generator=gen)
    prefix = means_key[: -len("gauss_params.means")]
    scales = state[prefix + "gauss_params.scales"]
    jitter = torch.randn(n, 3, generator=gen) * torch.exp(scales[idx].float()).mean(-1, True)
    for k, v in list(state.items()):
        if k.startswith(prefix) and torch.is_tensor(v) and v.ndim >= 1 and v.shape[0] == m:
            state[k] = v[idx].clone()
    state[means_key] = state[means_key] + jitter.to(state[means_key].dtype)
    ckpt_dir = run_settings(new_config).checkpoint_dir
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    torch.save({"step": ckpt["step"], "pipeline": state}, ckpt_dir / src_ckpt.name)
    info = json.loads((config.parent / RUN_INFO).read_text())
    info["config_sha256"] = config_digest(new_config)
    (dest / RUN_INFO).write_text(json.dumps(info))
    if (config.parent / "dataparser_transforms.json").is_file():
        shutil.copy2(config.parent / "dataparser_transforms.json", dest / "dataparser_transforms.json")
    (dest / "edits").mkdir()
    return new_config


# ---------------------------------------------------------------------------------- running
def _script(name: str) -> List[str]:
    """The console script beside this interpreter, else the module behind it."""
    path = Path(sys.executable).parent / name
    return [sys.executable, str(path)] if path.is_file() else [sys.executable, "-m", SCRIPTS[name]]


def _profiled(cmd: List[str], out: Path) -> List[str]:
    """``cmd`` under cProfile writing ``out``. A module (``-m``) is imported and its ``entrypoint`` called
    inside the profile: run as cProfile's ``__main__`` instead, its dataclasses' annotations would be
    resolved in cProfile's namespace and tyro would fail on them."""
    if cmd[1] != "-m":
        return [cmd[0], "-m", "cProfile", "-o", str(out)] + cmd[1:]
    module = cmd[2]
    code = (f"import cProfile, sys; sys.argv[0] = {module!r}; "
            f"cProfile.run('from {module} import entrypoint; entrypoint()', {str(out)!r})")
    return [cmd[0], "-c", code] + cmd[3:]


def _env(args: Args) -> dict:
    env = dict(os.environ)
    if args.device == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""
    if args.bytecode_cache:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str((args.out / "pycache").resolve())
    env.setdefault("COLUMNS", "120")
    return env


def _run(cmd: List[str], env: dict, cwd: Path, importtime: bool = False) -> Tuple[float, str, str]:
    """(wall seconds, stdout, stderr) of ``cmd``; a failing command stops the benchmark."""
    if importtime:
        cmd = [cmd[0], "-X", "importtime"] + cmd[1:]
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    # (a command's own error is one "error: ..." line; under cProfile its exit status can be lost)
    if p.returncode != 0 or any(line.startswith("error: ") for line in p.stderr.splitlines()):
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    return wall, p.stdout, p.stderr


def import_breakdown(stderr: str) -> dict:
    """From ``-X importtime`` output: seconds importing in all, torch's part (its cumulative time
    where a command imports it first), and the packages of most self time besides torch."""
    total, torch_s, per_pkg = 0, 0, Counter()
    for line in stderr.splitlines():
        if not line.startswith("import time:") or "self [us]" in line:
            continue
        try:
            self_us, cum_us, name = line[len("import time:"):].split("|", 2)
        except ValueError:
            continue
        name, self_us, cum_us = name.strip(), int(self_us), int(cum_us)
        total += self_us
        top = name.split(".")[0]
        per_pkg[top] += self_us
        if name == "torch":
            torch_s = cum_us
    others = [(k, v / 1e6) for k, v in per_pkg.most_common() if k not in ("torch", "torchgen")][:6]
    return {"imports_s": total / 1e6, "torch_s": torch_s / 1e6, "largest_others_s": dict(others)}


# per command, the phases read from a cProfile pass: (phase, [(file suffix, function), ...]), the
# functions' cumulative seconds summed (imports made inside a later phase count in both)
PHASES = {
    "list": [("imports", [("importlib._bootstrap>", "_find_and_load")])],
    "pick": [("imports", [("importlib._bootstrap>", "_find_and_load")]),
             ("run load", [("virgi_ns/nerfstudio/runs.py", "open_run")]),
             ("warm-up wait", [("virgi_ns/edit/warmup.py", "wait")]),
             ("fit", [("virgi_ns/edit/pick.py", "__init__"), ("virgi_ns/edit/pick.py", "update")]),
             ("write", [("virgi_ns/edit/pick.py", "commit")])],
    "apply": [("imports", [("importlib._bootstrap>", "_find_and_load")]),
              ("run load", [("virgi_ns/nerfstudio/runs.py", "open_run")]),
              ("warm-up wait", [("virgi_ns/edit/warmup.py", "wait")]),
              ("fit", [("virgi_ns/edit/engine.py", "__init__"), ("virgi_ns/edit/engine.py", "fit")]),
              ("write", [("virgi_ns/edit/stack.py", "add")])],
    "export": [("imports", [("importlib._bootstrap>", "_find_and_load")]),
               ("run load", [("virgi_ns/nerfstudio/runs.py", "open_run")]),
               ("fit", [("virgi_ns/nerfstudio/export.py", "bake")]),
               ("write", [("virgi_ns/nerfstudio/export.py", "write_splat")])],
    "render": [("imports", [("importlib._bootstrap>", "_find_and_load")]),
               ("run load", [("virgi_ns/io/__init__.py", "load_splat")]),
               ("fit", [("virgi_ns/cli/render.py", "render_image")])],
}


def profile_phases(name: str, path: Path, wall: float) -> dict:
    """Seconds per phase of ``name`` from its cProfile file; ``interpreter`` is the wall outside
    the profiled run (start-up, the profiler's own set-up and exit)."""
    import pstats

    stats = pstats.Stats(str(path)).stats  # {(file, line, func): (cc, nc, tt, ct, callers)}
    total = max((v[3] for v in stats.values()), default=0.0)
    out = {"interpreter": max(wall - total, 0.0)}
    for phase, funcs in PHASES.get(name, []):
        out[phase] = sum(v[3] for (f, _, fn), v in stats.items()
                         if any(f.endswith(suffix) and fn == want for suffix, want in funcs))
    return out


def reported(name: str, out: str) -> Optional[float]:
    """The seconds the command reports of its own work: ``apply``'s set-up + steps, ``export``'s
    bake + write (None where it reports none)."""
    m = re.search(r"setup ([0-9.]+) s \+ steps ([0-9.]+) s", out)
    if m:
        return float(m.group(1)) + float(m.group(2))
    if name == "export":
        m = re.search(r", ([0-9.]+) s\s*$", out.strip())
        return float(m.group(1)) if m else None
    return None


def main(args: Args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    src = args.load_config.resolve()
    if not src.is_file():
        raise SystemExit(f"no such config: {src}")
    if args.gaussians > 0:
        print(f"writing a copy of the run with {args.gaussians:,} Gaussians ...", flush=True)
        pristine = _resampled_copy(src, args.out / f"run_{args.gaussians}", args.gaussians)
    else:
        pristine = _writable_copy(src, args.out / "run_pristine")
    cfg = _writable_copy(pristine, args.out / "run")
    edits0 = pristine.parent / "edits"
    info = json.loads((pristine.parent / "virgi_run.json").read_text())
    w, h = info["train"]["width"][args.camera_index], info["train"]["height"][args.camera_index]
    x, y = args.pixel if args.pixel is not None else (w // 2, h // 2)
    env = _env(args)
    cwd = Path.cwd()
    where = subprocess.run([sys.executable, "-c", "import virgi_ns; print(virgi_ns.__file__)"], env=env,
                           capture_output=True, text=True).stdout.strip()
    print(f"virgi_ns from {where}; scripts: {' '.join(_script('virgi-edit')[1:2])} ...", flush=True)
    ply = args.out / "walls.ply"
    edited = args.out / "walls_edited.png"
    camera = args.out / "walls_camera.json"
    for stale in (ply, edited, camera):  # made by this run's first pass, never taken from an earlier run
        stale.unlink(missing_ok=True)

    def reset_edits() -> None:
        shutil.rmtree(cfg.parent / "edits")
        shutil.copytree(edits0, cfg.parent / "edits")

    def command(name: str) -> List[str]:
        c = ["--load-config", str(cfg)]
        if name == "list":
            return _script("virgi-edit") + ["list"] + c
        if name == "pick":
            return _script("virgi-edit") + ["pick"] + c + ["--camera-index", str(args.camera_index), "--pixel",
                                                           str(x), str(y), "--colour", args.colour]
        if name == "apply":
            return _script("virgi-edit") + ["apply"] + c + ["--camera-index", str(args.camera_index), "--image",
                                                            str(edited)]
        if name == "export":
            return _script("virgi-export") + c + ["--out", str(ply)]
        return _script("virgi-render") + [str(ply), "--camera", str(camera), "--out", str(args.out / "walls.png")]

    names = [n for n in COMMANDS if n in args.commands]
    unknown = set(args.commands) - set(COMMANDS)
    if unknown:
        raise SystemExit(f"unknown commands {sorted(unknown)} (known: {', '.join(COMMANDS)})")
    baseline = [sys.executable, "-c", BASELINE]

    def one_pass(importtime: bool = False, profile: bool = False
                 ) -> Tuple[Dict[str, float], List[float], Dict[str, str], Dict[str, str]]:
        """Each command, then a bare ``import torch``: (walls, the import torch walls, stdouts, stderrs);
        ``profile``: the commands run under cProfile, each writing ``--out/NAME.prof``."""
        walls, base, outs, errs = {}, [], {}, {}
        for name in names:
            reset_edits()
            cmd = command(name)
            if profile:
                cmd = _profiled(cmd, args.out / f"{name}.prof")
            walls[name], outs[name], errs[name] = _run(cmd, env, cwd, importtime)
            if name == "pick" and not edited.is_file():  # apply's image: the pick's edited image
                made = sorted((cfg.parent / "edits").glob("*_edited.png"))
                shutil.copy2(made[-1], edited)
            if name == "export" and "render" in names and not camera.is_file():
                _write_camera(pristine.parent / "virgi_run.json", args.camera_index, camera)
            wall, _, errs[BASELINE] = _run(baseline, env, cwd, importtime)
            base.append(wall)
        return walls, base, outs, errs

    if "apply" in names and "pick" not in names:
        raise SystemExit("apply fits the image pick makes: time pick too")
    if "render" in names and "export" not in names:
        raise SystemExit("render draws the file export writes: time export too")
    print("unmeasured pass ...", flush=True)
    one_pass()
    runs: List[Dict[str, float]] = []
    all_base: List[float] = []
    outs: Dict[str, str] = {}
    slow: set = set()  # commands that loaded the run through nerfstudio (their note on stderr)
    for r in range(args.repeats):
        walls, base_walls, outs, errs = one_pass()
        slow |= {k for k, v in errs.items() if "through nerfstudio" in v}
        runs.append(walls)
        all_base += base_walls
        print(f"pass {r + 1}/{args.repeats}: " + ", ".join(f"{k} {v:.2f}" for k, v in walls.items())
              + f"; import torch {', '.join(f'{w:.2f}' for w in base_walls)}", flush=True)
    breakdown = {}
    if args.importtime:
        _, _, _, errs = one_pass(importtime=True)
        breakdown = {k: import_breakdown(v) for k, v in errs.items()}
    phases = {}
    if args.profile:  # (extra figures: where a command cannot run under cProfile, the walls still stand)
        try:
            prof_walls, _, _, _ = one_pass(profile=True)
            phases = {k: profile_phases(k, args.out / f"{k}.prof", w) for k, w in prof_walls.items()}
        except SystemExit as e:
            print(f"the profiled pass failed, no phases: {str(e).splitlines()[0]}", flush=True)
    base = statistics.median(all_base)
    rows = []
    for name in names:
        walls = [run[name] for run in runs]
        rows.append({"command": name, "walls_s": walls, "median_s": statistics.median(walls),
                     "ratio_to_import_torch": statistics.median(walls) / base,
                     "reported_work_s": reported(name, outs.get(name, "")), "imports": breakdown.get(name),
                     "loaded_through_nerfstudio": name in slow, "profiled_phases_s": phases.get(name),
                     "argv": command(name)[1:]})
    result = {"device": args.device, "run": str(src), "gaussians": args.gaussians or None, "virgi_ns": where,
              "python": sys.version.split()[0], "bytecode_cache": args.bytecode_cache,
              "import_torch_walls_s": all_base, "import_torch_median_s": base,
              "import_torch_imports": breakdown.get(BASELINE), "rows": rows, "args": _jsonable(asdict(args))}
    (args.out / "cli_walls.json").write_text(json.dumps(result, indent=1))
    _table(result)
    print(f"JSON: {args.out / 'cli_walls.json'}")


def _write_camera(run_info: Path, index: int, path: Path) -> None:
    """A CAM.json of training view ``index`` in the capture's frame (the exported file's), for
    ``virgi-render``."""
    from virgi_ns.io.camera_json import CameraSpec, write_camera_json
    from virgi_ns.nerfstudio.frames import CaptureFrame
    from virgi_ns.nerfstudio.saved_run import RunInfo

    info = RunInfo.from_json(json.loads(run_info.read_text()))
    cam = info.train.camera(index)
    frame = CaptureFrame(info.capture_transform, info.capture_scale)
    vm = frame.viewmats_to_capture(cam.viewmats.double())[0].numpy()
    K = cam.Ks[0].double()
    write_camera_json(path, CameraSpec(int(cam.widths[0]), int(cam.heights[0]), float(K[0, 0]), float(K[1, 1]),
                                       float(K[0, 2]), float(K[1, 2]), vm))


def _table(result: dict) -> None:
    base = result["import_torch_median_s"]
    n = f"{result['gaussians']:,} Gaussians" if result["gaussians"] else "the run's Gaussians"
    passes = len(result["rows"][0]["walls_s"]) if result["rows"] else 0
    print(f"\nFresh-process walls, second call or later ({result['device']}; {n}; median of {passes}), "
          f"`python -c 'import torch'`: {base:.2f} s")
    print("| command | wall s | / import torch | command's own work s | imports s (torch) | largest other imports | "
          "profiled phases s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in result["rows"]:
        imp = r["imports"] or {}
        others = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in list(imp.get("largest_others_s", {}).items())[:3])
        work = "" if r["reported_work_s"] is None else f"{r['reported_work_s']:.2f}"
        imps = f"{imp['imports_s']:.2f} ({imp['torch_s']:.2f})" if imp else ""
        note = " (loaded through nerfstudio)" if r["loaded_through_nerfstudio"] else ""
        ph = ", ".join(f"{k} {v:.2f}" for k, v in (r.get("profiled_phases_s") or {}).items())
        print(f"| {r['command']}{note} | {r['median_s']:.2f} | {r['ratio_to_import_torch']:.2f}x | {work} | {imps} | "
              f"{others} | {ph} |")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return str(x) if isinstance(x, Path) else x


def entrypoint() -> None:
    main(tyro.cli(Args))


if __name__ == "__main__":
    entrypoint()
