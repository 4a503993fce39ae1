"""Real photos: is the objective's minimum wrong, or does the search not reach it?

Usage: .venv/bin/python bench/real_diagnose.py [--shared ../shared/real] [--option KEY=VALUE ...]
       [--cases N] [--tag TAG]

For each case of ``../shared/real``: register from ``init.json`` (with its box), then score the
objective the search minimises (the named loss plus ``edge_weight`` times the edge term) at

- the found pose, with the found pose's own GrabCut mask;
- the annotated rotation, its place, size and focal length refitted (300 simplex evaluations,
  rotation fixed) on the same mask;
- both again on a mask that GrabCut seeds with the annotated pose's silhouette;
- the annotated rotation placed by ``fit_to_box`` on the whole frame (these photos are crops to
  the car), on the found pose's mask: the loss, the edge term and the silhouette's IoU with the
  mask, beside the same for the found pose (``frame ...`` columns);
- the objective of the structure's anchored search (the chamfer, the place and size fitted to
  the client's box, the focal length the best of a grid) at the found rotation and at the
  annotated one (``structure ...`` columns; docs/decisions/0012-structure-first.md).

When the annotated rotation scores higher than the found pose on the same mask, the minimum
is wrong (the search found a better pose by the objective's own measure); when it scores lower,
the search did not reach it. Writes ``bench/results/real_diagnose[_TAG].json`` and, per case, a
picture of the two poses over the two masks and, below, both rotations tied to the box
(``real_diagnose[_TAG]/<case>.png``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from real import load_models

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.errors import CameraError, PoseError
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.geometry.parametrize import ViewParams
from vehicle_pose.loss.alternatives import make_loss
from vehicle_pose.loss.edges import EdgeLoss
from vehicle_pose.loss.invariant import make_target
from vehicle_pose.metrics import iou, rotation_error
from vehicle_pose.photo import load_photo, resized, resized_mask
from vehicle_pose.registration.structure import BoxAnchoredParams, StructureCost
from vehicle_pose.render.overlay import draw_overlay, save_png
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import NelderMeadRestarts
from vehicle_pose.search.views import fit_to_box
from vehicle_pose.segment.grabcut import grabcut_foreground

from common import RESULTS, parse_options, table, write_report


class Objective:
    """The search's objective on one photo and mask (the box term left out: it is zero within
    the box's tolerance, where both poses lie)."""

    def __init__(self, work: np.ndarray, mask: np.ndarray, options: RegistrationOptions, renderer: Renderer,
                 mesh) -> None:
        self.loss = make_loss(options.loss, make_target(work, mask, color=options.color))
        self.edges = EdgeLoss(work, foreground=mask) if options.terms.edge_weight > 0 else None
        self.weight, self.renderer, self.mesh = options.terms.edge_weight, renderer, mesh

    def __call__(self, camera: Camera) -> float:
        frame = self.renderer.render(self.mesh, camera)
        value = float(self.loss(frame))
        return value + (self.weight * self.edges(frame) if self.edges is not None else 0.0)


def refit_fixed_rotation(objective: Objective, model, camera: Camera, budget: int = 300) -> tuple[Camera, float]:
    """The best place, size and focal length for ``camera``'s rotation (view coordinates 3-6)."""
    centre, radius = model.mesh.sphere
    params = ViewParams(camera, centre, RegistrationOptions().probes.dolly_pivot * radius)

    def f(z: np.ndarray) -> float:
        x = np.concatenate([np.zeros(3), z])
        try:
            return objective(params.camera(x))
        except (PoseError, CameraError):
            return 10.0

    res = NelderMeadRestarts()(f, np.zeros(4), params.steps()[3:], max_evaluations=budget)
    return params.camera(np.concatenate([np.zeros(3), res.x])), float(res.fun)


def tied_to_box(work: np.ndarray, model, found: Camera, R: np.ndarray, box: list[float], W: int,
                options: RegistrationOptions, renderer: Renderer) -> tuple[Camera, float]:
    """``R`` as the structure's anchored search sees it: the place and size fitted to ``box``
    (photo pixels, the photo ``W`` wide), the focal length the best of a grid from a tenth to ten
    times ``found``'s; the camera (at ``work``'s size) and its cost."""
    Hf, Wf = work.shape[:2]
    s = min(1.0, options.structure.structure_size / max(Wf, Hf))
    w, h = max(8, round(Wf * s)), max(8, round(Hf * s))
    level_box = tuple(float(v) * w / W for v in box)
    cost = StructureCost(resized(work, w, h), model.exterior(options.pyramid.min_faces, renderer),
                         renderer, options, tau=options.structure.anchor_tau)
    ref = found.scaled(w, h)
    params = BoxAnchoredParams(ref, level_box, model.mesh.sample_points(1000), model.mesh.sphere[0])
    turn = cv2.Rodrigues(R @ ref.R.T)[0].ravel()
    value, g = min((cost(params.camera(np.r_[turn, g])), g) for g in np.linspace(-2.3, 2.3, 47))
    return params.camera(np.r_[turn, g]).scaled(Wf, Hf), float(value)


