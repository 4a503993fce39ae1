"""The car's parts: a fixed vocabulary, and a part label for every face of a model.

A claim is priced per panel, so a registered model is most useful as a map of which part is
where in the photo (:mod:`vehicle_pose.render.parts`). This module says which part each face
of a model's mesh belongs to, in a fixed :data:`VOCABULARY` (left and right are the car's own,
as its driver sees them).

Labels come from the mesh where it names its parts: a part's geometry and material names are
matched against a table of synonyms (:data:`SYNONYMS`: "bonnet" is the hood, "tailgate" the
trunk), and where a name says what a part is but not where (a "door", a "bumper", a "wheel"),
its place in the model's own frame says which one (front or rear, left or right). Faces whose
part names nothing in the table are labelled by a geometric partition of the model's own frame
(:func:`geometric_labels`): its up axis, its forward direction and the wheel metadata's axles,
track and radius. Fenders are the sides over the front wheels, the rear quarters the sides over
the rear ones, the doors the sides between, the bumpers the ends beyond the wheel arches below
the wheels' tops, hood and trunk the surfaces facing up in front of and behind the cabin. Those
labels are estimates, and the model's :class:`PartLabels` say which parts were estimated.

A model may also list its faces' parts in a part file beside its mesh (``parts`` in its
``model.json``; :func:`read_part_file`): for each geometry it names, the part of every face in
order, as a model built by a program knows them. The procedural models of ``vehicle_models/``
do so for their one-piece body and glass (labelled by construction), and name their tyres, rims
and lamps.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from vehicle_pose.errors import ModelError
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.metadata import WheelGeometry, parse_axis

log = logging.getLogger(__name__)

__all__ = ["LABELLING", "VOCABULARY", "LEGEND", "COLOURS", "SYNONYMS", "PartLabels", "face_geometry", "label_faces",
           "geometric_labels", "name_part", "model_frame", "part_index", "read_part_file", "part_file_text",
           "ListedParts"]

LABELLING = 5
"""Version of the labelling; raise it whenever the labels of a mesh change (prepared models
keep their labels under it)."""

VOCABULARY: tuple[str, ...] = (
    "front_bumper", "rear_bumper", "hood", "roof", "trunk", "windscreen", "rear_window",
    "front_fender_left", "front_fender_right", "rear_quarter_left", "rear_quarter_right",
    "front_door_left", "front_door_right", "rear_door_left", "rear_door_right",
    "front_door_window_left", "front_door_window_right", "rear_door_window_left", "rear_door_window_right",
    "quarter_window_left", "quarter_window_right", "mirror_left", "mirror_right",
    "headlamp_left", "headlamp_right", "taillamp_left", "taillamp_right",
    "wheel_front_left", "wheel_front_right", "wheel_rear_left", "wheel_rear_right",
    "other",
)
"""The part ids; a label is an id's index + 1 (0 is no part: the background)."""

LEGEND: dict[str, int] = {part: k + 1 for k, part in enumerate(VOCABULARY)}
"""Every part id and its label (its value in a label image)."""

# One colour per part, told apart at a glance: left and right share a hue, the right darker.
_HUES: dict[str, tuple[int, int, int]] = {
    "front_bumper": (230, 25, 75), "rear_bumper": (128, 0, 0), "hood": (255, 225, 25), "roof": (0, 130, 200),
    "trunk": (245, 130, 48), "windscreen": (70, 240, 240), "rear_window": (0, 128, 128),
    "front_fender": (240, 50, 230), "rear_quarter": (145, 30, 180), "front_door": (60, 180, 75),
    "rear_door": (170, 255, 195), "front_door_window": (100, 200, 255), "rear_door_window": (160, 220, 255),
    "quarter_window": (200, 235, 255), "mirror": (255, 215, 180), "headlamp": (255, 255, 200),
    "taillamp": (255, 80, 80), "wheel_front": (128, 128, 128), "wheel_rear": (90, 90, 90), "other": (210, 245, 60),
}


