"""Each variant against the engine defaults, on the rows' own figures (with ``--edit-seeds N`` those
are the medians of N fits), over one or more run sets, judged by the rule written before run sets
23 and 24 (bench/RESULTS.md, "Edit"). No GPU, no training: it reads ``bench/edit.py`` results.

    python bench/against_defaults.py --results runset23.json runset24.json --out bench_out/against_defaults

A variant becomes a candidate default when, having a row on every run set and scene the defaults have:

1. on each run set it meets every target on at least as many rows as the defaults;
2. over the run sets, at least :data:`MARGIN` more of its single fits (``per_seed``: what one user
   gets) meet every target than the defaults' fits do;
3. no scene whose defaults row meets every target on every run set fails a target with the variant
   on any of them.

(The edit time at 1M Gaussians, the rule's fourth condition, is measured apart by ``bench/edit_step.py``.)
Prints one table (per scene and run set: each variant's propagation difference and the targets it
misses) and the verdicts, and writes ``against_defaults.json``."""

from __future__ import annotations

import json
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List

import tyro
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))

from best_of import lacking, no_fits  # noqa: E402  (bench/best_of.py: the figures the targets judge)
from edit import read_result, targets  # noqa: E402  (bench/edit.py: its results and the set's targets)

from virgi_ns.errors import InputError, atomic_path, cli_entry  # noqa: E402

console = Console(width=200)
DEFAULTS = "engine defaults"
MARGIN = 3
"""Single fits meeting every target that a variant must gain: a refit of the defaults with nothing
changed moved that count by -1 and +2 on two run sets (bench/RESULTS.md), so a gain must exceed 2."""


@dataclass
class Args:
    results: List[Path] = field(default_factory=list)
    """results.json files of bench/edit.py (merged per run set, or not), each with a defaults row per scene."""
    out: Path = Path("bench_out/against_defaults")


def _judged(figures: dict, row: dict) -> dict:
    """Today's targets of a row's figures (its own or one fit's), with the row's warm edit time."""
    return targets(figures, row["timing_warm"]["total_s"], row["synthetic"])


def missed(row: dict) -> List[str]:
    """The targets a row's own figures (the medians of its fits) miss."""
    return [k for k, ok in _judged(row, row).items() if not ok]


def fits_passed(row: dict) -> int:
    """How many of the row's single fits (``per_seed``) meet every target."""
    return sum(all(_judged(f, row).values()) for f in row["per_seed"])


def check_fits(row: dict, path: Path) -> None:
    """Refuse a row whose single fits are missing or lack a figure the targets judge."""
    fits = row.get("per_seed") or []
    if not fits:
        raise no_fits(path, row)
    missing = lacking([row, *fits], bool(row["synthetic"]))
    if missing:
        raise InputError(f"{path}: row {row['scene']} ({row['variant']}) lacks {', '.join(missing)}")


def rows_by_run(paths: List[Path]) -> Dict[tuple, Dict[str, dict]]:
    """{(run set seed, scene): {variant: row}} over every file. A run set and scene seen twice for one
    variant is refused: two files of the same run set would count it twice."""
    out: Dict[tuple, Dict[str, dict]] = {}
    for p in paths:
        for row in read_result(p, "--results")["scenes"]:
            check_fits(row, p)
            key = (row["seed"], row["scene"])
            variants = out.setdefault(key, {})
            if row["variant"] in variants:
                raise InputError(f"{p}: {row['scene']} on run set {row['seed']} ({row['variant']}) is there twice")
            variants[row["variant"]] = row
    return out


