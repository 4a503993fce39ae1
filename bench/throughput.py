"""Rendering a population of poses: one draw a pose, the population drawn together, and the
chamfer overlapped with the next draw.

Usage: .venv/bin/python bench/throughput.py [--shared ../shared/real] [--poses 200]
       [--sizes 160,320,640] [--generation N] [--repeats 5] [--case NAME] [--registrations 12]
       [--modes hinted-real,...] [--tag T]

The searches that score populations (the structure's cross-entropy generations, CMA-ES) hand
the renderer each generation whole (:meth:`Renderer.render_many`, issue 36: "evaluate
populations in batches"). This measures, on the renderer this machine has, a pose's
milliseconds:

- ``single``: :meth:`Renderer.render` for each pose;
- ``together``: :meth:`Renderer.render_many` of all the poses: up to 100 a draw call, each into
  its own layer of layered targets (:mod:`vehicle_pose.render.layers`; one at a time where the
  context cannot); with ``--generation N``, N poses a call, as a search hands over its
  generations (CMA-ES's are 9 poses in seven dimensions). Its frames must equal the single
  draws' bit for bit: checked;
- ``chamfer`` and ``together + chamfer``: the same, each frame then scored by the structure's
  chamfer (:class:`EdgeLoss`), as its searches do;
- ``overlapped``: single draws and read-backs made through ctypes (which lets go of Python's
  lock, as the exterior pass does), each chamfer computed on a second thread while the next
  pose draws (the chamfer is compiled without the lock); not in the engine. Its values are
  checked equal.

The poses: a case's start camera (its ``init.json``; the first case unless ``--case``) at each
size, turned by random rotations of 8 degrees (seed 0), the exterior level the structure
renders. The runs take turns (a shared VM's speed drifts); the median of ``--repeats``.

Then whole registrations: ``--registrations`` cases of each of ``--modes`` (as
``bench/stages.py`` picks them) each registered twice, by a renderer that draws populations
together and by one that does not (``Renderer(layers=False)``), which first in turns; the
engine's seconds of each and the median of their ratios, the poses checked equal. Prints two
tables and writes bench/results/throughput[_TAG].json.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import moderngl
import numpy as np
from real import load_models
from stages import cases, prepared

from vehicle_pose import RegistrationOptions
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.loss.edges import EdgeLoss
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.photo import load_photo, resized
from vehicle_pose.registration.register import register
from vehicle_pose.render.gl import gl_library
from vehicle_pose.render.renderer import Frame, Renderer, _matrices, clip_planes, uniform

from common import same_frames, table, write_report

SHARED = Path(__file__).resolve().parents[2] / "shared"

_TRIANGLES, _UNSIGNED_INT, _UNSIGNED_BYTE, _FLOAT = 0x0004, 0x1405, 0x1401, 0x1406
_RGBA, _RED, _COLOR0 = 0x1908, 0x1903, 0x8CE0


def _gl() -> ctypes.CDLL:
    """The GL dispatch library, the calls of :func:`render_unlocked` typed."""
    lib = gl_library()
    if lib is None:
        raise SystemExit("no OpenGL library to call through ctypes")
    signatures = {
        "glDrawElements": [ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_void_p],
        "glReadPixels": [ctypes.c_int] * 4 + [ctypes.c_uint] * 2 + [ctypes.c_void_p],
        "glReadBuffer": [ctypes.c_uint],
        "glUseProgram": [ctypes.c_uint],
        "glBindVertexArray": [ctypes.c_uint],
    }
    for name, args in signatures.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, None
    return lib


def _window(mesh: Mesh, camera: Camera) -> tuple[int, int, int, int]:
    """The renderer's read-back window for ``camera`` (the poses measured are all in view)."""
    window = Renderer.window(mesh, camera)
    if window is None:
        raise SystemExit("a pose puts the model out of view")
    return window


