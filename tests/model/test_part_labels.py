"""Part labels: names read through the synonym table, the geometric partition, the store."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.parts import (
    VOCABULARY,
    label_faces,
    model_frame,
    name_part,
)


@pytest.mark.parametrize(("names", "kind"), [
    (("Bonnet",), "hood"),
    (("FrontDoor_L.001",), "front_door"),
    (("door_glass_rr",), "side_window"),
    (("Quarter_Glass_L",), "quarter_window"),
    (("Tailgate",), "trunk"),
    (("rear window",), "rear_window"),
    (("Windshield",), "windscreen"),
    (("Object_12", "mat_chrome_Grille"), "front_bumper"),
    (("Tyre_FL",), "wheel"),
    (("TailLight_R",), "taillamp"),
    (("RearDoor_Left",), "rear_door"),
    (("left wing mirror",), "mirror"),
    (("Mesh.001", "Material.004"), None),
])
def test_names_say_the_part(names, kind):
    assert name_part(*names) == kind


def test_the_shipped_models_named_parts_are_read_and_the_body_partitioned(library):
    """The shipped models name their wheels and lamps (``tyre_fl``, ``headlight_r``): those are
    read; their one-piece body and glass name no panel and are partitioned, marked estimated."""
    for model_id in library.ids():
        model = library.load(model_id)
        labels = label_faces(model.mesh, model.info.up, model.wheels)
        start = 0
        for part in model.mesh.parts:
            got = set(labels.labels[start:start + len(part.faces)].tolist())
            estimated = labels.estimated[start:start + len(part.faces)]
            start += len(part.faces)
            if part.kind in ("tyre", "wheel", "light"):
                assert len(got) == 1 and not estimated.any(), (model_id, part.name)
                name = VOCABULARY[got.pop() - 1]
                assert name.startswith("wheel_" if part.kind != "light" else ("headlamp_", "taillamp_")), name
            else:
                assert estimated.all() and len(got) > 3, (model_id, part.name)


def test_a_mesh_that_names_nothing_is_partitioned_and_marked_estimated(sedan):
    """The sedan's parts renamed ``mesh0``, ``mesh1`` ... (materials kept): every face is estimated,
    and the geometric partition puts each panel on its own side and end of the car."""
    anonymous = Mesh(tuple(replace(p, name=f"mesh{k}") for k, p in enumerate(sedan.mesh.parts)))
    labels = label_faces(anonymous, sedan.info.up, sedan.wheels)
    assert labels.estimated.all()
    frame = model_frame(sedan.info.up, sedan.wheels)
    centres = frame.local(np.concatenate([p.vertices[p.faces.astype(np.int64)].mean(1) for p in anonymous.parts]))
    names = np.array([VOCABULARY[k - 1] for k in labels.labels])
    left = np.char.endswith(names.astype(str), "_left")
    right = np.char.endswith(names.astype(str), "_right")
    assert (centres[left, 1] > 0).all() and (centres[right, 1] < 0).all()
    assert (centres[names == "front_bumper", 0] > frame.front_axle).all()
    assert (centres[names == "rear_bumper", 0] < frame.rear_axle).all()
    for part in ("hood", "roof", "trunk", "front_bumper", "front_door_left", "rear_quarter_right", "wheel_front_left",
                 "headlamp_right", "taillamp_left", "windscreen", "front_door_window_left"):
        assert (names == part).sum() > 0, part


def test_a_door_named_without_a_side_is_placed_by_its_faces(sedan):
    """The sedan's body cut in two geometries both called ``Door`` (its left and right halves):
    each becomes a door of its own side by where its faces are, and is not estimated."""
    frame = model_frame(sedan.info.up, sedan.wheels)
    body = next(p for p in sedan.mesh.parts if p.kind == "body")
    centres = frame.local(body.vertices[body.faces.astype(np.int64)].mean(1))
    halves = [replace(body, name="Door", faces=body.faces[keep]) for keep in (centres[:, 1] >= 0, centres[:, 1] < 0)]
    others = tuple(p for p in sedan.mesh.parts if p is not body)
    labels = label_faces(Mesh((*halves, *others)), sedan.info.up, sedan.wheels)
    first, second = len(halves[0].faces), len(halves[1].faces)
    left = {VOCABULARY[k - 1] for k in labels.labels[:first]}
    right = {VOCABULARY[k - 1] for k in labels.labels[first:first + second]}
    assert len(left) == 1 and left.pop() in ("front_door_left", "rear_door_left")
    assert len(right) == 1 and right.pop() in ("front_door_right", "rear_door_right")
    assert not labels.estimated[:first + second].any()


def test_labels_are_kept_with_the_prepared_model(tmp_path):
    from vehicle_pose.model.library import ModelLibrary, model_from_mesh
    from vehicle_pose.model.store import ModelStore

    lib = ModelLibrary()
    path = lib.info("hatchback").mesh_path
    store = ModelStore(tmp_path / "store")
    first: VehicleModel = model_from_mesh(path, store=store)
    made = first.part_labels()
    again = model_from_mesh(path, store=ModelStore(tmp_path / "store"))
    assert again.levels is not None and again.levels.entry is not None
    assert "parts" in again.levels.entry.manifest()
    kept = again.part_labels()
    assert np.array_equal(kept.labels, made.labels) and np.array_equal(kept.estimated, made.estimated)
