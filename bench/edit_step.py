"""Benchmark: the ways an edit step applies its pixel batch's sparse matrix (``EditConfig.batch_composite``)
on the edit benchmark's 1M-Gaussian 1280x720 scene (``bench/common/scenes.py`` ``million_scene``), in one command.

Per kind (``--variants``, default every kind of :data:`virgi_ns.edit.pixels.COMPOSITES`):

  check          the first pixel batch's ``A @ C`` and ``A^T @ g`` against the ``csr`` kind's on the same
                 batch (max abs difference, and relative to the largest csr value; pass: <= --tol)
  fwd / bwd ms   one ``A @ C`` / one ``A^T @ g`` alone (CUDA events, median of --op-repeats after a
                 warm-up), and the two as one autograd step (``render(C).backward(g)``)
  edit ms        the whole warm edit (features cached): a fresh EditEngine's setup and its steps with
                 CUDA graphs on, median of --repeats after a warm-up; "graphed" says whether the steps
                 ran as CUDA graphs (a kind whose step cannot be recorded falls back to eager steps, with
                 the engine's warning in the row)
  edit vs csr    the edit's final loss and the largest difference of its preview from the csr edit's

A kind that fails is a row with its error; the others go on. The fastest kind that passed the check is
named (by warm edit time), and, when the fastest forward and backward kinds differ, their pair
``FWD/BWD`` is measured too (``--no-combo``: not). ``--cpu-smoke`` runs a tiny scene on the CPU (tests).

    python bench/edit_step.py --out bench_out/edit_step
"""

from __future__ import annotations

import math
import statistics
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional

import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.results import provenance, write_json
from common.scenes import million_scene
from common.settings import edit_settings
from virgi_ns.edit.engine import EditConfig, EditEngine
from virgi_ns.edit.pixels import COMPOSITES, parse_composite
from virgi_ns.errors import InputError, cli_entry

console = Console(width=220)


@dataclass
class Args:
    out: Path = Path("bench_out/edit_step")
    variants: List[str] = field(default_factory=lambda: list(COMPOSITES))
    """EditConfig.batch_composite values to measure ('csr' is always measured first: the reference), each
    optionally with other EditConfig settings after a comma (``fused,fused_heads=false``)."""
    gaussians: int = 1_000_000
    width: int = 1280
    height: int = 720
    steps: Optional[int] = None
    """Edit steps (default: the engine's)."""
    repeats: int = 3
    """Warm edits per kind (median), after one warm-up edit."""
    op_repeats: int = 20
    """Timed forward / backward calls per kind (median), after a warm-up."""
    tol: float = 1e-4
    """Largest difference from csr, relative to csr's largest value, that passes the check."""
    combo: bool = True
    """Also measure 'FWD/BWD' of the fastest forward and backward kinds when they differ."""
    budget_s: float = 90.0
    """Past this many seconds since the start, the remaining kinds are checked and timed per call
    but their warm edits are skipped (the row says so)."""
    cpu_smoke: bool = False
    """A tiny scene on the CPU (a test of this script, not a measurement)."""


