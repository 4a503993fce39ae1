"""Registration accuracy and time: synthetic start-error sweep, loss comparison, photoreal cases.

Usage: .venv/bin/python bench/accuracy.py [--part sweep|losses|photoreal|all] [--cases N]
       [--shared ../shared/bench|../shared/bench-partial] [--start init.json|init_hard.json|box] [--no-box]
       [--oracle-mask] [--scale S] [--option KEY=VALUE ...] [--tag TAG]
Success = mean vertex projection error <= 5 px at 640 px width. Prints tables and writes
bench/results/accuracy_<part>.json; the photoreal part also a contact sheet of each case's start
(left) and final (right) outline, accuracy_photoreal.png (accuracy_bench-partial.png for the
cases cut by the frame). ``--start box`` gives the start file's box alone, no start camera.
``--scale`` registers each photoreal case resized by that factor, its true and start cameras, box
and mask to match (the error is still measured at 640 px width).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.model.library import ModelLibrary
from vehicle_pose.photo import load_photo, resized_mask
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from common import (
    overlay_pair,
    parse_options,
    perturbed,
    photoreal_cases,
    projection_error,
    rescaled_box,
    rescaled_photo,
    table,
    write_report,
    write_sheet,
)

SUCCESS_PX = 5.0


def summarise(label: dict, runs: list[dict]) -> dict:
    errs = np.array([r["error_px"] for r in runs])
    secs = np.array([r["seconds"] for r in runs])
    return {
        **label,
        "cases": len(runs),
        "success %": 100.0 * float(np.mean(errs <= SUCCESS_PX)),
        "median err px": float(np.median(errs)),
        "median s": float(np.median(secs)),
        "median evals": float(np.median([r["evaluations"] for r in runs])),
    }


def synthetic_cases(n: int, seed: int = 0):
    model = ModelLibrary().load("sedan")
    renderer = Renderer()
    rng = np.random.default_rng(seed)
    centre, _ = model.mesh.sphere
    lights = list(LIGHTINGS.values())
    for i in range(n):
        truth = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=rng.uniform(0, 360),
                               elevation_deg=rng.uniform(5, 30), distance=rng.uniform(7, 12),
                               focal=rng.uniform(600, 1500), width=640, height=480)
        photo, _ = synthesize(model.mesh, truth, lighting=lights[i % len(lights)], renderer=renderer, seed=i)
        yield model, renderer, truth, photo, rng


def run_one(model, renderer, photo, truth, start, options, **kw) -> dict:
    pts = model.mesh.vertices
    res = register(photo, model, init_camera=start, options=options, renderer=renderer, **kw)
    return {"error_px": projection_error(pts, res.camera, truth),
            "start_error_px": projection_error(pts, res.start_camera, truth),
            "seconds": res.seconds, "evaluations": res.evaluations, "loss": res.loss, "pose_stage": res.pose_stage,
            "failed": res.failed, "confidence": res.confidence, "camera": res.camera.to_dict(),
            "start_camera": res.start_camera.to_dict(), "checks": res.checks}


def _tiles(photo, model, renderer, r: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
    return overlay_pair(photo, model, Camera.from_dict(r["start_camera"]), Camera.from_dict(r["camera"]), renderer,
                        f"{name} {model.info.id} start {r['start_error_px']:.1f} px",
                        f"final {r['error_px']:.2f} px {r['pose_stage']}")


def sweep(n: int) -> dict:
    rows, runs = [], {}
    cases = list(synthetic_cases(n))
    for degrees in (5.0, 10.0, 20.0, 30.0):
        out = []
        for model, renderer, truth, photo, rng in cases:
            start = perturbed(truth, rng, degrees)
            out.append(run_one(model, renderer, photo, truth, start, RegistrationOptions()))
        runs[str(degrees)] = out
        rows.append(summarise({"start rotation deg": degrees,
                               "median start err px": float(np.median([r["start_error_px"] for r in out]))}, out))
        print(table(rows, list(rows[0])), flush=True)
    return {"rows": rows, "runs": runs}


def losses(n: int) -> dict:
    rows, runs = [], {}
    cases = [(m, r, t, p, perturbed(t, rng, 10.0)) for m, r, t, p, rng in synthetic_cases(n, seed=1)]
    for loss in ("invariant", "invariant-paper", "invariant-parts", "correlation", "squared", "silhouette-iou",
                 "mutual-information"):
        for color in ((False, True) if loss == "invariant" else (False,)):
            opts = RegistrationOptions(loss=loss, color=color)
            out = [run_one(m, r, p, t, s, opts) for m, r, t, p, s in cases]
            runs[f"{loss}{'-color' if color else ''}"] = out
            rows.append(summarise({"loss": loss + (" (n=3)" if color else "")}, out))
            print(table(rows, list(rows[0])), flush=True)
    return {"rows": rows, "runs": runs}


def oracle_mask(shared: Path, case: Path, gt: dict) -> np.ndarray:
    """The case's true vehicle mask: its own ``mask.npy``, or for a case cut by the frame
    (``gt["partial"]``) the source case's mask cut by the same crop (the renders cut by the
    frame point to their sources' folder through ``models.json``)."""
    if (case / "mask.npy").exists():
        return np.load(case / "mask.npy")
    part = gt.get("partial")
    if not part:
        raise SystemExit(f"{case}: no mask.npy and no source case to cut one from")
    catalogue = json.loads((shared / "models.json").read_text())
    mesh = (shared / catalogue[0]["mesh"]).resolve()
    source_root = next(p for p in mesh.parents if (p / "cases" / part["source"]).is_dir())
    x0, y0, x1, y1 = part["crop_xyxy"]
    return np.load(source_root / "cases" / part["source"] / "mask.npy")[y0:y1, x0:x1]


