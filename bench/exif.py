"""The phone's focal length: a registration with the photo's EXIF focal length against the same
photo with its EXIF stripped.

Usage: .venv/bin/python bench/exif.py [--views N] [--seed S] [--exact] [--option KEY=VALUE ...] [--tag TAG]

For every shipped model, ``--views`` random views (:func:`random_framed_view`: azimuth all
round, elevation 3-30 degrees, the car 40-80 % of a 640x480 frame), each with a lens drawn
log-uniformly from 24-85 mm (35 mm equivalent: a phone's main camera to a short telephoto),
alternately a matte render (the shading explains it) and one with mirror paint (it does not:
the edges find the pose). Each photo is written as a JPEG twice: with EXIF as a phone writes it
(FocalLengthIn35mmFilm: the true equivalent off by up to 4 % either way, as the width and
diagonal conventions of 4:3 sensors differ, then rounded to a whole millimetre; every third
photo in the focal plane form instead: FocalLength and FocalPlaneXResolution of a 5.6 mm wide
sensor), and stripped of it; with ``--exact``, every photo's EXIF in the focal plane form with
the true focal length (to a hundredth of a millimetre), the views the same. Both are read back
as the service reads them and registered with no hint.

Reports per model and over all: the focal length's error (% of the true one), the projection
error of the model's points (pixels at 640 wide), the rotation error, and the ratio of the
stripped photo's median errors to the EXIF photo's (the target: at least 2 for the focal
length and the projection). Writes ``bench/results/exif[_TAG].json`` and the contact sheet
``exif[_TAG].png`` (the stripped photo's registration left, the EXIF photo's right).
"""

from __future__ import annotations

import argparse
import io

import numpy as np
from PIL import ExifTags, Image

from vehicle_pose import register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import projection_error, rotation_error
from vehicle_pose.model.library import ModelLibrary
from vehicle_pose.photo import FULL_FRAME_DIAGONAL, decode_photo, read_focal
from vehicle_pose.render.overlay import draw_overlay
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.render.synth import random_framed_view, synthesize, synthesize_hazard
from vehicle_pose.search.views import view_camera

from common import parse_options, publish

W, H = 640, 480
SENSOR_MM = 5.6  # a phone's main sensor width, for the focal plane form


def jpeg(photo: np.ndarray, tags: dict[int, object] | None) -> bytes:
    """The photo as a JPEG, with ``tags`` in its Exif IFD (None: no EXIF at all)."""
    out = io.BytesIO()
    img = Image.fromarray(photo)
    if tags is None:
        img.save(out, "JPEG", quality=95)
    else:
        exif = Image.Exif()
        ifd = exif.get_ifd(ExifTags.IFD.Exif)
        ifd.update(tags)
        img.save(out, "JPEG", quality=95, exif=exif)
    return out.getvalue()


def focal_plane_tags(truth: Camera, factor: float = 1.0) -> dict[int, object]:
    """The focal plane form for the true camera: FocalLength (the true one times ``factor``, in
    hundredths of a millimetre) and FocalPlaneXResolution of a ``SENSOR_MM`` wide sensor."""
    per_mm = truth.width / SENSOR_MM
    return {0x920A: round(truth.focal / per_mm * factor, 2), 0xA20E: per_mm * 25.4, 0xA210: 2,
            0xA002: truth.width, 0xA003: truth.height}


def phone_tags(truth: Camera, rng: np.random.Generator, focal_plane: bool) -> dict[int, object]:
    """EXIF as a phone writes it for the true camera (see the module docstring)."""
    diagonal = float(np.hypot(truth.width, truth.height))
    equivalent = truth.focal / diagonal * FULL_FRAME_DIAGONAL
    if focal_plane:
        return focal_plane_tags(truth, float(rng.uniform(0.98, 1.02)))
    return {0xA405: int(round(equivalent * float(rng.uniform(0.96, 1.04)))), 0xA002: truth.width,
            0xA003: truth.height}