def _colour(part: str) -> tuple[int, int, int]:
    base = re.sub(r"_(left|right)$", "", part)
    r, g, b = _HUES[base]
    if part.endswith("_right"):
        return (int(r * 0.7), int(g * 0.7), int(b * 0.7))
    return (r, g, b)


COLOURS: dict[str, tuple[int, int, int]] = {p: _colour(p) for p in VOCABULARY}
"""The RGB colour each part is drawn in (label images, overlays, the admin page)."""


def part_index(part: str) -> int:
    """The label of a part id (its index in :data:`VOCABULARY` + 1)."""
    return LEGEND[part]


# What a name says a part is, tried in order (the first kind whose words a name holds wins, so
# "door glass" is a window, not a door). A kind says what but not always where: the place of
# the part's faces in the model's frame says front or rear, left or right (:func:`_placed`).
SYNONYMS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("windscreen", ("windscreen", "windshield", "front glass", "front screen", "front window")),
    ("rear_window", ("rear window", "back window", "rear glass", "back glass", "rear screen", "backlight",
                     "back light glass", "heckscheibe")),
    ("front_door_window", ("front door window", "front door glass")),
    ("rear_door_window", ("rear door window", "rear door glass", "back door window", "back door glass")),
    ("quarter_window", ("quarter window", "quarter glass")),
    ("side_window", ("door glass", "door window", "side window", "side glass", "window")),
    ("mirror", ("mirror", "wing mirror", "side view")),
    ("headlamp", ("headlight", "headlamp", "head lamp", "head light", "front light", "front lamp", "drl",
                  "fog")),
    ("taillamp", ("taillight", "taillamp", "tail lamp", "tail light", "rear light", "rear lamp", "brake light",
                  "stop lamp")),
    ("wheel", ("wheel", "tyre", "tire", "rim", "hub", "brake disc", "caliper")),
    ("front_bumper", ("front bumper", "front fascia", "grille", "grill", "front apron", "spoiler front")),
    ("rear_bumper", ("rear bumper", "rear fascia", "diffuser", "exhaust", "rear apron")),
    ("bumper", ("bumper", "fascia")),
    ("hood", ("hood", "bonnet", "engine cover")),
    ("trunk", ("trunk", "boot", "tailgate", "liftgate", "hatch", "decklid", "deck lid", "rear gate")),
    ("roof", ("roof", "sunroof", "moonroof", "top")),
    ("rear_quarter", ("quarter panel", "rear fender", "rear wing", "quarter")),
    ("front_fender", ("fender", "mudguard", "front wing", "wing")),
    ("rear_door", ("rear door", "back door")),
    ("front_door", ("front door",)),
    ("door", ("door",)),
    ("other", ("interior", "seat", "dashboard", "steering", "engine", "chassis", "underbody", "floor")),
)
"""Part kinds and the words in a geometry or material name that say them (lower case)."""


def _words(text: str) -> str:
    """A name as spaced lower-case words: ``FrontDoor_L.001`` as ``front door l 001``."""
    text = re.sub(r"([a-z])([A-Z])", r"\1 \2", text)
    return " " + re.sub(r"[^a-z0-9]+", " ", text.lower()).strip() + " "


def name_part(*names: str | None) -> str | None:
    """The part kind a geometry's names say (a key of :data:`SYNONYMS`), or None."""
    text = " ".join(_words(n) for n in names if n)
    for kind, words in SYNONYMS:
        if any(f" {w} " in text for w in words):
            return kind
    return None


