"""Where a registration's seconds go, per mode: the engine's stages, its renders and the rest.

Usage: .venv/bin/python bench/stages.py [--cases N] [--modes hinted-photoreal,hinted-real,...]
       [--real ../shared/real] [--photoreal ../shared/bench] [--option KEY=VALUE ...] [--tag T]

Modes: ``hinted-photoreal`` (start camera and box from each case's ``init.json``),
``hinted-real`` (the same on the real photos), ``camera-photoreal`` and ``camera-real`` (the start
camera alone, without the box), ``none-real`` and ``none-photoreal`` (no hint).
``--cases N`` takes N cases of each set, spread evenly (0: every case). For every
registration: the engine's seconds, its evaluations, the stages the result times (the shading
fit, the structure's and the view-sphere's searches, the part map), and what the engine's clock
(:mod:`vehicle_pose.clock`) charges to each kind of work: the searches' renders split into
drawing (the context finished) and read-back, the shading losses, the chamfers, template
matching, GrabCut and the photo's edges; "rest" is what is left (camera arithmetic, the
optimisers, bookkeeping and Python). The model's preparation (levels of detail, outlines,
part labels and templates, made from the mesh file) is timed apart, once per model. Prints one
table (the medians per mode) and writes bench/results/stages[_TAG].json. While the clock runs the renderer
finishes the context before each read-back, which takes away the overlap of drawing and
reading: the engine seconds here are a little above a plain run's.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from real import load_models

from vehicle_pose.clock import clocked
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.photo import load_photo
from vehicle_pose.registration.register import register
from vehicle_pose.render.renderer import Renderer

from common import parse_options, photoreal_cases, table, write_report

SHARED = Path(__file__).resolve().parents[2] / "shared"
MODES = ("hinted-photoreal", "hinted-real", "camera-photoreal", "camera-real", "none-real", "none-photoreal")
STAGES = ("shading", "structure", "sphere", "photo_search", "parts")
KINDS = ("draw", "read", "loss", "chamfer", "matching", "grabcut", "photo edges")


def spread(items: list, n: int) -> list:
    """``n`` of ``items`` spread evenly (all for 0 or n >= len)."""
    if n <= 0 or n >= len(items):
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


_LOADED: dict[Path, list[tuple[Path, VehicleModel]]] = {}


def _folders(real: Path, photoreal: Path, of_real: bool) -> list[tuple[Path, VehicleModel]]:
    """Each case folder of a set with its model, the models loaded once for every mode: a model
    loaded again would be prepared again inside its first registration, outside the preparation
    timed apart."""
    shared = real if of_real else photoreal
    if shared not in _LOADED:
        if of_real:
            model = next(iter(load_models(real).values()))
            _LOADED[shared] = [(case, model) for case in sorted((real / "cases").iterdir())]
        else:
            _LOADED[shared] = [(case, model) for case, _, model in photoreal_cases(photoreal)]
    return _LOADED[shared]


def cases(mode: str, real: Path, photoreal: Path, n: int) -> list[tuple[str, Path, VehicleModel, dict]]:
    """``(name, photo, model, hint)`` of a mode's cases; the hint is the start camera and box."""
    folders = _folders(real, photoreal, mode.endswith("-real"))
    return spread([(case.name, case / "photo.jpg", model, json.loads((case / "init.json").read_text()))
                   for case, model in folders], n)


def prepared(model: VehicleModel, renderer: Renderer) -> float:
    """Seconds to make what the registration needs of the model before it searches (its levels
    of detail, their exterior passes, its part labels and its view-sphere templates): the
    bench's models come from their mesh files, not from a prepared-model store."""
    t = time.perf_counter()
    model.prepare(renderer)
    model.templates(renderer)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="cases of each set, spread evenly (0: all)")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--real", type=Path, default=SHARED / "real")
    ap.add_argument("--photoreal", type=Path, default=SHARED / "bench")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a registration option (repeatable; tuples as Python literals)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    renderer = Renderer()
    options = parse_options(args.option)
    runs: list[dict] = []
    prep: dict[str, float] = {}
    for mode in args.modes.split(","):
        if mode not in MODES:
            raise SystemExit(f"unknown mode {mode!r}: one of {', '.join(MODES)}")
        for name, path, model, hint in cases(mode, args.real, args.photoreal, args.cases):
            if model.info.id not in prep:
                prep[model.info.id] = prepared(model, renderer)
            photo = load_photo(path)
            started = mode.startswith(("hinted", "camera"))
            t = time.perf_counter()
            with clocked() as clock:
                res = register(photo, model, init_camera=Camera.from_dict(hint) if started else None,
                               bbox=hint.get("bbox") if mode.startswith("hinted") else None, options=options,
                               renderer=renderer)
            wall = time.perf_counter() - t
            r = {"mode": mode, "case": name, "engine s": res.seconds, "wall s": wall,
                 "evaluations": res.evaluations, "renders": clock.calls.get("draw", 0),
                 "pose_stage": res.pose_stage}
            for kind in KINDS:
                r[f"{kind} s"] = clock.seconds.get(kind, 0.0)
            for stage in STAGES:
                r[f"{stage} s"] = res.timings.get(stage, 0.0)
            r["rest s"] = res.seconds - sum(clock.seconds.values()) - r["parts s"]
            print(f"{mode:16s} {name:18s} {res.seconds:6.2f} s  {res.evaluations:5d} evals  {r['renders']:5d} renders  "
                  + " ".join(f"{k} {r[f'{k} s']:.2f}" for k in KINDS) + f"  rest {r['rest s']:.2f}  "
                  + " ".join(f"{s} {r[f'{s} s']:.2f}" for s in STAGES[:4] if r[f"{s} s"] > 0)
                  + f"  ({res.pose_stage})", flush=True)
            runs.append(r)
    rows = []
    for mode in dict.fromkeys(r["mode"] for r in runs):
        sel = [r for r in runs if r["mode"] == mode]
        row: dict = {"mode": mode, "cases": len(sel)}
        for key in ("engine s", "evaluations", "renders", *(f"{k} s" for k in KINDS), "parts s", "rest s",
                    *(f"{s} s" for s in STAGES[:4])):
            row[key] = float(np.median([r[key] for r in sel]))
        row["ms a render"] = 1e3 * sum(r["draw s"] + r["read s"] for r in sel) / max(1, sum(r["renders"] for r in sel))
        rows.append(row)
    print(table(rows, list(rows[0])))
    print("preparation (made): " + ", ".join(f"{k} {v:.2f} s" for k, v in prep.items()))
    gl = renderer.ctx.info
    name = "stages" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"renderer": gl["GL_RENDERER"], "rows": rows, "runs": runs, "preparation": prep,
                              "cases": args.cases, "options": args.option}))


if __name__ == "__main__":
    main()