def summary(rows: list[dict], key: str) -> dict:
    def med(name: str) -> float:
        return float(np.median([r[name] for r in rows])) if rows else float("nan")

    return {"model": key, "photos": len(rows),
            "focal % exif": med("focal_exif"), "focal % stripped": med("focal_stripped"),
            "proj px exif": med("proj_exif"), "proj px stripped": med("proj_stripped"),
            "rot deg exif": med("rot_exif"), "rot deg stripped": med("rot_stripped"),
            "focal ratio": med("focal_stripped") / max(med("focal_exif"), 1e-9),
            "proj ratio": med("proj_stripped") / max(med("proj_exif"), 1e-9)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="")
    ap.add_argument("--exact", action="store_true",
                    help="EXIF with the true focal length (the focal plane form), not as a phone rounds it")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a registration option (repeatable), as bench/real.py takes it")
    args = ap.parse_args()
    options = parse_options(args.option)
    rng = np.random.default_rng(args.seed)
    renderer = Renderer()
    lib = ModelLibrary()
    runs, tiles, rows = [], [], []
    k = 0
    for model_id in lib.ids():
        model = lib.load(model_id)
        points = model.mesh.sample_points(1000)
        mine = []
        for _ in range(args.views):
            framed, view = random_framed_view(model, rng, W, H)
            equivalent = float(np.exp(rng.uniform(np.log(24.0), np.log(85.0))))
            focal = equivalent / FULL_FRAME_DIAGONAL * float(np.hypot(W, H))
            uv = framed.project(model.mesh.vertices)
            box = (float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max()))
            truth = view_camera(model, view["azimuth"], view["elevation"], 0.0, box, W, H, focal)
            kind = "matte" if k % 2 == 0 else "mirror-paint"
            if kind == "matte":
                photo, _ = synthesize(model.mesh, truth, renderer=renderer, seed=k)
            else:
                photo, _, truth = synthesize_hazard(model.mesh, truth, "mirror-paint", renderer=renderer, seed=k)
            form = "focal_plane" if k % 3 == 2 or args.exact else "35mm"
            # The phone's tags are drawn either way, so that every view is the same with --exact.
            tags = phone_tags(truth, rng, k % 3 == 2)
            tagged = jpeg(photo, focal_plane_tags(truth) if args.exact else tags)
            stripped = jpeg(photo, None)
            row = {"model": model_id, "kind": kind, "form": form, "azimuth": view["azimuth"],
                   "elevation": view["elevation"], "focal": truth.focal, "equivalent_mm": equivalent}
            pair = []
            for name, data in (("stripped", stripped), ("exif", tagged)):
                exif = read_focal(data)
                result = register(decode_photo(data), model, renderer=renderer, exif=exif, options=options)
                cam = result.camera
                row[f"focal_{name}"] = 100.0 * abs(cam.focal / truth.focal - 1.0)
                row[f"proj_{name}"] = projection_error(points, cam, truth, width=640)
                row[f"rot_{name}"] = rotation_error(cam.R, truth.R)
                row[f"source_{name}"] = result.focal["source"]
                row[f"stage_{name}"] = result.pose_stage
                row[f"seconds_{name}"] = result.seconds
                pair.append(draw_overlay(decode_photo(data), model.mesh, cam, renderer=renderer))
            runs.append(row)
            mine.append(row)
            tiles.append(tuple(pair))
            print(f"{model_id:9s} {kind:12s} {form:11s} {equivalent:5.1f} mm  focal err "
                  f"{row['focal_stripped']:5.1f} % -> {row['focal_exif']:5.1f} %  proj "
                  f"{row['proj_stripped']:6.2f} -> {row['proj_exif']:6.2f} px  rot "
                  f"{row['rot_stripped']:5.1f} -> {row['rot_exif']:5.1f} deg  ({row['source_exif']}; "
                  f"{row['stage_stripped']} -> {row['stage_exif']})", flush=True)
            k += 1
        rows.append(summary(mine, model_id))
    for kind in ("matte", "mirror-paint"):
        rows.append(summary([r for r in runs if r["kind"] == kind], f"all {kind}"))
    rows.append(summary(runs, "all"))
    publish("exif", args.tag, rows, {"runs": runs, "args": vars(args)}, tiles)


if __name__ == "__main__":
    main()