@dataclass(frozen=True)
class Frame:
    """The model's own frame (mesh units): ``x`` forward from the middle of the wheelbase,
    ``y`` to the car's left, ``z`` up from the ground; with the wheel metadata in it."""

    origin: npt.NDArray[np.float64]
    axes: npt.NDArray[np.float64]  # (3, 3): rows forward, left, up in mesh coordinates
    front_axle: float
    rear_axle: float
    radius: float

    @property
    def arch(self) -> float:
        """How far the panels around a wheel reach from its axle (:data:`ARCH` wheel radii)."""
        return ARCH * self.radius

    @property
    def door_split(self) -> float:
        """Where the front doors end and the rear doors begin: midway between the arches."""
        return 0.5 * ((self.rear_axle + self.arch) + (self.front_axle - self.arch))

    def local(self, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return np.asarray((points - self.origin) @ self.axes.T)

    def turn(self, vectors: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return np.asarray(vectors @ self.axes.T)


def model_frame(up_axis: str, wheels: WheelGeometry) -> Frame:
    """The model's own frame from its up axis and wheel metadata."""
    up = parse_axis(up_axis)
    fwd = wheels.front_axle_center - wheels.rear_axle_center
    fwd = fwd - (fwd @ up) * up
    fwd = fwd / np.linalg.norm(fwd)
    left = np.cross(up, fwd)
    if left @ wheels.axle_direction < 0:  # a mesh mirrored in its file: trust the axle's left
        left = -left
    origin = 0.5 * (wheels.front_axle_center + wheels.rear_axle_center) - wheels.wheel_radius * up
    half = 0.5 * float((wheels.front_axle_center - wheels.rear_axle_center) @ fwd)
    return Frame(origin, np.stack([fwd, left, up]), half, -half, float(wheels.wheel_radius))


@dataclass(frozen=True)
class PartLabels:
    """A label for every face of a mesh (its parts' faces in order) and whether it was
    estimated by the geometric partition (True) or read from the mesh's names (False)."""

    labels: npt.NDArray[np.uint8]
    estimated: npt.NDArray[np.bool_]

    def arrays(self) -> dict[str, npt.NDArray[np.generic]]:
        return {"labels": self.labels, "estimated": self.estimated}

    @classmethod
    def from_arrays(cls, arrays: dict[str, npt.NDArray[np.generic]]) -> PartLabels:
        return cls(np.asarray(arrays["labels"], np.uint8), np.asarray(arrays["estimated"], np.bool_))


def face_geometry(mesh: Mesh) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64],
                                       npt.NDArray[np.int64]]:
    """Every face's corners (F, 3, 3), unit normal (F, 3; sign arbitrary) and area (F,) in the
    mesh frame, and the index of the part it belongs to (F,): the parts' faces in order, as
    :class:`PartLabels` holds them."""
    tris = np.concatenate([p.vertices[p.faces.astype(np.int64)] for p in mesh.parts])
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    owner = np.repeat(np.arange(len(mesh.parts)), [len(p.faces) for p in mesh.parts])
    return tris, cross / np.maximum(norm, 1e-30)[:, None], 0.5 * norm, owner


@dataclass(frozen=True)
class _Shape:
    """What the geometric partition measures of a body in the model's frame."""

    front: float  # the bumpers' ends, forward coordinate
    rear: float
    top: float  # the roof's height
    belt: float  # the height of the windows' lower edge
    cabin: tuple[float, float]  # the forward range of the greenhouse (rear, front)


def _glazed(glass: npt.NDArray[np.bool_], areas: npt.NDArray[np.float64]) -> bool:
    """Whether ``glass`` is enough to read the greenhouse from (8 faces with an area)."""
    return bool(glass.sum() >= 8 and areas[glass].sum() > 0)


def _shape(c: npt.NDArray[np.float64], areas: npt.NDArray[np.float64], glass: npt.NDArray[np.bool_],
           frame: Frame) -> _Shape:
    x, z = c[:, 0], c[:, 2]
    front, rear = float(np.percentile(x, 99.8)), float(np.percentile(x, 0.2))
    top = float(np.percentile(z, 99.8))
    if _glazed(glass, areas):
        belt = float(np.percentile(z[glass], 5))
        cabin = (float(np.percentile(x[glass], 1)), float(np.percentile(x[glass], 99)))
    else:  # no glass named: the greenhouse is what stands above two thirds of the height
        belt = 0.66 * top
        high = z > belt + 0.5 * (top - belt)
        cabin = (float(x[high].min()), float(x[high].max())) if high.any() else (frame.rear_axle, frame.front_axle)
    return _Shape(front, rear, top, belt, cabin)


