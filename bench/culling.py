"""Faces culled on the CPU before each draw: what llvmpipe would save, and what choosing them costs.

Usage: .venv/bin/python bench/culling.py [--real ../shared/real] [--photoreal ../shared/bench]
       [--cases 3] [--sizes 160,240,320,640] [--repeats 60] [--tag T]

A software rasteriser pays for every triangle it is handed, culled or not. Two kinds of faces
could be left out of a pose's draw without changing a pixel: the faces of one-sided parts that
turn their back to the camera (the renderer culls them after the vertex stage), and the faces
whose box holds no pixel centre (they give no fragment; the exterior pass leaves such faces out
of its views for the same reason). For each case's start camera at each size, this draws the
exterior level the searches draw (``min_faces``) whole and with each kind of face left out,
checks every frame against the whole one (labels and covered attributes, bit for bit), and
times the draws (taking turns, the median of two runs of ``--repeats``) and the choice of the
faces (projecting the vertices and testing every face, in NumPy). Prints one table and writes
bench/results/culling[_TAG].json.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from real import load_models

from vehicle_pose import RegistrationOptions
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.render.renderer import Renderer

from common import photoreal_cases, same_frames, table, write_report

SHARED = Path(__file__).resolve().parents[2] / "shared"
MARGIN = 0.05  # pixels a face's box must miss every pixel centre by (the exterior pass's margin)


def chosen(mesh: Mesh, camera: Camera, back: bool, slivers: bool) -> list[np.ndarray]:
    """For each part, which faces to draw: without the back faces of one-sided parts (``back``)
    and without the faces whose box holds no pixel centre (``slivers``)."""
    eye = -camera.R.T @ camera.t
    keep = []
    for part in mesh.parts:
        k = np.ones(len(part.faces), bool)
        corners = part.vertices[part.faces]
        if back and part.one_sided:
            normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            k &= np.einsum("ij,ij->i", normal, eye - corners[:, 0]) < 0
        if slivers:
            pc = camera.to_camera(part.vertices)
            uvw = pc @ camera.K.T
            uv = (uvw[:, :2] / uvw[:, 2:3])[part.faces]
            lo, hi = uv.min(axis=1), uv.max(axis=1)
            k &= np.all(np.floor(hi + MARGIN) >= np.ceil(lo - MARGIN), axis=1) | np.any(pc[part.faces][..., 2] <= 0,
                                                                                        axis=1)
        keep.append(k)
    return keep


def culled(mesh: Mesh, keep: list[np.ndarray]) -> Mesh:
    return Mesh(tuple(replace(p, faces=p.faces[k]) for p, k in zip(mesh.parts, keep, strict=True) if k.any()))


def ms(run: Callable[[], object], repeats: int) -> float:
    t = time.perf_counter()
    for _ in range(repeats):
        run()
    return 1e3 * (time.perf_counter() - t) / repeats


def measure(renderer: Renderer, mesh: Mesh, cam: Camera, name: str, repeats: int) -> dict[str, object]:
    """One row: ``mesh`` drawn by ``cam`` whole and with each kind of face left out."""
    whole = renderer.render(mesh, cam)
    kinds = {"back": (True, False), "slivers": (False, True), "both": (True, True)}
    meshes = {kind: culled(mesh, chosen(mesh, cam, *flags)) for kind, flags in kinds.items()}
    draws: dict[str, Callable[[], object]] = {"whole": lambda: renderer.render(mesh, cam)}
    for kind, m in meshes.items():
        draws[kind] = functools.partial(renderer.render, m, cam)
    times: dict[str, list[float]] = {kind: [] for kind in draws}
    for draw in draws.values():
        draw()
    for _ in range(2):  # in turns
        for kind, draw in draws.items():
            times[kind].append(ms(draw, repeats))
    row: dict[str, object] = {"case": name, "size": f"{cam.width}x{cam.height}", "faces": mesh.n_faces,
                              "whole ms": float(np.median(times["whole"]))}
    for kind, m in meshes.items():
        row[f"{kind} faces"] = m.n_faces
        row[f"{kind} ms"] = float(np.median(times[kind]))
        row[f"{kind} same"] = same_frames([whole], [renderer.render(m, cam)])
    row["choosing ms"] = ms(lambda: chosen(mesh, cam, True, True), max(1, repeats // 4))
    print(row, flush=True)
    return row


def rows_for(renderer: Renderer, mesh: Mesh, start: Camera, name: str, sizes: list[int],
             repeats: int) -> list[dict[str, object]]:
    """A row for each size (the photo's longer side) of ``start``."""
    rows = []
    for size in sizes:
        s = size / max(start.width, start.height)
        cam = start.scaled(max(8, round(start.width * s)), max(8, round(start.height * s)))
        rows.append(measure(renderer, mesh, cam, name, repeats))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=SHARED / "real")
    ap.add_argument("--photoreal", type=Path, default=SHARED / "bench")
    ap.add_argument("--cases", type=int, default=3, help="cases of each set (the first of each model for the renders)")
    ap.add_argument("--sizes", default="160,240,320,640", help="the photo's longer side, pixels")
    ap.add_argument("--repeats", type=int, default=60)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    renderer = Renderer()
    faces = RegistrationOptions().pyramid.min_faces
    sizes = [int(s) for s in args.sizes.split(",")]
    rows: list[dict[str, object]] = []
    model = next(iter(load_models(args.real).values()))
    model.prepare(renderer)
    for case in sorted((args.real / "cases").iterdir())[: args.cases]:
        start = Camera.from_dict(json.loads((case / "init.json").read_text()))
        rows += rows_for(renderer, model.exterior(faces, renderer), start, case.name, sizes, args.repeats)
    seen: set[str] = set()
    for case, _, m in photoreal_cases(args.photoreal):
        if m.info.id in seen or len(seen) >= args.cases:
            continue
        seen.add(m.info.id)
        m.prepare(renderer)
        start = Camera.from_dict(json.loads((case / "init.json").read_text()))
        rows += rows_for(renderer, m.exterior(faces, renderer), start, f"{case.name} ({m.info.id})", sizes,
                         args.repeats)
    columns = ["case", "size", "faces", "whole ms", "back faces", "back ms", "slivers faces", "slivers ms",
               "both faces", "both ms", "choosing ms"]
    print(table(rows, columns))
    identical = all(r[f"{k} same"] for r in rows for k in ("back", "slivers", "both"))
    print("every frame the same as the whole draw:", identical)
    name = "culling" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"renderer": renderer.ctx.info["GL_RENDERER"], "rows": rows, "faces": faces}))


if __name__ == "__main__":
    main()