def annotated(camera: Camera, R: np.ndarray, centre: np.ndarray) -> Camera:
    """``camera`` turned to ``R`` about the model's centre."""
    c = camera.to_camera(centre[None])[0]
    return Camera(camera.K, R, c - R @ centre, camera.width, camera.height)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "real")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--cases", type=int, default=None)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    if not (args.shared / "cases").is_dir():
        print(f"no real cases at {args.shared}; skipped")
        return
    options = parse_options(args.option)
    name = "real_diagnose" + (f"_{args.tag}" if args.tag else "")
    pictures = RESULTS / name
    pictures.mkdir(parents=True, exist_ok=True)
    models = load_models(args.shared)
    renderer = Renderer()
    rows = []
    for case in sorted((args.shared / "cases").iterdir())[:args.cases]:
        gt = json.loads((case / "gt.json").read_text())
        model = models[gt["model"]]
        R_gt = np.asarray(gt["R"], float)
        hint = json.loads((case / "init.json").read_text())
        photo = load_photo(case / "photo.jpg")
        res = register(photo, model, init_camera=Camera.from_dict(hint), bbox=hint["bbox"], options=options,
                       renderer=renderer)
        H, W = photo.shape[:2]
        s = min(1.0, options.pyramid.max_size / max(W, H))
        Wf, Hf = round(W * s), round(H * s)
        work = resized(photo, Wf, Hf)
        mesh = model.exterior(16384, renderer)
        found = res.camera.scaled(Wf, Hf)
        own = resized_mask(res.foreground, Wf, Hf)
        on_own = Objective(work, own, options, renderer, mesh)
        truth, truth_own = refit_fixed_rotation(on_own, model, annotated(found, R_gt, model.mesh.sphere[0]))
        seeded = grabcut_foreground(work, renderer.render(model.lod(16384), truth).coverage, margin=0.08,
                                    sure_core=True, iterations=4, max_size=options.pyramid.max_size)
        on_seeded = Objective(work, seeded, options, renderer, mesh)
        truth2, truth_seeded = refit_fixed_rotation(on_seeded, model, truth)
        row = {
            "case": case.name,
            "found deg": rotation_error(found.R, R_gt),
            "found, own mask": on_own(found),
            "annotated, own mask": truth_own,
            "found, seeded mask": on_seeded(found),
            "annotated, seeded mask": truth_seeded,
            "mask iou": iou(own, seeded),
            "focal W found": found.focal / Wf,
            "focal W annotated": truth.focal / Wf,
        }
        row["minimum wrong"] = row["annotated, own mask"] > row["found, own mask"]
        framed = fit_to_box(annotated(found, R_gt, model.mesh.sphere[0]), model.mesh.sample_points(600),
                            model.mesh.sphere[0], (0.0, 0.0, Wf - 1.0, Hf - 1.0), clip=True)
        for label, cam in (("found", found), ("framed annotated", framed)):
            frame = renderer.render(mesh, cam)
            row[f"frame loss, {label}"] = float(on_own.loss(frame))
            row[f"frame edges, {label}"] = float(on_own.edges(frame)) if on_own.edges is not None else 0.0
            row[f"frame mask iou, {label}"] = iou(frame.coverage, own)
        tied_found, row["structure cost, found"] = tied_to_box(work, model, found, found.R, hint["bbox"], W, options,
                                                                renderer)
        tied_truth, row["structure cost, annotated"] = tied_to_box(work, model, found, R_gt, hint["bbox"], W, options,
                                                                   renderer)
        row["structure minimum wrong"] = row["structure cost, annotated"] > row["structure cost, found"]
        rows.append(row)
        print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
        over = np.concatenate([draw_overlay(work, model.lod(16384), found, renderer=renderer, shade=0.5),
                               draw_overlay(work, model.lod(16384), truth2, renderer=renderer, shade=0.5)], 1)
        masks = np.concatenate([own, seeded], 1)[..., None].repeat(3, 2).astype(np.uint8) * 255
        tied = np.concatenate([draw_overlay(work, model.lod(16384), tied_found, renderer=renderer),
                               draw_overlay(work, model.lod(16384), tied_truth, renderer=renderer)], 1)
        save_png(pictures / f"{case.name}.png", np.concatenate([over, masks, tied], 0))
    summary = [{
        "cases": len(rows),
        "minimum wrong, own mask": sum(r["minimum wrong"] for r in rows),
        "minimum wrong, seeded mask": sum(r["annotated, seeded mask"] > r["found, seeded mask"] for r in rows),
        "structure minimum wrong": sum(r["structure minimum wrong"] for r in rows),
        "median found deg": float(np.median([r["found deg"] for r in rows])),
        "median mask iou": float(np.median([r["mask iou"] for r in rows])),
    }]
    print(table(summary, list(summary[0])))
    print(write_report(name, {"rows": summary, "runs": rows, "options": options.flat()}))


if __name__ == "__main__":
    main()
