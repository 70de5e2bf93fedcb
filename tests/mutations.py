"""Deliberate breaks, one at a time, each against the default tests that guard it: does the suite fail
when the code breaks? Run by hand (it is not a test; a full run takes a while):

    python tests/mutations.py                  # every break: a table, exit 1 if any survived
    python tests/mutations.py --list           # the breaks
    python tests/mutations.py NAME [NAME ...]  # only these

Each break is (name, file, original snippet, replacement, tests). The tree is copied once to a temporary
folder (without .git, .venv and outputs; the real files are never edited); for each break the copy's file
gets the replacement, ``python -m pytest -x -q TESTS`` runs in the copy with ``PYTHONPATH=<copy>`` (the
default selection: no ``slow``, GPU tests skip without a GPU, and no ``../shared`` in reach, as in a
clone), and the file is put back. **killed**: a test failed; **survived**: they all passed; **stale**:
the snippet is not in the file any more (update the list); **error**: pytest could not run them.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Break:
    name: str
    file: str
    original: str
    replacement: str
    tests: tuple[str, ...]
    what: str


BREAKS = [
    # ---- the table
    Break("gsplat-pass-black", "virgi_ns/nerfstudio/gsplat_pass.py",
          "        img[..., -1:].div_(alpha.clamp(min=1e-10))\n    return img, alpha",
          "        img[..., -1:].div_(alpha.clamp(min=1e-10))\n    return torch.zeros_like(img), alpha",
          ("tests/test_render_cache.py",), "the whole-view gsplat pass returns black images"),
    Break("viewer-apply-noop", "virgi_ns/nerfstudio/viewer/panel.py",
          'ViewerButton("Apply edit", cb_hook=lambda e: self._guard(self.apply_edit))',
          'ViewerButton("Apply edit", cb_hook=lambda e: None)',
          ("tests/test_viewer.py",), "the panel's Apply button does nothing"),
    Break("viewer-upload-noop", "virgi_ns/nerfstudio/viewer/panel.py",
          'ViewerUpload("Upload edited image", cb_hook=lambda e: self._on_upload(e),',
          'ViewerUpload("Upload edited image", cb_hook=lambda e: None,',
          ("tests/test_viewer.py",), "the panel's upload does nothing"),
    Break("viewer-click-xy-swapped", "virgi_ns/nerfstudio/viewer/picking.py",
          "self.pick_at(cam, min(int(u * W), W - 1), min(int(v * H), H - 1))",
          "self.pick_at(cam, min(int(v * H), H - 1), min(int(u * W), W - 1))",
          ("tests/test_viewer.py",), "a scene click picks (y, x)"),
    Break("viewer-no-panel", "virgi_ns/nerfstudio/model.py",
          "self.viewer_panel = VirgiPanel(self)", "self.viewer_panel = None",
          ("tests/test_viewer.py",), "the model holds no panel (model.viewer_panel = None)"),
    Break("demo-heldout-unedited", "virgi_ns/demo/run.py",
          "ed = render_view(frozen, eval_cams, i, stack, contrib=contribs[i])",
          "ed = render_view(frozen, eval_cams, i, None, contrib=contribs[i])",
          ("tests/test_demo.py",), "the demo renders the held-out views without the edit"),
    Break("bench-leak-on-mask", "virgi_ns/bench/recolor.py",
          '"leak_psnr": psnr(after, truth_render, ~mask),', '"leak_psnr": psnr(after, truth_render, mask),',
          ("tests/test_recolor.py", "tests/test_edit_bench.py"), "the recolour bench measures leak on the mask instead of outside it"),
    Break("splatfacto-safe-load-raises", "virgi_ns/io/splatfacto.py",
          '    """``torch.load`` with safe unpickling; allows only the numpy scalar types checkpoints may hold."""\n',
          '    """``torch.load`` with safe unpickling; allows only the numpy scalar types checkpoints may hold."""\n'
          '    raise InputError(f"{path}: cannot read the checkpoint (broken)")\n',
          ("tests/test_io_splatfacto.py",), "the splatfacto reader's safe load raises on entry"),
    Break("cli-no-such-file-deleted", "virgi_ns/errors.py",
          '    except FileNotFoundError as e:\n        print(f"error: no such file: {e.filename or e}", file=sys.stderr)\n'
          "        sys.exit(EXIT_USER_ERROR)\n", "",
          ("tests/test_errors.py", "tests/test_io_bad_input.py", "tests/test_render_cli.py", "tests/test_edit_cli.py"),
          "the CLI's 'no such file' branch deleted"),
    Break("cli-ctrl-c-deleted", "virgi_ns/errors.py",
          '    except KeyboardInterrupt:\n        print("interrupted", file=sys.stderr)\n        sys.exit(130)\n', "",
          ("tests/test_errors.py", "tests/test_io_bad_input.py", "tests/test_render_cli.py", "tests/test_edit_cli.py"),
          "the CLI's Ctrl-C branch (exit 130) deleted"),
    # ---- across the package
    Break("raster-pixel-centre", "virgi_ns/raster/reference.py",
          "    ux0_t = ux0.to(dtype) + 0.5\n", "    ux0_t = ux0.to(dtype) + 0.0\n",
          ("tests/test_raster_reference.py",), "the reference rasterizer's pixel centres at x instead of x + 0.5"),
    Break("field-specular-dropped", "virgi_ns/colour/field.py",
          'return {"c_d": c_d, "c_s": c_s, "rgb": torch.sigmoid(c_d + c_s)}',
          'return {"c_d": c_d, "c_s": c_s, "rgb": torch.sigmoid(c_d)}',
          ("tests/test_field.py",), "the colour field's rgb leaves out the specular term"),
    Break("sh-band-signs", "virgi_ns/colour/sh.py", "    sign[1::2] = -1.0\n", "    sign[1::2] = 1.0\n",
          ("tests/test_io_ply.py", "tests/test_render_cli.py", "tests/test_export.py"),
          "SH colours without the 3DGS sign convention"),
    Break("ply-sh-rest-order", "virgi_ns/io/ply.py",
          "sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)", "sh[:, 1:] = rest.reshape(n, k - 1, 3)",
          ("tests/test_io_ply.py",), "INRIA .ply f_rest read coefficient-major instead of channel-major"),
    Break("spz-scale-offset", "virgi_ns/io/spz.py",
          "scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0",
          "scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 9.0",
          ("tests/test_io_spz.py",), ".spz log-scales decoded with the wrong offset"),
    Break("compressed-ply-bit-layout", "virgi_ns/io/compressed_ply.py",
          "np.stack([_unorm(v, 21, 11), _unorm(v, 11, 10), _unorm(v, 0, 11)], axis=1)",
          "np.stack([_unorm(v, 0, 11), _unorm(v, 11, 10), _unorm(v, 21, 11)], axis=1)",
          ("tests/test_io_compressed_ply.py",), "SuperSplat's 11-10-11 fields read in the wrong order"),
    Break("stack-renders-disabled-edits", "virgi_ns/edit/stack.py",
          "        return [e.edit for e in self.entries if e.enabled]\n", "        return [e.edit for e in self.entries]\n",
          ("tests/test_model_edit_stack.py", "tests/test_edit.py"), "a disabled edit still renders"),
    Break("manifest-enable-ignored", "virgi_ns/edit/manifest.py",
          '        self.entries[self._index(number)]["enabled"] = bool(enabled)\n',
          '        self.entries[self._index(number)]["enabled"] = True\n',
          ("tests/test_edit_cli.py",), "virgi-edit disable leaves the edit enabled in stack.json"),
    Break("export-dc-offset", "virgi_ns/nerfstudio/export.py",
          "sh[idx, 0] = ((torch.sigmoid(c_d) - 0.5) / SH_C0).float()", "sh[idx, 0] = (torch.sigmoid(c_d) / SH_C0).float()",
          ("tests/test_export.py",), "the export bakes matte colours without the SH offset of 0.5"),
    Break("camera-json-cx-cy-swapped", "virgi_ns/io/camera_json.py",
          'return CameraSpec(size["width"], size["height"], fx, fy, cx, cy, M)',
          'return CameraSpec(size["width"], size["height"], fx, fy, cy, cx, M)',
          ("tests/test_render_cli.py", "tests/test_viewer.py"), "CAM.json's principal point read as (cy, cx)"),
    Break("viewer-display-noop", "virgi_ns/nerfstudio/viewer/panel.py",
          'ViewerDropdown("Display", "rgb", list(DISPLAYS), cb_hook=lambda e: self._guard(lambda: self.set_display(e.value)),',
          'ViewerDropdown("Display", "rgb", list(DISPLAYS), cb_hook=lambda e: None,',
          ("tests/test_viewer.py",), "the panel's Display dropdown does nothing"),
    Break("pick-worker-not-woken", "virgi_ns/nerfstudio/viewer/picking.py",
          "            self._commit_after_s = float(seconds)\n            self._pick_cond.notify_all()\n",
          "            self._commit_after_s = float(seconds)\n",
          ("tests/test_viewer.py",), "the pick worker sleeps out a commit due under the old commit_after_s"),
    Break("pick-background-accepted", "virgi_ns/edit/pick.py",
          "    if cover < MIN_COVER:\n", "    if False:\n",
          ("tests/test_pick.py", "tests/test_edit_cli.py"), "a click on the background is not refused"),
    Break("pick-crosses-depth-edges", "virgi_ns/edit/pick.py",
          "math.log(1.0 + 4.0 * tolerance), maps.depth if depth_edges else None)",
          "math.log(1.0 + 4.0 * tolerance), None)",
          ("tests/test_pick_boundaries.py",), "the selection grows across an occlusion edge"),
    Break("pick-takes-neutral-neighbours", "virgi_ns/edit/pick.py",
          "return (chroma >= max(NEUTRAL_CHROMA, at / band)) & (chroma <= at * band)",
          "return chroma >= NEUTRAL_CHROMA",
          ("tests/test_pick_boundaries.py",), "a saturated click takes a touching near-neutral surface of its hue"),
]


def _copy_tree(dest: Path) -> Path:
    ignore = shutil.ignore_patterns(".git", ".venv", "bench_out", "demo_out", "__pycache__", ".pytest_cache", "*.egg-info")
    shutil.copytree(REPO, dest, ignore=ignore, symlinks=True)
    return dest


def run_break(b: Break, copy: Path, timeout: float) -> tuple[str, float, str]:
    """(result, seconds, last line of pytest's output) of one break applied to ``copy``."""
    path = copy / b.file
    if not path.is_file():
        return "stale", 0.0, f"{b.file} does not exist"
    text = path.read_text(encoding="utf-8")
    n = text.count(b.original)
    if n != 1:
        return ("stale" if n == 0 else "error"), 0.0, f"the snippet occurs {n} times in {b.file}"
    env = {**os.environ, "PYTHONPATH": str(copy) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "PYTHONDONTWRITEBYTECODE": "1"}  # no bytecode: a restored file of the same size must not reuse it
    env.pop("VIRGI_SHARED_DATA", None)
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *b.tests]
    t0 = time.monotonic()
    try:
        path.write_text(text.replace(b.original, b.replacement), encoding="utf-8")
        try:
            p = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
            rc, out = p.returncode, (p.stdout + p.stderr).strip()
        except subprocess.TimeoutExpired:
            rc, out = -1, f"timed out after {timeout:.0f} s"
    finally:
        path.write_text(text, encoding="utf-8")
    secs = time.monotonic() - t0
    last = out.splitlines()[-1] if out else ""
    if rc == 1:
        return "killed", secs, last
    if rc == 0:
        return "survived", secs, last
    if rc == -1:  # a hang is a failure the suite would report too (pytest-timeout)
        return "killed", secs, last
    return "error", secs, f"pytest exit {rc}: {last}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="only these breaks")
    ap.add_argument("--list", action="store_true", help="list the breaks and exit")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per break")
    args = ap.parse_args()
    if args.list:
        for b in BREAKS:
            print(f"{b.name:32s} {b.file}: {b.what}")
        return 0
    unknown = set(args.names) - {b.name for b in BREAKS}
    if unknown:
        ap.error(f"no such break: {', '.join(sorted(unknown))}")
    chosen = [b for b in BREAKS if not args.names or b.name in args.names]
    rows = []
    with tempfile.TemporaryDirectory(prefix="virgi_mutations_") as tmp:
        copy = _copy_tree(Path(tmp) / "repo")
        for b in chosen:
            result, secs, last = run_break(b, copy, args.timeout)
            rows.append((b, result, secs, last))
            print(f"{result:9s} {secs:6.0f} s  {b.name}: {last}", flush=True)
    print()
    print("| break | file | guarded by | result |")
    print("| --- | --- | --- | --- |")
    for b, result, secs, _ in rows:
        tests = ", ".join(t.replace("tests/", "") for t in b.tests)
        print(f"| {b.what} | `{b.file}` | {tests} | **{result}** ({secs:.0f} s) |")
    bad = [b.name for b, r, _, _ in rows if r != "killed"]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} breaks killed" + (f"; not killed: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