def render_unlocked(renderer: Renderer, mesh: Mesh, camera: Camera, gl: ctypes.CDLL) -> Frame:
    """:meth:`Renderer.render`, its draw and read-back made through ctypes (Python's lock let go)."""
    near, far = clip_planes(mesh, camera)  # type: ignore[misc]
    mvp, mv = _matrices(camera, near, far)
    x0, y0, w, h = win = _window(mesh, camera)
    program, ctx = renderer.program, renderer.ctx
    uniform(program, "mvp").write(mvp.T.astype("f4").tobytes())
    uniform(program, "mv").write(mv.T.astype("f4").tobytes())
    renderer._begin(renderer.framebuffer(camera.width, camera.height), camera.width, camera.height, win)
    gl.glUseProgram(program.glo)
    for vao, cull in renderer._gpu_mesh(mesh).draws:
        (ctx.enable if cull else ctx.disable)(moderngl.CULL_FACE)
        gl.glBindVertexArray(vao.glo)
        gl.glDrawElements(_TRIANGLES, vao.vertices, _UNSIGNED_INT, None)
    attrs = np.empty((h, w, 4), np.float32)
    labels = np.empty((h, w), np.uint8)
    gl.glReadBuffer(_COLOR0)
    gl.glReadPixels(x0, y0, w, h, _RGBA, _FLOAT, attrs.ctypes.data)
    gl.glReadBuffer(_COLOR0 + 1)
    gl.glReadPixels(x0, y0, w, h, _RED, _UNSIGNED_BYTE, labels.ctypes.data)
    ctx.scissor = None
    return Frame(attrs, labels, x0, y0, camera.width, camera.height)


def timed(runs: dict[str, Callable[[], object]], repeats: int, count: int) -> dict[str, float]:
    """Milliseconds a pose of each of ``runs`` over ``count`` poses, the median of ``repeats``;
    the runs take turns, so that a machine whose speed drifts (a shared VM) slows them alike."""
    times: dict[str, list[float]] = {name: [] for name in runs}
    for run in runs.values():
        run()
    for _ in range(repeats):
        for name, run in runs.items():
            t = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - t)
    return {name: 1e3 * float(np.median(ts)) / count for name, ts in times.items()}


def measure(renderer: Renderer, mesh: Mesh, photo: np.ndarray, start: Camera, size: int, turns: list[np.ndarray],
            gl: ctypes.CDLL, pool: ThreadPoolExecutor, args: argparse.Namespace) -> dict[str, object]:
    """One row of the table: the poses at ``size`` pixels on the photo's longer side."""
    options = RegistrationOptions()
    scale = size / max(start.width, start.height)
    w, h = max(8, round(start.width * scale)), max(8, round(start.height * scale))
    ref = start.scaled(w, h)
    cams = [Camera(ref.K.copy(), turn @ ref.R, ref.t.copy(), w, h) for turn in turns]
    edges = EdgeLoss(resized(photo, w, h), tau=options.structure.anchor_tau, crease=options.terms.edge_crease)
    single = [renderer.render(mesh, cam) for cam in cams]
    n = args.generation if args.generation > 0 else len(cams)  # poses handed over at a time
    row: dict[str, object] = {"size": f"{w}x{h}", "faces": mesh.n_faces, "poses": len(cams), "generation": n}
    values = [edges(f) for f in single]

    def overlapped() -> list[float]:
        futures = [pool.submit(edges, render_unlocked(renderer, mesh, cam, gl)) for cam in cams]
        return [f.result() for f in futures]

    def together() -> list[Frame]:
        return [f for k in range(0, len(cams), n) for f in renderer.render_many(mesh, cams[k : k + n])]

    runs: dict[str, Callable[[], object]] = {
        "single": lambda: [renderer.render(mesh, cam) for cam in cams],
        "together": together,
        "chamfer": lambda: [edges(renderer.render(mesh, cam)) for cam in cams],
        "together + chamfer": lambda: [edges(f) for f in together()],
        "overlapped": overlapped,
    }
    row["together identical"] = same_frames(together(), single)
    row["overlapped identical"] = overlapped() == values
    row.update({f"{name} ms": ms for name, ms in timed(runs, args.repeats, len(cams)).items()})
    if renderer.ctx.error != "GL_NO_ERROR":
        raise SystemExit("an OpenGL error while measuring")
    print(row, flush=True)
    return row


