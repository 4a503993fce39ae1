"""How much of a real-photo figure is the sampler's luck: several runs of ``bench/real.py`` that
differ only in a seed, compared case by case.

Usage: .venv/bin/python bench/seeds.py REPORT.json REPORT.json [...] [--against SEEDS.json] [--tag TAG]
       .venv/bin/python bench/seeds.py --seeds 0,2,4,6 [--shared ../shared/real-partial]
       [--start init.json] [--option KEY=VALUE ...] [--cases N] [--against SEEDS.json] [--tag TAG]

The reports are ``bench/real.py`` runs with ``--option structure_seed=S`` (the anchored
searches' first seed; 0 is the default), one ``--tag`` per seed, all else equal; with
``--seeds`` this script makes them itself, one ``bench/real.py`` run per seed with the options
given (each report and contact sheet written as ``bench/real.py`` names them, the tag followed
by ``_seedS``). The structure's pose leans into one pit of a chamfer floor a few degrees wide,
and which pit depends on the samples (``docs/decisions/0016-averaged-anchors.md``): a change is
better only when it beats this spread (``docs/decisions/0028-seed-spread.md``). Prints per case
the rotation error of each run, its range and mean, and per half (``a``, ``b``, all): the median
of each run, the spread of those medians, the median of the per-case means, and the cases worse
by 2 degrees in each run. ``--against`` an earlier report of this script (another variant over
the same seeds) adds, per half, its median of the per-case means and its count of runs worse by
2 beside this one's. Writes ``bench/results/seeds[_TAG].json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from real import report_name, run_and_write, worse

from common import parse_options, table, write_report

DEFAULT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "real"


def compare(runs: list[dict[str, dict]]) -> tuple[list[dict], list[dict]]:
    """Per half, the figures of several runs of the same cases (each a mapping of case name to
    its ``bench/real.py`` run), printed case by case; and each case's errors, range and mean."""
    cases = sorted(set(runs[0]).intersection(*runs[1:]))
    if not cases:
        raise SystemExit("the reports share no case")
    errors = np.array([[run[c]["final_deg"] for run in runs] for c in cases])
    half = {c: runs[0][c]["half"] for c in cases}
    worsened = np.array([[worse(run[c]) for run in runs] for c in cases])
    per_case = []
    for i, c in enumerate(cases):
        e = errors[i]
        each = " ".join(f"{v:6.2f}" for v in e)
        print(f"{c:30s} {half[c]}  {each}   range {np.ptp(e):5.2f}  mean {e.mean():5.2f}")
        per_case.append({"case": c, "half": half[c], "errors": e.tolist(), "range": float(np.ptp(e)),
                         "mean": float(e.mean())})
    rows = []
    for h in ("a", "b", "all"):
        pick = np.array([h == "all" or half[c] == h for c in cases])
        if not pick.any() or (h == "all" and len(set(half.values())) < 2):
            continue
        medians = np.median(errors[pick], axis=0)
        rows.append({"half": h, "cases": int(pick.sum()), "runs": len(runs),
                     "medians": " ".join(f"{m:.2f}" for m in medians),
                     "spread of medians": float(np.ptp(medians)),
                     "median of means": float(np.median(errors[pick].mean(axis=1))),
                     "median case range": float(np.median(np.ptp(errors[pick], axis=1))),
                     "worse by 2": " ".join(str(int(w)) for w in worsened[pick].sum(axis=0)),
                     "worse by 2 each run": [int(w) for w in worsened[pick].sum(axis=0)]})
    return rows, per_case


def _worse_total(row: dict) -> int:
    """A row's runs worse by 2, summed: from its counts, or (reports written before they were
    kept) from the table's string of them."""
    counts = row.get("worse by 2 each run")
    return sum(counts) if counts is not None else sum(int(w) for w in row["worse by 2"].split())


def against(rows: list[dict], earlier: Path) -> list[dict]:
    """Per half, ``earlier``'s (a report of this script) median of the per-case means and runs
    worse by 2 beside those of ``rows``."""
    before = {r["half"]: r for r in json.loads(earlier.read_text())["rows"]}
    out = []
    for r in rows:
        b = before.get(r["half"])
        if b is None:
            continue
        out.append({"half": r["half"], "median of means before": b["median of means"],
                    "median of means now": r["median of means"],
                    "worse by 2 before": _worse_total(b), "worse by 2 now": _worse_total(r),
                    "case range before": b["median case range"], "case range now": r["median case range"]})
    return out


def run_seeds(seeds: list[int], shared: Path, start: str, pairs: list[str], tag: str,
              cases: int | None = None) -> list[Path]:
    """One ``bench/real.py`` run per seed (the options of ``pairs`` and ``structure_seed``),
    each report and contact sheet written; the reports' paths."""
    if not (shared / "cases").is_dir():
        raise SystemExit(f"no real cases at {shared}")
    if any(p.partition("=")[0] == "structure_seed" for p in pairs):
        raise SystemExit("--seeds sets structure_seed itself")
    paths = []
    for seed in seeds:
        options = parse_options([*pairs, f"structure_seed={seed}"])
        name = report_name(shared, start, f"{tag}_seed{seed}" if tag else f"seed{seed}")
        paths.append(run_and_write(name, shared, start, options, cases))
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", type=Path, nargs="*", help="bench/real.py reports of the same cases")
    ap.add_argument("--seeds", default=None, metavar="S,S,...", help="run bench/real.py once per seed first")
    ap.add_argument("--shared", type=Path, default=DEFAULT_SHARED, help="with --seeds: the cases")
    ap.add_argument("--start", default="init.json", help="with --seeds: the start file (as bench/real.py)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="with --seeds: a RegistrationOptions field (repeatable)")
    ap.add_argument("--cases", type=int, default=None, help="with --seeds: only the first N cases")
    ap.add_argument("--against", type=Path, default=None, metavar="SEEDS.json",
                    help="an earlier report of this script to compare with")
    ap.add_argument("--tag", default="", help="suffix of the report's name")
    args = ap.parse_args()
    paths = list(args.reports)
    if args.seeds is not None:
        seeds = [int(s) for s in args.seeds.split(",")]
        paths += run_seeds(seeds, args.shared, args.start, args.option, args.tag, args.cases)
    if len(paths) < 2:
        raise SystemExit("give at least two reports, or two seeds")
    rows, per_case = compare([{r["case"]: r for r in json.loads(p.read_text())["runs"]} for p in paths])
    print(table(rows, [k for k in rows[0] if k != "worse by 2 each run"]))
    report = {"reports": [str(p) for p in paths], "rows": rows, "cases": per_case}
    if args.against is not None:
        report["against"] = str(args.against)
        beside = against(rows, args.against)
        if beside:
            print(table(beside, list(beside[0])))
    name = "seeds" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, report))


if __name__ == "__main__":
    main()
