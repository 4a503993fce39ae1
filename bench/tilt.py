"""How each cue's cost rises as the view is tilted up or down about a reference pose.

Usage: .venv/bin/python bench/tilt.py [--shared ../shared/bench] [--report REPORT.json [--found]] [--cases N]
       [--tag T]

The reference is each photoreal render's exact camera (``--shared ../shared/bench``, the
default), or with ``--report`` each real photo's annotated rotation (``--shared ../shared/real``
or ``../shared/real-partial``), placed by the camera that the ``bench/real.py`` report gives
for it (the photos it ended more than 30 degrees off are left out); with ``--found``, that
camera itself (the pose the registration found: is it at the cues' own minimum?).
The reference camera is turned about its own horizontal axis through the model's centre by
-6, -3, 0, +3 and +6 degrees (positive: the view from higher). Each turned pose's place, size
and focal length are refitted (rotation held, 200 evaluations) on the view-sphere search's
cost: its two-way chamfer for the photo's smallest no-hint target on a render (the car's own
region), for the whole frame on a real photo (a crop to the car). At each refitted pose two
cues are read:

- ``chamfer``: that cost (what the search minimises);
- ``colour split``: how well the projected outline parts the photo's colours (the region cue
  of PWP3D, SRT3D and ICG): the colours of a band inside the outline and of a band outside it
  (each 1.5 % of the search size's diagonal wide) counted in 8 levels a channel, and the
  conditional entropy of the side given the colour over the entropy of the side (0: no colour
  on both sides; 1: the colours do not tell the sides apart).

The table gives per cue the median rise over the reference's value at each tilt, the ratio of
the rise upward to the rise downward at 3 and 6 degrees (1: a symmetric valley; below 1: the
upper side shallow), and at which tilt each case's cue is lowest. Writes
bench/results/tilt_<set>[_TAG].json (docs/decisions/0056-the-edges-pose-sits-high.md,
0057-the-outline-s-colour-split.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
from real import annotated_start, load_models

from vehicle_pose import RegistrationOptions
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.loss.edges import photo_edges
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.photo import load_photo, resized
from vehicle_pose.registration import sphere
from vehicle_pose.registration.sphere import _HOLD, Pose, _Cost, _fit, _search_size
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import NelderMeadRestarts

from common import photoreal_cases, table, write_report

TILTS = (-6.0, -3.0, 0.0, 3.0, 6.0)
BAND = 0.015
LEVELS = 8


class ColourSplit:
    """The outline's colour split on one photo (H, W, 3 uint8): see the module docstring."""

    def __init__(self, image: npt.NDArray[np.uint8], band: int) -> None:
        q = (image.astype(np.int32) * LEVELS) // 256
        self.codes = (q[..., 0] * LEVELS + q[..., 1]) * LEVELS + q[..., 2]
        self.kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))

    def __call__(self, covered: npt.NDArray[np.bool_]) -> float:
        s = covered.astype(np.uint8)
        inner = covered & (cv2.erode(s, self.kernel, borderType=cv2.BORDER_REPLICATE) == 0)
        outer = ~covered & (cv2.dilate(s, self.kernel) > 0)
        fi = np.bincount(self.codes[inner], minlength=LEVELS**3).astype(np.float64)
        fo = np.bincount(self.codes[outer], minlength=LEVELS**3).astype(np.float64)
        if fi.sum() == 0 or fo.sum() == 0:
            return 1.0
        n = fi + fo
        share = fi.sum() / n.sum()
        side = -(share * np.log(share) + (1 - share) * np.log(1 - share))
        with np.errstate(divide="ignore", invalid="ignore"):
            given = -(np.nansum(fi * np.log(fi / n)) + np.nansum(fo * np.log(fo / n))) / n.sum()
        return float(given / side)


def tilted(camera: Camera, model: VehicleModel, degrees: float) -> Camera:
    """``camera`` turned by ``degrees`` about its own horizontal axis through the model's centre
    (the centre's image and depth kept)."""
    turned = cv2.Rodrigues(np.array([np.radians(degrees), 0.0, 0.0]))[0] @ camera.R
    return annotated_start(model, camera, turned)


