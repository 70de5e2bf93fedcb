"""Benchmark: the ways an edit step can apply its pixel batch's sparse matrix, on the edit benchmark's
1M-Gaussian 1280x720 scene (``bench/common/scenes.py`` ``million_scene``), in one command.

The kinds: the library's two (``EditConfig.batch_composite``: ``csr``, the reference, and ``fused``, the GPU's),
``fused_scattered`` (the fused kind with its gradient scattered by one atomic per entry, its fallback where the
entries sorted by Gaussian cannot be built), and the contestants defined here (:data:`CONTESTANTS`), each a
sparse product by another kernel put in the place of each pixel set's csr operator (or ``FWD/BWD``: one kind
for each pass). Per kind (``--variants``, default every kind):

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
``FWD/BWD`` is measured too (``--no-combo``: not). ``--changed-region`` times an edit of part of the render
instead of a random image. ``--cpu-smoke`` runs a tiny scene on the CPU (tests).

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
from typing import Callable, List, NamedTuple, Optional

import torch
import tyro
from torch import Tensor
from rich.console import Console
from rich.table import Table

from common.results import provenance, write_json
from common.scenes import million_scene
from common.settings import edit_settings
from virgi_ns.edit.engine import EditConfig, EditEngine
from virgi_ns.edit.fitting import sync
from virgi_ns.edit.pixels import CompositeOp, csr_matrix, row_offsets
from virgi_ns.edit.scene import render_view
from virgi_ns.edit.targets import RENDER_MATCH_MIN
from virgi_ns.errors import InputError, cli_entry

console = Console(width=220)

CONTESTANTS = {
    "csr32": "as csr with int32 indices (half the index traffic)",
    "csr4": "as csr32 with the dense operand padded to 4 columns (16-byte rows)",
    "csr_cm": "as csr32 with the dense operand column-major",
    "segment": "gather x[cols] * vals, then torch.segment_reduce over each row's entries (A^T: by Gaussian)",
    "index_add": "gather x[cols] * vals, then index_add_ by row (atomics; A^T: the same entries, by Gaussian)",
    "embedding_bag": "torch.embedding_bag, mode sum with per-sample weights: gather, weight and sum in one kernel",
}
"""The sparse products measured against the library's kinds (``csr`` may stand for one pass of a pair)."""
LIBRARY = ("csr", "fused", "auto")
SCATTERED = "fused_scattered"
_CSR_KINDS = ("csr", "csr32", "csr4", "csr_cm")


def parse_pair(name: str) -> tuple[str, str]:
    """``'segment'`` -> ``('segment', 'segment')``; ``'embedding_bag/index_add'`` -> the forward and the backward
    kind. Raises ValueError for a kind that is neither a contestant nor ``csr``."""
    parts = str(name).split("/")
    if len(parts) == 1:
        parts = parts * 2
    known = ("csr", *CONTESTANTS)
    if len(parts) != 2 or any(p not in known for p in parts):
        raise ValueError(f"unknown batch_composite kind {name!r}: one of {', '.join((*LIBRARY, SCATTERED, *CONTESTANTS))} "
                         "(or 'FWD/BWD' of csr and the contestants)")
    return parts[0], parts[1]


class _Side(NamedTuple):
    """One ordering of a sparse map's entries, out[target[j]] += vals[j] * x[gather[j]], out [n, k]."""

    n: int
    gather: Tensor  # [nnz] rows of x
    vals: Tensor  # [nnz]
    target: Optional[Tensor] = None  # [nnz] rows of out, sorted (segment, embedding_bag) or any (index_add)
    offsets: Optional[Tensor] = None  # [n+1] where each row of out starts (entries sorted by target)
    csr: Optional[Tensor] = None  # the map as a CSR matrix [n, len(x)]