def _timer(dev: torch.device, fn: Callable[[], object], repeats: int, warmup: int = 3) -> float:
    """Median seconds of ``fn`` (CUDA events on a GPU, the wall clock on the CPU)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        if dev.type == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b) / 1e3)
        else:
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return float(statistics.median(times))


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


class Bench:
    """The scene, its edited image and the csr kind's reference on the first pixel batch."""

    def __init__(self, args: Args) -> None:
        self.args = args
        if args.cpu_smoke:
            self.dev = torch.device("cpu")
        else:
            if not torch.cuda.is_available():
                raise SystemExit("bench/edit_step.py needs a CUDA GPU (or --cpu-smoke)")
            self.dev = torch.device("cuda")
        self.scene, self.cams = million_scene(args.gaussians, args.width, args.height, self.dev.type)
        self.scene.precompute_features()
        g = torch.Generator(device=self.dev).manual_seed(1)
        self.edited = torch.rand(args.height, args.width, 3, generator=g, device=self.dev)
        self.ref: dict = {}
        self.t0 = time.perf_counter()

    def cfg(self, variant: str) -> EditConfig:
        """``KIND[,FIELD=VALUE...]``: the composite kind and any other EditConfig settings (parsed as
        bench/edit.py's --variants are; its ``rule`` and ``source`` keys mean nothing here)."""
        kind, _, rest = variant.partition(",")
        settings = edit_settings(rest) if rest else {}
        for key in ("rule", "source"):
            if key in settings:
                raise InputError(f"--variants: EditConfig has no field {key!r}")
        steps = {} if self.args.steps is None else {"steps": self.args.steps}
        return EditConfig(**{"batch_composite": kind, **steps, **settings})

    @torch.no_grad()
    def check(self, kind: str, eng: EditEngine) -> dict:
        """The first batch's forward and backward against csr's (set by the csr row); for the fused
        kind, its loss and gradient to the colours against csr's loss and autograd gradient."""
        b = eng.batches[0]
        if not self.ref:  # the csr row: the reference colours, gradient and products
            C = eng.colours()[0].detach()
            gen = torch.Generator(device=self.dev).manual_seed(2)
            grad = torch.randn(b.target.shape, generator=gen, device=self.dev)
            Cg = C.clone().requires_grad_(True)
            with torch.enable_grad():
                loss = b.loss(Cg)
                (loss_grad,) = torch.autograd.grad(loss, Cg)
            self.ref = {"C": C, "grad": grad, "fwd": b.render(C), "bwd": b.render_transpose(grad),
                        "batch_loss": loss.detach(), "loss_grad": loss_grad, "pixels": b.pixels}
        r = self.ref
        if (b.pixels is None) != (r["pixels"] is None) or (b.pixels is not None and not torch.equal(b.pixels, r["pixels"])):
            raise RuntimeError("the first pixel batch is not csr's (the pixel sets differ)")
        if b.sets is not None:  # the kernel's loss and gradient for the first set
            b.sets.restart()
            loss, grad = b.sets.loss_and_grad(r["C"])
            d_f, d_b = float((loss - r["batch_loss"]).abs()), float((grad - r["loss_grad"]).abs().max())
            rel_f = d_f / max(float(r["batch_loss"].abs()), 1e-30)
            rel_b = d_b / max(float(r["loss_grad"].abs().max()), 1e-30)
        else:
            fwd, bwd = b.render(r["C"]), b.render_transpose(r["grad"])
            d_f, d_b = float((fwd - r["fwd"]).abs().max()), float((bwd - r["bwd"]).abs().max())
            rel_f = d_f / max(float(r["fwd"].abs().max()), 1e-30)
            rel_b = d_b / max(float(r["bwd"].abs().max()), 1e-30)
        return {"fwd_max_abs_diff": d_f, "bwd_max_abs_diff": d_b, "fwd_rel_diff": rel_f, "bwd_rel_diff": rel_b,
                "passed": bool(rel_f <= self.args.tol and rel_b <= self.args.tol)}

    def op_times(self, eng: EditEngine) -> dict:
        """One forward, one backward, and the two through autograd, on the first batch (fused: the
        loss and its gradient, one kernel, as fwd+bwd)."""
        b, n = eng.batches[0], self.args.op_repeats
        C, grad = self.ref["C"], self.ref["grad"]
        if b.sets is not None:
            return {"fwd_s": None, "bwd_s": None,
                    "fwd_bwd_s": _timer(self.dev, lambda: b.sets.loss_and_grad(C), n)}
        Cg = C.clone().requires_grad_(True)

        def both() -> None:
            Cg.grad = None
            b.render(Cg).backward(grad)

        with torch.no_grad():
            fwd = _timer(self.dev, lambda: b.render(C), n)
            bwd = _timer(self.dev, lambda: b.render_transpose(grad), n)
        with torch.enable_grad():
            fb = _timer(self.dev, both, n)
        return {"fwd_s": fwd, "bwd_s": bwd, "fwd_bwd_s": fb}

    def edits(self, kind: str) -> dict:
        """Warm edits of a fresh engine each (setup + steps), median of --repeats after a warm-up."""
        times, graphed, notes = [], [], []
        eng = None
        for i in range(1 + max(1, self.args.repeats)):
            cfg = self.cfg(kind)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                with torch.enable_grad():
                    eng = EditEngine(self.scene, self.cams, self.edited, cfg=cfg)
                    _, t = eng.fit()
            notes += [str(w.message).splitlines()[0] for w in caught if "CUDA graphs" in str(w.message)]
            graphed.append(cfg.cuda_graphs)
            if i > 0:
                times.append(t)
        med = lambda v: float(statistics.median(v))  # noqa: E731
        out = {"setup_s": med([t.setup_s for t in times]), "steps_s": med([t.steps_s for t in times]),
               "total_s": med([t.total_s for t in times]), "steps": times[0].steps, "final_loss": times[-1].final_loss,
               "graphed": all(graphed) if self.dev.type == "cuda" else None, "graph_warnings": sorted(set(notes))}
        with torch.no_grad():
            preview = eng.preview()["rgb"]
        if "preview" not in self.ref:
            self.ref["preview"], self.ref["loss"] = preview, out["final_loss"]
        out["preview_max_diff_vs_csr"] = float((preview - self.ref["preview"]).abs().max())
        out["loss_diff_vs_csr"] = out["final_loss"] - self.ref["loss"]
        return out

    def row(self, kind: str) -> dict:
        row: dict = {"variant": kind}
        try:
            with torch.enable_grad():
                eng = EditEngine(self.scene, self.cams, self.edited, cfg=self.cfg(kind))
            b0 = eng.batches[0]
            row["batch_pixels"] = int(b0.target.shape[0])
            row["batch_entries"] = int(b0.sets.pixel_offsets[b0.pixels + 1].sum() - b0.sets.pixel_offsets[b0.pixels].sum()
                                       if b0.sets is not None else b0.op.forward_side.gather.numel())
            row.update(self.check(kind, eng))
            row.update(self.op_times(eng))
            del eng
            if time.perf_counter() - self.t0 > self.args.budget_s and "preview" in self.ref:
                row["skipped"] = f"warm edits skipped: past --budget-s {self.args.budget_s:g}"
            else:
                row.update(self.edits(kind))
        except Exception as e:  # noqa: BLE001  a kind that fails is a row, not the end of the run
            row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
            row["traceback"] = traceback.format_exc(limit=6)
            console.print(f"[red]{kind} failed: {row['error']}[/red]")
        finally:
            if self.dev.type == "cuda":
                torch.cuda.empty_cache()
        if "error" not in row:
            console.log(f"{kind}: {'PASS' if row['passed'] else 'FAIL'} (rel diff fwd {row['fwd_rel_diff']:.1e}, bwd "
                        f"{row['bwd_rel_diff']:.1e}); fwd {_ms(row, 'fwd_s')} ms, bwd {_ms(row, 'bwd_s')} ms; warm edit "
                        f"{_ms(row, 'total_s')} ms (steps {_ms(row, 'steps_s')}, graphed {row.get('graphed')})")
        return row