ARCH = 1.8
"""How far the panels around a wheel reach from its axle, in wheel radii: the fenders and rear
quarters end, and the doors begin, this far in front of or behind the axles."""


def _sided(part: str, left: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint8]:
    """The label of ``part``'s left or right one (``part_left``, ``part_right``) for each face."""
    out: npt.NDArray[np.uint8] = np.where(left, LEGEND[f"{part}_left"], LEGEND[f"{part}_right"]).astype(np.uint8)
    return out


def _glass_part(c: npt.NDArray[np.float64], n: npt.NDArray[np.float64], left: npt.NDArray[np.bool_], s: _Shape,
                frame: Frame) -> npt.NDArray[np.uint8]:
    """Windscreen, rear window or the side window over each door (quarter windows behind)."""
    out = _sided("quarter_window", left)
    front_door = c[:, 0] >= frame.door_split
    rear_door = (c[:, 0] < frame.door_split) & (c[:, 0] >= frame.rear_axle + frame.arch)
    out[front_door] = _sided("front_door_window", left[front_door])
    out[rear_door] = _sided("rear_door_window", left[rear_door])
    up = n[:, 2] > 0.9
    # Glass facing up over the middle half of the car's width is a glass roof; beside it, the
    # top of a side window curving in under the roof's edge.
    central = np.abs(c[:, 1]) < 0.5 * np.max(np.abs(c[:, 1]))
    facing = (np.abs(n[:, 1]) < 0.6) & (central | ~up)  # the glass faces forward, back or up
    mid = 0.5 * (s.cabin[0] + s.cabin[1])
    out[facing & (c[:, 0] >= mid)] = LEGEND["windscreen"]
    out[facing & (c[:, 0] < mid)] = LEGEND["rear_window"]
    out[facing & up] = LEGEND["roof"]
    return out


def _body_part(c: npt.NDArray[np.float64], n: npt.NDArray[np.float64], left: npt.NDArray[np.bool_], s: _Shape,
               frame: Frame) -> npt.NDArray[np.uint8]:
    """The body panel of each face, from its place and the way it faces."""
    x, z = c[:, 0], c[:, 2]
    # the sides: fender over the front wheel, quarter over the rear one, doors between
    out = _sided("front_door", left)
    rear_door = x < frame.door_split
    out[rear_door] = _sided("rear_door", left[rear_door])
    fender = x >= frame.front_axle - frame.arch
    out[fender] = _sided("front_fender", left[fender])
    quarter = x <= frame.rear_axle + frame.arch
    out[quarter] = _sided("rear_quarter", left[quarter])
    # the surfaces facing up: hood before the cabin, trunk behind it, roof over it
    up = n[:, 2] > 0.55
    out[up & (x > s.cabin[1])] = LEGEND["hood"]
    out[up & (x < s.cabin[0])] = LEGEND["trunk"]
    above = z > s.belt + 0.02 * s.top
    roof = above & (x >= s.cabin[0]) & (x <= s.cabin[1]) & (np.abs(n[:, 1]) < 0.6)
    out[roof] = LEGEND["roof"]
    # the ends beyond the wheel arches: below the wheels' tops the bumpers, above them the
    # faces that look forward or back belong to the hood or the trunk (or a tailgate, which
    # reaches above the belt: the back of a van or an estate)
    lid = 2.0 * frame.radius
    ahead, behind = x > frame.front_axle + frame.arch, x < frame.rear_axle - frame.arch
    end = np.abs(n[:, 0]) > 0.7
    out[ahead & (z >= lid) & end & ~above] = LEGEND["hood"]
    out[behind & (z >= lid) & end & (x < s.cabin[0])] = LEGEND["trunk"]
    out[ahead & (z < lid)] = LEGEND["front_bumper"]
    out[behind & (z < lid)] = LEGEND["rear_bumper"]
    return out


