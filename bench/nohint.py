"""No-hint registration: success, failure-flag quality and time, with no start camera and no box.

Usage: .venv/bin/python bench/nohint.py [--part synthetic|photoreal|identify|all] [--cases N]
       [--shared ../shared/bench] [--option KEY=VALUE ...] [--oracle-mask] [--scale S] [--tag TAG]

synthetic: the five shipped body types at random views (azimuth 0-360, elevation 3-30 degrees,
focal 0.8-2.5 image widths, the vehicle 40-80 % of the width, fully in view), the four synthetic
lightings, textured backgrounds. photoreal: the cases of ../shared/bench without their hints.
identify: the synthetic photos registered against every shipped model, lowest loss wins.
Success = mean vertex projection error <= 5 px at 640 px width. A flagged result is one with
``failed`` set; precision = flagged results that were wrong / flagged results, recall = wrong
results flagged / wrong results. Writes bench/results/nohint_<part>.json and, for the synthetic
and photoreal parts, a contact sheet nohint_<part>.png of each case's start (the search's) and
final outline; the photoreal part's report is named after another folder of cases given with
``--shared`` (``nohint_bench-partial`` for ``../shared/bench-partial``). ``--scale`` registers each
photoreal case resized by that factor, its true camera and mask to match (the error is still
measured at 640 px width).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import ModelLibrary
from vehicle_pose.photo import load_photo, resized_mask
from vehicle_pose.registration.identify import identify
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.render.synth import LIGHTINGS, random_framed_view, synthesize

from common import (
    overlay_pair,
    parse_options,
    photoreal_cases,
    projection_error,
    rescaled_photo,
    table,
    write_report,
    write_sheet,
)

SUCCESS_PX = 5.0


def summarise(label: dict, runs: list[dict]) -> dict:
    ok = np.array([r["error_px"] <= SUCCESS_PX for r in runs])
    flagged = np.array([r["failed"] for r in runs])
    wrong = ~ok
    return {
        **label,
        "cases": len(runs),
        "success %": 100.0 * float(ok.mean()),
        "median err px": float(np.median([r["error_px"] for r in runs])),
        "flagged": int(flagged.sum()),
        "flag precision %": 100.0 * float((flagged & wrong).sum() / flagged.sum()) if flagged.any() else float("nan"),
        "flag recall %": 100.0 * float((flagged & wrong).sum() / wrong.sum()) if wrong.any() else float("nan"),
        "success unflagged %": 100.0 * float((ok & ~flagged).sum() / max(1, (~flagged).sum())),
        "median s": float(np.median([r["seconds"] for r in runs])),
    }


def synthetic_cases(n: int, seed: int = 7):
    lib = ModelLibrary()
    renderer = Renderer()
    rng = np.random.default_rng(seed)
    ids = lib.ids()
    lights = list(LIGHTINGS.values())
    for i in range(n):
        model = lib.load(ids[i % len(ids)])
        truth, view = random_framed_view(model, rng, 640, 480)
        photo, _ = synthesize(model.mesh, truth, lighting=lights[i % len(lights)], renderer=renderer, seed=seed + i)
        yield model, renderer, truth, photo, view


def _run(model, renderer, photo, truth, options, foreground=None, tiles=None, name="") -> dict:
    res = register(photo, model, options=options, renderer=renderer, foreground=foreground)
    r = {"error_px": projection_error(model.mesh.vertices, res.camera, truth), "seconds": res.seconds,
         "failed": res.failed, "confidence": res.confidence, "checks": res.checks, "method": res.start_method,
         "loss": res.loss, "camera": res.camera.to_dict()}
    if tiles is not None:
        tiles.append(overlay_pair(photo, model, res.start_camera, res.camera, renderer,
                                  f"{name} start ({r['method']})", f"final {r['error_px']:.1f} px conf "
                                  f"{r['confidence']:.2f}{' FLAGGED' if r['failed'] else ''}"))
    return r


def _print(r: dict, name: str) -> None:
    checks = " ".join(f"{k} {v:.3f}" for k, v in r["checks"].items())
    print(f"{name:32s} err {r['error_px']:8.2f} px  conf {r['confidence']:.2f} failed {r['failed']!s:5s} "
          f"{r['method']:11s} {r['seconds']:5.1f} s  {checks}", flush=True)


def synthetic(n: int, options: RegistrationOptions) -> dict:
    runs, tiles = [], []
    for model, renderer, truth, photo, view in synthetic_cases(n):
        name = f"{model.info.id} az {view['azimuth']:.0f} el {view['elevation']:.0f}"
        r = _run(model, renderer, photo, truth, options, tiles=tiles, name=name) | {"model": model.info.id,
                                                                                     "view": view}
        _print(r, name)
        runs.append(r)
    ids = sorted({r["model"] for r in runs})
    rows = [summarise({"model": mid}, [r for r in runs if r["model"] == mid]) for mid in ids]
    rows.append(summarise({"model": "all"}, runs))
    print(table(rows, list(rows[0])))
    return {"rows": rows, "runs": runs, "tiles": tiles}


def photoreal(shared: Path, options: RegistrationOptions, oracle: bool = False, scale: float = 1.0) -> dict:
    renderer, runs, tiles = Renderer(), [], []
    for case, gt, model in photoreal_cases(shared):
        mask = np.load(case / "mask.npy") if oracle else None
        photo, truth = load_photo(case / "photo.jpg"), Camera.from_dict(gt)
        if scale != 1.0:
            photo = rescaled_photo(photo, scale)
            h, w = photo.shape[:2]
            truth = truth.scaled(w, h)
            if mask is not None:
                mask = resized_mask(mask, w, h)
        r = _run(model, renderer, photo, truth, options, mask, tiles, f"{case.name} {model.info.id}")
        r |= {"case": case.name, "model": model.info.id}
        _print(r, f"{case.name} {model.info.id}")
        runs.append(r)
    rows = [summarise({"model": mid},
                      [r for r in runs if r["model"] == mid]) for mid in sorted({r["model"] for r in runs})]
    rows.append(summarise({"model": "all"}, runs))
    print(table(rows, list(rows[0])))
    return {"rows": rows, "runs": runs, "tiles": tiles}


def identification(n: int, options: RegistrationOptions) -> dict:
    lib = ModelLibrary()
    candidates = [lib.load(mid) for mid in lib.ids()]
    runs = []
    for model, renderer, truth, photo, _view in synthetic_cases(n, seed=11):
        t = time.perf_counter()
        ranking = identify(photo, candidates, options=options, renderer=renderer)
        best = ranking[0]
        r = {"model": model.info.id, "picked": best.model.info.id, "seconds": time.perf_counter() - t,
             "ranking": [(c.model.info.id, c.score) for c in ranking],
             "error_px": projection_error(model.mesh.vertices, best.camera, truth) if best.model is model else None}
        print(f"{model.info.id:10s} -> {r['picked']:10s} " + " ".join(f"{m}:{s:.3f}" for m, s in r["ranking"])
              + f"  {r['seconds']:.1f} s", flush=True)
        runs.append(r)
    rows = [{"true model": mid, "cases": sum(r["model"] == mid for r in runs),
             "identified %": 100.0 * float(np.mean([r["picked"] == mid for r in runs if r["model"] == mid])),
             "median s": float(np.median([r["seconds"] for r in runs if r["model"] == mid]))}
            for mid in sorted({r["model"] for r in runs})]
    rows.append({"true model": "all", "cases": len(runs),
                 "identified %": 100.0 * float(np.mean([r["picked"] == r["model"] for r in runs])),
                 "median s": float(np.median([r["seconds"] for r in runs]))})
    print(table(rows, list(rows[0])))
    return {"rows": rows, "runs": runs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", default="all", choices=("synthetic", "photoreal", "identify", "all"))
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "bench")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a RegistrationOptions field, e.g. starts=6 (repeatable)")
    ap.add_argument("--oracle-mask", action="store_true",
                    help="photoreal: give the true mask as the region and foreground (a ceiling)")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="photoreal: register each case resized by this factor, its camera and mask to match")
    ap.add_argument("--tag", default="", help="suffix of the report's name")
    args = ap.parse_args()
    options = parse_options(args.option)
    suffix = f"_{args.tag}" if args.tag else ""
    if args.part in ("synthetic", "all"):
        data = synthetic(args.cases, options)
        tiles = data.pop("tiles")
        print(write_report("nohint_synthetic" + suffix, data | {"options": options.flat()}))
        print(write_sheet("nohint_synthetic" + suffix, tiles))
    if args.part in ("photoreal", "all"):
        if (args.shared / "cases").is_dir():
            if args.scale <= 0:
                raise SystemExit("--scale takes a positive factor")
            data = photoreal(args.shared, options, oracle=args.oracle_mask, scale=args.scale)
            tiles = data.pop("tiles")
            # The renders' own folder names the report, as in bench/accuracy.py: another set of
            # cases (../shared/bench-partial) does not overwrite the photoreal one.
            name = "nohint_" + ("photoreal" if args.shared.resolve().name == "bench" else args.shared.resolve().name)
            name += f"_scale{args.scale:g}" if args.scale != 1.0 else ""
            print(write_report(name + suffix, data | {"options": options.flat(), "oracle_mask": args.oracle_mask,
                                                      "scale": args.scale}))
            print(write_sheet(name + suffix, tiles))
        else:
            print(f"no photoreal cases at {args.shared}; skipped")
    if args.part in ("identify", "all"):
        print(write_report("nohint_identify" + suffix, identification(min(args.cases, 10), options)
                           | {"options": options.flat()}))


if __name__ == "__main__":
    main()
