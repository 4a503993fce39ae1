"""Real photos: rotation error against human pose annotations, from a start camera, a box alone or no hint.

Usage: .venv/bin/python bench/real.py [--start init.json|init_box.json|gt|box|none] [--no-box]
       [--half a|b] [--stretch SX,SY,SZ] [--mirror] [--scale S] [--cases N] [--shared ../shared/real]
       [--option KEY=VALUE ...] [--tag TAG]

The cases of ``../shared/real`` (real photos with the exact CAD model their annotations were made
with; rotation only), or of ``--shared ../shared/real-partial`` (the same photos with part of the
car cut off by the frame). Per case: the start's and the result's rotation error (the angle of
``R_est R_gt^T``, degrees), the viewpoint's error (the same angle for the result's camera turned
about its centre to look at the model's centre: :func:`viewpoint`), the loss, the confidence and
the time. Summary, for each half of ``split.json`` (``a`` and ``b``, fixed: choose on one, report
on the other; a partial case belongs to the half of its source photo) and for all: the median
error, the median viewpoint error, Acc pi/6 (share within 30 degrees), the share within 10 degrees,
the cases that end more than 2 degrees further from the annotation than they started, the flags,
the poses whose projection's box meets the car's with an IoU under 0.2 (a model shrunk onto a
detail or grown past the frame: a rotation error can hide them) and how many of those are
unflagged, the median time, and how far the right poses' elevation lies above the annotation's
(median, degrees: the view's elevation is the angle of the camera's optical axis to the model's
ground plane, positive looking down; a search that settles at its templates' elevations shows
here). ``--half`` runs one half only. Writes ``bench/results/<set>_<start>[_TAG].json`` (``<set>``
is the cases' folder name) and a contact sheet ``<set>_<start>[_TAG].png`` with the start (left)
and final (right) outline of every case. ``--stretch`` registers a copy of the model scaled along
its file's axes, a CAD model close to the car but not exact (the annotated rotation still holds).
``--mirror`` registers each photo turned left to right, with its start, box and annotation mirrored
to match: the same cars seen in a mirror, photos that no constant was chosen on (the templates, the
searches' placements and the images' pixels all differ; the CAD model is left-right symmetric).
``--scale`` registers each photo resized by that factor, with its start and box to match: the same
cars photographed larger or smaller (every size-dependent step of the engine meets other sizes;
the engine's working size is at most ``pyramid.max_size`` either way).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import rotation_error
from vehicle_pose.model.library import VehicleModel, model_from_mesh
from vehicle_pose.model.metadata import parse_axis
from vehicle_pose.photo import load_photo
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.views import upright_axes

from common import (
    RESULTS,
    overlay_pair,
    parse_options,
    rescaled_box,
    rescaled_photo,
    table,
    write_report,
    write_sheet,
)

WORSE_DEG = 2.0
"""A case that ends more than this many degrees further from the annotation than it started."""

OFF_IOU = 0.2
"""A pose whose projection's box meets the car's box with an IoU below this is off the car."""


def stretched(mesh: Path, factors: tuple[float, float, float], folder: Path) -> Path:
    """A copy of the OBJ ``mesh`` (with its material library) in ``folder`` whose vertices are
    scaled by ``factors`` along the file's own axes: a CAD model close to the car but not exact.
    The rotation that maps the mesh to the camera is the same for both."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = []
    for line in mesh.read_text().splitlines():
        if line.startswith("v "):
            xyz = [float(v) for v in line.split()[1:4]]
            line = "v " + " ".join(f"{v * f:.6f}" for v, f in zip(xyz, factors, strict=True))
        lines.append(line)
    out = folder / mesh.name
    out.write_text("\n".join(lines) + "\n")
    for other in mesh.parent.iterdir():
        if other != mesh and not (folder / other.name).exists():
            (folder / other.name).symlink_to(other.resolve())
    return out