def _outward(c: npt.NDArray[np.float64], n: npt.NDArray[np.float64], s: _Shape) -> npt.NDArray[np.float64]:
    """Normals turned away from the car's middle line (mesh winding is not trusted)."""
    mid = np.column_stack([np.clip(c[:, 0], s.rear + 0.3 * (s.front - s.rear), s.front - 0.3 * (s.front - s.rear)),
                           np.zeros(len(c)), np.full(len(c), 0.45 * s.top)])
    flip = np.sum((c - mid) * n, axis=1) < 0
    return np.where(flip[:, None], -n, n)


def _opaque_windows(c: npt.NDArray[np.float64], n: npt.NDArray[np.float64], areas: npt.NDArray[np.float64],
                    owner: npt.NDArray[np.int64], candidate: npt.NDArray[np.bool_],
                    belt: float) -> npt.NDArray[np.bool_]:
    """The faces of every part among ``candidate``'s that is a car's windows by its place: all
    of it above the ``belt`` line, reaching over the wheelbase's middle (the frame's origin),
    and most of its area not facing up (a roof panel of its own does)."""
    out = np.zeros(len(c), bool)
    for k in np.unique(owner[candidate]):
        mine = candidate & (owner == k)
        x = c[mine, 0]
        up = areas[mine & (np.abs(n[:, 2]) > 0.9)].sum()
        if c[mine, 2].min() > belt and x.min() < 0.0 < x.max() and up < 0.5 * areas[mine].sum():
            out |= mine
    return out


def geometric_labels(mesh: Mesh, up_axis: str, wheels: WheelGeometry,
                     kinds: npt.NDArray[np.object_] | None = None) -> npt.NDArray[np.uint8]:
    """A label for every face of ``mesh`` from its place in the model's own frame alone.

    ``kinds`` (one per face, a key of :data:`SYNONYMS` or None) narrows faces whose names say
    what they are: glass is a window, a lamp a head or tail lamp, a wheel the wheel it is
    nearest. The faces of material kind glass, tyre, wheel and light are treated the same way
    when their names say nothing more, but for glass whose part lies wholly ahead of the front
    axle or behind the rear one and below the windows' lower edge: a lamp's clear cover, a
    head or tail lamp. With no glass known over the cabin, an unnamed body part that stands
    wholly above the belt over the wheelbase's middle, not mostly facing up, is the windows
    (:func:`_opaque_windows`).
    """
    frame = model_frame(up_axis, wheels)
    tris, nm, areas, owner = face_geometry(mesh)
    c, n = frame.local(tris.mean(1)), frame.turn(nm)
    material = np.array([p.kind for p in mesh.parts], object)[owner]
    kinds = kinds if kinds is not None else np.full(len(c), None, object)
    unnamed = np.array([k is None for k in kinds], bool)
    glass = np.isin(kinds, ["windscreen", "rear_window", "side_window", "front_door_window", "rear_door_window",
                            "quarter_window"]) | ((material == "glass") & unnamed)
    # Glass of a part that lies wholly beyond an axle (a lamp's clear cover at the car's end)
    # does not say where the cabin is; below the windows' edge it is that lamp.
    greenhouse, cover = glass.copy(), np.zeros_like(glass)
    for k in np.unique(owner[glass & unnamed]):
        mine = glass & unnamed & (owner == k)
        if c[mine, 0].min() > frame.front_axle or c[mine, 0].max() < frame.rear_axle:
            greenhouse[mine] = False
            cover[mine] = True
    s = _shape(c, areas, greenhouse, frame)
    if not _glazed(greenhouse, areas):
        # No glass known over the cabin: windows drawn in a material whose name says nothing.
        panes = _opaque_windows(c, n, areas, owner, unnamed & (material == "body"), s.belt)
        if panes.any():
            glass, greenhouse = glass | panes, greenhouse | panes
            s = _shape(c, areas, greenhouse, frame)
    for k in np.unique(owner[cover]):
        mine = cover & (owner == k)
        cover[mine] = c[mine, 2].max() < s.belt
    n = _outward(c, n, s)
    left = c[:, 1] >= 0.0
    out = _body_part(c, n, left, s, frame)
    g = _glass_part(c, n, left, s, frame)
    out[glass] = g[glass]
    lamp = ((material == "light") & unnamed) | cover
    head = (kinds == "headlamp") | (lamp & (c[:, 0] >= 0))
    tail = (kinds == "taillamp") | (lamp & (c[:, 0] < 0))
    out[head] = _sided("headlamp", left[head])
    out[tail] = _sided("taillamp", left[tail])
    wheel = (kinds == "wheel") | (np.isin(material, ["tyre", "wheel"]) & unnamed)
    front = c[:, 0] >= 0
    out[wheel & front] = _sided("wheel_front", left[wheel & front])
    out[wheel & ~front] = _sided("wheel_rear", left[wheel & ~front])
    mirror = kinds == "mirror"
    out[mirror] = _sided("mirror", left[mirror])
    out[(kinds == "other") | ((material == "other") & unnamed)] = LEGEND["other"]
    return out