def _ms(row: dict, key: str) -> str:
    v = row.get(key)
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{1e3 * v:.2f}"


def _ok(row: dict) -> bool:
    return "error" not in row and bool(row.get("passed")) and "total_s" in row


def fastest(rows: List[dict]) -> dict:
    """The fastest kind that passed (warm edit time), and the fastest forward and backward kinds."""
    ok = [r for r in rows if _ok(r)]
    out: dict = {"edit": min(ok, key=lambda r: r["total_s"])["variant"] if ok else None}
    single = [r for r in rows if "error" not in r and r.get("passed") and "/" not in r["variant"]]
    for side in ("fwd", "bwd"):  # (the fused kind does both in one kernel: no time of its own for either)
        timed = [r for r in single if r.get(f"{side}_s") is not None]
        out[side] = min(timed, key=lambda r: r[f"{side}_s"])["variant"] if timed else None
    csr = next((r for r in ok if r["variant"] == "csr"), None)
    if csr is not None and out["edit"] is not None:
        best = next(r for r in ok if r["variant"] == out["edit"])
        out["speedup_vs_csr"] = csr["total_s"] / best["total_s"]
    return out


def print_table(rows: List[dict], device: str, args: Args, best: dict) -> None:
    t = Table(title=f"edit step composite kinds: {args.gaussians:,} Gaussians at {args.width}x{args.height} ({device})")
    for c in ("variant", "check (fwd, bwd rel diff)", "fwd ms", "bwd ms", "fwd+bwd ms", "setup ms", "steps ms",
              "edit ms", "graphed", "loss - csr", "preview vs csr"):
        t.add_column(c)
    for r in rows:
        if "error" in r:
            t.add_row(r["variant"], f"ERROR: {r['error']}"[:120], *["-"] * 9)
            continue
        check = f"{'PASS' if r['passed'] else 'FAIL'} ({r['fwd_rel_diff']:.1e}, {r['bwd_rel_diff']:.1e})"
        t.add_row(r["variant"], check, _ms(r, "fwd_s"), _ms(r, "bwd_s"), _ms(r, "fwd_bwd_s"), _ms(r, "setup_s"),
                  _ms(r, "steps_s"), _ms(r, "total_s"),
                  {True: "yes", False: "NO"}.get(r.get("graphed"), "-"),
                  "-" if "loss_diff_vs_csr" not in r else f"{r['loss_diff_vs_csr']:+.2e}",
                  "-" if "preview_max_diff_vs_csr" not in r else f"{r['preview_max_diff_vs_csr']:.2e}")
    console.print(t)
    for r in rows:
        for w in r.get("graph_warnings", []) + ([r["skipped"]] if "skipped" in r else []):
            console.print(f"{r['variant']}: {w}")
    sp = best.get("speedup_vs_csr")
    console.print(f"fastest kind that passed: {best['edit']}" + (f" ({sp:.2f}x csr's warm edit)" if sp else "")
                  + f"; fastest forward {best['fwd']}, backward {best['bwd']}")


