"""Part labels: names read through the synonym table, the geometric partition, part files (the
shipped models labelled by construction), the store."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from vehicle_pose.errors import ModelError
from vehicle_pose.model.library import ModelLibrary, VehicleModel
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.parts import (
    LEGEND,
    VOCABULARY,
    face_geometry,
    label_faces,
    model_frame,
    name_part,
    part_file_text,
    read_part_file,
)
from vehicle_pose.model.procedural import SEDAN, construction_parts, write_model


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


def test_the_shipped_models_named_parts_are_read_and_the_body_partitioned_without_their_part_files(library):
    """The shipped models name their wheels and lamps (``tyre_fl``, ``headlight_r``): those are
    read; without their part files, their one-piece body and glass name no panel and are
    partitioned, marked estimated."""
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


def test_the_shipped_models_are_labelled_by_construction(library):
    """Every face of the shipped models is labelled from the names or the part file (none
    estimated), though the loader reorders the body's faces; each panel is where it was built."""
    for model_id in library.ids():
        model = library.load(model_id)
        assert model.info.parts_path is not None and model.info.parts_path.name == "parts.json"
        labels = model.part_labels()
        assert not labels.estimated.any(), model_id
        frame = model_frame(model.info.up, model.wheels)
        centres = frame.local(np.concatenate([p.vertices[p.faces.astype(np.int64)].mean(1)
                                              for p in model.mesh.parts]))
        names = np.array([VOCABULARY[k - 1] for k in labels.labels]).astype(str)
        assert (centres[np.char.endswith(names, "_left"), 1] > 0).all()
        assert (centres[np.char.endswith(names, "_right"), 1] < 0).all()
        # the trunk (a pickup's bed) behind the cabin, the hood before it
        assert centres[names == "trunk", 0].max() < centres[names == "roof", 0].min() < \
            centres[names == "roof", 0].max() < centres[names == "hood", 0].min()
        assert centres[names == "roof", 2].mean() > centres[names == "hood", 2].mean()
        for part in ("front_bumper", "rear_bumper", "front_door_left", "rear_door_right", "front_fender_right",
                     "rear_quarter_left", "windscreen", "front_door_window_left"):
            assert (names == part).sum() > 0, (model_id, part)


def test_a_part_file_is_read_by_the_faces_places_whatever_order_the_loader_keeps(tmp_path):
    write_model(SEDAN, tmp_path)
    folder = tmp_path / SEDAN.id
    built = construction_parts(SEDAN)
    listed = read_part_file(folder / "parts.json", folder / "model.glb")
    assert set(listed) == {"body", "glass"}
    assert [VOCABULARY[k - 1] for k in listed["body"].labels] == built["body"]
    model = ModelLibrary(tmp_path).load(SEDAN.id)
    labels = model.part_labels()
    # The loader's body faces are another order than the file's: labels follow the places.
    body = next(p for p in model.mesh.parts if p.name == "body")
    first = sum(len(p.faces) for p in model.mesh.parts[:model.mesh.parts.index(body)])
    centroids = body.vertices[body.faces.astype(np.int64)].mean(1)
    assert not np.allclose(centroids, listed["body"].centroids)
    k = int(np.argmin(np.linalg.norm(listed["body"].centroids - centroids[0], axis=1)))
    assert labels.labels[first] == listed["body"].labels[k]


def test_a_part_file_text_reads_back_and_names_only_known_parts(tmp_path):
    text = part_file_text({"body": ["hood", "hood", "roof", "hood"]})
    assert json.loads(text)["geometries"]["body"] == [["hood", 2], ["roof", 1], ["hood", 1]]
    with pytest.raises(KeyError):
        part_file_text({"body": ["bonnet"]})


@pytest.mark.parametrize("change,message", [
    (lambda d: d["geometries"]["body"].__setitem__(0, ["bonnet", 5]), "not a valid part file"),
    (lambda d: d["geometries"]["body"].append(["hood", 3]), "lists"),
    (lambda d: d["geometries"].__setitem__("spoiler", [["trunk", 4]]), "spoiler"),
    (lambda d: d.pop("geometries"), "not a valid part file"),
])
def test_a_part_file_that_cannot_be_right_is_a_model_error(tmp_path, change, message):
    write_model(SEDAN, tmp_path)
    folder = tmp_path / SEDAN.id
    data = json.loads((folder / "parts.json").read_text())
    change(data)
    (folder / "parts.json").write_text(json.dumps(data))
    with pytest.raises(ModelError, match=message):
        read_part_file(folder / "parts.json", folder / "model.glb")
    with pytest.raises(ModelError, match=message):
        ModelLibrary(tmp_path).load(SEDAN.id).part_labels()


def test_faces_a_part_file_does_not_place_are_labelled_without_it(sedan, caplog):
    """A mesh changed since its part file was written (here decimated): the faces the file does
    not place are partitioned, estimated, with a warning; the ones it places keep its labels."""
    changed = VehicleModel(sedan.info, sedan.mesh.decimated(6000))
    with caplog.at_level("WARNING"):
        labels = changed.part_labels()
    assert "not where the part file has them" in caplog.text
    assert labels.estimated.any() and not labels.estimated.all()
    assert LEGEND["hood"] in labels.labels


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


