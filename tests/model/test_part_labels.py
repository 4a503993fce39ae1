"""Part labels: names read through the synonym table, the geometric partition, the store."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vehicle_pose.model.library import VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.parts import (
    VOCABULARY,
    geometric_labels,
    label_faces,
    model_frame,
    name_part,
    part_index,
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


def _areas(mesh: Mesh) -> np.ndarray:
    out = []
    for p in mesh.parts:
        tri = p.vertices[p.faces.astype(np.int64)]
        out.append(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1))
    return np.concatenate(out)


def test_the_shipped_models_are_labelled_by_construction(library):
    for model_id in library.ids():
        model = library.load(model_id)
        labels = label_faces(model.mesh, model.info.up, model.wheels)
        assert not labels.estimated.any(), model_id
        start = 0
        for part in model.mesh.parts:
            got = set(labels.labels[start:start + len(part.faces)].tolist())
            start += len(part.faces)
            if part.name in VOCABULARY:
                assert got == {part_index(part.name)}, (model_id, part.name)
            else:  # tyre_front_left, rim_rear_right: the wheel it belongs to
                assert got == {part_index("wheel_" + part.name.split("_", 1)[1])}, (model_id, part.name)


def test_the_geometric_partition_agrees_with_the_construction(library):
    """Most of each shipped body's surface gets the same part from its shape alone as it was
    built as (the pixel figure over random views is bench/parts.py's)."""
    for model_id in library.ids():
        model = library.load(model_id)
        built = label_faces(model.mesh, model.info.up, model.wheels).labels
        shaped = geometric_labels(model.mesh, model.info.up, model.wheels)
        areas = _areas(model.mesh)
        agree = float(areas[built == shaped].sum() / areas.sum())
        assert agree > 0.85, (model_id, agree)


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
    for part in ("hood", "roof", "trunk", "windscreen", "front_door_left", "rear_quarter_right", "wheel_front_left",
                 "headlamp_right", "taillamp_left"):
        assert (names == part).sum() > 0, part


def test_a_door_named_without_a_side_is_placed_by_its_faces(sedan):
    """Two geometries both called ``Door`` (the sedan's front doors renamed) become the left and
    the right front door by where their faces are."""
    parts = tuple(replace(p, name="Door") if p.name.startswith("front_door_") and "window" not in p.name else p
                  for p in sedan.mesh.parts)
    labels = label_faces(Mesh(parts), sedan.info.up, sedan.wheels)
    start = 0
    for p, original in zip(parts, sedan.mesh.parts, strict=True):
        if p.name == "Door":
            assert set(labels.labels[start:start + len(p.faces)].tolist()) == {part_index(original.name)}
            assert not labels.estimated[start:start + len(p.faces)].any()
        start += len(p.faces)


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