def references(shared: Path, report: Path | None, renderer: Renderer, found: bool = False):
    """(name, photo, model, reference camera, whether the target is the frame) of each case."""
    if report is None:
        for case, gt, model in photoreal_cases(shared):
            if gt.get("rotation_only"):
                raise SystemExit(f"{case} is annotated by its rotation only: give --report, a bench/real.py report "
                                 "that places each photo's model")
            model.prepare(renderer)
            yield case.name, load_photo(case / "photo.jpg"), model, Camera.from_dict(gt), False
        return
    runs = {r["case"]: r for r in json.loads(report.read_text())["runs"]}
    models = load_models(shared)
    for m in models.values():
        m.prepare(renderer)
    for case in sorted((shared / "cases").iterdir()):
        run = runs.get(case.name)
        if run is None or run["final_deg"] > 30.0:
            continue
        gt = json.loads((case / "gt.json").read_text())
        model = models[gt["model"]]
        placed = Camera.from_dict(run["camera"])
        reference = placed if found else annotated_start(model, placed, np.array(gt["R"]))
        yield case.name, load_photo(case / "photo.jpg"), model, reference, True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "bench")
    ap.add_argument("--report", type=Path, default=None)
    ap.add_argument("--found", action="store_true", help="about the report's own cameras, not the annotations")
    ap.add_argument("--cases", type=int, default=0)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    options, renderer, optimizer = RegistrationOptions(), Renderer(), NelderMeadRestarts()
    runs = []
    cases = references(args.shared.resolve(), args.report, renderer, args.found)
    for name, photo, model, reference, frame in itertools.islice(cases, args.cases or None):
        w, h = _search_size(photo, options)
        image = resized(photo, w, h)
        edges = photo_edges(image)
        if frame:
            boxes = [(0.0, 0.0, w - 1.0, h - 1.0)]
        else:
            sx, sy = w / photo.shape[1], h / photo.shape[0]
            boxes = [(t.box[0] * sx, t.box[1] * sy, t.box[2] * sx, t.box[3] * sy)
                     for t in sphere._targets(photo, model, None, None)]
        among = (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes),
                 max(b[3] for b in boxes))
        k = int(np.argmin([(b[2] - b[0]) * (b[3] - b[1]) for b in boxes]))
        costs = [_Cost(image, model, b, None, options, renderer, edges, among, options.search.sphere_clutter)
                 for b in boxes]
        split = ColourSplit(image, max(1, round(BAND * float(np.hypot(w, h)))))
        chamfer, colour = [], []
        for degrees in TILTS:
            cam = tilted(reference, model, degrees)
            c0 = costs[k](cam)
            fitted = _fit(Pose(cam, -1, k, c0, c0), costs, model, options, optimizer, _HOLD, 200, None)
            chamfer.append(fitted.cost)
            colour.append(split(renderer.render(costs[k].mesh, fitted.camera.scaled(w, h)).coverage))
        runs.append({"case": name, "tilts": list(TILTS), "chamfer": chamfer, "colour split": colour})
        print(name, " ".join(f"{key} " + " ".join(f"{v - r[2]:+.4f}" for v in r)
                             for key, r in (("chamfer", chamfer), ("colour split", colour))), flush=True)
    rows = []
    for key in ("chamfer", "colour split"):
        rise = np.array([np.array(r[key]) - r[key][2] for r in runs])
        med = np.median(rise, axis=0)
        lowest = np.bincount(np.argmin(rise, axis=1), minlength=len(TILTS))
        row = {"cue": key, "cases": len(runs)}
        row.update({f"rise {t:+g}": round(float(m), 4) for t, m in zip(TILTS, med, strict=True)})
        row["up / down at 3"] = round(float(med[3] / med[1]), 2) if med[1] else float("nan")
        row["up / down at 6"] = round(float(med[4] / med[0]), 2) if med[0] else float("nan")
        row["lowest at -6/-3/0/+3/+6"] = "/".join(str(int(n)) for n in lowest)
        rows.append(row)
    print(table(rows, list(rows[0])))
    name = f"tilt_{args.shared.resolve().name}" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"benchmark": "tilt", "shared": str(args.shared), "report": str(args.report),
                              "found": args.found, "band": BAND, "levels": LEVELS, "rows": rows, "runs": runs}))


if __name__ == "__main__":
    main()
