"""One fit against the best of several: from ``bench/edit.py --edit-seeds N`` results, what a user
would get from one fit (seed 0, the product today) and from N fits with the one a figure of its own
ranks best kept (``--by``: its last step's loss, its loss on every pixel set, or its PSNR against the
edited image on the changed pixels), per row and variant, judged by the set's targets. No GPU, no
training: it reads the ``per_seed`` records (each fit's held-out figures and what it knows of itself).

    python bench/best_of.py --results runs17.json runs18.json --out bench_out/best_of

Prints one table (per row: seed 0's propagation, the best of N's, the difference, the targets each
meets) and the totals, and writes ``best_of.json``. The best of N's edit time is counted as N times
the row's warm edit (the fits run one after another)."""

from __future__ import annotations

import json
import math
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import tyro
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))

from edit import read_result, targets  # noqa: E402  (bench/edit.py: its results and the set's targets)

from virgi_ns.errors import InputError, atomic_path, cli_entry  # noqa: E402

console = Console(width=200)


@dataclass
class Args:
    results: List[Path] = field(default_factory=list)
    """results.json files of bench/edit.py runs made with --edit-seeds N (N >= 2)."""
    out: Path = Path("bench_out/best_of")
    by: str = "final_l1"
    """The fit's own figure that ranks the fits: one of :data:`SELECTORS`."""


SELECTORS = {"final_l1": min, "fit_l1": min, "edit_fit_changed_psnr": max}
"""Each figure a fit knows about itself (``per_seed``'s keys), and whether its lowest or highest is best."""


def chosen_fits(per_seed: List[dict], by: str = "final_l1") -> tuple[dict, dict, int]:
    """(the first fit's figures, the figures of the fit that ``by`` ranks best, its index). A fit
    whose figure is not finite (a diverged fit) ranks last."""
    if any(by not in r for r in per_seed):
        raise InputError(f"--by {by}: not recorded for every fit of these results (bench/edit.py records it "
                         "since it was added)")
    pick = SELECTORS[by]
    worst = math.inf if pick is min else -math.inf
    best = pick(range(len(per_seed)), key=lambda i: per_seed[i][by] if math.isfinite(per_seed[i][by]) else worst)
    return per_seed[0], per_seed[best], best


NEEDED = ("propagation_psnr", "miss_psnr", "leak_psnr", "recolour_psnr", "unedited_psnr")
"""The figures every fit must have to be judged (a synthetic row's also ``truth_psnr``)."""


def lacking(figures: List[dict], synthetic: bool) -> List[str]:
    """The figures the targets judge (:data:`NEEDED`, and ``truth_psnr`` where ``synthetic``) that any
    of ``figures`` (fits, or a row) lacks, sorted."""
    needed = NEEDED + (("truth_psnr",) if synthetic else ())
    return sorted({k for f in figures for k in needed if not isinstance(f.get(k), (int, float))})


def no_fits(path: Path, row: dict) -> InputError:
    """The error for a row that has too few single fits (``per_seed``) to be judged."""
    return InputError(f"{path}: row {row['scene']} ({row['variant']}) has no per-seed fits "
                      "(run bench/edit.py with --edit-seeds 2 or more)")


def row_summary(row: dict, by: str = "final_l1") -> dict:
    """One row (scene and variant): the first fit and the best of its fits, each with its targets."""
    per_seed = row["per_seed"]
    synthetic = bool(row["synthetic"])
    missing = lacking(per_seed, synthetic)
    if missing:
        raise InputError(f"row {row['scene']} ({row['variant']}): its fits lack {', '.join(missing)}")
    first, best, index = chosen_fits(per_seed, by)
    n = len(per_seed)
    edit_s = row["timing_warm"]["total_s"]
    return {"scene": row["scene"], "seed": row["seed"], "variant": row["variant"], "rule": row.get("rule"),
            "fits": n, "best_index": index,
            "first": {**first, "targets": targets(first, edit_s, synthetic)},
            "best": {**best, "targets": targets(best, n * edit_s, synthetic)},
            "difference_db": best["propagation_psnr"] - first["propagation_psnr"]}


def rows_of(paths: List[Path], by: str = "final_l1") -> List[dict]:
    """Every row of the results, each marked with the file it came from (``source``)."""
    out = []
    for source, p in enumerate(paths):
        for row in read_result(p, "--results")["scenes"]:
            if len(row.get("per_seed", [])) < 2:
                raise no_fits(p, row)
            out.append({**row_summary(row, by), "source": source})
    return out


