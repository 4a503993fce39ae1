"""The part map: how well the geometric partition and a registration label the car's pixels.

Usage: .venv/bin/python bench/parts.py [--views N] [--registrations N] [--seed S] [--tag TAG]

For every shipped model, over random views (azimuth uniform, elevation 0-35 degrees, the car
filling 50-90 % of a 640x480 frame):

- **geometric**: over ``--views`` views, the share of the body's and glass's visible pixels
  (by the construction labels of the model's part file) that the geometric partition
  (:func:`~vehicle_pose.model.parts.geometric_labels`, the labelling of a model without a part
  file) gives the same part;

- **registered**: for ``--registrations`` of those views, a synthetic photo registered from a
  rough start (6 degrees, 3 % of the distance, focal 10 % off): the share of the car's pixels
  (by the true pose's map) whose part the registered pose's map gets right, and the seconds the
  part map adds to the registration (``timings["parts"]``, PNG encoding included).

Writes ``bench/results/parts[_TAG].json`` and the contact sheet ``parts[_TAG].png`` (per
model, the construction map left and the geometric one right at the view where they agree
least; then per registration the true map left, the registration's overlay with parts right).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from vehicle_pose import register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import ModelLibrary, VehicleModel
from vehicle_pose.model.parts import LEGEND
from vehicle_pose.render.overlay import draw_overlay
from vehicle_pose.render.parts import palette, part_map
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.render.synth import synthesize
from vehicle_pose.search.views import view_camera

from common import perturbed, publish


def random_view(model: VehicleModel, rng: np.random.Generator) -> tuple[float, float, Camera]:
    """Azimuth, elevation and camera of a random view (the module docstring)."""
    az, el = float(rng.uniform(0, 360)), float(rng.uniform(0, 35))
    fill = float(rng.uniform(0.5, 0.9))
    w, h = 640 * fill, 480 * fill
    box = (320 - w / 2, 240 - h / 2, 320 + w / 2, 240 + h / 2)
    return az, el, view_camera(model, az, el, 0.0, box, 640, 480, float(rng.uniform(600, 2400)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--registrations", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    renderer = Renderer()
    lib = ModelLibrary()
    rows, runs, tiles = [], [], []
    colours = np.array(palette(), np.uint8).reshape(256, 3)
    # The body's and glass's parts: every part but the wheels, lamps, mirrors and "other".
    panels = np.zeros(256, bool)
    panels[[k for part, k in LEGEND.items() if not part.startswith(("wheel", "headlamp", "taillamp", "mirror",
                                                                     "other"))]] = True
    for model_id in lib.ids():
        model = lib.load(model_id)
        geometric = VehicleModel(replace(model.info, parts_path=None), model.mesh, model.levels)
        agree, seen, worst = 0, 0, (2.0, None)
        for _ in range(args.views):
            _, _, cam = random_view(model, rng)
            built, guessed = part_map(model, cam, renderer).image(), part_map(geometric, cam, renderer).image()
            body = panels[built]
            same = int((built[body] == guessed[body]).sum())
            agree, seen = agree + same, seen + int(body.sum())
            share = same / max(int(body.sum()), 1)
            if share < worst[0]:
                worst = (share, (colours[built], colours[guessed]))
        geo = 100.0 * agree / max(seen, 1)
        if worst[1] is not None:
            tiles.append(worst[1])
        print(f"{model_id:9s} geometric partition against construction: {geo:5.1f} % of {seen} body pixels "
              f"(worst view {100 * worst[0]:5.1f} %)", flush=True)
        registered, seconds = [], []
        for k in range(args.registrations):
            az, el, truth = random_view(model, rng)
            true_map = part_map(model, truth, renderer).image()
            car = true_map > 0
            photo, _ = synthesize(model.mesh, truth, renderer=renderer, seed=k)
            start = perturbed(truth, rng, 6.0)
            result = register(photo, model, init_camera=start, renderer=renderer)
            assert result.parts is not None
            t_png = time.perf_counter()
            png = result.parts.png()
            spent = result.timings["parts"] + time.perf_counter() - t_png
            found = result.parts.image()
            acc = float((found[car] == true_map[car]).mean())
            registered.append(acc)
            seconds.append(spent)
            runs.append({"model": model_id, "azimuth": az, "elevation": el, "pixel_accuracy": acc,
                         "parts_seconds": spent, "png_bytes": len(png), "seconds": result.seconds})
            print(f"{model_id:9s} az {az:5.1f} el {el:4.1f}  registered parts {100 * acc:5.1f} %  "
                  f"map+png {spent:.3f} s  registration {result.seconds:.1f} s", flush=True)
            truth_img = photo.copy()
            truth_img[car] = (0.55 * photo[car] + 0.45 * colours[true_map[car]]).astype(np.uint8)
            tiles.append((truth_img, draw_overlay(photo, model.mesh, result.camera, renderer=renderer,
                                                  parts=result.parts)))
        rows.append({"model": model_id, "views": args.views, "geometric %": geo,
                     "geometric worst view %": 100.0 * worst[0], "registrations": len(registered),
                     "registered %": 100 * float(np.mean(registered)) if registered else float("nan"),
                     "registered min %": 100 * float(np.min(registered)) if registered else float("nan"),
                     "map+png median s": float(np.median(seconds)) if seconds else float("nan")})
    every = {"model": "all", "views": args.views * len(lib.ids()),
             "geometric %": float(np.mean([r["geometric %"] for r in rows])),
             "geometric worst view %": float(np.min([r["geometric worst view %"] for r in rows])),
             "registrations": len(runs),
             "registered %": 100 * float(np.mean([r["pixel_accuracy"] for r in runs])) if runs else float("nan"),
             "registered min %": 100 * float(np.min([r["pixel_accuracy"] for r in runs])) if runs else float("nan"),
             "map+png median s": float(np.median([r["parts_seconds"] for r in runs])) if runs else float("nan")}
    rows.append(every)
    publish("parts", args.tag, rows, {"runs": runs, "args": vars(args)}, tiles)


if __name__ == "__main__":
    main()
