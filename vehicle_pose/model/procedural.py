"""Procedurally built cars: body, glass, tyres, rims and lights as separate material parts.

The body is a loft of rounded cross-sections along the car's length, following a side profile
and arching over the wheels; the greenhouse narrows towards the roof and its side faces form the
glass part. Axes: forward +x, left +y, up +z, metres, ground at z = 0. The wheel metadata of a
generated car is exact, and so are its part labels: every face of the body and the glass is
labelled by the panel or window it was built as (:func:`construction_parts`), written beside
the model as ``parts.json`` (the body stays one surface: panels split apart would shade their
seams apart).

Run ``python -m vehicle_pose.model.procedural DIR`` to (re)write the shipped models into DIR.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh

from vehicle_pose.model.metadata import WheelGeometry
from vehicle_pose.model.parts import part_file_text

__all__ = ["CarSpec", "SEDAN", "HATCHBACK", "SUV", "VAN", "PICKUP", "SPECS", "build_car", "construction_parts",
           "write_model"]


@dataclass(frozen=True)
class CarSpec:
    """Shape of a procedural car; lengths in metres.

    ``top`` is the side profile: (x, height of the upper surface) pairs from the front bumper
    to the rear bumper. ``glass_x`` is the length range of the greenhouse.
    """

    id: str
    name: str
    length: float
    width: float
    wheelbase: float
    track: float
    wheel_radius: float
    tyre_width: float
    clearance: float
    belt: float
    roof_inset: float
    top: tuple[tuple[float, float], ...]
    glass_x: tuple[float, float]
    body_albedo: float = 0.7
    stations: int = 72
    ring: int = 48


SEDAN = CarSpec(
    id="sedan",
    name="Procedural sedan",
    length=4.6,
    width=1.8,
    wheelbase=2.7,
    track=1.55,
    wheel_radius=0.32,
    tyre_width=0.21,
    clearance=0.18,
    belt=0.98,
    roof_inset=0.22,
    top=((2.3, 0.62), (2.2, 0.84), (0.95, 0.98), (0.15, 1.44), (-0.95, 1.44), (-1.6, 1.04), (-2.25, 1.0), (-2.3, 0.7)),
    glass_x=(-1.55, 0.9),
)

HATCHBACK = CarSpec(
    id="hatchback",
    name="Procedural hatchback",
    length=4.05,
    width=1.75,
    wheelbase=2.55,
    track=1.5,
    wheel_radius=0.31,
    tyre_width=0.2,
    clearance=0.16,
    belt=0.95,
    roof_inset=0.2,
    top=((2.02, 0.6), (1.92, 0.84), (0.85, 0.97), (0.05, 1.46), (-1.6, 1.43), (-1.96, 1.18), (-2.02, 0.92),
         (-2.02, 0.62)),
    glass_x=(-1.9, 0.78),
    body_albedo=0.55,
)

SUV = CarSpec(
    id="suv",
    name="Procedural SUV",
    length=4.75,
    width=1.92,
    wheelbase=2.82,
    track=1.64,
    wheel_radius=0.38,
    tyre_width=0.24,
    clearance=0.26,
    belt=1.14,
    roof_inset=0.15,
    top=((2.37, 0.78), (2.27, 1.04), (1.2, 1.17), (0.45, 1.74), (-2.05, 1.76), (-2.33, 1.55), (-2.37, 1.05),
         (-2.37, 0.8)),
    glass_x=(-2.2, 1.1),
    body_albedo=0.4,
)

VAN = CarSpec(
    id="van",
    name="Procedural van",
    length=5.1,
    width=1.98,
    wheelbase=3.25,
    track=1.7,
    wheel_radius=0.36,
    tyre_width=0.22,
    clearance=0.2,
    belt=1.12,
    roof_inset=0.05,
    top=((2.55, 0.78), (2.45, 1.06), (1.95, 1.24), (1.2, 2.02), (-2.5, 2.04), (-2.55, 1.9), (-2.55, 0.72)),
    glass_x=(0.55, 2.0),
    body_albedo=0.85,
)

PICKUP = CarSpec(
    id="pickup",
    name="Procedural pickup",
    length=5.35,
    width=1.96,
    wheelbase=3.4,
    track=1.7,
    wheel_radius=0.4,
    tyre_width=0.26,
    clearance=0.28,
    belt=1.2,
    roof_inset=0.12,
    top=((2.67, 0.82), (2.57, 1.14), (1.5, 1.24), (0.75, 1.86), (-0.55, 1.87), (-0.68, 1.28), (-2.62, 1.27),
         (-2.67, 0.86)),
    glass_x=(-0.66, 1.32),
    body_albedo=0.3,
)

SPECS: tuple[CarSpec, ...] = (SEDAN, HATCHBACK, SUV, VAN, PICKUP)
"""Every body type shipped in ``vehicle_models/``."""


def _profile(spec: CarSpec, x: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Bottom and top heights of the body at stations x."""
    px = np.array([p[0] for p in spec.top])[::-1]
    pz = np.array([p[1] for p in spec.top])[::-1]
    top = np.interp(x, px, pz)
    half = spec.length / 2
    bottom = spec.clearance + 0.2 * np.clip((np.abs(x) - (half - 0.45)) / 0.45, 0.0, 1.0)
    arch = spec.wheel_radius + 0.06
    for xa in (-spec.wheelbase / 2, spec.wheelbase / 2):
        d = np.abs(x - xa)
        over = np.where(d < arch, spec.wheel_radius + np.sqrt(np.maximum(arch * arch - d * d, 0.0)), 0.0)
        bottom = np.maximum(bottom, over)
    return bottom, np.maximum(top, bottom + 0.1)


