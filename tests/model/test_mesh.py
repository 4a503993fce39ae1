"""Meshes: material kinds from names, levels of detail that keep the outline and the small parts."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import trimesh

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.library import (
    LOD_AGREEMENT,
    VehicleModel,
)
from vehicle_pose.model.mesh import Mesh, Part, classify_part
from vehicle_pose.model.metadata import ModelInfo


def test_part_kinds_from_names():
    assert classify_part("Windows") == "glass"
    assert classify_part("tyre_fl") == "tyre"
    assert classify_part("Wheels3") == "wheel"
    assert classify_part("mesh", "HeadLight_mat") == "light"
    assert classify_part("Hybrid") == "body"


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


def test_the_extreme_points_bound_every_projection_of_the_samples(sedan):
    samples = sedan.mesh.sample_points(1000)
    extreme = sedan.mesh.extreme_points(1000)
    assert 4 <= len(extreme) < len(samples) // 4
    assert sedan.mesh.extreme_points(1000) is extreme  # kept
    centre, radius = sedan.mesh.sphere
    rng = np.random.default_rng(0)
    behind = 0
    for _ in range(200):
        R = cv2.Rodrigues(rng.normal(0.0, 2.0, 3))[0]
        t = -R @ centre + np.array([*rng.normal(0.0, radius, 2), rng.uniform(-1.0, 6.0) * radius])
        cam = Camera(np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]]), R, t, 640, 480)
        uv, ue = cam.project(samples), cam.project(extreme)
        # A sample behind the camera exactly when an extreme point is; else the same box.
        assert np.all(np.isfinite(uv)) == np.all(np.isfinite(ue))
        if not np.all(np.isfinite(uv)):
            behind += 1
            continue
        np.testing.assert_array_equal(uv.min(0), ue.min(0))
        np.testing.assert_array_equal(uv.max(0), ue.max(0))
    assert 20 < behind < 150


def test_a_flat_mesh_keeps_all_its_samples_as_extreme_points():
    xy = np.random.default_rng(1).uniform(-1.0, 1.0, (50, 2))
    vertices = np.column_stack([xy, np.zeros(50)])
    faces = np.array([[i, i + 1, i + 2] for i in range(48)], np.uint32)
    part = Part("plate", "body", vertices, np.tile(np.float32([0.0, 0.0, 1.0]), (50, 1)), faces,
                np.full(50, 0.5, np.float32))
    mesh = Mesh((part,))
    np.testing.assert_array_equal(mesh.extreme_points(20), mesh.sample_points(20))
