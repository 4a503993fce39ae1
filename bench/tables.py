"""The current tables of docs/benchmarks.md, printed in Markdown from the reports of one tag.

Usage: .venv/bin/python bench/tables.py --tag TAG [--results DIR]

Reads the reports that ``bench/real.py``, ``bench/accuracy.py --part photoreal`` and
``bench/nohint.py`` wrote with ``--tag TAG`` (``bench/results/<set>_<start>[_nobox][_mirror]_TAG.json``
and the like) and prints the tables of the page's sections "Real photos: every mode, both
halves", "Real photos in a mirror", "Photoreal cases" and "Registration without a hint", each
under the commit and date its reports name. A report not found is named and its row left out,
so the page is refreshed from runs, not copied by hand. The runs that make a full set:

    bench/real.py --start none|box|init.json [--no-box] [--shared ../shared/real-partial] [--mirror] --tag TAG
    bench/real.py --start init.json --stretch 1.06,1.0,0.95 --tag TAG
    bench/accuracy.py --part photoreal [--shared ../shared/bench-partial] [--start init_hard.json|box]
        [--no-box] --tag TAG
    bench/nohint.py --part photoreal|synthetic [--shared ../shared/bench-partial] --tag TAG
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

REAL_MODES = (
    # (label, report without the set's prefix and the tag, a start camera)
    ("no hint", "none", False),
    ("box alone", "box", False),
    ("start camera alone", "init_nobox", True),
    ("camera + box", "init", True),
)


def load(folder: Path, name: str, missing: list[str]) -> dict | None:
    path = folder / f"{name}.json"
    if not path.exists():
        missing.append(name)
        return None
    data: dict = json.loads(path.read_text())
    return data


def halves(report: dict) -> dict[str, dict]:
    return {row["half"]: row for row in report["rows"]}


def percent(value: float) -> str:
    """A share to a tenth of a per cent, without a trailing zero (``100 %``, ``91.7 %``)."""
    return f"{value:.1f}".rstrip("0").rstrip(".") + " %"


def real_cell(row: dict, started: bool) -> str:
    """Acc pi/6 (without a start camera), the median rotation error and, in brackets, the
    median viewpoint error."""
    errors = f"{row['median deg']:.2f} ({row['median viewpoint deg']:.2f})"
    return errors if started else f"{percent(row['acc pi/6 %'])}, {errors}"


def source(reports: list[dict]) -> str:
    """The commits the reports were made at, each with the span of their dates."""
    dates: dict[str, list[str]] = {}
    for r in reports:
        dates.setdefault(str(r.get("commit", "?")), []).append(str(r.get("date", "?")))
    spans = [f"{c} ({min(d)}{' to ' + max(d) if max(d) != min(d) else ''})" for c, d in sorted(dates.items())]
    return "Reports of " + "; ".join(spans) + "."


def real_table(folder: Path, tag: str, missing: list[str]) -> str:
    lines = ["| mode | half a | half b | all | worse by 2 | wrong unflagged | right flagged | median s |",
             "|---|---|---|---|---|---|---|---|"]
    used = []
    rows = [(label + partial, kind, started, shared)
            for label, kind, started in REAL_MODES for partial, shared in (("", "real"), (", partial", "real-partial"))]
    rows.append(("camera + box, the model stretched", "init_stretched", True, "real"))
    for label, kind, started, shared in rows:
        report = load(folder, f"{shared}_{kind}_{tag}", missing)
        if report is None:
            continue
        if report.get("stretch"):
            label += f" (`--stretch {','.join(f'{v:g}' for v in report['stretch'])}`)"
        used.append(report)
        h = halves(report)
        every = h["all"]
        lines.append(f"| {label} | {real_cell(h['a'], started)} | {real_cell(h['b'], started)} | "
                     f"{real_cell(every, started)} | {every['worse by 2'] if started else ''} | "
                     f"{every['wrong unflagged']} | {every['right flagged']} | {every['median s']:.1f} |")
    return "\n".join([source(used), "", *lines]) if used else ""


def mirror_cell(row_a: dict, row_b: dict, every: dict, started: bool) -> str:
    if started:
        return (f"a {row_a['median deg']:.2f} / b {row_b['median deg']:.2f} / all {every['median deg']:.2f}; "
                f"{every['worse by 2']} worse by 2, {every['flagged']} flagged")
    return (f"a {percent(row_a['acc pi/6 %'])} {row_a['median deg']:.3g} / b {percent(row_b['acc pi/6 %'])} "
            f"{row_b['median deg']:.3g} / all {percent(every['acc pi/6 %'])}, {every['median deg']:.3g}; "
            f"{every['wrong unflagged']} wrong unflagged, {every['right flagged']} right flagged")


def mirror_table(folder: Path, tag: str, missing: list[str]) -> str:
    lines = ["| mode | original photos | mirrored |", "|---|---|---|"]
    used = []
    for label, kind, started in REAL_MODES:
        for partial, shared in (("", "real"), (", partial", "real-partial")):
            original = load(folder, f"{shared}_{kind}_{tag}", missing)
            mirrored = load(folder, f"{shared}_{kind}_mirror_{tag}", missing)
            if original is None or mirrored is None:
                continue
            used += [original, mirrored]
            cells = []
            for report in (original, mirrored):
                h = halves(report)
                cells.append(mirror_cell(h["a"], h["b"], h["all"], started))
            lines.append(f"| {label}{partial} | {cells[0]} | {cells[1]} |")
    return "\n".join([source(used), "", *lines]) if used else ""


def model_table(report: dict, flags: bool) -> str:
    if flags:
        head = ["| model | cases | success | median error | flagged | precision | recall | median s |",
                "|---|---|---|---|---|---|---|---|"]
    else:
        head = ["| model | cases | success | median error | median s | median evaluations |",
                "|---|---|---|---|---|---|"]

    def share(v: float) -> str:
        return "-" if v != v else f"{v:.0f} %"

    lines = []
    for row in report["rows"]:
        name = row["model"] if row["model"] != "all" else "**all**"
        common = f"| {name} | {row['cases']} | {row['success %']:.0f} % | {row['median err px']:.3g} px |"
        if flags:
            lines.append(f"{common} {row['flagged']} | {share(row['flag precision %'])} | "
                         f"{share(row['flag recall %'])} | {row['median s']:.1f} |")
        else:
            lines.append(f"{common} {row['median s']:.1f} | {row['median evals']:.0f} |")
    return "\n".join(head + lines)


def render_tables(folder: Path, tag: str, missing: list[str]) -> str:
    out = []
    real = real_table(folder, tag, missing)
    if real:
        out += ["## Real photos: every mode, both halves", "", real, ""]
    mirror = mirror_table(folder, tag, missing)
    if mirror:
        out += ["## Real photos in a mirror", "", mirror, ""]
    sets = (("photoreal", "from `init.json`"), ("bench-partial", "cut by the frame, from `init.json`"),
            ("photoreal_hard", "from `init_hard.json`"), ("photoreal_nobox", "a start camera alone"),
            ("photoreal_box", "a box alone"), ("bench-partial_nobox", "cut by the frame, a start camera alone"),
            ("bench-partial_box", "cut by the frame, a box alone"))
    for name, what in sets:
        report = load(folder, f"accuracy_{name}_{tag}", missing)
        if report is not None:
            out += [f"### Photoreal, {what} (`accuracy_{name}_{tag}`)", "", source([report]), "",
                    model_table(report, flags=False), ""]
    for name, what in (("photoreal", "photoreal"), ("bench-partial", "photoreal cut by the frame"),
                       ("synthetic", "synthetic")):
        report = load(folder, f"nohint_{name}_{tag}", missing)
        if report is not None:
            out += [f"### No hint, {what} (`nohint_{name}_{tag}`)", "", source([report]), "",
                    model_table(report, flags=True), ""]
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tag", required=True)
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    missing: list[str] = []
    print(render_tables(args.results, args.tag, missing))
    if missing:
        print("not found (rows left out): " + ", ".join(sorted(set(missing))))


if __name__ == "__main__":
    main()