@dataclass(frozen=True)
class _Loft:
    """The body's loft: vertices, triangles, the greenhouse's side faces (``glass``), the end
    caps (``cap``), and where each triangle's panel is judged: ``panel_at``, the centre of the
    quad it belongs to, ``panel_rise``, that quad's place around the cross-section (the sine
    half-way along its ring edge: 1 on top, -1 underneath), and ``panel_normal``, the quad's
    normal (the cross product of its diagonals; its sign is not kept); a cap's triangle keeps
    its own centroid, its first vertex's sine and its own normal. Both triangles of a quad so go
    to one panel, and a panel's edge runs along the quads' edges instead of zigzagging through
    every quad a seam crosses."""

    vertices: npt.NDArray[np.float64]
    tris: npt.NDArray[np.int64]
    glass: npt.NDArray[np.bool_]
    cap: npt.NDArray[np.bool_]
    panel_at: npt.NDArray[np.float64]
    panel_rise: npt.NDArray[np.float64]
    panel_normal: npt.NDArray[np.float64]


def _loft(spec: CarSpec) -> _Loft:
    half = spec.length / 2
    xs = np.linspace(half, -half, spec.stations)
    bottom, top = _profile(spec, xs)
    ang = np.linspace(0.0, 2 * np.pi, spec.ring, endpoint=False)
    cy = np.sign(np.cos(ang)) * np.abs(np.cos(ang)) ** 0.5
    cz = np.sign(np.sin(ang)) * np.abs(np.sin(ang)) ** 0.5
    verts = []
    hw = spec.width / 2
    for x, z0, z1 in zip(xs, bottom, top, strict=True):
        zc, hz = 0.5 * (z0 + z1), 0.5 * (z1 - z0)
        z = zc + hz * cz
        taper = np.clip((z - spec.belt) / max(z1 - spec.belt, 1e-6), 0.0, 1.0)
        end = 1.0 - 0.12 * np.clip((abs(x) - (half - 0.3)) / 0.3, 0.0, 1.0)
        y = hw * end * cy * (1.0 - spec.roof_inset * taper)
        verts.append(np.column_stack([np.full(spec.ring, x), y, z]))
    v = np.concatenate(verts)
    n, r = spec.stations, spec.ring
    faces = []
    for i in range(n - 1):
        for j in range(r):
            a, b = i * r + j, i * r + (j + 1) % r
            c, d = a + r, b + r
            faces += [(a, c, b), (b, c, d)]
    caps_v = [v[:r].mean(0), v[-r:].mean(0)]
    front_c, rear_c = len(v), len(v) + 1
    v = np.vstack([v, caps_v])
    for j in range(r):
        faces.append((front_c, (j + 1) % r, j))
        last = (n - 1) * r
        faces.append((rear_c, last + j, last + (j + 1) % r))
    tris = np.array(faces)
    cent = v[tris].mean(1)
    seg = np.array([np.sin(ang[j]) for j in range(r)])
    ring_j = np.where(tris[:, 0] < n * r, tris[:, 0] % r, 0)
    roofish = seg[ring_j] > 0.93
    glass = (
        (cent[:, 0] > spec.glass_x[0])
        & (cent[:, 0] < spec.glass_x[1])
        & (cent[:, 2] > spec.belt + 0.04)
        & ~roofish
        & (tris[:, 0] < n * r)
    )
    quads = 2 * (n - 1) * r  # the loft's quads come first, two triangles each: (a, c, b), (b, c, d)
    corners = np.column_stack([tris[0:quads:2], tris[1:quads:2, 2]])
    panel_at = cent.copy()
    panel_at[:quads] = np.repeat(v[corners].mean(1), 2, axis=0)
    panel_rise = seg[ring_j].copy()
    panel_rise[:quads] = np.repeat(np.sin(ang[corners[:, 0] % r] + np.pi / r), 2)
    panel_normal = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    diagonals = np.cross(v[corners[:, 3]] - v[corners[:, 0]], v[corners[:, 2]] - v[corners[:, 1]])
    panel_normal[:quads] = np.repeat(diagonals, 2, axis=0)
    return _Loft(v, tris, glass, tris[:, 0] >= n * r, panel_at, panel_rise, panel_normal)


