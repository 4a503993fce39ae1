"""Cold and warm start: what a process pays before and around the engine's own work.

For each model (the shipped library, the photoreal benchmark's meshes when ``../shared/bench``
is there, the real benchmark's 2 MB ShapeNet OBJ when ``../shared/real`` is there, and a
2-million-triangle mesh made by subdividing the shipped sedan):

- ``prepare_s``: first preparation into an empty store (``vehicle-pose prepare``, wall time);
- ``load_s``: loading the prepared model in a fresh process (median of three);
- ``cold_wall_s`` / ``warm_wall_s``: wall time of one ``vehicle-pose register`` without the
  store (``--no-cache``: everything prepared in the process, as before the store) and with a
  prepared store, against ``engine_s``, the seconds the engine reports for that run;
- ``same``: largest difference between the two runs' K, R, t (0 when identical).

Also the wall time of ``vehicle-pose --help`` and ``vehicle-pose models``. Run one at a time:
timings on two cores are only comparable without other load.

    .venv/bin/python bench/coldstart.py [--skip-2m] [--only ID,ID]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
ROOT = HERE.parent
CLI = [sys.executable, "-m", "vehicle_pose.cli"]

from vehicle_pose.geometry.camera import look_at_camera  # noqa: E402
from vehicle_pose.model.library import ModelLibrary  # noqa: E402
from vehicle_pose.model.metadata import parse_axis  # noqa: E402

from common import table, write_report  # noqa: E402


def _run(cmd: list[str], env: dict[str, str]) -> tuple[float, subprocess.CompletedProcess[str]]:
    t = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if done.returncode not in (0, 4):
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return time.perf_counter() - t, done


def _subdivided_sedan(folder: Path, times: int = 4) -> Path:
    """The shipped sedan with every triangle split in four ``times`` times (8240 -> 2.1M faces)."""
    import trimesh

    scene = trimesh.load(ModelLibrary().info("sedan").mesh_path, force="scene")
    out = trimesh.Scene()
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name].copy()
        geom.apply_transform(transform)
        v, f = geom.vertices, geom.faces
        for _ in range(times):
            v, f = trimesh.remesh.subdivide(v, f)
        part = trimesh.Trimesh(v, f, process=False)
        part.visual = trimesh.visual.TextureVisuals(material=geom.visual.material)
        out.add_geometry(part, geom_name=name)
    path = folder / "sedan-2m.glb"
    out.export(path)
    return path


def _synthetic_case(model_id: str, folder: Path) -> tuple[Path, Path]:
    """A photo of a shipped model rendered by the project (and a start camera 6 degrees off)."""
    from vehicle_pose.render.synth import synthesize

    model = ModelLibrary().load(model_id)
    centre, _ = model.mesh.sphere
    up, fwd = parse_axis(model.info.up), parse_axis(model.info.forward)
    truth = look_at_camera(centre, fwd, up, azimuth_deg=35.0, elevation_deg=12.0, distance=9.0, focal=900.0,
                           width=640, height=480)
    start = look_at_camera(centre, fwd, up, azimuth_deg=41.0, elevation_deg=9.0, distance=9.3, focal=900.0,
                           width=640, height=480)
    photo, _ = synthesize(model.mesh, truth, seed=1)
    import cv2

    cv2.imwrite(str(folder / f"{model_id}.png"), photo[..., ::-1])
    (folder / f"{model_id}_init.json").write_text(json.dumps(start.to_dict()))
    return folder / f"{model_id}.png", folder / f"{model_id}_init.json"


def _cases(args: argparse.Namespace, work: Path) -> list[dict]:
    """(id, model spec, CLI axes, photo, init camera) for every model measured."""
    cases: list[dict] = []
    lib = ModelLibrary()
    for mid in lib.ids():
        photo, init = (ROOT / "examples/sedan.jpg", ROOT / "examples/sedan_init.json") if mid == "sedan" \
            else _synthetic_case(mid, work)
        cases.append({"id": mid, "spec": str(lib.info(mid).mesh_path),
                      "axes": [lib.info(mid).up, lib.info(mid).forward],
                      "photo": photo, "init": init, "kind": "shipped"})
    bench = args.shared / "bench"
    if (bench / "models.json").is_file():
        catalogue = {m["id"]: m for m in json.loads((bench / "models.json").read_text())}
        seen: set[str] = set()
        for case in sorted((bench / "cases").iterdir()):
            mid = json.loads((case / "gt.json").read_text())["model"]
            if mid in seen or mid not in catalogue:
                continue
            seen.add(mid)
            entry = catalogue[mid]
            extra = ["--texture-dir", str(bench / entry["texture_dir"])] if entry.get("texture_dir") else []
            cases.append({"id": mid, "spec": str(bench / entry["mesh"]), "axes": [entry["up"], entry["forward"]],
                          "photo": case / "photo.jpg", "init": case / "init.json", "kind": "photoreal", "extra": extra})
    real = args.shared / "real"
    if (real / "models.json").is_file():
        entry = json.loads((real / "models.json").read_text())[0]
        case = sorted((real / "cases").iterdir())[0]
        cases.append({"id": entry["id"], "spec": str(real / entry["mesh"]), "axes": [entry["up"], entry["forward"]],
                      "photo": case / "photo.jpg", "init": case / "init.json", "kind": "real"})
    if not args.skip_2m:
        cases.append({"id": "sedan-2m", "spec": str(_subdivided_sedan(work)), "axes": ["+z", "+x"],
                      "photo": ROOT / "examples/sedan.jpg", "init": ROOT / "examples/sedan_init.json", "kind": "2M"})
    if args.only:
        keep = set(args.only.split(","))
        cases = [c for c in cases if c["id"] in keep]
    return cases


_LOAD = """
import sys, time
from vehicle_pose.model.library import model_from_mesh
from vehicle_pose.model.store import ModelStore
t = time.perf_counter()
m = model_from_mesh(sys.argv[1], up=sys.argv[2], forward=sys.argv[3], store=ModelStore(sys.argv[4]),
                    texture_dirs=tuple(sys.argv[5:]))