def test_glass_facing_up_is_a_side_window_beside_the_roof_and_the_roof_over_its_middle(sedan):
    """The sedan's glass curves in under the roof's edge, facing up at its top: those faces are
    the side windows' (the geometric partition called them roof). The roof's own faces facing up
    over the middle half of the width, made glass (a glass roof), are the roof."""
    anonymous = Mesh(tuple(replace(p, name=f"mesh{k}") for k, p in enumerate(sedan.mesh.parts)))
    labels = label_faces(anonymous, sedan.info.up, sedan.wheels)
    frame = model_frame(sedan.info.up, sedan.wheels)
    tris, normals, _, owner = face_geometry(anonymous)
    centres, up = frame.local(tris.mean(1)), np.abs(frame.turn(normals)[:, 2]) > 0.9
    kinds = np.array([p.kind for p in anonymous.parts])[owner]
    glass = kinds == "glass"
    middle = np.abs(centres[:, 1]) < 0.5 * np.abs(centres[:, 1]).max()  # the middle half of the width
    beside = glass & up & ~middle
    assert beside.sum() >= 4
    names = np.array([VOCABULARY[k - 1] for k in labels.labels])
    assert all(name.endswith(("_window_left", "_window_right")) for name in names[beside])
    body = int(np.flatnonzero([p.kind == "body" for p in anonymous.parts])[0])
    start = int(np.flatnonzero(owner == body)[0])
    span = slice(start, start + len(anonymous.parts[body].faces))
    roof = (names[span] == "roof") & up[span] & middle[span]
    assert roof.sum() >= 4
    part = anonymous.parts[body]
    pane = replace(part, name="mesh-pane", kind="glass", faces=part.faces[roof])
    roofed = label_faces(Mesh((*anonymous.parts, pane)), sedan.info.up, sedan.wheels)
    assert (roofed.labels[-int(roof.sum()):] == LEGEND["roof"]).all()


def test_a_lamps_clear_cover_is_that_lamp_and_leaves_the_cabin_where_the_windows_are(sedan):
    """The anonymous sedan's lamps made glass (a lamp's clear cover, as a CAD model's material
    calls it): beyond the axles and below the windows, they are its head and tail lamps, and
    the cabin, the hood and the trunk are where they were with lamps of their own material."""
    anonymous = Mesh(tuple(replace(p, name=f"mesh{k}") for k, p in enumerate(sedan.mesh.parts)))
    covered = Mesh(tuple(replace(p, kind="glass") if p.kind == "light" else p for p in anonymous.parts))
    assert sum(p.kind == "light" for p in anonymous.parts) == 4
    before = label_faces(anonymous, sedan.info.up, sedan.wheels).labels
    after = label_faces(covered, sedan.info.up, sedan.wheels).labels
    np.testing.assert_array_equal(after, before)
    names = {VOCABULARY[k - 1] for k in after}
    assert {"headlamp_left", "headlamp_right", "taillamp_left", "taillamp_right", "hood", "trunk"} <= names


def test_windows_drawn_in_an_opaque_material_whose_name_says_nothing_are_the_windows(sedan):
    """The anonymous sedan's glass made an opaque body material: a part all above the belt line,
    over the wheelbase's middle and mostly not facing up is its windows, labelled as the glass
    was. A roof panel of its own (facing up) stays the roof."""
    anonymous = Mesh(tuple(replace(p, name=f"mesh{k}") for k, p in enumerate(sedan.mesh.parts)))
    opaque = Mesh(tuple(replace(p, kind="body") if p.kind == "glass" else p for p in anonymous.parts))
    assert sum(p.kind == "glass" for p in anonymous.parts) == 1
    np.testing.assert_array_equal(label_faces(opaque, sedan.info.up, sedan.wheels).labels,
                                  label_faces(anonymous, sedan.info.up, sedan.wheels).labels)

    # Without any glass, a roof panel of its own is not taken for the windows: splitting it off
    # the body changes no face's label.
    bare = Mesh(tuple(p for p in opaque.parts if p.name != next(q.name for q in anonymous.parts if q.kind == "glass")))
    labels = label_faces(bare, sedan.info.up, sedan.wheels).labels
    _, normals, _, owner = face_geometry(bare)
    body = int(np.argmax([len(p.faces) for p in bare.parts]))
    span = np.flatnonzero(owner == body)
    top = (labels[span] == LEGEND["roof"]) & (np.abs(normals[span][:, 2]) > 0.9)
    assert top.sum() >= 8
    part = bare.parts[body]
    split = Mesh((*[p for k, p in enumerate(bare.parts) if k != body],
                  replace(part, name="mesh-panel", faces=part.faces[top]), replace(part, faces=part.faces[~top])))
    others = np.flatnonzero(owner != body)
    expected = np.concatenate([labels[others], labels[span][top], labels[span][~top]])
    np.testing.assert_array_equal(label_faces(split, sedan.info.up, sedan.wheels).labels, expected)


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