def _body_and_glass(spec: CarSpec) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    loft = _loft(spec)
    body = trimesh.Trimesh(loft.vertices, loft.tris[~loft.glass], process=True)
    glass_mesh = trimesh.Trimesh(loft.vertices, loft.tris[loft.glass], process=True)
    body.remove_unreferenced_vertices()
    glass_mesh.remove_unreferenced_vertices()
    return body, glass_mesh


def _plateau(spec: CarSpec) -> tuple[float, float]:
    """The length range (rear, front) of the profile's roof: where it stands within 10 % of its
    highest point."""
    high = max(z for _, z in spec.top)
    xs = [x for x, z in spec.top if z >= 0.9 * high]
    return min(xs), max(xs)


def construction_parts(spec: CarSpec) -> dict[str, list[str]]:
    """The part (an id of :data:`vehicle_pose.model.parts.VOCABULARY`) each face of the body and
    of the glass was built as, in the order of their faces in the model's mesh: from the spec's
    own measures (its wheelbase, arches, greenhouse, belt and profile), not from the finished
    surface."""
    loft = _loft(spec)
    x, y, z = loft.panel_at[:, 0], loft.panel_at[:, 1], loft.panel_at[:, 2]
    half = spec.length / 2
    side = np.where(y >= 0, "left", "right")
    rear_roof, front_roof = _plateau(spec)
    xf, xr = spec.wheelbase / 2, -spec.wheelbase / 2
    arch = spec.wheel_radius + 0.06 + 0.2  # the arch's cut-out and the panel's lip around it
    split = 0.5 * ((xr + arch) + (xf - arch))
    out = np.array([f"front_door_{s}" for s in side], dtype=object)
    out[x < split] = [f"rear_door_{s}" for s in side[x < split]]
    out[x >= xf - arch] = [f"front_fender_{s}" for s in side[x >= xf - arch]]
    out[x <= xr + arch] = [f"rear_quarter_{s}" for s in side[x <= xr + arch]]
    top = loft.panel_rise > 0.5
    out[top & (x > spec.glass_x[1])] = "hood"
    out[top & (x < spec.glass_x[0])] = "trunk"
    out[top & (x >= spec.glass_x[0]) & (x <= spec.glass_x[1])] = "roof"
    # The pillars between the windows belong to the door below them.
    upper = (z > spec.belt + 0.04) & ~top & (x >= spec.glass_x[0]) & (x <= spec.glass_x[1])
    out[upper] = [f"{'front' if xx >= split else 'rear'}_door_{s}" for xx, s in zip(x[upper], side[upper],
                                                                                      strict=True)]
    # The ends, where the loft's floor rises: the bumpers up to the profile's first and last
    # heights; above them the end caps are the hood's nose and the trunk's (or tailgate's) back.
    front_top, rear_top = spec.top[0][1], spec.top[-1][1]
    out[(x > half - 0.45) & ~top & (z < front_top)] = "front_bumper"
    out[(x < -half + 0.45) & ~top & (z < rear_top)] = "rear_bumper"
    cap = loft.cap
    out[cap & (x > 0)] = np.where(z[cap & (x > 0)] < front_top, "front_bumper", "hood")
    out[cap & (x < 0)] = np.where(z[cap & (x < 0)] < rear_top, "rear_bumper", "trunk")
    windows = np.array([f"quarter_window_{s}" for s in side], dtype=object)
    windows[x >= split] = [f"front_door_window_{s}" for s in side[x >= split]]
    middle = (x < split) & (x >= xr + arch)
    windows[middle] = [f"rear_door_window_{s}" for s in side[middle]]
    # Ahead of the roof and behind it, the glass that faces forward or back is the windscreen
    # and the rear window; the side glass there is the window of the door (or the quarter) it
    # stands over, as on a real car.
    ends = np.abs(loft.panel_normal[:, 0]) > np.abs(loft.panel_normal[:, 1])
    windows[ends & (x > front_roof)] = "windscreen"
    windows[ends & (x < rear_roof)] = "rear_window"
    return {"body": [str(k) for k in out[~loft.glass]], "glass": [str(k) for k in windows[loft.glass]]}


