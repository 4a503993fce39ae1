"""Loading meshes of every format, metadata, estimation, levels of detail."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vehicle_pose.errors import EmptyMeshError, ModelError, UnknownModelError
from vehicle_pose.model.library import (
    LOD_AGREEMENT,
    ModelLibrary,
    VehicleModel,
    model_from_mesh,
)
from vehicle_pose.model.loading import load_mesh
from vehicle_pose.model.mesh import Mesh, Part, classify_part
from vehicle_pose.model.metadata import ModelInfo, estimate_wheels, parse_axis
from vehicle_pose.model.procedural import SEDAN, build_car


@pytest.mark.parametrize("fmt", ["obj", "ply", "off", "stl", "glb"])
def test_every_format_loads_in_file_coordinates(tmp_path, fmt):
    box = trimesh.creation.box(extents=(2, 1, 0.5))
    box.apply_translation([10.0, -3.0, 1.0])
    path = tmp_path / f"box.{fmt}"
    box.export(path)
    mesh = load_mesh(path)
    assert mesh.n_faces == 12
    np.testing.assert_allclose(mesh.bounds, [[9, -3.5, 0.75], [11, -2.5, 1.25]], atol=1e-5)


def test_scene_transforms_are_applied(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)),
                       transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    path = tmp_path / "scene.glb"
    scene.export(path)
    assert load_mesh(path).bounds[0, 0] == pytest.approx(4.5)


def test_empty_and_missing_meshes_are_clear_errors(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(EmptyMeshError):
        load_mesh(empty)
    with pytest.raises(ModelError):
        load_mesh(tmp_path / "missing.obj")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(ModelError):
        load_mesh(garbage)


def test_part_kinds_from_names():
    assert classify_part("Windows") == "glass"
    assert classify_part("tyre_fl") == "tyre"
    assert classify_part("Wheels3") == "wheel"
    assert classify_part("mesh", "HeadLight_mat") == "light"
    assert classify_part("Hybrid") == "body"


def test_shipped_sedan_has_material_parts_and_exact_wheels(sedan):
    kinds = {p.kind for p in sedan.mesh.parts}
    assert {"body", "glass", "tyre", "wheel", "light"} <= kinds
    assert sedan.info.estimated == ()
    assert sedan.wheels.wheel_radius == pytest.approx(SEDAN.wheel_radius)


def test_wheel_estimate_matches_the_generator(sedan):
    est = estimate_wheels(sedan.mesh.vertices, parse_axis("+z"), parse_axis("+x"))
    true = sedan.wheels
    assert np.linalg.norm(est.rear_axle_center - true.rear_axle_center) < 0.03
    assert np.linalg.norm(est.front_axle_center - true.front_axle_center) < 0.03
    assert est.wheel_radius == pytest.approx(true.wheel_radius, rel=0.05)
    assert est.track_width == pytest.approx(true.track_width, rel=0.05)


def test_mesh_path_model_reports_estimated_metadata(tmp_path):
    scene, _ = build_car(SEDAN)
    # The same car in another frame: up +y, forward -z, centimetres.
    rot = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])
    scene.apply_transform(rot)
    scene.apply_scale(100.0)
    path = tmp_path / "car.glb"
    scene.export(path)
    model = model_from_mesh(path, up="+y", forward="+x", units="cm", meters_per_unit=0.01)
    assert "wheels" in model.info.estimated
    assert model.wheels.wheel_radius == pytest.approx(32.0, rel=0.05)
    assert model.wheels.axle_direction @ np.array([0, 0, -1.0]) == pytest.approx(1.0)


def test_bad_axes_are_refused(tmp_path):
    with pytest.raises(ModelError):
        parse_axis("up")
    path = tmp_path / "b.ply"
    trimesh.creation.box().export(path)
    with pytest.raises(ModelError):
        model_from_mesh(path, up="+z", forward="-z")


def test_library_lookup_and_unknown_ids(tmp_path):
    lib = ModelLibrary()
    assert "sedan" in lib.ids()
    with pytest.raises(UnknownModelError, match="sedan"):
        lib.load("no-such-car")
    with pytest.raises(UnknownModelError):
        lib.load("../vehicle_models/sedan")
    assert lib.load("sedan") is lib.load("sedan")


def test_library_estimates_missing_wheels(tmp_path):
    scene, _ = build_car(SEDAN)
    folder = tmp_path / "car"
    folder.mkdir()
    (folder / "car.glb").write_bytes(scene.export(file_type="glb"))
    (folder / "model.json").write_text(json.dumps({"id": "car", "mesh": "car.glb", "up": "+z", "forward": "+x"}))
    model = ModelLibrary(tmp_path).load("car")
    assert model.info.estimated == ("wheels",)


def test_decimated_level_of_detail(sedan):
    coarse = sedan.lod(2000)
    assert coarse.n_faces <= 4200  # 2000, or one doubling when the outline was not kept
    assert sedan.mesh.outline_agreement(coarse) >= LOD_AGREEMENT
    np.testing.assert_allclose(coarse.bounds, sedan.mesh.bounds, atol=0.05)
    assert sedan.lod(2000) is coarse


def _soup(mesh: Mesh) -> Mesh:
    """The mesh with no vertex shared between faces, as CAD exports often come."""
    parts = []
    for p in mesh.parts:
        flat = p.faces.reshape(-1)
        parts.append(replace(p, vertices=p.vertices[flat], normals=p.normals[flat], uv=None, texture=None,
                             albedo=p.albedo[flat], faces=np.arange(len(flat), dtype=np.uint32).reshape(-1, 3)))
    return Mesh(tuple(parts))


def test_decimating_a_triangle_soup_keeps_its_outline(sedan):
    soup = _soup(sedan.mesh)
    coarse = soup.decimated(4096)
    assert coarse.n_faces <= 4200
    assert soup.outline_agreement(coarse) >= LOD_AGREEMENT


def test_a_level_of_detail_that_loses_the_outline_falls_back_to_more_faces():
    # 100 separate small boxes: no decimation to 64 faces can keep them all.
    rng = np.random.default_rng(0)
    boxes = [trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation(rng.uniform(-2, 2, 3)) for _ in range(100)]
    tm = trimesh.util.concatenate(boxes)
    part = Part("boxes", "body", np.asarray(tm.vertices), np.asarray(tm.vertex_normals, np.float32),
                np.asarray(tm.faces, np.uint32), np.full(len(tm.vertices), 0.5, np.float32))
    mesh = Mesh((part,))
    assert mesh.outline_agreement(mesh.decimated(64)) < LOD_AGREEMENT
    info = ModelInfo(id="boxes", name="boxes", mesh_path=Path("boxes"), units="m", meters_per_unit=1.0, up="+z",
                     forward="+x", wheels=None)
    model = VehicleModel(info, mesh)
    lod = model.lod(64)
    assert mesh.outline_agreement(lod) >= LOD_AGREEMENT
    assert lod.n_faces > 64


def test_decimation_keeps_small_parts_whole_and_takes_faces_from_the_body(sedan):
    coarse = sedan.mesh.decimated(4096)
    assert coarse.n_faces <= 4096
    for full, part in zip(sedan.mesh.parts, coarse.parts, strict=True):
        if full.kind in ("wheel", "tyre", "light"):
            assert len(part.faces) == len(full.faces)
    body = [p for p in coarse.parts if p.kind == "body"][0]
    assert len(body.faces) < len([p for p in sedan.mesh.parts if p.kind == "body"][0].faces) / 2
