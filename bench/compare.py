"""Two runs of a benchmark, case by case: what a change moved, half by half, and whether more than chance.

Usage: .venv/bin/python bench/compare.py BEFORE.json AFTER.json [AFTER.json ...] [--viewpoint] [--tag TAG]

Each argument is a report that ``bench/real.py``, ``bench/accuracy.py`` or ``bench/nohint.py``
wrote (a path, or a name in bench/results without ``.json``); every later report is compared
with the first, on the cases both hold. A real-photo report is compared per half of
``split.json`` (``a``, ``b``) and over all: the median error, Acc pi/6, the flags and the
wrong poses left unflagged, before and after; then the cases that moved by more than
``--moved`` degrees either way (errors counted up to 30 degrees: beyond it a pose is wrong,
however far), and a two-sided sign test over them (the chance that a change that moves the
cases either way at random would split them as unevenly or more). With twelve photos a half a
median moves by half a degree under a null change (docs/decisions/0056-the-edges-pose-sits-high.md),
so the moved cases and the sign test say more than the median's step. A photoreal report is
compared the same way in pixels (success within 5 px, errors counted up to 50 px). Then every
case that moved or changed its flag is listed. ``--viewpoint`` compares real-photo reports on
their viewpoint errors instead (``viewpoint_deg``: each camera turned to look at the model's
centre, docs/decisions/0059-the-viewpoint-and-the-principal-point.md). Writes bench/results/compare[_TAG].json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from common import RESULTS, table, write_report

CAP = {"deg": 30.0, "px": 50.0}
"""Errors are counted up to this: beyond it a pose is wrong, however far."""

RIGHT = {"deg": 30.0, "px": 5.0}
"""A pose within this is right: Acc pi/6 for the real photos, success for the renders."""


def load(name: str) -> dict:
    """The report at ``name``: a path, or a name in bench/results without ``.json``."""
    path = Path(name)
    if not path.exists():
        path = RESULTS / f"{name}.json"
    report: dict = json.loads(path.read_text())
    report["path"] = str(path)
    return report


def unit(report: dict) -> str:
    """``deg`` for a real-photo report (rotation error), ``px`` for a photoreal one."""
    run = report["runs"][0]
    return "deg" if "final_deg" in run else "px"


def error(run: dict, kind: str, field: str = "final_deg") -> float:
    return float(run[field] if kind == "deg" else run["error_px"])


def compare(before: dict, after: dict, moved: float, viewpoint: bool = False) -> tuple[list[dict], list[dict]]:
    """The summary rows (per half and over all) and the cases that moved or changed their flag;
    with ``viewpoint``, on the real photos' viewpoint errors."""
    kind = unit(before)
    if unit(after) != kind:
        raise SystemExit(f"{after['path']} and {before['path']} are reports of different benchmarks")
    field = "final_deg"
    if viewpoint:
        if kind != "deg":
            raise SystemExit("--viewpoint compares real-photo reports only")
        for report in (before, after):
            if "viewpoint_deg" not in report["runs"][0]:
                raise SystemExit(f"{report['path']} has no viewpoint errors (bench/real.py reports them since "
                                 "abaed67)")
        field = "viewpoint_deg"
    old = {r["case"]: r for r in before["runs"]}
    pairs = [(old[r["case"]], r) for r in after["runs"] if r["case"] in old]
    if not pairs:
        raise SystemExit(f"{after['path']} holds none of {before['path']}'s cases")
    half = np.array([b.get("half", "") for b, _ in pairs])
    e0 = np.array([error(b, kind, field) for b, _ in pairs])
    e1 = np.array([error(a, kind, field) for _, a in pairs])
    f0 = np.array([bool(b["failed"]) for b, _ in pairs])
    f1 = np.array([bool(a["failed"]) for _, a in pairs])
    step = np.minimum(e1, CAP[kind]) - np.minimum(e0, CAP[kind])
    right = RIGHT[kind]
    rows = []
    for name in [*sorted(set(half.tolist()) - {""}), "all"]:
        sel = np.ones(len(pairs), bool) if name == "all" else half == name
        better, worse = int((step[sel] < -moved).sum()), int((step[sel] > moved).sum())
        rows.append({"half": name, "cases": int(sel.sum()),
                     f"median {kind} before": float(np.median(e0[sel])),
                     f"median {kind} after": float(np.median(e1[sel])),
                     "right % before": 100.0 * float(np.mean(e0[sel] <= right)),
                     "right % after": 100.0 * float(np.mean(e1[sel] <= right)),
                     "flagged before": int(f0[sel].sum()), "flagged after": int(f1[sel].sum()),
                     "wrong unflagged before": int(((e0 > right) & ~f0)[sel].sum()),
                     "wrong unflagged after": int(((e1 > right) & ~f1)[sel].sum()),
                     "better": better, "worse": worse,
                     "mean step": float(step[sel].mean()),
                     "sign test p": binomtest(better, better + worse).pvalue if better + worse else 1.0})
    changed = [{"case": a["case"], "half": a.get("half", ""), f"{kind} before": float(e0[i]),
                f"{kind} after": float(e1[i]), "flag before": "flagged" if f0[i] else "",
                "flag after": "flagged" if f1[i] else ""}
               for i, (_, a) in enumerate(pairs) if abs(step[i]) > moved or f0[i] != f1[i]]
    return rows, changed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("reports", nargs="+", help="the report compared with (first), then the reports compared")
    ap.add_argument("--moved", type=float, default=None,
                    help="how far a case must move to count (default 0.5 deg, or 0.05 px on the renders)")
    ap.add_argument("--viewpoint", action="store_true",
                    help="real photos: compare the viewpoint errors (docs/decisions/0059) instead of the rotations'")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    if len(args.reports) < 2:
        ap.error("give the report to compare with and at least one report to compare")
    before = load(args.reports[0])
    moved = args.moved if args.moved is not None else (0.5 if unit(before) == "deg" else 0.05)
    out = []
    for name in args.reports[1:]:
        after = load(name)
        rows, changed = compare(before, after, moved, args.viewpoint)
        on = ", viewpoints" if args.viewpoint else ""
        print(f"\n{after['path']} against {before['path']} (moved: more than {moved:g}{on})")
        print(table(rows, list(rows[0])))
        if changed:
            print(table(changed, list(changed[0])))
        out.append({"before": before["path"], "after": after["path"], "rows": rows, "changed": changed})
    name = "compare" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"moved": moved, "viewpoint": args.viewpoint, "comparisons": out}))


if __name__ == "__main__":
    main()