def _placed(kind: str, c: npt.NDArray[np.float64], split: float) -> str:
    """A named kind put where its faces are: ``c`` is the part's mean centroid in the model's
    frame, ``split`` where the front doors end."""
    sd = "left" if c[1] >= 0 else "right"
    if kind == "bumper":
        return "front_bumper" if c[0] >= 0 else "rear_bumper"
    if kind == "door":
        return f"front_door_{sd}" if c[0] >= split else f"rear_door_{sd}"
    if kind in ("front_door", "rear_door", "front_fender", "rear_quarter", "mirror", "headlamp", "taillamp",
                "front_door_window", "rear_door_window", "quarter_window"):
        return f"{kind}_{sd}"
    if kind == "wheel":
        return f"wheel_{'front' if c[0] >= 0 else 'rear'}_{sd}"
    return kind  # front_bumper, rear_bumper, hood, roof, trunk, windscreen, rear_window, other


def part_file_text(parts: Mapping[str, Sequence[str]]) -> str:
    """The text of a part file: for each geometry, the part of each of its faces in order (ids of
    :data:`VOCABULARY`), as runs ``[part, count]``."""
    runs: dict[str, list[list[str | int]]] = {}
    for geometry, labels in parts.items():
        out: list[list[str | int]] = []
        for label in labels:
            part_index(label)  # a KeyError names an id outside the vocabulary
            if out and out[-1][0] == label:
                out[-1][1] = int(out[-1][1]) + 1
            else:
                out.append([label, 1])
        runs[geometry] = out
    return json.dumps({"format": "vehicle-pose parts 1", "geometries": runs}, separators=(",", ":")) + "\n"


@dataclass(frozen=True)
class ListedParts:
    """A part file's labels of one geometry: each face's label and the face's centroid in the
    mesh file's frame (the loader may reorder a part's faces; a face is found by its place)."""

    labels: npt.NDArray[np.uint8]
    centroids: npt.NDArray[np.float64]