def _apply(kind: str, side: _Side, x: Tensor) -> Tensor:
    """``out = M @ x`` for the map ``side`` by ``kind`` (no host sync, shapes fixed by ``side``)."""
    if kind in ("csr", "csr32"):
        return side.csr @ x
    if kind == "csr4":
        return (side.csr @ torch.nn.functional.pad(x, (0, 1)))[:, : x.shape[1]]
    if kind == "csr_cm":
        return side.csr @ x.t().contiguous().t()
    if side.gather.numel() == 0:  # no entry: nothing to gather (segment_reduce refuses empty data on some builds)
        return x.new_zeros(side.n, x.shape[1])
    if kind == "embedding_bag":
        return torch.embedding_bag(x, side.gather, side.offsets, False, 0, False, side.vals, True, None)[0]
    terms = x.index_select(0, side.gather) * side.vals[:, None]
    if kind == "segment":
        return torch.segment_reduce(terms, "sum", offsets=side.offsets, unsafe=True)
    return x.new_zeros(side.n, x.shape[1]).index_add_(0, side.target, terms)  # index_add


class _Product(torch.autograd.Function):
    """``A @ C`` by the operator's forward kind; the backward pass ``A^T @ grad`` by its backward kind."""

    @staticmethod
    def forward(ctx, colours: Tensor, op: "ContestantOp") -> Tensor:  # type: ignore[override]
        ctx.op = op
        return _apply(op.fwd, op.forward_side, colours)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        op = ctx.op
        return _apply(op.bwd, op.backward_side, grad.contiguous()), None


class _Transpose:
    """``op.transpose @ g``: the backward pass alone, as a pixel batch's ``render_transpose`` asks it."""

    def __init__(self, op: "ContestantOp") -> None:
        self.op = op

    def __matmul__(self, grad: Tensor) -> Tensor:
        return _apply(self.op.bwd, self.op.backward_side, grad)


class ContestantOp:
    """A pixel set's ``A`` [p, U] applied by the kinds ``kind`` names (:func:`parse_pair`), with every index
    array the two passes need built here, once; it takes the place of the set's :class:`CompositeOp`.
    ``rows``, ``cols``, ``vals``: the entries, sorted by row (pixel)."""

    def __init__(self, kind: str, rows: Tensor, cols: Tensor, vals: Tensor, p: int, U: int) -> None:
        self.kind = kind
        self.fwd, self.bwd = parse_pair(kind)
        nnz = rows.numel()
        small = max(nnz, p, U) < 2**31 - 1
        idx = torch.int64 if "csr" in (self.fwd, self.bwd) or not small else torch.int32
        rows, cols = rows.to(idx), cols.to(idx)
        crow = row_offsets(rows, p, idx)
        if self.fwd == "index_add":
            self.forward_side = _Side(p, cols, vals, target=rows)
        else:
            self.forward_side = _Side(p, cols, vals, rows, crow,
                                      csr_matrix(crow, cols, vals, (p, U)) if self.fwd in _CSR_KINDS else None)
        if self.bwd == "index_add":  # the same entries, the roles of rows and columns swapped
            self.backward_side = _Side(U, rows, vals, target=cols)
        else:  # the entries sorted by Gaussian (pixels ascending within one: rows are sorted already)
            t_order = torch.argsort(cols, stable=True)
            rows_t, cols_t, vals_t = rows[t_order], cols[t_order], vals[t_order]
            ccol = row_offsets(cols_t, U, idx)
            self.backward_side = _Side(U, rows_t, vals_t, cols_t, ccol,
                                       csr_matrix(ccol, rows_t, vals_t, (U, p)) if self.bwd in _CSR_KINDS else None)
        self.transpose = _Transpose(self)

    @staticmethod
    def replacing(kind: str, op: CompositeOp) -> "ContestantOp":
        """The contestant ``kind`` for the entries of a csr operator."""
        m = op.matrix
        crow, cols, vals = m.crow_indices(), m.col_indices(), m.values()
        rows = torch.repeat_interleave(torch.arange(op.shape[0], device=crow.device), crow[1:] - crow[:-1])
        return ContestantOp(kind, rows, cols, vals, *op.shape)

    def __call__(self, colours: Tensor) -> Tensor:
        return _Product.apply(colours, self)