def load_models(shared: Path, stretch: tuple[float, float, float] | None = None) -> dict[str, VehicleModel]:
    out = {}
    for entry in json.loads((shared / "models.json").read_text()):
        mesh = shared / entry["mesh"]
        if stretch is not None:
            mesh = stretched(mesh.resolve(), stretch, RESULTS / "stretched" / "_".join(f"{f:g}" for f in stretch))
        m = model_from_mesh(mesh, up=entry["up"], forward=entry["forward"], units="m",
                            meters_per_unit=entry["meters_per_unit"])
        out[entry["id"]] = m
    return out


def annotated_start(model: VehicleModel, init: Camera, R_gt: np.ndarray) -> Camera:
    """``init`` turned to the annotated rotation about the model's centre (the centre's image
    and depth kept): a start at the annotation, to see whether the registration stays there."""
    centre = model.mesh.sphere[0]
    c = init.to_camera(centre[None])[0]
    return Camera(init.K, R_gt, c - R_gt @ centre, init.width, init.height)


def box_iou(model: VehicleModel, camera: Camera, box: list[float]) -> float:
    """IoU of the model's projected box (clipped to the image) with the annotated box: a pose
    can turn the right way yet cover half the car."""
    uv = camera.project(model.mesh.sample_points(2000))
    if not np.all(np.isfinite(uv)):
        return 0.0
    a = [max(0.0, uv[:, 0].min()), max(0.0, uv[:, 1].min()),
         min(camera.width - 1.0, uv[:, 0].max()), min(camera.height - 1.0, uv[:, 1].max())]
    iw = max(0.0, min(a[2], box[2]) - max(a[0], box[0]))
    ih = max(0.0, min(a[3], box[3]) - max(a[1], box[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (box[2] - box[0]) * (box[3] - box[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def lateral_mirror(model: VehicleModel) -> tuple[np.ndarray, np.ndarray]:
    """The model's mirror across its plane of symmetry as ``(M, d)``: ``Y = M X + d``. The file's
    ``up`` and ``forward`` axes are the library's; the third is across the car, the plane through
    the bounds' middle."""
    across = int(np.argmax(np.abs(np.cross(parse_axis(model.info.up), parse_axis(model.info.forward)))))
    M = np.eye(3)
    M[across, across] = -1.0
    lo, hi = model.mesh.bounds
    d = np.zeros(3)
    d[across] = lo[across] + hi[across]
    return M, d


def mirrored(photo: np.ndarray, R_gt: np.ndarray, init: dict,
             model: VehicleModel) -> tuple[np.ndarray, np.ndarray, dict]:
    """The photo turned left to right, with its annotation and start file to match: the camera
    mirrored (``F R M``, ``F`` turning the camera's x axis) and the model mirrored across its plane of
    symmetry (``M``), so the rotation stays a rotation; the same car seen in a mirror, a photo no
    constant was chosen on. The CAD model must be left-right symmetric, as a car is."""
    W = photo.shape[1]
    M, d = lateral_mirror(model)
    F = np.diag([-1.0, 1.0, 1.0])
    out = dict(init)
    if "bbox" in init:
        x0, y0, x1, y1 = (float(v) for v in init["bbox"])
        out["bbox"] = [W - 1 - x1, y0, W - 1 - x0, y1]
    if "K" in init:
        K = np.asarray(init["K"], float).copy()
        K[0, 2] = W - 1 - K[0, 2]
        R = F @ np.asarray(init["R"], float) @ M
        out.update(K=K.tolist(), R=R.tolist(), t=(F @ np.asarray(init["t"], float) - R @ d).tolist())
    return np.ascontiguousarray(photo[:, ::-1]), F @ R_gt @ M, out


def rescaled(photo: np.ndarray, init: dict, factor: float) -> tuple[np.ndarray, dict]:
    """The photo resized by ``factor`` (:func:`rescaled_photo`), with its start file to match: the
    start camera for the new size (pixel centres kept, :meth:`Camera.scaled`) and the box's
    corners moved the same way. The rotation is unchanged."""
    H, W = photo.shape[:2]
    out_photo = rescaled_photo(photo, factor)
    h, w = out_photo.shape[:2]
    out = dict(init)
    if "bbox" in init:
        out["bbox"] = rescaled_box(init["bbox"], w / W, h / H)
    if "K" in init:
        out.update(Camera.from_dict(init).scaled(w, h).to_dict())
    return out_photo, out


def elevation(R: np.ndarray, model: VehicleModel) -> float:
    """The elevation (degrees) of a view of rotation ``R`` (model to camera): the angle between
    the model's ground plane (its up axis as the view-sphere templates measure it,
    :func:`~vehicle_pose.search.views.upright_axes`) and the line of sight along the optical
    axis, positive from above."""
    up = upright_axes(model)[0]
    return float(np.degrees(np.arcsin(np.clip(-(R.T @ [0.0, 0.0, 1.0]) @ up, -1.0, 1.0))))


def viewpoint(camera: Camera, centre: np.ndarray) -> np.ndarray:
    """The camera's viewpoint: its rotation turned about the camera's centre, by the smallest
    turn, until the optical axis passes through ``centre`` (mesh coordinates).

    A viewpoint as PASCAL3D+ defines one (azimuth, elevation and in-plane turn of a camera that
    looks at the object's centre) does not depend on the principal point. A camera's rotation
    does: for a photo cropped from a larger one the principal point is unknown, the search takes
    the crop's centre, and the rotation turns by the angle between that point's ray and the
    true one (about atan(offset / f): a few degrees with a short lens). The real set's annotations
    were made on such crops (docs/decisions/0059-the-viewpoint-and-the-principal-point.md).
    """
    d = camera.R @ centre + camera.t
    axis = np.cross(d, [0.0, 0.0, 1.0])  # |axis| = |d| sin(angle), d @ z = |d| cos(angle)
    s = float(np.linalg.norm(axis))
    turn = axis * (np.arctan2(s, d[2]) / s) if s > 1e-12 else np.zeros(3)  # d onto the optical axis
    return cv2.Rodrigues(turn)[0] @ camera.R


def worse(run: dict) -> bool:
    """Whether a case ended more than :data:`WORSE_DEG` further from the annotation than it started."""
    return run["start_deg"] is not None and run["final_deg"] > run["start_deg"] + WORSE_DEG


def summarise(label: dict, runs: list[dict]) -> dict:
    final = np.array([r["final_deg"] for r in runs])
    start = np.array([r["start_deg"] for r in runs if r["start_deg"] is not None] or [np.nan])
    wrong = final > 30.0
    flagged = np.array([bool(r["failed"]) for r in runs])
    # A pose whose outline barely meets the car's box (a model shrunk onto a lamp, or grown past
    # the frame) is a gross failure that a rotation error within 30 degrees can hide.
    off = np.array([r["box_iou"] < OFF_IOU for r in runs])
    return {
        **label,
        "cases": len(runs),
        "median start deg": float(np.median(start)),
        "median deg": float(np.median(final)),
        "median viewpoint deg": float(np.median([r["viewpoint_deg"] for r in runs])),
        "median box iou": float(np.median([r["box_iou"] for r in runs])),
        "acc pi/6 %": 100.0 * float(np.mean(final <= 30.0)),
        "within 10 %": 100.0 * float(np.mean(final <= 10.0)),
        "worse by 2": int(sum(worse(r) for r in runs)),
        "flagged": int(flagged.sum()),
        "wrong unflagged": int((wrong & ~flagged).sum()),
        "right flagged": int((~wrong & flagged).sum()),
        f"box iou < {OFF_IOU}": int(off.sum()),
        "of them unflagged": int((off & ~flagged).sum()),
        "elevation above ann. deg": float(np.median([r["elevation_deg"] - r["annotated_elevation_deg"]
                                                     for r in runs if r["final_deg"] <= 30.0] or [np.nan])),
        "median s": float(np.median([r["seconds"] for r in runs])),
    }


def halves(shared: Path) -> dict[str, str]:
    """The half (``a`` or ``b``) of each case of ``shared``: its own, or its source photo's."""
    split = json.loads((shared.parent / "real" / "split.json").read_text())
    of = {name: h for h in ("a", "b") for name in split[h]}
    out = {}
    for case in (shared / "cases").iterdir():
        gt = json.loads((case / "gt.json").read_text())
        out[case.name] = of[gt.get("partial", {}).get("source", case.name)]
    return out


def run(shared: Path, start_name: str, options: RegistrationOptions, cases: int | None,
        use_box: bool = True, half: str | None = None,
        stretch: tuple[float, float, float] | None = None, mirror: bool = False,
        scale: float = 1.0) -> tuple[dict, np.ndarray]:
    models = load_models(shared, stretch)
    renderer = Renderer()
    runs, tiles = [], []
    of = halves(shared)
    folders = [c for c in sorted((shared / "cases").iterdir()) if half is None or of[c.name] == half][:cases]
    for case in folders:
        gt = json.loads((case / "gt.json").read_text())
        model = models[gt["model"]]
        photo = load_photo(case / "photo.jpg")
        R_gt = np.asarray(gt["R"], float)
        hint = json.loads((case / ("init.json" if start_name in ("gt", "box", "none") else start_name)).read_text())
        if mirror:
            photo, R_gt, hint = mirrored(photo, R_gt, hint, model)
        if scale != 1.0:
            photo, hint = rescaled(photo, hint, scale)
        bbox = hint["bbox"]
        init, box = None, None
        if start_name == "box":
            box = bbox  # the client's box alone: the search without a start camera, in the box
        elif start_name != "none":
            init = Camera.from_dict(hint)
            box = hint.get("bbox") if use_box else None
            if start_name == "gt":
                init = annotated_start(model, init, R_gt)
        res = register(photo, model, init_camera=init, bbox=box, options=options, renderer=renderer)
        start_cam = res.start_camera
        r = {
            "case": case.name,
            "half": of[case.name],
            "width": photo.shape[1],
            "height": photo.shape[0],
            "start_deg": rotation_error(init.R, R_gt) if init is not None else None,
            "search_start_deg": rotation_error(start_cam.R, R_gt),
            "final_deg": rotation_error(res.camera.R, R_gt),
            "viewpoint_deg": rotation_error(viewpoint(res.camera, model.mesh.sphere[0]), R_gt),
            "elevation_deg": elevation(res.camera.R, model),
            "annotated_elevation_deg": elevation(R_gt, model),
            "box_iou": box_iou(model, res.camera, bbox),
            "focal_widths": res.camera.focal / photo.shape[1],
            "loss": res.loss,
            "pose_stage": res.pose_stage,
            "confidence": res.confidence,
            "failed": res.failed,
            "seconds": res.seconds,
            "evaluations": res.evaluations,
            "camera": res.camera.to_dict(),
            "checks": res.checks,
        }
        runs.append(r)
        start_txt = f"{r['start_deg']:.1f}" if r["start_deg"] is not None else f"({r['search_start_deg']:.1f})"
        print(f"{case.name} {photo.shape[1]:5d}x{photo.shape[0]:<4d} start {start_txt:>6s} deg -> "
              f"{r['final_deg']:6.1f} deg (view {r['viewpoint_deg']:5.1f})  box {r['box_iou']:.2f}  "
              f"f {r['focal_widths']:.2f} W  "
              f"loss {r['loss']:.4f} {r['pose_stage']}  "
              f"conf {'-' if r['confidence'] is None else format(r['confidence'], '.2f')} "
              f"{'FLAGGED ' if r['failed'] else ''}{r['seconds']:.1f} s", flush=True)
        tiles.append(overlay_pair(photo, model, start_cam, res.camera, renderer, f"{case.name} start {start_txt}",
                                  f"final {r['final_deg']:.1f} deg box {r['box_iou']:.2f}"
                                  f"{' FLAGGED' if r['failed'] else ''}"))
    rows = [summarise({"start": start_name, "half": h}, [r for r in runs if r["half"] == h])
            for h in ("a", "b") if any(r["half"] == h for r in runs)]
    if len(rows) > 1:
        rows.append(summarise({"start": start_name, "half": "all"}, runs))
    print(table(rows, list(rows[0])))
    return {"rows": rows, "runs": runs}, tiles


def report_name(shared: Path, start: str, tag: str, *, no_box: bool = False, half: str | None = None,
                stretched: bool = False, mirror: bool = False, scale: float = 1.0) -> str:
    """The name of a run's report and contact sheet: the case set, the start, then what differs."""
    return (f"{shared.resolve().name}_" + start.removesuffix(".json") + ("_nobox" if no_box else "")
            + (f"_{half}" if half else "") + ("_stretched" if stretched else "") + ("_mirror" if mirror else "")
            + (f"_scale{scale:g}" if scale != 1.0 else "") + (f"_{tag}" if tag else ""))


def run_and_write(name: str, shared: Path, start_name: str, options: RegistrationOptions, cases: int | None,
                  use_box: bool = True, half: str | None = None,
                  stretch: tuple[float, float, float] | None = None, mirror: bool = False,
                  scale: float = 1.0) -> Path:
    """:func:`run`, then its report (with the options, the box, the stretch, the mirror and the scale) and contact sheet
    written under ``name``, both paths printed; the report's path."""
    data, tiles = run(shared, start_name, options, cases, use_box=use_box, half=half, stretch=stretch, mirror=mirror,
                      scale=scale)
    data["stretch"] = stretch
    data["mirror"] = mirror
    data["scale"] = scale
    data["options"] = options.flat()
    data["box"] = use_box
    path = write_report(name, data)
    print(path)
    print(write_sheet(name, tiles))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "real")
    ap.add_argument("--start", default="init.json",
                    help="start file of each case (init.json, init_box.json), gt (init.json turned to the "
                    "annotated rotation), box (init.json's box alone, no start camera) or none")
    ap.add_argument("--cases", type=int, default=None, help="only the first N cases")
    ap.add_argument("--half", choices=("a", "b"), default=None, help="only the cases of this half of split.json")
    ap.add_argument("--stretch", default=None, metavar="SX,SY,SZ",
                    help="register a copy of the model scaled along its file's axes (a close but not exact CAD)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a RegistrationOptions field, e.g. loss=invariant (repeatable)")
    ap.add_argument("--no-box", action="store_true", help="give only the start camera, not the start file's box")
    ap.add_argument("--mirror", action="store_true",
                    help="register each photo turned left to right, its start, box and annotation to match")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="register each photo resized by this factor, its start and box to match")
    ap.add_argument("--tag", default="", help="suffix of the report's name")
    args = ap.parse_args()
    if not (args.shared / "cases").is_dir():
        print(f"no real cases at {args.shared}; skipped")
        return
    options = parse_options(args.option)
    name = report_name(args.shared, args.start, args.tag, no_box=args.no_box, half=args.half,
                       stretched=args.stretch is not None, mirror=args.mirror, scale=args.scale)
    if args.scale <= 0:
        raise SystemExit("--scale takes a positive factor")
    stretch = None if args.stretch is None else tuple(float(v) for v in args.stretch.split(","))
    if stretch is not None and len(stretch) != 3:
        raise SystemExit("--stretch takes three factors SX,SY,SZ")
    run_and_write(name, args.shared, args.start, options, args.cases, use_box=not args.no_box, half=args.half,
                  stretch=stretch, mirror=args.mirror, scale=args.scale)  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