def photoreal(shared: Path, start_name: str, options: RegistrationOptions, oracle: bool = False,
              use_box: bool = True, scale: float = 1.0) -> dict:
    renderer, out, tiles = Renderer(), [], []
    for case, gt, model in photoreal_cases(shared):
        truth = Camera.from_dict(gt)
        hint = json.loads((case / ("init.json" if start_name == "box" else start_name)).read_text())
        start = None if start_name == "box" else Camera.from_dict(hint)
        mask = oracle_mask(shared, case, gt) if oracle else None
        box = hint.get("bbox") if use_box else None
        photo = load_photo(case / "photo.jpg")
        if scale != 1.0:
            H, W = photo.shape[:2]
            photo = rescaled_photo(photo, scale)
            h, w = photo.shape[:2]
            truth = truth.scaled(w, h)
            start = None if start is None else start.scaled(w, h)
            box = None if box is None else rescaled_box(box, w / W, h / H)
            if mask is not None:
                mask = resized_mask(mask, w, h)
        r = run_one(model, renderer, photo, truth, start, options, foreground=mask, bbox=box)
        tiles.append(_tiles(photo, model, renderer, r, case.name))
        r["case"] = case.name
        r["model"] = model.info.id
        out.append(r)
        print(f"{case.name} {model.info.id:18s} start {r['start_error_px']:7.1f} px -> {r['error_px']:7.2f} px "
              f"loss {r['loss']:.4f} {r['pose_stage']} {r['evaluations']} evals {r['seconds']:.2f} s", flush=True)
    ids = sorted({r["model"] for r in out})
    rows = [summarise({"start": start_name, "model": mid}, [r for r in out if r["model"] == mid]) for mid in ids]
    rows.append(summarise({"start": start_name, "model": "all"}, out))
    print(table(rows, list(rows[0])))
    return {"rows": rows, "runs": out, "tiles": tiles}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", default="all", choices=("sweep", "losses", "photoreal", "all"))
    ap.add_argument("--cases", type=int, default=8)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "bench")
    ap.add_argument("--start", default="init.json",
                    help="start file of the photoreal cases (init.json, init_hard.json), or box (init.json's box "
                    "alone, no start camera)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a RegistrationOptions field for the photoreal part, e.g. parametrization=view (repeatable)")
    ap.add_argument("--oracle-mask", action="store_true",
                    help="photoreal: give the true mask instead of GrabCut (a ceiling)")
    ap.add_argument("--no-box", action="store_true",
                    help="photoreal: give only the start camera, not the start file's box")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="photoreal: register each case resized by this factor, its cameras, box and mask to match")
    ap.add_argument("--tag", default="", help="suffix of the photoreal report's name")
    args = ap.parse_args()
    if args.part in ("sweep", "all"):
        print(write_report("accuracy_sweep", sweep(args.cases)))
    if args.part in ("losses", "all"):
        print(write_report("accuracy_losses", losses(args.cases)))
    if args.part in ("photoreal", "all"):
        if (args.shared / "cases").is_dir():
            name = (f"accuracy_{'photoreal' if args.shared.resolve().name == 'bench' else args.shared.resolve().name}"
                    + ("_hard" if "hard" in args.start else "") + ("_box" if args.start == "box" else "")
                    + ("_nobox" if args.no_box else "") + (f"_scale{args.scale:g}" if args.scale != 1.0 else "")
                    + (f"_{args.tag}" if args.tag else ""))
            options = parse_options(args.option)
            if args.scale <= 0:
                raise SystemExit("--scale takes a positive factor")
            data = photoreal(args.shared, args.start, options, oracle=args.oracle_mask, use_box=not args.no_box,
                             scale=args.scale)
            tiles = data.pop("tiles")
            data["options"] = options.flat()
            data["oracle_mask"] = args.oracle_mask
            data["box"] = not args.no_box
            data["scale"] = args.scale
            print(write_report(name, data))
            print(write_sheet(name, tiles))
        else:
            print(f"no photoreal cases at {args.shared}; skipped")


if __name__ == "__main__":
    main()