def main(args: Args) -> dict:
    if args.cpu_smoke:
        args.gaussians, args.width, args.height = min(args.gaussians, 1500), min(args.width, 40), min(args.height, 24)
        args.steps = 6 if args.steps is None else args.steps
        args.repeats, args.op_repeats = min(args.repeats, 1), min(args.op_repeats, 2)
    t0 = time.perf_counter()
    b = Bench(args)
    device = torch.cuda.get_device_name(0) if b.dev.type == "cuda" else "cpu"
    kinds = ["csr"] + [v for v in args.variants if v != "csr"]
    rows: List[dict] = []
    result: dict = {"device": device, **provenance(), "gaussians": args.gaussians,
                    "image": f"{args.width}x{args.height}", "tol": args.tol, "rows": rows}
    for k in kinds:
        rows.append(b.row(k))
        if "error" in rows[0]:
            console.print("[red]the csr reference failed: nothing to check the other kinds against[/red]")
            break
    best = fastest(rows)
    if args.combo and best["fwd"] and best["bwd"] and best["fwd"] != best["bwd"]:
        pair = f"{best['fwd']}/{best['bwd']}"
        if pair not in kinds:
            try:
                parse_composite(pair)
                rows.append(b.row(pair))
            except ValueError:
                pass
            best = fastest(rows)
    result["fastest"] = best
    result["wall_s"] = time.perf_counter() - t0
    print_table(rows, device, args, best)
    write_json(args.out / "results.json", result, console)
    return result


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
