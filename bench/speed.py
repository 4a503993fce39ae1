"""Per-evaluation cost (render + loss) against image size and mesh size.

Usage: .venv/bin/python bench/speed.py [--repeats N] [--loss NAME] [--shared ../shared/bench]
Prints a table and writes bench/results/speed.json. "pipeline LOD" is the mesh the finest
registration level renders: the level of detail for the silhouette's size, without the faces
no outside view sees (vehicle_pose.render.exterior). With the photoreal cases present, each of their
models is also timed at its first case's true camera.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from vehicle_pose import RegistrationOptions
from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.loss.alternatives import LOSSES, make_loss
from vehicle_pose.loss.invariant import make_target
from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.loading import load_mesh
from vehicle_pose.model.metadata import ModelInfo
from vehicle_pose.model.procedural import SEDAN, build_car
from vehicle_pose.photo import load_photo
from vehicle_pose.registration.fit import face_budget
from vehicle_pose.render.exterior import exterior_faces
from vehicle_pose.render.renderer import Frame, Renderer
from vehicle_pose.render.synth import synthesize

from common import photoreal_cases, table, write_report


def dense_sedan(target_faces: int, tmp: str) -> VehicleModel:
    """The procedural sedan with its body loft refined to about ``target_faces`` faces."""
    ring = int(np.sqrt(target_faces / 2 / 1.5))
    spec = dataclasses.replace(SEDAN, stations=int(1.5 * ring), ring=ring)
    scene, wheels = build_car(spec)
    path = f"{tmp}/sedan_{target_faces}.glb"
    scene.export(path)
    mesh = load_mesh(path)
    info = ModelInfo(f"sedan-{target_faces}", "dense sedan", mesh.source, "m", 1.0, "+z", "+x", wheels)
    return VehicleModel(info, mesh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--loss", default=RegistrationOptions().loss, choices=sorted(LOSSES),
                    help="the loss timed (default: the registration's default)")
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "bench",
                    help="photoreal cases whose models are timed too, when present")
    args = ap.parse_args()
    import tempfile

    renderer = Renderer()
    rows: list[dict] = []
    options = RegistrationOptions()

    def time_meshes(name: str, model: VehicleModel, cam: Camera, photo: np.ndarray, mask: np.ndarray) -> None:
        loss = make_loss(args.loss, make_target(photo, mask, color=False))
        lod = model.lod(face_budget(float(mask.sum()), options.pyramid))
        for label, mesh in (("full mesh", model.mesh), ("pipeline LOD", exterior_faces(renderer, lod))):
            frame = renderer.render(mesh, cam)
            loss(frame)
            t0 = time.perf_counter()
            for _ in range(args.repeats):
                renderer.render(mesh, cam)
            t_render = (time.perf_counter() - t0) / args.repeats
            # A fresh Frame each time, so that nothing a frame caches is reused.
            copies = [Frame(frame.attrs, frame.labels, frame.x0, frame.y0, frame.width, frame.height)
                      for _ in range(args.repeats)]
            t0 = time.perf_counter()
            for f in copies:
                loss(f)
            t_loss = (time.perf_counter() - t0) / args.repeats
            rows.append({
                "model": name, "faces": model.mesh.n_faces, "image": f"{cam.width}x{cam.height}", "mesh": label,
                "rendered faces": mesh.n_faces, "silhouette px": frame.pixel_count, "render ms": 1e3 * t_render,
                "loss ms": 1e3 * t_loss, "total ms": 1e3 * (t_render + t_loss),
            })
            print(table(rows[-1:], list(rows[-1])).splitlines()[-1], flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        for target in (10_000, 100_000, 1_000_000):
            model = dense_sedan(target, tmp)
            centre, _ = model.mesh.sphere
            for W, H in ((320, 240), (640, 480)):
                cam = look_at_camera(centre, [1, 0, 0], [0, 0, 1], azimuth_deg=130, elevation_deg=15,
                                     distance=9.0, focal=900.0 * W / 640, width=W, height=H)
                photo, mask = synthesize(model.mesh, cam, renderer=renderer)
                time_meshes("sedan", model, cam, photo, mask)
    if (args.shared / "models.json").is_file():
        seen: set[str] = set()
        for case, gt, model in photoreal_cases(args.shared):
            if model.info.id in seen:
                continue
            seen.add(model.info.id)
            photo = load_photo(case / "photo.jpg")
            cam = Camera.from_dict(gt).scaled(photo.shape[1], photo.shape[0])
            mask = renderer.render(model.mesh, cam).coverage
            time_meshes(model.info.id, model, cam, photo, mask)
    cols = ["model", "faces", "image", "mesh", "rendered faces", "silhouette px", "render ms", "loss ms", "total ms"]
    print(table(rows, cols))
    gl = renderer.ctx.info
    print(write_report("speed", {"renderer": gl["GL_RENDERER"], "loss": args.loss, "rows": rows}))


if __name__ == "__main__":
    main()