def judge(by_run: Dict[tuple, Dict[str, dict]]) -> dict:
    """Per variant: rows meeting every target per run set (its own and the defaults'), the propagation
    differences, the stable passes it breaks, and the verdict of conditions 1-3."""
    seeds = sorted({s for s, _ in by_run})
    missing = sorted(f"{scene} (run set {s})" for (s, scene), v in by_run.items() if DEFAULTS not in v)
    if missing:
        raise InputError(f"no defaults row for {', '.join(missing)}")
    scenes = sorted({scene for _, scene in by_run})
    stable = [sc for sc in scenes if all((s, sc) in by_run and not missed(by_run[(s, sc)][DEFAULTS]) for s in seeds)]
    names = sorted({v for variants in by_run.values() for v in variants} - {DEFAULTS})
    out = {}
    for name in names:
        per_set, diffs, broken = {}, [], []
        for (s, sc), variants in sorted(by_run.items()):
            if name not in variants:
                continue
            row, base = variants[name], variants[DEFAULTS]
            t = per_set.setdefault(str(s), {"rows": 0, "passed": 0, "defaults_passed": 0, "fits_passed": 0,
                                            "defaults_fits_passed": 0})
            t["rows"] += 1
            t["passed"] += not missed(row)
            t["defaults_passed"] += not missed(base)
            t["fits_passed"] += fits_passed(row)
            t["defaults_fits_passed"] += fits_passed(base)
            diffs.append(row["propagation_psnr"] - base["propagation_psnr"])
            if sc in stable and missed(row):
                broken.append(f"{sc} (run set {s}: {', '.join(missed(row))})")
        fits = sum(t["fits_passed"] for t in per_set.values())
        base_fits = sum(t["defaults_fits_passed"] for t in per_set.values())
        mean = statistics.fmean(diffs) if diffs else float("nan")
        conditions = {
            "0: a row on every run set and scene": len(diffs) == len(by_run),
            "1: as many rows on each run set": all(t["passed"] >= t["defaults_passed"] for t in per_set.values()),
            f"2: at least {MARGIN} more single fits": fits >= base_fits + MARGIN,
            "3: no stable pass broken": not broken,
        }
        out[name] = {"per_run_set": per_set, "fits_passed": fits, "defaults_fits_passed": base_fits,
                     "mean_difference_db": mean, "worst_difference_db": min(diffs) if diffs else float("nan"),
                     "rows": len(diffs), "broken": broken, "conditions": conditions,
                     "candidate": all(conditions.values())}
    return {"run_sets": seeds, "stable_scenes": stable, "variants": out}


def print_tables(by_run: Dict[tuple, Dict[str, dict]], verdicts: dict) -> None:
    names = list(verdicts["variants"])
    t = Table(title="each variant against the engine defaults (the rows' figures: medians where several fits)")
    for c in ["scene", "run set", "defaults: prop / misses"] + names:
        t.add_column(c)
    for (s, sc), variants in sorted(by_run.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        base = variants[DEFAULTS]
        cells = [f"{base['propagation_psnr']:.2f} / {', '.join(missed(base)) or 'PASS'}"]
        for n in names:
            row = variants.get(n)
            cells.append("-" if row is None else
                         f"{row['propagation_psnr'] - base['propagation_psnr']:+.2f} / {', '.join(missed(row)) or 'PASS'}")
        t.add_row(sc, str(s), *cells)
    console.print(t)
    for n, v in verdicts["variants"].items():
        sets = ", ".join(f"run set {k}: {x['passed']} (defaults {x['defaults_passed']}) of {x['rows']}"
                         for k, x in v["per_run_set"].items())
        failed = [k for k, ok in v["conditions"].items() if not ok]
        console.print(f"{n}: rows meeting every target: {sets}; single fits meeting every target: "
                      f"{v['fits_passed']} (defaults {v['defaults_fits_passed']}); propagation difference mean "
                      f"{v['mean_difference_db']:+.2f}, worst {v['worst_difference_db']:+.2f} dB; "
                      + ("CANDIDATE (conditions 1-3 met)" if v["candidate"] else f"not a candidate: {'; '.join(failed)}")
                      + (f"; stable passes broken: {'; '.join(v['broken'])}" if v["broken"] else ""))


def main(args: Args) -> None:
    if not args.results:
        raise InputError("--results: name at least one results.json of bench/edit.py")
    by_run = rows_by_run(args.results)
    verdicts = judge(by_run)
    print_tables(by_run, verdicts)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "against_defaults.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"sources": [str(p) for p in args.results], **verdicts}, indent=1))
    console.print(f"wrote {path}")


def entry() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entry()