def read_part_file(path: str | Path, mesh_path: str | Path) -> dict[str, ListedParts]:
    """The labels of every geometry the part file ``path`` lists (:func:`part_file_text`), each
    with its faces' centroids read from the mesh file ``mesh_path``, in the file's order.
    ModelError for a file that cannot be read, names an unknown part or a geometry the mesh file
    lacks, or lists another number of faces than the geometry has."""
    import trimesh

    p = Path(path)
    try:
        data = json.loads(p.read_text())
        listed = {}
        for geometry, runs in data["geometries"].items():
            counts = [int(n) for _, n in runs]
            if any(n < 1 for n in counts):
                raise ValueError(f"a run of {geometry!r} is empty")
            listed[str(geometry)] = np.repeat(np.array([part_index(str(k)) for k, _ in runs], np.uint8), counts)
    except OSError as exc:
        raise ModelError(f"cannot read part file {p}: {exc.strerror}") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ModelError(f"part file {p} is not a valid part file: {exc}") from None
    try:
        scene = trimesh.load(str(mesh_path), force="scene")
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ModelError(f"cannot load mesh {Path(mesh_path).name} for its part file: {exc}") from None
    out = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        if name not in listed or name in out:
            continue
        geom = scene.geometry[name].copy()
        geom.apply_transform(transform)
        tris = np.asarray(geom.vertices, np.float64)[np.asarray(geom.faces, np.int64)]
        if len(tris) != len(listed[name]):
            raise ModelError(f"part file {p} lists {len(listed[name])} faces of {name!r}; the mesh has {len(tris)}")
        out[name] = ListedParts(listed[name], tris.mean(1))
    missing = sorted(set(listed) - set(out))
    if missing:
        raise ModelError(f"part file {p} lists {', '.join(map(repr, missing))}, which the mesh does not have")
    return out


def label_faces(mesh: Mesh, up_axis: str, wheels: WheelGeometry,
                given: Mapping[str, ListedParts] | None = None) -> PartLabels:
    """Every face's part: from ``given`` (a part file's labels by geometry name,
    :func:`read_part_file`) for the geometries it lists, each face labelled as the listed face
    at its centroid; from the mesh's names where they say it (:func:`name_part`); from the
    geometric partition elsewhere (:func:`geometric_labels`, marked estimated). A face of a
    listed geometry at no listed face's centroid (a mesh changed since its part file was written:
    decimated, edited) is labelled as if the file did not list it, and a warning is logged.

    A named part is one part (a door, a wheel) placed as a whole: front or rear, left or right
    by the mean of its faces' centroids. Side windows and parts that hold both sides of the car
    in one geometry (a "bumper" of both corners is fine; "wheels" holding four) are placed face
    by face.
    """
    frame = model_frame(up_axis, wheels)
    named = [name_part(p.name) for p in mesh.parts]
    counts = [len(p.faces) for p in mesh.parts]
    kinds = np.repeat(np.array(named, object), counts)
    geometric = geometric_labels(mesh, up_axis, wheels, kinds)
    labels = geometric.copy()
    estimated = np.repeat(np.array([k is None for k in named]), counts)
    start = 0
    for p, kind, count in zip(mesh.parts, named, counts, strict=True):
        if kind is not None and kind not in ("side_window", "wheel", "mirror", "headlamp", "taillamp"):
            tri = p.vertices[p.faces.astype(np.int64)].mean(1)
            local = frame.local(tri)
            spread = local[:, 1]
            if kind in ("door", "front_door", "rear_door", "front_fender", "rear_quarter", "front_door_window",
                        "rear_door_window", "quarter_window") and \
                    spread.min() < -0.25 * wheels.track_width and spread.max() > 0.25 * wheels.track_width:
                start += count  # both sides in one geometry: the geometric partition places it
                continue
            labels[start:start + count] = part_index(_placed(kind, local.mean(0), frame.door_split))
        start += count
    if given:
        from scipy.spatial import cKDTree

        tolerance = 1e-6 * float(np.ptp(np.concatenate([p.vertices for p in mesh.parts]), axis=0).max())
        start = 0
        for p, count in zip(mesh.parts, counts, strict=True):
            listed = given.get(p.name)
            if listed is not None:
                far, nearest = cKDTree(listed.centroids).query(p.vertices[p.faces.astype(np.int64)].mean(1))
                found = far <= tolerance
                if not found.all():
                    log.warning("%d of %d faces of %r are not where the part file has them: labelled without it",
                                int((~found).sum()), count, p.name)
                labels[start:start + count][found] = listed.labels[nearest[found]]
                estimated[start:start + count][found] = False
            start += count
    return PartLabels(labels, estimated)