def engine(scene, cams, edited: Tensor, variant: str, steps: Optional[int]) -> EditEngine:
    """A fresh engine on ``edited`` whose steps apply their pixel sets' matrices by ``variant``
    (``KIND[,FIELD=VALUE...]``: the kind, then any other EditConfig settings, parsed as ``bench/edit.py``'s
    ``--variants`` are); a contestant's operators, built in the place of csr's, count in its set-up."""
    kind, _, rest = variant.partition(",")
    settings = edit_settings(rest) if rest else {}
    for key in ("rule", "source"):
        if key in settings:
            raise InputError(f"--variants: EditConfig has no field {key!r}")
    if kind not in LIBRARY and kind != SCATTERED:
        parse_pair(kind)
    library = kind if kind in LIBRARY else ("fused" if kind == SCATTERED else "csr")
    cfg = EditConfig(**{"batch_composite": library, **({} if steps is None else {"steps": steps}), **settings})
    eng = EditEngine(scene, cams, edited, cfg=cfg)
    if kind == SCATTERED:
        eng.batches[0].sets.by_gaussian = None
    elif library != kind:
        dev = scene.device
        sync(dev)
        t0 = time.perf_counter()
        for b in eng.batches:
            b.op = ContestantOp.replacing(kind, b.op)
        sync(dev)
        eng.setup_s += time.perf_counter() - t0
    return eng


@dataclass
class Args:
    out: Path = Path("bench_out/edit_step")
    variants: List[str] = field(default_factory=lambda: [*CONTESTANTS, "fused", SCATTERED])
    """The kinds to measure ('csr' is always measured first: the reference), each optionally with other
    EditConfig settings after a comma (``fused,fused_heads=false``)."""
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
    changed_region: float = 0.0
    """0: the edited image is random (a whole-image fit). Above 0 (below a half, where the engine still reads
    the image as an edited render): it is the view's render with a centred box over this share of its pixels
    recoloured, so the edit fits the changed pixels, as an edited photo's does."""
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


def edited_render(scene, cams, share: float) -> Tensor:
    """The view's render with a centred box over ``share`` of its pixels inverted (``1 - rgb``)."""
    if not 0 < share < RENDER_MATCH_MIN:  # the engine reads an image that matches its render less as a whole-image edit
        raise InputError(f"--changed-region must be in (0, {RENDER_MATCH_MIN:g}), got {share:g}")
    rgb = render_view(scene, cams, 0)["rgb"].clone()
    H, W = rgb.shape[:2]
    h, w = max(1, round(H * share**0.5)), max(1, round(W * share**0.5))
    y, x = (H - h) // 2, (W - w) // 2
    rgb[y : y + h, x : x + w] = 1.0 - rgb[y : y + h, x : x + w]
    return rgb


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
        if args.changed_region > 0:
            self.edited = edited_render(self.scene, self.cams, args.changed_region)
        else:
            g = torch.Generator(device=self.dev).manual_seed(1)
            self.edited = torch.rand(args.height, args.width, 3, generator=g, device=self.dev)
        self.ref: dict = {}
        self.t0 = time.perf_counter()

    def engine(self, variant: str) -> EditEngine:
        with torch.enable_grad():
            return engine(self.scene, self.cams, self.edited, variant, self.args.steps)

    @torch.no_grad()
    def check(self, kind: str, eng: EditEngine) -> dict:
        """The first batch's forward and backward against csr's (set by the csr row); for the fused
        kind, its loss and gradient to the colours against csr's loss and autograd gradient."""
        b = eng.batches[0]
        if not self.ref:  # the csr row: the reference colours, gradient and products
            gen = torch.Generator(device=self.dev).manual_seed(2)
            # off the fit's start, where an unchanged pixel's residual is zero and the sign of its L1
            # gradient is decided by the order of float sums: a shift leaves every covered pixel's sign fixed
            C = eng.colours()[0].detach() + 0.05
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
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                eng = self.engine(kind)
                with torch.enable_grad():
                    _, t = eng.fit()
            notes += [str(w.message).splitlines()[0] for w in caught if "CUDA graphs" in str(w.message)]
            graphed.append(eng.cfg.cuda_graphs)
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
            eng = self.engine(kind)
            b0 = eng.batches[0]
            row["batch_pixels"] = int(b0.target.shape[0])
            row["changed_fraction"] = float(eng.changed_fraction)
            row["batch_entries"] = int(b0.sets.pixel_offsets[b0.pixels + 1].sum() - b0.sets.pixel_offsets[b0.pixels].sum()
                                       if b0.sets is not None else b0.op.forward_side.gather.numel()
                                       if isinstance(b0.op, ContestantOp) else b0.op.matrix.values().numel())
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
                    "image": f"{args.width}x{args.height}", "changed_region": args.changed_region, "tol": args.tol,
                    "rows": rows}
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
                parse_pair(pair)
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
