"""How much of a real-photo figure is the sampler's luck: several runs of ``bench/real.py`` that
differ only in a seed, compared case by case.

Usage: .venv/bin/python bench/seeds.py REPORT.json REPORT.json [...] [--tag TAG]

Make the reports with ``bench/real.py`` and ``--option structure_seed=S`` (the anchored
searches' first seed; 0 is the default), one ``--tag`` per seed, all else equal. The
structure's pose leans into one pit of a chamfer floor a few degrees wide, and which pit
depends on the samples (``docs/decisions/0016-averaged-anchors.md``): a change is better only
when it beats this spread. Prints per case the rotation error of each run, its range and mean,
and per half (``a``, ``b``, all): the median of each run, the spread of those medians, the
median of the per-case means, and the cases worse by 2 degrees in each run. Writes
``bench/results/seeds[_TAG].json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from real import worse

from common import table, write_report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", type=Path, nargs="+", help="bench/real.py reports of the same cases")
    ap.add_argument("--tag", default="", help="suffix of the report's name")
    args = ap.parse_args()
    if len(args.reports) < 2:
        raise SystemExit("give at least two reports")
    runs = [{r["case"]: r for r in json.loads(p.read_text())["runs"]} for p in args.reports]
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
                     "worse by 2": " ".join(str(int(w)) for w in worsened[pick].sum(axis=0))})
    print(table(rows, list(rows[0])))
    name = "seeds" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"reports": [str(p) for p in args.reports], "rows": rows, "cases": per_case}))


if __name__ == "__main__":
    main()
