"""Helpers shared by the benchmark scripts: tables, JSON reports, error metrics, start poses."""

from __future__ import annotations

import ast
import json
import os
import platform
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vehicle_pose import RegistrationOptions
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.metrics import projection_error as _projection_error
from vehicle_pose.model.library import VehicleModel, model_from_mesh
from vehicle_pose.render.gl import get_context
from vehicle_pose.render.overlay import draw_overlay, save_png
from vehicle_pose.render.renderer import Frame, Renderer

RESULTS = Path(__file__).resolve().parent / "results"


def table(rows: list[dict], columns: list[str]) -> str:
    """A plain-text table of ``rows`` with ``columns`` (floats to 3 significant digits)."""

    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = [" | ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)), "-+-".join("-" * w for w in widths)]
    lines += [" | ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)


def machine() -> dict:
    """Where a benchmark ran: platform, processor, cores, Python and the OpenGL renderer."""
    info = get_context().info
    return {"platform": platform.platform(), "processor": platform.processor(), "cores": os.cpu_count(),
            "python": platform.python_version(), "gl_renderer": info["GL_RENDERER"], "gl_version": info["GL_VERSION"]}


def write_report(name: str, data: dict) -> Path:
    """Write ``bench/results/<name>.json`` with machine details and return its path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = ""
    data = {
        "benchmark": name,
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "commit": commit or os.environ.get("BENCH_COMMIT", ""),
        "machine": machine(),
        **data,
    }
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2) + "\n")
    return path


def same_frames(a: list[Frame], b: list[Frame]) -> bool:
    """Whether two lists of frames hold the same windows, labels and covered attributes."""
    return all(f.x0 == g.x0 and f.y0 == g.y0 and np.array_equal(f.labels, g.labels)
               and np.array_equal(f.covered(f.attrs), g.covered(g.attrs)) for f, g in zip(a, b, strict=True))


def rescaled_photo(photo: np.ndarray, factor: float) -> np.ndarray:
    """The photo resized by ``factor`` (pixel areas averaged when it shrinks, bicubic when it
    grows), at least 8 pixels a side: the same scene photographed larger or smaller."""
    H, W = photo.shape[:2]
    size = (max(8, round(W * factor)), max(8, round(H * factor)))
    return cv2.resize(photo, size, interpolation=cv2.INTER_AREA if factor < 1.0 else cv2.INTER_CUBIC)


def rescaled_box(box: list[float], sx: float, sy: float) -> list[float]:
    """A box ``x0, y0, x1, y1`` (pixel centres at integers) in a photo resized by ``sx``, ``sy``."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return [(x0 + 0.5) * sx - 0.5, (y0 + 0.5) * sy - 0.5, (x1 + 0.5) * sx - 0.5, (y1 + 0.5) * sy - 0.5]


def projection_error(points: np.ndarray, est: Camera, truth: Camera) -> float:
    """Mean vertex projection distance in pixels, scaled to a 640-pixel-wide image."""
    return _projection_error(points, est, truth, width=640.0)


def perturbed(truth: Camera, rng: np.random.Generator, degrees: float) -> Camera:
    """A start camera rotated by ``degrees`` about a random axis through the camera, moved by
    degrees/300 of the distance and with the focal length off by up to degrees/100."""
    axis = rng.normal(size=3)
    rot = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    centre_depth = np.linalg.norm(truth.t)
    t = rot @ truth.t + (degrees / 300.0) * centre_depth * rng.normal(size=3) / np.sqrt(3)
    t = t + (truth.t - rot @ truth.t)
    K = truth.K.copy()
    k = 1.0 + rng.uniform(-1, 1) * degrees / 100.0
    K[0, 0] *= k
    K[1, 1] *= k
    return Camera(K, rot @ truth.R, t, truth.width, truth.height)


def photoreal_cases(shared: Path):
    """Yield ``(case folder, gt dict, model)`` for each case of ``shared/cases``, sorted; each
    model of ``shared/models.json`` is loaded once (axes, scale and textures as listed)."""
    catalogue = {m["id"]: m for m in json.loads((shared / "models.json").read_text())}
    models: dict[str, VehicleModel] = {}
    for case in sorted((shared / "cases").iterdir()):
        gt = json.loads((case / "gt.json").read_text())
        entry = catalogue[gt["model"]]
        if entry["id"] not in models:
            texture = [shared / entry["texture_dir"]] if entry.get("texture_dir") else []
            m = model_from_mesh(shared / entry["mesh"], up=entry["up"], forward=entry["forward"], units="m",
                                meters_per_unit=entry["meters_per_unit"], texture_dirs=tuple(texture))
            models[entry["id"]] = VehicleModel(replace(m.info, id=entry["id"], name=entry["id"]), m.mesh)
        yield case, gt, models[entry["id"]]


def parse_options(pairs: list[str]) -> RegistrationOptions:
    """RegistrationOptions from KEY=VALUE strings, each value typed like the field's default
    (tuples as Python literals, e.g. ``focal_starts=(0.6,1.7)``)."""
    defaults = RegistrationOptions().flat()
    fields = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in defaults:
            raise SystemExit(f"unknown option {key!r}")
        kind = type(defaults[key])
        if kind is bool:
            fields[key] = value.lower() in ("1", "true", "yes")
        elif kind is tuple:
            fields[key] = tuple(ast.literal_eval(value))
        elif kind is type(None):
            fields[key] = ast.literal_eval(value)
        else:
            fields[key] = kind(value)
    return RegistrationOptions.from_flat(fields)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 16), (0, 0, 0), -1)
    cv2.putText(out, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def overlay_pair(photo: np.ndarray, model: VehicleModel, start: Camera, final: Camera, renderer: Renderer,
                 start_text: str, final_text: str) -> tuple[np.ndarray, np.ndarray]:
    """The start's and the result's outline on the photo, each captioned: one row of a contact sheet."""
    mesh = model.lod(16384)
    left = draw_overlay(photo, mesh, start, renderer=renderer, wheels=model.wheels)
    right = draw_overlay(photo, mesh, final, renderer=renderer, wheels=model.wheels)
    return _label(left, start_text), _label(right, final_text)


def contact_sheet(tiles: list[tuple[np.ndarray, np.ndarray]], width: int = 360) -> np.ndarray:
    """Rows of (start, final) overlays, each reduced to ``width`` pixels."""
    rows = []
    for left, right in tiles:
        h = max(1, round(left.shape[0] * width / left.shape[1]))
        pair = [cv2.resize(im, (width, h), interpolation=cv2.INTER_AREA) for im in (left, right)]
        rows.append(np.concatenate([pair[0], np.full((h, 6, 3), 255, np.uint8), pair[1]], axis=1))
    w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 6), (0, w - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows, axis=0)


def write_sheet(name: str, tiles: list[tuple[np.ndarray, np.ndarray]]) -> Path:
    """Write ``bench/results/<name>.png``, the contact sheet of ``tiles``, and return its path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.png"
    save_png(path, contact_sheet(tiles))
    return path


def publish(name: str, tag: str, rows: list[dict], data: dict, tiles: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Print ``rows`` as a table, then write ``bench/results/<name>[_<tag>].json`` (``rows`` and
    ``data``) and its contact sheet of ``tiles``, printing their paths."""
    print(table(rows, list(rows[0])))
    full = name + (f"_{tag}" if tag else "")
    print(write_report(full, {"rows": rows, **data}))
    print(write_sheet(full, tiles))