def registrations(mode: str, count: int, shared: Path) -> dict[str, object]:
    """Each of ``count`` cases of ``mode`` (bench/stages.py's modes) registered twice, by a
    renderer that draws populations together and one that draws them one at a time, in turns
    (which first alternates); the poses must be equal."""
    together, alone = Renderer(), Renderer(layers=False)
    options = RegistrationOptions()
    picked = cases(mode, shared, SHARED / "bench", count)
    for model in {id(m): m for _, _, m, _ in picked}.values():
        prepared(model, together)
        prepared(model, alone)
    times: dict[str, list[float]] = {"together": [], "alone": []}
    for k, (name, path, model, hint) in enumerate(picked):
        photo = load_photo(path)
        hinted = mode.startswith("hinted")
        poses = {}
        for which in ("alone", "together") if k % 2 else ("together", "alone"):
            renderer = together if which == "together" else alone
            res = register(photo, model, init_camera=Camera.from_dict(hint) if hinted else None,
                           bbox=hint.get("bbox") if hinted else None, options=options, renderer=renderer)
            times[which].append(res.seconds)
            poses[which] = res.camera.to_dict()
        if poses["together"] != poses["alone"]:
            raise SystemExit(f"{name}: the pose differs when the poses are drawn together")
        print(f"{mode} {name}: together {times['together'][-1]:.2f} s, alone {times['alone'][-1]:.2f} s", flush=True)
    ratio = np.array(times["together"]) / np.array(times["alone"])
    return {"mode": mode, "cases": len(picked), "together s": float(np.median(times["together"])),
            "alone s": float(np.median(times["alone"])), "median ratio": float(np.median(ratio)),
            "poses equal": True}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=SHARED / "real")
    ap.add_argument("--poses", type=int, default=200)
    ap.add_argument("--sizes", default="160,320,640", help="the photo's longer side, pixels")
    ap.add_argument("--generation", type=int, default=0,
                    help="poses handed to the renderer at a time in the together runs (0: all)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--case", default="", help="the case whose photo and start are used (default: the first)")
    ap.add_argument("--registrations", type=int, default=12,
                    help="cases of each of --modes registered both ways (0: none)")
    ap.add_argument("--modes", default="hinted-real", help="bench/stages.py's modes, for --registrations")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    renderer = Renderer()
    model = next(iter(load_models(args.shared).values()))
    model.prepare(renderer)
    case = args.shared / "cases" / args.case if args.case else sorted((args.shared / "cases").iterdir())[0]
    photo = load_photo(case / "photo.jpg")
    start = Camera.from_dict(json.loads((case / "init.json").read_text()))
    mesh = model.exterior(RegistrationOptions().pyramid.min_faces, renderer)
    gl = _gl()
    pool = ThreadPoolExecutor(1)
    rng = np.random.default_rng(0)
    turns = [cv2.Rodrigues(rng.standard_normal(3) * np.radians(8.0))[0] for _ in range(args.poses)]
    rows = [measure(renderer, mesh, photo, start, size, turns, gl, pool, args)
            for size in (int(s) for s in args.sizes.split(","))]
    print(table(rows, list(rows[0])))
    paired = [registrations(mode, args.registrations, args.shared) for mode in args.modes.split(",")
              if args.registrations > 0]
    if paired:
        print(table(paired, list(paired[0])))
    name = "throughput" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"rows": rows, "registrations": paired, "case": case.name, "layers": renderer.draws_layers,
                              "renderer": renderer.ctx.info["GL_RENDERER"]}))


if __name__ == "__main__":
    main()