def against_defaults(rows: List[dict]) -> None:
    """Each variant row's first fit against the engine defaults' first fit on the same run and scene of
    the same results file, where both fitted the same rule (``first_vs_defaults_db``: propagation, dB),
    in place. Two default rows of one run and scene in one file are refused."""
    defaults: dict = {}
    for r in rows:
        if r["variant"] == "engine defaults":
            key = (r.get("source", 0), r["scene"], r["seed"])
            if key in defaults:
                raise InputError(f"two default rows of {r['scene']} on run seed {r['seed']} in one results file")
            defaults[key] = r
    for r in rows:
        d = defaults.get((r.get("source", 0), r["scene"], r["seed"]))
        if r["variant"] != "engine defaults" and d is not None and r.get("rule") == d.get("rule"):
            r["first_vs_defaults_db"] = r["first"]["propagation_psnr"] - d["first"]["propagation_psnr"]


def totals(rows: List[dict]) -> dict:
    """Per variant and run set (training seed): rows meeting every target, first fit and best of N;
    over all of a variant's rows: the differences' median, mean and worst (best of N against the first
    fit; for a variant also its first fit against the defaults' first fit)."""
    against_defaults(rows)
    out: dict = {}
    for r in rows:
        v = out.setdefault(r["variant"], {"per_run_set": {}, "differences": []})
        s = v["per_run_set"].setdefault(str(r["seed"]), {"rows": 0, "first_passed": 0, "best_passed": 0})
        s["rows"] += 1
        s["first_passed"] += all(r["first"]["targets"].values())
        s["best_passed"] += all(r["best"]["targets"].values())
        v["differences"].append(r["difference_db"])
        if "first_vs_defaults_db" in r:
            v.setdefault("against_defaults", []).append(r["first_vs_defaults_db"])
    for v in out.values():
        d = v.pop("differences")
        v.update(median_difference_db=statistics.median(d), mean_difference_db=statistics.fmean(d),
                 worst_difference_db=min(d), rows=len(d))
        if "against_defaults" in v:
            a = v.pop("against_defaults")
            v.update(first_vs_defaults_mean_db=statistics.fmean(a), first_vs_defaults_worst_db=min(a))
    return out


def _pass(t: dict) -> str:
    missed = [k for k, ok in t.items() if not ok]
    return "PASS" if not missed else "FAIL: " + ", ".join(k.split(" ")[0] for k in missed)


def print_table(rows: List[dict], tot: dict, by: str) -> None:
    t = Table(title=f"one fit (the row's first seed) against the best of its fits by their own {by}")
    for c in ("scene", "seed", "variant", "first: prop / miss / truth", "first", "best: which, prop / miss / truth",
              "best", "difference"):
        t.add_column(c)
    f = lambda x: "-" if x is None or math.isnan(x) else f"{x:.2f}"  # noqa: E731
    for r in rows:
        a, b = r["first"], r["best"]
        t.add_row(r["scene"], str(r["seed"]), r["variant"],
                  f"{f(a['propagation_psnr'])} / {f(a['miss_psnr'])} / {f(a.get('truth_psnr', math.nan))}",
                  _pass(a["targets"]),
                  f"{r['best_index']}: {f(b['propagation_psnr'])} / {f(b['miss_psnr'])} / "
                  f"{f(b.get('truth_psnr', math.nan))}", _pass(b["targets"]), f"{r['difference_db']:+.2f}")
    console.print(t)
    for name, v in tot.items():
        sets = ", ".join(f"run set seed {k}: {s['first_passed']} -> {s['best_passed']} of {s['rows']}"
                         for k, s in v["per_run_set"].items())
        vs = (f"; its first fit against the defaults' first fit: mean {v['first_vs_defaults_mean_db']:+.2f}, "
              f"worst {v['first_vs_defaults_worst_db']:+.2f} dB" if "first_vs_defaults_mean_db" in v else "")
        console.print(f"{name}: rows meeting every target, one fit -> best of N: {sets}; difference over "
                      f"{v['rows']} rows: median {v['median_difference_db']:+.2f}, mean "
                      f"{v['mean_difference_db']:+.2f}, worst {v['worst_difference_db']:+.2f} dB{vs}")


def main(args: Args) -> None:
    if not args.results:
        raise InputError("--results: name at least one results.json of bench/edit.py --edit-seeds N")
    if args.by not in SELECTORS:
        raise InputError(f"--by: one of {', '.join(SELECTORS)}, got {args.by!r}")
    rows = rows_of(args.results, args.by)
    tot = totals(rows)
    print_table(rows, tot, args.by)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "best_of.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"sources": [str(p) for p in args.results], "by": args.by, "rows": rows,
                                   "totals": tot}, indent=1))
    console.print(f"wrote {path}")


def entry() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entry()