def _wheel_parts(spec: CarSpec) -> list[tuple[str, trimesh.Trimesh]]:
    parts = []
    rot = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    for axle, xa in (("r", -spec.wheelbase / 2), ("f", spec.wheelbase / 2)):
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            centre = np.array([xa, sgn * spec.track / 2, spec.wheel_radius])
            tyre = trimesh.creation.cylinder(radius=spec.wheel_radius, height=spec.tyre_width, sections=40)
            tyre.apply_transform(rot)
            tyre.apply_translation(centre)
            rim = trimesh.creation.cylinder(radius=0.62 * spec.wheel_radius, height=0.03, sections=40)
            rim.apply_transform(rot)
            rim.apply_translation(centre + [0.0, sgn * (spec.tyre_width / 2 + 0.005), 0.0])
            parts += [(f"tyre_{axle}{side}", tyre), (f"rim_{axle}{side}", rim)]
    return parts


def _light_parts(spec: CarSpec) -> list[tuple[str, trimesh.Trimesh]]:
    half = spec.length / 2
    bottom, top = _profile(spec, np.array([half - 0.08, -half + 0.08]))
    parts = []
    for name, x, z in (("headlight", half - 0.06, top[0] - 0.1), ("taillight", -half + 0.05, top[1] - 0.12)):
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            box = trimesh.creation.box(extents=(0.12, 0.34, 0.09))
            box.apply_translation([x, sgn * spec.width * 0.3, z])
            parts.append((f"{name}_{side}", box))
    return parts


_ALBEDO = {"glass": 0.12, "tyre": 0.06, "rim": 0.6, "headlight": 0.9, "taillight": 0.3}


def build_car(spec: CarSpec = SEDAN) -> tuple[trimesh.Scene, WheelGeometry]:
    """The car as a trimesh scene of named, coloured parts, and its exact wheel geometry."""
    body, glass = _body_and_glass(spec)
    named = [("body", body), ("glass", glass), *_wheel_parts(spec), *_light_parts(spec)]
    scene = trimesh.Scene()
    for name, mesh in named:
        gray = spec.body_albedo if name == "body" else _ALBEDO[name.split("_")[0]]
        g = int(round(255 * gray))
        mesh.visual = trimesh.visual.TextureVisuals(
            material=trimesh.visual.material.PBRMaterial(name=name, baseColorFactor=[g, g, g, 255])
        )
        scene.add_geometry(mesh, geom_name=name, node_name=name)
    wheels = WheelGeometry(
        np.array([-spec.wheelbase / 2, 0.0, spec.wheel_radius]),
        np.array([spec.wheelbase / 2, 0.0, spec.wheel_radius]),
        np.array([0.0, 1.0, 0.0]),
        spec.track,
        spec.wheel_radius,
    )
    return scene, wheels


def write_model(spec: CarSpec, root: str | Path) -> Path:
    """Write ``root/<id>/model.glb``, ``parts.json`` and ``model.json``; returns the metadata path."""
    folder = Path(root) / spec.id
    folder.mkdir(parents=True, exist_ok=True)
    scene, wheels = build_car(spec)
    (folder / "model.glb").write_bytes(scene.export(file_type="glb"))
    (folder / "parts.json").write_text(part_file_text(construction_parts(spec)))
    meta = {
        "id": spec.id,
        "name": spec.name,
        "mesh": "model.glb",
        "parts": "parts.json",
        "units": "m",
        "meters_per_unit": 1.0,
        "up": "+z",
        "forward": "+x",
        "wheels": wheels.to_dict(),
        "estimated": [],
        "source": "vehicle_pose.model.procedural (generated by this project)",
    }
    path = folder / "model.json"
    path.write_text(json.dumps(meta, indent=2) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    root = Path(args[0]) if args else Path(__file__).resolve().parents[2] / "vehicle_models"
    for spec in SPECS:
        print(write_model(spec, root))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