print(time.perf_counter() - t)
"""


def _pose(path: Path) -> np.ndarray:
    data = json.loads(path.read_text())
    return np.array(data["cam_K"] + data["cam_R_m2c"] + data["cam_t_m2c"])


def measure(case: dict, work: Path) -> dict:
    cache = work / f"cache-{case['id']}"
    shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, VEHICLE_POSE_CACHE_DIR=str(cache))
    axes = ["--up", case["axes"][0], "--forward", case["axes"][1]]
    extra = case.get("extra", [])
    textures = [extra[1]] if extra else []
    prepare_s, done = _run([*CLI, "prepare", case["spec"], *axes, *extra], env)
    faces = int(done.stderr.split("(")[1].split(" faces")[0]) if "(" in done.stderr else 0
    loads = []
    for _ in range(3):
        _, out = _run([sys.executable, "-c", _LOAD, case["spec"], *case["axes"], str(cache / "prepared"), *textures],
                      env)
        loads.append(float(out.stdout.strip().splitlines()[-1]))
    register = [*CLI, "register", str(case["photo"]), "--model", case["spec"], *axes, "--init-camera",
                str(case["init"]), *extra]
    cold_out, warm_out = work / f"{case['id']}-cold.json", work / f"{case['id']}-warm.json"
    cold_s, _ = _run([*register, "--out", str(cold_out), "--no-cache"], env)
    warm_s, _ = _run([*register, "--out", str(warm_out)], env)
    engine_cold = json.loads(cold_out.read_text())["seconds"]
    engine_warm = json.loads(warm_out.read_text())["seconds"]
    return {
        "model": case["id"], "kind": case["kind"], "faces": faces, "mesh_mb": Path(case["spec"]).stat().st_size / 1e6,
        "prepare_s": prepare_s, "load_s": statistics.median(loads),
        "cold_wall_s": cold_s, "cold_engine_s": engine_cold, "warm_wall_s": warm_s, "engine_s": engine_warm,
        "warm_ratio": warm_s / engine_warm,
        "same": float(np.abs(_pose(cold_out) - _pose(warm_out)).max()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--skip-2m", action="store_true", help="leave out the 2-million-triangle mesh")
    ap.add_argument("--only", help="comma-separated model ids")
    args = ap.parse_args()
    env = dict(os.environ)
    commands = []
    for argv in (["--help"], ["models"]):
        times = [_run([*CLI, *argv], env)[0] for _ in range(3)]
        commands.append({"command": "vehicle-pose " + " ".join(argv), "wall_s": statistics.median(times)})
    print(table(commands, ["command", "wall_s"]))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for case in _cases(args, work):
            row = measure(case, work)
            rows.append(row)
            print(f"{row['model']:<20} prepare {row['prepare_s']:6.1f} s  load {row['load_s']:.3f} s  "
                  f"cold {row['cold_wall_s']:5.1f} s  warm {row['warm_wall_s']:5.1f} s "
                  f"/ engine {row['engine_s']:5.1f} s  "
                  f"same {row['same']:.1e}", flush=True)
    columns = ["model", "kind", "faces", "mesh_mb", "prepare_s", "load_s", "cold_wall_s", "cold_engine_s",
               "warm_wall_s", "engine_s", "warm_ratio", "same"]
    print(table(rows, columns))
    path = write_report("coldstart", {"commands": commands, "models": rows})
    print(f"-> {path}")


if __name__ == "__main__":
    main()
